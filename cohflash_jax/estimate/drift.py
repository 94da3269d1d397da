"""A carrier drift common to the capture (turbulence in the common path): found from the data,
without knowing the pixels' depths, and the choice of carrier alignment it implies.

`--carrier auto` (the default) looks for such a drift in a sample of pixels before the
reconstruction starts. Where one is found it is removed from every pixel (a phase estimated
from many pixels, so each pixel's noise stays white and the detection test's null holds);
otherwise each pixel is aligned statically. The depth file records which ran and why.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .iq import DRIFT_WINDOW_FRAMES, iq_from_frames, moving_average

# A common drift is declared where the moving average's leading singular value stands this many
# times above the pure-noise level and above the next one (nearly rank one over pixels), it
# needs this many windows of frames, and its circle fit a relative radial spread below the limit
DRIFT_DETECTION_FACTOR = 3.0
DRIFT_MIN_WINDOWS = 4
DRIFT_MAX_CIRCLE_SPREAD = 0.3
# A drift is kept only where the tones' axis turns by more than this, rms over stretches of a
# window (`tone_axis_rotation`; measured on 16×16-px calibration captures: 0.01 rad on static
# ones, 0.49–1.21 under the simulator's default turbulence, tracking the drift's own rms)
DRIFT_MIN_AXIS_TURN_RAD = 0.08
# half-width (bins) of the band around each pixel's tone that the drift test looks at
TONE_HALF_WIDTH_BINS = 16
# The moving average's rows (windows of `DRIFT_WINDOW_FRAMES` = 101 frames) whose Gram matrix
# finds the leading singular directions: every 8th (`leading_singular_pairs`). Over 40 simulated
# 24×24-px captures, static and turbulent, with and without hybrid errors, the decisions were
# those of every row and the drifts' phases correlated above 0.9996 (docs/performance.md)
GRAM_ROW_STEP = 8


def initial_common_drift(i, q, window_frames: int = DRIFT_WINDOW_FRAMES) -> tuple[np.ndarray, str]:
    """First estimate of a carrier drift common to the pixels, without knowing their depths.

    The moving average of Z = I + iQ keeps the mean term z_p·w_0·e^{iφ[m]} (the tone averages
    out); minus its time mean, it is (nearly) rank one over pixels, so its leading left singular
    vector is κ·(e^{iφ[m]} − c): a circle, fitted algebraically (Kåsa) to recover φ. Leakage of
    common mode through an uncalibrated hybrid is constant and drops out with the mean.
    Returns (φ (N,) zero-mean, description); φ = 0 when the data show no drift."""
    i, q = np.asarray(i), np.asarray(q)
    n, p = i.shape
    half = window_frames // 2
    if n <= DRIFT_MIN_WINDOWS * window_frames:
        return np.zeros(n), "too few frames to look for a carrier drift"
    m, noise_var = centred_window_means(i, q, window_frames)
    u, sv = leading_singular_pairs(m, row_step=GRAM_ROW_STEP)
    floor = math.sqrt(noise_var) * (math.sqrt(m.shape[0]) + math.sqrt(p))
    if sv.size < 2 or not (sv[0] > DRIFT_DETECTION_FACTOR * floor and sv[0] > DRIFT_DETECTION_FACTOR * sv[1]):
        return np.zeros(n), "no common carrier drift detected"
    lead = u[:, 0]
    x, y = lead.real, lead.imag
    design = np.stack([2 * x, 2 * y, np.ones_like(x)], 1)
    (cx, cy, k), *_ = np.linalg.lstsq(design, x * x + y * y, rcond=None)
    centre = cx + 1j * cy
    radius = math.sqrt(max(k + abs(centre) ** 2, 0.0))
    spread = np.std(np.abs(lead - centre) - radius) / max(radius, 1e-300)
    if not (radius > 0 and spread < DRIFT_MAX_CIRCLE_SPREAD):
        return np.zeros(n), f"carrier drift not resolved (circle fit spread {spread:.2f}): treated as static"
    phi = np.unwrap(np.angle(lead - centre))
    phi = np.concatenate([np.full(half, phi[0]), phi, np.full(n - half - phi.size, phi[-1])])
    axis_turn, phase_turn = tone_axis_rotation(i + 1j * q, phi)
    if not axis_turn > DRIFT_MIN_AXIS_TURN_RAD:
        return np.zeros(n), (
            f"a slow common change found, but the tones' axis does not turn ({axis_turn:.2f} rad rms against "
            f"{phase_turn:.2f} for the change): an amplitude change (e.g. the modulator's roll-off), not a drift"
        )
    return phi - phi.mean(), f"common carrier drift found (rms {np.std(phi):.2f} rad)"


# Pixels a block of `centred_window_means`: Z's blocks (1.5 MB at 3000 frames) and their
# moving averages stay in cache, and the allocator hands the same memory back block after block
# where whole (N, P) temporaries each took fresh pages (docs/performance.md)
WINDOW_MEANS_BLOCK_PIXELS = 32


def centred_window_means(i, q, window_frames: int) -> tuple[np.ndarray, float]:
    """Z = I + iQ averaged over each whole window of `window_frames` frames, minus
    each pixel's time mean: (N − 2·half, P), half = window // 2, where the shrinking windows at
    the ends (which let the tone through) are left out; and the noise variance it implies: the
    high-passed Z's mean power over every frame, divided by the window (a pure-noise N×P matrix
    of entry variance v has a top singular value ≈ √v(√N + √P); the high-passed power, tone
    included, bounds v from above). Computed a block of pixels at a time: each pixel's values
    are those of the whole array's."""
    n, p = i.shape
    half = window_frames // 2
    m = np.empty((n - 2 * half, p), np.result_type(i.dtype, q.dtype, np.complex64))
    high_passed_power = 0.0
    for a in range(0, p, WINDOW_MEANS_BLOCK_PIXELS):
        cols = slice(a, a + WINDOW_MEANS_BLOCK_PIXELS)
        z = i[:, cols] + 1j * q[:, cols]
        average = moving_average(z, window_frames)
        residual = z - average
        high_passed_power += float(
            np.sum(residual.real**2, dtype=np.float64) + np.sum(residual.imag**2, dtype=np.float64)
        )
        whole = average[half : n - half]
        m[:, cols] = whole - whole.mean(axis=0)
    return m, high_passed_power / (n * p) / window_frames


