"""`cohflash calibrate`: four-CCD registration from chessboard views (`registration`), and the
hybrid, modulator and τ_sys from a stepped-frequency capture of a calibration target (`hybrid`)."""

from __future__ import annotations

import sys

import numpy as np

from .common import HelpFormatter, add_quiet, number_in, provenance

DEFAULT_MAX_PIXELS = 1024


def add_parser(sub) -> None:
    cal = sub.add_parser("calibrate", help="calibration of the instrument from captures")
    calsub = cal.add_subparsers(dest="what", required=True)
    cr = calsub.add_parser(
        "registration",
        help="four-CCD registration from chessboard views (Zhang, OpenCV)",
        formatter_class=HelpFormatter,
    )
    cr.add_argument(
        "--images",
        nargs=4,
        required=True,
        metavar=("CCD1_DIR", "CCD2_DIR", "CCD3_DIR", "CCD4_DIR"),
        help="one folder of chessboard images per CCD; a view is the same file name (suffix aside) in every folder; "
        "a view missing from some folders is used in the others and named. CCDs may be mirrored or rotated: "
        "corners are labelled by the board, and each CCD's orientation is found",
    )
    cr.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 9x6")
    cr.add_argument(
        "--square-mm", type=number_in(0, 1e4, "square size (mm)"), required=True, help="chessboard square size (mm)"
    )
    cr.add_argument("--out", required=True, help="registration JSON to write")
    cr.add_argument("--report", help="report figure (PNG): corners, per-view errors, XOR images")
    cr.add_argument(
        "--distance-mm",
        type=number_in(0, 1e8, "working distance (mm)"),
        default=None,
        help="working distance for the pixel maps (default: median board distance)",
    )
    cr.add_argument(
        "--mirrored",
        action="append",
        default=[],
        metavar="CCD=yes|no",
        help="say whether CCD 2, 3 or 4 sees the scene mirrored (behind an odd number of mirrors), where the "
        "views cannot tell (found from the views by default); repeatable",
    )
    add_quiet(cr)
    cr.set_defaults(func=run_registration)
    ch = calsub.add_parser(
        "hybrid",
        help="per-CCD phase/gain/offset, modulation index and roll-off, τ_sys "
        "from a stepped-frequency capture of a calibration target (optimistix)",
        formatter_class=HelpFormatter,
    )
    ch.add_argument(
        "capture",
        help="capture of a uniform target within the unambiguous range whose pixels see different optical "
        "carrier phases (a diffuse surface, or one tilted by a few wavelengths across the view: a mirror-flat "
        "target facing the camera is refused for the hybrid); the carrier phase must also drift within pixels "
        "(turbulence or a reference-arm phase ramp) for the hybrid's phases and gains",
    )
    ch.add_argument("--out", required=True, help="calibration file: .json, or .h5 to keep per-pixel maps")
    ch.add_argument("--dark", help="dark capture (light blocked): per-pixel offset map, and o_1")
    ch.add_argument(
        "--flat", help="flat-field capture (reference only, echo blocked; needs --dark): per-pixel relative gain maps"
    )
    ch.add_argument(
        "--known-distance-m",
        type=number_in(0, 1e5, "known distance (m)"),
        default=None,
        help="target distance; without it τ_sys is not identifiable",
    )
    ch.add_argument(
        "--max-pixels",
        type=number_in(1, 10**9, "maximum pixels", False, True),
        default=DEFAULT_MAX_PIXELS,
        help="strongest valid pixels used",
    )
    ch.add_argument("--report", help="report figure (PNG): I/Q before/after, tone taper, drift")
    add_quiet(ch)
    ch.set_defaults(func=run_hybrid)


