"""The Python API behind each CLI command: ``neuralrt X`` calls ``neuralrt.api.X`` with the same
arguments, so scripts and the command line do the same thing."""

from __future__ import annotations

from pathlib import Path

__all__ = ["compare", "info"]

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
    return scene.summary()


def _model_info(path: Path) -> dict:
    from .methods import load_model

    model = load_model(path)
    report = model.memory_bytes()
    header = getattr(model, "header", {}) or {}
    return {
        "kind": "model",
        "path": str(path),
        "method": header.get("method", type(model).__name__),
        "memory_bytes": report.total,
        "memory_parts": {k: int(v) for k, v in report.parts.items()},
        "bounds": model.bounds.tolist(),
        **{k: header[k] for k in ("format_version", "source_mesh_hash", "training") if k in header},
    }

