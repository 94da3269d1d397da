"""What a frequency sweep makes of depth: DFT bins, the unambiguous window, folding and its
mirror — derived once per configuration from the sweep, the modulator's dominant sideband
order and τ_sys (`SweepGeometry.of`), and read by the coarse stage, every estimator, the
reconstruction's checks, the posteriors and the design's sweeps.

A real tone's DFT shows its total delay τ = τ_sys + 2d/c folded into [0, P/2], P =
1/(order·Δf): τ and −τ modulo P look alike. Depth is therefore unambiguous over one
half-period of total delay (`delay_window`).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .constants import SPEED_OF_LIGHT_M_PER_S as C

# Frequencies within this relative tolerance (and 1 mHz) of equal steps make a uniform sweep.
UNIFORM_STEP_RTOL = 1e-9
UNIFORM_STEP_ATOL_HZ = 1e-3
MIN_FRAMES = 4  # a tone's DFT peak beyond DC, with a neighbour on each side


def delay_window(period_s: float, system_delay_s: float) -> tuple[int, tuple[float, float]]:
    """Where depth is unambiguous, given the beat tone's delay period P = 1/(order·Δf) and the
    system delay τ_sys: one half-period of total delay, [jP/2, (j+1)P/2), j the half-period
    boundary nearest τ_sys, so the window [(jP/2 − τ_sys)·c/2, ((j+1)P/2 − τ_sys)·c/2) starts
    within a quarter period of depth 0. τ_sys = 0 gives [0, c/(4·order·Δf)); τ_sys = 6.7 ns
    (1 m of extra one-way path) gives [−1 m, c/(4·order·Δf) − 1 m), and a target beyond the
    window's end folds back onto it. Returns (j, (start_m, end_m))."""
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


def is_uniform(frequencies_hz) -> bool:
    """Equal steps (to `UNIFORM_STEP_RTOL`): f_m = f_0 + m·Δf."""
    d = np.diff(np.asarray(frequencies_hz, np.float64))
    step = float(np.median(d))
    return bool(np.allclose(d, step, rtol=UNIFORM_STEP_RTOL, atol=UNIFORM_STEP_ATOL_HZ))


# A non-uniform schedule's tone repeats (an alias) at the first delay beyond the main lobe where
# its ambiguity function |mean_m e^{i2πf_mτ}| reaches this level; where none does within the
# horizon, the search stops at the horizon: the window of a uniform sweep of the same N and band
# (2(N−1) grid points of a quarter envelope), and at least MIN_HORIZON_POINTS of them
ALIAS_LEVEL = 0.9
MIN_HORIZON_POINTS = 2048
POINTS_PER_ENVELOPE = 4


def ambiguity_level(frequencies_hz, delays_s) -> np.ndarray:
    """|mean_m e^{i2πf_mτ}| at the delays (G,): how alike a tone at delay τ₀ and τ₀ + τ look to
    frequency-only processing (1: an alias)."""
    centred = np.asarray(frequencies_hz, np.float64) - frequencies_hz[0]  # a common phase drops out
    cycles = np.outer(np.asarray(delays_s, np.float64), centred)
    return np.abs(np.exp(2j * np.pi * (cycles - np.floor(cycles))).mean(axis=1))


# A schedule on one comb (every gap a whole number of comb steps) is searched over the comb's
# whole window where its periodogram grid stays below this many entries (frequencies × delays)
MAX_COMB_GRID_ENTRIES = 2**25


def comb_step_hz(frequencies_hz) -> float | None:
    """The step of the coarsest comb that holds every frequency — the smallest gap times the
    greatest common divisor of the gaps in its units — or None where the gaps are not whole
    multiples of the smallest (to 1e-6 of a step)."""
    gaps = np.diff(np.asarray(frequencies_hz, np.float64))
    smallest = float(np.min(gaps))
    units = gaps / smallest
    whole = np.rint(units)
    if not np.all(np.abs(units - whole) < 1e-6 * np.maximum(whole, 1.0)):
        return None
    return smallest * float(np.gcd.reduce(whole.astype(np.int64)))


def schedule_period_s(frequencies_hz) -> float:
    """The delay period of a schedule's fundamental tone: 1/Δf for a subset of a comb of
    step Δf (`comb_step_hz`) whose window the periodogram can cover (`MAX_COMB_GRID_ENTRIES`);
    otherwise the first delay beyond the main lobe where the `ambiguity_level` reaches
    `ALIAS_LEVEL`, or twice the search horizon where none does, so that the unambiguous window
    (half a period) is the horizon — never sized by the smallest gap, which a
    random schedule may make a few hertz. The level is evaluated on a grid of a quarter envelope
    c/(2B) by one FFT of the frequencies binned to 1/16 of a cycle at the horizon (≤ 0.4 rad of
    phase: a true alias still reads ≥ 0.97), then exactly around the first hit."""
    f = np.asarray(frequencies_hz, np.float64)
    n = f.size
    spacing = 1 / (POINTS_PER_ENVELOPE * (f[-1] - f[0]))
    step = comb_step_hz(f)
    if step is not None and n * (0.5 / step) / spacing <= MAX_COMB_GRID_ENTRIES:
        return 1 / step  # a subset of one comb: its period, and no nearer alias than the comb's
    points = 2 * max(2 * (n - 1), MIN_HORIZON_POINTS)  # a whole period of the horizon window
    span = points * spacing
    oversample = 8
    size = oversample * points
    cells = np.rint((f - f[0]) * oversample * span).astype(np.int64) % size
    level = np.abs(np.fft.ifft(np.bincount(cells, minlength=size)))[: points + 1] * size / n
    low = np.flatnonzero(level < 0.5)
    if low.size:
        hits = low[0] + np.flatnonzero(level[low[0] :] >= ALIAS_LEVEL - 0.05)
        for k in hits[:64]:  # confirm exactly: the binned level reads up to ~0.03 off
            fine = spacing * (k + np.linspace(-1, 1, 33))
            exact = ambiguity_level(f, fine)
            if exact.max() >= ALIAS_LEVEL:
                return float(fine[int(np.argmax(exact))])
    return float(span)


