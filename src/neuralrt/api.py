"""The Python API behind each CLI command: ``neuralrt X`` calls ``neuralrt.api.X`` with the same
arguments, so scripts and the command line do the same thing."""

from __future__ import annotations

import os
from pathlib import Path

from .arguments import check_count, check_flags, check_name, check_seed, given, seed_or_default
from .devices import check_device, check_device_name, check_path
from .errors import ConfigError, ModelFileError, NeuralRTError, TrainingError, outside_stacklevel
from .io.files import (check_output_file, check_output_files, check_output_folder, folders_removed_if_left_empty,
                       written_together)
from .io.model_file import MODEL_SUFFIX, check_model_path
from .io.run_lock import held_alone

__all__ = ["compare", "convert", "demo", "evaluate", "import_scene", "info", "list_builtins", "list_presets", "render",
           "train"]

MODEL_SUFFIXES = {MODEL_SUFFIX}
MAX_EVAL_RAYS = 1 << 22  # ~0.44 KB per held-out ray measured (bunny, 2^18 vs 2^20 rays): 2^22 take ~1.9 GB
CHECKPOINT_SUFFIX = ".ckpt"  # training writes MODEL.nrt.ckpt beside MODEL.nrt
SCENE_SUFFIXES = {".toml", ".json"}


def compare(reference: str | Path, test: str | Path, heatmap: str | Path | None = None, hdr: bool = False) -> dict:
    """FLIP, PSNR and relMSE of ``test`` against ``reference``; writes the FLIP heat map PNG if asked."""
    from .eval.image_metrics import compare_files

    check_flags(hdr=hdr)
    reference, test = check_path("reference", reference), check_path("test", test)
    heatmap = check_path("heatmap", heatmap, optional=True)
    for name, image in (("reference", reference), ("test", test)):
        if heatmap is not None and heatmap.is_file() and image.is_file() and os.path.samefile(heatmap, image):
            raise NeuralRTError(f"{heatmap}: the heat map would replace the {name} image: give another {given('heatmap')}")
    result = compare_files(reference, test, heatmap=heatmap, hdr=hdr)
    out = result.as_dict()
    if heatmap is not None:
        out["heatmap"] = str(heatmap)
    return out


def info(path, plot: str | Path | None = None) -> dict:
    """Facts about a mesh (a file or a `Mesh`), scene (file or ``builtin:NAME``) or model file; for a
    model or training checkpoint, ``plot`` (.png, .pdf or .svg) draws its training curve (loss, its
    terms, hit accuracy)."""
    from .geometry.mesh import Mesh
    from .io.plots import check_plot_path

    if isinstance(path, Mesh):  # (as train and evaluate take one)
        if plot is not None:
            raise NeuralRTError("a mesh has no training curve to plot: plot takes a model or checkpoint file")
        return _mesh_info(path)
    spec = str(check_path("path", path))
    suffix = Path(spec).suffix.lower()
    is_model = suffix in MODEL_SUFFIXES or suffix == CHECKPOINT_SUFFIX
    if plot is not None:
        plot = check_plot_path(check_path(given("plot"), plot))
        if not is_model:
            raise NeuralRTError(f"{spec}: only a model (.nrt) or training checkpoint (.ckpt) has a training curve to plot")
    if is_model:
        return _model_info(Path(spec), plot)
    if spec.startswith("builtin:") or suffix in SCENE_SUFFIXES:
        return _scene_info(spec)
    return _mesh_info(Path(spec))


def _mesh_info(path) -> dict:
    from .accel.classical_memory import classical_memory
    from .geometry.mesh import Mesh, load_mesh

    mesh = path if isinstance(path, Mesh) else load_mesh(path)
    lo, hi = mesh.bounds
    mem = classical_memory(mesh)
    return {
        "kind": "mesh",
        "path": str(path) if not isinstance(path, Mesh) else None,
        "name": mesh.name,
        "triangles": mesh.num_triangles,
        "vertices": int(len(mesh.vertices)),
        "bounds": [lo.tolist(), hi.tolist()],
        "materials": [m.name for m in mesh.materials],
        "uvs": mesh.uvs is not None,
        "vertex_colors": mesh.vertex_colors is not None,
        "textured_materials": [m.name for m in mesh.materials if m.texture is not None],
        "normal_mapped_materials": [m.name for m in mesh.materials if m.normal_map is not None],
        **mem.as_dict(),
    }


