"""Detection with a stated false-alarm probability: is there a tone at all?

The coarse stage's peak is the largest of many noisy ordinates, and the noise level is
estimated from the same N frames, so a threshold on the fitted SNR has no known false-alarm
rate (where few pixels pass, the ones that pass are those whose noise happened to look small).
This test is built on statistics whose null distribution is known exactly.

Each ordinate is an energy E_g of the real, mean-removed sequence r = Re(e^{−iφ}z) — the
carrier-aligned I/Q, φ any phase, the principal axis included — in a subspace: |⟨r, v⟩|² for a
vector v (a delay of the periodogram), or Σ 2|R_j|² over two adjacent unitary DFT bins j of a
uniform sweep. Because Re(e^{−iφ}z) mixes z and z̄,

    |⟨r, v⟩|² ≤ ½(|⟨z, a⟩|² + |⟨z, ā⟩|²) ≤ ½·λ_max(Gram(a, ā))·‖P z‖²,    a = v − mean(v),
    2|R_j|² ≤ |Z_j|² + |Z_{N−j}|²  (the energy of z in the two DFT bins ±j),

so E_g ≤ c_g·‖P_g z‖² with P_g the projection onto a subspace of dimension d_g (2 for a
delay, 2 per DFT bin). Under pure noise — z white, circular complex Gaussian, mean removed —
‖P_g z‖² divided by the total energy T = Σ|z − z̄|² = N(var I + var Q) is Beta(d_g, N−1−d_g),
whatever the noise level. A pixel is detected where some searched ordinate has E_g > c_g·x_g·T,
x_g chosen so that each ordinate's tail is α/K over K searched ordinates: by the union bound the
false-alarm probability per pixel is at most α.

Two DFT bins rather than one capture a tone between bins (a single bin loses up to 3.9 dB)
and nearly all its energy at few frames (a single Hann bin holds at most ⅔ of it, which at 35
frames would not clear the threshold even without noise). The bound is loose: for a fixed φ
the two bins' energy is Gamma(2), bounded here by Gamma(4) (φ is chosen from the data, so the
bound must hold for every φ); the measured rates sit well below α (docs/physics.md). The
isotropy it assumes holds for balanced I/Q (a calibrated or nominal hybrid); a tracked carrier
drift is removed with a phase estimated from the data, which it ignores.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Complex, Float

from ..runtime import device_value

DEFAULT_FALSE_ALARM = 1e-6
_BISECTION_STEPS = 200


def beta_tail(x: float, dim: int, num_frames: int) -> float:
    """P(Beta(d, N−1−d) > x): the chance that a d-dimensional projection holds more than the
    share x of the total noise energy of N frames (complex, mean removed: N−1 dimensions).
    For integer d it is a binomial sum, P(Bin(N−2, x) ≤ d−1), summed in logs."""
    n = num_frames - 2  # d + b − 1 with b = N − 1 − d
    if x <= 0:
        return 1.0
    if x >= 1:
        return 0.0
    terms = [
        math.lgamma(n + 1) - math.lgamma(i + 1) - math.lgamma(n - i + 1) + i * math.log(x) + (n - i) * math.log1p(-x)
        for i in range(dim)
    ]
    top = max(terms)
    return math.exp(top) * sum(math.exp(t - top) for t in terms)


def share_threshold(dim: int, num_frames: int, tail: float) -> float:
    """The share x at which P(Beta(d, N−1−d) > x) = `tail` (bisection: the tail falls with x)."""
    lo, hi = 0.0, 1.0
    for _ in range(_BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if beta_tail(mid, dim, num_frames) > tail else (lo, mid)
    return hi


def union_limits(
    scales: np.ndarray, dims: np.ndarray, searched: np.ndarray, num_frames: int, false_alarm: float
) -> np.ndarray:
    """Per ordinate the energy limit c_g·x_g (share of T), each ordinate's tail α/K over the K
    searched ones (∞ where not searched or of rank 0)."""
    use = np.asarray(searched, bool) & (np.asarray(dims) > 0) & (num_frames - 1 - np.asarray(dims) > 0)
    count = int(use.sum())
    limits = np.full(len(dims), np.inf)
    if count == 0:
        return limits
    by_dim = {d: share_threshold(int(d), num_frames, false_alarm / count) for d in np.unique(np.asarray(dims)[use])}
    limits[use] = np.asarray(scales)[use] * np.array([by_dim[d] for d in np.asarray(dims)[use]])
    return limits


def projection_bounds(norm_sq, mean, sum_sq, num_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """For vectors v_g of N entries, given ‖v‖², mean(v) and Σ v_m² (each (G,)): the scale
    c = ½λ_max(Gram(a, ā)) and the rank d of span(a, ā), a = v − mean(v), such that
    |⟨r, v⟩|² ≤ c·‖P z‖² (module docstring). ⟨a, a⟩ = ‖v‖² − N|mean|², ⟨a, ā⟩ = Σv² − N·mean²."""
    aa = np.asarray(norm_sq, np.float64) - num_frames * np.abs(mean) ** 2
    cross = np.abs(np.asarray(sum_sq) - num_frames * np.asarray(mean) ** 2)
    scale = 0.5 * (aa + cross)  # λ_max of [[aa, ρ], [ρ̄, aa]]
    rank = np.where(cross >= aa * (1 - 1e-9), 1, 2)
    rank = np.where(aa <= 1e-12 * max(float(np.max(aa, initial=0.0)), 1e-300), 0, rank)
    return scale, rank


class Detection(eqx.Module):
    """The detection test of a coarse stage: per ordinate the limit c_g·x_g on its energy as a
    share of the total T (∞ where not searched); noise alone exceeds some limit with
    probability at most `false_alarm`. `false_alarm` = 1 switches the test off: every pixel is
    detected, and the ratio is reported against the default rate's limits, for information."""

    limits: Float[Array, " G"]
    false_alarm: float = eqx.field(static=True)

    @classmethod
    def of(cls, scales, dims, searched, num_frames: int, false_alarm: float) -> Detection:
        if not 0 < false_alarm <= 1:
            raise ValueError(f"the false-alarm probability must lie in (0, 1], got {false_alarm}")
        rate = DEFAULT_FALSE_ALARM if false_alarm == 1 else false_alarm
        return cls(device_value(union_limits(scales, dims, searched, num_frames, rate)), float(false_alarm))

    def ratio(self, energy: Float[Array, "P G"], total_energy: Float[Array, " P"]) -> Float[Array, " P"]:
        """max_g E_g/(limit_g·T) (P,): above 1 where noise alone would rarely reach."""
        share = energy.astype(jnp.float64) / jnp.maximum(total_energy, 1e-300)[:, None]
        return jnp.max(share / self.limits, axis=-1)

    def detected(self, ratio: Float[Array, " P"]) -> Bool[Array, " P"]:
        """Where the test finds a tone (everywhere when it is switched off)."""
        return jnp.ones(ratio.shape, bool) if self.false_alarm == 1 else ratio > 1


