"""The LSNIF paper's Table 1 on our scenes: memory, render time and FLIP of hybrid vs exact
rendering, for any of the methods (LSNIF, N-BVH) and, at the same bytes, quadric decimation.

For each scene: replace its large objects (the converter's rule) by each variant's models (one per
unique mesh, trained once and cached in --models-dir under the converter's names; bench_methods.py
shares them), render it exactly (seed S and, for the noise floor, seed S+1) and with each variant
(seed S: correlated sampling) at equal spp and resolution, and report: neural objects (unique),
bytes per variant, BVH A and BVH B of the replaced meshes and their ratios to each variant's bytes,
render times (ratios to exact in the same run, best of --repeats, interleaved), FLIP vs exact (same
seed: shared noise, mostly the variant's own error), FLIP vs the exact render at seed S+1
(``other_seed_flip_*``: the figure to hold against the noise floor, FLIP exact vs that render) and
each variant's summed training time. With
--decimate V, the large meshes are also replaced by quadric decimations (fast-simplification)
whose mesh + BVH A bytes match variant V's model bytes; they answer every ray, camera rays included.

Scenes: the built-ins (at --detail, default 2, or per scene with name?detail=N) and "shared", a
scene of ../shared/meshes objects Loop-subdivided to >= 1M triangles each (skipped when absent).
Rows merge by scene into benchmarks/results/NAME.json; a FLIP-vs-memory plot goes to NAME.png.

    python benchmarks/bench_scenes.py                       # all scenes, LSNIF hq and lq, 256x256, 64 spp
    python benchmarks/bench_scenes.py --scenes builtin:hairball?detail=6 --spp 16 --res 128
    python benchmarks/bench_scenes.py --variants lsnif:hq nbvh:cpu:t15 nbvh:cpu --decimate lsnif:hq \\
        --models-dir /tmp/methods-models --name scenes_methods --res 128 --spp 64
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (RESULTS_DIR, ArgumentParser, check_output_folder, check_scene, description,  # noqa: E402
                     nonnegative_int, positive_int, print_table, read_results, result_name, run_main, save_figure,
                     seed_int, write_results)

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"
DEFAULT_SCENES = ["builtin:cornell-statue", "builtin:hairball", "builtin:foliage", "builtin:instances", "shared"]


def shared_scene(work: Path) -> Path | None:
    """A scene of shared meshes subdivided to >= 1M triangles each (written once into ``work``)."""
    from neuralrt.geometry.mesh import load_mesh
    from neuralrt.scene.schema import (CameraSpec, DiffuseMaterialSpec, EmissiveMaterialSpec, EnvironmentSpec,
                                       GeneratorSpec, ObjectSpec, PlasticMaterialSpec, SceneSpec, TransformSpec)
    from neuralrt.scene.scene import save_scene
    import trimesh

    sources = {"bunny": ("bunny00.off", 2), "devil": ("mannequin-devil.off", 3)}
    if not all((SHARED / f).is_file() for f, _ in sources.values()):
        return None
    folder = work / "shared_scene"
    folder.mkdir(parents=True, exist_ok=True)
    extent = {}  # largest side of each file: the devil's is ~42 units (the bunny's ~1), so its scale is per unit of it
    for name, (file, loops) in sources.items():
        target = folder / f"{name}_loop{loops}.ply"
        if not target.is_file():
            mesh = load_mesh(SHARED / file).subdivided(loops)
            trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(target)
        extent[name] = float(trimesh.load(target, process=False).extents.max())
    spec = SceneSpec(
        camera=CameraSpec(position=(0.0, 0.6, 3.2), look_at=(0.0, -0.2, 0.0), fov=40.0),
        materials=[PlasticMaterialSpec(name="clay", albedo=(0.7, 0.55, 0.45), roughness=0.3),
                   DiffuseMaterialSpec(name="floor", albedo=(0.5, 0.5, 0.5)),
                   EmissiveMaterialSpec(name="light", emission=(6.0, 6.0, 6.0))],
        objects=[
            ObjectSpec(name="bunny", mesh=str(folder / "bunny_loop2.ply"), material="clay",
                       transform=TransformSpec(translate=(-0.55, -0.62, 0.0), scale=0.8)),
            ObjectSpec(name="bunny2", mesh=str(folder / "bunny_loop2.ply"), material="clay",
                       transform=TransformSpec(translate=(0.2, -0.75, -0.8), rotate=(0, -60, 0), scale=0.5)),
            ObjectSpec(name="devil", mesh=str(folder / "devil_loop3.ply"), material="clay",
                       transform=TransformSpec(translate=(0.6, -0.52, 0.2), rotate=(-90, 0, 0), scale=0.9 / extent["devil"])),
            ObjectSpec(name="floor", generator=GeneratorSpec(name="plane", params={"size": 8.0}), material="floor",
                       transform=TransformSpec(translate=(0.0, -1.0, 0.0))),
            ObjectSpec(name="light", generator=GeneratorSpec(name="plane", params={"size": 1.5}), material="light",
                       transform=TransformSpec(translate=(0.0, 2.5, 0.0), rotate=(180, 0, 0))),
        ],
        environment=EnvironmentSpec(color=(0.3, 0.35, 0.45)),
    )
    path = folder / "scene.toml"
    save_scene(spec, path)
    return path


def variant_label(variant: str) -> str:
    """Row-key label of a variant: LSNIF presets keep their bare names (hq, lq: the earlier JSON's keys)."""
    if variant.startswith("lsnif:") and variant.count(":") == 1 and "+" not in variant:
        return variant.split(":")[1]
    return variant.replace(":", "_").replace("+", "_")


def scene_objects(scene: str, min_triangles: int | None):
    """(spec, per-object meshes, indices of the objects a conversion replaces): the converter's own choice."""
    from neuralrt.scene.convert import selected_objects  # the converter's selection rule
    from neuralrt.scene.loader import load_scene_spec, shape_for

    spec, _, label = load_scene_spec(scene)
    shapes: dict = {}
    meshes = [getattr(shape_for(obj, shapes, label, f"objects.{i}"), "mesh", None) for i, obj in enumerate(spec.objects)]
    return spec, meshes, selected_objects(spec, meshes, None, min_triangles)


def convert_variant(scene: str, output: Path, variant: str, args) -> dict:
    """Write ``output``: the scene with its large objects answered by ``variant``'s models
    (bench_methods' METHOD:PRESET[:tN], trained once per unique mesh and cached in --models-dir under
    the converter's names); returns {"bytes_by_mesh": ..., "train_s": summed recorded training time}."""
    from bench_methods import per_method, train_or_load, variant_config
    from neuralrt.scene.scene import save_scene

    spec, meshes, chosen = scene_objects(scene, args.min_triangles)
    _, cfg = variant_config(variant, per_method(args.steps), per_method(args.batch))
    out_spec, trained, train_s = spec.model_copy(deep=True), {}, 0.0
    for i in chosen:
        if id(meshes[i]) not in trained:
            model, info = train_or_load(meshes[i], cfg, args.models_dir, args.quiet)
            from bench_methods import cached_model_path

            trained[id(meshes[i])] = (cached_model_path(meshes[i], cfg, args.models_dir), model.memory_bytes().total)
            train_s += model.training_record["seconds"]
        out_spec.objects[i].model = str(trained[id(meshes[i])][0])
    save_scene(out_spec, output)
    return {"bytes_by_mesh": {meshes[i].name: trained[id(meshes[i])][1] for i in chosen}, "train_s": train_s}


def decimate_variant(scene: str, output: Path, bytes_by_mesh: dict, args) -> dict:
    """Write ``output``: the scene with each large object's mesh replaced (for every ray, camera rays
    included) by its quadric decimation whose mesh + BVH A bytes match ``bytes_by_mesh[mesh name]``."""
    import trimesh
    from bench_methods import decimated_mesh
    from neuralrt.scene.scene import save_scene

    spec, meshes, chosen = scene_objects(scene, args.min_triangles)
    out_spec, done = spec.model_copy(deep=True), {}
    for i in chosen:
        if id(meshes[i]) not in done:
            small, mem = decimated_mesh(meshes[i], bytes_by_mesh[meshes[i].name])
            path = output.parent / f"{output.stem}-{len(done)}.ply"
            trimesh.Trimesh(small.vertices, small.faces, process=False).export(path)
            done[id(meshes[i])] = (path, mem)
        out_spec.objects[i] = out_spec.objects[i].model_copy(update={"mesh": str(done[id(meshes[i])][0]), "generator": None})
    save_scene(out_spec, output)
    return {"bytes": int(sum(m["bytes"] for _, m in done.values())),
            "kept_triangles": int(sum(m["triangles"] for _, m in done.values()))}


def run_scene(scene: str, work: Path, args) -> dict:
    from neuralrt.eval.image_metrics import compare_images
    from neuralrt.io.images import write_png
    from neuralrt.methods import is_neural
    from neuralrt.render.integrator import render, warm_up
    from neuralrt.scene.convert import neural_bytes, replaced_memory
    from neuralrt.scene.loader import load_scene

    tag = scene.replace("builtin:", "").replace("?", "_").replace("=", "").replace("/", "_")
    out = work / tag
    out.mkdir(parents=True, exist_ok=True)
    res = (args.res, args.res)
    common = dict(spp=args.spp, max_depth=args.max_depth, progress=False)

    # Train (or reuse) every variant's models first, so renders are timed back to back.
    # A variant ending in "+neural" is the same models answering camera rays too (--primary neural).
    labels = {variant: variant_label(variant) for variant in args.variants}
    bases = {variant: variant.removesuffix("+neural") for variant in args.variants}
    converted = {base: convert_variant(scene, out / f"{variant_label(base)}.toml", base, args) for base in dict.fromkeys(bases.values())}
    reports = {variant: converted[bases[variant]] for variant in args.variants}
    scenes = {"exact": load_scene(scene, resolution=res)}
    scenes.update({labels[v]: load_scene(out / f"{variant_label(bases[v])}.toml", resolution=res,
                                         primary="neural" if v.endswith("+neural") else "exact") for v in args.variants})
    decimated = {}
    for source in args.decimate or []:
        label = f"decimate_{labels[source]}"
        decimated[label] = decimate_variant(scene, out / f"{label}.toml", reports[source]["bytes_by_mesh"], args)
        scenes[label] = load_scene(out / f"{label}.toml", resolution=res)
    # Same seed for exact and the others (correlated sampling); timings: best of --repeats, interleaved.
    images, seconds = {}, {name: float("inf") for name in scenes}
    for loaded in scenes.values():  # untimed: a scene's first render loads its kernels (--repeats 1 would time that)
        warm_up(loaded, max_depth=args.max_depth)
    for _ in range(args.repeats):
        for name, loaded in scenes.items():
            result = render(loaded, seed=args.seed, **common)
            images[name], seconds[name] = result.image, min(seconds[name], result.seconds)
    floor = render(scenes["exact"], seed=args.seed + 1, **common)
    write_png(out / "exact.png", images["exact"])
    import hashlib

    row = {"scene": scene, "res": args.res, "spp": args.spp, "exact_s": seconds["exact"],
           "scene_sha256": hashlib.sha256(Path(scene).read_bytes()).hexdigest() if Path(scene).is_file() else None,
           "flip_floor": compare_images(images["exact"], floor.image).flip}
    for name in scenes:
        if name == "exact":
            continue
        write_png(out / f"{'hybrid_' if name in labels.values() else ''}{name}.png", images[name])
        row[f"flip_{name}"] = compare_images(images["exact"], images[name]).flip
        row[f"other_seed_flip_{name}"] = compare_images(floor.image, images[name]).flip
        row[f"{name}_s"] = seconds[name]
        row[f"time_{name}_ratio"] = seconds[name] / seconds["exact"]
        if name in decimated:
            row[f"neural_{name}_bytes"] = decimated[name]["bytes"]  # mesh + BVH A of the decimated meshes
            row[f"{name}_triangles"] = decimated[name]["kept_triangles"]
        else:
            row[f"train_{name}_s"] = reports[next(v for v, lb in labels.items() if lb == name)]["train_s"]
            row[f"neural_{name}_bytes"] = neural_bytes(scenes[name])
    first = labels[next(v for v in args.variants if not v.endswith('+neural'))]
    memory = replaced_memory(scenes[first])  # every variant replaces the same meshes
    row["objects"] = sum(1 for i in scenes[first].accel.instances if is_neural(i.blas))
    row["unique"] = len(reports[args.variants[0]]["bytes_by_mesh"])
    row["triangles"] = memory["neural_triangles"]
    row["bvh_a_bytes"], row["bvh_b_bytes"] = memory["bvh_a_bytes"], memory["bvh_b_bytes"]
    for name in labels.values():
        row[f"bvh_a_ratio_{name}"] = row["bvh_a_bytes"] / row[f"neural_{name}_bytes"]
        row[f"bvh_b_ratio_{name}"] = row["bvh_b_bytes"] / row[f"neural_{name}_bytes"]
    row["load_average_1min_at_end"] = os.getloadavg()[0]
    return row


SCENE_WIDE = ("scene", "settings", "res", "spp", "scene_sha256", "exact_s", "flip_floor", "objects", "unique", "triangles", "bvh_a_bytes",
              "bvh_b_bytes", "load_average_1min_at_end", "wall_s", "later_runs")


def merge_row(rows: list[dict], row: dict, scene: str) -> list[dict]:
    """``rows`` with ``row`` merged into the scene's row: a later run of other variants adds their
    columns (FLIP vs the same seed's exact image; time ratios to that run's own exact render) and
    keeps the first run's scene-wide figures, the later run's going to ``later_runs``; a run at
    another resolution, spp or scene file (``scene_sha256``), or a re-run of every variant the row
    holds, replaces the row (else its scene-wide figures would be an earlier run's, beside ratios
    to this run's exact render)."""
    old = next((r for r in rows if short_name(r["scene"]) == short_name(scene)), None)
    rest = [r for r in rows if r is not old]
    if old is None or (old["res"], old["spp"], old.get("scene_sha256")) != (row["res"], row["spp"], row.get("scene_sha256")):
        return rest + [row]
    if _variants(old) <= _variants(row):
        return rest + [row]
    later = {k: row[k] for k in SCENE_WIDE if k in row and k not in ("scene", "later_runs")}
    later["variants"] = sorted(_variants(row))
    merged = {**old, **{k: v for k, v in row.items() if k not in SCENE_WIDE}}
    merged["later_runs"] = old.get("later_runs", []) + [later]
    return rest + [merged]


def _variants(row: dict) -> set[str]:
    """The variant labels whose figures ``row`` holds (its ``flip_<label>`` columns)."""
    return {k.removeprefix("flip_") for k in row if k.startswith("flip_") and k != "flip_floor"}


def short_name(scene: str) -> str:
    return "shared" if scene.endswith("shared_scene/scene.toml") else scene.replace("builtin:", "").replace("?detail=", " d")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    markers = "osD^vP*"
    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for k, r in enumerate(rows):
        color = f"C{k}"
        labels = [key.removeprefix("flip_") for key in r if key.startswith("flip_") and key != "flip_floor"]
        for j, label in enumerate(labels):
            x, y = r[f"neural_{label}_bytes"] / 2**20, r[f"flip_{label}"]
            ax.scatter(x, y, marker=markers[j % len(markers)], color=color)
            ax.annotate(f"{short_name(r['scene'])} {label}", (x, y), fontsize=6, xytext=(5, 4 - 7 * j), textcoords="offset points", color=color)
        ax.scatter(r["bvh_a_bytes"] / 2**20, r["flip_floor"], marker="x", color=color)
        ax.annotate(short_name(r["scene"]), (r["bvh_a_bytes"] / 2**20, r["flip_floor"]), fontsize=7,
                    xytext=(-5, 5), textcoords="offset points", ha="right", color=color)
    ax.set_xscale("log")
    ax.set_xlabel("memory of replaced objects [MiB] (x: BVH A at the noise floor)")
    ax.set_ylabel("FLIP vs exact render")
    ax.set_title("Hybrid rendering: error vs memory")
    fig.tight_layout()
    save_figure(fig, path)


def check_arguments(args) -> None:
    """Every scene, variant, count and folder, before anything is trained or written (one-line errors)."""
    from bench_methods import per_method, variant_config
    from neuralrt.errors import ConfigError

    if not args.scenes:
        raise ConfigError("--scenes: no scene given")
    for scene in args.scenes:
        if scene != "shared":
            check_scene(scene)
    steps, batch = per_method(args.steps, "--steps"), per_method(args.batch, "--batch")
    for variant in args.variants:
        variant_config(variant.removesuffix("+neural"), steps, batch)
    if all(v.endswith("+neural") for v in args.variants):
        raise ConfigError("--variants: at least one variant without +neural (its scene gives the replaced objects' figures)")
    for source in args.decimate or []:
        if source not in args.variants:
            raise ConfigError(f"--decimate {source}: not one of --variants ({' '.join(args.variants)}): decimation matches the bytes of a variant's models")
    check_output_folder(args.work, "work files")
    check_output_folder(args.models_dir, "models")
    read_results(args.name)  # (an unreadable earlier results file: said now, not after the renders)


def main() -> None:
    p = ArgumentParser(description=description(__doc__))
    p.add_argument("--scenes", nargs="*", default=DEFAULT_SCENES)
    p.add_argument("--res", type=positive_int, default=256)
    p.add_argument("--spp", type=positive_int, default=64)
    p.add_argument("--max-depth", type=positive_int, default=4)
    p.add_argument("--seed", type=seed_int, default=1)
    p.add_argument("--repeats", type=positive_int, default=2, help="timed renders per scene and mode (best is kept)")
    p.add_argument("--steps", nargs="*", default=[], metavar="METHOD=N", help="training steps per method (default: the presets')")
    p.add_argument("--batch", nargs="*", default=[], metavar="METHOD=N", help="training rays per step per method (default: the presets')")
    p.add_argument("--min-triangles", type=nonnegative_int, default=None)
    p.add_argument("--variants", nargs="+", default=["lsnif:hq", "lsnif:lq"],
                   help="METHOD:PRESET[:tN] answering the large objects (bench_methods.py's variants; default: %(default)s); "
                        "a trailing +neural: the same models answer camera rays too (--primary neural)")
    p.add_argument("--decimate", nargs="*", default=None, metavar="VARIANT",
                   help="also render with each large mesh decimated to the bytes of these variants' models")
    p.add_argument("--models-dir", type=Path, default=None, help="model cache (default: WORK/models); bench_methods.py's is /tmp/methods-models")
    p.add_argument("--name", type=result_name, default="scenes", help="results: benchmarks/results/NAME.json and NAME.png (rows merge by scene)")
    p.add_argument("--work", type=Path, default=Path("/tmp/neuralrt-bench-scenes"))
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args()
    args.models_dir = args.models_dir or args.work / "models"
    check_arguments(args)
    path = RESULTS_DIR / f"{args.name}.json"
    previous = read_results(args.name)
    rows = previous.get("rows", [])
    settings = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}
    # Rows carry the settings they were measured with; the file's earlier run-level settings are kept
    # (files from before per-row settings describe only their last run there).
    earlier = previous.get("earlier_settings", []) + ([previous["settings"]] if previous.get("settings") else [])
    for scene in args.scenes:
        if scene == "shared":
            path = shared_scene(args.work)
            if path is None:
                print("skipping 'shared': ../shared/meshes not found")
                continue
            scene = str(path)
        start = time.perf_counter()
        row = run_scene(scene, args.work, args)
        row["wall_s"] = time.perf_counter() - start
        row["settings"] = settings
        rows = merge_row(rows, row, scene)
        path = write_results(args.name, rows, {"settings": settings, "earlier_settings": earlier})
        print_table([row], [k for k in row if k.startswith(("flip", "other_seed_flip", "neural_", "time_"))])
    labels = [variant_label(v) for v in args.variants] + [f"decimate_{variant_label(v)}" for v in args.decimate or []]
    columns = ["scene", "objects", "unique", "triangles", "bvh_a_bytes", "bvh_b_bytes", "exact_s", "flip_floor"]
    columns += [f"{prefix}{label}{suffix}" for label in labels
                for prefix, suffix in (("neural_", "_bytes"), ("time_", "_ratio"), ("flip_", ""), ("other_seed_flip_", ""))]
    print()
    print_table(rows, columns)
    plot(rows, RESULTS_DIR / f"{args.name}.png")
    print(f"\nwrote {path} and {RESULTS_DIR / f'{args.name}.png'}")


if __name__ == "__main__":
    run_main(main)
