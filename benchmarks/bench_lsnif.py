"""LSNIF figures: training time and held-out quality (hq, lq), inference rays/s against Embree on
the same rays in the same run, and model bytes against classical BVH bytes.

Usage (one mesh per call is fine; results merge into the JSON file)::

    python benchmarks/bench_lsnif.py bunny00.off armadillo.off mannequin-devil.off bunny00.off@loop2
    python benchmarks/bench_lsnif.py procedural:hairball:6 --presets hq lq --inference-only-steps 300

A mesh is a file name in ../shared/meshes (or a path), optionally ``@loopK`` for K Loop
subdivisions, or ``procedural:NAME:DETAIL``. Timings are noisy on shared machines: each speed is
reported next to Embree's on the same rays, measured interleaved in the same process.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import (SHARED_MESHES, ArgumentParser, check_mesh_spec, check_output_folder, check_presets,  # noqa: E402
                     description, load_mesh_spec, nonnegative_int, positive_int, result_name, run_main, seed_int)

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.eval.intersection_metrics import evaluate_model  # noqa: E402
from neuralrt.errors import ConfigError  # noqa: E402
from neuralrt.geometry.mesh import Mesh  # noqa: E402
from neuralrt.methods import get_method  # noqa: E402
from neuralrt.methods.lsnif import LSNIFModel  # noqa: E402
from neuralrt.training.api import train  # noqa: E402
from neuralrt.training.ray_distribution import BoxRayDistribution  # noqa: E402

SHARED = SHARED_MESHES


def resolve_mesh(spec: str) -> Mesh:
    """The mesh of ``spec``: a file in ../shared/meshes or a path, optionally ``@loopK``, or
    ``procedural:NAME:DETAIL`` (`_common.parse_mesh_spec`; a bad spec is a one-line `MeshError`)."""
    return load_mesh_spec(spec)


def best_rate(fn, n: int, repeats: int) -> float:
    """Best-of-``repeats`` rays/s of ``fn()`` over ``n`` rays."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def inference_speed(model: LSNIFModel, exact: MeshBLAS, rays_n: int, repeats: int) -> dict:
    """rays/s of the model and of Embree on the same rays (training distribution), interleaved."""
    rays = BoxRayDistribution(exact, model.box, seed=4242, pool_size=1 << 16).sample(rays_n).rays
    model.intersect(rays[: 1 << 12])  # warm-up (numba/JIT caches)
    neural, embree = [], []
    for _ in range(repeats):
        embree.append(best_rate(lambda: exact.intersect(rays), rays_n, 1))
        neural.append(best_rate(lambda: model.intersect(rays), rays_n, 1))
    sample = rays[torch.arange(0, rays_n, 16)]  # outside and surface rays alike (the batch holds outside rays first)
    network_fraction = len(model._prepare(sample).active) / len(sample)
    # The MLP's own limit: the network alone on a full chunk of features, at the inference precision.
    cfg = model.config
    h, w = cfg.network.hidden_width, cfg.network.hidden_layers
    n_in, n_out = model.network_inputs, 8 + model.num_materials
    flops = 2 * (n_in * h + (w - 1) * h * h + h * n_out)
    x = torch.randn(cfg.inference.chunk_size, n_in)
    dtype = model.compute_dtype()

    def mlp_only():
        with torch.no_grad():
            model.network(x, dtype)

    mlp_only()
    mlp_rate = best_rate(mlp_only, len(x), repeats)
    neural_rate, embree_rate = max(neural), max(embree)
    return {
        "rays": rays_n,
        "network_fraction": network_fraction,
        "lsnif_rays_per_s": neural_rate,
        "embree_rays_per_s": embree_rate,
        "speedup_vs_embree": neural_rate / embree_rate,
        "mlp_flops_per_ray": flops,
        "compute_precision": str(dtype).replace("torch.", ""),
        "mlp_only_rays_per_s": mlp_rate,
        # Network rays/s of the whole pipeline over the MLP alone: 1.0 = the MLP is the only cost.
        "fraction_of_mlp_limit": neural_rate * network_fraction / mlp_rate,
    }


def model_file_name(spec: str, preset: str) -> str:
    return f"{spec.replace('/', '_').replace(':', '_')}-{preset}.nrt"


