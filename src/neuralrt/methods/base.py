"""`NeuralBLAS`: what every neural intersection method shares, so a method only writes its own parts.

A method subclasses `NeuralBLAS` and provides:

- ``from_mesh(mesh, config)``: an untrained model of a mesh (bounds, materials, mesh hash set here);
- ``training_step(rays, truth) -> StepResult``: the loss of one batch against exact hits;
- ``_intersect_chunk(rays) -> Hits``: answers for at most `rays_per_chunk` rays (``config.inference.chunk_size``
  unless the method takes more on a device);
- ``memory_bytes()``: run-time bytes, itemised;
- ``_arrays()`` / ``_from_arrays(config, bounds, materials, arrays)``: what its model file stores
  besides the common header, and how a model is rebuilt from it;
- optionally ``prepare_training_batch(rays)`` (the part of a step that depends on the batch alone,
  which the training loop may compute on the thread that draws the batch, handing it to
  ``training_step(rays, truth, prepared)``; LSNIF: the voxel walk and the network rays),
  ``after_training_step(step, optimizer)`` (e.g. N-BVH refines its BVH cut), ``box``
  (the region training rays aim at; default: the bounds), ``training_rays(truth, device)`` (the
  training ray distribution; default: `BoxRayDistribution` around ``box``) and
  ``_learned_modules(config, num_materials)`` (the modules whose parameters the file stores,
  which loading builds on the meta device first to check a file's arrays against its config
  before allocating anything).

The base class holds config, bounds, mesh hash, materials and training record; it answers rays in
chunks, picks the compute precision, rounds to the storage precision, and saves and loads every
method through one typed model-file header (`neuralrt.io.model_file.ModelHeader`).
"""

from __future__ import annotations

import contextlib
import contextvars
import copy
import json
import os
import warnings
from abc import ABC, abstractmethod
from pathlib import Path
from typing import ClassVar

import torch
from pydantic import ValidationError
from torch import Tensor, nn

from ..arguments import given
from ..accel.blas import MemoryReport
from ..devices import check_device, check_path
from ..errors import ConfigError, DeviceError, MeshMismatchError, ModelFileError, TrainingError, outside_stacklevel, validation_message
from ..fork_guard import check_not_forked
from ..io.files import check_output_file
from ..io.model_file import ModelHeader, check_model_path, read_model, write_model
from ..neural.precision import STORAGE_BYTES, STORAGE_DTYPES, compute_dtype
from ..rays import AABB, Hits, Rays, check_rays
from .config import MethodConfig

__all__ = ["NeuralBLAS", "is_neural", "ray_views", "memory_owner", "check_mesh_match", "MeshMismatchWarning", "material_table",
           "checked_inference", "mesh_mismatch_unsaid"]

DEFAULT_MATERIALS = [{"name": "default", "base_color": [1.0, 1.0, 1.0]}]


class MeshMismatchWarning(UserWarning):
    """A model is used without its source mesh at hand, so nothing checks that they belong together."""


# Set by `mesh_mismatch_unsaid` in this thread or task only: `warnings.catch_warnings` changed the
# filters of every thread, and leaving it made Python repeat warnings it had already shown.
_MISMATCH_UNSAID = contextvars.ContextVar("neuralrt_mesh_mismatch_unsaid", default=False)


@contextlib.contextmanager
def mesh_mismatch_unsaid():
    """Within the block, `check_mesh_match` says no `MeshMismatchWarning` (a model rendered alone
    has no object mesh to belong to; `info` inspects a scene, and rendering it says so)."""
    token = _MISMATCH_UNSAID.set(True)
    try:
        yield
    finally:
        _MISMATCH_UNSAID.reset(token)


def _stored_arrays_problem(found: dict[str, Tensor], expected: dict[str, Tensor]) -> str | None:
    """What is wrong with a model file's arrays (None if nothing), judged against what the model
    they built would store (`_arrays`): other names, dtypes or shapes (a table stored as int32
    was read as numbers), or values that are not finite (NaN weights answer NaN distances)."""
    if set(found) != set(expected):
        extra, missing = sorted(set(found) - set(expected)), sorted(set(expected) - set(found))
        return "; ".join(([f"arrays it does not use: {', '.join(extra[:3])}"] if extra else [])
                         + ([f"arrays missing: {', '.join(missing[:3])}"] if missing else []))
    for name in sorted(found):
        a, b = found[name], expected[name]
        if a.dtype != b.dtype or a.shape != b.shape:
            return f"array '{name}' is {str(a.dtype).removeprefix('torch.')} {list(a.shape)}, expected " \
                   f"{str(b.dtype).removeprefix('torch.')} {list(b.shape)}"
        if a.is_floating_point() and not torch.isfinite(a).all():
            return f"array '{name}' holds NaN or infinite values"
    return None


