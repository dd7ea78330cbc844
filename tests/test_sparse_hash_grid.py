"""Sparse hash grid: exact interpolation on faces, numba kernels against the torch reference."""

import numpy as np
import pytest
import torch

from neuralrt.neural import sparse_hash_grid  # (its HALF_READS)
from neuralrt.methods.lsnif_features import featurize_rays
from neuralrt.neural.sparse_hash_grid import (
    HASH_PRIMES,
    SparseHashGrid,
    check_resolutions,
    count_stored_entries,
    sparse_hash_grid_reference,
)


def _slot(v: np.ndarray, table_size: int) -> np.ndarray:
    v = v.astype(np.int64)
    return (v[..., 0] * HASH_PRIMES[0] ^ v[..., 1] * HASH_PRIMES[1] ^ v[..., 2] * HASH_PRIMES[2]) & (
        table_size - 1
    )


def _featurized_points(n=3000, res=16, max_points=12, seed=0):
    rng = np.random.default_rng(seed)
    occ = rng.uniform(size=(res,) * 3) < 0.2
    o = np.concatenate([rng.normal(size=(n // 2, 3)) * 1.5 + 0.5, rng.uniform(size=(n - n // 2, 3))])
    d = rng.normal(size=(n, 3))
    f = featurize_rays(torch.tensor(o, dtype=torch.float32), torch.tensor(d, dtype=torch.float32), occ, max_points)
    assert (f.face_axis == 3).any() and (f.face_axis == -1).any() and (f.face_axis == 0).any()
    return f


def test_bilinear_on_a_face_reproduces_a_linear_function():
    grid = SparseHashGrid(resolutions=(64, 128), log2_table_size=17)
    table = torch.randn_like(grid.table) * 100  # garbage everywhere, including off-plane vertices
    rng = np.random.default_rng(0)
    slope = rng.normal(size=(2, 3, 3))  # [level, feature, xyz]
    offset = rng.normal(size=(2, 3))
    n = 500
    pts = np.empty((3, n, 3))
    for axis in range(3):
        # points on the voxel plane (axis) = 13/32, inside a small patch of the other two coordinates
        pts[axis] = rng.uniform(0.40, 0.45, (n, 3))
        pts[axis, :, axis] = 13 / 32
    points = torch.tensor(pts, dtype=torch.float32).reshape(1, 3 * n, 3).repeat(1, 1, 1)
    face_axis = torch.arange(3).repeat_interleave(n)[None].to(torch.int8)
    for lvl, res in enumerate(grid.resolutions):
        for axis in range(3):
            # all vertices of the face cells that the patch touches, on the plane only
            lo, hi = int(0.40 * res), int(0.45 * res) + 1
            g = np.stack(np.meshgrid(*[np.arange(lo, hi + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
            g[:, axis] = 13 * res // 32
            g = np.unique(g, axis=0)
            slots = _slot(g, table.shape[1])
            assert len(np.unique(slots)) == len(g)  # no collisions inside the patch
            table[lvl, slots] = torch.tensor(g / res @ slope[lvl].T + offset[lvl], dtype=torch.float32)
    with torch.no_grad():
        grid.table.copy_(table)
        out = grid(points, face_axis).reshape(3 * n, 2, 3)
        ref = sparse_hash_grid_reference(points, face_axis, grid.table, grid.resolutions).reshape(3 * n, 2, 3)
    expected = np.einsum("nc,lfc->nlf", points[0].double().numpy(), slope) + offset
    np.testing.assert_allclose(out.numpy(), expected, atol=2e-5)
    np.testing.assert_allclose(ref.numpy(), expected, atol=2e-5)


def test_trilinear_origin_points_reproduce_a_linear_function():
    grid = SparseHashGrid(resolutions=(32,), log2_table_size=20, features_per_level=1)
    rng = np.random.default_rng(1)
    slope, offset = rng.normal(size=3), 0.25
    g = np.stack(np.meshgrid(*[np.arange(10, 16)] * 3, indexing="ij"), -1).reshape(-1, 3)
    slots = _slot(g, 2**20)
    assert len(np.unique(slots)) == len(g)
    with torch.no_grad():
        grid.table[0, slots, 0] = torch.tensor(g / 32 @ slope + offset, dtype=torch.float32)
    p = 10 / 32 + torch.rand(1, 400, 3) * 5 / 32
    out = grid(p, torch.full((1, 400), 3, dtype=torch.int8))
    np.testing.assert_allclose(out[0].detach().numpy(), p[0].double().numpy() @ slope + offset, atol=2e-5)


def test_kernel_forward_and_backward_match_reference():
    f = _featurized_points()
    grid = SparseHashGrid(resolutions=(32, 64), log2_table_size=12, init_scale=1.0)  # collisions too
    out = grid(f.points, f.face_axis)
    ref = sparse_hash_grid_reference(f.points, f.face_axis, grid.table, grid.resolutions)
    assert out.shape == (len(f), grid.output_dim(12)) == ref.shape
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
    upstream = torch.randn_like(out)
    (g_kernel,) = torch.autograd.grad((out * upstream).sum(), grid.table)
    (g_ref,) = torch.autograd.grad((ref * upstream).sum(), grid.table)
    assert g_kernel.abs().sum() > 0
    torch.testing.assert_close(g_kernel, g_ref, atol=1e-4, rtol=1e-4)


def test_layout_padding_and_face_vertex_count():
    grid = SparseHashGrid(resolutions=(64, 128), init_scale=1.0)
    points = torch.tensor([[[0.25, 0.3, 0.7], [0.1, 0.5, 0.2], [0.0, 0.0, 0.0]]])
    face_axis = torch.tensor([[0, 1, -1]], dtype=torch.int8)
    out = grid(points, face_axis).reshape(3, 2, 3)  # point-major, then level, then feature
    assert (out[2] == 0).all() and (out[:2] != 0).all()
    single = grid(points[:, 1:2], face_axis[:, 1:2]).reshape(2, 3)
    torch.testing.assert_close(out[1], single)
    # a face point reads exactly 4 table entries per level
    (g,) = torch.autograd.grad(grid(points[:, :1], face_axis[:, :1]).sum(), grid.table)
    assert ((g != 0).any(-1).sum(-1) == 4).all()


def test_training_step_changes_only_touched_entries():
    f = _featurized_points(n=200)
    grid = SparseHashGrid(resolutions=(32, 64), log2_table_size=14)
    before = grid.table.detach().clone()
    opt = torch.optim.SGD(grid.parameters(), lr=1.0)
    grid(f.points, f.face_axis).square().sum().backward()
    opt.step()
    changed = (grid.table.detach() != before).any(-1)
    assert 0 < changed.sum() < changed.numel()


def test_count_stored_entries_single_voxel():
    occ = np.zeros((32, 32, 32), bool)
    occ[3, 4, 5] = True
    report = count_stored_entries(occ, (64, 128))
    lv64, lv128 = report["levels"]
    assert (lv64["face_vertices"], lv64["interior_vertices"]) == (3**3 - 1, 1)
    assert (lv128["face_vertices"], lv128["interior_vertices"]) == (5**3 - 3**3, 3**3)
    assert lv64["dense_vertices"] == 65**3 and lv128["table_size"] == 2**17
    assert lv64["face_slots_used"] <= lv64["face_vertices"]
    assert lv128["dense_slots_used"] <= 2**17


def test_bad_configuration():
    with pytest.raises(ValueError, match="multiples"):
        check_resolutions((64, 100), 32)
    with pytest.raises(ValueError, match="multiples"):
        count_stored_entries(np.zeros((32,) * 3, bool), (48,))
    with pytest.raises(ValueError, match=r"\[N, H, 3\]"):
        SparseHashGrid()(torch.zeros(4, 3), torch.zeros(4, dtype=torch.int8))


def test_runs_on_device(device):
    f = _featurized_points(n=300).to(device)
    grid = SparseHashGrid(resolutions=(32, 64), log2_table_size=12, init_scale=1.0).to(device)
    out = grid(f.points, f.face_axis)
    assert out.device == f.points.device
    ref = sparse_hash_grid_reference(f.points.cpu(), f.face_axis.cpu(), grid.table.cpu(), grid.resolutions)
    torch.testing.assert_close(out.cpu(), ref, atol=1e-5, rtol=1e-5)


def test_row_range_backward_is_the_serial_scatter_bit_for_bit():
    """The row-owning backward (hashing the points again, or from the rows and weights the forward
    saved) gives the serial per-thread-table scatter's gradient exactly, for any number of row
    ranges per level (the thread count sets it), and is what autograd returns with each scatter."""
    from neuralrt.neural import sparse_hash_grid as shg

    f = _featurized_points(n=2500, seed=3)
    grid = SparseHashGrid(resolutions=(16, 32, 64), log2_table_size=12, seed=1)  # small table: many collisions
    upstream = torch.randn(len(f.points), grid.output_dim(f.points.shape[1]), generator=torch.Generator().manual_seed(2))
    args = (f.points.numpy(), f.face_axis.numpy(), upstream.numpy(), grid._resolutions_np)
    serial = np.zeros((1, 3 * 2**12, 3), np.float32)
    shg._backward_kernel(*args, serial)  # one chunk: rays in order
    for ranges in (1, 2, 5):
        got = np.full((3 * 2**12, 3), np.nan, np.float32)  # the kernel zeroes every row it owns
        shg._backward_rows_kernel(*args[:2], np.arange(len(f.points)), *args[2:], ranges, got)
        assert np.array_equal(got, serial[0]), ranges
    # The backward from the rows and weights the forward saved (face points; origin points hashed again).
    n, h = f.face_axis.shape
    valid = (f.face_axis >= 0).numpy()
    offsets = np.concatenate([[0], np.cumsum(valid.sum(1))])
    saved = np.full((3, offsets[-1], 4), -1, np.int32), np.full((3, offsets[-1], 4), np.nan, np.float32)
    flat = grid.table.detach().numpy().reshape(-1, 3)
    out = np.empty((n, grid.output_dim(h)), np.float32)
    every = np.arange(n, dtype=np.int64)
    shg._forward_kernel(f.points.numpy(), f.face_axis.numpy(), every, flat, shg.padded_table(grid.table), grid._resolutions_np, 7, 2,
                        np.empty((n, 0), np.float32), out, np.empty((0, out.shape[1]), np.uint16), offsets, *saved)  # fmt: skip
    face = f.face_axis.numpy()[valid] < 3  # packed in ray order: face points saved, origin points not
    assert (saved[0][:, face] >= 0).all() and (saved[0][:, ~face] == -1).all() and (~face).any()
    for ranges in (1, 2, 5):
        got = np.full((3 * 2**12, 3), np.nan, np.float32)
        shg._backward_saved_kernel(*args[:2], every, *args[2:], ranges, *saved, got)
        assert np.array_equal(got, serial[0]), ranges
    # Bucketed by row range (counted, then written, per chunk of rays): any ranges, any chunks.
    for ranges, chunks in ((1, 1), (2, 3), (5, 7), (7, 64)):
        got = np.full((3 * 2**12, 3), np.nan, np.float32)
        shg._backward_buckets_kernel(*args[:2], every, *args[2:], ranges, chunks, got)
        assert np.array_equal(got, serial[0]), (ranges, chunks)
    rehash = shg._backward_rows_kernel
    for scatter in ("saved_rows", "row_ranges", "buckets"):  # (thread_tables sums per-thread tables: not serial)
        grid.backward_scatter = scatter
        if scatter == "saved_rows":  # autograd must take the saved rows, not hash again
            shg._backward_rows_kernel = None
        try:
            (g_autograd,) = torch.autograd.grad((grid(f.points, f.face_axis) * upstream).sum(), grid.table)
        finally:
            shg._backward_rows_kernel = rehash
        assert torch.equal(g_autograd.reshape(-1, 3), torch.from_numpy(serial[0])), scatter
    assert (serial != 0).sum() > 1000


def test_extra_columns_are_appended_without_changing_the_gradient():
    f = _featurized_points(n=800, seed=4)
    grid = SparseHashGrid(resolutions=(16, 32), log2_table_size=12, init_scale=1.0)
    extra = torch.rand(len(f.points), 12, generator=torch.Generator().manual_seed(0))
    plain = grid(f.points, f.face_axis)
    joined = grid(f.points, f.face_axis, extra)
    assert torch.equal(joined, torch.cat([plain, extra], 1))
    upstream = torch.randn_like(joined)
    (g_joined,) = torch.autograd.grad((joined * upstream).sum(), grid.table)
    (g_plain,) = torch.autograd.grad((plain * upstream[:, : plain.shape[1]]).sum(), grid.table)
    assert torch.equal(g_joined, g_plain) and g_plain.abs().sum() > 0
    with pytest.raises(ValueError, match="extra columns"):
        grid(f.points, f.face_axis, extra[:-1])


@pytest.mark.parametrize("scatter", ["row_ranges", "thread_tables"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_out_rows_pad_the_output_with_zero_rows(dtype, scatter):
    """``out_rows``: the rays' rows (extra columns too) as without it, then zero rows; the rows past
    the rays' take no part in the table's gradient, whatever their upstream gradient."""
    f = _featurized_points(n=700, seed=9)
    grid = SparseHashGrid(resolutions=(16, 32), log2_table_size=12, init_scale=1.0)
    grid.backward_scatter = scatter
    rows = torch.arange(0, 700, 3)
    extra = torch.rand(len(rows), 5, generator=torch.Generator().manual_seed(3))
    plain = grid(f.points, f.face_axis, extra, dtype, rows=rows)
    padded = grid(f.points, f.face_axis, extra, dtype, rows=rows, out_rows=len(rows) + 45)
    assert padded.shape == (len(rows) + 45, plain.shape[1]) and padded.dtype == dtype
    assert torch.equal(padded[: len(rows)], plain) and (padded[len(rows):] == 0).all()
    upstream = torch.randn(padded.shape, generator=torch.Generator().manual_seed(4)).to(dtype)
    (g_padded,) = torch.autograd.grad((padded * upstream).sum(), grid.table)
    (g_plain,) = torch.autograd.grad((plain * upstream[: len(rows)]).sum(), grid.table)
    assert torch.equal(g_padded, g_plain) and g_plain.abs().sum() > 0
    # The torch path (other devices) pads the same way.
    ref = SparseHashGrid(resolutions=(16, 32), log2_table_size=12, init_scale=1.0).double()
    ref.table.data = grid.table.detach().double()
    assert torch.equal(ref(f.points, f.face_axis, out_rows=len(f.points) + 3)[-3:], torch.zeros(3, plain.shape[1] - 5, dtype=torch.float64))
    with pytest.raises(ValueError, match="out_rows"):
        grid(f.points, f.face_axis, rows=rows, out_rows=len(rows) - 1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_padding_slots_anywhere_encode_zeros(dtype):
    """The kernel writes the padding after a ray's last point as zeros at once; padding between
    points (not made by `featurize_rays`, but valid input) is encoded as zeros in place, and the
    points after it are still encoded, as the reference does."""
    grid = SparseHashGrid(resolutions=(64, 128), init_scale=1.0)
    points = torch.tensor([[[0.25, 0.3, 0.7], [0.1, 0.5, 0.2], [0.6, 0.45, 0.5], [0.0, 0.0, 0.0]],
                           [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
    face_axis = torch.tensor([[0, -1, 2, -1], [-1, -1, -1, -1]], dtype=torch.int8)
    out = grid(points, face_axis, dtype=dtype).float().reshape(2, 4, 2, 3)
    ref = sparse_hash_grid_reference(points, face_axis, grid.table, grid.resolutions).reshape(2, 4, 2, 3)
    tolerance = 1e-5 if dtype == torch.float32 else 1e-2  # the reference sums in another order; bf16 rounds
    torch.testing.assert_close(out, ref, atol=tolerance, rtol=tolerance)
    assert (out[0, [1, 3]] == 0).all() and (out[0, [0, 2]] != 0).all() and (out[1] == 0).all()


def test_bf16_output_is_the_cast_of_the_fp32_one_bit_for_bit():
    """``dtype=torch.bfloat16``: the CPU kernel's own rounding gives the bits of ``.to(torch.bfloat16)``
    of the fp32 features (extra columns too), and the backward, handed the bf16 gradient, gives the
    table gradient of its fp32 widening exactly."""
    f = _featurized_points(n=1500, seed=5)
    grid = SparseHashGrid(resolutions=(16, 32), log2_table_size=12, init_scale=1.0)
    extra = torch.rand(len(f.points), 12, generator=torch.Generator().manual_seed(1))
    fp32 = grid(f.points, f.face_axis, extra)
    low = grid(f.points, f.face_axis, extra, torch.bfloat16)
    assert low.dtype == torch.bfloat16 and low.shape == fp32.shape
    assert torch.equal(low.view(torch.int16), fp32.to(torch.bfloat16).view(torch.int16))
    # The rounding is real (almost every nonzero feature changes) and goes both ways in magnitude.
    nonzero = fp32 != 0
    assert (fp32 != low.float())[nonzero].float().mean() > 0.9
    grew = low.float().abs() > fp32.abs()
    assert 0.3 < grew[nonzero].float().mean() < 0.7
    upstream = torch.randn(fp32.shape, generator=torch.Generator().manual_seed(2)).to(torch.bfloat16)
    (g_low,) = torch.autograd.grad((low * upstream).sum(), grid.table)  # bf16 gradient into the backward
    (g_ref,) = torch.autograd.grad((fp32 * upstream.float()).sum(), grid.table)
    assert torch.equal(g_low, g_ref) and g_ref.abs().sum() > 0
    grid.low_precision_output = False  # the earlier path: fp32 features, then the cast
    assert torch.equal(grid(f.points, f.face_axis, extra, torch.bfloat16).view(torch.int16), low.view(torch.int16))


@pytest.mark.parametrize("scatter", ["saved_rows", "row_ranges", "thread_tables", "buckets"])
def test_rows_encode_the_selected_rays_as_their_copy_bit_for_bit(scatter):
    """``rows``: the kernels read the selected rays through the index; features (fp32 and bf16,
    extra columns too) and table gradients are those of the copied selection, bit for bit."""
    f = _featurized_points(n=2000, seed=6)
    grid = SparseHashGrid(resolutions=(16, 32), log2_table_size=12, init_scale=1.0)
    grid.backward_scatter = scatter
    rows = torch.nonzero(f.count > 0).squeeze(1)[torch.randperm(int((f.count > 0).sum()), generator=torch.Generator().manual_seed(0))][:900]
    extra = torch.rand(len(rows), 12, generator=torch.Generator().manual_seed(1))
    for dtype in (torch.float32, torch.bfloat16):
        copied = grid(f.points[rows], f.face_axis[rows], extra, dtype)
        indexed = grid(f.points, f.face_axis, extra, dtype, rows=rows)
        assert torch.equal(indexed, copied) and copied.abs().sum() > 0
        upstream = torch.randn(copied.shape, generator=torch.Generator().manual_seed(2)).to(dtype)
        (g_copied,) = torch.autograd.grad((copied * upstream).sum(), grid.table)
        (g_indexed,) = torch.autograd.grad((grid(f.points, f.face_axis, extra, dtype, rows=rows) * upstream).sum(), grid.table)
        assert torch.equal(g_indexed, g_copied) and g_copied.abs().sum() > 0
    reference = sparse_hash_grid_reference(f.points[rows], f.face_axis[rows], grid.table.detach(), grid.resolutions)
    torch.testing.assert_close(grid(f.points, f.face_axis, rows=rows).detach(), reference, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="rows"):
        grid(f.points, f.face_axis, rows=torch.tensor([len(f.points)]))


def test_auto_scatter_buckets_on_hosts_with_many_threads_per_level(monkeypatch):
    """``backward_scatter = "auto"`` (the default) takes the bucketed scatter from
    `BUCKETS_FROM_THREADS_PER_LEVEL` threads per level on, the row-range one below: same gradient."""
    from neuralrt.neural import sparse_hash_grid as shg

    f = _featurized_points(n=600, seed=7)
    grid = SparseHashGrid(resolutions=(16, 32), log2_table_size=12, init_scale=1.0)
    assert grid.backward_scatter == "auto"
    upstream = torch.randn(len(f.points), grid.output_dim(f.points.shape[1]), generator=torch.Generator().manual_seed(3))

    def table_grad():
        return torch.autograd.grad((grid(f.points, f.face_axis) * upstream).sum(), grid.table)[0]

    grid.backward_scatter = "row_ranges"
    expected = table_grad()
    grid.backward_scatter = "auto"
    monkeypatch.setattr(shg, "_backward_rows_kernel", None)  # the row-range scatter cannot run
    monkeypatch.setattr(shg, "BUCKETS_FROM_THREADS_PER_LEVEL", 0)  # any host has "many" threads
    assert torch.equal(table_grad(), expected) and expected.abs().sum() > 0
    monkeypatch.setattr(shg, "BUCKETS_FROM_THREADS_PER_LEVEL", 10**6)  # no host has: row ranges
    with pytest.raises(TypeError):
        table_grad()


def test_origin_rows_are_point_levels_rows_and_weights_bit_for_bit():
    """The branch-free `origin_rows` (structure of arrays, for the fused CPU pass) gives the rows
    and weights `_point_level` gives an origin point, in its order, including points on the box's
    faces and corners (clamped)."""
    import numba

    from neuralrt.neural.sparse_hash_grid import _ORIGIN_POINT, _point_level, origin_rows

    @numba.njit
    def both(points, res, mask, base):
        n = points.shape[0]
        slots, weights = np.empty((8, n), np.int64), np.empty((8, n), np.float32)
        ref_slots, ref_weights = np.empty((n, 8), np.int64), np.empty((n, 8), np.float32)
        for i in range(n):
            origin_rows(points[i, 0], points[i, 1], points[i, 2], res, mask, base, slots, weights, i)
            _point_level(points[i, 0], points[i, 1], points[i, 2], _ORIGIN_POINT, res, mask, base, ref_slots[i], ref_weights[i])
        return slots, weights, ref_slots, ref_weights

    rng = np.random.default_rng(5)
    points = np.concatenate([rng.random((500, 3)), [[0, 0, 0], [1, 1, 1], [1, 0, 0.5], [0.25, 0.5, 1]]]).astype(np.float32)
    for res in (16, 64):
        slots, weights, ref_slots, ref_weights = both(points, res, np.int64((1 << 12) - 1), np.int64(1 << 12))
        assert np.array_equal(slots, ref_slots.T) and np.array_equal(weights, ref_weights.T)
        assert np.allclose(weights.sum(0), 1.0, atol=1e-6)


def test_vector_row_reads_equal_the_scalar_reads_bit_for_bit():
    """`read_rows3` (a row per vector load, 4 or 8 rows) gives `read_rows`' bits, reads the
    table's last row (its fourth lane is the padding float) and writes nothing past 3 features."""
    import numba

    from neuralrt.neural.sparse_hash_grid import read_rows, read_rows3

    @numba.njit
    def both(table_flat, slots, weights, scalar, vector):
        table = table_flat[:-1].reshape(-1, 3)
        for i in range(slots.shape[0]):
            s, c = slots[i], weights[i]
            read_rows(table, s[:4], c[:4], 4, scalar[0], 3 * i)
            read_rows3(table_flat, (s[0], s[1], s[2], s[3]), (c[0], c[1], c[2], c[3]), vector[0], 3 * i)
            read_rows(table, s, c, 8, scalar[1], 3 * i)
            read_rows3(table_flat, (s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]), (c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]),
                       vector[1], 3 * i)  # fmt: skip

    rng = np.random.default_rng(8)
    rows = 5000
    table_flat = np.full(3 * rows + 1, np.nan, np.float32)  # the padding float must not reach an output
    table_flat[:-1] = rng.standard_normal(3 * rows) * 10.0 ** rng.integers(-4, 4, 3 * rows)
    slots = rng.integers(0, rows, (3000, 8)).astype(np.int32)
    slots[:5] = rows - 1
    weights = rng.random((3000, 8)).astype(np.float32)
    weights[5] = 0.0  # -0.0 products and a zero sum: 0 + (-0) is +0 in both
    table_flat[3 * slots[5]] = -1.0
    scalar = np.full((2, 3 * 3000 + 1), 7.0, np.float32)
    vector = scalar.copy()
    both(table_flat, slots, weights, scalar, vector)
    assert np.array_equal(scalar.view(np.uint32), vector.view(np.uint32))
    assert np.all(vector[:, -1] == 7.0) and np.isfinite(vector).all()


def test_rows_then_a_value_in_one_store_equal_the_reads_and_a_store():
    """`read_rows3_then` writes `read_rows3`'s 3 features and the value after them (the fused
    pass's point distance), from float32 and float16 tables, and nothing else."""
    import numba

    from neuralrt.neural.sparse_hash_grid import half_table, padded_table, read_rows3, read_rows3_then

    @numba.njit
    def both(table_flat, slots, weights, values, separate, together):
        for i in range(slots.shape[0]):
            s, c = slots[i], weights[i]
            read_rows3(table_flat, (s[0], s[1], s[2], s[3]), (c[0], c[1], c[2], c[3]), separate, 5 * i)
            separate[5 * i + 3] = values[i]
            read_rows3_then(table_flat, (s[0], s[1], s[2], s[3]), (c[0], c[1], c[2], c[3]), together, 5 * i, values[i])

    rng = np.random.default_rng(10)
    rows = 3000
    table = torch.from_numpy(rng.standard_normal((rows, 3)).astype(np.float16).astype(np.float32))
    slots = rng.integers(0, rows, (1000, 4)).astype(np.int32)
    slots[0] = rows - 1
    weights = rng.random((1000, 4)).astype(np.float32)
    values = rng.standard_normal(1000).astype(np.float32)
    for table_flat in (padded_table(table), half_table(table)):
        if table_flat is None:  # (no half tables where numba does not target F16C: `HALF_READS`)
            continue
        separate, together = np.full(5 * 1000 + 1, 7.0, np.float32), np.full(5 * 1000 + 1, 7.0, np.float32)
        both(table_flat, slots, weights, values, separate, together)
        assert np.array_equal(separate.view(np.uint32), together.view(np.uint32))
        assert (together[4::5] == 7.0).all() and not (together.reshape(-1)[:-1].reshape(-1, 5)[:, :4] == 7.0).any()


def test_no_half_tables_where_numba_does_not_target_f16c(monkeypatch):
    """Without F16C the tables stay float32: `half_table` gives none, and `read_rows3` does not
    type a float16 table (a typing error, not a kernel that would call a missing routine)."""
    import numba

    from neuralrt.neural import sparse_hash_grid as grid
    from neuralrt.simd import numba_targets

    assert grid.HALF_READS == numba_targets("f16c")
    monkeypatch.setattr(grid, "HALF_READS", False)
    assert grid.half_table(torch.zeros(4, 3)) is None

    @numba.njit
    def read(table_flat, out):
        grid.read_rows3(table_flat, (0, 1, 2, 3), (np.float32(1), np.float32(1), np.float32(1), np.float32(1)), out, 0)

    with pytest.raises(numba.core.errors.TypingError):
        read(np.zeros(13, np.uint16), np.zeros(4, np.float32))


@pytest.mark.skipif(not sparse_hash_grid.HALF_READS, reason="numba does not target F16C here: no float16 tables")
def test_half_table_reads_give_the_float32_tables_bits_and_only_exact_tables_get_one():
    """`read_rows3` from `half_table`'s float16 bits gives the bits of the same reads from the
    float32 table where every value is a float16 (normals, subnormals, zeros, the largest); a
    table with one value that float16 does not hold gets no half copy."""
    import numba

    from neuralrt.neural.sparse_hash_grid import half_table, padded_table, read_rows3

    @numba.njit
    def reads(table_flat, slots, weights, out):
        for i in range(slots.shape[0]):
            s, c = slots[i], weights[i]
            read_rows3(table_flat, (s[0], s[1], s[2], s[3]), (c[0], c[1], c[2], c[3]), out[0], 3 * i)
            read_rows3(table_flat, (s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]), (c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]),
                       out[1], 3 * i)  # fmt: skip

    rng = np.random.default_rng(9)
    rows = 4000
    values = (rng.standard_normal(3 * rows) * 10.0 ** rng.integers(-7, 4, 3 * rows)).astype(np.float16)
    values[:4] = [np.finfo(np.float16).max, -np.finfo(np.float16).smallest_subnormal, 0.0, -0.0]
    table = torch.from_numpy(values.astype(np.float32).reshape(rows, 3))
    half = half_table(table)
    assert half.dtype == np.uint16 and half.shape == (3 * rows + 1,)
    assert np.array_equal(half[:-1].view(np.float16).astype(np.float32), table.reshape(-1).numpy())
    slots = rng.integers(0, rows, (2000, 8)).astype(np.int32)
    slots[:3] = [0, 1, rows - 1, 0, 1, rows - 1, 2, 3]  # the largest value, the subnormal, the last row
    weights = rng.random((2000, 8)).astype(np.float32)
    from_half, from_float = (np.full((2, 3 * 2000), 7.0, np.float32) for _ in range(2))
    reads(half, slots, weights, from_half)
    reads(padded_table(table), slots, weights, from_float)
    assert np.array_equal(from_half.view(np.uint32), from_float.view(np.uint32)) and not (from_half == 7.0).any()
    inexact = table.clone()
    inexact[5, 1] = 1.0 + 2.0**-12  # between two float16s
    assert half_table(inexact) is None


def test_padded_table_is_a_view_of_the_grids_table_and_a_copy_otherwise(tmp_path):
    """The fused CPU pass reads the table through `padded_table`: for a `SparseHashGrid` (new, or
    in a model loaded from a file) a view of the parameter's storage, which has the spare float
    (no second copy of the table in memory), following in-place updates; any other table is
    copied, with the same values."""
    from neuralrt.geometry.procedural import statue
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel
    from neuralrt.neural.sparse_hash_grid import padded_table

    grid = SparseHashGrid(log2_table_size=6)
    flat = padded_table(grid.table)
    assert flat.shape == (grid.table.numel() + 1,) and np.shares_memory(flat, grid.table.detach().numpy())
    with torch.no_grad():
        grid.table.mul_(2.0)
    assert np.array_equal(flat[:-1], grid.table.detach().reshape(-1).numpy())
    other = grid.table.detach().clone()
    copy = padded_table(other)
    assert not np.shares_memory(copy, other.numpy()) and np.array_equal(copy[:-1], other.reshape(-1).numpy()) and copy[-1] == 0
    config = LSNIFConfig.preset("lq", voxel={"resolution": 8}, encoding={"resolutions": (8, 16), "log2_table_size": 6})
    model = LSNIFModel.from_mesh(statue(0), config)
    model.save(tmp_path / "m.nrt")
    loaded = LSNIFModel.load(tmp_path / "m.nrt")
    assert np.shares_memory(padded_table(loaded.encoder.table), loaded.encoder.table.detach().numpy())
