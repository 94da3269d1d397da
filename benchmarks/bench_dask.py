"""Benchmark: reconstruction scaled out on Dask (issue #24). Printed, never asserted.

1. The full capture (320×256×3000), whole processes, interleaved round by round with the
   compilation cache warm: reading it once (the floor), the single-process CLI, and
   `cohflash reconstruct --scheduler processes --workers K` for K = 1, 2 (the CLI starts and
   stops its own local cluster: that start-up is in the figure).
2. A simulated 100-megapixel reconstruction: tiles of 32×320 pixels × 3000 frames (one full
   capture's tile) are simulated inside the workers and reconstructed there, so nothing of that
   size touches the disk. Per worker-tile: the reconstruction's time (after each worker's first
   tile, which compiles or loads its programs) and the simulation's (a stand-in for the read);
   the peak memory of each worker; and the projected wall time of 100 MPx on N workers from the
   measured per-tile time.

    python benchmarks/bench_dask.py [--capture FILE] [--rounds 3] [--tiles-per-worker 4]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cohflash_jax.runtime import cpu_description
from cohflash_jax.scaleout import available_cores

READ_ONCE = """
import sys, h5py, numpy as np
with h5py.File(sys.argv[1]) as f:
    frames = f["frames"]
    _, n, h, w = frames.shape
    buf = np.empty((4, n, 32, w), frames.dtype)
    for r0 in range(0, h, 32):
        rows = min(32, h - r0)
        frames.read_direct(buf, np.s_[:, :, r0 : r0 + rows], np.s_[:, :, :rows])
"""

TILE_ROWS, TILE_COLS, FRAMES = 32, 320, 3000
TARGET_PIXELS = 100e6


def timed(argv, env=None) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def synthetic_tile(seed: int) -> dict:
    """A worker's task: simulate one tile (a tilted plane at 30.5 m) and reconstruct it."""
    import jax
    import numpy as np

    import cohflash_jax as cf
    from cohflash_jax.reconstruct import ReconstructOptions, reconstruct_array
    from cohflash_jax.scaleout import prepare_worker, worker_peak_memory_bytes

    prepare_worker()
    instrument = cf.Instrument.paper(FRAMES)
    rows, cols = np.mgrid[0:TILE_ROWS, 0:TILE_COLS]
    depth = 30.5 + 1e-3 * cols + 1e-2 * rows + 0.1 * (seed % 7)
    scene = cf.from_arrays(depth, np.full(depth.shape, 0.5), effects=("shot_noise", "read_noise", "quantization"))
    t0 = time.perf_counter()
    frames = cf.simulate(scene, instrument, TILE_ROWS, TILE_COLS, jax.random.key(seed))
    t1 = time.perf_counter()
    out = reconstruct_array(frames, instrument, ReconstructOptions(progress=False))
    t2 = time.perf_counter()
    return {
        "pid": os.getpid(),
        "simulate_s": t1 - t0,
        "reconstruct_s": t2 - t1,
        "valid": float(out["valid"].mean()),
        "peak_bytes": worker_peak_memory_bytes(),
    }


