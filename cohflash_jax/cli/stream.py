"""`cohflash stream`: one warm process over a sequence of short captures (the 10 Hz mode):
a depth file per capture, the time of each map and the rate in maps/s."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import os
import sys
import time
from pathlib import Path

from ..early_read import file_identity
from .common import HelpFormatter, add_quiet, file_record
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


def lowest_cpu_priority() -> None:
    """Run the calling thread only on a core nothing else in the machine wants (Linux's
    SCHED_IDLE). No unprivileged thread can take its priority back."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except OSError:
        pass


def identified_record(path: Path) -> tuple[list[int], dict]:
    """(`early_read.file_identity`, `file_record`) of a file, its identity taken first: a file
    written while it is hashed has another identity after."""
    return file_identity(path), file_record(path)


class RecordsAhead:
    """The depth files' records of a stream's captures (`file_record`), made `AHEAD` captures
    ahead by one thread at the lowest CPU priority (`lowest_cpu_priority`). A 10 Hz capture's
    SHA-256 is ~16 ms of CPU, a fifth of a streamed map's; beside the reconstruction it took
    the cores from the inversions, ahead it runs where a core would wait (the depth file's
    write, the next capture's open and read). A record the thread has not made within
    `GRACE_S` of being asked for (a busy machine starves that thread), of a file that has
    changed since (its `early_read.file_identity`), or of a store (a folder), is made by the
    caller at its own priority. Where the priority cannot be lowered there is no thread:
    `record` gives None and each record is made as `cohflash reconstruct` makes it."""

    AHEAD = 2
    GRACE_S = 0.02

    def __init__(self, paths):
        self.paths = [Path(p) for p in paths]
        self.futures = {}
        self.pool = None
        if hasattr(os, "SCHED_IDLE") and hasattr(os, "sched_setscheduler"):
            self.pool = concurrent.futures.ThreadPoolExecutor(
                1, thread_name_prefix="records-ahead", initializer=lowest_cpu_priority
            )
            for k in range(min(self.AHEAD, len(self.paths))):
                self.start(k)

    def start(self, k: int) -> None:
        """Capture k's record made ahead, after those asked for before it."""
        self.futures[k] = self.pool.submit(identified_record, self.paths[k])

    def record(self, k: int):
        """A callable giving capture k's record (`provenance`'s `capture_record`), or None;
        capture k + `AHEAD`'s is started."""
        if self.pool is None:
            return None
        if k + self.AHEAD < len(self.paths):
            self.start(k + self.AHEAD)
        future, path = self.futures.pop(k), self.paths[k]

        def made() -> dict:
            try:
                identity, record = future.result(timeout=self.GRACE_S)
            except concurrent.futures.TimeoutError:
                future.cancel()
                return file_record(path)
            return record if not path.is_dir() and file_identity(path) == identity else file_record(path)

        return made

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)


def run(args) -> int:
    out_dir = Path(args.out_dir)
    outs = output_paths(args.captures, out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    options = dataclasses.replace(options_from_args(args), progress=False)
    seconds, failed = [], 0
    start = time.perf_counter()
    records = RecordsAhead(args.captures)
    try:
        for k, (capture, out) in enumerate(zip(args.captures, outs)):
            t0 = time.perf_counter()
            record = records.record(k)
            try:
                result = run_reconstruct(
                    capture, out, options, args.calibration, registration=args.registration, capture_record=record
                )
            except (ValueError, OSError) as exc:
                failed += 1
                print(f"{capture}: error: {exc}", file=sys.stderr)
                continue
            seconds.append(time.perf_counter() - t0)
            valid = result.outputs["valid"]
            if not args.quiet:
                print(f"{out}: {valid.mean():.1%} valid, {1e3 * seconds[-1]:.1f} ms", flush=True)
    finally:
        records.close()
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
