#!/usr/bin/env bash
# Recompress the Mitsuba and Dr.Jit archives of a GPU bundle (../shared/tools/gpu-bundle.sh) with xz,
# so that the bundle and the working tree fit the 64 MiB a device call carries:
#
#   bash benchmarks/gpu_bundle_xz.sh [.gpu-deps]
#
# Session 34: gzip's mitsuba.tgz 38.9 MB -> mitsuba.txz 24.6 MB (xz -9, ~50 s on 2 cores); with the
# wheels (20.3 MB) and drjit the full bundle was 61 MiB, the tree 4 MiB: over the limit.
# benchmarks/run_gpu.sh unpacks either form.
set -euo pipefail
D=${1:-.gpu-deps}
[ -d "$D" ] || { echo "neuralrt: error: $D missing: run bash ../shared/tools/gpu-bundle.sh $D first" >&2; exit 2; }
command -v xz >/dev/null || { echo "neuralrt: error: xz not found (apt-get install xz-utils)" >&2; exit 2; }
for name in mitsuba drjit; do
    [ -e "$D/$name.tgz" ] || continue
    T=$(mktemp -d)
    tar xzf "$D/$name.tgz" -C "$T"
    tar cf - -C "$T" . | xz -9 -T0 > "$D/$name.txz.part"
    mv "$D/$name.txz.part" "$D/$name.txz" && rm "$D/$name.tgz"
    rm -rf "$T"
done
du -sh "$D"
