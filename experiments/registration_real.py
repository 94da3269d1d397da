"""Registration on real photographs, side by side with mrcal on the same corners, and a
cross-validation of the stated pixel-map σ.

    python -m cohflash_experiments.registration_real [--out out/registration_real] [--images DIR]

The images are OpenCV's stereo sample set (tests/data/opencv_stereo: left/right 01–14 without 10,
640×480, 9×6 inner corners). cohflash registers four CCD folders L/R/L/R (CCDs 3 and 4 are
pixel-identical copies in another file format) and states every parameter's σ. mrcal
(Debian's `mrcal` / `python3-mrcal`, for the system Python) calibrates the L/R pair on the very
corners cohflash labelled, with the same lens model (OPENCV5), twice: with its board-flatness
(warp) fit and with a flat board; its pose σ comes from its own Jacobian. Where mrcal is absent
the study says so and reports cohflash alone. The cross-validation registers the odd and the
even views apart and compares the two pixel maps of CCD 2 with the σ each states.

Writes registration.json, report.png, comparison.csv/.md (cohflash ± σ, mrcal, difference in
σ), cross_validation.png/.md.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import tempfile
from pathlib import Path

import cv2
import numpy as np

from cohflash_calibration import joint
from cohflash_calibration.board import Board
from cohflash_calibration.registration import angle_deg, register, write_registration
from cohflash_calibration.report import save_report
from cohflash_experiments import study_parser
from cohflash_jax.fileio import save_figure, write_csv

DEFAULT_IMAGES = Path(__file__).resolve().parents[1] / "tests" / "data" / "opencv_stereo"
BOARD = Board(9, 6, 25.0)
SYSTEM_PYTHON = "/usr/bin/python3"

# Runs in the system Python (where python3-mrcal lives): a model's intrinsics, camera 1's pose
# and its σ from mrcal's own Jacobian (σ² (JᵀJ)⁻¹ over the board observations, unpacked)
MRCAL_READER = r"""
import json, sys
import mrcal, numpy as np
m0, m1 = mrcal.cameramodel(sys.argv[1]), mrcal.cameramodel(sys.argv[2])
oi = m1.optimization_inputs()
p, x, J = mrcal.optimizer_callback(**oi, no_factorization=True)[:3]
J = J.toarray()
nb = mrcal.num_measurements_boards(**oi)
sigma = float(np.sqrt(np.mean(x[:nb] ** 2)))
cov = np.linalg.pinv(J.T @ J) * sigma**2
scale = np.ones(len(p)); mrcal.unpack_state(scale, **oi)
cov = cov * scale[:, None] * scale[None, :]
i = mrcal.state_index_extrinsics(0, **oi)
out = {"intrinsics": [m.intrinsics()[1].tolist() for m in (m0, m1)], "rt": m1.extrinsics_rt_fromref().tolist(),
       "rt_sigma": np.sqrt(np.diag(cov)[i:i + 6]).tolist(), "residual_rms_px": sigma,
       "warp": (oi["calobject_warp"].tolist() if oi.get("calobject_warp") is not None else None)}
