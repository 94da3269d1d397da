"""Maximum-likelihood depth for short uniform sweeps (the 10 Hz mode), from a tone table.

Over all N frames the phase-locked model r[m] = c + A·t(d)[m], t(d)[m] = Σ_{n≥1} 2 w_n
cos(2π n f_m τ(d)), is the same for every pixel. So for a short sweep its tone is tabulated
once, on a depth grid over the unambiguous window, with its first K depth derivatives
(`ToneTable`). A pixel's fit then needs no trigonometry:

1. basin search: the projected likelihood on the grid, (y·t̂_g)² for the mean-removed data y
   and unit tones t̂_g, is one matrix product for a whole tile; the best point within the
   coarse stage's ±half-width (as `window_ml`'s grid) is picked;
2. polish: about that point t(d_g + u·s) = Σ_j u^j/j!·R_j (R_j = s^j ∂^j t/∂d^j, spacing s) is a
   polynomial in u, so the projected cost −(y·t)²/|t|² is a ratio of polynomials whose
   coefficients are K+1 dot products a pixel; Newton's method (`polish.newton_polish`, with the
   ratio's exact derivatives) runs on it;
3. the final fit, σ from the Fisher information and the well-posedness checks, in the time
   domain over every frame (exact ML, not a DFT window).

The grid spacing keeps the Taylor remainder below `TAYLOR_TOLERANCE` of the tone within
±half a spacing (`table_spacing_m`).
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..fisher import depth_information, phase_locked_sigma_m, sigma_from_information, well_posed
from ..runtime import MATMUL_PRECISION, device_value
from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup, FitResult, reduced_chi2
from .coarse import at_grid_point, first_argmax
from .polish import STEP_TOLERANCE_FLOOR_MM, STEP_TOLERANCE_SIGMA, newton_polish
from .window_ml import grid_for
from .window_model import UniformModel

TAYLOR_ORDER = 6  # derivatives tabulated per grid depth (K)
TAYLOR_TOLERANCE = 1e-6  # Taylor remainder at half a spacing, relative to the dominant tone
POINTS_PER_COST_RIPPLE = 6  # the projected cost ripples with period c/(4 f̄) (signed amplitude)
MAX_POLISH_SPACINGS = 1.0  # a polish that moves further from its grid point is not trusted
# Newton steps every pixel's polish takes unrolled, in one fused pass over the batch, before a
# loop takes those still going: from its grid point a pixel converges in at most 4 (measured on
# the dense 10 Hz scene: 3.9 on average), and each pass of a batched loop costs its slowest pixel
POLISH_UNROLLED_STEPS = 4
# With float32 projections a fit's residual cost is taken from the frames, not from the
# polynomials, where it is below this share of |y|² (per-frame SNR above ~40 dB, or no noise)
RESIDUAL_COST_SHARE = 1e-4


def table_spacing_m(frequencies_hz, weights, order: int = TAYLOR_ORDER, tolerance: float = TAYLOR_TOLERANCE) -> float:
    """Grid spacing (m): the largest at which each order's Taylor remainder over half a
    spacing, (n·κ_max·s/2)^(K+1)/(K+1)!·|w_n|/max|w|, sums to at most `tolerance`
    (κ_max = 4π f_max/c), and no more than a sixth of the projected cost's ripple c/(4 f̄)."""
    f = np.asarray(frequencies_hz, np.float64)
    w = np.abs(np.asarray(weights, np.float64))[1:]
    rel = w / max(w.max(), 1e-300)
    kappa = 4 * math.pi * f.max() / C
    orders = np.arange(1, w.size + 1)

    def remainder(s):
        return float(np.sum(rel * (orders * kappa * s / 2) ** (order + 1)) / math.factorial(order + 1))

    lo, hi = 0.0, C / (4 * f.mean()) / POINTS_PER_COST_RIPPLE
    if remainder(hi) <= tolerance:
        return hi
    for _ in range(60):  # bisection: the remainder grows monotonically with s
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if remainder(mid) <= tolerance else (lo, mid)
    return lo


def table_points(depth_range_m: tuple[float, float], spacing_m: float) -> int:
    return int(math.ceil((depth_range_m[1] - depth_range_m[0]) / spacing_m)) + 1


