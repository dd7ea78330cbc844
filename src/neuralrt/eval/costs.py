"""A model's costs, speed and memory, against exact ray tracing of its mesh, measured in the same
run (``neuralrt eval``'s ``speed`` and ``memory``).

Speed: the same rays through the model and through `MeshBLAS` (Embree on the CPU, OptiX on
CUDA), `intersect` and `occluded` each called once untimed (kernels load, caches fill), then
``repeats`` times alternating model and exact, the median wall time of each. eval times
`TIMING_RAYS` rays of its held-out distribution (half from a sphere around the object, many of
which miss it, half from its surface), not a render's rays: a render's speed is `bench_scenes.py`'s.
A ratio of two figures from one run on one machine, as the benchmarks report them; `benchmarks/`
holds the controlled measurements (fixed ray sets, thread counts, idle machines).
"""

from __future__ import annotations

import statistics
import time

import torch

__all__ = ["TIMING_RAYS", "same_run_speed", "memory_against_bvh"]

TIMING_RAYS = 1 << 17  # per call: enough that a call's fixed cost is a few percent on the CPU


def _seconds(call, rays, device: torch.device) -> float:
    synchronize = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    synchronize()
    start = time.perf_counter()
    call(rays)
    synchronize()
    return time.perf_counter() - start


def same_run_speed(model, exact, rays, repeats: int = 5) -> dict:
    """Rays per second of ``model`` and ``exact`` (two BLAS on the same device) on ``rays``."""
    device = rays.device
    out = {"rays": len(rays), "repeats": repeats, "device": str(device), "threads": torch.get_num_threads(),
           "exact_backend": getattr(exact, "backend", type(exact).__name__)}
    for query in ("intersect", "occluded"):
        calls = {"neural": getattr(model, query), "exact": getattr(exact, query)}
        for call in calls.values():
            call(rays)  # untimed: the first call loads kernels
        times = {name: [] for name in calls}
        for _ in range(repeats):
            for name, call in calls.items():
                times[name].append(_seconds(call, rays, device))
        rate = {name: len(rays) / max(statistics.median(t), 1e-12) for name, t in times.items()}
        out[query] = {"neural_rays_per_second": rate["neural"], "exact_rays_per_second": rate["exact"],
                      "neural_over_exact": rate["neural"] / rate["exact"]}
    return out


def memory_against_bvh(model, mesh) -> dict:
    """The model's bytes beside the mesh's and its BVH A / BVH B bytes (docs/memory.md), with ratios
    (above 1: the model is smaller)."""
    from ..accel.classical_memory import classical_memory

    classical = classical_memory(mesh)
    model_bytes = int(model.memory_bytes().total)
    return {"model_bytes": model_bytes, "mesh_bytes": classical.mesh_bytes, "bvh_a_bytes": classical.bvh_a_bytes,
            "bvh_b_bytes": classical.bvh_b_bytes,
            "bvh_a_over_model": classical.bvh_a_bytes / max(model_bytes, 1),
            "bvh_b_over_model": classical.bvh_b_bytes / max(model_bytes, 1)}
