"""The reconstruction's entry points: frames in memory (`reconstruct_array`), an open capture
streamed in tiles (`reconstruct_capture`), and a capture file with its calibration and
registration files (`open_and_reconstruct`). Each takes the instrument it reconstructs for."""

from __future__ import annotations

import concurrent.futures
import contextvars
import dataclasses
import json
import math
import time

import jax
import numpy as np

from .. import native
from ..calibration_file import Calibration, CaptureSetup, PixelMaps
from ..capture import Capture, CaptureError
from ..estimate.drift import CarrierAlignment, choose_carrier_alignment
from ..fisher import crlb_at_unit_snr_m
from ..instrument import Instrument
from ..progress import progress_bar
from ..runtime import EXECUTABLES, quick_compile, retain_freed_memory
from ..tiling import QUICK_COMPILE_MAX_PIXELS
from .engine import BlockReader, PendingTile, PieceReader, TileDispatcher, TilePieces, sub_tile_pixels
from .plan import TilePlan, build_plan, frequency_path
from .policy import ReconstructOptions


@dataclasses.dataclass
class Reconstruction:
    """A reconstructed capture: per-pixel `outputs` (H, W) (depth_m, sigma_m, valid, …), the
    `meta` data a depth file records, and the instrument it was reconstructed for."""

    outputs: dict
    meta: dict
    instrument: Instrument


def reconstruct_array(
    frames,
    instrument: Instrument,
    options: ReconstructOptions | None = None,
    *,
    maps: PixelMaps | None = None,
    saturation_dn: float | None = None,
    carrier_phase_rad=None,
) -> dict:
    """Reconstruct in-memory frames (4, N, H, W) of `instrument` → dict of (H, W) arrays, in
    sub-tiles dispatched asynchronously (as `reconstruct_capture` does within each tile).
    `maps`: per-pixel offsets and gains; `saturation_dn`: the DN that marks ADC saturation
    (default: none checked); `carrier_phase_rad` (N,): a known common carrier drift to remove."""
    options = options or ReconstructOptions(progress=False)
    maps = maps or PixelMaps()
    retain_freed_memory()
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[0] != 4:
        raise ValueError(f"frames must have shape (4, N, H, W), got {frames.shape}")
    _, n, h, w = frames.shape
    for name, arr, shape in (
        ("instrument.sweep.frequencies_hz", instrument.sweep.frequencies_hz, (n,)),
        ("carrier_phase_rad", carrier_phase_rad, (n,)),
    ):
        if arr is not None and np.shape(arr) != shape:
            raise ValueError(f"{name} must have shape {shape} to match frames {frames.shape}, got {np.shape(arr)}")
    maps.check_shape(h, w, "maps")
    instrument = maps.apply(instrument)
    flat = lambda a: None if a is None else np.asarray(a, np.float32).reshape(4, h * w)
    dark, gain = flat(maps.offset_dn), flat(maps.gain)
    if carrier_phase_rad is not None:
        alignment = CarrierAlignment("common", "given by the caller", np.asarray(carrier_phase_rad, np.float64))
    else:
        alignment = align_carrier(options, instrument, frames.reshape(4, n, h * w), dark, gain)
    _, dispatcher = plan_and_dispatcher(instrument, options, saturation_dn, alignment, sub_tile_pixels(h * w, n))
    with quick_compile(h * w <= QUICK_COMPILE_MAX_PIXELS):
        dispatcher.prepare(frames.reshape(4, n, h * w), dark, None, gain)  # compiled beside the I/Q programs
        out = dispatcher.dispatch(frames.reshape(4, n, h * w), dark, None, gain).gather()
    return {k: v.reshape(h, w) for k, v in out.items()}


def align_carrier(options: ReconstructOptions, instrument: Instrument, frames, dark=None, gain=None):
    """The carrier alignment `options.carrier` asks for; for "auto" decided on `frames`
    (4, N, P) in DN (`estimate.drift.choose_carrier_alignment`), with per-pixel `dark` and
    `gain` (4, P) where known."""
    if options.carrier != "auto":
        return choose_carrier_alignment(options.carrier)
    if isinstance(frames, TilePieces):
        frames = frames.frames  # (4, N, pieces, sub): the survey reads it as (4, N, P)
    iq_w, iq_b = instrument.hybrid.iq_matrix_dn(1.0)
    return choose_carrier_alignment("auto", frames, iq_w, iq_b, dark, gain)


