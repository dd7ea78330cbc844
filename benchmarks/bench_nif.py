"""NIF shadow rays against exact shadow rays, in the paper's Table 2 form, plus image quality.

    python benchmarks/bench_nif.py [--resolution 128] [--spp 64] [--train-spp 32] [--passes 1] [--pair-fraction 0.5] [--repeats 3]
                                   [--shadow-rays first_hit|every_hit] [--scenes cornell-statue:2,cornell-statue:4] [--device cpu] [--name NAME]

Scenes: ``NAME:D`` is ``builtin:NAME?detail=D`` with NIF on every statue (cornell-statue detail 2 =
75,720 triangles, 4 = statue(4), 1.2M, 5 = statue(5), 4.8M; ``instances:D`` = 12 instances of
statue(D-1) sharing one NIF object among 24 other objects). ``mesh:FILE@loopK`` is FILE from
../shared/meshes Loop-subdivided K times (subdivided once and cached as binary PLY under
``--mesh-cache``, default /tmp/neuralrt-nif-meshes), scaled to 1.6 units, on a floor under a square
area light, with NIF on it. Per scene, one NIF render with ``audit=True``: every shadow-ray batch NIF
takes (``--shadow-rays``: those of the camera rays' hits, the default and the paper's use, or of
every bounce) in the samples after training is answered by the NIF stand-in (exact objects + NIF
stages 1 and 2) AND by the whole exact accelerator (Embree on the CPU, OptiX on CUDA), timed in the
same run on the same rays; ``exact_only_rays`` counts the other shadow rays. Columns:

- ``tris``, ``shadow_rays``, ``outer``, ``inner`` (pairs each network answered), ``exact_ms`` /
  ``nif_ms`` (the shadow rays NIF takes, of the NIF samples), ``speedup`` = exact / NIF (the paper's "x");
- ``disagree``: share of shadow rays whose answer differs from the exact one, and ``visible_err``
  the same for always answering "visible" for the statue (the baseline NIF must beat);
- ``psnr_same`` / ``flip_same``: the NIF render against the same samples with exact shadow rays
  (only the answers differ: the NIF error itself); ``psnr`` / ``flip``: against an exact render
  with other samples (seed 1), next to ``psnr_floor`` / ``flip_floor``, exact against exact with
  other samples (the noise floor at this spp);
- ``train_s_per_spp``, ``train_share`` (training time over the whole NIF render's time), both the
  median of ``--repeats`` NIF renders WITHOUT the audit (the audit's exact shadow rays would
  inflate the render time), with every run's share in ``train_share_runs``; ``render_vs_exact``:
  the median NIF render time over the exact render's (seed 1, same spp) in the same run;
- ``paper_kb`` / ``real_kb`` (memory in the paper's convention and the real bytes), ``peak_rss_gb``
  (the process's peak resident memory after the row: run one big scene per process to attribute it).

Every scene is first rendered tiny (16 x 16, 2 spp, NIF trained on 1), so no timing includes a
compile. The machine is shared: compare ratios within a run; the JSON records the load average
before and after each row. Writes benchmarks/results/nif[_<device>].json.
"""

from __future__ import annotations

import os
import resource
import statistics
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (before torch: sets how OpenMP threads wait)

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, check_device, check_scene, description, nonnegative_int,  # noqa: E402
                     parse_mesh_spec, positive_int, print_table, result_name, run_main, write_results)

from neuralrt.errors import ConfigError, MeshError, validation_message  # noqa: E402
from neuralrt.eval.image_metrics import compare_images  # noqa: E402
from neuralrt.methods.nif_config import NIFConfig, NIFTrainingConfig  # noqa: E402
from neuralrt.render.integrator import render  # noqa: E402
from neuralrt.render.nif_render import render_nif  # noqa: E402
from neuralrt.scene.loader import load_scene  # noqa: E402

COLUMNS = ["scene", "tris", "nif_instances", "shadow_rays", "outer", "inner", "exact_ms", "nif_ms", "speedup", "disagree", "visible_err",
           "psnr_same", "flip_same", "psnr", "psnr_floor", "flip", "flip_floor", "train_s_per_spp", "train_share", "render_vs_exact",
           "paper_kb", "real_kb", "peak_rss_gb"]
