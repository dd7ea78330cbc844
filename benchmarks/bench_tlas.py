"""Throughput of the exact intersection stack, layer by layer, on the same 1M rays in one process:
embreex's `EmbreeScene.run` called directly (one call; and split into chunks on a thread pool),
`MeshBLAS`, and the scene TLAS (`SceneAccel`) over one instance with an identity transform,
one with a rotation/scale/translation, and 16 instances of the mesh in a grid. Closest hit and
occlusion. Prints a table and writes benchmarks/results/NAME.json (``--name``, default tlas).

Ratios are against direct embreex in the same process (1.0 = no overhead). The identity and
transformed instances see the same object-space rays as `MeshBLAS` (the world rays are mapped by
the instance transform), so their ratios to the `MeshBLAS` row are the TLAS's own cost. The grid
traces other rays (through the whole grid), so its row is a throughput, not an overhead.

    python benchmarks/bench_tlas.py [--rays 1000000] [--repeats 5] [--statue-detail 4] [--name tlas]
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numba
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, description, detail_level, positive_int, print_table, result_name,  # noqa: E402
                     run_main, write_results)

from neuralrt import host_threads  # noqa: E402
from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.accel.tlas import Instance, SceneAccel  # noqa: E402
from neuralrt.geometry.procedural import statue  # noqa: E402
from neuralrt.rays import Rays, Transform  # noqa: E402

COLUMNS = ["case", "query", "hit_frac", "Mrays/s", "ratio_vs_embree", "ratio_vs_embree_threads", "cpu_s", "cpu_ratio_vs_embree"]
# A transform with every part (rotation, non-uniform scale, translation).
MOVED = Transform.translate([0.3, -0.2, 0.1]) @ Transform.rotate([0.2, 1.0, 0.3], 30) @ Transform.scale([1.2, 0.8, 1.1])
GRID_SPACING = 2.5  # the statue fits in [-1, 1]^3


def rays_through_box(lo: np.ndarray, hi: np.ndarray, n: int, seed: int = 0) -> Rays:
    """Origins uniform on a sphere around the box (1.5x its bounding radius), aimed at uniform
    points inside it; t in [0, inf). The rays of bench_mesh_blas for a mesh's box."""
    rng = np.random.default_rng(seed)
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    centre, radius = 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))
    u = rng.normal(size=(n, 3))
    origins = centre + 1.5 * radius * u / np.linalg.norm(u, axis=1, keepdims=True)
    targets = lo + rng.uniform(size=(n, 3)) * (hi - lo)
    return Rays(torch.from_numpy(origins.astype(np.float32)), torch.from_numpy((targets - origins).astype(np.float32)))


def grid_transforms(side: int = 4) -> list[Transform]:
    """``side`` x ``side`` copies in the x/z plane, each turned a little differently."""
    offsets = (np.arange(side) - (side - 1) / 2) * GRID_SPACING
    return [
        Transform.translate([float(x), 0.0, float(z)]) @ Transform.rotate([0, 1, 0], 23.0 * k)
        for k, (x, z) in enumerate((x, z) for x in offsets for z in offsets)
    ]


def embree_direct(scene, o: np.ndarray, d: np.ndarray, query: str, pool: ThreadPoolExecutor | None, threads: int = 1):
    """What a caller gets from embreex alone: one `run`, or chunks of `run` on a thread pool."""
    tfar = np.full(len(o), 1e37, np.float32)
    kwargs = {"output": 1} if query == "intersect" else {"query": "OCCLUDED"}
    if pool is None:
        return lambda: scene.run(o, d, dists=tfar.copy(), **kwargs)
    chunks = host_threads.chunk_slices(len(o), threads)

    def run():
        futures = [pool.submit(lambda c=c: scene.run(o[c], d[c], dists=tfar[c].copy(), **kwargs)) for c in chunks]
        return [f.result() for f in futures]

    return run