def _scene_info(spec: str) -> dict:
    from .methods.base import is_neural, mesh_mismatch_unsaid
    from .scene.loader import load_scene
    from .scene.memory import scene_memory

    with mesh_mismatch_unsaid():  # info inspects: a mismatch matters when rendering (which says so)
        scene = load_scene(spec, allow_mesh_mismatch=True)
    accel = scene.accel
    blases = accel.unique_blases
    # Triangles traced for every ray (exact objects), apart from the meshes neural objects keep for
    # camera rays only (hybrid scenes): counted in both figures before, only in the unique one.
    exact = {id(i.blas): i.blas for i in accel.instances if not is_neural(i.blas)}
    camera = {id(i.camera_blas): i.camera_blas for i in accel.instances
              if i.camera_blas is not None and not is_neural(i.camera_blas) and id(i.camera_blas) not in exact}
    triangles = sum(b.mesh.num_triangles for b in exact.values())
    instanced = sum(i.blas.mesh.num_triangles for i in accel.instances if not is_neural(i.blas))
    memory = accel.memory_bytes()
    return {
        "kind": "scene",
        "scene": spec,
        "instances": len(accel.instances),
        "unique_blas": len(blases),
        "neural_instances": sum(is_neural(inst.blas) for inst in accel.instances),
        "triangles_unique": triangles,
        "triangles_instanced": instanced,
        "triangles_camera_only": sum(b.mesh.num_triangles for b in camera.values()),
        "materials": len(scene.materials),
        "lights": scene.lights.kinds,
        "resolution": [scene.camera.width, scene.camera.height],
        "bounds": accel.bounds.tolist(),
        "memory_bytes": memory.total,
        "memory_parts": {k: int(v) for k, v in memory.parts.items()},
        # by role: exact objects, neural models, meshes kept for camera rays, what the models replaced
        "memory_by_role": scene_memory(scene).as_dict(),
    }


def _model_info(path: Path, plot: Path | None = None) -> dict:
    from .io.model_file import FORMAT_VERSION, read_header, read_model_header
    from .methods import get_method, load_model
    from .training.trainer import CHECKPOINT_METHOD

    raw = read_header(path)
    if raw.get("method") == CHECKPOINT_METHOD:
        return _plotted(_checkpoint_info(path, raw), plot)
    if path.suffix.lower() == CHECKPOINT_SUFFIX:
        raise NeuralRTError(f"{path}: a {CHECKPOINT_SUFFIX} file that holds no training checkpoint (method {raw.get('method')!r})")
    header = read_model_header(path)
    model = load_model(path)
    report = model.memory_bytes()
    spec = get_method(header.method)
    preset = spec.preset_of(model.config)
    nearest = {} if preset is not None else dict(zip(("nearest_preset", "changed_from_preset"), spec.nearest_preset(model.config)))
    return _plotted({
        "kind": "model",
        "path": str(path),
        "method": header.method,
        "preset": preset,  # (None: keys set past a preset's; then the nearest one and the keys set)
        **nearest,
        "format_version": raw["format_version"],  # (the header read above: read_model_header checks it)
        "reader_format_version": FORMAT_VERSION,
        "memory_bytes": report.total,
        "memory_parts": {k: int(v) for k, v in report.parts.items()},
        # (the parameters as a loaded model holds them, float32 whatever the storage, and its
        # buffers: memory_bytes counts them at the storage precision, the papers' convention)
        "held_bytes": sum(t.numel() * t.element_size() for t in (*model.parameters(), *model.buffers())),
        "bounds": [list(header.bounds[0]), list(header.bounds[1])],
        "materials": model.material_names,
        "mesh_name": header.mesh_name,
        "mesh_sha256": header.mesh_sha256,
        "arrays_sha256": raw["arrays_sha256"],  # (two runs of one seed: the same, though their files' timings differ)
        "config": model.config.model_dump(mode="json"),
        "training": header.training,
    }, plot)


