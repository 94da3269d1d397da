"""Independent truth for the tests: closed-form bounds of a real tone in white noise, written
here from the textbook formulas (not imported from the package), and the I/Q noise and tone
amplitude of a pixel from the sensor's one noise model (`Sensor.port_variance_e2`) and
docs/design-reference.md §1's port signal."""

import numpy as np

C = 299_792_458.0


def closed_form_noise_and_amplitude(inst, reflectance: float, distance_m: float = 30.5):
    """Per-sample σ of I = V₀ − V₂ (electrons) and the fundamental's amplitude a = √(N_l N_e)·2w₁
    (docs/design-reference.md §1: a port carries ¼(N_l + N_e)·S₀ on average; I carries two ports' variance)."""
    s, link, mzm = inst.sensor, inst.link, inst.modulator
    n_ref = float(s.electrons(link.reference_power_per_pixel_w))
    n_echo = float(s.electrons(link.echo_power_w(distance_m, reflectance)))
    effects = ("shot_noise", "dark_current", "read_noise", "quantization")
    var_i = 2 * float(s.port_variance_e2(0.25 * (n_ref + n_echo) * float(mzm.mean_transmission()), effects))
    return np.sqrt(var_i), np.sqrt(n_ref * n_echo) * 2 * float(mzm.weights()[1])


def crlb_phase_locked_m(frequencies_hz, tone_amplitude, noise_sigma) -> float:
    """r = c + a·cos(2π f_m τ) + white noise, the tone's phase locked to τ:
    var τ = σ²/(a²/2 · Σ(2π f_m)²)."""
    f = np.asarray(frequencies_hz, np.float64)
    info = 0.5 * tone_amplitude**2 * np.sum((2 * np.pi * f) ** 2) / noise_sigma**2
    return C / 2 / np.sqrt(info)


def crlb_frequency_only_m(num_frames: int, step_hz: float, tone_amplitude, noise_sigma, order: int = 1) -> float:
    """The tone's frequency alone (Kay, Example 3.14): var ω = 24σ²/(a²N(N²−1)), ω in rad/frame."""
    n = num_frames
    var_omega = 24 * noise_sigma**2 / (tone_amplitude**2 * n * (n**2 - 1))
    return float(np.sqrt(var_omega) / (2 * np.pi * order * step_hz) * C / 2)
