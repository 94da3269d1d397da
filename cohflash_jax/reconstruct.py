"""Depth reconstruction of a capture, streamed in pixel tiles.

A capture is read in row tiles (the file's chunk rows) into two reused buffers; each tile is
cut into sub-tiles of a few hundred pixels (`sub_tile_pixels`) whose frames fit in cache,
dispatched asynchronously (on a GPU a tile is one piece). Per sub-tile (one
compiled function per sub-tile shape): data checks → I/Q (nominal or calibrated
hybrid) → carrier alignment (static or tracked) → one unwindowed unitary rFFT over the
frame index; its periodic-Hann spectrum (a 3-tap convolution of the same bins) gives the
coarse peak; `dft` reads depth off the peak bin, `interp` interpolates it, `ml` fits the
phase-locked model to the W bins around it (`estimate.ml`).
"""

from __future__ import annotations

import dataclasses
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from .calibration_file import Calibration
from .capture import Capture, CaptureError, frequency_problem
from .constants import SPEED_OF_LIGHT_M_PER_S as C
from .estimate.coarse import coarse_peak, hann_power, interpolate_peak, unitary_rfft
from .estimate.iq import carrier_axis, derotate, iq_from_frames, rotate_onto_axis, track_carrier_drift
from .estimate.ml import (FIRST_PASS_STEPS, UniformModel, crlb_frequency_only_m, grid_for, grid_orders,
                          refine_ml_uniform)
from .estimate.nonuniform import depth_grid, periodogram_coarse, refine_time_domain
from .estimate.table import ToneTable, build_tone_table, refine_ml_table, table_points, table_spacing_m
from .hybrid import Hybrid
from .modulator import MZM
from .runtime import async_filter_jit, retain_freed_memory

METHODS = ("dft", "interp", "ml")
STATUS = {0: "ok", 1: "low_snr", 2: "not_converged", 3: "fit_failed", 4: "bad_data (NaN/inf)",
          5: "saturated", 6: "dead (constant)", 7: "out_of_range", 8: "outside_registration",
          9: "poor_fit (reduced χ² above max_fit_chi2)", 10: "dc_edge (power rises towards DC: slow drift)"}
OK, LOW_SNR, NOT_CONVERGED, FIT_FAILED, BAD_DATA, SATURATED, DEAD, OUT_OF_RANGE = range(8)
POOR_FIT = 9
DC_EDGE = 10
DEFAULT_SNR_THRESHOLD_DB = 14.0
MIN_FRAMES = 4

# Reduced χ² of the ML window fit above which the model does not describe the pixel (measured:
# ≤ 2.9 at 30 dB peak-bin SNR with sidebands and roll-off; ~18 when carrier tracking failed
# through an uncalibrated hybrid and the "tone" found was drift clutter near DC)
DEFAULT_MAX_FIT_CHI2 = 5.0


def snr_threshold_margin(num_frames: int) -> float:
    """Factor on the SNR threshold for the noise variance's own estimation error: σ² comes from
    the pixel's N frames, with relative standard deviation √(2/(N−1)), and a pixel is valid when
    its SNR with σ² one standard deviation above the estimate clears the threshold (N = 3000:
    +0.11 dB; N = 35: +1.2 dB). Measured on the 35-frame 10 Hz mode at falling reflectance
    (112 k pixels): the fits more than 5 CRLB off reached 14.16 dB of measured SNR, so a bare
    14 dB threshold passed 4 of 5051 such pixels; none reached 15 dB."""
    return 1.0 / max(1.0 - math.sqrt(2.0 / max(num_frames - 1, 1)), 0.25)


def applied_snr_threshold_db(threshold_db: float, num_frames: int) -> float:
    """The SNR threshold (dB) a reconstruction of N frames applies for a requested one."""
    return threshold_db + 10 * math.log10(snr_threshold_margin(num_frames))


class TileConfig(eqx.Module):
    iq_weights: jax.Array
    iq_bias: jax.Array
    model: UniformModel
    saturation_dn: float | None = eqx.field(static=True)
    method: str = eqx.field(static=True)
    tracking: bool = eqx.field(static=True)
    track_window: int = eqx.field(static=True)
    window_bins: int = eqx.field(static=True)
    grid_half_width_m: float = eqx.field(static=True)
    grid_points: int = eqx.field(static=True)
    grid_candidates: int = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    dominant_order: int = eqx.field(static=True)
    ambiguity_m: float = eqx.field(static=True)
    bin_depth_m: float = eqx.field(static=True)
    snr_threshold: float = eqx.field(static=True)
    dtype: str = eqx.field(static=True)
    uniform: bool = eqx.field(static=True, default=True)
    frequencies_hz: jax.Array | None = None  # non-uniform path only
    depth_grid_m: jax.Array | None = None  # non-uniform path only: coarse periodogram depths
    min_bin: int = eqx.field(static=True, default=1)  # coarse search starts here (--min-depth-m)
    # the unambiguous depth window (m) and the half-period of total delay it maps to (`delay_window`)
    depth_window_m: tuple[float, float] = eqx.field(static=True, default=(0.0, math.inf))
    fold_index: int = eqx.field(static=True, default=0)
    max_fit_chi2: float = eqx.field(static=True, default=DEFAULT_MAX_FIT_CHI2)
    grid_max_order: int | None = eqx.field(static=True, default=None)  # ml basin grid (`grid_orders`)
    tone_table: ToneTable | None = None  # ml on short uniform sweeps (`TABLE_MAX_FRAMES`)
    # f_0 a whole multiple of Δf: the model is symmetric about the window's edges (`reflect_into_window`)
    mirror_symmetric: bool = eqx.field(static=True, default=False)