SHARED = Path(__file__).resolve().parents[2] / "shared" / "meshes"


def cached_subdivided_mesh(spec: str, cache: Path):
    """``FILE@loopK``: FILE (in ../shared/meshes, or a path) Loop-subdivided K times, cached as binary PLY."""
    import numpy as np
    import trimesh

    from neuralrt.geometry.mesh import load_mesh
    from neuralrt.geometry.subdivision import loop_subdivided

    file, _, loops = spec.partition("@loop")
    source = Path(file) if Path(file).is_file() else SHARED / file
    target = cache / f"{source.stem}_loop{loops or 0}.ply"
    if not target.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        base = load_mesh(source)
        vertices, faces = base.vertices.astype(np.float64), base.faces
        del base
        for _ in range(int(loops or 0)):  # trimesh's triangles at a fifth of its memory (50M fits)
            vertices, faces = loop_subdivided(vertices, faces)
        partial = target.with_suffix(".part.ply")
        trimesh.Trimesh(vertices.astype(np.float32), faces, process=False).export(partial)
        partial.replace(target)
        del vertices, faces
    return load_mesh(target)


def mesh_scene(spec: str, args):
    """The subdivided mesh on a floor, under a square area light off to one side (shadows on the floor
    and on the mesh itself), camera in front; NIF on the mesh."""
    from neuralrt.scene.loader import load_dict

    mesh = cached_subdivided_mesh(spec, Path(args.mesh_cache))
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    scale = 1.6 / float((hi - lo).max())
    centre = 0.5 * (lo + hi)
    translate = [float(-centre[0] * scale), float(-1.0 - lo[1] * scale), float(-centre[2] * scale)]  # on the floor, centred
    scene = load_dict({
        "camera": {"position": [0.0, 0.4, 3.6], "look_at": [0.0, -0.3, 0.0], "fov": 40.0, "resolution": [args.resolution, args.resolution]},
        "materials": [{"name": "clay", "type": "plastic", "albedo": [0.7, 0.55, 0.45], "roughness": 0.3},
                      {"name": "floor", "type": "diffuse", "albedo": [0.5, 0.5, 0.5]},
                      {"name": "light", "type": "emissive", "emission": [8.0, 8.0, 8.0]}],
        "objects": [{"name": "object", "mesh": mesh, "material": "clay", "transform": {"translate": translate, "scale": scale}},
                    {"name": "floor", "generator": {"name": "plane", "params": {"size": 8.0}}, "material": "floor",
                     "transform": {"translate": [0.0, -1.0, 0.0]}},
                    {"name": "light", "generator": {"name": "plane", "params": {"size": 1.0}}, "material": "light",
                     "transform": {"translate": [1.2, 1.8, 0.8], "rotate": [180.0, 0.0, 0.0]}}],
        "environment": {"color": [0.2, 0.22, 0.28]},
    }, device=args.device, label=f"mesh:{spec}")
    return scene, ["object"]


def warm_up(device: str) -> None:
    """Compile (or load from numba's cache) the answer path once, so no row's timing includes it."""
    import torch

    from neuralrt.methods.nif import NIFNetworks, NIFPairs
    from neuralrt.methods.nif_features import nif_features_for
    from neuralrt.rays import AABB

    net = NIFNetworks(NIFConfig(), [AABB(torch.full((3,), -1.0), torch.full((3,), 1.0))]).to(device)
    o = torch.tensor([[-3.0, 0.1, 0.2], [0.1, 0.2, 0.3]], device=device)
    pairs = NIFPairs(torch.zeros(2, dtype=torch.long, device=device), o, -2 * o, torch.zeros(2, device=device), torch.ones(2, device=device))
    net.occluded_from_features(2, *nif_features_for(device)(net, pairs))


