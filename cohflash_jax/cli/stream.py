"""`cohflash stream`: one warm process over a sequence of short captures (the 10 Hz mode):
a depth file per capture, the time of each map and the rate in maps/s."""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

from .common import HelpFormatter, add_quiet
from .reconstruct import add_reconstruction_options, options_from_args, run_reconstruct


def add_parser(sub) -> None:
    r = sub.add_parser(
        "stream",
        help="reconstruct a sequence of captures in one warm process → DIR/NAME.depth.h5 each, maps/s",
        formatter_class=HelpFormatter,
        description="Reconstruct captures one after another in one process, so programs are compiled "
        "(or loaded) once: the 10 Hz mode's sequence of short captures. Each capture's depth file is "
        "written as soon as it is done; a capture that fails is reported and the stream goes on "
        "(exit status 1 at the end). Prints each map's time and the rate, with and without the first "
        "map (which carries the start-up).",
    )
    r.add_argument("captures", nargs="+", help="capture files (format v1, .h5), reconstructed in this order")
    r.add_argument("--out-dir", required=True, help="folder for the depth files (NAME.depth.h5 per capture)")
    add_reconstruction_options(r)
    add_quiet(r)
    r.set_defaults(func=run)


def output_paths(captures, out_dir) -> list[Path]:
    """DIR/NAME.depth.h5 for each capture; two captures of one name would overwrite each other."""
    outs = [Path(out_dir) / f"{Path(c).stem}.depth.h5" for c in captures]
    seen, inputs = {}, {Path(c).resolve() for c in captures}
    for c, o in zip(captures, outs):
        if o.resolve() in inputs:
            raise ValueError(f"{o} is one of the captures this command reads: choose another --out-dir")
        if o in seen:
            raise ValueError(f"captures {seen[o]} and {c} would both write {o}: give them different names")
        seen[o] = c
    return outs


def run(args) -> int:
    out_dir = Path(args.out_dir)
    outs = output_paths(args.captures, out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    options = dataclasses.replace(options_from_args(args), progress=False)
    seconds, failed = [], 0
    start = time.perf_counter()
    for capture, out in zip(args.captures, outs):
        t0 = time.perf_counter()
        try:
            result = run_reconstruct(capture, out, options, args.calibration, registration=args.registration)
        except (ValueError, OSError) as exc:
            failed += 1
            print(f"{capture}: error: {exc}", file=sys.stderr)
            continue
        seconds.append(time.perf_counter() - t0)
        valid = result.outputs["valid"]
        if not args.quiet:
            print(f"{out}: {valid.mean():.1%} valid, {1e3 * seconds[-1]:.1f} ms", flush=True)
    total = time.perf_counter() - start
    if seconds:
        line = f"{len(seconds)} maps in {total:.2f} s: {len(seconds) / total:.1f} maps/s"
        if len(seconds) > 1:
            rest = sum(seconds[1:])
            line += f"; after the first ({1e3 * seconds[0]:.0f} ms): {(len(seconds) - 1) / rest:.1f} maps/s"
        print(line)
    if failed:
        print(f"{failed} of {len(args.captures)} captures failed", file=sys.stderr)
    return 1 if failed else 0
