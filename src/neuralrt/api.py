"""The Python API behind each CLI command: ``neuralrt X`` calls ``neuralrt.api.X`` with the same
arguments, so scripts and the command line do the same thing."""

from __future__ import annotations

from pathlib import Path

from .errors import NeuralRTError

__all__ = ["compare", "convert", "demo", "evaluate", "info", "list_builtins", "render", "train"]

MODEL_SUFFIXES = {".nrt"}
SCENE_SUFFIXES = {".toml", ".json"}


def compare(reference: str | Path, test: str | Path, heatmap: str | Path | None = None, hdr: bool = False) -> dict:
    """FLIP, PSNR and relMSE of ``test`` against ``reference``; writes the FLIP heat map PNG if asked."""
    from .eval.image_metrics import compare_files

    result = compare_files(reference, test, heatmap=heatmap, hdr=hdr)
    out = result.as_dict()
    if heatmap is not None:
        out["heatmap"] = str(heatmap)
    return out


def info(path: str | Path) -> dict:
    """Facts about a mesh, scene (file or ``builtin:NAME``) or model file."""
    spec = str(path)
    suffix = Path(spec).suffix.lower()
    if suffix in MODEL_SUFFIXES:
        return _model_info(Path(spec))
    if spec.startswith("builtin:") or suffix in SCENE_SUFFIXES:
        return _scene_info(spec)
    return _mesh_info(Path(spec))


def _mesh_info(path: Path) -> dict:
    from .accel.classical_memory import classical_memory
    from .geometry.mesh import load_mesh

    mesh = load_mesh(path)
    lo, hi = mesh.bounds
    mem = classical_memory(mesh)
    return {
        "kind": "mesh",
        "path": str(path),
        "triangles": mesh.num_triangles,
        "vertices": int(len(mesh.vertices)),
        "bounds": [lo.tolist(), hi.tolist()],
        "materials": [m.name for m in mesh.materials],
        **mem.as_dict(),
    }


def _scene_info(spec: str) -> dict:
    from .scene.loader import load_scene

    scene = load_scene(spec)
    accel = scene.accel
    blases = accel.unique_blases
    triangles = sum(b.mesh.num_triangles for b in blases if hasattr(b, "mesh"))
    instanced = sum(inst.blas.mesh.num_triangles for inst in accel.instances if hasattr(inst.blas, "mesh"))
    memory = accel.memory_bytes()
    return {
        "kind": "scene",
        "scene": spec,
        "instances": len(accel.instances),
        "unique_blas": len(blases),
        "neural_instances": sum(not hasattr(inst.blas, "mesh") for inst in accel.instances),
        "triangles_unique": triangles,
        "triangles_instanced": instanced,
        "materials": len(scene.materials),
        "lights": scene.lights.kinds,
        "resolution": [scene.camera.width, scene.camera.height],
        "bounds": accel.bounds.tolist(),
        "memory_bytes": memory.total,
        "memory_parts": {k: int(v) for k, v in memory.parts.items()},
    }


def _model_info(path: Path) -> dict:
    from .io.model_file import read_header
    from .methods import load_model

    header = read_header(path)
    report = load_model(path).memory_bytes()
    training = header.get("training") or {}
    return {
        "kind": "model",
        "path": str(path),
        "method": header["method"],
        "format_version": header["format_version"],
        "memory_bytes": report.total,
        "memory_parts": {k: int(v) for k, v in report.parts.items()},
        "bounds": header.get("bounds"),
        "mesh_name": header.get("mesh_name"),
        "mesh_sha256": header.get("mesh_sha256"),
        "training": {k: training[k] for k in ("steps", "rays", "seconds", "hit_accuracy") if k in training},
    }


def list_builtins() -> list[tuple[str, str]]:
    """(name, description) of every built-in scene, usable as ``builtin:NAME``."""
    from .scene.builtins import list_builtins as _list

    return _list()


