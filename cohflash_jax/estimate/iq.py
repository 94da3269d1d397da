"""I/Q from the four CCDs, and carrier-phase alignment (static or tracked).

float32 throughout: the inputs are DN with ≤ 16 bits, and every later use is a
difference or an average of them; float64 would double memory traffic for nothing.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..xp import namespace


def iq_from_frames(
    frames: Array,
    iq_weights: Float[Array, "2 4"],
    iq_bias: Float[Array, " 2"],
    dark: Float[Array, "4 P"] | None = None,
    gain: Float[Array, "4 P"] | None = None,
):
    """[I, Q] = W @ ((DN − dark)/gain) + b; frames (4, N, P) in DN → I, Q of shape (N, P).

    `dark` per-pixel offsets, `gain` per-pixel gains relative to those folded into W; both
    are folded into per-pixel weights and bias, so the frames are read once."""
    xp = namespace(frames, iq_weights, iq_bias, dark, gain)
    x = frames if xp.issubdtype(frames.dtype, xp.floating) else frames.astype(xp.float32)
    w, b = folded_weights(iq_weights, iq_bias, dark, gain, x.dtype)
    i = w[0, 0] * x[0] + w[0, 1] * x[1] + w[0, 2] * x[2] + w[0, 3] * x[3] + b[0]
    q = w[1, 0] * x[0] + w[1, 1] * x[1] + w[1, 2] * x[2] + w[1, 3] * x[3] + b[1]
    return i, q


def folded_weights(iq_weights, iq_bias, dark=None, gain=None, dtype=None):
    """The weights W (2, 4), or (2, 4, P) with per-pixel `gain`, and bias b (2, 1) or (2, P)
    with per-pixel `dark`, that make [I, Q] = W·DN + b (`iq_from_frames`), in `dtype`
    (default: the weights' own). NumPy in, NumPy out; JAX in, JAX out."""
    xp = namespace(iq_weights, iq_bias, dark, gain)
    w = xp.asarray(iq_weights)
    dtype = w.dtype if dtype is None else dtype
    w = w.astype(dtype)
    b = xp.asarray(iq_bias).astype(dtype)[:, None]
    if gain is not None:
        w = w[:, :, None] / gain.astype(dtype)[None]  # (2, 4, P)
    if dark is not None:
        d = dark.astype(dtype)
        # dark folded into the bias, not subtracted per frame
        b = b - (xp.einsum("ikp,kp->ip", w, d) if w.ndim == 3 else w @ d)
    return w, b


def _rotate(i, q, phase):
    c, s = jnp.cos(phase), jnp.sin(phase)
    return i * c + q * s, -i * s + q * c


class CarrierAxis(eqx.Module):
    """Each pixel's carrier axis (P,): cos φ, sin φ, φ; the variance of the orthogonal
    component (`noise_var`: noise and hybrid-error leakage only) and the total variance of the
    mean-removed I/Q, var I + var Q (`total_var`: the detection test's noise estimate)."""

    cos: Float[Array, " P"]
    sin: Float[Array, " P"]
    noise_var: Float[Array, " P"]
    phase: Float[Array, " P"]
    total_var: Float[Array, " P"]


def carrier_axis(i: Float[Array, "N P"], q: Float[Array, "N P"]) -> CarrierAxis:
    """Principal axis of each pixel's (mean-removed) I/Q cloud, from its second moments.

    Z = e^{iφ}·(real sequence) + noise lies on a line at angle φ; ½·arg Σ(Z − Z̄)² finds it
    up to a sign, taken from the mean term A·w_0 (reliable once the hybrid is calibrated; the
    fit's signed amplitude absorbs a wrong sign). The variances come from the same moments,
    without another pass. The orthogonal component has N − 2 degrees of freedom (the mean and
    the axis, chosen to minimise it, take one each), so its sum of squares is divided by N − 2:
    divided by N it read 6 % low at 35 frames, and the fits' χ² sat at 1.06."""
    n = i.shape[0]
    mi, mq = jnp.mean(i, axis=0), jnp.mean(q, axis=0)
    sii = jnp.sum(i * i, axis=0) / n - mi * mi
    sqq = jnp.sum(q * q, axis=0) / n - mq * mq
    siq = jnp.sum(i * q, axis=0) / n - mi * mq
    c, s = half_angle(sii - sqq, 2 * siq)  # φ = ½·atan2(2 siq, sii − sqq) ∈ (−π/2, π/2]
    # orient the axis so the mean term A·w_0 (which S keeps) comes out positive
    flip = mi * c + mq * s < 0
    c, s = jnp.where(flip, -c, c), jnp.where(flip, -s, s)
    noise_var = jnp.maximum(s * s * sii + c * c * sqq - 2 * s * c * siq, 0.0) * (n / max(n - 2, 1))
    return CarrierAxis(c, s, noise_var, jnp.arctan2(s, c), jnp.maximum(sii + sqq, 0.0))


def half_angle(x, y):
    """cos φ and sin φ of φ = ½·atan2(y, x) ∈ (−π/2, π/2], without trigonometry: the axis is
    along (r + x, y) (r = |(x, y)|), or along (y, r − x) where x < 0, which avoids the
    cancellation in r + x; then turned so that cos φ ≥ 0. (1, 0) where x = y = 0, as atan2
    gives. A per-pixel atan2, cos and sin are scalar libm calls in XLA's CPU code: about a
    quarter of the 10 Hz carrier-axis program (docs/performance.md)."""
    r = jnp.hypot(x, y)
    ax, ay = jnp.where(x >= 0, r + x, y), jnp.where(x >= 0, y, r - x)
    norm = jnp.hypot(ax, ay)
    ok = norm > 0
    c = jnp.where(ok, ax / jnp.where(ok, norm, 1), 1)
    s = jnp.where(ok, ay / jnp.where(ok, norm, 1), 0)
    turn = (c < 0) | ((c == 0) & (s < 0))
    return jnp.where(turn, -c, c), jnp.where(turn, -s, s)


def rotate_onto_axis(
    i: Float[Array, "N P"], q: Float[Array, "N P"], cos_phase: Float[Array, " P"], sin_phase: Float[Array, " P"]
) -> Float[Array, "N P"]:
    """The real sequence r = I cos φ + Q sin φ along each pixel's carrier axis."""
    return i * cos_phase + q * sin_phase


def align_carrier_static(i: Float[Array, "N P"], q: Float[Array, "N P"]):
    """`carrier_axis` then `rotate_onto_axis` → (r, noise_var, phase).

    Within one XLA CPU program the per-pixel cos φ, sin φ (and the arctan2 before them) are
    fused into the rotation and recomputed for every frame; the reconstruction therefore runs
    the two halves as separate programs (`reconstruct.programs`; docs/performance.md). Fine
    for small arrays."""
    axis = carrier_axis(i, q)
    return rotate_onto_axis(i, q, axis.cos, axis.sin), axis.noise_var, axis.phase


# Frames a carrier-drift estimate averages over: long enough to average the tone out of the
# mean term at 3000 frames, short against the drift of turbulence (0.05 rad/√frame)
DRIFT_WINDOW_FRAMES = 101


def moving_average(x: Array, window: int) -> Array:
    """Centred moving average along axis 0 with a window shrinking at the ends. A NumPy array
    is averaged in NumPy (the one-off host-side drift search: no compilation in a fresh
    process), anything else in JAX. Each window's sum is a difference of two running sums,
    taken as slices (the windows cut by either end, and the whole ones between) rather than
    gathered by index: the same values, without a gather."""
    xp = np if isinstance(x, np.ndarray) else jnp
    n = x.shape[0]
    half = window // 2
    c = xp.cumsum(xp.concatenate([xp.zeros_like(x[:1]), x], axis=0), axis=0)
    idx = xp.arange(n)
    lo, hi = xp.maximum(idx - half, 0), xp.minimum(idx + half + 1, n)  # each window's frames
    count = (hi - lo).astype(x.real.dtype).reshape((n,) + (1,) * (x.ndim - 1))
    if n <= 2 * half:  # every window shrinks: gathered
        return (c[hi] - c[lo]) / count
    sums = xp.concatenate(
        [
            c[half + 1 : 2 * half + 1] - c[:1],  # the first `half` windows start at frame 0
            c[2 * half + 1 :] - c[: n - 2 * half],
            c[n:] - c[n - 2 * half : n - half],  # the last `half` end at the last frame
        ],
        axis=0,
    )
    return sums / count


def track_carrier_drift(
    i: Float[Array, "N P"], q: Float[Array, "N P"], window_frames: int = DRIFT_WINDOW_FRAMES
) -> Float[Array, "N P"]:
    """Slow drift φ[m] of the optical carrier phase (turbulence), per pixel, zero-mean.

    Z[m] = e^{iφ[m]}·A·S[m] and S[m] = w_0 + 2Σ w_n cos(nψ_m) keeps the sign of its mean
    term A·w_0, so a moving average of Z over `window_frames` is e^{iφ[m]}·A·w_0·(1 + small)
    and its unwrapped phase follows φ with noise linear in the data. (Squaring Z — the
    textbook way to drop a tone's sign — squares the raw noise and slips by π at the paper's
    SNR; demodulating at the tone uses the weaker w_1.) Requires w_0 > 0 (any bias but
    θ_b = π/2) and a hybrid without common-mode leakage: calibrate the hybrid first."""
    z = (i + 1j * q).astype(jnp.complex64 if i.dtype == jnp.float32 else jnp.complex128)
    phase = jnp.unwrap(jnp.angle(moving_average(z, window_frames)), axis=0)
    return phase - jnp.mean(phase, axis=0)


def derotate(i: Float[Array, "N P"], q: Float[Array, "N P"], phase: Float[Array, "N P"]):
    """(I, Q) rotated by −phase per frame and pixel."""
    return _rotate(i, q, phase)
