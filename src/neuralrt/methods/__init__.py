"""Neural intersection methods. `load_model` opens any `.nrt` model file as a `BLAS`."""

from __future__ import annotations

import os

import torch

from ..accel.blas import BLAS
from ..errors import ModelFileError
from ..io.model_file import read_header

__all__ = ["load_model", "MODEL_LOADERS"]


def _load_lsnif(path, device):
    from .lsnif import LSNIFModel

    return LSNIFModel.load(path, device=device)


# method name in the file header -> loader(path, device) returning a BLAS
MODEL_LOADERS = {"lsnif": _load_lsnif}


def load_model(path: str | os.PathLike, device: str | torch.device = "cpu") -> BLAS:
    """Open a model file of any method as its BLAS (intersect/occluded in object space)."""
    method = read_header(path)["method"]
    if method not in MODEL_LOADERS:
        known = ", ".join(sorted(MODEL_LOADERS))
        raise ModelFileError(f"{path}: method '{method}' is not a loadable model (this neuralrt reads: {known})")
    return MODEL_LOADERS[method](path, device)