class ToneTable(eqx.Module):
    """The tone t(d) and its scaled depth derivatives R_j = s^j ∂^j t/∂d^j on a depth grid
    d_g = start + g·s. `unit_tones` (N, G) float32: mean-removed t, unit norm (the basin
    search's matrix); `rows` (G, K+1, N) float32: mean-removed R_j; `means` (G, K+1): the
    R_j's means over frames; `norm_coeffs` (G, 2K+1): coefficients of |Σ_j u^j/j!·R_j|² in u
    (mean-removed, from the float32 rows). `start_m` moves with τ_sys: a field, which the
    reconstruction's programs take as an array (`reconstruct.plan.program_plan`);
    `slope_norm_coeffs` (G, 2K−1): coefficients of |Σ_{j≥1} u^{j−1}/(j−1)!·R_j|², the squared
    norm of the tone's derivative in u, so the final fit's Fisher information needs no pass
    over the frames."""

    unit_tones: Float[Array, "N G"]
    rows: Float[Array, "G K1 N"]
    means: Float[Array, "G K1"]
    norm_coeffs: Float[Array, "G K2"]
    slope_norm_coeffs: Float[Array, "G K3"]
    start_m: float
    spacing_m: float = eqx.field(static=True)

    @property
    def num_points(self) -> int:
        return self.rows.shape[0]


def build_tone_table(
    frequencies_hz,
    weights,
    system_delay_s: float,
    depth_range_m: tuple[float, float],
    spacing_m: float,
    order: int = TAYLOR_ORDER,
) -> ToneTable:
    """`ToneTable` over [depth_range_m] (NumPy, float64; the phases reduced modulo 2π)."""
    f = np.asarray(frequencies_hz, np.float64)
    w = np.asarray(weights, np.float64)
    depths = depth_range_m[0] + spacing_m * np.arange(table_points(depth_range_m, spacing_m))
    tau = system_delay_s + 2 * depths / C  # (G,)
    kappa_s = 4 * math.pi * f * spacing_m / C  # phase per spacing of the first order, (N,)
    rows = np.zeros((depths.size, order + 1, f.size))
    for n in range(1, w.size):
        cycles = n * tau[:, None] * f[None, :]
        phase = 2 * math.pi * (cycles - np.floor(cycles))  # (G, N)
        for j in range(order + 1):  # ∂^j cos φ = (∂φ)^j·cos(φ + jπ/2)
            rows[:, j] += 2 * w[n] * (n * kappa_s) ** j * np.cos(phase + j * math.pi / 2)
    means = rows.mean(axis=-1)
    centred = (rows - means[..., None]).astype(np.float32)
    exact = centred.astype(np.float64)
    inv_fact = inverse_factorials(order + 1)
    gram = np.einsum("gim,gjm->gij", exact, exact) * inv_fact[None, :, None] * inv_fact[None, None, :]
    coeffs = np.zeros((depths.size, 2 * order + 1))
    slope_coeffs = np.zeros((depths.size, 2 * order - 1))
    for i in range(order + 1):
        for j in range(order + 1):
            coeffs[:, i + j] += gram[:, i, j]
            if i and j:  # d/du of u^i/i! is u^(i−1)/(i−1)!: the same Gram entry, scaled by i·j
                slope_coeffs[:, i + j - 2] += i * j * gram[:, i, j]
    norm0 = np.sqrt(np.maximum(coeffs[:, 0], 1e-300))
    unit = (exact[:, 0] / norm0[:, None]).T.astype(np.float32)
    return ToneTable(
        device_value(unit),
        device_value(centred),
        device_value(means),
        device_value(coeffs),
        device_value(slope_coeffs),
        float(depth_range_m[0]),
        float(spacing_m),
    )


def inverse_factorials(count: int) -> np.ndarray:
    """1/j! for j < count (the Taylor sums' weights)."""
    return np.array([1 / math.factorial(j) for j in range(count)])


def _poly(coeffs, u):
    """Σ_k coeffs[..., k]·u^k (Horner; coefficients on the last axis)."""
    acc = coeffs[..., -1]
    for k in range(coeffs.shape[-1] - 2, -1, -1):
        acc = acc * u + coeffs[..., k]
    return acc


def _poly_and_derivatives(coeffs, u):
    """(p, p′, p″) at u of p(u) = Σ_k coeffs[..., k]·u^k (Horner, all three in one pass)."""
    value, first, half_second = coeffs[..., -1], jnp.zeros_like(u), jnp.zeros_like(u)
    for k in range(coeffs.shape[-1] - 2, -1, -1):
        half_second = half_second * u + first
        first = first * u + value
        value = value * u + coeffs[..., k]
    return value, first, 2 * half_second


def _derivative_coeffs(coeffs):
    """The coefficients of p′ from those of p (last axis)."""
    return coeffs[..., 1:] * np.arange(1, coeffs.shape[-1])


