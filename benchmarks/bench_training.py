"""LSNIF training throughput on the CPU: the step with and without drawing the next batch on a
background thread (`neuralrt.training.prefetch.BatchSource`), alternating in one run.

    python benchmarks/bench_training.py [--mesh PATH] [--steps 60] [--repeats 3] [--preset hq]

Each run trains a fresh model (same seed) for ``--steps`` steps after one warm-up run (numba
compilation); rays/s is rays drawn / wall time of the whole loop. Also records a cProfile of one
run with overlap, summarised as seconds per stage, and the 1-minute load average before and after.
Writes benchmarks/results/training_cpu.json.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import statistics
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets OMP_WAIT_POLICY before torch loads OpenMP)
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_info, print_table, write_results  # noqa: E402

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.geometry.mesh import load_mesh  # noqa: E402
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel  # noqa: E402
from neuralrt.training.trainer import train_model  # noqa: E402

# Stages of a step as cProfile names them (cumulative seconds of these functions).
_STAGES = {
    "sample (rays + Embree ground truth)": "ray_distribution.py:sample",
    "featurize (voxel walk)": "lsnif.py:_featurize",
    "hash-grid forward": "sparse_hash_grid.py:_forward_kernel",
    "MLP forward": "mlp.py:forward",
    "backward (all)": "_tensor.py:backward",
    "hash-grid backward kernel": "sparse_hash_grid.py:_backward_kernel",
    "optimizer (fused Adam)": "adam.py:step",
}


def _train(mesh, truth, config, steps: int, overlap: bool) -> tuple[float, int]:
    model = LSNIFModel.from_mesh(mesh, config)
    rays = model.training_rays(truth, torch.device("cpu"))
    tc = config.training
    t0 = time.perf_counter()
    record = train_model(model, rays, steps=steps, batch_size=tc.batch_size, learning_rate=tc.learning_rate,
                         adam_betas=tc.adam_betas, adam_eps=tc.adam_eps, lr_decay_final=tc.lr_decay_final,
                         progress=False, on_step=model.after_training_step, overlap_sampling=overlap)
    return time.perf_counter() - t0, record.rays


def _profile(mesh, truth, config, steps: int, overlap: bool) -> dict:
    prof = cProfile.Profile()
    prof.enable()
    wall, _ = _train(mesh, truth, config, steps, overlap)
    prof.disable()
    stats = pstats.Stats(prof).stats
    stages = {}
    for label, key in _STAGES.items():
        file, func = key.split(":")
        stages[label] = round(sum(v[3] for (f, _, fn), v in stats.items() if f.endswith(file) and fn == func), 4)
    return {"wall_s": round(wall, 4), "steps": steps, "cumulative_s": stages}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default="/work/shared/meshes/bunny00.off")
    ap.add_argument("--preset", default="hq")
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--name", default="training_cpu")
    args = ap.parse_args()
    mesh = load_mesh(args.mesh)
    truth = MeshBLAS(mesh)
    config = LSNIFConfig.preset(args.preset)
    load_before = os.getloadavg()[0]
    _train(mesh, truth, config, 5, True)  # warm-up: numba compilation, thread pools
    rows = []
    for rep in range(args.repeats):
        for overlap in (False, True):
            wall, n = _train(mesh, truth, config, args.steps, overlap)
            rows.append({"repeat": rep, "overlap": overlap, "steps": args.steps, "batch": config.training.batch_size,
                         "wall_s": round(wall, 4), "rays_per_s": round(n / wall)})
    profiles = {"serial": _profile(mesh, truth, config, args.steps, False),
                "overlap": _profile(mesh, truth, config, args.steps, True)}
    load_after = os.getloadavg()[0]
    print_table(rows, ["repeat", "overlap", "steps", "batch", "wall_s", "rays_per_s"])
    best = {o: max(r["rays_per_s"] for r in rows if r["overlap"] == o) for o in (False, True)}
    median = {o: statistics.median(r["rays_per_s"] for r in rows if r["overlap"] == o) for o in (False, True)}
    # Each overlapped run against the serial run just before it (same load, as near as we can get).
    paired = [b["rays_per_s"] / a["rays_per_s"] for a, b in zip(rows[::2], rows[1::2])]
    summary = {
        "mesh": Path(args.mesh).name, "triangles": int(len(mesh.faces)), "preset": args.preset,
        "torch_threads": torch.get_num_threads(), "load_1min_before_after": [round(load_before, 2), round(load_after, 2)],
        "best_rays_per_s": {"serial": best[False], "overlap": best[True]},
        "overlap_over_serial_best": round(best[True] / best[False], 3),
        "median_rays_per_s": {"serial": median[False], "overlap": median[True]},
        "paired_ratios_overlap_over_serial": [round(r, 3) for r in paired],
        "median_paired_ratio": round(statistics.median(paired), 3),
        "profile_cumulative_s": profiles,
    }
    print(summary)
    path = write_results(args.name, rows, {"machine": machine_info(), "summary": summary})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
