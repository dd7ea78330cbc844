"""neuralrt on one device, end to end, in one run (issue 8): training, inference of the neural BLAS
against the exact backend on the same rays, and renders exact vs hybrid.

For ``--device`` (cpu or cuda; the exact backend is Embree on the CPU and OptiX via Mitsuba 3 on
CUDA, as `MeshBLAS(mesh, device=...)` picks it):

1. **train**: an LSNIF model of each ``--meshes`` entry with the device's default preset (``hq`` on
   the CPU, ``gpu`` = 2,000 x 2^18 rays on CUDA; ``--steps`` shortens it), wall time and training
   rays/s, then held-out figures (hit accuracy, |t| error, normal error, normal FLIP) with
   `evaluate_model`.
2. **inference**: 2^``--rays-log2`` rays from a sphere around each mesh aimed at random points of its
   box (the rays issue 8 measured OptiX with): closest-hit and shadow rays/s of the model and of the
   exact backend, same rays, same run, median of ``--repeats`` calls with the device synchronised.
3. **render**: ``--scene`` converted with the same preset, rendered exact and hybrid (``--primary
   exact``: camera rays exact, every other ray neural) at ``--res``/``--spp``: seconds per spp and
   FLIP of the hybrid image against the exact one (and exact vs exact at another seed: the noise
   floor).

Prints tables and writes benchmarks/results/devices_<device>.json (device, versions, date,
figures), or ``--out PATH``. Every argument is checked before the first training.

    python benchmarks/bench_devices.py --device cuda [--methods lsnif,nbvh] [--method-steps nbvh=1000]
    python benchmarks/bench_devices.py --device cpu --steps 300 --rays-log2 18 --res 96 --spp 4
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (RESULTS_DIR, ArgumentParser, check_device, check_output_file, check_scene,  # noqa: E402
                     description, int_in, machine_info, make_short_procedural, parse_short_procedural,
                     per_method_counts, positive_int, print_table, run_main, write_json)
from bench_exact_backends import median_seconds, sphere_rays, versions  # noqa: E402

from neuralrt import api  # noqa: E402
from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.eval.intersection_metrics import HELD_OUT_SEED, evaluate_model  # noqa: E402
from neuralrt.errors import ConfigError  # noqa: E402
from neuralrt.methods import get_method  # noqa: E402
from neuralrt.training.api import train  # noqa: E402

TRAIN_COLUMNS = ["method", "mesh", "triangles", "preset", "steps", "batch", "train_s", "train_Mrays/s", "outside_acc",
                 "t_err_med", "normal_err_med_deg", "normal_flip", "memory_MiB"]
INFER_COLUMNS = ["method", "mesh", "query", "neural_Mrays/s", "exact_Mrays/s", "neural_x_exact", "hit_agreement"]
RENDER_COLUMNS = ["scene", "res", "spp", "exact_s_per_spp", "hybrid_s_per_spp", "hybrid_x_exact", "flip", "noise_floor"]


SECTIONS = ("train", "inference", "render")


def _mesh(spec: str):
    return make_short_procedural(spec, "--meshes")


def _first(metrics: dict, *keys):
    """The first of ``keys`` present in the nested ``metrics`` ("a.b" paths); None if none is."""
    for key in keys:
        value = metrics
        for part in key.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        if value is not None:
            return value
    return None


def bench_train(method: str, spec: str, device: torch.device, steps: int | None, images_dir: Path) -> tuple[dict, object, object]:
    mesh = _mesh(spec)
    registered = get_method(method)
    preset = registered.default_preset(device.type)
    config = registered.config(preset, device=device.type, steps=steps)
    start = time.perf_counter()
    model = train(mesh, config, progress=False, device=device)
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    seconds = time.perf_counter() - start
    tc = config.training
    metrics = evaluate_model(model, mesh, seed=HELD_OUT_SEED, images=True,
                             image_dir=images_dir / f"{method}_{spec.replace(':', '_')}")
    row = {
        "method": method, "mesh": spec, "triangles": len(mesh.faces), "preset": preset, "steps": tc.steps, "batch": tc.batch_size,
        "train_s": seconds, "train_Mrays/s": tc.steps * tc.batch_size / seconds / 1e6,
        "outside_acc": _first(metrics, "outside.accuracy"),
        "t_err_med": _first(metrics, "outside.t_rel_error_median", "outside.t_error_median"),
        "normal_err_med_deg": _first(metrics, "outside.normal_error_deg_median"),
        "normal_flip": _first(metrics, "images.normal_flip", "normal_flip"),
        "memory_MiB": model.memory_bytes().total / 2**20,
        "metrics": metrics,
    }
    return row, mesh, model


def bench_inference(method: str, spec: str, mesh, model, device: torch.device, rays_log2: int, repeats: int) -> list[dict]:
    rays = sphere_rays(mesh, 1 << rays_log2).to(device)
    exact = MeshBLAS(mesh, device=device)
    rows = []
    for query in ("intersect", "occluded"):
        neural_fn, exact_fn = getattr(model, query), getattr(exact, query)
        t_neural = median_seconds(lambda: neural_fn(rays), device, repeats)
        t_exact = median_seconds(lambda: exact_fn(rays), device, repeats)
        a, b = neural_fn(rays), exact_fn(rays)
        a, b = (a.hit, b.hit) if query == "intersect" else (a, b)
        n = len(rays)
        rows.append({"method": method, "mesh": spec, "query": query, "rays": n, "neural_Mrays/s": n / t_neural / 1e6,
                     "exact_Mrays/s": n / t_exact / 1e6, "neural_x_exact": t_exact / t_neural,
                     "hit_agreement": float((a == b).float().mean())})
    return rows


def bench_render(scene: str, device: torch.device, steps: int | None, res: int, spp: int, work: Path) -> dict:
    converted = work / "converted.toml"
    report = api.convert(scene, converted, steps=steps, device=device.type, progress=False)
    for name, target in (("warm_exact", scene), ("warm_hybrid", converted)):  # compile kernels, build BVHs once
        api.render(str(target), work / f"{name}.exr", spp=1, resolution=(16, 16), device=device.type, progress=False)
    seconds = {}
    for name, target, seed in (("exact", scene, 0), ("exact_seed1", scene, 1), ("hybrid", converted, 0)):
        out = api.render(str(target), work / f"{name}.exr", spp=spp, resolution=(res, res), seed=seed,
                         device=device.type, progress=False)
        seconds[name] = out["seconds"]
    flip = api.compare(work / "exact.exr", work / "hybrid.exr")["flip"]
    floor = api.compare(work / "exact.exr", work / "exact_seed1.exr")["flip"]
    return {"scene": scene, "res": res, "spp": spp, "exact_s_per_spp": seconds["exact"] / spp,
            "hybrid_s_per_spp": seconds["hybrid"] / spp, "hybrid_x_exact": seconds["hybrid"] / seconds["exact"],
            "flip": flip, "noise_floor": floor, "train_s": report.get("train_seconds")}


def _items(text: str) -> list[str]:
    return [item for item in text.split(",") if item]


def check_arguments(args) -> tuple:
    """Every argument, before the first training: (device, methods, per-method steps, per-method meshes, skipped
    sections). A bad one is a one-line error."""
    device = check_device(args.device)
    skip = set(_items(args.skip))
    unknown = sorted(skip - set(SECTIONS))
    if unknown:
        raise ConfigError(f"--skip {args.skip}: unknown section(s) {', '.join(unknown)} (use {', '.join(SECTIONS)})")
    methods = _items(args.methods)
    if not methods:
        raise ConfigError("--methods: no method given (e.g. lsnif or lsnif,nbvh)")
    method_steps = per_method_counts(_items(args.method_steps), "--method-steps")
    method_meshes = {}
    for item in _items(args.method_meshes):
        method, eq, specs = item.partition("=")
        if not eq or not specs:
            raise ConfigError(f"--method-meshes {item}: expected METHOD=NAME:DETAIL[+NAME:DETAIL...], e.g. nbvh=statue:2+hairball:6")
        try:
            get_method(method)
        except ConfigError as exc:
            raise ConfigError(f"--method-meshes {item}: {exc}") from None
        method_meshes[method] = specs.split("+")
    for method in methods:
        spec = get_method(method)  # an unknown method: one line
        spec.config(spec.default_preset(device.type), device=device.type, steps=method_steps.get(method, args.steps))
        for mesh in method_meshes.get(method, _items(args.meshes)):
            parse_short_procedural(mesh, "--method-meshes" if method in method_meshes else "--meshes")
    for method in (*method_steps, *method_meshes):
        if method not in methods:
            raise ConfigError(f"--method-steps/--method-meshes name {method}, which is not in --methods {args.methods}")
    if "render" not in skip:
        check_scene(args.scene)
    if args.out is not None:
        check_output_file(args.out, "results file")
    return device, methods, method_steps, method_meshes, skip


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--meshes", default="statue:2,hairball:6", help="procedural meshes (name:detail, comma-separated)")
    parser.add_argument("--methods", default="lsnif", help="registered methods to train and time (comma-separated)")
    parser.add_argument("--steps", type=positive_int, default=None, help="training steps (default: the preset's)")
    parser.add_argument("--method-steps", default="", help="per-method steps, e.g. nbvh=1000 (overrides --steps)")
    parser.add_argument("--method-meshes", default="", help="per-method meshes, e.g. nbvh=statue:2+hairball:6 (overrides --meshes)")
    parser.add_argument("--rays-log2", type=int_in(0, 30), default=22)
    parser.add_argument("--repeats", type=positive_int, default=10)
    parser.add_argument("--scene", default="builtin:hairball?detail=6")
    parser.add_argument("--res", type=positive_int, default=256)
    parser.add_argument("--spp", type=positive_int, default=16)
    parser.add_argument("--skip", default="", help="sections to skip: train,inference,render")
    parser.add_argument("--out", type=Path, default=None, help="JSON path (default benchmarks/results/devices_<device type>.json)")
    args = parser.parse_args()
    device, methods, method_steps, method_meshes, skip = check_arguments(args)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else machine_info()["cpu"]
    out = args.out or RESULTS_DIR / f"devices_{device.type}.json"
    payload = {"benchmark": "devices", "device": name, "machine": machine_info(), "versions": versions(),
               "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
               "train": [], "inference": [], "render": []}

    def save() -> None:
        write_json(out, payload)

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for index, method in enumerate(methods):
            if index == 1 and "render" not in skip:  # the render (LSNIF) before the other methods' rows
                payload["render"].append(bench_render(args.scene, device, args.steps, args.res, args.spp, work))
                save()
            for spec in method_meshes.get(method, _items(args.meshes)):
                if "train" in skip and "inference" in skip:
                    break
                row, mesh, model = bench_train(method, spec, device, method_steps.get(method, args.steps), work)
                payload["train"].append(row)
                save()
                if "inference" not in skip:
                    payload["inference"] += bench_inference(method, spec, mesh, model, device, args.rays_log2, args.repeats)
                    save()
                del model
        if "render" not in skip and not payload["render"]:
            payload["render"].append(bench_render(args.scene, device, args.steps, args.res, args.spp, work))
            save()
    print(f"{name} ({device.type})")
    print_table(payload["train"], TRAIN_COLUMNS)
    print()
    print_table(payload["inference"], INFER_COLUMNS)
    print()
    print_table(payload["render"], RENDER_COLUMNS)
    print(f"wrote {out}")


if __name__ == "__main__":
    run_main(main)
