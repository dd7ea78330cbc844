"""Dense spherical feature grids (NIF's encodings): coordinates, bilinear interpolation, the azimuth
wrap, pole clamping, per-object tables and their gradients, on every device present."""

import math

import pytest
import torch

from neuralrt.neural.dense_grid import DenseGrid1D, SphericalGrid2D, spherical_coords


def test_spherical_coords_of_the_axes():
    v = torch.tensor([[0, 1, 0], [0, -1, 0], [1, 0, 0], [0, 0, 1], [0, 0, -1], [0, 0, 0]], dtype=torch.float32)
    uv = spherical_coords(v * 3.0)  # length does not matter
    assert uv[0, 0] == pytest.approx(0.0) and uv[1, 0] == pytest.approx(1.0)  # poles
    assert uv[2].tolist() == pytest.approx([0.5, 0.5])  # +x: phi = 0
    assert uv[3].tolist() == pytest.approx([0.5, 0.75])  # +z: phi = pi/2
    assert uv[4].tolist() == pytest.approx([0.5, 0.25])
    assert torch.isfinite(uv[5]).all()  # the zero vector maps somewhere finite


def _grid(device, objects=2, r=8, n=3):
    g = torch.Generator().manual_seed(0)
    grid = SphericalGrid2D(objects, r, n, init_scale=1.0, generator=g).to(device)
    return grid


def test_vertices_return_their_values_and_between_them_bilinear(device):
    grid = _grid(device)
    r = grid.resolution
    table = grid.table.detach().reshape(2, r, r, -1)
    obj = torch.tensor([1, 1, 0], device=device)
    # Vertex (row i, column j) sits at u = i / (R - 1), v = j / R.
    uv = torch.tensor([[2 / (r - 1), 3 / r], [0.0, 5 / r], [1.0, 0.0]], device=device)
    out = grid(obj, uv).detach()
    assert torch.allclose(out[0], table[1, 2, 3], atol=1e-6)
    assert torch.allclose(out[1], table[1, 0, 5], atol=1e-6)
    assert torch.allclose(out[2], table[0, r - 1, 0], atol=1e-6)
    # Half-way between four vertices: their mean.
    mid = grid(torch.tensor([1], device=device), torch.tensor([[2.5 / (r - 1), 3.5 / r]], device=device)).detach()[0]
    assert torch.allclose(mid, table[1, 2:4, 3:5].reshape(4, -1).mean(0), atol=1e-6)


def test_azimuth_wraps_without_a_seam_and_poles_clamp(device):
    grid = _grid(device)
    obj = torch.zeros(5, dtype=torch.long, device=device)
    u = 0.37
    uv = torch.tensor([[u, 0.0], [u, 1.0], [u, 1.0 - 1e-6], [u, 1e-6], [u, 2.0]], device=device)
    out = grid(obj, uv).detach()
    assert torch.allclose(out[0], out[1], atol=1e-5)  # phi = -pi and +pi are the same direction
    assert torch.allclose(out[2], out[0], atol=1e-4) and torch.allclose(out[3], out[0], atol=1e-4)  # continuous across
    assert torch.allclose(out[4], out[0], atol=1e-5)
    # Between the last column and column 0 the grid interpolates the two (periodic, not clamped).
    r = grid.resolution
    table = grid.table.detach().reshape(2, r, r, -1)
    between = grid(obj[:1], torch.tensor([[0.0, (r - 0.5) / r]], device=device)).detach()[0]
    assert torch.allclose(between, 0.5 * (table[0, 0, r - 1] + table[0, 0, 0]), atol=1e-6)
    # Beyond the poles: the pole's values.
    poles = grid(obj[:4], torch.tensor([[-0.3, 0.2], [0.0, 0.2], [1.4, 0.2], [1.0, 0.2]], device=device)).detach()
    assert torch.allclose(poles[0], poles[1]) and torch.allclose(poles[2], poles[3])


def test_gradients_reach_the_four_vertices_of_the_queried_object_only(device):
    grid = _grid(device)
    out = grid(torch.tensor([1], device=device), torch.tensor([[0.3, 0.6]], device=device))
    out.sum().backward()
    grad = grid.table.grad.reshape(2, grid.resolution, grid.resolution, -1)
    assert grad[0].abs().sum() == 0  # object 0 untouched
    touched = (grad[1].abs().sum(-1) > 0).sum()
    assert int(touched) == 4
    assert grad[1].sum().item() == pytest.approx(3.0, abs=1e-5)  # bilinear weights sum to 1, per feature


def test_one_dimensional_grid_interpolates_and_clamps(device):
    g = torch.Generator().manual_seed(1)
    grid = DenseGrid1D(3, 5, 2, init_scale=1.0, generator=g).to(device)
    table = grid.table.detach().reshape(3, 5, 2)
    obj = torch.tensor([2, 2, 2, 0], device=device)
    out = grid(obj, torch.tensor([0.25, 0.375, 1.5, -1.0], device=device)).detach()
    assert torch.allclose(out[0], table[2, 1], atol=1e-6)
    assert torch.allclose(out[1], 0.5 * (table[2, 1] + table[2, 2]), atol=1e-6)
    assert torch.allclose(out[2], table[2, 4], atol=1e-6)
    assert torch.allclose(out[3], table[0, 0], atol=1e-6)


def test_init_is_seeded_and_small():
    a = SphericalGrid2D(1, 16, 3, generator=torch.Generator().manual_seed(5))
    b = SphericalGrid2D(1, 16, 3, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a.table, b.table)
    assert a.table.abs().max() <= 1e-4 and a.table.abs().max() > 0
    with pytest.raises(ValueError):
        SphericalGrid2D(0, 16, 3)
    assert a.memory_bytes(2) == 16 * 16 * 3 * 2
    assert math.isclose(DenseGrid1D(1, 128, 3).memory_bytes(4), 128 * 3 * 4)
