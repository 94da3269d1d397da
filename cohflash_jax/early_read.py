"""A `cohflash reconstruct` capture's first tile, read while the process imports.

A `cohflash reconstruct` process imports JAX and the package on one core, and would then read
its first tile on one core before any program could run. Instead, as the package starts
importing (no thread exists yet), the process maps the memory its first tile buffer needs,
shared, and forks a child: with an interpreter lock of its own (a thread would wait for the
parent's at each of its reads), the child touches those pages and reads the first tile into
them, laid out as `engine.PieceReader` will lay out its first buffer there (`tiling`), while
the parent imports on the other core, and sends the parent the chunk index it listed. The
reader takes the tile as read (`holds_first_tile`) where the child read the same file,
unchanged, into the same layout at the same address; anything else (a Zarr store, a
compressed or HDF5-filled capture, another tile size, a GPU's tiles) finds the memory touched
and reads as before. The child only reads: the capture is validated by the parent, as always.

Standard library only until the child runs (the package imports this module before NumPy and
JAX). Measured: docs/performance.md.
"""

from __future__ import annotations

import fcntl
import json
import mmap
import os
import select
import signal
import struct
import sys

from .process import cli_command, cli_input_path

# The commands whose first tile is read early, and the most memory mapped for it: a full
# capture's first tile of 32 rows (4 × 3000 frames × 32 × 320 px × 2 bytes = 246 MB) fits; a
# larger tile is read as before
EARLY_READ_COMMANDS = ("reconstruct",)
EARLY_READ_MAX_BYTES = 256 * 2**20
# A smaller file is read in a few hundredths of a second: a child would cost more than it saves
# (a region of interest, a 10 Hz capture)
EARLY_READ_MIN_BYTES = 64 * 2**20
# Options with which the tiles are read elsewhere: a registered capture's are resampled into
# buffers of their own, a Dask run's are read by its workers
READ_ELSEWHERE_OPTIONS = ("--registration", "--scheduler")
# The longest the parent waits for the child's report before it stops it and reads itself
CHILD_WAIT_S = 60.0
# madvise(2): fault every page of a range in, writable (Linux 5.14); older kernels refuse it,
# and the read then faults the pages in as it goes
MADV_POPULATE_WRITE = 23
# The child's report begins with the length of its JSON part; the pipe it goes through is
# made this large (Linux's default most for a user: a full capture's index is 768 kB)
REPORT_HEADER = struct.Struct("<Q")
REPORT_PIPE_BYTES = 2**20

# "mapping"; "child": (pid, report pipe) until waited for; then its "report"; then the "outcome"
_EARLY: dict = {}


def start_for_cli(argv) -> bool:
    """Where this interpreter runs `cohflash reconstruct` on a capture file (`cli_input_path`)
    of at least `EARLY_READ_MIN_BYTES`, map as much shared memory as its first tile can need
    (the file's size, at most `EARLY_READ_MAX_BYTES`) and fork the child that fills it
    (`read_first_tile`). Called by the package before it imports anything else. Returns
    whether a child started."""
    path = cli_input_path(argv)
    elsewhere = any(a.startswith(READ_ELSEWHERE_OPTIONS) for a in argv)
    if cli_command(argv) not in EARLY_READ_COMMANDS or path is None or elsewhere or "mapping" in _EARLY:
        return False
    if not hasattr(os, "fork") or not sys.platform.startswith("linux"):
        return False
    try:
        size = os.path.getsize(path)
        if size < EARLY_READ_MIN_BYTES:
            return False
        mapping = mmap.mmap(-1, min(size, EARLY_READ_MAX_BYTES), flags=mmap.MAP_SHARED | mmap.MAP_ANONYMOUS)
    except (OSError, ValueError):  # no memory for it: the tile is allocated as usual
        return False
    report_fd, child_fd = os.pipe()
    try:  # room for the whole report, chunk index and all, so the child never waits to write it
        fcntl.fcntl(child_fd, getattr(fcntl, "F_SETPIPE_SZ", 1031), REPORT_PIPE_BYTES)
    except OSError:  # more than the system lets a pipe hold: the child writes as it is read
        pass
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        pid = os.fork()
    except OSError:
        os.close(report_fd)
        os.close(child_fd)
        mapping.close()
        return False
    if pid == 0:  # the child: never returns
        os.close(report_fd)
        run_child(mapping, path, tile_rows_option(argv), child_fd)
    os.close(child_fd)
    _EARLY.update(mapping=mapping, child=(pid, report_fd))
    return True


