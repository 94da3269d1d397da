"""Stage 1: per-CCD hybrid phase errors, gains and offsets (gauge CCD 1) from each pixel's
sufficient statistics, and the carrier phase common to all pixels."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from ..runtime import async_filter_jit
from .common import GAIN_SIGMA_LIMIT, PHASE_SIGMA_LIMIT_RAD, covariance, least_squares_moments


@jax.jit
def pixel_statistics(frames: Float[Array, "4 N P"], regressor) -> dict:
    """Means, the Gram matrix of (Re s̃, Im s̃), cross products with the centred ports, and the
    per-(CCD, pixel) noise variance left by an unconstrained regression (s̃ = s − mean s)."""
    n = frames.shape[1]
    mean_v = jnp.mean(frames, axis=1)  # (4, P)
    v = frames - mean_v[:, None]
    s_mean = jnp.mean(regressor, axis=0)  # (P,) complex
    s = regressor - s_mean
    basis = jnp.stack([jnp.real(s), jnp.imag(s)], axis=-1)  # (N, P, 2)
    gram = jnp.einsum("npi,npj->pij", basis, basis)
    cross = jnp.einsum("knp,npi->kpi", v, basis)  # (4, P, 2)
    evals, evecs = jnp.linalg.eigh(gram)
    keep = evals > 1e-9 * jnp.max(evals, axis=1, keepdims=True)
    inv = jnp.where(keep, 1 / jnp.where(keep, evals, 1.0), 0.0)
    proj = jnp.einsum("pij,kpi->kpj", evecs, cross)  # components along the eigenvectors
    explained = jnp.sum(proj**2 * inv[None], axis=-1)
    rank = jnp.sum(keep, axis=1)
    rss = jnp.sum(v * v, axis=1) - explained
    noise_var = jnp.maximum(rss, 1e-30) / (n - 1 - rank)[None, :]
    return {
        "mean_dn": mean_v,
        "s_mean": s_mean,
        "evals": evals,
        "evecs": evecs,
        "keep": keep,
        "cross": cross,
        "noise_var": noise_var,
        "rank": rank,
    }


def _hybrid_matrices(nominal_rad, params):
    theta = nominal_rad + jnp.concatenate([jnp.zeros(1), params[:3]])
    gain = jnp.exp(jnp.concatenate([jnp.zeros(1), params[3:]]))
    c, s = jnp.cos(theta), jnp.sin(theta)
    # β_k = H_k @ (Re z, Im z): coefficients of (Re s, Im s) in port k
    return 0.5 * gain[:, None, None] * jnp.stack([jnp.stack([c, -s], -1), jnp.stack([-s, -c], -1)], -2)


hybrid_matrices = async_filter_jit(_hybrid_matrices)


def _hybrid_design(nominal_rad, params, stats):
    """Whitened per-pixel design M_p (8×2) and data y_p (8,) of the projected problem."""
    h = _hybrid_matrices(nominal_rad, params)  # (4, 2, 2)
    keep = stats["keep"]
    root = jnp.where(keep, jnp.sqrt(jnp.where(keep, stats["evals"], 1.0)), 0.0)  # (P, 2)
    iroot = jnp.where(keep, 1 / jnp.where(keep, root, 1.0), 0.0)
    vt = jnp.swapaxes(stats["evecs"], 1, 2)  # rows: eigenvectors
    sigma = jnp.sqrt(stats["noise_var"])  # (4, P)
    a = jnp.einsum("pij,kjl->kpil", vt, h) * root[None, :, :, None] / sigma[:, :, None, None]
    y = jnp.einsum("pij,kpj->kpi", vt, stats["cross"]) * iroot[None] / sigma[:, :, None]
    p = a.shape[1]
    return jnp.transpose(a, (1, 0, 2, 3)).reshape(p, 8, 2), jnp.transpose(y, (1, 0, 2)).reshape(p, 8)


def _solve_2x2(m, y):
    mtm = jnp.einsum("pai,paj->pij", m, m)
    mtm = mtm + (1e-12 * jnp.trace(mtm, axis1=1, axis2=2) + 1e-300)[:, None, None] * jnp.eye(2)
    return jnp.linalg.solve(mtm, jnp.einsum("pai,pa->pi", m, y)[..., None])[..., 0]


def hybrid_residuals(params, args):
    """Whitened residuals (8 a pixel), zero for the pixels weighted out (`used` 0)."""
    nominal_rad, stats, used = args
    m, y = _hybrid_design(nominal_rad, params, stats)
    z = _solve_2x2(m, y)
    return ((jnp.einsum("paj,pj->pa", m, z) - y) * used[:, None]).reshape(-1)


@async_filter_jit
def hybrid_fit_moments(params, args, *, clusters=None):
    """`least_squares_moments` of the hybrid fit: one compiled program, kept on disk."""
    return least_squares_moments(hybrid_residuals, params, args, clusters)


@async_filter_jit
def pixel_amplitudes(nominal_rad, params, stats):
    """Fitted complex tone amplitudes z_p (carrier phase included) at given hybrid parameters."""
    m, y = _hybrid_design(nominal_rad, params, stats)
    ab = _solve_2x2(m, y)
    return ab[:, 0] + 1j * ab[:, 1]


@jax.jit
def common_carrier(frames, hybrid_h, amplitudes, tone, noise_var, step_var_rad2=0.01):
    """Carrier phasor u[m] common to all pixels (turbulence in the shared path, or a phase
    ramp on the reference arm), from centred ports:
    ṽ_kp[m] = Re(c_kp[m]·u[m]) − mean_m Re(c_kp·u),  c_kp[m] = h_k·z_p·S_p[m].

    Centring (needed: uncalibrated common mode leaks into the ports) leaves u undetermined
    along κ/S[m] when the pixels share one depth, so a random-walk prior with step variance
    `step_var_rad2` per frame (Σ|u[m+1] − u[m]|²/step_var added to the χ²) makes it a MAP
    estimate, which also smooths u where the tones pass through zero. Solved by conjugate
    gradients (u as real pairs, per-frame 2×2 blocks as preconditioner). A pixel of zero
    amplitude (one `fit_hybrid` did not use) adds nothing."""
    # c_kp[m] = h_k·zs[m, p]: every product over the 4 ports and P pixels reduces to sums over
    # the pixels of per-pixel port sums, so one CG step costs O(N·P), not several passes over
    # (4, N, P) arrays. With W = diag(1/σ²) constant over the frames, centring C commutes with
    # it: the normal operator Aᵀ C W C A u = D[m]·u[m] − (1/N)·Σ_p conj(zs[m, p])·g_p(u)
    n = frames.shape[1]
    weight = 1 / noise_var  # (4, P)
    zs = amplitudes[None, :] * tone  # (N, P)
    power = jnp.abs(zs) ** 2 @ jnp.sum(weight * jnp.abs(hybrid_h[:, None]) ** 2, 0)  # Σ w|c|²
    square = zs**2 @ jnp.sum(weight * hybrid_h[:, None] ** 2, 0)  # Σ w c²
    # per-frame 2×2 blocks of Σ w·(Re c, −Im c)ᵀ(Re c, −Im c)
    a00, a01, a11 = 0.5 * (power + jnp.real(square)), -0.5 * jnp.imag(square), 0.5 * (power - jnp.real(square))
    weighted_conj_h = weight * jnp.conj(hybrid_h)[:, None]  # (4, P)
    zs_conj = jnp.conj(zs)

    def normal(u):  # (N, 2) → Aᵀ C W C A u
        uc = u[:, 0] + 1j * u[:, 1]
        ports = jnp.real(hybrid_h[:, None] * (uc @ zs)[None, :])  # Σ_m Re(c_kp[m]·u[m]), (4, P)
        mean_term = zs_conj @ jnp.sum(weighted_conj_h * ports, 0) / n  # (N,)
        block = jnp.stack([a00 * u[:, 0] + a01 * u[:, 1], a01 * u[:, 0] + a11 * u[:, 1]], -1)
        return block - jnp.stack([jnp.real(mean_term), jnp.imag(mean_term)], -1)

    def roughness(u):  # Dᵀ D u for the first difference D
        d = jnp.diff(u, axis=0)
        zero = jnp.zeros((1, 2), u.dtype)
        return (jnp.concatenate([zero, d]) - jnp.concatenate([d, zero])) / step_var_rad2

    b00, b11 = a00 + 2 / step_var_rad2, a11 + 2 / step_var_rad2
    det = b00 * b11 - a01 * a01

    def precondition(x):
        return jnp.stack([(b11 * x[:, 0] - a01 * x[:, 1]) / det, (b00 * x[:, 1] - a01 * x[:, 0]) / det], -1)

    centred = frames - jnp.mean(frames, axis=1, keepdims=True)
    rhs_c = jnp.sum(zs_conj * jnp.einsum("kp,knp->np", weighted_conj_h, centred), 1)  # Aᵀ W C x
    rhs = jnp.stack([jnp.real(rhs_c), jnp.imag(rhs_c)], -1)
    sol, _ = jax.scipy.sparse.linalg.cg(
        lambda u: normal(u) + roughness(u), rhs, x0=precondition(rhs), M=precondition, tol=1e-10, maxiter=500
    )
    return sol[:, 0] + 1j * sol[:, 1]


@dataclasses.dataclass
class HybridFit:
    phases_rad: np.ndarray
    relative_gains: np.ndarray
    phase_sigma_rad: np.ndarray
    gain_sigma: np.ndarray
    chi2_per_dof: float
    amplitudes: np.ndarray  # z_p
    identified: bool
    note: str | None
    params: np.ndarray
    nominal_rad: np.ndarray
    used: np.ndarray  # (P,) bool: the pixels fitted (amplitudes are zero elsewhere)


HYBRID_MAX_STEPS = 200


@async_filter_jit
def solve_hybrid(y0, args):
    """The hybrid's Levenberg–Marquardt fit from `y0` → (parameters, converged, steps): one
    compiled program, loaded from the executable cache in later processes without tracing
    optimistix's solver again."""
    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12)
    sol = optx.least_squares(hybrid_residuals, solver, y0, args=args, max_steps=HYBRID_MAX_STEPS, throw=False)
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


