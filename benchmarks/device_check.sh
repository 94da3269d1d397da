#!/usr/bin/env bash
# One prepared run on a lent GPU machine (issue #21, item 5): the whole-process figures (on the GPU
# and on its host's CPU alone), the 10 Hz mode in memory and from files, where a GPU process's
# time goes, and the GPU-relevant tests. Each step has its own time limit, so one that hangs
# costs only its share; the log is also written to $OUT/device_check.log. Run from the
# repository root, with the image's own JAX (no install: the package runs from the checkout
# through PYTHONPATH).
#
#     bash benchmarks/device_check.sh
set -u
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
OUT=${OUT:-/tmp/cohflash-device-out}
work=/tmp/cohflash-device
mkdir -p "$OUT" "$work"
exec > >(tee "$OUT/device_check.log") 2>&1
py=${PYTHON:-python3}
cli=("$py" -m cohflash_jax.cli)
step() { echo; echo "== $(date +%T) $*"; }
timed() {  # timed LIMIT_S COMMAND…: the command's wall seconds, or why it stopped
    local t0=$SECONDS
    timeout "$1" "${@:2}"
    echo "   [rc $? after $((SECONDS - t0)) s]"
}

step machine
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv
"$py" -c "import jax, jaxlib, equinox, optimistix, h5py, numpy; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, 'equinox', equinox.__version__, 'numpy', numpy.__version__, jax.devices())"
"$py" -c "from cohflash_jax.runtime import cpu_description; print(cpu_description())"

step "simulate traffic (full size, default effects), whole process"
timed 150 "${cli[@]}" simulate traffic --out "$work/traffic.h5" --quiet

step "whole processes beside the read floor and the NumPy script (ml, 2 interleaved rounds; the host's CPU alone too)"
timed 300 "$py" benchmarks/bench_process.py --capture "$work/traffic.h5" --rounds 2 --methods ml --platforms default,cpu

step "in one process: full capture dft/ml, references, the 10 Hz mode in memory"
timed 150 "$py" benchmarks/bench_reconstruct.py --capture "$work/traffic.h5" --repeats 1

step "cohflash stream: eight 35-frame full-frame captures (the 10 Hz mode from files)"
"$py" -c "import sys, cohflash_jax as cf; from cohflash_jax.simulate import simulate_to_file
simulate_to_file(sys.argv[1], cf.planar(effects=('shot_noise', 'read_noise', 'quantization', 'sidebands')),
                 cf.Instrument.ten_hz_mode(), 256, 320, progress=False)" "$work/ten_hz.h5"
for k in 1 2 3 4 5 6 7 8; do cp "$work/ten_hz.h5" "$work/ten_hz_$k.h5"; done
for method in ml dft; do
    timed 60 "${cli[@]}" stream "$work"/ten_hz_?.h5 --out-dir "$work/stream-$method" --method "$method" --quiet
done

step "where a whole GPU process's time goes (warm cache, 1 round)"
timed 150 "$py" benchmarks/bench_stages.py --capture "$work/traffic.h5" --rounds 1

step "tests that exercise the reconstruction on the GPU"
# the image may lack Zarr (a dependency the checkout's install would bring): its tests left out
"$py" -c "import zarr" 2>/dev/null && only=() || { only=(-k "not zarr"); echo "no zarr here: its tests left out"; }
XLA_PYTHON_CLIENT_PREALLOCATE=false timed 200 "$py" -m pytest -q -p no:cacheprovider -n 4 "${only[@]}" \
    tests/test_inversion.py tests/test_detection.py tests/test_honest_sigma.py tests/test_short_sweeps.py \
    tests/test_executable_cache.py
step done
