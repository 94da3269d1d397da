"""Every Cramér–Rao bound of depth in cohflash: the Fisher information of the forward model by
automatic differentiation, the closed forms it reduces to, and the per-pixel bound each
estimator reports as its σ.

Autodiff: the expected port electrons n_k[m](θ) come from `simulate.expected_port_electrons`
(the code that simulates captures), θ = (depth, log echo amplitude, carrier phase[, tone
frequency offset]), over the instrument's own sweep; the noise is Gaussian with the sensor's
per-port variance (`Sensor.port_variance_e2`: shot, dark, read, ADC rounding), so

    F_ij = Σ_k Σ_m ∂n_k[m]/∂θ_i · ∂n_k[m]/∂θ_j / var_k[m]

and the depth CRLB is √[F⁻¹]₀₀ with amplitude and carrier phase as nuisances. With
`frequency_only=True` a common offset δf of all microwave frequencies joins the nuisances:
it shifts the tone's phase by 2π·δf·τ, which removes what the tone's absolute phase tells
about τ — the bound of an estimator that uses only the tone's frequency (the DFT stage).
Everything is jittable and differentiable in the instrument's parameters (design by gradient).

Closed forms (a real tone r = c + a·cos(2π f_m τ) in white noise of variance σ²):
phase-locked σ_τ² = σ²/(a²/2·Σ(2π f_m)²); frequency only σ_τ² = σ²/(a²/2·Σ(2π(f_m − f̄))²),
which for a uniform sweep is Kay's var ω = 24σ²/(a²N(N²−1)).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .constants import SPEED_OF_LIGHT_M_PER_S as C
from .effects import EffectSettings
from .instrument import Instrument
from .simulate import Returns, expected_port_electrons

# The noise of a capture at the sensor: what the design and the CRLB tables assume.
SENSOR_NOISE = ("shot_noise", "dark_current", "read_noise", "quantization")
# The carrier phase at which the autodiff bound is evaluated (any value: the hybrid's four
# ports make the information independent of it)
_CARRIER_PHASE_RAD = 0.3


def _returns(instrument: Instrument, depth_m, log_amplitude, carrier_phase, echo_e) -> Returns:
    delay = 2.0 * depth_m / C + instrument.system_delay_s
    amp = jnp.sqrt(echo_e * jnp.exp(2 * log_amplitude)) * jnp.exp(1j * carrier_phase)
    return Returns(
        jnp.reshape(delay, (1, 1, 1)),
        jnp.reshape(amp, (1, 1, 1)),
        jnp.reshape(echo_e * jnp.exp(2 * log_amplitude), (1, 1)),
    )


def depth_fisher(
    instrument: Instrument,
    distance_m,
    reflectance,
    effects=SENSOR_NOISE,
    settings: EffectSettings | None = None,
    frequency_only: bool = False,
    range_falloff: bool = True,
    frame_weights: Float[Array, " N"] | None = None,
) -> Float[Array, "K K"]:
    """Fisher information of (depth m, log amplitude, carrier phase rad[, δf Hz]) for one pixel
    of a target at `distance_m` with `reflectance`, per capture of the instrument's sweep: all
    frames, or each frame weighted by `frame_weights` (a 0/1 mask gives sweeps of any N one
    compiled shape). The instrument is taken as it is, its modulator's roll-off included.
    Called outside a transformation it runs one compiled program per sweep length and options
    (`_run_compiled`)."""
    return _run_compiled(
        _fisher, instrument, distance_m, reflectance, effects, settings, frequency_only, range_falloff, frame_weights
    )


def crlb_from_fisher(fisher: Float[Array, "K K"]) -> Float[Array, ""]:
    """√[F⁻¹]₀₀ with a scaled solve (the unknowns' units differ by many decades)."""
    scale = jnp.sqrt(jnp.maximum(jnp.diag(fisher), 1e-300))
    normed = fisher / scale[:, None] / scale[None, :]
    e0 = jnp.zeros(fisher.shape[0]).at[0].set(1.0)
    inv00 = jnp.linalg.solve(normed + 1e-14 * jnp.eye(fisher.shape[0]), e0)[0]
    return jnp.sqrt(jnp.maximum(inv00, 0.0)) / scale[0]


def depth_crlb_m(
    instrument: Instrument,
    distance_m,
    reflectance,
    effects=SENSOR_NOISE,
    settings: EffectSettings | None = None,
    frequency_only: bool = False,
    range_falloff: bool = True,
    frame_weights: Float[Array, " N"] | None = None,
) -> Float[Array, ""]:
    """Depth CRLB (m) of one pixel: phase-locked (all of f_m) or frequency-only (`depth_fisher`)."""
    return _run_compiled(
        _crlb, instrument, distance_m, reflectance, effects, settings, frequency_only, range_falloff, frame_weights
    )


def _fisher(instrument, distance_m, reflectance, settings, frame_weights, *, effects, frequency_only, range_falloff):
    f = jnp.asarray(instrument.sweep.frequencies_hz, jnp.float64)
    echo_e = instrument.sensor.electrons(instrument.link.echo_power_w(distance_m, reflectance, range_falloff))
    idx = jnp.arange(f.shape[0], dtype=jnp.float64)

    def ports(theta):
        shift = theta[3] if frequency_only else 0.0
        returns = _returns(instrument, theta[0], theta[1], theta[2], echo_e)
        return expected_port_electrons(instrument, settings, returns, f + shift, idx, None, effects)[..., 0]

    theta0 = jnp.asarray([distance_m, 0.0, _CARRIER_PHASE_RAD] + ([0.0] if frequency_only else []), jnp.float64)
    mean = ports(theta0)
    var = jax.lax.stop_gradient(instrument.sensor.port_variance_e2(mean, effects))
    jac = jax.jacfwd(ports)(theta0)  # (4, N, K)
    w = jac / jnp.sqrt(var)[..., None]
    if frame_weights is not None:
        w = w * jnp.sqrt(frame_weights)[:, None]
    return jnp.einsum("kni,knj->ij", w, w)


def _crlb(instrument, distance_m, reflectance, settings, frame_weights, *, effects, frequency_only, range_falloff):
    fisher = _fisher(
        instrument,
        distance_m,
        reflectance,
        settings,
        frame_weights,
        effects=effects,
        frequency_only=frequency_only,
        range_falloff=range_falloff,
    )
    return crlb_from_fisher(fisher)


_STATIC_OPTIONS = ("effects", "frequency_only", "range_falloff")
_COMPILED = {
    _fisher: jax.jit(_fisher, static_argnames=_STATIC_OPTIONS),
    _crlb: jax.jit(_crlb, static_argnames=_STATIC_OPTIONS),
}


def _run_compiled(
    function, instrument, distance_m, reflectance, effects, settings, frequency_only, range_falloff, frame_weights
):
    """`function` as one compiled program, the instrument's, target's and settings' numbers its
    arguments (one program per sweep length and options), where no input is being traced; run
    op by op, the forward model's Jacobian was ~100 programs of its own to compile for each new
    sweep length, seconds before the first bound. Inside a transformation (the design's
    programs) it is traced inline, as part of the caller's program."""
    values = (instrument, distance_m, reflectance, settings or EffectSettings(), frame_weights)
    options = {"effects": tuple(effects), "frequency_only": bool(frequency_only), "range_falloff": bool(range_falloff)}
    traced = any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(values))
    return (function if traced else _COMPILED[function])(*values, **options)


