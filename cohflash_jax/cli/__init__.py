"""The `cohflash` command: one module per command, each with `add_parser(subparsers)` and
`run(args)`. To add a command: write its module and add it to `COMMANDS`."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..fileio import OutputSet
from ..process import cli_capture_bytes, resume_garbage_collection
from ..runtime import (
    EXECUTABLES,
    PREFETCH_COMMANDS,
    cli_cpu_streams,
    enable_compilation_cache,
    exit_process,
    use_cpu_streams,
)
from . import (
    calibrate,
    convert,
    demo,
    design,
    info,
    paper_report,
    reconstruct,
    scenes,
    simulate,
    stream,
    sweep,
    uncertainty,
)
from .common import check_output_paths
from .reconstruct import run_reconstruct, summary

COMMANDS = (
    demo,
    simulate,
    convert,
    reconstruct,
    stream,
    calibrate,
    sweep,
    design,
    uncertainty,
    info,
    scenes,
    paper_report,
)
# commands whose files are committed as they go: the sweep's checkpoint after every chunk of
# points, the demo's capture (which it then reads), a stream's depth file per capture, the report's
# figures and tables section by section; every other command's outputs form one set
WRITES_AS_IT_GOES = ("sweep", "demo", "stream", "report")


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    p = argparse.ArgumentParser(
        prog="cohflash",
        description="Stepped-frequency coherent flash LiDAR: simulate "
        "captures, reconstruct depth with stated uncertainty.",
    )
    p.add_argument("--version", action="version", version=f"cohflash {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "scheduler", None) == "processes":  # the GPUs' memory is the workers', not this process's
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    enable_compilation_cache()
    use_cpu_streams(cli_cpu_streams(args.command))
    try:
        check_output_paths(args)
        if args.command in WRITES_AS_IT_GOES:
            code = args.func(args)
        else:
            with OutputSet():  # every output of the command renamed into place together, at the end
                code = args.func(args)
        if args.command in PREFETCH_COMMANDS:  # the next run loads these while it imports
            command_line = ["cohflash", *(sys.argv[1:] if argv is None else argv)]
            EXECUTABLES.remember(args.command, cli_capture_bytes(command_line))
        return code
    except BrokenPipeError:  # e.g. `cohflash scenes | head` (before OSError, of which it is one)
        sys.stderr.close()
        return 0
    except (ValueError, FileNotFoundError, NotImplementedError, OSError) as exc:
        print(f"cohflash {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if args.command == "sweep" and Path(args.out).exists():
            print(
                f"interrupted; the finished points are in {args.out}: rerun the same command to resume", file=sys.stderr
            )
        elif args.command == "sweep":
            print(f"interrupted before the first points finished; {args.out} was not written", file=sys.stderr)
        else:
            print("interrupted; nothing was written (files from earlier runs are as they were)", file=sys.stderr)
        return 130


def entry() -> None:
    """The `cohflash` program: `main` on the command line, then the process ends at once
    (`runtime.exit_process`: the interpreter's teardown skipped where nothing depends on it).
    In-process callers (tests, notebooks) call `main`, which returns the exit status."""
    exit_process(main())


# the imports are done: collection on again (paused in a `cohflash` process as the package loads)
resume_garbage_collection()

__all__ = ["COMMANDS", "build_parser", "entry", "main", "run_reconstruct", "summary"]
