"""Time-domain ML: the phase-locked model fitted over all N frames, for any schedule (the
non-uniform path; e.g. sparse schedules). Its coarse stage is the periodogram over delay
(`coarse.DelayPeriodogram`)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..fisher import depth_information, sigma_from_information, well_posed
from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup, FitResult, best_of, reduced_chi2
from .polish import descended, newton_polish
from .window_ml import grid_for
from .window_model import (
    GRAM_DATA,
    GRAM_DC,
    GRAM_TONE,
    cmul,
    gram_matrix,
    jet_add,
    jet_scale,
    phasor_jet,
    projected_cost,
    projected_cost_slope_and_curvature,
    solve_normal_2x2,
)


def first_order_phasor(frequencies_hz, delay_s):
    """e^{i2π f_m τ} as (cos, sin), the angle reduced modulo 2π in float64 first."""
    cycles = frequencies_hz * delay_s
    angle = 2 * jnp.pi * (cycles - jnp.floor(cycles))
    return jnp.cos(angle), jnp.sin(angle)


def tone_jets(first, weights, rates, derivatives: int):
    """The tone t[m] = Σ_{n≥1} 2 w_n cos(2π n f_m τ) and its first `derivatives` derivatives
    in an unknown along which order n's angle turns at n·`rates`[m] (rad per unit), each (N,),
    from the first order's phasor `first` (`first_order_phasor`).

    Order n's phasor is the first order's to the n-th power: one float64 cos and sin a frame,
    not one a frame and order (XLA's CPU float64 cos was most of a fit's time). A phasor
    turning at rate φ has derivatives iφ·z and −φ²·z, so the tone's come in closed form
    (`phasor_jet`)."""
    power = first
    out = (0.0,) * (derivatives + 1)
    for order in range(1, weights.shape[0]):
        if order > 1:
            power = cmul(power, first)
        re, _ = phasor_jet(power, order * rates, derivatives)
        out = jet_add(out, jet_scale(2 * weights[order], re))
    return out


def refine_time_domain(
    r: Float[Array, " N"],
    frequencies_hz: Float[Array, " N"],
    weights: Float[Array, " K"],
    coarse_depth_m,
    noise_var,
    *,
    system_delay_s: float,
    grid_half_width_m: float,
    grid_points: int,
    max_steps: int,
) -> FitResult:
    """ML depth of one pixel over all frames: r[m] = c + A·Σ_{n≥1} 2 w_n cos(2π n f_m τ), with
    (c, A) projected out, a basin grid, then Newton's polish on the depth offset (mm).

    Every cost, slope and curvature comes from the Gram matrix of the constant column, the
    data and the tone's jets (`tone_jets`, `window_model.projected_cost_slope_and_curvature`)."""
    f = frequencies_hz.astype(jnp.float64)
    y = r.astype(jnp.float64)
    scale = jnp.maximum(jnp.std(y), 1e-30)
    y = y / scale
    ones = jnp.ones_like(f)
    rate_per_mm = 1e-3 * 4 * jnp.pi * f / C  # the first order's angle per mm of depth

    def jets(offset_mm, derivatives):
        delay = system_delay_s + 2 * (coarse_depth_m + 1e-3 * offset_mm) / C
        return tone_jets(first_order_phasor(f, delay), weights, rate_per_mm, derivatives)

    def gram(columns):
        return gram_matrix([(ones, None), (y, None)] + [(c, None) for c in columns])

    grid_mm = jnp.linspace(-1e3 * grid_half_width_m, 1e3 * grid_half_width_m, grid_points)
    costs = jax.vmap(lambda g: projected_cost(gram(jets(g, 0))))(grid_mm)
    polish = newton_polish(
        lambda x: projected_cost_slope_and_curvature(gram(jets(x, 2))), grid_mm[jnp.argmin(costs)], max_steps=max_steps
    )
    depth = coarse_depth_m + 1e-3 * polish.value
    tone, slope_per_mm = jets(polish.value, 1)
    g = gram([tone])
    coef = solve_normal_2x2(
        g[GRAM_DC, GRAM_DC],
        g[GRAM_DC, GRAM_TONE],
        g[GRAM_TONE, GRAM_TONE],
        g[GRAM_DC, GRAM_DATA],
        g[GRAM_TONE, GRAM_DATA],
    )
    res = y - coef[0] - coef[1] * tone
    converged = polish.succeeded & descended(jnp.sum(res**2), jnp.min(costs))
    amp = coef[1] * scale
    # Fisher information of (depth, c, A) per unit noise variance, with the data unscaled
    slope = amp * 1e3 * slope_per_mm  # ∂(A·t)/∂depth (per m)
    f_dd = slope @ slope
    information = depth_information(f_dd, slope @ tone, tone @ tone, jnp.sum(slope), float(f.shape[0]), jnp.sum(tone))
    sigma = sigma_from_information(information / jnp.maximum(noise_var, 1e-30))
    posed = well_posed(coef[1], tone @ tone, y @ y, f_dd, information)
    return FitResult(depth, coef[0] * scale, amp, sigma, converged, polish.num_steps, jnp.sum(res**2) * scale**2, posed)