def prefixed_parameters(modules: dict[str, nn.Module]) -> dict[str, nn.Parameter]:
    """File key -> parameter: each module's parameters under its prefix (``network.output.weight``)."""
    return {f"{prefix}.{k}": p for prefix, module in modules.items() for k, p in module.named_parameters()}


def _declared_parameters_problem(cls: type["NeuralBLAS"], config: MethodConfig, num_materials: int,
                                 arrays: dict[str, Tensor]) -> str | None:
    """Whether a file holds the parameters its config declares (None if it does), judged on
    modules built on the meta device, which allocates nothing: a 2 KB file whose config asks for
    a thousand hash-grid levels or 4096-wide layers is refused before they take gigabytes."""
    with torch.device("meta"):
        modules = cls._learned_modules(config, num_materials)
    declared = prefixed_parameters(modules) if modules is not None else {}
    for name, p in declared.items():
        if name not in arrays:
            return f"arrays missing: {name}"
        if tuple(arrays[name].shape) != tuple(p.shape):
            return f"array '{name}' is {list(arrays[name].shape)}, expected {list(p.shape)} by its config"
    return None


def _bounds_problem(bounds: AABB) -> str | None:
    """Why a model file's bounds cannot be a trained model's (None if they can): not finite, corners
    swapped, or a diagonal outside the sizes training takes (`FLOAT32_DIAGONAL_RANGE`)."""
    from ..geometry.mesh import FLOAT32_DIAGONAL_RANGE

    lo, hi = bounds.lo.double(), bounds.hi.double()
    diagonal = float(torch.linalg.norm(hi - lo))
    low, high = FLOAT32_DIAGONAL_RANGE
    if not (torch.isfinite(lo).all() and torch.isfinite(hi).all() and (lo <= hi).all()) or not low <= diagonal <= high:
        return f"its bounds {bounds.tolist()} are no box a model is trained in (diagonal within [{low:g}, {high:g}])"
    return None


def is_neural(blas) -> bool:
    """Whether ``blas`` answers rays with a trained model (the one place that decides it)."""
    return isinstance(blas, NeuralBLAS)


def ray_views(blas) -> tuple:
    """(camera_blas, other_blas): what answers an object's camera rays and every other ray
    (`NeuralBLAS.views_for_rays`); a BLAS without the hook answers both itself."""
    views = getattr(blas, "views_for_rays", None)
    return views() if views is not None else (blas, blas)


def memory_owner(blas):
    """The object whose bytes ``blas`` reports: a view sharing a model's parameters names the model,
    so that a scene counts them once (`NeuralBLAS.memory_owner`); any other BLAS is its own owner."""
    return getattr(blas, "memory_owner", blas)


def check_mesh_match(model, mesh_hash: str | None, *, allow_mismatch: bool = False, label: str = "") -> None:
    """Check that ``model`` was trained on the mesh whose content hash is ``mesh_hash``.

    A mismatch raises `MeshMismatchError`, or with ``allow_mismatch`` warns; ``mesh_hash=None`` (no mesh at
    hand, e.g. a scene object given only a model) or a model that records no hash warns
    (`MeshMismatchWarning`). ``label`` prefixes the message (e.g. the scene file and key).
    """
    prefix = f"{label}: " if label else ""
    expected = getattr(model, "mesh_hash", None)
    name = getattr(model, "mesh_name", None) or "?"
    own_mesh = getattr(model, "mesh", None)  # an exact BLAS given as the model: its mesh says
    if expected is None and own_mesh is not None and hasattr(own_mesh, "content_hash"):
        expected, name = own_mesh.content_hash(), own_mesh.name
    if mesh_hash is None or expected is None:
        what = "no mesh is given" if mesh_hash is None else "the model records no mesh hash"
        if not _MISMATCH_UNSAID.get():
            warnings.warn(f"{prefix}cannot check that the model belongs to this object ({what})", MeshMismatchWarning,
                          stacklevel=outside_stacklevel())
        return
    if mesh_hash != expected and allow_mismatch:  # (used as asked, and said: the figures are of another mesh)
        if _MISMATCH_UNSAID.get():
            return
        warnings.warn(f"{prefix}the model was trained on another mesh ({name!r}, sha256 {expected[:12]}...; this mesh: "
                      f"{mesh_hash[:12]}...): used anyway, as {given('allow_mesh_mismatch', True, flag='--allow-mesh-mismatch')} "
                      "asks", MeshMismatchWarning, stacklevel=outside_stacklevel())
    elif mesh_hash != expected:
        raise MeshMismatchError(
            f"{prefix}the model was trained on another mesh ({name!r}, sha256 {expected[:12]}...; this mesh: {mesh_hash[:12]}...; "
            f"or the same mesh read differently, as by a newer neuralrt or from another export); retrain, or pass "
            f"{given('allow_mesh_mismatch', True, flag='--allow-mesh-mismatch')} to use it anyway"
        )


