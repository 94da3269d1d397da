"""Depth result file (HDF5, `cohflash-depth` v1) and exports (preview PNG, float TIFF, PLY).

depth.h5 — root attributes: format = "cohflash-depth", format_version = 1, method,
ambiguity_m, depth_window_m, bin_depth_m, carrier_alignment, snr_threshold_db,
snr_threshold_effective_db, status_codes (JSON),
provenance (JSON: input name, size, mtime, package version, options). Datasets (H, W):
depth_m float64 (range along the pixel's ray, after τ_sys), amplitude float32 (the 2-D
intensity image, signal DN), valid uint8, sigma_m float32 (CRLB from fitted amplitude and
measured noise), snr float32 (peak-bin SNR, linear), fit_status int8, coarse_depth_m
float64. Invalid pixels keep their numbers (never NaN) and valid = 0.
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from .fileio import atomic_path, is_store_folder, json_value, save_figure
from .instrument import DEFAULT_FIELD_OF_VIEW_DEG
from .status import Status

FORMAT_NAME = "cohflash-depth"
FORMAT_VERSION = 1
_DTYPES = {
    "depth_m": np.float64,
    "amplitude": np.float32,
    "valid": np.uint8,
    "sigma_m": np.float32,
    "snr": np.float32,
    "fit_status": np.int8,
    "coarse_depth_m": np.float64,
    "fit_chi2": np.float32,
    "detection_ratio": np.float32,
}


def write_depth(path, outputs: dict, meta: dict, provenance: dict) -> Path:
    """depth.h5 from a reconstruction's outputs and meta data, with provenance, atomically; a
    path NAME.zarr gets the same attributes and arrays as a Zarr store."""
    path = Path(path)
    if is_store_folder(path):
        return write_depth_zarr(path, outputs, meta, provenance)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        f.attrs["format"] = FORMAT_NAME
        f.attrs["format_version"] = FORMAT_VERSION
        for k, v in meta.items():
            f.attrs[k] = v
        f.attrs["status_codes"] = Status.table_json()
        f.attrs["provenance"] = json.dumps(provenance, default=str)
        for name, dtype in _DTYPES.items():
            if name in outputs:
                # gzip for the status maps (mostly one value); measured noise-like floats shrink
                # by 15 % for 10× the time (60 of 69 ms a full-frame depth file)
                small_ints = np.dtype(dtype).kind in "iub"
                f.create_dataset(name, data=stored_as(outputs[name], dtype), compression="gzip" if small_ints else None)
    return path


def write_depth_zarr(path: Path, outputs: dict, meta: dict, provenance: dict) -> Path:
    """The depth file's attributes and arrays as a Zarr store (chunks of 256 rows), atomically."""
    import zarr

    with atomic_path(path) as tmp:
        group = zarr.open_group(tmp, mode="w")
        group.attrs.update(
            {
                "format": FORMAT_NAME,
                "format_version": FORMAT_VERSION,
                **{k: json_value(v) for k, v in meta.items()},
                "status_codes": Status.table_json(),
                "provenance": json.dumps(provenance, default=str),
            }
        )
        for name, dtype in _DTYPES.items():
            if name in outputs:
                values = stored_as(outputs[name], dtype)
                group.create_array(name, data=values, chunks=(min(256, values.shape[0]), values.shape[1]))
    return path


def stored_as(values, dtype) -> np.ndarray:
    """`values` in the file's dtype; floats beyond its range are clipped to its largest finite
    value (a dead pixel's SNR over a zero noise estimate is finite in float64 but not in
    float32: the file holds no inf)."""
    a = np.asarray(values)
    if np.issubdtype(dtype, np.floating) and np.issubdtype(a.dtype, np.floating):
        top = float(np.finfo(dtype).max)
        a = np.clip(a, -top, top)
    return a.astype(dtype)


