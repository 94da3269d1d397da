"""The design command's result: the optimum, optionally a warped schedule beside it, and its
Monte Carlo validation → a JSON document and a summary."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..constants import SPEED_OF_LIGHT_M_PER_S as C
from .monte_carlo import monte_carlo
from .optimise import DesignResult, frame_cap, meets, optimise_design, solve_for_n
from .problem import DesignProblem

DESIGN_FORMAT = "cohflash-design"


def design_point(result: DesignResult, problem: DesignProblem) -> dict:
    """The optimum as a sweep/Monte Carlo point (paper units)."""
    return optimum_point(result.variables, result.num_frames, dataclasses.asdict(problem))


def optimum_point(variables: dict, num_frames: int, problem: dict) -> dict:
    """A design's optimum (its SI `variables`, frame count and problem, as a design JSON holds
    them) as a sweep/Monte Carlo point (paper units)."""
    v = variables
    return {
        "start_ghz": v["start_hz"] / 1e9,
        "step_mhz": v["step_hz"] / 1e6,
        "num_steps": num_frames,
        "distance_m": problem["distance_m"],
        "reflectance": problem["reflectance"],
        "probe_power_mw": v["probe_power_w"] * 1e3,
        "exposure_ms": v["exposure_s"] * 1e3,
        "modulation_index": v["modulation_index"],
        "bias_rad": v["bias_rad"],
        "frame_rate_hz": problem["frame_rate_hz"],
    }


def design_report(
    problem: DesignProblem, compare_warped: bool = False, validate_trials: int = 256, progress: bool = True
) -> dict:
    """Optimise, optionally compare a warped schedule at the same frame count, validate by
    Monte Carlo at the optimum → {"document": JSON-able dict, "text": summary}."""
    result = optimise_design(problem, progress)
    v = result.variables
    doc = {
        "format": DESIGN_FORMAT,
        "format_version": 1,
        "problem": dataclasses.asdict(problem),
        "feasible": result.feasible,
        "note": result.note,
        "num_frames": result.num_frames,
        "acquisition_s": result.acquisition_s,
        "crlb_mm": result.crlb_m * 1e3,
        "coarse_crlb_mm": result.coarse_crlb_m * 1e3,
        "variables": v,
        "active_constraints": result.active_constraints,
        "unambiguous_range_m": C / (4 * float(np.max(np.diff(result.frequencies_hz)))),
        "frequencies_hz": {"first": float(result.frequencies_hz[0]), "last": float(result.frequencies_hz[-1])},
    }
    lines = [
        ("optimum" if result.feasible else "NOT FEASIBLE: " + result.note),
        f"  {result.num_frames} frames = {result.acquisition_s:.4g} s at {problem.frame_rate_hz:g} frames/s; "
        f"CRLB {result.crlb_m * 1e3:.4g} mm (target {problem.target_precision_m * 1e3:g} mm)",
        f"  sweep {result.frequencies_hz[0] / 1e9:.4f} … {result.frequencies_hz[-1] / 1e9:.4f} GHz, step "
        f"{v['step_hz'] / 1e6:.4g} MHz (unambiguous to {doc['unambiguous_range_m']:.4g} m)",
        f"  modulation index {v['modulation_index']:.3f}, bias {v['bias_rad']:.3f} rad, exposure "
        f"{v['exposure_s'] * 1e3:.4g} ms, probe power {v['probe_power_w'] * 1e3:.4g} mW",
        "  active constraints: " + ("; ".join(result.active_constraints) or "none"),
    ]
    if compare_warped and result.feasible:
        warped_problem = dataclasses.replace(problem, schedule="warped")
        _, ev_w = solve_for_n(result.num_frames, frame_cap(problem, result.num_frames), warped_problem)
        ok = meets(ev_w, problem)
        doc["warped"] = {
            "crlb_mm": ev_w.crlb_m * 1e3,
            "coarse_crlb_mm": ev_w.coarse_crlb_m * 1e3,
            "warp": ev_w.variables["warp"],
            "meets_constraints": ok,
            "frames": result.num_frames,
        }
        verdict = "beats" if (ok and ev_w.crlb_m < 0.99 * result.crlb_m) else "does not beat"
        lines.append(
            f"  warped schedule (f = start + span·u^p, p = {ev_w.variables['warp']:.3f}) at the same "
            f"{result.num_frames} frames: CRLB {ev_w.crlb_m * 1e3:.4g} mm"
            f"{'' if ok else ' (violates the range/ripple constraints)'}"
            f" — {verdict} the uniform one ({result.crlb_m * 1e3:.4g} mm)"
        )
    if validate_trials > 0 and result.feasible:
        mc = monte_carlo(design_point(result, problem), validate_trials, seed=1)
        doc["validation"] = mc
        lines.append(
            f"  Monte Carlo (simulate + ML reconstruct, {mc['mc_trials']} pixels): precision "
            f"{mc['mc_precision_mm']:.4g} mm = {mc['mc_precision_mm'] / (result.crlb_m * 1e3):.2f}× CRLB, "
            f"bias {mc['mc_bias_mm']:+.3g} mm, valid {mc['mc_valid_fraction']:.0%}"
        )
    return {"document": doc, "text": "\n".join(lines)}