def process_tile(cfg: TileConfig, frames, dark, data_status=None, gain=None, carrier_phase_rad=None):
    """Depth and companions for a tile of pixels: frames (4, N, P) → dict of (P,) arrays.
    `dark` (4, P): per-pixel offsets (DN); `gain` (4, P): per-pixel gains relative to the
    hybrid's global ones; `data_status` (P,) int8: codes found upstream (e.g. registration);
    `carrier_phase_rad` (N,): a known carrier drift common to all pixels, removed first.

    Three or four compiled programs, dispatched asynchronously: data checks and I/Q in the
    file's (frame, pixel) layout, with the carrier axis from I/Q's moments; the rotation onto
    it; and `invert_sequence`, which transposes the real sequence to (pixel, frame) for the FFT
    along its contiguous last axis. XLA's CPU compiler fuses these badly: within one program
    it recomputed the per-pixel cos/sin of the carrier axis for every frame, and computed the
    rotated sequence straight into the transposed layout, reading I/Q with a stride (see
    `align_carrier_static`; for 512 px × 3000 frames 4.0 ms for the rotation, transpose and
    FFT fused against 1.7 ms apart). For long sweeps (`SPLIT_AXIS_MIN_FRAMES`) the carrier axis
    is a program of its own too: fused with I/Q, its moments recomputed I/Q from the frames
    (`dft`, per pixel, interleaved runs: 1000 frames 5.8 → 4.7 µs, 3000 frames 13.2 → 11.5 µs;
    35–300 frames unchanged or ~5 % slower, where the extra dispatch costs more)."""
    if frames.shape[1] >= SPLIT_AXIS_MIN_FRAMES:
        i, q, flags = iq_and_checks(cfg, frames, dark, gain, carrier_phase_rad)
        c, s, noise_var = _carrier_axis(i, q)
    else:
        i, q, (c, s, noise_var), flags = iq_and_carrier_axis(cfg, frames, dark, gain, carrier_phase_rad)
    return invert_sequence(cfg, _rotate_onto_axis(i, q, c, s), noise_var, flags, data_status)


SPLIT_AXIS_MIN_FRAMES = 512
# `ml` on uniform sweeps of at most this many frames fits every frame in the time domain from
# a tone table (`estimate.table`), if the table needs at most `TABLE_MAX_POINTS` grid depths
# (its basin search is a (P, N)·(N, G) product, O(N·G) a pixel); longer sweeps, and narrow
# ones high in frequency (thousands of depths), fit the DFT window (`estimate.ml`). Measured
# on the 35-frame 10 Hz mode (256×320, 2 cores, interleaved): `ml` 85 ms per depth map
# against 472 ms with the DFT-window fit (`dft` 31 ms), same valid pixels and precision.
TABLE_MAX_FRAMES = 64
TABLE_MAX_POINTS = 1024
# The ML polish's straggler pass pays off for short sweeps, whose large batches hold a few
# pixels that need 2–3× the steps of the rest (10 Hz mode: the fit 7.8 → 5.5 µs a pixel); at
# 3000 frames it measured neutral (±5 %) and its second polish adds ~4 s of compilation.
TWO_PASS_MAX_FRAMES = 512
_rotate_onto_axis = jax.jit(rotate_onto_axis)


def _axis(i, q):
    """`carrier_axis`'s cos φ, sin φ and noise variance (float64, as the ML stage uses it)."""
    c, s, noise_var, _ = carrier_axis(i, q)
    return c, s, noise_var.astype(jnp.float64)


_carrier_axis = jax.jit(_axis)


def _checks_and_iq(cfg: TileConfig, frames, dark, gain=None, carrier_phase_rad=None):
    """Data checks and I/Q: frames (4, N, P) → I, Q (N, P) (drift removed where asked) and the
    data flags (dead, saturated, finite), each (P,)."""
    real = jnp.float64 if cfg.dtype == "float64" else jnp.float32
    high, low = jnp.max(frames, axis=1), jnp.min(frames, axis=1)  # (4, P)
    dead = jnp.any(high == low, axis=0)
    saturated = jnp.zeros(dead.shape, bool) if cfg.saturation_dn is None else jnp.any(high >= cfg.saturation_dn, axis=0)
    if jnp.issubdtype(frames.dtype, jnp.floating):
        finite = jnp.all(jnp.isfinite(frames), axis=(0, 1))
        frames = jnp.where(jnp.isfinite(frames), frames, 0.0)
    else:
        finite = jnp.ones(dead.shape, bool)
    i, q = iq_from_frames(frames.astype(real), cfg.iq_weights, cfg.iq_bias, dark, gain)  # (N, P) each
    if carrier_phase_rad is not None:
        i, q = derotate(i, q, jnp.asarray(carrier_phase_rad, i.dtype)[:, None])
    if cfg.tracking:  # remove a slow carrier drift first (turbulence)
        i, q = derotate(i, q, track_carrier_drift(i, q, cfg.track_window))
    return i, q, (dead, saturated, finite)


iq_and_checks = async_filter_jit(_checks_and_iq)


@async_filter_jit
def iq_and_carrier_axis(cfg: TileConfig, frames, dark, gain=None, carrier_phase_rad=None):
    """`iq_and_checks` and the carrier axis in one program → I, Q, (cos φ, sin φ, noise
    variance), flags."""
    i, q, flags = _checks_and_iq(cfg, frames, dark, gain, carrier_phase_rad)
    return i, q, _axis(i, q), flags


