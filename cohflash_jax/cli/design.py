"""`cohflash design`: the shortest acquisition that reaches a target precision under range,
power and frequency limits, validated by Monte Carlo."""

from __future__ import annotations

import json

from ..design.problem import DesignProblem
from ..radiometry import PAPER_DISTANCE_M, PAPER_PROBE_POWER_W, PAPER_REFLECTANCE
from .common import HelpFormatter, add_quiet, number_in

DEFAULT_MAX_FRAMES = 8192
DEFAULT_MAX_FREQUENCY_GHZ = 6.0
DEFAULT_VALIDATE_TRIALS = 256


def add_parser(sub) -> None:
    de = sub.add_parser(
        "design",
        help="gradient-based design: the shortest acquisition that reaches a target "
        "precision under range, power and frequency limits, validated by Monte Carlo",
        formatter_class=HelpFormatter,
    )
    de.add_argument(
        "--target-precision-mm",
        type=number_in(0, 1e4, "target precision (mm)"),
        required=True,
        help="depth precision (1σ) to reach",
    )
    de.add_argument(
        "--max-range-m", type=number_in(0, 1e5, "maximum range (m)"), required=True, help="required unambiguous range"
    )
    de.add_argument(
        "--distance-m",
        type=number_in(0, 1e5, "distance (m)"),
        default=PAPER_DISTANCE_M,
        help="target distance the precision is for",
    )
    de.add_argument(
        "--reflectance", type=number_in(0, 1, "reflectance"), default=PAPER_REFLECTANCE, help="target reflectance (0–1)"
    )
    de.add_argument(
        "--max-power-mw",
        type=number_in(0, 1e6, "probe power (mW)"),
        default=PAPER_PROBE_POWER_W * 1e3,
        help="probe power limit",
    )
    de.add_argument(
        "--frame-rate-hz",
        type=number_in(0, 1e6, "frame rate (Hz)"),
        default=DesignProblem.frame_rate_hz,
        help="camera frame rate",
    )
    de.add_argument(
        "--min-frequency-ghz",
        type=number_in(0, 1e3, "minimum frequency (GHz)"),
        default=DesignProblem.min_frequency_hz / 1e9,
        help="lowest microwave frequency (hardware)",
    )
    de.add_argument(
        "--max-frequency-ghz",
        type=number_in(0, 1e3, "maximum frequency (GHz)"),
        default=DEFAULT_MAX_FREQUENCY_GHZ,
        help="highest microwave frequency (hardware)",
    )
    de.add_argument(
        "--max-frames",
        type=number_in(2, 10**7, "maximum frames", False, True),
        default=DEFAULT_MAX_FRAMES,
        help="longest acquisition considered",
    )
    de.add_argument(
        "--schedule",
        choices=("uniform", "both"),
        default="uniform",
        help="'both': also optimise a warped (non-uniform) schedule at the same frame count",
    )
    de.add_argument(
        "--validate-trials",
        type=number_in(0, 10**7, "validation trials", False, True),
        default=DEFAULT_VALIDATE_TRIALS,
        help="Monte Carlo pixels at the optimum (0: skip)",
    )
    de.add_argument("--out", help="design JSON")
    add_quiet(de)
    de.set_defaults(func=run)


def run(args) -> int:
    from ..design import design_report
    from ..fileio import atomic_path

    problem = DesignProblem(
        args.target_precision_mm * 1e-3,
        args.max_range_m,
        args.distance_m,
        args.reflectance,
        args.max_power_mw * 1e-3,
        args.frame_rate_hz,
        args.min_frequency_ghz * 1e9,
        args.max_frequency_ghz * 1e9,
        schedule="uniform",
        max_frames=args.max_frames,
    )
    report = design_report(
        problem, compare_warped=args.schedule == "both", validate_trials=args.validate_trials, progress=not args.quiet
    )
    print(report["text"])
    if args.out:
        with atomic_path(args.out) as tmp:
            tmp.write_text(json.dumps(report["document"], indent=1))
        print(f"wrote {args.out}")
    return 0 if report["document"]["feasible"] else 1
