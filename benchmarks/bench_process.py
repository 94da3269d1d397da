"""Benchmark: what a user feels — the whole `cohflash reconstruct` process on a full capture,
timed beside two references in the same session, interleaved round by round:

- the floor: a Python process that reads every frame of the capture once (h5py, row tiles into
  one reused buffer) and nothing else;
- a plain NumPy script: read, I/Q from the nominal hybrid, the principal axis per pixel, rFFT
  over the frames, argmax → depth (no validity, no σ);
- `cohflash reconstruct CAPTURE --out … --quiet` for each method asked, with the compilation
  cache warm (a run before the rounds filled it) and cold (an empty cache folder each time);
- the same on a small capture (16×16 pixels, 3000 frames: a user's region of interest), where
  start-up is everything.

Prints the CPU model, its vector ISA (and XLA_FLAGS, e.g. --xla_cpu_max_isa=AVX2), the JAX and
jaxlib versions, each row's median over the rounds and its ratio to the floor and to the NumPy
script (ratios taken within a round, then their median: these VMs drift by tens of per cent).
Printed, never asserted.

    python benchmarks/bench_process.py [--capture FILE] [--rounds 3] [--methods ml,dft] [--no-cold]
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

from cohflash_jax.process import allocator_description
from cohflash_jax.runtime import cpu_description

READ_ONCE = """
import sys, h5py, numpy as np
with h5py.File(sys.argv[1]) as f:
    frames = f["frames"]
    _, n, h, w = frames.shape
    buf = np.empty((4, n, 32, w), frames.dtype)
    total = 0.0
    for r0 in range(0, h, 32):
        rows = min(32, h - r0)
        frames.read_direct(buf, np.s_[:, :, r0 : r0 + rows], np.s_[:, :, :rows])
        total += float(buf[0, 0, 0, 0])
print(total)
"""

NUMPY_SCRIPT = """
import sys, h5py, numpy as np
C = 299_792_458.0
with h5py.File(sys.argv[1]) as f:
    frames = f["frames"]
    freqs = f["frequencies_hz"][()]
    _, n, h, w = frames.shape
    depth = np.empty((h, w))
    for r0 in range(0, h, 32):
        v = frames[:, :, r0 : r0 + 32].astype(np.float32).reshape(4, n, -1)
        i, q = v[0] - v[2], v[1] - v[3]  # nominal hybrid: 0°, 90°, 180°, 270°
        i -= i.mean(axis=0)
        q -= q.mean(axis=0)
        # principal axis of (I, Q) per pixel: the carrier-aligned real tone
        sii, sqq, siq = (i * i).sum(0), (q * q).sum(0), (i * q).sum(0)
        angle = 0.5 * np.arctan2(2 * siq, sii - sqq)
        r = np.cos(angle) * i + np.sin(angle) * q
        spectrum = np.abs(np.fft.rfft(r * np.hanning(n)[:, None], axis=0))
        spectrum[0] = 0
        k = spectrum.argmax(axis=0)
        depth[r0 : r0 + 32] = (k / n * C / (2 * (freqs[1] - freqs[0]))).reshape(-1, w)
print(float(np.median(depth)))
"""


def timed(argv: list[str], env: dict | None = None) -> float:
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--capture", help="full-size capture (default: simulate the traffic scene, 320×256×3000)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    p.add_argument("--methods", default="ml,dft", help="comma-separated estimators to time")
    p.add_argument("--no-cold", action="store_true", help="skip the cold-cache runs")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="cohflash-bench-process-") as tmp:
        run(args, Path(tmp))


def run(args, folder: Path):
    import jax
    import jaxlib

    capture = args.capture
    cli = [sys.executable, "-m", "cohflash_jax.cli"]
    if capture is None:
        capture = str(folder / "traffic.h5")
        effects = "shot_noise,read_noise,quantization,sidebands"
        subprocess.run([*cli, "simulate", "traffic", "--out", capture, "--effects", effects, "--quiet"], check=True)
    small = str(folder / "small.h5")  # an ROI: 16×16 pixels, 3000 frames
    subprocess.run([*cli, "simulate", "planar", "--size", "16x16", "--out", small, "--quiet"], check=True)
    scripts = {"read once (floor)": READ_ONCE, "NumPy script": NUMPY_SCRIPT}
    for name, text in scripts.items():
        (folder / f"{name.split()[0]}.py").write_text(text)
    warm_cache = folder / "cache-warm"
    env_warm = os.environ | {"COHFLASH_JAX_CACHE": str(warm_cache)}
    methods = args.methods.split(",")
    for m in methods:  # fill the warm cache
        timed([*cli, "reconstruct", capture, "--out", str(folder / "d.h5"), "--method", m, "--quiet"], env_warm)
    timed([*cli, "reconstruct", small, "--out", str(folder / "s.h5"), "--quiet"], env_warm)

    rows: dict[str, list[float]] = {}
    ratios: dict[str, list[tuple[float, float]]] = {}
    for r in range(args.rounds):
        this = {}
        for name in scripts:
            this[name] = timed([sys.executable, str(folder / f"{name.split()[0]}.py"), capture])
        for m in methods:
            argv = [*cli, "reconstruct", capture, "--out", str(folder / f"d-{m}.h5"), "--method", m, "--quiet"]
            this[f"cohflash reconstruct --method {m}, warm cache"] = timed(argv, env_warm)
            if not args.no_cold:
                cold = os.environ | {"COHFLASH_JAX_CACHE": str(folder / f"cache-cold-{m}-{r}")}
                this[f"cohflash reconstruct --method {m}, cold cache"] = timed(argv, cold)
        argv = [*cli, "reconstruct", small, "--out", str(folder / "s.h5"), "--quiet"]
        this["small capture 16×16×3000 (ml), warm cache"] = timed(argv, env_warm)
        if not args.no_cold:
            this["small capture 16×16×3000 (ml), cold cache"] = timed(
                argv, os.environ | {"COHFLASH_JAX_CACHE": str(folder / f"cache-cold-small-{r}")}
            )
        for name, seconds in this.items():
            rows.setdefault(name, []).append(seconds)
            floor, numpy = this["read once (floor)"], this["NumPy script"]
            ratios.setdefault(name, []).append((seconds / floor, numpy / seconds))
        print(f"round {r + 1}: " + ", ".join(f"{k} {v:.2f} s" for k, v in this.items()), flush=True)

    print(
        f"\n{cpu_description()}; JAX {jax.__version__}, jaxlib {jaxlib.__version__}; Python {platform.python_version()}"
    )
    print(f"JAX device: {jax.devices()[0].device_kind} ({jax.default_backend()})")
    print(allocator_description())
    print(f"capture {capture}; {args.rounds} interleaved rounds, medians; whole processes")
    print(f"{'what':48s} {'seconds':>8s} {'× floor':>8s} {'NumPy ÷ it':>10s}")
    for name, values in rows.items():
        over_floor = statistics.median(a for a, _ in ratios[name])
        numpy_over = statistics.median(b for _, b in ratios[name])
        print(f"{name:48s} {statistics.median(values):8.2f} {over_floor:8.2f} {numpy_over:10.2f}")


if __name__ == "__main__":
    main()
