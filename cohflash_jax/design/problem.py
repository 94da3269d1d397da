"""What a design must achieve and within which limits (`DesignProblem`, SI units), and the
parametrisation that holds the box constraints by construction (`decode`, `schedule`)."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..radiometry import LinkBudget
from ..sensor import Sensor


@dataclasses.dataclass(frozen=True)
class DesignProblem:
    """Targets and constraints of `optimise_design` (SI units)."""

    target_precision_m: float
    max_range_m: float
    distance_m: float = 30.5
    reflectance: float = 0.5
    max_power_w: float = 15.86e-3
    frame_rate_hz: float = 150.0
    min_frequency_hz: float = 0.1e9
    max_frequency_hz: float = 30e9
    max_modulation_index: float = 5.0
    schedule: str = "uniform"  # or "warped": f = start + span·u^p, p optimised
    max_frames: int = 32768
    saturation_fraction: float = 0.8  # exposure keeps the brightest port below this share of full well

    def __post_init__(self):
        for name in (
            "target_precision_m",
            "max_range_m",
            "distance_m",
            "max_power_w",
            "frame_rate_hz",
            "max_frequency_hz",
            "reflectance",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if self.reflectance > 1:
            raise ValueError(f"reflectance must be at most 1, got {self.reflectance}")
        if self.max_frequency_hz <= self.min_frequency_hz:
            raise ValueError("max_frequency_hz must exceed min_frequency_hz")
        if self.schedule not in ("uniform", "warped"):
            raise ValueError("schedule must be 'uniform' or 'warped'")
        sensor = Sensor()
        ref_rate = float(sensor.electrons(LinkBudget().reference_power_per_pixel_w)) / float(sensor.exposure_s)
        # brightest port: a quarter of the reference ideally; budget half of it (hybrid imbalance)
        t_sat = (
            self.saturation_fraction * float(sensor.full_well_e) / (0.5 * ref_rate + float(sensor.dark_current_e_per_s))
        )
        object.__setattr__(self, "_max_exposure_s", min(1.0 / self.frame_rate_hz, t_sat))

    def as_values(self) -> DesignProblem:
        """This problem with its numbers as 0-d float64 arrays: a compiled design program takes
        them as values, not as part of what it was compiled for, so a new target, range,
        power, frame rate or most frames runs the programs compiled already (one per schedule
        and frame cap). Only the schedule shapes a program."""
        return jax.tree.map(lambda value: np.asarray(value, np.float64), self)

    def max_step_hz(self, n):
        """Largest step: the unambiguous range, and the band's room for n frames (n may be traced)."""
        room = (self.max_frequency_hz - self.min_frequency_hz) / jnp.maximum(n - 1, 1)
        return jnp.minimum(C / (4 * self.max_range_m), room)

    def max_exposure_s(self) -> float:
        """Longest exposure: the frame period, or where the brightest port nears full well."""
        return self._max_exposure_s


_sig = jax.nn.sigmoid


def decode(z, n, problem: DesignProblem):
    """Unconstrained z → design variables inside their bounds (constraints by construction)."""
    step_max = problem.max_step_hz(n)
    span_max = problem.max_frequency_hz - problem.min_frequency_hz
    step = step_max * _sig(z[0])
    start = problem.min_frequency_hz + (span_max - (n - 1) * step) * _sig(z[1])
    x = 0.05 + (0.5 * problem.max_modulation_index - 0.05) * _sig(z[2])
    bias = 0.05 + (math.pi / 2 - 0.1) * _sig(z[3])
    exposure = problem.max_exposure_s() * (0.01 + 0.99 * _sig(z[4]))
    power = problem.max_power_w * _sig(z[5])
    warp = jnp.exp(0.7 * jnp.tanh(z[6])) if problem.schedule == "warped" else 1.0
    return {
        "step_hz": step,
        "start_hz": start,
        "modulation_index": 2 * x,
        "bias_rad": bias,
        "exposure_s": exposure,
        "probe_power_w": power,
        "warp": warp,
    }


def carry_over(z, n_from: int, n_to: int, problem: DesignProblem) -> np.ndarray:
    """z of a design of `n_from` frames → z of the design of `n_to` frames with the same start
    frequency and step (where they fit the band and the range's largest step) and the same
    other variables: a warm start that keeps the design, where the same z would not (`decode`
    scales the step and start to the frames). Host-side."""
    z = np.array(z, np.float64)
    v = decode(z, n_from, problem)
    step_max = float(problem.max_step_hz(n_to))
    step = min(float(v["step_hz"]), step_max)
    room = problem.max_frequency_hz - problem.min_frequency_hz - (n_to - 1) * step
    share = (float(v["start_hz"]) - problem.min_frequency_hz) / room if room > 0 else 0.5
    logit = lambda p: math.log(p / (1 - p))
    z[0] = logit(min(max(step / step_max, 1e-3), 1 - 1e-3))
    z[1] = logit(min(max(share, 1e-3), 1 - 1e-3))
    return z


def schedule(v, n, n_cap):
    """Frequencies (n_cap,) of which the first n are used: uniform (warp 1), or warped
    f = start + span·u^p over the same band (p < 1 crowds frames towards the top)."""
    m = jnp.arange(n_cap, dtype=jnp.float64)
    span = (n - 1) * v["step_hz"]
    u = jnp.clip(m / jnp.maximum(n - 1, 1), 0.0, 1.0)
    return v["start_hz"] + span * u ** v["warp"]


# A `DesignProblem` is a pytree: its numbers are leaves (values a compiled program takes), its
# schedule the structure (what a program is compiled for; the frames it holds are an argument of
# their own, `frame_cap`). Unflattening sets the fields as they come, without `__post_init__`'s
# checks: inside a program they are traced.
_PROBLEM_STRUCTURE = ("schedule",)
_PROBLEM_VALUES = tuple(f.name for f in dataclasses.fields(DesignProblem) if f.name not in _PROBLEM_STRUCTURE) + (
    "_max_exposure_s",
)


def _flatten_problem(problem: DesignProblem):
    return tuple(getattr(problem, name) for name in _PROBLEM_VALUES), tuple(
        getattr(problem, name) for name in _PROBLEM_STRUCTURE
    )


def _unflatten_problem(structure, values) -> DesignProblem:
    problem = object.__new__(DesignProblem)
    for name, value in zip(_PROBLEM_STRUCTURE + _PROBLEM_VALUES, tuple(structure) + tuple(values)):
        object.__setattr__(problem, name, value)
    return problem


jax.tree_util.register_pytree_node(DesignProblem, _flatten_problem, _unflatten_problem)
