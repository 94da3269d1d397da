"""Capture file format v1 (HDF5, or the same layout as a Zarr store; docs/formats.md): this
module owns it end to end — the header an instrument writes (`capture_attributes`), atomic
writing (`write_capture`), and validated tiled reading of either store with the instrument it
describes (`Capture`, `Capture.instrument`). Zarr writing and conversion: `capture_zarr`.

Root attributes: format = "cohflash-capture", format_version = 1, exposure_s,
frame_rate_hz, wavelength_m. Optional root attributes that cohflash writes and reads
when present (extensions, all optional): field_of_view_deg (2,), modulation_index,
bias_rad, sideband_max_order, adc_bits, dn_per_electron.
Datasets: frames (4, N, H, W) uint16|float32; frequencies_hz (N,) float64;
hybrid_phases_rad (4,) float64; optional dark (4, H, W) float32; optional
truth/depth_m and truth/reflectance (H, W) float32 (truth/ attributes record the
simulation's settings).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterable
from pathlib import Path

import h5py
import numpy as np

from . import early_read
from .chunk_reads import ChunkIndexError, DirectChunkReader
from .fileio import atomic_path, is_store_folder
from .hybrid import NOMINAL_PHASES_RAD, Hybrid
from .instrument import DEFAULT_FIELD_OF_VIEW_DEG, Instrument
from .modulator import MZM
from .progress import progress_bar
from .sensor import Sensor
from .sweep import FrequencySweep

FORMAT_NAME = "cohflash-capture"
FORMAT_VERSION = 1
REQUIRED_ATTRS = ("exposure_s", "frame_rate_hz", "wavelength_m")
FRAME_DTYPES = (np.dtype(np.uint16), np.dtype(np.float32))
# A capture that does not state its ADC's bits: only the uint16 maximum is surely saturated.
UNSTATED_ADC_BITS = 16


def capture_attributes(instrument: Instrument) -> dict:
    """The root attributes a capture of `instrument` carries: the instrument as described
    (nominal or calibrated), never its departures (`Instrument.errors`), which a real capture
    cannot know. `Capture.instrument` reads them back."""
    sensor, mzm = instrument.sensor, instrument.modulator
    return {
        "exposure_s": float(sensor.exposure_s),
        "frame_rate_hz": float(instrument.frame_rate_hz),
        "wavelength_m": float(sensor.wavelength_m),
        "field_of_view_deg": np.asarray(instrument.field_of_view_deg),
        "modulation_index": float(mzm.modulation_index),
        "bias_rad": float(mzm.bias_rad),
        "sideband_max_order": int(mzm.max_order),
        "adc_bits": int(sensor.adc_bits),
        "dn_per_electron": float(sensor.dn_per_electron),
    }


def frequency_problem(frequencies_hz) -> str | None:
    """What is wrong with a sweep's frequencies (NaN/inf, not strictly increasing), or None."""
    f = np.asarray(frequencies_hz, np.float64)
    if f.ndim != 1:
        return f"frequencies_hz must be 1-D, got shape {f.shape}"
    if not np.all(np.isfinite(f)):
        return "frequencies_hz contains NaN or inf"
    if np.any(np.diff(f) <= 0):
        first = int(np.argmax(np.diff(f) <= 0)) + 1
        return f"frequencies_hz must be strictly increasing (first violation at frame {first})"
    return None


class CaptureError(ValueError):
    """A capture file is missing, corrupt or does not follow format v1."""


def _chunk_shape(num_frames, height, width, frames_per_chunk, rows_per_chunk=32):
    return (1, max(1, min(frames_per_chunk, num_frames)), max(1, min(rows_per_chunk, height)), width)


# attributes each store's writer sets itself (not copied from one capture to another)
STORE_ATTRS = ("format", "format_version", "complete", "chunking")


