"""The LSNIF paper's Table 1 on our scenes: memory, render time and FLIP of hybrid vs exact rendering.

For each scene: convert it with the `hq` and `lq` presets (models cached in --work), render it
exactly (seed S and, for the noise floor, seed S+1) and hybrid (`hq`, `lq`; seed S: correlated
sampling) at equal spp and resolution, and report:

  neural objects (unique), neural memory, BVH A and BVH B of the replaced meshes and their ratios
  to neural memory, render times exact / hybrid hq / hybrid lq (ratios in the same run), FLIP hq /
  lq vs exact, and the noise floor (FLIP exact vs exact, other seed).

Scenes: the built-ins (at --detail, default 2, or per scene with name?detail=N) and "shared", a
scene of ../shared/meshes objects Loop-subdivided to >= 1M triangles each (skipped when absent).
Writes benchmarks/results/scenes.json and a FLIP-vs-memory plot benchmarks/results/scenes.png.

    python benchmarks/bench_scenes.py                       # all scenes, 256x256, 64 spp
    python benchmarks/bench_scenes.py --scenes builtin:hairball?detail=6 --spp 16 --res 128
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import RESULTS_DIR, print_table, write_results  # noqa: E402

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
    for name, (file, loops) in sources.items():
        target = folder / f"{name}_loop{loops}.ply"
        if not target.is_file():
            mesh = load_mesh(SHARED / file).subdivided(loops)
            trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(target)
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
                       transform=TransformSpec(translate=(0.6, -0.55, 0.2), rotate=(-90, 0, 0), scale=0.9)),
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


def run_scene(scene: str, work: Path, args) -> dict:
    from neuralrt.eval.image_metrics import compare_images
    from neuralrt.io.images import write_png
    from neuralrt.render.integrator import render
    from neuralrt.scene.convert import convert_scene, neural_bytes, replaced_memory
    from neuralrt.scene.loader import load_scene

    tag = scene.replace("builtin:", "").replace("?", "_").replace("=", "").replace("/", "_")
    out = work / tag
    out.mkdir(parents=True, exist_ok=True)
    res = (args.res, args.res)
    common = dict(spp=args.spp, max_depth=args.max_depth, progress=False)

    # Train (or reuse) both presets first, so renders are timed back to back on a quiet machine.
    reports = {preset: convert_scene(scene, out / f"{preset}.toml", models_dir=work / "models", preset=preset,
                                     steps=args.steps, min_triangles=args.min_triangles, progress=not args.quiet)
               for preset in ("hq", "lq")}
    scenes = {"exact": load_scene(scene, resolution=res)}
    scenes.update({preset: load_scene(out / f"{preset}.toml", resolution=res) for preset in ("hq", "lq")})
    # Same seed for exact and hybrid (correlated sampling); timings: best of --repeats, interleaved.
    images, seconds = {}, {name: float("inf") for name in scenes}
    for _ in range(args.repeats):
        for name, loaded in scenes.items():
            result = render(loaded, seed=args.seed, **common)
            images[name], seconds[name] = result.image, min(seconds[name], result.seconds)
    floor = render(scenes["exact"], seed=args.seed + 1, **common)
    write_png(out / "exact.png", images["exact"])
    row = {"scene": scene, "res": args.res, "spp": args.spp, "exact_s": seconds["exact"],
           "flip_floor": compare_images(images["exact"], floor.image).flip}
    for preset, report in reports.items():
        write_png(out / f"hybrid_{preset}.png", images[preset])
        row[f"flip_{preset}"] = compare_images(images["exact"], images[preset]).flip
        row[f"{preset}_s"] = seconds[preset]
        row[f"time_{preset}_ratio"] = seconds[preset] / seconds["exact"]
        row[f"train_{preset}_s"] = report.train_seconds
        row[f"neural_{preset}_bytes"] = neural_bytes(scenes[preset])
    memory = replaced_memory(scenes["hq"])  # both presets replace the same meshes
    report = reports["hq"]
    row["objects"], row["unique"] = report.neural_objects, report.unique_models
    row["triangles"] = memory["neural_triangles"]
    row["bvh_a_bytes"], row["bvh_b_bytes"] = memory["bvh_a_bytes"], memory["bvh_b_bytes"]
    row["bvh_a_ratio"] = row["bvh_a_bytes"] / row["neural_hq_bytes"]
    row["bvh_b_ratio"] = row["bvh_b_bytes"] / row["neural_hq_bytes"]
    return row


def short_name(scene: str) -> str:
    return "shared" if scene.endswith("shared_scene/scene.toml") else scene.replace("builtin:", "").replace("?detail=", " d")


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
    for k, r in enumerate(rows):
        color = f"C{k}"
        for preset, marker, dy in (("hq", "o", 4), ("lq", "s", -10)):
            ax.scatter(r[f"neural_{preset}_bytes"] / 2**20, r[f"flip_{preset}"], marker=marker, color=color)
            ax.annotate(f"{short_name(r['scene'])} {preset}", (r[f"neural_{preset}_bytes"] / 2**20, r[f"flip_{preset}"]),
                        fontsize=7, xytext=(5, dy), textcoords="offset points", color=color)
        ax.scatter(r["bvh_a_bytes"] / 2**20, r["flip_floor"], marker="x", color=color)
        ax.annotate(short_name(r["scene"]), (r["bvh_a_bytes"] / 2**20, r["flip_floor"]), fontsize=7,
                    xytext=(-5, 5), textcoords="offset points", ha="right", color=color)
    ax.set_xscale("log")
    ax.set_xlabel("memory of replaced objects [MiB] (o hq, s lq, x BVH A at noise floor)")
    ax.set_ylabel("FLIP vs exact render")
    ax.set_title("Hybrid LSNIF rendering: error vs memory")
    fig.tight_layout()
    fig.savefig(path)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="*", default=DEFAULT_SCENES)
    p.add_argument("--res", type=int, default=256)
    p.add_argument("--spp", type=int, default=64)
    p.add_argument("--max-depth", type=int, default=4)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--repeats", type=int, default=2, help="timed renders per scene and mode (best is kept)")
    p.add_argument("--steps", type=int, default=None, help="training steps (default: the preset's)")
    p.add_argument("--min-triangles", type=int, default=None)
    p.add_argument("--work", type=Path, default=Path("/tmp/neuralrt-bench-scenes"))
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args()
    rows = []
    for scene in args.scenes:
        if scene == "shared":
            path = shared_scene(args.work)
            if path is None:
                print("skipping 'shared': ../shared/meshes not found")
                continue
            scene = str(path)
        start = time.perf_counter()
        rows.append(run_scene(scene, args.work, args))
        rows[-1]["wall_s"] = time.perf_counter() - start
        print_table(rows[-1:], ["scene", "objects", "unique", "neural_hq_bytes", "bvh_a_ratio", "flip_hq", "flip_floor"])
    columns = ["scene", "objects", "unique", "triangles", "neural_hq_bytes", "neural_lq_bytes", "bvh_a_bytes", "bvh_a_ratio",
               "bvh_b_bytes", "bvh_b_ratio", "exact_s", "time_hq_ratio", "time_lq_ratio", "flip_hq", "flip_lq", "flip_floor",
               "train_hq_s", "train_lq_s"]
    print()
    print_table(rows, columns)
    path = write_results("scenes", rows, {"settings": vars(args) | {"work": str(args.work)}})
    plot(rows, RESULTS_DIR / "scenes.png")
    print(f"\nwrote {path} and {RESULTS_DIR / 'scenes.png'}")


if __name__ == "__main__":
    main()
