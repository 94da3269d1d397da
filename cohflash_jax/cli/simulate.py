"""`cohflash simulate`: a capture file (format v1) of a scene, with the effects it calls for."""

from __future__ import annotations

import time

from ..instrument import Instrument
from ..sweep import FrequencySweep
from .common import HelpFormatter, add_quiet, number_in, size, steps

DEFAULT_SIZE = (256, 320)


def add_parser(sub) -> None:
    s = sub.add_parser("simulate", help="simulate a capture file (format v1)", formatter_class=HelpFormatter)
    s.add_argument("scene", help="planar, staircase, traffic, or file (with --depth-map)")
    s.add_argument(
        "--out",
        required=True,
        help="capture to write: an .h5 file, or NAME.zarr for a Zarr store (chunked by the simulator's "
        "frame bands; `cohflash convert` rechunks pixel-major)",
    )
    s.add_argument("--size", type=size, default=DEFAULT_SIZE, help="HxW")
    s.add_argument("--steps", type=steps, default=3000, help="frequency steps from 0.1 GHz by 1.97 MHz")
    s.add_argument("--seed", type=int, default=0, help="seed of the noise and speckle")
    s.add_argument(
        "--effects", default=None, help="comma-separated effects (default: the scene's own); see `cohflash scenes`"
    )
    s.add_argument("--depth-map", help="scene 'file': depth map (.npy in m, or image × --depth-scale-m)")
    s.add_argument(
        "--reflectance-map",
        help="scene 'file': reflectance map (.npy in [0,1], or image: "
        "value / the dtype's full scale, e.g. /255 for 8-bit)",
    )
    s.add_argument(
        "--set",
        action="append",
        metavar="NAME=VALUE[,…]",
        help="instrument and target by the design's parameter names (as `sweep --set`): start_ghz, step_mhz "
        "or bandwidth_ghz, num_steps, probe_power_mw, exposure_ms, modulation_index, bias_rad, frame_rate_hz; "
        "distance_m and reflectance of the planar scene (distance_m of the others)",
    )
    s.add_argument("--design", help="design JSON from `cohflash design`: simulate its optimum's instrument and target")
    s.add_argument(
        "--tilt-m",
        type=tilt,
        default=(0.0, 0.0),
        help="planar scene: depth change across the field of view, DX,DY in m (a tilted calibration target)",
    )
    s.add_argument(
        "--depth-scale-m",
        type=number_in(0, 1e6, "depth scale (m per unit)"),
        default=1.0,
        help="metres per image unit of --depth-map",
    )
    add_quiet(s)
    s.set_defaults(func=run)


# The simulator holds a scene's per-pixel returns (delays, amplitudes, speckle, per-CCD terms)
# in float64 while it streams frames: about this many bytes a pixel at most
SIMULATOR_BYTES_PER_PIXEL = 512


def check_capture_fits(out, height: int, width: int, frames: int, uint16: bool) -> None:
    """Before any work: the capture fits on the output's disk and the scene in memory."""
    import os
    import shutil
    from pathlib import Path

    need = 4 * frames * height * width * (2 if uint16 else 4)
    free = shutil.disk_usage(Path(out).resolve().parent).free
    if need > free:
        raise ValueError(
            f"--size {height}x{width} with {frames} steps makes a {need / 1e9:.3g} GB capture; "
            f"{free / 1e9:.3g} GB are free in {Path(out).resolve().parent}"
        )
    memory = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if height * width * SIMULATOR_BYTES_PER_PIXEL > memory:
        raise ValueError(
            f"--size {height}x{width} needs about {height * width * SIMULATOR_BYTES_PER_PIXEL / 1e9:.3g} GB of "
            f"memory to simulate; this machine has {memory / 1e9:.3g} GB"
        )


def tilt(text: str) -> tuple[float, float]:
    import argparse
    import math

    try:
        dx, dy = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"tilt must look like DX,DY in metres, got {text!r}") from None
    if not (math.isfinite(dx) and math.isfinite(dy)):
        raise argparse.ArgumentTypeError(f"tilt must be finite, got {text!r}")
    return dx, dy


