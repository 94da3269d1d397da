"""The zero-padded DFT's peak: the frame sequence's DFT evaluated on a grid `pad` times finer
than the bins (a DFT of the sequence padded with zeros to pad·N), read at its strongest point
within a bin of the coarse peak.

Unwindowed, so its maximum converges on the periodogram's, the frequency-only ML estimate, as
the grid refines; what is left is the grid's quantisation, uniform within ±½ of 1/pad bin
(rms 1/(pad·√12)). The cost is a pad·N-point FFT a pixel. Uniform sweeps; a non-uniform
schedule's periodogram is read at its interpolated peak.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup
from .peak import MIRROR_EDGE_BINS, peak_estimate, peak_sigma_m


def padded_peak_bins(sequence: Float[Array, "N P"], peak: Int[Array, " P"], pad: int) -> Float[Array, " P"]:
    """Each pixel's strongest point of the zero-padded DFT, in bins (a multiple of 1/pad),
    searched within ±1 bin of its coarse `peak` (mean removed first: DC's leakage is not a tone)."""
    n = sequence.shape[0]
    x = sequence - jnp.mean(sequence, axis=0, keepdims=True)
    spec = jnp.fft.rfft(x, n=pad * n, axis=0)  # (pad·N/2 + 1, P)
    offsets = jnp.arange(-pad, pad + 1)
    idx = jnp.clip(peak[None, :] * pad + offsets[:, None], 0, spec.shape[0] - 1)
    power = jnp.abs(jnp.take_along_axis(spec, idx, axis=0)) ** 2
    return peak.astype(jnp.float64) + offsets[jnp.argmax(power, axis=0)].astype(jnp.float64) / pad


class ZeroPaddedPeak(AbstractDepthEstimator):
    """The zero-padded DFT's peak, on a grid of 1/`pad` bin. σ: the frequency-only CRLB with the
    grid's quantisation, √(σ_f² + (1/(pad·√12) bin)²)."""

    pad: int = eqx.field(static=True, default=4)
    noise_factor: float = eqx.field(static=True, default=1.0)
    edge_bins: ClassVar[float] = MIRROR_EDGE_BINS

    @classmethod
    def build(cls, setup: EstimatorSetup, pad: int = 4) -> ZeroPaddedPeak:
        return cls(pad)

    @property
    def description(self) -> str:
        return f"peak of the DFT zero-padded ×{self.pad}"

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        amplitude = stage.tone_amplitude(coarse)
        if coarse.spectrum is None:  # a periodogram: no DFT to pad
            depth = stage.depth(coarse, interpolate=True)
        else:
            n = sequence.shape[0]
            depth = stage.geometry.depth_from_folded(padded_peak_bins(sequence, coarse.peak, self.pad) / n)
        bias = 1 / (self.pad * math.sqrt(12))
        return peak_estimate(depth, peak_sigma_m(stage, amplitude, noise_var, self.noise_factor, bias), amplitude)