def builtin_scene(builtin: str, detail: int, args):
    scene = load_scene(f"builtin:{builtin}?detail={detail}", device=args.device, resolution=(args.resolution, args.resolution))
    statues = sorted({inst.name for inst in scene.accel.instances if getattr(inst.blas, "mesh", None) is not None
                      and inst.blas.mesh.name.startswith("statue")})
    return scene, statues


def check_scene_item(item: str) -> None:
    """One ``--scenes`` item checked before any scene loads: ``mesh:FILE@loopK`` (FILE found, K a whole
    number) or ``NAME[:D]``, a built-in scene with statues (NIF goes on them) at detail D."""
    from neuralrt.scene.builtins import BUILTIN_SCENES, builtin_spec

    if not item:
        raise ConfigError("--scenes: an empty item (want NAME:DETAIL or mesh:FILE@loopK, comma-separated)")
    if item.startswith("mesh:"):
        spec = item[len("mesh:"):]
        if spec.startswith("procedural:"):
            raise MeshError(f"--scenes {item}: mesh:FILE@loopK takes a mesh file, not a procedural mesh")
        parse_mesh_spec(spec)
        return
    builtin, _, detail = item.partition(":")
    if not detail.isdigit() and detail != "":
        raise ConfigError(f"--scenes {item}: want NAME:DETAIL (DETAIL a whole number) or mesh:FILE@loopK")
    spec = check_scene(f"builtin:{builtin}?detail={int(detail or 2)}")
    if not any(obj.generator is not None and obj.generator.name == "statue" for obj in spec.objects):
        with_statues = [n for n in BUILTIN_SCENES if any(o.generator is not None and o.generator.name == "statue"
                                                          for o in builtin_spec(n).objects)]
        raise ConfigError(f"--scenes {item}: builtin:{builtin} has no statue to put NIF on (use {' or '.join(with_statues)}, or mesh:FILE@loopK)")


def nif_config(args) -> NIFConfig:
    """The NIF config of --passes, --train-spp, --pair-fraction and --shadow-rays (a bad value is a one-line `ConfigError`)."""
    from pydantic import ValidationError

    try:
        return NIFConfig(training=NIFTrainingConfig(passes_per_spp=args.passes, train_spp=args.train_spp, pair_fraction=args.pair_fraction),
                         shadow_rays=args.shadow_rays)
    except ValidationError as exc:
        raise ConfigError(f"nif config: {validation_message(exc, NIFTrainingConfig)}") from None