def depth_meta(plan: TilePlan, options: ReconstructOptions, alignment: CarrierAlignment, **extra) -> dict:
    """What a depth file records about how its depths were made."""
    g = plan.geometry
    return {
        "method": options.method,
        "ambiguity_m": plan.ambiguity_m,
        "bin_depth_m": g.bin_depth_m,
        "depth_window_m": list(plan.policy.valid_window_m),
        "carrier_alignment": alignment.mode,
        "carrier_reason": alignment.reason,
        "carrier_drift_rms_rad": alignment.drift_rms_rad,
        "snr_threshold_db": options.snr_threshold_db,
        "snr_threshold_effective_db": 10 * math.log10(plan.policy.snr_threshold),
        "dtype": options.dtype,
        "window_bins": options.window_bins,
        "dominant_harmonic": g.dominant_order,
        "frequency_path": frequency_path(plan),
        "false_alarm": plan.coarse.detection.false_alarm,
        **extra,
    }


# the last set-ups (plan, dispatcher) of this process: a stream of captures of one instrument
# builds its plan and places it on the devices once, not once per capture
_SETUPS: dict = {}
MAX_SETUPS = 4


def forget_setups() -> None:
    """Drop the plans and dispatchers kept for later captures (`plan_and_dispatcher`): the
    next capture builds its own, after a change to a module-level setting `build_plan` reads."""
    _SETUPS.clear()


def plan_and_dispatcher(instrument, options, saturation, alignment, sub_px):
    """The plan for these settings and a dispatcher of sub-tiles of `sub_px` pixels, reused
    from an earlier capture of this process where every setting is equal (and hashable)."""
    key = None
    if alignment.phase_rad is None:  # a known drift is the capture's own
        leaves, treedef = jax.tree.flatten(instrument)
        if not any(isinstance(x, jax.Array) for x in leaves):  # traced or placed: built afresh
            values = tuple((x.shape, x.dtype.str, x.tobytes()) if isinstance(x, np.ndarray) else x for x in leaves)
            settings = repr(dataclasses.replace(options, progress=False))
            key = (treedef, values, settings, saturation, alignment.tracking, sub_px)
            if key in _SETUPS:
                return _SETUPS[key]
    plan = build_plan(instrument, options, saturation, tracking=alignment.tracking)
    setup = (plan, TileDispatcher(plan, sub_px, alignment.phase_rad))
    if key is not None:
        if len(_SETUPS) >= MAX_SETUPS:
            _SETUPS.pop(next(iter(_SETUPS)))
        _SETUPS[key] = setup
    return setup


class TileFeeder:
    """Dispatches tiles in a thread of its own, in turn, while the caller reads the next. A CPU
    device queues a bounded number of program calls and a call beyond them waits, so
    dispatching a tile's sub-tiles returns only when most of them have run: dispatched from
    the caller's thread, the next tile's read began then, and the devices ran out of work
    while it was read (the first tile's most of all)."""

    def __init__(self):
        self.pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="dispatch-tiles")

    def submit(self, dispatch, *arguments) -> concurrent.futures.Future:
        """`dispatch(*arguments)` after the tiles submitted before it: a future of its `PendingTile`."""
        return self.pool.submit(contextvars.copy_context().run, dispatch, *arguments)

    def close(self):
        self.pool.shutdown(wait=True)