def tone_sequences_only(z: np.ndarray, half_width_bins: int = TONE_HALF_WIDTH_BINS) -> np.ndarray:
    """Each pixel's tone alone: the bins within ±`half_width_bins` of its strongest bin away
    from DC (and of that bin's mirror, where a real tone's other half lies), transformed back.

    A moving average would also pass the mean term's drift-induced wobble, z_mean·e^{iφ}·iδφ,
    which squares to the *opposite* axis of the tone's and is comparable to it (w_0 ≈ 3 w_1
    at β = 2): under a strong drift it cancelled the tone's turn (measured: 0.05 rad rms
    against a drift of 1.1 rad). The drift broadens the tone by about a bin; the window keeps
    its wings."""
    n = z.shape[0]
    spectrum = np.fft.fft(z, axis=0)
    k = np.fft.fftfreq(n, 1.0 / n)  # signed bin index
    away = np.abs(k) > 2 * half_width_bins
    peak = np.argmax(np.where(away[:, None], np.abs(spectrum), -1.0), axis=0)  # (P,)
    distance = lambda centre: np.abs((k[:, None] - k[centre][None, :] + n / 2) % n - n / 2)
    keep = (distance(peak) <= half_width_bins) | (distance((n - peak) % n) <= half_width_bins)
    return np.fft.ifft(np.where(keep, spectrum, 0.0), axis=0)


