"""Row tiles of an uncompressed, chunked HDF5 frames dataset read straight from the file.

HDF5 reads a chunk into its own buffer and then copies the selected part into the caller's
array: two copies of every byte (page cache → HDF5 → array), under h5py's lock. Where the
frames' chunks are stored raw (no filters) and span whole rows, a chunk of one CCD, a run of
frames and a band of rows is a C-ordered block of bytes at a known file offset, so it can be
read with one `os.preadv` (which releases the GIL) straight into the rows of the tile buffer
it belongs to: one copy. Anything else (filters, chunks cutting rows, unallocated chunks, a
tile not on chunk boundaries) is left to HDF5.
"""

from __future__ import annotations

import os

import h5py
import numpy as np


class ChunkIndexError(ValueError):
    """The dataset's chunks cannot be read directly (the caller reads through HDF5)."""


class DirectChunkReader:
    """File offsets of every chunk of a (4, N, H, W) frames dataset whose chunks are
    (1, frames_per_chunk, rows_per_chunk, W), and `read_rows_into`, which reads a band of
    whole chunk rows into a (4, N, ≥rows, W) buffer with one `preadv` per chunk."""

    def __init__(self, dataset: h5py.Dataset, path: os.PathLike):
        shape, chunks = dataset.shape, dataset.chunks
        if not hasattr(os, "preadv"):  # e.g. Windows
            raise ChunkIndexError("this system has no preadv")
        if chunks is None or len(shape) != 4:
            raise ChunkIndexError("frames are not chunked")
        plist = dataset.id.get_create_plist()
        if plist.get_nfilters():
            raise ChunkIndexError("frames are filtered (compressed)")
        if chunks[0] != 1 or chunks[3] != shape[3]:
            raise ChunkIndexError(f"chunks {chunks} do not span whole rows of one CCD")
        if not dataset.dtype.isnative:
            raise ChunkIndexError(f"frames are stored {dataset.dtype.str}, not in this machine's byte order")
        self.shape, self.chunks = shape, chunks
        chunk_bytes = int(np.prod(chunks)) * dataset.dtype.itemsize
        offsets = {}

        def visit(info):
            if info.size != chunk_bytes or info.filter_mask:
                raise ChunkIndexError(f"chunk {info.chunk_offset} is stored in {info.size} bytes")
            offsets[info.chunk_offset] = info.byte_offset

        try:
            dataset.id.chunk_iter(visit)
        except AttributeError:  # HDF5 older than 1.12.3
            raise ChunkIndexError("this HDF5 cannot list chunks") from None
        expected = int(np.prod([-(-s // c) for s, c in zip(shape, chunks, strict=True)]))
        if len(offsets) != expected:
            raise ChunkIndexError(f"{expected - len(offsets)} chunks were never written (HDF5 fills them)")
        self.offsets = offsets
        self.fd = os.open(path, os.O_RDONLY)

    def covers(self, rows: slice) -> bool:
        """Whether rows `rows` are whole bands of chunk rows (the last band may end at H only
        where H is a multiple of the chunk's rows: a partial chunk's rows are not contiguous)."""
        r0, r1, _ = rows.indices(self.shape[2])
        rc = self.chunks[2]
        return r0 % rc == 0 and (r1 - r0) % rc == 0 and r1 > r0

    def read_rows_into(self, out: np.ndarray, rows: slice) -> None:
        """Frames of rows `rows` (`covers` them) into the first rows of `out` (4, N, ≥h, W),
        C-contiguous, of the dataset's dtype."""
        _, n, _, _ = self.shape
        r0, r1, _ = rows.indices(self.shape[2])
        _, fc, rc, _ = self.chunks
        for c in range(4):
            for n0 in range(0, n, fc):
                k = min(fc, n - n0)  # a last chunk of frames holds fewer than fc frames of data
                for band in range(r0, r1, rc):
                    target = out[c, n0 : n0 + k, band - r0 : band - r0 + rc]
                    views = [target] if target.flags.c_contiguous else list(target)
                    want = sum(v.nbytes for v in views)
                    got = os.preadv(self.fd, views, self.offsets[(c, n0, band, 0)])
                    if got != want:
                        raise OSError(f"chunk {(c, n0, band, 0)}: {got} of {want} bytes read (a truncated file?)")

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
