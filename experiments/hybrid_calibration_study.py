"""What hybrid calibration buys: depth bias and precision with and without each part of it.

    python -m cohflash_experiments.hybrid_calibration_study [--out out/hybrid] [--size 24] [--seeds 2]

The instrument carries the errors the issue names: hybrid phase errors (0, +5°, −3°, +4°),
gains (1, 1.10, 0.95, 1.05), offsets (0, +25, −15, +10 DN), a modulation-index roll-off
f_3dB = 8 GHz (20 % at 6 GHz), sidebands, and a 1.9 m system path offset. A calibration capture
(uniform target at 30.5 m with carrier drift) is fitted by `calibrate_hybrid`; then planar
captures at the paper's link budget — static and with turbulence (0.05 rad/√frame) — are
reconstructed (ML; tracked alignment under turbulence) with: no calibration, τ_sys only,
τ_sys + hybrid, and everything (τ_sys + hybrid + modulator). Writes hybrid_study.csv / .md and
hybrid_study.png (bias and precision per case, with the CRLB).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

import cohflash_jax as cf
from cohflash_experiments import study_parser
from cohflash_jax.calibration_file import Calibration, CaptureSetup
from cohflash_jax.capture import Capture
from cohflash_jax.fileio import save_figure, write_csv
from cohflash_jax.hybrid_fit import calibrate_hybrid
from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_capture
from cohflash_jax.simulate import simulate_to_file

NOISE = ("shot_noise", "read_noise", "dark_current", "quantization")
ERRORS = ("hybrid_errors", "beta_rolloff", "sidebands")
PATH_OFFSET_M = 1.9
DISTANCE_M = 30.5


def variants(full: Calibration) -> dict[str, Calibration | None]:
    return {
        "none": None,
        "τ_sys": Calibration(None, full.system_delay_s, None),
        "τ_sys + hybrid": Calibration(full.hybrid, full.system_delay_s, None),
        "τ_sys + hybrid + modulator": full,
    }


def run(out: Path, size: int, seeds: int):
    out.mkdir(parents=True, exist_ok=True)
    inst = cf.Instrument.paper(3000, system_delay_s=2 * PATH_OFFSET_M / cf.SPEED_OF_LIGHT_M_PER_S)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        cal_capture = tmp / "calibration.h5"
        scene = cf.planar(DISTANCE_M, 0.9, tilt_m_per_fov=(2e-4, 1.3e-4), effects=NOISE + ERRORS + ("turbulence",))
        simulate_to_file(cal_capture, scene, inst, 16, 16, seed=100, progress=False)
        result = calibrate_hybrid(cal_capture, known_distance_m=DISTANCE_M, progress=False)
        doc = result["document"]
        full = Calibration.from_document(doc)
        for condition, extra, tracking in (("static", (), False), ("turbulence", ("turbulence",), True)):
            errors = {name: [] for name in variants(full)}
            sigmas = {name: [] for name in variants(full)}
            valid_frac = {name: [] for name in variants(full)}
            for seed in range(seeds):
                path = tmp / f"{condition}{seed}.h5"
                simulate_to_file(
                    path,
                    cf.planar(DISTANCE_M, 0.5, effects=NOISE + ERRORS + extra),
                    inst,
                    size,
                    size,
                    seed=seed,
                    progress=False,
                )
                with Capture(path) as cap:
                    for name, calib in variants(full).items():
                        setup = CaptureSetup.of(cap, calib)
                        outputs = reconstruct_capture(
                            cap,
                            ReconstructOptions(carrier="tracked" if tracking else "static", progress=False),
                            setup.instrument,
                            maps=setup.maps,
                        ).outputs
                        ok = outputs["valid"]
                        valid_frac[name].append(ok.mean())
                        errors[name].append(outputs["depth_m"][ok] - DISTANCE_M)
                        sigmas[name].append(outputs["sigma_m"][ok])
            for name in variants(full):
                err = np.concatenate(errors[name])
                sig = np.concatenate(sigmas[name])
                # a robust spread as well: uncalibrated turbulent pixels slip ripples
                mad = 1.4826 * np.median(np.abs(err - np.median(err))) if err.size else np.nan
                rows.append(
                    {
                        "condition": condition,
                        "calibration": name,
                        "valid_fraction": float(np.mean(valid_frac[name])),
                        "bias_mm": 1e3 * float(np.mean(err)) if err.size else np.nan,
                        "precision_mm": 1e3 * float(np.std(err)) if err.size else np.nan,
                        "robust_precision_mm": 1e3 * float(mad),
                        "median_crlb_mm": 1e3 * float(np.median(sig)) if sig.size else np.nan,
                        "pixels": int(err.size),
                    }
                )
    write_csv(out / "hybrid_study.csv", rows)
    fit = doc["fit"]
    hyb = doc["hybrid"]
    md = [
        f"Calibration capture: 16×16 px × 3000 frames, uniform target at {DISTANCE_M} m (ρ = 0.9), carrier "
        f"drift ({fit['carrier_drift']}); hybrid χ²/dof {fit['hybrid_chi2_per_dof']:.3f}.",
        "",
        "| parameter | fitted | true |",
        "|---|---|---|",
    ]
    true_phase = np.degrees(np.asarray(cf.Hybrid().phases_rad) + np.asarray(inst.errors.hybrid_phase_error_rad))
    if hyb["phases_rad"] is not None:
        for k in range(1, 4):
            md.append(
                f"| CCD {k + 1} phase (°) | {np.degrees(hyb['phases_rad'][k]):.3f} ± "
                f"{np.degrees(hyb['phases_sigma_rad'][k]):.3f} | {true_phase[k]:.3f} |"
            )
            md.append(
                f"| CCD {k + 1} gain | {hyb['relative_gains'][k]:.4f} ± {hyb['relative_gains_sigma'][k]:.4f} | "
                f"{inst.errors.hybrid_gain_factors[k]:.4f} |"
            )
    mod = doc["modulator"]
    md.append(f"| β | {mod['modulation_index']['value']:.3f} ± {mod['modulation_index']['sigma']:.3f} | 2.000 |")
    md.append(
        f"| f_3dB (GHz) | {mod['rolloff_3db_hz']['value'] / 1e9:.3f} ± {mod['rolloff_3db_hz']['sigma'] / 1e9:.3f} "
        f"| {inst.errors.modulator_rolloff_3db_hz / 1e9:.3f} |"
    )
    d = doc["system_delay_s"]
    md.append(
        f"| path offset (mm) | {d['value'] * cf.SPEED_OF_LIGHT_M_PER_S / 2 * 1e3:.3f} ± "
        f"{d['sigma'] * cf.SPEED_OF_LIGHT_M_PER_S / 2 * 1e3:.3f} | {PATH_OFFSET_M * 1e3:.3f} |"
    )
    md += [
        "",
        f"Test captures: planar {DISTANCE_M} m, paper link budget (ρ = 0.5), {size}×{size} px × {seeds} seeds, ML.",
        "",
        "| condition | calibration | valid | bias (mm) | precision (mm) | robust σ (mm) | CRLB (mm) |",
        "|---|---|---|---|---|---|---|",
    ]
    md += [
        f"| {r['condition']} | {r['calibration']} | {r['valid_fraction']:.0%} | {r['bias_mm']:+.3f} | "
        f"{r['precision_mm']:.3f} | {r['robust_precision_mm']:.3f} | {r['median_crlb_mm']:.3f} |"
        for r in rows
    ]
    (out / "hybrid_study.md").write_text("\n".join(md) + "\n")
    _plot(out / "hybrid_study.png", rows)
    print("\n".join(md))
    return rows


def _plot(path, rows):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), constrained_layout=True)
    names = list(dict.fromkeys(r["calibration"] for r in rows))
    x = np.arange(len(names))
    for j, condition in enumerate(("static", "turbulence")):
        sel = [next(r for r in rows if r["condition"] == condition and r["calibration"] == n) for n in names]
        axes[0].bar(x + 0.4 * j - 0.2, [abs(r["bias_mm"]) for r in sel], 0.4, label=condition)
        axes[1].bar(x + 0.4 * j - 0.2, [r["precision_mm"] for r in sel], 0.4, label=condition)
        axes[1].plot(
            x + 0.4 * j - 0.2, [r["median_crlb_mm"] for r in sel], "k_", ms=20, label="CRLB" if j == 0 else None
        )
    for ax, title in zip(axes, ("|bias| (mm)", "precision (mm)")):
        ax.set_yscale("log")
        ax.set_xticks(x, names, rotation=15)
        ax.set_title(title)
        ax.legend()
    fig.suptitle("What calibration buys (planar 30.5 m, paper link budget; errors as in the issue)")
    return save_figure(fig, path)


def main():
    p = study_parser(__doc__)
    p.add_argument("--out", type=Path, default=Path("out/hybrid"), help="output folder")
    p.add_argument("--size", type=int, default=24, help="pixels per side of each simulated capture")
    p.add_argument("--seeds", type=int, default=2, help="noise realisations per case")
    a = p.parse_args()
    run(a.out, a.size, a.seeds)


if __name__ == "__main__":
    main()
