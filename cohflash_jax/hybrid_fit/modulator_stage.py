"""Stage 2: the modulator's index β and its roll-off from carrier-aligned sequences, with
the hybrid calibrated; the bias θ_b stays fixed."""

from __future__ import annotations

import dataclasses
import math

import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..modulator import MZM, beat_spectrum, sideband_weights
from .common import Estimate, covariance


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


def fit_modulator(
    frequencies_hz, r: np.ndarray, noise_var: np.ndarray, delay0_s: np.ndarray, start: MZM
) -> ModulatorFit:
    """Stage 2: β and its roll-off from carrier-aligned sequences r (N, P); θ_b stays fixed.

    (Fitting θ_b as well was tried and dropped: β and θ_b trade off through the 2nd-harmonic
    ratio, and the joint fit came out 7σ from the true bias on a simulated capture — a
    confident wrong number. The bias is a setting of the modulator's bias controller.)"""
    f = jnp.asarray(frequencies_hz, jnp.float64)
    f_max = float(f[-1])
    order = int(start.max_order)
    p = r.shape[1]
    x0 = 0.5 * float(start.modulation_index)
    params0 = {"depth_mm": jnp.zeros(p), "log_x0": jnp.asarray(math.log(max(x0, 1e-3))), "rolloff_u": jnp.asarray(0.0)}
    # the depths stay at the reconstruction's (errors of ~10 µm shift the tone's phase by
    # ~2e-3 rad at 6 GHz: nothing the amplitudes or harmonic ratios notice), so only two
    # global unknowns remain and the Jacobian is cheap
    free = ("log_x0", "rolloff_u")
    y0 = {k: params0[k] for k in free}
    fixed = {k: v for k, v in params0.items() if k not in free}
    args = (
        f,
        jnp.asarray(r, jnp.float64),
        jnp.sqrt(jnp.asarray(noise_var, jnp.float64)),
        jnp.asarray(delay0_s, jnp.float64),
        float(start.bias_rad),
        order,
        fixed,
    )
    solver = optx.LevenbergMarquardt(rtol=1e-9, atol=1e-10)
    sol = optx.least_squares(modulator_residuals, solver, y0, args=args, max_steps=200, throw=False)
    flat, unravel = jax.flatten_util.ravel_pytree(sol.value)
    dof = r.size - flat.size - 2 * p
    cov, chi2, singular, _ = covariance(_flat_modulator_residuals, flat, (unravel, args), dof)
    sig = unravel(jnp.asarray(np.sqrt(np.maximum(np.diag(cov), 0))))
    val = sol.value
    x0_fit, x0_sig = float(jnp.exp(val["log_x0"])), float(jnp.exp(val["log_x0"]) * sig["log_x0"])
    converged = sol.result == optx.RESULTS.successful
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
