"""Scene conversion: train one model (any registered method) per unique selected mesh and write a scene that uses them.

The paper's pipeline (LSNIF, Sec. 4 and 6.3): complex objects are replaced by per-object models
trained offline in object space, so instances share one model and the converted scene can be
moved, re-lit and re-materialised without retraining. Models are cached in a models folder by
(mesh hash, config hash): converting again reuses every model whose mesh and config are unchanged.

``group=True`` is the paper's granularity option: all selected objects are merged (in world space)
into one mesh and one model; the merged mesh is written beside the models so camera rays can still
be answered exactly. It keeps each mesh slot's colour and texture (the model learns them as it
would per object; textures and normal maps are written as PNGs beside the merged OBJ) and vertex
colours (``v x y z r g b``, 8-bit sRGB as OBJ readers take them; white on objects without).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..arguments import given
from ..errors import ConfigError, ModelFileError, SceneError
from ..geometry.mesh import Mesh, MeshMaterial, check_float32_extent
from ..io.files import check_output_file, check_output_files, check_output_folder, folders_removed_if_left_empty, write_atomically
from ..io.model_file import read_model_file, read_model_header
from ..io.run_lock import held_alone, wait_while_held
from ..methods import DEFAULT_METHOD, MethodConfig, config_from_dict, get_method, is_neural
from ..methods.base import memory_owner
from .convert_executors import Executor, TrainingJob, make_executor
from .loader import load_scene_spec, shape_for
from .material_rules import is_emissive, lit_slots, material_index, scene_material_for
from .schema import ObjectSpec, SceneSpec, TransformSpec
from .scene import save_scene

__all__ = ["ConvertedModel", "ConversionReport", "convert_scene", "model_file_stem", "cached_model_is_valid", "cached_model_stem", "inference_changes",
           "selected_objects", "neural_bytes", "replaced_memory", "DEFAULT_MIN_TRIANGLES"]

# Objects smaller than this stay triangles unless selected by name: a model costs ~1.5 MB, a
# 10k-triangle mesh with its BVH about as much, so smaller meshes gain nothing.
DEFAULT_MIN_TRIANGLES = 10_000


@dataclass
class ConvertedModel:
    """One trained (or reused) model and the objects that use it."""

    mesh_name: str
    triangles: int
    model_path: str
    objects: list[str]
    reused: bool
    train_seconds: float
    trained_on: str = ""  # "local" or the Ray node's address; "" when reused


@dataclass
class ConversionReport:
    scene_path: str
    models: list[ConvertedModel] = field(default_factory=list)
    neural_objects: int = 0
    seconds: float = 0.0  # the whole conversion, wall clock (scene loading and every model)

    @property
    def unique_models(self) -> int:
        return len(self.models)

    @property
    def train_seconds(self) -> float:
        """The models' training times summed (Ray's run side by side: more than the wall time)."""
        return float(sum(m.train_seconds for m in self.models))

    def as_dict(self) -> dict:
        return {
            "scene": self.scene_path,
            "neural_objects": self.neural_objects,
            "unique_models": self.unique_models,
            "trained_models": sum(not m.reused for m in self.models),
            "reused_models": sum(m.reused for m in self.models),
            "seconds": self.seconds,
            "train_seconds": self.train_seconds,
            "models": [m.__dict__ for m in self.models],
        }


def _config_hash(config: MethodConfig) -> str:
    return hashlib.sha256(json.dumps(config.model_defining(), sort_keys=True).encode()).hexdigest()


def _parameters_defining(config: MethodConfig) -> dict:
    """What makes a model's trained parameters: `MethodConfig.model_defining` but the inference
    settings a model may answer with other values of (`NeuralBLAS.with_inference`; all but the
    inference section's `STORED_KEYS`)."""
    data = config.model_defining()
    stored = type(config.inference).STORED_KEYS
    data["inference"] = {k: v for k, v in data["inference"].items() if k in stored}
    return data


def cached_model_is_valid(path: Path, mesh_hash: str, config: MethodConfig, *, answering_alike: bool = True) -> bool:
    """The file exists, is a readable model of this config's method, of this mesh, with this config
    (`MethodConfig.model_defining`: the checkpoint interval aside; ``answering_alike=False``: up to
    the inference settings a scene object changes, `_parameters_defining`)."""
    if not path.is_file():
        return False
    try:
        header = read_model_header(path, method=config.method)
        stored = config_from_dict(header.config)
        same = (stored.model_defining() == config.model_defining() if answering_alike
                else _parameters_defining(stored) == _parameters_defining(config))
        if header.mesh_sha256 != mesh_hash or not same:
            return False
        read_model_file(path, method=config.method)  # the arrays' checksum too: a corrupted file is retrained, not reused
    except (ModelFileError, ConfigError):
        return False
    return True


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "mesh"


def model_file_stem(mesh_name: str, mesh_hash: str, config: MethodConfig) -> str:
    """The models folder's cache name of (mesh, config), without suffix: ``name-meshhash-confighash``."""
    return f"{_safe_name(mesh_name)}-{mesh_hash[:10]}-{_config_hash(config)[:8]}"


def cached_model_stem(models_dir: Path, mesh_name: str, mesh_hash: str, config: MethodConfig) -> str | None:
    """The stem of a valid cached model of (mesh, config) in ``models_dir``: the one named after
    ``mesh_name``, else one written for the same mesh under another name (a copied file, another
    scene's object); None when there is none."""
    stem = model_file_stem(mesh_name, mesh_hash, config)
    if cached_model_is_valid(models_dir / f"{stem}.nrt", mesh_hash, config):
        return stem
    if (models_dir / f"{stem}.nrt").is_file():  # (its name says it is this model: a reader would expect it reused)
        import warnings

        warnings.warn(f"{models_dir / f'{stem}.nrt'}: cannot be read as this mesh's model (corrupted, or written by "
                      "another version): it is trained again and replaced", stacklevel=2)
    suffix = f"-{mesh_hash[:10]}-{_config_hash(config)[:8]}.nrt"
    for path in sorted(models_dir.glob(f"*{suffix}")):
        if cached_model_is_valid(path, mesh_hash, config):
            return path.stem
    # One trained with other inference settings: its objects say the asked ones (`inference_changes`).
    for path in sorted(models_dir.glob(f"*-{mesh_hash[:10]}-*.nrt")):
        if cached_model_is_valid(path, mesh_hash, config, answering_alike=False):
            return path.stem
    return None


def inference_changes(model_path: Path, config: MethodConfig) -> dict:
    """The inference settings ``config`` asks that the model file's config holds otherwise (a scene
    object's ``inference``, `ObjectSpec.inference`): {} for a model trained with them."""
    stored = config_from_dict(read_model_header(model_path, method=config.method).config).inference.model_dump(mode="json")
    asked = config.inference.model_dump(mode="json")
    return {k: v for k, v in asked.items() if stored.get(k) != v}


def _object_names(spec: SceneSpec) -> list[str]:
    """Each object's name as the loader names its instance."""
    return [obj.name or f"object{i}" for i, obj in enumerate(spec.objects)]


def selected_objects(spec: SceneSpec, meshes: list[Mesh | None], select: list[str] | None, min_triangles: int | None) -> list[int]:
    """Indices of the objects to convert; errors name unknown or unconvertible selections."""
    names = _object_names(spec)
    if select:
        unknown = sorted(set(select) - set(names))
        if unknown:
            raise SceneError(f"{given('select')}: no object named {', '.join(map(repr, unknown))} (objects: {', '.join(names)})")
    chosen = []
    threshold = DEFAULT_MIN_TRIANGLES if min_triangles is None else min_triangles
    for i, (obj, mesh) in enumerate(zip(spec.objects, meshes)):
        if mesh is None or obj.model is not None:
            if select and names[i] in select and obj.model is not None:
                raise SceneError(f"{given('select')}: object {names[i]!r} already has a model ({obj.model})")
            continue  # already neural
        if is_emissive(spec, obj, [m.name for m in mesh.materials]):
            if select and names[i] in select:
                raise SceneError(f"{given('select')}: object {names[i]!r} is an area light; lights stay triangles")
            continue
        if select:
            if names[i] in select:
                chosen.append(i)
        elif mesh.num_triangles >= threshold:
            chosen.append(i)
    return chosen


def _merged_world_mesh(spec: SceneSpec, objects: list[int], meshes: list[Mesh]) -> tuple[Mesh, dict[str, str]]:
    """Selected objects baked into one world-space mesh, and the slot -> scene material map its
    object needs. A slot per (scene material, slot colour, texture, normal map): the first of a
    scene material is named after it, others ``NAME~2``, ... (mapped back to NAME), so meshes keep
    their own colours, textures and normal maps (a textured slot's colour is multiplied into its
    texture: an OBJ's ``map_Kd`` replaces ``Kd``). A normal map stays valid in world space: its
    tangent frame follows the transformed positions and UVs."""

    index = material_index(spec)
    slot_of: dict[tuple, int] = {}  # (scene material, colour bytes, texture's id) -> merged slot
    materials: list[MeshMaterial] = []
    mapping: dict[str, str] = {}
    verts, faces, normals, uvs, colours, mat_ids = [], [], [], [], [], []
    any_uv = any(meshes[i].uvs is not None for i in objects)
    any_colour = any(meshes[i].vertex_colors is not None for i in objects)
    offset = 0
    for i in objects:
        obj, mesh = spec.objects[i], meshes[i]
        xf = obj.transform.to_transform()
        verts.append(xf.apply_points(torch.from_numpy(mesh.vertices)).numpy())
        normals.append(xf.apply_normals(torch.from_numpy(mesh.vertex_normals)).numpy())
        faces.append(mesh.faces + offset)
        if any_uv:
            uvs.append(mesh.uvs if mesh.uvs is not None else np.zeros((len(mesh.vertices), 2), np.float32))
        if any_colour:  # (colours multiply the slot's colour: white leaves an uncoloured object as it was)
            colours.append(mesh.vertex_colors if mesh.vertex_colors is not None else np.ones((len(mesh.vertices), 3), np.float32))
        slot_to_merged = []
        for slot in mesh.materials:
            target = scene_material_for(obj, slot.name, index)
            colour = np.asarray(slot.base_color, np.float32).reshape(-1)[:3]
            textured = slot.texture is not None and mesh.uvs is not None
            normal_map = slot.normal_map if mesh.uvs is not None else None
            key = (target, colour.tobytes(), id(slot.texture) if textured else None, id(normal_map))
            if key not in slot_of:
                taken = sum(1 for t, *_ in slot_of if t == target)
                name = target if taken == 0 else f"{target}~{taken + 1}"
                if taken:
                    mapping[name] = target
                slot_of[key] = len(materials)
                materials.append(MeshMaterial(name, base_color=np.ones(3, np.float32), texture=slot.texture * colour,
                                              normal_map=normal_map)
                                 if textured else MeshMaterial(name, base_color=colour, normal_map=normal_map))
            slot_to_merged.append(slot_of[key])
        mat_ids.append(np.asarray(slot_to_merged, np.int32)[mesh.face_material_ids])
        offset += len(mesh.vertices)
    merged = Mesh(np.concatenate(verts), np.concatenate(faces), vertex_normals=np.concatenate(normals),
                  uvs=np.concatenate(uvs) if any_uv else None, face_material_ids=np.concatenate(mat_ids),
                  vertex_colors=np.concatenate(colours) if any_colour else None, materials=materials, name="group")
    return merged, mapping


def _obj_round_trip(mesh: Mesh, folder: Path) -> Mesh:
    """``mesh`` written as OBJ and read back."""
    from ..geometry.mesh import load_mesh

    import shutil
    import tempfile

    # A folder of its own: two conversions into one models folder must not read each other's files.
    private = Path(tempfile.mkdtemp(prefix=".round-trip-", dir=folder))
    try:
        path = private / f"{_safe_name(mesh.name)}-round-trip.obj"
        write_mesh_obj(mesh, path)
        again = load_mesh(path)
    finally:
        shutil.rmtree(private, ignore_errors=True)
    again.name = mesh.name
    return again


def write_mesh_obj(mesh: Mesh, path: Path) -> None:
    """Write positions (with vertex colours, sRGB, after them: ``v x y z r g b``), normals, UVs and
    per-face material groups as OBJ (+ MTL: each slot's colour
    as ``Kd``, sRGB as OBJ readers and `load_mesh` take it; a textured slot's texture as an 8-bit
    sRGB PNG beside it, ``map_Kd``; a normal map as an 8-bit PNG of its stored values, ``norm``),
    each file atomically (`neuralrt.io.files.write_atomically`)."""
    from ..io.images import linear_to_srgb, write_data_png, write_png

    path = Path(path)
    mtl = path.with_suffix(".mtl")
    lines = [f"mtllib {mtl.name}"]
    if mesh.vertex_colors is None:
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in mesh.vertices]
    else:
        srgb = linear_to_srgb(np.clip(mesh.vertex_colors, 0.0, 1.0))
        lines += [f"v {x:.9g} {y:.9g} {z:.9g} {r:.6g} {g:.6g} {b:.6g}" for (x, y, z), (r, g, b) in zip(mesh.vertices, srgb)]
    lines += [f"vn {x:.6g} {y:.6g} {z:.6g}" for x, y, z in mesh.vertex_normals]
    corner = "{0}//{0}"
    if mesh.uvs is not None:
        lines += [f"vt {u:.9g} {v:.9g}" for u, v in mesh.uvs]
        corner = "{0}/{0}/{0}"
    for k, material in enumerate(mesh.materials):
        sel = mesh.faces[mesh.face_material_ids == k] + 1
        if len(sel) == 0:
            continue
        lines.append(f"usemtl {material.name}")
        lines += [" ".join(["f", *(corner.format(i) for i in face)]) for face in sel.tolist()]
    mtl_text = ""
    for k, m in enumerate(mesh.materials):
        r, g, b = linear_to_srgb(np.clip(np.asarray(m.base_color, np.float32).reshape(-1)[:3], 0, 1))
        mtl_text += f"newmtl {m.name}\nKd {r:.6g} {g:.6g} {b:.6g}\n"
        if m.texture is not None and mesh.uvs is not None:
            texture = path.with_name(f"{path.stem}-texture{k}.png")
            write_png(texture, m.texture)
            mtl_text += f"map_Kd {texture.name}\n"
        if m.normal_map is not None and mesh.uvs is not None:
            normal_map = path.with_name(f"{path.stem}-normal{k}.png")
            write_data_png(normal_map, m.normal_map)
            mtl_text += f"norm {normal_map.name}\n"
        mtl_text += "\n"
    write_atomically(mtl, lambda tmp: Path(tmp).write_text(mtl_text))
    write_atomically(path, lambda tmp: Path(tmp).write_text("\n".join(lines) + "\n"))


