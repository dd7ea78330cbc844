"""Neural intersection methods, registered by name. `load_model` opens any `.nrt` model file as a `BLAS`.

Adding a method: write ``methods/NAME.py`` (a `MethodConfig` subclass with presets and a
`NeuralBLAS` subclass) and register it below with one `register_method` call; or keep it in a
module of your own, loaded as a plugin (`registry.load_plugins`; docs/methods.md).
"""

from __future__ import annotations

import os

import torch

from ..devices import check_device, check_path
from ..errors import ModelFileError
from ..io.model_file import read_header
from .base import MeshMismatchWarning, NeuralBLAS, check_mesh_match, is_neural
from .config import MethodConfig
from .lsnif_config import LSNIFConfig
from .nbvh_config import NBVHConfig
from .registry import DEFAULT_METHOD, HOW_TO_REGISTER, MethodSpec, config_from_dict, get_method, method_names, register_method

__all__ = [
    "load_model", "NeuralBLAS", "MethodConfig", "MethodSpec", "register_method", "get_method", "method_names",
    "config_from_dict", "is_neural", "check_mesh_match", "MeshMismatchWarning", "DEFAULT_METHOD",
]

register_method(MethodSpec(
    name="lsnif", config_class=LSNIFConfig, model="neuralrt.methods.lsnif:LSNIFModel",
    summary="LSNIF (Fujieda et al. 2025): voxels + sparse hash grid + MLP, all ray types",
    default_presets={"cuda": "gpu", "*": "hq"},
))
register_method(MethodSpec(
    name="nbvh", config_class=NBVHConfig, model="neuralrt.methods.nbvh:NBVHModel",
    summary="N-BVH (Weier et al. 2024): BVH cut + hash grid + MLP over leaf chords, all ray types",
    default_presets={"cuda": "paper", "*": "cpu"},
))


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu") -> NeuralBLAS:
    """Open a model file of any registered method as its BLAS.

    Args:
        path: a ``.nrt`` file written by ``model.save`` (any format version this neuralrt reads).
        device: where the model's tensors live, e.g. ``"cpu"`` or ``"cuda"``.

    Returns:
        A `NeuralBLAS` (e.g. `LSNIFModel`), in eval mode. ``intersect(rays)`` takes `Rays` on
        ``device`` in the object space of the mesh it was trained on (origins and directions
        float32 ``[N, 3]``, directions not necessarily unit) and returns `Hits` on ``device``
        (``t`` in units of the direction's length, normals facing the ray); ``occluded(rays)``
        returns ``[N]`` bool. Rays on another device raise a one-line `DeviceError`.

    Missing, truncated, corrupted, newer-version or unknown-method files raise `ModelFileError`
    with one line; a ``path`` that is no path `ConfigError`, a device this process cannot use
    (``cuda`` on a CPU-only torch) `DeviceError`."""
    path, device = check_path("path", path), check_device(device)  # before the file is read
    method = read_header(path)["method"]
    from ..training.trainer import CHECKPOINT_METHOD

    if method == CHECKPOINT_METHOD:
        raise ModelFileError(f"{path}: a training checkpoint, not a model file: continue its run to the model with "
                             "`neuralrt train MESH -o MODEL --resume`")
    if method not in method_names():
        raise ModelFileError(f"{path}: method '{method}' is not registered in this neuralrt (registered: "
                             f"{', '.join(method_names())}); {HOW_TO_REGISTER}")
    return get_method(method).model_class.load(path, device=device)
