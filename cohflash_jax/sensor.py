"""CCD model: photo-electrons from optical power, noise sources, gain, ADC."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import ArrayLike, Float

from .constants import PLANCK_J_S, SPEED_OF_LIGHT_M_PER_S
from .xp import namespace


class Sensor(eqx.Module):
    """One CCD of the coherent image sensor (all four share these settings).

    Defaults are typical of an InGaAs SWIR camera like the paper's Xenics Bobcat-320
    (14-bit ADC); they are plausible values, not measurements of that camera.
    """

    quantum_efficiency: Float[ArrayLike, ""] = 0.8
    exposure_s: Float[ArrayLike, ""] = 4e-3
    wavelength_m: Float[ArrayLike, ""] = 1550e-9
    dark_current_e_per_s: Float[ArrayLike, ""] = 1.0e4
    read_noise_e: Float[ArrayLike, ""] = 30.0
    full_well_e: Float[ArrayLike, ""] = 1.0e5
    dn_per_electron: Float[ArrayLike, ""] = 0.16
    adc_offset_dn: Float[ArrayLike, ""] = 200.0
    adc_bits: int = eqx.field(static=True, default=14)
    shot_noise_model: str = eqx.field(static=True, default="gaussian")

    def __check_init__(self):
        for name in ("quantum_efficiency", "exposure_s", "wavelength_m", "dn_per_electron", "full_well_e"):
            v = getattr(self, name)
            if isinstance(v, (int, float)) and not v > 0:
                raise ValueError(f"Sensor.{name} must be positive, got {v}")
        for name in ("dark_current_e_per_s", "read_noise_e"):
            v = getattr(self, name)
            if isinstance(v, (int, float)) and not v >= 0:
                raise ValueError(f"Sensor.{name} must be ≥ 0, got {v}")
        if not 1 <= self.adc_bits <= 16:
            raise ValueError(f"Sensor.adc_bits must be in 1..16, got {self.adc_bits}")
        if self.shot_noise_model not in ("gaussian", "poisson"):
            raise ValueError("Sensor.shot_noise_model must be 'gaussian' or 'poisson'")

    @property
    def photon_energy_j(self):
        """hν = h·c/λ (J)."""
        return PLANCK_J_S * SPEED_OF_LIGHT_M_PER_S / self.wavelength_m

    def electrons(self, power_w):
        """Mean photo-electrons per frame from optical power on a pixel, η·P·T_e/hν (NumPy on
        the host, `xp.namespace`)."""
        xp = namespace(power_w, self)
        return self.quantum_efficiency * xp.asarray(power_w) * self.exposure_s / self.photon_energy_j

    @property
    def dark_electrons(self):
        return self.dark_current_e_per_s * self.exposure_s

    @property
    def quantization_variance_e2(self):
        """ADC rounding as noise, in electrons²: one DN step is 1/g electrons, uniform ±½ step."""
        return (1.0 / self.dn_per_electron) ** 2 / 12.0

    def port_variance_e2(self, mean_e, effects, *, quantization: bool = True):
        """Variance (electrons²) of one port's sample with `mean_e` mean electrons: shot noise on
        them, dark-current shot noise, read noise and ADC rounding, each where `effects` lists
        it (`quantization=False` leaves the rounding out, where the caller rounds for real).

        The one noise model of cohflash: the simulator draws its Gaussian noise with this
        variance, and the Fisher information, the design's SNR and the tests' closed forms use
        it. Poisson shot noise (`shot_noise_model`) has the same variance. NumPy on the host
        (`xp.namespace`)."""
        xp = namespace(mean_e, self)
        var = xp.zeros_like(mean_e)
        if "shot_noise" in effects:
            var = var + xp.maximum(mean_e, 0.0)
        if "dark_current" in effects:
            var = var + xp.asarray(self.dark_electrons, var.dtype)
        if "read_noise" in effects:
            var = var + xp.asarray(self.read_noise_e, var.dtype) ** 2
        if quantization and "quantization" in effects:
            var = var + self.quantization_variance_e2
        return var

    @property
    def adc_max_dn(self) -> int:
        return 2**self.adc_bits - 1
