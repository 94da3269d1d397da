"""Coverage and width of emcee depth intervals against simulated truth, and the time per pixel
against the ML fit (a row of the accuracy-versus-time table).

    python -m cohflash_experiments.posterior_coverage [--out out/posterior] [--pixels 400] [--reflectance 0.5]
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

import cohflash_jax as cf
from cohflash_experiments import study_parser
from cohflash_jax.fileio import write_csv
from cohflash_jax.reconstruct import ReconstructOptions, build_plan, process_tile
from cohflash_jax.uncertainty import sample_pixels

NOISE = ("shot_noise", "read_noise", "dark_current", "quantization")


def run(out: Path, pixels: int, reflectance: float, seed: int):
    out.mkdir(parents=True, exist_ok=True)
    inst = cf.Instrument.paper(3000)
    width = 20
    height = -(-pixels // width)
    frames = cf.simulate(cf.planar(reflectance=reflectance, effects=NOISE), inst, height, width, jax.random.key(seed))
    options = ReconstructOptions(method="ml")
    plan = build_plan(inst, options, saturation_dn=float(inst.sensor.adc_max_dn))
    x = jax.numpy.asarray(frames.reshape(4, 3000, -1))
    jax.block_until_ready(process_tile(plan, x, None))
    t0 = time.perf_counter()
    jax.block_until_ready(process_tile(plan, x, None))
    ml_per_pixel = (time.perf_counter() - t0) / x.shape[-1]
    t0 = time.perf_counter()
    posts = sample_pixels(inst, frames, rng=np.random.default_rng(seed))
    rows = [
        {
            "pixel": p,
            "covered68": post.covers(30.5, 68),
            "covered95": post.covers(30.5, 95),
            "half68_over_crlb": (post.interval68_m[1] - post.interval68_m[0]) / 2 / post.crlb_m,
            "converged": post.converged,
            "multimodal": post.multimodal,
            "steps": post.steps,
            "tau": post.autocorr_steps,
        }
        for p, post in enumerate(posts)
    ]
    seconds = (time.perf_counter() - t0) / len(rows)
    write_csv(out / "coverage.csv", rows)
    c68 = np.mean([r["covered68"] for r in rows])
    c95 = np.mean([r["covered95"] for r in rows])
    n = len(rows)
    print(
        f"{n} pixels, reflectance {reflectance}: 68 % coverage {c68:.3f} (±{np.sqrt(0.68 * 0.32 / n):.3f} binomial), "
        f"95 % coverage {c95:.3f} (±{np.sqrt(0.95 * 0.05 / n):.3f}); median 68 % half-width / CRLB "
        f"{np.median([r['half68_over_crlb'] for r in rows]):.3f}; "
        f"converged {np.mean([r['converged'] for r in rows]):.0%}; "
        f"multimodal {np.mean([r['multimodal'] for r in rows]):.0%}; "
        f"median τ {np.median([r['tau'] for r in rows]):.0f} steps"
    )
    print(
        f"time per pixel: emcee {seconds:.2f} s (median steps {np.median([r['steps'] for r in rows]):.0f}) "
        f"vs ML fit {ml_per_pixel * 1e6:.0f} µs → {seconds / ml_per_pixel:,.0f}× the ML cost"
    )


def main():
    p = study_parser(__doc__)
    p.add_argument("--out", default="out/posterior", help="output folder")
    p.add_argument("--pixels", type=int, default=400, help="simulated pixels sampled with emcee")
    p.add_argument("--reflectance", type=float, default=0.5, help="target reflectance (sets the SNR)")
    p.add_argument("--seed", type=int, default=7, help="random seed")
    args = p.parse_args()
    run(Path(args.out), args.pixels, args.reflectance, args.seed)


if __name__ == "__main__":
    main()
