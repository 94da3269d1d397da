"""`cohflash uncertainty`: per-pixel depth posteriors with emcee, for the capture's instrument
or a calibrated one (`--calibration`, as `reconstruct --calibration`)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from .common import HelpFormatter, add_quiet, chains_path, number_in, pixel, provenance, roi

DEFAULT_MAX_STEPS = 20000
DEFAULT_MAX_PLOTS = 16
PRINTED_PIXELS = 20


def add_parser(sub) -> None:
    u = sub.add_parser("uncertainty", help="per-pixel depth posteriors with emcee", formatter_class=HelpFormatter)
    u.add_argument("capture", help="capture file (format v1, .h5)")
    u.add_argument("--pixel", type=pixel, action="append", help="ROW,COL (repeatable)")
    u.add_argument("--roi", type=roi, help="R0:R1,C0:C1 (end-exclusive)")
    u.add_argument("--out", required=True, help="posterior file (.h5)")
    u.add_argument(
        "--calibration",
        help="calibration file (.json or .h5) from `cohflash calibrate hybrid`: the "
        "posteriors of the calibrated instrument, as `reconstruct --calibration` reconstructs it",
    )
    u.add_argument("--plot", help="PNG per pixel: depth marginal with the CRLB Gaussian, corner plot")
    u.add_argument(
        "--max-plots",
        type=number_in(0, 10**6, "maximum plots", False, True),
        default=DEFAULT_MAX_PLOTS,
        help="at most this many plots",
    )
    u.add_argument("--chains", action="store_true", help="keep all chains in OUT.chains.h5 (emcee HDF backend)")
    u.add_argument(
        "--max-steps",
        type=number_in(1, 10**9, "maximum steps", False, True),
        default=DEFAULT_MAX_STEPS,
        help="emcee steps a pixel at most",
    )
    u.add_argument("--seed", type=int, default=0, help="seed of the walkers")
    add_quiet(u)
    u.set_defaults(func=run)


def run(args) -> int:
    from ..calibration_file import Calibration, CaptureSetup
    from ..capture import Capture
    from ..fileio import atomic_path
    from ..posteriors import plot_posterior, run_pixels, write_posteriors
    from ..reconstruct import ReconstructOptions

    pixels = list(args.pixel or []) + (args.roi or [])
    if not pixels:
        raise ValueError("name pixels with --pixel ROW,COL (repeatable) or --roi R0:R1,C0:C1")
    calibration = None if args.calibration is None else Calibration.load(args.calibration)
    options = ReconstructOptions(method="ml", progress=False)
    t0 = time.perf_counter()
    with Capture(args.capture) as cap:
        setup = CaptureSetup.of(cap, calibration)
        run = lambda chains: run_pixels(
            cap,
            pixels,
            options,
            instrument=setup.instrument,
            maps=setup.maps,
            seed=args.seed,
            max_steps=args.max_steps,
            chains_path=chains,
            progress=not args.quiet,
        )
        if args.chains:
            with atomic_path(chains_path(args.out)) as tmp:
                results, skipped = run(tmp)
        else:
            results, skipped = run(None)
    seconds = time.perf_counter() - t0
    sampler_options = {"max_steps": args.max_steps, "seed": args.seed}
    meta = {
        "capture": str(Path(args.capture).resolve()),
        "seconds": seconds,
        "seconds_per_pixel": seconds / len(results),
        "skipped_pixels": json.dumps([[r, c, why] for r, c, why in skipped]),
        "calibration": str(Path(args.calibration).resolve()) if args.calibration else "",
        "system_delay_s": float(setup.instrument.system_delay_s),
        "notes": json.dumps(list(setup.notes)),
        "provenance": json.dumps(
            provenance(args.capture, sampler_options, {"calibration": args.calibration}), default=str
        ),
    }
    if calibration is not None:
        meta["calibration_applied"] = json.dumps(calibration.values())
    write_posteriors(args.out, results, meta)
    print(f"wrote {args.out}: {len(results)} pixel(s), {seconds / len(results):.2f} s per pixel")
    for note in setup.notes:
        print(f"note: {note}")
    if skipped:
        print(
            f"  skipped {len(skipped)} pixel(s) with unusable data (no posterior): "
            + ", ".join(f"({r},{c}) {why}" for r, c, why in skipped[:PRINTED_PIXELS])
            + (" …" if len(skipped) > PRINTED_PIXELS else "")
        )
    for r, c, p in results[:PRINTED_PIXELS]:
        print(
            f"  ({r},{c}): median {p.median_m:.5f} m, 68 % [{(p.interval68_m[0] - p.median_m) * 1e3:+.3f}, "
            f"{(p.interval68_m[1] - p.median_m) * 1e3:+.3f}] mm, 95 % [{(p.interval95_m[0] - p.median_m) * 1e3:+.3f}, "
            f"{(p.interval95_m[1] - p.median_m) * 1e3:+.3f}] mm, CRLB σ {p.crlb_m * 1e3:.3f} mm"
            + ("; MULTIMODAL" if p.multimodal else "")
            + (f" — {p.note}" if p.note else "")
        )
    if len(results) > PRINTED_PIXELS:
        print(f"  … {len(results) - PRINTED_PIXELS} more in the file")
    if args.plot:
        base = Path(args.plot)
        for r, c, p in results[: args.max_plots]:
            target = base if len(results) == 1 else base.with_name(f"{base.stem}_{r}_{c}{base.suffix}")
            plot_posterior(target, p, title=f"pixel ({r}, {c})")
        print(f"wrote {min(len(results), args.max_plots)} plot(s) at {base.parent}/")
    return 0
