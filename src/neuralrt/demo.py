"""`neuralrt demo`: convert a built-in scene, render it exact and hybrid, compare, and write a report.

The report folder holds both renders (EXR + PNG), the FLIP heat map, a side-by-side PNG, and a
table (``report.md`` and ``report.json``) of memory (BVH A, BVH B, neural), FLIP and PSNR, render times and
training time, and each model's training curve (``training_K.png``). FLIP comes twice: hybrid vs exact at the same seed (shared random numbers: the
difference is mostly the model's) and hybrid vs exact at another seed, the figure to hold against
the noise floor (exact vs exact at that other seed, same spp).
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from .io.files import write_atomically
from .methods.registry import DEFAULT_METHOD

__all__ = ["DemoSettings", "DEMO_DEFAULT", "DEMO_QUICK", "run_demo"]

# The report's files, relative to its folder (the renders' PNGs and AOVs are written beside their
# EXRs: `render.film.output_files`).
EXACT_EXR, HYBRID_EXR = "exact.exr", "hybrid.exr"
FLIP_PNG, SIDE_BY_SIDE = "flip.png", "side_by_side.png"
REPORT_JSON, REPORT_MD = "report.json", "report.md"


@dataclass(frozen=True)
class DemoSettings:
    """What the demo converts and renders. Defaults finish in 2-3 minutes on 2 CPU cores (measured:
    1 min 56 s at load 1.2-2.0, of which 71 s training; 3 min 2 s on a busier machine; numba kernels
    cached); 256 spp keep the noise floor (exact vs exact at another seed: FLIP 0.018) low enough
    to show the model's error beside it (FLIP 0.007).

    Every value is checked on construction (one-line `ConfigError` naming it), so a bad argument
    fails before any training starts."""

    scene: str = "builtin:cornell-statue"
    method: str = DEFAULT_METHOD  # registered method of the trained models
    preset: str | None = None  # the method's preset (None: its default for the device; LSNIF: hq on the CPU)
    steps: int | None = None  # training steps (None: the preset's)
    batch: int | None = None  # training rays per step (None: the preset's CPU default)
    detail: int | None = None  # procedural mesh detail of the built-in scene (None: its default)
    min_triangles: int | None = None  # objects this large become neural (None: the converter's default)
    resolution: tuple[int, int] = (256, 256)
    spp: int = 256
    max_depth: int = 4
    primary: str = "exact"  # camera rays: "exact" (paper's rasterized G-buffer stand-in) or "neural"
    seed: int = 1

    def __post_init__(self) -> None:
        from .arguments import check_count, check_seed, given
        from .errors import ConfigError
        from .methods import get_method
        from .scene.schema import MAX_DEPTH, MAX_SPP, check_resolution

        # Render's bounds too: a bad value fails here, not after the training (as `render` refuses it at once).
        # (kept as Python ints: a numpy integer reached the report's JSON, after the whole run)
        for name, minimum, maximum in (("spp", 1, MAX_SPP), ("max_depth", 1, MAX_DEPTH), ("steps", 1, None),
                                       ("batch", 1, None), ("detail", 0, None), ("min_triangles", 0, None)):
            # (named as the caller spelled it: --spp, spp)
            object.__setattr__(self, name, check_count(given(name), getattr(self, name), minimum, maximum))
        object.__setattr__(self, "seed", check_seed(given("seed"), self.seed))
        object.__setattr__(self, "resolution", check_resolution(self.resolution))
        if self.primary not in ("exact", "neural"):
            raise ConfigError(f"primary: must be exact or neural, got {self.primary!r}")
        # The training config too (unknown preset, batch below the method's minimum, ...).
        get_method(self.method).config(self.preset, steps=self.steps, batch_size=self.batch)


DEMO_DEFAULT = DemoSettings()
# The same model trained briefly (150 steps of 4,096 rays), a small image: measured 9 s on 2 idle
# cores with numba's kernels cached (session 35), 21 s on 2 cores shared with other jobs (load 2).
DEMO_QUICK = DemoSettings(steps=150, batch=1 << 12, resolution=(96, 96), spp=8, max_depth=3)


def _side_by_side(images: list[np.ndarray], labels: list[str], path: Path) -> None:
    """Tone-mapped images next to each other with a caption strip (the FLIP map is already sRGB)."""
    from PIL import Image, ImageDraw

    tiles = [Image.fromarray(np.round(np.clip(im, 0, 1) * 255).astype(np.uint8)) for im in images]
    w, h = tiles[0].size
    caption = 16
    canvas = Image.new("RGB", (w * len(tiles), h + caption), (0, 0, 0))
    draw = ImageDraw.Draw(canvas)
    for k, (tile, label) in enumerate(zip(tiles, labels)):
        canvas.paste(tile, (k * w, caption))
        draw.text((k * w + 4, 2), label, fill=(255, 255, 255))
    write_atomically(path, canvas.save)


def _markdown(report: dict) -> str:
    m, t, q = report["memory"], report["time"], report
    rows = [
        ("scene", report["scene"]),
        ("neural objects (unique models)", f"{report['neural_objects']} ({report['unique_models']})"),
        ("triangles replaced", f"{m['neural_triangles']:,}"),
        ("neural memory", f"{m['neural_bytes'] / 2**20:.2f} MiB"),
        ("BVH A (4-wide, uncompressed)", f"{m['bvh_a_bytes'] / 2**20:.2f} MiB ({m['bvh_a_ratio']:.1f}x neural)"),
        ("BVH B (8-wide, compressed, est.)", f"{m['bvh_b_bytes'] / 2**20:.2f} MiB ({m['bvh_b_ratio']:.1f}x neural)"),
        ("kept for camera rays (meshes + Embree BVHs)", f"{m['camera_bytes'] / 2**20:.2f} MiB (primary rays {report['settings']['primary']})"),
        ("run-time memory, exact scene / hybrid scene",
         f"{m['exact_scene_bytes'] / 2**20:.2f} / {m['hybrid_scene_bytes'] / 2**20:.2f} MiB"),
        ("FLIP hybrid vs exact (same seed: shared noise)", f"{q['flip']:.4f}"),
        ("FLIP hybrid vs exact at another seed / noise floor (exact vs that seed)",
         f"{q['flip_other_seed']:.4f} / {q['flip_noise_floor']:.4f}"),
        ("PSNR hybrid vs exact: same seed; another seed / floor",
         f"{q['psnr']:.2f} dB; {q['psnr_other_seed']:.2f} / {q['psnr_noise_floor']:.2f} dB"),
        ("training time (wall: setup and steps; the model's record counts steps only)",
         "none: the model was reused from the folder" if all(model["reused"] for model in report["models"])
         else f"{t['train_s']:.1f} s"),
        ("exact render", f"{t['exact_render_s']:.3g} s"),
        ("hybrid render", f"{t['hybrid_render_s']:.3g} s ({t['hybrid_render_s'] / max(t['exact_render_s'], 1e-9):.2f}x exact)"),
    ]
    s = report["settings"]
    lines = [
        "# neuralrt demo report",
        "",
        f"{s['resolution'][0]}x{s['resolution'][1]}, {s['spp']} spp, max depth {s['max_depth']}, seed {s['seed']}, "
        f"preset `{s['preset']}`, primary rays {s['primary']}; {report['machine']}",
        "",
        "| figure | value |",
        "|---|---|",
        *[f"| {k} | {v} |" for k, v in rows],
        "",
        f"![exact | hybrid | FLIP]({SIDE_BY_SIDE})",
        "",
    ]
    for name, image in report["images"].get("training", {}).items():
        lines += [f"Training of `{name}`:", "", f"![training curve of {name}]({image})", ""]
    return "\n".join(lines)


def _training_plots(models, out: Path) -> dict[str, str]:
    """Each model's training curve drawn into ``out`` (mesh name -> file name); models trained
    before curves were kept have none to draw."""
    from .io.model_file import read_model_header
    from .io.plots import plot_problem, training_plot_title, write_training_plot
    from .methods import get_method
    from .methods.registry import config_from_dict

    plots = {}
    for k, m in enumerate(models):
        header = read_model_header(m.model_path)
        if plot_problem(header.training) is None:
            name = _training_plot(k)
            preset = get_method(header.method).preset_of(config_from_dict(header.config))  # (as `info` names it)
            title = training_plot_title(header.method, preset, m.mesh_name, header.training)
            write_training_plot(out / name, header.training["curve"], title)
            plots[m.mesh_name] = name
    return plots


def _write_text(path: Path, text: str) -> None:
    write_atomically(path, lambda tmp: Path(tmp).write_text(text))


def _training_plot(k: int) -> str:
    return f"training_{k}.png"


def _png(exr_name: str) -> str:
    from .render.film import output_files

    return str(output_files(exr_name)[1])  # (the render's PNG, written beside its EXR)


def report_files(out: Path, objects: int) -> list[Path]:
    """Every file of the report `run_demo` writes into ``out`` (the training plots: at most one per
    object of the scene), checked before any step starts."""
    from .render.film import output_files

    return [*output_files(out / EXACT_EXR), *output_files(out / HYBRID_EXR), out / FLIP_PNG, out / SIDE_BY_SIDE,
            *(out / _training_plot(k) for k in range(objects)), out / REPORT_JSON, out / REPORT_MD]


def run_demo(out_dir: str | Path = "neuralrt-demo", quick: bool = False, device: str = "cpu",
             progress: bool = True, settings: DemoSettings | None = None) -> dict:
    """Run the whole demo and return the report (also written to ``out_dir/report.json``)."""
    from .eval.image_metrics import compare_images, write_srgb_png
    from .io.files import check_output_files, check_output_folder, written_together
    from .io.images import linear_to_srgb, tone_map
    from .render.integrator import render, warm_up
    from .scene.convert import convert_scene, replaced_memory
    from .scene.memory import scene_memory
    from .scene.loader import load_scene, load_scene_spec

    from .methods import get_method

    s = settings or (DEMO_QUICK if quick else DEMO_DEFAULT)
    if s.preset is None:
        s = replace(s, preset=get_method(s.method).default_preset(device))
    out = Path(out_dir)
    check_output_folder(out, "demo report")  # (made by the conversion, once the scene is known to be good)
    spec, _, _ = load_scene_spec(s.scene, detail=s.detail)  # a bad scene fails here, before any step starts
    # (a folder or unwritable file where a report file goes: said now, not after the training)
    check_output_files(report_files(out, len(spec.objects)), "demo report file")

    def say(msg: str) -> None:
        if progress:
            print(msg, file=sys.stderr, flush=True)  # (stdout is the result: --json)

    say(f"[1/4] converting {s.scene} ({s.method} {s.preset}) ...")
    conversion = convert_scene(s.scene, out / "scene_neural.toml", models_dir=out / "models", method=s.method, preset=s.preset,
                               steps=s.steps, batch=s.batch, detail=s.detail, min_triangles=s.min_triangles,
                               device=device, progress=progress)

    say("[2/4] rendering exact (two seeds, for the noise floor) and hybrid ...")
    exact_scene = load_scene(s.scene, device=device, resolution=s.resolution, detail=s.detail)
    hybrid_scene = load_scene(out / "scene_neural.toml", device=device, resolution=s.resolution)
    common = dict(spp=s.spp, max_depth=s.max_depth, progress=progress)
    # Untimed first: each scene's first render loads the kernels it uses (~0.3 s, not per sample).
    warm_up(exact_scene, max_depth=s.max_depth)
    warm_up(hybrid_scene, primary=s.primary, max_depth=s.max_depth)
    exact = render(exact_scene, seed=s.seed, **common)
    exact_other_seed = render(exact_scene, seed=s.seed + 1, **common)
    hybrid = render(hybrid_scene, seed=s.seed, primary=s.primary, **common)

    say("[3/4] comparing ...")
    quality = compare_images(exact.image, hybrid.image)
    floor = compare_images(exact.image, exact_other_seed.image)
    # Against the same independent render as the floor: noise no longer shared, so the two compare.
    other_seed = compare_images(exact_other_seed.image, hybrid.image)
    say("[4/4] memory accounting ...")
    memory = replaced_memory(hybrid_scene)
    # What the hybrid scene really holds: with exact camera rays the neural objects keep their meshes too.
    by_role = scene_memory(hybrid_scene)
    memory.update(camera_bytes=by_role.camera_bytes, hybrid_scene_bytes=by_role.total,
                  exact_scene_bytes=int(exact_scene.accel.memory_bytes().total))

    report = {
        "scene": s.scene,
        "settings": {**asdict(s), "quick": quick, "device": device},
        "machine": f"{platform.machine()} {platform.processor() or ''} torch {torch.__version__} "
                   f"{torch.get_num_threads()} threads".replace("  ", " "),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "neural_objects": conversion.neural_objects,
        "unique_models": conversion.unique_models,
        "flip": quality.flip,
        "psnr": quality.psnr,
        "relmse": quality.relmse,
        "flip_other_seed": other_seed.flip,
        "psnr_other_seed": other_seed.psnr,
        "flip_noise_floor": floor.flip,
        "psnr_noise_floor": floor.psnr,
        "memory": {
            **memory,
            "bvh_a_ratio": memory["bvh_a_bytes"] / max(memory["neural_bytes"], 1),
            "bvh_b_ratio": memory["bvh_b_bytes"] / max(memory["neural_bytes"], 1),
        },
        "time": {
            "train_s": conversion.train_seconds,
            "exact_render_s": exact.seconds,
            "hybrid_render_s": hybrid.seconds,
        },
        # (paths relative to the report's folder, as the images' are)
        "models": [{**m.__dict__, "model_path": os.path.relpath(m.model_path, out)} for m in conversion.models],
        "images": {
            "exact": _png(EXACT_EXR), "exact_exr": EXACT_EXR, "hybrid": _png(HYBRID_EXR), "hybrid_exr": HYBRID_EXR,
            "flip": FLIP_PNG, "side_by_side": SIDE_BY_SIDE, "report_md": REPORT_MD,
            "training": {},  # (filled as they are drawn, below)
        },
    }
    # The report's files appear together (an interrupt leaves an earlier report whole, or none).
    with written_together():
        exact.save(out / EXACT_EXR)
        hybrid.save(out / HYBRID_EXR)
        write_srgb_png(out / FLIP_PNG, quality.flip_map)
        _side_by_side([linear_to_srgb(tone_map(exact.image)), linear_to_srgb(tone_map(hybrid.image)), quality.flip_map],
                      ["exact", f"hybrid ({s.preset})", f"FLIP {quality.flip:.3f}"], out / SIDE_BY_SIDE)
        report["images"]["training"] = _training_plots(conversion.models, out)
        _write_text(out / REPORT_JSON, json.dumps(report, indent=2) + "\n")
        _write_text(out / REPORT_MD, _markdown(report))
    return report