def convert_scene(
    scene: str | os.PathLike,
    output: str | os.PathLike,
    *,
    models_dir: str | os.PathLike | None = None,
    select: list[str] | None = None,
    min_triangles: int | None = None,
    method: str | None = None,
    preset: str | None = None,
    group: bool = False,
    steps: int | None = None,
    batch: int | None = None,
    seed: int | None = None,
    detail: int | None = None,
    device: str = "cpu",
    progress: bool = True,
    executor: str = "local",
    address: str | None = None,
    cpus_per_model: float | None = None,
    gpus_per_model: float | None = None,
    threads_per_model: int | None = None,
    max_retries: int | None = None,
    settings: dict | None = None,
) -> ConversionReport:
    """Convert ``scene`` (file or ``builtin:NAME``) into ``output`` (a .toml/.json scene file).

    Objects are selected by name (``select``) or by size (``min_triangles``, default
    `DEFAULT_MIN_TRIANGLES`); area lights always stay triangles. One model is trained per unique
    mesh (instances share it), or one for all selected objects with ``group=True``, with
    ``method`` (default: lsnif) and its ``preset`` (default: the method's default for ``device``).
    Models go to ``models_dir`` (default: ``<output folder>/models``) and are reused when their
    mesh hash and config match. ``settings`` changes config keys of the preset
    (``{"voxel": {"resolution": 64}}``; the CLI's ``--set voxel.resolution=64``).

    ``executor`` trains the missing models: ``"local"`` one after another in this process,
    ``"ray"`` one Ray task each on a local Ray instance or the cluster at ``address``, with
    ``cpus_per_model`` / ``gpus_per_model`` / ``threads_per_model`` / ``max_retries`` (see
    `neuralrt.scene.convert_executors`). Either way each finished model is written at once, an
    interrupted training resumes from its checkpoint on the next run, and the scene file is
    written only when every model exists.
    """
    output = Path(output)
    if output.suffix.lower() not in (".toml", ".json"):
        raise SceneError(f"{output}: converted scene must end in .toml or .json")
    check_output_file(output, "converted scene")
    models_dir = Path(models_dir) if models_dir is not None else output.parent / "models"
    check_output_folder(models_dir, "models")
    placed, models_at = Path(os.path.abspath(output)), Path(os.path.abspath(models_dir))
    if models_at == placed or placed in models_at.parents:  # (found after training, when the scene is written)
        raise SceneError(f"{models_dir}: the models folder would be at or under the converted scene's path {output}")
    if isinstance(scene, (str, os.PathLike)) and output.is_file() and Path(scene).is_file() and os.path.samefile(scene, output):
        raise SceneError(f"{output}: the converted scene would replace the scene it converts: give another output")
    spec_of_method = get_method(method or DEFAULT_METHOD)
    preset = preset or spec_of_method.default_preset(device)
    config = spec_of_method.config(preset, device=device, settings=settings, steps=steps, batch_size=batch, seed=seed)
    # Checked before the scene loads: Ray installed, the options valid (a given cluster is reached
    # once a model needs training: a rerun with every model present needs none).
    runner = make_executor(executor, device=device, progress=progress, threads_per_model=threads_per_model,
                           address=address, cpus_per_model=cpus_per_model, gpus_per_model=gpus_per_model,
                           max_retries=max_retries)
    start = time.perf_counter()
    with runner, folders_removed_if_left_empty(output.parent, models_dir):  # (Ray may fail once they exist)
        report = _convert(scene, output, runner, models_dir=models_dir, select=select, min_triangles=min_triangles,
                          config=config, preset=preset, group=group, detail=detail, progress=progress)
    report.seconds = time.perf_counter() - start
    return report


