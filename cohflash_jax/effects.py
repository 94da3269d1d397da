"""The opt-in effects a scene may call for (docs/physics.md) and the settings of the scene's own.

A scene lists the effects it wants; the simulator computes exactly those. An effect that is
not listed is not computed and draws no random numbers. To add an effect: name it in
`KNOWN_EFFECTS`, put its parameters here (a property of the scene or the air path) or on
`InstrumentErrors` (a departure of the instrument), and switch it on in the one simulator
stage where it acts (`simulate.build_returns`, `expected_port_electrons` or `sensor_readout`).
"""

from __future__ import annotations

from collections.abc import Iterable

import equinox as eqx

KNOWN_EFFECTS: dict[str, str] = {
    "sidebands": "Bessel orders beyond ±1: harmonics of the beat tone (and their aliases)",
    "beta_rolloff": "the modulator's true roll-off β(f) = β/√(1+(f/f_3dB)²), f_3dB from the instrument's errors",
    "hybrid_errors": "per-CCD hybrid phase errors, gain mismatch and offsets (the instrument's errors)",
    "shot_noise": "photon shot noise on all photo-electrons (Gaussian limit or Poisson)",
    "dark_current": "dark electrons and their shot noise",
    "read_noise": "Gaussian read noise",
    "quantization": "ADC rounding to integer DN (uint16 frames, clipped to the ADC range)",
    "saturation": "full-well clipping of electrons and ADC clipping of DN",
    "background_light": "incoherent background light: common mode plus its shot noise",
    "speckle": "several random scatterers per pixel (random complex amplitudes, depth spread)",
    "turbulence": "slow random drift of the optical carrier phase over the frames",
    "motion": "radial motion during the sweep: τ(t) and the carrier's Doppler phase",
    "misregistration": "CCDs 2–4 see the scene shifted/rotated against CCD 1 (the instrument's errors)",
    "range_falloff": "echo power ∝ reflectance / distance² (else ∝ reflectance only)",
    "mixed_pixels": "sub-pixel sampling: pixels on depth edges hold several returns",
}


def parse_effects(effects: str | Iterable[str] | None) -> tuple[str, ...]:
    """Validate effect names (comma-separated string or iterable) → sorted tuple."""
    if effects is None:
        return ()
    if isinstance(effects, str):
        names = [e.strip() for e in effects.split(",") if e.strip()]
    else:
        names = [str(e).strip() for e in effects]
    unknown = sorted(set(names) - set(KNOWN_EFFECTS))
    if unknown:
        raise ValueError(
            f"unknown effect(s) {', '.join(map(repr, unknown))}; known effects: " + ", ".join(KNOWN_EFFECTS)
        )
    return tuple(sorted(set(names)))


class EffectSettings(eqx.Module):
    """Parameters of the scene's and the air path's effects; used only for effects a scene
    switches on. The instrument's own departures (hybrid errors, the modulator's roll-off,
    misregistration) are not here: they belong to the instrument (`InstrumentErrors`)."""

    background_power_per_pixel_w: float = 50e-15
    speckle_scatterers: int = eqx.field(static=True, default=4)
    surface_roughness_m: float = 0.5e-3
    turbulence_rad_per_sqrt_frame: float = 0.05
    radial_velocity_m_per_s: float = 2e-6
    mixed_pixel_subsamples: int = eqx.field(static=True, default=2)
