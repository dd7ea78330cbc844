"""Throughput of the LSNIF kernels on one training-sized batch, against Embree on the same rays.

For each mesh: voxelization time; `featurize_rays` (numba DDA), `SparseHashGrid` forward, and
forward + backward on 2^16 rays from the LSNIF training distribution (half from outside, half
from the surface), in rays/s and as a ratio to `MeshBLAS.intersect` (Embree) on the same rays in
the same process (the machine is shared, so ratios are steadier than absolute rates). Also the
featurization statistics (rays crossing an occupied voxel, points per ray, truncation at H,
surface rays whose origin is a point) and the sparse grid's stored entries vs a dense grid.
Best of ``--repeats`` runs. Prints a table and writes benchmarks/results/NAME.json (``--name``,
default lsnif_kernels).

    python benchmarks/bench_lsnif_kernels.py [MESH ...] [--rays 65536] [--repeats 5] [--threads 1 2] [--name lsnif_kernels]

A MESH is a file name in ../shared/meshes (or a path), optionally ``@loopK``, or ``procedural:NAME:DETAIL``.

On a CUDA GPU (Triton kernels, fused inference, training step): bench_lsnif_kernels_cuda.py.
"""

from __future__ import annotations

import sys
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numba
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, check_mesh_spec, description, int_in, load_mesh_spec,  # noqa: E402
                     nonnegative_int, parse_mesh_spec, positive_int, print_table, result_name, run_main, run_seconds,
                     write_results)

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.geometry.mesh import Mesh  # noqa: E402
from neuralrt.geometry.voxelize import voxelize_triangles  # noqa: E402
from neuralrt.methods.lsnif_features import ORIGIN_POINT, featurize_rays  # noqa: E402
from neuralrt.neural.sparse_hash_grid import SparseHashGrid, count_stored_entries  # noqa: E402
from neuralrt.rays import AABB  # noqa: E402
from neuralrt.training.ray_distribution import BoxRayDistribution  # noqa: E402

COLUMNS = ["mesh", "triangles", "threads", "H", "voxelize_ms", "featurize_Mrays/s", "encode_fwd_Mrays/s",
           "encode_fwd_bwd_Mrays/s", "embree_Mrays/s", "featurize_vs_embree", "fwd_bwd_vs_embree",
           "active_frac", "mean_points", "truncated_frac", "hit_past_last_point_frac_of_hits",
           "hits_without_points"]


def best_time(fn, repeats: int) -> float:
    return min(run_seconds(fn, repeats))