def _plotted(facts: dict, plot: Path | None) -> dict:
    """``facts`` (`info` of a model or checkpoint), with its training curve drawn to ``plot`` if asked."""
    from .io.plots import plot_problem, training_plot_title, write_training_plot

    if plot is None:
        return facts
    record = facts["training"]
    problem = plot_problem(record)
    if problem:
        raise ModelFileError(f"{facts['path']}: {problem}")
    name = facts.get("mesh_name") or f"mesh {str(facts.get('mesh_sha256'))[:12]}"
    step = facts["step"] if facts["kind"] == "checkpoint" else None
    title = training_plot_title(facts["method"], facts.get("preset"), name, record, checkpoint_step=step)
    write_training_plot(plot, record["curve"], title)
    return {**facts, "plot": str(plot)}


def _checkpoint_info(path: Path, header: dict) -> dict:
    """What an interrupted training run left: its method, step and figures so far (``train --resume`` continues it)."""
    identity = header.get("identity") if isinstance(header.get("identity"), dict) else {}
    config = identity.get("config") if isinstance(identity.get("config"), dict) else {}
    record = header.get("record") if isinstance(header.get("record"), dict) else {}
    return {
        "kind": "checkpoint",
        "path": str(path),
        "method": config.get("method"),
        "mesh_name": header.get("mesh_name") if isinstance(header.get("mesh_name"), str) else None,
        "step": header.get("step"),
        "format_version": header.get("format_version"),
        "mesh_sha256": identity.get("mesh_sha256"),
        "config": config,  # without checkpoint_every, and training.steps unless the method's schedule spans them
        "training": record,
        "resume": _resume_hint(path),
    }


def _resume_hint(checkpoint: Path) -> str:
    """The command that continues a checkpoint's run: `train --resume` writes MODEL.nrt.ckpt; `convert`
    writes its models folder's STEM.ckpt, which a rerun of the same convert command resumes."""
    import shlex

    if checkpoint.name.lower().endswith(MODEL_SUFFIX + CHECKPOINT_SUFFIX):
        model = shlex.quote(str(checkpoint)[: -len(CHECKPOINT_SUFFIX)])
        return f"neuralrt train MESH -o {model} --resume (with the run's settings; its method is read from the checkpoint)"
    return "run the neuralrt convert command that wrote it again: its unfinished models resume from their checkpoints"


def list_builtins() -> list[dict]:
    """Every built-in scene, as ``render --list-builtins --json`` prints it: ``{"scene":
    "builtin:NAME", "description": ...}`` (the scene as `render` and `load_scene` take it)."""
    from .scene.builtins import list_builtins as _list

    return [{"scene": f"builtin:{name}", "description": description} for name, description in _list()]


