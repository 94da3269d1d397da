"""What the commands share: argument types, the output-path checks done before any work, and
the provenance a result file records."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..fileio import require_output_folders


class HelpFormatter(argparse.HelpFormatter):
    """Every option's help shows its default, where it has one (not for flags and required
    options)."""

    def _get_help_string(self, action):
        text = action.help or ""
        default = action.default
        if "(default" in text or any(default is v for v in (None, False, argparse.SUPPRESS)) or action.required:
            return text
        shown = "x".join(map(str, default)) if isinstance(default, tuple) else default
        return f"{text} (default: {shown})"


def number_in(low: float, high: float, what: str, low_open: bool = True, integer: bool = False):
    """An argparse type: a number in (low, high] (or [low, high] with `low_open` False) whose
    error says what the option is and what it must be."""

    def parse(text: str):
        try:
            value = int(text) if integer else float(text)
        except ValueError:
            kind = "a whole number" if integer else "a number"
            raise argparse.ArgumentTypeError(f"{what} must be {kind}, got {text!r}") from None
        above = value > low if low_open else value >= low
        if not (above and value <= high):  # NaN fails both
            bracket = "(" if low_open else "["
            raise argparse.ArgumentTypeError(f"{what} must lie in {bracket}{low:g}, {high:g}], got {text}")
        return value

    parse.__name__ = what  # argparse names the type in some messages
    return parse


def size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like HxW (e.g. 256x320), got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return h, w


def range_mm(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO,HI in mm, got {text!r}") from None
    if not hi > lo:
        raise argparse.ArgumentTypeError(f"HI must exceed LO, got {text!r}")
    return lo, hi


def steps(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"the number of steps must be a whole number, got {text!r}") from None
    if n < 2:
        raise argparse.ArgumentTypeError(f"a sweep needs at least 2 steps, got {n}")
    return n


def pixel(text: str) -> tuple[int, int]:
    try:
        r, c = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"pixel must look like ROW,COL, got {text!r}") from None
    return r, c


def roi(text: str) -> list[tuple[int, int]]:
    try:
        rows, cols = text.split(",")
        r0, r1 = (int(v) for v in rows.split(":"))
        c0, c1 = (int(v) for v in cols.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"ROI must look like R0:R1,C0:C1, got {text!r}") from None
    if r1 <= r0 or c1 <= c0:
        raise argparse.ArgumentTypeError(f"empty ROI {text!r}")
    return [(r, c) for r in range(r0, r1) for c in range(c0, c1)]


def scheduler(text: str) -> str:
    """An argparse type: 'threads', 'processes' or a Dask scheduler's address (tcp://HOST:PORT)."""
    from ..scaleout import ADDRESS_PREFIXES, SCHEDULERS

    if text in SCHEDULERS or (text.startswith(ADDRESS_PREFIXES) and len(text.split("://", 1)[1]) > 0):
        return text
    raise argparse.ArgumentTypeError(
        f"scheduler must be threads, processes or a Dask scheduler's address such as tcp://HOST:8786, got {text!r}"
    )


WORKERS = number_in(1, 10**6, "workers", False, True)


def add_scheduler_options(parser: argparse.ArgumentParser, workers_help: str | None = None) -> None:
    """--scheduler, and --workers where `workers_help` is given (`sweep` has its own)."""
    parser.add_argument(
        "--scheduler",
        type=scheduler,
        default=None,
        help="run on Dask: threads or processes (local workers), or tcp://HOST:PORT (a dask.distributed "
        "cluster's scheduler) (default: this process alone)",
    )
    if workers_help is not None:
        parser.add_argument("--workers", type=WORKERS, default=None, help=workers_help)


