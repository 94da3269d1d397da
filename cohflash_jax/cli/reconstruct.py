"""`cohflash reconstruct`: depth from a capture → depth.h5 (+ PNG, TIFF, PLY)."""

from __future__ import annotations

import concurrent.futures
from pathlib import Path

import numpy as np

from ..estimate import METHODS
from ..estimate.detection import DEFAULT_FALSE_ALARM
from ..estimate.drift import CARRIER_ALIGNMENTS
from ..reconstruct.policy import (
    DEFAULT_MAX_FIT_CHI2,
    DEFAULT_SNR_THRESHOLD_DB,
    ReconstructOptions,
)
from ..status import Status
from ..tiling import DEFAULT_TILE_ROWS, TILE_FRAME_BYTES
from .common import HelpFormatter, add_quiet, add_scheduler_options, number_in, provenance, range_mm


def add_parser(sub) -> None:
    r = sub.add_parser(
        "reconstruct", help="depth from a capture → depth.h5 (+ PNG, TIFF, PLY)", formatter_class=HelpFormatter
    )
    r.add_argument("capture", help="capture (format v1): an .h5 file or a .zarr store")
    r.add_argument("--out", required=True, help="depth result: an .h5 file, or NAME.zarr for a Zarr store")
    add_reconstruction_options(r)
    add_scheduler_options(r, "local Dask workers (threads or processes) (default: one per core, or one per GPU)")
    r.add_argument("--png", help="colour-mapped depth preview with a colour bar in mm")
    r.add_argument("--tiff", help="float32 depth TIFF in metres (NaN = invalid)")
    r.add_argument("--ply", help="point cloud of valid pixels")
    r.add_argument(
        "--png-range-mm",
        type=range_mm,
        default=None,
        help="LO,HI colour limits of the PNG in mm relative to the median depth (default: 1st–99th percentile)",
    )
    add_quiet(r)
    r.set_defaults(func=run)


def add_reconstruction_options(r) -> None:
    """The options of a reconstruction (method, calibration, registration, thresholds, …),
    shared by `reconstruct` and `stream`."""
    r.add_argument(
        "--method",
        choices=tuple(METHODS),
        default="ml",
        help="estimator: " + "; ".join(f"{k}: {m.help}" for k, m in METHODS.items()),
    )
    r.add_argument("--calibration", help="calibration file (.json or .h5) from `cohflash calibrate hybrid`")
    r.add_argument(
        "--max-fit-chi2",
        type=number_in(0, 1e12, "χ² limit"),
        default=DEFAULT_MAX_FIT_CHI2,
        help="ml: flag pixels whose fit has a larger reduced χ² (status 9, poor_fit)",
    )
    r.add_argument(
        "--min-depth-m",
        type=number_in(0, 1e6, "minimum depth (m)", False),
        default=0.0,
        help="coarse search ignores shallower depths (clutter near DC: drift, leakage)",
    )
    r.add_argument("--registration", help="four-CCD registration JSON from `cohflash calibrate registration`")
    r.add_argument(
        "--carrier",
        choices=CARRIER_ALIGNMENTS,
        default="auto",
        help="carrier-phase alignment: auto (default) finds a drift common to the capture (turbulence) and "
        "removes it, else aligns statically; static; tracked (follow each pixel's drift)",
    )
    r.add_argument("--tracking", action="store_true", help="the same as --carrier tracked")
    r.add_argument(
        "--tile-rows",
        type=number_in(1, 10**6, "tile rows", False, True),
        default=None,
        help=f"rows per streamed tile (memory vs speed; default: {DEFAULT_TILE_ROWS}, the chunking cohflash writes, or "
        f"more for short sweeps, up to {TILE_FRAME_BYTES // 2**20} MB of frames a tile)",
    )
    r.add_argument(
        "--snr-threshold-db",
        type=number_in(-100, 100, "SNR threshold (dB)", False),
        default=DEFAULT_SNR_THRESHOLD_DB,
        help="validity threshold on the peak-bin SNR (raised by 10·log10(1/(1 − √(2/(N−1)))) for the "
        "noise estimate's error from N frames)",
    )
    r.add_argument(
        "--false-alarm",
        type=number_in(0, 1, "false-alarm probability"),
        default=DEFAULT_FALSE_ALARM,
        help="probability per pixel that pure noise is detected as a tone (the detection test; 1 switches it off)",
    )
    r.add_argument(
        "--dtype", choices=("float32", "float64"), default="float32", help="I/Q and FFT precision (ML always float64)"
    )


