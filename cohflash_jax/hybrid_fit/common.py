"""What every calibration stage shares: a fitted value with its uncertainty (`Estimate`), the
covariance of a least-squares fit, the model's tone, and the limits of identifiability."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..modulator import MZM, beat_spectrum
from ..runtime import async_filter_jit

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


def tone_sequences(frequencies_hz, delay_s: Float[Array, " P"], modulator: MZM) -> Float[Array, "N P"]:
    """S(2π f_m τ_p) with the modulator's (frequency-dependent) sideband weights, float64.
    One compiled program whatever the modulator's values (they are its inputs, not constants)."""
    return _tone_program(
        np.asarray(frequencies_hz, np.float64), np.asarray(delay_s, np.float64), modulator_inputs(modulator)
    )


def modulator_inputs(modulator: MZM) -> MZM:
    """`modulator` with its values as float64 arrays, so that a program taking it is compiled
    once for any value (a Python float would be compiled into it)."""
    return jax.tree.map(lambda v: np.asarray(v, np.float64), modulator)


@async_filter_jit
def _tone_program(f, delay_s, modulator: MZM):
    w = modulator.weights(f)  # (N, K)
    cycles = f[:, None] * delay_s[None, :]
    psi = 2 * jnp.pi * (cycles - jnp.floor(cycles))
    return beat_spectrum(psi, w[:, None, :])


def least_squares_moments(residual_fn, params, args, clusters: int | None):
    """What `covariance` needs of a least-squares fit at `params`, in one program: χ², JᵀJ
    and, with `clusters`, each cluster's score Σ J·r (see `covariance`)."""
    res, jac = residual_fn(params, args), jax.jacfwd(residual_fn)(params, args)
    scores = None if clusters is None else jnp.sum((jac * res[:, None]).reshape(clusters, -1, jac.shape[1]), axis=1)
    return jnp.sum(res**2), jac.T @ jac, scores


def covariance(moments_program, params, args, dof, clusters: int | None = None):
    """Covariance of least-squares parameters from the Jacobian at the optimum,
    (JᵀJ)⁻¹·χ²/dof (residuals whitened by the measured noise), with χ² and whether JᵀJ is
    singular (an unidentifiable direction: its variances are then ∞). `moments_program`:
    the fit's `least_squares_moments` as a compiled program of (params, args, clusters).

    `clusters`: the residuals come in that many consecutive groups whose errors may be
    correlated within a group (the frames of a calibration: a common carrier-drift error moves
    every pixel of a frame alike, which the per-pixel noise model does not count). Each
    variance is then the larger of the model's and the cluster-robust (sandwich) one,
    (JᵀJ)⁻¹ (Σ_g s_g s_gᵀ) (JᵀJ)⁻¹ with s_g the group's score Σ J·r, which holds for any
    correlation within a group given many groups (the correlations are kept, the standard
    deviations scaled)."""
    chi2, jtj, scores = moments_program(params, args, clusters=clusters)
    chi2, jtj = float(chi2), np.asarray(jtj)
    evals = np.linalg.eigvalsh(jtj)
    singular = evals[0] <= 1e-12 * max(evals[-1], 1e-300)
    inverse = np.linalg.pinv(jtj)
    cov = inverse * max(chi2 / max(dof, 1), 1e-300)
    if clusters is not None and clusters > jtj.shape[0]:
        scores = np.asarray(scores)
        robust = inverse @ (scores.T @ scores) @ inverse * clusters / (clusters - jtj.shape[0])
        inflate = np.sqrt(np.maximum(np.diag(robust) / np.maximum(np.diag(cov), 1e-300), 1.0))
        cov = cov * inflate[:, None] * inflate[None, :]
    if singular:
        cov = cov + np.diag(np.where(np.diag(jtj) <= 0, np.inf, 0.0))
    return cov, chi2, singular
