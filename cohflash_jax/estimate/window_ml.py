"""Window ML: maximum-likelihood depth beyond the DFT bin (uniform sweeps).

The phase-locked model (`window_model`) is fitted on the W ≈ 17 bins around each pixel's
peak: for a tone in white noise that gives the precision of the full time-domain fit from
~1 % of the residuals (docs/physics.md). The model is linear in (c, A), so those are
projected out: the nonlinear fit is one unknown, the depth offset from the coarse estimate in
millimetres. A grid of the projected cost over ±1 bin picks the basin of the right likelihood
ripple (period c/(2 f̄)) before Newton's method polishes it (`polish.newton_polish`). float64
throughout: it is ~20 numbers per pixel.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Complex, Float, Int

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..fisher import depth_information, phase_locked_sigma_m, sigma_from_information, well_posed
from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup, FitResult, reduced_chi2
from .polish import (
    FIRST_PASS_STEPS,
    STEP_TOLERANCE_FLOOR_MM,
    STEP_TOLERANCE_SIGMA,
    descended,
    newton_polish,
    polish_in_passes,
)
from .window_model import (
    GRAM_DATA,
    GRAM_DC,
    GRAM_SLOPE,
    GRAM_TONE,
    Phasors,
    UniformModel,
    WindowData,
    WindowTables,
    bin_weights,
    jet_scale,
    projected_coefficients,
    projected_cost_slope_and_curvature,
    shift_phasors,
    window_tables,
)


class PixelFit(eqx.Module):
    """One pixel's fit between its stages (`prepare_pixel`, the polish, `finish_pixel`): the
    ω-weighted window, its tables, the tone's phasors at the coarse depth, the data scale, the
    polish's starts (mm from the coarse depth) and ceilings (`descended`), one per basin
    candidate, and the polish's step tolerance (mm)."""

    data: WindowData
    tables: WindowTables
    omega: Float[Array, " W"]
    base: Phasors
    scale: Float[Array, ""]
    starts_mm: Float[Array, " C"]
    ceilings: Float[Array, " C"]
    tolerance_mm: Float[Array, ""]

    def weighted_tone(self, model: UniformModel, rotation: Phasors, max_order: int | None = None):
        """The ω-weighted tone (Re, Im) with the phasors moved by `rotation` (`UniformModel.rotation`)."""
        re, im = model.tone_from_phasors(shift_phasors(self.base, rotation), self.tables, max_order)
        return re * self.omega, im * self.omega

    def weighted_tone_jets(self, model: UniformModel, offset_mm, derivatives: int):
        """The ω-weighted tone's jets (Re, Im; value and derivatives per mm) at a depth offset
        (mm), every order modelled (`UniformModel.tone_jets`)."""
        rates_per_mm = tuple(1e-3 * rate for rate in model.angle_rates())
        phasors = shift_phasors(self.base, model.rotation(1e-3 * offset_mm))
        re, im = model.tone_jets(phasors, self.tables, rates=rates_per_mm, derivatives=derivatives)
        return jet_scale(self.omega, re), jet_scale(self.omega, im)

    def residual_energy(self, tone_re, tone_im):
        """Projected cost of a weighted tone: residual energy after the least-squares (c, A)."""
        _, res_re, res_im = self.data.project(tone_re, tone_im)
        return res_re @ res_re + res_im @ res_im

    def cost_at(self, model: UniformModel, rotation: Phasors, max_order: int | None = None):
        """Projected cost with the phasors moved by `rotation`."""
        return self.residual_energy(*self.weighted_tone(model, rotation, max_order))

    def slope_and_curvature(self, model: UniformModel):
        """The projected cost's first and second derivatives in the depth offset (mm), as a
        function of the offset, for the polish's Newton steps.

        The tone's own derivatives come in closed form (`weighted_tone_jets`), the cost's from
        the Gram matrix of (dc, y, t, t′, t″) (`projected_cost_slope_and_curvature`): one
        batched product of the window, then scalar arithmetic."""

        def at(offset_mm):
            (re, d_re, dd_re), (im, d_im, dd_im) = self.weighted_tone_jets(model, offset_mm, 2)
            return projected_cost_slope_and_curvature(self.data.gram([(re, im), (d_re, d_im), (dd_re, dd_im)]))

        return at


