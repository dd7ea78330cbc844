"""NIF shadow rays against exact shadow rays, in the paper's Table 2 form, plus image quality.

    python benchmarks/bench_nif.py [--resolution 128] [--spp 64] [--train-spp 32] [--passes 1]
                                   [--scenes cornell-statue:2,cornell-statue:4] [--device cpu] [--name NAME]

Per scene (``builtin:NAME?detail=D``, NIF on every statue: cornell-statue detail 2 = 75,720
triangles, detail 4 = statue(4), 1.2M; ``instances:3`` = 12 instances of statue(2) sharing one NIF
object among 24 other objects), one NIF render with ``audit=True``: every shadow-ray batch of the samples
after training is answered by the NIF stand-in (exact objects + NIF stages 1 and 2) AND by the
whole exact accelerator (Embree on the CPU, OptiX on CUDA), timed in the same run on the same
rays. Columns:

- ``tris``, ``shadow_rays``, ``outer``, ``inner`` (pairs each network answered), ``exact_ms`` /
  ``nif_ms`` (all shadow rays of the NIF samples), ``speedup`` = exact / NIF (the paper's "x");
- ``disagree``: share of shadow rays whose answer differs from the exact one, and ``visible_err``
  the same for always answering "visible" for the statue (the baseline NIF must beat);
- ``psnr_same`` / ``flip_same``: the NIF render against the same samples with exact shadow rays
  (only the answers differ: the NIF error itself); ``psnr`` / ``flip``: against an exact render
  with other samples (seed 1), next to ``psnr_floor`` / ``flip_floor``, exact against exact with
  other samples (the noise floor at this spp);
- ``train_s_per_spp``, ``train_share`` (training time over the whole NIF render's time),
  ``paper_kb`` / ``real_kb`` (memory in the paper's convention and the real bytes).

The machine is shared: compare ratios within a run. Writes benchmarks/results/nif[_<device>].json.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (before torch: sets OMP_WAIT_POLICY)

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import print_table, write_results  # noqa: E402

from neuralrt.eval.image_metrics import compare_images  # noqa: E402
from neuralrt.methods.nif_config import NIFConfig, NIFTrainingConfig  # noqa: E402
from neuralrt.render.integrator import render  # noqa: E402
from neuralrt.render.nif_render import render_nif  # noqa: E402
from neuralrt.scene.loader import load_scene  # noqa: E402

COLUMNS = ["scene", "tris", "nif_instances", "shadow_rays", "outer", "inner", "exact_ms", "nif_ms", "speedup", "disagree", "visible_err",
           "psnr_same", "flip_same", "psnr", "psnr_floor", "flip", "flip_floor", "train_s_per_spp", "train_share", "paper_kb", "real_kb"]


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


def bench_scene(builtin: str, detail: int, args) -> dict:
    t0 = time.perf_counter()
    scene = load_scene(f"builtin:{builtin}?detail={detail}", device=args.device, resolution=(args.resolution, args.resolution))
    load_s = time.perf_counter() - t0
    statues = sorted({inst.name for inst in scene.accel.instances if getattr(inst.blas, "mesh", None) is not None
                      and inst.blas.mesh.name.startswith("statue")})
    cfg = NIFConfig(training=NIFTrainingConfig(passes_per_spp=args.passes, train_spp=args.train_spp))
    kw = dict(spp=args.spp, seed=0, config=cfg, progress=False)
    nif, report = render_nif(scene, statues, audit=True, **kw)
    same, _ = render_nif(scene, statues, answer="exact", **kw)
    other = render(scene, spp=args.spp, seed=1, progress=False)
    st = report["shadow_rays"]
    rays = max(st["shadow_rays"], 1)
    vs_same, vs_other, floor = compare_images(same.image, nif.image), compare_images(other.image, nif.image), compare_images(other.image, same.image)
    return {
        "scene": f"{builtin}?detail={detail}",
        "tris": report["triangles"][0],
        "nif_instances": report["instances"],
        "shadow_rays": st["shadow_rays"],
        "outer": st["outer"],
        "inner": st["inner"],
        "exact_ms": 1e3 * st["audit_exact_seconds"],
        "nif_ms": 1e3 * st["seconds"],
        "speedup": st["audit_exact_seconds"] / max(st["seconds"], 1e-12),
        "disagree": st["audit_disagreements"] / rays,
        "visible_err": st["audit_blocked_by_nif_objects_only"] / rays,
        "psnr_same": vs_same.psnr, "flip_same": vs_same.flip,
        "psnr": vs_other.psnr, "psnr_floor": floor.psnr, "flip": vs_other.flip, "flip_floor": floor.flip,
        "train_s_per_spp": report["training_seconds_per_spp"],
        "train_share": report["training_share_of_render"],
        "paper_kb": report["memory"]["paper_bytes"] / 1024,
        "real_kb": report["memory"]["real_bytes"] / 1024,
        "nif_ms_parts": {"exact_objects": 1e3 * st["exact_seconds"], "stage1": 1e3 * st["stage1_seconds"], "stage2": 1e3 * st["stage2_seconds"]},
        "render_seconds": report["render_seconds"],
        "training": report["training"],
        "load_s": load_s,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--resolution", type=int, default=128)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--train-spp", type=int, default=32)
    ap.add_argument("--passes", type=int, default=NIFTrainingConfig().passes_per_spp)
    ap.add_argument("--scenes", default="cornell-statue:2,cornell-statue:4", help="builtin:detail pairs, comma-separated")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--name", help="results file name (default: nif, or nif_<device>)")
    args = ap.parse_args()
    warm_up(args.device)
    rows = []
    for item in args.scenes.split(","):
        builtin, _, detail = item.partition(":")
        rows.append(bench_scene(builtin, int(detail or 2), args))
        print_table(rows[-1:], COLUMNS)
    print()
    print_table(rows, COLUMNS)
    settings = {k: getattr(args, k) for k in ("resolution", "spp", "train_spp", "passes", "device")}
    name = args.name or ("nif" if args.device == "cpu" else f"nif_{args.device}")
    path = write_results(name, rows, {"settings": settings, "load_average_1min": os.getloadavg()[0]})
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
