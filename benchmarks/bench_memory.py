"""Mesh and classical BVH memory (BVH A / BVH B, docs/memory.md) over the shared meshes and one
mesh of >= 1M triangles; prints a table and writes benchmarks/results/memory.json.

    python benchmarks/bench_memory.py [--meshes DIR] [--large statue:4] [--subdivide bunny00.off:2] [--no-large]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import print_table, write_results  # noqa: E402

from neuralrt.accel.classical_memory import classical_memory  # noqa: E402
from neuralrt.geometry.bvh import build_bvh  # noqa: E402
from neuralrt.geometry.mesh import load_mesh  # noqa: E402
from neuralrt.geometry.procedural import make_procedural  # noqa: E402

SHARED_MESHES = Path(__file__).resolve().parents[2] / "shared" / "meshes"
MESH_FILES = ["bunny00.off", "refined_elephant.off", "armadillo.off", "man.off", "mannequin-devil.off",
              "camel.off", "pig.stl", "bull.off", "homer.off", "knot1.off"]
COLUMNS = ["mesh", "triangles", "mesh_MB", "bvh_a_MB", "bvh_a_B/tri", "bvh_b_MB", "bvh_b_B/tri", "build_s"]


def row(source: str, mesh) -> dict:
    mem = classical_memory(mesh)
    return {
        "mesh": mesh.name,
        "source": source,
        **mem.as_dict(),
        "mesh_MB": mem.mesh_bytes / 1e6,
        "bvh_a_MB": mem.bvh_a_bytes / 1e6,
        "bvh_a_B/tri": mem.bvh_a_bytes_per_triangle,
        "bvh_b_MB": mem.bvh_b_bytes / 1e6,
        "bvh_b_B/tri": mem.bvh_b_bytes_per_triangle,
        "build_s": mem.build_seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", type=Path, default=SHARED_MESHES, help="folder of the shared meshes")
    parser.add_argument("--large", default="statue:4", help="procedural NAME:DETAIL of >= 1M triangles")
    parser.add_argument("--subdivide", default="bunny00.off:2", help="shared FILE:LOOP_STEPS, a second >= 1M mesh")
    parser.add_argument("--no-large", action="store_true", help="skip both large meshes")
    args = parser.parse_args()

    build_bvh(make_procedural("sphere", subdivisions=1))  # numba compile outside the timings
    rows = []
    for name in MESH_FILES:
        path = args.meshes / name
        if not path.is_file():
            print(f"skip {path} (missing)")
            continue
        rows.append(row(str(path), load_mesh(path)))
    if not args.no_large:
        gen, detail = args.large.split(":")
        rows.append(row(f"procedural {gen}(detail={detail}, seed=0)", make_procedural(gen, detail=int(detail))))
        name, steps = args.subdivide.split(":")
        path = args.meshes / name
        if path.is_file():
            rows.append(row(f"{path} Loop-subdivided {steps}x", load_mesh(path).subdivided(int(steps))))
        else:
            print(f"skip {path} (missing)")
    print_table(rows, COLUMNS)
    out = write_results("memory", rows, {
        "notes": "BVH A = 128 B x (4-wide internal + leaf nodes), leaves <= 2 triangles; "
                 "BVH B = 80 B x 8-wide internal nodes + 4 B x triangles (Ylitie et al. 2017); "
                 "build_s = single-threaded numba binned-SAH build + both collapses. See docs/memory.md.",
    })
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
