"""The runtime scene the integrator renders, and writing a scene spec back to a file."""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from ..accel.tlas import SceneAccel
from ..errors import SceneError
from ..io.files import write_atomically
from ..render.camera import Camera
from ..render.lights import LightSet
from ..render.materials import MaterialTable
from .schema import RenderSettings, SceneSpec

__all__ = ["Scene", "save_scene", "instance_ray_offsets"]


@dataclass
class Scene:
    """Everything needed to render: camera, accelerator, materials, lights, render defaults.

    ``instance_offsets[i]`` is how far (world units, along the geometric normal) a secondary ray
    leaving instance ``i`` starts, so it does not hit the surface it leaves.
    """

    camera: Camera
    accel: SceneAccel
    materials: MaterialTable
    lights: LightSet
    instance_offsets: Tensor  # [I] float32
    settings: RenderSettings
    spec: SceneSpec | None = None  # what the scene was built from (paths made absolute)
    name: str = ""
    device: torch.device = torch.device("cpu")
    primary: str = "exact"  # who answers camera rays of objects with a model ("neural": they kept no mesh BVH)

    def __post_init__(self) -> None:
        # A material index beyond the table would only fail at render time, deep in shading.
        n = len(self.materials)
        for k, inst in enumerate(self.accel.instances):
            bad = (inst.material_map < 0) | (inst.material_map >= n)
            if bool(bad.any()):
                raise SceneError(f"instance {k} ({inst.name or 'unnamed'}): material index "
                                 f"{int(inst.material_map[bad][0])} is out of range (the scene has {n} materials)")

    @property
    def environment(self):
        return self.lights.environment

    def __repr__(self) -> str:
        return (f"Scene({self.name!r}: {len(self.accel.instances)} instances, {len(self.materials)} materials, "
                f"lights={self.lights.kinds}, {self.camera.width}x{self.camera.height})")


def instance_ray_offsets(accel: SceneAccel) -> Tensor:
    """Each instance's BLAS ``secondary_offset`` scaled to world units by its largest axis scale."""
    out = []
    for inst in accel.instances:
        linear = inst.transform.matrix[:3, :3]
        scale = float(torch.linalg.norm(linear, dim=0).max())
        out.append(float(getattr(inst.blas, "secondary_offset", 1e-4)) * scale)
    return torch.tensor(out, dtype=torch.float32, device=accel.device)


def _relocated_paths(spec: SceneSpec, folder: Path) -> SceneSpec:
    """A copy whose absolute file paths are rewritten relative to ``folder`` (where the file will live)."""

    def rel(p: str) -> str:
        if not os.path.isabs(p):
            return p
        try:
            return os.path.relpath(p, folder)
        except ValueError:  # another drive on Windows: keep absolute
            return p

    return spec.with_paths(rel)


def save_scene(spec: SceneSpec, path: str | Path) -> None:
    """Write ``spec`` as TOML (``.toml``) or JSON (``.json``) that `load_scene` reads back to the same
    scene; absolute file paths are written relative to the new file's folder. Atomic. ``spec`` is a
    `SceneSpec` (e.g. the first of `neuralrt.scene.loader.load_scene_spec`'s three values)."""
    from ..devices import check_path
    from .loader import IN_MEMORY

    if not isinstance(spec, SceneSpec):
        raise SceneError(f"spec: expected a SceneSpec (load_scene_spec(path)[0], or one built in Python), got {type(spec).__name__}")
    path = check_path("path", path)
    held = [f"objects.{i}.{key}" for i, obj in enumerate(spec.objects) for key in ("mesh", "model")
            if Path(getattr(obj, key) or "").name.startswith(IN_MEMORY)]  # (made absolute like a path)
    if held:  # (a file naming "<in-memory mesh 'x'>" would not load)
        raise SceneError(f"{path}: {', '.join(held)}: an in-memory mesh or model (load_dict) has no file to name; "
                         "save it first (Mesh: trimesh export; model: .save) and name that file")
    suffix = path.suffix.lower()
    if suffix not in (".toml", ".json"):
        raise SceneError(f"{path}: scene files must end in .toml or .json")
    if not path.parent.is_dir():
        raise SceneError(f"{path}: folder {path.parent} does not exist")
    data = _without_defaults(_relocated_paths(spec, path.parent.resolve()).model_dump(mode="json", exclude_none=True))
    if suffix == ".json":
        text = json.dumps(data, indent=2) + "\n"
    else:
        import tomli_w

        unset = [f"objects.{i}.inference.{k}" for i, o in enumerate(data.get("objects", []))
                 for k, v in o.get("inference", {}).items() if v is None]
        if unset:  # (secondary_lod = None: TOML has no null)
            raise SceneError(f"{path}: {unset[0]} is None, which TOML cannot write: save the scene as .json")
        text = _numbers_on_one_line(tomli_w.dumps(data))
    write_atomically(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


_IDENTITY = {"translate": [0.0, 0.0, 0.0], "rotate": [0.0, 0.0, 0.0], "scale": 1.0}


def _without_defaults(data: dict) -> dict:
    """A scene's dict without what each object's defaults say again (an identity ``translate``,
    ``rotate`` and ``scale``, which a ``matrix`` replaces anyway; an empty ``materials`` or
    ``inference`` map): an imported scene has thousands of objects."""
    for obj in data.get("objects", []):
        transform = obj.get("transform", {})
        for key, identity in _IDENTITY.items():
            if "matrix" in transform or transform.get(key) == identity:
                transform.pop(key, None)
        if not transform:
            obj.pop("transform", None)
        for key in ("materials", "inference"):
            if not obj.get(key, True):
                obj.pop(key)
    return data


_NUMBER_ARRAY = re.compile(r"\[\n((?:[ \t]+[-+0-9.eEinfa]+,\n)+)[ \t]*\]")


def _numbers_on_one_line(text: str) -> str:
    """tomli_w's TOML with each array of numbers on one line (``[0.0, 1.0, 0.0]``; it writes one
    number per line)."""
    return _NUMBER_ARRAY.sub(lambda m: "[" + ", ".join(v.strip().rstrip(",") for v in m.group(1).splitlines()) + "]", text)