def checked_inference(inference) -> dict:
    """A caller's inference changes (None: none) as a dict of setting names, for
    `NeuralBLAS.with_inference`; a one-line `ConfigError` for anything else."""
    if inference is None:
        return {}
    if not isinstance(inference, dict) or not all(isinstance(k, str) for k in inference):
        raise ConfigError(f"inference: expected a dict of setting names (e.g. {{'lod': 2}}), got {type(inference).__name__}")
    from .registry import methods_answering_with

    unknown = [key for key in inference if not methods_answering_with(key)]
    if unknown:  # (a setting of no method at all: said before any scene or model is read)
        from .registry import changeable_inference_keys

        raise ConfigError(f"inference.{unknown[0]}: not a setting of any method's models (theirs: "
                          f"{', '.join(changeable_inference_keys())}; python -m neuralrt.configdoc)")
    return inference


def material_table(mesh) -> list[dict]:
    """A mesh's material slots as stored in a model file: ``[{"name": str, "base_color": [r, g, b]}, ...]``."""
    import numpy as np

    return [{"name": m.name, "base_color": [float(c) for c in np.asarray(m.base_color).reshape(-1)[:3]]} for m in mesh.materials]


class NeuralBLAS(nn.Module, ABC):
    """A trained (or training) neural model of one object; implements the `BLAS` protocol.

    Args:
        config: the method's full config.
        bounds: the object's tight AABB in object space (kept on the CPU).
        materials: the material table, ``[{"name": str, "base_color": [r, g, b]}, ...]``.
    """

    METHOD: ClassVar[str]  # the name registered for the method and written in model files
    TITLE: ClassVar[str]  # how messages name the method, e.g. "LSNIF"
    CONFIG: ClassVar[type[MethodConfig]]

    def __init__(self, config: MethodConfig, bounds: AABB, materials: list[dict] | None = None):
        super().__init__()
        self.config = config
        self.bounds = AABB(bounds.lo.float().cpu(), bounds.hi.float().cpu())
        self.materials = [dict(m) for m in materials] if materials else [dict(m) for m in DEFAULT_MATERIALS]
        self.training_record: dict = {}  # `TrainingRecord.as_dict()` of the run that trained it
        self.mesh_hash: str | None = None  # SHA-256 of the source mesh's content
        self.mesh_name: str | None = None

    # -- what a method provides ------------------------------------------------------------------
    @classmethod
    @abstractmethod
    def from_mesh(cls, mesh, config: MethodConfig | None = None) -> "NeuralBLAS":
        """An untrained model of ``mesh`` (set ``mesh_hash``/``mesh_name`` with `_remember_mesh`)."""

    @abstractmethod
    def training_step(self, rays: Rays, truth: Hits):
        """`neuralrt.training.step.StepResult` of one batch against the exact hits ``truth``."""

    @abstractmethod
    def _intersect_chunk(self, rays: Rays) -> Hits:
        """Closest hits of at most `rays_per_chunk` rays (on the model's device)."""

    @abstractmethod
    def memory_bytes(self) -> MemoryReport:
        """Run-time bytes at the storage precision, itemised."""

    @abstractmethod
    def _arrays(self) -> dict[str, Tensor]:
        """The named arrays the model file stores (at the storage precision)."""

    @classmethod
    @abstractmethod
    def _from_arrays(cls, config: MethodConfig, bounds: AABB, materials: list[dict], arrays: dict[str, Tensor]) -> "NeuralBLAS":
        """Rebuild a model from a file's arrays; raise ValueError/KeyError for missing or mis-shaped ones."""

    @classmethod
    def _learned_modules(cls, config: MethodConfig, num_materials: int) -> dict[str, nn.Module] | None:
        """Optional: the modules whose parameters the model file stores, by the prefix of their
        arrays' names (``{"encoder": ..., "network": ...}``: `prefixed_parameters`), freshly built
        from ``config`` on the default device. `load` builds them on the meta device, which
        allocates nothing, to check a file's arrays against its config before building the model:
        a small file whose config asks for gigabytes of layers is refused first. None (the
        default): no such check."""
        return None

    def prepare_training_batch(self, rays: Rays):
        """What ``training_step`` computes from the batch alone, never from the parameters, or None
        when it has nothing such (the default): the training loop may run this on the thread that
        draws the next batch while the current step runs, and passes the result to
        ``training_step(rays, truth, prepared)``. Runs beside a training step: reads only state
        that training does not change."""
        return None

    def after_training_step(self, step: int, optimizer: torch.optim.Optimizer) -> None:
        """Called by the training loop after each optimizer step (e.g. to refine a BVH cut). Default: nothing."""

    def progress_fields(self) -> dict[str, str]:
        """Method-specific fields the training progress bar shows (e.g. N-BVH's node count). Default: none."""
        return {}

    def curve_states(self) -> dict[str, float]:
        """Method-specific values the training curve keeps at each of its points, as they stand
        (e.g. N-BVH's node count; the plot draws them). Default: none."""
        return {}

    def training_rays(self, truth, device: torch.device):
        """The ray distribution training draws batches from (``sample(n)``, ``state_dict``/``load_state_dict``),
        with exact answers from ``truth``. Default: `BoxRayDistribution` around `box` (N-BVH draws its own)."""
        from ..training.ray_distribution import BoxRayDistribution

        tc = self.config.training
        return BoxRayDistribution(truth, self.box, surface_fraction=tc.surface_fraction, pool_size=tc.surface_pool_size,
                                  surface_offset=tc.surface_offset, seed=tc.seed, device=device)

    def views_for_rays(self) -> tuple["NeuralBLAS", "NeuralBLAS"]:
        """(camera_blas, other_blas) a scene registers for this model: what answers camera rays and
        what answers every other ray (e.g. N-BVH's coarser level of detail after the first bounce).
        Views share this model's parameters (`memory_owner`). Default: the model answers both."""
        return self, self

    def with_inference(self, **changes) -> "NeuralBLAS":
        """This model answering with some ``inference`` settings changed (N-BVH's ``lod`` or
        ``secondary_lod``, a ``compute_precision``, a ``chunk_size``; none changes the trained
        parameters): a view that shares every parameter and buffer (a shallow copy with its own
        config; `memory_owner` names this model), made once per setting; the model itself where
        nothing changes. ``storage_precision``, how the parameters were stored, is no setting to
        change. A bad key or value is a one-line `ConfigError`."""
        if not changes:
            return self
        fields = type(self.config.inference).model_fields
        unknown = [key for key in changes if key not in fields]
        if unknown:  # (pydantic would say "Extra inputs are not permitted")
            from .registry import methods_answering_with

            others = [m for m in methods_answering_with(unknown[0]) if m != self.METHOD]
            where = f"; it is one of {', '.join(others)}'s" if others else ""
            raise ConfigError(f"inference.{unknown[0]}: not a setting of {self.METHOD} models{where} ({self.METHOD}'s: "
                              f"{', '.join(type(self.config.inference).changeable_keys())})")
        stored = [key for key in type(self.config.inference).STORED_KEYS if key in changes]
        if stored:
            raise ConfigError(f"inference.{stored[0]} is how the model's parameters were stored, not a setting "
                              "to change when it answers")
        data = self.config.model_dump()
        data["inference"] = {**data["inference"], **changes}
        config = type(self.config).validated(data)  # (the cross-section rules too: N-BVH's lod < cut.lods)
        owner = self.memory_owner
        if config.inference == owner.config.inference:
            return owner
        views = owner.__dict__.setdefault("_inference_views", {})
        key = json.dumps(config.inference.model_dump(mode="json"), sort_keys=True)
        if key not in views:
            view = copy.copy(owner)  # shares _parameters/_buffers/_modules: no bytes copied
            view.config = config
            object.__setattr__(view, "_view_of", owner)  # not nn.Module.__setattr__: a model is no submodule of its view
            views[key] = view
        return views[key]

    @property
    def memory_owner(self) -> "NeuralBLAS":
        """The model whose parameters this object uses (itself, unless it is a view of another)."""
        return self.__dict__.get("_view_of") or self

    # -- common properties -------------------------------------------------------------------------
    @property
    def box(self) -> AABB:
        """The region the model answers in (object space); training and held-out rays aim at it."""
        return self.bounds

    @property
    def material_names(self) -> list[str]:
        """Material slot names, in material-index order (the scene maps them to scene materials)."""
        return [m["name"] for m in self.materials]

    @property
    def num_materials(self) -> int:
        return len(self.materials)

    @property
    def secondary_offset(self) -> float:
        """Origin offset (object-space units, along the normal) for rays leaving a neural hit."""
        return float(self.config.inference.secondary_offset * self.box.diagonal)

    def to(self, *args, **kwargs):
        """``nn.Module.to``, with the device checked first: one line naming it where this process has
        no such device (torch's own is an AssertionError about how it was compiled)."""
        device = torch._C._nn._parse_to(*args, **kwargs)[0]
        if device is not None:
            check_device(device)
        return super().to(*args, **kwargs)

    def cuda(self, device=None):
        """``nn.Module.cuda`` through `to` (its one-line check where this process has no GPU)."""
        return self.to(torch.device("cuda", device) if isinstance(device, int) else device or "cuda")

    @property
    def device(self) -> torch.device:
        for tensor in self.buffers():
            return tensor.device
        return next(self.parameters()).device

    def compute_dtype(self, training: bool = False) -> torch.dtype:
        """Hidden-layer arithmetic for training or inference on the model's device (see `neuralrt.neural.precision`)."""
        section = self.config.training if training else self.config.inference
        return compute_dtype(section.compute_precision, self.device)

    def _remember_mesh(self, mesh) -> None:
        self.mesh_hash, self.mesh_name = mesh.content_hash(), mesh.name

    # -- inference -----------------------------------------------------------------------------------
    @torch.no_grad()
    def intersect(self, rays: Rays) -> Hits:
        """Closest hit per ray in object space: hit, t, normal (facing the ray, as trained: `Hits.normal`), albedo, material.

        ``rays`` must be on the model's device; hits come back on it. Rays with NaN/Inf origins or
        directions, zero directions or an empty ``[t_min, t_max]`` miss."""
        check_rays(rays, "intersect")
        self._check_device(rays)
        n = len(rays)
        chunk = self.rays_per_chunk(rays.device)
        if n <= chunk:
            return self._intersect_chunk(rays)
        out = self._chunk_records(n, rays.device)
        for start in range(0, n, chunk):
            part = rays[slice(start, start + chunk)]
            self._intersect_chunk_into(part, out[start:start + len(part)])
        return out

    def _chunk_records(self, n: int, device: torch.device) -> Hits:
        """Records for ``n`` rays that `_intersect_chunk_into` writes into: all misses (`Hits.empty`);
        a method whose pass writes every row, misses included, returns `Hits.uninitialized` (no fill)."""
        return Hits.empty(n, device)

    def rays_per_chunk(self, device: torch.device) -> int:
        """Rays answered at a time on ``device``: ``inference.chunk_size`` (a method may take more where that pays)."""
        return self.config.inference.chunk_size

    def _intersect_chunk_into(self, rays: Rays, hits: Hits) -> None:
        """`_intersect_chunk`'s answers written into ``hits`` (`_chunk_records`' rows for these rays,
        views of a larger batch's). Default: computed, then copied; a method whose pass writes records
        in place overrides it (no per-chunk records, no copy)."""
        hits.scatter_(slice(None), self._intersect_chunk(rays))

    @torch.no_grad()
    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: the model predicts a hit within [t_min, t_max] (same decision as `intersect`)."""
        check_rays(rays, "occluded")
        return self.intersect(rays).hit

    def _check_device(self, rays: Rays) -> None:
        check_rays(rays, "rays")  # (a method's own entry points call only this)
        if rays.device != self.device:
            raise DeviceError(f"rays are on {rays.device} but the {self.TITLE} model is on {self.device}: move one with .to()")

    # -- precision and memory ---------------------------------------------------------------------------
    @property
    def storage_bytes(self) -> int:
        """Bytes per stored parameter (``inference.storage_precision``)."""
        return STORAGE_BYTES[self.config.inference.storage_precision]

    def parameter_bytes(self, module: nn.Module) -> int:
        """Bytes of ``module``'s parameters at the storage precision."""
        return sum(p.numel() for p in module.parameters()) * self.storage_bytes

    def round_to_storage_precision_(self) -> "NeuralBLAS":
        """Round parameters to the stored precision in place, so the model in memory answers exactly as its file."""
        dt = STORAGE_DTYPES[self.config.inference.storage_precision]
        with torch.no_grad():
            for p in self.parameters():
                p.copy_(p.to(dt).float())
        return self

    def _stored(self, named: dict[str, nn.Parameter]) -> dict[str, Tensor]:
        """``named`` parameters as CPU tensors at the storage precision (for `_arrays`)."""
        dt = STORAGE_DTYPES[self.config.inference.storage_precision]
        return {k: p.detach().cpu().to(dt) for k, p in named.items()}

    @staticmethod
    def _load_parameters(named: dict[str, nn.Parameter], arrays: dict[str, Tensor]) -> None:
        """Copy file arrays into ``named`` parameters, checking presence and shape."""
        with torch.no_grad():
            for key, p in named.items():
                if key not in arrays:
                    raise ValueError(f"array '{key}' missing")
                if tuple(arrays[key].shape) != tuple(p.shape):
                    raise ValueError(f"array '{key}' has shape {tuple(arrays[key].shape)}, expected {tuple(p.shape)}")
                p.copy_(arrays[key].float())

    # -- files ----------------------------------------------------------------------------------------
    def header(self) -> ModelHeader:
        """The typed header of this model's file (nothing derivable is stored)."""
        return ModelHeader(
            method=self.METHOD, config=self.config.model_dump(mode="json"), bounds=self.bounds.tolist(),
            materials=self.materials, training=self.training_record, mesh_sha256=self.mesh_hash, mesh_name=self.mesh_name,
        )

    def save(self, path: str | os.PathLike) -> Path:
        """Write the model to ``path``, atomically. ``path`` must end in ``.nrt`` (`neuralrt info` and
        scene files tell models by it) and its folder must take files: else a one-line `ConfigError`
        / `NeuralRTError` before anything is written."""
        path = check_path("path", path)
        check_model_path(path)
        check_output_file(path, "model file")
        arrays = self._arrays()
        beyond = next((name for name, a in sorted(arrays.items()) if a.is_floating_point() and not torch.isfinite(a).all()), None)
        if beyond is not None:  # (a file no command could load: say so here, and write nothing)
            raise TrainingError(f"{path}: the model cannot be stored: its {beyond} holds NaN or infinite values as "
                                f"{str(arrays[beyond].dtype).removeprefix('torch.')} (weights past the storage's range: "
                                f"training diverged; a lower training.learning_rate or encoding.init_scale keeps them in range)")
        return write_model(path, self.header(), arrays)

    @classmethod
    def load(cls, path: str | os.PathLike, device: str | torch.device = "cpu") -> "NeuralBLAS":
        """Load a model file; bad, truncated, corrupted, newer or other-method files raise `ModelFileError`,
        a ``path`` that is no path `ConfigError`, a device this process cannot use `DeviceError`."""
        path, device = check_path("path", path), check_device(device)  # before the file is read
        check_not_forked("load_model")  # (loading runs parallel regions: a forked child would hang there)
        header, arrays = read_model(path, method=cls.METHOD)
        try:
            config = cls.CONFIG.model_validate(header.config)
        except ValidationError as exc:
            raise ModelFileError(f"{path}: invalid {cls.TITLE} config in the model header ({validation_message(exc)[:300]})") from None
        try:
            bounds = AABB(torch.tensor(header.bounds[0], dtype=torch.float32), torch.tensor(header.bounds[1], dtype=torch.float32))
            problem = _bounds_problem(bounds)
            if problem:  # (an edited file: a model of no extent answers nothing, and a scene of it divides by zero)
                raise ModelFileError(f"{path}: invalid {cls.TITLE} model ({problem})")
            problem = _declared_parameters_problem(cls, config, len(header.materials), arrays)
            if problem:  # (before building: a small file's config may ask for gigabytes of layers)
                raise ModelFileError(f"{path}: invalid {cls.TITLE} model ({problem})")
            model = cls._from_arrays(config, bounds, [m.model_dump() for m in header.materials], arrays)
            problem = _stored_arrays_problem(arrays, model._arrays())
        except ModelFileError:
            raise
        except Exception as exc:  # invalid config value, missing array, wrong array shape
            msg = str(exc).replace("\n", " ")
            raise ModelFileError(f"{path}: invalid {cls.TITLE} model ({type(exc).__name__}: {msg[:300]})") from None
        if problem:
            raise ModelFileError(f"{path}: invalid {cls.TITLE} model ({problem})")
        model.training_record = dict(header.training)
        model.mesh_hash, model.mesh_name = header.mesh_sha256, header.mesh_name
        return model.to(device).eval()
