"""The exact-BLAS backends present on this machine, for tests that run against each of them."""

import pytest
import torch

from neuralrt import MeshBLAS
from neuralrt.accel.mesh_blas import EmbreeMeshBLAS
from neuralrt.accel.mesh_blas_mitsuba import MitsubaMeshBLAS, mitsuba_variant_available

# (id, device, class): Embree on the CPU always; Mitsuba's LLVM variant on the CPU where Dr.Jit finds
# an LLVM library; on CUDA, whatever MeshBLAS(mesh, device="cuda") chooses (OptiX through Mitsuba).
EXACT_BACKENDS = [("embree-cpu", "cpu", EmbreeMeshBLAS)]
if mitsuba_variant_available("cpu"):
    EXACT_BACKENDS.append(("mitsuba-cpu", "cpu", MitsubaMeshBLAS))
if torch.cuda.is_available():
    EXACT_BACKENDS.append(("cuda", "cuda", MeshBLAS))


def backend_params():
    return [pytest.param((device, cls), id=name) for name, device, cls in EXACT_BACKENDS]


def other_backends():
    """Every backend but the CPU Embree reference."""
    return [pytest.param((device, cls), id=name) for name, device, cls in EXACT_BACKENDS[1:]]