def _convert(scene, output: Path, runner: Executor, *, models_dir: Path, select, min_triangles, config: MethodConfig,
             preset: str, group: bool, detail, progress: bool) -> ConversionReport:
    spec, _, label = load_scene_spec(scene, detail=detail)
    shapes: dict = {}  # instances of one mesh share one load
    meshes = [getattr(shape_for(obj, shapes, label, f"objects.{i}", lit=lit_slots(spec, obj)), "mesh", None)
              for i, obj in enumerate(spec.objects)]
    chosen = selected_objects(spec, meshes, select, min_triangles)
    if not chosen:
        raise SceneError(f"{label}: no object to convert (none selected, or none with >= "
                         f"{DEFAULT_MIN_TRIANGLES if min_triangles is None else min_triangles} triangles)")
    checked: set[int] = set()
    for i in chosen:  # what training would refuse, said before any model trains (on Ray: before the others finish)
        if id(meshes[i]) not in checked:
            checked.add(id(meshes[i]))
            check_float32_extent(meshes[i], f"{label}: objects.{i}.mesh ({meshes[i].name})")
    # Folders are made only once the input is known to be good (a failed convert leaves none behind).
    output.parent.mkdir(parents=True, exist_ok=True)
    # One conversion per output: a second one stops here, before any model. (Before, only each
    # model's checkpoint was held, one at a time; in a trial, two converts started together both stopped.)
    with held_alone(output, "converting into this scene file"):
        models_dir.mkdir(parents=True, exist_ok=True)
        return _converted(spec, meshes, chosen, output, runner, models_dir=models_dir, config=config,
                          preset=preset, group=group, progress=progress)


