"""Shared fixtures: seeded RNGs, the shared meshes folder, a device fixture (cpu, and cuda when present)."""

from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numpy as np
import pytest
import torch

SHARED_MESHES = Path(__file__).resolve().parents[1].parent / "shared" / "meshes"

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)


@pytest.fixture
def shared_mesh():
    """Path of a mesh in ../shared/meshes, or skip when the folder is absent."""

    def get(name: str) -> Path:
        path = SHARED_MESHES / name
        if not path.is_file():
            pytest.skip(f"{path} not available")
        return path

    return get
