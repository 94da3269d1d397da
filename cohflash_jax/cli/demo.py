"""`cohflash demo`: simulate the built-in staircase, reconstruct it (ML), compare with the truth."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .common import HelpFormatter, add_quiet, size, steps
from .reconstruct import run_reconstruct, summary

DEFAULT_SIZE = (128, 160)
STAIRCASE_BASE_M = 30.5
# colour scale of the preview on the staircase (steps 0…30 mm proud of its base); the wall saturates
PREVIEW_RANGE_MM = (-35.0, 5.0)


def add_parser(sub) -> None:
    d = sub.add_parser(
        "demo",
        help="simulate the staircase scene, reconstruct it (ML), write a depth PNG",
        formatter_class=HelpFormatter,
    )
    d.add_argument("--out", default="out/demo", help="output folder")
    d.add_argument("--size", type=size, default=DEFAULT_SIZE, help="HxW")
    d.add_argument("--steps", type=steps, default=3000, help="frequency steps")
    d.add_argument("--seed", type=int, default=0, help="seed of the noise")
    add_quiet(d)
    d.set_defaults(func=run)


def run(args) -> int:
    from ..capture import Capture
    from ..instrument import Instrument
    from ..reconstruct import ReconstructOptions
    from ..scenes import staircase
    from ..simulate import simulate_to_file

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    h, w = args.size
    scene = staircase(STAIRCASE_BASE_M)
    inst = Instrument.paper(args.steps)
    capture = out / "staircase.h5"
    print(f"simulating the staircase scene: {h}×{w} px, {args.steps} frames, effects: {', '.join(scene.effects)}")
    t0 = time.perf_counter()
    simulate_to_file(capture, scene, inst, h, w, seed=args.seed, progress=not args.quiet)
    t_sim = time.perf_counter() - t0
    options = ReconstructOptions(method="ml", progress=not args.quiet)
    result = run_reconstruct(
        capture,
        out / "depth.h5",
        options,
        png=out / "depth.png",
        png_reference_m=STAIRCASE_BASE_M,
        png_range_mm=PREVIEW_RANGE_MM,
    )
    outputs = result.outputs
    with Capture(capture) as cap:
        truth = cap.truth("depth_m").astype(np.float64)
    valid = outputs["valid"].astype(bool)
    err = (outputs["depth_m"] - truth)[valid]
    print(summary(outputs, result.meta))
    print(f"simulation {t_sim:.1f} s (includes compilation)")
    if err.size:
        # interior pixels only for precision: mixed pixels on step edges are a separate effect
        interior = valid & (np.abs(np.gradient(truth, axis=1)) == 0) & (np.abs(np.gradient(truth, axis=0)) == 0)
        e_in = (outputs["depth_m"] - truth)[interior]
        pred = np.median(outputs["sigma_m"][interior]) if interior.any() else float("nan")
        edge = valid & ~interior
        print(
            f"against truth, away from depth edges ({interior.sum()} px): bias {e_in.mean() * 1e3:+.4f} mm, "
            f"std {e_in.std() * 1e3:.3f} mm (predicted σ {pred * 1e3:.3f} mm); on depth edges (mixed pixels, "
            f"{edge.sum()} px): median |error| {np.median(np.abs(outputs['depth_m'] - truth)[edge]) * 1e3:.1f} mm"
        )
        levels = np.unique(np.round(truth[interior], 4))
        rows = [
            f"{t:9.4f} m → {np.median(outputs['depth_m'][interior & (np.abs(truth - t) < 5e-5)]):9.4f} m"
            for t in levels
        ]
        print("true depth → median reconstructed:\n  " + "\n  ".join(rows))
    print(f"wrote {capture}, {out / 'depth.h5'}, {out / 'depth.png'}")
    return 0