@async_filter_jit
def invert_sequence(cfg: TileConfig, r, noise_var, flags, data_status=None):
    """Depth, its σ, amplitude, SNR and status per pixel from the carrier-aligned sequence
    r (N, P) and the carrier axis's noise variance and the data flags (`iq_and_checks`)."""
    dead, saturated, finite = flags
    n = r.shape[0]
    if cfg.uniform:
        depth, amplitude, sigma, coarse, converged, finite_fit, wandered, chi2, dc_edge = _invert_uniform(cfg, r, noise_var)
    else:
        depth, amplitude, sigma, coarse, converged, finite_fit, wandered = _invert_nonuniform(cfg, r, noise_var)
        chi2 = jnp.full(depth.shape, -1.0)
        dc_edge = jnp.zeros_like(wandered)
    # a fit that ran off (seen at ~7 dB: 1e14 m) is flagged out_of_range, a peak on the DC edge
    # dc_edge; both report the coarse depth, so depth maps of flagged pixels stay in range
    depth = jnp.where(wandered | dc_edge, coarse, depth)
    snr = n * (amplitude * cfg.model.weights[cfg.dominant_order]) ** 2 / jnp.maximum(noise_var, 1e-30)
    out_of_range = (depth < max(0.0, cfg.depth_window_m[0])) | (depth >= cfg.depth_window_m[1]) | wandered
    status = jnp.full(depth.shape, OK, jnp.int8)
    # later conditions win: the status names the most basic reason a pixel is invalid
    for cond, code in ((out_of_range, OUT_OF_RANGE), (chi2 > cfg.max_fit_chi2, POOR_FIT), (dc_edge, DC_EDGE),
                       (~converged, NOT_CONVERGED),
                       (snr < cfg.snr_threshold, LOW_SNR),
                       (~finite_fit, FIT_FAILED), (dead, DEAD), (saturated, SATURATED), (~finite, BAD_DATA)):
        status = jnp.where(cond, jnp.int8(code), status)
    if data_status is not None:
        status = jnp.where(data_status != 0, data_status.astype(jnp.int8), status)
    safe = lambda a: jnp.where(jnp.isfinite(a), a, 0.0)
    return {"depth_m": safe(depth), "amplitude": safe(amplitude), "sigma_m": safe(sigma),
            "snr": safe(snr), "fit_status": status, "valid": status == OK, "coarse_depth_m": safe(coarse),
            "fit_chi2": safe(chi2)}