def _projected_gain_slope_and_curvature(b_coeffs, norm_coeffs, ridge):
    """u ↦ the slope and curvature in u of the projected cost −b(u)²/(n(u) + ridge), b and n
    polynomials: Newton's step from exact derivatives (`polish.newton_polish`)."""

    def at(u):
        b, b1, b2 = _poly_and_derivatives(b_coeffs, u)
        m, m1, m2 = _poly_and_derivatives(norm_coeffs, u)
        m = m + ridge
        # gain g = b²/m: g′ = (2b·b′·m − b²·m′)/m², g″ = 2(b′² + b·b″)/m − (4b·b′·m′ + b²·m″)/m² + 2b²·m′²/m³
        b_sq, m_sq = b * b, m * m
        slope = (2 * b * b1 * m - b_sq * m1) / m_sq
        curvature = 2 * (b1 * b1 + b * b2) / m - (4 * b * b1 * m1 + b_sq * m2) / m_sq + 2 * b_sq * m1 * m1 / (m_sq * m)
        return -slope, -curvature

    return at


def refine_ml_table(
    table: ToneTable,
    model: UniformModel,
    r: Float[Array, "N P"],
    coarse_depth_m: Float[Array, " P"],
    noise_var: Float[Array, " P"],
    *,
    half_width_m: float,
    max_steps: int,
    prefer_positive: bool = False,
    projection_dtype=jnp.float32,
) -> FitResult:
    """ML depth of each pixel of the carrier-aligned sequences r (N, P) from `table`: the
    basin search within ±`half_width_m` of the coarse depth, the polish, the final fit.
    `prefer_positive`: pick the best grid point with a positive amplitude where there is one
    (where ripples are narrower than a bin; the carrier alignment makes A·w_0 > 0).

    Precision: the data are centred in their own type (float32 from the reconstruction); the
    basin's scores are float32, the polish's projections y·R_j `projection_dtype` (float32:
    products of the float32 rows, the table's own precision, summed over the N frames in
    float32); |y|², the polynomials, the polish and the fit are float64, and with float32
    projections the residual cost is the residual's own sum of squares where the polynomials
    would not resolve it (`RESIDUAL_COST_SHARE`). Against float64 projections, float32 ones
    move a depth by ≤ 1e-6 of σ at ~15 dB a frame and ~1e-4 at 55 dB (the brightest target
    over the quantisation noise), 1e-3 in the last 0.1 mm before the window's
    mirror-symmetric edge, where the cost is flat; σ by < 1e-4 and the reduced χ² by < 1e-3;
    the flags not at all, in those tests (`tests/test_short_sweeps.py`) and on dense 10 Hz
    captures. The fit then costs about a third less."""
    n = r.shape[0]
    # the mean as a sum of rows in frame order (a loop): a pixel's fit is then the same bits
    # whatever its batch (XLA's CPU float32 reductions, fused, sum in an order that depends on
    # the batch's size)
    mean = jax.lax.scan(lambda total, row: (total + row, None), jnp.zeros_like(r[0]), r)[0] / n
    y = r - mean  # (N, P), r's type: float32 subtraction of nearby values is exact or nearly
    y32 = y.astype(jnp.float32)
    mean_r = mean.astype(jnp.float64)
    data_sq = jnp.sum(jnp.square(y.astype(jnp.float64)), axis=0)
    # 1. basin search: one matrix product (float32 suffices to rank grid points), then the
    # grid points within ±half_width of the coarse depth: a window of at most `width` points
    # at full float32 precision wherever it runs (a GPU's default, TF32, keeps 10 bits)
    scores = jnp.matmul(table.unit_tones.T, y32, precision=MATMUL_PRECISION)  # (G, P)
    g_count = table.num_points
    s = table.spacing_m
    lo = jnp.ceil((coarse_depth_m - half_width_m - table.start_m) / s).astype(jnp.int32)
    hi = jnp.floor((coarse_depth_m + half_width_m - table.start_m) / s).astype(jnp.int32)
    width = int(math.floor(2 * half_width_m / s)) + 2  # the window's points, one to spare for rounding
    idx = lo[None, :] + jnp.arange(width, dtype=jnp.int32)[:, None]  # (W, P)
    inside = (idx >= 0) & (idx <= hi[None, :]) & (idx < g_count)
    window = jnp.take_along_axis(scores, jnp.clip(idx, 0, g_count - 1), axis=0)  # (W, P)
    found = jnp.any(inside, axis=0)  # an empty window (no finite coarse depth) picks point 0, as a full mask did
    pick = lambda k: jnp.where(found, at_grid_point(idx, k, axis=0), 0)
    best = pick(first_argmax(jnp.where(inside, jnp.abs(window), -1.0), axis=0))
    if prefer_positive:
        signed = jnp.where(inside, window, -1.0)
        k_signed = first_argmax(signed, axis=0)
        has_positive = at_grid_point(signed, k_signed, axis=0) > 0
        best = jnp.where(has_positive, pick(k_signed), best)
    # the table's entries at each pixel's grid point (`best` is a grid index: "clip" is a
    # plain gather, without "fill"'s out-of-range select)
    at_best = lambda field: jnp.take(field, best, axis=0, mode="clip")
    # 2. polish: b(u) = y·t(u) and |t(u)|² are polynomials in u
    rows = at_best(table.rows)  # (P, K+1, N)
    k1 = rows.shape[1]
    dots = jnp.einsum(
        "pjm,mp->pj", rows.astype(projection_dtype), y.astype(projection_dtype), precision=MATMUL_PRECISION
    )
    b_coeffs = dots.astype(jnp.float64) * inverse_factorials(k1)
    norm_coeffs = at_best(table.norm_coeffs)  # (P, 2K+1)
    ridge = 1e-12 * norm_coeffs[:, 0] + 1e-300
    # the polish's step tolerance from the phase-locked bound, with the tone's amplitude taken
    # from the data's energy (|y|² ≈ N·a²/2; noise makes it an overestimate: a finer tolerance)
    tone_amp = jnp.sqrt(2 * data_sq / n)
    sigma_pred_mm = 1e3 * phase_locked_sigma_m(model.sum_angular_frequency_sq(), tone_amp, noise_var)
    tolerance_u = jnp.maximum(STEP_TOLERANCE_FLOOR_MM, STEP_TOLERANCE_SIGMA * sigma_pred_mm) / (1e3 * s)
    gain = lambda b_c, n_c, rid, u: _poly(b_c, u) ** 2 / (_poly(n_c, u) + rid)

    def polish(b_c, n_c, rid, tol):
        p = newton_polish(
            _projected_gain_slope_and_curvature(b_c, n_c, rid),
            jnp.zeros(()),
            max_steps=max_steps,
            tolerance_mm=tol,
            unrolled_steps=POLISH_UNROLLED_STEPS,
        )
        descended = gain(b_c, n_c, rid, p.value) >= gain(b_c, n_c, rid, 0.0) * (1 - 1e-9)
        return p.value, p.succeeded & descended, p.num_steps

    u, solved, num_steps = jax.vmap(polish)(b_coeffs, norm_coeffs, ridge, tolerance_u)
    # a data-free pixel (dead, or zeroed NaN frames) has a flat cost and a NaN Newton step
    within = jnp.isfinite(u) & (jnp.abs(u) <= MAX_POLISH_SPACINGS)
    u = jnp.where(jnp.isfinite(u), jnp.clip(u, -MAX_POLISH_SPACINGS, MAX_POLISH_SPACINGS), 0.0)
    # 3. the final fit over every frame, from the same polynomials: y·t(u) = b(u), |t(u)|² =
    # n(u), t(u)·t′(u) = n′(u)/2 and |t′(u)|² from the table's slope polynomial (mean-removed
    # throughout; the means' Taylor sums give the DC parts)
    tone_y = _poly(b_coeffs, u)
    tone_norm = _poly(norm_coeffs, u)
    tone_sq = tone_norm + ridge
    amp = tone_y / tone_sq
    cost = jnp.maximum(data_sq - 2 * amp * tone_y + amp * amp * tone_norm, 0.0)
    if jnp.dtype(projection_dtype) != jnp.float64:
        # from float32 projections that difference keeps their rounding, ~1e-7 of |y|²: where
        # it is not well above that (a noiseless fit, a very bright target) the cost is the
        # residual's own sum of squares, whose rounding is ~1e-7 of each frame's value, squared
        unresolved = cost < RESIDUAL_COST_SHARE * data_sq

        def residual_cost():
            powers = [jnp.ones_like(u)]
            for j in range(1, k1):
                powers.append(powers[-1] * u / j)  # u^j/j!
            weights_u = (amp[:, None] * jnp.stack(powers, axis=1)).astype(jnp.float32)  # (P, K+1)
            model = jnp.einsum("pj,pjm->pm", weights_u, rows, precision=MATMUL_PRECISION)  # A·t(u): (P, N)
            return jnp.where(unresolved, jnp.sum(jnp.square(y32.T - model).astype(jnp.float64), axis=1), cost)

        cost = jax.lax.cond(jnp.any(unresolved), residual_cost, lambda: cost)
    mean_coeffs = at_best(table.means) * inverse_factorials(k1)  # (P, K+1)
    mean_tone, mean_tone_u = _poly(mean_coeffs, u), _poly(_derivative_coeffs(mean_coeffs), u)
    offset = mean_r - amp * mean_tone
    # Fisher information of (depth, c, A), per unit noise variance: c is eliminated exactly by
    # the mean-removed columns, A by the Schur complement; ∂t/∂d = (∂t/∂u)/s
    du_sq = _poly(at_best(table.slope_norm_coeffs), u)
    tone_du = 0.5 * _poly(_derivative_coeffs(norm_coeffs), u)
    f_da = amp * tone_du / s
    schur_unit = depth_information(amp**2 * du_sq / s**2, f_da, tone_sq)
    sigma = sigma_from_information(schur_unit / jnp.maximum(noise_var, 1e-30))
    f_dd = amp**2 * (du_sq + n * mean_tone_u**2) / s**2
    posed = well_posed(amp, tone_sq + n * mean_tone**2, data_sq + n * mean_r**2, f_dd, schur_unit)
    depth = table.start_m + s * (best.astype(jnp.float64) + u)
    converged = solved & within & jnp.isfinite(cost)
    return FitResult(depth, offset, amp, sigma, converged, num_steps, cost, posed)


