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
    s.add_argument("--out", required=True, help="capture file to write (.h5)")
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


def scene_from_args(args):
    """The scene a command line names (built-in, or a depth map with --depth-map)."""
    from ..scenes import from_files, get_scene

    if args.scene == "file":
        if not args.depth_map:
            raise ValueError("scene 'file' needs --depth-map (and optionally --reflectance-map)")
        return from_files(args.depth_map, args.reflectance_map, depth_scale_m=args.depth_scale_m)
    return get_scene(args.scene)


def run(args) -> int:
    from ..effects import parse_effects
    from ..simulate import simulate_to_file

    scene = scene_from_args(args)
    effects = scene.effects if args.effects is None else parse_effects(args.effects)
    h, w = args.size
    check_capture_fits(args.out, h, w, args.steps, "quantization" in effects)
    inst = Instrument(sweep=FrequencySweep.paper(args.steps))
    t0 = time.perf_counter()
    path = simulate_to_file(args.out, scene, inst, h, w, seed=args.seed, effects=effects, progress=not args.quiet)
    sweep = inst.sweep
    print(
        f"wrote {path}: scene {scene.name}, {h}×{w} px, {args.steps} frames "
        f"({sweep.start_hz / 1e9:.3g}–{sweep.frequencies_hz[-1] / 1e9:.4g} GHz, Δf {sweep.step_hz / 1e6:.3g} MHz, "
        f"ambiguity {sweep.ambiguity_m:.2f} m), effects: {', '.join(effects) or 'none'}; "
        f"{time.perf_counter() - t0:.1f} s"
    )
    return 0
