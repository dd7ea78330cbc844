"""N-BVH figures: training time and held-out quality, inference rays/s against Embree on the same
rays in the same run, and model bytes (itemised) against classical BVH bytes.

Usage (results merge into benchmarks/results/NAME.json)::

    python benchmarks/bench_nbvh.py bunny00.off --presets cpu
    python benchmarks/bench_nbvh.py bunny00.off --presets cpu --steps 1500 --inference-rays 262144
    python benchmarks/bench_nbvh.py bunny00.off --set query.chord_points=stratified --set loss.normal=3
    python benchmarks/bench_nbvh.py bunny00.off --presets paper --device cuda --name nbvh_h100
    python benchmarks/bench_nbvh.py --offsets MODEL.nrt bunny00.off   # secondary-ray offsets -> nbvh_offset.json (or --name)
    python benchmarks/bench_nbvh.py --lods MODEL.nrt bunny00.off      # quality and rays/s per LoD -> nbvh_lod.json (or --name)

A mesh is a file name in ../shared/meshes (or a path), optionally ``@loopK``, or
``procedural:NAME:DETAIL`` (as in bench_lsnif.py). Timings on a shared machine are noisy: the
load average at the start and end of training is recorded beside every training time.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import (ArgumentParser, check_device, check_mesh_spec, check_output_folder, description,  # noqa: E402
                     fail, nonnegative_int, positive_int, result_name, run_main, seed_int)
from bench_lsnif import best_rate, resolve_mesh  # noqa: E402

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.errors import ConfigError  # noqa: E402
from neuralrt.eval.intersection_metrics import evaluate_model  # noqa: E402
from neuralrt.methods import get_method  # noqa: E402
from neuralrt.methods.config import parse_settings  # noqa: E402
from neuralrt.training.api import train  # noqa: E402
from neuralrt.training.ray_distribution import BoxRayDistribution  # noqa: E402


def inference_speed(model, exact, rays_n: int, repeats: int, device: torch.device) -> dict:
    """rays/s of the model and of the exact backend on the same held-out rays, interleaved; and of occluded()."""
    rays = BoxRayDistribution(exact, model.box, seed=4242, pool_size=1 << 16, device=device).sample(rays_n).rays
    model.intersect(rays[: 1 << 12])  # warm-up (numba caches)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    def timed(fn):
        def run():
            fn()
            sync()
        return run

    neural, exact_rate, shadow = [], [], []
    for _ in range(repeats):
        exact_rate.append(best_rate(timed(lambda: exact.intersect(rays)), rays_n, 1))
        neural.append(best_rate(timed(lambda: model.intersect(rays)), rays_n, 1))
        shadow.append(best_rate(timed(lambda: model.occluded(rays)), rays_n, 1))
    return {"rays": rays_n, "nbvh_rays_per_s": max(neural), "nbvh_occluded_rays_per_s": max(shadow),
            "exact_rays_per_s": max(exact_rate), "speedup_vs_exact": max(neural) / max(exact_rate)}


def preset_config(preset: str, args):
    """The preset's config with --steps / --batch / --seed, then the --set keys (one-line `ConfigError`s)."""
    cfg = get_method("nbvh").config(preset, steps=args.steps, batch_size=args.batch, seed=args.seed)
    if args.set:
        overrides = parse_settings(args.set)
        data = cfg.model_dump()
        for section, values in overrides.items():
            if not isinstance(data.get(section), dict):
                raise ConfigError(f"--set {section}.*: unknown config section {section!r} (sections: "
                                  f"{', '.join(k for k, v in data.items() if isinstance(v, dict))})")
            data[section].update(values)
        cfg = type(cfg).validated(data)
    return cfg