# `ml` on uniform sweeps of at most this many frames fits every frame from a tone table, if the
# table needs at most `TABLE_MAX_POINTS` grid depths (its basin search is a (P, N)·(N, G)
# product, O(N·G) a pixel); longer sweeps, and narrow ones high in frequency (thousands of
# depths), fit the DFT window (`window_ml`). Timings: docs/performance.md.
TABLE_MAX_FRAMES = 64
TABLE_MAX_POINTS = 1024


def table_fits(setup: EstimatorSetup) -> bool:
    """Whether a tone table serves this configuration (`TABLE_MAX_FRAMES`, `TABLE_MAX_POINTS`)."""
    g = setup.geometry
    if not g.uniform or g.num_frames > TABLE_MAX_FRAMES:
        return False
    return (
        table_points(_table_span(setup), table_spacing_m(setup.frequencies_hz, setup.model.weights)) <= TABLE_MAX_POINTS
    )


def _table_span(setup: EstimatorSetup) -> tuple[float, float]:
    """Depths the table spans: the unambiguous window and the basin search's reach beyond it."""
    g = setup.geometry
    half, _, _ = grid_for(g.bin_depth_m, g.ripple_m)
    spacing = table_spacing_m(setup.frequencies_hz, setup.model.weights)
    return g.depth_window_m[0] - half - spacing, g.depth_window_m[1] + half + spacing