def run(spec: str, preset: str, args) -> dict:
    mesh = resolve_mesh(spec)
    exact = MeshBLAS(mesh)
    cfg = get_method("lsnif").config(preset, steps=args.steps, batch_size=args.batch, seed=args.seed)
    t0 = time.perf_counter()
    model = train(mesh, cfg, progress=not args.quiet)
    train_wall = time.perf_counter() - t0
    if args.models_dir:
        Path(args.models_dir).mkdir(parents=True, exist_ok=True)
        model.save(Path(args.models_dir) / model_file_name(spec, preset))
    metrics = evaluate_model(model, mesh, rays=args.eval_rays, resolution=args.image_resolution)
    out = {
        "mesh": spec,
        "triangles": mesh.num_triangles,
        "preset": preset,
        "config": cfg.model_dump(mode="json"),
        "training": {**model.training_record, "wall_seconds_incl_setup": train_wall},
        "metrics": metrics,
        "memory": {"lsnif": model.memory_bytes().as_dict()},
    }
    if args.inference_rays:
        out["inference"] = inference_speed(model, exact, args.inference_rays, args.repeats)
    try:
        from neuralrt.accel.classical_memory import classical_memory

        out["memory"]["classical"] = classical_memory(mesh).as_dict()
        out["memory"]["lsnif_over_bvh_a"] = out["memory"]["lsnif"]["total"] / out["memory"]["classical"]["bvh_a_bytes"]
        out["memory"]["lsnif_over_bvh_b"] = out["memory"]["lsnif"]["total"] / out["memory"]["classical"]["bvh_b_bytes"]
    except ImportError:
        pass
    try:
        from neuralrt.neural.sparse_hash_grid import count_stored_entries

        out["memory"]["sparse_grid_entries"] = count_stored_entries(model.occupancy.cpu().numpy(), tuple(cfg.encoding.resolutions))
    except ImportError:
        pass
    return out


COLUMNS = ["mesh", "preset", "train_s", "train_rays_per_s", "acc_out", "acc_surf", "t_err_med", "n_err_deg_med",
           "flip_normal", "flip_depth", "lsnif_rays_per_s", "embree_rays_per_s", "vs_embree", "memory_mb", "vs_bvh_a"]


def summary_row(r: dict) -> dict:
    m, tr, inf, mem = r["metrics"], r["training"], r.get("inference", {}), r["memory"]
    return {
        "mesh": r["mesh"], "preset": r["preset"], "train_s": tr["seconds"], "train_rays_per_s": tr["rays_per_second"],
        "acc_out": m["outside"]["accuracy"], "acc_surf": m["surface"]["accuracy"],
        "t_err_med": m["outside"]["t_error_median"], "n_err_deg_med": m["outside"]["normal_error_deg_median"],
        "flip_normal": m["images"]["normal_flip"], "flip_depth": m["images"]["depth_flip"],
        "lsnif_rays_per_s": inf.get("lsnif_rays_per_s"), "embree_rays_per_s": inf.get("embree_rays_per_s"),
        "vs_embree": inf.get("speedup_vs_embree"), "memory_mb": mem["lsnif"]["total"] / 2**20,
        "vs_bvh_a": mem.get("lsnif_over_bvh_a"),
    }


def main() -> None:
    from _common import RESULTS_DIR, print_table, read_results, write_results

    p = ArgumentParser(description=description(__doc__))
    p.add_argument("meshes", nargs="+")
    p.add_argument("--presets", nargs="+", default=["hq", "lq"])
    p.add_argument("--steps", type=positive_int, default=None, help="training steps (default: the config's)")
    p.add_argument("--batch", type=positive_int, default=None, help="rays per step (default: the config's)")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("--eval-rays", type=positive_int, default=1 << 18)
    p.add_argument("--image-resolution", type=positive_int, default=256)
    p.add_argument("--inference-rays", type=nonnegative_int, default=1_000_000, help="0 skips the speed test")
    p.add_argument("--repeats", type=positive_int, default=3)
    p.add_argument("--models-dir", default=None, help="also save the trained models here")
    p.add_argument("--remeasure-inference", action="store_true",
                   help="only re-measure inference speed of models saved in --models-dir, updating existing runs")
    p.add_argument("--name", type=result_name, default="lsnif", help="results file: benchmarks/results/NAME.json (runs merge into it)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args()

    # Every check before the first training (a bad second preset or mesh must not cost the first's run).
    for spec in args.meshes:
        check_mesh_spec(spec)
    check_presets("lsnif", args.presets, "--presets", steps=args.steps, batch_size=args.batch, seed=args.seed)
    path = RESULTS_DIR / f"{args.name}.json"
    runs = read_results(args.name).get("runs", {})
    if args.remeasure_inference:
        if not args.models_dir:
            raise ConfigError("--remeasure-inference needs --models-dir (the folder the models were saved in)")
        for spec in args.meshes:
            for preset in args.presets:
                model_path = Path(args.models_dir) / model_file_name(spec, preset)
                if f"{spec}|{preset}" not in runs:
                    raise ConfigError(f"--remeasure-inference: {path} has no run of {spec} {preset} to update")
                if not model_path.is_file():
                    raise ConfigError(f"--remeasure-inference: {model_path}: model file not found")
    elif args.models_dir:
        check_output_folder(args.models_dir, "models")
    for spec in args.meshes:
        for preset in args.presets:
            if args.remeasure_inference:
                r = runs[f"{spec}|{preset}"]
                model = LSNIFModel.load(Path(args.models_dir) / model_file_name(spec, preset))
                r["inference"] = inference_speed(model, MeshBLAS(resolve_mesh(spec)), args.inference_rays, args.repeats)
            else:
                r = run(spec, preset, args)
            runs[f"{spec}|{preset}"] = r
            write_results(args.name, [summary_row(v) for v in runs.values()], extra={"runs": runs})
            print_table([summary_row(r)], COLUMNS)
    print_table([summary_row(v) for v in runs.values()], COLUMNS)
    print(f"wrote {path}")


if __name__ == "__main__":
    run_main(main)
