"""Calibration of the hybrid (per-CCD phase, gain, offset), the modulator (β, roll-off) and
τ_sys from a stepped-frequency capture of a calibration target, with optimistix.

Model of CCD k at pixel p and frame m (DN; DESIGN.md §1, gauge CCD 1: θ error 0, g = 1):

    v_k[m] = o_k + g_k·L_p + ½·g_k·Re(e^{iθ_k}·z_p·s_p[m]),
    s_p[m] = S(2π f_m τ_p; β(f_m))·e^{iφ̃_p[m]}

with L_p the common level (reference, echo intensity, dark), z_p the pixel's complex tone
amplitude (carrier phase included) and φ̃_p the tracked carrier drift (zero when static).

Stage 1, hybrid: given s_p (from a reconstruction), each pixel's centred port sequences are
linear in (Re z_p, Im z_p), so z_p is projected out (variable projection) and only six global
unknowns remain (three phase errors, three log gains). The fit needs only each pixel's
sufficient statistics — the 2×2 Gram matrix of (Re s, Im s) and the 4×2 cross products —
so it costs nothing per frame once those are formed. A static pixel (Im s ≡ 0) carries its
line's direction in the four-port space; pixels with different carrier phases (speckle, a
target tilted by more than a wavelength, carrier drift) make phases and gains identifiable.
Offsets follow from the per-pixel means: only o_k − g_k·o_1 is observable (a common term
∝ g_k is cancelled by the I/Q combination), so the gauge is o_1 = 0 unless a dark capture
gives o_1.

Stage 2, modulator: with the calibrated hybrid, each pixel's carrier-aligned real sequence
r_p[m] = A_p·S(2π f_m τ_p; x(f_m)) + b_p is fitted in the time domain for per-pixel depth
(A_p, b_p projected out) and the global x_0 = β/2 and roll-off u = (f_max/f_3dB)², where
x(f) = x_0/√(1 + u·(f/f_max)²). The harmonic ratios identify β, the fundamental's taper
over the band identifies the roll-off; the bias θ_b stays fixed (from the capture), since β
and θ_b are nearly degenerate through the 2nd-harmonic ratio.

Stage 3, τ_sys: depths reconstructed with the calibration and τ_sys = 0, against a known
target distance.

Uncertainties: from the Jacobian at the optimum, cov = (JᵀJ)⁻¹·χ²/dof, with residuals
whitened by each pixel's (and CCD's) measured noise. A parameter whose uncertainty exceeds
what the data can support is reported as not identified, with the reason.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

from .capture import Capture, CaptureError
from .constants import SPEED_OF_LIGHT_M_PER_S as C
from .estimate.iq import _moving_average, align_carrier_static, derotate, iq_from_frames
from .hybrid import Hybrid
from .modulator import MZM, beat_spectrum, sideband_weights

# A parameter is "not identified" when its 1σ exceeds these (the data then say nothing useful)
PHASE_SIGMA_LIMIT_RAD = math.radians(3.0)
GAIN_SIGMA_LIMIT = 0.05
MIN_FRAMES = 64
MIN_PIXELS = 8


@dataclasses.dataclass
class Estimate:
    """A fitted value with its 1σ uncertainty, or `value=None` and the reason it is not identified."""

    value: float | None
    sigma: float | None = None
    note: str | None = None

    def as_dict(self):
        return {"value": self.value, "sigma": self.sigma, **({"note": self.note} if self.note else {})}


# ----------------------------------------------------------------------------- the tone
def tone_sequences(frequencies_hz, delay_s: Float[Array, " P"], modulator: MZM) -> Float[Array, "N P"]:
    """S(2π f_m τ_p) with the modulator's (frequency-dependent) sideband weights, float64."""
    f = jnp.asarray(frequencies_hz, jnp.float64)
    w = modulator.weights(f)  # (N, K)
    cycles = f[:, None] * jnp.asarray(delay_s, jnp.float64)[None, :]
    psi = 2 * jnp.pi * (cycles - jnp.floor(cycles))
    return beat_spectrum(psi, w[:, None, :])


# ----------------------------------------------------------------------------- stage 1: hybrid
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
    return {"mean_dn": mean_v, "s_mean": s_mean, "evals": evals, "evecs": evecs, "keep": keep,
            "cross": cross, "noise_var": noise_var, "rank": rank}


