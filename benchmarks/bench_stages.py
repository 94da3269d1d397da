"""Benchmark: where the time of a whole `cohflash reconstruct` process goes, stage by stage.

Each round runs two fresh processes on the same capture (in the page cache) and the same
compilation cache (warm: a run before the rounds fills it; `--cold` empties it each round):

1. the whole command, timed from outside, and from inside: interpreter start and exit (the rest;
   it ends as `cohflash` does, without the interpreter's teardown),
   imports, backend start, then the command with JAX's own compile events (tracing, lowering,
   XLA compile, XLA cache loads) and the executable cache's loads and compiles; the command's
   own reconstruction seconds; the rest of the command (open, provenance, write, summary);
2. the same reconstruction twice in one process: the second run is the steady state (read and
   compute), so first − second − compile events is the first run's one-time cost (first touch
   of memory, thread pools, device placement); then the steady state split into a read-only
   pass over the file, and the compiled programs one by one on one sub-tile (the data checks
   with the carrier axis, the rotated sequence, each computing I/Q from the frames; the coarse
   FFT stage; the whole inversion: ML = inversion − coarse), scaled to the capture, as one
   device runs them, the native I/Q kernel that replaces the first two where it is built
   (`cohflash_jax.native`), and the depth file write.

Prints medians over rounds with the CPU model, ISA and JAX versions. Printed, never asserted.

    python benchmarks/bench_stages.py --capture FILE [--method ml] [--rounds 3] [--cold]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from cohflash_jax.native import description as native_description
from cohflash_jax.process import allocator_description, allocator_environment, compile_package_bytecode
from cohflash_jax.runtime import cpu_description

WHOLE = r"""
import json, sys, time
t0 = time.perf_counter()
# as `cohflash reconstruct` starts: the package's import loads the last run's programs ahead
sys.orig_argv = [sys.executable, "-m", "cohflash_jax.cli", "reconstruct", sys.argv[1]]
import cohflash_jax.cli as cli
t1 = time.perf_counter()
import jax, jax.monitoring as mon
from cohflash_jax.runtime import EXECUTABLES, cli_cpu_streams, exit_process, use_cpu_streams
use_cpu_streams(cli_cpu_streams("reconstruct"))
jax.devices()
t2 = time.perf_counter()
events = {}
def listen(event, duration, **_):
    events[event] = events.get(event, 0.0) + duration
mon.register_event_duration_secs_listener(listen)
capture, out, method = sys.argv[1:4]
import io, contextlib
text = io.StringIO()
with contextlib.redirect_stdout(text):
    assert cli.main(["reconstruct", capture, "--out", out, "--method", method, "--quiet"]) == 0
t3 = time.perf_counter()
seconds = float(text.getvalue().rsplit("reconstruction ", 1)[1].split()[0])
print(json.dumps({
    "imports": t1 - t0, "backend start": t2 - t1, "command": t3 - t2, "reconstruction": seconds,
    "tracing": events.get("/jax/core/compile/jaxpr_trace_duration", 0.0),
    "lowering": events.get("/jax/core/compile/jaxpr_to_mlir_module_duration", 0.0),
    "XLA compile or cache load": events.get("/jax/core/compile/backend_compile_duration", 0.0),
    "executable cache load": EXECUTABLES.load_seconds, "executable compile": EXECUTABLES.compile_seconds,
}))
exit_process(0)  # as `cohflash` ends: no interpreter teardown
"""

STEADY = r"""
import json, sys, time
import numpy as np
import jax
from cohflash_jax.runtime import async_filter_jit, cli_cpu_streams, enable_compilation_cache, use_cpu_streams
use_cpu_streams(cli_cpu_streams("reconstruct"))
enable_compilation_cache()
from cohflash_jax.capture import Capture
from cohflash_jax.cli import run_reconstruct
from cohflash_jax.reconstruct import ReconstructOptions
from cohflash_jax.reconstruct.api import tile_rows
from cohflash_jax.reconstruct.engine import BlockReader, PieceReader, sub_tile_pixels
from cohflash_jax.reconstruct.plan import build_plan
from cohflash_jax.reconstruct import programs
from cohflash_jax.results import write_depth
capture, out, method = sys.argv[1:4]
options = ReconstructOptions(method=method, progress=False)
runs = []
for _ in range(2):
    t = time.perf_counter()
    result = run_reconstruct(capture, out, options)
    runs.append(time.perf_counter() - t)
t = time.perf_counter()
write_depth(out, result.outputs, result.meta, {})
write = time.perf_counter() - t
with Capture(capture) as cap:
    n, h, w = cap.shape
    rows = tile_rows(cap, options)
    # as the reconstruction reads: straight into its sub-tiles where it can (`PieceReader`)
    pieces = PieceReader.of(cap, rows)
    reader = pieces or BlockReader(cap, rows)
    t = time.perf_counter()
    for r0 in range(0, h, rows):
        block = reader.read(r0)
    read = time.perf_counter() - t
    instrument = cap.instrument()
    block = reader.read(0)
    sub = pieces.layout.sub if pieces else sub_tile_pixels(rows * w, n)
    first = block.pieces[0] if pieces else block[..., :sub]