def prepare_pixel(
    model: UniformModel,
    window: Complex[Array, " W"],
    k0,
    coarse_depth_m,
    noise_var,
    *,
    grid_half_width_m: float,
    grid_points: int,
    candidates: int = 1,
    grid_max_order: int | None = None,
) -> PixelFit:
    """The window's data and the basin search: the projected cost on a grid over
    ±grid_half_width around the coarse depth picks where the polish starts. The grid models
    the orders up to `grid_max_order` (all where None)."""
    n = model.num_frames
    tables = window_tables(k0, window.shape[0], n)
    omega = bin_weights(tables, n)
    scale = jnp.maximum(jnp.max(jnp.abs(window)), 1e-30)
    data = WindowData(
        jnp.real(window) * omega / scale, jnp.imag(window) * omega / scale, model.dc_column(tables) * omega
    )
    # the tone at the coarse depth; an offset δ rotates its phasors by e^{iκδ} (`rotation`)
    pix = PixelFit(
        data,
        tables,
        omega,
        model.phasors(coarse_depth_m),
        scale,
        jnp.zeros(candidates),
        jnp.zeros(candidates),
        jnp.zeros(()),
    )

    # basin search: projected cost on a grid spanning ±grid_half_width around the coarse
    # depth (its rotations are constants). Where a strong harmonic's alias falls inside the
    # window the fundamental-only cost misjudges the ripples (measured: 6× the full cost at the
    # minima on a 5.1–5.7 GHz sweep), so the grid models every order down to `grid_max_order`
    grid_mm = np.linspace(-1e3 * grid_half_width_m, 1e3 * grid_half_width_m, grid_points)
    grid_rotations = jax.tree.map(jnp.asarray, model.rotation(1e-3 * grid_mm, xp=np))
    costs = jax.vmap(lambda r: pix.cost_at(model, r, grid_max_order))(grid_rotations)
    # polish the best `candidates` local minima of the grid and keep the lowest: where the
    # ripple is narrower than the grid can resolve, the best grid point may sit on the wrong one
    padded = jnp.concatenate([jnp.array([jnp.inf]), costs, jnp.array([jnp.inf])])
    left, right = padded[:-2], padded[2:]
    local_min = (costs <= left) & (costs <= right)
    # rank the minima by the minimum of the cosine through each and its neighbours, not by the
    # grid value: with a signed amplitude the projected cost ripples with period c/(4f̄) (half
    # the likelihood's ripple) as a − b·cos(2π·depth/period + φ), and at high SNR the grid's
    # sampling error (up to half a spacing off the minimum) outweighs the cost difference
    # between adjacent ripples — the wrong ripple would win (measured on a 5.1–5.7 GHz sweep)
    spacing = float(grid_mm[1] - grid_mm[0]) if grid_points > 1 else 1.0
    mean_f = model.start_hz + 0.5 * model.step_hz * (n - 1)
    theta = min(max(2 * math.pi * 1e-3 * spacing / (C / (4 * mean_f)), 1e-3), 3.0)  # grid step in cost phase
    interior = jnp.isfinite(left) & jnp.isfinite(right)
    l_, r_ = jnp.where(interior, left, costs), jnp.where(interior, right, costs)
    b_cos = (l_ + r_ - 2 * costs) / (2 * (1 - math.cos(theta)))
    b_sin = (r_ - l_) / (2 * math.sin(theta))
    amplitude = jnp.hypot(b_cos, b_sin)
    vertex = jnp.where(local_min, costs + b_cos - amplitude, jnp.inf)
    order = jnp.argmin(vertex)[None] if candidates == 1 else jax.lax.top_k(-vertex, candidates)[1]
    shift = jnp.where(amplitude[order] > 0, -jnp.arctan2(b_sin[order], b_cos[order]) / theta, 0.0)  # in spacings
    starts = jnp.asarray(grid_mm)[order] + jnp.clip(shift, -1.0, 1.0) * spacing
    # a polish must not end above its grid point's cost with every order modelled (`descended`)
    if grid_max_order is None or grid_max_order >= model.weights.shape[0] - 1:
        ceilings = costs[order]
    else:
        ceilings = jax.vmap(lambda r: pix.cost_at(model, r))(jax.tree.map(lambda v: v[order], grid_rotations))
    # step tolerance from the closed-form phase-locked bound at the window's peak amplitude
    # (a tone a·cos has unitary DFT peak a·√N/2 on a bin)
    tone_amplitude = 2 * scale / math.sqrt(n)
    sigma_pred_mm = 1e3 * phase_locked_sigma_m(model.sum_angular_frequency_sq(), tone_amplitude, noise_var)
    tolerance_mm = jnp.maximum(STEP_TOLERANCE_FLOOR_MM, STEP_TOLERANCE_SIGMA * sigma_pred_mm)
    return eqx.tree_at(lambda f: (f.starts_mm, f.ceilings, f.tolerance_mm), pix, (starts, ceilings, tolerance_mm))


