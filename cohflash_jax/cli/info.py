"""`cohflash info FILE`: what a cohflash file holds, for every format the project writes —
capture, depth result, posterior, calibration (.json/.h5), registration, design JSON and
sweep CSV. Reads headers and small datasets only: a capture's frames are never loaded."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .common import HelpFormatter


def add_parser(sub) -> None:
    i = sub.add_parser(
        "info",
        help="what a cohflash file holds: capture, depth, posterior, calibration, registration, design, sweep",
        formatter_class=HelpFormatter,
    )
    i.add_argument("file", help="any file cohflash writes (.h5, .json, .csv, .zarr)")
    i.set_defaults(func=run)


def run(args) -> int:
    print(describe(args.file))
    return 0


def describe(path) -> str:
    """The file in a few lines; ValueError naming the file where it is not a cohflash file."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"file not found: {path}")
    if path.is_dir():
        return _describe_zarr(path)
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        return _describe_h5(path)
    if suffix == ".json":
        return _describe_json(path)
    if suffix == ".csv":
        return _describe_sweep(path)
    raise ValueError(f"{path}: not a cohflash file (expected .h5, .json or .csv)")


def _describe_zarr(path: Path) -> str:
    """A Zarr store cohflash writes: a capture or a depth result."""
    from ..capture_zarr import open_zarr_group

    kind = open_zarr_group(path, ValueError).attrs.get("format")
    if kind == "cohflash-capture":
        return _describe_capture(path)
    if kind == "cohflash-depth":
        return _describe_depth(path)
    raise ValueError(f"{path}: a Zarr store, but not a cohflash capture or depth result (format {kind!r})")


def _describe_h5(path: Path) -> str:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            kind = f.attrs.get("format")
            if "document" in f.attrs:  # a calibration with per-pixel maps
                maps = {k: f[k].shape for k in f if isinstance(f[k], h5py.Dataset)}
                return _describe_calibration(path, json.loads(f.attrs["document"]), maps)
    except OSError as exc:
        raise ValueError(f"{path}: not a readable HDF5 file ({exc})") from None
    if kind == "cohflash-capture":
        return _describe_capture(path)
    if kind == "cohflash-depth":
        return _describe_depth(path)
    if kind == "cohflash-posterior":
        return _describe_posterior(path)
    raise ValueError(f"{path}: HDF5, but not a cohflash file (format attribute {kind!r})")


def _describe_capture(path: Path) -> str:
    from ..capture import Capture

    with Capture(path) as cap:
        n, h, w = cap.shape
        f = cap.frequencies_hz
        inst = cap.instrument()
        attrs = cap.attrs
        truth = cap.truth_names
        dtype = cap.frames.dtype
        store = f"{cap.store} store, chunks {cap.frames.chunks}" if cap.store == "zarr" else "HDF5"
    uniform = np.allclose(np.diff(f), f[1] - f[0], rtol=1e-9, atol=1e-3) if n > 1 else True
    lines = [
        f"{path}: cohflash capture, format v{attrs.get('format_version')} ({store})",
        f"frames (4, {n}, {h}, {w}) {dtype}: {n} frequency steps, {h}×{w} pixels",
        f"band {f[0] / 1e9:.6g}–{f[-1] / 1e9:.6g} GHz, "
        + (f"uniform step {(f[1] - f[0]) / 1e6:.6g} MHz" if uniform else "non-uniform schedule")
        + f"; unambiguous range {inst.sweep.ambiguity_m:.4g} m (fundamental)",
        f"frame rate {inst.frame_rate_hz:g} Hz ({n / inst.frame_rate_hz:.3g} s a sweep), "
        f"exposure {inst.sensor.exposure_s * 1e3:g} ms, wavelength {attrs['wavelength_m'] * 1e9:g} nm",
        f"modulator β {inst.modulator.modulation_index:g}, bias {inst.modulator.bias_rad:.4g} rad; "
        f"hybrid phases {np.round(np.rad2deg(np.asarray(inst.hybrid.phases_rad)), 2).tolist()}°",
        "truth: " + (", ".join(truth) if truth else "none (a real capture)"),
        "attributes: " + ", ".join(sorted(attrs)),
    ]
    return "\n".join(lines)


def _describe_depth(path: Path) -> str:
    from ..results import read_depth
    from ..status import Status

    outputs, meta = read_depth(path)
    valid = outputs["valid"].astype(bool)
    counts = np.bincount(outputs["fit_status"].astype(int).ravel(), minlength=len(Status))
    statuses = ", ".join(f"{Status(k).message} {c}" for k, c in enumerate(counts) if c)
    start, end = meta.get("depth_window_m", (0.0, meta.get("ambiguity_m", float("nan"))))
    prov = json.loads(meta.get("provenance", "{}"))
    inputs = prov.get("inputs", {"capture": {"path": prov.get("input", "?")}})
    lines = [
        f"{path}: cohflash depth result, format v{meta.get('format_version')}",
        f"{valid.shape[0]}×{valid.shape[1]} pixels; method {meta.get('method')}; "
        f"carrier {meta.get('carrier_alignment', '?')}; false alarm {meta.get('false_alarm', '?')}",
        f"unambiguous depths [{start:.4g}, {end:.4g}) m; DFT bin {meta.get('bin_depth_m', float('nan')) * 1e3:.3g} mm",
        f"valid {valid.sum()} / {valid.size} ({valid.mean():.1%}); statuses: {statuses}",
    ]
    if valid.any():
        lines.append(
            f"depth {outputs['depth_m'][valid].min():.4f} … {outputs['depth_m'][valid].max():.4f} m; "
            f"median σ {np.median(outputs['sigma_m'][valid]) * 1e3:.4g} mm"
        )
    lines += [f"input {role}: {rec.get('path')}" for role, rec in inputs.items()]
    if "jax_device" in prov:  # where it ran: a small capture runs on the CPU even beside a GPU
        lines.append(
            f"made by cohflash {prov.get('cohflash_version', '?')}, JAX {prov.get('jax_version', '?')} "
            f"on {prov['jax_device']}" + (f"; I/Q: {meta['iq_path']}" if "iq_path" in meta else "")
        )
    lines += [f"note: {n}" for n in json.loads(meta.get("notes", "[]"))]
    return "\n".join(lines)


