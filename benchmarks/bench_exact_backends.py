"""Exact-ray throughput of the MeshBLAS backends on the same rays in the same run: OptiX through
Mitsuba 3 on CUDA (full `intersect` with our torch attribute pass, the geometric query alone, and
`occluded`) against Embree on the host's cores. Without a GPU, Mitsuba's LLVM variant stands in
for OptiX (to check the script, not as a GPU figure).

Rays as issue 8 measured OptiX: 2^22 from a sphere around the object (1.5x its bounding radius)
aimed at uniform points of its box. Prints a table; writes
benchmarks/results/exact_backends_<device>.json (device, versions, date, figures), or ``--out PATH``.

    python benchmarks/bench_exact_backends.py [--rays-log2 22] [--meshes statue:2,hairball:6,statue:5]
        [--repeats 10] [--out PATH] [--profile PATH]
"""

from __future__ import annotations

import re
import statistics
import sys
import time
from importlib import metadata
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (RESULTS_DIR, ArgumentParser, check_output_file, description, fail, int_in,  # noqa: E402
                     parse_short_procedural, positive_int, print_table, run_main, write_json, write_results)
from bench_mesh_blas import random_rays  # noqa: E402

from neuralrt.accel.mesh_blas import EmbreeMeshBLAS, MeshBLAS  # noqa: E402
from neuralrt.accel.mesh_blas_attributes import closest_hit_records  # noqa: E402
from neuralrt.accel.mesh_blas_mitsuba import MitsubaMeshBLAS, mitsuba_variant_available  # noqa: E402
from neuralrt.geometry.mesh import Mesh  # noqa: E402
from neuralrt.geometry.procedural import make_procedural  # noqa: E402
from neuralrt.rays import Rays  # noqa: E402

COLUMNS = ["mesh", "triangles", "hit_frac", "backend", "closest_Mrays/s", "trace_only_Mrays/s",
           "attr_pass_ms", "attr_floor_ms", "anyhit_Mrays/s", "closest_Mrays/s_at_2^16", "embree_closest_Mrays/s",
           "embree_anyhit_Mrays/s", "fallback_closest_Mrays/s", "closest_x_embree", "anyhit_x_embree",
           "hit_mismatch", "t_rel_max"]
# Bytes the attribute pass must move per ray at least: rays in (o, d, t_min, t_max: 32) and the Hits
# record out (hit 1, t 4, normal 12, geometric normal 12, uv 8, albedo 12, material/primitive/instance 24).
ATTR_FLOOR_BYTES_PER_RAY = 32 + 73


def sphere_rays(mesh: Mesh, n: int, seed: int = 0) -> Rays:
    """Origins uniform on a sphere around the mesh (1.5x its bounding radius), aimed at uniform
    points of its bounding box; t in [0, inf). CPU tensors (bench_mesh_blas's rays)."""
    return random_rays(mesh, n, seed)


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        import drjit as dr

        torch.cuda.synchronize(device)
        dr.sync_thread()


