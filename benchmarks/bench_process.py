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

`--isas native,AVX2` times every `cohflash` row once with XLA free to use the CPU's widest vector
ISA and once held to AVX2 (`XLA_FLAGS=--xla_cpu_max_isa=AVX2`, each with a cache of its own),
within the same rounds: both are then judged against the same floor and NumPy runs, whose times
drift with the hour more than the code's. `--platforms default,cpu,cuda` does the same for the
JAX platforms a process may use (`JAX_PLATFORMS`; `default`: as the environment and `cohflash`
choose): on a GPU machine, the GPU's rows beside its host CPU's.

Prints the CPU model, its vector ISA (and XLA_FLAGS), the JAX and jaxlib versions, each row's
median over the rounds and its ratio to the floor and to the NumPy script (ratios taken within a
round, then their median: these VMs drift by tens of per cent). Each timed process starts
`--settle` seconds (default 2) after the last ends, none in the wake of the one before it.
Printed, never asserted.

    python benchmarks/bench_process.py [--capture FILE] [--rounds 3] [--methods ml,dft] [--no-cold]
                                       [--isas native,AVX2] [--platforms default,cpu] [--settle 2]
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
from typing import NamedTuple

from cohflash_jax.native import description as native_description
from cohflash_jax.process import allocator_description, compile_package_bytecode
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


# the values XLA's CPU compiler takes for --xla_cpu_max_isa (xla/backends/cpu/codegen/cpu_features.cc,
# `CpuFeatureFromString`, any case); another value it only logs, and ignores
XLA_ISAS = ("SSE4_2", "AVX", "AVX2", "AVX512", "AVX512_VNNI", "AVX512_BF16", "AMX", "AMX_FP16", "NEON", "SVE", "SVE2")


