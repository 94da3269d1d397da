"""Streaming a capture through the sub-tile programs with bounded memory.

Row tiles are read into reused buffers (`BlockReader`); each tile is cut into sub-tiles
of a few hundred pixels (`sub_tile_pixels`) whose frames fit in cache, dispatched
asynchronously and in turn to the stream devices (`TileDispatcher`); a tile is gathered
(`PendingTile.gather`) while the next one is read and computed. Where a capture's chunks can be
read straight from the file, a tile is read into its sub-tiles of whole rows instead
(`PieceReader`), none copied. On a GPU a tile is one piece.
Measured sizes and timings: docs/performance.md.
"""

from __future__ import annotations

import collections
import concurrent.futures
import contextvars
import dataclasses
import math
import os
import threading

import jax
import jax.numpy as jnp
import numpy as np

from .. import early_read, native, tiling
from ..capture import Capture
from ..estimate.iq import folded_weights
from ..runtime import EXECUTABLES, device_value, place_on_devices, stream_devices
from .plan import TilePlan, program_plan
from .programs import SPLIT_AXIS_MIN_FRAMES, inversion_half, inversion_plan, prepare_stages, process_stages

# the native kernel's rotated-sequence buffers kept for later sub-tiles, at most
# (`TileDispatcher.free_sequence_buffer`): two tiles' worth of a full frame (32 sub-tiles a tile)
SEQUENCE_BUFFERS_KEPT = 64


def sub_tile_pixels(num_pixels: int, num_frames: int, platform: str | None = None) -> int:
    """`tiling.sub_tile_pixels` on `platform` (default: JAX's default backend)."""
    return tiling.sub_tile_pixels(num_pixels, num_frames, platform or jax.default_backend())


def aligned_copy(view: np.ndarray, width: int) -> np.ndarray:
    """A C-contiguous copy of `view`, its last axis zero-padded to `width`, in a 64-byte
    aligned buffer, which `jax.device_put` aliases on the CPU instead of copying again
    (`jnp.asarray` of a strided sub-tile copies twice)."""
    out = tiling.aligned_empty(view.shape[:-1] + (width,), view.dtype)
    out[..., : view.shape[-1]] = view
    out[..., view.shape[-1] :] = 0
    return out


def padded(arr: np.ndarray, width: int, fill) -> np.ndarray:
    """`arr` with its last axis filled out to `width` with `fill` (itself where it is that wide)."""
    if arr.shape[-1] == width:
        return arr
    return np.pad(arr, [(0, 0)] * (arr.ndim - 1) + [(0, width - arr.shape[-1])], constant_values=fill)


_KERNEL_THREADS = (None, None, 0)  # (the process id that made them, the pool, its threads)
_KERNEL_THREADS_LOCK = threading.Lock()


def kernel_threads() -> concurrent.futures.ThreadPoolExecutor:
    """The threads the native I/Q kernel runs sub-tiles on, one per stream device (made once a
    process, and again in a forked child, which has none of its parent's threads): the
    dispatching thread only places the inversions, so that a short sweep's sub-tiles, whose
    kernel time is a good part of a 10 Hz map, compute beside each other and beside the
    inversions (docs/performance.md)."""
    global _KERNEL_THREADS
    with _KERNEL_THREADS_LOCK:
        made_by, pool, count = _KERNEL_THREADS
        if pool is None or made_by != os.getpid():
            count = count or max(1, len(stream_devices()))  # a forked child does not ask JAX again
            pool = concurrent.futures.ThreadPoolExecutor(count, thread_name_prefix="native-iq")
            _KERNEL_THREADS = (os.getpid(), pool, count)
        return pool


def tile_buffer(shape: tuple, dtype) -> np.ndarray:
    """A zeroed C-contiguous array for tiles read from a capture: in the memory a `cohflash
    reconstruct` process mapped while it imported (`early_read.take_mapping`) where there is
    such memory and it is large enough, else newly allocated."""
    nbytes = math.prod(shape) * np.dtype(dtype).itemsize
    mapping = early_read.take_mapping(nbytes)
    if mapping is None:
        return np.zeros(shape, dtype)
    return np.frombuffer(mapping, np.uint8, count=nbytes).view(dtype).reshape(shape)


