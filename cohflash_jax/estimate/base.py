"""The estimator interface: what every depth estimator takes and returns.

In the style of optimistix's solvers: an abstract base (`AbstractDepthEstimator`) with one
abstract method, concrete final classes (one file each, registered in `estimate.registry`),
each an `eqx.Module` holding its settings and per-configuration tables, each returning one
typed per-pixel result (`DepthEstimate`). The coarse stage (`estimate.coarse`) runs first and
is shared: a DFT-peak estimator reads its answer off it, the ML estimators start from it.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ..geometry import SweepGeometry
from .window_model import UniformModel


class DepthEstimate(eqx.Module):
    """One estimator's answer for a batch of pixels; every field (P,).

    `amplitude` is the tone amplitude A (DN of I/Q, ≥ 0: the 2-D intensity image); `sigma_m`
    the CRLB-predicted standard deviation at the fitted values; `coarse_depth_m` the coarse
    stage's depth it started from; `converged` whether an iterative fit converged (always
    True for a direct read-out); `fit_ok` whether the answer is finite and well posed;
    `fit_chi2` the reduced χ² of a fit (−1 where the estimator computes none); `ambiguous`
    where another depth the model predicts fits the frames nearly as well (None: not tested)."""

    depth_m: Float[Array, " P"]
    amplitude: Float[Array, " P"]
    sigma_m: Float[Array, " P"]
    coarse_depth_m: Float[Array, " P"]
    converged: Bool[Array, " P"]
    fit_ok: Bool[Array, " P"]
    fit_chi2: Float[Array, " P"]
    ambiguous: Bool[Array, " P"] | None = None


class FitResult(eqx.Module):
    """A model fit's raw result (per pixel, or per pixel and candidate), before it becomes a
    `DepthEstimate`: the depth, the projected-out offset c and signed amplitude A, σ, the
    solver's convergence and steps, the residual cost, and whether the fit is well posed
    (`fisher.well_posed`)."""

    depth_m: Float[Array, "..."]
    offset: Float[Array, "..."]
    amplitude: Float[Array, "..."]
    sigma_depth_m: Float[Array, "..."]
    converged: Array
    num_steps: Array
    cost: Float[Array, "..."]
    well_posed: Array

    def finite_and_well_posed(self):
        """Finite depth, σ and amplitude, and a well-posed fit: the answer may be used."""
        finite = jnp.isfinite(self.depth_m) & jnp.isfinite(self.sigma_depth_m) & jnp.isfinite(self.amplitude)
        return finite & self.well_posed

    def to_estimate(self, coarse_depth_m, fit_chi2) -> DepthEstimate:
        """The fit as an estimator's answer (amplitude ≥ 0), started from `coarse_depth_m`."""
        return DepthEstimate(
            self.depth_m,
            jnp.abs(self.amplitude),
            self.sigma_depth_m,
            coarse_depth_m,
            self.converged,
            self.finite_and_well_posed(),
            fit_chi2,
        )


# The noise variance a reduced χ² divides by is floored at this fraction of the mean square
# of the data: noiseless frames (tests, simulations) would otherwise give 0/0
CHI2_NOISE_FLOOR = 1e-9


def reduced_chi2(cost, noise_var, mean_square, dof):
    """Residual sum of squares `cost` per degree of freedom in units of the noise variance
    (floored at `CHI2_NOISE_FLOOR` × the data's `mean_square`)."""
    return cost / (jnp.maximum(noise_var, jnp.maximum(CHI2_NOISE_FLOOR * mean_square, 1e-30)) * dof)


# A rival depth is told apart from the fitted one only where the frames favour the fit by at
# least this Δχ² (residual sums in units of the noise variance): a 5σ preference
AMBIGUITY_MIN_DELTA_CHI2 = 25.0


def best_of(fits: FitResult, noise_var, min_separation_m):
    """Per pixel, the fit with the lowest residual among K started from rival depths (every
    field of `fits` (K, P)), whether the choice is ambiguous — another fit that ended more than
    `min_separation_m` away has a residual within `AMBIGUITY_MIN_DELTA_CHI2` noise variances —
    and the index of the one taken (P,)."""
    usable = fits.finite_and_well_posed() & jnp.isfinite(fits.cost)
    cost = jnp.where(usable, fits.cost, jnp.inf)
    best = jnp.argmin(cost, axis=0)
    take = lambda a: jnp.take_along_axis(a, best[None], axis=0)[0]
    chosen = jax.tree.map(take, fits)
    delta = (cost - take(cost)[None]) / jnp.maximum(noise_var, 1e-30)[None]
    apart = jnp.abs(fits.depth_m - chosen.depth_m[None]) > min_separation_m
    ambiguous = jnp.any(usable & apart & (delta < AMBIGUITY_MIN_DELTA_CHI2), axis=0)
    return chosen, ambiguous, best