# Depths the fit starts from: the periodogram's peak and its strongest rivals. Few frames over a
# wide band leave high sidelobes (20 random steps: the truth was not among the two strongest
# for a third of the pixels at 27 dB), many frames low ones
RIVAL_STARTS_SHORT = 6
RIVAL_STARTS_LONG = 2
RIVAL_STARTS_MAX_FRAMES = 512


class TimeDomainML(AbstractDepthEstimator):
    """Phase-locked maximum likelihood over every frame in the time domain, for any schedule
    (the non-uniform path): a basin grid over ±1 envelope width c/(2B) of the periodogram's
    depth, then Newton's polish (`refine_time_domain`, vmapped over pixels)."""

    refines: ClassVar[bool] = True

    @property
    def description(self) -> str:
        return "time-domain ML over all frames"

    frequencies_hz: Float[Array, " N"]
    weights: Float[Array, " K"]
    system_delay_s: float = eqx.field(static=True)
    grid_half_width_m: float = eqx.field(static=True)
    grid_points: int = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    candidates: int = eqx.field(static=True, default=1)

    @classmethod
    def build(cls, setup: EstimatorSetup) -> TimeDomainML:
        g = setup.geometry
        n = len(setup.frequencies_hz)
        if n < RIVAL_STARTS_MAX_FRAMES:
            # few frames leave the cost's finest oscillation, c/(2 f_max), unaveraged: a grid
            # resolving c/(2 f̄) at 6 points sent Newton from a grid point outside the true
            # basin to a false minimum in 30 % of the pixels of a 20-step random schedule
            finest_m = C / (2 * float(np.max(setup.frequencies_hz)))
            half, points, _ = grid_for(g.bin_depth_m, min(g.ripple_m, finest_m), points_per_ripple=16)
        else:
            half, points, _ = grid_for(g.bin_depth_m, g.ripple_m)
        return cls(
            jnp.asarray(setup.frequencies_hz),
            setup.model.weights,
            g.system_delay_s,
            half,
            points,
            setup.max_steps,
            RIVAL_STARTS_SHORT if n < RIVAL_STARTS_MAX_FRAMES else RIVAL_STARTS_LONG,
        )

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        """Fits from the periodogram's peak and its strongest rivals beyond the main lobe
        (a schedule's sidelobes, where the frequency-only periodogram can favour a wrong
        depth): the best, flagged ambiguous where the frames barely prefer it (`base.best_of`)."""
        starts = stage.candidates(coarse, self.candidates)  # (K, P), the peak first
        return self.best_fit(self.fit_each(sequence, starts, noise_var), starts, sequence, noise_var, stage.grid_step_m)

    def fit_each(self, sequence: Float[Array, "N P"], starts: Float[Array, "K P"], noise_var) -> FitResult:
        """`refine_time_domain` of every pixel from each of its K starting depths → fields (K, P)."""
        fit_from = lambda start: jax.vmap(
            lambda r, d, v: refine_time_domain(
                r,
                self.frequencies_hz,
                self.weights,
                d,
                v,
                system_delay_s=self.system_delay_s,
                grid_half_width_m=self.grid_half_width_m,
                grid_points=self.grid_points,
                max_steps=self.max_steps,
            )
        )(sequence.T, start, noise_var)
        return jax.vmap(fit_from)(starts)

    @staticmethod
    def best_fit(fits: FitResult, starts, sequence, noise_var, min_separation_m) -> DepthEstimate:
        """The best of `fits` (K, P) as a `DepthEstimate` started from its start, its reduced χ²
        over all N frames (depth, offset and amplitude fitted), and `ambiguous` where another
        fit ended more than `min_separation_m` away within `base.AMBIGUITY_MIN_DELTA_CHI2`."""
        fit, ambiguous, best = best_of(fits, noise_var, min_separation_m)
        mean_square = jnp.mean(jnp.square(sequence.astype(jnp.float64)), axis=0)
        chi2 = reduced_chi2(fit.cost, noise_var, mean_square, max(sequence.shape[0] - 3, 1))
        estimate = fit.to_estimate(jnp.take_along_axis(starts, best[None], axis=0)[0], chi2)
        return eqx.tree_at(lambda e: e.ambiguous, estimate, ambiguous, is_leaf=lambda x: x is None)
