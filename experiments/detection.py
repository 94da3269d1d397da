"""Detection with a stated false-alarm probability (`cohflash_jax.estimate.detection`):
the rate at which pure noise is detected, against the rate stated, and the detection
probability against SNR (the threshold curve), for 35, 88, 350 and 3000 frames and a sparse
non-uniform schedule.

    python -m cohflash_experiments.detection [--out out/detection] [--pixels 1000000] [--quick]

Pure noise: white Gaussian frames on the four CCDs (nominal hybrid), reconstructed with
`--method dft` (the test lives in the coarse stage, shared by every estimator). A pixel counts
as a false alarm where its `detection_ratio` exceeds 1 at the stated α; the rate at several α
comes from one set of pixels (the ratio scales with the threshold). Writes false_alarm.csv
(N, schedule, α, pixels, detections, rate, 95 % upper confidence limit), detection.csv and
detection.png (the fraction of a planar target's pixels detected against the closed-form SNR
N·a²/(4σ²) of the fundamental, at α = 1e-6).
"""

from __future__ import annotations

import math
from pathlib import Path

import jax
import numpy as np

import cohflash_jax as cf
from cohflash_experiments import study_parser
from cohflash_jax.estimate.detection import DEFAULT_FALSE_ALARM, share_threshold
from cohflash_jax.fileio import save_figure, write_csv
from cohflash_jax.fisher import SENSOR_NOISE, iq_noise_and_tone_amplitude
from cohflash_jax.radiometry import PAPER_PROBE_POWER_W, LinkBudget
from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array

ALPHAS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6)


def instruments() -> dict[str, cf.Instrument]:
    """The frame counts of the issue, each a sweep over ~0.1–6 GHz, and a sparse schedule."""
    rng = np.random.default_rng(0)
    sparse = 0.1e9 + 1.97e6 * np.sort(rng.choice(3000, 400, replace=False))
    out = {"35 (10 Hz mode)": cf.Instrument.ten_hz_mode()}
    for n in (88, 350):
        out[str(n)] = cf.Instrument(
            sweep=cf.FrequencySweep.uniform(0.1e9, 5.9e9 / (n - 1), n),
            frame_rate_hz=350.0,
            sensor=cf.Sensor(exposure_s=2e-3),
        )
    out["3000"] = cf.Instrument.paper(3000)
    out["400 sparse"] = cf.Instrument(sweep=cf.FrequencySweep(sparse))
    return out


def clopper_pearson_upper(count: int, total: int, level: float = 0.95) -> float:
    """One-sided upper confidence limit of a binomial rate (bisection on the binomial tail)."""
    lo, hi = count / total, 1.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        # P(X ≤ count | mid), summed in logs
        logs = [
            math.lgamma(total + 1)
            - math.lgamma(k + 1)
            - math.lgamma(total - k + 1)
            + k * math.log(mid)
            + (total - k) * math.log1p(-mid)
            for k in range(count + 1)
        ]
        top = max(logs)
        cdf = math.exp(top) * sum(math.exp(v - top) for v in logs)
        lo, hi = (mid, hi) if cdf > 1 - level else (lo, mid)
    return hi