@dataclasses.dataclass
class PendingTile:
    """The dispatched sub-tiles of one tile of `num_pixels` pixels (their results computing)."""

    parts: list
    num_pixels: int
    holds_frames: bool = True  # the device arrays may alias the host frames until gathered
    native_iq: bool = False  # its I/Q halves computed by the native kernel (`TileDispatcher.host_iq`)

    def gather(self) -> dict:
        """Join the sub-tiles' results → dict of (P,) NumPy arrays (blocks until computed)."""
        parts = self.parts
        return {k: np.concatenate([np.asarray(r[k]) for r in parts])[: self.num_pixels] for k in parts[0]}


class TileDispatcher:
    """Runs `process_tile` over tiles in sub-tiles of `sub_px` pixels, each dispatched
    asynchronously (the last padded to the same shape: one compilation per device), in turn
    on each of `stream_devices`. The plan (as `program_plan` gives it, split into its I/Q
    stage and inversion plan for `process_stages`) and a known carrier drift are placed on
    every device once, when the dispatcher is made, not once per tile."""

    def __init__(self, plan: TilePlan, sub_px: int | None = None, carrier_phase_rad=None):
        self.sub_px = sub_px
        self.devices = stream_devices()
        carrier = None if carrier_phase_rad is None else device_value(carrier_phase_rad)
        plan = program_plan(plan)
        self.placed = place_on_devices((plan.iq, inversion_plan(plan), carrier), self.devices)
        self.no_status = {}  # (pixels, device) → placed zeros: "no upstream status"
        self.all_finite = {}  # (pixels, device) → placed `True`s: integer frames are finite
        # the native kernel's rotated-sequence buffers, oldest first, each with an output of the
        # inversion that reads it (`free_sequence_buffer`)
        self.sequence_buffers = collections.deque(maxlen=SEQUENCE_BUFFERS_KEPT)
        self.buffers_lock = threading.Lock()  # the kernel's threads take buffers, this one returns them
        self.prepared = set()  # the kinds of tile `prepare` was asked for
        # the I/Q stage on the host, for the native kernel (`host_iq`): weights, bias, saturation
        stage = plan.iq
        self.host_stage = (np.asarray(stage.weights, np.float32), np.asarray(stage.bias, np.float32), stage)

    def zero_status(self, pixels: int, device):
        """A sub-tile's upstream status where there is none (all 0: nothing found upstream),
        placed once: the inversion programs then take a status array whether or not a capture
        has one (a registered capture's resampling has), and the two share their programs."""
        return self.placed_constant(self.no_status, 0, np.int8, pixels, device)

    def cut(self, frames) -> tuple[int, int]:
        """(pixels, pixels a sub-tile) of a tile (4, N, P), its `TilePieces` or its
        `jax.ShapeDtypeStruct`, as `dispatch` cuts it (a sub-tile larger than the tile pads it:
        `pixel_bucket`)."""
        p = frames.num_pixels if isinstance(frames, TilePieces) else frames.shape[-1]
        return p, self.sub_px or p

    def stream(self, k: int) -> tuple:
        """Where sub-tile k runs: (its device, None on a single stream; the I/Q stage, inversion
        plan and carrier drift placed there)."""
        device = self.devices[k % len(self.devices)] if len(self.devices) > 1 else None
        return device, self.placed[k % len(self.placed)]

    def prepare(self, frames, dark=None, data_status=None, gain=None) -> concurrent.futures.Future | None:
        """Start getting, in a thread, the inversion program each stream device will run on
        the sub-tiles of a tile like this one (as `dispatch` takes it, or its
        `jax.ShapeDtypeStruct`s), loaded or compiled (`programs.prepare_stages`). On a cold
        cache its compile, most of a first run's, then overlaps the first read and the I/Q
        programs' compiles instead of following them. The caller's `quick_compile` setting
        holds in the thread. Returns the thread's future; None where tiles of this kind were
        prepared before (a stream of captures prepares once) or the executable cache is loading
        this process's programs already (`ExecutableCache.loading`): nothing to gain."""
        kind = tuple(None if a is None else shape_and_type(a) for a in (frames, dark, data_status, gain))
        if kind in self.prepared or EXECUTABLES.loading():
            return None
        self.prepared.add(kind)
        p, sub = self.cut(frames)
        halves = self.host_iq(frames) or None  # the native kernel's tiles run the inversion half alone

        def like(arr, device):
            """A sub-tile of `arr` as `dispatch` places it, as shape, type and device."""
            if arr is None:
                return None
            shape, dtype = shape_and_type(arr)
            placed = jax.sharding.SingleDeviceSharding(jax.devices()[0] if device is None else device)
            return jax.ShapeDtypeStruct(shape[:-1] + (sub,), dtype, sharding=placed)

        def prepare_all():
            # the first sub-tile each device runs (as many devices as the tile has sub-tiles)
            for k in range(min(len(self.devices), -(-p // sub))):
                device, (stage, plan, carrier) = self.stream(k)
                prepare_stages(
                    stage,
                    plan,
                    like(frames, device),
                    like(dark, device),
                    self.zero_status(sub, device) if data_status is None else like(data_status, device),
                    like(gain, device),
                    carrier,
                    halves=halves,
                )

        pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="prepare-programs")
        future = pool.submit(contextvars.copy_context().run, prepare_all)
        pool.shutdown(wait=False)  # its thread ends with the preparation
        return future

    def placed_constant(self, cache: dict, value, dtype, pixels: int, device):
        """`value` over a sub-tile's pixels, placed on `device` once (`cache`: (pixels, device) → array)."""
        if (pixels, device) not in cache:
            cache[pixels, device] = jax.device_put(np.full(pixels, value, dtype), device)
        return cache[pixels, device]

    def host_iq(self, frames) -> bool:
        """Whether a tile's I/Q halves run in the native kernel on the host (`native.iq_half`)
        instead of XLA's I/Q programs: on the CPU, for 16-bit frames on the host (a tile read
        as its sub-tiles, `TilePieces`, or an array whose sub-tiles the kernel reads in place;
        a tile's `jax.ShapeDtypeStruct` asks of such a tile), in float32, without a tracked
        carrier or a known carrier drift to remove."""
        if not native.available() or jax.default_backend() != "cpu":
            return False
        stage, (_, _, carrier) = self.host_stage[2], self.placed[0]
        piece = first_piece(frames)
        on_host = isinstance(piece, (np.ndarray, jax.ShapeDtypeStruct))
        return (
            carrier is None
            and on_host
            and piece.dtype == np.uint16
            and stage.real_dtype == jnp.float32
            and not stage.tracking
        )

    @staticmethod
    def kernel_on_threads(frames) -> bool:
        """Whether a tile's sub-tiles go to the kernel's threads (`kernel_threads`): a short
        sweep's, whose kernel is a good part of their work (a 10 Hz map's dispatching thread
        would hold the inversions back), not a long sweep's, whose inversion costs several times
        its kernel: there the dispatching (feeding) thread runs each between its dispatches,
        which measured quicker whole (docs/performance.md)."""
        return first_piece(frames).shape[1] < SPLIT_AXIS_MIN_FRAMES

    def host_iq_half(self, frames, dark, gain, k: int) -> native.IQHalf:
        """Sub-tile k's I/Q half by the native kernel, on the calling thread (the dispatching one,
        or one of `kernel_threads`; the interpreter lock released while it runs): its frames read
        in place where they can be (a `TilePieces` piece, or the sub-tile's columns of an
        array), else from an aligned, zero-padded copy (a tile's last, narrower sub-tile)."""
        _, sub = self.cut(frames)
        columns = slice(k * sub, (k + 1) * sub)
        if isinstance(frames, TilePieces):
            piece = frames.pieces[k]
        else:
            piece = frames[..., columns]
            if piece.shape[-1] != sub or not native.readable_in_place(piece):
                piece = aligned_copy(piece, sub)
        weights, bias, stage = self.host_stage
        pixel_map = lambda m, fill: None if m is None else padded(np.asarray(m[..., columns], np.float32), sub, fill)
        weights, bias = folded_weights(weights, bias, pixel_map(dark, 0.0), pixel_map(gain, 1.0), np.float32)
        return native.iq_half(piece, weights, bias, stage.saturation_dn, self.free_sequence_buffer(piece.shape[1:]))

    def invert_host_iq(self, half: native.IQHalf, data_status, k: int, sub: int):
        """Sub-tile k's inversion (`programs.inversion_half`) dispatched on its device, from its
        I/Q half by the native kernel (`host_iq_half`) as host arrays: the program places them
        there itself, aliased (`runtime.host_arrays_placed`), cheaper than a `jax.device_put`
        each."""
        device, (_, plan, _) = self.stream(k)
        finite = self.placed_constant(self.all_finite, True, bool, sub, device)
        flags = (half.dead.view(bool), half.saturated.view(bool), finite)
        iq = (half.r, half.noise_var, half.total_var, flags)
        if data_status is None:
            status = self.zero_status(sub, device)
        else:
            status = padded(np.asarray(data_status[k * sub : (k + 1) * sub]), sub, 0)
        result = inversion_half(plan, iq, status)
        with self.buffers_lock:
            self.sequence_buffers.append((half.r, result["depth_m"]))
        return result

    def free_sequence_buffer(self, shape: tuple) -> np.ndarray | None:
        """The oldest rotated-sequence buffer the native kernel wrote whose inversion has run
        (its device array read it, aliased), for the next sub-tile, or None (a new one): a
        buffer freed and allocated again was fresh memory to the allocator each time (~30 k
        page faults a full capture, docs/performance.md). Safe from the kernel's threads."""
        with self.buffers_lock:
            buffers = self.sequence_buffers
            if buffers and buffers[0][0].shape == shape and buffers[0][1].is_ready():
                return buffers.popleft()[0]
        return None

    def dispatch(self, frames, dark=None, data_status=None, gain=None) -> PendingTile:
        """Dispatch a tile (4, N, P), or read as its sub-tiles (`TilePieces` of `sub_px`), with
        its per-pixel maps (4, P) and upstream status (P,). Where the native kernel applies
        (`host_iq`) the sub-tiles' I/Q halves run on this thread or on the kernel's threads
        (`kernel_on_threads`), and this thread dispatches each one's inversion as its half is
        done: it returns once the kernel has read every frame."""
        p, sub = self.cut(frames)
        several = len(self.devices) > 1
        if self.host_iq(frames):
            count = -(-p // sub)
            if self.kernel_on_threads(frames):
                halves = [kernel_threads().submit(self.host_iq_half, frames, dark, gain, k) for k in range(count)]
                try:
                    parts = [self.invert_host_iq(half.result(), data_status, k, sub) for k, half in enumerate(halves)]
                finally:
                    concurrent.futures.wait(halves)  # none still reading the frames when this returns
            else:
                parts = [
                    self.invert_host_iq(self.host_iq_half(frames, dark, gain, k), data_status, k, sub)
                    for k in range(count)
                ]
            return PendingTile(parts, p, holds_frames=False, native_iq=True)  # read by the kernel, not aliased

        def piece(arr, k, device):
            if arr is None:
                return None
            if isinstance(arr, TilePieces):  # read as its sub-tiles: aliased, not copied
                return jax.device_put(arr.pieces[k], device)
            part = arr[..., k * sub : (k + 1) * sub]
            if isinstance(part, np.ndarray):  # one host copy at most (none for a whole contiguous tile)
                whole = part.shape[-1] == sub and part.flags.c_contiguous
                return jax.device_put(part if whole else aligned_copy(part, sub), device)
            if part.shape[-1] < sub:
                part = jnp.pad(part, [(0, 0)] * (part.ndim - 1) + [(0, sub - part.shape[-1])])
            return jax.device_put(part, device) if several else part

        parts = []
        pieces = -(-p // sub)
        for k in range(pieces):
            device, (stage, plan, carrier) = self.stream(k)
            parts.append(
                process_stages(
                    stage,
                    plan,
                    piece(frames, k, device),
                    piece(dark, k, device),
                    self.zero_status(sub, device) if data_status is None else piece(data_status, k, device),
                    piece(gain, k, device),
                    carrier,
                )
            )
        # host frames cut into several pieces were copied (`aligned_copy`); one whole piece is
        # aliased on the CPU, and on a GPU its transfer may still be reading them
        return PendingTile(parts, p, holds_frames=not (isinstance(frames, np.ndarray) and pieces > 1))


@dataclasses.dataclass(frozen=True)
class TilePieces:
    """A tile read as its sub-tiles (`PieceReader`): `pieces`, each (4, N, sub) frames of whole
    consecutive rows, C-contiguous and `BUFFER_ALIGNMENT_BYTES`-aligned, so that a CPU device
    array aliases it; `frames`, the same memory seen as (4, N, pieces, sub), pixels in
    row-major order (the carrier survey's sample)."""

    pieces: list
    frames: np.ndarray

    @property
    def num_pixels(self) -> int:
        return len(self.pieces) * self.pieces[0].shape[-1]


def first_piece(arr):
    """What `TileDispatcher.dispatch` cuts an input as: a `TilePieces`' first piece, else the
    array (or its `jax.ShapeDtypeStruct`) itself."""
    return arr.pieces[0] if isinstance(arr, TilePieces) else arr


def shape_and_type(arr) -> tuple:
    """(shape, dtype) of an input as `TileDispatcher.dispatch` cuts it (a `TilePieces` by its
    pieces; an array, or its `jax.ShapeDtypeStruct`, whole)."""
    piece = first_piece(arr)
    return piece.shape, np.dtype(piece.dtype)


class TileBuffers:
    """Reused buffers that row tiles are read into, at most two: a tile whose buffer is still
    aliased by dispatched work (`hold_last`) keeps it, and the next tile goes into the other
    (the caller gathers tile k before reading tile k + 2). A reader makes a buffer with its
    `new_buffer` (appending it to `buffers`; None where it cannot: a `PieceReader` whose
    capture cannot be scattered into it)."""

    def __init__(self):
        self.buffers = []
        self.last = self.held = None

    def release_in_background(self) -> None:
        """Let go of the buffers (the caller holds no tile of them) in a thread of their own, so
        that their memory is unmapped there: at a run's end that was ~0.1 s of one core (the
        early read's shared pages truncated, docs/performance.md) while the other core finished
        the last inversions, or waited."""
        buffers, self.buffers = self.buffers, []
        self.last = self.held = None
        threading.Thread(target=buffers.clear, name="release-tile-buffers", daemon=True).start()

    def hold_last(self, held: bool) -> None:
        """Whether the last tile read is still in use (its buffer not to be read into next)."""
        self.held = self.last if held else None

    def free_buffer(self):
        """A buffer not held, made where there is none, for the next tile (then the last one)."""
        free = [k for k in range(len(self.buffers)) if k != self.held]
        if not free:
            if self.new_buffer() is None:
                raise RuntimeError(f"{self.capture.path}: no buffer for its next tile could be made")
            free = [len(self.buffers) - 1]
        self.last = free[0]
        return self.buffers[self.last]


class PieceReader(TileBuffers):
    """Row tiles of a capture read straight into their sub-tiles of whole rows, laid out as
    `layout` says (`Capture.read_tile_into_pieces`): each chunk scattered by one `preadv` to the pieces its
    rows belong to, so no piece is copied out of a tile buffer before it is dispatched (a
    `BlockReader` tile cut into sub-tiles is). A piece dispatched to XLA's I/Q programs is
    aliased by its device array until its tile is gathered, so such tiles alternate between two
    buffers (`hold_last`; the caller gathers tile k before reading tile k + 2); pieces the
    native kernel reads are free once their tile's dispatch returns, and the next tile is read
    into the same buffer (`reconstruct.api`). None from `of` where the capture's frames are
    not stored for it (`Capture.scatter_tables`)."""

    def __init__(self, capture: Capture, layout: tiling.PieceLayout):
        super().__init__()  # (TilePieces, scatter tables) a buffer
        self.capture, self.layout = capture, layout

    @classmethod
    def of(cls, capture: Capture, rows: int) -> PieceReader | None:
        layout = tiling.PieceLayout.of(capture.shape, capture.frames.dtype, rows, jax.default_backend())
        if layout is None or capture.store != "hdf5" or capture.direct_reader is None:
            return None
        reader = cls(capture, layout)
        return reader if reader.new_buffer() is not None else None

    def new_buffer(self):
        """Pieces for one tile in one aligned allocation (`tile_buffer`), and their scatter
        tables; None where the capture cannot scatter into them."""
        layout = self.layout
        raw = tile_buffer((layout.buffer_bytes,), np.uint8)
        pieces = layout.pieces(raw)
        tables = self.capture.scatter_tables(pieces, layout.rows, layout.rows_per_piece)
        if tables is None:
            return None
        self.buffers.append((TilePieces(pieces, layout.tile_view(raw)), tables))
        return self.buffers[-1]

    def read(self, r0: int) -> TilePieces:
        rows, sub = self.layout.rows, self.layout.sub
        r1 = min(self.capture.shape[1], r0 + rows)
        tile, tables = self.free_buffer()
        if r0 == 0 and self.first_tile_read_early(tile):
            return tile
        if r1 - r0 < rows:  # pad the last tile so every tile has one compiled shape
            rows_read = (r1 - r0) * sub // self.layout.rows_per_piece
            for k, piece in enumerate(tile.pieces):
                piece[..., max(0, min(sub, rows_read - k * sub)) :] = 0
        self.capture.read_tile_into_pieces(tile.pieces, tables, slice(r0, r1))
        return tile

    def first_tile_read_early(self, tile: TilePieces) -> bool:
        """Whether `tile`, the first buffer, holds the capture's first tile already: read there,
        in this layout, by the child this process forked as it started (`early_read`)."""
        if tile is not self.buffers[0][0]:
            return False
        address = tile.pieces[0].ctypes.data
        return early_read.holds_first_tile(self.capture.direct_reader.fd, self.layout.key, address)


class BlockReader(TileBuffers):
    """Row tiles of a capture read into reused buffers: allocating a fresh ~250 MB array per
    tile costs more than the read itself on a cold machine (first touch of its memory).

    A tile cut into sub-tiles is copied out of its buffer when dispatched, so the next tile
    is read into the same buffer. A tile dispatched whole may stay aliased by its device
    arrays (a contiguous NumPy array becomes a CPU device array without a copy) until it is
    gathered: the caller says so (`hold_last`), and the next tile goes into a second buffer
    (the caller gathers tile k before reading tile k + 2)."""

    def __init__(self, capture: Capture, rows: int):
        super().__init__()
        n, h, w = capture.shape
        self.capture, self.rows, self.h = capture, rows, h
        self.shape, self.dtype = (4, n, rows, w), capture.frames.dtype

    def new_buffer(self) -> np.ndarray:
        self.buffers.append(tile_buffer(self.shape, self.dtype))
        return self.buffers[-1]

    def read(self, r0: int) -> np.ndarray:
        r1 = min(self.h, r0 + self.rows)
        buf = self.free_buffer()
        if r1 - r0 < self.rows:
            buf[:, :, r1 - r0 :] = 0  # pad the last tile so every tile has one compiled shape
        self.capture.read_tile_into(buf, slice(r0, r1))
        return buf.reshape(buf.shape[0], buf.shape[1], -1)
