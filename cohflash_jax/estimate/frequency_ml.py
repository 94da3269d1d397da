"""Frequency-only maximum likelihood: the tone's frequency with its phase free, the maximum
of the unwindowed periodogram |Σ_m r_m e^{−i2πνm/N}|² over continuous ν (a real tone in white
noise, Rife & Boorstyn 1974).

It ignores what the phase-locked model knows — that the tone's phase is 2π·f₀·τ, locked to
the depth — so it reaches the frequency-only CRLB, not the phase-locked one: the price of not
trusting the phase (e.g. an unknown carrier drift, or a system delay not yet calibrated).
Started on the ×4 zero-padded DFT's peak (within 1/8 bin of the maximum, inside its main
lobe), polished by Newton's method on the slope. Uniform sweeps; a non-uniform schedule's
periodogram is read at its interpolated peak.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .base import AbstractDepthEstimator, DepthEstimate, EstimatorSetup
from .padded import padded_peak_bins
from .peak import MIRROR_EDGE_BINS, peak_estimate, peak_sigma_m
from .polish import descended, polish_depth

START_PAD = 4
# Newton stops once its step is below this many bins (1e-6 bin is ~0.03 µm at 3000 frames)
STEP_TOLERANCE_BINS = 1e-6


class FrequencyOnlyML(AbstractDepthEstimator):
    """The periodogram's maximum over continuous frequency. σ: the frequency-only CRLB."""

    max_steps: int = eqx.field(static=True, default=16)
    refines: ClassVar[bool] = True
    edge_bins: ClassVar[float] = MIRROR_EDGE_BINS

    @classmethod
    def build(cls, setup: EstimatorSetup) -> FrequencyOnlyML:
        return cls(setup.max_steps)

    @property
    def description(self) -> str:
        return "maximum of the periodogram over continuous frequency (frequency-only ML)"

    def estimate(self, stage, coarse, sequence, noise_var) -> DepthEstimate:
        amplitude = stage.tone_amplitude(coarse)
        sigma = peak_sigma_m(stage, amplitude, noise_var, 1.0, 0.0)
        coarse_depth = stage.depth(coarse, interpolate=True)
        if coarse.spectrum is None:
            return peak_estimate(coarse_depth, sigma, amplitude)
        n = sequence.shape[0]
        x = (sequence - jnp.mean(sequence, axis=0, keepdims=True)).astype(jnp.float64)
        start = padded_peak_bins(sequence, coarse.peak, START_PAD)
        frames = jnp.arange(n, dtype=jnp.float64)

        def periodogram(xp, bins):
            """|X(ν)|²/N at ν = `bins` (in DFT bins) for one pixel's sequence."""
            phase = (2 * math.pi / n) * bins * frames
            re, im = xp @ jnp.cos(phase), xp @ jnp.sin(phase)
            return (re * re + im * im) / n

        def fit(xp, bins0):
            cost = lambda offset: -periodogram(xp, bins0 + offset)
            p = polish_depth(cost, jnp.zeros(()), max_steps=self.max_steps, tolerance_mm=STEP_TOLERANCE_BINS)
            ok = p.succeeded & descended(cost(p.value), cost(jnp.zeros(())))
            return bins0 + jnp.where(ok, p.value, 0.0), ok

        bins, ok = jax.vmap(fit, in_axes=(1, 0))(x, start)
        depth = stage.geometry.depth_from_folded(bins / n)
        estimate = peak_estimate(depth, sigma, amplitude)
        return eqx.tree_at(lambda e: (e.coarse_depth_m, e.converged), estimate, (coarse_depth, ok))
