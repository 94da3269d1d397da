"""The opt-in effects a scene may call for (DESIGN.md §2) and their settings.

A scene lists the effects it wants; the simulator computes exactly those. An effect
that is not listed is not computed and draws no random numbers.
"""

from __future__ import annotations

from collections.abc import Iterable

import equinox as eqx
import numpy as np
from jaxtyping import ArrayLike, Float

KNOWN_EFFECTS: dict[str, str] = {
    "sidebands": "Bessel orders beyond ±1: harmonics of the beat tone (and their aliases)",
    "beta_rolloff": "modulation index falling with frequency, β(f) = β/√(1+(f/f_3dB)²)",
    "hybrid_errors": "per-CCD hybrid phase errors, gain mismatch and offsets",
    "shot_noise": "photon shot noise on all photo-electrons (Gaussian limit or Poisson)",
    "dark_current": "dark electrons and their shot noise",
    "read_noise": "Gaussian read noise",
    "quantization": "ADC rounding to integer DN (uint16 frames, clipped to the ADC range)",
    "saturation": "full-well clipping of electrons and ADC clipping of DN",
    "background_light": "incoherent background light: common mode plus its shot noise",
    "speckle": "several random scatterers per pixel (random complex amplitudes, depth spread)",
    "turbulence": "slow random drift of the optical carrier phase over the frames",
    "motion": "radial motion during the sweep: τ(t) and the carrier's Doppler phase",
    "misregistration": "CCDs 2–4 see the scene shifted/rotated against CCD 1",
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
        raise ValueError(f"unknown effect(s) {', '.join(map(repr, unknown))}; known effects: "
                         + ", ".join(KNOWN_EFFECTS))
    return tuple(sorted(set(names)))


_DEG = np.pi / 180


class EffectSettings(eqx.Module):
    """Parameters of the opt-in effects; used only for effects a scene switches on."""

    hybrid_phase_error_rad: Float[ArrayLike, "4"] = (0.0, 5 * _DEG, -3 * _DEG, 4 * _DEG)
    hybrid_relative_gains: Float[ArrayLike, "4"] = (1.0, 1.10, 0.95, 1.05)
    hybrid_offset_error_dn: Float[ArrayLike, "4"] = (0.0, 25.0, -15.0, 10.0)
    beta_rolloff_3db_hz: float = 8.0e9  # 20 % roll-off at 6 GHz
    background_power_per_pixel_w: float = 50e-15
    speckle_scatterers: int = eqx.field(static=True, default=4)
    surface_roughness_m: float = 0.5e-3
    turbulence_rad_per_sqrt_frame: float = 0.05
    radial_velocity_m_per_s: float = 2e-6
    # rows: CCD 2, 3, 4; columns: dx (px), dy (px), rotation (deg) of the sampled scene
    misregistration_px_px_deg: tuple = ((0.6, -0.4, 0.10), (-0.5, 0.3, -0.15), (0.3, 0.5, 0.05))
    mixed_pixel_subsamples: int = eqx.field(static=True, default=2)