def _describe_posterior(path: Path) -> str:
    import h5py

    with h5py.File(path, "r") as f:
        attrs = dict(f.attrs)
        count = len(f["row"]) if "row" in f else 0
        multimodal = int(np.sum(f["multimodal"][()])) if "multimodal" in f else 0
        converged = int(np.sum(f["converged"][()])) if "converged" in f else 0
    return "\n".join(
        [
            f"{path}: cohflash posterior, format v{attrs.get('format_version')}",
            f"{count} pixels: {converged} converged, {multimodal} multimodal",
            "attributes: " + ", ".join(sorted(attrs)),
        ]
    )


def _describe_json(path: Path) -> str:
    from ..fileio import read_json

    doc = read_json(path, "cohflash")
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: a JSON {type(doc).__name__}, not a cohflash file")
    kind = doc.get("format")
    if kind == "cohflash-calibration":
        return _describe_calibration(path, doc, {})
    if kind == "cohflash-registration":
        poses = []
        for p in doc.get("relative_poses", []):
            sigma = p.get("rotation_sigma_deg")
            poses.append(
                f"CCD {p['ccd']}{' (mirrored)' if p.get('mirrored') else ''}: rotation {p['rotation_deg']:.3f}°"
                + (f" (σ {np.linalg.norm(sigma):.3f}°)" if sigma else "")
                + f", T {np.round(p['T_mm'], 3).tolist()} mm"
                + (f" ± {np.round(p['T_sigma_mm'], 3).tolist()}" if p.get("T_sigma_mm") else "")
                + f", stereo RMS {p['stereo_rms_px']:.3f} px"
            )
        dropped = [
            f"CCD {k + 1} {name}: {reason}"
            for k, cam in enumerate(doc.get("cameras", []))
            for name, reason in cam.get("views_left_out", {}).items()
        ]
        return "\n".join(
            [
                f"{path}: cohflash registration, format v{doc.get('format_version')}",
                f"image {doc.get('image_size')}; board {doc.get('board')}; working distance "
                f"{doc.get('working_distance_mm', float('nan')):.1f} mm",
                *poses,
                f"files not used: {len(doc.get('failed_views', {}))}; views missing from a folder: "
                f"{len(doc.get('missing_views', {}))}; views dropped in single CCDs: {len(dropped)}",
                *dropped,
            ]
        )
    if kind == "cohflash-design" or "problem" in doc:  # design JSONs before format v1 had no format key
        verdict = "feasible" if doc.get("feasible") else f"NOT FEASIBLE: {doc.get('note')}"
        return "\n".join(
            [
                f"{path}: cohflash design result ({verdict})",
                f"{doc.get('num_frames')} frames, {doc.get('acquisition_s', float('nan')):.4g} s; "
                f"CRLB {doc.get('crlb_mm', float('nan')):.4g} mm; unambiguous to "
                f"{doc.get('unambiguous_range_m', float('nan')):.4g} m",
                "variables: " + ", ".join(f"{k} {v:.4g}" for k, v in (doc.get("variables") or {}).items()),
            ]
        )
    raise ValueError(f"{path}: JSON, but not a cohflash file (format {kind!r})")


def _describe_calibration(path: Path, doc: dict, maps: dict) -> str:
    from ..calibration_file import Calibration

    cal = Calibration.from_document(doc, str(path))
    values = cal.values()
    fmt = lambda v, k=1.0: "not identified" if v is None else np.round(np.asarray(v) * k, 4).tolist()
    lines = [
        f"{path}: cohflash calibration, format v{doc.get('format_version')}",
        f"hybrid phases (°) {fmt(values['hybrid_phases_rad'], 180 / np.pi)}; "
        f"gains {fmt(values['hybrid_relative_gains'])}; offsets (DN) {fmt(values['hybrid_offsets_dn'])}",
        f"modulator β {fmt(values['modulation_index'])}, bias {fmt(values['bias_rad'])} rad; "
        f"τ_sys {values['system_delay_s'] * 1e9:.4g} ns",
    ]
    if maps:
        lines.append("per-pixel maps: " + ", ".join(f"{k} {v}" for k, v in maps.items()))
    lines += [f"note: {n}" for n in values["notes"]]
    return "\n".join(lines)


def _describe_sweep(path: Path) -> str:
    from ..design.grid import read_rows

    rows = read_rows(path)
    if not rows:
        raise ValueError(f"{path}: an empty sweep CSV")
    names = rows[0]["swept"].split(",")
    mc = [r for r in rows if r.get("mc_trials") not in (None, "")]
    beyond = sum(float(r["distance_m"]) >= float(r["ambiguity_m"]) for r in rows)
    crlb = np.array([float(r["crlb_mm"]) for r in rows])
    return "\n".join(
        [
            f"{path}: cohflash sweep, {len(rows)} points over {', '.join(names)}",
            f"CRLB {crlb.min():.4g} … {crlb.max():.4g} mm; Monte Carlo at {len(mc)} points; "
            f"{beyond} points beyond the unambiguous range",
        ]
    )