def bench_scene(item: str, args) -> dict:
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    if item.startswith("mesh:"):
        label = item
        scene, objects = mesh_scene(item[len("mesh:"):], args)
    else:
        builtin, _, detail = item.partition(":")
        label = f"{builtin}?detail={int(detail or 2)}"
        scene, objects = builtin_scene(builtin, int(detail or 2), args)
    load_s = time.perf_counter() - t0
    cfg = nif_config(args)
    render_nif(scene, objects, spp=2, train_spp=1, seed=0, config=cfg, progress=False, resolution=(16, 16))  # compile everything once
    kw = dict(spp=args.spp, seed=0, config=cfg, progress=False)
    nif, report = render_nif(scene, objects, audit=True, **kw)
    same, _ = render_nif(scene, objects, answer="exact", **kw)
    other = render(scene, spp=args.spp, seed=1, progress=False)
    timed = [render_nif(scene, objects, **kw)[1] for _ in range(args.repeats)]  # no audit: the render time NIF users see
    shares = [r["training_share_of_render"] for r in timed]
    totals = [r["render_seconds"]["total"] for r in timed]
    st = report["shadow_rays"]
    rays = max(st["shadow_rays"], 1)
    vs_same, vs_other, floor = compare_images(same.image, nif.image), compare_images(other.image, nif.image), compare_images(other.image, same.image)
    return {
        "scene": label,
        "tris": report["triangles"][0],
        "nif_instances": report["instances"],
        "shadow_rays": st["shadow_rays"],
        "exact_only_rays": st["exact_only_rays"],  # (later bounces' shadow rays, traced exactly: shadow_rays first_hit)
        "outer": st["outer"],
        "inner": st["inner"],
        "exact_ms": 1e3 * st["audit_exact_seconds"],
        "nif_ms": 1e3 * st["seconds"],
        "speedup": st["audit_exact_seconds"] / max(st["seconds"], 1e-12),
        "disagree": st["audit_disagreements"] / rays,
        "visible_err": st["audit_blocked_by_nif_objects_only"] / rays,
        "psnr_same": vs_same.psnr, "flip_same": vs_same.flip,
        "psnr": vs_other.psnr, "psnr_floor": floor.psnr, "flip": vs_other.flip, "flip_floor": floor.flip,
        "train_s_per_spp": statistics.median(r["training_seconds_per_spp"] for r in timed) if timed else None,
        "train_share": statistics.median(shares) if timed else None,
        "render_vs_exact": statistics.median(totals) / other.seconds if timed else None,
        "train_share_runs": shares,
        "nif_render_seconds_runs": totals,
        "training_runs": [r["training"] for r in timed],
        "render_seconds_runs": [r["render_seconds"] for r in timed],
        # collecting: the exact objects, stage 1, and labels + queries (training excluded), per timed run
        "collect_seconds_runs": [{k: r["shadow_rays_training"][k] for k in ("exact_seconds", "stage1_seconds", "stage2_seconds")} for r in timed],
        "exact_render_seconds": other.seconds,
        "paper_kb": report["memory"]["paper_bytes"] / 1024,
        "real_kb": report["memory"]["real_bytes"] / 1024,
        "nif_ms_parts": {"exact_objects": 1e3 * st["exact_seconds"], "stage1": 1e3 * st["stage1_seconds"], "stage2": 1e3 * st["stage2_seconds"]},
        "render_seconds": report["render_seconds"],
        "training": report["training"],
        "load_s": load_s,
        "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
    }


def main() -> None:
    ap = ArgumentParser(description=description(__doc__))
    ap.add_argument("--resolution", type=positive_int, default=128)
    ap.add_argument("--spp", type=positive_int, default=64)
    ap.add_argument("--train-spp", type=positive_int, default=32)
    ap.add_argument("--passes", type=positive_int, default=NIFTrainingConfig().passes_per_spp)
    ap.add_argument("--scenes", default="cornell-statue:2,cornell-statue:4", help="builtin:detail pairs, comma-separated")
    ap.add_argument("--pair-fraction", type=float, default=NIFTrainingConfig().pair_fraction,
                    help="share of each round's pairs a training pass uses (NIFTrainingConfig.pair_fraction)")
    ap.add_argument("--shadow-rays", choices=("first_hit", "every_hit"), default=NIFConfig().shadow_rays,
                    help="the shadow rays NIF takes (NIFConfig.shadow_rays; every_hit: every figure before session 58)")
    ap.add_argument("--repeats", type=nonnegative_int, default=3, help="NIF renders without the audit, for the training share (median; 0: quality only)")
    ap.add_argument("--mesh-cache", default="/tmp/neuralrt-nif-meshes", help="where mesh:FILE@loopK scenes keep their subdivided meshes")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--name", type=result_name, help="results file name (default: nif, or nif_<device>)")
    args = ap.parse_args()
    check_device(args.device)  # every check before the first scene's work
    nif_config(args)
    if not args.scenes.strip(","):
        raise ConfigError("--scenes: no scene given")
    for item in args.scenes.split(","):
        check_scene_item(item)
    warm_up(args.device)
    rows = []
    for item in args.scenes.split(","):
        rows.append(bench_scene(item, args))
        print_table(rows[-1:], COLUMNS)
    print()
    print_table(rows, COLUMNS)
    settings = {k: getattr(args, k) for k in ("resolution", "spp", "train_spp", "passes", "pair_fraction", "shadow_rays", "repeats", "device")}
    name = args.name or ("nif" if args.device == "cpu" else f"nif_{args.device}")
    path = write_results(name, rows, {"settings": settings, "load_average_1min": os.getloadavg()[0]})
    print(f"\nwrote {path}")


if __name__ == "__main__":
    run_main(main)