def _converted(spec: SceneSpec, meshes: list, chosen: list[int], output: Path, runner: Executor, *,
               models_dir: Path, config: MethodConfig, preset: str, group: bool, progress: bool) -> ConversionReport:
    """`_convert`'s work once its input is checked and its output held: train what is missing, write the scene."""
    names = _object_names(spec)
    out_spec = spec.model_copy(deep=True)
    report = ConversionReport(scene_path=str(output))

    # Work items: mesh hash -> (mesh to train, objects that use it). Instances share one Mesh
    # object (the loader's cache), so each distinct object is hashed once.
    jobs: dict[str, tuple[Mesh, list[int]]] = {}
    if group:
        # Train on the merged mesh as the converted scene will read it back from its OBJ (the
        # round trip rounds normals), so the model's mesh hash matches what the loader checks.
        # The scene's OBJ is written from the same merged mesh, so it reads back as this one (a
        # second round trip would not: trimesh lists an OBJ's materials in reverse order).
        group_source, group_slots = _merged_world_mesh(spec, chosen, meshes)
        merged = _obj_round_trip(group_source, models_dir)
        jobs[merged.content_hash()] = (merged, chosen)
    else:
        hashes: dict[int, str] = {}
        for i in chosen:
            if id(meshes[i]) not in hashes:
                hashes[id(meshes[i])] = meshes[i].content_hash()
            jobs.setdefault(hashes[id(meshes[i])], (meshes[i], []))[1].append(i)

    stems = {h: model_file_stem(mesh.name, h, config) for h, (mesh, _) in jobs.items()}
    method = get_method(config.method)
    to_train: list[TrainingJob] = []
    for k, (mesh_hash, (mesh, users)) in enumerate(jobs.items()):
        cached = cached_model_stem(models_dir, mesh.name, mesh_hash, config)
        if cached is not None:
            (models_dir / f"{stems[mesh_hash]}.ckpt").unlink(missing_ok=True)  # left if a run stopped between the two
            stems[mesh_hash] = stem = cached
            if progress:
                print(f"reusing {stem}.nrt for {mesh.name!r}", file=sys.stderr, flush=True)  # (stdout is the result: --json)
            continue
        stem = stems[mesh_hash]
        # Absolute: a Ray worker runs in its own folder, where a relative path would put (and look for) another file.
        to_train.append(TrainingJob(stem, mesh, config, method, models_dir.absolute() / f"{stem}.ckpt",
                                    f"{config.method} {preset} model of {mesh.name!r} ({mesh.num_triangles:,} triangles, "
                                    f"{len(users)} object(s))"))
    to_train = [job for job in to_train if not _trained_meanwhile(job, models_dir, jobs, stems, config, progress)]
    # (a folder or unwritable file where a model goes: said now, not after its training)
    check_output_files([models_dir / f"{job.key}.nrt" for job in to_train], "model file")
    check_output_files([job.checkpoint for job in to_train], "training checkpoint")
    trained = {}
    def trained_meanwhile(job: TrainingJob) -> bool:  # (asked again as each local job starts: a conversion
        return _trained_meanwhile(job, models_dir, jobs, stems, config, progress)  # started beside this one may be training it)

    for result in runner.run(to_train, skip=trained_meanwhile):  # each model is written as soon as it exists
        result.save(models_dir / f"{result.key}.nrt")
        (models_dir / f"{result.key}.ckpt").unlink(missing_ok=True)
        trained[result.key] = result

    for mesh_hash, (mesh, users) in jobs.items():
        stem = stems[mesh_hash]
        model_path = models_dir / f"{stem}.nrt"
        done = trained.get(stem)
        report.models.append(ConvertedModel(mesh.name, mesh.num_triangles, str(model_path), [names[i] for i in users],
                                            done is None, done.seconds if done else 0.0, done.where if done else ""))
        changes = inference_changes(model_path, config)  # (a model reused from a run with other inference settings)
        if group:
            mesh_path = models_dir / f"{stem}.obj"
            write_mesh_obj(group_source, mesh_path)
            grouped = ObjectSpec(name="group:" + "+".join(names[i] for i in users), mesh=str(mesh_path.resolve()),
                                 model=str(model_path.resolve()), transform=TransformSpec(), materials=group_slots,
                                 inference=changes)
            out_spec.objects = [o for i, o in enumerate(out_spec.objects) if i not in set(users)] + [grouped]
        else:
            for i in users:
                out_spec.objects[i].model = str(model_path.resolve())
                out_spec.objects[i].inference = changes
    report.neural_objects = len(chosen)
    save_scene(out_spec, output)
    return report


