"""The registration's report figure: corners, per-view errors, XOR images after registration."""

from __future__ import annotations

from pathlib import Path

from .registration import Registration, RegistrationError, xor_image


def save_report(path, reg: Registration) -> Path:
    """Corners on one view per CCD, reprojection error per view, XOR images after registration."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from cohflash_jax.fileio import save_figure

    if reg.views is None:
        raise RegistrationError("the report needs the views the registration was computed from (`register`'s result)")
    images8, detections = reg.views.images8, reg.views.detections
    common = [n for n in reg.cameras[0].views_used if all(n in c.views_used for c in reg.cameras)]
    view = common[0] if common else reg.cameras[0].views_used[0]
    fig, axes = plt.subplots(3, 4, figsize=(16, 11), dpi=90)
    for k in range(4):
        ax = axes[0, k]
        ax.imshow(images8[k][view], cmap="gray")
        if view in detections[k]:
            c = detections[k][view]
            ax.plot(c[:, 0], c[:, 1], "r+", ms=5)
        ax.set_title(f"CCD {k + 1}: {view}, RMS {reg.cameras[k].rms_px:.3f} px")
        ax.axis("off")
        ax = axes[1, k]
        names = list(reg.cameras[k].per_view_rms_px)
        ax.bar(range(len(names)), [reg.cameras[k].per_view_rms_px[n] for n in names])
        ax.set_xlabel("view")
        ax.set_ylabel("reprojection RMS (px)")
        if reg.cameras[k].views_left_out:
            ax.set_title(f"left out: {', '.join(reg.cameras[k].views_left_out)}", fontsize=8)
    axes[2, 0].axis("off")
    axes[2, 0].text(
        0,
        0.5,
        f"working distance {reg.distance_mm:.0f} mm\n"
        + "\n".join(
            f"CCD {k + 2}: XOR {b:.2%} → {a:.2%}, stereo RMS {s:.3f} px"
            for k, (b, a, s) in enumerate(zip(reg.xor_before, reg.xor_after, reg.stereo_rms_px))
        ),
        fontsize=11,
        va="center",
    )
    for k in range(1, 4):
        axes[2, k].imshow(xor_image(images8[0][view], images8[k][view], *reg.maps(k + 1))[0], cmap="gray")
        axes[2, k].set_title(f"XOR CCD 1 vs registered CCD {k + 1}: {reg.xor_after[k - 1]:.2%}")
        axes[2, k].axis("off")
    fig.tight_layout()
    return save_figure(fig, path)
