"""The whole instrument: sweep, modulator, hybrid, sensor, link budget, timing, optics — and
how the real one departs from that description (`InstrumentErrors`, the simulator's truth).

Every stage takes an `Instrument`: the simulator, the Fisher information and the design
(what the instrument is), reconstruction, calibration and the posteriors (what it is believed
to be: a capture's nominal description, `Capture.instrument`, or a calibrated one,
`Calibration.apply`).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .hybrid import Hybrid
from .modulator import MZM
from .radiometry import PAPER_PROBE_POWER_W, LinkBudget
from .sensor import Sensor
from .sweep import FrequencySweep

# Full field of view (horizontal, vertical) of the paper's receiver: 320×256 pixels over
# 0.72°×0.58° at 30.5 m (≈ 1.2 mm a pixel). Used where a capture does not state its own.
DEFAULT_FIELD_OF_VIEW_DEG = (0.72, 0.58)
DEFAULT_FRAME_RATE_HZ = 150.0
TEN_HZ_FRAMES = 35  # frames of the paper's 10 Hz mode

_DEG = math.pi / 180


class InstrumentErrors(eqx.Module):
    """How the real instrument departs from its description: what calibration measures, and
    what the simulator makes true. Reconstruction never reads it (it knows only the
    description, nominal or calibrated).

    Each departure acts in a simulation only where the scene lists its effect:
    `hybrid_errors` (phase errors, gain factors and offsets of CCDs 1–4, CCD 1 the gauge),
    `beta_rolloff` (the modulator's true roll-off replaces the described one) and
    `misregistration` (CCDs 2–4 see the scene shifted and rotated against CCD 1). The
    defaults are plausible errors of a free-space hybrid, not measurements."""

    hybrid_phase_error_rad: Float[ArrayLike, "4"] = (0.0, 5 * _DEG, -3 * _DEG, 4 * _DEG)
    hybrid_gain_factors: Float[ArrayLike, "4"] = (1.0, 1.10, 0.95, 1.05)
    hybrid_offset_error_dn: Float[ArrayLike, "4"] = (0.0, 25.0, -15.0, 10.0)
    modulator_rolloff_3db_hz: Float[ArrayLike, ""] = 8.0e9  # 20 % roll-off of β at 6 GHz
    # rows: CCD 2, 3, 4; columns: dx (px), dy (px), rotation (deg) of the sampled scene
    misregistration_px_px_deg: tuple = ((0.6, -0.4, 0.10), (-0.5, 0.3, -0.15), (0.3, 0.5, 0.05))

    def __check_init__(self):
        for name in ("hybrid_phase_error_rad", "hybrid_gain_factors", "hybrid_offset_error_dn"):
            if np.shape(getattr(self, name)) != (4,):
                raise ValueError(f"InstrumentErrors.{name} must have shape (4,), got {np.shape(getattr(self, name))}")
        if np.shape(self.misregistration_px_px_deg) != (3, 3):
            raise ValueError("misregistration_px_px_deg must be 3 rows (CCD 2–4) of (dx_px, dy_px, rot_deg)")

    def true_hybrid(self, hybrid: Hybrid) -> Hybrid:
        """The hybrid the light really meets: the described one with these errors."""
        return Hybrid(
            phases_rad=_combine(hybrid.phases_rad, self.hybrid_phase_error_rad, np.add, jnp.add),
            relative_gains=_combine(hybrid.relative_gains, self.hybrid_gain_factors, np.multiply, jnp.multiply),
            offsets_dn=_combine(hybrid.offsets_dn, self.hybrid_offset_error_dn, np.add, jnp.add),
        )

    def true_modulator(self, modulator: MZM) -> MZM:
        """The modulator with its true roll-off."""
        return dataclasses.replace(modulator, rolloff_3db_hz=self.modulator_rolloff_3db_hz)

    def ccd_transforms(self, effects) -> list[tuple[float, float, float]]:
        """(dx px, dy px, rotation deg) of the scene each CCD samples: CCD 1 none, CCDs 2–4
        theirs where `misregistration` is listed; one entry (all CCDs alike) otherwise."""
        if "misregistration" not in effects:
            return [(0.0, 0.0, 0.0)]
        rows = np.asarray(self.misregistration_px_px_deg, dtype=np.float64)
        return [(0.0, 0.0, 0.0)] + [tuple(r) for r in rows]


def _combine(a, b, host_op, traced_op):
    """a ∘ b for a part and its error: a tuple of floats where both are host values (static
    under jit, as a described part is), an array where either is traced (differentiation)."""
    if any(isinstance(x, jax.Array) for x in (a, b)):
        return traced_op(jnp.asarray(a), jnp.asarray(b))
    return tuple(float(v) for v in host_op(np.asarray(a, np.float64), np.asarray(b, np.float64)))


class Instrument(eqx.Module):
    """Everything about the LiDAR that is not the scene.

    `hybrid`, `modulator` and `system_delay_s` are the instrument as described: nominal, or
    calibrated. `system_delay_s` is τ_sys, the fixed delay of the echo path against the
    reference that is not target distance. `errors` are the real instrument's departures from
    that description (`InstrumentErrors`; only the simulator reads them, `truth`)."""

    sweep: FrequencySweep
    modulator: MZM = MZM()
    hybrid: Hybrid = Hybrid()
    sensor: Sensor = Sensor()
    link: LinkBudget = LinkBudget()
    system_delay_s: Float[ArrayLike, ""] = 0.0
    errors: InstrumentErrors = InstrumentErrors()
    frame_rate_hz: float = eqx.field(static=True, default=DEFAULT_FRAME_RATE_HZ)
    field_of_view_deg: tuple[float, float] = eqx.field(static=True, default=DEFAULT_FIELD_OF_VIEW_DEG)

    def __check_init__(self):
        if not self.frame_rate_hz > 0:
            raise ValueError(f"frame_rate_hz must be positive, got {self.frame_rate_hz}")
        if isinstance(self.sensor.exposure_s, (int, float)) and self.sensor.exposure_s > 1 / self.frame_rate_hz:
            raise ValueError(
                f"exposure {self.sensor.exposure_s} s exceeds the frame period {1 / self.frame_rate_hz:.4g} s"
            )
        fov = np.asarray(self.field_of_view_deg, dtype=np.float64)
        if fov.shape != (2,) or not np.all(np.isfinite(fov)) or not np.all((fov > 0) & (fov < 180)):
            raise ValueError(
                "field_of_view_deg must be two angles (horizontal, vertical) in (0°, 180°), "
                f"got {self.field_of_view_deg}"
            )

    @classmethod
    def paper(cls, num_steps: int = 3000, **kwargs) -> Instrument:
        """The paper's set-up: 0.1 GHz + m·1.97 MHz, 150 frames/s, 4 ms exposure, 15.86 mW."""
        return cls(sweep=FrequencySweep.paper(num_steps), **kwargs)

    @classmethod
    def ten_hz_mode(cls, **kwargs) -> Instrument:
        """The paper's 10 Hz mode as the benchmark runs it: 35 frames over 0.17–6 GHz
        (f_0 = Δf), 350 frames/s, 2 ms exposures, 10× the paper's probe power."""
        n = TEN_HZ_FRAMES
        parts = {
            "frame_rate_hz": 350.0,
            "sensor": Sensor(exposure_s=2e-3),
            "link": LinkBudget(probe_power_w=10 * PAPER_PROBE_POWER_W),
            **kwargs,
        }
        return cls(sweep=FrequencySweep.uniform(6e9 / n, 6e9 / n, n), **parts)

    def truth(self, effects) -> Instrument:
        """The instrument as a simulation of a scene with `effects` makes it: the described
        parts with the departures (`errors`) whose effects are listed."""
        hybrid = self.errors.true_hybrid(self.hybrid) if "hybrid_errors" in effects else self.hybrid
        modulator = self.errors.true_modulator(self.modulator) if "beta_rolloff" in effects else self.modulator
        return dataclasses.replace(self, hybrid=hybrid, modulator=modulator)

    def replace(self, **parts) -> Instrument:
        """A copy with some parts replaced (e.g. `hybrid=`, `modulator=`, `system_delay_s=`)."""
        return dataclasses.replace(self, **parts)


def differentiable(tree):
    """Turn every Python float leaf of a parameter pytree into a float64 array, so that
    `eqx.filter_grad` / `jax.grad` differentiate with respect to it (equinox treats Python
    floats as static constants)."""
    return jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64) if isinstance(x, float) else x, tree)