class TileSource:
    """The inputs of a capture's row tiles of `rows` rows for `process_tile`: the frames
    (registered onto CCD 1's grid where `registration_maps` are given), the upstream status and
    the per-pixel dark and gain maps, each padded to the tile shape (one compiled shape)."""

    def __init__(self, capture: Capture, maps: PixelMaps, registration_maps, rows: int):
        self.num_frames, self.h, self.w = capture.shape
        self.frames_dtype = capture.frames.dtype
        self.rows = rows
        self.dark, self.gain = maps.offset_dn, maps.gain
        self.registered = self.reader = None
        if registration_maps is not None:
            from ..registered import RegisteredTiles, register_pixel_map

            self.registered = RegisteredTiles(capture, registration_maps, rows)
            self.dark = None if self.dark is None else register_pixel_map(self.dark, registration_maps)
            self.gain = None if self.gain is None else register_pixel_map(self.gain, registration_maps)
        else:
            self.reader = PieceReader.of(capture, rows) or BlockReader(capture, rows)

    def sub_tile_pixels(self, num_frames: int) -> int:
        """Pixels per dispatched sub-tile: the pieces the reader reads (`PieceReader`), else
        `engine.sub_tile_pixels`."""
        if isinstance(self.reader, PieceReader):
            return self.reader.layout.sub
        return sub_tile_pixels(self.rows * self.w, num_frames)

    def map_tile(self, arr, r0, r1, fill):
        """Rows r0:r1 of a (4, H, W) per-pixel map, padded to the tile shape → (4, P)."""
        if arr is None:
            return None
        block = np.full((4, self.rows, self.w), fill, np.float32)
        block[:, : r1 - r0] = arr[:, r0:r1]
        return block.reshape(4, self.rows * self.w)

    def release_buffers(self) -> None:
        """Let go of the reader's tile buffers in the background (`TileBuffers.release_in_background`)."""
        if self.reader is not None:
            self.reader.release_in_background()

    def feeds_in_thread(self) -> bool:
        """Whether tiles may be dispatched from a thread while the next is read (`TileFeeder`):
        where they are read into their sub-tiles (`PieceReader`), which no dispatch copies:
        a tile XLA's I/Q programs alias keeps its buffer until gathered and the next is read
        beside its dispatch; one the native kernel reads is read over once its dispatch returns."""
        return isinstance(self.reader, PieceReader)

    def hold_last(self, held: bool) -> None:
        """Whether the last tile's frames are still in use (`BlockReader.hold_last`)."""
        if self.reader is not None:
            self.reader.hold_last(held)

    def tile_like(self) -> tuple:
        """(frames (4, N, P), dark (4, P), data status (P,), gain (4, P)) of every tile as
        `jax.ShapeDtypeStruct`s (None where tiles have none), in `TileDispatcher.dispatch`'s
        order: what `inputs` gives, known before any tile is read."""
        p, like = self.rows * self.w, jax.ShapeDtypeStruct
        registered = self.registered is not None  # resampled: float32, with an upstream status
        frames = like((4, self.num_frames, p), np.float32 if registered else self.frames_dtype)
        dark, gain = (None if m is None else like((4, p), np.float32) for m in (self.dark, self.gain))
        return frames, dark, like((p,), np.int8) if registered else None, gain

    def inputs(self, r0: int) -> tuple:
        """(r1, frames (4, N, P) or its `TilePieces`, data status (P,) or None, dark (4, P), gain (4, P))
        of the tile at row r0."""
        r1 = min(self.h, r0 + self.rows)
        maps = (self.map_tile(self.dark, r0, r1, 0.0), self.map_tile(self.gain, r0, r1, 1.0))
        if self.registered is not None:
            return self.registered.tile(r0) + maps
        return (r1, self.reader.read(r0), None) + maps


def calibrated_inputs(capture: Capture, instrument, maps):
    """The instrument and per-pixel maps a capture is reconstructed with (default: the
    capture's own instrument and dark frame), the maps' gains folded into the instrument."""
    _, h, w = capture.shape
    instrument = capture.instrument() if instrument is None else instrument
    maps = PixelMaps(capture.dark) if maps is None else maps
    maps.check_shape(h, w, "per-pixel maps")
    return maps.apply(instrument), maps


def tile_rows(capture: Capture, options: ReconstructOptions) -> int:
    """Rows per streamed tile of `capture` (`ReconstructOptions.rows_per_tile`)."""
    return options.rows_per_tile(capture.shape, capture.frames.dtype.itemsize)


def capture_alignment(
    capture: Capture, options: ReconstructOptions, instrument=None, *, maps=None, registration_maps=None
) -> CarrierAlignment:
    """The carrier alignment `reconstruct_capture` chooses for this capture (decided on its
    first tile): a distributed run decides it once and gives it to every band."""
    instrument, maps = calibrated_inputs(capture, instrument, maps)
    source = TileSource(capture, maps, registration_maps, tile_rows(capture, options))
    _, block, _, dark, gain = source.inputs(0)
    return align_carrier(options, instrument, block, dark, gain)


