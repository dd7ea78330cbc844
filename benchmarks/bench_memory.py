"""Mesh and classical BVH memory (BVH A / BVH B, docs/memory.md) over the shared meshes and one
mesh of >= 1M triangles; prints a table and writes benchmarks/results/NAME.json (``--name``,
default memory).

    python benchmarks/bench_memory.py [--meshes DIR] [--large statue:4] [--subdivide bunny00.off:2] [--no-large] [--name memory]
"""

from __future__ import annotations

import sys
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (SHARED_MESHES, ArgumentParser, description, parse_short_procedural, print_table,  # noqa: E402
                     result_name, run_main, subdivided_file, write_results)

from neuralrt.accel.classical_memory import classical_memory  # noqa: E402
from neuralrt.geometry.bvh import build_bvh  # noqa: E402
from neuralrt.geometry.mesh import load_mesh  # noqa: E402
from neuralrt.geometry.procedural import make_procedural  # noqa: E402

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
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--meshes", type=Path, default=SHARED_MESHES, help="folder of the shared meshes")
    parser.add_argument("--large", default="statue:4", help="procedural NAME:DETAIL of >= 1M triangles")
    parser.add_argument("--subdivide", type=subdivided_file, default="bunny00.off:2",
                        help="shared FILE:LOOP_STEPS, a second >= 1M mesh (skipped when missing)")
    parser.add_argument("--no-large", action="store_true", help="skip both large meshes")
    parser.add_argument("--name", type=result_name, default="memory", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args()
    # Every check before the first mesh is processed.
    if args.meshes.exists() and not args.meshes.is_dir():
        parser.error(f"argument --meshes: {args.meshes}: not a folder")
    large = parse_short_procedural(args.large, "--large", detail_required=True)
    sub_name, sub_steps = args.subdivide
    if not any((args.meshes / name).is_file() for name in MESH_FILES):  # (a typo wrote an empty table over the results)
        parser.error(f"argument --meshes: {args.meshes}: {'holds none of the shared meshes' if args.meshes.is_dir() else 'no such folder'} "
                     f"({', '.join(MESH_FILES[:3])}, ...)")

    build_bvh(make_procedural("sphere", subdivisions=1))  # numba compile outside the timings
    rows = []
    for name in MESH_FILES:
        path = args.meshes / name
        if not path.is_file():
            print(f"skip {path} (missing)")
            continue
        rows.append(row(str(path), load_mesh(path)))
    if not args.no_large:
        gen, params = large
        rows.append(row(f"procedural {gen}(detail={params['detail']}, seed=0)", make_procedural(gen, **params)))
        path = args.meshes / sub_name
        if path.is_file():
            rows.append(row(f"{path} Loop-subdivided {sub_steps}x", load_mesh(path).subdivided(sub_steps)))
        else:
            print(f"skip {path} (missing)")
    print_table(rows, COLUMNS)
    out = write_results(args.name, rows, {
        "notes": "BVH A = 128 B x (4-wide internal + leaf nodes), leaves <= 2 triangles; "
                 "BVH B = 80 B x 8-wide internal nodes + 4 B x triangles (Ylitie et al. 2017); "
                 "build_s = single-threaded numba binned-SAH build + both collapses. See docs/memory.md.",
    })
    print(f"wrote {out}")


if __name__ == "__main__":
    run_main(main)
