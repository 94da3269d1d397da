"""Benchmark: on a GPU machine, which is quicker for a whole `cohflash reconstruct` process, the
GPU or its host's CPU, by capture size: the measurement behind `process.GPU_MIN_CAPTURE_BYTES`
(below it, `cohflash reconstruct` runs on the CPU alone).

Simulates the planar scene at each `--sizes` (3000 frames; `--capture` is timed as well), then
times interleaved rounds of whole processes with each `--platforms` value as `JAX_PLATFORMS`
('default': as the environment has it and `cohflash` chooses), with a warm cache (a run before the
rounds filled it) and, with `--cold`, an empty one. Also times the imports and the backend start
alone (`import cohflash_jax; jax.devices()`, no teardown) per platform. Prints medians with the
CPU model, JAX versions and the devices. Printed, never asserted.

    python benchmarks/bench_platforms.py [--capture FILE] [--sizes 16x16,64x64,128x128]
                                         [--platforms cuda,cpu] [--rounds 2] [--cold]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from bench_process import Variant, platform_list, timed

from cohflash_jax.runtime import cpu_description

# ended as `cohflash` ends, without the interpreter's teardown
STARTUP = "import os, cohflash_jax, jax; jax.devices(); os._exit(0)"


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--capture", help="a capture to time as well (e.g. the full traffic scene)")
    p.add_argument("--sizes", default="16x16,64x64,128x128", help="planar captures to simulate, HxW, 3000 frames")
    p.add_argument("--platforms", default="cuda,cpu", help="JAX_PLATFORMS values to compare ('default': as set here)")
    p.add_argument("--rounds", type=int, default=2, help="interleaved rounds")
    p.add_argument("--cold", action="store_true", help="also time each capture with an empty cache")
    args = p.parse_args()
    platforms = platform_list(args.platforms)
    with tempfile.TemporaryDirectory(prefix="cohflash-bench-platforms-") as tmp:
        run(args, platforms, Path(tmp))


def run(args, platforms: list[str], folder: Path):
    import jax
    import jaxlib

    cli = [sys.executable, "-m", "cohflash_jax.cli"]
    captures = {}
    for size in args.sizes.split(","):
        path = folder / f"planar-{size}.h5"
        subprocess.run([*cli, "simulate", "planar", "--size", size, "--out", str(path), "--quiet"], check=True)
        captures[size] = path
    if args.capture:
        captures[Path(args.capture).name] = Path(args.capture)
    warm = {v: Variant(v, "native").environment(folder / f"cache-warm-{v}") for v in platforms}
    command = lambda path: [*cli, "reconstruct", str(path), "--out", str(folder / "d.h5"), "--quiet"]
    for v in platforms:  # fill the warm caches
        for path in captures.values():
            timed(command(path), warm[v])

    rows: dict[str, list[float]] = {}
    for r in range(args.rounds):
        this = {}
        for v in platforms:
            this[f"imports and backend start [{v}]"] = timed([sys.executable, "-c", STARTUP], warm[v])
        for name, path in captures.items():
            for v in platforms:
                this[f"{name} ({path.stat().st_size / 2**20:.0f} MB), warm [{v}]"] = timed(command(path), warm[v])
                if args.cold:
                    cold = Variant(v, "native").environment(folder / f"cache-cold-{name}-{v}-{r}")
                    this[f"{name} ({path.stat().st_size / 2**20:.0f} MB), cold [{v}]"] = timed(command(path), cold)
        for name, seconds in this.items():
            rows.setdefault(name, []).append(seconds)
        print(f"round {r + 1}: " + ", ".join(f"{k} {s:.2f} s" for k, s in this.items()), flush=True)

    print(
        f"\n{cpu_description()}; JAX {jax.__version__}, jaxlib {jaxlib.__version__}; Python {platform.python_version()}"
    )
    print(f"JAX devices: {', '.join(f'{d.device_kind} ({d.platform})' for d in jax.devices())}")
    print(f"{args.rounds} interleaved rounds, medians; whole processes (`cohflash reconstruct … --quiet`)")
    print(f"{'what':52s} {'seconds':>8s}")
    for name, values in rows.items():
        print(f"{name:52s} {statistics.median(values):8.2f}")


if __name__ == "__main__":
    main()