def reconstruct_capture(
    capture: Capture,
    options: ReconstructOptions,
    instrument: Instrument | None = None,
    *,
    maps: PixelMaps | None = None,
    registration_maps=None,
    row_band: tuple[int, int] | None = None,
    alignment: CarrierAlignment | None = None,
) -> Reconstruction:
    """Reconstruct an open capture tile by tile (bounded memory) for `instrument` (default:
    the capture's own, `Capture.instrument`). `maps`: per-pixel offsets and gains (default:
    the capture's dark frame); `registration_maps`: three (map_x, map_y) arrays (H, W) placing
    CCDs 2–4 on CCD 1's grid. `row_band` (r0, r1): those rows only (r0 a multiple of
    `tile_rows`, so the tiles, and the results, are the whole capture's);
    `alignment`: the carrier alignment to use (default: decided on the first tile)."""
    retain_freed_memory()
    n, h, w = capture.shape
    # registered tiles arrive as float32 with saturation judged upstream on the source pixels
    saturation = None if registration_maps is not None else capture.saturation_dn
    instrument, maps = calibrated_inputs(capture, instrument, maps)
    rows = tile_rows(capture, options)
    band_start, band_end = (0, h) if row_band is None else row_band
    if band_start % rows or not 0 <= band_start < band_end <= h:
        raise ValueError(f"row band {band_start}:{band_end} must start on a tile of {rows} rows and lie in 0:{h}")
    t0 = time.perf_counter()
    source = TileSource(capture, maps, registration_maps, rows)
    outputs = {}
    native_tiles = 0  # tiles whose I/Q halves the native kernel computed (the depth file's `iq_path`)

    def collect(pending, bar):
        nonlocal native_tiles
        tile, r0, r1 = pending
        if isinstance(tile, concurrent.futures.Future):
            tile = tile.result()
        native_tiles += tile.native_iq
        for k, v in tile.gather().items():
            arr = v.reshape(rows, w)[: r1 - r0]
            band = outputs.setdefault(k, np.empty((band_end - band_start, w), arr.dtype))
            band[r0 - band_start : r1 - band_start] = arr
        bar.update((r1 - r0) * w)

    # "auto" carrier alignment looks at the first tile: its survey (NumPy) runs in a thread
    # while the first tile is dispatched as if static, which "auto" finds in most captures;
    # where it finds a drift, the tile is dispatched again with it before the second is
    # dispatched: after the second is read where tiles keep their buffers until gathered
    # (`TileSource.feeds_in_thread`), else before a read could take the first tile's buffer
    auto = alignment is None and options.carrier == "auto"
    # where this process's programs are being loaded (a warm cache) the first tile is read
    # beside the loads, at once; where they are compiled, the plan is made first and the
    # inversion's compile started (`TileDispatcher.prepare`), and the tile read beside it
    first = source.inputs(band_start) if EXECUTABLES.loading() else None
    if alignment is None:
        alignment = choose_carrier_alignment("static" if auto else options.carrier)
    sub_px = source.sub_tile_pixels(n)
    plan, dispatcher = plan_and_dispatcher(instrument, options, saturation, alignment, sub_px)
    total = (band_end - band_start) * w
    bar = progress_bar(total=total, unit="px", desc="reconstruct", disable=not options.progress, unit_scale=True)
    # the whole capture's size decides, so that every band of a distributed run decides alike
    with bar, quick_compile(h * w <= QUICK_COMPILE_MAX_PIXELS):
        # the inversion program compiled in a thread while the first tile is read and its I/Q
        # programs compile: on a cold cache its compile is most of the run
        dispatcher.prepare(*source.tile_like())
        first = first or source.inputs(band_start)
        survey = None
        if auto:
            pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="carrier-survey")
            survey = pool.submit(align_carrier, options, instrument, first[1], first[3], first[4])
            pool.shutdown(wait=False)  # its thread ends with the survey
        pending = first_inputs = None
        feeder = TileFeeder() if source.feeds_in_thread() else None

        def follow_survey():
            """Take the survey's alignment; where it found a drift, dispatch the first tile
            again with it (its frames still held; its first dispatch queued before)."""
            nonlocal alignment, plan, dispatcher, pending, survey
            alignment, survey = survey.result(), None
            if alignment.mode != "static":
                plan, dispatcher = plan_and_dispatcher(instrument, options, saturation, alignment, sub_px)
                if isinstance(pending[0], concurrent.futures.Future):
                    pending[0].result()
                pending = (dispatcher.dispatch(*first_inputs), *pending[1:])

        # a tile whose sub-tiles the native kernel reads (`host_iq`) is done with its buffer once
        # its dispatch returns (it waits for the kernel's reads): the next tile is read into that buffer
        # then, and no second tile buffer is taken (a full capture's: 246 MB of fresh memory)
        freed_by = None  # the feeding thread's dispatch of the last tile, where it frees the buffer
        try:
            for r0 in range(band_start, band_end, rows):
                if freed_by is not None:
                    if survey is not None:
                        follow_survey()  # before the first tile's buffer is read into again
                    if isinstance(pending[0], PendingTile):  # dispatched again, a drift found
                        source.hold_last(pending[0].holds_frames)
                    freed_by.result()
                r1, block, data_status, d, g = first if r0 == band_start else source.inputs(r0)
                r1 = min(r1, band_end)
                if survey is not None and r0 != band_start:
                    follow_survey()  # the second tile read beside the survey, before its dispatch
                if feeder is not None:
                    # fed in a thread: the next tile is read while this one's sub-tiles queue
                    tile = feeder.submit(dispatcher.dispatch, block, d, data_status, g)
                    freed_by = tile if dispatcher.host_iq(block) else None
                    source.hold_last(freed_by is None)
                else:
                    # dispatched asynchronously: the next tile is read while this one computes
                    tile = dispatcher.dispatch(block, d, data_status, g)
                    source.hold_last(tile.holds_frames)
                if pending is not None:
                    collect(pending, bar)
                pending = (tile, r0, r1)
                if r0 == band_start:
                    first_inputs = (block, d, data_status, g)
                    if survey is not None and (feeder is None or r1 >= band_end):
                        follow_survey()  # the next read may take the first tile's buffer, or there is none
            if isinstance(pending[0], concurrent.futures.Future) and pending[0].result().native_iq:
                # the last tile's frames were read by the native kernel, not aliased by its device
                # arrays: the buffers are let go while its inversions run
                del block, first, first_inputs
                source.release_buffers()
            collect(pending, bar)
        finally:
            if feeder is not None:
                feeder.close()
    meta = depth_meta(
        plan,
        options,
        alignment,
        seconds=time.perf_counter() - t0,
        iq_path=native.description() if native_tiles else "XLA's I/Q programs",
        registered=registration_maps is not None,
        crlb_at_unit_snr_m=crlb_at_unit_snr_m(instrument.sweep.frequencies_hz, plan.geometry.dominant_order),
    )
    return Reconstruction(outputs, meta, instrument)


