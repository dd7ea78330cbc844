"""Render time per sample per pixel of each built-in scene (or scene file: a converted scene renders
hybrid, its models answering the rays other than camera rays) in three configurations in the same
run, split into ray queries and the rest. Prints a table and writes benchmarks/results/NAME.json
(default render.json).

- ``torch``: torch shading ops and random numbers, the TLAS broad phase testing every instance box
  and each BLAS computing hit attributes for all its rays (the shading before the numba kernels;
  the other TLAS stages are today's numba passes);
- ``numba_all_boxes``: fused numba shading, broad phase testing every box, attributes per BLAS
  (last state before the BVH);
- ``numba``: fused numba shading and random numbers, the broad phase walking a BVH over each
  group's instance boxes, and scenes with Embree meshes answered by the TLAS's fused path
  (`NumbaTLASStages.intersect_fused`: attributes only for each ray's final hit) (today's default).

    python benchmarks/bench_render.py [--resolution 256] [--spp 4] [--repeats 3] [--threads 1] [--detail N] [--scenes a,b]
    python benchmarks/bench_render.py --scenes converted/scene.toml --name render_hybrid   # after `neuralrt convert`

Per scene and implementation: ``s_per_spp`` (the fastest of ``--repeats`` renders, taken in
alternation, in a rotated order, so all see the same machine load); ``queries_s_per_spp``, the time inside
`SceneAccel.intersect` / ``occluded`` (TLAS + BLAS: Embree and its bookkeeping);
``rest_s_per_spp``, everything else, of which ``shading_s_per_spp`` is inside the shading stages
(shading, sampling, NEE, roulette, accumulation; the remainder is camera rays, random numbers and
the film); ``blas_share``, the fraction inside `BLAS.intersect` / ``occluded`` alone (and
`EmbreeMeshBLAS.trace_closest`, Embree's own closest-hit call in the fused path).
``speedup`` is torch s/spp over numba s/spp (wall clock), ``cpu_speedup`` the same for the CPU
seconds the process used (all threads; least of the repeats), which other jobs on a shared
machine disturb less; ``tlas_speedup`` numba_all_boxes s/spp over numba s/spp (the gain of the
instance BVH and the fused TLAS path; ``tlas_queries_speedup`` the same for the query time); ``pixels_differing`` the fraction of pixels whose
values differ by more than 0.1% between torch and numba (same seed); the two numba configurations
must render the same image (checked).
The machines are shared, so compare ratios of one run, not seconds across runs; the 1-minute load
average is recorded. ``--threads`` sets torch's intra-op threads (default 1: on an oversubscribed
machine torch's spinning worker threads cost far more than they give); the numba shading kernels
run on chunks of rows over numba's threads; Embree, the TLAS broad phase and the neural models'
kernels use their own threads.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (before torch: sets how OpenMP threads wait)
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, check_scene, description, nonnegative_int, positive_int, print_table,  # noqa: E402
                     result_name, run_main, write_results)

from neuralrt.accel.tlas_stages import NumbaTLASStages  # noqa: E402
from neuralrt.errors import ConfigError  # noqa: E402
from neuralrt.render import shading_stages  # noqa: E402
from neuralrt.render.integrator import render  # noqa: E402
from neuralrt.scene.builtins import BUILTIN_SCENES  # noqa: E402
from neuralrt.scene.loader import load_scene  # noqa: E402

# configuration -> (shading implementation, TLAS broad phase, TLAS fused path for Embree meshes)
CONFIGS = {"torch": ("torch", "all_boxes", False), "numba_all_boxes": ("numba", "all_boxes", False), "numba": ("numba", "bvh", True)}
BACKENDS = tuple(CONFIGS)
COLUMNS = ["scene", "instanced_tris", "rays_per_spp", "torch_s_per_spp", "numba_s_per_spp", "speedup", "cpu_speedup",
           "torch_queries_s_per_spp", "torch_rest_s_per_spp", "torch_shading_s_per_spp", "numba_queries_s_per_spp",
           "numba_rest_s_per_spp", "numba_shading_s_per_spp", "numba_query_share", "numba_all_boxes_s_per_spp",
           "numba_all_boxes_queries_s_per_spp", "tlas_speedup", "pixels_differing"]


class _Timer:
    """Wraps the ``intersect`` / ``occluded`` methods of some objects so their time and rays are counted."""

    def __init__(self, objects):
        self.seconds = 0.0
        self.rays = 0
        for obj in objects:
            for name in ("intersect", "occluded", "trace_closest"):
                if hasattr(obj, name):
                    setattr(obj, name, self._wrap(getattr(obj, name)))

    def _wrap(self, fn):
        def timed(rays, *args, **kwargs):
            t0 = time.perf_counter()
            out = fn(rays, *args, **kwargs)
            self.seconds += time.perf_counter() - t0
            self.rays += len(rays)
            return out

        return timed

    def reset(self) -> None:
        self.seconds, self.rays = 0.0, 0


class _StageTimer:
    """Times the shading stages (``shade`` + ``add_unoccluded``) of both implementations (class-level)."""

    def __init__(self):
        self.seconds = 0.0
        for cls in (shading_stages.TorchShadingStages, shading_stages.NumbaShadingStages):
            for name in ("shade", "add_unoccluded"):
                setattr(cls, name, self._wrap(getattr(cls, name)))

    def _wrap(self, fn):
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            self.seconds += time.perf_counter() - t0
            return out

        return timed



def _is_file(name: str) -> bool:
    return name.endswith((".toml", ".json"))


def check_scenes(names: list[str], detail: int | None) -> None:
    """Every --scenes item (a built-in name, or a .toml/.json scene file) before any render (one-line errors)."""
    if not any(names):
        raise ConfigError("--scenes: no scene given")
    for name in names:
        if not name:
            raise ConfigError(f"--scenes {','.join(names)}: an empty item (built-in names and/or scene files, comma-separated)")
        check_scene(name if _is_file(name) else f"builtin:{name}", detail=None if _is_file(name) else detail)


def bench_scene(name: str, resolution: int, spp: int, detail: int | None, repeats: int, threads: int,
                stage_timer: _StageTimer) -> dict:
    # A built-in name, or a scene file (e.g. one `neuralrt convert` wrote: neural models beside meshes).
    is_file = _is_file(name)
    scene = load_scene(name if is_file else f"builtin:{name}", resolution=(resolution, resolution), detail=None if is_file else detail)
    unique = {id(i.blas): i.blas for i in scene.accel.instances}
    stages = {backend: NumbaTLASStages(scene.accel.table, broad_phase=CONFIGS[backend][1], fused_meshes=CONFIGS[backend][2])
              for backend in BACKENDS}
    for backend in BACKENDS:  # warm-up: allocator, first calls, numba's compiled-kernel cache
        scene.accel.stages = stages[backend]
        render(scene, spp=1, seed=123, progress=False, shading=CONFIGS[backend][0])
    blas_timer = _Timer(unique.values())
    query_timer = _Timer([scene.accel])
    best: dict[str, tuple] = {}
    cpu_best: dict[str, float] = {}  # CPU seconds of the process (all its threads): less sensitive to other jobs
    for rep in range(repeats):
        # Alternate, so that a burst of load from other jobs hits all alike, and rotate the order
        # each repeat, so that no configuration always runs right after another.
        for backend in BACKENDS[rep % len(BACKENDS):] + BACKENDS[:rep % len(BACKENDS)]:
            blas_timer.reset()
            query_timer.reset()
            stage_timer.seconds = 0.0
            torch.set_num_threads(threads)  # numba's OpenMP layer (Embree/TLAS kernels) may have reset it
            cpu0 = time.process_time()
            scene.accel.stages = stages[backend]
            result = render(scene, spp=spp, seed=0, progress=False, shading=CONFIGS[backend][0])
            cpu = time.process_time() - cpu0
            if backend not in best or result.seconds < best[backend][0].seconds:
                best[backend] = (result, query_timer.seconds, blas_timer.seconds, query_timer.rays, stage_timer.seconds)
            cpu_best[backend] = min(cpu_best.get(backend, float("inf")), cpu)
    meshes = [i.blas.mesh for i in scene.accel.instances if hasattr(i.blas, "mesh")]
    row = {"scene": name, "instanced_tris": sum(m.num_triangles for m in meshes), "instances": len(scene.accel.instances),
           "neural_instances": len(scene.accel.instances) - len(meshes), "rays_per_spp": best["numba"][3] / spp}
    for backend in BACKENDS:
        result, query_s, blas_s, _, shading_s = best[backend]
        row[f"{backend}_s_per_spp"] = result.seconds / spp
        row[f"{backend}_queries_s_per_spp"] = query_s / spp
        row[f"{backend}_rest_s_per_spp"] = (result.seconds - query_s) / spp
        row[f"{backend}_shading_s_per_spp"] = shading_s / spp  # part of the rest
        row[f"{backend}_cpu_s_per_spp"] = cpu_best[backend] / spp
        row[f"{backend}_query_share"] = query_s / result.seconds
        row[f"{backend}_blas_share"] = blas_s / result.seconds
    row["speedup"] = row["torch_s_per_spp"] / row["numba_s_per_spp"]
    row["cpu_speedup"] = row["torch_cpu_s_per_spp"] / row["numba_cpu_s_per_spp"]
    row["rest_speedup"] = row["torch_rest_s_per_spp"] / row["numba_rest_s_per_spp"]
    row["tlas_speedup"] = row["numba_all_boxes_s_per_spp"] / row["numba_s_per_spp"]
    row["tlas_queries_speedup"] = row["numba_all_boxes_queries_s_per_spp"] / row["numba_queries_s_per_spp"]
    if not np.array_equal(best["numba"][0].image, best["numba_all_boxes"][0].image):
        raise AssertionError(f"{name}: the instance BVH or the fused TLAS path changed the image (both must give the same hits)")
    # Same seed: the same paths through both, except where float32 (torch) and float64 (numba)
    # rounding of a direction makes a ray graze past or into thin geometry (a path then diverges).
    a, b = best["torch"][0].image, best["numba"][0].image
    row["pixels_differing"] = float((~np.isclose(b, a, rtol=1e-3, atol=1e-4).all(-1)).mean())
    row["mean_radiance_torch"], row["mean_radiance_numba"] = float(a.mean()), float(b.mean())
    return row


def main(argv=None) -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--resolution", type=positive_int, default=256)
    parser.add_argument("--spp", type=positive_int, default=4)
    parser.add_argument("--detail", type=nonnegative_int, default=None, help="procedural detail (default: each scene's)")
    parser.add_argument("--scenes", default=",".join(BUILTIN_SCENES),
                        help="built-in names and/or scene files (.toml/.json, e.g. converted hybrid scenes), comma-separated")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch intra-op threads")
    parser.add_argument("--name", type=result_name, default="render", help="results file: benchmarks/results/NAME.json")
    parser.add_argument("--repeats", type=positive_int, default=3, help="renders per scene and implementation; the fastest is reported")
    args = parser.parse_args(argv)
    check_scenes(args.scenes.split(","), args.detail)
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    stage_timer = _StageTimer()
    rows = [bench_scene(n, args.resolution, args.spp, args.detail, args.repeats, args.threads, stage_timer)
            for n in args.scenes.split(",")]
    load_after = os.getloadavg()[0]
    print(f"{args.resolution}x{args.resolution}, {args.spp} spp (best of {args.repeats}), max_depth = scene default, "
          f"torch threads = {args.threads}, load average {load_before:.1f} -> {load_after:.1f} on {os.cpu_count()} cores, "
          f"{time.perf_counter() - start:.0f} s")
    print_table(rows, COLUMNS)
    path = write_results(args.name, rows, {"resolution": args.resolution, "spp": args.spp, "detail": args.detail,
                                          "torch_threads": args.threads, "repeats": args.repeats,
                                          "load_average_1min_before": load_before, "load_average_1min_after": load_after})
    print(f"wrote {path}")


if __name__ == "__main__":
    run_main(main)
