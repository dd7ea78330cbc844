"""Command line: thin wrappers that parse arguments, call `neuralrt.api`, and print.

Bad input ends with one line on stderr (``neuralrt: error: ...``) and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import signal
import sys
import threading
import warnings
from pathlib import Path

import numpy as np

from . import __version__, api
from .arguments import spelled_as_flags
from .errors import NeuralRTError
from .methods.config import parse_settings


class _Parser(argparse.ArgumentParser):
    """Argument errors as one line ``neuralrt: error: ...`` and exit 2, like every other bad input."""

    def error(self, message: str):
        self.exit(2, f"neuralrt: error: {message} (see {self.prog} --help)\n")

    def _print_message(self, message, file=None):
        """``--help`` and ``--version`` as argparse prints them, but a failed write to standard output
        is an error (argparse dropped it: ``--help > /dev/full`` exited 0 having written nothing)."""
        if not message or file is not sys.stdout:
            return super()._print_message(message, file)
        file.write(message)
        file.flush()


class _NamedStandardOutput:
    """``sys.stdout`` during a command, whose write errors name it (a failed print names no file)."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text):
        return self._named(self._stream.write, text)

    def flush(self):
        return self._named(self._stream.flush)

    @staticmethod
    def _named(call, *args):
        try:
            return call(*args)
        except BrokenPipeError:  # (`neuralrt info X | head`: quiet, as for every command)
            raise
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror or str(exc), "standard output") from None

    def __getattr__(self, name):
        return getattr(self._stream, name)