def fit_hybrid(stats: dict, nominal_rad, start=None, used=None) -> HybridFit:
    """Stage 1: per-CCD phase errors and gains (gauge CCD 1) from the pixel statistics of the
    pixels `used` (P,) bool (all by default; the others are weighted out, not dropped, so that
    the programs keep the arrays' shapes whatever the count)."""
    nominal = np.asarray(nominal_rad, np.float64)
    rank = np.asarray(stats["rank"])
    used = np.ones(rank.shape, bool) if used is None else np.asarray(used, bool)
    args = (nominal, stats, used.astype(np.float64))
    y0 = np.zeros(6) if start is None else np.asarray(start, np.float64)
    params, succeeded, steps = solve_hybrid(y0, args)
    params, succeeded = np.asarray(params), bool(succeeded)
    dof = int(4 * rank[used].sum() - 2 * used.sum() - 6)
    cov, chi2, singular = covariance(hybrid_fit_moments, params, args, dof)
    sig = np.sqrt(np.maximum(np.diag(cov), 0))
    z = np.where(used, np.asarray(pixel_amplitudes(nominal, params, stats)), 0.0)
    note = None
    singular = singular or not np.all(np.isfinite(sig))
    phase_sig, gain_sig = sig[:3], np.exp(np.asarray(params[3:])) * sig[3:]
    identified = (
        not singular and succeeded and np.all(phase_sig < PHASE_SIGMA_LIMIT_RAD) and np.all(gain_sig < GAIN_SIGMA_LIMIT)
    )
    if not identified:
        why = (
            "the information matrix is singular"
            if singular
            else f"σ would be {np.degrees(np.max(phase_sig)):.2g}° and {np.max(gain_sig):.2g}"
        )
        note = (
            f"phases and gains are not identifiable from these data ({why}): the four ports fix only the "
            "plane the hybrid spans; the ellipse's shape in it needs the carrier phase to vary within "
            "pixels over the sweep (air turbulence, or a slow phase ramp on the reference arm), "
            "which these data do not show"
        )
        precise = np.all(phase_sig < PHASE_SIGMA_LIMIT_RAD) and np.all(gain_sig < GAIN_SIGMA_LIMIT)
        if not succeeded and precise and not singular:
            note = (
                f"the fit did not converge (Levenberg–Marquardt stopped after {int(steps)} of {HYBRID_MAX_STEPS} steps)"
            )
    theta = np.asarray(nominal) + np.concatenate([[0.0], np.asarray(params[:3])])
    gains = np.exp(np.concatenate([[0.0], np.asarray(params[3:])]))
    return HybridFit(
        theta,
        gains,
        np.concatenate([[0.0], phase_sig]),
        np.concatenate([[0.0], gain_sig]),
        chi2 / max(dof, 1),
        z,
        bool(identified),
        note,
        np.asarray(params),
        np.asarray(nominal),
        used,
    )