def _hybrid_matrices(nominal_rad, params):
    theta = nominal_rad + jnp.concatenate([jnp.zeros(1), params[:3]])
    gain = jnp.exp(jnp.concatenate([jnp.zeros(1), params[3:]]))
    c, s = jnp.cos(theta), jnp.sin(theta)
    # β_k = H_k @ (Re z, Im z): coefficients of (Re s, Im s) in port k
    return 0.5 * gain[:, None, None] * jnp.stack([jnp.stack([c, -s], -1), jnp.stack([-s, -c], -1)], -2)


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
    nominal_rad, stats = args
    m, y = _hybrid_design(nominal_rad, params, stats)
    z = _solve_2x2(m, y)
    return (jnp.einsum("paj,pj->pa", m, z) - y).reshape(-1)


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
    gradients (u as real pairs, per-frame 2×2 blocks as preconditioner)."""
    c = hybrid_h[:, None, None] * amplitudes[None, None, :] * tone[None]  # (4, N, P)
    wgt = (1 / noise_var)[:, None, :]
    centred = frames - jnp.mean(frames, axis=1, keepdims=True)
    cr, ci = jnp.real(c), jnp.imag(c)

    def model(u):  # u (N, 2) → centred Re(c·u)
        m = cr * u[None, :, 0, None] - ci * u[None, :, 1, None]
        return m - jnp.mean(m, axis=1, keepdims=True)

    def adjoint(x):  # (4, N, P) → (N, 2)
        x = wgt * (x - jnp.mean(x, axis=1, keepdims=True))
        return jnp.stack([jnp.sum(x * cr, (0, 2)), -jnp.sum(x * ci, (0, 2))], -1)

    def roughness(u):  # Dᵀ D u for the first difference D
        d = jnp.diff(u, axis=0)
        zero = jnp.zeros((1, 2), u.dtype)
        return (jnp.concatenate([zero, d]) - jnp.concatenate([d, zero])) / step_var_rad2

    a00, a01, a11 = jnp.sum(wgt * cr * cr, (0, 2)), -jnp.sum(wgt * cr * ci, (0, 2)), jnp.sum(wgt * ci * ci, (0, 2))
    a00, a11 = a00 + 2 / step_var_rad2, a11 + 2 / step_var_rad2
    det = a00 * a11 - a01 * a01

    def precondition(x):
        return jnp.stack([(a11 * x[:, 0] - a01 * x[:, 1]) / det, (a00 * x[:, 1] - a01 * x[:, 0]) / det], -1)

    rhs = adjoint(centred)
    sol, _ = jax.scipy.sparse.linalg.cg(lambda u: adjoint(model(u)) + roughness(u), rhs, x0=precondition(rhs),
                                        M=precondition, tol=1e-10, maxiter=500)
    return sol[:, 0] + 1j * sol[:, 1]


@eqx.filter_jit
def _residuals_and_jacobian(residual_fn, params, args):
    return residual_fn(params, args), jax.jacfwd(residual_fn)(params, args)


def _covariance(residual_fn, params, args, dof):
    res, jac = _residuals_and_jacobian(residual_fn, params, args)
    chi2 = float(jnp.sum(res**2))
    jtj = np.asarray(jac.T @ jac)
    evals = np.linalg.eigvalsh(jtj)
    singular = evals[0] <= 1e-12 * max(evals[-1], 1e-300)
    cov = np.linalg.pinv(jtj) * max(chi2 / max(dof, 1), 1e-300)
    if singular:
        cov = cov + np.diag(np.where(np.diag(jtj) <= 0, np.inf, 0.0))
    return cov, chi2, singular, np.asarray(jac)


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


def fit_hybrid(stats: dict, nominal_rad, start=None) -> HybridFit:
    """Stage 1: per-CCD phase errors and gains (gauge CCD 1) from the pixel statistics."""
    nominal = jnp.asarray(nominal_rad, jnp.float64)
    args = (nominal, stats)
    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12)
    y0 = jnp.zeros(6) if start is None else jnp.asarray(start, jnp.float64)
    sol = optx.least_squares(hybrid_residuals, solver, y0, args=args, max_steps=200, throw=False)
    params = sol.value
    rank = np.asarray(stats["rank"])
    dof = int(4 * rank.sum() - 2 * rank.size - 6)
    cov, chi2, singular, _ = _covariance(hybrid_residuals, params, args, dof)
    sig = np.sqrt(np.maximum(np.diag(cov), 0))
    z = np.asarray(pixel_amplitudes(nominal, params, stats))
    note = None
    singular = singular or not np.all(np.isfinite(sig))
    phase_sig, gain_sig = sig[:3], np.exp(np.asarray(params[3:])) * sig[3:]
    identified = (not singular and sol.result == optx.RESULTS.successful
                  and np.all(phase_sig < PHASE_SIGMA_LIMIT_RAD) and np.all(gain_sig < GAIN_SIGMA_LIMIT))
    if not identified:
        why = ("the information matrix is singular" if singular else
               f"σ would be {np.degrees(np.max(phase_sig)):.2g}° and {np.max(gain_sig):.2g}")
        note = (f"phases and gains are not identifiable from these data ({why}): the four ports fix only the "
                "plane the hybrid spans; the ellipse's shape in it needs the carrier phase to vary within "
                "pixels over the sweep (air turbulence, or a slow phase ramp on the reference arm), "
                "which these data do not show")
        precise = np.all(phase_sig < PHASE_SIGMA_LIMIT_RAD) and np.all(gain_sig < GAIN_SIGMA_LIMIT)
        if sol.result != optx.RESULTS.successful and precise and not singular:
            note = f"the fit did not converge ({sol.result})"
    theta = np.asarray(nominal) + np.concatenate([[0.0], np.asarray(params[:3])])
    gains = np.exp(np.concatenate([[0.0], np.asarray(params[3:])]))
    return HybridFit(theta, gains, np.concatenate([[0.0], phase_sig]), np.concatenate([[0.0], gain_sig]),
                     chi2 / max(dof, 1), z, bool(identified), note, np.asarray(params),
                     np.asarray(nominal))


def fit_offsets(port_means_dn, stats: dict, fit: HybridFit, dark_dn: np.ndarray | None):
    """Offsets o_k (DN) from the per-pixel means after removing each port's modelled tone mean.

    Only o_k − g_k·o_1 is observable; o_1 comes from the dark frame when given, else the
    gauge o_1 = 0 (the I/Q combination cancels any offset ∝ g_k, so depth is unaffected)."""
    h = np.asarray(_hybrid_matrices(jnp.asarray(fit.nominal_rad), jnp.asarray(fit.params)))
    z = np.stack([fit.amplitudes.real, fit.amplitudes.imag], -1)  # (P, 2)
    s_mean = np.asarray(stats["s_mean"])
    s_vec = np.stack([s_mean.real, s_mean.imag], -1)  # (P, 2)
    tone_mean = np.einsum("kij,pj,pi->kp", h, z, s_vec)
    level = np.asarray(port_means_dn) - tone_mean  # o_k + g_k·L_p
    g = fit.relative_gains
    per_pixel = level - g[:, None] * level[:1]  # o_k − g_k·o_1
    n = per_pixel.shape[1]
    offsets = np.median(per_pixel, axis=1)
    spread = 1.4826 * np.median(np.abs(per_pixel - offsets[:, None]), axis=1)
    sigma = np.sqrt((1.2533 * spread) ** 2 / n + (fit.gain_sigma * np.median(level[0])) ** 2)
    if dark_dn is not None:
        o1 = float(np.median(dark_dn[0]))
        return offsets + g * o1, sigma, "o_1 from the dark frame; o_k − g_k·o_1 from the capture"
    return offsets, sigma, ("gauge o_1 = 0: only o_k − g_k·o_1 is observable without a dark frame, "
                            "and the I/Q combination cancels the rest")


# ----------------------------------------------------------------------------- stage 2: modulator
def _modulator_x(x0, u, f, f_max):
    return x0 / jnp.sqrt(jnp.maximum(1.0 + u * (f / f_max) ** 2, 1e-6))


def modulator_residuals(free, args):
    """Whitened time-domain residuals of r_p[m] − A_p·S − b_p with (A_p, b_p) projected out.
    `free`: the fitted parameters (a dict); the others come fixed in `args`."""
    f, r, noise_sigma, delay0, bias, order, fixed = args
    params = {**fixed, **free}
    f_max = f[-1]
    x = _modulator_x(jnp.exp(params["log_x0"]), params["rolloff_u"], f, f_max)
    w = sideband_weights(x, bias, order)  # (N, K)
    tau = delay0 + 2e-3 * params["depth_mm"] / C
    cycles = f[:, None] * tau[None, :]
    s = beat_spectrum(2 * jnp.pi * (cycles - jnp.floor(cycles)), w[:, None, :])  # (N, P)
    one = jnp.ones_like(s)
    g00, g01, g11 = jnp.sum(s * s, 0), jnp.sum(s, 0), jnp.sum(one, 0)
    r0, r1 = jnp.sum(s * r, 0), jnp.sum(r, 0)
    det = g00 * g11 - g01 * g01 + 1e-300
    amp, off = (g11 * r0 - g01 * r1) / det, (g00 * r1 - g01 * r0) / det
    return ((r - amp * s - off) / noise_sigma[None, :]).reshape(-1)


def _flat_modulator_residuals(flat, args):
    unravel, inner = args
    return modulator_residuals(unravel(flat), inner)


@dataclasses.dataclass
class ModulatorFit:
    modulation_index: Estimate
    rolloff_3db_hz: Estimate
    bias_rad: Estimate
    chi2_per_dof: float
    pixels: int
    modulator: MZM


def fit_modulator(frequencies_hz, r: np.ndarray, noise_var: np.ndarray, delay0_s: np.ndarray,
                  start: MZM) -> ModulatorFit:
    """Stage 2: β and its roll-off from carrier-aligned sequences r (N, P); θ_b stays fixed.

    (Fitting θ_b as well was tried and dropped: β and θ_b trade off through the 2nd-harmonic
    ratio, and the joint fit came out 7σ from the true bias on a simulated capture — a
    confident wrong number. The bias is a setting of the modulator's bias controller.)"""
    f = jnp.asarray(frequencies_hz, jnp.float64)
    f_max = float(f[-1])
    order = int(start.max_order)
    p = r.shape[1]
    x0 = 0.5 * float(start.modulation_index)
    params0 = {"depth_mm": jnp.zeros(p), "log_x0": jnp.asarray(math.log(max(x0, 1e-3))),
               "rolloff_u": jnp.asarray(0.0)}
    # the depths stay at the reconstruction's (errors of ~10 µm shift the tone's phase by
    # ~2e-3 rad at 6 GHz: nothing the amplitudes or harmonic ratios notice), so only two
    # global unknowns remain and the Jacobian is cheap
    free = ("log_x0", "rolloff_u")
    y0 = {k: params0[k] for k in free}
    fixed = {k: v for k, v in params0.items() if k not in free}
    args = (f, jnp.asarray(r, jnp.float64), jnp.sqrt(jnp.asarray(noise_var, jnp.float64)),
            jnp.asarray(delay0_s, jnp.float64), float(start.bias_rad), order, fixed)
    solver = optx.LevenbergMarquardt(rtol=1e-9, atol=1e-10)
    sol = optx.least_squares(modulator_residuals, solver, y0, args=args, max_steps=200, throw=False)
    flat, unravel = jax.flatten_util.ravel_pytree(sol.value)
    dof = r.size - flat.size - 2 * p
    cov, chi2, singular, _ = _covariance(_flat_modulator_residuals, flat, (unravel, args), dof)
    sig = unravel(jnp.asarray(np.sqrt(np.maximum(np.diag(cov), 0))))
    val = sol.value
    x0_fit, x0_sig = float(jnp.exp(val["log_x0"])), float(jnp.exp(val["log_x0"]) * sig["log_x0"])
    converged = sol.result == optx.RESULTS.successful
    beta = Estimate(2 * x0_fit, 2 * x0_sig)
    if not converged or singular or not x0_sig < 0.1 * x0_fit:
        beta = Estimate(None, None, "modulation index not identifiable from these data (harmonics too weak "
                                    "for their ratio to fix β, or the fit did not converge)")
    u, u_sig = float(val["rolloff_u"]), float(sig["rolloff_u"])
    if beta.value is not None and u > 3 * u_sig and u > 0:
        f3 = f_max / math.sqrt(u)
        roll = Estimate(f3, 0.5 * f3 * u_sig / u)
    elif beta.value is not None and np.isfinite(u_sig):
        bound = f_max / math.sqrt(max(u, 0) + 3 * u_sig) if (max(u, 0) + 3 * u_sig) > 0 else float("inf")
        roll = Estimate(float("inf"), None, f"no roll-off detected (u = {u:.3g} ± {u_sig:.2g}); f_3dB > {bound:.3g} Hz")
    else:
        roll = Estimate(None, None, "roll-off not identifiable from these data")
    bias = Estimate(float(start.bias_rad), None, "fixed (the capture's bias_rad attribute, or the default π/4)")
    modulator = MZM(beta.value if beta.value is not None else float(start.modulation_index),
                    bias.value if bias.value is not None else float(start.bias_rad),
                    roll.value if roll.value is not None else float(start.rolloff_3db_hz), max_order=order)
    return ModulatorFit(beta, roll, bias, chi2 / max(dof, 1), p, modulator)


# ----------------------------------------------------------------------------- the whole calibration
def initial_common_drift(i, q, window_frames: int = 101) -> tuple[np.ndarray, str]:
    """First estimate of a carrier drift common to the pixels, without knowing their depths.

    The moving average of Z = I + iQ keeps the mean term z_p·w_0·e^{iφ[m]} (the tone averages
    out); minus its time mean, it is (nearly) rank one over pixels, so its leading left singular
    vector is κ·(e^{iφ[m]} − c): a circle, fitted algebraically (Kåsa) to recover φ. Leakage of
    common mode through an uncalibrated hybrid is constant and drops out with the mean.
    Returns (φ (N,) zero-mean, description); φ = 0 when the data show no drift."""
    z = np.asarray(i) + 1j * np.asarray(q)
    n, p = z.shape
    half = window_frames // 2
    if n <= 4 * window_frames:
        return np.zeros(n), "too few frames to look for a carrier drift"
    average = np.asarray(_moving_average(jnp.asarray(z), window_frames))
    # a pure-noise N×P matrix of entry variance v has a top singular value ≈ √v(√N + √P); the
    # high-passed variance (tone included) over the window bounds v from above
    noise_var = np.mean(np.abs(z - average) ** 2) / window_frames
    m = average[half:n - half]  # the shrinking windows at the ends let the tone through
    m = m - m.mean(axis=0)
    u, sv, _ = np.linalg.svd(m, full_matrices=False)
    floor = math.sqrt(noise_var) * (math.sqrt(m.shape[0]) + math.sqrt(p))
    if sv.size < 2 or not (sv[0] > 3 * floor and sv[0] > 3 * sv[1]):
        return np.zeros(n), "no common carrier drift detected"
    lead = u[:, 0]
    x, y = lead.real, lead.imag
    design = np.stack([2 * x, 2 * y, np.ones_like(x)], 1)
    (cx, cy, k), *_ = np.linalg.lstsq(design, x * x + y * y, rcond=None)
    centre = cx + 1j * cy
    radius = math.sqrt(max(k + abs(centre) ** 2, 0.0))
    spread = np.std(np.abs(lead - centre) - radius) / max(radius, 1e-300)
    if not (radius > 0 and spread < 0.3):
        return np.zeros(z.shape[0]), f"carrier drift not resolved (circle fit spread {spread:.2f}): treated as static"
    phi = np.unwrap(np.angle(lead - centre))
    phi = np.concatenate([np.full(half, phi[0]), phi, np.full(n - half - phi.size, phi[-1])])
    return phi - phi.mean(), f"common carrier drift found (rms {np.std(phi):.2f} rad)"


def _select_pixels(capture: Capture, max_pixels: int, snr_map: np.ndarray, status_map: np.ndarray):
    # dc_edge pixels are usable: through an uncalibrated hybrid the untracked turbulent carrier
    # makes the survey's mean term wander near DC, which the calibration's drift model removes
    from .reconstruct import DC_EDGE

    ok = ((status_map == 0) | (status_map == DC_EDGE)) & np.isfinite(snr_map)
    if int(ok.sum()) < MIN_PIXELS:
        counts = {int(c): int((status_map == c).sum()) for c in np.unique(status_map)}
        raise CaptureError(f"{capture.path}: only {int(ok.sum())} pixels are usable for calibration (need ≥ "
                           f"{MIN_PIXELS}); fit status counts {counts} (1 low SNR, 5 saturated, 6 dead, 4 NaN)")
    idx = np.flatnonzero(ok.ravel())
    idx = idx[np.argsort(-snr_map.ravel()[idx])][:max_pixels]
    return np.sort(idx)


def _gather(capture: Capture, flat_idx: np.ndarray) -> np.ndarray:
    """Frames (4, N, P) float64 of the chosen pixels, read row by row."""
    n, h, w = capture.shape
    rows, cols = np.divmod(flat_idx, w)
    out = np.empty((4, n, flat_idx.size), np.float64)
    for r in np.unique(rows):
        sel = rows == r
        tile = capture.read_tile(slice(int(r), int(r) + 1))[:, :, 0, :]
        out[:, :, sel] = tile[:, :, cols[sel]]
    return out


def read_mean_frame(path) -> np.ndarray:
    """Mean frame (4, H, W) of a dark or flat capture (its `dark` dataset if frames are absent)."""
    with Capture(path) as cap:
        n, h, w = cap.shape
        total = np.zeros((4, h, w), np.float64)
        for m0 in range(0, n, 256):
            block = cap.frames[:, m0:m0 + 256].astype(np.float64)
            if not np.all(np.isfinite(block)):
                raise CaptureError(f"{path}: frames contain NaN or inf")
            total += block.sum(axis=1)
        return total / n


def calibrate_hybrid(capture_path, *, dark_path=None, flat_path=None, known_distance_m: float | None = None,
                     max_pixels: int = 1024, modulator_pixels: int = 48,
                     iterations: int = 2, inner_iterations: int = 3, min_depth_m: float = 1.0,
                     progress: bool = True) -> dict:
    """The whole calibration → a `cohflash-calibration` document (dict) plus per-pixel maps.

    Returns {"document": JSON-able dict, "maps": {name: array} (may be empty)}."""
    from .reconstruct import ReconstructOptions, reconstruct_array, reconstruct_capture, modulator_from_attrs

    if known_distance_m is not None and not (math.isfinite(known_distance_m) and known_distance_m > 0):
        raise ValueError(f"known distance must be a positive number of metres, got {known_distance_m}")
    if max_pixels < 1 or modulator_pixels < 1:
        raise ValueError(f"max_pixels and modulator_pixels must be ≥ 1, got {max_pixels} and {modulator_pixels}")
    with Capture(capture_path) as cap:
        n, h, w = cap.shape
        if n < MIN_FRAMES:
            raise CaptureError(f"{capture_path}: {n} frames are too few to calibrate (need ≥ {MIN_FRAMES}: the tone's "
                               "harmonics and the roll-off need a resolved spectrum)")
        freqs = cap.frequencies_hz
        nominal = np.asarray(cap.hybrid_phases_rad, np.float64)
        modulator = modulator_from_attrs(cap.attrs)
        dark = read_mean_frame(dark_path) if dark_path is not None else None
        if dark is not None and dark.shape != (4, h, w):
            raise CaptureError(f"{dark_path}: dark frame has shape {dark.shape}, the capture needs (4, {h}, {w})")
        options = ReconstructOptions(method="interp", progress=progress)
        survey, _ = reconstruct_capture(cap, options)
        idx = _select_pixels(cap, max_pixels, survey["snr"], survey["fit_status"])
        frames = _gather(cap, idx)
    p = idx.size
    hybrid = Hybrid(tuple(nominal))
    # remove each port's mean: common mode leaking through the uncalibrated hybrid is constant,
    # but once the carrier drift is derotated it would wander near DC and swamp the tone
    port_means = frames.mean(axis=1)  # (4, P) DN, for the offsets
    frames = frames - port_means[:, None]
    data = jnp.asarray(frames)
    iq_w, iq_b = hybrid.iq_matrix_dn(1.0)
    drift, drift_note = initial_common_drift(*iq_from_frames(data, iq_w, iq_b))
    drifting = bool(np.any(drift != 0))  # without a drift u ≡ 1: fitting it would only fit noise
    u = jnp.asarray(np.exp(1j * drift))
    params = None
    ml = ReconstructOptions(method="ml", progress=False, dtype="float64", min_depth_m=min_depth_m)

    def reconstruct_selected(hyb, mod, carrier):
        hyb = Hybrid(hyb.phases_rad, hyb.relative_gains, (0.0,) * 4)  # the frames are centred
        out = reconstruct_array(frames.reshape(4, n, 1, p), freqs, ml, hybrid=hyb, modulator=mod,
                                carrier_phase_rad=carrier)
        return out["depth_m"][0], out["fit_status"][0]

    for _ in range(iterations):
        depth, status = reconstruct_selected(hybrid, modulator, drift)
        good = np.flatnonzero(status == 0)
        if good.size < MIN_PIXELS:
            raise CaptureError(f"{capture_path}: only {good.size} of {p} pixels reconstruct validly: "
                               "too little signal to calibrate")
        tone = tone_sequences(freqs, 2 * depth / C, modulator)
        sub, tone_g = data[:, :, good], tone[:, good]
        for _ in range(inner_iterations):  # alternate: hybrid given the drift, drift given the hybrid
            stats = pixel_statistics(sub, tone_g * u[:, None])
            fit = fit_hybrid(stats, nominal, params)
            params = fit.params
            hybrid_h = jnp.asarray(0.5 * fit.relative_gains * np.exp(1j * fit.phases_rad))
            if drifting:
                u = common_carrier(sub, hybrid_h, jnp.asarray(fit.amplitudes), tone_g, stats["noise_var"])
        if drifting:
            drift = np.unwrap(np.angle(np.asarray(u)))
            drift = drift - np.mean(drift)
        # stage 2 on the strongest pixels, with the current hybrid and drift. The time-domain
        # fit needs the uncentred I/Q (a mean removed before derotation would wander after it,
        # and pass for a roll-off); a calibrated hybrid cancels the common mode, so no leakage.
        if fit.identified:
            offsets = fit_offsets(port_means[:, good], stats, fit, None)[0]
            hybrid = Hybrid(tuple(fit.phases_rad), tuple(fit.relative_gains), tuple(offsets))
            source = data + jnp.asarray(port_means)[:, None]
        else:
            source = data
        iq_w, iq_b = hybrid.iq_matrix_dn(1.0)
        i, q = iq_from_frames(source, iq_w, iq_b)
        i, q = derotate(i, q, jnp.asarray(drift)[:, None])
        r, noise_var, _ = align_carrier_static(i, q)
        amp = np.zeros(p)
        amp[good] = np.abs(fit.amplitudes)
        strongest = good[np.argsort(-amp[good])][:modulator_pixels]
        mod_fit = fit_modulator(freqs, np.asarray(r)[:, strongest], np.asarray(noise_var)[strongest],
                                2 * depth[strongest] / C, modulator)
        modulator = mod_fit.modulator
    offsets, offset_sigma, offset_note = fit_offsets(port_means[:, good], stats, fit, dark)
    if fit.identified:
        hybrid = Hybrid(tuple(fit.phases_rad), tuple(fit.relative_gains), tuple(offsets))
    depth, status = reconstruct_selected(hybrid, modulator, drift)
    ok = status == 0
    if known_distance_m is None:
        delay_est = Estimate(None, None, "not identifiable without --known-distance-m (τ_sys and the target "
                                         "distance enter the data only as their sum)")
    elif ok.sum() < MIN_PIXELS:
        delay_est = Estimate(None, None, f"only {int(ok.sum())} pixels reconstructed validly")
    else:
        d = depth[ok]
        delay_est = Estimate(float(2 * (np.mean(d) - known_distance_m) / C),
                             float(2 * np.std(d, ddof=1) / math.sqrt(d.size) / C))
    maps = {}
    if dark is not None:
        maps["offset_map_dn"] = dark.astype(np.float32)
    if flat_path is not None:
        if dark is None:
            raise ValueError("--flat needs --dark: the flat field is measured above the dark level")
        flat = read_mean_frame(flat_path)
        if flat.shape != (4, h, w):
            raise CaptureError(f"{flat_path}: flat frame has shape {flat.shape}, the capture needs (4, {h}, {w})")
        above = flat - dark
        if np.any(above[0] <= 0):
            raise CaptureError(f"{flat_path}: the flat field is not above the dark level on CCD 1 "
                               f"({int((above[0] <= 0).sum())} pixels)")
        maps["gain_map"] = (above / (above[:1] * fit.relative_gains[:, None, None])).astype(np.float32)
    hyb_note = fit.note
    doc = {
        "format": "cohflash-calibration", "format_version": 1,
        "gauge": "CCD 1: phase error 0, gain 1" + ("; offsets: " + offset_note),
        "hybrid": {
            "phases_rad": fit.phases_rad.tolist() if fit.identified else None,
            "phases_sigma_rad": fit.phase_sigma_rad.tolist() if fit.identified else None,
            "relative_gains": fit.relative_gains.tolist() if fit.identified else None,
            "relative_gains_sigma": fit.gain_sigma.tolist() if fit.identified else None,
            "offsets_dn": offsets.tolist() if fit.identified else None,
            "offsets_sigma_dn": offset_sigma.tolist() if fit.identified else None,
            **({"note": hyb_note} if hyb_note else {}),
        },
        "modulator": {
            "modulation_index": mod_fit.modulation_index.as_dict(),
            "rolloff_3db_hz": mod_fit.rolloff_3db_hz.as_dict(),
            "bias_rad": mod_fit.bias_rad.as_dict(),
            "max_order": int(modulator.max_order),
            "sideband_weights": {name: np.asarray(modulator.weights(fq)).tolist()
                                 for name, fq in (("start", freqs[0]), ("centre", np.mean(freqs)), ("end", freqs[-1]))},
        },
        "system_delay_s": delay_est.as_dict(),
        "fit": {
            "pixels": int(p), "frames": int(n), "modulator_pixels": mod_fit.pixels,
            "hybrid_chi2_per_dof": fit.chi2_per_dof, "modulator_chi2_per_dof": mod_fit.chi2_per_dof,
            "carrier_drift_rms_rad": float(np.std(drift)), "carrier_drift": drift_note, "known_distance_m": known_distance_m,
            "depth_spread_m": float(np.std(depth[ok])) if ok.any() else None,
        },
        "maps": sorted(maps),
    }
    strongest = int(good[np.argmax(np.abs(fit.amplitudes))]) if fit.amplitudes.size else 0
    calibrated = Hybrid(hybrid.phases_rad, hybrid.relative_gains, (0.0,) * 4)
    views = {}
    for name, hyb in (("nominal", Hybrid(tuple(nominal))), ("calibrated", calibrated)):
        w_iq, b_iq = hyb.iq_matrix_dn(1.0)
        i, q = iq_from_frames(data[:, :, strongest:strongest + 1], w_iq, b_iq)
        views[name] = np.asarray(i[:, 0]) + 1j * np.asarray(q[:, 0])
    diagnostics = {"frequencies_hz": np.asarray(freqs), "drift_rad": np.asarray(drift), "iq": views,
                   "modulator": modulator, "pixel": divmod(int(idx[strongest]), w)}
    return {"document": doc, "maps": maps, "diagnostics": diagnostics}


def save_hybrid_report(path, result: dict):
    """Report figure: I/Q of the strongest pixel with the nominal and the calibrated hybrid,
    the carrier drift, and the fitted sideband weights over the sweep."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .fileio import save_figure

    diag = result["diagnostics"]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5), constrained_layout=True)
    ax = axes[0]
    for name, colour in (("nominal", "tab:red"), ("calibrated", "tab:blue")):
        z = diag["iq"][name] - np.mean(diag["iq"][name])
        z = z * np.exp(-1j * diag["drift_rad"])
        ax.plot(z.real, z.imag, ".", ms=1.5, alpha=0.4, color=colour, label=f"{name} hybrid")
    ax.set_aspect("equal")
    ax.set(title=f"I/Q of pixel {diag['pixel']} (drift removed, centred)", xlabel="I (DN)", ylabel="Q (DN)")
    ax.legend(markerscale=6)
    ax = axes[1]
    ax.plot(diag["drift_rad"])
    ax.set(title="common carrier drift", xlabel="frame", ylabel="phase (rad)")
    ax = axes[2]
    f = diag["frequencies_hz"]
    w = np.asarray(diag["modulator"].weights(f))
    for n in range(1, w.shape[1]):
        ax.semilogy(f / 1e9, w[:, n], label=f"|c_{n}|²")
    doc = result["document"]["modulator"]
    ax.set(title=f"fitted sideband weights (β = {doc['modulation_index']['value']}, "
           f"f_3dB = {doc['rolloff_3db_hz']['value']})", xlabel="frequency (GHz)", ylabel="weight")
    ax.title.set_fontsize(8)
    ax.legend()
    return save_figure(fig, path)