def render(
    scene,
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
    allow_mesh_mismatch: bool = False,
    nif: str | list[str] | None = None,
    nif_train_spp: int | None = None,
    nif_config: dict | None = None,
    inference: dict | None = None,
) -> dict:
    """Path-trace ``scene`` to ``output`` (EXR; PNG and AOVs beside it).

    ``scene`` is a scene file, ``builtin:NAME``, one mesh (a mesh file, ``procedural:NAME:DETAIL``)
    or model file (``.nrt``) to render alone (`neuralrt.scene.studio`), a dict shaped like a scene file (objects may hold
    `Mesh` and loaded model objects; see `neuralrt.scene.load_dict`) or an already built `Scene`
    (then ``resolution``, ``detail``, ``primary`` and ``inference`` are the scene's own: passing them is an error).
    A scene object whose model was trained on another mesh is an error unless ``allow_mesh_mismatch``.
    ``inference`` (``{"lod": 2}``; the CLI's ``--set inference.lod=2``) changes how every neural model
    of the scene that has the setting answers, over its object's own (`neuralrt.scene.build_scene`).
    ``nif`` (object names, or ``"auto"``) answers those objects' shadow rays with NIF, trained
    online on the first ``nif_train_spp`` samples (docs/nif.md); the result then has a ``"nif"`` report.
    ``nif_config`` changes NIF's settings (``{"shadow_rays": "every_hit"}``; the CLI's ``--set nif.KEY=VALUE``)."""
    from .render.integrator import render as _render
    from .render.integrator import warm_up
    from .scene.schema import MAX_DEPTH, MAX_SPP

    check_device(device)
    check_flags(progress=progress, allow_mesh_mismatch=allow_mesh_mismatch)
    spp = check_count(given("spp"), spp, maximum=MAX_SPP)  # a scene file's bounds (named as the caller spells it)
    max_depth = check_count(given("max_depth"), max_depth, minimum=1, maximum=MAX_DEPTH)
    seed = seed_or_default(given("seed"), seed)
    nif_train_spp = check_count(given("nif_train_spp"), nif_train_spp)  # NIF hook (issue 10)
    if nif_train_spp is not None and nif is None:
        raise ConfigError(f"{given('nif_train_spp')} needs {given('nif', flag='--nif OBJECTS|auto')}")
    if inference is not None:  # (a key of no method: said now, as eval says it, not after the scene loads)
        from .methods.base import checked_inference

        inference = checked_inference(inference)
    if nif_config is not None and nif is None:
        raise ConfigError(f"{given('nif_config', flag='--set nif.KEY=VALUE')} needs {given('nif', flag='--nif OBJECTS|auto')}")
    if nif is not None:
        from .render.nif_render import check_nif_names, checked_nif_config

        check_nif_names(nif)
        nif_config = checked_nif_config(nif_config, given("nif_config", flag="--set nif.KEY=VALUE"))
    from .render.film import check_render_output, output_files

    output = check_render_output(output)

    nif_plot = output.with_name(f"{output.stem}_nif_training.png") if nif is not None else None
    written = output_files(output) + ([nif_plot] if nif_plot else [])  # the image, every AOV beside it, NIF's plot
    check_output_files(written, "render output")  # (before the scene loads)
    # (a dict's warnings name the output: one sweep's scenes were all "scene", and Python shows a
    # warning of the same text from the same line once)
    loaded = _scene_from(scene, device=device, resolution=resolution, detail=detail, primary=primary,
                         allow_mesh_mismatch=allow_mesh_mismatch, inference=inference, label=f"scene rendered to {output}")
    _check_not_an_input(written, loaded, scene)
    primary = loaded.primary
    import warnings

    from .render.enclosure import enclosure_notes
    from .render.far_objects import far_object_notes

    if not loaded.lights:
        warnings.warn(f"{getattr(loaded, 'name', '') or 'scene'}: the scene has no light (no point light with intensity, "
                      "no emissive object, no environment): it renders black", stacklevel=outside_stacklevel())
    for note in [*enclosure_notes(loaded), *far_object_notes(loaded)]:  # (said before the render)
        warnings.warn(note, stacklevel=outside_stacklevel())
    nif_report = None
    try:
        # (untimed: the process's one-time kernel loading is not the render's time per sample)
        warmup_seconds = warm_up(loaded, primary=primary, max_depth=max_depth)
        if nif is not None:  # NIF hook (issue 10): objects and spp are checked before any sample is rendered
            from .render.nif_render import render_nif

            result, nif_report = render_nif(loaded, nif, spp=spp, train_spp=nif_train_spp, seed=seed, config=nif_config,
                                            max_depth=max_depth, progress=progress, primary=primary)
        else:
            result = _render(loaded, spp=spp, seed=seed, max_depth=max_depth, progress=progress, primary=primary)
    except NeuralRTError:
        raise  # already ours (a ConfigError is a ValueError too): keep its class
    except ValueError as exc:  # settings the integrator refuses (pydantic's errors are ValueErrors too)
        from pydantic import ValidationError

        from .errors import validation_message

        raise NeuralRTError(validation_message(exc) if isinstance(exc, ValidationError) else str(exc)) from None
    files = result.save(output)
    if nif_report is not None and nif_report["training"]["rounds"]:
        from .io.plots import write_nif_training_plot

        title = f"NIF online training: {', '.join(nif_report['objects'])}, first {nif_report['train_spp']} of {nif_report['spp']} spp"
        files.append(write_nif_training_plot(nif_plot, nif_report["training"], title))
    h, w = result.image.shape[:2]
    return {
        "scene": scene if isinstance(scene, (str, Path)) else (getattr(loaded, "name", "") or type(scene).__name__),
        "output": str(output),
        "files": [str(f) for f in files],
        "resolution": [w, h],
        "spp": result.spp,
        "max_depth": max_depth if max_depth is not None else loaded.settings.max_depth,
        "seed": seed,
        "seconds": result.seconds,
        "warmup_seconds": warmup_seconds,
        "seconds_per_spp_per_megapixel": result.seconds / result.spp / (w * h / 1e6),
        **({"nif": nif_report} if nif_report is not None else {}),
    }


