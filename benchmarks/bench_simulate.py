"""Benchmark: simulate the full paper traffic capture (4 CCDs × 3000 frames × 256×320, shot +
read noise) to a file; print seconds and peak memory. Printed, never asserted.

    python benchmarks/bench_simulate.py [--out DIR] [--repeats 3] [--keep]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def one_run(out: Path) -> dict:
    import cohflash_jax as cf
    from cohflash_jax.simulate import simulate_to_file

    scene = cf.traffic(effects=("shot_noise", "read_noise", "quantization"))
    inst = cf.Instrument.paper(3000)
    t0 = time.perf_counter()
    simulate_to_file(out, scene, inst, 256, 320, seed=1, progress=False)
    seconds = time.perf_counter() - t0
    return {
        "seconds": seconds,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6,
        "file_gb": out.stat().st_size / 1e9,
    }


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--out", default=None)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(one_run(Path(args.child))))
        return
    folder = Path(args.out or tempfile.mkdtemp(prefix="cohflash-bench-"))
    folder.mkdir(parents=True, exist_ok=True)
    capture_gb = 4 * 3000 * 256 * 320 * 2 / 1e9
    runs = []
    for k in range(args.repeats):  # each in a fresh process: includes JAX start-up and compilation
        res = subprocess.run(
            [sys.executable, __file__, "--child", str(folder / "traffic.h5")],
            check=True,
            capture_output=True,
            text=True,
        )
        runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
        print(f"run {k + 1}: {runs[-1]['seconds']:.1f} s, peak RSS {runs[-1]['peak_rss_gb']:.2f} GB")
    secs = sorted(r["seconds"] for r in runs)
    rss = sorted(r["peak_rss_gb"] for r in runs)
    print(
        f"simulate traffic 4×3000×256×320 (shot + read noise, uint16): median {secs[len(secs) // 2]:.1f} s "
        f"(min {secs[0]:.1f}, max {secs[-1]:.1f}); peak RSS median {rss[len(rss) // 2]:.2f} GB "
        f"= {rss[len(rss) // 2] / capture_gb:.2f}× the uint16 capture ({capture_gb:.2f} GB); "
        f"target < 60 s and < 2× capture"
    )
    print(f"capture left at {folder / 'traffic.h5'} (input for bench_reconstruct.py --capture)")


if __name__ == "__main__":
    main()