def render(
    scene: str | Path,
    output: str | Path,
    *,
    spp: int | None = None,
    resolution: tuple[int, int] | None = None,
    seed: int = 0,
    max_depth: int | None = None,
    primary: str = "exact",
    detail: int | None = None,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """Path-trace ``scene`` (file or ``builtin:NAME``) to ``output`` (EXR; PNG and AOVs beside it)."""
    from .render.integrator import render as _render
    from .scene.loader import load_scene

    output = Path(output)
    if output.suffix.lower() != ".exr":
        raise NeuralRTError(f"{output}: output must be an .exr file (a .png and AOVs are written beside it)")
    loaded = load_scene(str(scene), device=device, resolution=resolution, detail=detail, primary=primary)
    try:
        result = _render(loaded, spp=spp, seed=seed, max_depth=max_depth, progress=progress, primary=primary)
    except ValueError as exc:
        raise NeuralRTError(str(exc)) from None
    files = result.save(output)
    h, w = result.image.shape[:2]
    return {
        "scene": str(scene),
        "output": str(output),
        "files": [str(f) for f in files],
        "resolution": [w, h],
        "spp": result.spp,
        "seconds": result.seconds,
        "seconds_per_spp_per_megapixel": result.seconds / result.spp / (w * h / 1e6),
    }


def train(
    mesh: str | Path,
    output: str | Path,
    *,
    preset: str = "hq",
    steps: int | None = None,
    batch: int | None = None,
    seed: int | None = None,
    resume: bool = False,
    device: str = "cpu",
    progress: bool = True,
) -> dict:
    """Train an LSNIF model of ``mesh`` and write it to ``output`` (atomically).

    A checkpoint ``<output>.ckpt`` is written as training goes; ``resume=True`` continues an
    interrupted run from it. It is removed once the model file is written.
    """
    from .methods.lsnif import LSNIFConfig
    from .training.api import train_lsnif

    output = Path(output)
    if not output.parent.exists():
        output.parent.mkdir(parents=True, exist_ok=True)
    try:
        config = LSNIFConfig.preset(preset).with_training(steps=steps, batch_size=batch, seed=seed)
    except ValueError as exc:
        raise NeuralRTError(str(exc).splitlines()[0]) from None
    checkpoint = output.with_name(output.name + ".ckpt")
    if resume and not checkpoint.is_file():
        raise NeuralRTError(f"{checkpoint}: no checkpoint to resume from")
    model = train_lsnif(str(mesh), config, progress=progress, checkpoint=checkpoint, resume=resume, device=device)
    model.save(output)
    checkpoint.unlink(missing_ok=True)
    memory = model.memory_bytes()
    return {"model": str(output), "preset": preset, "memory_bytes": memory.total,
            "memory_parts": dict(memory.parts), "training": model.training_record}


def evaluate(
    model: str | Path,
    mesh: str | Path,
    *,
    rays: int = 1 << 17,
    seed: int | None = None,
    images: bool = True,
    image_dir: str | Path | None = None,
    device: str = "cpu",
) -> dict:
    """Held-out accuracy of a model against its mesh: rays from outside and from the surface,
    plus normal/depth images from orbit cameras, neural vs exact, with FLIP."""
    from .eval.intersection_metrics import HELD_OUT_SEED, evaluate_model
    from .geometry.mesh import load_mesh
    from .methods import load_model

    blas = load_model(model, device=device)
    source = load_mesh(mesh)
    expected = getattr(blas, "mesh_hash", None)
    result = evaluate_model(blas, source, rays=rays, seed=HELD_OUT_SEED if seed is None else seed,
                            images=images, image_dir=image_dir)
    result["mesh_matches_model"] = expected is None or expected == source.content_hash()
    return result


def convert(scene: str | Path, output: str | Path, **options) -> dict:
    """Train models for a scene's complex objects and write a scene that uses them
    (see `neuralrt.scene.convert.convert_scene` for the options)."""
    from .scene.convert import convert_scene

    return convert_scene(str(scene), output, **options).as_dict()


def demo(out_dir: str | Path = "neuralrt-demo", quick: bool = False, *, device: str = "cpu", progress: bool = True,
         **overrides) -> dict:
    """Convert a built-in scene, render exact and hybrid, compare, and write a report folder."""
    from dataclasses import replace

    from .demo import DEMO_DEFAULT, DEMO_QUICK, run_demo

    settings = replace(DEMO_QUICK if quick else DEMO_DEFAULT, **{k: v for k, v in overrides.items() if v is not None})
    return run_demo(out_dir, quick=quick, device=device, progress=progress, settings=settings)