@dataclasses.dataclass(frozen=True)
class EstimatorSetup:
    """What an estimator is built from, once per configuration: the sweep's schedule, its
    geometry, the phase-locked tone model (sideband weights, τ_sys), and the fit's limits."""

    frequencies_hz: np.ndarray
    geometry: SweepGeometry
    model: UniformModel
    window_bins: int = 17
    max_steps: int = 16


class AbstractDepthEstimator(eqx.Module):
    """Depth per pixel from its carrier-aligned sequence and the shared coarse stage.

    `refines`: the estimator may move beyond the coarse stage's bin (a model fit). Its depths
    are then reflected into a mirror-symmetric sweep's window, and a pixel whose fit ran more
    than two bins from the coarse depth is flagged out of range. `edge_bins`: within this many
    grid steps of either end of the depth window the estimator is biased by the tone's mirror
    image (at −τ, and at P − τ beyond the far end); pixels there are flagged `edge_bias`."""

    refines: ClassVar[bool] = False
    edge_bins: ClassVar[float] = 0.0
    # fit only the pixels where the detection test found a tone (`estimate_detected`): where
    # the fit is most of a short sweep's cost, and a pixel with no tone is flagged not_detected
    # whatever the fit says
    detected_only: ClassVar[bool] = False

    @property
    def description(self) -> str:
        """What the estimator adds to the coarse stage, in words ("" for a read-out)."""
        return ""

    @classmethod
    @abc.abstractmethod
    def build(cls, setup: EstimatorSetup) -> AbstractDepthEstimator:
        """The estimator for a configuration (its tables are computed here, once)."""

    @abc.abstractmethod
    def estimate(self, stage, coarse, sequence: Float[Array, "N P"], noise_var: Float[Array, " P"]) -> DepthEstimate:
        """Depth of each pixel: `stage` the coarse stage (`estimate.coarse`), `coarse` its
        result for these pixels, `sequence` the carrier-aligned real sequences, `noise_var`
        the per-pixel noise variance measured in the quadrature channel."""


# `estimate_detected` fits the detected pixels alone where they are at most this share of a
# batch of at least this many pixels (the 10 Hz mode's full-frame sub-tiles: 2560 px read from a
# file, 8192 px in memory); a smaller batch (a region of interest, a test's capture) runs the
# plain fit and compiles it once, not twice
DETECTED_FEW_SHARE = 8
DETECTED_ONLY_MIN_PIXELS = 2048


def estimate_detected(
    estimator: AbstractDepthEstimator, stage, coarse, sequence: Float[Array, "N P"], noise_var, detected
) -> DepthEstimate:
    """`estimator.estimate`, fitting the detected pixels alone where they are at most an
    eighth of a batch of `DETECTED_ONLY_MIN_PIXELS` or more (else every pixel, as `estimate`
    does); the others then take the coarse stage's answer: its interpolated depth, tone
    amplitude and frequency-only σ, no χ² (−1). Their status is not_detected whatever a fit
    would say (`policy.classify`), so their fit need not run: where few pixels hold a tone (a
    short sweep near its threshold) the fit costs an eighth. A pixel's fit depends on its own
    data only, not on its batch. Both ways are in the program; it takes one."""
    p = sequence.shape[1]
    if p < DETECTED_ONLY_MIN_PIXELS:
        return estimator.estimate(stage, coarse, sequence, noise_var)
    group = max(1, -(-p // DETECTED_FEW_SHARE))

    def fit(idx):
        picked = jax.tree.map(lambda a: a[idx], coarse)  # every field of the coarse result leads with pixels
        return estimator.estimate(stage, picked, sequence[:, idx], noise_var[idx])

    def few():
        from .peak import peak_estimate  # the read-outs' answer; `peak` builds on this module

        # `p` marks an empty slot: its fit runs on a clamped index, its writes are dropped
        slots = jnp.nonzero(detected, size=group, fill_value=p)[0]
        fitted = fit(jnp.minimum(slots, p - 1))
        amplitude = stage.tone_amplitude(coarse)
        read_out = peak_estimate(
            stage.depth(coarse, interpolate=True), stage.frequency_only_sigma(amplitude, noise_var), amplitude
        )
        if fitted.ambiguous is not None:  # a read-out tests no rival depths
            read_out = dataclasses.replace(read_out, ambiguous=jnp.zeros(p, bool))
        scatter = lambda whole, part: whole.astype(part.dtype).at[slots].set(part, mode="drop")
        return jax.tree.map(scatter, read_out, fitted)

    return jax.lax.cond(jnp.sum(detected) <= group, few, lambda: estimator.estimate(stage, coarse, sequence, noise_var))
