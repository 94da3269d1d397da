"""Depth for non-uniform (e.g. sparse) frequency schedules.

There is no "frequency over the frame index" when f_m is not f_0 + mΔf, so the coarse stage
is a periodogram over delay, |Σ_m (r[m] − r̄)·e^{−i2π f_m τ}|², evaluated on a depth grid (one
matrix product per tile), and the ML fit runs in the time domain over all N frames. This path
costs O(N·G) per pixel for G grid depths: suited to regions of interest and moderate N, not to
full frames at video rate. The magnitude of the periodogram is smooth on the envelope scale
c/(2B) (the tone's phase ripple cancels in |·|), so the grid needs ~4 points per c/(2B).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from .coarse import first_argmax
from .ml import (MAX_VARIANCE_INFLATION, FitResult, _solve_normal, descended, polish_depth, tone_cancels_offset,
                 variance_inflation)


def depth_grid(frequencies_hz: np.ndarray, depth_window_m: tuple[float, float], points_per_envelope: int = 4) -> np.ndarray:
    """Depths (m) over the unambiguous window [max(0, start), end), spaced c/(2B)/points_per_envelope."""
    f = np.asarray(frequencies_hz, np.float64)
    envelope = C / (2 * (f[-1] - f[0]))
    return np.arange(max(0.0, depth_window_m[0]), depth_window_m[1], envelope / points_per_envelope)


def periodogram_coarse(r: Float[Array, "N P"], frequencies_hz: Float[Array, " N"], depths_m: Float[Array, " G"],
                       system_delay_s: float = 0.0) -> tuple[Float[Array, " P"], Float[Array, " P"]]:
    """Coarse depth per pixel (parabolic interpolation between grid depths) and the peak's
    amplitude estimate |X|·2/N."""
    n = r.shape[0]
    tau = system_delay_s + 2 * depths_m / C
    cycles = frequencies_hz[:, None].astype(jnp.float64) * tau[None, :]
    basis = jnp.exp(-2j * jnp.pi * (cycles - jnp.floor(cycles))).astype(jnp.complex64)  # (N, G)
    centred = (r - jnp.mean(r, axis=0)).astype(jnp.float32)
    power = jnp.abs(centred.T.astype(jnp.complex64) @ basis) ** 2  # (P, G)
    g = power.shape[-1]
    k = first_argmax(power)
    take = lambda idx: jnp.take_along_axis(power, jnp.clip(idx, 0, g - 1)[:, None], axis=-1)[:, 0]
    a, b, c = take(k - 1), take(k), take(k + 1)
    den = a - 2 * b + c
    interior = (den < 0) & (k > 0) & (k < g - 1)
    delta = jnp.where(interior, 0.5 * (a - c) / jnp.where(interior, den, -1.0), 0.0)
    step = depths_m[1] - depths_m[0]
    return depths_m[k] + jnp.clip(delta, -0.5, 0.5) * step, 2 * jnp.sqrt(b) / n


def _project(design, y):
    """Least-squares (c, A) for a 2-column real design (explicit 2×2 normal equations,
    ridge-stabilised so a vanishing tone column gives A = 0, not NaN)."""
    a, b = design[:, 0], design[:, 1]
    coef = _solve_normal(a @ a, a @ b, b @ b, a @ y, b @ y)
    return coef, y - design @ coef


def refine_time_domain(r: Float[Array, " N"], frequencies_hz: Float[Array, " N"], weights: Float[Array, " K"],
                       coarse_depth_m, noise_var, *, system_delay_s: float, grid_half_width_m: float,
                       grid_points: int, max_steps: int) -> FitResult:
    """ML depth of one pixel over all frames: r[m] = c + A·Σ_{n≥1} 2 w_n cos(2π n f_m τ), with
    (c, A) projected out, a basin grid, then `polish_depth` on the depth offset (mm)."""
    f = frequencies_hz.astype(jnp.float64)
    y = r.astype(jnp.float64)
    scale = jnp.maximum(jnp.std(y), 1e-30)
    y = y / scale

    def design(depth_m):
        tau = system_delay_s + 2 * depth_m / C
        tone = jnp.zeros_like(f)
        for order in range(1, weights.shape[0]):
            cyc = order * f * tau
            tone = tone + 2 * weights[order] * jnp.cos(2 * jnp.pi * (cyc - jnp.floor(cyc)))
        return jnp.stack([jnp.ones_like(f), tone], axis=1)

    def residual(offset_mm, _=None):
        return _project(design(coarse_depth_m + 1e-3 * offset_mm), y)[1]

    grid_mm = jnp.linspace(-1e3 * grid_half_width_m, 1e3 * grid_half_width_m, grid_points)
    costs = jax.vmap(lambda g: jnp.sum(residual(g) ** 2))(grid_mm)
    offset_mm, solved, num_steps = polish_depth(lambda x: jnp.sum(residual(x) ** 2), grid_mm[jnp.argmin(costs)],
                                                max_steps=max_steps)
    depth = coarse_depth_m + 1e-3 * offset_mm
    final = design(depth)
    coef, res = _project(final, y)
    converged = solved & descended(jnp.sum(res**2), jnp.min(costs))
    amp = coef[1] * scale
    d_tone = jax.jvp(lambda d: design(d)[:, 1], (depth,), (jnp.ones_like(depth),))[1]
    cols = jnp.stack([jnp.ones_like(f), final[:, 1], amp * d_tone], axis=1)
    fisher = cols.T @ cols / jnp.maximum(noise_var, 1e-30)
    cov = jnp.linalg.inv(fisher + 1e-300 * jnp.eye(3))
    sigma = jnp.where(cov[2, 2] > 0, jnp.sqrt(jnp.abs(cov[2, 2])), jnp.inf)
    inflation = variance_inflation(fisher[2, 2], 1 / jnp.where(cov[2, 2] > 0, cov[2, 2], jnp.inf))
    well_posed = ~tone_cancels_offset(coef[1], final[:, 1] @ final[:, 1], y @ y) & (inflation <= MAX_VARIANCE_INFLATION)
    return FitResult(depth, coef[0] * scale, amp, sigma, converged, num_steps, jnp.sum(res**2) * scale**2, well_posed)