def tile_rows_option(argv) -> int | None:
    """The `--tile-rows` a command line gives (None where none, or not a number: the parent's
    parser then says so, and the layouts differ)."""
    for k, arg in enumerate(argv):
        value = arg.split("=", 1)[1] if arg.startswith("--tile-rows=") else None
        if arg == "--tile-rows" and k + 1 < len(argv):
            value = argv[k + 1]
        if value is not None:
            try:
                return int(value)
            except ValueError:
                return None
    return None


def run_child(mapping: mmap.mmap, path: str, tile_rows: int | None, report_fd: int):
    """The child: its standard streams on /dev/null, its pages touched, the first tile read,
    then its report (`read_first_tile`'s) written to the parent (`REPORT_HEADER`: the length
    of its JSON, the JSON, then the chunk index's bytes) and the child gone (`os._exit`: none
    of the parent's exit handlers run twice)."""
    report = {"read": False}
    try:
        quiet = os.open(os.devnull, os.O_RDWR)
        for fd in (0, 1, 2):
            os.dup2(quiet, fd)
        os.environ["OPENBLAS_NUM_THREADS"] = "1"  # NumPy's import here would start its BLAS's threads
        try:
            mapping.madvise(MADV_POPULATE_WRITE)
        except (OSError, ValueError, AttributeError):
            pass
        report = read_first_tile(mapping, path, tile_rows)
    except BaseException as exc:  # a report, whatever happened: the parent reads as before
        report = {"read": False, "why": f"{type(exc).__name__}: {exc}"}
    finally:
        try:
            data = memoryview(encode_report(report))
            while data:
                data = data[os.write(report_fd, data) :]
        finally:
            os._exit(0)


def encode_report(report: dict) -> bytes:
    """The child's report as it goes through the pipe (`parse_report` reads it back):
    `REPORT_HEADER` (the length of its JSON), the JSON, then its chunk index's bytes, where it
    has one ("index", replaced in the JSON by its shape, "index_shape")."""
    index = report.get("index")
    fields = {k: v for k, v in report.items() if k != "index"}
    if index is not None:
        fields["index_shape"] = list(index.shape)
    header = json.dumps(fields).encode()
    return REPORT_HEADER.pack(len(header)) + header + (b"" if index is None else index.tobytes())


def file_identity(file: int | str | os.PathLike) -> list[int]:
    """What tells a file (an open descriptor or a path) apart and changes when it is written:
    device, inode, size, times."""
    st = os.stat(file)
    return [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]


def read_first_tile(mapping: mmap.mmap, path: str, tile_rows: int | None = None) -> dict:
    """Read the first tile of the capture at `path` into `mapping` as `engine.PieceReader`
    lays out its first buffer there on the CPU (`tiling.PieceLayout`): {"read": True, "file":
    `file_identity`, "layout": `PieceLayout.key`, "address": the first piece's address}, or
    {"read": False, "why": …} where it cannot (the parent then reads as before); with the
    frames' chunk index where it was listed ("index": `DirectChunkReader.offsets`, of the
    file "file"), which the parent's reader then takes instead of listing it again."""
    import h5py

    from .chunk_reads import ChunkIndexError, DirectChunkReader

    try:
        with h5py.File(path, "r") as f:
            frames = f.get("frames")
            if not isinstance(frames, h5py.Dataset) or frames.ndim != 4 or frames.shape[0] != 4:
                return {"read": False, "why": "no (4, N, H, W) frames dataset"}
            dtype = frames.dtype
            reader = DirectChunkReader(frames, path)
    except ChunkIndexError as exc:
        return {"read": False, "why": str(exc)}
    listed = {"file": file_identity(reader.fd), "index": reader.offsets}
    try:
        return listed | read_into(mapping, reader, dtype, tile_rows)
    finally:
        reader.close()