def finish_pixel(
    model: UniformModel,
    pix: PixelFit,
    coarse_depth_m,
    noise_var,
    offsets_mm: Float[Array, " C"],
    solved: Bool[Array, " C"],
    num_steps: Int[Array, " C"],
) -> FitResult:
    """The fit at the polished depth of each candidate, the best candidate, and its σ from
    the Fisher information."""
    data = pix.data

    def final_fit(offset_mm):
        """The fit at a depth: (c, A), cost, and the Gram matrix of (dc, y, the weighted tone,
        its derivative in depth: the Jacobian's depth column)."""
        (re, d_re_per_mm), (im, d_im_per_mm) = pix.weighted_tone_jets(model, offset_mm, 1)
        g = data.gram([(re, im), (1e3 * d_re_per_mm, 1e3 * d_im_per_mm)])
        coef = projected_coefficients(g)
        res_re, res_im = data.y_re - data.dc * coef[0] - re * coef[1], data.y_im - im * coef[1]
        return coef, res_re @ res_re + res_im @ res_im, g

    coefs, finals, grams = jax.vmap(final_fit)(offsets_mm)
    oks = solved & descended(finals, pix.ceilings)
    if offsets_mm.shape[0] > 1:
        ranked = jnp.where(jnp.isfinite(finals), finals, jnp.inf)
        # Where ripples are narrower than a bin, (A, τ) and (−A, τ + half a ripple) fit almost
        # equally: the carrier alignment made A·w_0 > 0, so prefer a positive amplitude.
        amps = coefs[:, 1]
        best = jnp.argmin(jnp.where((amps >= 0) | jnp.all(amps < 0), ranked, jnp.inf))
    else:  # one basin: no comparison
        best = 0
    pick = lambda tree: jax.tree.map(lambda leaf: leaf[best], tree)
    offset_mm, ok, steps, coef, cost_final, g = pick((offsets_mm, oks, num_steps, coefs, finals, grams))
    depth = coarse_depth_m + 1e-3 * offset_mm
    # Fisher information of (depth, c, A): components of a unitary DFT of white noise of
    # variance σ² carry σ²/2 each (the weights ω already account for DC/Nyquist bins).
    # Jacobian columns (in units of the scaled data): depth A·∂tone/∂depth, offset dc, amplitude tone
    dc, y, tone, d_tone = GRAM_DC, GRAM_DATA, GRAM_TONE, GRAM_SLOPE
    amp = coef[1]
    tone_sq = g[tone, tone]
    f_dd = amp**2 * g[d_tone, d_tone]
    f_dc, f_da = amp * g[d_tone, dc], amp * g[d_tone, tone]
    f_cc, f_ca, f_aa = g[dc, dc], g[dc, tone], tone_sq
    schur_scaled = depth_information(f_dd, f_da, f_aa, f_dc, f_cc, f_ca)
    scale = pix.scale
    sigma = sigma_from_information(schur_scaled * scale**2 / (0.5 * jnp.maximum(noise_var, 1e-30)))
    data_sq = g[y, y]
    posed = well_posed(amp, tone_sq, data_sq, f_dd, schur_scaled)
    return FitResult(
        depth, coef[0] * scale, amp * scale, sigma, ok & jnp.isfinite(cost_final), steps, cost_final * scale**2, posed
    )


def refine_ml_uniform(
    model: UniformModel,
    windows,
    k0,
    coarse_depth_m,
    noise_var,
    *,
    grid_half_width_m: float,
    grid_points: int,
    max_steps: int = 16,
    candidates: int = 1,
    grid_max_order: int | None = None,
    first_pass_steps: int = FIRST_PASS_STEPS,
) -> FitResult:
    """ML depth of a batch of pixels (the leading axis of every array argument) from their DFT
    windows (unitary bins k0..k0+W−1): `prepare_pixel`, the polish, `finish_pixel`.

    The polish (`newton_polish`, up to `max_steps` Newton steps a pixel and candidate) runs in
    two passes (`polish_in_passes`, the first of `first_pass_steps`, default `FIRST_PASS_STEPS`)."""
    prep = lambda w, k, d, v: prepare_pixel(
        model,
        w,
        k,
        d,
        v,
        grid_half_width_m=grid_half_width_m,
        grid_points=grid_points,
        candidates=candidates,
        grid_max_order=grid_max_order,
    )
    pix = jax.vmap(prep)(windows, k0, coarse_depth_m, noise_var)
    num_pixels = windows.shape[0]
    # one polish per (pixel, candidate), flattened
    owner = jnp.repeat(jnp.arange(num_pixels), candidates)
    starts = pix.starts_mm.reshape(-1)

    def polish(index, start, steps):
        one = jax.tree.map(lambda leaf: leaf[owner[index]], pix)
        p = newton_polish(one.slope_and_curvature(model), start, max_steps=steps, tolerance_mm=one.tolerance_mm)
        return p.value, p.succeeded, p.num_steps, p.at_step_limit

    values, solved, num_steps = polish_in_passes(polish, starts, max_steps=max_steps, first_pass_steps=first_pass_steps)
    shape = (num_pixels, candidates)
    fin = lambda p, d, v, x, ok, steps: finish_pixel(model, p, d, v, x, ok, steps)
    return jax.vmap(fin)(
        pix, coarse_depth_m, noise_var, values.reshape(shape), solved.reshape(shape), num_steps.reshape(shape)
    )


