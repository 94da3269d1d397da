"""The `cohflash` command: demo, simulate, reconstruct, scenes."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from cohflash_jax.design import PARAMETERS
from cohflash_jax.fileio import require_output_folders
from cohflash_jax.reconstruct import DEFAULT_SNR_THRESHOLD_DB
from cohflash_jax.runtime import enable_compilation_cache, use_cpu_streams


def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like HxW (e.g. 256x320), got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"size must be positive, got {text!r}")
    return h, w


def _range_mm(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO,HI in mm, got {text!r}") from None
    if not hi > lo:
        raise argparse.ArgumentTypeError(f"HI must exceed LO, got {text!r}")
    return lo, hi


def _steps(text: str) -> int:
    n = int(text)
    if n < 2:
        raise argparse.ArgumentTypeError(f"a sweep needs at least 2 steps, got {n}")
    return n


def _scene_from_args(args):
    import cohflash_jax as cf

    if args.scene == "file":
        if not args.depth_map:
            raise ValueError("scene 'file' needs --depth-map (and optionally --reflectance-map)")
        return cf.from_files(args.depth_map, args.reflectance_map, depth_scale_m=args.depth_scale_m)
    return cf.get_scene(args.scene)


def cmd_scenes(args) -> int:
    import cohflash_jax as cf

    print("built-in scenes (default effects):")
    for name, make in cf.BUILTIN_SCENES.items():
        s = make()
        print(f"  {name:10s} {s.description}\n  {'':10s} effects: {', '.join(s.effects)}")
    print("  file       --depth-map FILE [--reflectance-map FILE] (.npy or image)\n\neffects:")
    for name, text in cf.KNOWN_EFFECTS.items():
        print(f"  {name:17s} {text}")
    return 0


def cmd_simulate(args) -> int:
    import cohflash_jax as cf
    from cohflash_jax.simulate import simulate_to_file

    scene = _scene_from_args(args)
    effects = scene.effects if args.effects is None else cf.parse_effects(args.effects)
    h, w = args.size
    inst = cf.Instrument.paper(args.steps)
    t0 = time.perf_counter()
    path = simulate_to_file(args.out, scene, inst, h, w, seed=args.seed, effects=effects, progress=not args.quiet)
    print(f"wrote {path}: scene {scene.name}, {h}×{w} px, {args.steps} frames "
          f"({inst.sweep.start_hz/1e9:.3g}–{inst.sweep.frequencies_hz[-1]/1e9:.4g} GHz, Δf {inst.sweep.step_hz/1e6:.3g} MHz, "
          f"ambiguity {inst.sweep.ambiguity_m:.2f} m), effects: {', '.join(effects) or 'none'}; "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


def _provenance(path: Path, options) -> dict:
    import dataclasses

    import jax

    import cohflash_jax as cf

    st = path.stat()
    # the device too: CPU and GPU results agree to ~1e-6 mm, not bit for bit
    return {"input": str(path.resolve()), "input_size_bytes": st.st_size, "input_mtime": st.st_mtime,
            "cohflash_version": cf.__version__, "jax_version": jax.__version__, "jax_device": str(jax.devices()[0]),
            "options": dataclasses.asdict(options)}


def run_reconstruct(capture_path, out, options, calibration=None, png=None, ply=None, tiff=None,
                    png_reference_m=None, png_range_mm=None, registration=None) -> tuple[dict, dict]:
    from cohflash_jax.capture import Capture
    from cohflash_jax.reconstruct import open_and_reconstruct
    from cohflash_jax.results import save_depth_tiff, save_ply, save_preview_png, write_depth

    capture_path = Path(capture_path)
    outputs, meta = open_and_reconstruct(capture_path, options, calibration, registration)
    write_depth(out, outputs, meta, _provenance(capture_path, options))
    with Capture(capture_path) as cap:
        fov = tuple(np.asarray(cap.attrs.get("field_of_view_deg", (0.72, 0.58)), float))
    if png:
        save_preview_png(png, outputs["depth_m"], outputs["valid"],
                         title=f"{capture_path.name}: {meta['method']} depth, {outputs['valid'].mean():.1%} valid",
                         reference_m=png_reference_m, range_mm=png_range_mm)
    if ply:
        save_ply(ply, outputs["depth_m"], outputs["valid"], outputs["amplitude"], fov)
    if tiff:
        save_depth_tiff(tiff, outputs["depth_m"], outputs["valid"])
    return outputs, meta


def _summary(outputs, meta) -> str:
    from cohflash_jax.reconstruct import STATUS

    valid = outputs["valid"].astype(bool)
    counts = np.bincount(outputs["fit_status"].astype(int).ravel(), minlength=len(STATUS))
    flagged = ", ".join(f"{STATUS[k]} {c}" for k, c in enumerate(counts) if k and c)
    start, end = meta.get("depth_window_m", (0.0, meta["ambiguity_m"]))
    lines = [f"method {meta['method']} ({meta['carrier_alignment']} carrier alignment); unambiguous depths "
             f"[{start:.3f}, {end:.3f}) m; DFT bin {meta['bin_depth_m'] * 1e3:.2f} mm",
             f"valid pixels {valid.sum()} / {valid.size} ({valid.mean():.1%})" + (f"; flagged: {flagged}" if flagged else "")]
    if valid.any():
        d = outputs["depth_m"][valid]
        lines.append(f"depth {d.min():.4f} … {d.max():.4f} m; median predicted σ (CRLB) "
                     f"{np.median(outputs['sigma_m'][valid]) * 1e3:.3f} mm")
    lines.append(f"reconstruction {meta['seconds']:.2f} s")
    return "\n".join(lines)


def cmd_reconstruct(args) -> int:
    from cohflash_jax.reconstruct import ReconstructOptions

    options = ReconstructOptions(method=args.method, tracking=args.tracking, tile_rows=args.tile_rows,
                                 snr_threshold_db=args.snr_threshold_db, dtype=args.dtype, progress=not args.quiet,
                                 min_depth_m=args.min_depth_m, max_fit_chi2=args.max_fit_chi2)
    outputs, meta = run_reconstruct(args.capture, args.out, options, args.calibration, args.png, args.ply, args.tiff,
                                    png_range_mm=args.png_range_mm, registration=args.registration)
    print(f"wrote {args.out}\n" + _summary(outputs, meta))
    return 0


def cmd_demo(args) -> int:
    import cohflash_jax as cf
    from cohflash_jax.capture import Capture
    from cohflash_jax.reconstruct import ReconstructOptions
    from cohflash_jax.simulate import simulate_to_file

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    h, w = args.size
    scene = cf.staircase()
    inst = cf.Instrument.paper(args.steps)
    capture = out / "staircase.h5"
    print(f"simulating the staircase scene: {h}×{w} px, {args.steps} frames, effects: {', '.join(scene.effects)}")
    t0 = time.perf_counter()
    simulate_to_file(capture, scene, inst, h, w, seed=args.seed, progress=not args.quiet)
    t_sim = time.perf_counter() - t0
    options = ReconstructOptions(method="ml", progress=not args.quiet)
    # colour scale on the staircase (its base at 30.5 m, steps 0…30 mm proud); the wall saturates
    outputs, meta = run_reconstruct(capture, out / "depth.h5", options, png=out / "depth.png",
                                    png_reference_m=30.5, png_range_mm=(-35.0, 5.0))
    with Capture(capture) as cap:
        truth = cap.truth("depth_m").astype(np.float64)
    valid = outputs["valid"].astype(bool)
    err = (outputs["depth_m"] - truth)[valid]
    print(_summary(outputs, meta))
    print(f"simulation {t_sim:.1f} s (includes compilation)")
    if err.size:
        # interior pixels only for precision: mixed pixels on step edges are a separate effect
        interior = valid & (np.abs(np.gradient(truth, axis=1)) == 0) & (np.abs(np.gradient(truth, axis=0)) == 0)
        e_in = (outputs["depth_m"] - truth)[interior]
        pred = np.median(outputs["sigma_m"][interior]) if interior.any() else float("nan")
        edge = valid & ~interior
        print(f"against truth, away from depth edges ({interior.sum()} px): bias {e_in.mean() * 1e3:+.4f} mm, "
              f"std {e_in.std() * 1e3:.3f} mm (predicted σ {pred * 1e3:.3f} mm); on depth edges (mixed pixels, "
              f"{edge.sum()} px): median |error| {np.median(np.abs(outputs['depth_m'] - truth)[edge]) * 1e3:.1f} mm")
        steps = np.unique(np.round(truth[interior], 4))
        rows = [f"{t:9.4f} m → {np.median(outputs['depth_m'][interior & (np.abs(truth - t) < 5e-5)]):9.4f} m"
                for t in steps]
        print("true depth → median reconstructed:\n  " + "\n  ".join(rows))
    print(f"wrote {capture}, {out / 'depth.h5'}, {out / 'depth.png'}")
    return 0


def _pixel(text: str) -> tuple[int, int]:
    try:
        r, c = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"pixel must look like ROW,COL, got {text!r}") from None
    return r, c


def _roi(text: str) -> list[tuple[int, int]]:
    try:
        rows, cols = text.split(",")
        r0, r1 = (int(v) for v in rows.split(":"))
        c0, c1 = (int(v) for v in cols.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"ROI must look like R0:R1,C0:C1, got {text!r}") from None
    if r1 <= r0 or c1 <= c0:
        raise argparse.ArgumentTypeError(f"empty ROI {text!r}")
    return [(r, c) for r in range(r0, r1) for c in range(c0, c1)]


def cmd_uncertainty(args) -> int:
    import json

    from cohflash_jax.capture import Capture
    from cohflash_jax.fileio import atomic_path
    from cohflash_jax.reconstruct import ReconstructOptions
    from cohflash_jax.uncertainty import plot_posterior, run_pixels, write_posteriors

    pixels = list(args.pixel or []) + (args.roi or [])
    if not pixels:
        raise ValueError("name pixels with --pixel ROW,COL (repeatable) or --roi R0:R1,C0:C1")
    options = ReconstructOptions(method="ml", progress=False)
    t0 = time.perf_counter()
    with Capture(args.capture) as cap:
        if args.chains:
            chains = chains_path(args.out)
            with atomic_path(chains) as tmp:
                results, skipped = run_pixels(cap, pixels, options, seed=args.seed, max_steps=args.max_steps,
                                              chains_path=tmp, progress=not args.quiet)
        else:
            results, skipped = run_pixels(cap, pixels, options, seed=args.seed, max_steps=args.max_steps,
                                          progress=not args.quiet)
    seconds = time.perf_counter() - t0
    write_posteriors(args.out, results, {"capture": str(Path(args.capture).resolve()), "seconds": seconds,
                                         "seconds_per_pixel": seconds / len(results),
                                         "skipped_pixels": json.dumps([[r, c, why] for r, c, why in skipped])})
    print(f"wrote {args.out}: {len(results)} pixel(s), {seconds / len(results):.2f} s per pixel")
    if skipped:
        print(f"  skipped {len(skipped)} pixel(s) with unusable data (no posterior): "
              + ", ".join(f"({r},{c}) {why}" for r, c, why in skipped[:20]) + (" …" if len(skipped) > 20 else ""))
    for r, c, p in results[:20]:
        print(f"  ({r},{c}): median {p.median_m:.5f} m, 68 % [{(p.interval68_m[0] - p.median_m) * 1e3:+.3f}, "
              f"{(p.interval68_m[1] - p.median_m) * 1e3:+.3f}] mm, 95 % [{(p.interval95_m[0] - p.median_m) * 1e3:+.3f}, "
              f"{(p.interval95_m[1] - p.median_m) * 1e3:+.3f}] mm, CRLB σ {p.crlb_m * 1e3:.3f} mm"
              + ("; MULTIMODAL" if p.multimodal else "") + (f" — {p.note}" if p.note else ""))
    if len(results) > 20:
        print(f"  … {len(results) - 20} more in the file")
    if args.plot:
        base = Path(args.plot)
        for k, (r, c, p) in enumerate(results[: args.max_plots]):
            target = base if len(results) == 1 else base.with_name(f"{base.stem}_{r}_{c}{base.suffix}")
            plot_posterior(target, p, title=f"pixel ({r}, {c})")
        print(f"wrote {min(len(results), args.max_plots)} plot(s) at {base.parent}/")
    return 0


def cmd_calibrate_registration(args) -> int:
    from cohflash_calibration.board import Board
    from cohflash_calibration.registration import register, save_report, write_registration

    board = Board.parse(args.board, args.square_mm)
    reg = register(args.images, board, args.distance_mm, progress=not args.quiet)
    write_registration(args.out, reg)
    if args.report:
        save_report(args.report, reg)
    print(f"wrote {args.out}: image {reg.image_size[0]}×{reg.image_size[1]}, working distance {reg.distance_mm:.0f} mm")
    for k, c in enumerate(reg.cameras, start=1):
        kk = c.camera_matrix
        print(f"  CCD {k}: f = {kk[0, 0]:.2f} ± {c.std_intrinsics[0]:.2f} px, c = ({kk[0, 2]:.2f}, {kk[1, 2]:.2f}) px, "
              f"RMS {c.rms_px:.3f} px over {len(c.views_used)} views"
              + (f"; left out: {', '.join(f'{n} ({r})' for n, r in c.views_left_out.items())}" if c.views_left_out else ""))
    for k, (r, t, s, b, a) in enumerate(zip(reg.R, reg.T, reg.stereo_rms_px, reg.xor_before, reg.xor_after), start=2):
        import cv2

        ang = float(np.rad2deg(np.linalg.norm(cv2.Rodrigues(np.asarray(r))[0])))
        print(f"  CCD {k} vs CCD 1: rotation {ang:.3f}°, translation {np.linalg.norm(t):.2f} mm, stereo RMS {s:.3f} px; "
              f"XOR misalignment {b:.2%} → {a:.2%}")
    if reg.failed:
        print("views left out (board not found): " + ", ".join(reg.failed))
    print(f"{reg.seconds_per_view * 1e3:.0f} ms per view")
    return 0


def _pm(entry, scale=1.0, unit="", digits=4) -> str:
    if entry.get("value") is None:
        return "not identified: " + entry.get("note", "")
    sig = entry.get("sigma")
    text = f"{entry['value'] * scale:.{digits}g}" + (f" ± {sig * scale:.2g}" if sig is not None else "")
    return text + unit + (f" ({entry['note']})" if entry.get("note") else "")


def cmd_calibrate_hybrid(args) -> int:
    import warnings

    from cohflash_jax.calibration_file import write_calibration
    from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
    from cohflash_jax.hybrid_fit import calibrate_hybrid, save_hybrid_report

    result = calibrate_hybrid(args.capture, dark_path=args.dark, flat_path=args.flat,
                              known_distance_m=args.known_distance_m,
                              max_pixels=args.max_pixels, progress=not args.quiet)
    doc = result["document"]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        write_calibration(args.out, doc, result["maps"])
    for w in caught:
        print(f"warning: {w.message}", file=sys.stderr)
    if args.report:
        save_hybrid_report(args.report, result)
    fit, hyb, mod = doc["fit"], doc["hybrid"], doc["modulator"]
    print(f"wrote {args.out}: {fit['pixels']} pixels × {fit['frames']} frames; gauge {doc['gauge']}")
    print(f"carrier: {fit['carrier_drift']}")
    if hyb["phases_rad"] is None:
        print(f"hybrid: {hyb['note']}")
    else:
        for k in range(4):
            print(f"  CCD {k + 1}: phase {np.degrees(hyb['phases_rad'][k]):8.3f} ± {np.degrees(hyb['phases_sigma_rad'][k]):.3f}°"
                  f", gain {hyb['relative_gains'][k]:.4f} ± {hyb['relative_gains_sigma'][k]:.4f}"
                  f", offset {hyb['offsets_dn'][k]:8.2f} ± {hyb['offsets_sigma_dn'][k]:.2f} DN")
        print(f"  χ²/dof {fit['hybrid_chi2_per_dof']:.3f}")
    print(f"modulation index β: {_pm(mod['modulation_index'])}")
    print(f"roll-off f_3dB: {_pm(mod['rolloff_3db_hz'], 1e-9, ' GHz')}")
    print(f"bias: {_pm(mod['bias_rad'], unit=' rad')}   (χ²/dof {fit['modulator_chi2_per_dof']:.3f} over "
          f"{fit['modulator_pixels']} pixels)")
    delay = doc["system_delay_s"]
    if delay["value"] is None:
        print(f"system delay τ_sys: not identified: {delay['note']}")
    else:
        print(f"system delay τ_sys: {delay['value'] * 1e9:.6f} ± {delay['sigma'] * 1e9:.6f} ns "
              f"(path offset {delay['value'] * C / 2 * 1e3:.3f} ± {delay['sigma'] * C / 2 * 1e3:.3f} mm in depth)")
    if result["maps"]:
        print("per-pixel maps: " + ", ".join(sorted(result["maps"])))
    return 0


def _assignments(items) -> dict:
    out = {}
    for item in items or []:
        for part in item.split(","):
            if "=" not in part:
                raise ValueError(f"expected NAME=VALUE, got {part!r}")
            k, v = part.split("=", 1)
            if k.strip() not in PARAMETERS:
                raise ValueError(f"unknown parameter {k.strip()!r}; known: {', '.join(PARAMETERS)}")
            out[k.strip()] = float(v)
    return out


def cmd_sweep(args) -> int:
    from cohflash_jax.design import parse_axis, plot_sweep, run_sweep

    axes = [parse_axis(a) for a in args.axis]
    mc_points = [_assignments([m]) for m in args.mc or []]
    rows = run_sweep(axes, args.out, fixed=_assignments(args.set), mc_points=mc_points, mc_all=args.mc_all,
                     mc_trials=args.mc_trials, workers=args.workers, progress=not args.quiet)
    names = [n for n, _ in axes]
    if args.plot:
        plot_sweep(rows, names, args.plot)
    crlb = np.array([float(r["crlb_mm"]) for r in rows])
    print(f"wrote {args.out}: {len(rows)} points over {', '.join(names)}; CRLB {crlb.min():.4g} … {crlb.max():.4g} mm")
    for r in rows:
        if "mc_trials" in r:
            where = ", ".join(f"{n}={float(r[n]):g}" for n in names)
            print(f"  Monte Carlo at {where}: {float(r['mc_precision_mm']):.4g} mm over {int(r['mc_trials'])} pixels "
                  f"(CRLB {float(r['crlb_mm']):.4g} mm, bias {float(r['mc_bias_mm']):+.3g} mm, "
                  f"valid {float(r['mc_valid_fraction']):.0%})")
    return 0


def cmd_design(args) -> int:
    import json

    from cohflash_jax.design import DesignProblem, design_report

    problem = DesignProblem(args.target_precision_mm * 1e-3, args.max_range_m, args.distance_m, args.reflectance,
                            args.max_power_mw * 1e-3, args.frame_rate_hz, args.min_frequency_ghz * 1e9,
                            args.max_frequency_ghz * 1e9, schedule="uniform", max_frames=args.max_frames)
    report = design_report(problem, compare_warped=args.schedule == "both", validate_trials=args.validate_trials,
                           progress=not args.quiet)
    print(report["text"])
    if args.out:
        from cohflash_jax.fileio import atomic_path

        with atomic_path(args.out) as tmp:
            tmp.write_text(json.dumps(report["document"], indent=1))
        print(f"wrote {args.out}")
    return 0 if report["document"]["feasible"] else 1


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cohflash", description="Stepped-frequency coherent flash LiDAR: simulate "
                                "captures, reconstruct depth with stated uncertainty.")
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="simulate the staircase scene, reconstruct it (ML), write a depth PNG")
    d.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    d.add_argument("--size", type=_size, default=(128, 160), help="HxW (default 128x160)")
    d.add_argument("--steps", type=_steps, default=3000, help="frequency steps (default 3000)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--quiet", action="store_true", help="no progress bars")
    d.set_defaults(func=cmd_demo)

    s = sub.add_parser("simulate", help="simulate a capture file (format v1)")
    s.add_argument("scene", help="planar, staircase, traffic, or file (with --depth-map)")
    s.add_argument("--out", required=True, help="capture file to write (.h5)")
    s.add_argument("--size", type=_size, default=(256, 320), help="HxW (default 256x320)")
    s.add_argument("--steps", type=_steps, default=3000, help="frequency steps from 0.1 GHz by 1.97 MHz (default 3000)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--effects", default=None, help="comma-separated effects (default: the scene's own); "
                   "see `cohflash scenes`")
    s.add_argument("--depth-map", help="scene 'file': depth map (.npy in m, or image × --depth-scale-m)")
    s.add_argument("--reflectance-map", help="scene 'file': reflectance map (.npy in [0,1], or image: "
                   "value / the dtype's full scale, e.g. /255 for 8-bit)")
    s.add_argument("--depth-scale-m", type=float, default=1.0, help="metres per image unit of --depth-map")
    s.add_argument("--quiet", action="store_true")
    s.set_defaults(func=cmd_simulate)

    r = sub.add_parser("reconstruct", help="depth from a capture → depth.h5 (+ PNG, TIFF, PLY)")
    r.add_argument("capture")
    r.add_argument("--out", required=True, help="depth result file (.h5)")
    r.add_argument("--method", choices=("dft", "interp", "ml"), default="ml")
    r.add_argument("--calibration", help="calibration file (.json or .h5) from `cohflash calibrate hybrid`")
    r.add_argument("--max-fit-chi2", type=float, default=5.0,
                   help="ml: flag pixels whose window fit has a larger reduced χ² (status 9, poor_fit)")
    r.add_argument("--min-depth-m", type=float, default=0.0,
                   help="coarse search ignores shallower depths (clutter near DC: drift, leakage)")
    r.add_argument("--registration", help="four-CCD registration JSON from `cohflash calibrate registration`")
    r.add_argument("--tracking", action="store_true", help="track a drifting carrier phase (turbulence)")
    r.add_argument("--png", help="colour-mapped depth preview with a colour bar in mm")
    r.add_argument("--tiff", help="float32 depth TIFF in metres (NaN = invalid)")
    r.add_argument("--ply", help="point cloud of valid pixels")
    r.add_argument("--png-range-mm", type=_range_mm, default=None, help="LO,HI colour limits of the PNG in mm "
                   "relative to the median depth (default: 1st–99th percentile)")
    r.add_argument("--tile-rows", type=int, default=32, help="rows per streamed tile (memory vs speed; "
                   "32 matches the chunking cohflash writes)")
    r.add_argument("--snr-threshold-db", type=float, default=None,
                   help=f"validity threshold on the peak-bin SNR (default {DEFAULT_SNR_THRESHOLD_DB:g} dB; raised "
                        "by 10·log10(1/(1 − √(2/(N−1)))) for the noise estimate's error from N frames)")
    r.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                   help="I/Q and FFT precision (ML always float64)")
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=cmd_reconstruct)

    cal = sub.add_parser("calibrate", help="calibration of the instrument from captures")
    calsub = cal.add_subparsers(dest="what", required=True)
    cr = calsub.add_parser("registration", help="four-CCD registration from chessboard views (Zhang, OpenCV)")
    cr.add_argument("--images", nargs=4, required=True, metavar=("CCD1_DIR", "CCD2_DIR", "CCD3_DIR", "CCD4_DIR"),
                    help="one folder of chessboard images per CCD; views are paired by sorted file name")
    cr.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 9x6")
    cr.add_argument("--square-mm", type=float, required=True, help="chessboard square size (mm)")
    cr.add_argument("--out", required=True, help="registration JSON to write")
    cr.add_argument("--report", help="report figure (PNG): corners, per-view errors, XOR images")
    cr.add_argument("--distance-mm", type=float, default=None,
                    help="working distance for the pixel maps (default: median board distance)")
    cr.add_argument("--quiet", action="store_true")
    cr.set_defaults(func=cmd_calibrate_registration)
    ch = calsub.add_parser("hybrid", help="per-CCD phase/gain/offset, modulation index and roll-off, τ_sys "
                           "from a stepped-frequency capture of a calibration target (optimistix)")
    ch.add_argument("capture", help="capture of a flat, uniform target; the carrier phase must drift within pixels "
                    "(turbulence or a reference-arm phase ramp) for the hybrid's phases and gains")
    ch.add_argument("--out", required=True, help="calibration file: .json, or .h5 to keep per-pixel maps")
    ch.add_argument("--dark", help="dark capture (light blocked): per-pixel offset map, and o_1")
    ch.add_argument("--flat", help="flat-field capture (reference only, echo blocked; needs --dark): "
                    "per-pixel relative gain maps")
    ch.add_argument("--known-distance-m", type=float, default=None,
                    help="target distance; without it τ_sys is not identifiable")
    ch.add_argument("--max-pixels", type=int, default=1024, help="strongest valid pixels used (default 1024)")
    ch.add_argument("--report", help="report figure (PNG): I/Q before/after, tone taper, drift")
    ch.add_argument("--quiet", action="store_true")
    ch.set_defaults(func=cmd_calibrate_hybrid)

    sw = sub.add_parser("sweep", help="depth precision (CRLB from the autodiff Fisher information, and Monte "
                        "Carlo) over a grid of design parameters → CSV (+ figure); resumable")
    sw.add_argument("--axis", action="append", required=True, metavar="NAME=START:STOP:COUNT[:log] | NAME=V1,V2,…",
                    help="a swept parameter (repeat for a grid): " + ", ".join(PARAMETERS))
    sw.add_argument("--set", action="append", metavar="NAME=VALUE[,…]", help="fixed parameters (default: the paper's)")
    sw.add_argument("--mc", action="append", metavar="NAME=VALUE,…", help="grid point that also gets a Monte Carlo run")
    sw.add_argument("--mc-all", action="store_true", help="Monte Carlo at every grid point")
    sw.add_argument("--mc-trials", type=int, default=256, help="pixels (independent trials) per Monte Carlo point")
    sw.add_argument("--workers", type=int, default=1, help="processes for Monte Carlo points (the CRLB grid is "
                    "vectorised in one process)")
    sw.add_argument("--out", required=True, help="CSV; an existing file is resumed (finished points are kept)")
    sw.add_argument("--plot", help="figure (PNG): heat map with contours, or precision against the axis")
    sw.add_argument("--quiet", action="store_true")
    sw.set_defaults(func=cmd_sweep)

    de = sub.add_parser("design", help="gradient-based design: the shortest acquisition that reaches a target "
                        "precision under range, power and frequency limits, validated by Monte Carlo")
    de.add_argument("--target-precision-mm", type=float, required=True)
    de.add_argument("--max-range-m", type=float, required=True, help="required unambiguous range")
    de.add_argument("--distance-m", type=float, default=30.5, help="target distance the precision is for")
    de.add_argument("--reflectance", type=float, default=0.5)
    de.add_argument("--max-power-mw", type=float, default=15.86)
    de.add_argument("--frame-rate-hz", type=float, default=150.0)
    de.add_argument("--min-frequency-ghz", type=float, default=0.1)
    de.add_argument("--max-frequency-ghz", type=float, default=6.0, help="highest microwave frequency (hardware)")
    de.add_argument("--max-frames", type=int, default=8192)
    de.add_argument("--schedule", choices=("uniform", "both"), default="uniform",
                    help="'both': also optimise a warped (non-uniform) schedule at the same frame count")
    de.add_argument("--validate-trials", type=int, default=256, help="Monte Carlo pixels at the optimum (0: skip)")
    de.add_argument("--out", help="design JSON")
    de.add_argument("--quiet", action="store_true")
    de.set_defaults(func=cmd_design)

    u = sub.add_parser("uncertainty", help="per-pixel depth posteriors with emcee")
    u.add_argument("capture")
    u.add_argument("--pixel", type=_pixel, action="append", help="ROW,COL (repeatable)")
    u.add_argument("--roi", type=_roi, help="R0:R1,C0:C1 (end-exclusive)")
    u.add_argument("--out", required=True, help="posterior file (.h5)")
    u.add_argument("--plot", help="PNG per pixel: depth marginal with the CRLB Gaussian, corner plot")
    u.add_argument("--max-plots", type=int, default=16)
    u.add_argument("--chains", action="store_true", help="keep all chains in OUT.chains.h5 (emcee HDF backend)")
    u.add_argument("--max-steps", type=int, default=20000)
    u.add_argument("--seed", type=int, default=0)
    u.add_argument("--quiet", action="store_true")
    u.set_defaults(func=cmd_uncertainty)

    sc = sub.add_parser("scenes", help="list built-in scenes and effects")
    sc.set_defaults(func=cmd_scenes)
    return p


# arguments that name files a command writes, and files it reads
OUTPUT_ARGUMENTS = ("out", "png", "ply", "tiff", "plot", "report")
INPUT_ARGUMENTS = ("capture", "calibration", "registration", "dark", "flat", "depth_map", "reflectance_map")


def chains_path(out) -> Path:
    """Where `uncertainty --chains` keeps every chain: OUT.chains.h5."""
    return Path(out).with_suffix(".chains.h5")


def check_output_paths(args) -> None:
    """Before any work: every output's folder exists, no output is an input of the command
    (`reconstruct x.h5 --out x.h5` replaced the capture with its depth map) and no two
    outputs are one file."""
    if args.command == "demo":  # its --out is a folder it makes
        return
    outputs = [(name, getattr(args, name)) for name in OUTPUT_ARGUMENTS if getattr(args, name, None)]
    if getattr(args, "chains", False):
        outputs.append(("chains", chains_path(args.out)))
    require_output_folders(*(path for _, path in outputs))
    inputs = {Path(getattr(args, name)).resolve(): name for name in INPUT_ARGUMENTS if getattr(args, name, None)}
    seen = {}
    for name, path in outputs:
        where = Path(path).resolve()
        if where in inputs:
            raise ValueError(f"--{name} {path} is the {inputs[where].replace('_', ' ')} file this command reads: "
                             "writing it would destroy the input; choose another path")
        if where in seen:
            raise ValueError(f"--{name} and --{seen[where]} name the same file {path}")
        seen[where] = name


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "snr_threshold_db", 0) is None:
        args.snr_threshold_db = DEFAULT_SNR_THRESHOLD_DB
    enable_compilation_cache()
    use_cpu_streams()
    try:
        check_output_paths(args)
        return args.func(args)
    except BrokenPipeError:  # e.g. `cohflash scenes | head` (before OSError, of which it is one)
        sys.stderr.close()
        return 0
    except (ValueError, FileNotFoundError, NotImplementedError, OSError) as exc:
        print(f"cohflash {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if args.command == "sweep":
            print(f"interrupted; the finished points are in {args.out}: rerun the same command to resume",
                  file=sys.stderr)
        else:
            print("interrupted; no partial output was kept", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
