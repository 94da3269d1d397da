"""Stage 2: the modulator's index β and its roll-off from carrier-aligned sequences, with
the hybrid calibrated; the bias θ_b stays fixed."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..modulator import MZM, beat_spectrum, sideband_weights
from ..runtime import async_filter_jit
from .common import Estimate, covariance, least_squares_moments, modulator_inputs


def _modulator_x(x0, u, f, f_max):
    return x0 / jnp.sqrt(jnp.maximum(1.0 + u * (f / f_max) ** 2, 1e-6))


def modulator_residuals(free, args):
    """Whitened time-domain residuals of r_p[m] − A_p·S − b_p with (A_p, b_p) projected out.
    `free`: the fitted parameters (a dict); the others come fixed in `args`."""
    f, r, noise_sigma, delay0, bias, order, fixed, frame_weight = args
    params = {**fixed, **free}
    f_max = f[-1]
    x = _modulator_x(jnp.exp(params["log_x0"]), params["rolloff_u"], f, f_max)
    w = sideband_weights(x, bias, order)  # (N, K)
    tau = delay0 + 2e-3 * params["depth_mm"] / C
    cycles = f[:, None] * tau[None, :]
    s = beat_spectrum(2 * jnp.pi * (cycles - jnp.floor(cycles)), w[:, None, :])  # (N, P)
    m = frame_weight[:, None]  # 1 for a frame in the fit, 0 for one left out (the jackknife)
    g00, g01, g11 = jnp.sum(m * s * s, 0), jnp.sum(m * s, 0), jnp.sum(m * jnp.ones_like(s), 0)
    r0, r1 = jnp.sum(m * s * r, 0), jnp.sum(m * r, 0)
    det = g00 * g11 - g01 * g01 + 1e-300
    amp, off = (g11 * r0 - g01 * r1) / det, (g00 * r1 - g01 * r0) / det
    return (m * (r - amp * s - off) / noise_sigma[None, :]).reshape(-1)


# the fitted parameters, in the order of the covariance's rows
FREE_PARAMETERS = ("log_x0", "rolloff_u")


def flat_modulator_residuals(flat, args):
    """`modulator_residuals` of the free parameters as a vector (`FREE_PARAMETERS`' order)."""
    return modulator_residuals(dict(zip(FREE_PARAMETERS, flat)), args)


@async_filter_jit
def modulator_fit_moments(flat, args, *, clusters=None):
    """`least_squares_moments` of the modulator fit: one compiled program, kept on disk."""
    return least_squares_moments(flat_modulator_residuals, flat, args, clusters)


@dataclasses.dataclass
class ModulatorFit:
    modulation_index: Estimate
    rolloff_3db_hz: Estimate
    bias_rad: Estimate
    chi2_per_dof: float
    pixels: int
    modulator: MZM


JACKKNIFE_RTOL = 1e-6  # the leave-a-block-out fits' relative tolerance (the full fit: 1e-9)


@async_filter_jit
def solve_modulator(y0: dict, args: tuple, *, rtol: float, max_steps: int):
    """The modulator's Levenberg–Marquardt fit from `y0` → (parameters, converged, steps)
    (absolute tolerance rtol/10): one compiled program per tolerance and shapes, loaded from
    the executable cache in later processes without tracing optimistix's solver again."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=0.1 * rtol)
    sol = optx.least_squares(modulator_residuals, solver, y0, args=args, max_steps=max_steps, throw=False)
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


def block_jackknife_sigma(value: dict, args: tuple, blocks: int) -> dict:
    """σ of each fitted parameter from the delete-a-block jackknife over `blocks` contiguous
    runs of frames, √((G−1)/G · Σ_g (θ_(g) − θ̄)²): it holds whatever the errors' correlation
    within a run, where the model's σ assumes white residuals. Under turbulence the residual
    error of the common drift estimate is slow and acts on every pixel's amplitude alike, as a
    roll-off would (measured: roll-off pulls of std 1.26–1.35 with the model's σ)."""
    n = args[1].shape[0]
    edges = np.linspace(0, n, blocks + 1).astype(int)
    # each leave-a-block-out fit starts at the full fit, a fraction of the parameters' spread
    # away from its own optimum, and needs that optimum only to a small fraction of the spread
    # (the jackknife σ itself is uncertain by ~1/√(2G)): two Gauss–Newton steps reach it to
    # ~1e-4 of σ (Levenberg–Marquardt took ~9), checked by their quadratic convergence; a fit
    # that does not converge so is refitted by Levenberg–Marquardt from the full fit
    flat = np.array([value[k] for k in FREE_PARAMETERS], np.float64)
    start = {k: np.asarray(v, np.float64) for k, v in value.items()}  # arrays: one program for any start
    fits = []
    for a, b in zip(edges[:-1], edges[1:]):
        weight = np.ones(n)
        weight[a:b] = 0.0
        block_args = args[:-1] + (weight,)
        theta, moves = (np.asarray(x) for x in jackknife_gauss_newton(flat, block_args, steps=JACKKNIFE_NEWTON_STEPS))
        if np.all(np.isfinite(theta)) and moves[-1] <= JACKKNIFE_NEWTON_CONVERGED * max(moves[0], 1e-300):
            fits.append(dict(zip(FREE_PARAMETERS, map(float, theta))))
        else:
            fitted, _, _ = solve_modulator(start, block_args, rtol=JACKKNIFE_RTOL, max_steps=50)
            fits.append({k: float(v) for k, v in fitted.items()})
    out = {}
    for k in value:
        theta = np.array([f[k] for f in fits])
        out[k] = math.sqrt((blocks - 1) / blocks * np.sum((theta - theta.mean()) ** 2))
    return out


# Gauss–Newton steps of each leave-a-block-out fit from the full fit; a fit whose last step is
# not below this fraction of its first (not converging quadratically) is refitted by `solve_modulator`
JACKKNIFE_NEWTON_STEPS = 2
JACKKNIFE_NEWTON_CONVERGED = 0.05


@async_filter_jit
def jackknife_gauss_newton(flat, args, *, steps: int):
    """A leave-a-block-out fit (the block's frames weighted out in `args`) as `steps`
    Gauss–Newton steps from the full fit's parameters `flat` (`FREE_PARAMETERS`' order) →
    (parameters, each step's size)."""

    def step(theta, _):
        res = flat_modulator_residuals(theta, args)
        jac = jax.jacfwd(flat_modulator_residuals)(theta, args)
        move = jnp.linalg.solve(jac.T @ jac, jac.T @ res)
        return theta - move, jnp.sqrt(jnp.sum(move**2))

    return jax.lax.scan(step, flat, None, length=steps)


def fit_modulator(
    frequencies_hz,
    r: np.ndarray,
    noise_var: np.ndarray,
    delay0_s: np.ndarray,
    start: MZM,
    jackknife_blocks: int | None = None,
) -> ModulatorFit:
    """Stage 2: β and its roll-off from carrier-aligned sequences r (N, P); θ_b stays fixed.

    (Fitting θ_b as well was tried and dropped: β and θ_b trade off through the 2nd-harmonic
    ratio, and the joint fit came out 7σ from the true bias on a simulated capture — a
    confident wrong number. The bias is a setting of the modulator's bias controller.)"""
    f = np.asarray(frequencies_hz, np.float64)
    f_max = float(f[-1])
    order = int(start.max_order)
    p = r.shape[1]
    x0 = 0.5 * float(start.modulation_index)
    params0 = {"depth_mm": np.zeros(p), "log_x0": np.asarray(math.log(max(x0, 1e-3))), "rolloff_u": np.asarray(0.0)}
    # the depths stay at the reconstruction's (errors of ~10 µm shift the tone's phase by
    # ~2e-3 rad at 6 GHz: nothing the amplitudes or harmonic ratios notice), so only two
    # global unknowns remain and the Jacobian is cheap
    y0 = {k: params0[k] for k in FREE_PARAMETERS}
    fixed = {k: v for k, v in params0.items() if k not in FREE_PARAMETERS}
    args = (
        f,
        np.asarray(r, np.float64),
        np.sqrt(np.asarray(noise_var, np.float64)),
        np.asarray(delay0_s, np.float64),
        float(start.bias_rad),
        order,
        fixed,
        np.ones(r.shape[0]),
    )
    val, converged, _ = solve_modulator(y0, args, rtol=1e-9, max_steps=200)
    converged = bool(converged)
    val = {k: float(v) for k, v in val.items()}
    flat = np.array([val[k] for k in FREE_PARAMETERS])
    dof = r.size - flat.size - 2 * p
    # clustered by frame: a residual error of the common carrier drift moves every pixel of a
    # frame alike. A floor only: under turbulence the error is also correlated across frames,
    # which this misses (roll-off pull std 1.26–1.35 with it); the block jackknife below counts it
    cov, chi2, singular = covariance(modulator_fit_moments, flat, args, dof, clusters=r.shape[0])
    sig = dict(zip(FREE_PARAMETERS, np.sqrt(np.maximum(np.diag(cov), 0))))
    if jackknife_blocks:
        spread = block_jackknife_sigma(val, args, jackknife_blocks)
        sig = {k: max(sig[k], spread[k]) for k in sig}
    x0_fit = math.exp(val["log_x0"])
    x0_sig = x0_fit * float(sig["log_x0"])
    beta = Estimate(2 * x0_fit, 2 * x0_sig)
    if not converged or singular or not x0_sig < 0.1 * x0_fit:
        beta = Estimate(
            None,
            None,
            "modulation index not identifiable from these data (harmonics too weak "
            "for their ratio to fix β, or the fit did not converge)",
        )
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
    modulator = MZM(
        beta.value if beta.value is not None else float(start.modulation_index),
        bias.value if bias.value is not None else float(start.bias_rad),
        roll.value if roll.value is not None else float(start.rolloff_3db_hz),
        max_order=order,
    )
    return ModulatorFit(beta, roll, bias, chi2 / max(dof, 1), p, modulator)


# Newton steps of `exact_model_depths_m` and the largest step (mm): the window fit's error is
# tens of µm, its basin millimetres wide
EXACT_DEPTH_STEPS = 6
EXACT_DEPTH_MAX_STEP_MM = 0.1


@async_filter_jit
def exact_model_depths_program(f, r, depth_m, delay_offset_s, modulator: MZM):
    """`exact_model_depths_m` as one compiled program, kept on disk (the modulator's values
    and the delay offset are its inputs: `modulator_inputs`)."""
    weights = modulator.weights(f)

    def cost(offset_mm, r_p, depth_p):
        cycles = f * (delay_offset_s + 2 * (depth_p + 1e-3 * offset_mm) / C)
        s = beat_spectrum(2 * jnp.pi * (cycles - jnp.floor(cycles)), weights)
        s_c, r_c = s - jnp.mean(s), r_p - jnp.mean(r_p)  # the offset projected out
        return r_c @ r_c - (s_c @ r_c) ** 2 / jnp.maximum(s_c @ s_c, 1e-300)  # and the amplitude

    def pixel(r_p, depth_p):
        grad = jax.grad(cost)
        curvature = jax.grad(grad)

        def step(offset_mm, _):
            g, h = grad(offset_mm, r_p, depth_p), curvature(offset_mm, r_p, depth_p)
            move = jnp.where(h > 0, -g / jnp.where(h > 0, h, 1.0), -jnp.sign(g) * EXACT_DEPTH_MAX_STEP_MM)
            return offset_mm + jnp.clip(move, -EXACT_DEPTH_MAX_STEP_MM, EXACT_DEPTH_MAX_STEP_MM), None

        # a start batched like the depth: vmap's scan rule then traces the step once
        offset_mm, _ = jax.lax.scan(step, 0.0 * depth_p, None, length=EXACT_DEPTH_STEPS)
        return depth_p + 1e-3 * offset_mm

    return jax.vmap(pixel, in_axes=(1, 0))(r, depth_m)


def exact_model_depths_m(frequencies_hz, r: np.ndarray, depth_m: np.ndarray, modulator: MZM, delay_offset_s=0.0):
    """Each pixel's depth refined by the time-domain fit of its carrier-aligned sequence r (N, P)
    with the sideband weights at every frequency, from `depth_m` (P,) of the reconstruction.

    The reconstruction's window fit takes the weights at the sweep's mean frequency; with a
    roll-off the fundamental tapers over the band, and that approximation moves depths by
    ±15 µm (depending on depth; measured noiseless at 3000 frames with an 8 GHz roll-off). Per
    pixel that is a tenth of σ, but τ_sys averages hundreds of pixels: the mean moved 0.3σ.
    `delay_offset_s`: the delay the depths do not include (the described τ_sys)."""
    out = exact_model_depths_program(
        np.asarray(frequencies_hz, np.float64),
        np.asarray(r, np.float64),
        np.asarray(depth_m, np.float64),
        np.asarray(delay_offset_s, np.float64),
        modulator_inputs(modulator),
    )
    return np.asarray(out)