DETECTION_WINDOW_BINS = 2  # adjacent DFT bins whose energy a uniform sweep's test sums


def uniform_sums(spectrum: Complex[Array, "P K"], num_frames: int, axis: int = -1) -> Float[Array, "P K"]:
    """Σ 2|R_j|² over the DFT bins j = k..k+1 of each window k, leaving out the DC bin and
    (even N) the real Nyquist bin, whose bound differs; bins along `axis`."""
    p2 = 2 * (jnp.real(spectrum) ** 2 + jnp.imag(spectrum) ** 2)
    axis = axis % p2.ndim
    k = spectrum.shape[axis]
    keep = jnp.asarray(uniform_bins(num_frames)[:k]).reshape((k,) + (1,) * (p2.ndim - 1 - axis))
    p2 = jnp.where(keep, p2, 0.0)
    pad = jnp.pad(p2, [(0, DETECTION_WINDOW_BINS - 1) if d == axis else (0, 0) for d in range(p2.ndim)])
    return sum(jax.lax.slice_in_dim(pad, j, j + k, axis=axis) for j in range(DETECTION_WINDOW_BINS))


def uniform_bins(num_frames: int) -> np.ndarray:
    """The rFFT bins whose 2|R_j|² is bounded by a 2-D energy of z: 1 ≤ j < N/2."""
    j = np.arange(num_frames // 2 + 1)
    return (j >= 1) & (2 * j < num_frames)


def uniform_detection(num_frames: int, min_bin: int, false_alarm: float) -> Detection:
    """The test over windows of two adjacent bins that hold a searched bin (k ≥ `min_bin`): a
    window bounds a 2·(bins it holds)-dimensional energy with scale 1. Two bins hold 81–100 %
    of a tone's energy wherever it falls between them (one bin: 41 %); more bins add noise."""
    keep = uniform_bins(num_frames).astype(int)
    padded = np.pad(keep, (0, DETECTION_WINDOW_BINS - 1))
    dims = 2 * sum(padded[j : j + keep.size] for j in range(DETECTION_WINDOW_BINS))
    searched = np.arange(keep.size) + DETECTION_WINDOW_BINS - 1 >= min_bin
    return Detection.of(np.ones(keep.size), dims, searched, num_frames, false_alarm)


def delay_detection(frequencies_hz: np.ndarray, delays_s: np.ndarray, false_alarm: float) -> Detection:
    """The test over every delay of a periodogram grid (single-delay projections)."""
    n = len(frequencies_hz)
    scales, dims = projection_bounds(*delay_moments(frequencies_hz, delays_s), n)
    return Detection.of(scales, dims, np.ones(len(delays_s), bool), n, false_alarm)


def delay_moments(frequencies_hz: np.ndarray, delays_s: np.ndarray, chunk: int = 256):
    """(‖v_g‖², mean(v_g), Σ v_g²) of v_g = e^{i2πf_mτ_g} (the periodogram's ordinates
    |Σ r_m e^{−i2πf_mτ_g}|² = |⟨r, v_g⟩|²), in chunks of delays (bounded memory)."""
    f = np.asarray(frequencies_hz, np.float64)
    delays = np.asarray(delays_s, np.float64)
    n = f.size
    mean = np.empty(len(delays), complex)
    sum_sq = np.empty(len(delays), complex)
    phasor = lambda tau: np.exp(2j * math.pi * np.mod(np.multiply.outer(tau, f), 1.0))
    steps = np.diff(delays)
    # an evenly spaced grid (as `coarse.delay_grid` makes): each chunk's rows are its first row
    # times powers of one step's phasor (a cumulative product: no exponential per entry). The
    # grid's steps differ by the rounding of the delays (2e-12 of a step over a 38 m window):
    # steps equal to 1e-9 move a chunk's last row by < 1e-6 rad; the moments agree with the
    # exponential's to 1e-13 of their size (tested)
    even = steps.size > 0 and np.allclose(steps, steps[0], rtol=1e-9, atol=0.0)
    step = phasor(steps[0]) if even else None
    for g0 in range(0, len(delays), chunk):
        count = min(chunk, len(delays) - g0)
        if even:
            powers = np.cumprod(np.broadcast_to(step, (count, n)), axis=0) / step
            rows = phasor(delays[g0])[None] * powers
        else:
            rows = phasor(delays[g0 : g0 + count])
        mean[g0 : g0 + count] = rows.mean(axis=1)
        sum_sq[g0 : g0 + count] = (rows * rows).sum(axis=1)
    return np.full(len(delays), float(n)), mean, sum_sq