def median_seconds(fn, device: torch.device, repeats: int, warmup: int = 2) -> float:
    """Median wall time of ``fn()`` with the device idle before and after each call (host overhead
    included, as a renderer sees it)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        synchronize(device)
        start = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def copy_bandwidth(device: torch.device) -> float:
    """Bytes/s of a large device-to-device copy (read + write counted)."""
    x = torch.rand(1 << 28, device=device)
    y = torch.empty_like(x)
    seconds = median_seconds(lambda: y.copy_(x), device, repeats=10)
    return 2 * x.numel() * 4 / seconds


def versions() -> dict:
    out = {}
    for name in ("torch", "mitsuba", "drjit", "embreex", "numpy"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    if torch.cuda.is_available():
        out["cuda_runtime"] = torch.version.cuda
        try:
            import drjit as dr

            out["cuda_driver"] = str(dr.detail.cuda_version()) if hasattr(dr.detail, "cuda_version") else None
        except Exception:  # informative only
            out["cuda_driver"] = None
    return out


def measure(spec: str, n: int, repeats: int, device: torch.device, bandwidth: float | None, profile) -> dict:
    name, params = parse_short_procedural(spec, "--meshes", detail_required=True)
    detail = params["detail"]
    start = time.perf_counter()
    mesh = make_procedural(name, **params)
    build_s = time.perf_counter() - start
    rays_cpu = sphere_rays(mesh, n)
    rays = rays_cpu.to(device)
    embree = EmbreeMeshBLAS(mesh)
    other = MeshBLAS(mesh, device=device) if device.type == "cuda" else MitsubaMeshBLAS(mesh, device="cpu")
    cpu = torch.device("cpu")

    reference, answer = embree.intersect(rays_cpu), other.intersect(rays).to("cpu")
    both = reference.hit & answer.hit
    same = both & (reference.primitive_id == answer.primitive_id)
    rel_t = (reference.t - answer.t).abs() / reference.t.abs().clamp(min=1e-6)

    row = {
        "mesh": f"{name}({detail})", "triangles": mesh.num_triangles, "rays": n, "mesh_build_s": build_s,
        "hit_frac": float(reference.hit.float().mean()), "backend": other.backend,
        "hit_mismatch": int((reference.hit != answer.hit).sum()),
        "occluded_mismatch": int((embree.occluded(rays_cpu) != other.occluded(rays).cpu()).sum()),
        "same_triangle_frac": float(same.sum() / reference.hit.sum().clamp(min=1)),
        "t_rel_max": float(rel_t[same].max()) if same.any() else 0.0,
        "t_rel_over_1e-4": int((rel_t[both] > 1e-4).sum()),
    }
    t_closest = median_seconds(lambda: other.intersect(rays), device, repeats)
    t_anyhit = median_seconds(lambda: other.occluded(rays), device, repeats)
    row["closest_Mrays/s"] = n / t_closest / 1e6
    row["anyhit_Mrays/s"] = n / t_anyhit / 1e6
    if isinstance(other, MitsubaMeshBLAS):
        raw = other.closest_hits(rays)
        t_trace = median_seconds(lambda: other.closest_hits(rays), device, repeats)
        t_attr = median_seconds(lambda: closest_hit_records(other._tables, *raw), device, repeats)
        row["trace_only_Mrays/s"] = n / t_trace / 1e6
        row["attr_pass_ms"] = 1e3 * t_attr
        if bandwidth:
            row["attr_floor_ms"] = 1e3 * n * ATTR_FLOOR_BYTES_PER_RAY / bandwidth
        if profile is not None:
            write_profile(profile, other, rays, device, f"{row['mesh']}: one intersect of {n} rays")
    small = rays[: 1 << 16]  # a wavefront of a 256x256 image: per-call overhead shows here
    row["closest_Mrays/s_at_2^16"] = len(small) / median_seconds(lambda: other.intersect(small), device, repeats) / 1e6
    t_embree = median_seconds(lambda: embree.intersect(rays_cpu), cpu, max(3, repeats // 3), warmup=1)
    t_embree_any = median_seconds(lambda: embree.occluded(rays_cpu), cpu, max(3, repeats // 3), warmup=1)
    row["embree_closest_Mrays/s"] = n / t_embree / 1e6
    row["embree_anyhit_Mrays/s"] = n / t_embree_any / 1e6
    if device.type == "cuda":  # what a CUDA machine without Mitsuba gets: Embree, rays to the host and back
        fallback = EmbreeMeshBLAS(mesh, device=device)
        row["fallback_closest_Mrays/s"] = n / median_seconds(lambda: fallback.intersect(rays), device, 3, warmup=1) / 1e6
    row["closest_x_embree"] = row["closest_Mrays/s"] / row["embree_closest_Mrays/s"]
    row["anyhit_x_embree"] = row["anyhit_Mrays/s"] / row["embree_anyhit_Mrays/s"]
    return row


def write_profile(file, blas, rays: Rays, device: torch.device, title: str) -> None:
    """torch profiler table (kernels by device time) of one ``blas.intersect(rays)``, into ``file``."""
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    try:
        with profile(activities=activities) as prof:
            blas.intersect(rays)
            synchronize(device)
        sort = "cuda_time_total" if device.type == "cuda" else "cpu_time_total"
        file.write(f"== {title}\n{prof.key_averages().table(sort_by=sort, row_limit=30)}\n\n")
    except Exception as exc:  # the profile is a diagnostic: never lose the measurements to it
        file.write(f"== {title}: profiler failed: {exc!r}\n\n")
    file.flush()


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--rays-log2", type=int_in(0, 30), default=22)
    parser.add_argument("--meshes", default="statue:2,hairball:6,statue:5", help="procedural NAME:DETAIL, comma-separated")
    parser.add_argument("--repeats", type=positive_int, default=10)
    parser.add_argument("--out", type=Path, default=None, help="JSON path (default benchmarks/results/exact_backends_<device>.json)")
    parser.add_argument("--profile", type=Path, default=None, help="write torch profiler tables of one intersect per mesh here")
    args = parser.parse_args()
    # Every check before the first mesh is built.
    meshes = args.meshes.split(",")
    for spec in meshes:
        parse_short_procedural(spec, "--meshes", detail_required=True)
    if args.out is not None:
        check_output_file(args.out, "results file")
    if args.profile is not None:
        check_output_file(args.profile, "profile file")

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device.type == "cpu" and not mitsuba_variant_available("cpu"):
        fail("needs CUDA, or Mitsuba's llvm_ad_rgb variant on the CPU")
    device_name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu (Mitsuba llvm_ad_rgb)"
    slug = re.search(r"[AHBL]\d{2,3}", device_name).group(0).lower() if device.type == "cuda" and re.search(
        r"[AHBL]\d{2,3}", device_name) else device.type
    out = args.out or RESULTS_DIR / f"exact_backends_{slug}.json"
    bandwidth = copy_bandwidth(device) if device.type == "cuda" else None
    extra = {"device": device_name, "versions": versions(), "rays": 1 << args.rays_log2,
             "copy_bandwidth_GBps": bandwidth / 1e9 if bandwidth else None,
             "method": "median wall time per call (device synchronised before and after), 2 warm-up calls; "
                       "Embree on the host's cores with CPU tensors; fallback = Embree with CUDA rays"}
    profile = open(args.profile, "w") if args.profile else None
    rows = []
    for spec in meshes:
        rows.append(measure(spec, 1 << args.rays_log2, args.repeats, device, bandwidth, profile))
        print_table(rows[-1:], COLUMNS)
        sys.stdout.flush()
        # Written after each mesh, so a run cut short keeps what it measured.
        written = write_results(out.stem, rows, extra) if out.parent == RESULTS_DIR else _write(out, rows, extra)
    if profile:
        profile.close()
    print()
    print(f"{device_name}, {1 << args.rays_log2} rays")
    print_table(rows, COLUMNS)
    print(f"wrote {written}")


def _write(path: Path, rows: list[dict], extra: dict) -> Path:
    """`write_results` to a path outside benchmarks/results (a device run's output folder), atomically."""
    from _common import machine_info

    return write_json(path, {"benchmark": path.stem, "machine": machine_info(), **extra, "rows": rows})


if __name__ == "__main__":
    run_main(main)