def measure(cases: dict, repeats: int) -> dict[str, tuple[float, float]]:
    """Best wall and CPU seconds per case; the cases take turns in every repeat, so that a busy
    moment on a shared machine hits all of them alike."""
    best = {name: (np.inf, np.inf) for name in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            wall, cpu = time.perf_counter(), time.process_time()
            fn()
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            best[name] = (min(best[name][0], wall), min(best[name][1], cpu))
    return best


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--rays", type=positive_int, default=1_000_000)
    parser.add_argument("--repeats", type=positive_int, default=5)
    parser.add_argument("--statue-detail", type=detail_level("statue"), default=4, help="4 = 1,211,520 triangles")
    parser.add_argument("--name", type=result_name, default="tlas", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args()

    mesh = statue(args.statue_detail)
    blas = MeshBLAS(mesh)
    threads = numba.get_num_threads()
    lo, hi = mesh.bounds
    rays = rays_through_box(lo, hi, args.rays)
    o, d = rays.origins.numpy(), rays.directions.numpy()
    world_rays = MOVED.apply_rays(rays)  # object-space rays of the moved instance ~= `rays`
    identity = SceneAccel([Instance(blas, Transform(), torch.tensor([0]), name="identity")])
    moved = SceneAccel([Instance(blas, MOVED, torch.tensor([0]), name="moved")])
    grid = SceneAccel([Instance(blas, xf, torch.tensor([0]), name=f"grid{k}") for k, xf in enumerate(grid_transforms())])
    grid_rays = rays_through_box(grid.bounds.lo.numpy(), grid.bounds.hi.numpy(), args.rays, seed=1)

    # The same object-space work as MeshBLAS: check the hits agree (up to the transform's rounding).
    hits = {
        "MeshBLAS": blas.intersect(rays),
        "SceneAccel identity": identity.intersect(rays),
        "SceneAccel transformed": moved.intersect(world_rays),
        "SceneAccel 16-instance grid": grid.intersect(grid_rays),
    }
    reference = hits["MeshBLAS"].primitive_id
    agreement = {
        "identity": float((hits["SceneAccel identity"].primitive_id == reference).float().mean()),
        "transformed": float((hits["SceneAccel transformed"].primitive_id == reference).float().mean()),
    }
    hit_frac = {name: float(h.hit.float().mean()) for name, h in hits.items()}
    del hits
    rows = []
    from embreex import mesh_construction, rtcore_scene

    direct = rtcore_scene.EmbreeScene()  # the same mesh in embreex's own scene (MeshBLAS calls Embree's C API itself)
    mesh_construction.TriangleMesh(direct, mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32))
    with ThreadPoolExecutor(threads) as pool:
        for query in ("intersect", "occluded"):
            cases = {
                "embreex direct": embree_direct(direct, o, d, query, None),
                f"embreex direct, {threads} threads": embree_direct(direct, o, d, query, pool, threads),
                "MeshBLAS": lambda: getattr(blas, query)(rays),
                "SceneAccel identity": lambda: getattr(identity, query)(rays),
                "SceneAccel transformed": lambda: getattr(moved, query)(world_rays),
                "SceneAccel 16-instance grid": lambda: getattr(grid, query)(grid_rays),
            }
            for fn in cases.values():
                fn()  # warm up: page in the BVH, compile/load the kernels
            times = measure(cases, args.repeats)
            (base, base_cpu), base_threads = times["embreex direct"], times[f"embreex direct, {threads} threads"][0]
            for name, (wall, cpu) in times.items():
                rows.append({
                    "case": name, "query": query, "rays": args.rays, "hit_frac": hit_frac.get(name, hit_frac["MeshBLAS"]),
                    "Mrays/s": args.rays / wall / 1e6, "ratio_vs_embree": base / wall,
                    "ratio_vs_embree_threads": base_threads / wall, "wall_s": wall, "cpu_s": cpu,
                    "cpu_ratio_vs_embree": base_cpu / cpu,
                })  # fmt: skip
    print(f"{mesh.name}: {mesh.num_triangles:,} triangles, {args.rays:,} rays, {threads} threads")
    print_table(rows, COLUMNS)
    out = write_results(args.name, rows, {
        "mesh": mesh.name,
        "triangles": mesh.num_triangles,
        "threads": threads,
        "torch_threads": torch.get_num_threads(),
        "agreement_prim_id_vs_meshblas": agreement,
        "notes": "ratio_vs_embree = direct single-call embreex time / case time on the same rays, best "
                 "of repeats taken in turns, same process; ratio_vs_embree_threads uses embreex split "
                 "into the chunks MeshBLAS uses, on the same number of threads. The grid row traces "
                 "other rays (through 16 instances), so its ratios are throughputs, not overheads. "
                 "cpu_s is process CPU time (all threads); cpu_ratio_vs_embree = direct embreex "
                 "CPU time / case CPU time, the overhead measure least disturbed by other load.",
    })  # fmt: skip
    print(f"wrote {out}")


if __name__ == "__main__":
    run_main(main)
