"""The calibration file (`cohflash-calibration` v1): JSON, or HDF5 when it carries per-pixel maps.

Written by `cohflash calibrate hybrid`, read by `cohflash reconstruct --calibration`; the
format is documented in docs/formats.md. Every fitted number may be given plainly or as
{"value": v, "sigma": s, "note": …}; a value of null means "not identified" and the
capture's nominal setting is used instead.
"""

from __future__ import annotations

import dataclasses
import json
import math
import warnings
from pathlib import Path

import h5py
import numpy as np

from .fileio import atomic_path, read_json
from .hybrid import Hybrid
from .instrument import Instrument
from .modulator import MZM

FORMAT = "cohflash-calibration"
FORMAT_VERSION = 1
MAP_NAMES = ("offset_map_dn", "gain_map")


# Plausibility bounds on a calibration's values: past them the file is wrong, not the instrument
MAX_OFFSET_DN = 65535  # a 16-bit ADC's full scale
MIN_RELATIVE_GAIN = 0.1  # a CCD 10× weaker or stronger than CCD 1 is a wiring fault, not a gain
MAX_SYSTEM_DELAY_S = 1e-5  # 10 µs: 2 km of fibre


def _value(entry):
    """A plain number, or the value of a {"value", "sigma"} entry (None when not identified)."""
    if isinstance(entry, dict):
        return entry.get("value")
    return entry


@dataclasses.dataclass(frozen=True)
class PixelMaps:
    """Per-pixel corrections applied before I/Q, each (4, H, W) or None. `offset_dn`: offsets
    (DN) per CCD and pixel — a dark frame — which then replace the hybrid's global offsets
    (never both); `gain`: gains relative to the hybrid's global ones (CCD 1 ≡ 1)."""

    offset_dn: np.ndarray | None = None
    gain: np.ndarray | None = None

    def apply(self, instrument: Instrument) -> Instrument:
        """The instrument whose hybrid these maps correct: per-pixel offsets replace the
        hybrid's global ones (never both are subtracted)."""
        if self.offset_dn is None:
            return instrument
        return instrument.replace(hybrid=dataclasses.replace(instrument.hybrid, offsets_dn=(0.0,) * 4))

    def check_shape(self, height: int, width: int, source: str = "pixel maps"):
        for name in ("offset_dn", "gain"):
            arr = getattr(self, name)
            if arr is not None and np.shape(arr) != (4, height, width):
                raise ValueError(
                    f"{source}: {name} has shape {np.shape(arr)}, the capture needs (4, {height}, {width})"
                )


