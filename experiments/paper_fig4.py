"""The paper's Fig. 4c, 4d and 4f as design sweeps: precision against distance, the
bandwidth × distance map, and precision against frame count / acquisition time.

    python -m cohflash_experiments.paper_fig4 [--out out/fig4] [--mc-trials 256] [--workers 1]

Each panel is a `cohflash sweep` (autodiff-Fisher CRLB, phase-locked and frequency-only) with
Monte Carlo (simulate + ML reconstruct) at chosen points; CSVs and PNGs go to --out, with
fig4.md comparing our numbers with the paper's. Resumable: rerunning skips finished points.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cohflash_experiments import study_parser
from cohflash_jax.design import parse_axis, plot_sweep, run_sweep

PAPER = {"crlb_30m_mm": 0.079, "measured_30m_mm": 0.47, "frames_35_mm": 1.33, "frames_3500_mm": 0.35}


def run(out: Path, mc_trials: int, workers: int):
    out.mkdir(parents=True, exist_ok=True)
    # 4c: precision against distance at 15.86 mW (echo ∝ 1/d²), paper sweep
    axes_c = [parse_axis("distance_m=10:240:24")]
    rows_c = run_sweep(
        axes_c,
        out / "fig4c.csv",
        mc_points=[{"distance_m": d} for d in (30.0, 60.0, 120.0)],
        mc_trials=mc_trials,
        workers=workers,
    )
    plot_sweep(rows_c, ["distance_m"], out / "fig4c.png")
    # 4d: bandwidth 6–30 GHz × distance 30–240 m, 3000 steps
    axes_d = [parse_axis("bandwidth_ghz=6:30:13"), parse_axis("distance_m=30:240:15")]
    rows_d = run_sweep(axes_d, out / "fig4d.csv", fixed={"num_steps": 3000})
    plot_sweep(rows_d, ["bandwidth_ghz", "distance_m"], out / "fig4d.png")
    # 4f: 35 … 3500 frames at 350 frames/s (2.5 ms exposure), the same 0.1–6.0 GHz band; the
    # unambiguous interval c/(4Δf) shrinks to 0.44 m at 35 frames, so the target sits at 0.3 m
    # within it with the 30.5 m link budget (range_falloff = 0)
    axes_f = [parse_axis("num_steps=35,88,175,350,700,1750,3500")]
    fixed_f = {
        "bandwidth_ghz": 5.91,
        "frame_rate_hz": 350.0,
        "exposure_ms": 2.5,
        "distance_m": 0.3,
        "range_falloff": 0.0,
    }
    rows_f = run_sweep(axes_f, out / "fig4f.csv", fixed=fixed_f, mc_all=True, mc_trials=mc_trials, workers=workers)
    plot_sweep(rows_f, ["num_steps"], out / "fig4f.png")

    def at(rows, **kv):
        return next(r for r in rows if all(abs(float(r[k]) - v) < 1e-9 for k, v in kv.items()))

    c30 = at(rows_c, distance_m=30.0)
    f35, f3500 = at(rows_f, num_steps=35.0), at(rows_f, num_steps=3500.0)
    d = np.array([[float(r["bandwidth_ghz"]), float(r["distance_m"]), float(r["crlb_mm"])] for r in rows_d])
    md = [
        "| quantity | paper | cohflash (CRLB, phase-locked) | cohflash (Monte Carlo, ML) |",
        "|---|---|---|---|",
        f"| precision at 30 m, 3000 frames, 15.86 mW | CRLB {PAPER['crlb_30m_mm']} mm, measured "
        f"{PAPER['measured_30m_mm']} mm | {float(c30['crlb_mm']):.3f} mm (frequency-only "
        f"{float(c30['crlb_frequency_only_mm']):.3f}) | {float(c30.get('mc_precision_mm', np.nan)):.3f} mm |",
        f"| 35 frames at 350 Hz (0.1 s) | {PAPER['frames_35_mm']} mm | {float(f35['crlb_mm']):.3f} mm | "
        f"{float(f35.get('mc_precision_mm', np.nan)):.3f} mm ({float(f35['mc_valid_fraction']):.0%} of pixels "
        "above the 14 dB validity threshold) |",
        f"| 3500 frames at 350 Hz (10 s) | {PAPER['frames_3500_mm']} mm | {float(f3500['crlb_mm']):.3f} mm | "
        f"{float(f3500.get('mc_precision_mm', np.nan)):.3f} mm |",
        f"| Fig. 4d range (6–30 GHz × 30–240 m) | — | {d[:, 2].min():.4f} … {d[:, 2].max():.3f} mm | — |",
        "",
        "Trends reproduced: precision worsens with distance as the echo falls as 1/d² (4c: ∝ d, "
        "shot-noise limited by the reference); improves as 1/B with bandwidth (4d); and improves with "
        "frame count (4f: ∝ 1/√N at a fixed band). Below ~350 frames most pixels fall under the ML "
        "fit's 14 dB validity threshold at this link budget and are flagged (fig4f.csv: mc_valid_fraction).",
        "Why the numbers differ: the paper's Eq. (4) is a frequency-only bound with its own SNR "
        "definition; ours is the phase-locked bound of the full four-CCD model with the sensor noise "
        "budget of `Sensor()` (dark current 10⁴ e/s, 30 e read noise — plausible values, not the "
        "paper's camera), so 0.079 mm vs ours. The paper's measured 0.47 mm includes speckle and "
        "processing losses that the planar Monte Carlo here leaves out; its frame-count study "
        "(1.33 → 0.35 mm, ∝ N^-0.29) falls more slowly than 1/√N, as a speckle or systematic floor "
        "would make it.",
    ]
    (out / "fig4.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


def main():
    p = study_parser(__doc__)
    p.add_argument("--out", type=Path, default=Path("out/fig4"), help="output folder")
    p.add_argument("--mc-trials", type=int, default=256, help="pixels per Monte Carlo point")
    p.add_argument("--workers", type=int, default=1, help="processes for the Monte Carlo points")
    a = p.parse_args()
    run(a.out, a.mc_trials, a.workers)


if __name__ == "__main__":
    main()
