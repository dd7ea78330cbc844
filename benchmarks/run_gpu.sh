#!/usr/bin/env bash
# neuralrt on an offline CUDA machine (Python 3.12 + CUDA torch + Triton + numba there; Mitsuba/Dr.Jit and the
# other wheels carried in .gpu-deps, made by ../shared/tools/gpu-bundle.sh), one or more STAGEs per device call:
#
#   bash benchmarks/run_gpu.sh nbvh      # ~560 s: issue 9's figures (run it first)
#       sm_90 compile table (60 s at most), then benchmarks/bench_nbvh_cuda.py (480 s at most): the `paper`
#       preset trained for NBVH_TRAIN_S seconds (default 200) of its 10,000-step schedule with the projection
#       to 10,000 steps, the training step in pieces (device events), the kernels against the torch path, and
#       intersect / occluded rays/s against OptiX on the same rays. NBVH_ARGS are passed on.
#   bash benchmarks/run_gpu.sh tests     # <= 480 s: the cuda tests outside the BLAS contract file (TESTS_S, 120 s at most),
#       the contract file's cuda tests (CONTRACT_S, 240), the N-BVH Triton tests compiled for the GPU (TESTS_S). Seen
#       on a fresh H100 machine (session 23): the first 26 passed in 57 s, the Triton files' 11 in 49 s; the
#       contract file trains its models on the CPU and compiles each method's kernels first: 5 of its 21 in 95 s.
#   bash benchmarks/run_gpu.sh scaling   # <= SCALING_S (330) + 60 s: issue 11's 16-core figures, on the host CPU (no GPU):
#       first benchmarks/bench_simd_stores.py (ns per compress store, expand load, gather, scatter in each form), then
#       benchmarks/bench_scaling.py at SCALING_THREADS (2 16 8 4; the 2-thread process is the baseline, each
#       process's row written as soon as it ends), training also at 2^15- and 2^17-ray batches, ms per step in
#       each stage at every batch size, the encoder backward per table-gradient scatter, and inference also
#       with 2^16-ray chunks whatever the threads (MIN_RAYS_PER_THREAD=0: the chunk rule against the
#       code before session 34), with the chunks split statically among the threads (DYNAMIC_CHUNKS=False:
#       no task queue), with both (session 34's code) and with every layer in numba where the CPU has AMX
#       (SCALING_ARGS replaces those last five's flags; session 34's inference-only A/Bs: SCALING_ARGS="--skip-training --repeats 8
#       --switches chunk_size=1048576 FIRST_LAYER_IN_PASS=True,HIDDEN_LAYERS_IN_DECODE=True"); JSON SCALING_NAME.
#   bash benchmarks/run_gpu.sh pairs     # <= PAIR_S (100) s per pair: benchmarks/bench_training.py pairs on all the host's
#       cores (PAIRS, words of pair[:draw threads], default "overlap_trial draw_threads:1"), procedural statue(2),
#       hq, PAIR_STEPS steps x 5 (default 200; 600 for overlap_trial, whose trial takes 70); JSON training_host_<pair>.
#   bash benchmarks/run_gpu.sh devices   # ~350 s: benchmarks/bench_devices.py (BENCH_SECONDS, default 330)
#   bash benchmarks/run_gpu.sh nif       # <= 560 s: issue 10's GPU rows, NIF vs OptiX shadow rays (bench_nif.py --device cuda)
#       on statue(5) (4.8M triangles) and instances:6 (12 instances of statue(5) sharing one NIF object, 58M
#       instanced triangles; procedural: ../shared does not travel; the statue stops at detail 5), one process
#       each, each under its own timeout (bench_nif writes its JSON at the end). Not run to the end yet: the
#       first try named statue(6), which does not exist, and stopped at once.
#
# Why stages: one device call runs at most 600 s, and a session now has 15 device-minutes (it had 30); a
# fresh machine takes ~1 min to start and is given back 30 s after a call (give_back sooner), so count each
# call as its run + ~1.5 min: one long stage per session (nbvh, nif, or devices + scaling), or `scaling`
# (seen: 4 thread counts + `TESTS_S=100 ... tests` 383 s; SCALING_THREADS="2 16" 190 s; session 23's
# `pairs scaling tests` with three pairs, SCALING_THREADS="2 16" SCALING_ARGS=--profile and TESTS_S=120: 468 s,
# of which pairs ~180, scaling ~120 (its processes 79 + 21 s)). Every stage's
# timeouts add up to less than 600 s, and every benchmark writes its JSON after each section, so a stage
# cut short still returns what it measured.
# Several stages run one after the other in one call (`run_gpu.sh pairs scaling tests`); devices takes
# no stage after it (its further arguments are bench_devices.py's).
# Size: the bundle as gpu-bundle.sh makes it (61 MiB) and the tree (4 MiB) exceed the 64 MiB a call
# carries (session 34). Run `bash benchmarks/gpu_bundle_xz.sh` first (Mitsuba and Dr.Jit recompressed
# with xz: the bundle 46 MiB), or, for scaling and pairs alone, carry .gpu-deps without
# mitsuba.tgz and drjit.tgz (the wheels, 20 MiB); the stages that need OptiX then stop at once.
# Logs and JSON go to $OUT (default ./gpu-out). A call brings back at most 8 files: for more, point OUT
# at a folder of /tmp and tar it into the call's $OUT at the end.
set -uo pipefail
[ $# -gt 0 ] || { echo "usage: run_gpu.sh STAGE... (nbvh, tests, devices, nif, scaling, pairs)" >&2; exit 2; }
gpu_stage=""
for STAGE in "$@"; do
    [ "$STAGE" = devices ] && { gpu_stage=devices; break; }
    case "$STAGE" in nbvh|tests|nif) gpu_stage=${gpu_stage:-$STAGE} ;; scaling|pairs) ;; *) echo "neuralrt: error: unknown stage $STAGE (nbvh, tests, devices, nif, scaling or pairs)" >&2; exit 2 ;; esac