def _invert_uniform(cfg: TileConfig, r, noise_var):
    """Uniform sweep: rFFT over the frame index, Hann peak, then (ml) the DFT-window fit."""
    n = r.shape[0]
    spec = unitary_rfft(r)  # (P, K)
    power = hann_power(spec, n)
    peak = coarse_peak(power, cfg.min_bin)
    frac_bin = peak.astype(jnp.float64) if cfg.method == "dft" else interpolate_peak(power, peak).astype(jnp.float64)
    m = cfg.model
    coarse = unfold_delay(frac_bin / n, 1 / (cfg.dominant_order * m.step_hz), cfg.fold_index,
                          m.system_delay_s) * C / 2
    tone_weight = m.weights[cfg.dominant_order]
    if cfg.method == "ml" and cfg.tone_table is not None:  # short sweep: time-domain ML from the tone table
        fit = refine_ml_table(cfg.tone_table, m, r, coarse, noise_var, half_width_m=cfg.grid_half_width_m,
                              max_steps=cfg.max_steps, prefer_positive=cfg.grid_candidates > 1)
        # reduced χ² over the N frames less the three fitted unknowns (noise floored as below)
        floor = 1e-9 * jnp.mean(jnp.square(r.astype(jnp.float64)), axis=0)
        chi2 = fit.cost / (jnp.maximum(noise_var, jnp.maximum(floor, 1e-30)) * (n - 3))
    elif cfg.method == "ml":
        k_count = spec.shape[-1]
        w = min(cfg.window_bins, k_count)
        k0 = jnp.clip(peak - w // 2, 0, k_count - w)
        windows = jnp.take_along_axis(spec, k0[:, None] + jnp.arange(w), axis=-1).astype(jnp.complex128)
        # the straggler pass (`refine_ml_uniform`) for short sweeps only (`TWO_PASS_MAX_FRAMES`)
        first_pass = FIRST_PASS_STEPS if n < TWO_PASS_MAX_FRAMES else cfg.max_steps
        fit = refine_ml_uniform(m, windows, k0, coarse, noise_var, grid_half_width_m=cfg.grid_half_width_m,
                                grid_points=cfg.grid_points, max_steps=cfg.max_steps,
                                candidates=cfg.grid_candidates, grid_max_order=cfg.grid_max_order,
                                first_pass_steps=first_pass)
        # reduced χ² of the window fit: each unitary bin holds noise of variance σ²/2 per
        # component; 2W real residuals less the three fitted unknowns
        # (noise floored at 1e-9 of the window's mean power: noiseless data have rounding-level
        # residuals and a zero noise estimate, which is not a misfit)
        floor = 1e-9 * jnp.mean(jnp.abs(windows) ** 2, axis=-1)
        chi2 = fit.cost / (0.5 * jnp.maximum(noise_var, jnp.maximum(floor, 1e-30)) * (2 * w - 3))
    if cfg.method == "ml":
        depth, amplitude, sigma = fit.depth_m, jnp.abs(fit.amplitude), fit.sigma_depth_m
        if cfg.mirror_symmetric:
            depth = reflect_into_window(depth, cfg.depth_window_m)
        finite_fit = jnp.isfinite(depth) & jnp.isfinite(sigma) & jnp.isfinite(amplitude) & fit.well_posed
        converged = fit.converged
        wandered = jnp.abs(depth - coarse) > 2 * cfg.bin_depth_m
    else:
        # amplitude from the Hann peak: |H| = a·w·√N/4 for a tone a·2w·cos, Hann gain ½
        peak_mag = jnp.sqrt(jnp.take_along_axis(power, peak[:, None], axis=-1)[:, 0]).astype(jnp.float64)
        amplitude = 2 * peak_mag / (math.sqrt(n) * tone_weight)
        depth = coarse
        sigma = crlb_frequency_only_m(n, m.step_hz, amplitude * 2 * tone_weight, jnp.sqrt(noise_var),
                                      cfg.dominant_order)
        if cfg.method == "dft":  # a bin read off without interpolation is uniform within ±½ bin
            sigma = jnp.maximum(sigma, cfg.bin_depth_m / math.sqrt(12))
        finite_fit = jnp.isfinite(depth)
        converged = jnp.ones_like(finite_fit)
        wandered = jnp.zeros_like(finite_fit)
        chi2 = jnp.full(depth.shape, -1.0)  # not computed
    # the DC edge: a peak on the first searched bin with more power just below it is the tail
    # of a spectrum rising towards DC — slow drift looks exactly so (measured at 35 frames: a
    # quadratic drift and no echo gave 16 of 64 pixels "valid" at one bin, χ² < 5, all with
    # this signature; so does an untracked turbulent carrier, whose mean term wanders); such a
    # pixel is flagged dc_edge and reports the coarse depth
    dc_edge = (peak == cfg.min_bin) & (power[:, cfg.min_bin - 1] > power[:, cfg.min_bin])
    return depth, amplitude, sigma, coarse, converged, finite_fit, wandered, chi2, dc_edge


def _invert_nonuniform(cfg: TileConfig, r, noise_var):
    """Non-uniform schedule: periodogram over a depth grid, then (ml) the time-domain fit."""
    m = cfg.model
    f = cfg.frequencies_hz
    depths = cfg.depth_grid_m
    coarse, peak_amp = periodogram_coarse(r, f, depths, m.system_delay_s)
    if cfg.method == "dft":  # nearest grid depth, no interpolation
        step = depths[1] - depths[0]
        coarse = depths[0] + jnp.round((coarse - depths[0]) / step) * step
    tone_weight = m.weights[cfg.dominant_order]
    if cfg.method == "ml":
        fit = jax.vmap(lambda rr, d, v: refine_time_domain(
            rr, f, m.weights, d, v, system_delay_s=m.system_delay_s, grid_half_width_m=cfg.grid_half_width_m,
            grid_points=cfg.grid_points, max_steps=cfg.max_steps))(r.T, coarse, noise_var)
        depth, amplitude, sigma = fit.depth_m, jnp.abs(fit.amplitude), fit.sigma_depth_m
        finite_fit = jnp.isfinite(depth) & jnp.isfinite(sigma) & jnp.isfinite(amplitude) & fit.well_posed
        return depth, amplitude, sigma, coarse, fit.converged, finite_fit, jnp.abs(depth - coarse) > 2 * cfg.bin_depth_m
    amplitude = peak_amp / (2 * tone_weight)
    # frequency-only bound for an arbitrary schedule: the tone's phase is a nuisance, so only
    # the spread of f_m about its mean informs τ: var τ = σ²/(a²/2 · Σ(2π(f_m − f̄))²)
    spread = jnp.sum((2 * jnp.pi * (f - jnp.mean(f))) ** 2)
    sigma = C / 2 * jnp.sqrt(noise_var / (0.5 * (amplitude * 2 * tone_weight) ** 2 * spread + 1e-300))
    if cfg.method == "dft":
        sigma = jnp.maximum(sigma, (depths[1] - depths[0]) / math.sqrt(12))
    finite_fit = jnp.isfinite(coarse)
    return coarse, amplitude, sigma, coarse, jnp.ones_like(finite_fit), finite_fit, jnp.zeros_like(finite_fit)


@dataclasses.dataclass
class ReconstructOptions:
    method: str = "ml"
    tracking: bool = False
    track_window_frames: int = 101
    tile_rows: int = 32  # = the capture writer's chunk rows: each chunk is read once
    window_bins: int = 17
    max_steps: int = 16
    snr_threshold_db: float = DEFAULT_SNR_THRESHOLD_DB
    dtype: str = "float32"
    progress: bool = True
    min_depth_m: float = 0.0  # coarse search ignores shallower depths (slow drift / leakage lives near DC)
    max_fit_chi2: float = DEFAULT_MAX_FIT_CHI2  # ml: pixels whose window fit is worse are flagged poor_fit

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError("dtype must be float32 or float64")
        if self.tile_rows < 1:
            raise ValueError("tile_rows must be ≥ 1")
        if not self.min_depth_m >= 0:
            raise ValueError(f"min_depth_m must be ≥ 0, got {self.min_depth_m}")
        # NaN compares false: a NaN threshold would pass every pixel, a NaN χ² limit none
        if not math.isfinite(self.snr_threshold_db):
            raise ValueError(f"snr_threshold_db must be a finite number of dB, got {self.snr_threshold_db}")
        if not (self.max_fit_chi2 > 0):
            raise ValueError(f"max_fit_chi2 must be positive, got {self.max_fit_chi2}")
        if self.window_bins < 3 or self.max_steps < 1 or self.track_window_frames < 3:
            raise ValueError(f"window_bins (≥ 3), max_steps (≥ 1) and track_window_frames (≥ 3) out of range: "
                             f"{self.window_bins}, {self.max_steps}, {self.track_window_frames}")


def frequency_path(cfg: TileConfig) -> str:
    """Which estimator a configuration runs, in words (recorded in the depth file)."""
    if not cfg.uniform:
        return "non-uniform schedule: periodogram over a depth grid; time-domain ML over all frames"
    if cfg.method == "ml" and cfg.tone_table is not None:
        return ("uniform sweep: rFFT over the frame index; ML over all frames from a tone table "
                f"({cfg.tone_table.num_points} depths)")
    return "uniform sweep: rFFT over the frame index" + ("; ML on the DFT window (Dirichlet kernels)"
                                                         if cfg.method == "ml" else "")


def modulator_from_attrs(attrs: dict) -> MZM:
    """The capture's modulator (optional attributes) or the default MZM."""
    default = MZM()
    return MZM(float(attrs.get("modulation_index", default.modulation_index)),
               float(attrs.get("bias_rad", default.bias_rad)),
               max_order=int(attrs.get("sideband_max_order", default.max_order)))


def delay_window(period_s: float, system_delay_s: float) -> tuple[int, tuple[float, float]]:
    """Where depth is unambiguous, given the beat tone's delay period P = 1/(order·Δf) and the
    system delay τ_sys. A real tone's DFT shows its total delay τ folded into [0, P/2]: τ and
    −τ modulo P look alike. Depths are therefore unambiguous over one half-period of total
    delay, [jP/2, (j+1)P/2); j is the half-period boundary nearest τ_sys, so the window
    [(jP/2 − τ_sys)·c/2, ((j+1)P/2 − τ_sys)·c/2) starts within a quarter period of depth 0.
    τ_sys = 0 gives [0, c/(4·order·Δf)); τ_sys = 6.7 ns (1 m of extra one-way path) gives
    [−1 m, c/(4·order·Δf) − 1 m), and a target beyond the window's end folds back onto it.
    Pixels outside [max(0, start), end) are flagged out of range. Returns (j, (start_m, end_m))."""
    half = period_s / 2
    fold = int(math.floor(system_delay_s / half + 0.5))
    return fold, ((fold * half - system_delay_s) * C / 2, ((fold + 1) * half - system_delay_s) * C / 2)


def reflect_into_window(depth_m, window_m: tuple[float, float]):
    """A depth beyond an edge of the unambiguous window (`delay_window`), reflected about that
    edge. Where f_0 is a whole multiple of Δf (a comb such as the 10 Hz mode's, f_m = (m+1)Δf)
    cos(2π n f_m τ) is exactly symmetric about every multiple of P/2 = 1/(2Δf) of total delay,
    the window's edges: a target 1 mm inside an edge and its mirror 1 mm beyond give the same
    frames, and the ML fit may land on either. The window's convention picks the one inside."""
    lo, hi = window_m
    return jnp.where(depth_m >= hi, 2 * hi - depth_m, jnp.where(depth_m < lo, 2 * lo - depth_m, depth_m))


def unfold_delay(folded_cycles, period_s: float, fold_index: int, system_delay_s: float):
    """Depth delay (s, two-way, τ_sys removed) from the tone's frequency in cycles per frame
    (folded into [0, ½]), placed in the half-period `fold_index` of `delay_window`."""
    k, odd = divmod(fold_index, 2)
    folded_s = folded_cycles * period_s
    return k * period_s + ((period_s - folded_s) if odd else folded_s) - system_delay_s


def build_config(frequencies_hz, hybrid: Hybrid, modulator: MZM, system_delay_s: float,
                 saturation_dn, options: ReconstructOptions) -> TileConfig:
    problem = frequency_problem(frequencies_hz)
    if problem:
        raise ValueError(problem)
    f = np.asarray(frequencies_hz, np.float64)
    n = f.size
    if n < MIN_FRAMES:
        raise ValueError(f"{n} frames are too few to reconstruct depth: need ≥ {MIN_FRAMES} (a tone's DFT peak "
                         "beyond DC, with a neighbour on each side)")
    step = float(np.median(np.diff(f)))
    uniform = bool(np.allclose(np.diff(f), step, rtol=1e-9, atol=1e-3))
    # sideband weights at the sweep's mean frequency: with a roll-off the fundamental's
    # amplitude tapers over the band, which to first order leaves the phase-locked depth
    # unbiased (the taper's odd part is in quadrature with the tone's even kernel)
    weights = np.asarray(modulator.weights(float(np.mean(f))), np.float64)
    if weights.shape[0] < 2 or not np.any(weights[1:] > 1e-12 * max(weights[0], 1e-300)):
        raise ValueError("the modulator settings give no beat tone (all sideband weights beyond n=0 vanish): "
                         "check modulation_index and bias_rad")
    dominant = int(np.argmax(weights[1:]) + 1)
    ripple = C / (2 * float(np.mean(f)))
    if uniform:
        bin_depth = C / (2 * n * step)
        half, points, candidates = grid_for(bin_depth, ripple)
    else:  # the envelope width c/(2B) plays the bin's part
        bin_depth = float(C / (2 * (f[-1] - f[0])))
        half, points, candidates = grid_for(bin_depth, ripple)
        candidates = 1
    iq_w, iq_b = hybrid.iq_matrix_dn(1.0)
    model = UniformModel(float(f[0]), step, jnp.asarray(weights), float(system_delay_s), num_frames=n)
    # a non-uniform schedule is unambiguous up to its finest step (coarser steps add sidelobes)
    period = 1 / ((step if uniform else float(np.min(np.diff(f)))) * dominant)
    ambiguity = C * period / 4
    fold, window = delay_window(period, float(system_delay_s))
    harmonics = f[0] / step
    extra = {"max_fit_chi2": float(options.max_fit_chi2), "depth_window_m": window, "fold_index": fold,
             "grid_max_order": grid_orders(weights),
             "mirror_symmetric": bool(uniform and abs(harmonics - round(harmonics)) < 1e-9 * max(1.0, harmonics))}
    if options.min_depth_m > 0:
        if not uniform:
            raise ValueError("min_depth_m applies to uniform sweeps only")
        if fold % 2:
            raise ValueError(f"min_depth_m: with a system delay of {system_delay_s:.4g} s depth grows towards "
                             "lower DFT bins (an odd half-period of delay), where a lower bin limit cannot apply")
        first = (2 * options.min_depth_m / C + system_delay_s - fold // 2 * period) / period * n
        if first >= n // 2:
            raise ValueError(f"min_depth_m = {options.min_depth_m} m leaves no depth below the ambiguity limit")
        extra["min_bin"] = max(1, int(math.floor(first)))
    if uniform and options.method == "ml" and n <= TABLE_MAX_FRAMES:
        spacing = table_spacing_m(f, weights)
        # the table spans the window and the basin search's reach beyond it
        span = (window[0] - half - spacing, window[1] + half + spacing)
        if table_points(span, spacing) <= TABLE_MAX_POINTS:
            extra["tone_table"] = build_tone_table(f, weights, float(system_delay_s), span, spacing)
    if not uniform:
        extra.update({"uniform": False, "frequencies_hz": jnp.asarray(f),
                      "depth_grid_m": jnp.asarray(depth_grid(f, window))})
        extra.pop("min_bin", None)
    return TileConfig(iq_w, iq_b, model, saturation_dn, options.method, options.tracking,
                      options.track_window_frames, options.window_bins, half, points, candidates, options.max_steps,
                      dominant, ambiguity, bin_depth, 10 ** (applied_snr_threshold_db(options.snr_threshold_db, n) / 10),
                      options.dtype, **extra)


def reconstruct_array(frames, frequencies_hz, options: ReconstructOptions | None = None, *,
                      hybrid: Hybrid | None = None, modulator: MZM | None = None, system_delay_s: float = 0.0,
                      dark=None, saturation_dn=None, carrier_phase_rad=None) -> dict:
    """Reconstruct in-memory frames (4, N, H, W) → dict of (H, W) arrays, in sub-tiles
    dispatched asynchronously (as `reconstruct_capture` does within each streamed tile).
    `carrier_phase_rad` (N,): a known common carrier drift to remove (calibration)."""
    options = options or ReconstructOptions(progress=False)
    retain_freed_memory()
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[0] != 4:
        raise ValueError(f"frames must have shape (4, N, H, W), got {frames.shape}")
    _, n, h, w = frames.shape
    for name, arr, shape in (("frequencies_hz", frequencies_hz, (n,)), ("dark", dark, (4, h, w)),
                             ("carrier_phase_rad", carrier_phase_rad, (n,))):
        if arr is not None and np.shape(arr) != shape:
            raise ValueError(f"{name} must have shape {shape} to match frames {frames.shape}, got {np.shape(arr)}")
    cfg = build_config(frequencies_hz, hybrid or Hybrid(), modulator or MZM(), system_delay_s, saturation_dn, options)
    d = None if dark is None else np.asarray(dark, np.float32).reshape(4, h * w)
    carrier = None if carrier_phase_rad is None else jnp.asarray(carrier_phase_rad)
    out = gather_tile(dispatch_tile(cfg, frames.reshape(4, n, h * w), d, None, None, sub_tile_pixels(h * w, n), carrier))
    return {k: v.reshape(h, w) for k, v in out.items()}


def sub_tile_pixels(num_pixels: int, num_frames: int, budget_bytes: int = 12 * 2**20, min_pieces: int = 4,
                    max_pixels: int = 8192, platform: str | None = None, device_budget_bytes: int = 256 * 2**20) -> int:
    """Pixels per dispatched sub-tile on `platform` (default: JAX's default backend).

    CPU: the uint16 frames of a sub-tile (4·N·2 bytes a pixel) fit in ~12 MiB, so its I/Q,
    moment and FFT passes run from cache (measured on 2 cores, N = 3000: 10240-px tiles 0.87 s,
    640-px sub-tiles 0.38 s per 10240 px for `dft`), and a tile gives at least `min_pieces`
    sub-tiles, dispatched asynchronously (`runtime.async_filter_jit`: with `eqx.filter_jit`
    every program waited for its result, so the pipeline ran serially; made asynchronous,
    interleaved runs on the full capture from its file: `dft` 1.94–2.01 → 1.57–1.63 s, `ml`
    2.37–3.39 → 2.06–2.17 s; 10 Hz `dft` 49 → 38–42 ms, `ml` unchanged within noise). At most
    `max_pixels`: short sweeps would otherwise give a few huge pieces (measured, 10 Hz mode, 35
    frames, 256×320, with the two-pass polish of `refine_ml_uniform`: `dft` 65 / 46 / 39 / 35 ms
    per depth map in 1024 / 2048 / 4096 / 8192-px pieces, `ml` 603 / 545 / 545 / 534 ms; before
    that polish a vmapped fit ran as long as the slowest of its pixels, and 20480-px pieces
    took `ml` 1.87 s against 0.99 s in 2048).

    GPU (any other platform): the whole tile, one launch sequence — its pixels run in
    parallel, and per-dispatch overhead dominates small pieces (measured on an H100, 10 Hz
    mode: `ml` 133 ms per depth map in 2048-px pieces, 23 ms as one; full 320×256×3000
    capture from its file, `ml` 1.8 s in CPU-sized sub-tiles, 0.93 s in whole tiles) — up to
    `device_budget_bytes` of frames a piece (a 32-row tile of 3000 frames is 245 MB; its
    float intermediates take several times that on the device)."""
    if (platform or jax.default_backend()) != "cpu":
        return int(max(1, min(num_pixels, device_budget_bytes // (8 * max(1, num_frames)))))
    by_memory = budget_bytes // (8 * max(1, num_frames))
    return int(max(1, min(num_pixels, by_memory, max_pixels, max(256, -(-num_pixels // min_pieces)))))


def aligned_copy(view: np.ndarray, width: int) -> np.ndarray:
    """A C-contiguous copy of `view`, its last axis zero-padded to `width`, in a 64-byte
    aligned buffer, which `jax.device_put` aliases on the CPU instead of copying again
    (`jnp.asarray` of a strided sub-tile copies twice: measured 1.42 → 1.14 ms a 524-px
    sub-tile of 3000 frames)."""
    shape = view.shape[:-1] + (width,)
    size = math.prod(shape)
    raw = np.empty(size * view.itemsize + 64, np.uint8)
    start = -raw.ctypes.data % 64
    out = raw[start:start + size * view.itemsize].view(view.dtype).reshape(shape)
    out[..., :view.shape[-1]] = view
    out[..., view.shape[-1]:] = 0
    return out


def stream_devices() -> list:
    """The devices sub-tiles are spread over, in turn: every local CPU device where JAX has
    several (`runtime.use_cpu_streams`), else the default device alone. One CPU device runs
    its programs one at a time, and the serial stretches of a program (the ML polish's Newton
    loop on a few hundred pixels) leave the other cores idle; two devices run two sub-tiles'
    programs at once."""
    devices = jax.local_devices()
    return devices if devices[0].platform == "cpu" else devices[:1]


_placed: list = []  # the last (cfg, carrier, devices, their copies) of `_configs_on_devices`


def _configs_on_devices(cfg: TileConfig, carrier_phase_rad, devices: tuple) -> list:
    """(cfg, carrier) committed to each of `devices` — copied once per reconstruction, not once
    per tile: the last placement is kept and reused while the same objects come back."""
    if len(devices) == 1:
        return [(cfg, carrier_phase_rad)]
    if _placed and _placed[0] is cfg and _placed[1] is carrier_phase_rad and _placed[2] == devices:
        return _placed[3]
    put = lambda tree, device: jax.tree.map(lambda x: jax.device_put(x, device) if eqx.is_array(x) else x, tree)
    configs = [put((cfg, carrier_phase_rad), d) for d in devices]
    _placed[:] = [cfg, carrier_phase_rad, devices, configs]
    return configs


def dispatch_tile(cfg: TileConfig, frames, dark=None, data_status=None, gain=None, sub_px: int | None = None,
                  carrier_phase_rad=None):
    """`process_tile` over a tile (4, N, P) in sub-tiles of `sub_px` pixels, each dispatched
    asynchronously (the last padded to the same shape: one compilation per device), in turn on each of
    `stream_devices`. Returns the per-sub-tile result dicts; `gather_tile` joins them."""
    p = frames.shape[-1]
    sub = p if sub_px is None else min(sub_px, p)
    pieces = -(-p // sub)
    devices = stream_devices()
    configs = _configs_on_devices(cfg, carrier_phase_rad, tuple(devices))

    def piece(arr, k, device):
        if arr is None:
            return None
        part = arr[..., k * sub:(k + 1) * sub]
        if isinstance(part, np.ndarray):  # one host copy at most (none for a whole contiguous tile)
            whole = part.shape[-1] == sub and part.flags.c_contiguous
            return jax.device_put(part if whole else aligned_copy(part, sub), device)
        if part.shape[-1] < sub:
            part = jnp.pad(part, [(0, 0)] * (part.ndim - 1) + [(0, sub - part.shape[-1])])
        return part if len(devices) == 1 else jax.device_put(part, device)

    out = []
    for k in range(pieces):
        device = devices[k % len(devices)] if len(devices) > 1 else None
        tile_cfg, carrier = configs[k % len(configs)]
        out.append(process_tile(tile_cfg, piece(frames, k, device), piece(dark, k, device),
                                piece(data_status, k, device), piece(gain, k, device), carrier))
    return out, p


def gather_tile(results) -> dict:
    """Join `dispatch_tile`'s results → dict of (P,) NumPy arrays (blocks until computed)."""
    parts, p = results
    return {k: np.concatenate([np.asarray(r[k]) for r in parts])[:p] for k in parts[0]}


def _collect(pending, outputs, h, w, rows, bar):
    """Gather a dispatched tile into rows r0:r1 of `outputs` and advance the progress bar."""
    results, r0, r1 = pending
    for k, v in gather_tile(results).items():
        arr = v.reshape(rows, w)[: r1 - r0]
        outputs.setdefault(k, np.empty((h, w), arr.dtype))[r0:r1] = arr
    bar.update((r1 - r0) * w)


class _BlockReader:
    """Row tiles of a capture read into two reused buffers. On the CPU a contiguous NumPy
    array can become a device array without a copy (JAX aliases 64-byte-aligned buffers), so
    a buffer is reused only after the tile read into it has been gathered (the caller
    collects tile k before reading tile k + 2).
    Allocating a fresh ~250 MB array per tile costs more than the read itself on a cold VM
    (first touch of its memory)."""

    def __init__(self, capture: Capture, rows: int):
        n, h, w = capture.shape
        self.capture, self.rows, self.h = capture, rows, h
        self.buffers = [np.zeros((4, n, rows, w), capture.frames.dtype) for _ in range(2)]
        self.count = 0

    def read(self, r0: int) -> np.ndarray:
        r1 = min(self.h, r0 + self.rows)
        buf = self.buffers[self.count % 2]
        self.count += 1
        if r1 - r0 < self.rows:
            buf[:, :, r1 - r0:] = 0  # pad the last tile so every tile has one compiled shape
        self.capture.read_tile_into(buf, slice(r0, r1))
        return buf.reshape(buf.shape[0], buf.shape[1], -1)


def reconstruct_capture(capture: Capture, options: ReconstructOptions, calibration: Calibration | None = None,
                        registration_maps=None):
    """Reconstruct an open capture tile by tile (bounded memory) → (outputs, metadata).

    `registration_maps`: three (map_x, map_y) arrays (H, W) placing CCDs 2–4 on CCD 1's grid."""
    retain_freed_memory()
    n, h, w = capture.shape
    attrs = capture.attrs
    hybrid = Hybrid(tuple(capture.hybrid_phases_rad))
    modulator = modulator_from_attrs(attrs)
    delay = 0.0
    dark = capture.dark
    gain_map = None
    if calibration is not None:
        calibration.check_shape(h, w)
        hybrid = calibration.hybrid or hybrid
        modulator = calibration.modulator or modulator
        delay = calibration.system_delay_s
        gain_map = calibration.gain_map
        if dark is None:
            dark = calibration.offset_map_dn
    if dark is not None:  # per-pixel offsets replace the global ones (never subtract both)
        hybrid = Hybrid(hybrid.phases_rad, hybrid.relative_gains, (0.0,) * 4)
    if hybrid.conditioning() > 1e3:
        raise ValueError(f"hybrid phases {np.round(np.asarray(hybrid.phases_rad), 4)} are nearly equal: "
                         "I/Q cannot be separated")
    # registered tiles arrive as float32 with saturation judged upstream on the source pixels
    saturation = None if registration_maps is not None else capture.saturation_dn
    cfg = build_config(capture.frequencies_hz, hybrid, modulator, delay, saturation, options)
    rows = min(options.tile_rows, h)
    outputs = {}
    t0 = time.perf_counter()

    registered = None
    if registration_maps is not None:
        from .registered import RegisteredTiles, register_pixel_map

        registered = RegisteredTiles(capture, registration_maps, rows)
        if dark is not None:
            dark = register_pixel_map(dark, registration_maps)
        if gain_map is not None:
            gain_map = register_pixel_map(gain_map, registration_maps)

    def map_tile(arr, r0, r1, fill):
        """Rows r0:r1 of a (4, H, W) per-pixel map, padded to the tile shape → (4, P)."""
        if arr is None:
            return None
        block = np.full((4, rows, w), fill, np.float32)
        block[:, : r1 - r0] = arr[:, r0:r1]
        return block.reshape(4, rows * w)

    reader = None if registered is not None else _BlockReader(capture, rows)

    def tile_inputs(r0):
        r1 = min(h, r0 + rows)
        if registered is not None:
            return registered.tile(r0) + (map_tile(dark, r0, r1, 0.0), map_tile(gain_map, r0, r1, 1.0))
        return (r1, reader.read(r0), None, map_tile(dark, r0, r1, 0.0), map_tile(gain_map, r0, r1, 1.0))

    starts = list(range(0, h, rows))
    sub_px = sub_tile_pixels(rows * w, n)
    with tqdm(total=h * w, unit="px", desc="reconstruct", disable=not options.progress, unit_scale=True) as bar:
        pending = None
        for r0 in starts:
            r1, block, data_status, d, g = tile_inputs(r0)
            # dispatched asynchronously: the next tile is read while this one computes
            results = dispatch_tile(cfg, block, d, data_status, g, sub_px)
            if pending is not None:
                _collect(pending, outputs, h, w, rows, bar)
            pending = (results, r0, r1)
        _collect(pending, outputs, h, w, rows, bar)
    meta = {"method": options.method, "ambiguity_m": cfg.ambiguity_m, "bin_depth_m": cfg.bin_depth_m,
            "depth_window_m": [max(0.0, cfg.depth_window_m[0]), cfg.depth_window_m[1]],
            "carrier_alignment": "tracked" if options.tracking else "static",
            "snr_threshold_db": options.snr_threshold_db,
            "snr_threshold_effective_db": 10 * math.log10(cfg.snr_threshold), "dtype": options.dtype,
            "seconds": time.perf_counter() - t0, "window_bins": options.window_bins,
            "dominant_harmonic": cfg.dominant_order, "registered": registration_maps is not None,
            "frequency_path": frequency_path(cfg)}
    return outputs, meta


def open_and_reconstruct(path, options: ReconstructOptions, calibration_path=None, registration_path=None):
    calibration = None if calibration_path is None else Calibration.load(calibration_path)
    maps = None
    if registration_path is not None:
        from cohflash_calibration.registration import load_registration

        reg = load_registration(registration_path)
        maps = [reg.maps(k) for k in (2, 3, 4)]
    with Capture(path) as cap:
        try:
            return reconstruct_capture(cap, options, calibration, maps)
        except (NotImplementedError, ValueError) as exc:
            raise CaptureError(f"{path}: {exc}") from None
