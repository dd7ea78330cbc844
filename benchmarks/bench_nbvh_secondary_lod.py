"""N-BVH in a scene: camera rays at LoD 0, every other ray at ``inference.secondary_lod``.

Two instances of one trained model side by side (every ray neural, ``primary="neural"``), rendered
with secondary_lod None (LoD 0 for every ray), 1, 2, 3: seconds per render (best of ``--repeats``),
MLP rows queried, and the mean |difference| from the LoD-0 image beside the noise floor (the LoD-0
image at another seed; the LoD images share seed 0, so their difference is mostly the cut's, not noise).

Writes benchmarks/results/NAME.json (``--name``, default nbvh_secondary_lod). MESH is the model's
mesh: a file name in ../shared/meshes (or a path), optionally ``@loopK``, or ``procedural:NAME:DETAIL``.

    python benchmarks/bench_nbvh_secondary_lod.py MODEL.nrt bunny00.off [--res 96] [--spp 4] [--repeats 3]
"""

from __future__ import annotations

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)

import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, check_mesh_spec, check_model_file, description, load_mesh_spec,  # noqa: E402
                     positive_int, result_name, run_main, write_results)

import neuralrt.methods.nbvh as nbvh  # noqa: E402
import neuralrt.methods.nbvh_wavefront_cpu as nbvh_wavefront_cpu  # noqa: E402
from neuralrt.methods import load_model  # noqa: E402
from neuralrt.render.integrator import render  # noqa: E402
from neuralrt.scene.loader import load_dict  # noqa: E402


def main() -> None:
    ap = ArgumentParser(description=description(__doc__))
    ap.add_argument("model", help="a trained N-BVH model file (.nrt)")
    ap.add_argument("mesh", help="its mesh")
    ap.add_argument("--res", type=positive_int, default=96)
    ap.add_argument("--spp", type=positive_int, default=4)
    ap.add_argument("--repeats", type=positive_int, default=3)
    ap.add_argument("--name", type=result_name, default="nbvh_secondary_lod", help="results file: benchmarks/results/NAME.json")
    args = ap.parse_args()
    check_model_file(args.model, method="nbvh")  # both before any model or mesh is loaded
    check_mesh_spec(args.mesh)
    mesh = load_mesh_spec(args.mesh)

    # MLP rows = leaf queries: the torch loop's `_query` calls (CUDA and the reference path), and on
    # the CPU each wavefront step's active rays (`_step_decode` decodes one row per active ray).
    rows = [0]
    query, decode = nbvh.NBVHModel._query, nbvh_wavefront_cpu._step_decode

    def counted(self, origins, *a, **k):
        rows[0] += len(origins)
        return query(self, origins, *a, **k)

    def counted_decode(active, *a):
        rows[0] += len(active)
        return decode(active, *a)

    nbvh.NBVHModel._query, nbvh_wavefront_cpu._step_decode = counted, counted_decode
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
                "objects": [{"mesh": mesh, "model": model, "material": "white", "transform": {"translate": [x * diag, 0.0, 0.0]}}
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
    extra = {"model": os.path.basename(args.model), "mesh": args.mesh, "resolution": args.res, "spp": args.spp, "max_depth": 4,
             "noise_floor_mean_abs_diff": floor, "load_average": os.getloadavg(), "results": results}
    path = write_results(args.name, [{"secondary_lod": key, **value} for key, value in results.items()], extra)
    print("noise floor", floor, "->", path)


if __name__ == "__main__":
    run_main(main)