# design parameters that describe the target, not the instrument
TARGET_PARAMETERS = ("distance_m", "reflectance")


def design_point(args) -> dict:
    """The design point (paper units) that --design and --set give, --set last; {} for neither."""
    from ..design.report import optimum_point
    from ..fileio import read_json
    from .sweep import assignments

    point = {}
    if args.design:
        doc = read_json(args.design, "design")
        if not isinstance(doc, dict) or "variables" not in doc or "problem" not in doc:
            raise ValueError(f"{args.design}: not a design JSON from `cohflash design` (no variables/problem)")
        if not doc.get("feasible", True):
            raise ValueError(f"{args.design}: the design is not feasible ({doc.get('note')}): nothing to simulate")
        point = optimum_point(doc["variables"], doc["num_frames"], doc["problem"])
    given = assignments(args.set)
    if "range_falloff" in given:
        raise ValueError("range_falloff is an effect of the simulation: list it in --effects instead of --set")
    if "bandwidth_ghz" in given:
        point.pop("step_mhz", None)
    return point | given


def scene_from_args(args, point: dict | None = None):
    """The scene a command line names (built-in, or a depth map with --depth-map), at the
    target distance and reflectance `point` gives."""
    from ..scenes import BUILTIN_SCENES, from_files, get_scene, planar

    target = {k: v for k, v in (point or {}).items() if k in TARGET_PARAMETERS}
    tilted = args.tilt_m != (0.0, 0.0)
    if args.scene == "file":
        if target:
            raise ValueError(
                f"--set {', '.join(target)}: a depth-map scene takes its depths and reflectance from files"
            )
        if not args.depth_map:
            raise ValueError("scene 'file' needs --depth-map (and optionally --reflectance-map)")
        return from_files(args.depth_map, args.reflectance_map, depth_scale_m=args.depth_scale_m)
    if tilted and args.scene != "planar":
        raise ValueError("--tilt-m applies to the planar scene only")
    if args.scene == "planar" and (target or tilted):
        return planar(tilt_m_per_fov=args.tilt_m, **target)
    if "reflectance" in target:
        raise ValueError(f"--set reflectance applies to the planar scene; {args.scene} has its own reflectances")
    if target and args.scene in BUILTIN_SCENES:
        return BUILTIN_SCENES[args.scene](distance_m=target["distance_m"])
    return get_scene(args.scene)


def run(args) -> int:
    from ..effects import parse_effects
    from ..simulate import simulate_to_file

    point = design_point(args)
    scene = scene_from_args(args, point)
    effects = scene.effects if args.effects is None else parse_effects(args.effects)
    h, w = args.size
    instrument_values = {k: v for k, v in point.items() if k not in TARGET_PARAMETERS}
    if instrument_values:
        from ..design.parameters import point_instrument

        instrument_values.setdefault("num_steps", args.steps)
        inst = point_instrument(instrument_values)
    else:
        inst = Instrument(sweep=FrequencySweep.paper(args.steps))
    steps_count = inst.sweep.num_steps
    check_capture_fits(args.out, h, w, steps_count, "quantization" in effects)
    t0 = time.perf_counter()
    path = simulate_to_file(args.out, scene, inst, h, w, seed=args.seed, effects=effects, progress=not args.quiet)
    sweep = inst.sweep
    print(
        f"wrote {path}: scene {scene.name} ({scene.description}), {h}×{w} px, {steps_count} frames "
        f"({sweep.start_hz / 1e9:.3g}–{sweep.frequencies_hz[-1] / 1e9:.4g} GHz, Δf {sweep.step_hz / 1e6:.3g} MHz, "
        f"ambiguity {sweep.ambiguity_m:.2f} m), effects: {', '.join(effects) or 'none'}; "
        f"{time.perf_counter() - t0:.1f} s"
    )
    return 0