done
[ -d .gpu-deps ] || { echo "neuralrt: error: .gpu-deps missing: run bash ../shared/tools/gpu-bundle.sh .gpu-deps and carry it" >&2; exit 2; }
mitsuba=$(ls .gpu-deps/mitsuba.t[gx]z 2>/dev/null | head -1)
if [ -n "$gpu_stage" ] && [ -z "$mitsuba" ] && [ ! -d /tmp/site/mitsuba ]; then
    echo "neuralrt: error: stage $gpu_stage needs Mitsuba (OptiX): .gpu-deps/mitsuba.tgz missing (only scaling and pairs run without it)" >&2; exit 2
fi
OUT=${OUT:-gpu-out}; mkdir -p "$OUT"
mkdir -p /tmp/site
# scaling and pairs run on the host CPU alone: a bundle carried without Mitsuba (wheels only, 20 MiB) does for them
if [ -n "$mitsuba" ] && [ ! -d /tmp/site/mitsuba ]; then  # once per machine; .txz: benchmarks/gpu_bundle_xz.sh
    for archive in "$mitsuba" "$(ls .gpu-deps/drjit.t[gx]z | head -1)"; do
        python3 -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall('/tmp/site', filter='tar')" "$archive" || exit 2
    done
elif [ ! -d /tmp/site/mitsuba ]; then
    echo "no .gpu-deps/mitsuba.tgz: no OptiX (enough for scaling and pairs)"