@dataclasses.dataclass(frozen=True)
class Calibration:
    """Hybrid and system calibration applied before inversion.

    `hybrid`/`modulator` None: use the capture's nominal ones. `offset_map_dn` (4, H, W) acts as
    the dark frame (offsets per pixel; then the global offsets are not applied a second time);
    `gain_map` (4, H, W) holds per-pixel gains relative to the global ones (CCD 1 ≡ 1)."""

    hybrid: Hybrid | None = None
    system_delay_s: float = 0.0
    modulator: MZM | None = None
    offset_map_dn: np.ndarray | None = None
    gain_map: np.ndarray | None = None
    notes: tuple[str, ...] = ()

    @classmethod
    def from_document(cls, data: dict, source: str = "calibration", maps: dict | None = None) -> "Calibration":
        if not isinstance(data, dict):
            raise ValueError(f"{source}: a calibration is a JSON object, got a {type(data).__name__}")
        if data.get("format") != FORMAT:
            raise ValueError(f"{source}: format is {data.get('format')!r}, expected {FORMAT!r}")
        version = data.get("format_version", FORMAT_VERSION)
        if version != FORMAT_VERSION:
            raise ValueError(
                f"{source}: format_version {version!r} is not supported (this reader knows version {FORMAT_VERSION})"
            )
        notes = []
        h = data.get("hybrid") or {}
        hybrid = None
        if h.get("phases_rad") is not None:
            try:
                hybrid = Hybrid(
                    tuple(map(float, h["phases_rad"])),
                    tuple(map(float, h.get("relative_gains") or (1.0,) * 4)),
                    tuple(map(float, h.get("offsets_dn") or (0.0,) * 4)),
                )
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{source}: hybrid: {exc}") from None
            for name in ("phases_rad", "relative_gains", "offsets_dn"):
                if not np.all(np.isfinite(np.asarray(getattr(hybrid, name), float))):
                    raise ValueError(f"{source}: hybrid {name} contains NaN or inf")
            gains = np.asarray(hybrid.relative_gains)
            if np.any(gains < MIN_RELATIVE_GAIN) or np.any(gains > 1 / MIN_RELATIVE_GAIN):
                raise ValueError(
                    f"{source}: hybrid relative_gains {hybrid.relative_gains} are implausible: each CCD's gain "
                    f"relative to CCD 1 must lie in [{MIN_RELATIVE_GAIN}, {1 / MIN_RELATIVE_GAIN:g}]"
                )
            if np.any(np.abs(hybrid.offsets_dn) > MAX_OFFSET_DN):
                raise ValueError(
                    f"{source}: hybrid offsets_dn {hybrid.offsets_dn} are implausible: beyond ±{MAX_OFFSET_DN} DN, "
                    "the range of a 16-bit ADC"
                )
        else:
            notes.append("hybrid not identified in the calibration: nominal hybrid used")
        mod = data.get("modulator")
        modulator = None
        if mod is not None:
            beta, bias, roll = (_value(mod.get(k)) for k in ("modulation_index", "bias_rad", "rolloff_3db_hz"))
            if beta is None or bias is None:
                notes.append("modulator not identified in the calibration: the capture's settings used")
            else:
                try:
                    modulator = MZM(
                        float(beta),
                        float(bias),
                        float("inf") if roll is None else float(roll),
                        max_order=int(mod.get("max_order", 3)),
                    )
                except (TypeError, ValueError) as exc:
                    raise ValueError(f"{source}: modulator: {exc}") from None
        delay = _value(data.get("system_delay_s", 0.0))
        if delay is None:
            notes.append("system delay not identified in the calibration: τ_sys = 0 used")
            delay = 0.0
        given = delay
        try:
            delay = float(delay)
        except (TypeError, ValueError):
            delay = math.nan
        if not math.isfinite(delay):
            raise ValueError(f"{source}: system_delay_s must be a finite number of seconds, got {given!r}")
        if abs(delay) > MAX_SYSTEM_DELAY_S:
            raise ValueError(
                f"{source}: system_delay_s {delay:g} s is implausible: beyond ±{MAX_SYSTEM_DELAY_S:g} s "
                f"({MAX_SYSTEM_DELAY_S * 2e8 / 1e3:g} km of fibre)"
            )
        if modulator is not None and not all(
            math.isfinite(v) for v in (modulator.modulation_index, modulator.bias_rad)
        ):
            raise ValueError(f"{source}: modulator modulation_index and bias_rad must be finite")
        maps = maps or {}
        for name, arr in maps.items():
            if arr.ndim != 3 or arr.shape[0] != 4 or not np.all(np.isfinite(arr)):
                raise ValueError(f"{source}: map {name} must be a finite (4, H, W) array, got shape {arr.shape}")
            if name == "offset_map_dn" and np.any(np.abs(arr) > MAX_OFFSET_DN):
                raise ValueError(f"{source}: map {name} holds offsets beyond ±{MAX_OFFSET_DN} DN (a 16-bit ADC)")
        gain = maps.get("gain_map")
        if gain is not None and np.any(gain <= 0):
            raise ValueError(f"{source}: gain_map has {int((gain <= 0).sum())} values ≤ 0")
        return cls(hybrid, float(delay), modulator, maps.get("offset_map_dn"), gain, tuple(notes))

    @classmethod
    def load(cls, path) -> "Calibration":
        path = Path(path)
        if path.suffix.lower() in (".h5", ".hdf5"):
            if not path.is_file():
                raise FileNotFoundError(f"calibration file not found: {path}")
            try:
                with h5py.File(path, "r") as f:
                    if "document" not in f.attrs:
                        raise ValueError(f"{path}: no 'document' attribute: not a {FORMAT} file")
                    data = json.loads(f.attrs["document"])
                    maps = {k: f[k][()] for k in MAP_NAMES if k in f}
            except OSError as exc:
                raise ValueError(f"{path}: not a readable HDF5 file ({exc})") from None
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path}: the 'document' attribute is not valid JSON ({exc})") from None
            return cls.from_document(data, str(path), maps)
        return cls.from_document(read_json(path, "calibration"), str(path))

    def values(self) -> dict:
        """The values this calibration applies (None: the capture's own is kept), for a
        result's provenance."""
        hyb, mod = self.hybrid, self.modulator
        return {
            "hybrid_phases_rad": None if hyb is None else [float(v) for v in hyb.phases_rad],
            "hybrid_relative_gains": None if hyb is None else [float(v) for v in hyb.relative_gains],
            "hybrid_offsets_dn": None if hyb is None else [float(v) for v in hyb.offsets_dn],
            "system_delay_s": self.system_delay_s,
            "modulation_index": None if mod is None else float(mod.modulation_index),
            "bias_rad": None if mod is None else float(mod.bias_rad),
            "offset_map": self.offset_map_dn is not None,
            "gain_map": self.gain_map is not None,
            "notes": list(self.notes),
        }

    def apply(self, instrument: Instrument) -> Instrument:
        """The calibrated instrument: `instrument` (a capture's nominal one,
        `Capture.instrument`) with the identified hybrid, modulator and system delay; a part
        the calibration did not identify stays as it was (`notes` says which)."""
        return instrument.replace(
            hybrid=self.hybrid or instrument.hybrid,
            modulator=self.modulator or instrument.modulator,
            system_delay_s=self.system_delay_s,
        )

    def pixel_maps(self, dark_dn: np.ndarray | None = None) -> PixelMaps:
        """Per-pixel corrections: a capture's own dark frame (`dark_dn`) before the
        calibration's offset map, and the calibration's gain map."""
        return PixelMaps(dark_dn if dark_dn is not None else self.offset_map_dn, self.gain_map)

    def check_shape(self, height: int, width: int, source: str = "calibration"):
        for name in MAP_NAMES:
            arr = getattr(self, name)
            if arr is not None and arr.shape != (4, height, width):
                raise ValueError(f"{source}: {name} has shape {arr.shape}, the capture needs (4, {height}, {width})")


