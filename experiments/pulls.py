"""Is `sigma_m` honest? The pull table: error/σ of valid pixels against the true depth, for
every estimator, 35, 88, 350 and 3000 frames, at closed-form SNRs from below the detection
threshold to well above it.

    python -m cohflash_experiments.pulls [--out out/pulls] [--side 64] [--seeds 2] [--quick]

Each scene is a plane of random depths uniform over the whole unambiguous window (so the
grid's quantisation, interpolation biases and the window's ends all count), simulated with
sensor noise and sidebands, the probe power set for the SNR N·a²/(4σ²) of the fundamental
(no range falloff), reconstructed with the default options. Writes pulls.csv (N, method,
SNR, valid fraction, pull mean and standard deviation, count beyond 6σ, largest |pull|),
pulls.md and pulls.png (pull standard deviation against SNR; the band is ±10 %).
"""

from __future__ import annotations

import math
from pathlib import Path

import jax
import numpy as np

import cohflash_jax as cf
from cohflash_experiments import study_parser
from cohflash_jax.constants import SPEED_OF_LIGHT_M_PER_S as C
from cohflash_jax.fileio import save_figure, write_csv
from cohflash_jax.fisher import SENSOR_NOISE, iq_noise_and_tone_amplitude
from cohflash_jax.radiometry import LinkBudget
from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array

METHODS = ("ml", "dft", "interp", "candan")


def instruments() -> dict[int, cf.Instrument]:
    out = {35: cf.Instrument.ten_hz_mode()}
    for n in (88, 350):
        out[n] = cf.Instrument(
            sweep=cf.FrequencySweep.uniform(0.1e9, 5.9e9 / (n - 1), n),
            frame_rate_hz=350.0,
            sensor=cf.Sensor(exposure_s=2e-3),
        )
    out[3000] = cf.Instrument.paper(3000)
    return out


def at_snr(inst: cf.Instrument, snr_db: float) -> cf.Instrument:
    """The instrument with the probe power that gives the fundamental an SNR of `snr_db`."""
    sigma, amp = iq_noise_and_tone_amplitude(inst, 30.5, 0.5, range_falloff=False)
    now = 10 * math.log10(inst.sweep.num_steps * amp**2 / (4 * sigma**2))
    return inst.replace(link=LinkBudget(probe_power_w=inst.link.probe_power_w * 10 ** ((snr_db - now) / 10)))


def pull_rows(n: int, inst: cf.Instrument, snrs, side: int, seeds: int) -> list[dict]:
    f = inst.sweep.frequencies_hz
    window = C / (4 * (f[1] - f[0]))
    rows = []
    for snr_db in snrs:
        pulls = {m: [] for m in METHODS}
        valid = dict.fromkeys(METHODS, 0)
        for seed in range(seeds):
            rng = np.random.default_rng(1000 * n + seed)
            depth = rng.uniform(0.0, window, (side, side))
            scene = cf.from_arrays(depth, np.full(depth.shape, 0.5), effects=SENSOR_NOISE + ("sidebands",))
            key = jax.random.key(int(10 * snr_db) + 7919 * seed)
            frames = np.asarray(cf.simulate(scene, at_snr(inst, snr_db), side, side, key))
            for m in METHODS:
                out = reconstruct_array(frames, inst, ReconstructOptions(method=m, progress=False))
                ok = out["valid"].astype(bool)
                valid[m] += int(ok.sum())
                pulls[m].append(((out["depth_m"] - depth) / out["sigma_m"])[ok])
        for m in METHODS:
            p = np.concatenate(pulls[m])
            rows.append(
                {
                    "frames": n,
                    "method": m,
                    "snr_db": snr_db,
                    "valid_fraction": valid[m] / (seeds * side * side),
                    "valid_pixels": p.size,
                    "pull_mean": float(p.mean()) if p.size else math.nan,
                    "pull_std": float(p.std()) if p.size > 1 else math.nan,
                    "beyond_6_sigma": int(np.sum(np.abs(p) > 6)),
                    "max_abs_pull": float(np.abs(p).max()) if p.size else math.nan,
                }
            )
            r = rows[-1]
            print(
                f"{n:5d} frames {m:6s} {snr_db:4.0f} dB: valid {r['valid_fraction']:6.1%}, pull std "
                f"{r['pull_std']:.3f}, mean {r['pull_mean']:+.3f}, beyond 6σ {r['beyond_6_sigma']}"
            )
    return rows


def run(out: Path, side: int, seeds: int, quick: bool):
    out.mkdir(parents=True, exist_ok=True)
    snrs = (16.0, 20.0, 30.0) if quick else (14.0, 16.0, 18.0, 20.0, 24.0, 30.0)
    rows = []
    for n, inst in instruments().items():
        rows += pull_rows(n, inst, snrs, side, seeds)
    write_csv(out / "pulls.csv", rows)
    md = [
        "| frames | method | SNR (dB) | valid | pull std | pull mean | beyond 6σ |",
        "|---:|---|---:|---:|---:|---:|---:|",
    ]
    md += [
        f"| {r['frames']} | {r['method']} | {r['snr_db']:.0f} | {r['valid_fraction']:.1%} | {r['pull_std']:.3f} | "
        f"{r['pull_mean']:+.3f} | {r['beyond_6_sigma']} |"
        for r in rows
    ]
    (out / "pulls.md").write_text("\n".join(md) + "\n")
    from cohflash_jax.fileio import headless_pyplot

    plt = headless_pyplot()

    fig, axes = plt.subplots(1, len(METHODS), figsize=(14, 3.8), sharey=True, constrained_layout=True)
    for ax, m in zip(axes, METHODS):
        for n in instruments():
            sel = [r for r in rows if r["method"] == m and r["frames"] == n]
            ax.plot([r["snr_db"] for r in sel], [r["pull_std"] for r in sel], "o-", label=f"{n} frames")
        ax.axhspan(0.9, 1.1, color="0.9")
        ax.set(title=m, xlabel="SNR of the fundamental (dB)")
    axes[0].set_ylabel("std of (depth − truth)/σ, valid pixels")
    axes[0].legend()
    save_figure(fig, out / "pulls.png")


def main():
    p = study_parser(__doc__)
    p.add_argument("--out", default="out/pulls", help="output folder")
    p.add_argument("--side", type=int, default=64, help="pixels per side of each scene")
    p.add_argument("--seeds", type=int, default=2, help="scenes per SNR")
    p.add_argument("--quick", action="store_true", help="three SNRs")
    args = p.parse_args()
    run(Path(args.out), args.side, args.seeds, args.quick)


if __name__ == "__main__":
    main()