def _check_not_an_input(outputs: list[Path], loaded, scene) -> None:
    """A one-line error where a render output would replace a file the scene reads (its file, a
    mesh, model, texture or environment image): ``-o sky.exr`` beside a scene lit by sky.png."""
    inputs = [Path(scene)] if isinstance(scene, (str, Path)) else []
    if loaded.spec is not None:
        loaded.spec.with_paths(lambda p: inputs.append(Path(p)) or p)  # (every file path the scene names)
    read = {_file_identity(i) for i in dict.fromkeys(inputs)} - {None}  # (a scene of 20,000 objects: one stat each)
    for out in outputs:
        if _file_identity(out) in read:
            raise NeuralRTError(f"{out}: the render would replace a file its scene reads: give another output name")


def _file_identity(path: Path) -> tuple[int, int] | None:
    """(device, inode) of the file at ``path``, as `os.path.samefile` compares them; None where none is."""
    import stat
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino) if stat.S_ISREG(st.st_mode) else None


def _scene_from(scene, *, device, resolution, detail, primary, allow_mesh_mismatch, inference=None, label="scene"):
    """A built `Scene` from a path / ``builtin:NAME``, a scene dict (named ``label`` in its errors
    and warnings), or a `Scene` (returned as is)."""
    import torch

    from .scene.loader import load_dict, load_scene
    from .scene.scene import Scene

    if isinstance(scene, Scene):
        if resolution is not None or detail is not None or primary != "exact" or inference is not None:
            raise NeuralRTError("resolution, detail, primary and inference belong to a built Scene: set them when building it")
        if torch.device(device).type != scene.device.type:
            raise NeuralRTError(f"the scene was built on {scene.device}, not on {device}: build it with device={device!r}")
        return scene
    if isinstance(scene, dict):
        if detail is not None:
            raise NeuralRTError("detail applies to builtin scenes, not to a scene dict")
        if resolution is not None:
            scene = {**scene, "camera": {**scene.get("camera", {}), "resolution": list(resolution)}}
        return load_dict(scene, device=device, primary=primary, allow_mesh_mismatch=allow_mesh_mismatch,
                         inference=inference, label=label)
    if not isinstance(scene, (str, Path)):
        raise NeuralRTError(f"scene must be a path, 'builtin:NAME', a dict or a Scene, not {type(scene).__name__}")
    return load_scene(str(scene), device=device, resolution=resolution, detail=detail, primary=primary,
                      allow_mesh_mismatch=allow_mesh_mismatch, inference=inference)