fi
if [ ! -e /tmp/site/.neuralrt-unpacked ]; then  # once per machine
    python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .gpu-deps/wheels/*.whl && touch /tmp/site/.neuralrt-unpacked
fi
export PYTHONPATH=/tmp/site:$PWD/src PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv | tee "$OUT/gpu.txt"
while [ $# -gt 0 ]; do
STAGE=$1; shift
case "$STAGE" in
nbvh)
    timeout 60 python3 benchmarks/bench_nbvh_cuda.py --compile-only --out "$OUT/nbvh_cuda_compile.json" 2>&1 | tee "$OUT/nbvh_cuda_compile.log"
    # shellcheck disable=SC2086  # NBVH_ARGS: words on purpose
    timeout 480 python3 benchmarks/bench_nbvh_cuda.py --train-budget-s "${NBVH_TRAIN_S:-200}" --repeats 10 \
        --out "$OUT/nbvh_cuda.json" ${NBVH_ARGS:-} 2>&1 | tee "$OUT/nbvh_cuda.log"
    ;;
tests)
    # -v: a run cut short still names the tests that passed
    timeout "${TESTS_S:-120}" python3 -m pytest -v -p no:cacheprovider -k cuda tests --ignore=tests/test_blas_contract.py \
        --durations=10 2>&1 | tee "$OUT/tests.log" | tail -25
    timeout "${CONTRACT_S:-240}" python3 -m pytest -v -p no:cacheprovider -k cuda tests/test_blas_contract.py --durations=10 2>&1 \
        | tee "$OUT/tests_contract.log" | tail -25
    timeout "${TESTS_S:-120}" python3 -m pytest -v -p no:cacheprovider tests/test_nbvh_triton.py tests/test_nbvh_rays_triton.py 2>&1 \
        | tee "$OUT/tests_nbvh_triton.log" | tail -15
    ;;
devices)
    timeout "${BENCH_SECONDS:-330}" python3 benchmarks/bench_devices.py --device cuda --out "$OUT/devices_cuda.json" "$@" 2>&1 \
        | tee "$OUT/bench.log"
    shift $#
    ;;
scaling)
    lscpu | grep -E "Model name|^CPU\(s\)|Thread|NUMA node\(s\)" | tee "$OUT/cpu.txt"
    # the host's cost of each form of the SIMD stores and loads the kernels use (a microcoded one halved LSNIF on Zen 4)
    timeout 60 python3 benchmarks/bench_simd_stores.py --name simd_stores_host 2>&1 | tee -a "$OUT/cpu.txt"
    cp benchmarks/results/simd_stores_host.json "$OUT/" 2>/dev/null || true
    name=${SCALING_NAME:-scaling_cpu_16}
    # shellcheck disable=SC2086  # SCALING_THREADS, SCALING_ARGS: words on purpose
    timeout "${SCALING_S:-330}" python3 benchmarks/bench_scaling.py --threads ${SCALING_THREADS:-2 16 8 4} --steps 40 --repeats 4 \
        ${SCALING_ARGS:---train-batches 32768 131072 --profile --scatters row_ranges buckets saved_rows --switches MIN_RAYS_PER_THREAD=0 DYNAMIC_CHUNKS=False MIN_RAYS_PER_THREAD=0,DYNAMIC_CHUNKS=False FIRST_LAYER_IN_PASS=True,HIDDEN_LAYERS_IN_DECODE=True} \
        --name "$name" 2>&1 \
        | tee "$OUT/scaling.log"
    cp "benchmarks/results/$name.json" "$OUT/" 2>/dev/null || echo "no scaling JSON (cut short before the first process ended?)"
    ;;
pairs)
    lscpu | grep -E "Model name|^CPU\(s\)|Thread|NUMA node\(s\)" | tee "$OUT/cpu.txt"
    # shellcheck disable=SC2086  # PAIRS: words on purpose
    for item in ${PAIRS:-overlap_trial draw_threads:1}; do
        pair=${item%%:*} draw=${item#*:}; [ "$draw" = "$item" ] && draw=1
        steps=${PAIR_STEPS:-200}; [ "$pair" = overlap_trial ] && steps=${PAIR_STEPS:-600}
        name="training_host_${item/:/_}"
        timeout "${PAIR_S:-100}" python3 benchmarks/bench_training.py --mesh procedural:statue:2 --pair "$pair" --draw-threads "$draw" \
            --steps "$steps" --repeats 5 --name "$name" 2>&1 | tee -a "$OUT/pairs.log"
        cp "benchmarks/results/$name.json" "$OUT/" 2>/dev/null || echo "no $name.json (cut short?)" | tee -a "$OUT/pairs.log"
    done
    ;;
nif)
    # (NIF's default since session 58: the shadow rays of the camera rays' hits; the CPU's Table 2
    # rows in docs/nif.md were measured with SHADOW_RAYS=every_hit)
    for scene in cornell-statue:5 instances:6; do
        name="nif_cuda_${scene/:/_}"
        timeout 270 python3 benchmarks/bench_nif.py --device cuda --resolution 256 --spp 64 --train-spp 32 --repeats 2 \
            --shadow-rays "${SHADOW_RAYS:-first_hit}" --scenes "$scene" --name "$name" 2>&1 | tee -a "$OUT/nif.log"
        cp "benchmarks/results/$name.json" "$OUT/" 2>/dev/null || echo "no $name.json (cut short?)" | tee -a "$OUT/nif.log"
    done
    ;;
esac
done