@dataclasses.dataclass
class CaptureHeader:
    """Everything a capture holds but its frames: their shape and dtype, the root attributes,
    the sweep, the hybrid's nominal phases (default: `NOMINAL_PHASES_RAD`), the dark frame and
    the truth (`depth_m`, `reflectance`, `attrs`). Checked when made; the writers of both
    stores take it (`write_capture`, `capture_zarr.create_zarr_capture`)."""

    frequencies_hz: np.ndarray
    height: int
    width: int
    dtype: np.dtype
    attrs: dict
    hybrid_phases_rad: np.ndarray | None = None
    dark: np.ndarray | None = None
    truth: dict | None = None

    def __post_init__(self):
        self.frequencies_hz = np.asarray(self.frequencies_hz, np.float64)
        self.dtype = np.dtype(self.dtype)
        if self.dtype not in FRAME_DTYPES:
            raise CaptureError(f"frames dtype must be uint16 or float32, got {self.dtype}")
        missing = [k for k in REQUIRED_ATTRS if k not in self.attrs]
        if missing:
            raise CaptureError(f"capture attributes missing: {', '.join(missing)}")
        phases = NOMINAL_PHASES_RAD if self.hybrid_phases_rad is None else self.hybrid_phases_rad
        self.hybrid_phases_rad = np.asarray(phases, np.float64)

    @property
    def num_frames(self) -> int:
        return self.frequencies_hz.size

    def fields(self) -> dict:
        """The header as `write_capture`'s keyword arguments."""
        return dict(vars(self))

    @classmethod
    def of(cls, capture: Capture) -> CaptureHeader:
        """The header of an open capture (to copy it into another store)."""
        n, h, w = capture.shape
        truth = {name: capture.truth(name) for name in capture.truth_names}
        if truth:
            truth["attrs"] = capture.truth_attrs
        return cls(
            capture.frequencies_hz,
            h,
            w,
            capture.frames.dtype,
            {k: v for k, v in capture.attrs.items() if k not in STORE_ATTRS},
            capture.hybrid_phases_rad,
            capture.dark,
            truth or None,
        )


def counted_blocks(chunks, header: CaptureHeader, by_rows: bool, desc: str, progress: bool):
    """The blocks (m0, m1, frames) of `chunks`, bands of frames or (`by_rows`) of rows, passed
    on with a progress bar; CaptureError if they do not add up to the whole capture."""
    total, unit = (header.height, "row") if by_rows else (header.num_frames, "frame")
    written = 0
    with progress_bar(total=total, unit=unit, desc=desc, disable=not progress) as bar:
        for m0, m1, block in chunks:
            yield m0, m1, block
            written += m1 - m0
            bar.update(m1 - m0)
    if written != total:
        raise CaptureError(f"wrote {written} of {total} {unit}s")


def write_capture(
    path,
    chunks: Iterable[tuple[int, int, np.ndarray]],
    *,
    frequencies_hz,
    height: int,
    width: int,
    dtype,
    attrs: dict,
    hybrid_phases_rad=None,
    dark=None,
    truth: dict | None = None,
    frames_per_chunk: int = 64,
    progress: bool = True,
    by_rows: bool = False,
    rows_per_chunk: int = 32,
) -> Path:
    """Write a v1 capture atomically from an iterator of (m0, m1, frames[4, m1−m0, H, W]), or
    with `by_rows` of (r0, r1, frames[4, N, r1−r0, W]) (bands of rows, all frames). A path
    NAME.zarr is written as a Zarr store (`capture_zarr.write_zarr_capture`)."""
    path = Path(path)
    header = CaptureHeader(frequencies_hz, height, width, dtype, attrs, hybrid_phases_rad, dark, truth)
    if is_store_folder(path):
        from .capture_zarr import write_zarr_capture

        return write_zarr_capture(
            path,
            chunks,
            header,
            frames_per_chunk=frames_per_chunk,
            progress=progress,
            by_rows=by_rows,
            rows_per_chunk=rows_per_chunk,
        )
    n = header.num_frames
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["format_version"] = FORMAT_VERSION
        for k, v in header.attrs.items():
            f.attrs[k] = v
        frames = f.create_dataset(
            "frames",
            shape=(4, n, height, width),
            dtype=header.dtype,
            chunks=_chunk_shape(n, height, width, frames_per_chunk, rows_per_chunk),
        )
        f.create_dataset("frequencies_hz", data=header.frequencies_hz)
        f.create_dataset("hybrid_phases_rad", data=header.hybrid_phases_rad)
        if header.dark is not None:
            f.create_dataset("dark", data=np.asarray(header.dark, np.float32))
        for m0, m1, block in counted_blocks(chunks, header, by_rows, f"writing {path.name}", progress):
            expected = (4, n, m1 - m0, width) if by_rows else (4, m1 - m0, height, width)
            if block.shape != expected:
                raise CaptureError(f"block {m0}:{m1} has shape {block.shape}, expected {expected}")
            if by_rows:
                frames[:, :, m0:m1] = block
            else:
                frames[:, m0:m1] = block
        if header.truth is not None:
            g = f.create_group("truth")
            g.create_dataset("depth_m", data=np.asarray(header.truth["depth_m"], np.float32))
            g.create_dataset("reflectance", data=np.asarray(header.truth["reflectance"], np.float32))
            for k, v in header.truth.get("attrs", {}).items():
                g.attrs[k] = v
    return path