def train(
    mesh,
    output: str | Path,
    *,
    method: str | None = None,
    preset: str | None = None,
    steps: int | None = None,
    batch: int | None = None,
    seed: int | None = None,
    resume: bool = False,
    device: str = "cpu",
    progress: bool = True,
    settings: dict | None = None,
    plot: str | Path | None = None,
) -> dict:
    """Train a model of ``mesh`` (a path or a `Mesh`) with ``method`` (default: lsnif) and ``preset``
    (default: the method's default for ``device``; LSNIF: ``hq`` on the CPU, ``gpu`` on CUDA), and
    write it to ``output`` (atomically). ``settings`` changes config keys of the preset
    (``{"voxel": {"resolution": 64}}``; the CLI's ``--set voxel.resolution=64``; keys: docs/config.md).

    A checkpoint ``<output>.ckpt`` is written as training goes; ``resume=True`` continues an
    interrupted run from it (``method`` and ``training.checkpoint_every`` default to the run's, and,
    for N-BVH, whose cut schedule spans the run, ``steps`` too). It is removed once the model file is written. ``plot`` (.png, .pdf or
    .svg) draws the run's training curve (also kept in the model file: `info` draws it later).
    """
    from .geometry.mesh import Mesh, load_mesh
    from .methods import DEFAULT_METHOD, get_method
    from .training.api import train as _train
    from .training.trainer import checkpoint_run

    check_device(device)
    check_name("method", method)
    check_name("preset", preset)
    check_flags(resume=resume, progress=progress)
    steps = check_count(given("steps"), steps)
    batch = check_count(given("batch"), batch)  # its bounds are the config's (training.batch_size)
    seed = check_seed(given("seed"), seed)
    output = check_path("output", output)
    checkpoint = output.with_name(output.name + CHECKPOINT_SUFFIX)
    run_every = None
    if resume:  # what is not given is the run's it continues (--resume alone resumes an N-BVH run)
        run_method, run_steps, run_every = checkpoint_run(checkpoint)
        method = method or run_method
        steps = steps if steps is not None or method != run_method else run_steps
    spec = get_method(method or DEFAULT_METHOD)
    preset = preset or spec.default_preset(device)
    config = spec.config(preset, device=device, settings=settings, steps=steps, batch_size=batch, seed=seed)
    if run_every is not None and "checkpoint_every" not in ((settings or {}).get("training") or {}):
        config = config.with_training(checkpoint_every=run_every)  # (how often the run saves, unless given anew)
    if not isinstance(mesh, Mesh):
        mesh = check_path("mesh", mesh)
    check_model_path(output)
    check_output_file(output, "model file")
    check_output_file(checkpoint, "checkpoint")  # (its name is longer)
    if plot is not None:
        from .io.plots import check_plot_path

        plot = check_plot_path(check_path(given("plot"), plot))
    # (an interrupt too) stopped before the first checkpoint: no new empty folder is left
    with folders_removed_if_left_empty(output.parent):
        output.parent.mkdir(parents=True, exist_ok=True)
        # Another run on this checkpoint is told first: the checks below would call its checkpoint left over.
        # (Locked by the model file it writes: `-o link.nrt`, a link to m.nrt, ran beside `-o m.nrt`.)
        written = Path(os.path.realpath(output))
        with held_alone(written.with_name(written.name + CHECKPOINT_SUFFIX)), held_alone(checkpoint):
            if resume and not checkpoint.is_file():
                raise NeuralRTError(f"{checkpoint}: no checkpoint to resume from")
            if not resume and checkpoint.is_file():  # the run below overwrites it at its first checkpoint
                import warnings

                warnings.warn(f"{checkpoint}: an earlier interrupted run's checkpoint is there; this run starts afresh "
                              f"and replaces it ({given('resume', True, flag='--resume')} continues it instead)", stacklevel=outside_stacklevel())
            if not isinstance(mesh, Mesh):
                mesh = load_mesh(mesh)
            model = _train(mesh, config, progress=progress, checkpoint=checkpoint, resume=resume, device=device)
            try:
                model.save(output)
            except TrainingError:  # (weights past the storage's range: resuming would store the same)
                checkpoint.unlink(missing_ok=True)
                raise
            checkpoint.unlink(missing_ok=True)
    memory = model.memory_bytes()
    result = {"model": str(output), "method": spec.name, "preset": preset, "memory_bytes": memory.total,
              "memory_parts": dict(memory.parts), "training": model.training_record}
    if plot is not None:
        from .io.plots import training_plot_title, write_training_plot

        record = model.training_record
        title = training_plot_title(spec.name, spec.preset_of(model.config), model.mesh_name, record)  # (as `info` names it)
        write_training_plot(plot, record["curve"], title)
        result["plot"] = str(plot)
    return result


