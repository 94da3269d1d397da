"""The native I/Q kernel (`cohflash_jax.native`) against XLA's I/Q programs, which it replaces
on the CPU: the same data checks, carrier axis, variances and rotated sequence to float32
rounding, and the same reconstruction, on frames from the independent writer."""

from __future__ import annotations

import collections
import os
import threading

import jax
import numpy as np
import pytest

from cohflash_jax import native
from cohflash_jax.calibration_file import PixelMaps
from cohflash_jax.capture import Capture
from cohflash_jax.estimate.iq import folded_weights
from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_capture
from cohflash_jax.reconstruct import programs as P
from cohflash_jax.reconstruct.api import tile_rows
from cohflash_jax.reconstruct.engine import PieceReader
from cohflash_jax.reconstruct.plan import IQStage
from cohflash_jax.tiling import BUFFER_ALIGNMENT_BYTES

from .independent_writer import PAPER_FREQUENCIES_HZ, Writer

needs_kernel = pytest.mark.skipif(not native.available(), reason="the native kernel was not built (no C compiler)")


def frames_with_bad_pixels(n: int, shape: tuple[int, int], seed: int) -> np.ndarray:
    """uint16 frames (4, N, H·W) of a tone at ~30.5 m, pixel 3's third CCD dead (constant),
    pixel 5's first CCD at the ADC's top in one frame, pixel 6 all dark (every CCD constant)."""
    rng = np.random.default_rng(seed)
    depth = 30.5 + 0.3 * rng.random(shape)
    frames = Writer(frequencies_hz=PAPER_FREQUENCIES_HZ[:n]).frames(depth, rng).reshape(4, n, -1)
    frames[2, :, 3] = 211
    frames[0, n // 3, 5] = 16383
    frames[:, :, 6] = 200
    return np.ascontiguousarray(frames)


@needs_kernel
@pytest.mark.parametrize("maps", [False, True])
@pytest.mark.parametrize("saturation_dn", [16383.0, None])
def test_the_kernel_gives_the_xla_programs_checks_axis_and_sequence(maps, saturation_dn):
    """Odd sizes (37 pixels, 515 frames: neither a multiple of the kernel's vectors nor of its
    blocks of frames), with and without per-pixel dark and gain maps: the flags are equal, the
    variances agree to 1e-5, and the axis and the rotated sequence to float32 rounding wherever
    the axis is defined (an I/Q cloud not round to 1e-3; a dark pixel's has no axis)."""
    n, p = 515, 37
    frames = frames_with_bad_pixels(n, (1, p), seed=4)
    rng = np.random.default_rng(5)
    dark = (200 + rng.normal(0, 3, (4, p))).astype(np.float32) if maps else None
    gain = (1 + rng.normal(0, 0.05, (4, p))).astype(np.float32) if maps else None
    weights = np.array([[1.0, 0.02, -1.0, 0.01], [-0.03, 1.0, 0.02, -1.0]], np.float32)
    bias = np.array([0.5, -0.25], np.float32)
    stage = IQStage(weights, bias, saturation_dn, "float32", tracking=False, track_window=101)

    (c, s, noise_var, total_var), (dead, saturated, finite) = P.axis_and_checks(stage, frames, dark, gain)
    r = np.asarray(P.rotated_from_frames(stage, frames, dark, c, s, gain))
    w, b = folded_weights(weights, bias, dark, gain, np.float32)
    half = native.iq_half(frames, w, b, saturation_dn)

    np.testing.assert_array_equal(half.dead.view(bool), np.asarray(dead))
    np.testing.assert_array_equal(half.saturated.view(bool), np.asarray(saturated))
    assert np.asarray(finite).all()
    assert half.dead[[3, 6]].all() and half.dead.sum() == 2
    assert half.saturated.sum() == (0 if saturation_dn is None else 1) and (saturation_dn is None or half.saturated[5])
    live = ~np.asarray(dead)
    np.testing.assert_allclose(half.noise_var[live], np.asarray(noise_var)[live], rtol=1e-5)
    np.testing.assert_allclose(half.total_var[live], np.asarray(total_var)[live], rtol=1e-5)
    # the axis where the cloud is not round: (sii − sqq)² + (2 siq)² against (sii + sqq)²
    i, q = (np.asarray(x, np.float64) for x in P.stage_iq(stage, P.frame_values(stage, frames), dark, gain))
    i, q = i - i.mean(0), q - q.mean(0)
    ellipticity = np.hypot((i * i).mean(0) - (q * q).mean(0), 2 * (i * q).mean(0)) / ((i * i + q * q).mean(0) + 1e-30)
    defined = live & (ellipticity > 1e-3)
    assert defined.sum() >= p - 3
    np.testing.assert_allclose(half.cos_phase[defined], np.asarray(c)[defined], atol=2e-5)
    np.testing.assert_allclose(half.sin_phase[defined], np.asarray(s)[defined], atol=2e-5)
    scale = np.abs(r[:, defined]).max(axis=0)
    assert np.all(np.abs(half.r[:, defined] - r[:, defined]) <= 2e-5 * scale + 1e-3)
    assert half.r.ctypes.data % BUFFER_ALIGNMENT_BYTES == 0 and half.r.flags.c_contiguous


@needs_kernel
@pytest.mark.parametrize("n", [35, 515])
def test_the_kernel_reads_a_sub_tiles_columns_in_place(n):
    """A sub-tile cut from a wider tile (its columns: rows `P` apart) is read where it is, and
    gives every output bit for bit as its contiguous copy does; a short sweep (the 10 Hz mode's
    35 frames) and a long one."""
    frames = frames_with_bad_pixels(n, (3, 24), seed=6)  # (4, n, 72): three sub-tiles of 24
    weights = np.array([[1.0, 0.02, -1.0, 0.01], [-0.03, 1.0, 0.02, -1.0]], np.float32)
    bias = np.zeros((2, 24), np.float32)
    for k in range(3):
        view = frames[..., 24 * k : 24 * (k + 1)]
        assert not view.flags.c_contiguous and native.readable_in_place(view)
        in_place, copied = (
            native.iq_half(view, weights, bias, 16383.0),
            native.iq_half(np.ascontiguousarray(view), weights, bias, 16383.0),
        )
        for name, got, want in zip(native.IQHalf._fields, in_place, copied):
            np.testing.assert_array_equal(got, want, err_msg=name)
    assert native.iq_half(frames[..., :24], weights, bias, 16383.0).dead[[3, 6]].all()


@needs_kernel
def test_a_wide_sub_tile_gives_what_its_pieces_give():
    """A sub-tile wider than the kernel's pixel blocks (`PIXEL_BLOCK` in native_kernels.c: a
    short sweep's sub-tile is thousands of pixels), with per-pixel weights and bias: each
    pixel's outputs are the bits the kernel gives it in a narrow sub-tile of its own."""
    n, p = 35, 1100
    frames = frames_with_bad_pixels(n, (1, p), seed=9)
    rng = np.random.default_rng(10)
    weights = np.array([[1.0, 0.02, -1.0, 0.01], [-0.03, 1.0, 0.02, -1.0]])[..., None] * (1 + 0.05 * rng.random(p))
    weights = weights.astype(np.float32)
    bias = rng.normal(0, 3, (2, p)).astype(np.float32)
    whole = native.iq_half(frames, weights, bias, 16383.0)
    for cut in (slice(0, 300), slice(300, 700), slice(700, p)):
        piece = native.iq_half(frames[..., cut], weights[..., cut], bias[:, cut], 16383.0)
        for name, got, want in zip(native.IQHalf._fields, piece, whole):
            np.testing.assert_array_equal(got, want[..., cut], err_msg=name)


@needs_kernel
def test_the_kernel_refuses_frames_it_cannot_read():
    w, b = np.eye(2, 4, dtype=np.float32), np.zeros((2, 1), np.float32)
    good = np.zeros((4, 8, 16), np.uint16)
    with pytest.raises(ValueError, match="uint16"):
        native.iq_half(good.astype(np.int16), w, b, None)
    with pytest.raises(ValueError, match="contiguous pixels"):
        native.iq_half(np.zeros((4, 8, 32), np.uint16)[..., ::2], w, b, None)
    with pytest.raises(ValueError, match="contiguous pixels"):  # rows that overlap
        native.iq_half(np.lib.stride_tricks.as_strided(good, (4, 8, 16), (256, 16, 2)), w, b, None)
    with pytest.raises(ValueError, match="weights"):
        native.iq_half(good, np.zeros((2, 3), np.float32), b, None)
    with pytest.raises(ValueError, match="empty"):
        native.iq_half(np.zeros((4, 0, 16), np.uint16), w, b, None)


@needs_kernel
def test_a_capture_reconstructs_alike_through_the_kernel_and_through_xla(tmp_path, monkeypatch):
    """A 64×64 capture of 1,200 frames in two tiles, read into their sub-tiles, with per-pixel
    dark and gain maps: each sub-tile's I/Q half runs in the kernel (counted; its sequence
    buffers taken again once read), both tiles are read into one buffer (the second once the
    kernel has read the first; XLA's programs alias theirs, two buffers), and the
    reconstruction equals XLA's I/Q programs' to float32 rounding: the same statuses, depths
    within 1 µm (σ ~0.3 mm), σ and SNR within 1e-4."""
    rng = np.random.default_rng(21)
    path = tmp_path / "c.h5"
    depth = 30.5 + 0.2 * rng.random((64, 64))

    def bad_pixels(frames):
        frames[2, :, 3, 3] = 211  # a dead CCD
        frames[0, 100, 40, 7] = 16383  # one frame at the ADC's top
        return frames

    Writer(frequencies_hz=PAPER_FREQUENCIES_HZ[:1200]).write(path, depth, rng, alter=bad_pixels, chunks=(1, 4, 32, 64))
    options = ReconstructOptions(method="ml", progress=False, tile_rows=32)  # two tiles
    # a calibration's dark frame and relative gains, cut per sub-tile as the kernel's weights and bias
    gains = np.concatenate([np.ones((1, 64, 64)), 1 + rng.normal(0, 0.03, (3, 64, 64))])
    maps = PixelMaps(offset_dn=200 + rng.normal(0, 2, (4, 64, 64)), gain=gains)
    calls, buffers = [], []
    kernel = native.iq_half
    monkeypatch.setattr(native, "iq_half", lambda *a: calls.append(1) or kernel(*a))
    new_buffer = PieceReader.new_buffer
    monkeypatch.setattr(PieceReader, "new_buffer", lambda self: buffers.append(1) or new_buffer(self))
    with Capture(path) as cap:
        layout = PieceReader.of(cap, tile_rows(cap, options)).layout
        with_kernel = reconstruct_capture(cap, options, maps=maps)
    through_kernel = with_kernel.outputs
    assert with_kernel.meta["iq_path"].startswith("native I/Q kernel")  # the depth file says so
    sub_tiles = -(-64 // layout.rows) * (layout.rows * 64 // layout.sub)
    assert sub_tiles > 1 and len(calls) == (sub_tiles if jax.default_backend() == "cpu" else 0)
    kernel_buffers = len(buffers)  # `PieceReader.of`'s above, and the reconstruction's: one on the CPU
    monkeypatch.setattr(native, "available", lambda: False)
    with Capture(path) as cap:
        with_xla = reconstruct_capture(cap, options, maps=maps)
    through_xla = with_xla.outputs
    assert with_xla.meta["iq_path"] == "XLA's I/Q programs"
    if jax.default_backend() == "cpu":  # XLA's programs alias their tiles: the second read beside the first
        assert (kernel_buffers, len(buffers) - kernel_buffers) == (2, 2)
    np.testing.assert_array_equal(through_kernel["fit_status"], through_xla["fit_status"])
    valid = through_xla["valid"].astype(bool)
    assert valid.sum() > 4000 and not valid[3, 3] and not valid[40, 7]
    sigma = np.median(through_xla["sigma_m"][valid])
    depth_difference = np.abs(through_kernel["depth_m"][valid] - through_xla["depth_m"][valid])
    assert depth_difference.max() < 1e-6 < sigma / 100  # 1 µm, against σ ~0.3 mm
    for name in ("sigma_m", "snr", "amplitude"):
        np.testing.assert_allclose(through_kernel[name][valid], through_xla[name][valid], rtol=1e-4, err_msg=name)


def test_a_sequence_buffer_is_taken_again_only_once_its_inversion_has_run():
    """`TileDispatcher.free_sequence_buffer`: the oldest buffer whose inversion's output is
    ready, of the shape asked for; none while it is not (its device array may still read it)."""
    from cohflash_jax.reconstruct.engine import TileDispatcher

    class Marker:
        def __init__(self, ready):
            self.ready = ready

        def is_ready(self):
            return self.ready

    dispatcher = TileDispatcher.__new__(TileDispatcher)  # only its buffers are used here
    dispatcher.sequence_buffers, dispatcher.buffers_lock = collections.deque(), threading.Lock()
    first, second = np.zeros((8, 4), np.float32), np.zeros((8, 4), np.float32)
    pending, done = Marker(False), Marker(True)
    dispatcher.sequence_buffers.extend([(first, pending), (second, done)])
    assert dispatcher.free_sequence_buffer((8, 4)) is None  # the oldest still being read
    pending.ready = True
    assert dispatcher.free_sequence_buffer((8, 5)) is None  # another shape
    assert dispatcher.free_sequence_buffer((8, 4)) is first
    assert dispatcher.free_sequence_buffer((8, 4)) is second
    assert dispatcher.free_sequence_buffer((8, 4)) is None


@needs_kernel
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the kernel runs on the CPU only")
def test_the_kernels_sub_tiles_run_the_inversion_prepared_for_the_tile(tmp_path, monkeypatch):
    """The kernel's outputs go to the inversion as host arrays (no `jax.device_put` each:
    `runtime.host_arrays_placed`), and that call runs the very program `TileDispatcher.prepare`
    compiled from the tile's shapes for arrays placed on each device: dispatching the tile
    through the kernel compiles nothing more (with a signature of its own, the host arrays'
    call would compile a second inversion)."""
    import cohflash_jax as cf
    from cohflash_jax import runtime
    from cohflash_jax.reconstruct import TileDispatcher, build_plan
    from cohflash_jax.reconstruct.engine import TilePieces
    from cohflash_jax.tiling import aligned_empty

    n, sub, count = P.SPLIT_AXIS_MIN_FRAMES, 8, 2  # sub-tiles of a size no other test's programs take
    frames = frames_with_bad_pixels(n, (4, sub * count // 4), seed=8)
    pieces = aligned_empty((count, 4, n, sub), np.uint16)
    pieces[...] = frames.reshape(4, n, count, sub).transpose(2, 0, 1, 3)
    tile = TilePieces(list(pieces), pieces.transpose(1, 2, 0, 3))
    monkeypatch.setattr(runtime.EXECUTABLES, "folder", tmp_path)
    with runtime.quick_compile():
        plan = build_plan(cf.Instrument.paper(n), ReconstructOptions(method="ml", progress=False), 16383.0)
        dispatcher = TileDispatcher(plan, sub_px=sub)  # two sub-tiles: one a device where there are two
        before = runtime.EXECUTABLES.compiled
        dispatcher.prepare(tile).result(timeout=600)
        prepared = runtime.EXECUTABLES.compiled
        assert prepared - before <= 1  # the inversion (none where this process made it already)
        pending = dispatcher.dispatch(tile)
        result = pending.gather()
        assert pending.native_iq and runtime.EXECUTABLES.compiled == prepared  # nothing more
    assert result["depth_m"].shape == (sub * count,) and np.isfinite(result["depth_m"]).all()


@needs_kernel
@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the kernel runs on the CPU only")
def test_a_short_sweep_array_reconstructs_alike_through_the_kernel_and_through_xla(monkeypatch):
    """The 10 Hz mode's 35 frames, an in-memory array of 61×63 pixels with per-pixel dark and
    gain maps: its four sub-tiles' I/Q halves run in the kernel (three read in place as the
    array's columns, the narrower last one from a padded copy), and the reconstruction equals
    XLA's I/Q programs' to float32 rounding: the same statuses, depths within 1e-4 σ, σ and SNR
    within 1e-4."""
    import cohflash_jax as cf
    from cohflash_jax.reconstruct import reconstruct_array

    inst = cf.Instrument.ten_hz_mode()
    rng = np.random.default_rng(12)
    depth = 30.5 + 0.2 * rng.random((61, 63))
    writer = Writer(frequencies_hz=np.asarray(inst.sweep.frequencies_hz), echo_scale=30.0)
    frames = writer.frames(depth, rng)
    frames[2, :, 3, 3] = 211  # a dead CCD
    gains = np.concatenate([np.ones((1, 61, 63)), 1 + rng.normal(0, 0.03, (3, 61, 63))])
    maps = PixelMaps(offset_dn=200 + rng.normal(0, 2, (4, 61, 63)), gain=gains)
    options = ReconstructOptions(method="ml", progress=False)
    calls, kernel = [], native.iq_half
    contiguous = lambda piece, *rest: calls.append(piece.flags.c_contiguous) or kernel(piece, *rest)
    monkeypatch.setattr(native, "iq_half", contiguous)
    through_kernel = reconstruct_array(frames, inst, options, maps=maps)
    assert calls == [False, False, False, True]  # three sub-tiles' columns in place, the last copied
    monkeypatch.setattr(native, "available", lambda: False)
    through_xla = reconstruct_array(frames, inst, options, maps=maps)
    assert len(calls) == 4
    np.testing.assert_array_equal(through_kernel["fit_status"], through_xla["fit_status"])
    valid = through_xla["valid"].astype(bool)
    assert valid.sum() > 3000 and not valid[3, 3]
    sigma = through_xla["sigma_m"][valid]
    assert np.max(np.abs(through_kernel["depth_m"][valid] - through_xla["depth_m"][valid]) / sigma) < 1e-4
    for name in ("sigma_m", "snr", "amplitude"):
        np.testing.assert_allclose(through_kernel[name][valid], through_xla[name][valid], rtol=1e-4, err_msg=name)


@needs_kernel
def test_a_library_built_from_another_source_is_not_called(monkeypatch):
    """A kernel library left from an older build (another calling convention) is not loaded:
    XLA's I/Q programs run, and the kernel's description says to rebuild it."""
    monkeypatch.setattr(native, "KERNEL_ABI", native.KERNEL_ABI + 1)
    native.library.cache_clear()
    try:
        assert not native.available() and not native.reads_chunks()
        assert "another version" in native.description() and "XLA's I/Q programs run" in native.description()
    finally:
        monkeypatch.undo()
        native.library.cache_clear()
    assert native.available()


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork here")
@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # the child calls nothing of JAX's
@pytest.mark.filterwarnings("ignore:This process .* is multi-threaded:DeprecationWarning")  # the fork is the test
def test_a_forked_child_gets_kernel_threads_of_its_own():
    """A child forked after the kernel's threads were made has none of them: it makes its own,
    rather than queueing work for threads that do not exist (which would wait for ever)."""
    import multiprocessing

    from cohflash_jax.reconstruct.engine import kernel_threads

    assert kernel_threads().submit(os.getpid).result(timeout=30) == os.getpid()
    context = multiprocessing.get_context("fork")
    with context.Pool(1) as pool:
        child, ran_in = pool.apply(_kernel_threads_ran_in, ())
    assert child == ran_in != os.getpid()


def _kernel_threads_ran_in() -> tuple[int, int]:
    from cohflash_jax.reconstruct.engine import kernel_threads

    return os.getpid(), kernel_threads().submit(os.getpid).result(timeout=30)
