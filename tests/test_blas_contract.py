"""The BLAS contract (`neuralrt.testing.CONTRACT_CHECKS`), checked the same way for exact `MeshBLAS` and
every registered neural method (each after a short training run), on every device of the `device` fixture.

A new method gets these tests by registering itself (`neuralrt.methods.register_method`); out of
tree, `neuralrt.testing.check_contract` runs the same checks (docs/methods.md).
"""

import pytest
import torch

from neuralrt.accel.mesh_blas import EmbreeMeshBLAS, MeshBLAS
from neuralrt.methods import method_names
from neuralrt.testing import CONTRACT_CHECKS, check_contract, contract_mesh, train_for_contract

KINDS = ["exact", *method_names()]


@pytest.fixture(scope="module")
def torus():
    return contract_mesh()


@pytest.fixture(scope="module")
def trained(torus):
    """kind -> BLAS on the CPU: the exact mesh, or a model of each method after a short run."""
    return {"exact": MeshBLAS(torus), **{name: train_for_contract(name, torus) for name in method_names()}}


@pytest.fixture(params=KINDS)
def blas(request, trained, torus, device):
    kind = request.param
    if kind == "exact":
        return MeshBLAS(torus, device=device)
    return trained[kind].to(device)


@pytest.mark.parametrize("check", CONTRACT_CHECKS)
def test_contract(check, blas, torus, device, tmp_path):
    CONTRACT_CHECKS[check].run_or_skip(blas, torus, device, tmp_path)


class _LateHits(EmbreeMeshBLAS):
    """Embree's BLAS that breaks one promise: it drops hits at exactly t_max."""

    def intersect(self, rays):
        h = super().intersect(rays)
        at_end = h.hit & (h.t >= rays.t_max)
        h.hit[at_end], h.t[at_end], h.material_id[at_end] = False, float("inf"), -1
        return h

    def occluded(self, rays):
        return self.intersect(rays).hit


def test_check_contract_runs_every_check_and_names_the_broken_one(torus, tmp_path):
    assert check_contract(MeshBLAS(torus), torus) == [n for n, c in CONTRACT_CHECKS.items() if c.applies(MeshBLAS(torus), torch.device("cpu"))]
    with pytest.raises(AssertionError, match="contract check interval_is_respected: t_max set to a hit's own t"):
        check_contract(_LateHits(torus), torus, tmp_dir=tmp_path)