class Capture:
    """A validated, open v1 capture, an HDF5 file or a Zarr store (`capture_zarr`: the same
    attributes and arrays). Reads pixel tiles without loading the whole file.

    Use as a context manager. Raises CaptureError naming the problem on open."""

    def __init__(self, path):
        self.path = Path(path)
        self.store = "zarr" if self.path.is_dir() else "hdf5"
        if self.store == "zarr":
            from .capture_zarr import open_zarr_group

            self._file = open_zarr_group(self.path, CaptureError)
        else:
            if not self.path.is_file():
                raise CaptureError(f"capture file not found: {self.path}")
            try:
                self._file = h5py.File(self.path, "r")
            except OSError as exc:
                raise CaptureError(f"{self.path}: not a readable HDF5 file ({exc})") from None
        try:
            self._validate()
        except Exception:
            self.close()
            raise

    def _fail(self, msg):
        raise CaptureError(f"{self.path}: {msg}")

    def _number_attr(self, name) -> float:
        try:
            return float(np.asarray(self._file.attrs[name]))
        except (TypeError, ValueError):
            self._fail(f"attribute {name} must be a number, got {self._file.attrs[name]!r}")

    def _validate(self):
        f = self._file
        if f.attrs.get("format") != FORMAT_NAME:
            self._fail(f"attribute format is {f.attrs.get('format')!r}, expected {FORMAT_NAME!r}")
        version = f.attrs.get("format_version")
        if version is None:
            self._fail(f"attribute format_version is missing (this reader knows version {FORMAT_VERSION})")
        shown = np.asarray(version).tolist()
        if np.ndim(version) != 0 or not isinstance(shown, int | float) or shown != FORMAT_VERSION:
            self._fail(f"format_version {shown!r} is not supported (this reader knows version {FORMAT_VERSION})")
        for k in REQUIRED_ATTRS:
            if k not in f.attrs:
                self._fail(f"required attribute {k!r} is missing")
            v = self._number_attr(k)
            if not (np.isfinite(v) and v > 0):
                self._fail(f"attribute {k} must be a positive number, got {v}")
        if self.store == "zarr" and f.attrs.get("complete") is not True:
            self._fail(
                "the Zarr capture is incomplete: its writers have not all finished "
                "(`capture_zarr.finish_zarr_capture` marks it complete once every chunk is written)"
            )
        for name in ("frames", "frequencies_hz", "hybrid_phases_rad"):
            if name not in f or not hasattr(f[name], "shape"):
                self._fail(f"dataset {name!r} is missing")
        frames = f["frames"]
        if frames.ndim != 4 or frames.shape[0] != 4:
            self._fail(f"frames must have shape (4, N, H, W), got {frames.shape}")
        if frames.dtype not in FRAME_DTYPES:
            self._fail(f"frames dtype must be uint16 or float32, got {frames.dtype}")
        _, n, h, w = frames.shape
        if n < 2 or h < 1 or w < 1:
            self._fail(f"frames shape {frames.shape}: need at least 2 frames and one pixel")
        if self.store == "zarr":
            from .capture_zarr import missing_chunks

            missing, total = missing_chunks(frames)
            if missing:
                self._fail(f"{missing} of {total} chunks of frames are missing (deleted, or never written)")
        freqs = f["frequencies_hz"]
        if freqs.shape != (n,):
            self._fail(f"frequencies_hz has shape {freqs.shape}, expected ({n},) to match frames")
        if freqs.dtype != np.float64:
            self._fail(f"frequencies_hz must be float64, got {freqs.dtype}")
        problem = frequency_problem(freqs[()])
        if problem:
            self._fail(problem)
        phases = f["hybrid_phases_rad"]
        if phases.shape != (4,):
            self._fail(f"hybrid_phases_rad must have shape (4,), got {phases.shape}")
        if not np.all(np.isfinite(phases[()])):
            self._fail("hybrid_phases_rad contains NaN or inf")
        if "field_of_view_deg" in f.attrs:
            try:
                fov = np.asarray(f.attrs["field_of_view_deg"], np.float64)
            except (TypeError, ValueError):
                fov = np.zeros(0)
            if fov.shape != (2,) or not np.all(np.isfinite(fov)) or not np.all((fov > 0) & (fov < 180)):
                self._fail(
                    f"attribute field_of_view_deg must be two angles (horizontal, vertical) in (0°, 180°), "
                    f"got {np.asarray(f.attrs['field_of_view_deg']).tolist()!r}"
                )
        for name in ("modulation_index", "dn_per_electron"):
            if name in f.attrs and not (np.isfinite(v := self._number_attr(name)) and v > 0):
                self._fail(f"attribute {name} must be a positive number, got {v}")
        if "bias_rad" in f.attrs and not np.isfinite(self._number_attr("bias_rad")):
            self._fail("attribute bias_rad must be a finite number of radians")
        if "adc_bits" in f.attrs:
            bits = self._number_attr("adc_bits")
            if not (np.isfinite(bits) and bits == round(bits) and 1 <= bits <= 16):
                self._fail(f"attribute adc_bits must be an integer from 1 to 16, got {bits:g}")
        if "dark" in f:
            if f["dark"].shape != (4, h, w):
                self._fail(f"dark must have shape (4, {h}, {w}), got {f['dark'].shape}")
            if not np.all(np.isfinite(f["dark"][()])):
                self._fail("dark contains NaN or inf")
        if "truth" in f:
            for name in ("depth_m", "reflectance"):
                if name in f["truth"] and f["truth"][name].shape != (h, w):
                    self._fail(f"truth/{name} must have shape ({h}, {w}), got {f['truth'][name].shape}")

    # -- metadata ---------------------------------------------------------------------------
    @property
    def frames(self):
        """The frames (4, N, H, W): an h5py dataset or a Zarr array (sliced alike)."""
        return self._file["frames"]

    @property
    def shape(self) -> tuple[int, int, int]:
        """(N, H, W): frames, rows, columns."""
        return tuple(self.frames.shape[1:])

    @property
    def frequencies_hz(self) -> np.ndarray:
        return self._file["frequencies_hz"][()]

    @property
    def hybrid_phases_rad(self) -> np.ndarray:
        return self._file["hybrid_phases_rad"][()]

    @property
    def attrs(self) -> dict:
        """The root attributes: scalars as Python numbers, vectors as arrays (either store)."""
        plain = lambda v: v.item() if isinstance(v, np.generic) else np.asarray(v) if isinstance(v, list) else v
        return {k: plain(v) for k, v in self._file.attrs.items()}

    @property
    def dark(self) -> np.ndarray | None:
        return self._file["dark"][()] if "dark" in self._file else None

    def truth(self, name: str) -> np.ndarray | None:
        g = self._file.get("truth")
        return None if g is None or name not in g else g[name][()]

    @property
    def truth_names(self) -> list[str]:
        """The truth datasets a simulated capture carries (none for a real one)."""
        g = self._file.get("truth")
        return [] if g is None else sorted(g)

    @property
    def truth_attrs(self) -> dict:
        g = self._file.get("truth")
        return {} if g is None else dict(g.attrs)

    @property
    def saturation_dn(self) -> float | None:
        """DN value that marks ADC saturation (uint16 frames): the ADC maximum of the capture's
        instrument (adc_bits when stated, else 16 bits); None for float frames."""
        if self.frames.dtype != np.uint16:
            return None
        return float(2 ** int(self._file.attrs.get("adc_bits", UNSTATED_ADC_BITS)) - 1)

    def instrument(self) -> Instrument:
        """The instrument this capture describes: its sweep, nominal hybrid phases, modulator
        (β, θ_b and sideband orders where stated, else `MZM`'s defaults), sensor (exposure,
        wavelength, ADC bits, gain) and timing; no system delay and no known departures.
        `Calibration.apply` turns it into the calibrated instrument."""
        a = self.attrs
        default_mzm, default_sensor = MZM(), Sensor()
        try:
            modulator = MZM(
                float(a.get("modulation_index", default_mzm.modulation_index)),
                float(a.get("bias_rad", default_mzm.bias_rad)),
                max_order=int(a.get("sideband_max_order", default_mzm.max_order)),
            )
            sensor = Sensor(
                exposure_s=float(a["exposure_s"]),
                wavelength_m=float(a["wavelength_m"]),
                adc_bits=int(a.get("adc_bits", UNSTATED_ADC_BITS)),
                dn_per_electron=float(a.get("dn_per_electron", default_sensor.dn_per_electron)),
            )
            fov = tuple(float(v) for v in np.asarray(a.get("field_of_view_deg", DEFAULT_FIELD_OF_VIEW_DEG)))
            return Instrument(
                sweep=FrequencySweep(self.frequencies_hz),
                modulator=modulator,
                hybrid=Hybrid(tuple(float(v) for v in self.hybrid_phases_rad)),
                sensor=sensor,
                frame_rate_hz=float(a["frame_rate_hz"]),
                field_of_view_deg=fov,
            )
        except (TypeError, ValueError) as exc:
            self._fail(f"the attributes do not describe a usable instrument: {exc}")

    # -- data -------------------------------------------------------------------------------
    def read_tile(self, rows: slice, cols: slice = slice(None)) -> np.ndarray:
        """Frames of a pixel tile, (4, N, h, w), in the file's dtype."""
        return self.frames[:, :, rows, cols]

    def read_tile_into(self, out: np.ndarray, rows: slice) -> None:
        """Frames of rows `rows` (all columns) read straight into the first rows of `out`
        (4, N, ≥h, W), a C-contiguous array of the file's dtype: no temporary array."""
        count = len(range(*rows.indices(self.shape[1])))
        if self.store == "zarr":
            out[:, :, :count, :] = self.frames[:, :, rows, :]
        elif (direct := self.direct_reader) is not None and direct.covers(rows):
            try:
                direct.read_rows_into(out, rows)
            except OSError as exc:  # e.g. the file truncated since it was opened
                self._fail(f"frames of rows {rows.start}:{rows.stop} could not be read ({exc})")
        else:
            self.frames.read_direct(out, np.s_[:, :, rows, :], np.s_[:, :, :count, :])

    def scatter_tables(self, pieces: list[np.ndarray], rows: int, rows_per_piece: int) -> list | None:
        """Where tiles of `rows` rows can be read straight into `pieces` of `rows_per_piece`
        rows each (4, N, rows_per_piece·W) (`read_tile_into_pieces`), the scatter tables for
        it (`DirectChunkReader.scatter_table`); else None."""
        direct = self.direct_reader if self.store == "hdf5" else None
        if direct is None or not direct.covers(slice(0, rows)) or not direct.scatters(rows, rows_per_piece):
            return None
        return direct.scatter_table(pieces, rows, rows_per_piece)

    def read_tile_into_pieces(self, pieces: list[np.ndarray], tables: list, rows: slice) -> None:
        """Frames of rows `rows` read into `pieces` of consecutive rows, each (4, N, k·W),
        C-contiguous, of the file's dtype, with the `scatter_tables` made for them: straight
        from the file where the rows are whole chunk bands, else through HDF5 and a copy."""
        r0, r1, _ = rows.indices(self.shape[1])
        direct = self.direct_reader
        if direct is not None and direct.covers(rows):
            try:
                direct.read_rows_into_pieces(tables, rows)
            except OSError as exc:  # e.g. the file truncated since it was opened
                self._fail(f"frames of rows {r0}:{r1} could not be read ({exc})")
            return
        n, _, w = self.shape
        block = np.empty((4, n, r1 - r0, w), self.frames.dtype)
        self.read_tile_into(block, rows)
        flat, k = block.reshape(4, n, -1), pieces[0].shape[-1]
        for s, piece in enumerate(pieces):
            part = flat[..., s * k : (s + 1) * k]
            piece[..., : part.shape[-1]] = part

    @functools.cached_property
    def direct_reader(self) -> DirectChunkReader | None:
        """The frames' `DirectChunkReader` (made on first use), or None where their chunks
        must be read through HDF5 (compressed, cutting rows, unwritten)."""
        try:
            # the index a `cohflash reconstruct` process's child listed, where it did (`early_read`)
            return DirectChunkReader(self._file["frames"], self.path, known=early_read.known_chunk_index())
        except ChunkIndexError:
            return None

    def close(self):
        if self.store == "hdf5":
            if self.__dict__.get("direct_reader") is not None:
                self.direct_reader.close()
            self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
