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
from ..runtime import device_value
from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup, FitResult, best_of, reduced_chi2
from .polish import Polish, descended, newton_polish, polish_in_passes
from .window_ml import grid_for
from .window_model import (
    cmul,
    gram_matrix,
    jet_add,
    jet_scale,
    phasor_jet,
    projected_coefficients,
    projected_cost_slope_and_curvature,
    projected_residual_energy,
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


class TimeDomainPixel(eqx.Module):
    """One pixel's sequence for the time-domain fit, scaled to unit standard deviation, and
    the scale."""

    y: Float[Array, " N"]
    scale: Float[Array, ""]

    @classmethod
    def of(cls, r: Float[Array, " N"]) -> TimeDomainPixel:
        y = r.astype(jnp.float64)
        scale = jnp.maximum(jnp.std(y), 1e-30)
        return cls(y / scale, scale)

    def gram(self, columns) -> Float[Array, "K K"]:
        """Gram matrix of (the constant column, the data, *columns) (`window_model.GRAM_*` rows)."""
        return gram_matrix([(jnp.ones_like(self.y), None), (self.y, None)] + [(c, None) for c in columns])


class TimeDomainModel(eqx.Module):
    """The phase-locked tone over a schedule: its frequencies, sideband weights and τ_sys."""

    frequencies_hz: Float[Array, " N"]
    weights: Float[Array, " K"]
    system_delay_s: float

    def jets(self, depth_m, offset_mm, derivatives: int):
        """The tone at `depth_m` + `offset_mm` and its derivatives per mm (`tone_jets`)."""
        f = self.frequencies_hz.astype(jnp.float64)
        delay = self.system_delay_s + 2 * (depth_m + 1e-3 * offset_mm) / C
        return tone_jets(first_order_phasor(f, delay), self.weights, 1e-3 * 4 * jnp.pi * f / C, derivatives)

    def grid_starts(self, pixels: TimeDomainPixel, depths_m, grid_half_width_m: float, grid_points: int):
        """The basin grid of a batch of fits (`pixels` and `depths_m` with a leading axis F):
        each fit's best offset (mm) from its depth and the projected cost there (the polish's
        ceiling, `descended`), each (F,).

        The cost at grid offset δ_g needs only 1·t, y·t and t·t. With z_m = e^{i2πf_mτ} at the
        fit's depth and ρ_gm = e^{i2πf_m·2δ_g/c}, order n's phasor is (z_m ρ_gm)^n, so
        1·t = Σ_n 2w_n Re S_n and y·t = Σ_n 2w_n Re Y_n with S_k = Σ_m ρ_gm^k z_m^k and
        Y_k = Σ_m ρ_gm^k y_m z_m^k; and since Re a·Re b = ½Re(ab) + ½Re(a b̄),
        t·t = Σ_{n,n'} 2w_n w_n' (Re S_{n+n'} + Re S_{|n−n'|}) (S_0 = N). Re S_k and Re Y_k of
        every fit and grid point are real matrix products of the grid's (G, N) powers ρ^k with
        the fits' (F, N) powers z^k: no cos/sin per fit, grid point and frame, which were four
        fifths of the fit's time on a 300-step random schedule (docs/performance.md)."""
        f = self.frequencies_hz.astype(jnp.float64)
        n_frames = f.shape[0]
        orders = self.weights.shape[0] - 1
        grid_mm = jnp.linspace(-1e3 * grid_half_width_m, 1e3 * grid_half_width_m, grid_points)
        rho = first_order_phasor(f[None, :], 2e-3 * grid_mm[:, None] / C)  # (G, N) each
        z = first_order_phasor(f[None, :], self.system_delay_s + 2 * depths_m[:, None] / C)  # (F, N) each
        y = pixels.y
        w = self.weights
        # c_k: t·t = Σ_k c_k Re S_k over k = 0..2K
        coefficient = [0.0] * (2 * orders + 1)
        for a in range(1, orders + 1):
            for b in range(1, orders + 1):
                coefficient[a + b] = coefficient[a + b] + 2 * w[a] * w[b]
                coefficient[abs(a - b)] = coefficient[abs(a - b)] + 2 * w[a] * w[b]
        # Re(Σ_m ρ^k x_m) over the grid and the fits: Re ρ^k·Re x − Im ρ^k·Im x, two real
        # products contracting the frames
        real_part = lambda r, x: r[0] @ x[0].T - r[1] @ x[1].T
        zeros = jnp.zeros((grid_points, y.shape[0]))

        def order_k(carry, weights_k):
            """S_k (and Y_k for the modelled orders k ≤ K) from ρ^k and z^k, carried: in a
            loop XLA keeps each power once instead of recomputing the chain of products, and
            z's cos/sin, in every consumer."""
            rho_k, z_k, one_t, y_t, t_t = carry
            two_w, c = weights_k
            s_k = real_part(rho_k, z_k)  # (G, F)
            if two_w is not None:
                one_t, y_t = one_t + two_w * s_k, y_t + two_w * real_part(rho_k, (y * z_k[0], y * z_k[1]))
            return (cmul(rho_k, rho), cmul(z_k, z), one_t, y_t, t_t + c * s_k), None

        c = jnp.stack(coefficient[1:])
        carry = (rho, z, zeros, zeros, zeros + coefficient[0] * n_frames)
        carry, _ = jax.lax.scan(order_k, carry, (2 * w[1:], c[:orders]))
        carry, _ = jax.lax.scan(order_k, carry, (None, c[orders:]))  # k > K: t·t's terms alone
        _, _, one_t, y_t, t_t = carry
        # the Gram matrix's constant and data rows, one a fit, against every grid point's products
        ones_y = jnp.sum(y, axis=1)
        rows = jnp.stack(
            [jnp.stack([jnp.full_like(ones_y, n_frames), ones_y]), jnp.stack([ones_y, jnp.sum(y * y, axis=1)])]
        )  # (2, 2, F): rows as `window_model.GRAM_DC`, `GRAM_DATA`
        costs = projected_residual_energy(rows, one_t, y_t, t_t).T  # (F, G)
        best = jnp.argmin(costs, axis=1)
        return grid_mm[best], jnp.min(costs, axis=1)

    def polish(self, pixel: TimeDomainPixel, depth_m, start_mm, max_steps: int) -> Polish:
        """Newton's polish of the offset (mm) from `depth_m`, slope and curvature from the Gram
        matrix of the tone's jets (`window_model.projected_cost_slope_and_curvature`)."""
        at = lambda x: projected_cost_slope_and_curvature(pixel.gram(self.jets(depth_m, x, 2)))
        return newton_polish(at, start_mm, max_steps=max_steps)

    def finish(self, pixel: TimeDomainPixel, depth_m, offset_mm, solved, num_steps, ceiling, noise_var) -> FitResult:
        """The fit at the polished depth, σ from the Fisher information there."""
        tone, slope_per_mm = self.jets(depth_m, offset_mm, 1)
        coef = projected_coefficients(pixel.gram([tone]))
        y, scale = pixel.y, pixel.scale
        res = y - coef[0] - coef[1] * tone
        converged = solved & descended(jnp.sum(res**2), ceiling)
        amp = coef[1] * scale
        # Fisher information of (depth, c, A) per unit noise variance, with the data unscaled
        slope = amp * 1e3 * slope_per_mm  # ∂(A·t)/∂depth (per m)
        f_dd = slope @ slope
        n = float(y.shape[0])
        information = depth_information(f_dd, slope @ tone, tone @ tone, jnp.sum(slope), n, jnp.sum(tone))
        sigma = sigma_from_information(information / jnp.maximum(noise_var, 1e-30))
        posed = well_posed(coef[1], tone @ tone, y @ y, f_dd, information)
        cost = jnp.sum(res**2) * scale**2
        return FitResult(depth_m + 1e-3 * offset_mm, coef[0] * scale, amp, sigma, converged, num_steps, cost, posed)


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
    (c, A) projected out, a basin grid, then Newton's polish on the depth offset (mm) in one
    pass (`TimeDomainML.fit_each` polishes a batch in two, `polish_in_passes`, to the same
    result). Every cost, slope and curvature comes from the Gram matrix of the constant
    column, the data and the tone's jets (`tone_jets`)."""
    model = TimeDomainModel(frequencies_hz, weights, system_delay_s)
    pixel = TimeDomainPixel.of(r)
    batch = lambda a: jnp.asarray(a)[None]
    starts, ceilings = model.grid_starts(
        jax.tree.map(batch, pixel), batch(coarse_depth_m), grid_half_width_m, grid_points
    )
    start, ceiling = starts[0], ceilings[0]
    p = model.polish(pixel, coarse_depth_m, start, max_steps)
    return model.finish(pixel, coarse_depth_m, p.value, p.succeeded, p.num_steps, ceiling, noise_var)


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
            device_value(setup.frequencies_hz),
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
        """The time-domain fit of every pixel from each of its K starting depths → fields (K, P):
        `refine_time_domain`'s stages, the polish in two passes (`polish_in_passes`)."""
        k, p = starts.shape
        model = TimeDomainModel(self.frequencies_hz, self.weights, self.system_delay_s)
        pixels = jax.vmap(TimeDomainPixel.of)(sequence.T)
        # one fit per (start, pixel), flattened: fit i is pixel i mod P's
        fits = jax.tree.map(
            lambda leaf: jnp.broadcast_to(leaf, (k, *leaf.shape)).reshape(k * p, *leaf.shape[1:]), pixels
        )
        depths, variances = starts.reshape(-1), jnp.tile(noise_var, k)
        offsets, ceilings = model.grid_starts(fits, depths, self.grid_half_width_m, self.grid_points)

        def polish_one(index, start, steps):
            q = model.polish(jax.tree.map(lambda leaf: leaf[index], fits), depths[index], start, steps)
            return q.value, q.succeeded, q.num_steps, q.at_step_limit

        values, solved, num_steps = polish_in_passes(polish_one, offsets, max_steps=self.max_steps)
        out = jax.vmap(model.finish)(fits, depths, values, solved, num_steps, ceilings, variances)
        return jax.tree.map(lambda leaf: leaf.reshape(k, p), out)

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
