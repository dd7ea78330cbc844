#!/usr/bin/env bash
# One call on an offline CUDA machine (Python 3.12 + CUDA torch + Triton + numba there; the rest carried
# in .gpu-deps, made by ../shared/tools/gpu-bundle.sh): unpack, then the cuda variants of the tests and
# benchmarks/bench_devices.py, then N-BVH's kernels (benchmarks/bench_nbvh_cuda.py: registers and spills
# by ptxas, stages and whole queries against the torch path and OptiX; NBVH_SECONDS, default 300; NBVH_ARGS
# passed on, e.g. "--steps 10000" for the training target) and the Triton kernel tests compiled for the GPU.
# Logs and JSON go to $OUT (default ./gpu-out).
#   bash benchmarks/run_gpu.sh [BENCH_SECONDS] [TEST_SECONDS] [bench_devices arguments...]
set -uo pipefail
OUT=${OUT:-gpu-out}; mkdir -p "$OUT"
BENCH_SECONDS=${1:-330}; TEST_SECONDS=${2:-200}; shift 2 || true
mkdir -p /tmp/site
tar xzf .gpu-deps/mitsuba.tgz -C /tmp/site && tar xzf .gpu-deps/drjit.tgz -C /tmp/site
python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .gpu-deps/wheels/*.whl
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$OUT/gpu.txt"
timeout "$BENCH_SECONDS" python3 benchmarks/bench_devices.py --device cuda --out "$OUT/devices_cuda.json" "$@" 2>&1 | tee "$OUT/bench.log"
python3 benchmarks/bench_nbvh_cuda.py --compile-only --out "$OUT/nbvh_cuda_compile.json" 2>&1 | tee "$OUT/nbvh_cuda_compile.log"
# shellcheck disable=SC2086  # NBVH_ARGS: words on purpose
timeout "${NBVH_SECONDS:-300}" python3 benchmarks/bench_nbvh_cuda.py --out "$OUT/nbvh_cuda.json" ${NBVH_ARGS:-} 2>&1 | tee "$OUT/nbvh_cuda.log"
timeout "$TEST_SECONDS" python3 -m pytest -q -p no:cacheprovider -k cuda tests 2>&1 | tee "$OUT/tests.log" | tail -40
timeout "$TEST_SECONDS" python3 -m pytest -q -p no:cacheprovider tests/test_nbvh_triton.py 2>&1 | tee "$OUT/tests_nbvh_triton.log" | tail -20