plan = build_plan(instrument, options, None, tracking=False)
frames = jax.device_put(np.array(first))
dark = jax.device_put(np.zeros((4, sub), np.float32))
coarse = async_filter_jit(lambda plan, r: plan.coarse(r))
def timed(fn, *args, repeats=5):
    jax.block_until_ready(fn(*args))
    best = []
    for _ in range(repeats):
        t = time.perf_counter(); jax.block_until_ready(fn(*args)); best.append(time.perf_counter() - t)
    return float(np.median(best)) * (h * w) / sub
(c, s, noise_var, total_var), flags = programs.axis_and_checks(plan.iq, frames, dark)
r = programs.rotated_from_frames(plan.iq, frames, dark, c, s)
stages = {
    "data checks and carrier axis (I/Q)": timed(programs.axis_and_checks, plan.iq, frames, dark),
    "rotated sequence (I/Q again)": timed(programs.rotated_from_frames, plan.iq, frames, dark, c, s),
    "coarse stage (FFT, detection)": timed(coarse, plan, r),
}
inversion = timed(programs.invert_sequence, programs.inversion_plan(plan), r, noise_var, total_var, flags)
stages["estimator (inversion − coarse)"] = max(inversion - stages["coarse stage (FFT, detection)"], 0.0)
from cohflash_jax import native
if native.available() and pieces and first.dtype == np.uint16:  # what runs instead of the two I/Q programs
    from cohflash_jax.estimate.iq import folded_weights
    no_dark = np.zeros((4, sub), np.float32)
    weights, bias = folded_weights(np.asarray(plan.iq.weights), np.asarray(plan.iq.bias), no_dark)
    piece = np.array(first)
    stages["native I/Q kernel (replaces both)"] = timed(
        lambda: native.iq_half(piece, weights, bias, plan.iq.saturation_dn).r, repeats=9
    )
print(json.dumps({"first run": runs[0], "second run": runs[1], "read pass": read, "write depth file": write,
                  **stages}))
"""


def child(code: str, capture: str, out: str, method: str, env: dict) -> tuple[dict, float]:
    t = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-c", code, capture, out, method], capture_output=True, text=True, env=env, check=False
    )
    wall = time.perf_counter() - t
    if done.returncode:
        raise SystemExit(done.stderr[-3000:])
    return json.loads(done.stdout.strip().splitlines()[-1]), wall


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--capture", required=True, help="capture file (.h5)")
    p.add_argument("--method", default="ml")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--cold", action="store_true", help="an empty compilation cache for every whole-process run")
    args = p.parse_args()
    import jax
    import jaxlib

    print(f"{cpu_description()}; JAX {jax.__version__}, jaxlib {jaxlib.__version__}; capture {args.capture}")
    print(allocator_description())
    print(native_description())
    print(compile_package_bytecode())  # the package as an install leaves it, before any timing
    with tempfile.TemporaryDirectory(prefix="cohflash-bench-stages-") as tmp:
        tmp = Path(tmp)
        cache = tmp / "cache"
        # the children imitate a `cohflash reconstruct` process, on the allocator it would run on
        env = {**(allocator_environment() or os.environ), "COHFLASH_JAX_CACHE": str(cache)}
        out = str(tmp / "d.h5")
        child(WHOLE, args.capture, out, args.method, env)  # fills the cache
        wholes, steadies = [], []
        for _ in range(args.rounds):
            if args.cold:
                shutil.rmtree(cache, ignore_errors=True)
            whole, wall = child(WHOLE, args.capture, out, args.method, env)
            whole["process (outside)"] = wall
            whole["interpreter start and exit"] = wall - whole["imports"] - whole["backend start"] - whole["command"]
            wholes.append(whole)
            steadies.append(child(STEADY, args.capture, out, args.method, env)[0])
    med = lambda rows, k: statistics.median(r[k] for r in rows)
    state = "cold (empty cache)" if args.cold else "warm cache"
    print(f"\nwhole `cohflash reconstruct --method {args.method}` process, {state}, median of {args.rounds}:")
    for k in (
        "process (outside)",
        "interpreter start and exit",
        "imports",
        "backend start",
        "command",
        "reconstruction",
        "tracing",
        "lowering",
        "XLA compile or cache load",
        "executable cache load",
        "executable compile",
    ):
        print(f"  {k:34s} {med(wholes, k):7.3f} s")
    print(f"  {'command less reconstruction':34s} {med(wholes, 'command') - med(wholes, 'reconstruction'):7.3f} s")
    print("\nsteady state (same process, second run) and its stages, one device, scaled to the capture:")
    for k in steadies[0]:
        print(f"  {k:34s} {med(steadies, k):7.3f} s")
    print(f"  {'first run − second run':34s} {med(steadies, 'first run') - med(steadies, 'second run'):7.3f} s")


if __name__ == "__main__":
    main()
