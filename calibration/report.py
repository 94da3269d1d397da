"""The registration's report: what a calibration engineer checks before trusting the pixel maps.

One figure: each CCD's corners on one view (labels from the board: corner 0 and the board's
x axis marked), per-view reprojection RMS under the views' names as on disk, the residuals of
every corner (outliers in red), where the board's corners fell on CCD 1 (coverage: the maps are
trustworthy where the board went), each pixel map's 1σ over CCD 1's grid, the XOR images after
registration, and a text panel with the poses, their σ, what was left out and the verdict."""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from .registration import Registration, RegistrationError, angle_deg, xor_image

# A baseline above this fraction of the working distance makes the XOR check meaningless:
# parallax moves the background against the board, and XOR stays at 14–40 % whatever the poses
NEAR_COMMON_APERTURE = 0.02


def xor_meaning(reg: Registration) -> str:
    """Whether the XOR misalignment says anything for this rig."""
    baseline = max(float(np.linalg.norm(t)) for t in reg.T)
    if baseline <= NEAR_COMMON_APERTURE * reg.distance_mm:
        return (
            f"XOR misalignment is a check here: the CCDs share an aperture to {baseline:.1f} mm at "
            f"{reg.distance_mm:.0f} mm (the paper reports 1.5–2 % after registration)"
        )
    return (
        f"XOR misalignment means little here: a {baseline:.0f} mm baseline at {reg.distance_mm:.0f} mm is not a "
        "common aperture, so parallax keeps it high whatever the registration; trust the stereo RMS and σ instead"
    )


def verdict(reg: Registration) -> str:
    """One line: usable or not, and how well the maps are known where the board went."""
    problems = reg.quality_problems()
    if problems:
        return "verdict: NOT USABLE — " + "; ".join(problems)
    worst_rms = max(reg.stereo_rms_px)
    sigmas = [np.asarray(m["sigma"]) for m in reg.map_sigma_px]
    median = max(float(np.nanmedian(s)) for s in sigmas) if sigmas else float("nan")
    dropped = sum(len(c.views_left_out) for c in reg.cameras)
    mirrored = [k + 1 for k, c in enumerate(reg.cameras) if c.mirrored]
    return (
        f"verdict: usable — stereo RMS ≤ {worst_rms:.2f} px, pixel maps known to {median:.2f} px (median 1σ over "
        f"CCD 1's grid; larger where the board never went)"
        + (f"; CCD {', '.join(map(str, mirrored))} mirrored" if mirrored else "")
        + (f"; {dropped} view(s) left out in single CCDs (listed)" if dropped else "")
    )


