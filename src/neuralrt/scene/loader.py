"""Loading scenes: a file (TOML / JSON) or ``builtin:<name>[?detail=N]`` -> validated spec -> runtime `Scene`.

Relative paths in a file (meshes, models, textures, environment images) resolve against the
file's folder. Every problem is raised as a one-line `SceneError` naming the file and the key,
e.g. ``scene.toml: objects.2.transform.scale: scale must be finite and non-zero``.
Objects that use the same mesh (same resolved file, or same generator and parameters) share one
`MeshBLAS` (instancing): it is loaded and built once.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
import math
import numbers
import os
import tomllib
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch
from pydantic import ValidationError

from ..accel.blas import BLAS
from ..accel.mesh_blas import MeshBLAS
from ..arguments import given
from ..accel.tlas import Instance, SceneAccel
from ..devices import check_device, check_path
from ..errors import ConfigError, NeuralRTError, SceneError, outside_stacklevel, validation_errors
from ..geometry.mesh import Mesh, load_mesh
from ..io.files import input_file_problem, resolved
from ..io.model_file import read_header
from ..rays import AABB
from ..methods.base import check_mesh_match, checked_inference, is_neural, mesh_mismatch_unsaid, ray_views
from ..render.camera import Camera
from ..render.lights import AreaLights, Environment, LightSet, PointLights
from ..render.materials import MaterialKind, MaterialTable
from .schema import (
    ConductorMaterialSpec,
    DiffuseMaterialSpec,
    MAX_RADIANCE,
    EmissiveMaterialSpec,
    ObjectSpec,
    PlasticMaterialSpec,
    SceneSpec,
    check_resolution,
)
from .material_rules import is_emissive, lit_slots, material_index, material_map, scene_material_for, scene_materials
from .scene import Scene, instance_ray_offsets
from .studio import is_lone_object

__all__ = ["load_scene", "load_dict", "load_scene_spec", "build_scene", "scene_material_for", "shape_for", "BUILTIN_PREFIX"]

BUILTIN_PREFIX = "builtin:"
IN_MEMORY = "<in-memory "  # how a `load_dict` spec names a Mesh or model object given in place of a file


def load_scene(
    path_or_builtin: str | os.PathLike,
    device="cpu",
    resolution: tuple[int, int] | None = None,
    detail: int | None = None,
    primary: str = "exact",
    allow_mesh_mismatch: bool = False,
    inference: dict | None = None,
) -> Scene:
    """Load and build a scene.

    ``path_or_builtin``: a ``.toml`` / ``.json`` scene file, ``builtin:<name>`` with an optional
    ``?detail=N`` (see `neuralrt.scene.builtins.list_builtins`), or one mesh (a mesh file,
    ``procedural:NAME:DETAIL``) or model file (``.nrt``) alone, framed and lit
    (`neuralrt.scene.studio`). ``resolution`` (width, height)
    overrides the camera's; ``detail`` overrides a builtin's detail (procedural mesh size).
    ``primary``: who answers camera rays of objects with a model; ``allow_mesh_mismatch``: accept
    a model trained on another mesh than its object's; ``inference``: settings every neural model
    that has them answers with (see `build_scene`). A bad ``resolution``
    or ``path_or_builtin`` raises `ConfigError`, a device this process cannot use `DeviceError`,
    before the scene is read.
    """
    device = check_device(device)
    size = None if resolution is None else check_resolution(resolution)
    if isinstance(path_or_builtin, (str, os.PathLike)) and is_lone_object(os.fspath(path_or_builtin)):
        return _lone_object_scene(os.fspath(path_or_builtin), device, size, detail, primary, allow_mesh_mismatch,
                                  inference)
    spec, base_dir, label = load_scene_spec(path_or_builtin, detail=detail)  # (its own spec, paths absolute)
    if size is not None:
        spec.camera.resolution = size
    return _build(spec, base_dir, device, label, primary, _InMemory({}, {}), allow_mesh_mismatch, inference)


def _lone_object_scene(name: str, device, size, detail, primary: str, allow_mesh_mismatch: bool,
                       inference: dict | None) -> Scene:
    """`neuralrt.scene.studio`: one mesh or model file, framed and lit; the file is read once."""
    from .studio import MODEL_SUFFIX, studio_dict

    if detail is not None:
        raise SceneError(f"{name}: {given('detail')} applies to built-in scenes (builtin:NAME); a procedural mesh "
                         f"names its detail (procedural:NAME:DETAIL)")
    if name.lower().endswith(MODEL_SUFFIX):
        from ..methods import load_model

        value, key = load_model(name, device=device), "model"  # (its errors name the file: one line as they are)
        lo, hi = value.bounds.lo.cpu().numpy(), value.bounds.hi.cpu().numpy()
    else:
        from ..geometry.mesh import check_float32_extent
        from .gltf_import import unread_alpha_note, unused_scene_note

        value, key = load_mesh(name), "mesh"
        check_float32_extent(value, name)  # (said of the mesh, before its framing's light is out of range)
        lo, hi = value.bounds
        for note in (unused_scene_note(name), unread_alpha_note(name)):
            if note:
                warnings.warn(note, stacklevel=outside_stacklevel())
    with mesh_mismatch_unsaid():  # (a model alone has no object mesh to belong to: "cannot check" says nothing here)
        return load_dict(studio_dict(key, value, lo, hi, size), device=device, primary=primary, label=name,
                         allow_mesh_mismatch=allow_mesh_mismatch, inference=inference)


def load_dict(scene: dict, base_dir: str | os.PathLike = ".", device="cpu", primary: str = "exact", label: str = "scene",
              allow_mesh_mismatch: bool = False, inference: dict | None = None) -> Scene:
    """Build a scene from a dict shaped like a scene file (cf. Mitsuba's ``load_dict``).

    Every key is that of a scene file (docs/scenes.md) and is validated at once: a bad value or an
    unknown material is a one-line `SceneError` naming ``label`` and the key, raised here, not at
    render time. In ``objects``, ``mesh`` may also be a `neuralrt.Mesh`, and ``model`` a loaded
    BLAS (``neuralrt.load_model(...)``, a freshly trained model, or your own object with
    ``bounds``, ``intersect``, ``occluded``, ``memory_bytes``, ``secondary_offset`` and
    ``material_names``). The same Python object used by several objects is built once
    (instancing). Relative paths resolve against ``base_dir``::

        scene = load_dict({
            "camera": {"position": [0, 0.5, 3], "resolution": [128, 128]},
            "materials": [{"name": "white", "type": "diffuse", "albedo": [0.7, 0.7, 0.7]}],
            "objects": [{"mesh": bunny_mesh, "model": bunny_model, "material": "white",
                         "transform": {"rotate": [0, 30, 0]}}],
            "environment": {"color": [1, 1, 1]},
        })

    The returned scene's ``spec`` names in-memory objects ``<in-memory ...>``: it cannot be saved.
    A ``base_dir`` that is no path raises `ConfigError`, a device this process cannot use `DeviceError`.
    """
    base_dir, device = check_path("base_dir", base_dir), check_device(device)  # before the scene is read
    if not isinstance(scene, dict):
        raise SceneError(f"{label}: a scene must be a dict, got {type(scene).__name__}")
    data = dict(scene)
    given = _InMemory({}, {})
    objects = data.get("objects")
    if objects is not None and not isinstance(objects, (list, tuple)):  # (a generator would be read as one object)
        raise SceneError(f"{label}: objects: expected a list of objects, got {type(objects).__name__}")
    if isinstance(objects, (list, tuple)):
        data["objects"] = [_take_in_memory(obj, i, given, label) for i, obj in enumerate(objects)]
    spec = validate_spec(data, label)
    _absolute_in_place(spec, Path(base_dir))  # (a fresh spec: no copy needed)
    return _build(spec, base_dir, device, label, primary, given, allow_mesh_mismatch, inference)


def _take_in_memory(obj, i: int, given: _InMemory, label: str):
    """``obj`` with a `Mesh` / BLAS value replaced by a placeholder name (kept in ``given``)."""
    if not isinstance(obj, dict):
        return obj
    obj = dict(obj)
    mesh, model = obj.get("mesh"), obj.get("model")
    if isinstance(mesh, Mesh):
        given.meshes[i] = mesh
        obj["mesh"] = f"{IN_MEMORY}mesh {mesh.name!r}>"
    elif isinstance(mesh, os.PathLike):
        obj["mesh"] = os.fspath(mesh)
    elif mesh is not None and not isinstance(mesh, str):  # (pydantic would print an array's repr over lines)
        raise SceneError(f"{label}: objects.{i}.mesh: expected a mesh file path or a neuralrt.Mesh, got {type(mesh).__name__}")
    if isinstance(model, os.PathLike):
        obj["model"] = os.fspath(model)
    elif model is not None and not isinstance(model, str):
        problem = _blas_problem(model)
        if problem:
            raise SceneError(f"{label}: objects.{i}.model: expected a model file path or a BLAS, got "
                             f"{type(model).__name__} ({problem})")
        given.models[i] = model
        obj["model"] = f"{IN_MEMORY}model {type(model).__name__}>"
    return obj


# What a scene uses of a BLAS object (`neuralrt.accel.blas.BLAS`): checked when it is given, not at render.
BLAS_ATTRIBUTES = ("bounds", "intersect", "occluded", "memory_bytes", "secondary_offset", "material_names")


def _blas_problem(model) -> str | None:
    """Why ``model`` is no BLAS (a missing or mistyped attribute of `BLAS_ATTRIBUTES`), or None.
    Reads attributes only: nothing is traced."""
    missing = [a for a in BLAS_ATTRIBUTES if not hasattr(model, a)]
    if missing:
        hint = "; a Mesh goes in 'mesh'" if isinstance(model, Mesh) else ""
        return f"no {', '.join(missing)}{hint}"
    if not isinstance(model.bounds, AABB):
        return f"bounds must be a neuralrt.AABB, got {type(model.bounds).__name__}"
    uncallable = [a for a in ("intersect", "occluded", "memory_bytes") if not callable(getattr(model, a))]
    if uncallable:
        return f"{', '.join(uncallable)} must be methods"
    offset = model.secondary_offset
    if isinstance(offset, bool) or not isinstance(offset, numbers.Real) or not math.isfinite(offset) or offset < 0:
        shown = offset if isinstance(offset, numbers.Real) else type(offset).__name__
        return f"secondary_offset must be a finite number >= 0, got {shown}"
    if _names_problem(model.material_names):
        return f"material_names {_names_problem(model.material_names)}"
    return None


def _names_problem(names) -> str | None:
    """Why ``names`` is no list of material slot names (`BLAS.material_names`), or None."""
    if isinstance(names, str) or not isinstance(names, (list, tuple)):
        return f"must be a list of str, got {type(names).__name__}"
    if not names or not all(isinstance(n, str) for n in names):
        return "must name each material slot (a non-empty list of str)"
    return None


def load_scene_spec(path_or_builtin: str | os.PathLike, detail: int | None = None) -> tuple[SceneSpec, Path, str]:
    """(validated spec with file paths made absolute, folder paths were relative to, label for errors)."""
    text = str(check_path("path_or_builtin", path_or_builtin))
    if text.startswith(BUILTIN_PREFIX):
        from .builtins import builtin_spec

        spec = builtin_spec(text[len(BUILTIN_PREFIX):], detail=detail)
        return spec, Path.cwd(), text
    path = Path(path_or_builtin)
    label = str(path)  # as the user wrote it, like the file-level errors
    if detail is not None:
        raise SceneError(f"{path}: {given('detail')} applies to built-in scenes (builtin:NAME), not to a scene file")
    if path.name.lower().endswith(".ckpt"):
        raise SceneError(f"{path}: a training checkpoint, not a scene: `neuralrt train ... --resume` continues it; "
                         f"render the finished model (.nrt)")
    if is_lone_object(str(path)):
        raise SceneError(f"{path}: not a scene file (.toml or .json): `neuralrt render` takes a mesh or model file "
                         f"alone; `neuralrt train` makes a model of a mesh")
    problem = input_file_problem(path, "scene file")
    if problem:
        raise SceneError(problem)
    try:
        raw = path.read_bytes().decode("utf-8").removeprefix("\ufeff")  # (a byte-order mark, as some editors write)
    except UnicodeDecodeError as exc:
        line = exc.object[:exc.start].count(b"\n") + 1
        raise SceneError(f"{path}: not UTF-8 text (byte 0x{exc.object[exc.start]:02x} on line {line}): scene files "
                         "are UTF-8") from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read scene file ({exc})") from None
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            data = tomllib.loads(raw)
        elif suffix == ".json":
            data = json.loads(raw, object_pairs_hook=_keys_once)
        else:
            raise SceneError(f"{path}: unknown scene file type {suffix!r} (use .toml or .json)")
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise SceneError(f"{label}: not valid {suffix[1:].upper()}: {exc}") from None
    except RecursionError:
        raise SceneError(f"{label}: not valid {suffix[1:].upper()}: nested too deeply") from None
    except ValueError as exc:  # (an integer of thousands of digits: Python's conversion limit; a key given twice)
        raise SceneError(f"{label}: not valid {suffix[1:].upper()}: {str(exc).split(';')[0]}") from None
    spec, folder = validate_spec(data, label), path.resolve().parent
    _absolute_in_place(spec, folder)  # (a fresh spec: no copy needed)
    return spec, folder, label


def _keys_once(pairs: list) -> dict:
    """A JSON object whose keys are all different (TOML refuses a key given twice; JSON's last would win)."""
    found = {}
    for key, value in pairs:
        if key in found:
            raise ValueError(f"key {key!r} is given twice in one object")
        found[key] = value
    return found


def validate_spec(data, label: str) -> SceneSpec:
    """pydantic validation and cross-references, as one-line `SceneError`s naming ``label`` and the key."""
    if not isinstance(data, dict):
        raise SceneError(f"{label}: a scene must be a table/object at the top level")
    try:
        spec = SceneSpec.model_validate(data)
    except ValidationError as exc:
        errors = validation_errors(exc, SceneSpec)  # keys as written: no pydantic union labels
        key, msg = errors[0]
        more = _more(len(errors) - 1)
        msg = " ".join(msg.split())  # one line, whatever the input's repr (an array spans several)
        raise SceneError(f"{label}: {key or '(top level)'}: {msg}{more}") from None
    problems = spec.reference_errors() + _path_errors(spec)
    if problems:
        key, msg = problems[0]
        more = _more(len(problems) - 1)
        raise SceneError(f"{label}: {key}: {msg}{more}")
    return spec


def _path_errors(spec: SceneSpec) -> list[tuple[str, str]]:
    """(key, problem) for each file path given as "" (resolved, it would name the scene's folder:
    a confusing "is a directory" later) or holding a NUL character (no file system takes one). The
    paths of `SceneSpec.with_paths`, with their keys."""
    paths = [(f"materials.{i}.albedo", m.albedo) for i, m in enumerate(spec.materials) if isinstance(m.albedo, str)]
    for i, obj in enumerate(spec.objects):
        paths += [(f"objects.{i}.mesh", obj.mesh), (f"objects.{i}.model", obj.model)]
    if spec.environment is not None:
        paths.append(("environment.image", spec.environment.image))
    return [(key, "empty path" if not path.strip() else "a path cannot hold a NUL character")
            for key, path in paths if path is not None and (not path.strip() or "\0" in path)]


def absolutize_paths(spec: SceneSpec, base_dir: Path) -> SceneSpec:
    """A copy of ``spec`` (sharing nothing with it) whose relative file paths are resolved against ``base_dir``."""
    return spec.with_paths(_absolute(base_dir))


def _absolute_in_place(spec: SceneSpec, base_dir: Path) -> None:
    spec.map_paths_in_place(_absolute(base_dir))


def _absolute(base_dir: Path):
    return lambda p: str(resolved(base_dir / os.path.expanduser(p)))


# --- building --------------------------------------------------------------------------------------

PRIMARY_CHOICES = ("exact", "neural")


class _Shape:
    """A mesh and its exact BLAS (built on first use), shared by every object that uses them."""

    def __init__(self, mesh: Mesh, device=None):
        self.mesh = mesh
        self._device = device
        self._blas: MeshBLAS | None = None
        self._hash: str | None = None

    @property
    def content_hash(self) -> str:
        """`Mesh.content_hash`, computed once for all the objects that share the mesh."""
        if self._hash is None:
            self._hash = self.mesh.content_hash()
        return self._hash

    @property
    def blas(self) -> MeshBLAS:
        if self._blas is None:
            self._blas = MeshBLAS(self.mesh, device=self._device)
        return self._blas


@dataclass
class _InMemory:
    """Objects of a `load_dict` scene given as Python objects instead of paths, by object index."""

    meshes: dict[int, Mesh]
    models: dict[int, BLAS]


def build_scene(spec: SceneSpec, base_dir: Path | str = ".", device="cpu", label: str = "scene", primary: str = "exact",
                allow_mesh_mismatch: bool = False, inference: dict | None = None) -> Scene:
    """Runtime `Scene` from a validated spec (relative paths resolve against ``base_dir``).

    ``primary`` says who will answer camera rays for objects that have a model: ``"exact"`` keeps
    their mesh's BVH for camera rays (hybrid rendering), ``"neural"`` builds no BVH for them at all.
    An object's model must have been trained on the object's mesh (content hash) unless
    ``allow_mesh_mismatch``; a model-only object warns that nothing checks it
    (`neuralrt.methods.check_mesh_match`).

    ``inference`` (``{"lod": 2}``) changes how the scene's neural models answer: each model whose
    method has a key answers with it, over its object's own ``inference``; a key no model of the
    scene has is an error (`NeuralBLAS.with_inference`).
    """
    base_dir, device = check_path("base_dir", base_dir), check_device(device)
    if not isinstance(spec, SceneSpec):
        raise SceneError(f"{label}: spec: expected a SceneSpec (load_scene_spec(path)[0], or one built in Python), "
                         f"got {type(spec).__name__}")
    # A copy: the scene keeps its spec (and render settings), which the caller may edit or build again.
    return _build(absolutize_paths(spec, Path(base_dir)), base_dir, device, label, primary, _InMemory({}, {}),
                  allow_mesh_mismatch, inference)


def _build(spec: SceneSpec, base_dir: Path | str, device, label: str, primary: str, given: _InMemory,
           allow_mesh_mismatch: bool = False, inference: dict | None = None) -> Scene:
    """The scene of ``spec``, which it keeps: one no one else holds, its paths absolute."""
    if not isinstance(primary, str) or primary not in PRIMARY_CHOICES:  # (an array: "truth value is ambiguous")
        raise SceneError(f"{label}: primary must be 'exact' or 'neural', got {primary!r}")
    dev = device  # (checked by the public callers: `check_device`)
    index = material_index(spec)
    material_specs = scene_materials(spec)
    used_materials: set[int] = set()
    materials = _material_table(material_specs, label, dev)

    try:
        inference = checked_inference(inference)
    except ConfigError as exc:
        raise SceneError(f"{label}: {exc}") from None
    applied: set[str] = set()  # the keys of ``inference`` some model had
    shapes: dict[tuple, _Shape] = {}
    models: dict[str, BLAS] = {}
    by_content: dict[str, BLAS] = {}  # (the same models again: byte-identical copies of one model file)
    instances: list[Instance] = []
    meshes: list[Mesh | None] = []  # exact objects' meshes (area lights come from them)
    for i, obj in enumerate(spec.objects):
        key = f"objects.{i}"
        if i in given.meshes:
            shape = shapes.setdefault(("memory", id(given.meshes[i])), _Shape(given.meshes[i], dev))
        else:
            shape = shape_for(obj, shapes, label, key, device=dev, lit=lit_slots(spec, obj))
        if obj.model is None:
            slots = [m.name for m in shape.mesh.materials]
            blas, camera_blas = shape.blas, None
        else:
            # Area lights are sampled from triangles, and MIS needs the triangle a BSDF ray hit:
            # known from the mesh before a model file is read, and checked again with the model's slots.
            if shape is not None and is_emissive(spec, obj, [m.name for m in shape.mesh.materials]):
                raise SceneError(f"{label}: {key}.model: emissive objects (area lights) must stay exact meshes")
            if i in given.models:
                blas = given.models[i]
            else:
                if obj.model not in models:
                    models[obj.model] = _load_model(obj.model, label, key, dev, by_content)
                blas = models[obj.model]
            check_mesh_match(blas, shape.content_hash if shape is not None else None, allow_mismatch=allow_mesh_mismatch,
                             label=f"{label}: {key}.model")
            changes = {**obj.inference, **_inference_of(blas, inference, applied)}
            if changes:
                blas = _with_inference(blas, changes, label, key)
            slots = _material_names(blas, label, key)
            if is_emissive(spec, obj, slots):
                raise SceneError(f"{label}: {key}.model: emissive objects (area lights) must stay exact meshes")
            camera_view, blas = ray_views(blas)  # e.g. N-BVH: a coarser LoD for all but camera rays
            if shape is not None and primary == "exact":
                camera_blas = shape.blas
            else:
                camera_blas = camera_view if camera_view is not blas else None
        unknown = [slot for slot in obj.materials if slot not in slots]
        if unknown:  # a typo would silently leave the slot at its default
            warnings.warn(f"{label}: {key}.materials: no material slot named {', '.join(map(repr, unknown))} "
                          f"(the object's slots: {', '.join(slots)})", stacklevel=outside_stacklevel())
        slot_materials = material_map(obj, slots, index)
        used_materials.update(slot_materials)
        _warn_untextured(material_specs, obj, slot_materials, shape, label, key, primary)
        instances.append(Instance(blas=blas, transform=obj.transform.to_transform(), material_map=torch.tensor(slot_materials),
                                  name=obj.name or f"object{i}", camera_blas=camera_blas))
        meshes.append(shape.mesh if obj.model is None else None)

    _check_applied(inference, applied, models, given, label)
    unlit = [m.name for k, m in enumerate(material_specs) if isinstance(m, EmissiveMaterialSpec) and k not in used_materials]
    if unlit:  # (a misspelt slot falls back to 'default': the light is gone, silently)
        warnings.warn(f"{label}: emissive material {', '.join(map(repr, unlit))} is used by no object: no light comes "
                      "from it (an object's material, or a mesh slot of its name, makes it a light)",
                      stacklevel=outside_stacklevel())
    accel = SceneAccel(instances, device=dev)
    area = _area_lights(instances, meshes, materials, dev)
    points = None
    if spec.lights:
        points = PointLights([l.position for l in spec.lights], [l.intensity for l in spec.lights], device=dev,
                             scene_bounds=accel.bounds) \
            if any(max(l.intensity) > 0 for l in spec.lights) else None
    env = _environment(spec, label, dev)
    cam = spec.camera
    camera = Camera.look_at(cam.position, cam.look_at, cam.up, cam.fov, cam.resolution)
    return Scene(camera=camera, accel=accel, materials=materials, lights=LightSet(area, points, env),
                 instance_offsets=instance_ray_offsets(accel), settings=spec.render, spec=spec, name=label, device=dev,
                 primary=primary)


def _inference_of(blas, inference: dict, applied: set[str]) -> dict:
    """The settings of the scene-wide ``inference`` that ``blas``'s method has (noted in ``applied``)."""
    if not inference or not is_neural(blas):
        return {}
    keys = [k for k in inference if k in type(blas.config.inference).model_fields]
    applied.update(keys)
    return {k: inference[k] for k in keys}


def _check_applied(inference: dict, applied: set[str], models: dict, given: _InMemory, label: str) -> None:
    """A scene-wide setting no model of the scene has (a typo, or no model of that method) is an error."""
    missing = [k for k in inference if k not in applied]
    if not missing:
        return
    methods = sorted({b.METHOD for b in [*models.values(), *given.models.values()] if is_neural(b)})
    held = (f"no neural model of the scene ({', '.join(methods)}) has this setting" if methods
            else "the scene has no neural model")
    raise SceneError(f"{label}: inference.{missing[0]}: {held} (the keys of each method: python -m neuralrt.configdoc)")


def _with_inference(blas, changes: dict, label: str, key: str):
    """``blas`` answering with the object's ``inference`` settings (`NeuralBLAS.with_inference`)."""
    if not is_neural(blas):
        raise SceneError(f"{label}: {key}.inference: the object's model is no neural model ({type(blas).__name__})")
    try:
        return blas.with_inference(**changes)
    except NeuralRTError as exc:
        raise SceneError(f"{label}: {key}.inference: {exc}") from None


def _warn_untextured(specs: list, obj: ObjectSpec, slot_materials: list[int], shape, label: str, key: str,
                     primary: str) -> None:
    """Warn when a texture ``albedo`` lands where no UVs are: a neural object's hits carry none (nor
    do a mesh without UVs' hits): the texture would show one texel, silently. ``specs``: `scene_materials`."""
    textured = sorted({specs[m].name for m in slot_materials if isinstance(specs[m].albedo, str)})
    if not textured:
        return
    names = ", ".join(map(repr, textured))
    if obj.model is not None:
        kept = shape is not None and primary == "exact" and shape.mesh.uvs is not None  # (who answers camera rays)
        warnings.warn(f"{label}: {key}: material {names} has a texture, but a neural model's hits carry no UVs: "
                      f"they show one texel{' (camera rays answered by the kept mesh show the texture)' if kept else ''}",
                      stacklevel=outside_stacklevel())
    elif shape is not None and shape.mesh.uvs is None:
        warnings.warn(f"{label}: {key}: material {names} has a texture, but the mesh has no UVs: it shows one texel",
                      stacklevel=outside_stacklevel())


def _more(count: int) -> str:
    """" (and N more problems)" after the first problem of several."""
    return "" if count < 1 else f" (and {count} more problem{'s' if count > 1 else ''})"


def _material_names(blas, label: str, key: str) -> list[str]:
    """The model's material slot names (`BLAS.material_names`: what its ``material_id`` indexes)."""
    names = getattr(blas, "material_names", None)
    if _names_problem(names):
        raise SceneError(f"{label}: {key}.model: {type(blas).__name__} has no material_names (the BLAS contract: "
                         "one name per material slot)")
    return list(names)


def shape_for(obj: ObjectSpec, shapes: dict, label: str, key: str, device=None, lit=()) -> _Shape | None:
    """The object's mesh and exact BLAS (on ``device``, built on first use of ``.blas``), loaded once
    per source (cached in ``shapes``); None for a model-only object. Errors name ``label`` and ``key``;
    ``lit``: the slots the object makes lights (`lit_slots`: their emission in the file is used)."""
    if obj.mesh is not None:
        cache_key = ("file", obj.mesh, obj.gltf_mesh)
    elif obj.generator is not None:
        cache_key = ("generator", obj.generator.name, _generator_arguments(obj.generator.name, obj.generator.params))
    else:
        return None
    if cache_key not in shapes:
        if obj.mesh is not None:
            try:
                mesh = load_mesh(obj.mesh, obj.gltf_mesh, lit)
            except NeuralRTError as exc:
                raise SceneError(f"{label}: {key}.mesh: {exc}") from None
        else:
            mesh = _generate(obj, label, key)
        shapes[cache_key] = _Shape(mesh, device)
    return shapes[cache_key]


def _generator_arguments(name: str, params: dict) -> str:
    """A generator's arguments as one key: defaults filled in and whole floats written as ints, so that
    ``{}``, ``{subdivisions = 4}`` and ``{subdivisions = 4.0}`` share one mesh (bad arguments: as given,
    for `_generate` to report)."""
    def plain(value):
        if isinstance(value, float) and value.is_integer():
            return int(value)
        return [plain(v) for v in value] if isinstance(value, (list, tuple)) else value

    try:
        bound = _generator_signature(name).bind(**params)
        bound.apply_defaults()
        params = bound.arguments
    except (KeyError, TypeError):
        pass
    return json.dumps({k: plain(v) for k, v in params.items()}, sort_keys=True, default=str)


@functools.cache
def _generator_signature(name: str) -> inspect.Signature:
    # once per generator: inspect.signature took ~0.1 ms, once per object of a large scene
    from ..geometry import procedural

    return inspect.signature(procedural.GENERATORS[name])


def _generate(obj: ObjectSpec, label: str, key: str) -> Mesh:
    from ..geometry import procedural

    gen = obj.generator
    if gen.name not in procedural.GENERATORS:
        raise SceneError(f"{label}: {key}.generator.name: unknown generator {gen.name!r} (known: {', '.join(sorted(procedural.GENERATORS))})")
    try:
        return procedural.make_procedural(gen.name, **gen.params)
    except (NeuralRTError, TypeError, ValueError) as exc:
        raise SceneError(f"{label}: {key}.generator.params: {exc}") from None


def _load_model(path: str, label: str, key: str, device, by_content: dict[str, BLAS]):
    """A trained neural model as this object's BLAS (the methods package is imported only here).
    A file whose content ``by_content`` already holds (a copy of a model file another object
    names) gives that model: one model in memory, counted once."""
    problem = input_file_problem(path, "model file")
    if problem:
        raise SceneError(f"{label}: {key}.model: {problem}")
    try:
        from ..methods import load_model
    except ImportError as exc:
        raise SceneError(f"{label}: {key}.model: neural models are not available ({exc})") from None
    try:
        content = _content_digest(read_header(path))
        if content not in by_content:
            by_content[content] = load_model(path, device=device)
        return by_content[content]
    except NeuralRTError as exc:
        raise SceneError(f"{label}: {key}.model: {exc}") from None


def _content_digest(header: dict) -> str:
    """What identifies a model file's content: its header, which holds the digest of its arrays
    (loading the file checks both digests against what it reads)."""
    return hashlib.sha256(json.dumps(header, sort_keys=True).encode()).hexdigest()


def _material_table(specs: list, label: str, device) -> MaterialTable:
    from ..io.images import nonfinite_problem, read_image

    kind, albedo, rough, ior, emission, textures = [], [], [], [], [], []
    kinds = {DiffuseMaterialSpec: MaterialKind.DIFFUSE, ConductorMaterialSpec: MaterialKind.CONDUCTOR,
             PlasticMaterialSpec: MaterialKind.PLASTIC, EmissiveMaterialSpec: MaterialKind.EMISSIVE}
    for i, m in enumerate(specs):
        kind.append(int(kinds[type(m)]))
        if isinstance(m.albedo, str):
            try:
                pixels = read_image(m.albedo)
            except NeuralRTError as exc:
                raise SceneError(f"{label}: materials.{i}.albedo: {exc}") from None
            # (as albedo = [-0.8, ...] is refused: a reflectance is >= 0)
            problem = nonfinite_problem(pixels, m.albedo) or _negative_problem(pixels, m.albedo, "texel", "albedo")
            if problem:
                raise SceneError(f"{label}: materials.{i}.albedo: {problem}")
            textures.append(torch.from_numpy(pixels))
            albedo.append((1.0, 1.0, 1.0))
        else:
            textures.append(None)
            albedo.append(m.albedo)
        rough.append(getattr(m, "roughness", 1.0))
        ior.append(getattr(m, "ior", 1.5))
        emission.append(getattr(m, "emission", (0.0, 0.0, 0.0)))
    return MaterialTable(kind, albedo, rough, ior, emission, textures, [m.name for m in specs], device=device)


def _area_lights(instances: list[Instance], meshes: list[Mesh | None], materials: MaterialTable, device) -> AreaLights | None:
    """World-space emissive triangles of every instance (normals by the inverse transpose, like hits)."""
    emissive = materials.emissive_mask.cpu()
    tris, normals, emission, inst_ids, prim_ids = [], [], [], [], []
    for i, (inst, mesh) in enumerate(zip(instances, meshes)):
        if mesh is None:
            continue
        face_material = inst.material_map.cpu()[torch.from_numpy(mesh.face_material_ids).long().clamp(max=inst.material_map.numel() - 1)]
        faces = torch.nonzero(emissive[face_material]).reshape(-1)
        if faces.numel() == 0:
            continue
        obj_tris = torch.from_numpy(mesh.triangles())[faces]
        tris.append(inst.transform.apply_points(obj_tris.reshape(-1, 3)).reshape(-1, 3, 3))
        normals.append(inst.transform.apply_normals(torch.from_numpy(mesh.face_normals())[faces]))
        emission.append(materials.emission.cpu()[face_material[faces]])
        inst_ids.append(torch.full((faces.numel(),), i, dtype=torch.int64))
        prim_ids.append(faces)
    if not tris:
        return None
    counts = [m.num_triangles if m is not None else 0 for m in meshes]
    return AreaLights(torch.cat(tris), torch.cat(normals), torch.cat(emission), torch.cat(inst_ids), torch.cat(prim_ids), counts, device=device)


def _negative_problem(pixels, name: str, unit: str, quantity: str) -> str | None:
    """``"{name}: 3 pixels are negative (radiance must be >= 0)"``, or None where none is."""
    negative = int((pixels < 0).any(axis=-1).sum())
    return f"{name}: {negative} {unit}{'s are' if negative != 1 else ' is'} negative ({quantity} must be >= 0)" if negative else None


def _radiance_image_problem(pixels, name: str, scale: float) -> str | None:
    """Why an image cannot be rendered as radiance (NaN/Inf or negative pixels, or values that overflow
    float32 once scaled), or None."""
    from ..io.images import nonfinite_problem

    problem = nonfinite_problem(pixels, name) or _negative_problem(pixels, name, "pixel", "radiance")
    if problem:
        return problem
    if pixels.size and float(pixels.max()) * scale > MAX_RADIANCE:
        return f"{name}: pixel values times scale reach {float(pixels.max()) * scale:.3g}, above {MAX_RADIANCE:g} (float32 rendering would overflow)"
    return None


def _environment(spec: SceneSpec, label: str, device) -> Environment | None:
    env = spec.environment
    if env is None:
        return None
    if env.color is not None:
        return Environment(color=env.color, scale=env.scale, device=device) if max(env.color) * env.scale > 0 else None
    from ..io.images import read_image

    try:
        pixels = read_image(env.image)
    except NeuralRTError as exc:
        raise SceneError(f"{label}: environment.image: {exc}") from None
    problem = _radiance_image_problem(pixels, env.image, env.scale)
    if problem:
        raise SceneError(f"{label}: environment.image: {problem}")
    image = torch.from_numpy(pixels)
    return Environment(image=image, scale=env.scale, device=device, rotate_y=env.rotate_y)
