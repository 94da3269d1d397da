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

import ctypes
import os

import h5py
import numpy as np

from . import native
from .early_read import file_identity

# struct iovec {void *iov_base; size_t iov_len;}, as `preadv` takes an array of them
IOVEC = np.dtype([("base", np.uintp), ("length", np.uintp)])


def _libc_preadv():
    """libc's `preadv` through ctypes, or None where there is none: `os.preadv` takes a list of
    buffers, and a chunk scattered over a tile's pieces is one buffer per frame and piece
    (128 for a 32-row chunk of 4 frames in pieces of one row), so the scatter tables are built
    once per buffer as arrays of `IOVEC` and the calls take pointers into them."""
    try:
        call = ctypes.CDLL(None, use_errno=True).preadv
    except (OSError, AttributeError):
        return None
    call.argtypes = [ctypes.c_int, ctypes.c_void_p, ctypes.c_int, ctypes.c_int64]
    call.restype = ctypes.c_ssize_t
    return call


PREADV = _libc_preadv()
# a scatter of more buffers than this is left to the gathered read (Linux's IOV_MAX)
MAX_IOVECS = 1024


class ChunkIndexError(ValueError):
    """The dataset's chunks cannot be read directly (the caller reads through HDF5)."""


class DirectChunkReader:
    """File offsets of every chunk of a (4, N, H, W) frames dataset whose chunks are
    (1, frames_per_chunk, rows_per_chunk, W), and `read_rows_into`, which reads a band of
    whole chunk rows into a (4, N, ≥rows, W) buffer with one `preadv` per chunk.

    `known`: (`early_read.file_identity`, offsets) of the same dataset, listed by another
    process (a `cohflash reconstruct` process's child): taken where the file opened here is
    that file, unchanged, instead of listing the chunks again."""

    def __init__(self, dataset: h5py.Dataset, path: os.PathLike, known: tuple | None = None):
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
        self.shape, self.chunks, self.itemsize = shape, chunks, dataset.dtype.itemsize
        grid = (4, -(-shape[1] // chunks[1]), -(-shape[2] // chunks[2]))  # CCD, frame chunk, band
        self.fd = os.open(path, os.O_RDONLY)
        if known is not None and known[0] == file_identity(self.fd) and known[1].shape == grid:
            self.offsets = known[1]
            return
        chunk_bytes = int(np.prod(chunks)) * dataset.dtype.itemsize
        offsets = np.full(grid, -1, np.int64)  # the file offset of chunk (c, g, b)

        def visit(info):
            if info.size != chunk_bytes or info.filter_mask:
                raise ChunkIndexError(f"chunk {info.chunk_offset} is stored in {info.size} bytes")
            c, n0, r0, _ = info.chunk_offset
            offsets[c, n0 // chunks[1], r0 // chunks[2]] = info.byte_offset

        try:
            dataset.id.chunk_iter(visit)
        except AttributeError:  # HDF5 older than 1.12.3
            self.close()
            raise ChunkIndexError("this HDF5 cannot list chunks") from None
        except ChunkIndexError:
            self.close()
            raise
        if (unwritten := int(np.count_nonzero(offsets < 0))) > 0:
            self.close()
            raise ChunkIndexError(f"{unwritten} chunks were never written (HDF5 fills them)")
        self.offsets = offsets

    def covers(self, rows: slice) -> bool:
        """Whether rows `rows` are whole bands of chunk rows (the last band may end at H only
        where H is a multiple of the chunk's rows: a partial chunk's rows are not contiguous)."""
        r0, r1, _ = rows.indices(self.shape[2])
        rc = self.chunks[2]
        return r0 % rc == 0 and (r1 - r0) % rc == 0 and r1 > r0

    def chunks_of(self, rows: slice):
        """The chunks holding rows `rows` (`covers` them), in file order by CCD, frames and band:
        (CCD c, frame chunk g, its first frame n0, the frames of data it holds, band b of the
        rows, its first row, the chunk's file offset, its bytes of data)."""
        _, n, _, w = self.shape
        r0, r1, _ = rows.indices(self.shape[2])
        _, fc, rc, _ = self.chunks
        offsets = self.offsets[:, :, r0 // rc : -(-r1 // rc)].tolist()  # (4, frame chunks, bands), as ints
        for c in range(4):
            for g, n0 in enumerate(range(0, n, fc)):
                k = min(fc, n - n0)  # a last chunk of frames holds fewer than fc frames of data
                for b, band in enumerate(range(r0, r1, rc)):
                    yield c, g, n0, k, b, band, offsets[c][g][b], k * rc * w * self.itemsize

    @staticmethod
    def check_read(got: int, want: int, chunk: tuple, errno: int | None = None) -> None:
        """A chunk read short (a truncated file) or failed, as an `OSError` naming the chunk
        (`errno`: the failed read's, default ctypes' last)."""
        if got != want:
            errno = ctypes.get_errno() if errno is None else errno
            error = f" ({os.strerror(errno)})" if got < 0 else " (a truncated file?)"
            raise OSError(f"chunk {chunk}: {got} of {want} bytes read{error}")

    def read_rows_into(self, out: np.ndarray, rows: slice) -> None:
        """Frames of rows `rows` (`covers` them) into the first rows of `out` (4, N, ≥h, W),
        C-contiguous, of the dataset's dtype."""
        r0 = rows.indices(self.shape[2])[0]
        rc = self.chunks[2]
        for c, _, n0, k, _, band, offset, want in self.chunks_of(rows):
            target = out[c, n0 : n0 + k, band - r0 : band - r0 + rc]
            got = os.preadv(self.fd, [target] if target.flags.c_contiguous else list(target), offset)
            self.check_read(got, want, (c, n0, band, 0))

    def scatters(self, rows: int, rows_per_piece: int) -> bool:
        """Whether `read_rows_into_pieces` reads a tile of `rows` rows (whole chunk bands) in
        pieces of `rows_per_piece` rows: libc's `preadv` is at hand and a chunk's scatter fits
        in one call."""
        _, fc, rc, _ = self.chunks
        pieces_per_band = -(-rc // rows_per_piece) + 1
        return PREADV is not None and rows % rows_per_piece == 0 and fc * pieces_per_band <= MAX_IOVECS

    def scatter_table(self, pieces: list[np.ndarray], rows: int, rows_per_piece: int) -> list[np.ndarray]:
        """For each chunk band of a tile of `rows` rows, the `IOVEC`s that scatter each of its
        chunks into `pieces` (4, N, rows_per_piece·W) of consecutive rows: (4, frame chunks,
        frames per chunk × runs), a run being a chunk's frame's rows within one piece."""
        _, n, _, w = self.shape
        _, fc, rc, _ = self.chunks
        item = pieces[0].itemsize
        addresses = np.array([p.ctypes.data for p in pieces], np.uintp)
        frame_bytes = rows_per_piece * w * item
        groups = -(-n // fc)
        frames = np.minimum(np.arange(groups * fc).reshape(groups, fc), n - 1)  # past N: never read
        tables = []
        for band in range(0, rows, rc):
            rel = np.arange(band, band + rc)
            piece, row = rel // rows_per_piece, rel % rows_per_piece
            starts = np.flatnonzero(np.r_[True, piece[1:] != piece[:-1]])  # runs of rows in one piece
            counts = np.diff(np.r_[starts, rc])
            base = addresses[piece[starts]] + (row[starts] * w * item).astype(np.uintp)  # (runs,)
            table = np.empty((4, groups, fc, starts.size), IOVEC)
            table["base"] = (
                base[None, None, None, :]
                + (np.arange(4) * n * frame_bytes).astype(np.uintp)[:, None, None, None]
                + (frames * frame_bytes).astype(np.uintp)[None, :, :, None]
            )
            table["length"] = (counts * w * item).astype(np.uintp)[None, None, None, :]
            tables.append(table.reshape(4, groups, fc * starts.size))
        return tables

    def read_rows_into_pieces(self, tables: list[np.ndarray], rows: slice) -> None:
        """Frames of rows `rows` (`covers` them; as many rows as the tables were made for) read
        straight into the pieces of `scatter_table`'s `tables`: each chunk with one `preadv`
        that scatters its frames' rows to the pieces they belong to, so a piece is ready to be
        computed on without a copy."""
        offsets, wants, addresses, counts = self.piece_reads(tables, rows)
        if native.reads_chunks():  # the whole tile in one call (`native.read_chunks`)
            short = native.read_chunks(self.fd, offsets.ravel(), wants.ravel(), addresses.ravel(), counts.ravel())
        else:  # one call a chunk, in the same order
            short = None
            for i, (offset, want, address, count) in enumerate(
                zip(*(a.ravel().tolist() for a in (offsets, wants, addresses, counts)))
            ):
                if (got := PREADV(self.fd, address, count, offset)) != want:
                    short = (i, got, ctypes.get_errno())
                    break
        if short is not None:
            index, got, errno = short
            c, g, b = (int(i) for i in np.unravel_index(index, offsets.shape))
            r0, fc, rc = rows.indices(self.shape[2])[0], self.chunks[1], self.chunks[2]
            self.check_read(got, int(wants[c, g, b]), (c, g * fc, r0 + b * rc, 0), errno)

    def piece_reads(self, tables: list[np.ndarray], rows: slice) -> tuple:
        """`read_rows_into_pieces`'s reads, in `chunks_of`'s order, as arrays (4, frame chunks,
        bands): each chunk's file offset, its bytes of data, the address of its `IOVEC`s in
        `tables` and their count."""
        _, n, _, w = self.shape
        _, fc, rc, _ = self.chunks
        r0, r1, _ = rows.indices(self.shape[2])
        groups = tables[0].shape[1]
        offsets = self.offsets[:, :, r0 // rc : -(-r1 // rc)]
        held = np.minimum(fc, n - fc * np.arange(groups))[None, :, None]  # frames of data a chunk holds
        runs = np.asarray([t.shape[-1] // fc for t in tables], np.uint64)[None, None, :]  # IOVECs a frame
        first = (np.arange(4)[:, None, None] * groups + np.arange(groups)[None, :, None]).astype(np.uint64)
        start = np.asarray([t.ctypes.data for t in tables], np.uint64)[None, None, :]  # (c, g) rows of a band's table
        addresses = start + first * np.uint64(fc * IOVEC.itemsize) * runs
        counts = np.broadcast_to(held.astype(np.uint64) * runs, offsets.shape)
        wants = np.broadcast_to(held * rc * w * self.itemsize, offsets.shape)
        return offsets, wants, addresses, counts

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None