def _strict_json(value):
    """``value`` with every non-finite float as None: JSON has no NaN or Infinity (PSNR of two equal
    images is +inf), and strict readers (jq, JavaScript's JSON.parse) reject Python's tokens for them."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict_json(v) for v in value]
    return value


def _print_result(result: dict, as_json: bool) -> None:
    if as_json:
        plain = json.loads(json.dumps(result, default=float))  # numpy scalars and the like as Python floats
        print(json.dumps(_strict_json(plain), allow_nan=False))
        return
    width = max([24, *(len(str(key)) for key in result)])  # (a long key keeps the column)
    for key, value in result.items():
        if key == "training" and isinstance(value, dict) and isinstance(value.get("curve"), dict):
            value = {**value, "curve": _curve_summary(value["curve"])}
        if isinstance(value, float):
            value = f"{value:.6g}"
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            print(f"{key:>{width}}:")  # (convert's models): one line each
            for row in value:
                print(f"{'':>{width}}  - {_printable(_flat_text(row))}")
            continue
        elif isinstance(value, list) and not any(isinstance(v, dict) for v in value):
            # (per-view figures, material names, bounds' corners: float32's shortest, or a box at 1e7 read flat)
            value = _flat_text(value, float32=key == "bounds") if value else "none"
        elif isinstance(value, dict) and any(isinstance(v, dict) for v in value.values()):
            value = json.dumps(value, default=float)  # nested (a config, a training record): compact JSON
        elif isinstance(value, dict):
            value = _flat_text(value)
        print(f"{key:>{width}}: {_printable(str(value))}")


def _flat_text(value, float32: bool = False) -> str:
    """A flat dict as ``k=v, ...``, a list as ``a, b``: floats to 6 digits (``float32``: as many as
    tell the float32 value from its neighbours), lists inside joined."""
    def one(v):
        if isinstance(v, float):
            return _float32_text(v) if float32 else f"{v:.6g}"
        return " ".join(map(one, v)) if isinstance(v, (list, tuple)) else str(v)
    if isinstance(value, dict):
        return ", ".join(f"{k}={one(v)}" for k, v in value.items())
    return ", ".join(map(one, value))


def _float32_text(v: float) -> str:
    """The fewest digits that tell the float32 nearest ``v`` from its neighbours (numpy's shortest
    round trip), positional unless very large or small (``10000001``, ``0.999``, ``1e+20``)."""
    x = np.float32(v)
    if x != 0 and not 1e-4 <= abs(x) < 1e16:
        return np.format_float_scientific(x, unique=True, trim="-")
    return np.format_float_positional(x, unique=True, trim="-")


def _printable(text: str) -> str:
    """``text`` with control characters escaped: a name from a file (a model's mesh name) cannot move
    the cursor, colour the terminal or start a line of its own."""
    return text if text.isprintable() else "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _message(text: str) -> str:
    """An error or warning as one readable line: printable (`_printable`), its middle left out past
    `MESSAGE_CHARACTERS` (a 100,000-character name from a file was echoed whole)."""
    text = _printable(text)
    if len(text) <= MESSAGE_CHARACTERS:
        return text
    head, tail = MESSAGE_CHARACTERS * 2 // 3, MESSAGE_CHARACTERS // 3
    return f"{text[:head]} ... ({len(text) - head - tail:,} characters left out) ... {text[-tail:]}"


MESSAGE_CHARACTERS = 3000  # (a path may be 4,096 bytes; messages name one or two of them at the most)


def _curve_summary(curve: dict) -> str:
    """A training curve in one phrase: ``150 points, loss 2.95 -> 0.236 (--plot FILE.png draws them)``
    (its points are for --json and --plot)."""
    losses = curve.get("loss") if isinstance(curve.get("loss"), list) else []
    if not losses:
        return "none"
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and -1e308 < x < 1e308 for x in (losses[0], losses[-1])):
        return f"{len(losses)} points, not numbers (an edited file: --plot says what is wrong)"
    return f"{len(losses)} points, loss {losses[0]:.3g} -> {losses[-1]:.3g} (--plot FILE.png draws them)"


# --- commands -----------------------------------------------------------------------------------


def _cmd_compare(args) -> None:
    _print_result(api.compare(args.reference, args.test, heatmap=args.heatmap, hdr=args.hdr), args.json)


def _cmd_info(args) -> None:
    _print_result(api.info(args.path, plot=args.plot), args.json)


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must look like 256x256, got {text!r}") from None
    if w <= 0 or h <= 0:
        raise argparse.ArgumentTypeError(f"resolution must be positive, got {text!r}")
    return w, h


def _cmd_render(args) -> None:
    if args.list_builtins:
        rows = api.list_builtins()
        if args.json:
            print(json.dumps(rows))
        for row in [] if args.json else rows:
            print(f"{row['scene']:<24} {row['description']}")
        return
    if args.scene is None or args.output is None:
        raise NeuralRTError("render needs SCENE and -o OUTPUT.exr (or --list-builtins)")
    settings = _settings_of(args.settings, "render", {"inference", "nif"})
    result = api.render(args.scene, args.output, spp=args.spp, resolution=args.res, seed=args.seed,
                        max_depth=args.max_depth, primary=args.primary, detail=args.detail, device=args.device,
                        progress=not args.quiet, allow_mesh_mismatch=args.allow_mesh_mismatch,
                        nif=args.nif, nif_train_spp=args.nif_train_spp, nif_config=settings.get("nif"),
                        inference=settings.get("inference"))
    _print_result(result, args.json)


def _modified(path: str) -> int | None:
    try:
        return os.stat(path).st_mtime_ns
    except OSError:
        return None


def _cmd_train(args) -> None:
    if args.list_presets:
        rows = [row for row in api.list_presets() if args.method in (None, row["method"])]  # (--method: its own)
        if args.json:
            print(json.dumps(rows))
        for row in [] if args.json else rows:
            default = f" (default on {', '.join(row['default_on'])})" if row["default_on"] else ""
            print(f"{row['method']:<8} {row['preset']:<8}{default}")
        return
    if args.mesh is None or args.output is None:
        raise NeuralRTError("train needs MESH and -o OUTPUT.nrt (or --list-presets)")
    checkpoint = f"{args.output}.ckpt"
    before, model_before = _modified(checkpoint), _modified(args.output)  # (an earlier run's, or the one --resume continues)
    args.interrupt_hint = lambda: (  # (asked once interrupted: has this run written its model, or a checkpoint?)
        f"the model was written before the interrupt{'; `neuralrt info MODEL --plot FILE` draws its training plot' if args.plot else ''}"
        if _modified(args.output) not in (None, model_before)
        else "run the same command with --resume to continue from the last checkpoint"
        if _modified(checkpoint) not in (None, before) or (args.resume and before is not None)
        else "no checkpoint was written yet: run the command again to start over")
    result = api.train(args.mesh, args.output, method=args.method, preset=args.preset, steps=args.steps, batch=args.batch,
                       seed=args.seed, resume=args.resume, device=args.device, progress=not args.quiet,
                       settings=parse_settings(args.settings) or None, plot=args.plot)
    _print_result(result, args.json)


def _inference_settings(pairs: list[str] | None, command: str) -> dict | None:
    """The ``inference`` section of ``--set`` pairs (None without any): the one section a trained
    model may change when it answers."""
    return _settings_of(pairs, command, {"inference"}).get("inference")


def _settings_of(pairs: list[str] | None, command: str, sections: set[str]) -> dict:
    """``--set`` pairs by section, where each is one of ``sections`` (``inference``: how a trained
    model answers; ``nif``: render's NIF settings)."""
    settings = parse_settings(pairs)
    if set(settings) - sections:
        takes = " and ".join(f"{s}.KEY=VALUE" for s in sorted(sections))
        raise NeuralRTError(f"{command} --set takes {takes} only, not {sorted(set(settings) - sections)[0]}.*"
                            + (": other keys make another model (neuralrt train)" if "inference" in sections else ""))
    return settings


def _cmd_evaluate(args) -> None:
    result = api.evaluate(args.model, args.mesh, rays=args.rays, seed=args.seed, images=not args.no_images,
                          image_dir=args.images, device=args.device, allow_mesh_mismatch=args.allow_mesh_mismatch,
                          timing=not args.no_timing, progress=not args.quiet, inference=_inference_settings(args.settings, "eval"))
    if args.json:
        _print_result(result, True)
        return
    parts = ("outside", "surface", "images", "features", "memory", "speed")
    _print_result({k: v for k, v in result.items() if k not in parts}, False)  # (rays, seed, whether the mesh matches)
    for part in parts:
        if part in result:
            print(f"{part}:")
            _print_result(result[part], False)


def _cmd_import(args) -> None:
    _print_result(api.import_scene(args.gltf, args.output), args.json)


def _cmd_convert(args) -> None:
    select = [n.strip() for n in args.select.split(",") if n.strip()] if args.select else None
    args.interrupt_hint = ("run the same command again: finished models are reused, and unfinished ones resume "
                           "from their checkpoints where one was written")
    result = api.convert(args.scene, args.output, models_dir=args.models_dir, select=select,
                         min_triangles=args.min_triangles, method=args.method, preset=args.preset, group=args.group,
                         steps=args.steps,
                         batch=args.batch, seed=args.seed, detail=args.detail, device=args.device,
                         progress=not args.quiet, executor=args.executor, address=args.address,
                         cpus_per_model=args.cpus_per_model, gpus_per_model=args.gpus_per_model,
                         threads_per_model=args.threads_per_model, max_retries=args.max_retries,
                         settings=parse_settings(args.settings) or None)
    _print_result(result, args.json)


def _cmd_demo(args) -> None:
    args.interrupt_hint = "run the same command again: a model already trained in the folder is reused"
    report = api.demo(args.out, quick=args.quick, device=args.device, progress=not args.quiet, scene=args.scene,
                      method=args.method, preset=args.preset, spp=args.spp, resolution=args.res, steps=args.steps,
                      batch=args.batch, detail=args.detail, min_triangles=args.min_triangles, max_depth=args.max_depth,
                      primary=args.primary, seed=args.seed)
    if args.json:
        _print_result(report, True)
        return
    m, t = report["memory"], report["time"]
    reused = all(model.get("reused") for model in report["models"])
    trained = "models reused from the folder" if reused else f"train {t['train_s']:.0f} s"
    print(f"FLIP {report['flip']:.4f} (same seed; at another seed {report['flip_other_seed']:.4f}, "
          f"noise floor {report['flip_noise_floor']:.4f}), "
          f"PSNR {report['psnr']:.2f} dB; neural {m['neural_bytes'] / 2**20:.2f} MiB vs BVH A "
          f"{m['bvh_a_bytes'] / 2**20:.2f} MiB; {trained}, exact {t['exact_render_s']:.3g} s, "
          f"hybrid {t['hybrid_render_s']:.3g} s ({t['hybrid_render_s'] / max(t['exact_render_s'], 1e-9):.2f}x)")
    print(f"report: {(Path(args.out) / report['images']['report_md']).resolve()}")


def _add_method(p: argparse.ArgumentParser) -> None:
    from .methods import DEFAULT_METHOD, method_names

    p.add_argument("--method", choices=method_names(), help=f"intersection method (default: {DEFAULT_METHOD})")
    p.add_argument("--preset", help="the method's preset (default: the method's for the device, e.g. lsnif: hq on cpu, "
                                    "gpu on cuda; list them with `neuralrt train --list-presets`)")


def _add_training(p: argparse.ArgumentParser) -> None:
    """Options shared by everything that trains models."""
    _add_method(p)
    p.add_argument("--steps", type=int, help="training steps per model (default: the preset's)")
    p.add_argument("--batch", type=int, help="rays per training step (default: the preset's)")
    p.add_argument("--seed", type=int, help="seed of weights, hash table and rays (default: 0)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", dest="settings",
                   help="change one config key of the preset, e.g. --set voxel.resolution=64 (repeatable; keys: python -m neuralrt.configdoc)")
    p.add_argument("--quiet", action="store_true", help="no progress output")


def _add_common(p: argparse.ArgumentParser, json_flag: bool = True) -> None:
    p.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda")
    if json_flag:
        p.add_argument("--json", action="store_true", help="print the result as JSON (a list for the --list-* options)")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="neuralrt",
        description="Neural ray intersection (LSNIF, N-BVH, NIF) beside exact Embree ray tracing.",
    )
    parser.add_argument("--version", action="version", version=f"neuralrt {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("compare", help="FLIP, PSNR and relMSE of a test image against a reference")
    p.add_argument("reference", help="reference image (EXR, PNG, JPG, HDR)")
    p.add_argument("test", help="test image of the same size")
    p.add_argument("--heatmap", metavar="PNG", help="write the FLIP error map (magma) here")
    p.add_argument("--hdr", action="store_true", help="HDR-FLIP on linear values (default: LDR-FLIP on clamped sRGB)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_compare)

    p = sub.add_parser("info", help="triangles, bounds and BVH A/B bytes of a mesh; summary of a scene or model")
    p.add_argument("path", help="mesh file or procedural:NAME:DETAIL, scene file / builtin:NAME, or model file (.nrt)")
    p.add_argument("--plot", metavar="FILE", help="a model or checkpoint: draw its training curve here (.png, .pdf, .svg)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("render", help="path-trace a scene to EXR + PNG (+ albedo/normal/depth AOVs)")
    p.add_argument("scene", nargs="?", help="scene file (.toml/.json), builtin:NAME[?detail=N], or one mesh (a file, "
                                            "procedural:NAME:DETAIL) or model (.nrt) to render alone, framed and lit")
    p.add_argument("-o", "--output", help="output .exr (the .png and AOVs are written beside it)")
    p.add_argument("--spp", type=int, help="samples per pixel (default: the scene's)")
    p.add_argument("--res", type=_resolution, metavar="WxH", help="resolution (default: the scene's)")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same image; default: 0)")
    p.add_argument("--max-depth", type=int, help="maximum bounces (default: the scene's)")
    p.add_argument("--primary", choices=["exact", "neural"], default="exact",
                   help="who answers camera rays for neural objects that keep their mesh (default: exact)")
    p.add_argument("--detail", type=int, help="procedural mesh detail of a built-in scene")
    p.add_argument("--list-builtins", action="store_true", help="list the built-in scenes and exit")
    p.add_argument("--allow-mesh-mismatch", action="store_true",
                   help="use models trained on another mesh than their object's (default: an error)")
    p.add_argument("--nif", metavar="OBJECTS|auto", help="answer these objects' shadow rays with NIF, trained online "
                   "(comma-separated names; auto: objects over 100K triangles; docs/nif.md)")
    p.add_argument("--nif-train-spp", type=int, metavar="N", help="samples per pixel rendered exactly to train NIF (default: 32, or half of the spp when 32 is not below it)")
    p.add_argument("--set", dest="settings", action="append", metavar="inference.KEY=VALUE",
                   help="neural models answer with an inference setting changed, each model that has the key, e.g. "
                        "inference.lod=2 (an N-BVH level of detail); over an object's own (repeatable; keys: python -m neuralrt.configdoc); "
                        "with --nif, nif.KEY=VALUE changes a NIF setting, e.g. nif.shadow_rays=every_hit (docs/nif.md)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_common(p)
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("train", help="train a neural model (LSNIF, ...) of a mesh")
    p.add_argument("mesh", nargs="?", help="mesh file (OBJ, PLY, OFF, STL, glTF/GLB) or a built-in mesh, procedural:NAME:DETAIL (statue:0..5, hairball:0..8, foliage:0..6)")
    p.add_argument("-o", "--output", help="model file to write (.nrt)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from OUTPUT.ckpt (its method, "
                   "training.checkpoint_every and N-BVH's --steps are the run's unless given)")
    p.add_argument("--plot", metavar="FILE", help="draw the training curve (loss, its terms, hit accuracy) here (.png, .pdf, .svg)")
    p.add_argument("--list-presets", action="store_true", help="list every method's presets (with --method: its own) and exit")
    _add_training(p)
    _add_common(p)
    p.set_defaults(func=_cmd_train)

    p = sub.add_parser("eval", help="held-out accuracy of a model against its mesh (+ orbit images with FLIP)")
    p.add_argument("model", help="model file (.nrt)")
    p.add_argument("mesh", help="the mesh the model was trained on (a file or procedural:NAME:DETAIL)")
    p.add_argument("--rays", type=int, default=1 << 17, help="held-out rays, half outside, half surface (default: 131072, at most 4194304)")
    p.add_argument("--seed", type=int, help="seed of the held-out rays (default: 1000003)")
    images = p.add_mutually_exclusive_group()
    images.add_argument("--images", metavar="DIR", help="write the neural/exact normal and depth images here, with overview.png "
                        "(all of them) and errors.png (error distributions, IoU per view)")
    images.add_argument("--no-images", action="store_true", help="skip the orbit-camera images")
    p.add_argument("--allow-mesh-mismatch", action="store_true",
                   help="evaluate even if the model was trained on another mesh (default: an error)")
    p.add_argument("--no-timing", action="store_true",
                   help="skip the speed figures (rays/s of the model and of exact tracing on the held-out rays)")
    p.add_argument("--set", dest="settings", action="append", metavar="inference.KEY=VALUE",
                   help="evaluate the model answering with an inference setting changed, e.g. inference.lod=2 (an "
                        "N-BVH level of detail; repeatable; keys: python -m neuralrt.configdoc)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_common(p)
    p.set_defaults(func=_cmd_evaluate)

    p = sub.add_parser("import", help="a glTF scene as a scene file: its nodes' meshes as instances, its camera and lights")
    p.add_argument("gltf", help="glTF file (.gltf, .glb)")
    p.add_argument("-o", "--output", required=True, help="scene file to write (.toml/.json)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_import)

    p = sub.add_parser("convert", help="train models for a scene's complex objects; write a scene that uses them")
    p.add_argument("scene", help="scene file or builtin:NAME")
    p.add_argument("-o", "--output", required=True, help="converted scene file (.toml/.json)")
    p.add_argument("--models-dir", help="where models are written and reused (default: OUTPUT's folder/models)")
    p.add_argument("--select", metavar="NAMES", help="comma-separated object names to convert")
    p.add_argument("--min-triangles", type=int, help="convert objects with at least this many triangles (default: 10000)")
    p.add_argument("--group", action="store_true", help="one model for all selected objects together")
    p.add_argument("--detail", type=int, help="procedural mesh detail of a built-in scene")
    _add_training(p)
    _add_common(p)
    g = p.add_argument_group("executor", "who trains the models (docs/cluster.md)")
    g.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="local: one after another in this process (default); ray: one Ray task per model")
    g.add_argument("--address", help="ray: an existing cluster (auto, HOST:PORT, ray://HOST:PORT); "
                                     "default: a local Ray instance on this machine's cores")
    g.add_argument("--cpus-per-model", type=float, metavar="C", help="ray: CPUs each training task asks for (default: 1)")
    g.add_argument("--gpus-per-model", type=float, metavar="G",
                   help="ray: GPUs each task asks for (default: 1 with --device cuda, else 0; 0.5 shares a GPU)")
    g.add_argument("--threads-per-model", type=int, metavar="T",
                   help="torch and numba threads while a model trains (ray default: --cpus-per-model; local default: "
                        "the process's); the same threads give the same model bits")
    g.add_argument("--max-retries", type=int, metavar="N",
                   help="ray: reruns of a task whose worker died; it resumes from its checkpoint (default: 3)")
    p.set_defaults(func=_cmd_convert)

    p = sub.add_parser("demo", help="convert a built-in scene, render exact and hybrid, compare, write a report")
    p.add_argument("-o", "--out", "--output", dest="out", default="neuralrt-demo",  # (-o, as the other commands take)
                   help="report folder (default: ./neuralrt-demo)")
    p.add_argument("--quick", action="store_true", help="a short run: the same model trained for 150 steps of 4,096 rays, a small image")
    p.add_argument("--scene", help="scene to convert (default: builtin:cornell-statue)")
    _add_method(p)
    p.add_argument("--spp", type=int, help="samples per pixel of each render (default: 256; --quick: 8)")
    p.add_argument("--res", type=_resolution, metavar="WxH", help="render resolution (default: 256x256; --quick: 96x96)")
    p.add_argument("--steps", type=int, help="training steps (default: the preset's; --quick: 150)")
    p.add_argument("--batch", type=int, help="rays per training step (default: the preset's; --quick: 4096)")
    p.add_argument("--detail", type=int, help="procedural mesh detail of the built-in scene")
    p.add_argument("--min-triangles", type=int, help="objects this large become neural (default: convert's, 10000)")
    p.add_argument("--max-depth", type=int, help="maximum bounces of both renders (default: 4; --quick: 3)")
    p.add_argument("--primary", choices=("exact", "neural"),
                   help="who answers the hybrid render's camera rays (default: exact)")
    p.add_argument("--seed", type=int, help="seed of both renders (default: 1)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    _add_common(p)
    p.set_defaults(func=_cmd_demo)

    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"neuralrt: warning: {_message(str(message))}", file=sys.stderr)  # (names from files: escaped, one line)


def main(argv: list[str] | None = None) -> int:
    show = warnings.showwarning
    warnings.showwarning = _show_warning  # one line per warning, no source line (a method plugin's too)
    on_term = _terminate_as_interrupt()
    unraisable, sys.unraisablehook = sys.unraisablehook, _note_swallowed_interrupt
    _SWALLOWED.clear()
    _OTHER_UNRAISABLE[:] = [unraisable]
    args = None
    stdout = sys.stdout
    if stdout is not None:  # (None: started with it closed, `>&-`; print then writes nothing, as Python's does)
        sys.stdout = _NamedStandardOutput(stdout)
    try:
        args = build_parser().parse_args(argv)  # (loads method plugins: --method lists theirs)
        _check_environment()  # (after --help and --version, which need none of it)
        with spelled_as_flags():  # errors name --flags, as the user typed them
            args.func(args)
        if _SWALLOWED:  # (it ran to its end: an interrupt is still an interrupt, exit 130 or 143)
            raise _SWALLOWED[0]
        if sys.stdout is not None:  # (left to the interpreter's final flush, `> /dev/full` was "Exception ignored", exit 120)
            sys.stdout.flush()
    except NeuralRTError as exc:
        print(f"neuralrt: error: {_message(str(exc))}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader went away (`neuralrt info X | head`): stop quietly, as other tools do
        discard_the_rest(sys.stdout)
        return 141
    except OSError as exc:  # the system refused a read or write the checks above let through (disk full, ...)
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"neuralrt: error: {_message(f'{where}{exc.strerror or exc}')}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - an interrupt inside another exception, or not ours
        interrupt = _interrupt_within(exc)
        if interrupt is None:
            raise
        return _interrupted(interrupt, args)
    except KeyboardInterrupt as exc:
        return _interrupted(exc, args)
    finally:
        sys.stdout = stdout
        warnings.showwarning = show
        sys.unraisablehook = unraisable
        if on_term is not None:
            signal.signal(signal.SIGTERM, on_term)
    return 0


def discard_the_rest(stream) -> None:
    """What a stream that cannot be written still holds goes to /dev/null, so the interpreter's own
    final flush cannot fail again (a closed pipe; "Exception ignored in: <stdout>", exit 120, after
    the command's one line said why)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, stream.fileno())
        finally:
            os.close(devnull)
        stream.flush()
    except (OSError, ValueError):
        pass


def _check_environment() -> None:
    """One line for an environment setting that a library would answer with a traceback, later."""
    threads = os.environ.get("NUMBA_NUM_THREADS")
    try:
        usable = threads is None or int(threads) >= 1  # (as numba parses it)
    except ValueError:
        usable = False
    if not usable:
        raise NeuralRTError(f"NUMBA_NUM_THREADS={threads!r}: expected a whole number of threads, 1 or more (unset, "
                            "numba uses every core)")
    layer = os.environ.get("NUMBA_THREADING_LAYER")
    if layer is not None and layer.lower() not in _NUMBA_LAYERS:
        raise NeuralRTError(f"NUMBA_THREADING_LAYER={layer!r}: numba's threading layers are {', '.join(_NUMBA_LAYERS)}")
    if layer is not None and layer.lower() in ("tbb", "safe"):  # (only TBB will do: numba's traceback at the first kernel)
        try:
            importlib.import_module("numba.np.ufunc.parallel")._check_tbb_version_compatible()  # (as numba asks first)
            importlib.import_module("numba.np.ufunc.tbbpool")
        except (ImportError, ValueError) as exc:
            raise NeuralRTError(f"NUMBA_THREADING_LAYER={layer}: numba cannot load TBB here ({exc}): pip install tbb, "
                                "or choose another layer") from None


_NUMBA_LAYERS = ("default", "safe", "threadsafe", "forksafe", "omp", "tbb", "workqueue")


def _interrupt_within(exc: BaseException) -> KeyboardInterrupt | None:
    """The Ctrl-C or SIGTERM an exception was raised from, if any: Python wraps one raised in a
    class's ``__set_name__`` (as matplotlib's first import runs them) in a RuntimeError, which
    printed a traceback and exit 1 instead of the interrupt's one line."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _interrupted(exc: KeyboardInterrupt, args) -> int:
    """The interrupt's one line (with the command's hint), and its exit status: 130, or 143 for SIGTERM."""
    hint = getattr(args, "interrupt_hint", None)
    hint = hint() if callable(hint) else hint
    terminated = isinstance(exc, Terminated) or Terminated.received  # (Ray's waits re-raise a plain KeyboardInterrupt)
    print(f"neuralrt: {'terminated' if terminated else 'interrupted'}{f' ({hint})' if hint else ''}", file=sys.stderr)
    return 128 + (signal.SIGTERM if terminated else signal.SIGINT)


def _note_swallowed_interrupt(unraisable) -> None:
    """`sys.unraisablehook`: an interrupt raised inside a finalizer or weakref callback (garbage
    collection, as matplotlib's figures are freed) cannot propagate: Python printed "Exception
    ignored in ..." with its traceback, and the command ran on to exit 0. It is noted instead, and
    the command, once it returns, ends as interrupted (sending the signal again from here would
    raise it inside this hook); other exceptions go to the hook `main` found."""
    if isinstance(unraisable.exc_value, KeyboardInterrupt):
        _SWALLOWED.append(unraisable.exc_value)
        return
    (_OTHER_UNRAISABLE or [sys.__unraisablehook__])[0](unraisable)


_SWALLOWED: list[KeyboardInterrupt] = []  # interrupts raised where they could not propagate, this command
_OTHER_UNRAISABLE: list = []  # the hook `main` found (pytest's, say): every other exception goes there


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a job scheduler), raised where Ctrl-C would be: the same clean stop."""

    received = False  # set by the handler: code that turns any KeyboardInterrupt into its own (Ray) loses the class


def _terminate_as_interrupt():
    """Make SIGTERM stop a command as Ctrl-C does (checkpoints kept, temporary files and new empty
    folders removed, one line); returns the previous handler (None off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None

    Terminated.received = False

    def stop(signum, frame):
        Terminated.received = True
        raise Terminated()

    return signal.signal(signal.SIGTERM, stop)


if __name__ == "__main__":
    raise SystemExit(main())