def read_into(mapping: mmap.mmap, reader, dtype, tile_rows: int | None) -> dict:
    """`read_first_tile`'s read, with the frames' `DirectChunkReader` (`reader`)."""
    import numpy as np

    from . import tiling

    shape = reader.shape[1:]
    layout = tiling.PieceLayout.of(shape, dtype, tiling.rows_per_tile(shape, dtype.itemsize, tile_rows), "cpu")
    if layout is None:
        return {"read": False, "why": "its tiles are not read in pieces"}
    rows = slice(0, layout.rows)
    if not reader.covers(rows) or not reader.scatters(layout.rows, layout.rows_per_piece):
        return {"read": False, "why": "its chunks cannot be scattered into pieces"}
    if len(mapping) < layout.buffer_bytes:
        return {"read": False, "why": "the tile is larger than the memory mapped"}
    pieces = layout.pieces(np.frombuffer(mapping, np.uint8))
    before = file_identity(reader.fd)
    reader.read_rows_into_pieces(reader.scatter_table(pieces, layout.rows, layout.rows_per_piece), rows)
    if file_identity(reader.fd) != before:
        return {"read": False, "why": "the file changed while it was read"}
    return {"read": True, "file": before, "layout": layout.key, "address": pieces[0].ctypes.data}


def take_mapping(nbytes: int):
    """The shared memory `start_for_cli` mapped (zeroed or holding the first tile, writable,
    page-aligned), once, where it holds `nbytes`; else None (and it is let go). Waits for the
    child's report first, so that nothing writes the memory once it is taken."""
    wait_for_child()
    mapping = _EARLY.pop("mapping", None)
    if mapping is not None and len(mapping) >= nbytes:
        return mapping
    if "report" in _EARLY:  # a tile in memory let go is no use
        _EARLY["outcome"] = {"report": _EARLY.pop("report"), "held": False}
    return None


def wait_for_child(timeout_s: float = CHILD_WAIT_S) -> None:
    """Read the child's report (at most `timeout_s`; a child still reading then is stopped) and
    let it go."""
    child = _EARLY.pop("child", None)
    if child is None:
        return
    pid, report_fd = child
    chunks = []
    try:
        while select.select([report_fd], [], [], timeout_s)[0]:
            chunk = os.read(report_fd, REPORT_PIPE_BYTES)
            if not chunk:
                break
            chunks.append(chunk)
        else:
            os.kill(pid, signal.SIGKILL)
    finally:
        os.close(report_fd)
        try:
            os.waitpid(pid, 0)
        except ChildProcessError:  # reaped already (a process that ignores SIGCHLD)
            pass
    _EARLY["report"] = parse_report(b"".join(chunks))
    if "index" in _EARLY["report"]:
        _EARLY["index"] = (_EARLY["report"]["file"], _EARLY["report"].pop("index"))


def parse_report(data: bytes) -> dict:
    """The child's report from its bytes (`encode_report`): {} where they are cut short or garbled
    (a child stopped or killed); its chunk index, where it sent one, as "index"."""
    import numpy as np

    try:
        (length,) = REPORT_HEADER.unpack_from(data)
        start = REPORT_HEADER.size
        report = json.loads(data[start : start + length])
        if "index_shape" in report:
            shape = tuple(report.pop("index_shape"))
            index = np.frombuffer(data, np.int64, offset=start + length)
            report["index"] = index.reshape(shape)  # raises where bytes are missing
    except (struct.error, ValueError, TypeError):
        return {}
    return report if isinstance(report, dict) else {}


def known_chunk_index() -> tuple | None:
    """The frames' chunk index the child listed, as `DirectChunkReader`'s `known` takes it
    ((the file's `file_identity`, offsets)), once; None where it sent none."""
    wait_for_child()
    return _EARLY.pop("index", None)


def holds_first_tile(fd: int, layout: list, address: int) -> bool:
    """Whether the memory taken (`take_mapping`) holds the first tile of the file open as `fd`,
    laid out as `layout` (`tiling.PieceLayout.key`) from `address`: the child read that file, unchanged
    since, so. Asked once: the report is let go (False where there is none)."""
    if "report" not in _EARLY:
        return False
    report = _EARLY.pop("report")
    held = bool(report.get("read")) and report.get("layout") == layout and report.get("address") == address
    held = held and report.get("file") == file_identity(fd)
    _EARLY["outcome"] = {"report": report, "held": held}
    return held


def outcome() -> dict | None:
    """What became of this process's early read once a reader asked (`holds_first_tile`): the
    child's report and whether its tile was taken; None before (for tests and diagnostics)."""
    return _EARLY.get("outcome")
