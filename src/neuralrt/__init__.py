"""neuralrt: neural ray intersection (NIF, N-BVH, LSNIF) beside exact Embree ray tracing."""

import os

# The one place neuralrt sets how OpenMP threads wait (tests and benchmarks import neuralrt before
# torch to get it). torch's and numba's parallel regions alternate in every training step and
# inference batch, on one runtime: torch loads its libgomp into the global symbol scope, and
# numba's OpenMP layer binds to it (LD_DEBUG=bindings; the system's copy is mapped, unused). After
# a region its threads spin GOMP_SPINCOUNT=30000 times (~0.5-1 ms) before they sleep: long enough
# to bridge most gaps between regions (a sleeping thread took ~25-35 us to wake on a 2-core VM).
# Bunny `hq` training, 2-core Zen 4, drawn in turn: 1.07-1.19x the rays/s of 3,000 spins (medians
# of 5-6 alternating runs; 20 of 21 pairs faster); 10,000: 1.03-1.04x; longer spins no faster
# (100,000 or libgomp's default 300,000: 0.97-1.00x, when Embree still ran on Python threads that
# the spinning ones competed with) (docs/lsnif.md, session 44). Sleeping at once
# (OMP_WAIT_POLICY=PASSIVE) makes every torch GEMM wake its team at each of its regions (2 cores,
# session 36: an N-BVH intersect 1.3x the time).
# libgomp reads GOMP_SPINCOUNT only where OMP_WAIT_POLICY is unset; LLVM's and Intel's runtimes
# (macOS, some builds) read KMP_BLOCKTIME instead: 0, sleep at once. This only takes effect if
# neuralrt is imported before torch loads OpenMP, and a value the user set (an OMP_WAIT_POLICY
# included) is never overridden.
if "OMP_WAIT_POLICY" not in os.environ:
    os.environ.setdefault("GOMP_SPINCOUNT", "30000")
    os.environ.setdefault("KMP_BLOCKTIME", "0")

from .errors import NeuralRTError
from .kernel_cache import choose_kernel_cache, guard_cache_writes

choose_kernel_cache()  # (before any kernel compiles: a read-only install with no home cached nowhere, and failed)
guard_cache_writes()  # (a full disk under the cache made every command on a cold cache fail)

__version__ = "0.1.0"

# Everything else loads on first use: ``import neuralrt`` stays cheap (the `neuralrt` command
# imports torch under its own Ctrl-C handling, `neuralrt.launch`), numba kernels and the training
# loop only when asked for.
_LAZY = {
    "AABB": ("neuralrt.rays", "AABB"),
    "BLAS": ("neuralrt.accel.blas", "BLAS"),
    "Hits": ("neuralrt.rays", "Hits"),
    "Mesh": ("neuralrt.geometry.mesh", "Mesh"),
    "MeshBLAS": ("neuralrt.accel.mesh_blas", "MeshBLAS"),
    "MemoryReport": ("neuralrt.accel.blas", "MemoryReport"),
    "Rays": ("neuralrt.rays", "Rays"),
    "Transform": ("neuralrt.rays", "Transform"),
    "face_forward": ("neuralrt.rays", "face_forward"),
    "load_mesh": ("neuralrt.geometry.mesh", "load_mesh"),
    "pinhole_rays": ("neuralrt.rays", "pinhole_rays"),
    "load_model": ("neuralrt.methods", "load_model"),
    "train": ("neuralrt.training.api", "train"),
    "is_neural": ("neuralrt.methods", "is_neural"),
    "get_method": ("neuralrt.methods", "get_method"),
    "method_names": ("neuralrt.methods", "method_names"),
    "NeuralBLAS": ("neuralrt.methods.base", "NeuralBLAS"),
    "LSNIFModel": ("neuralrt.methods.lsnif", "LSNIFModel"),
    "LSNIFBLAS": ("neuralrt.methods.lsnif", "LSNIFBLAS"),
    "LSNIFConfig": ("neuralrt.methods.lsnif_config", "LSNIFConfig"),
    "NBVHModel": ("neuralrt.methods.nbvh", "NBVHModel"),
    "NBVHConfig": ("neuralrt.methods.nbvh_config", "NBVHConfig"),
    "NIFConfig": ("neuralrt.methods.nif_config", "NIFConfig"),
    "load_scene": ("neuralrt.scene.loader", "load_scene"),
    "load_dict": ("neuralrt.scene.loader", "load_dict"),
    "scene_memory": ("neuralrt.scene.memory", "scene_memory"),
    # (not "render": that name is the neuralrt.render subpackage, which importing any of its modules binds)
    "render_scene": ("neuralrt.render.integrator", "render"),
}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        module, attr = _LAZY[name]
        return getattr(importlib.import_module(module), attr)
    raise AttributeError(f"module 'neuralrt' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})


__all__ = ["NeuralRTError", *_LAZY]