def run(spec: str, preset: str, args) -> dict:
    device = torch.device(args.device)
    mesh = resolve_mesh(spec)
    cfg = preset_config(preset, args)
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    model = train(mesh, cfg, progress=not args.quiet, device=device)
    wall = time.perf_counter() - t0
    load_after = os.getloadavg()
    if args.models_dir:
        Path(args.models_dir).mkdir(parents=True, exist_ok=True)
        model.save(Path(args.models_dir) / f"{Path(spec).stem}-nbvh-{preset}.nrt")
    metrics = evaluate_model(model, mesh, rays=args.eval_rays, resolution=args.image_resolution)
    out = {
        "mesh": spec, "triangles": mesh.num_triangles, "preset": preset, "overrides": args.set or [], "config": cfg.model_dump(mode="json"),
        "training": {**model.training_record, "wall_seconds_incl_setup": wall,
                     "load_average_1min_before_after": [load_before[0], load_after[0]]},
        "nodes": model.num_nodes, "metrics": metrics, "memory": {"nbvh": model.memory_bytes().as_dict()},
    }
    if args.inference_rays:
        out["inference"] = inference_speed(model, MeshBLAS(mesh, device=device), args.inference_rays, args.repeats, device)
    try:
        from neuralrt.accel.classical_memory import classical_memory

        classical = classical_memory(mesh).as_dict()
        out["memory"]["classical"] = classical
        out["memory"]["nbvh_over_bvh_a"] = out["memory"]["nbvh"]["total"] / classical["bvh_a_bytes"]
    except ImportError:
        pass
    return out


COLUMNS = ["mesh", "preset", "steps", "nodes", "train_s", "train_rays_per_s", "acc_out", "acc_surf", "t_err_med", "n_err_deg_med",
           "flip_normal", "nbvh_rays_per_s", "exact_rays_per_s", "memory_mb"]


def summary_row(r: dict) -> dict:
    m, tr, inf = r["metrics"], r["training"], r.get("inference", {})
    return {
        "mesh": r["mesh"], "preset": r["preset"], "steps": tr["steps"], "nodes": r["nodes"], "train_s": tr["seconds"],
        "train_rays_per_s": tr["rays_per_second"], "acc_out": m["outside"]["accuracy"], "acc_surf": m["surface"]["accuracy"],
        "t_err_med": m["outside"]["t_error_median"], "n_err_deg_med": m["outside"]["normal_error_deg_median"],
        "flip_normal": m.get("images", {}).get("normal_flip"), "nbvh_rays_per_s": inf.get("nbvh_rays_per_s"),
        "exact_rays_per_s": inf.get("exact_rays_per_s"), "memory_mb": r["memory"]["nbvh"]["total"] / 2**20,
    }


def offsets(model: str, mesh: str, name: str) -> None:
    """bench_lsnif_offset.py's measurement (it takes any model file), written to NAME.json."""
    import bench_lsnif_offset

    sys.argv = [sys.argv[0], model, mesh, "--name", name]
    bench_lsnif_offset.main()


def lods(model_path: str, mesh_spec: str, name: str) -> None:
    """Held-out outside/surface quality and rays/s of one model answering with each registered LoD."""
    from _common import print_table, write_results

    from neuralrt.methods import load_model

    model, mesh = load_model(model_path), resolve_mesh(mesh_spec)
    exact = MeshBLAS(mesh)
    rays = BoxRayDistribution(exact, model.box, seed=4242, pool_size=1 << 16).sample(1 << 17).rays
    rows = []
    for lod in [lvl for lvl in range(7) if bool(model.registered[lvl])]:
        model.config.inference.lod = lod
        m = evaluate_model(model, mesh, rays=1 << 17, images=False)
        leaves = int(((model.node_lod <= lod) & ~_has_leaf_ancestor(model, lod)).sum())
        rows.append({"lod": lod, "leaves": leaves, "acc_out": m["outside"]["accuracy"], "t_err_med": m["outside"]["t_error_median"],
                     "n_err_deg_med": m["outside"]["normal_error_deg_median"], "acc_surf": m["surface"]["accuracy"],
                     "rays_per_s": best_rate(lambda: model.intersect(rays), len(rays), 2)})
    print_table(rows, list(rows[0]))
    print(f"wrote {write_results(name, rows, extra={'model': model_path, 'mesh': mesh_spec})}")