def bench_mesh(name: str, mesh: Mesh, n_rays: int, repeats: int, max_points: int) -> dict:
    lo, hi = (torch.from_numpy(b.astype(np.float32)) for b in mesh.bounds)
    pad = 0.01 * (hi - lo).max()
    box = AABB(lo - pad, hi + pad)  # the slightly inflated AABB the model lives in
    ext = box.hi - box.lo
    unit_tris = (mesh.triangles().astype(np.float64) - box.lo.double().numpy()) / ext.double().numpy()
    voxelize_triangles(unit_tris[:8], 32)  # compile
    t_vox = best_time(lambda: voxelize_triangles(unit_tris, 32), max(1, repeats // 2))
    occ = voxelize_triangles(unit_tris, 32)

    blas = MeshBLAS(mesh)
    sampler = BoxRayDistribution(blas, box, pool_size=1 << 16, seed=0)
    batch = sampler.sample(n_rays)
    rays = batch.rays
    o = ((rays.origins - box.lo) / ext).contiguous()
    d = (rays.directions / ext).contiguous()

    featurize_rays(o[:8], d[:8], occ, max_points)  # compile
    t_feat = best_time(lambda: featurize_rays(o, d, occ, max_points), repeats)
    t_embree = best_time(lambda: blas.intersect(rays), repeats)
    fp = featurize_rays(o, d, occ, max_points)

    grid = SparseHashGrid()
    grid(fp.points[:8], fp.face_axis[:8]).sum().backward()  # compile
    t_fwd = best_time(lambda: grid(fp.points, fp.face_axis), repeats)

    def fwd_bwd():
        out = grid(fp.points, fp.face_axis)
        out.backward(torch.ones_like(out))
        grid.table.grad = None

    t_fb = best_time(fwd_bwd, repeats)
    surface = batch.from_surface
    # Pitfall 4/6 checks against Embree's hits (unit-box t equals object-space t: d was scaled too).
    hit = batch.truth.hit
    last = (fp.count.long() - 1).clamp(min=0)
    last_point = fp.points[torch.arange(n_rays), last]
    t_last = ((last_point - o) * d).sum(-1) / (d * d).sum(-1)
    hit_past_last = hit & fp.truncated & (batch.truth.t > t_last)
    stored = count_stored_entries(occ, grid.resolutions)
    return {
        "mesh": name,
        "triangles": int(len(mesh.faces)),
        "H": max_points,
        "rays": n_rays,
        "threads": numba.get_num_threads(),
        "voxelize_ms": 1e3 * t_vox,
        "occupied_voxels": int(occ.sum()),
        "featurize_Mrays/s": n_rays / t_feat / 1e6,
        "encode_fwd_Mrays/s": n_rays / t_fwd / 1e6,
        "encode_fwd_bwd_Mrays/s": n_rays / t_fb / 1e6,
        "embree_Mrays/s": n_rays / t_embree / 1e6,
        "featurize_vs_embree": t_embree / t_feat,
        "fwd_bwd_vs_embree": t_embree / t_fb,
        "active_frac": float((fp.count > 0).float().mean()),
        "mean_points": float(fp.count.float().mean()),
        "truncated_frac": float(fp.truncated.float().mean()),
        "truncated_frac_outside": float(fp.truncated[~surface].float().mean()),
        "truncated_frac_surface": float(fp.truncated[surface].float().mean()),
        "hits_without_points": int((hit & (fp.count == 0)).sum()),  # must be 0 (certain misses)
        "hit_frac": float(hit.float().mean()),
        "hit_past_last_point_frac_of_hits": float(hit_past_last.sum() / hit.sum().clamp(min=1)),
        "surface_origin_point_frac": float((fp.face_axis[surface, 0] == ORIGIN_POINT).float().mean()),
        "stored_entries": stored["levels"],
    }


def mesh_label(spec: str) -> str:
    """A mesh file's stem (``bunny00``; ``bunny00@loop2``), a procedural spec as given."""
    kind, name, detail = parse_mesh_spec(spec)
    if kind == "procedural":
        return spec
    return Path(name).stem + (f"@loop{detail}" if detail else "")


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("meshes", nargs="*", default=["bunny00.off"],
                        help="mesh files (a path, or a file in ../shared/meshes; @loopK) or procedural:NAME:DETAIL "
                             "(default: bunny00.off)")
    parser.add_argument("--rays", type=positive_int, default=1 << 16)
    parser.add_argument("--repeats", type=positive_int, default=5)
    parser.add_argument("--threads", type=nonnegative_int, nargs="+", default=[0],
                        help="numba/torch thread counts to run (0, the default: all cores)")
    parser.add_argument("--max-points", type=int_in(1, 256), default=18, help="H, points kept per ray (1..256, as LSNIF's config)")
    parser.add_argument("--name", type=result_name, default="lsnif_kernels", help="results file: benchmarks/results/NAME.json")
    args = parser.parse_args()
    # Every check before the first mesh is loaded.
    for spec in args.meshes:
        check_mesh_spec(spec)
    cores = numba.config.NUMBA_NUM_THREADS
    too_many = [n for n in args.threads if n > cores]
    if too_many:
        parser.error(f"argument --threads: {too_many[0]} is more than numba's {cores} threads (NUMBA_NUM_THREADS)")
    rows = []
    for spec in args.meshes:
        mesh = load_mesh_spec(spec)
        for threads in args.threads:
            threads = threads or cores
            numba.set_num_threads(threads)
            torch.set_num_threads(threads)
            rows.append(bench_mesh(mesh_label(spec), mesh, args.rays, args.repeats, args.max_points))
            print_table(rows[-1:], COLUMNS)
    out = write_results(args.name, rows)
    print(f"wrote {out}")


if __name__ == "__main__":
    run_main(main)
