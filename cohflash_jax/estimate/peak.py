"""Depth read off the coarse stage's peak: at the grid point (`DFTPeak`) or interpolated
between grid points (`InterpolatedPeak`). Amplitude from the peak's power; σ the
frequency-only CRLB, the only information a peak's position carries."""

from __future__ import annotations

import math

import jax.numpy as jnp

from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup


def _read_out(stage, coarse, noise_var, interpolate: bool) -> DepthEstimate:
    depth = stage.depth(coarse, interpolate=interpolate)
    amplitude = stage.tone_amplitude(coarse)
    sigma = stage.frequency_only_sigma(amplitude, noise_var)
    if not interpolate:  # a grid point read off without interpolation is uniform within ±½ step
        sigma = jnp.maximum(sigma, stage.grid_step_m / math.sqrt(12))
    finite = jnp.isfinite(depth)
    return DepthEstimate(depth, amplitude, sigma, depth, jnp.ones_like(finite), finite, jnp.full(depth.shape, -1.0))


class DFTPeak(AbstractDepthEstimator):
    """The strongest grid point's depth (a DFT bin, or a periodogram depth)."""

    @classmethod
    def build(cls, setup: EstimatorSetup) -> DFTPeak:
        return cls()

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        return _read_out(stage, coarse, noise_var, interpolate=False)


class InterpolatedPeak(AbstractDepthEstimator):
    """The peak interpolated between grid points: a Gaussian (log-power parabola) for a
    uniform sweep's Hann spectrum, a power parabola for a periodogram."""

    @classmethod
    def build(cls, setup: EstimatorSetup) -> InterpolatedPeak:
        return cls()

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        return _read_out(stage, coarse, noise_var, interpolate=True)