def tone_axis_rotation(z: np.ndarray, phi: np.ndarray, segment_frames: int = DRIFT_WINDOW_FRAMES):
    """(rms turn of the tones' axis, rms turn of φ) over stretches of `segment_frames` frames (short
    enough that the doubled angle turns by less than π between neighbours: unwrapped).

    A carrier drift turns the whole of each pixel's Z, its tone too: the tone (`tone_sequences_only`)
    lies along z_p·e^{iφ}, so its axis, ½·arg Σ tone², follows φ from stretch to stretch, in every
    pixel alike. A slow amplitude change of the mean term (the modulator's roll-off of w_0 along
    the sweep) traces a line the circle fit can take for an arc, but turns no tone."""
    tone = tone_sequences_only(z)
    edges = np.linspace(0, z.shape[0], max(2, z.shape[0] // segment_frames) + 1).astype(int)
    whole = np.sum(tone**2, axis=0)
    reference = np.conj(whole) / np.maximum(np.abs(whole), 1e-300)
    turns, phases = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        part = np.sum(tone[a:b] ** 2, axis=0) * reference  # this stretch's axis against the whole's, doubled
        turns.append(0.5 * np.angle(np.sum(part)))
        phases.append(np.mean(phi[a:b]))
    turns, phases = np.unwrap(2 * np.asarray(turns)) / 2, np.asarray(phases)
    return float(np.std(turns)), float(np.std(phases))


def leading_singular_pairs(m: np.ndarray, count: int = 2, row_step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The `count` largest singular values of m (T, P) and their left vectors.

    The right vectors come from the eigenvectors of the P×P Gram matrix (cheaper than a full
    SVD for T ≫ P) of every `row_step`-th row: where m's rows change slowly (a moving average
    over a window much longer than `row_step`), those rows span the same leading directions.
    The values and left vectors are then taken from the whole of m along those directions
    (‖m v‖ and m v/‖m v‖), so they are m's own, not the sampled rows'."""
    sampled = m[::row_step]
    values, vectors = np.linalg.eigh(sampled.conj().T @ sampled)
    along = m @ vectors[:, np.argsort(values)[::-1][:count]]
    sv = np.linalg.norm(along, axis=0)
    return along / np.maximum(sv, 1e-300), sv


CARRIER_ALIGNMENTS = ("auto", "static", "tracked")
# Pixels of the first tile the automatic choice looks at: the strongest mean terms (echoes),
# those of integer frames ranked by their means over the first frames: a contiguous stretch (a
# stride over the frames would alias some tones onto the mean), enough to rank echoes by
# strength, without reading the whole tile
DRIFT_SAMPLE_PIXELS = 256
DRIFT_RANK_FRAMES = 512


@dataclasses.dataclass(frozen=True)
class CarrierAlignment:
    """The carrier alignment a reconstruction runs: `mode` "static" (each pixel's own axis),
    "tracked" (each pixel's drift followed) or "common" (a drift common to the capture,
    `phase_rad` (N,), removed first), and why (`reason`, recorded in the depth file)."""

    mode: str
    reason: str
    phase_rad: np.ndarray | None = None

    @property
    def tracking(self) -> bool:
        return self.mode == "tracked"

    @property
    def drift_rms_rad(self) -> float:
        return 0.0 if self.phase_rad is None else float(np.std(self.phase_rad))


def frame_means(frames) -> np.ndarray:
    """Each pixel's mean over the frames (axis 1) in float64. Integer frames of up to 16 bits
    are summed as integers, exactly (the float64 sums of a mean are exact too: the same
    values), in half the time of a float64 sum, which converts every value first."""
    n = frames.shape[1]
    if np.issubdtype(frames.dtype, np.integer) and frames.dtype.itemsize <= 2:
        wide = np.uint32 if n * np.iinfo(frames.dtype).max < 2**32 and frames.dtype.kind == "u" else np.int64
        return np.add.reduce(frames, axis=1, dtype=wide) / n
    return np.mean(frames, axis=1, dtype=np.float64)


def pixel_columns(frames, pixels):
    """The frames (4, N, K) of `pixels` (K,) of `frames` (4, N, P), or of (4, N, S, Q): S pieces
    of Q pixels, P = S·Q in row-major order."""
    if frames.ndim == 3:
        return frames[..., pixels]
    piece, column = np.divmod(pixels, frames.shape[-1])
    return frames[:, :, piece, column]


def choose_carrier_alignment(
    requested: str, frames=None, iq_weights=None, iq_bias=None, dark=None, gain=None
) -> CarrierAlignment:
    """The alignment for `requested` ∈ `CARRIER_ALIGNMENTS`. For "auto", `frames` (4, N, P) in
    DN — a sample of the capture, e.g. its first tile, or (4, N, S, Q) of it in S pieces of Q
    pixels — are searched for a common drift (`initial_common_drift`) in the
    `DRIFT_SAMPLE_PIXELS` pixels with the strongest mean term."""
    if requested == "static":
        return CarrierAlignment("static", "requested (--carrier static)")
    if requested == "tracked":
        return CarrierAlignment("tracked", "requested (--carrier tracked)")
    if requested != "auto":
        raise ValueError(f"carrier alignment must be one of {', '.join(CARRIER_ALIGNMENTS)}, got {requested!r}")
    n = frames.shape[1]
    if n <= DRIFT_MIN_WINDOWS * DRIFT_WINDOW_FRAMES:
        return CarrierAlignment("static", f"auto: {n} frames are too few to look for a carrier drift")
    # the strongest mean terms, from the frames' means (I/Q is linear in the frames): integer
    # frames over their first frames; floating ones over all, whose means also leave out a pixel
    # with a non-finite value in any frame
    ranked = frames[:, :DRIFT_RANK_FRAMES] if np.issubdtype(frames.dtype, np.integer) else frames
    means = frame_means(ranked).reshape(4, 1, -1)  # (4, 1, P)
    # in NumPy: a one-off survey, with no programs to compile or load in a fresh process
    pick = lambda a, idx: None if a is None else np.asarray(a, np.float32)[:, idx]
    everywhere = slice(None)
    weights, bias = np.asarray(iq_weights), np.asarray(iq_bias)
    i0, q0 = iq_from_frames(means.astype(np.float32), weights, bias, pick(dark, everywhere), pick(gain, everywhere))
    with np.errstate(invalid="ignore"):  # a pixel with a NaN frame has a NaN mean: left out
        strength = np.abs(np.asarray(i0[0], np.float64) + 1j * np.asarray(q0[0], np.float64))
    strength = np.where(np.isfinite(strength), strength, -1.0)
    keep = np.sort(np.argsort(-strength)[:DRIFT_SAMPLE_PIXELS])
    keep = keep[strength[keep] >= 0]
    if keep.size < 2:
        return CarrierAlignment("static", "auto: too few finite pixels to look for a carrier drift")
    x = np.asarray(pixel_columns(frames, keep), np.float32)
    i, q = iq_from_frames(x, weights, bias, pick(dark, keep), pick(gain, keep))
    i, q = np.asarray(i, np.float64), np.asarray(q, np.float64)
    phase, note = initial_common_drift(i, q)
    if np.any(phase != 0):
        return CarrierAlignment("common", f"auto: {note} in {keep.size} sample pixels; removed", phase)
    return CarrierAlignment("static", f"auto: {note} in {keep.size} sample pixels")
