"""A glTF file of many distinct meshes, each read alone (``load_mesh(path, gltf_mesh=i)``, as the
scene `neuralrt import` writes reads them) against the whole file read once (`load_mesh`), same
run; then the import of the file and the load of its scene. Prints a table and writes
benchmarks/results/NAME.json (``--name``, default gltf_mesh_reads).

The file is written here with trimesh: MESHES icospheres (subdivision SUBDIV), each jittered so
that no two are alike, in a grid. Reading every mesh alone should cost about one read of the file
(`neuralrt.geometry.gltf_pack`: each reads its own bytes); when each read the whole file, it cost
MESHES reads of it.

    python benchmarks/bench_gltf_mesh_reads.py [--meshes 200] [--subdiv 3] [--repeats 3]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ArgumentParser, description, int_in, positive_int, print_table, result_name, run_main, write_results  # noqa: E402

COLUMNS = ["what", "seconds", "per_mesh_ms", "vs_whole_file"]


def _distinct_meshes_glb(meshes: int, subdiv: int, path: Path) -> None:
    import numpy as np
    import trimesh
    from trimesh.transformations import translation_matrix

    rng = np.random.default_rng(0)
    scene = trimesh.Scene()
    side = int(np.ceil(np.sqrt(meshes)))
    for i in range(meshes):
        ball = trimesh.creation.icosphere(subdiv, 0.4)
        ball.vertices = ball.vertices * (1 + 0.1 * rng.random((len(ball.vertices), 1)))
        scene.add_geometry(ball, node_name=f"n{i}", geom_name=f"g{i}", transform=translation_matrix([i % side, 0, i // side]))
    scene.export(path)


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--meshes", type=int_in(2, 10_000), default=200, help="distinct meshes in the file (default 200)")
    parser.add_argument("--subdiv", type=int_in(0, 6), default=3, help="icosphere subdivisions of each (default 3: 1,280 triangles)")
    parser.add_argument("--repeats", type=positive_int, default=3, help="timed runs of each; medians (default 3)")
    parser.add_argument("--name", type=result_name, default="gltf_mesh_reads", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args()

    from statistics import median

    from neuralrt import api
    from neuralrt.geometry.mesh import load_mesh
    from neuralrt.scene.loader import load_scene

    def timed(work) -> float:
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            work()
            times.append(time.perf_counter() - start)
        return median(times)

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "many.glb"
        _distinct_meshes_glb(args.meshes, args.subdiv, path)
        size = path.stat().st_size
        load_mesh(path), load_mesh(path, 0)  # (untimed: imports and first-call set-up)
        whole = timed(lambda: load_mesh(path))
        alone = timed(lambda: [load_mesh(path, i) for i in range(args.meshes)])
        imported = timed(lambda: api.import_scene(path, Path(folder) / "many.toml"))
        loaded = timed(lambda: load_scene(Path(folder) / "many.toml"))
    rows = [{"what": "whole file, once", "seconds": whole, "per_mesh_ms": 1e3 * whole / args.meshes, "vs_whole_file": 1.0},
            {"what": "each mesh alone", "seconds": alone, "per_mesh_ms": 1e3 * alone / args.meshes, "vs_whole_file": alone / whole},
            {"what": "neuralrt import", "seconds": imported, "per_mesh_ms": 1e3 * imported / args.meshes,
             "vs_whole_file": imported / whole},
            {"what": "load the imported scene", "seconds": loaded, "per_mesh_ms": 1e3 * loaded / args.meshes,
             "vs_whole_file": loaded / whole}]
    print_table(rows, COLUMNS)
    out = write_results(args.name, rows, {
        "meshes": args.meshes, "subdiv": args.subdiv, "repeats": args.repeats, "file_bytes": size,
        "notes": "median wall seconds; vs_whole_file: over one load_mesh of the whole file (every mesh, merged) in this run.",
    })
    print(f"wrote {out}")


if __name__ == "__main__":
    run_main(main)