def read_depth(path) -> tuple[dict, dict]:
    """A depth file's (or depth Zarr store's) arrays and attributes."""
    path = Path(path)
    if path.is_dir() and (path / "zarr.json").is_file():
        from .capture_zarr import open_zarr_group

        group = open_zarr_group(path, ValueError)
        if group.attrs.get("format") != FORMAT_NAME:
            raise ValueError(f"{path}: not a cohflash depth store")
        return {k: group[k][()] for k in group.array_keys()}, dict(group.attrs)
    if not path.is_file():
        raise FileNotFoundError(f"depth file not found: {path}")
    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != FORMAT_NAME:
            raise ValueError(f"{path}: not a cohflash depth file")
        return {k: f[k][()] for k in f.keys()}, dict(f.attrs)


def save_preview_png(
    path, depth_m, valid, title: str = "", reference_m: float | None = None, range_mm: tuple[float, float] | None = None
) -> Path:
    """Colour-mapped depth in mm relative to a reference (default: median of valid pixels),
    colour bar in mm, invalid pixels grey. `range_mm` fixes the colour limits (default: 1st
    to 99th percentile); values outside saturate, as the colour bar's arrows show."""
    from .fileio import headless_pyplot

    plt = headless_pyplot()

    valid = np.asarray(valid, bool)
    depth = np.asarray(depth_m, np.float64)
    ref = float(np.median(depth[valid])) if reference_m is None and valid.any() else (reference_m or 0.0)
    rel_mm = np.where(valid, (depth - ref) * 1e3, np.nan)
    finite = rel_mm[np.isfinite(rel_mm)]
    lo, hi = range_mm if range_mm is not None else (np.percentile(finite, [1, 99]) if finite.size else (-1, 1))
    cmap = plt.get_cmap("turbo").with_extremes(bad="0.6")
    h, w = depth.shape
    fig, ax = plt.subplots(figsize=(6.4, 6.4 * h / w + 0.6), dpi=110)
    im = ax.imshow(rel_mm, cmap=cmap, vmin=lo, vmax=hi if hi > lo else lo + 1, interpolation="nearest")
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, extend="both")
    cb.set_label(f"depth − {ref:.4f} m  (mm)" if finite.size else "no valid pixel: nothing to colour")
    ax.set_title(title or f"depth ({valid.mean():.1%} valid; grey = invalid)")
    ax.set_xlabel("column")
    ax.set_ylabel("row")
    fig.tight_layout()
    return save_figure(fig, path)


def save_depth_tiff(path, depth_m, valid) -> Path:
    """32-bit float TIFF of depth in metres, NaN where invalid."""
    import cv2

    img = np.where(np.asarray(valid, bool), depth_m, np.nan).astype(np.float32)
    path = Path(path)
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(".tiff", img)
        if not ok:
            raise RuntimeError("OpenCV could not encode the TIFF")
        tmp.write_bytes(buf.tobytes())
    return path


def pixel_rays(height: int, width: int, fov_deg: tuple[float, float]) -> np.ndarray:
    """Unit ray per pixel (H, W, 3) for a pinhole camera with the given full field of view
    (horizontal, vertical); z is the optical axis, x right, y down."""
    fx = (width / 2) / np.tan(np.deg2rad(fov_deg[0]) / 2)
    fy = (height / 2) / np.tan(np.deg2rad(fov_deg[1]) / 2)
    v, u = np.meshgrid(np.arange(height) + 0.5 - height / 2, np.arange(width) + 0.5 - width / 2, indexing="ij")
    rays = np.stack([u / fx, v / fy, np.ones_like(u)], axis=-1)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def save_ply(path, depth_m, valid, amplitude, fov_deg=DEFAULT_FIELD_OF_VIEW_DEG) -> Path:
    """Binary little-endian PLY of valid pixels: x, y, z (m, float32) and intensity."""
    valid = np.asarray(valid, bool)
    h, w = valid.shape
    pts = pixel_rays(h, w, fov_deg) * np.asarray(depth_m, np.float64)[..., None]
    sel = pts[valid].astype(np.float32)
    inten = np.asarray(amplitude, np.float32)[valid]
    vertex = np.empty(sel.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4")])
    vertex["x"], vertex["y"], vertex["z"], vertex["intensity"] = sel[:, 0], sel[:, 1], sel[:, 2], inten
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment cohflash depth export\n"
        f"element vertex {sel.shape[0]}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float intensity\nend_header\n"
    ).encode()
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(header + vertex.tobytes())
    return path
