"""N-BVH in a scene: camera rays at LoD 0, every other ray at ``inference.secondary_lod``.

Two instances of one trained model side by side (every ray neural, ``primary="neural"``), rendered
with secondary_lod None (LoD 0 for every ray), 1, 2, 3: seconds per render (best of ``--repeats``),
MLP rows queried, and the mean |difference| from the LoD-0 image beside the noise floor (the LoD-0
image at another seed; the LoD images share seed 0, so their difference is mostly the cut's, not noise). Writes benchmarks/results/nbvh_secondary_lod.json.

    python benchmarks/bench_nbvh_secondary_lod.py MODEL.nrt ../shared/meshes/bunny00.off
"""

from __future__ import annotations

import neuralrt  # noqa: F401  (before torch: see README "Tests")

import argparse
import json
import os
import platform
import time
import warnings
from pathlib import Path

import numpy as np

import neuralrt.methods.nbvh as nbvh
from neuralrt.methods import load_model
from neuralrt.render.integrator import render
from neuralrt.scene.loader import load_dict

RESULTS = Path(__file__).resolve().parent / "results" / "nbvh_secondary_lod.json"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model")
    ap.add_argument("mesh")
    ap.add_argument("--res", type=int, default=96)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    rows = [0]
    query = nbvh.NBVHModel._query

    def counted(self, origins, *a, **k):  # MLP rows = leaf queries
        rows[0] += len(origins)
        return query(self, origins, *a, **k)

    nbvh.NBVHModel._query = counted
    results, reference, floor = {}, None, None
    for secondary in (None, 1, 2, 3):
        model = load_model(args.model)
        inf = model.config.inference.model_copy(update={"secondary_lod": secondary})
        model.config = model.config.model_copy(update={"inference": inf})
        c = model.bounds.center.numpy()
        diag = float(model.bounds.diagonal)
        spec = {"camera": {"position": (c + np.array([0.0, 0.19, 1.4]) * diag).tolist(), "look_at": c.tolist(),
                           "resolution": [args.res, args.res], "fov": 40},
                "materials": [{"name": "white", "type": "diffuse", "albedo": [0.7, 0.7, 0.7]}],
                "objects": [{"mesh": args.mesh, "model": model, "material": "white", "transform": {"translate": [x * diag, 0.0, 0.0]}}
                            for x in (-0.28, 0.28)],
                "environment": {"color": [1, 1, 1]}}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene = load_dict(spec, primary="neural")
        render(scene, spp=1, seed=0, progress=False, max_depth=4)  # warm-up (numba compiles)
        times = []
        for _ in range(args.repeats):
            rows[0] = 0
            t = time.perf_counter()
            result = render(scene, spp=args.spp, seed=0, progress=False, max_depth=4)
            times.append(time.perf_counter() - t)
        queried = rows[0]
        image = np.asarray(result.image, dtype=np.float64)
        if reference is None:
            reference = image
            other = render(scene, spp=args.spp, seed=1, progress=False, max_depth=4)
            floor = float(np.abs(np.asarray(other.image, dtype=np.float64) - reference).mean())
        results[str(secondary)] = {"lod_other_rays": scene.accel.instances[0].blas.config.inference.lod,
                                   "seconds_best": round(min(times), 3), "seconds_all": [round(t, 3) for t in times],
                                   "mlp_rows": queried, "mean_abs_diff_vs_lod0": float(np.abs(image - reference).mean()),
                                   "coverage": float(np.asarray(result.coverage).mean())}
        print(secondary, results[str(secondary)], flush=True)
    out = {"model": os.path.basename(args.model), "resolution": args.res, "spp": args.spp, "max_depth": 4,
           "noise_floor_mean_abs_diff": floor, "load_average": os.getloadavg(), "machine": platform.processor() or platform.machine(),
           "cpus": os.cpu_count(), "results": results}
    RESULTS.write_text(json.dumps(out, indent=1) + "\n")
    print("noise floor", floor, "->", RESULTS)


if __name__ == "__main__":
    main()
