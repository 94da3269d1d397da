"""The whole instrument: sweep, modulator, hybrid, sensor, link budget, timing, optics."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import ArrayLike, Float

from .hybrid import Hybrid
from .modulator import MZM
from .radiometry import LinkBudget
from .sensor import Sensor
from .sweep import FrequencySweep


class Instrument(eqx.Module):
    """Everything about the LiDAR that is not the scene.

    `hybrid` holds the nominal hybrid (what reconstruction assumes); the simulator's
    `hybrid_errors` effect perturbs it. `system_delay_s` is τ_sys, the fixed delay of the
    echo path against the reference that is not target distance.
    """

    sweep: FrequencySweep
    modulator: MZM = MZM()
    hybrid: Hybrid = Hybrid()
    sensor: Sensor = Sensor()
    link: LinkBudget = LinkBudget()
    system_delay_s: Float[ArrayLike, ""] = 0.0
    frame_rate_hz: float = eqx.field(static=True, default=150.0)
    field_of_view_deg: tuple[float, float] = eqx.field(static=True, default=(0.72, 0.58))

    def __check_init__(self):
        if not self.frame_rate_hz > 0:
            raise ValueError(f"frame_rate_hz must be positive, got {self.frame_rate_hz}")
        if isinstance(self.sensor.exposure_s, (int, float)) and self.sensor.exposure_s > 1 / self.frame_rate_hz:
            raise ValueError(f"exposure {self.sensor.exposure_s} s exceeds the frame period "
                             f"{1 / self.frame_rate_hz:.4g} s")

    @classmethod
    def paper(cls, num_steps: int = 3000, **kwargs) -> "Instrument":
        """The paper's set-up: 0.1 GHz + m·1.97 MHz, 150 frames/s, 4 ms exposure, 15.86 mW."""
        return cls(sweep=FrequencySweep.paper(num_steps), **kwargs)


def differentiable(tree):
    """Turn every Python float leaf of a parameter pytree into a float64 array, so that
    `eqx.filter_grad` / `jax.grad` differentiate with respect to it (equinox treats Python
    floats as static constants)."""
    import jax
    import jax.numpy as jnp

    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if isinstance(x, float) else x, tree)
