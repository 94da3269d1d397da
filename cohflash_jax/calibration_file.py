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
from .modulator import MZM

FORMAT = "cohflash-calibration"
FORMAT_VERSION = 1
MAP_NAMES = ("offset_map_dn", "gain_map")


def _value(entry):
    """A plain number, or the value of a {"value", "sigma"} entry (None when not identified)."""
    if isinstance(entry, dict):
        return entry.get("value")
    return entry


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
        if data.get("format") != FORMAT:
            raise ValueError(f"{source}: format is {data.get('format')!r}, expected {FORMAT!r}")
        version = data.get("format_version", FORMAT_VERSION)
        if version != FORMAT_VERSION:
            raise ValueError(f"{source}: format_version {version!r} is not supported (this reader knows "
                             f"version {FORMAT_VERSION})")
        notes = []
        h = data.get("hybrid") or {}
        hybrid = None
        if h.get("phases_rad") is not None:
            try:
                hybrid = Hybrid(tuple(map(float, h["phases_rad"])),
                                tuple(map(float, h.get("relative_gains") or (1.0,) * 4)),
                                tuple(map(float, h.get("offsets_dn") or (0.0,) * 4)))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{source}: hybrid: {exc}") from None
            for name in ("phases_rad", "relative_gains", "offsets_dn"):
                if not np.all(np.isfinite(np.asarray(getattr(hybrid, name), float))):
                    raise ValueError(f"{source}: hybrid {name} contains NaN or inf")
            if min(hybrid.relative_gains) <= 0:
                raise ValueError(f"{source}: hybrid relative_gains must be positive, got {hybrid.relative_gains}")
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
                    modulator = MZM(float(beta), float(bias), float("inf") if roll is None else float(roll),
                                    max_order=int(mod.get("max_order", 3)))
                except (TypeError, ValueError) as exc:
                    raise ValueError(f"{source}: modulator: {exc}") from None
        delay = _value(data.get("system_delay_s", 0.0))
        if delay is None:
            notes.append("system delay not identified in the calibration: τ_sys = 0 used")
            delay = 0.0
        try:
            delay = float(delay)
        except (TypeError, ValueError):
            delay = math.nan
        if not math.isfinite(delay):
            raise ValueError(f"{source}: system_delay_s must be a finite number of seconds, got {delay!r}")
        if modulator is not None and not all(math.isfinite(v) for v in (modulator.modulation_index, modulator.bias_rad)):
            raise ValueError(f"{source}: modulator modulation_index and bias_rad must be finite")
        maps = maps or {}
        for name, arr in maps.items():
            if arr.ndim != 3 or arr.shape[0] != 4 or not np.all(np.isfinite(arr)):
                raise ValueError(f"{source}: map {name} must be a finite (4, H, W) array, got shape {arr.shape}")
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
        warnings.warn(f"per-pixel maps ({', '.join(sorted(maps))}) are not stored in JSON: write a .h5 "
                      "calibration to keep them", stacklevel=2)
        document = {**document, "maps": []}
        text = json.dumps(document, indent=1, allow_nan=True)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path