def write_calibration(path, document: dict, maps: dict | None = None) -> Path:
    """Write atomically: `.json` (global values; maps are left out with a warning) or `.h5`
    (the same document as a JSON attribute, plus the maps as datasets)."""
    path = Path(path)
    maps = maps or {}
    text = json.dumps(document, indent=1, allow_nan=True)
    if path.suffix.lower() in (".h5", ".hdf5"):
        with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["format_version"] = FORMAT_VERSION
            f.attrs["document"] = text
            for name, arr in maps.items():
                f.create_dataset(name, data=np.asarray(arr, np.float32), compression="gzip")
        return path
    if path.suffix.lower() != ".json":
        raise ValueError(f"calibration output must end in .json or .h5, got {path.name}")
    if maps:
        warnings.warn(
            f"per-pixel maps ({', '.join(sorted(maps))}) are not stored in JSON: write a .h5 calibration to keep them",
            stacklevel=2,
        )
        document = {**document, "maps": []}
        text = json.dumps(document, indent=1, allow_nan=True)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


@dataclasses.dataclass(frozen=True)
class CaptureSetup:
    """What to reconstruct a capture with: its instrument (nominal, or calibrated), the
    per-pixel maps (its dark frame, or the calibration's maps), and the calibration's fallback
    notes. `reconstruct`, `uncertainty` and the studies take a capture through here."""

    instrument: Instrument
    maps: PixelMaps
    notes: tuple[str, ...] = ()

    @classmethod
    def of(cls, capture, calibration: Calibration | None = None) -> CaptureSetup:
        """The setup of an open `Capture`, calibrated by `calibration` where given."""
        instrument = capture.instrument()
        if calibration is None:
            return cls(instrument, PixelMaps(capture.dark))
        calibration.check_shape(*capture.shape[1:])
        return cls(calibration.apply(instrument), calibration.pixel_maps(capture.dark), calibration.notes)
