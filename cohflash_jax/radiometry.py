"""Link budget: probe power, distance and reflectance → optical power per pixel.

Echo power on one pixel from a Lambertian target of reflectance ρ at distance d,
flood-illuminated by a probe of power P spread evenly over the N_pix pixel footprints:

    P_e = (P/N_pix) · (ρ/π) · (A_rx/d²) · η_rx,      A_rx = π·(D/2)²

D is the receiver aperture and η_rx lumps every receive loss (optics, polarizer, hybrid
split losses, fill factor). The paper quotes 0.26 fW per pixel at 30.5 m for a 15.86 mW
probe; with D = 25.4 mm and a reference reflectance of 0.5, that fixes η_rx (below).
The link budget is per pixel of the paper's 320×256 format at any simulated size, so a
smaller simulated image is a lower-resolution view with the same per-pixel SNR.
"""

from __future__ import annotations

import math

import equinox as eqx
from jaxtyping import ArrayLike, Float

from .xp import namespace

PAPER_PROBE_POWER_W = 15.86e-3
PAPER_REFERENCE_POWER_PER_PIXEL_W = 0.64e-12
PAPER_ECHO_POWER_PER_PIXEL_W = 0.26e-15
PAPER_DISTANCE_M = 30.5
PAPER_PIXELS = 320 * 256
PAPER_REFLECTANCE = 0.5
APERTURE_DIAMETER_M = 25.4e-3


def _lambertian_factor(probe_w, pixels, aperture_m, distance_m):
    area = math.pi * (aperture_m / 2) ** 2
    return probe_w / pixels / math.pi * area / distance_m**2


# η_rx such that the defaults reproduce the paper's 0.26 fW at 30.5 m for ρ = 0.5 (≈ 1.5 %).
PAPER_RECEIVER_EFFICIENCY = PAPER_ECHO_POWER_PER_PIXEL_W / (
    PAPER_REFLECTANCE * _lambertian_factor(PAPER_PROBE_POWER_W, PAPER_PIXELS, APERTURE_DIAMETER_M, PAPER_DISTANCE_M)
)


class LinkBudget(eqx.Module):
    """Optical powers per pixel (W). Defaults: the paper's link budget."""

    probe_power_w: Float[ArrayLike, ""] = PAPER_PROBE_POWER_W
    reference_power_per_pixel_w: Float[ArrayLike, ""] = PAPER_REFERENCE_POWER_PER_PIXEL_W
    aperture_diameter_m: Float[ArrayLike, ""] = APERTURE_DIAMETER_M
    receiver_efficiency: Float[ArrayLike, ""] = PAPER_RECEIVER_EFFICIENCY
    reference_distance_m: Float[ArrayLike, ""] = PAPER_DISTANCE_M
    illuminated_pixels: int = eqx.field(static=True, default=PAPER_PIXELS)

    def __check_init__(self):
        for name in (
            "probe_power_w",
            "reference_power_per_pixel_w",
            "aperture_diameter_m",
            "receiver_efficiency",
            "reference_distance_m",
        ):
            v = getattr(self, name)
            if isinstance(v, (int, float)) and not v >= 0:
                raise ValueError(f"LinkBudget.{name} must be ≥ 0 (a power cannot be negative), got {v}")

    def echo_power_w(self, distance_m, reflectance, range_falloff: bool = True):
        """Echo power per pixel. Without range falloff, distance is pinned to the reference.
        NumPy on the host (a simulator's scene), jax.numpy under tracing (`xp.namespace`)."""
        xp = namespace(distance_m, reflectance, self)
        d = xp.asarray(distance_m if range_falloff else self.reference_distance_m)
        area = math.pi * (self.aperture_diameter_m / 2) ** 2
        per_pixel = self.probe_power_w / self.illuminated_pixels
        return per_pixel * xp.asarray(reflectance) / math.pi * area / xp.square(d) * self.receiver_efficiency