def list_presets() -> list[dict]:
    """Every registered method's presets: ``[{"method", "preset", "default_on", "summary"}, ...]``."""
    from .methods import get_method, method_names

    rows = []
    for name in method_names():
        spec = get_method(name)
        defaults = {}
        for device, preset in spec.default_presets.items():
            defaults.setdefault(preset, []).append("other devices" if device == "*" else device)
        for preset in spec.presets:
            rows.append({"method": name, "preset": preset, "default_on": defaults.get(preset, []), "summary": spec.summary})
    return rows


def evaluate(
    model,
    mesh,
    *,
    rays: int = 1 << 17,
    seed: int | None = None,
    images: bool = True,
    image_dir: str | Path | None = None,
    device: str = "cpu",
    allow_mesh_mismatch: bool = False,
    timing: bool = True,
    progress: bool = True,
    inference: dict | None = None,
) -> dict:
    """Held-out accuracy of a model (a path or a loaded model) against its mesh (a path or a `Mesh`):
    rays from outside and from the surface, plus normal/depth images from orbit cameras, neural vs
    exact, with FLIP; its memory against BVH A / B; with ``timing``, its rays/s against exact
    tracing's on the held-out rays (this run, this machine). A model trained on another mesh is an
    error unless ``allow_mesh_mismatch``. ``progress``: a bar over the stages on stderr.
    ``inference`` changes how the model answers (``{"lod": 2}``: `NeuralBLAS.with_inference`; the
    CLI's ``--set inference.lod=2``)."""
    from .eval.intersection_metrics import HELD_OUT_SEED, evaluate_model
    from .geometry.mesh import Mesh, load_mesh
    from .methods import check_mesh_match, is_neural, load_model
    from .methods.base import checked_inference

    check_device(device)
    rays = check_count(given("rays"), rays, minimum=2, maximum=MAX_EVAL_RAYS)
    seed = check_seed(given("seed"), seed)
    check_flags(images=images, allow_mesh_mismatch=allow_mesh_mismatch, timing=timing, progress=progress)
    if not is_neural(model):
        if isinstance(model, Mesh):
            raise ConfigError("model: got a Mesh; evaluate(model, mesh) takes the model first")
        model = check_path("model", model)
        if str(model).startswith("procedural:"):
            raise ConfigError(f"{model}: names a built-in mesh, not a model: eval takes a model file (.nrt, from "
                              "neuralrt train) first, then the mesh it was trained on")
    if not isinstance(mesh, Mesh):
        mesh = check_path("mesh", mesh)
        if mesh.suffix.lower() in MODEL_SUFFIXES and not is_neural(model) and Path(model).suffix.lower() not in MODEL_SUFFIXES:
            raise ConfigError(f"{model}, {mesh}: the model comes first: eval MODEL MESH ({mesh.name} is the model file)")
    image_dir = check_path("image_dir", image_dir, optional=True)
    if image_dir is not None:
        if not images:
            raise ConfigError(f"{given('image_dir', flag='--images DIR')} and {given('images', False, flag='--no-images')} contradict each other: give one")
        check_output_folder(image_dir, "image")
        from .eval.intersection_metrics import image_files

        check_output_files(image_files(image_dir), "eval image")  # (a folder in the way: said now, not after the work)
    inference = checked_inference(inference)
    blas = model if is_neural(model) else load_model(model, device=device)
    blas = blas.with_inference(**inference)
    if seed is not None and seed == blas.config.training.seed:  # (a NeuralBLAS: every method's config has it)
        import warnings

        warnings.warn(f"{given('seed', seed)} is the model's training seed: these rays may repeat its training rays "
                      f"(not held out; the default seed, {HELD_OUT_SEED}, is far from training seeds)",
                      stacklevel=outside_stacklevel())
    source = mesh if isinstance(mesh, Mesh) else load_mesh(mesh)
    mesh_hash = source.content_hash()
    check_mesh_match(blas, mesh_hash, allow_mismatch=allow_mesh_mismatch, label=str(model) if isinstance(model, (str, os.PathLike)) else "")
    with folders_removed_if_left_empty(*([image_dir] if image_dir is not None else [])), written_together():
        result = evaluate_model(blas, source, rays=rays, seed=HELD_OUT_SEED if seed is None else seed,
                                images=images, image_dir=image_dir, timing=timing, progress=progress)
    result["mesh_matches_model"] = blas.mesh_hash is None or blas.mesh_hash == mesh_hash
    if inference:
        result["inference"] = dict(inference)  # (the settings it answered with, changed from the model file's)
    return result


