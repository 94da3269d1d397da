#!/usr/bin/env bash
# On a lent GPU machine: what XLA's GPU autotuning costs a first (cold-cache) run. Whole
# `cohflash reconstruct` processes, cold then warm, with XLA's default autotuning and with
# --xla_gpu_autotune_level=0, interleaved; the full traffic capture and a 16×16×3000 region of
# interest; and whether the two give the same depth files. Run from the repository root:
#
#     bash benchmarks/gpu_first_run.sh [ROUNDS]
set -u
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
py=${PYTHON:-python3}
work=/tmp/cohflash-gpu-first
mkdir -p "$work"
"$py" -m cohflash_jax.cli simulate traffic --out "$work/traffic.h5" --quiet
"$py" -c "import sys, cohflash_jax as cf; from cohflash_jax.simulate import simulate_to_file
simulate_to_file(sys.argv[1], cf.planar(), cf.Instrument.paper(3000), 16, 16, progress=False)" "$work/small.h5"
run() {  # run LABEL XLA_FLAGS CAPTURE OUT CACHE
    local s e
    s=$EPOCHREALTIME
    XLA_FLAGS="$2" COHFLASH_JAX_CACHE="$5" "$py" -m cohflash_jax.cli reconstruct "$3" --out "$4" --quiet >/dev/null 2>&1 || echo "$1 failed"
    e=$EPOCHREALTIME
    awk -v l="$1" -v s="$s" -v e="$e" 'BEGIN { printf "%-40s %6.2f s\n", l, e - s }'
}
for r in $(seq "${1:-2}"); do
    for mode in default level0; do
        flags=""; [ "$mode" = level0 ] && flags="--xla_gpu_autotune_level=0"
        for cap in traffic small; do
            rm -rf "$work/cache-$mode"
            run "round $r $mode $cap cold" "$flags" "$work/$cap.h5" "$work/$cap-$mode.h5" "$work/cache-$mode"
            run "round $r $mode $cap warm" "$flags" "$work/$cap.h5" "$work/$cap-$mode.h5" "$work/cache-$mode"
        done
    done
done
"$py" - "$work" <<'PY'
import sys, h5py, numpy as np
w = sys.argv[1]
for cap in ("traffic", "small"):
    with h5py.File(f"{w}/{cap}-default.h5") as a, h5py.File(f"{w}/{cap}-level0.h5") as b:
        same = {k: np.array_equal(a[k][()], b[k][()], equal_nan=True) for k in ("depth_m", "sigma_m", "fit_status", "valid")}
        dv = a["valid"][()].astype(bool) & b["valid"][()].astype(bool)
        d = np.abs(a["depth_m"][()] - b["depth_m"][()])[dv]
        print(cap, "identical:", same, "max |Δdepth| over valid", float(d.max()) if d.size else None)
PY
