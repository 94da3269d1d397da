"""Harmonic ambiguity resolved by the model: when the fundamental is starved.

The coarse stage and the estimators follow the strongest beat tone, of order n_d, whose delay
period is P/n_d (P = 1/Δf): alone it fixes depth only within c/(4·n_d·Δf). Where the modulator
starves the fundamental (x = β/2 at a zero of J₁, where orders 2 and 3 are of nearly equal
power) the other orders it predicts are present too, and the orders together repeat only with
the period P/g, g the greatest common divisor of the orders that carry weight. Depth is then
unambiguous over c/(4·g·Δf), and the dominant tone's answer is one of n_d/g unfoldings (each
with its mirror). `HarmonicResolver` fits the phase-locked model with every order (time domain,
all frames) from each unfolding and keeps the best; a pixel whose frames barely prefer it is
flagged ambiguous (`base.best_of`), so no depth that explains one peak and ignores another is
reported valid. θ_b = 0 leaves only even orders (g = 2 = n_d: the dominant window is already
the whole story); θ_b = π/2 leaves odd ones with the fundamental dominant (g = n_d = 1).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..geometry import SweepGeometry, delay_window
from ..runtime import device_value
from .base import DepthEstimate
from .time_domain import TimeDomainML
from .window_ml import grid_for

# An order takes part in fixing the period where its weight is at least this share of the
# dominant order's (its tone at most 20 dB below the dominant one): fitted jointly, it tells the
# unfoldings apart, or the pixel is flagged ambiguous
HARMONIC_MIN_WEIGHT_SHARE = 0.1
# The best reading is accepted only where its reduced χ² is within this many standard
# deviations (√(2/dof)) of 1, plus a margin for the model's own small errors: at
# SNR 60 a wrong reading 0.37 m off left χ² = 1.53 at 3000 frames, under the general limit of 5
UNEXPLAINED_CHI2_SIGMAS = 6.0
UNEXPLAINED_CHI2_MARGIN = 0.1


def window_order(weights) -> int:
    """g: the greatest common divisor of the orders n ≥ 1 whose weight is at least
    `HARMONIC_MIN_WEIGHT_SHARE` of the strongest one's."""
    return int(np.gcd.reduce(present_orders(weights)))


def present_orders(weights) -> np.ndarray:
    """The orders n ≥ 1 whose weight is at least `HARMONIC_MIN_WEIGHT_SHARE` of the strongest."""
    w = np.asarray(weights, np.float64)[1:]
    return np.flatnonzero(w >= HARMONIC_MIN_WEIGHT_SHARE * w.max()) + 1


class HarmonicResolver(eqx.Module):
    """The unfoldings of the dominant tone's depth over the orders' common window, each
    refined by the time-domain ML over all frames with every order, and the best kept."""

    fitter: TimeDomainML  # the time-domain ML with every order, over all frames
    dominant_period_s: float = eqx.field(static=True)
    dominant_order: int = eqx.field(static=True)
    depth_window_m: tuple[float, float] = eqx.field(static=True)
    readings: tuple[tuple[int, int, int], ...] = eqx.field(static=True)  # (order, m, ±1)

    @classmethod
    def build(cls, frequencies_hz, weights, geometry: SweepGeometry, max_steps: int) -> HarmonicResolver | None:
        """The resolver of a configuration whose orders repeat with a longer period than the
        dominant tone's (None where they do not: nothing to resolve)."""
        g = window_order(weights)
        if not geometry.uniform or g >= geometry.dominant_order:
            return None
        period = geometry.delay_period_s * geometry.dominant_order / g
        _, window = delay_window(period, geometry.system_delay_s)
        # the likelihood ripples at c/(2·n·f̄) for the highest order n that carries weight
        highest = int(np.max(present_orders(weights)))
        half, points, _ = grid_for(geometry.bin_depth_m, geometry.ripple_m / highest)
        # the peak the coarse stage found may be any present order's tone (orders of nearly equal
        # weight trade places with noise): order n reads a folded frequency x at total delays
        # (m ± x)/(n·Δf), m = 0…n·(window periods)
        step = 1 / (geometry.delay_period_s * geometry.dominant_order)
        top = int(math.ceil(window[1] * 2 / C * step * highest)) + 1
        readings = tuple((int(n), m, s) for n in present_orders(weights) for m in range(top + 1) for s in (1, -1))
        fitter = TimeDomainML(
            device_value(np.asarray(frequencies_hz, np.float64)),
            device_value(np.asarray(weights, np.float64)),
            geometry.system_delay_s,
            half,
            points,
            max_steps,
        )
        return cls(fitter, geometry.delay_period_s, geometry.dominant_order, window, readings)

    @property
    def ambiguity_m(self) -> float:
        return self.depth_window_m[1] - self.depth_window_m[0]

    def candidates(self, depth_m: Float[Array, " P"]) -> tuple[Float[Array, "K P"], Array]:
        """Depths at which some present order's tone sits where the dominant tone of `depth_m`
        does (`readings`), and whether they lie in the common window."""
        delay = self.fitter.system_delay_s
        tau = delay + 2 * depth_m / C
        step = 1 / (self.dominant_period_s * self.dominant_order)  # Δf
        folded = jnp.mod(self.dominant_order * step * tau, 1.0)  # cycles per frame of the peak
        order, m, sign = (jnp.asarray(v, jnp.float64)[:, None] for v in zip(*self.readings))
        delays = (m + sign * folded[None]) / (order * step)
        depths = (delays - delay) * C / 2
        lo, hi = self.depth_window_m
        return depths, (depths >= lo) & (depths < hi)

    def resolve(self, estimate: DepthEstimate, sequence: Float[Array, "N P"], noise_var) -> DepthEstimate:
        """The estimator's answer with its depth replaced by the best unfolding's fit."""
        starts, inside = self.candidates(estimate.depth_m)
        fits = self.fitter.fit_each(sequence, starts, noise_var)
        fits = eqx.tree_at(lambda f: f.well_posed, fits, fits.well_posed & inside)
        resolved = self.fitter.best_fit(fits, starts, sequence, noise_var, self.fitter.grid_half_width_m)
        # where no reading explains the frames (the peak the coarse stage found was noise's, or
        # a reading was missed), the best one still leaves a residual no noise makes
        dof = max(sequence.shape[0] - 3, 1)
        unexplained = resolved.fit_chi2 > 1 + UNEXPLAINED_CHI2_SIGMAS * math.sqrt(2 / dof) + UNEXPLAINED_CHI2_MARGIN
        return eqx.tree_at(lambda e: e.ambiguous, resolved, resolved.ambiguous | unexplained)


def harmonic_note(resolver: HarmonicResolver | None) -> str:
    """The resolution in words (recorded in the depth file's `frequency_path`)."""
    if resolver is None:
        return ""
    orders = sorted({n for n, _, _ in resolver.readings})
    return f"orders {orders} fitted together over a {resolver.ambiguity_m:.3f} m window"