print(json.dumps(out))
"""


def build_folders(images: Path, root: Path, views=None) -> list[Path]:
    """CCD folders L, R, L (PNG), R (PNG) with views named viewNN (optionally a subset)."""
    dirs = []
    for name, side, suffix in (("ccd1", "left", ".jpg"), ("ccd2", "right", ".jpg"), ("ccd3", "left", ".png"),
                               ("ccd4", "right", ".png")):  # fmt: skip
        d = root / name
        d.mkdir(parents=True, exist_ok=True)
        for p in sorted(images.glob(f"{side}*.jpg")):
            view = p.stem.replace(side, "view")
            if views is not None and view not in views:
                continue
            target = d / (view + suffix)
            if suffix == ".jpg":
                shutil.copy(p, target)
            else:
                cv2.imwrite(str(target), cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))
        dirs.append(d)
    return dirs


def run_mrcal(reg, images: Path, work: Path, warp: bool) -> dict | None:
    """mrcal on cohflash's labelled corners of CCDs 1 and 2 (None, with a note, where absent)."""
    exe = shutil.which("mrcal-calibrate-cameras")
    if exe is None or not Path(SYSTEM_PYTHON).exists():
        return None
    work.mkdir(parents=True, exist_ok=True)
    lines = ["# filename x y level"]
    for k, side in ((0, "left"), (1, "right")):
        for p in sorted(images.glob(f"{side}*.jpg")):
            link = work / p.name
            if not link.exists():
                shutil.copy(p, link)
            c = reg.views.corners[k].get(p.stem.replace(side, "view"))
            lines += [f"{p.name} - - -"] if c is None else [f"{p.name} {x:.4f} {y:.4f} 0" for x, y in c]
    (work / "corners.vnl").write_text("\n".join(lines) + "\n")
    focal = reg.cameras[0].camera_matrix[0, 0]
    cmd = [exe, "--corners-cache", "corners.vnl", "--lensmodel", "LENSMODEL_OPENCV5", "--focal", f"{focal:.1f}"]
    cmd += ["--object-spacing", str(BOARD.square_mm), "--object-width-n", str(BOARD.cols)]
    cmd += ["--object-height-n", str(BOARD.rows), "left*.jpg", "right*.jpg"]
    if not warp:
        cmd.insert(1, "--skip-calobject-warp-solve")
    subprocess.run(cmd, cwd=work, check=True, capture_output=True, text=True)
    out = subprocess.run(
        [SYSTEM_PYTHON, "-c", MRCAL_READER, "camera-0.cameramodel", "camera-1.cameramodel"],
        cwd=work,
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(out.stdout)


def comparison_rows(reg, mrcal_runs: dict) -> list[dict]:
    rot_sd, t_sd = reg.pose_sigma(0)
    rvec = cv2.Rodrigues(reg.R[0])[0].ravel()
    ours = {
        **{f"CCD {k + 1} {n}": (reg.cameras[k].camera_matrix[i, j], reg.cameras[k].std_intrinsics[m])
           for k in (0, 1) for m, (n, i, j) in enumerate((("fx", 0, 0), ("fy", 1, 1), ("cx", 0, 2), ("cy", 1, 2)))},
        **{f"CCD 2 r{a} (deg)": (np.rad2deg(rvec[i]), rot_sd[i]) for i, a in enumerate("xyz")},
        **{f"CCD 2 T{a} (mm)": (reg.T[0][i], t_sd[i]) for i, a in enumerate("xyz")},
        "corner noise (px)": (reg.corner_sigma_px, float("nan")),
    }  # fmt: skip
    rows = []
    for name, (value, sigma) in ours.items():
        row = {"parameter": name, "cohflash": value, "cohflash_sigma": sigma}
        for label, m in mrcal_runs.items():
            if m is None:
                continue
            if name.startswith("CCD") and name.split()[2] in ("fx", "fy", "cx", "cy"):
                k, i = int(name.split()[1]) - 1, ("fx", "fy", "cx", "cy").index(name.split()[2])
                other, other_sd = m["intrinsics"][k][i], float("nan")
            elif " r" in name:
                i = "xyz".index(name.split()[2][1])
                other, other_sd = np.rad2deg(m["rt"][i]), np.rad2deg(m["rt_sigma"][i])
            elif " T" in name:
                i = "xyz".index(name.split()[2][1])
                other, other_sd = m["rt"][3 + i], m["rt_sigma"][3 + i]
            else:
                other, other_sd = m["residual_rms_px"], float("nan")
            row[label] = other
            row[f"{label}_sigma"] = other_sd
            row[f"{label}_diff_in_sigma"] = (value - other) / sigma if sigma == sigma and sigma > 0 else float("nan")
        rows.append(row)
    return rows


def cross_validate(images: Path, work: Path, reg_all) -> tuple[dict, object]:
    """Odd and even views registered apart: CCD 2's map difference against √(σ_a² + σ_b²)."""
    names = sorted(reg_all.views.corners[0])
    halves = [names[0::2], names[1::2]]
    # at one working distance: each half's own median board distance would move the maps by the
    # parallax of the 83 mm baseline (1.4 px per 1 % of distance), not by calibration error
    regs = [
        register(build_folders(images, work / f"half{i}", set(h)), BOARD, reg_all.distance_mm, progress=False)
        for i, h in enumerate(halves)
    ]
    w, h = reg_all.image_size
    u, v = np.linspace(0, w - 1, 32), np.linspace(0, h - 1, 24)
    pix = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    maps, sigmas = [], []
    for r in regs:
        mx, my = r.maps(2)
        maps.append(np.stack([cv2.remap(mx, *np.float32(pix.T[:, None, :]), cv2.INTER_LINEAR).ravel(),
                              cv2.remap(my, *np.float32(pix.T[:, None, :]), cv2.INTER_LINEAR).ravel()], 1))  # fmt: skip
        sigmas.append(joint.map_sigma_at(r.views.solution, 1, pix, w, r.distance_mm, False))
    diff = np.linalg.norm(maps[0] - maps[1], axis=1)
    predicted = np.hypot(*sigmas)
    corners = np.concatenate(list(reg_all.views.corners[0].values()))
    hull = cv2.convexHull(corners.astype(np.float32))
    inside = np.array([cv2.pointPolygonTest(hull, (float(x), float(y)), False) >= 0 for x, y in pix])
    ratio = diff / predicted
    stats = {
        "views per half": [len(x) for x in halves],
        "covered grid points": int(inside.sum()),
        "median |Δmap| covered (px)": float(np.median(diff[inside])),
        "median predicted σ_Δ covered (px)": float(np.median(predicted[inside])),
        "fraction |Δ|/σ_Δ < 1 (covered)": float(np.mean(ratio[inside] < 1)),
        "fraction |Δ|/σ_Δ < 2.5 (covered)": float(np.mean(ratio[inside] < 2.5)),
        "fraction |Δ|/σ_Δ < 2.5 (whole image)": float(np.mean(ratio < 2.5)),
    }
    from cohflash_jax.fileio import headless_pyplot

    plt = headless_pyplot()

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), dpi=90)
    im = axes[0].imshow(np.clip(ratio.reshape(24, 32), 0, 5), extent=(0, w, h, 0), cmap="RdYlGn_r", vmin=0, vmax=5)
    axes[0].plot(*np.r_[hull[:, 0], hull[:1, 0]].T, "k-", lw=1)
    fig.colorbar(im, ax=axes[0], label="|map_odd − map_even| / √(σ_odd² + σ_even²)")
    axes[0].set_title("CCD 2 map: odd views against even views (line: board coverage)", fontsize=9)
    axes[1].hist(ratio[inside], bins=np.linspace(0, 5, 26), density=True, alpha=0.7, label="covered grid points")
    r = np.linspace(0, 5, 200)
    axes[1].plot(r, r * np.exp(-(r**2) / 2), "k--", label="Rayleigh (isotropic 2-D error)")
    axes[1].set_xlabel("|Δ| / σ_Δ")
    axes[1].legend(fontsize=8)
    axes[1].set_title("difference over stated σ", fontsize=9)
    fig.tight_layout()
    return stats, fig


