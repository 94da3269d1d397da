"""Mach–Zehnder modulator: Bessel sideband weights and the exposure-averaged beat S(ψ).

Convention (docs/design-reference.md §1): drive V(t) = V_b + V_m cos Ωt, modulation index
β = π·V_m/V_π, x = β/2, bias angle θ_b; field transfer t = cos(θ_b + x cos Ωt) =
Σ c_n e^{inΩt} with |c_n|² = J_n(x)² cos²θ_b (n even), J_n(x)² sin²θ_b (n odd).
The exposure-averaged product of reference and echo transfers is
S(ψ) = |c_0|² + 2 Σ_{n≥1} |c_n|² cos(nψ), ψ = 2π f τ.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .xp import namespace

# Trapezoid nodes for the Bessel integral. The M-node rule is exact up to terms J_{M±n}(x):
# with M = 128, negligible (< 1e-40) for orders n ≤ MAX_ORDER and |x| ≤ MAX_BESSEL_ARGUMENT.
# Where the orders stop lower, M = n_max + `BESSEL_NODES_BEYOND_ORDER` nodes keep J_{M−n}(20)
# ≤ J_60(20) ≈ 1e-22, below float64 rounding, for half or less of the work (the sideband
# weights of a 3rd-order model: 63 nodes; they were most of the calibration's modulator fit)
_BESSEL_NODES = 128
BESSEL_NODES_BEYOND_ORDER = 60
MAX_ORDER = 32
MAX_BESSEL_ARGUMENT = 20.0


def bessel_nodes(max_order: int) -> int:
    """Trapezoid nodes that give J_n(x) to rounding for |n| ≤ max_order and |x| ≤ 20."""
    return min(_BESSEL_NODES, abs(int(max_order)) + BESSEL_NODES_BEYOND_ORDER)


def bessel_j(orders: ArrayLike, x: ArrayLike, nodes: int = _BESSEL_NODES) -> Float[Array, "..."]:
    """J_n(x) for integer orders n (|n| ≤ 32) and real |x| ≤ 20, broadcast over x and n;
    `nodes`: fewer where the orders stop lower (`bessel_nodes`).

    Uses the periodic trapezoid rule on Bessel's integral
    J_n(x) = (1/2π)∫ cos(n t − x sin t) dt, which converges geometrically, is finite and
    smooth at x = 0 (no NaN, finite gradients of every order) and keeps absolute error
    at rounding level in float64 and float32 — unlike `jax.scipy.special.bessel_jn`,
    which is NaN at x = 0 and inaccurate for large arguments.
    """
    xp = namespace(orders, x)
    n = xp.asarray(orders).astype(xp.int32)
    x = xp.asarray(x)
    dtype = xp.result_type(x.dtype, xp.float32)
    count = int(nodes)
    k = np.arange(count)
    n_b, x_b = xp.broadcast_arrays(n, x.astype(dtype))
    # n·t_k reduced modulo 2π in integers, (n·k mod M)·2π/M, so the cosine's argument stays
    # below 2π + |x| at every order: in float32 the rounding of n·t_k itself (up to 200 rad at
    # order 32) would otherwise dominate (measured: max error 7.9e-7 → 2.5e-7 over orders ≤ 32)
    turns = xp.mod(n_b[..., None] * k, count).astype(dtype)
    phase = turns * (2 * np.pi / count) - x_b[..., None] * xp.asarray(np.sin(2 * np.pi * k / count), dtype)
    return xp.mean(xp.cos(phase), axis=-1)


def sideband_weights(x: ArrayLike, bias_rad: ArrayLike, max_order: int) -> Float[Array, "... K"]:
    """|c_n|² for n = 0..max_order (K = max_order + 1), broadcast over x and bias."""
    if not 0 <= max_order <= MAX_ORDER:
        raise ValueError(f"max_order must be in 0..{MAX_ORDER}, got {max_order}")
    xp = namespace(x, bias_rad)
    x = xp.asarray(x)
    bias = xp.asarray(bias_rad)
    orders = xp.arange(max_order + 1)
    j = bessel_j(orders, x[..., None], bessel_nodes(max_order))
    even = (orders % 2) == 0
    cos2 = xp.cos(bias)[..., None] ** 2
    sin2 = xp.sin(bias)[..., None] ** 2
    return j**2 * xp.where(even, cos2, sin2)


def mean_transmission(x: ArrayLike, bias_rad: ArrayLike) -> Float[Array, "..."]:
    """S_0 = Σ_n |c_n|² over all orders = ½ + ½·cos(2θ_b)·J_0(2x) (closed form)."""
    return 0.5 + 0.5 * jnp.cos(2 * jnp.asarray(bias_rad)) * bessel_j(0, 2 * jnp.asarray(x))


def beat_spectrum(psi: ArrayLike, weights: Float[Array, "... K"]) -> Float[Array, "..."]:
    """S(ψ) = w_0 + 2 Σ_{n≥1} w_n cos(nψ) for sideband weights w (last axis = order).

    cos(nψ) is built by the Chebyshev recurrence from cos ψ, so only one cosine is
    evaluated per sample whatever the order.
    """
    psi = jnp.asarray(psi)
    c1 = jnp.cos(psi)
    total = weights[..., 0] * jnp.ones_like(c1)
    prev, cur = jnp.ones_like(c1), c1
    for n in range(1, weights.shape[-1]):
        total = total + 2 * weights[..., n] * cur
        prev, cur = cur, 2 * c1 * cur - prev
    return total


class MZM(eqx.Module):
    """Modulator settings. `rolloff_3db_hz` models β(f) = β/√(1+(f/f_3dB)²) (∞ = flat)."""

    modulation_index: Float[ArrayLike, ""] = 2.0
    bias_rad: Float[ArrayLike, ""] = float(np.pi / 4)
    rolloff_3db_hz: Float[ArrayLike, ""] = float("inf")
    max_order: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        if not 0 <= self.max_order <= MAX_ORDER:
            raise ValueError(f"max_order must be in 0..{MAX_ORDER}, got {self.max_order}")
        for name in ("modulation_index", "rolloff_3db_hz"):
            v = getattr(self, name)
            if isinstance(v, (int, float)) and not v >= 0:
                raise ValueError(f"MZM.{name} must be ≥ 0, got {v}")
        if isinstance(self.modulation_index, (int, float)) and self.modulation_index / 2 > MAX_BESSEL_ARGUMENT:
            raise ValueError(f"modulation_index/2 must be ≤ {MAX_BESSEL_ARGUMENT}")

    def x_at(self, frequencies_hz: ArrayLike) -> Float[Array, "..."]:
        """Half modulation index x = β(f)/2 at each frequency (roll-off applied)."""
        xp = namespace(frequencies_hz, self.rolloff_3db_hz, self.modulation_index)
        f = xp.asarray(frequencies_hz)
        ratio = f / xp.asarray(self.rolloff_3db_hz, dtype=f.dtype)
        return 0.5 * self.modulation_index / xp.sqrt(1.0 + ratio**2)

    @property
    def flat(self) -> bool:
        """True when β does not depend on frequency (no roll-off, f_3dB = ∞, known on the host)."""
        r = self.rolloff_3db_hz
        return isinstance(r, (int, float)) and math.isinf(r)

    def half_index(self, frequencies_hz: ArrayLike | None = None):
        """x = β/2: a scalar where β is flat or no frequencies are given, else x(f) per frequency."""
        if frequencies_hz is None or self.flat:
            return 0.5 * self.modulation_index
        return self.x_at(frequencies_hz)

    def weights(self, frequencies_hz: ArrayLike | None = None, max_order: int | None = None):
        """Sideband weights |c_n|²: (K,) without frequencies, (…, K) at each frequency (the
        roll-off applied). The simulator, the Fisher information, calibration and every
        estimator take the sidebands from here."""
        order = self.max_order if max_order is None else max_order
        x = (
            0.5 * namespace(self.modulation_index).asarray(self.modulation_index, np.float64)
            if frequencies_hz is None
            else self.x_at(frequencies_hz)
        )
        return sideband_weights(x, self.bias_rad, order)

    def mean_transmission(self, frequencies_hz: ArrayLike | None = None):
        """S_0 = Σ|c_n|²: a scalar without frequencies, else at each frequency (roll-off applied)."""
        x = (
            0.5 * namespace(self.modulation_index).asarray(self.modulation_index, np.float64)
            if frequencies_hz is None
            else self.x_at(frequencies_hz)
        )
        return mean_transmission(x, self.bias_rad)
