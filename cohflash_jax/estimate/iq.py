"""I/Q from the four CCDs, and carrier-phase alignment (static or tracked).

float32 throughout: the inputs are DN with ≤ 16 bits, and every later use is a
difference or an average of them; float64 would double memory traffic for nothing.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float


def iq_from_frames(frames: Array, iq_weights: Float[Array, "2 4"], iq_bias: Float[Array, " 2"],
                   dark: Float[Array, "4 P"] | None = None):
    """[I, Q] = W @ (DN − dark) + b; frames (4, N, P) in DN → I, Q of shape (N, P)."""
    x = frames if jnp.issubdtype(frames.dtype, jnp.floating) else frames.astype(jnp.float32)
    w = iq_weights.astype(x.dtype)
    b = iq_bias.astype(x.dtype)[:, None]
    if dark is not None:
        b = b - w @ dark.astype(x.dtype)  # (2, P): dark folded into the bias, not subtracted per frame
    i = w[0, 0] * x[0] + w[0, 1] * x[1] + w[0, 2] * x[2] + w[0, 3] * x[3] + b[0]
    q = w[1, 0] * x[0] + w[1, 1] * x[1] + w[1, 2] * x[2] + w[1, 3] * x[3] + b[1]
    return i, q


def _rotate(i, q, phase):
    c, s = jnp.cos(phase), jnp.sin(phase)
    return i * c + q * s, -i * s + q * c


def align_carrier_static(i: Float[Array, "N P"], q: Float[Array, "N P"]):
    """Rotate I/Q by the principal axis of each pixel's (mean-removed) I/Q cloud.

    Z = e^{iφ}·(real sequence) + noise lies on a line at angle φ; ½·arg Σ(Z − Z̄)² finds it
    (up to a sign that the signed amplitude of the fit absorbs). Returns (r, noise_var,
    phase): r carries the signal; noise_var is the variance of the orthogonal component,
    which holds only noise (and hybrid-error leakage), computed from the same second
    moments without another pass over the data."""
    n = i.shape[0]
    mi, mq = jnp.mean(i, axis=0), jnp.mean(q, axis=0)
    sii = jnp.sum(i * i, axis=0) / n - mi * mi
    sqq = jnp.sum(q * q, axis=0) / n - mq * mq
    siq = jnp.sum(i * q, axis=0) / n - mi * mq
    phase = 0.5 * jnp.arctan2(2 * siq, sii - sqq)
    c, s = jnp.cos(phase), jnp.sin(phase)
    noise_var = jnp.maximum(s * s * sii + c * c * sqq - 2 * s * c * siq, 0.0)
    r = i * c + q * s
    return r, noise_var, phase


def _moving_average(x: Array, window: int) -> Array:
    """Centred moving average along axis 0 with a window shrinking at the ends."""
    n = x.shape[0]
    half = window // 2
    c = jnp.cumsum(jnp.concatenate([jnp.zeros_like(x[:1]), x], axis=0), axis=0)
    idx = jnp.arange(n)
    lo = jnp.clip(idx - half, 0, n)
    hi = jnp.clip(idx + half + 1, 0, n)
    count = (hi - lo).astype(x.real.dtype).reshape((n,) + (1,) * (x.ndim - 1))
    return (c[hi] - c[lo]) / count


def align_carrier_tracked(i: Float[Array, "N P"], q: Float[Array, "N P"], window_frames: int = 101):
    """Track a slowly drifting carrier phase φ[m] (turbulence) and de-rotate.

    Z² = e^{2iφ}·(non-negative) removes the sign of the tone, so a moving average of
    (Z − Z̄)² over `window_frames` frames follows 2φ[m]; φ is half its unwrapped phase.
    Returns (r, q_residual, phase[N, P])."""
    z = (i - jnp.mean(i, axis=0)) + 1j * (q - jnp.mean(q, axis=0))
    smooth = _moving_average(z * z, window_frames)
    phase = 0.5 * jnp.unwrap(jnp.angle(smooth), axis=0)
    r, qr = _rotate(i, q, phase)
    return r, qr, phase