# ----------------------------------------------------------------------------- closed forms
def iq_noise_and_tone_amplitude(
    instrument: Instrument, distance_m: float, reflectance: float, effects=SENSOR_NOISE, range_falloff: bool = True
) -> tuple[float, float]:
    """Per-sample σ of I (electrons) and the fundamental's amplitude a = √(N_l N_e)·2w₁ on a
    pixel of a target at `distance_m` with `reflectance`: I = V₀ − V₂ carries twice a port's
    variance (`Sensor.port_variance_e2` at its mean ¼(N_l + N_e)·S₀). With them the closed
    forms below give the bound of that pixel."""
    sensor, link, mzm = instrument.sensor, instrument.link, instrument.modulator
    n_ref = float(sensor.electrons(link.reference_power_per_pixel_w))
    n_echo = float(sensor.electrons(link.echo_power_w(distance_m, reflectance, range_falloff)))
    var_i = 2 * float(sensor.port_variance_e2(0.25 * (n_ref + n_echo) * float(mzm.mean_transmission()), effects))
    return math.sqrt(var_i), math.sqrt(n_ref * n_echo) * 2 * float(mzm.weights()[1])


def phase_locked_sigma_m(sum_angular_frequency_sq, tone_amplitude, noise_var):
    """Phase-locked depth CRLB (m) from Σ(2π f_m)² (rad²/s²), the tone's amplitude a and the
    noise variance σ² (NumPy or JAX arguments, a JAX result: `jnp.sqrt`, where `** 0.5` would
    compile to a `pow` call): c/2 · σ/√(a²/2·Σ(2π f_m)²). Valid when amplitude and offset
    decouple from τ (many cycles over the sweep)."""
    return C / 2 / jnp.sqrt(0.5 * tone_amplitude**2 * sum_angular_frequency_sq / noise_var)