SAVED_WITHIN_SECONDS = 30.0  # how long a waiting conversion looks for the model another one trained


def _trained_meanwhile(job: TrainingJob, models_dir: Path, jobs: dict, stems: dict, config: MethodConfig,
                       progress: bool) -> bool:
    """Whether another process was training ``job``'s model (a conversion of another scene into the
    same models folder): then this one waits for it to end and reuses the model it wrote."""
    def say(pid: str) -> None:
        if progress:
            print(f"waiting for {f'pid {pid}' if pid else 'another process'}, which is training {job.key}.nrt",
                  file=sys.stderr, flush=True)

    if not wait_while_held(job.checkpoint, say):
        return False
    mesh_hash = next(h for h, stem in stems.items() if stem == job.key)
    deadline = time.monotonic() + SAVED_WITHIN_SECONDS  # (a Ray driver saves the model after its worker's lock ends)
    while (cached := cached_model_stem(models_dir, jobs[mesh_hash][0].name, mesh_hash, config)) is None \
            and Path(job.checkpoint).exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    if cached is None:
        return False  # (it stopped short: this run resumes its checkpoint)
    stems[mesh_hash] = cached
    if progress:
        print(f"reusing {cached}.nrt for {jobs[mesh_hash][0].name!r}", file=sys.stderr, flush=True)
    return True


def neural_bytes(scene) -> int:
    """Run-time bytes of a scene's neural models, each counted once (instancing), model-only objects included."""
    models = {id(memory_owner(i.blas)): memory_owner(i.blas) for i in scene.accel.instances if is_neural(i.blas)}
    return int(sum(m.memory_bytes().total for m in models.values()))


def replaced_memory(scene) -> dict:
    """Memory of a converted scene's neural objects: their models (each once) and the BVH A / B
    that their meshes (kept for camera rays, each once) would need instead."""
    from ..accel.classical_memory import classical_memory

    meshes = {id(i.camera_blas): i.camera_blas.mesh for i in scene.accel.instances if i.camera_blas is not None and not is_neural(i.camera_blas)}
    classical = [classical_memory(mesh) for mesh in meshes.values()]
    return {
        "neural_bytes": neural_bytes(scene),
        "bvh_a_bytes": int(sum(c.bvh_a_bytes for c in classical)),
        "bvh_b_bytes": int(sum(c.bvh_b_bytes for c in classical)),
        "neural_triangles": int(sum(c.triangles for c in classical)),
    }
