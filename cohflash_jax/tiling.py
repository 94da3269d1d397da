"""How a capture is cut for reconstruction: rows per streamed tile, pixels per dispatched
sub-tile, and the pieces of whole rows a tile is read into. Plain arithmetic on the capture's
shape, without JAX: a `cohflash reconstruct` process reads its first tile (`early_read`) before
JAX is imported, into the very pieces the reconstruction then takes (`engine.PieceReader`).
The platform ("cpu", "gpu", …) is an argument here; `reconstruct.engine` passes JAX's.
Measured sizes and timings: docs/performance.md.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

DEFAULT_TILE_ROWS = 32  # = the capture writer's chunk rows: each chunk is read once
# A streamed tile holds more than `DEFAULT_TILE_ROWS` rows where its frames stay within this:
# a short sweep's whole frame (the 10 Hz mode: 23 MB) is one tile, dispatched in sub-tiles of
# the full size (`sub_tile_pixels`) instead of 32-row pieces of a quarter of it
TILE_FRAME_BYTES = 64 * 2**20

# CPU: the uint16 frames of a sub-tile (4·N·2 bytes a pixel) fit in ~12 MiB, so its I/Q,
# moment and FFT passes run from cache; a tile gives at least `MIN_PIECES` sub-tiles to overlap
# reads and copies with compute; at most `MAX_SUB_TILE_PIXELS` (short sweeps would otherwise
# give a few huge pieces, and a vmapped fit runs as long as its slowest pixel).
SUB_TILE_CACHE_BYTES = 12 * 2**20
MIN_PIECES = 4
MIN_SUB_TILE_PIXELS = 256
MAX_SUB_TILE_PIXELS = 8192
# GPU: the whole tile a piece (per-dispatch overhead dominates small pieces), up to this much
# of frames (a 32-row tile of 3000 frames is 245 MB; its float intermediates take several times that)
DEVICE_PIECE_BYTES = 256 * 2**20
BUFFER_ALIGNMENT_BYTES = 64  # JAX aliases (does not copy) host buffers aligned so on the CPU

# A capture smaller than a sub-tile is padded to a power of two of at least this many pixels:
# regions of interest of different sizes then share compiled programs (one per bucket, not
# one per pixel count), for at most twice the compute of a capture that is small anyway
MIN_PIXEL_BUCKET = 64

# work on at most this many pixels (a region of interest, a test's capture, the pixels a
# posterior or a calibration fits) runs its programs once or twice, so they are compiled for a
# short compile; larger work for speed (`runtime.quick_compile`)
QUICK_COMPILE_MAX_PIXELS = 1024


def aligned_empty(shape: tuple, dtype) -> np.ndarray:
    """An uninitialised C-contiguous array at a `BUFFER_ALIGNMENT_BYTES`-aligned address, which
    a CPU device array aliases (`jax.device_put` does not copy it)."""
    dtype = np.dtype(dtype)
    size = math.prod(shape) * dtype.itemsize
    raw = np.empty(size + BUFFER_ALIGNMENT_BYTES, np.uint8)
    start = -raw.ctypes.data % BUFFER_ALIGNMENT_BYTES
    return raw[start : start + size].view(dtype).reshape(shape)


def rows_per_tile(shape: tuple[int, int, int], itemsize: int = 2, tile_rows: int | None = None) -> int:
    """Rows per streamed tile of a capture of `shape` (frames, height, width) stored with
    `itemsize` bytes a value: `tile_rows` where given, else whole multiples of
    `DEFAULT_TILE_ROWS` (the writer's chunk rows) holding at most `TILE_FRAME_BYTES` of
    frames, at least one; never more than the height."""
    n, h, w = shape
    if tile_rows is not None:
        return min(tile_rows, h)
    chunk_bytes = 4 * n * w * itemsize * DEFAULT_TILE_ROWS
    return min(h, DEFAULT_TILE_ROWS * max(1, TILE_FRAME_BYTES // max(1, chunk_bytes)))


def power_of_two_bucket(count: int, minimum: int) -> int:
    """The next power of two at or above `count`, at least `minimum`: the size work of `count`
    items is padded to, so that nearby counts share one compiled program."""
    return max(minimum, 1 << (max(1, count) - 1).bit_length())


def pixel_bucket(num_pixels: int) -> int:
    """The padded pixel count of a small capture: the next power of two, at least `MIN_PIXEL_BUCKET`."""
    return power_of_two_bucket(num_pixels, MIN_PIXEL_BUCKET)


def sub_tile_pixels(num_pixels: int, num_frames: int, platform: str) -> int:
    """Pixels per dispatched sub-tile on `platform`; a capture smaller than one sub-tile is
    padded to its `pixel_bucket`. On a GPU, where a piece is the whole tile, a region of
    interest (`QUICK_COMPILE_MAX_PIXELS`) is padded alike, so its neighbours in size run its
    programs there too."""
    if platform != "cpu":
        pixels = pixel_bucket(num_pixels) if num_pixels <= QUICK_COMPILE_MAX_PIXELS else num_pixels
        return int(max(1, min(pixels, DEVICE_PIECE_BYTES // (8 * max(1, num_frames)))))
    by_memory = SUB_TILE_CACHE_BYTES // (8 * max(1, num_frames))
    limit = min(by_memory, MAX_SUB_TILE_PIXELS, max(MIN_SUB_TILE_PIXELS, -(-num_pixels // MIN_PIECES)))
    return int(max(1, min(pixel_bucket(num_pixels), limit)))


def piece_rows(rows: int, num_frames: int, width: int, platform: str) -> int | None:
    """Rows per sub-tile where a tile of `rows` rows is read straight into its sub-tiles
    (`engine.PieceReader`), on the CPU, for a tile of at least `MIN_PIECES` sub-tiles: the
    most whole rows within `sub_tile_pixels`' size that divide the tile, and at least half that
    size; None where no such number is (a piece of one row would be far smaller than a
    sub-tile: the tile is read whole and its sub-tiles copied) or the tile is smaller (a region
    of interest keeps its `pixel_bucket`, and the programs its neighbours in size run)."""
    if platform != "cpu":
        return None
    sub = sub_tile_pixels(rows * width, num_frames, platform)
    if rows * width < MIN_PIECES * sub:
        return None
    fits = [k for k in range(1, rows + 1) if rows % k == 0 and k * width <= sub]
    return fits[-1] if fits and 2 * fits[-1] * width >= sub and fits[-1] < rows else None


@dataclasses.dataclass(frozen=True)
class PieceLayout:
    """How a tile of `rows` rows of a capture of `shape` (N, H, W) and `dtype` is read into
    pieces of `rows_per_piece` whole rows (`engine.PieceReader`, and a `cohflash reconstruct`
    process's child, `early_read`): `count` pieces of (4, N, `sub`) frames, `stride` bytes
    apart from the first `BUFFER_ALIGNMENT_BYTES`-aligned byte of a buffer of `buffer_bytes`."""

    shape: tuple[int, int, int]
    dtype: np.dtype
    rows: int
    rows_per_piece: int

    @classmethod
    def of(cls, shape: tuple[int, int, int], dtype, rows: int, platform: str) -> PieceLayout | None:
        """The layout where tiles of `rows` rows are read in pieces on `platform` (`piece_rows`);
        None for a region of interest (`QUICK_COMPILE_MAX_PIXELS`), whose tiles keep their
        `pixel_bucket`, or where no piece size fits."""
        n, h, w = shape
        rows_per_piece = None if h * w <= QUICK_COMPILE_MAX_PIXELS else piece_rows(rows, n, w, platform)
        if rows_per_piece is None:
            return None
        return cls(tuple(int(s) for s in shape), np.dtype(dtype), int(rows), rows_per_piece)

    @property
    def sub(self) -> int:
        """Pixels a piece (a dispatched sub-tile)."""
        return self.rows_per_piece * self.shape[2]

    @property
    def count(self) -> int:
        return self.rows // self.rows_per_piece

    @property
    def piece_shape(self) -> tuple[int, int, int]:
        return (4, self.shape[0], self.sub)

    @property
    def stride(self) -> int:
        nbytes = math.prod(self.piece_shape) * self.dtype.itemsize
        return -(-nbytes // BUFFER_ALIGNMENT_BYTES) * BUFFER_ALIGNMENT_BYTES

    @property
    def buffer_bytes(self) -> int:
        """Bytes of a buffer that holds a tile's pieces wherever it starts."""
        return self.count * self.stride + BUFFER_ALIGNMENT_BYTES

    @property
    def key(self) -> list:
        """The layout as plain values (`early_read` reports it and the reader compares it): N, H,
        W, the dtype's name, the tile's rows, the rows a piece, the pieces' stride."""
        return [*self.shape, str(self.dtype), self.rows, self.rows_per_piece, self.stride]

    def pieces(self, raw: np.ndarray) -> list[np.ndarray]:
        """The pieces laid out in the bytes `raw` (uint8, at least `buffer_bytes`), as views of
        `raw`, the first at its first `BUFFER_ALIGNMENT_BYTES`-aligned byte."""
        start = -raw.ctypes.data % BUFFER_ALIGNMENT_BYTES
        size = math.prod(self.piece_shape) * self.dtype.itemsize
        offsets = [start + k * self.stride for k in range(self.count)]
        return [raw[o : o + size].view(self.dtype).reshape(self.piece_shape) for o in offsets]

    def tile_view(self, raw: np.ndarray) -> np.ndarray:
        """The same pieces of `raw` seen as one read-only (4, N, `count`, `sub`) array: the
        tile's pixels in row-major order (the carrier survey's sample)."""
        start = -raw.ctypes.data % BUFFER_ALIGNMENT_BYTES
        (_, n, sub), item = self.piece_shape, self.dtype.itemsize
        return np.lib.stride_tricks.as_strided(
            raw[start:].view(self.dtype),
            shape=(4, n, self.count, sub),
            strides=(n * sub * item, sub * item, self.stride, item),
            writeable=False,
        )