@dataclasses.dataclass
class FileSetup:
    """What a capture file is reconstructed with: its `CaptureSetup`, and the calibration and
    registration loaded from their files (None where not given) with the registration's three
    maps placing CCDs 2–4 on CCD 1's grid."""

    setup: CaptureSetup
    calibration: Calibration | None = None
    registration: object = None
    registration_maps: list | None = None

    @classmethod
    def load(cls, capture: Capture, calibration_path=None, registration_path=None) -> FileSetup:
        calibration = None if calibration_path is None else Calibration.load(calibration_path)
        out = cls(CaptureSetup.of(capture, calibration), calibration)
        if registration_path is not None:
            from cohflash_calibration.registration import load_registration

            out.registration = load_registration(registration_path)
            out.registration_maps = [out.registration.maps(k) for k in (2, 3, 4)]
        return out

    def alignment(self, capture: Capture, options: ReconstructOptions) -> CarrierAlignment:
        """The carrier alignment a reconstruction of `capture` with this setup chooses."""
        return capture_alignment(
            capture, options, self.setup.instrument, maps=self.setup.maps, registration_maps=self.registration_maps
        )

    def record(self, meta: dict) -> dict:
        """`meta` with the calibration's fallback notes and what was applied (JSON)."""
        meta["notes"] = json.dumps(list(self.setup.notes))
        if self.calibration is not None:
            meta["calibration_applied"] = json.dumps(self.calibration.values())
        if self.registration is not None:
            meta["registration_applied"] = json.dumps(self.registration.summary())
        return meta


def open_and_reconstruct(
    path,
    options: ReconstructOptions,
    calibration_path=None,
    registration_path=None,
    capture: Capture | None = None,
    *,
    row_band: tuple[int, int] | None = None,
    alignment: CarrierAlignment | None = None,
) -> Reconstruction:
    """Reconstruct a capture file for its instrument, calibrated by `calibration_path` and
    registered by `registration_path` where given. `capture`: the file already open (it is
    then not opened again). The calibration's fallback notes are in `meta["notes"]` (JSON).
    `row_band`, `alignment`: as `reconstruct_capture` (a band of a distributed run)."""
    cap = capture if capture is not None else Capture(path)
    try:
        files = FileSetup.load(cap, calibration_path, registration_path)
        result = reconstruct_capture(
            cap,
            options,
            files.setup.instrument,
            maps=files.setup.maps,
            registration_maps=files.registration_maps,
            row_band=row_band,
            alignment=alignment,
        )
    except CaptureError:
        raise
    except (NotImplementedError, ValueError) as exc:
        raise CaptureError(f"{path}: {exc}") from None
    finally:
        if capture is None:
            cap.close()
    files.record(result.meta)
    return result