# The basin grid leaves out sideband orders whose weight is below this fraction of the
# dominant tone's: a tone of relative amplitude ε left unmodelled adds ε²·(signal energy) to
# every grid cost alike (1e-4 of it at ε = 1 %), far below both the noise near the SNR
# threshold and the differences between ripples at high SNR; the polish models every order.
GRID_MIN_RELATIVE_WEIGHT = 1e-2


def grid_orders(weights) -> int:
    """The highest sideband order the basin grid models (`GRID_MIN_RELATIVE_WEIGHT`)."""
    w = np.abs(np.asarray(weights, np.float64))[1:]
    keep = np.nonzero(w >= GRID_MIN_RELATIVE_WEIGHT * w.max())[0]
    return int(keep.max() + 1)


def grid_for(
    sweep_bin_depth_m: float,
    ripple_m: float,
    half_width_bins: float = 1.0,
    points_per_ripple: int = 6,
    max_points: int = 257,
) -> tuple[float, int, int]:
    """Basin search: half-width (m), odd number of grid points, and how many of the grid's
    best local minima to polish (3 where the ripple is narrower than a bin, else 1)."""
    half = half_width_bins * sweep_bin_depth_m
    # the grid must resolve the likelihood's ripple; where the ripple is wider than a bin
    # (0.1–6 GHz: 49 mm vs 25 mm) a quarter-bin spacing already lands in the right basin
    spacing = min(sweep_bin_depth_m / 4, ripple_m / points_per_ripple)
    points = int(min(max_points, 2 * math.ceil(half / spacing) + 1))
    return half, points, (3 if ripple_m < sweep_bin_depth_m else 1)


# The straggler pass pays off for short sweeps, whose large batches hold a few pixels that need
# 2–3× the steps of the rest; at long sweeps it measured neutral and costs a second compiled
# polish (docs/performance.md), so they polish in one pass.
TWO_PASS_MAX_FRAMES = 512


class WindowML(AbstractDepthEstimator):
    """Phase-locked maximum likelihood on the W DFT bins around each pixel's peak (uniform
    sweeps): a basin grid over ±1 bin of the coarse depth, Newton's polish, σ from the Fisher
    information at the fit (`refine_ml_uniform`)."""

    refines: ClassVar[bool] = True

    @property
    def description(self) -> str:
        return "ML on the DFT window (Dirichlet kernels)"

    model: UniformModel
    window_bins: int = eqx.field(static=True)
    grid_half_width_m: float = eqx.field(static=True)
    grid_points: int = eqx.field(static=True)
    candidates: int = eqx.field(static=True)
    grid_max_order: int = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    first_pass_steps: int = eqx.field(static=True)

    @classmethod
    def build(cls, setup: EstimatorSetup) -> WindowML:
        g = setup.geometry
        half, points, candidates = grid_for(g.bin_depth_m, g.ripple_m)
        first_pass = FIRST_PASS_STEPS if g.num_frames < TWO_PASS_MAX_FRAMES else setup.max_steps
        return cls(
            setup.model,
            setup.window_bins,
            half,
            points,
            candidates,
            grid_orders(setup.model.weights),
            setup.max_steps,
            first_pass,
        )

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        spec = coarse.spectrum
        coarse_depth = stage.depth(coarse, interpolate=True)
        k_count = spec.shape[-1]
        w = min(self.window_bins, k_count)
        k0 = jnp.clip(coarse.peak - w // 2, 0, k_count - w)
        windows = jnp.take_along_axis(spec, k0[:, None] + jnp.arange(w), axis=-1).astype(jnp.complex128)
        fit = refine_ml_uniform(
            self.model,
            windows,
            k0,
            coarse_depth,
            noise_var,
            grid_half_width_m=self.grid_half_width_m,
            grid_points=self.grid_points,
            max_steps=self.max_steps,
            candidates=self.candidates,
            grid_max_order=self.grid_max_order,
            first_pass_steps=self.first_pass_steps,
        )
        # reduced χ² of the window fit: each unitary bin holds noise of variance σ²/2 per
        # component; 2W real residuals less the three fitted unknowns (noise floored at 1e-9 of
        # the window's mean power: noiseless data have rounding-level residuals and a zero noise
        # estimate, which is not a misfit)
        chi2 = reduced_chi2(fit.cost, 0.5 * noise_var, 0.5 * jnp.mean(jnp.abs(windows) ** 2, axis=-1), 2 * w - 3)
        return fit.to_estimate(coarse_depth, chi2)
