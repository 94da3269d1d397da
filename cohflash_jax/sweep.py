"""Stepped-frequency sweep: the microwave tone f_m of each camera frame."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .constants import SPEED_OF_LIGHT_M_PER_S


class FrequencySweep(eqx.Module):
    """An increasing schedule of microwave frequencies, one per frame (Hz, float64).

    Uniform sweeps (f_m = f_0 + m·Δf) are the usual case; any strictly increasing
    schedule is legal. A concrete schedule is validated and held as a float64 NumPy array (a
    pytree leaf, traced under jit); the properties below are host-side and read its values.
    A schedule built from traced values (inside `jax.vmap` or `jax.jit`, as the design's
    gradient search does) is held as it is and checked by nobody: only `frequencies_hz`,
    `num_steps` and `as_array` are meaningful for it.
    """

    frequencies_hz: np.ndarray

    def __init__(self, frequencies_hz):
        if isinstance(frequencies_hz, jax.core.Tracer):
            self.frequencies_hz = frequencies_hz
            return
        f = np.asarray(frequencies_hz, dtype=np.float64)
        validate_frequencies(f)
        self.frequencies_hz = f

    @classmethod
    def uniform(cls, start_hz: float, step_hz: float, num_steps: int) -> "FrequencySweep":
        """f_m = start + m·step for m = 0..num_steps−1."""
        if num_steps < 2:
            raise ValueError(f"a sweep needs at least 2 steps, got {num_steps}")
        if not step_hz > 0:
            raise ValueError(f"step_hz must be positive, got {step_hz}")
        return cls(start_hz + step_hz * np.arange(num_steps, dtype=np.float64))

    @classmethod
    def paper(cls, num_steps: int = 3000) -> "FrequencySweep":
        """The paper's sweep: 0.1 GHz start, Δf = 1.97 MHz (3000 steps reach ≈6.0 GHz)."""
        return cls.uniform(0.1e9, 1.97e6, num_steps)

    @property
    def num_steps(self) -> int:
        return int(self.frequencies_hz.size)

    @property
    def start_hz(self) -> float:
        return float(self.frequencies_hz[0])

    @property
    def step_hz(self) -> float:
        """Frequency step Δf (Hz); the median step for a non-uniform schedule."""
        return float(np.median(np.diff(self.frequencies_hz)))

    @property
    def bandwidth_hz(self) -> float:
        """Synthetic bandwidth B = N·Δf for uniform sweeps (span + one step otherwise)."""
        return float(self.frequencies_hz[-1] - self.frequencies_hz[0] + self.step_hz)

    @property
    def mean_frequency_hz(self) -> float:
        return float(np.mean(self.frequencies_hz))

    @property
    def is_uniform(self) -> bool:
        d = np.diff(self.frequencies_hz)
        return bool(np.all(np.abs(d - d[0]) <= 1e-9 * abs(d[0]) + 1e-3))

    @property
    def ambiguity_m(self) -> float:
        """Unambiguous depth interval [0, c/(4Δf)) of frequency-only processing of a real tone."""
        return SPEED_OF_LIGHT_M_PER_S / (4.0 * self.step_hz)

    @property
    def bin_depth_m(self) -> float:
        """Depth spanned by one DFT bin over the frame index, c/(2·N·Δf)."""
        return SPEED_OF_LIGHT_M_PER_S / (2.0 * self.num_steps * self.step_hz)

    @property
    def ripple_period_m(self) -> float:
        """Period in depth of the phase-locked likelihood's ripple, c/(2·f̄)."""
        return SPEED_OF_LIGHT_M_PER_S / (2.0 * self.mean_frequency_hz)

    def as_array(self) -> Float[Array, " N"]:
        return jnp.asarray(self.frequencies_hz, dtype=jnp.float64)

    def __repr__(self) -> str:  # short: frequency arrays are long
        if isinstance(self.frequencies_hz, jax.core.Tracer):
            return f"FrequencySweep(traced, N={self.num_steps})"
        kind = "uniform" if self.is_uniform else "non-uniform"
        return (
            f"FrequencySweep({kind}, N={self.num_steps}, {self.start_hz / 1e9:.4g}–"
            f"{self.frequencies_hz[-1] / 1e9:.4g} GHz, Δf={self.step_hz / 1e6:.4g} MHz)"
        )


def validate_frequencies(f: np.ndarray) -> None:
    """Raise ValueError unless f is a finite, strictly increasing 1-D schedule of ≥ 2 positive Hz."""
    if f.ndim != 1:
        raise ValueError(f"frequencies must be 1-D, got shape {f.shape}")
    if f.size < 2:
        raise ValueError(f"a sweep needs at least 2 steps, got {f.size}")
    if not np.all(np.isfinite(f)):
        raise ValueError("frequencies contain NaN or inf")
    if np.any(f < 0):
        raise ValueError("frequencies must be non-negative")
    if np.any(np.diff(f) <= 0):
        bad = int(np.argmax(np.diff(f) <= 0))
        raise ValueError(
            f"frequencies must be strictly increasing (step {bad}→{bad + 1}: {f[bad]:.6g} Hz → {f[bad + 1]:.6g} Hz)"
        )
