"""Mesh loading: `load_mesh` against trimesh's own `trimesh.load` of the same file, per format.

The files are an icosphere of ``--subdivisions`` as trimesh writes it (OBJ; GLB without normals,
which the glTF spec shades flat: three vertices per triangle; GLB with normals; PLY; OFF; STL),
written to a temporary folder. Per format: the median seconds of ``--repeats`` loads by each,
their ratio (what `load_mesh` adds over trimesh's parse: the text clean-up, the glTF JSON, normals,
materials, float32 arrays and checks), and `load_mesh`'s peak traced memory in bytes per triangle
(tracemalloc, in a separate, untimed load). Prints a table and writes benchmarks/results/NAME.json
(default mesh_load.json).

    python benchmarks/bench_mesh_load.py [--subdivisions 8] [--repeats 5] [--formats obj,glb,glb-normals,ply,off,stl]
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import tracemalloc
from pathlib import Path

import neuralrt  # noqa: F401  (before torch: sets how OpenMP threads wait)

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, description, fail, int_in, print_table, result_name, run_main,  # noqa: E402
                     run_seconds, write_results)

from neuralrt.geometry.mesh import import_trimesh, load_mesh  # noqa: E402

FORMATS = ("obj", "glb", "glb-normals", "ply", "off", "stl")


def _write(mesh, folder: Path, fmt: str) -> Path:
    if fmt == "glb-normals":
        mesh = mesh.copy()
        _ = mesh.vertex_normals  # (computed into trimesh's cache: exported as NORMAL)
        path = folder / "sphere-normals.glb"
    else:
        path = folder / f"sphere.{fmt}"
    mesh.export(path)
    return path


def _median_seconds(fn, repeats: int) -> float:
    return statistics.median(run_seconds(fn, repeats))


def main(argv=None) -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--subdivisions", type=int_in(1, 9), default=8, help="icosphere subdivisions (8: 1.31M triangles)")
    parser.add_argument("--repeats", type=int_in(1, 100), default=5, help="timed loads per format and reader")
    parser.add_argument("--formats", default=",".join(FORMATS), help=f"comma-separated, of {', '.join(FORMATS)}")
    parser.add_argument("--name", type=result_name, default="mesh_load", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args(argv)
    formats = args.formats.split(",")
    unknown = [f for f in formats if f not in FORMATS]
    if unknown:
        fail(f"--formats: unknown format {unknown[0]!r} (use {', '.join(FORMATS)})")
    trimesh = import_trimesh()
    sphere = trimesh.creation.icosphere(subdivisions=args.subdivisions)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for fmt in formats:
            path = _write(sphere, Path(folder), fmt)
            load_mesh(path)  # (untimed: the process's one-time kernel loading)
            ours = _median_seconds(lambda: load_mesh(path), args.repeats)
            theirs = _median_seconds(lambda: trimesh.load(str(path), process=False), args.repeats)
            tracemalloc.start()
            mesh = load_mesh(path)
            peak = tracemalloc.get_traced_memory()[1]
            tracemalloc.stop()
            rows.append({"format": fmt, "triangles": mesh.num_triangles, "vertices": len(mesh.vertices),
                         "file_mb": path.stat().st_size / 2**20, "load_mesh_s": ours, "trimesh_load_s": theirs,
                         "ratio": ours / theirs, "peak_bytes_per_triangle": peak / mesh.num_triangles})
    print_table(rows, ["format", "triangles", "vertices", "file_mb", "load_mesh_s", "trimesh_load_s", "ratio",
                       "peak_bytes_per_triangle"])
    settings = {"subdivisions": args.subdivisions, "repeats": args.repeats,
                "command": " ".join(["python", "benchmarks/bench_mesh_load.py", *(argv if argv is not None else sys.argv[1:])])}
    print(write_results(args.name, rows, {"settings": settings}))


if __name__ == "__main__":
    run_main(main)
