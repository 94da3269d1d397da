"""Quinn's first estimator (IEEE Trans. Signal Process. 42, 1264 (1994)): the DFT peak's
offset from the ratios of its complex neighbours to it.

For a tone at bin k + δ in the unwindowed DFT, X[k−1]/X[k] = δ/(1 + δ) and X[k+1]/X[k] =
−δ/(1 − δ); each ratio's real part α gives an offset, α₁/(1 − α₁) from below and −α₂/(1 − α₂)
from above, and Quinn takes the one from above where both are positive, else the one from
below. Uniform sweeps; a non-uniform schedule's periodogram has no complex bins, and there it
reads the interpolated periodogram peak.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup
from .peak import MIRROR_EDGE_BINS, peak_estimate, peak_neighbours, peak_sigma_m


class QuinnPeak(AbstractDepthEstimator):
    """The DFT peak interpolated by Quinn's first estimator. σ: the frequency-only CRLB times
    `noise_factor`, with an rms bias of `bias_steps` bin (the real tone's mirror image and
    sideband aliases near the peak)."""

    noise_factor: float = eqx.field(static=True, default=1.4)
    bias_steps: float = eqx.field(static=True, default=0.006)
    edge_bins: ClassVar[float] = MIRROR_EDGE_BINS

    @classmethod
    def build(cls, setup: EstimatorSetup) -> QuinnPeak:
        return cls()

    @property
    def description(self) -> str:
        return "the DFT peak's offset from its complex neighbours (Quinn)"

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        amplitude = stage.tone_amplitude(coarse)
        spec = coarse.spectrum
        if spec is None:
            depth = stage.depth(coarse, interpolate=True)
        else:
            n = sequence.shape[0]
            below, centre, above, peak = peak_neighbours(spec, coarse.peak)
            safe = jnp.where(jnp.abs(centre) > 0, centre, 1.0)
            alpha1, alpha2 = jnp.real(below / safe), jnp.real(above / safe)
            delta1, delta2 = alpha1 / (1 - alpha1), -alpha2 / (1 - alpha2)
            delta = jnp.where((delta1 > 0) & (delta2 > 0), delta2, delta1)
            delta = jnp.clip(jnp.where(jnp.isfinite(delta), delta, 0.0), -0.5, 0.5)
            depth = stage.geometry.depth_from_folded((peak + delta) / n)
        sigma = peak_sigma_m(stage, amplitude, noise_var, self.noise_factor, self.bias_steps)
        return peak_estimate(depth, sigma, amplitude)
