"""The design's parameters: names and units at the edge (CLI, CSV: the paper's units), SI
inside, and the one builder of an `Instrument` from SI values (`design_instrument`), which
the CRLB grid, the Monte Carlo and the gradient design all use."""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from ..instrument import Instrument
from ..modulator import MZM
from ..radiometry import LinkBudget
from ..sensor import Sensor
from ..sweep import FrequencySweep


@dataclasses.dataclass(frozen=True)
class Parameter:
    """A sweepable parameter: its help, the paper's value in its unit, and unit → SI."""

    help: str
    paper_value: float
    si_name: str
    si_per_unit: float = 1.0


PARAMETERS: dict[str, Parameter] = {
    "bandwidth_ghz": Parameter("sweep bandwidth N·Δf (GHz); sets the step with num_steps", 5.91, "bandwidth_hz", 1e9),
    "start_ghz": Parameter("first microwave frequency (GHz)", 0.1, "start_hz", 1e9),
    "step_mhz": Parameter("frequency step Δf (MHz); alternative to bandwidth_ghz", 1.97, "step_hz", 1e6),
    "num_steps": Parameter("frames per capture N (one per frequency step)", 3000, "num_steps"),
    "distance_m": Parameter("target distance (m)", 30.5, "distance_m"),
    "probe_power_mw": Parameter("probe optical power (mW)", 15.86, "probe_power_w", 1e-3),
    "exposure_ms": Parameter("CCD exposure (ms)", 4.0, "exposure_s", 1e-3),
    "modulation_index": Parameter("MZM modulation index β", 2.0, "modulation_index"),
    "bias_rad": Parameter("MZM bias angle θ_b (rad)", math.pi / 4, "bias_rad"),
    "reflectance": Parameter("target reflectance", 0.5, "reflectance"),
    "frame_rate_hz": Parameter("camera frame rate (Hz): acquisition time = N / frame rate", 150.0, "frame_rate_hz"),
    "range_falloff": Parameter(
        "1: echo power ∝ 1/distance²; 0: the 30.5 m link budget at any distance (depth "
        "then only sets the tone's phase)",
        1.0,
        "range_falloff",
    ),
}
# Limits of a plausible design point (paper units): refused beyond them
PLAUSIBLE = {
    "reflectance": (0.0, 1.0),
    "bias_rad": (0.0, math.pi),
    "modulation_index": (0.0, 40.0),
    "start_ghz": (0.0, 1e3),  # a microwave frequency: not negative, below a THz
    "bandwidth_ghz": (0.0, 1e3),
    "distance_m": (0.0, 1e5),
    "probe_power_mw": (0.0, 1e6),
    "frame_rate_hz": (0.0, 1e7),
    "num_steps": (4, 1e8),
}


def complete_point(point: dict) -> dict:
    """Fill a design point (paper units) from the paper's values and derive the step or the
    bandwidth, checking what must be positive and plausible."""
    full = {k: p.paper_value for k, p in PARAMETERS.items()}
    full.update(point)
    n = int(full["num_steps"])
    if n < 4:
        raise ValueError(f"num_steps must be ≥ 4, got {n}")
    if "bandwidth_ghz" in point and "step_mhz" in point:
        if not math.isclose(point["bandwidth_ghz"], point["step_mhz"] * n / 1e3, rel_tol=1e-9):
            raise ValueError("give either bandwidth_ghz or step_mhz, not both")
    elif "bandwidth_ghz" in point:
        full["step_mhz"] = full["bandwidth_ghz"] * 1e3 / n
    else:
        full["bandwidth_ghz"] = full["step_mhz"] * n / 1e3
    for name in ("distance_m", "probe_power_mw", "exposure_ms", "frame_rate_hz", "step_mhz"):
        if not full[name] > 0:
            raise ValueError(f"{name} must be positive, got {full[name]}")
    for name, (lo, hi) in PLAUSIBLE.items():
        if not lo <= full[name] <= hi:
            raise ValueError(f"{name} = {full[name]:g} is outside its plausible range [{lo:g}, {hi:g}]")
    if full["exposure_ms"] > 1e3 / full["frame_rate_hz"]:
        raise ValueError(f"exposure {full['exposure_ms']} ms exceeds the frame period at {full['frame_rate_hz']} Hz")
    return full