def crlb_at_unit_snr_m(frequencies_hz, order: int = 1) -> float:
    """The phase-locked CRLB (m) of a pixel whose tone has SNR N·(A·w)²/σ² = 1, the SNR a
    depth file records; a pixel's CRLB is this over √snr, whatever estimator ran: with a = 2·A·w
    the tone's amplitude, a²/(2σ²)·Σ(2π·k·f_m)² = 2·snr/N·Σ(2π·k·f_m)² for order k."""
    f = np.asarray(frequencies_hz, np.float64)
    # snr = 1 is a²/σ² = 4/N: amplitude 2 over noise variance N
    return float(phase_locked_sigma_m(np.sum((2 * np.pi * order * f) ** 2), 2.0, float(f.size)))


def crlb_phase_locked_m(frequencies_hz, tone_amplitude, noise_sigma) -> float:
    """Closed-form CRLB (m) of depth for r = c + a·cos(2π f_m τ) + white noise of std σ, when
    the tone's phase is locked to τ (uses all f_m)."""
    f = np.asarray(frequencies_hz, np.float64)
    return float(phase_locked_sigma_m(np.sum((2 * np.pi * f) ** 2), tone_amplitude, noise_sigma**2))


def pixel_crlb_phase_locked_m(instrument: Instrument, distance_m: float, reflectance: float) -> float:
    """`crlb_phase_locked_m` of a pixel of a target at `distance_m` with `reflectance`, its
    tone amplitude and noise from `iq_noise_and_tone_amplitude` (sensor noise, range falloff)."""
    noise_sigma, tone_amplitude = iq_noise_and_tone_amplitude(instrument, distance_m, reflectance)
    return crlb_phase_locked_m(instrument.sweep.frequencies_hz, tone_amplitude, noise_sigma)


def crlb_frequency_only_m(num_frames: int, step_hz: float, tone_amplitude, noise_sigma, order: int = 1):
    """Closed-form CRLB (m) of depth from the tone's frequency alone on a uniform sweep (real
    sinusoid, unknown amplitude and phase; Kay, Example 3.14): var(ω) = 24σ²/(a²·N(N²−1)),
    ω in rad/frame, of the `order`-th harmonic."""
    n = num_frames
    var_omega = 24 * noise_sigma**2 / (tone_amplitude**2 * n * (n**2 - 1))
    return jnp.sqrt(var_omega) / (2 * np.pi * order * step_hz) * C / 2


def frequency_only_sigma_m(frequencies_hz, tone_amplitude, noise_var):
    """Frequency-only depth CRLB (m) of any schedule: only the spread of f_m about its mean
    informs τ when the tone's phase is a nuisance, var τ = σ²/(a²/2·Σ(2π(f_m − f̄))²)."""
    f = jnp.asarray(frequencies_hz)
    spread = jnp.sum((2 * jnp.pi * (f - jnp.mean(f))) ** 2)
    return C / 2 * jnp.sqrt(noise_var / (0.5 * tone_amplitude**2 * spread + 1e-300))


# ----------------------------------------------------------------------------- per-pixel bounds
# A fit is ill-posed where the offset and amplitude inflate the depth's variance by more than
# this factor, F_dd·[F⁻¹]_dd (see `variance_inflation`).
MAX_VARIANCE_INFLATION = 4.0
# A fitted tone carrying more than this multiple of the data's energy cancels itself against
# the offset (see `tone_cancels_offset`).
MAX_TONE_TO_DATA_ENERGY = 4.0


def depth_information(f_dd, f_da, f_aa, f_dc=None, f_cc=None, f_ca=None):
    """Depth information with the amplitude A — and the offset c, where its terms are given —
    as nuisances: the Schur complement F₀₀ − F₀ᵣ F_rr⁻¹ F_r0 of the Fisher matrix of
    (depth, [c,] A). With c its 2×2 block is inverted explicitly and ridged so a vanishing
    tone gives 0, not NaN; without (c already eliminated by mean-removed columns) it is
    F_dd − F_da²/F_aa."""
    if f_dc is None:
        return f_dd - f_da**2 / f_aa
    ridge = 1e-12 * (f_cc + f_aa) + 1e-300
    f_cc, f_aa = f_cc + ridge, f_aa + ridge
    det = f_cc * f_aa - f_ca**2
    return f_dd - (f_aa * f_dc**2 - 2 * f_ca * f_dc * f_da + f_cc * f_da**2) / det