def import_scene(gltf: str | Path, output: str | Path) -> dict:
    """Write a scene file (.toml/.json) for the glTF scene ``gltf`` (``neuralrt import``): each node's
    mesh an object naming that mesh of the file, placed by the node (a mesh many nodes draw is one
    accelerator), the file's first perspective camera, its lights and its named materials
    (`neuralrt.scene.gltf_import`). Returns what the scene holds."""
    from .scene.gltf_import import import_gltf_scene

    gltf, output = check_path("gltf", gltf), check_path("output", output)
    check_output_file(output, "scene file")
    return import_gltf_scene(gltf, output)


def convert(
    scene: str | Path | dict,
    output: str | Path,
    *,
    models_dir: str | Path | None = None,
    select: str | list[str] | None = None,
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
) -> dict:
    """Train models for a scene's complex objects and write a scene that uses them (``neuralrt convert``).

    The keywords are `neuralrt.scene.convert.convert_scene`'s, which tells each (the CLI's
    ``convert`` flags are the same); ``select`` also takes comma-separated names, as on the command
    line, and ``executor`` is ``"local"`` or ``"ray"`` (`neuralrt.scene.convert_executors`).
    Returns the conversion report (what ``convert --json`` prints)."""
    from .scene.convert import convert_scene

    if not isinstance(scene, dict):
        scene = check_path("scene", scene)
    output = check_path("output", output)
    models_dir = check_path("models_dir", models_dir, optional=True)
    for name, value in (("method", method), ("preset", preset), ("executor", executor), ("address", address)):
        check_name(name, value)
    check_flags(group=group, progress=progress)
    seed = check_seed(given("seed"), seed)  # (None stays None; names as train gives them)
    steps, batch = check_count(given("steps"), steps), check_count(given("batch"), batch)
    min_triangles = check_count(given("min_triangles"), min_triangles, minimum=0)
    if isinstance(select, str):  # as on the command line: comma-separated names
        select = [n.strip() for n in select.split(",") if n.strip()]
    elif select is not None and not (isinstance(select, (list, tuple)) and all(isinstance(n, str) for n in select)):
        raise ConfigError(f"select: expected object names (a str or a list of str), got {type(select).__name__}")
    if executor != "ray":
        check_device(device)
    else:  # Ray tasks train on the cluster's devices, whose presence is checked there; the name, here
        check_device_name(device)
    return convert_scene(scene, output, models_dir=models_dir, select=select, min_triangles=min_triangles,
                         method=method, preset=preset, group=group, steps=steps, batch=batch, seed=seed,
                         detail=detail, device=device, progress=progress, executor=executor, address=address,
                         cpus_per_model=cpus_per_model, gpus_per_model=gpus_per_model,
                         threads_per_model=threads_per_model, max_retries=max_retries, settings=settings).as_dict()


def demo(out_dir: str | Path = "neuralrt-demo", quick: bool = False, *, device: str = "cpu", progress: bool = True,
         **overrides) -> dict:
    """Convert a built-in scene, render exact and hybrid, compare, and write a report folder."""
    from dataclasses import fields, replace

    from . import demo as demo_module

    check_device(device)
    check_flags(quick=quick, progress=progress)
    out_dir = check_path("out_dir", out_dir)
    known = [f.name for f in fields(demo_module.DemoSettings)]
    unknown = sorted(set(overrides) - set(known))
    if unknown:
        raise ConfigError(f"demo: unknown setting(s) {', '.join(unknown)} (known: {', '.join(known)})")
    base = demo_module.DEMO_QUICK if quick else demo_module.DEMO_DEFAULT
    settings = replace(base, **{k: v for k, v in overrides.items() if v is not None})  # validated on construction
    return demo_module.run_demo(out_dir, quick=quick, device=device, progress=progress, settings=settings)