def run_registration(args) -> int:
    from cohflash_calibration.board import Board
    from cohflash_calibration.registration import angle_deg, register, write_registration
    from cohflash_calibration.report import save_report, verdict

    board = Board.parse(args.board, args.square_mm)
    mirrored = {}
    for item in args.mirrored:
        ccd, _, answer = item.partition("=")
        if ccd.strip() not in ("2", "3", "4") or answer.strip().lower() not in ("yes", "no"):
            raise ValueError(f"--mirrored {item!r}: expected CCD=yes|no with CCD 2, 3 or 4 (e.g. --mirrored 4=yes)")
        mirrored[int(ccd)] = answer.strip().lower() == "yes"
    reg = register(args.images, board, args.distance_mm, progress=not args.quiet, mirrored=mirrored or None)
    write_registration(args.out, reg)
    if args.report:
        save_report(args.report, reg)
    print(
        f"wrote {args.out}: image {reg.image_size[0]}×{reg.image_size[1]}, working distance {reg.distance_mm:.0f} mm, "
        f"corner noise {reg.corner_sigma_px:.3f} px (joint solve of the four CCDs)"
    )
    for k, c in enumerate(reg.cameras, start=1):
        kk, sd = c.camera_matrix, c.std_intrinsics
        print(
            f"  CCD {k}{' (mirrored)' if c.mirrored else ''}: f = {kk[0, 0]:.2f} ± {sd[0]:.2f} px, "
            f"c = ({kk[0, 2]:.2f} ± {sd[2]:.2f}, {kk[1, 2]:.2f} ± {sd[3]:.2f}) px, "
            f"RMS {c.rms_px:.3f} px over {len(c.views_used)} views"
        )
        for name, reason in c.views_left_out.items():
            print(f"    view {name} left out: {reason}")
        if c.corners_rejected:
            print(
                "    outlier corners left out: "
                + ", ".join(f"{n} ({m})" for n, m in sorted(c.corners_rejected.items()))
            )
    for k, (r, t, s, b, a) in enumerate(zip(reg.R, reg.T, reg.stereo_rms_px, reg.xor_before, reg.xor_after), start=2):
        rot_sd, t_sd = reg.pose_sigma(k - 2)
        sigma_map = reg.map_sigma_px[k - 2]["sigma"] if reg.map_sigma_px else np.full(1, np.nan)
        print(
            f"  CCD {k} vs CCD 1: rotation {angle_deg(r):.3f}° (σ {np.linalg.norm(rot_sd):.3f}°), translation "
            f"({t[0]:.2f}, {t[1]:.2f}, {t[2]:.2f}) ± ({t_sd[0]:.2f}, {t_sd[1]:.2f}, {t_sd[2]:.2f}) mm, "
            f"stereo RMS {s:.3f} px; pixel map σ median {np.nanmedian(sigma_map):.3f} px; "
            f"XOR misalignment {b:.2%} → {a:.2%}"
        )
    for path, reason in reg.failed.items():
        print(f"  {path}: {reason}")
    for name, ccds in reg.missing_views.items():
        print(f"  view {name} missing from CCD {', '.join(map(str, ccds))}: used in the other CCDs only")
    print(f"{reg.seconds_per_view * 1e3:.0f} ms per view")
    print(verdict(reg))
    return 0


def plus_minus(entry, scale=1.0, unit="", digits=4) -> str:
    """A calibration file's {"value", "sigma", "note"} entry as 'v ± σ unit', or why it is not identified."""
    if entry.get("value") is None:
        return "not identified: " + entry.get("note", "")
    sig = entry.get("sigma")
    text = f"{entry['value'] * scale:.{digits}g}" + (f" ± {sig * scale:.2g}" if sig is not None else "")
    return text + unit + (f" ({entry['note']})" if entry.get("note") else "")


def run_hybrid(args) -> int:
    import warnings

    from ..calibration_file import write_calibration
    from ..constants import SPEED_OF_LIGHT_M_PER_S as C
    from ..hybrid_fit import calibrate_hybrid, save_hybrid_report

    result = calibrate_hybrid(
        args.capture,
        dark_path=args.dark,
        flat_path=args.flat,
        known_distance_m=args.known_distance_m,
        max_pixels=args.max_pixels,
        progress=not args.quiet,
    )
    doc = result["document"]
    options = {"known_distance_m": args.known_distance_m, "max_pixels": args.max_pixels}
    doc["provenance"] = provenance(args.capture, options, {"dark": args.dark, "flat": args.flat})
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
            print(
                f"  CCD {k + 1}: phase {np.degrees(hyb['phases_rad'][k]):8.3f} ± "
                f"{np.degrees(hyb['phases_sigma_rad'][k]):.3f}°"
                f", gain {hyb['relative_gains'][k]:.4f} ± {hyb['relative_gains_sigma'][k]:.4f}"
                f", offset {hyb['offsets_dn'][k]:8.2f} ± {hyb['offsets_sigma_dn'][k]:.2f} DN"
            )
        print(f"  χ²/dof {fit['hybrid_chi2_per_dof']:.3f}")
    print(f"modulation index β: {plus_minus(mod['modulation_index'])}")
    print(f"roll-off f_3dB: {plus_minus(mod['rolloff_3db_hz'], 1e-9, ' GHz')}")
    print(
        f"bias: {plus_minus(mod['bias_rad'], unit=' rad')}   (χ²/dof {fit['modulator_chi2_per_dof']:.3f} over "
        f"{fit['modulator_pixels']} pixels)"
    )
    delay = doc["system_delay_s"]
    if delay["value"] is None:
        print(f"system delay τ_sys: not identified: {delay['note']}")
    else:
        print(
            f"system delay τ_sys: {delay['value'] * 1e9:.6f} ± {delay['sigma'] * 1e9:.6f} ns "
            f"(path offset {delay['value'] * C / 2 * 1e3:.3f} ± {delay['sigma'] * C / 2 * 1e3:.3f} mm in depth)"
        )
    if result["maps"]:
        print("per-pixel maps: " + ", ".join(sorted(result["maps"])))
    return 0