def dominant_order(weights) -> int:
    """The sideband order whose beat tone is strongest (θ_b = 0 puts it at 2, not 1)."""
    w = np.asarray(weights, np.float64)
    if w.shape[0] < 2 or not np.any(w[1:] > 1e-12 * max(w[0], 1e-300)):
        raise ValueError(
            "the modulator settings give no beat tone (all sideband weights beyond n=0 vanish): "
            "check modulation_index and bias_rad"
        )
    return int(np.argmax(w[1:]) + 1)


class SweepGeometry(eqx.Module):
    """Bins, windows and folds of one sweep, modulator and τ_sys (host-side numbers, static
    under jit). For a non-uniform schedule the envelope width c/(2B) plays the bin's part and
    the ambiguity is the schedule's own (`schedule_period_s`).

    τ_sys and the depth window it places are fields, not static ones: Python floats on the
    host (static to `eqx.filter_jit` all the same), which the reconstruction's programs take
    as arrays (`reconstruct.plan.program_plan`), so that a calibration's new τ_sys runs the
    programs already compiled. The fold index stays static: it picks code (a mirrored half-period)."""

    num_frames: int = eqx.field(static=True)
    uniform: bool = eqx.field(static=True)
    start_hz: float = eqx.field(static=True)
    step_hz: float = eqx.field(static=True)  # the median step of a non-uniform schedule
    mean_frequency_hz: float = eqx.field(static=True)
    dominant_order: int = eqx.field(static=True)
    system_delay_s: float
    bin_depth_m: float = eqx.field(static=True)
    ambiguity_m: float = eqx.field(static=True)
    delay_period_s: float = eqx.field(static=True)
    fold_index: int = eqx.field(static=True)
    depth_window_m: tuple[float, float]
    mirror_symmetric: bool = eqx.field(static=True)

    @classmethod
    def of(cls, frequencies_hz, weights, system_delay_s: float = 0.0) -> SweepGeometry:
        """The geometry of a strictly increasing schedule with sideband `weights` and τ_sys."""
        f = np.asarray(frequencies_hz, np.float64)
        n = f.size
        if n < MIN_FRAMES:
            raise ValueError(
                f"{n} frames are too few to reconstruct depth: need ≥ {MIN_FRAMES} (a tone's DFT peak "
                "beyond DC, with a neighbour on each side)"
            )
        step = float(np.median(np.diff(f)))
        uniform = is_uniform(f)
        order = dominant_order(weights)
        bin_depth = C / (2 * n * step) if uniform else float(C / (2 * (f[-1] - f[0])))
        period = (1 / step if uniform else schedule_period_s(f)) / order
        fold, window = delay_window(period, float(system_delay_s))
        harmonics = f[0] / step
        # f_0 a whole multiple of Δf: the model is symmetric about the window's edges (`reflect_into_window`)
        mirror = bool(uniform and abs(harmonics - round(harmonics)) < 1e-9 * max(1.0, harmonics))
        return cls(
            num_frames=n,
            uniform=uniform,
            start_hz=float(f[0]),
            step_hz=step,
            mean_frequency_hz=float(np.mean(f)),
            dominant_order=order,
            system_delay_s=float(system_delay_s),
            bin_depth_m=bin_depth,
            ambiguity_m=C * period / 4,
            delay_period_s=period,
            fold_index=fold,
            depth_window_m=window,
            mirror_symmetric=mirror,
        )

    @property
    def ripple_m(self) -> float:
        """Period in depth of the phase-locked likelihood's ripple, c/(2·f̄)."""
        return C / (2 * self.mean_frequency_hz)

    @property
    def valid_window_m(self) -> tuple[float, float]:
        """The depths a valid pixel may have: the unambiguous window, never below 0."""
        return max(0.0, self.depth_window_m[0]), self.depth_window_m[1]

    def depth_from_folded(self, folded_cycles):
        """Depth (m) from the dominant tone's frequency in cycles per frame, folded into [0, ½]."""
        return unfold_delay(folded_cycles, self.delay_period_s, self.fold_index, self.system_delay_s) * C / 2

    def reflect(self, depth_m):
        """`reflect_into_window` where the sweep is mirror-symmetric, else the depth as it is."""
        return reflect_into_window(depth_m, self.depth_window_m) if self.mirror_symmetric else depth_m

    def first_bin(self, min_depth_m: float) -> int:
        """The lowest DFT bin the coarse search may use so that depths below `min_depth_m` are
        ignored (≥ 1: bin 0 is the mean)."""
        if min_depth_m <= 0:
            return 1
        if not self.uniform:
            raise ValueError("min_depth_m applies to uniform sweeps only")
        if self.fold_index % 2:
            raise ValueError(
                f"min_depth_m: with a system delay of {self.system_delay_s:.4g} s depth grows towards "
                "lower DFT bins (an odd half-period of delay), where a lower bin limit cannot apply"
            )
        period, n = self.delay_period_s, self.num_frames
        first = (2 * min_depth_m / C + self.system_delay_s - self.fold_index // 2 * period) / period * n
        if first >= n // 2:
            raise ValueError(f"min_depth_m = {min_depth_m} m leaves no depth below the ambiguity limit")
        return max(1, int(math.floor(first)))
