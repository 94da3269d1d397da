"""Three-point interpolation of the complex DFT peak: Jacobsen's estimator with Candan's bias
correction (IEEE Signal Process. Lett. 18, 351 (2011)).

For a tone in the unwindowed DFT, δ = Re[(X[k−1] − X[k+1]) / (2X[k] − X[k−1] − X[k+1])] is the
peak's offset from bin k to first order; Candan's factor tan(π/N)/(π/N) removes the remaining
bias. It uses the complex bins (the Hann power's log-parabola uses magnitudes only), so it is
near the frequency-only bound at high SNR. Uniform sweeps; a non-uniform schedule's periodogram
has no complex bins, and there it reads the interpolated periodogram peak.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp

from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup
from .peak import MIRROR_EDGE_BINS, peak_estimate, peak_neighbours, peak_sigma_m


class CandanPeak(AbstractDepthEstimator):
    """The DFT peak interpolated from its complex neighbours (Jacobsen–Candan). Measured with
    random depths away from the window's ends (35–3000 frames, 16–30 dB): error spread
    1.4–1.6× the frequency-only CRLB; bias ≤ 0.003 bin without sidebands, to 0.035 bin (rms
    0.006) where sideband aliases fall near the peak at 35 frames."""

    noise_factor: float = eqx.field(static=True, default=1.4)
    bias_steps: float = eqx.field(static=True, default=0.006)
    edge_bins: ClassVar[float] = MIRROR_EDGE_BINS

    @classmethod
    def build(cls, setup: EstimatorSetup) -> CandanPeak:
        return cls()

    @property
    def description(self) -> str:
        return "three-point complex interpolation of the peak (Jacobsen–Candan)"

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        spec = coarse.spectrum
        if spec is None:
            depth = stage.depth(coarse, interpolate=True)
        else:
            n = sequence.shape[0]
            a, b, c, peak = peak_neighbours(spec, coarse.peak)
            den = 2 * b - a - c
            jacobsen = jnp.real((a - c) / jnp.where(jnp.abs(den) > 0, den, 1.0))
            delta = jnp.clip(jacobsen * math.tan(math.pi / n) / (math.pi / n), -0.5, 0.5)
            depth = stage.geometry.depth_from_folded((peak + delta) / n)
        amplitude = stage.tone_amplitude(coarse)
        return peak_estimate(
            depth, peak_sigma_m(stage, amplitude, noise_var, self.noise_factor, self.bias_steps), amplitude
        )