class Variant(NamedTuple):
    """How the `cohflash` rows run: the JAX platforms ("default": as the environment has them)
    and the vector ISA XLA may use ("native": as the environment has it)."""

    platforms: str
    isa: str

    def environment(self, cache: Path) -> dict:
        """This process's environment with the executable cache at `cache`, `JAX_PLATFORMS` set
        unless "default", and XLA held to the ISA unless "native" (appended to any XLA_FLAGS
        already set)."""
        env = os.environ | {"COHFLASH_JAX_CACHE": str(cache)}
        if self.platforms != "default":
            env["JAX_PLATFORMS"] = self.platforms
        if self.isa != "native":
            env["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_cpu_max_isa={self.isa}".strip()
        return env

    @property
    def label(self) -> str:
        named = [v for v, usual in ((self.platforms, "default"), (self.isa, "native")) if v != usual]
        return f" [{', '.join(named)}]" if named else ""

    @property
    def slug(self) -> str:
        return f"{self.platforms}-{self.isa}"


def platform_list(text: str) -> list[str]:
    """Comma-separated JAX platforms as `JAX_PLATFORMS` reads them (any case), each once."""
    return list(dict.fromkeys(v.strip().lower() for v in text.split(",")))


# seconds each timed process waits before it starts (`--settle`): a process that frees
# gigabytes (the NumPy script) leaves a VM returning those pages to its host for a while
# after it exits, and the process right after it ran ~4 % slower (docs/performance.md)
SETTLE_SECONDS = 2.0


def timed(argv: list[str], env: dict | None = None, settle: float = SETTLE_SECONDS) -> float:
    """Seconds of one whole process, started `settle` seconds after the previous one ended."""
    time.sleep(settle)
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--capture", help="full-size capture (default: simulate the traffic scene, 320×256×3000)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds")
    p.add_argument("--methods", default="ml,dft", help="comma-separated estimators to time")
    p.add_argument("--no-cold", action="store_true", help="skip the cold-cache runs")
    p.add_argument(
        "--settle",
        type=float,
        default=SETTLE_SECONDS,
        help="seconds to wait before each timed process, so that none starts in the wake of the last",
    )
    p.add_argument(
        "--isas",
        default="native",
        help="comma-separated vector ISAs XLA may use for the cohflash rows, in the same rounds: "
        "'native' (as the environment has it) or a --xla_cpu_max_isa value such as AVX2",
    )
    p.add_argument(
        "--platforms",
        default="default",
        help="comma-separated JAX platforms for the cohflash rows, in the same rounds: 'default' "
        "(as the environment and cohflash choose) or a JAX_PLATFORMS value such as cpu or cuda",
    )
    args = p.parse_args()
    args.platforms = platform_list(args.platforms)
    # as XLA reads them (any case), each once: "avx2,AVX2" is one ISA, timed once
    named = (isa.strip() for isa in args.isas.split(","))
    args.isas = list(dict.fromkeys(isa if isa == "native" else isa.upper() for isa in named))
    unknown = [isa for isa in args.isas if isa != "native" and isa not in XLA_ISAS]
    if unknown:
        p.error(f"--isas: unknown {', '.join(unknown)}; use 'native' or one of {', '.join(XLA_ISAS)}")
    with tempfile.TemporaryDirectory(prefix="cohflash-bench-process-") as tmp:
        run(args, Path(tmp))


def run(args, folder: Path):
    import jax
    import jaxlib

    bytecode = compile_package_bytecode()  # the package as an install leaves it, before any timing

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
    variants = [Variant(platforms, isa) for platforms in args.platforms for isa in args.isas]
    env_warm = {v: v.environment(folder / f"cache-warm-{v.slug}") for v in variants}
    methods = args.methods.split(",")
    for v in variants:  # fill the warm caches
        for m in methods:
            argv = [*cli, "reconstruct", capture, "--out", str(folder / "d.h5"), "--method", m, "--quiet"]
            timed(argv, env_warm[v], settle=0)
        timed([*cli, "reconstruct", small, "--out", str(folder / "s.h5"), "--quiet"], env_warm[v], settle=0)

    rows: dict[str, list[float]] = {}
    ratios: dict[str, list[tuple[float, float]]] = {}
    for r in range(args.rounds):
        this = {}
        for name in scripts:
            this[name] = timed([sys.executable, str(folder / f"{name.split()[0]}.py"), capture], settle=args.settle)
        for v in variants:
            cold = lambda what, v=v, r=r: v.environment(folder / f"cache-cold-{what}-{v.slug}-{r}")
            for m in methods:
                argv = [*cli, "reconstruct", capture, "--out", str(folder / f"d-{m}.h5"), "--method", m, "--quiet"]
                this[f"cohflash reconstruct --method {m}, warm cache{v.label}"] = timed(argv, env_warm[v], args.settle)
                if not args.no_cold:
                    this[f"cohflash reconstruct --method {m}, cold cache{v.label}"] = timed(argv, cold(m), args.settle)
            argv = [*cli, "reconstruct", small, "--out", str(folder / "s.h5"), "--quiet"]
            this[f"small capture 16×16×3000 (ml), warm cache{v.label}"] = timed(argv, env_warm[v], args.settle)
            if not args.no_cold:
                this[f"small capture 16×16×3000 (ml), cold cache{v.label}"] = timed(argv, cold("small"), args.settle)
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
    print(native_description())
    print(bytecode)
    print(
        f"capture {capture}; {args.rounds} interleaved rounds, medians; whole processes, "
        f"each started {args.settle:g} s after the last"
    )
    print(f"{'what':56s} {'seconds':>8s} {'× floor':>8s} {'NumPy ÷ it':>10s}")
    for name, values in rows.items():
        over_floor = statistics.median(a for a, _ in ratios[name])
        numpy_over = statistics.median(b for _, b in ratios[name])
        print(f"{name:56s} {statistics.median(values):8.2f} {over_floor:8.2f} {numpy_over:10.2f}")


if __name__ == "__main__":
    main()