def to_si(point: dict) -> dict:
    """A completed point (paper units) in SI, keyed by each parameter's SI name."""
    return {p.si_name: float(point[name]) * p.si_per_unit for name, p in PARAMETERS.items()}


def design_instrument(
    *,
    start_hz,
    step_hz,
    num_steps: int,
    probe_power_w,
    exposure_s,
    modulation_index,
    bias_rad,
    frame_rate_hz: float = 150.0,
    frequencies_hz=None,
) -> Instrument:
    """The instrument of a design point (SI values; jittable and vmappable: values may be
    traced). The schedule is uniform, f_m = start + m·step, unless `frequencies_hz` is given."""
    if frequencies_hz is None:
        frequencies_hz = start_hz + step_hz * jnp.arange(num_steps, dtype=jnp.float64)
        if not any(isinstance(v, jnp.ndarray) for v in (start_hz, step_hz)):
            frequencies_hz = float(start_hz) + float(step_hz) * np.arange(num_steps, dtype=np.float64)
    return Instrument(
        sweep=FrequencySweep(frequencies_hz),
        modulator=MZM(modulation_index, bias_rad),
        sensor=Sensor(exposure_s=exposure_s),
        link=LinkBudget(probe_power_w=probe_power_w),
        frame_rate_hz=frame_rate_hz,
    )


def variables_instrument(variables: dict, num_steps: int, frequencies_hz=None, frame_rate_hz: float = 150.0):
    """The instrument of decoded design variables (`problem.decode`'s start_hz, step_hz,
    probe_power_w, exposure_s, modulation_index, bias_rad; traced or concrete)."""
    v = variables
    return design_instrument(
        start_hz=v["start_hz"],
        step_hz=v["step_hz"],
        num_steps=num_steps,
        probe_power_w=v["probe_power_w"],
        exposure_s=v["exposure_s"],
        modulation_index=v["modulation_index"],
        bias_rad=v["bias_rad"],
        frame_rate_hz=frame_rate_hz,
        frequencies_hz=frequencies_hz,
    )


def point_instrument(point: dict, frequencies_hz=None) -> Instrument:
    """The instrument of a completed design point (paper units), optionally with its own schedule."""
    si = to_si(complete_point(point))
    return design_instrument(
        start_hz=si["start_hz"],
        step_hz=si["step_hz"],
        num_steps=int(si["num_steps"]),
        probe_power_w=si["probe_power_w"],
        exposure_s=si["exposure_s"],
        modulation_index=si["modulation_index"],
        bias_rad=si["bias_rad"],
        frame_rate_hz=si["frame_rate_hz"],
        frequencies_hz=frequencies_hz,
    )


def ambiguity_m(point: dict) -> float:
    """Unambiguous depth interval of a point's uniform sweep, c/(4Δf)."""
    return C / (4 * float(point["step_mhz"]) * 1e6)


def parse_axis(spec: str) -> tuple[str, np.ndarray]:
    """'name=a:b:n' (linear), 'name=a:b:n:log', or 'name=v1,v2,…' → (name, values)."""
    if "=" not in spec:
        raise ValueError(f"sweep axis {spec!r}: expected NAME=START:STOP:COUNT[:log] or NAME=V1,V2,…")
    name, text = spec.split("=", 1)
    name = name.strip()
    if name not in PARAMETERS:
        raise ValueError(f"unknown sweep parameter {name!r}; known: {', '.join(PARAMETERS)}")
    try:
        if ":" in text:
            parts = text.split(":")
            lo, hi, n = float(parts[0]), float(parts[1]), int(parts[2])
            log = len(parts) > 3 and parts[3] == "log"
            if n < 1 or (log and (lo <= 0 or hi <= 0)):
                raise ValueError
            values = np.geomspace(lo, hi, n) if log else np.linspace(lo, hi, n)
        else:
            values = np.array([float(v) for v in text.split(",") if v.strip()])
    except (ValueError, IndexError):
        raise ValueError(f"sweep axis {spec!r}: could not read the values") from None
    if name == "num_steps":
        values = np.round(values)
    if values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError(f"sweep axis {spec!r}: no finite values")
    return name, values