def _has_leaf_ancestor(model, lod: int) -> torch.Tensor:
    """[M] bool: nodes below a node that is already a leaf at ``lod`` (traversal never reaches them)."""
    below = torch.zeros(len(model.node_lod), dtype=torch.bool)
    children = model.node_children.long()
    for node in range(len(children)):  # parents come before their children
        if children[node, 0] >= 0 and (below[node] or model.node_lod[node] <= lod):
            below[children[node]] = True
    return below


def _check_model_and_mesh(model: str, mesh: str) -> None:
    """``--offsets`` / ``--lods`` take MODEL.nrt and a mesh spec: both checked before any work."""
    from neuralrt.io.files import input_file_problem

    problem = input_file_problem(model, "model file")
    if problem:
        fail(problem)
    check_mesh_spec(mesh)


def main() -> None:
    from _common import RESULTS_DIR, print_table, read_results, write_results

    p = ArgumentParser(description=description(__doc__))
    p.add_argument("meshes", nargs="*", help="meshes to train and measure (not with --offsets / --lods)")
    one_model = p.add_mutually_exclusive_group()
    one_model.add_argument("--offsets", nargs=2, metavar=("MODEL", "MESH"),
                           help="secondary-ray offsets of a trained model (default --name nbvh_offset)")
    one_model.add_argument("--lods", nargs=2, metavar=("MODEL", "MESH"),
                           help="quality and rays/s of a trained model per LoD (default --name nbvh_lod)")
    p.add_argument("--presets", nargs="+", default=["cpu"])
    p.add_argument("--steps", type=positive_int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--batch", type=positive_int, default=None, help="samples per step (default: the preset's)")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="change one config key of the preset (repeatable)")
    p.add_argument("--eval-rays", type=positive_int, default=1 << 17)
    p.add_argument("--image-resolution", type=positive_int, default=128)
    p.add_argument("--inference-rays", type=nonnegative_int, default=1 << 18, help="0 skips the speed test")
    p.add_argument("--repeats", type=positive_int, default=3)
    p.add_argument("--models-dir", default=None, help="also save the trained models here")
    p.add_argument("--name", type=result_name, default=None,
                   help="results file: benchmarks/results/NAME.json (default nbvh; training runs merge into it)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args()
    one_model = args.offsets or args.lods
    if one_model:
        if args.meshes:
            p.error(f"{'--offsets' if args.offsets else '--lods'} measures one trained model: no MESHES beside it "
                    f"(got {' '.join(args.meshes)})")
        _check_model_and_mesh(*one_model)
        if args.offsets:
            return offsets(*args.offsets, args.name or "nbvh_offset")
        return lods(*args.lods, args.name or "nbvh_lod")
    if not args.meshes:
        p.error("give the MESHES to train and measure, or --offsets / --lods MODEL MESH")
    args.name = args.name or "nbvh"

    # Every check before the first training (a bad second preset or mesh must not cost the first's run).
    for spec in args.meshes:
        check_mesh_spec(spec)
    check_device(args.device)
    for preset in args.presets:
        preset_config(preset, args)
    if args.models_dir:
        check_output_folder(args.models_dir, "models")
    path = RESULTS_DIR / f"{args.name}.json"
    runs = read_results(args.name).get("runs", {})
    for spec in args.meshes:
        for preset in args.presets:
            r = run(spec, preset, args)
            runs["|".join([spec, preset, str(r["training"]["steps"]), *r["overrides"]])] = r
            write_results(args.name, [summary_row(v) for v in runs.values()], extra={"runs": runs})
            print_table([summary_row(r)], COLUMNS)
    print_table([summary_row(v) for v in runs.values()], COLUMNS)
    print(f"wrote {path}")


if __name__ == "__main__":
    run_main(main)