def false_alarm_rows(name: str, inst: cf.Instrument, pixels: int, seed: int) -> list[dict]:
    """Detections among `pixels` pure-noise pixels at each α (the same noise for every α). The
    limits grow as α falls, so a pixel detected at a smaller α is detected at the largest: only
    those are reconstructed again at the smaller ones."""
    n = inst.sweep.num_steps
    side = 128 if n <= 400 else 64
    key = jax.random.key(seed)
    first, rest = ALPHAS[0], ALPHAS[1:]
    kept, total = [], 0
    for k in range(-(-pixels // (side * side))):
        frames = np.asarray(400.0 + 20.0 * jax.random.normal(jax.random.fold_in(key, k), (4, n, side, side)))
        out = reconstruct_array(frames, inst, ReconstructOptions(method="dft", progress=False, false_alarm=first))
        kept.append(frames[:, :, out["detection_ratio"] > 1])
        total += side * side
    hits = np.concatenate(kept, axis=-1)[:, :, None, :]
    counts = {first: hits.shape[-1]}
    for alpha in rest:
        if hits.shape[-1] == 0:
            counts[alpha] = 0
            continue
        out = reconstruct_array(hits, inst, ReconstructOptions(method="dft", progress=False, false_alarm=alpha))
        counts[alpha] = int(np.sum(out["detection_ratio"] > 1))
    return [
        {
            "frames": n,
            "schedule": name,
            "alpha": alpha,
            "pixels": total,
            "detections": c,
            "rate": c / total,
            "ci95_upper": clopper_pearson_upper(c, total),
        }
        for alpha, c in counts.items()
    ]


def detection_rows(name: str, inst: cf.Instrument, size: int, seed: int) -> list[dict]:
    """Fraction of a planar target's pixels detected against the closed-form SNR, probe power
    stepped so the SNR spans the threshold."""
    rows = []
    n = inst.sweep.num_steps
    for factor_db in np.arange(-20.0, 14.0, 2.0):
        power = PAPER_PROBE_POWER_W * 10 ** (factor_db / 10) * (3000 / n)
        probe = inst.replace(link=LinkBudget(probe_power_w=power))
        sigma, amp = iq_noise_and_tone_amplitude(probe, 30.5, 0.5)
        snr_db = 10 * math.log10(n * amp**2 / (4 * sigma**2))
        frames = cf.simulate(cf.planar(effects=SENSOR_NOISE), probe, size, size, jax.random.key(seed))
        out = reconstruct_array(frames, inst, ReconstructOptions(method="dft", progress=False))
        rows.append(
            {"frames": n, "schedule": name, "snr_db": snr_db, "detected": float(np.mean(out["detection_ratio"] > 1))}
        )
    return rows


def run(out: Path, pixels: int, quick: bool):
    out.mkdir(parents=True, exist_ok=True)
    fa, pd = [], []
    for k, (name, inst) in enumerate(instruments().items()):
        fa += false_alarm_rows(name, inst, pixels, seed=k)
        pd += detection_rows(name, inst, 8 if quick else 24, seed=100 + k)
        for r in fa[-len(ALPHAS) :]:
            print(
                f"{name:16s} α {r['alpha']:.0e}: {r['detections']} of {r['pixels']} pure-noise pixels detected, "
                f"rate {r['rate']:.2e} (95 % upper limit {r['ci95_upper']:.2e})"
            )
    write_csv(out / "false_alarm.csv", fa)
    write_csv(out / "detection.csv", pd)
    from cohflash_jax.fileio import headless_pyplot

    plt = headless_pyplot()

    fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
    for name in dict.fromkeys(r["schedule"] for r in pd):
        rows = [r for r in pd if r["schedule"] == name]
        ax.plot([r["snr_db"] for r in rows], [r["detected"] for r in rows], "o-", label=f"{name} frames")
    ax.set(
        xlabel="SNR of the fundamental, N·a²/(4σ²) (dB)",
        ylabel="fraction detected",
        title=f"detection at a false-alarm probability of {DEFAULT_FALSE_ALARM:g} per pixel",
    )
    ax.grid(True, alpha=0.3)
    ax.legend()
    save_figure(fig, out / "detection.png")
    for n in (35, 88, 350, 3000):
        print(
            f"{n} frames: a two-bin window must hold {share_threshold(4, n, DEFAULT_FALSE_ALARM / (n // 2)):.4f} of "
            "the total I/Q energy"
        )


def main():
    p = study_parser(__doc__)
    p.add_argument("--out", default="out/detection", help="output folder")
    p.add_argument("--pixels", type=int, default=1_000_000, help="pure-noise pixels per schedule")
    p.add_argument("--quick", action="store_true", help="small detection curves (the false-alarm pixels as asked)")
    args = p.parse_args()
    run(Path(args.out), args.pixels, args.quick)


if __name__ == "__main__":
    main()
