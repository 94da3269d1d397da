"""Captures as Zarr v3 stores: format v1's attributes and arrays (`capture`, docs/formats.md)
in a folder `NAME.zarr`, for captures too large for one file or one machine.

Layout: the group's attributes are the HDF5 file's root attributes plus `complete` (true once
every chunk of the frames is written) and `chunking`; arrays `frames` (4, N, H, W),
`frequencies_hz` (N,), `hybrid_phases_rad` (4,), optional `dark` (4, H, W) and group `truth/`.
The frames are chunked pixel-major by default, (1, N, 32, 64): every frame of a block of
32×64 pixels of one CCD in one chunk (12 MiB at N = 3000), so a tile of rows reads whole
chunks, each contiguous. Chunks are stored uncompressed: shot-noise-limited frames barely
compress and decompression would cost more than the read.

Several writers, on several machines, can fill one capture (`create_zarr_capture`, then a
`ZarrCaptureWriter` each, then `finish_zarr_capture`): each writes whole chunks of its own
rows or frames, which the writer checks. The arrays are not sharded: Zarr v3 rewrites a whole
shard for a partial write, and writers filling parts of one shard lose each other's data.
A store stays marked incomplete (and `Capture` refuses it) until `finish_zarr_capture` has
checked that every chunk is on disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .capture import FORMAT_NAME, FORMAT_VERSION, Capture, CaptureError, CaptureHeader, counted_blocks, write_capture
from .fileio import atomic_path, is_store_folder, json_value

DEFAULT_ROWS_PER_CHUNK = 32
DEFAULT_COLS_PER_CHUNK = 64
# every chunk is stored, even one equal to the fill value, so a finished capture can be checked
# for completeness by counting chunks
_WRITE_EVERY_CHUNK = {"write_empty_chunks": True}


def open_zarr_group(path: Path, error=CaptureError):
    """The Zarr group at `path`, opened for reading; `error` naming the problem where it is none."""
    import zarr

    if not (path / "zarr.json").is_file():
        raise error(f"{path} is a folder, not a capture file (nor a Zarr store: it has no zarr.json)")
    try:
        return zarr.open_group(path, mode="r")
    except Exception as exc:  # zarr raises several types for a corrupt store
        raise error(f"{path}: not a readable Zarr v3 store ({exc})") from None


def create_zarr_capture(
    path,
    header: CaptureHeader,
    *,
    frames_per_chunk: int | None = None,
    rows_per_chunk: int = DEFAULT_ROWS_PER_CHUNK,
    cols_per_chunk: int = DEFAULT_COLS_PER_CHUNK,
) -> Path:
    """Create an empty capture store at `path` (marked incomplete) for writers to fill.
    `frames_per_chunk`: default all frames (pixel-major chunks); give fewer where writers each
    own a band of frames."""
    import zarr

    path = Path(path)
    n, h, w = header.num_frames, header.height, header.width
    for name, value in (("frames_per_chunk", frames_per_chunk or n), ("rows_per_chunk", rows_per_chunk)):
        if int(value) < 1:
            raise CaptureError(f"{name} must be at least 1, got {value}")
    chunks = (1, min(n, int(frames_per_chunk or n)), min(h, int(rows_per_chunk)), min(w, int(cols_per_chunk)))
    group = zarr.open_group(path, mode="w")
    group.attrs.update(
        {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            **{k: json_value(v) for k, v in header.attrs.items()},
            "chunking": "frames (CCD, frames, rows, columns) = " + "×".join(map(str, chunks)),
            "complete": False,
        }
    )
    group.create_array(
        "frames",
        shape=(4, n, h, w),
        chunks=chunks,
        dtype=header.dtype,
        fill_value=0,
        compressors=None,
        config=_WRITE_EVERY_CHUNK,
    )
    group.create_array("frequencies_hz", data=header.frequencies_hz)
    group.create_array("hybrid_phases_rad", data=header.hybrid_phases_rad)
    if header.dark is not None:
        group.create_array("dark", data=np.asarray(header.dark, np.float32))
    if header.truth is not None:
        g = group.create_group("truth")
        for name in ("depth_m", "reflectance"):
            if name in header.truth:
                g.create_array(name, data=np.asarray(header.truth[name], np.float32))
        g.attrs.update({k: json_value(v) for k, v in header.truth.get("attrs", {}).items()})
    return path


def chunk_aligned(selection: slice, size: int, chunk: int) -> bool:
    """Whether `selection` of an axis of `size` starts and ends on chunk boundaries (or the end)."""
    start, stop, step = selection.indices(size)
    return step == 1 and start % chunk == 0 and (stop % chunk == 0 or stop == size) and stop > start


class ZarrCaptureWriter:
    """One writer of a capture store made by `create_zarr_capture`: writes blocks of frames
    (4, frames, rows, W) that cover whole chunks, so writers never share a chunk."""

    def __init__(self, path):
        import zarr

        self.path = Path(path)
        group = open_zarr_group(self.path)
        if group.attrs.get("format") != FORMAT_NAME:
            raise CaptureError(f"{self.path}: not a cohflash capture store")
        self.frames = zarr.open_array(self.path / "frames", mode="r+", config=_WRITE_EVERY_CHUNK)

    def write(self, block: np.ndarray, frames: slice = slice(None), rows: slice = slice(None)) -> None:
        """Write `block` (4, frames, rows, W) at frames `frames` and rows `rows`."""
        _, n, h, w = self.frames.shape
        _, chunk_n, chunk_h, _ = self.frames.chunks
        for axis, selection, size, chunk in (("frames", frames, n, chunk_n), ("rows", rows, h, chunk_h)):
            if not chunk_aligned(selection, size, chunk):
                start, stop, _ = selection.indices(size)
                raise CaptureError(
                    f"{self.path}: {axis} {start}:{stop} do not cover whole chunks of {chunk} {axis} "
                    "(a writer owns whole chunks, or writers overwrite each other)"
                )
        expected = (4, len(range(*frames.indices(n))), len(range(*rows.indices(h))), w)
        if block.shape != expected:
            raise CaptureError(f"{self.path}: block of shape {block.shape} for a region of shape {expected}")
        self.frames[:, frames, rows, :] = block


def missing_chunks(array) -> tuple[int, int]:
    """(chunks absent from the store, chunks in all) of a Zarr array: an absent chunk reads
    as the fill value, zeros, so a store is complete only when none is absent."""
    total = array.nchunks
    return total - array.nchunks_initialized, total


def finish_zarr_capture(path) -> Path:
    """Mark a filled capture store complete, after checking that every chunk was written
    (CaptureError naming how many are missing otherwise)."""
    import zarr

    path = Path(path)
    missing, total = missing_chunks(zarr.open_array(path / "frames", mode="r"))
    if missing:
        raise CaptureError(f"{path}: {missing} of {total} chunks of frames were never written")
    zarr.open_group(path, mode="r+").attrs["complete"] = True
    return path


def write_zarr_capture(
    path,
    chunks,
    header: CaptureHeader,
    *,
    frames_per_chunk: int = 64,
    progress: bool = True,
    by_rows: bool = False,
    rows_per_chunk: int = DEFAULT_ROWS_PER_CHUNK,
) -> Path:
    """`capture.write_capture` into a Zarr store, atomically (a temporary folder renamed into
    place once complete): from bands of frames (chunks of `frames_per_chunk` frames, as a
    simulator writes them) or, with `by_rows`, bands of rows of all frames (pixel-major chunks)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        chunking = dict(frames_per_chunk=None if by_rows else frames_per_chunk, rows_per_chunk=rows_per_chunk)
        writer = ZarrCaptureWriter(create_zarr_capture(tmp, header, **chunking))
        for m0, m1, block in counted_blocks(chunks, header, by_rows, f"writing {path.name}", progress):
            writer.write(block, **{"rows" if by_rows else "frames": slice(m0, m1)})
        finish_zarr_capture(tmp)
    return path


def convert_capture(source, target, *, progress: bool = True, rows_per_chunk: int = DEFAULT_ROWS_PER_CHUNK) -> Path:
    """Copy a capture between HDF5 and Zarr (`NAME.zarr`), either way, streaming one band of
    `rows_per_chunk` rows at a time (all its frames: a few hundred MB at most for a full
    frame). The target appears whole or not at all."""
    source, target = Path(source), Path(target)
    with Capture(source) as cap:
        if is_store_folder(target) == (cap.store == "zarr"):
            kind = {"zarr": "a Zarr", "hdf5": "an HDF5"}[cap.store]
            raise CaptureError(f"{source} is already {kind} capture: give a target of the other kind (.h5 or .zarr)")
        h = cap.shape[1]
        bands = ((r0, min(h, r0 + rows_per_chunk)) for r0 in range(0, h, rows_per_chunk))
        return write_capture(
            target,
            ((r0, r1, cap.read_tile(slice(r0, r1))) for r0, r1 in bands),
            **CaptureHeader.of(cap).fields(),
            progress=progress,
            by_rows=True,
            rows_per_chunk=rows_per_chunk,
        )