class TableML(AbstractDepthEstimator):
    """Phase-locked maximum likelihood over every frame from a tone table (short uniform
    sweeps, such as the paper's 10 Hz mode): basin search within ±1 bin of the coarse depth,
    Newton's polish on the Taylor polynomial, the exact final fit (`refine_ml_table`)."""

    refines: ClassVar[bool] = True
    detected_only: ClassVar[bool] = True

    @property
    def description(self) -> str:
        return f"ML over all frames from a tone table ({self.table.num_points} depths)"

    table: ToneTable
    model: UniformModel
    half_width_m: float = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    prefer_positive: bool = eqx.field(static=True)

    @classmethod
    def build(cls, setup: EstimatorSetup) -> TableML:
        g = setup.geometry
        half, _, candidates = grid_for(g.bin_depth_m, g.ripple_m)
        spacing = table_spacing_m(setup.frequencies_hz, setup.model.weights)
        table = build_tone_table(
            setup.frequencies_hz, setup.model.weights, g.system_delay_s, _table_span(setup), spacing
        )
        return cls(table, setup.model, half, setup.max_steps, candidates > 1)

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        coarse_depth = stage.depth(coarse, interpolate=True)
        fit = refine_ml_table(
            self.table,
            self.model,
            sequence,
            coarse_depth,
            noise_var,
            half_width_m=self.half_width_m,
            max_steps=self.max_steps,
            prefer_positive=self.prefer_positive,
        )
        # reduced χ² over the N frames less the three fitted unknowns (noise floored as the
        # window fit floors it)
        mean_square = jnp.mean(jnp.square(sequence.astype(jnp.float64)), axis=0)
        return fit.to_estimate(coarse_depth, reduced_chi2(fit.cost, noise_var, mean_square, sequence.shape[0] - 3))