def run_reconstruct(
    capture_path,
    out,
    options,
    calibration=None,
    png=None,
    ply=None,
    tiff=None,
    png_reference_m=None,
    png_range_mm=None,
    registration=None,
    scheduler=None,
    workers=None,
    capture_record=None,
):
    """Reconstruct a capture file and write depth.h5 and the exports asked for → the
    `reconstruct.Reconstruction`. The capture is opened once. `scheduler`: run on Dask
    (`scaleout.dask_client`) with `workers` local workers; the depths are the same.
    `capture_record`: a callable giving the capture's `file_record`, where it is made
    elsewhere (`provenance`)."""
    from ..capture import Capture
    from ..reconstruct import open_and_reconstruct
    from ..results import save_depth_tiff, save_ply, save_preview_png, write_depth

    capture_path = Path(capture_path)
    applied = {"calibration": calibration, "registration": registration}
    # the inputs' record (each file up to 64 MB hashed whole) is made while the reconstruction
    # computes: hashing and reading release the GIL (docs/performance.md)
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        record = pool.submit(provenance, capture_path, options, applied, capture_record)
        if scheduler is not None:
            from ..dask_cluster import dask_client
            from ..reconstruct.dask_bands import reconstruct_on_dask

            with dask_client(scheduler, workers) as client:
                result, run = reconstruct_on_dask(capture_path, options, client, calibration, registration)
            result.meta["dask_run"] = run.describe()
        else:
            with Capture(capture_path) as cap:
                result = open_and_reconstruct(capture_path, options, calibration, registration, capture=cap)
        outputs, meta = result.outputs, result.meta
        write_depth(out, outputs, meta, record.result())
    if png:
        save_preview_png(
            png,
            outputs["depth_m"],
            outputs["valid"],
            title=f"{capture_path.name}: {meta['method']} depth, {outputs['valid'].mean():.1%} valid",
            reference_m=png_reference_m,
            range_mm=png_range_mm,
        )
    if ply:
        save_ply(ply, outputs["depth_m"], outputs["valid"], outputs["amplitude"], result.instrument.field_of_view_deg)
    if tiff:
        save_depth_tiff(tiff, outputs["depth_m"], outputs["valid"])
    return result


def summary(outputs, meta) -> str:
    """What a reconstruction found, in a few lines."""
    import json

    valid = outputs["valid"].astype(bool)
    counts = np.bincount(outputs["fit_status"].astype(int).ravel(), minlength=len(Status))
    flagged = ", ".join(f"{Status(k).message} {c}" for k, c in enumerate(counts) if k and c)
    start, end = meta.get("depth_window_m", (0.0, meta["ambiguity_m"]))
    lines = [
        f"method {meta['method']}; carrier alignment {meta['carrier_alignment']} ({meta.get('carrier_reason', '')})",
        f"unambiguous depths [{start:.3f}, {end:.3f}) m; DFT bin {meta['bin_depth_m'] * 1e3:.2f} mm",
        f"valid pixels {valid.sum()} / {valid.size} ({valid.mean():.1%})"
        + (f"; flagged: {flagged}" if flagged else ""),
    ]
    if valid.any():
        d = outputs["depth_m"][valid]
        line = (
            f"depth {d.min():.4f} … {d.max():.4f} m; median σ ({meta['method']}'s own) "
            f"{np.median(outputs['sigma_m'][valid]) * 1e3:.3f} mm"
        )
        if "crlb_at_unit_snr_m" in meta:  # the bound at each pixel's SNR: the same for every method
            crlb = meta["crlb_at_unit_snr_m"] / np.sqrt(np.maximum(outputs["snr"][valid], 1e-30))
            line += f"; median CRLB (phase-locked, any method) {np.median(crlb) * 1e3:.3f} mm"
        lines.append(line)
    lines += [f"note: {n}" for n in json.loads(meta.get("notes", "[]"))]
    if "scheduler" in meta:
        lines.append(f"{meta['scheduler']}; {meta.get('dask_run', '')}")
    lines.append(f"reconstruction {meta['seconds']:.2f} s")
    return "\n".join(lines)


def options_from_args(args) -> ReconstructOptions:
    return ReconstructOptions(
        method=args.method,
        carrier="tracked" if args.tracking else args.carrier,
        tile_rows=args.tile_rows,
        snr_threshold_db=args.snr_threshold_db,
        false_alarm=args.false_alarm,
        dtype=args.dtype,
        progress=not args.quiet,
        min_depth_m=args.min_depth_m,
        max_fit_chi2=args.max_fit_chi2,
    )


def run(args) -> int:
    result = run_reconstruct(
        args.capture,
        args.out,
        options_from_args(args),
        args.calibration,
        args.png,
        args.ply,
        args.tiff,
        png_range_mm=args.png_range_mm,
        registration=args.registration,
        scheduler=args.scheduler,
        workers=args.workers,
    )
    print(f"wrote {args.out}\n" + summary(result.outputs, result.meta))
    return 0
