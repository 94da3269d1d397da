"""Fisher information of depth, by automatic differentiation of the forward model.

The expected port electrons n_k[m](θ) come from `simulate.expected_port_electrons` (the same
code that simulates captures), θ = (depth, log echo amplitude, carrier phase[, tone frequency
offset]); the noise is Gaussian with the per-sample variance of the sensor model (shot noise
on every electron, dark shot, read noise, ADC quantization, in electrons), so

    F_ij = Σ_k Σ_m ∂n_k[m]/∂θ_i · ∂n_k[m]/∂θ_j / var_k[m]

and the depth CRLB is √[F⁻¹]₀₀ with amplitude and carrier phase as nuisances. With
`frequency_only=True` a common offset δf of all microwave frequencies joins the nuisances:
it shifts the tone's phase by 2π·δf·τ, which removes what the tone's absolute phase tells
about τ — the bound of an estimator that uses only the tone's frequency (the DFT stage).
Everything is jittable and differentiable in the instrument's parameters (design by gradient).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .constants import SPEED_OF_LIGHT_M_PER_S as C
from .effects import EffectSettings
from .instrument import Instrument
from .simulate import Returns, expected_port_electrons


def _returns(instrument: Instrument, depth_m, log_amplitude, carrier_phase, echo_e) -> Returns:
    delay = 2.0 * depth_m / C + instrument.system_delay_s
    amp = jnp.sqrt(echo_e * jnp.exp(2 * log_amplitude)) * jnp.exp(1j * carrier_phase)
    return Returns(jnp.reshape(delay, (1, 1, 1)), jnp.reshape(amp, (1, 1, 1)),
                   jnp.reshape(echo_e * jnp.exp(2 * log_amplitude), (1, 1)))


def port_variance_e2(instrument: Instrument, mean_e, effects) -> Array:
    """Per-sample noise variance (electrons²) of each port: shot noise on the mean electrons
    (when on), dark shot, read noise and ADC quantization, as the simulator draws them."""
    sensor = instrument.sensor
    var = jnp.zeros_like(mean_e)
    if "shot_noise" in effects:
        var = var + jnp.maximum(mean_e, 0.0)
    if "dark_current" in effects:
        var = var + sensor.dark_electrons
    if "read_noise" in effects:
        var = var + sensor.read_noise_e**2
    if "quantization" in effects:
        var = var + (1.0 / sensor.dn_per_electron) ** 2 / 12.0
    return var


def depth_fisher(instrument: Instrument, frequencies_hz: Float[Array, " N"], distance_m, reflectance,
                 effects=("shot_noise", "dark_current", "read_noise", "quantization"),
                 settings: EffectSettings | None = None, frequency_only: bool = False,
                 range_falloff: bool = True, frame_weights: Float[Array, " N"] | None = None) -> Float[Array, "K K"]:
    """Fisher information of (depth m, log amplitude, carrier phase rad[, δf Hz]) for one pixel
    of a target at `distance_m` with `reflectance`, per capture: all frames, or each frame
    weighted by `frame_weights` (a 0/1 mask gives sweeps of any N one compiled shape)."""
    settings = settings or EffectSettings()
    effects = tuple(effects)
    f = jnp.asarray(frequencies_hz, jnp.float64)
    echo_e = instrument.sensor.electrons(instrument.link.echo_power_w(distance_m, reflectance, range_falloff))
    idx = jnp.arange(f.shape[0], dtype=jnp.float64)

    def ports(theta):
        shift = theta[3] if frequency_only else 0.0
        returns = _returns(instrument, theta[0], theta[1], theta[2], echo_e)
        return expected_port_electrons(instrument, settings, returns, f + shift, idx, None, effects)[..., 0]

    theta0 = jnp.asarray([distance_m, 0.0, 0.3] + ([0.0] if frequency_only else []), jnp.float64)
    mean = ports(theta0)
    var = jax.lax.stop_gradient(port_variance_e2(instrument, mean, effects))
    jac = jax.jacfwd(ports)(theta0)  # (4, N, K)
    w = jac / jnp.sqrt(var)[..., None]
    if frame_weights is not None:
        w = w * jnp.sqrt(frame_weights)[:, None]
    return jnp.einsum("kni,knj->ij", w, w)


def crlb_from_fisher(fisher: Float[Array, "K K"]) -> Float[Array, ""]:
    """√[F⁻¹]₀₀ with a scaled solve (the unknowns' units differ by many decades)."""
    scale = jnp.sqrt(jnp.maximum(jnp.diag(fisher), 1e-300))
    normed = fisher / scale[:, None] / scale[None, :]
    e0 = jnp.zeros(fisher.shape[0]).at[0].set(1.0)
    inv00 = jnp.linalg.solve(normed + 1e-14 * jnp.eye(fisher.shape[0]), e0)[0]
    return jnp.sqrt(jnp.maximum(inv00, 0.0)) / scale[0]


def depth_crlb_m(instrument: Instrument, frequencies_hz, distance_m, reflectance, effects=None,
                 settings: EffectSettings | None = None, frequency_only: bool = False,
                 range_falloff: bool = True) -> Float[Array, ""]:
    """Depth CRLB (m) of one pixel: phase-locked (all of f_m) or frequency-only."""
    effects = ("shot_noise", "dark_current", "read_noise", "quantization") if effects is None else effects
    return crlb_from_fisher(depth_fisher(instrument, frequencies_hz, distance_m, reflectance, effects, settings,
                                         frequency_only, range_falloff))
