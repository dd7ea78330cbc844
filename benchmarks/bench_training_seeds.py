"""Model quality over seeds: whether a training change makes models better or worse, or only other.

    python benchmarks/bench_training_seeds.py [--mesh sphere|PATH|procedural:NAME:DETAIL] [--preset hq]
        [--steps 150] [--batch 4096] [--lr-decay 0.5] [--seeds 0-15] [--walks float64 float32]
        [--name training_seeds]

Trains one model per seed and per CPU voxel walk of the training batches (``float64``:
`featurize_rays_numba`; ``float32``: the fused pass's 16-lane walk, `lsnif_features_simd`, where it
applies), and scores each on the same 8,192 held-out rays of the training distribution (seed
12345): hit/miss accuracy, median |t error| (% of the mesh's diagonal) and median normal error
(degrees) where both hit, as `tests/test_lsnif.py`'s short-run test. ``sphere`` (the default) is
that test's sphere. Short runs are noisy: compare the spread over many seeds, not one seed
(docs/lsnif.md, "Session 42"). Writes benchmarks/results/<--name>.json.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (ArgumentParser, check_mesh_spec, check_presets, description, positive_int,  # noqa: E402
                     print_table, result_name, run_main, write_results)
from bench_lsnif import resolve_mesh  # noqa: E402

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.geometry.mesh import Mesh  # noqa: E402
from neuralrt.geometry.procedural import sphere  # noqa: E402
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel  # noqa: E402
from neuralrt.training.api import train  # noqa: E402
from neuralrt.training.ray_distribution import BoxRayDistribution  # noqa: E402


def _mesh(spec: str) -> Mesh:
    if spec == "sphere":  # tests/test_lsnif.py's
        base = sphere(subdivisions=3)
        return Mesh(base.vertices * 4.0 + np.array([10.0, -5.0, 3.0]), base.faces, vertex_normals=base.vertex_normals, name="ball")
    return resolve_mesh(spec)


def _seeds(text: str) -> list[int]:
    """``"0-15"`` (a range, both ends included) or ``"0,3,7"`` (argparse type: a bad list is one line)."""
    lo, dash, hi = text.partition("-")
    try:
        seeds = list(range(int(lo), int(hi) + 1)) if dash else [int(s) for s in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: want FIRST-LAST (e.g. 0-15) or a comma-separated list (e.g. 0,3,7) of seeds >= 0") from None
    if not seeds:
        raise argparse.ArgumentTypeError(f"{text!r}: an empty range (FIRST-LAST needs FIRST <= LAST)")
    if min(seeds) < 0 or max(seeds) >= 1 << 63:
        raise argparse.ArgumentTypeError(f"{text!r}: seeds must be in [0, 2^63)")
    return seeds


def _score(model, blas: MeshBLAS) -> dict:
    batch = BoxRayDistribution(blas, model.box, seed=12345, pool_size=4096).sample(8192)
    pred, truth = model.intersect(batch.rays), batch.truth
    both = pred.hit & truth.hit
    t_err = ((pred.t - truth.t).abs() * batch.rays.directions.norm(dim=1))[both] / blas.bounds.diagonal
    facing = -torch.sign((truth.normal[both] * batch.rays.directions[both]).sum(1, keepdim=True)) * truth.normal[both]
    cos = (pred.normal[both] * facing).sum(1).clamp(-1, 1)
    return {"accuracy": float((pred.hit == truth.hit).float().mean()), "t_error_pct": 100 * float(t_err.median()),
            "normal_error_deg": float(np.degrees(np.arccos(float(cos.median()))))}  # fmt: skip


def main() -> None:
    ap = ArgumentParser(description=description(__doc__))
    ap.add_argument("--mesh", default="sphere", help="sphere (tests/test_lsnif.py's ball) or a mesh spec as bench_lsnif.py's")
    ap.add_argument("--preset", default="hq")
    ap.add_argument("--steps", type=positive_int, default=150)
    ap.add_argument("--batch", type=positive_int, default=4096)
    ap.add_argument("--lr-decay", type=float, default=0.5, help="lr_decay_final (1: a constant rate)")
    ap.add_argument("--seeds", type=_seeds, default="0-15", help="'0-15' or '0,3,7'")
    ap.add_argument("--walks", nargs="+", choices=("float64", "float32"), default=["float64", "float32"])
    ap.add_argument("--name", type=result_name, default="training_seeds")
    args = ap.parse_args()
    if args.mesh != "sphere":  # every check before the first training
        check_mesh_spec(args.mesh)
    check_presets("lsnif", [args.preset], steps=args.steps, batch_size=args.batch, lr_decay_final=args.lr_decay,
                  seed=max(args.seeds))
    mesh = _mesh(args.mesh)
    blas = MeshBLAS(mesh)
    init = LSNIFModel.__init__
    rows = []
    for walk in args.walks:

        def with_walk(self, *a, _walk=walk, **k):
            init(self, *a, **k)
            self.float32_walk = _walk == "float32"

        LSNIFModel.__init__ = with_walk
        for seed in args.seeds:
            config = LSNIFConfig.preset(args.preset).with_training(steps=args.steps, batch_size=args.batch, seed=seed,
                                                                   lr_decay_final=args.lr_decay)  # fmt: skip
            t0 = time.perf_counter()
            model = train(mesh, config, progress=False)
            rows.append({"walk": walk, "seed": seed, **_score(model, blas), "train_s": time.perf_counter() - t0})
            print_table(rows[-1:], list(rows[-1]))
    LSNIFModel.__init__ = init
    summary = {}
    for walk in args.walks:
        mine = [r for r in rows if r["walk"] == walk]
        summary[walk] = {k: {"min": min(r[k] for r in mine), "median": statistics.median(r[k] for r in mine),
                             "max": max(r[k] for r in mine)} for k in ("accuracy", "t_error_pct", "normal_error_deg")}  # fmt: skip
    print_table(rows, ["walk", "seed", "accuracy", "t_error_pct", "normal_error_deg", "train_s"])
    for walk, figures in summary.items():
        print(walk, {k: f"{v['min']:.4g} / {v['median']:.4g} / {v['max']:.4g}" for k, v in figures.items()}, "(min / median / max)")
    config = {"mesh": args.mesh, "preset": args.preset, "steps": args.steps, "batch": args.batch, "lr_decay_final": args.lr_decay}
    print("wrote", write_results(args.name, rows, {"config": config, "summary": summary}))


if __name__ == "__main__":
    run_main(main)