def save_report(path, reg: Registration) -> Path:
    """The report figure (PNG)."""
    import matplotlib.colors as mcolors

    from cohflash_jax.fileio import headless_pyplot

    plt = headless_pyplot()

    from cohflash_jax.fileio import save_figure

    if reg.views is None or reg.views.solution is None:
        raise RegistrationError("the report needs the views the registration was computed from (`register`'s result)")
    images8, corners, sol, names = reg.views.images8, reg.views.corners, reg.views.solution, reg.views.view_names
    w, h = reg.image_size
    common = [n for n in reg.cameras[0].views_used if all(n in c.views_used for c in reg.cameras)]
    view = common[0] if common else reg.cameras[0].views_used[0]
    fig, axes = plt.subplots(5, 4, figsize=(18, 22), dpi=80)
    small = dict(fontsize=9)
    for k, cam in enumerate(reg.cameras):
        ax = axes[0, k]
        img = images8[k].get(view)
        if img is not None:
            ax.imshow(img[:, ::-1] if cam.mirrored else img, cmap="gray")
        if view in corners[k]:
            c = corners[k][view]
            ax.plot(c[:, 0], c[:, 1], "r+", ms=5)
            ax.plot(c[0, 0], c[0, 1], "go", ms=7)
            ax.annotate("", xy=c[1], xytext=c[0], arrowprops=dict(color="lime", arrowstyle="->"))
        frame = " (mirrored: shown flipped)" if cam.mirrored else ""
        ax.set_title(f"CCD {k + 1}{frame}: view {view}\ncorner 0 green, board x →", **small)
        ax.axis("off")
        ax = axes[1, k]
        shown = [n for n in names if n in cam.per_view_rms_px or n in cam.views_left_out]
        values = [cam.per_view_rms_px.get(n, 0.0) for n in shown]
        colours = ["tab:red" if n in cam.views_left_out else "tab:blue" for n in shown]
        ax.bar(range(len(shown)), values, color=colours)
        ax.set_xticks(range(len(shown)), shown, rotation=90, fontsize=7)
        ax.set_ylabel("reprojection RMS (px)")
        ax.set_title(
            f"CCD {k + 1}: RMS {cam.rms_px:.3f} px" + (" (red: view left out)" if cam.views_left_out else ""), **small
        )
        ax = axes[2, k]
        res = sol.residuals_px[k]
        seen = np.isfinite(res[..., 0])
        inl = sol.inliers[k]
        ax.plot(res[inl][:, 0], res[inl][:, 1], ".", ms=2, alpha=0.5, label="kept")
        out = seen & ~inl
        if out.any():
            ax.plot(res[out][:, 0], res[out][:, 1], "r.", ms=3, label=f"left out ({int(out.sum())})")
        lim = 5 * max(reg.corner_sigma_px, 0.05)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.set_xlabel("residual u (px)")
        ax.set_ylabel("residual v (px)")
        ax.legend(fontsize=7, loc="upper right")
        ax.set_title(f"CCD {k + 1}: corner residuals", **small)
    # coverage: where the corners fell on CCD 1
    ax = axes[3, 0]
    pts = np.concatenate([c for c in corners[0].values()]) if corners[0] else np.zeros((0, 2))
    hist, _, _ = np.histogram2d(pts[:, 1], pts[:, 0], bins=(12, 16), range=((0, h), (0, w)))
    im = ax.imshow(hist, extent=(0, w, h, 0), cmap="viridis")
    fig.colorbar(im, ax=ax, shrink=0.7, label="corners")
    ax.set_title("board coverage on CCD 1 (corners per cell)", **small)
    for k, m in enumerate(reg.map_sigma_px, start=1):
        ax = axes[3, k]
        sigma = np.clip(np.asarray(m["sigma"]), 1e-3, 1e3)
        im = ax.imshow(
            sigma,
            extent=(0, w, h, 0),
            norm=mcolors.LogNorm(vmin=max(sigma.min(), 1e-3), vmax=max(sigma.max(), 2e-3)),
            cmap="magma",
        )
        ax.plot(pts[:, 0], pts[:, 1], "c.", ms=1, alpha=0.3)
        fig.colorbar(im, ax=ax, shrink=0.7, label="1σ (px)")
        ax.set_title(f"CCD {k + 1} pixel map: 1σ at {reg.distance_mm:.0f} mm\n(dots: board corners)", **small)
    ax = axes[4, 0]
    ax.axis("off")
    lines = [f"working distance {reg.distance_mm:.0f} mm; corner noise {reg.corner_sigma_px:.3f} px"]
    for k, (r, t, s, b, a) in enumerate(zip(reg.R, reg.T, reg.stereo_rms_px, reg.xor_before, reg.xor_after)):
        rot_sd, t_sd = reg.pose_sigma(k)
        lines.append(
            f"CCD {k + 2}{' mirrored' if reg.cameras[k + 1].mirrored else ''}: {angle_deg(r):.3f}° ± "
            f"{np.linalg.norm(rot_sd):.3f}°, |T| {np.linalg.norm(t):.2f} ± {np.linalg.norm(t_sd):.2f} mm, "
            f"stereo RMS {s:.3f} px, XOR {b:.1%} → {a:.1%}"
        )
    left = [f"CCD {k + 1} {n}: {r}" for k, c in enumerate(reg.cameras) for n, r in c.views_left_out.items()]
    left += [f"{Path(p).parent.name}/{Path(p).name}: {r}" for p, r in reg.failed.items()]
    left += [f"{n}: missing from CCD {', '.join(map(str, ks))}" for n, ks in reg.missing_views.items()]
    lines += ["left out:"] + (left or ["nothing"])
    lines += [xor_meaning(reg), verdict(reg)]
    text = "\n".join(textwrap.fill(line, 70, subsequent_indent="  ") for line in lines)
    ax.text(0, 1, text, fontsize=8, va="top", family="monospace")
    for k in range(1, 4):
        ax = axes[4, k]
        if view in images8[0] and view in images8[k]:
            ax.imshow(xor_image(images8[0][view], images8[k][view], *reg.maps(k + 1))[0], cmap="gray")
        ax.set_title(f"XOR CCD 1 vs registered CCD {k + 1}, {view}: {reg.xor_after[k - 1]:.1%}", **small)
        ax.axis("off")
    fig.tight_layout()
    return save_figure(fig, path)