def add_quiet(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


# arguments that name files a command writes, and files it reads
OUTPUT_ARGUMENTS = ("out", "png", "ply", "tiff", "plot", "report")
INPUT_ARGUMENTS = ("capture", "calibration", "registration", "dark", "flat", "depth_map", "reflectance_map")


def chains_path(out) -> Path:
    """Where `uncertainty --chains` keeps every chain: OUT.chains.h5."""
    return Path(out).with_suffix(".chains.h5")


def check_output_paths(args) -> None:
    """Before any work: every output's folder exists, no output is an input of the command
    (`reconstruct x.h5 --out x.h5` replaced the capture with its depth map) and no two
    outputs are one file."""
    if args.command in ("demo", "report"):  # their --out is a folder they make
        return
    outputs = [(name, getattr(args, name)) for name in OUTPUT_ARGUMENTS if getattr(args, name, None)]
    if getattr(args, "chains", False):
        outputs.append(("chains", chains_path(args.out)))
    require_output_folders(*(path for _, path in outputs))
    inputs = {Path(getattr(args, name)).resolve(): name for name in INPUT_ARGUMENTS if getattr(args, name, None)}
    seen = {}
    for name, path in outputs:
        where = Path(path).resolve()
        if where in inputs:
            raise ValueError(
                f"--{name} {path} is the {inputs[where].replace('_', ' ')} file this command reads: "
                "writing it would destroy the input; choose another path"
            )
        if where in seen:
            raise ValueError(f"--{name} and --{seen[where]} name the same file {path}")
        seen[where] = name


# Files up to this size are hashed whole; larger ones (captures of gigabytes) by their first and
# last MiB with the size, so the record costs milliseconds, not a second pass over the frames
FULL_HASH_MAX_BYTES = 64 * 2**20
HASH_SAMPLE_BYTES = 2**20


def file_record(path) -> dict:
    """A file an output depended on: absolute path, size, modification time and a SHA-256."""
    import hashlib

    path = Path(path)
    if path.is_dir():  # a Zarr store: its metadata hashed, its size summed
        return store_record(path)
    st = path.stat()
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        if st.st_size <= FULL_HASH_MAX_BYTES:
            for block in iter(lambda: fh.read(HASH_SAMPLE_BYTES), b""):
                digest.update(block)
            kind = "sha256"
        else:
            digest.update(fh.read(HASH_SAMPLE_BYTES))
            fh.seek(-HASH_SAMPLE_BYTES, 2)
            digest.update(fh.read(HASH_SAMPLE_BYTES))
            kind = "sha256_first_and_last_mib"
    return {
        "path": str(path.resolve()),
        "size_bytes": st.st_size,
        "mtime": st.st_mtime,
        kind: digest.hexdigest(),
    }


def store_record(path: Path) -> dict:
    """A Zarr store an output depended on: its metadata documents hashed (every array's shape,
    chunks and attributes), its size summed, its latest modification time."""
    import hashlib

    digest = hashlib.sha256()
    size, mtime = 0, 0.0
    for item in sorted(p for p in path.rglob("*") if p.is_file()):
        st = item.stat()
        size, mtime = size + st.st_size, max(mtime, st.st_mtime)
        if item.name == "zarr.json":
            digest.update(str(item.relative_to(path)).encode() + item.read_bytes())
    return {"path": str(path.resolve()), "size_bytes": size, "mtime": mtime, "sha256_metadata": digest.hexdigest()}


def provenance(path: Path, options, applied: dict | None = None, capture_record=None) -> dict:
    """What a result file records of its inputs and how it was made: the capture (`path`) and
    every other file `applied` ({role: path}; None skipped), each as a `file_record`.
    `capture_record`: a callable giving the capture's record where it is made elsewhere
    (`cohflash stream` makes them ahead)."""
    import dataclasses

    import jax

    from .. import __version__

    capture = file_record(path) if capture_record is None else capture_record()
    files = {role: file_record(p) for role, p in (applied or {}).items() if p is not None}
    # the device too: CPU and GPU results agree to ~1e-6 mm, not bit for bit
    return {
        "input": capture["path"],
        "input_size_bytes": capture["size_bytes"],
        "input_mtime": capture["mtime"],
        "inputs": {"capture": capture} | files,
        "cohflash_version": __version__,
        "jax_version": jax.__version__,
        "jax_device": str(jax.devices()[0]),
        "options": dataclasses.asdict(options) if dataclasses.is_dataclass(options) else options,
    }
