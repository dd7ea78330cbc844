"""LSNIF and N-BVH side by side on the same meshes: held-out quality, normal-image FLIP, memory
against BVH A / B, inference rays/s against Embree on the same rays in the same run, training time;
and quadric decimation (fast-simplification) at the same bytes.

Usage (rows merge into benchmarks/results/NAME.json, so runs can be split and resumed)::

    python benchmarks/bench_methods.py bunny00.off                       # the default variants
    python benchmarks/bench_methods.py armadillo.off --variants lsnif:hq nbvh:cpu:t15
    python benchmarks/bench_methods.py bunny00.off --train-only          # only train (models cached)
    python benchmarks/bench_methods.py bunny00.off --steps lsnif=2000 --batch nbvh=4096 --decimate
    python benchmarks/bench_methods.py --plot --steps lsnif=2000 --batch nbvh=4096   # results/methods_flip_memory.png

A mesh is a file name in ../shared/meshes (or a path), optionally ``@loopK``, or
``procedural:NAME:DETAIL`` (as in bench_lsnif.py). A variant is ``METHOD:PRESET[:tN]``: the
preset, with ``encoding.log2_table_size = N`` when ``tN`` is given. The defaults are LSNIF ``hq``
(2 levels x 2^17 entries x 3 features) and N-BVH ``cpu`` at tables 2^15 (about LSNIF ``hq``'s
bytes), 2^16 and 2^18 (the paper's memory points). Trained models are kept in --models-dir under
the scene converter's cache names, so bench_scenes.py --models-dir reuses them for the same mesh
and config; a model found there is not retrained (its recorded training time is reported).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import (ArgumentParser, check_mesh_spec, check_output_folder, description, nonnegative_int,  # noqa: E402
                     per_method_counts, positive_int, result_name, run_main, save_figure)
from bench_lsnif import resolve_mesh  # noqa: E402
from bench_nbvh import inference_speed  # noqa: E402

from neuralrt.accel.classical_memory import classical_memory  # noqa: E402
from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.errors import ConfigError  # noqa: E402
from neuralrt.eval.intersection_metrics import evaluate_model  # noqa: E402
from neuralrt.geometry.mesh import Mesh  # noqa: E402
from neuralrt.io.files import write_atomically  # noqa: E402
from neuralrt.methods import get_method, load_model  # noqa: E402
from neuralrt.training.api import train  # noqa: E402

DEFAULT_VARIANTS = ["lsnif:hq", "nbvh:cpu:t15", "nbvh:cpu:t16", "nbvh:cpu:t18"]
DEFAULT_MODELS = Path("/tmp/methods-models")


def per_method(items: list[str], option: str = "--steps") -> dict[str, int]:
    """["lsnif=2000", "nbvh=1000"] -> {"lsnif": 2000, "nbvh": 1000} (``--steps`` / ``--batch``;
    a malformed item, an unknown method or N < 1 is a one-line `ConfigError` naming ``option``)."""
    return per_method_counts(items, option)


def variant_config(variant: str, steps: dict[str, int], batch: dict[str, int] | None = None):
    """``METHOD:PRESET[:tN]`` -> (method, config); ``steps`` / ``batch`` map a method to its
    training steps / rays per step (absent: the preset's). A bad variant is a one-line `ConfigError`."""
    parts = variant.split(":")
    table = parts[2].removeprefix("t") if len(parts) == 3 else None
    if len(parts) not in (2, 3) or (table is not None and not table.isdigit()):
        raise ConfigError(f"variant {variant!r}: want METHOD:PRESET or METHOD:PRESET:tN (N: log2 of the hash table size), e.g. nbvh:cpu:t15")
    method, preset = parts[:2]
    cfg = get_method(method).config(preset, steps=steps.get(method), batch_size=(batch or {}).get(method))
    if table is not None:
        data = cfg.model_dump()
        data["encoding"]["log2_table_size"] = int(table)
        cfg = type(cfg).validated(data)
    return method, cfg


def cached_model_path(mesh: Mesh, cfg, models_dir: Path) -> Path:
    """The scene converter's cache name for (mesh, config), so its scenes reuse these models."""
    from neuralrt.scene.convert import model_file_stem

    return models_dir / f"{model_file_stem(mesh.name, mesh.content_hash(), cfg)}.nrt"


def train_or_load(mesh: Mesh, cfg, models_dir: Path, quiet: bool):
    """(model, training info): the cached model when its file matches, else a freshly trained one
    (the wall time and the load average before/after are kept beside it in ``*.train.json``)."""
    from neuralrt.scene.convert import cached_model_is_valid

    path = cached_model_path(mesh, cfg, models_dir)
    side = path.with_suffix(".train.json")
    if cached_model_is_valid(path, mesh.content_hash(), cfg) and side.is_file():
        return load_model(path), {**json.loads(side.read_text()), "reused_model": str(path)}
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    model = train(mesh, cfg, progress=not quiet)
    info = {"wall_seconds_incl_setup": time.perf_counter() - t0,
            "load_average_1min_before_after": [load_before[0], os.getloadavg()[0]]}
    models_dir.mkdir(parents=True, exist_ok=True)
    model.save(path)
    write_atomically(side, lambda tmp: Path(tmp).write_text(json.dumps(info)))
    return model, info


def measure_model(spec: str, mesh: Mesh, classical: dict, variant: str, model, train_info: dict, args) -> dict:
    exact = MeshBLAS(mesh)
    metrics = evaluate_model(model, mesh, rays=args.eval_rays, resolution=args.image_resolution)
    memory = model.memory_bytes().as_dict()
    row = {
        "mesh": spec, "triangles": mesh.num_triangles, "variant": variant, "method": model.config.method,
        "config": model.config.model_dump(mode="json"),
        "training": {**model.training_record, **train_info},
        "metrics": metrics, "memory": memory,
        "bytes": memory["total"], "over_bvh_a": memory["total"] / classical["bvh_a_bytes"],
        "over_bvh_b": memory["total"] / classical["bvh_b_bytes"],
    }
    if getattr(model, "num_nodes", None) is not None:
        row["nodes"] = int(model.num_nodes)
    if args.inference_rays:
        speed = inference_speed(model, exact, args.inference_rays, args.repeats, torch.device("cpu"))
        row["inference"] = {"rays": speed["rays"], "neural_rays_per_s": speed["nbvh_rays_per_s"],
                            "neural_occluded_rays_per_s": speed["nbvh_occluded_rays_per_s"],
                            "embree_rays_per_s": speed["exact_rays_per_s"], "vs_embree": speed["speedup_vs_exact"]}
    return row


def decimated_mesh(mesh: Mesh, target_bytes: int, tolerance: float = 0.05) -> tuple[Mesh, dict]:
    """Quadric decimation of ``mesh`` whose mesh bytes + BVH A bytes are within ``tolerance`` of
    ``target_bytes`` (the triangle count is corrected a few times: bytes per triangle vary a little);
    the mesh itself when its own bytes are within the target."""
    import fast_simplification

    full = classical_memory(mesh)
    if full.mesh_bytes + full.bvh_a_bytes <= target_bytes:  # the whole mesh fits: nothing to decimate
        return mesh, {**full.as_dict(), "bytes": full.mesh_bytes + full.bvh_a_bytes, "target_bytes": target_bytes}
    per_triangle = (full.mesh_bytes + full.bvh_a_bytes) / mesh.num_triangles
    target = max(4, int(target_bytes / per_triangle))
    for _ in range(4):
        reduction = min(max(1.0 - target / mesh.num_triangles, 0.0), 0.9999)
        points, faces = fast_simplification.simplify(mesh.vertices, mesh.faces, target_reduction=reduction)
        out = Mesh(vertices=np.ascontiguousarray(points, np.float32), faces=np.ascontiguousarray(faces, np.int32),
                   name=f"{mesh.name}-decimated")
        mem = classical_memory(out)
        got = mem.mesh_bytes + mem.bvh_a_bytes
        if abs(got / target_bytes - 1.0) <= tolerance or reduction == 0.0:
            break
        target = max(4, int(out.num_triangles * target_bytes / got))
    return out, {**mem.as_dict(), "bytes": got, "target_bytes": target_bytes}


def measure_decimation(spec: str, mesh: Mesh, target_bytes: int, label: str, args) -> dict:
    small, mem = decimated_mesh(mesh, target_bytes)
    metrics = evaluate_model(MeshBLAS(small), mesh, rays=args.eval_rays, resolution=args.image_resolution)
    return {"mesh": spec, "triangles": mesh.num_triangles, "variant": f"decimate@{label}", "method": "decimation",
            "kept_triangles": small.num_triangles, "metrics": metrics, "memory": mem, "bytes": mem["bytes"]}


COLUMNS = ["mesh", "variant", "steps", "nodes", "train_s", "load", "acc_out", "t_err_med", "n_err_deg_med", "acc_surf",
           "flip_normal", "bytes_mb", "vs_bvh_a", "vs_bvh_b", "rays_per_s", "occl_rays_per_s", "embree_rays_per_s", "vs_embree"]


def summary_row(r: dict) -> dict:
    m, tr, inf = r["metrics"], r.get("training", {}), r.get("inference", {})
    return {
        "mesh": r["mesh"], "variant": r["variant"], "steps": tr.get("steps"), "nodes": r.get("nodes", r.get("kept_triangles")),
        "train_s": tr.get("seconds"), "load": max(tr["load_average_1min_before_after"]) if tr else None,
        "acc_out": m["outside"]["accuracy"], "t_err_med": m["outside"]["t_error_median"],
        "n_err_deg_med": m["outside"]["normal_error_deg_median"], "acc_surf": m["surface"]["accuracy"],
        "flip_normal": m["images"]["normal_flip"], "bytes_mb": r["bytes"] / 2**20,
        "vs_bvh_a": r.get("over_bvh_a"), "vs_bvh_b": r.get("over_bvh_b"),
        "rays_per_s": inf.get("neural_rays_per_s"), "occl_rays_per_s": inf.get("neural_occluded_rays_per_s"),
        "embree_rays_per_s": inf.get("embree_rays_per_s"), "vs_embree": inf.get("vs_embree"),
    }


def plot(runs: dict, scenes_json: Path | None, path: Path) -> None:
    """FLIP against bytes: per mesh, LSNIF / N-BVH (table sizes) / decimation (the rows in ``runs``);
    per scene, every variant of the scenes JSON rows that have a decimation."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    meshes = list(dict.fromkeys(r["mesh"] for r in runs.values()))
    scene_rows = json.loads(scenes_json.read_text())["rows"] if scenes_json and scenes_json.is_file() else []
    scene_rows = [r for r in scene_rows if any(k.startswith("flip_decimate") for k in r)]
    cols, rows_n = max(len(meshes), len(scene_rows), 1), 1 + bool(scene_rows)
    fig, axes = plt.subplots(rows_n, cols, figsize=(3.6 * cols, 3.4 * rows_n), dpi=110, squeeze=False)
    for ax in axes.flat[len(meshes):cols]:
        ax.set_visible(False)
    for ax in axes.flat[cols + len(scene_rows):]:
        ax.set_visible(False)
    style = {"lsnif": ("o", "C0", "LSNIF"), "nbvh": ("s", "C1", "N-BVH"), "decimation": ("^", "C2", "decimation")}
    for ax, mesh in zip(axes[0], meshes):
        rows = [r for r in runs.values() if r["mesh"] == mesh]
        for method, (marker, color, label) in style.items():
            pts = sorted((r["bytes"] / 2**20, r["metrics"]["images"]["normal_flip"], r["variant"]) for r in rows if r["method"] == method)
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=marker, color=color, label=label,
                    linestyle="-" if method != "lsnif" else "none")
            for x, y, v in pts:
                if method != "decimation":
                    ax.annotate(v.split(":", 1)[1], (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points", color=color)
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):  # plain numbers: the ranges are too narrow for powers of ten
            axis.set_major_formatter(ticker.FormatStrFormatter("%.3g"))
            axis.set_minor_formatter(ticker.FormatStrFormatter("%.3g"))
        ax.tick_params(which="minor", labelsize=6)
        ax.set_title(mesh.split("/")[-1].replace("procedural:", ""), fontsize=9)
        ax.set_xlabel("bytes [MiB]")
    for ax, r in zip(axes[-1], scene_rows):
        for key, value in r.items():
            if not key.startswith("flip_") or key == "flip_floor":
                continue
            label = key.removeprefix("flip_")
            method = "decimation" if label.startswith("decimate") else ("nbvh" if label.startswith("nbvh") else "lsnif")
            marker, color, _ = style[method]
            ax.scatter(r[f"neural_{label}_bytes"] / 2**20, value, marker=marker, color=color)
            ax.annotate(label, (r[f"neural_{label}_bytes"] / 2**20, value), fontsize=6, xytext=(3, 3), textcoords="offset points")
        ax.axhline(r["flip_floor"], color="gray", linestyle=":", label="noise floor")
        name = "shared" if r["scene"].endswith("shared_scene/scene.toml") else r["scene"].replace("builtin:", "")
        ax.set_title(f"scene {name}", fontsize=9)
        ax.set_xlabel("bytes of the replaced objects [MiB]")
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("normal-image FLIP vs exact (4 orbit views)")
    axes[0][0].legend(fontsize=7)
    if scene_rows:
        axes[-1][0].set_ylabel("render FLIP vs exact")
    fig.tight_layout()
    save_figure(fig, path)


def main() -> None:
    from _common import RESULTS_DIR, print_table, read_results, write_results

    p = ArgumentParser(description=description(__doc__))
    p.add_argument("meshes", nargs="*")
    p.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS, help="METHOD:PRESET[:tN] (default: %(default)s)")
    p.add_argument("--steps", nargs="*", default=[], metavar="METHOD=N", help="training steps per method (default: the preset's)")
    p.add_argument("--batch", nargs="*", default=[], metavar="METHOD=N", help="training rays per step per method (default: the preset's)")
    p.add_argument("--decimate", nargs="*", default=None, metavar="VARIANT",
                   help="also decimate the mesh to the bytes of these variants (no names: every variant's)")
    p.add_argument("--decimate-only", action="store_true", help="only the decimation rows (the variants' rows must exist)")
    p.add_argument("--eval-rays", type=positive_int, default=1 << 17)
    p.add_argument("--image-resolution", type=positive_int, default=256)
    p.add_argument("--inference-rays", type=nonnegative_int, default=1 << 18, help="0 skips the speed test")
    p.add_argument("--repeats", type=positive_int, default=3)
    p.add_argument("--models-dir", type=Path, default=DEFAULT_MODELS)
    p.add_argument("--train-only", action="store_true", help="only train (or find) the models")
    p.add_argument("--plot", action="store_true",
                   help="draw results/NAME_flip_memory.png from the JSON (rows trained as --steps/--batch say; and --scenes-json)")
    p.add_argument("--scenes-json", type=Path, default=RESULTS_DIR / "scenes_methods.json")
    p.add_argument("--name", type=result_name, default="methods", help="results file: benchmarks/results/NAME.json (rows merge into it)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args()
    # Every check before the first training (a bad later mesh or variant must not cost the earlier ones' runs).
    steps, batch = per_method(args.steps, "--steps"), per_method(args.batch, "--batch")
    for spec in args.meshes:
        check_mesh_spec(spec)
    for variant in args.variants + (args.decimate or []):
        variant_config(variant, steps, batch)

    path = RESULTS_DIR / f"{args.name}.json"
    runs = read_results(args.name).get("runs", {})
    if args.decimate is not None and not args.train_only and not args.plot:
        for variant in args.decimate or args.variants:  # each needs its variant's row: made by this run or an earlier one
            _, cfg = variant_config(variant, steps, batch)
            for spec in args.meshes if args.decimate_only or variant not in args.variants else []:
                if f"{spec}|{variant}|{cfg.training.steps}x{cfg.training.batch_size}" not in runs:
                    raise ConfigError(f"--decimate {variant}: {path} has no {variant} row of {spec} at these steps and batch "
                                      "(run the variant first, or name it in --variants)")
    if not args.plot:
        check_output_folder(args.models_dir, "models")
    if args.plot:
        out = RESULTS_DIR / f"{args.name}_flip_memory.png"
        # Only models trained as --steps / --batch say (one consistent setting per method), and their decimations.
        keep = {}
        for key, r in runs.items():
            if r["method"] == "decimation" or (args.meshes and r["mesh"] not in args.meshes):
                continue
            cfg = variant_config(r["variant"], steps, batch)[1].training
            if (r["training"]["steps"], r["training"]["batch_size"]) == (cfg.steps, cfg.batch_size):
                keep[key] = r
                keep.update({k: v for k, v in runs.items() if k == f"{r['mesh']}|decimate@{r['variant']}"})
        plot(keep, args.scenes_json, out)
        print(f"wrote {out}")
        return

    def save():
        write_results(args.name, [summary_row(v) for v in runs.values()], extra={"runs": runs})

    for spec in args.meshes:
        mesh = resolve_mesh(spec)
        classical = classical_memory(mesh).as_dict()
        for variant in [] if args.decimate_only else args.variants:
            _, cfg = variant_config(variant, steps, batch)
            model, info = train_or_load(mesh, cfg, args.models_dir, args.quiet)
            if args.train_only:
                continue
            row = measure_model(spec, mesh, classical, variant, model, info, args)
            row["classical"] = classical
            row["load_average_1min_at_end"] = os.getloadavg()[0]
            runs[f"{spec}|{variant}|{row['training']['steps']}x{row['training']['batch_size']}"] = row
            save()
            print_table([summary_row(row)], COLUMNS)
        if args.decimate is not None and not args.train_only:
            for variant in args.decimate or args.variants:
                _, cfg = variant_config(variant, steps, batch)
                source = runs[f"{spec}|{variant}|{cfg.training.steps}x{cfg.training.batch_size}"]
                row = measure_decimation(spec, mesh, source["bytes"], variant, args)
                runs[f"{spec}|decimate@{variant}"] = row
                save()
                print_table([summary_row(row)], COLUMNS)
    if runs and not args.train_only:
        print_table([summary_row(v) for v in runs.values()], COLUMNS)
        print(f"wrote {path}")


if __name__ == "__main__":
    run_main(main)
