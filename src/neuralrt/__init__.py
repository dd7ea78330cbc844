"""neuralrt: neural ray intersection (NIF, N-BVH, LSNIF) beside exact Embree ray tracing."""

import os

# The one place neuralrt sets OMP_WAIT_POLICY (tests and benchmarks import neuralrt before torch to
# get it). torch's and numba's OpenMP pools alternate in every training step and inference batch;
# with libgomp's default spin-waiting each pool burns the cores the other needs (measured on 2
# cores: 147k -> 230k training rays/s). It only takes effect if neuralrt is imported before torch
# loads OpenMP, and a value the user set is never overridden.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .accel.blas import BLAS, MemoryReport
from .accel.mesh_blas import MeshBLAS
from .errors import NeuralRTError
from .geometry.mesh import Mesh, load_mesh
from .rays import AABB, Hits, Rays, Transform, face_forward, pinhole_rays

__version__ = "0.1.0"

# Heavier parts (numba kernels, the training loop) load on first use.
_LAZY = {
    "load_model": ("neuralrt.methods", "load_model"),
    "train": ("neuralrt.training.api", "train"),
    "is_neural": ("neuralrt.methods", "is_neural"),
    "get_method": ("neuralrt.methods", "get_method"),
    "method_names": ("neuralrt.methods", "method_names"),
    "NeuralBLAS": ("neuralrt.methods.base", "NeuralBLAS"),
    "LSNIFModel": ("neuralrt.methods.lsnif", "LSNIFModel"),
    "LSNIFBLAS": ("neuralrt.methods.lsnif", "LSNIFBLAS"),
    "LSNIFConfig": ("neuralrt.methods.lsnif_config", "LSNIFConfig"),
    "load_scene": ("neuralrt.scene.loader", "load_scene"),
    "load_dict": ("neuralrt.scene.loader", "load_dict"),
    "scene_memory": ("neuralrt.scene.memory", "scene_memory"),
    "render": ("neuralrt.render.integrator", "render"),
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'neuralrt' has no attribute {name!r}")


__all__ = ["AABB", "BLAS", "Hits", "Mesh", "MeshBLAS", "MemoryReport", "NeuralRTError", "Rays", "Transform",
           "face_forward", "load_mesh", "pinhole_rays", *_LAZY]
