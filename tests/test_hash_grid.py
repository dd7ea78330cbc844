"""Multiresolution hash grid: layout and memory as N-BVH's, numba and torch against the slow reference and each other."""

import numpy as np
import pytest
import torch

from neuralrt.neural.hash_grid import HashGrid, HashGridLayout, hash_grid_reference, hash_grid_torch


def test_layout_is_dense_where_a_level_fits_and_matches_the_papers_memory():
    lay = HashGridLayout.create(8, 8, 18)
    assert lay.resolutions == (8, 16, 32, 64, 128, 256, 512, 1024)
    assert lay.dense == (True, True, True, True, False, False, False, False)  # 64^3 = 2^18 still fits
    # METHODS-SPEC A5: 2^18 -> 10.78 MB and 2^16 -> 2.92 MB at 4 fp16 features per row.
    assert lay.rows * 4 * 2 == pytest.approx(10.78e6, rel=1e-3)
    assert HashGridLayout.create(8, 8, 16).rows * 8 == pytest.approx(2.92e6, rel=2e-3)
    assert lay.offsets[1] == 512 and lay.offsets[-1] + lay.sizes[-1] == lay.rows


def _points(n, p, seed):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, p, 3, generator=g) * 1.2 - 0.1  # some outside the cube: clamped
    pts[0, 0] = torch.tensor([1.0, 1.0, 1.0])  # the far corner (clamped vertex index)
    pts[0, 1] = torch.tensor([0.0, 0.0, 0.0])
    return pts


@pytest.mark.parametrize("features", [3, 4])  # 4: the forward's register path (N-BVH's)
@pytest.mark.parametrize("log2_table", [9, 14])
def test_numba_and_torch_match_the_reference(log2_table, features):
    grid = HashGrid(levels=5, base_resolution=4, features_per_level=features, log2_table_size=log2_table, init_scale=1.0, seed=3)
    pts = _points(43, 3, 1)  # (groups of 8 rays and a shorter last one)
    ref = hash_grid_reference(pts.numpy(), grid.table.detach().numpy(), grid.layout)
    numba_out = grid(pts).detach().numpy()
    torch_out = hash_grid_torch(pts, grid.table, grid.layout).detach().numpy()
    assert numba_out.shape == (43, 3 * 5 * features)
    assert np.abs(numba_out - ref).max() < 1e-5
    assert np.abs(torch_out - ref).max() < 1e-5


@pytest.mark.parametrize("features", [4, 2])  # 4: a row per vector (`add_rows4`); others: the scalar adds
def test_backward_matches_torch_autograd(features):
    """The numba backward (groups of rays, rows found before any is added to; several threads'
    tables summed) against torch's autograd of the same encoding, over 300 rays (not a multiple
    of the group) on dense and hashed levels."""
    grid = HashGrid(levels=8, base_resolution=8, features_per_level=features, log2_table_size=12, init_scale=1.0, seed=0)
    pts = _points(300, 3, 2)
    weights = torch.randn(300, grid.output_dim(3), generator=torch.Generator().manual_seed(5))
    (grid(pts) * weights).sum().backward()
    numba_grad = grid.table.grad.clone()
    table = grid.table.detach().clone().requires_grad_(True)
    (hash_grid_torch(pts, table, grid.layout) * weights).sum().backward()
    assert numba_grad.abs().sum() > 0
    assert torch.allclose(numba_grad, table.grad, atol=1e-4, rtol=1e-4)


def test_encoding_is_continuous_and_seeded():
    a, b = HashGrid(log2_table_size=12, seed=7), HashGrid(log2_table_size=12, seed=7)
    assert torch.equal(a.table, b.table) and a.table.abs().max() <= 1e-4
    x = torch.tensor([[[0.3, 0.4, 0.5]], [[0.3 + 1e-6, 0.4, 0.5]]])
    with torch.no_grad():
        out = HashGrid(log2_table_size=12, init_scale=1.0, seed=1)(x)
    assert (out[0] - out[1]).abs().max() < 1e-2  # trilinear: tiny moves, tiny changes
    assert (out[0]).abs().max() > 1e-3


def test_empty_batch_and_bad_shape():
    grid = HashGrid(log2_table_size=10)
    assert grid(torch.zeros(0, 3, 3)).shape == (0, 96)
    with pytest.raises(ValueError, match="points"):
        grid(torch.zeros(4, 3))