def synthetic(workers: int, tiles_per_worker: int) -> dict:
    from distributed import wait

    from cohflash_jax.dask_cluster import dask_client
    from cohflash_jax.scaleout import core_sets

    with dask_client("processes", workers) as client:
        warm = client.map(synthetic_tile, range(workers), pure=False)  # each worker's first tile
        wait(warm)
        first = [f.result() for f in warm]
        t0 = time.perf_counter()
        futures = client.map(synthetic_tile, range(100, 100 + workers * tiles_per_worker), pure=False)
        results = [f.result() for f in futures]
        wall = time.perf_counter() - t0
    peaks: dict[int, int] = {}
    for r in first + results:
        peaks[r["pid"]] = max(peaks.get(r["pid"], 0), r["peak_bytes"])
    return {
        "workers": workers,
        "cores_each": len(core_sets(workers)[0]),
        "tiles": len(results),
        "wall_s": wall,
        "first_tile_s": statistics.median(r["simulate_s"] + r["reconstruct_s"] for r in first),
        "reconstruct_s": statistics.median(r["reconstruct_s"] for r in results),
        "simulate_s": statistics.median(r["simulate_s"] for r in results),
        "valid": statistics.mean(r["valid"] for r in results),
        "peak_mib": max(peaks.values()) / 2**20,
    }


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--capture", help="full-size capture (default: simulate the traffic scene, 320×256×3000)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds of part 1")
    p.add_argument("--tiles-per-worker", type=int, default=4, help="part 2: timed tiles a worker")
    p.add_argument("--skip-capture", action="store_true", help="part 2 only")
    args = p.parse_args()
    import jax
    import jaxlib

    print(
        f"{cpu_description()}; JAX {jax.__version__}, jaxlib {jaxlib.__version__}; Python {platform.python_version()}"
    )
    with tempfile.TemporaryDirectory(prefix="cohflash-bench-dask-") as tmp:
        if not args.skip_capture:
            whole_capture(args, Path(tmp))
    print("\nsimulated 100-megapixel reconstruction: tiles of 32×320 px × 3000 frames, made inside the workers")
    print(
        f"{'workers':>7s} {'tiles':>5s} {'wall s':>7s} {'tiles/s':>7s} {'reconstruct s/tile':>18s} "
        f"{'simulate s/tile':>15s} {'first tile s':>12s} {'valid':>6s} {'peak MiB/worker':>15s}"
    )
    per_tile = None
    for workers in sorted({1, len(available_cores())}):
        r = synthetic(workers, args.tiles_per_worker)
        print(
            f"{r['workers']:7d} {r['cores_each']:10d} {r['tiles']:5d} {r['wall_s']:7.1f} "
            f"{r['tiles'] / r['wall_s']:7.2f} "
            f"{r['reconstruct_s']:18.2f} {r['simulate_s']:15.2f} {r['first_tile_s']:12.1f} {r['valid']:6.1%} "
            f"{r['peak_mib']:15.0f}"
        )
        if r["cores_each"] == 1:
            per_tile = r["reconstruct_s"]
    tiles = TARGET_PIXELS / (TILE_ROWS * TILE_COLS)
    if per_tile is None:
        return
    print(
        f"\n100 MPx = {tiles:.0f} tiles; reconstruction alone at {per_tile:.2f} s a worker-tile (a worker on 1 core):"
    )
    for n in (1, 16, 64, 256, 1024):
        print(f"  {n:5d} workers: {tiles * per_tile / n / 60:8.1f} min (perfect scaling; reads not included)")


def whole_capture(args, folder: Path):
    cli = [sys.executable, "-m", "cohflash_jax.cli"]
    capture = args.capture
    if capture is None:
        capture = str(folder / "traffic.h5")
        effects = "shot_noise,read_noise,quantization,sidebands"
        subprocess.run([*cli, "simulate", "traffic", "--out", capture, "--effects", effects, "--quiet"], check=True)
    (folder / "read.py").write_text(READ_ONCE)
    env = os.environ | {"COHFLASH_JAX_CACHE": str(folder / "cache")}
    variants = {
        "single process (CLI)": [],
        "Dask, 1 local worker": ["--scheduler", "processes", "--workers", "1"],
        "Dask, 2 local workers": ["--scheduler", "processes", "--workers", "2"],
    }
    out = str(folder / "d.h5")
    for extra in variants.values():  # fill the cache (the workers share it)
        timed([*cli, "reconstruct", capture, "--out", out, "--quiet", *extra], env)
    rows: dict[str, list[float]] = {}
    for r in range(args.rounds):
        this = {"read once (floor)": timed([sys.executable, str(folder / "read.py"), capture])}
        for name, extra in variants.items():
            this[name] = timed([*cli, "reconstruct", capture, "--out", out, "--quiet", *extra], env)
        for k, v in this.items():
            rows.setdefault(k, []).append(v)
        print(f"round {r + 1}: " + ", ".join(f"{k} {v:.2f} s" for k, v in this.items()), flush=True)
    print(f"\nfull capture {capture}: whole processes, warm cache, medians of {args.rounds} interleaved rounds")
    single = statistics.median(rows["single process (CLI)"])
    for k, v in rows.items():
        m = statistics.median(v)
        print(f"  {k:28s} {m:7.2f} s   {m / single:5.2f}× the single process")


if __name__ == "__main__":
    main()