def fit_offsets(port_means_dn, stats: dict, fit: HybridFit, dark_dn: np.ndarray | None):
    """Offsets o_k (DN) from the per-pixel means (4, P) of the pixels the fit used, after removing
    each port's modelled tone mean.

    Only o_k − g_k·o_1 is observable; o_1 comes from the dark frame when given, else the
    gauge o_1 = 0 (the I/Q combination cancels any offset ∝ g_k, so depth is unaffected)."""
    h = np.asarray(hybrid_matrices(np.asarray(fit.nominal_rad, np.float64), np.asarray(fit.params, np.float64)))
    z = np.stack([fit.amplitudes.real, fit.amplitudes.imag], -1)[fit.used]  # (P used, 2)
    s_mean = np.asarray(stats["s_mean"])[fit.used]
    s_vec = np.stack([s_mean.real, s_mean.imag], -1)  # (P, 2)
    tone_mean = np.einsum("kij,pj,pi->kp", h, z, s_vec)
    level = np.asarray(port_means_dn)[:, fit.used] - tone_mean  # o_k + g_k·L_p
    g = fit.relative_gains
    per_pixel = level - g[:, None] * level[:1]  # o_k − g_k·o_1
    n = per_pixel.shape[1]
    offsets = np.median(per_pixel, axis=1)
    spread = 1.4826 * np.median(np.abs(per_pixel - offsets[:, None]), axis=1)
    sigma = np.sqrt((1.2533 * spread) ** 2 / n + (fit.gain_sigma * np.median(level[0])) ** 2)
    if dark_dn is not None:
        o1 = float(np.median(dark_dn[0]))
        return offsets + g * o1, sigma, "o_1 from the dark frame; o_k − g_k·o_1 from the capture"
    return (
        offsets,
        sigma,
        (
            "gauge o_1 = 0: only o_k − g_k·o_1 is observable without a dark frame, "
            "and the I/Q combination cancels the rest"
        ),
    )