def sigma_from_information(information):
    """σ = 1/√information where it is positive, ∞ where the data say nothing about depth."""
    return jnp.where(information > 0, 1 / jnp.sqrt(jnp.maximum(information, 1e-300)), jnp.inf)


def variance_inflation(f_dd, schur):
    """F_dd·[F⁻¹]_dd = F_dd / (F_dd − F_dr F_rr⁻¹ F_rd): how much not knowing the offset and
    amplitude inflates the depth's variance. ≈ 1 wherever the tone is a tone; it grows without
    bound within about half a bin of depth 0, where the tone flattens into a constant and
    trades off against the offset (noiseless, 3000 and 35 frames alike: 1.06 at 20 mm = 0.8
    bin, 1.5 at 15 mm, 19 at 10 mm, 550 at 5 mm). Measured on the 35-frame 10 Hz mode at low
    reflectance: inliers ≤ 1.014; pixels whose fit slid from a noise peak near DC to ~4 mm
    reported SNR 17–21 dB, amplitudes 3–7× the echo's and errors of ~100 mm (6σ) with
    inflations of 670–1240. Such fits are not valid (`MAX_VARIANCE_INFLATION`)."""
    return jnp.where(schur > 0, f_dd / jnp.where(schur > 0, schur, 1.0), jnp.inf)


def tone_cancels_offset(amplitude_coef, tone_norm_sq, data_norm_sq):
    """True where the fitted tone (coefficient `amplitude_coef` on a column of squared norm
    `tone_norm_sq`) carries more than `MAX_TONE_TO_DATA_ENERGY` × the data's energy: the tone
    column has become nearly collinear with the offset column (depth → 0, where the tone
    flattens into a constant) and the two cancel with huge coefficients. Seen at 35 frames on
    a noise peak near DC: amplitude 3·10⁵ against ~90 for real echoes, SNR 86 dB, σ 0.2 mm — a
    wild fit that every other check passed. A real echo's tone carries at most the data's
    energy plus noise."""
    return amplitude_coef**2 * tone_norm_sq > MAX_TONE_TO_DATA_ENERGY * data_norm_sq


def well_posed(amplitude, tone_sq, data_sq, f_dd, schur):
    """The fit is neither degenerate (`tone_cancels_offset`) nor has a depth variance inflated
    beyond `MAX_VARIANCE_INFLATION` by its nuisances: its σ may be reported as a CRLB."""
    return ~tone_cancels_offset(amplitude, tone_sq, data_sq) & (
        variance_inflation(f_dd, schur) <= MAX_VARIANCE_INFLATION
    )


def noise_estimate_inflation(num_frames: int) -> float:
    """√(ν/(ν − 2)) with ν = N − 2: the standard deviation of error/σ̂ when σ̂ comes from the
    carrier axis's orthogonal channel (N − 2 degrees of freedom), not the true noise — the
    spread of a Student t. 1.03 at 35 frames, 1.0003 at 3000."""
    dof = max(num_frames - 2, 3)
    return math.sqrt(dof / (dof - 2))


def amplitude_margin(snr):
    """1/(1 − 1/√(2·snr)): the CRLB evaluated at the fitted amplitude lowered by one standard
    error (σ_A/A ≤ 1/√(2·snr) for the peak-bin SNR N·(A·w)²/σ²), capped at 2. A pixel that
    passes the detection threshold was more often lucky than not: where few pixels pass, the
    ones that pass have amplitudes above their true ones and σ too small (measured at 35 frames,
    random depths: error/σ spread 1.12 at a true 16 dB, 1.25 at 14 dB). 1.11 at 16 dB, 1.03 at
    27 dB."""
    return 1 / (1 - jnp.minimum(1 / jnp.sqrt(2 * jnp.maximum(snr, 1e-30)), 0.5))


def reported_sigma_m(sigma_m, num_frames: int, snr):
    """The σ a depth file reports: an estimator's σ at the fitted values, widened for the
    noise estimate's own error (`noise_estimate_inflation`) and the amplitude's
    (`amplitude_margin`). Measured error/σ spread 0.92–1.06 from the 50 %-detection SNR up, at
    35–3000 frames (docs/physics.md)."""
    return sigma_m * noise_estimate_inflation(num_frames) * amplitude_margin(snr)


def sum_angular_frequency_sq_uniform(num_frames: int, start_hz: float, step_hz: float) -> float:
    """Σ_m (2π f_m)² (rad²/s²) of a uniform sweep in closed form (the phase-locked Fisher sum)."""
    n, f0, df = num_frames, start_hz, step_hz
    return (2 * math.pi) ** 2 * (n * f0**2 + f0 * df * n * (n - 1) + df**2 * (n - 1) * n * (2 * n - 1) / 6)
