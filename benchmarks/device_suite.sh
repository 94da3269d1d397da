#!/usr/bin/env bash
# The whole test suite on a lent GPU machine, with the image's own JAX (the package runs from the
# checkout through PYTHONPATH). Packages the image lacks travel as wheels in .whl/ (see the device
# tool's notes: `pip download --no-deps --only-binary=:all: --python-version 3.12 … -d .whl` of
# zarr, numcodecs, donfig, google-crc32c, dask, distributed, tblib, zict, partd, locket, tornado,
# emcee, corner; name .whl in the call's carry). Stopped by SIGINT at LIMIT_S seconds, so that pytest
# still prints which tests failed and why (a kill leaves only its progress dots); the log and a
# JUnit report go to $OUT.
#
#     bash benchmarks/device_suite.sh [LIMIT_S] [PYTEST_ARGS…]
set -u
limit=${1:-280}
shift || true
OUT=${OUT:-/tmp/cohflash-device-out}
mkdir -p "$OUT"
py=${PYTHON:-python3}
if compgen -G ".whl/*.whl" >/dev/null; then
    "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
"$py" -c "import jax, numpy, cv2; print('jax', jax.__version__, 'numpy', numpy.__version__, 'opencv', cv2.__version__, jax.devices())"
t0=$SECONDS
timeout -s INT -k 20 "$limit" "$py" -m pytest -q -p no:cacheprovider -n 8 --dist loadgroup -rfE \
    --junitxml="$OUT/suite.xml" "$@" 2>&1 | tee "$OUT/suite.log" | grep -v PytestBenchmarkWarning
echo "[suite rc ${PIPESTATUS[0]} after $((SECONDS - t0)) s]"
