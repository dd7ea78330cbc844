"""A glTF scene of one mesh drawn by many nodes, read merged (a mesh file: `load_mesh`) and imported
(`neuralrt import`: one accelerator per mesh, an instance per node): memory and render time of the
same image, same run; prints a table and writes benchmarks/results/NAME.json (``--name``, default
gltf_import).

The file is written here with trimesh (a mesh per node naming the same accessors, as trimesh
writes them): GRID x GRID copies of MESH, each turned about +y, on a floor, without camera or
lights (both scenes are framed and lit as `neuralrt render mesh.glb` frames a lone mesh).

    python benchmarks/bench_gltf_import.py [--mesh ../shared/meshes/bunny00.off] [--grid 8] [--spp 8] [--repeats 3]
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (SHARED_MESHES, ArgumentParser, check_mesh_spec, description, int_in, load_mesh_spec,  # noqa: E402
                     positive_int, print_table, result_name, run_main, write_results)

COLUMNS = ["scene", "instances", "blas", "memory_MB", "load_s", "render_s", "render_vs_merged"]


def _grid_glb(mesh, grid: int, path: Path) -> None:
    import numpy as np
    import trimesh
    from trimesh.transformations import rotation_matrix, translation_matrix

    lo, hi = mesh.bounds
    step = 1.3 * float(np.max(hi - lo))
    scene = trimesh.Scene()
    floor = trimesh.creation.box((step * (grid + 1), step / 50, step * (grid + 1)))
    scene.add_geometry(floor, node_name="floor", geom_name="floor", transform=translation_matrix([0, float(lo[1]) - step / 100, 0]))
    copy = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    for i in range(grid):
        for j in range(grid):
            place = translation_matrix([(i - (grid - 1) / 2) * step, 0, (j - (grid - 1) / 2) * step])
            scene.add_geometry(copy, node_name=f"copy{i}_{j}", geom_name="copy", transform=place @ rotation_matrix(0.4 * (i + j), [0, 1, 0]))
    scene.export(path)


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    default_mesh = str(SHARED_MESHES / "bunny00.off") if (SHARED_MESHES / "bunny00.off").is_file() else "statue:2"
    parser.add_argument("--mesh", default=default_mesh, help="mesh file or NAME:DETAIL (default: bunny00.off, else statue:2)")
    parser.add_argument("--grid", type=int_in(1, 64), default=8, help="copies per side (default 8: 64 copies)")
    parser.add_argument("--spp", type=positive_int, default=8, help="samples per pixel of each render (default 8)")
    parser.add_argument("--repeats", type=positive_int, default=3, help="renders of each scene, alternating; medians (default 3)")
    parser.add_argument("--name", type=result_name, default="gltf_import", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args()
    check_mesh_spec(args.mesh)

    from statistics import median

    from neuralrt import api
    from neuralrt.scene.loader import load_scene, load_scene_spec
    from neuralrt.scene.memory import scene_memory
    from neuralrt.scene.schema import ObjectSpec
    from neuralrt.scene.scene import save_scene

    mesh = load_mesh_spec(args.mesh)
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        _grid_glb(mesh, args.grid, folder / "grid.glb")
        start = time.perf_counter()
        facts = api.import_scene(folder / "grid.glb", folder / "imported.toml")
        import_seconds = time.perf_counter() - start
        spec, _, _ = load_scene_spec(folder / "imported.toml")  # (the merged scene: the same camera and lights)
        spec.objects = [ObjectSpec(name="merged", mesh=spec.objects[0].mesh)]
        save_scene(spec, folder / "merged.toml")
        rows, scenes, times = [], {}, {"imported": [], "merged": []}
        for name in ("imported", "merged"):
            start = time.perf_counter()
            scenes[name] = load_scene(folder / f"{name}.toml")
            load_seconds = time.perf_counter() - start
            memory = scene_memory(scenes[name]).as_dict()
            instances = scenes[name].accel.instances
            rows.append({"scene": name, "instances": len(instances), "blas": len({id(i.blas) for i in instances}), "load_s": load_seconds,
                         "memory_MB": memory["total_bytes"] / 1e6, **memory})
        for name in ("imported", "merged"):  # (one untimed render each: numba compiles, caches warm)
            api.render(scenes[name], folder / f"{name}.exr", spp=1, progress=False)
        for _ in range(args.repeats):
            for name in ("imported", "merged"):
                done = api.render(scenes[name], folder / f"{name}.exr", spp=args.spp, progress=False)
                times[name].append(done["seconds"])
        flip = api.compare(folder / "merged.exr", folder / "imported.exr")["flip"]
    for row in rows:
        row["render_s"] = median(times[row["scene"]])
        row["render_vs_merged"] = row["render_s"] / median(times["merged"])
        row["render_seconds"] = times[row["scene"]]
    print_table(rows, COLUMNS)
    print(f"import: {import_seconds:.2f} s; FLIP of the imported render against the merged one: {flip:.4f} (same seed)")
    out = write_results(args.name, rows, {
        "mesh": args.mesh, "grid": args.grid, "spp": args.spp, "repeats": args.repeats, "import": facts,
        "import_seconds": import_seconds, "flip_imported_vs_merged": flip,
        "notes": "memory: neuralrt.scene.memory.scene_memory (meshes, BVH A of each unique BLAS, instances); "
                 "render_s: median wall seconds of api.render at --spp, alternating the two scenes.",
    })
    print(f"wrote {out}")


if __name__ == "__main__":
    run_main(main)