def run(out: Path, images: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        reg = register(build_folders(images, tmp / "all"), BOARD, progress=False)
        write_registration(out / "registration.json", reg)
        save_report(out / "report.png", reg)
        mrcal_runs = {}
        notes = []
        for label, warp in (("mrcal (board warp fitted)", True), ("mrcal (flat board)", False)):
            try:
                mrcal_runs[label] = run_mrcal(reg, images, tmp / label.split()[1].strip("()"), warp)
            except (subprocess.CalledProcessError, json.JSONDecodeError) as exc:
                mrcal_runs[label] = None
                notes.append(f"{label} failed: {getattr(exc, 'stderr', exc)}")
            if mrcal_runs[label] is None and not notes:
                notes.append("mrcal is not installed here (Debian: apt install mrcal python3-mrcal): cohflash alone")
        rows = comparison_rows(reg, mrcal_runs)
        write_csv(out / "comparison.csv", rows)
        labels = [k for k, m in mrcal_runs.items() if m is not None]
        md = ["| parameter | cohflash ± σ | " + " | ".join(f"{k} ± σ | Δ/σ" for k in labels) + " |"]
        md.append("|---|---|" + "---|---|" * len(labels))
        for r in rows:
            cells = [f"{r['parameter']}", f"{r['cohflash']:.4f} ± {r['cohflash_sigma']:.4f}"]
            for k in labels:
                sd = r[f"{k}_sigma"]
                cells += [f"{r[k]:.4f}" + (f" ± {sd:.4f}" if sd == sd else ""), f"{r[f'{k}_diff_in_sigma']:+.2f}"]
            md.append("| " + " | ".join(cells) + " |")
        for k in labels:
            if mrcal_runs[k]["warp"] is not None:
                md.append(f"\n{k}: board warp (sag) {np.round(mrcal_runs[k]['warp'], 3).tolist()} mm")
        md += [f"\n{n}" for n in notes]
        md.append(
            f"\ncohflash: CCD 2 at {angle_deg(reg.R[0]):.3f}° from CCD 1, CCD 3 (pixel-identical copy of CCD 1) at "
            f"{angle_deg(reg.R[1]):.5f}°; {reg.seconds_per_view * 1e3:.0f} ms per view"
        )
        (out / "comparison.md").write_text("\n".join(md) + "\n")
        print("\n".join(md))
        stats, fig = cross_validate(images, tmp, reg)
        save_figure(fig, out / "cross_validation.png")
        text = "\n".join(f"- {k}: {v if isinstance(v, list | int) else round(v, 4)}" for k, v in stats.items())
        (out / "cross_validation.md").write_text(text + "\n")
        print(text)


def main():
    p = study_parser(__doc__)
    p.add_argument("--out", default="out/registration_real", help="output folder")
    p.add_argument("--images", default=str(DEFAULT_IMAGES), help="folder with left*.jpg / right*.jpg")
    args = p.parse_args()
    run(Path(args.out), Path(args.images))


if __name__ == "__main__":
    main()
