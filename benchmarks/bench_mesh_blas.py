"""Exact intersection throughput of `MeshBLAS` (closest hit and occlusion) on >= 1M-triangle meshes,
and its ratio to calling embreex's `EmbreeScene.run` directly on the same rays in the same process
(the cost of our wrapper: tensor <-> numpy conversion, ray validation, hit attribute interpolation).
Prints a table and writes benchmarks/results/NAME.json (``--name``, default mesh_blas).

    python benchmarks/bench_mesh_blas.py [--rays 1000000] [--repeats 3] [--statue-detail 4] [--name mesh_blas]
"""

from __future__ import annotations

import sys
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (SHARED_MESHES, ArgumentParser, description, detail_level, positive_int, print_table,  # noqa: E402
                     result_name, run_main, run_seconds, subdivided_file, write_results)

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.geometry.mesh import Mesh, load_mesh  # noqa: E402
from neuralrt.geometry.procedural import statue  # noqa: E402
from neuralrt.rays import Rays  # noqa: E402

COLUMNS = ["mesh", "triangles", "rays", "hit_frac", "intersect_Mrays/s", "embree_intersect_Mrays/s",
           "intersect_ratio", "occluded_Mrays/s", "embree_occluded_Mrays/s", "occluded_ratio"]


def random_rays(mesh: Mesh, n: int, seed: int = 0) -> Rays:
    """Origins uniform on a sphere around the mesh (1.5x its bounding radius), aimed at uniform
    points in its bounding box; t in [0, inf)."""
    rng = np.random.default_rng(seed)
    lo, hi = (b.astype(np.float64) for b in mesh.bounds)
    centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    u = rng.normal(size=(n, 3))
    origins = centre + 1.5 * radius * u / np.linalg.norm(u, axis=1, keepdims=True)
    targets = lo + rng.uniform(size=(n, 3)) * (hi - lo)
    return Rays(torch.from_numpy(origins.astype(np.float32)), torch.from_numpy((targets - origins).astype(np.float32)),
                torch.zeros(n), torch.full((n,), float("inf")))


def best_seconds(fn, repeats: int) -> float:
    """Fastest of ``repeats`` runs: the machine is shared, the minimum is the least disturbed."""
    return min(run_seconds(fn, repeats))


def measure(label: str, mesh: Mesh, n_rays: int, repeats: int) -> dict:
    from embreex import mesh_construction, rtcore_scene

    blas = MeshBLAS(mesh)
    # The baseline: a scene built exactly as MeshBLAS builds its own, queried with plain arrays.
    scene = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(scene, np.ascontiguousarray(mesh.triangles(), dtype=np.float32))
    rays = random_rays(mesh, n_rays)
    o = np.ascontiguousarray(rays.origins.numpy())
    d = np.ascontiguousarray(rays.directions.numpy())
    tfar = np.full(n_rays, 1e37, np.float32)

    # Warm up (first queries touch memory and caches) and check both paths agree.
    hits = blas.intersect(rays)
    direct = scene.run(o, d, dists=tfar.copy(), output=1)
    agree = float((hits.primitive_id.numpy() == direct["primID"]).mean())
    occ = blas.occluded(rays)
    occ_direct = scene.run(o, d, dists=tfar.copy(), query="OCCLUDED") >= 0

    t_intersect = best_seconds(lambda: blas.intersect(rays), repeats)
    t_embree_intersect = best_seconds(lambda: scene.run(o, d, dists=tfar.copy(), output=1), repeats)
    t_occluded = best_seconds(lambda: blas.occluded(rays), repeats)
    t_embree_occluded = best_seconds(lambda: scene.run(o, d, dists=tfar.copy(), query="OCCLUDED"), repeats)
    return {
        "mesh": label,
        "triangles": mesh.num_triangles,
        "rays": n_rays,
        "hit_frac": float(hits.hit.float().mean()),
        "agreement_prim_id": agree,
        "agreement_occluded": float((occ.numpy() == occ_direct).mean()),
        "intersect_s": t_intersect,
        "embree_intersect_s": t_embree_intersect,
        "occluded_s": t_occluded,
        "embree_occluded_s": t_embree_occluded,
        "intersect_Mrays/s": n_rays / t_intersect / 1e6,
        "embree_intersect_Mrays/s": n_rays / t_embree_intersect / 1e6,
        "intersect_ratio": t_embree_intersect / t_intersect,  # fraction of raw Embree throughput we keep
        "occluded_Mrays/s": n_rays / t_occluded / 1e6,
        "embree_occluded_Mrays/s": n_rays / t_embree_occluded / 1e6,
        "occluded_ratio": t_embree_occluded / t_occluded,
    }


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--rays", type=positive_int, default=1_000_000)
    parser.add_argument("--repeats", type=positive_int, default=3)
    parser.add_argument("--statue-detail", type=detail_level("statue"), default=4, help="4 = 1,211,520 triangles")
    parser.add_argument("--subdivide", type=subdivided_file, default="bunny00.off:2",
                        help="shared FILE:LOOP_STEPS (skipped when missing)")
    parser.add_argument("--meshes", type=Path, default=SHARED_MESHES, help="folder of the shared meshes")
    parser.add_argument("--name", type=result_name, default="mesh_blas", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args()
    name, steps = args.subdivide
    path = args.meshes / name
    if path.exists() and not path.is_file():
        parser.error(f"argument --subdivide: {path}: not a mesh file")

    rows = [measure(f"statue(detail={args.statue_detail})", statue(args.statue_detail), args.rays, args.repeats)]
    if path.is_file():
        rows.append(measure(f"{Path(name).stem} loop x{steps}", load_mesh(path).subdivided(steps), args.rays, args.repeats))
    else:
        print(f"skip {path} (missing)")
    print_table(rows, COLUMNS)
    out = write_results(args.name, rows, {
        "torch_threads": torch.get_num_threads(),
        "notes": "ratio = embreex EmbreeScene.run time / MeshBLAS time on the same rays and the same "
                 "triangles, best of repeats, same process (1.0 = no wrapper overhead).",
    })
    print(f"wrote {out}")


if __name__ == "__main__":
    run_main(main)
