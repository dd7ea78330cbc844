"""Triton kernels of LSNIF against the numba kernels and the references.

With a GPU the kernels are compiled for CUDA; without one they run on CPU tensors under Triton's
interpreter (TRITON_INTERPRET=1, set here before triton is imported), on small inputs. Skipped
when triton is not installed.
"""

import os

import numpy as np
import pytest
import torch

CUDA = torch.cuda.is_available()
if not CUDA:
    os.environ.setdefault("TRITON_INTERPRET", "1")
pytest.importorskip("triton")

from test_lsnif_features import _assert_same, _random_rays, _torus_occupancy  # noqa: E402

from neuralrt.methods.lsnif_features import (  # noqa: E402
    ORIGIN_POINT,
    featurize_rays,
    featurize_rays_numba,
    featurize_rays_reference,
)
from neuralrt.methods.lsnif_features_triton import featurize_rays_triton  # noqa: E402

DEVICE = torch.device("cuda" if CUDA else "cpu")
# The interpreter computes masked-off lanes too (NaN rays, inf times): numpy warns about them.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")
if not CUDA and os.environ.get("TRITON_INTERPRET") != "1":
    pytest.skip("no GPU and TRITON_INTERPRET is not 1", allow_module_level=True)


def _assert_features_match(fast, ref):
    """Bit-identical under the interpreter. Compiled, the GPU may fuse ``o + t * d`` into an FMA
    (one float64 ulp): all but rare rays on a voxel plane match exactly in count and codes, and
    points agree to float32 rounding."""
    fast = fast.to("cpu")
    if not CUDA:
        _assert_same(fast, ref)
        return
    same = (fast.count == ref.count) & (fast.face_axis == ref.face_axis).all(1)
    assert same.float().mean() >= 0.999
    torch.testing.assert_close(fast.points[same], ref.points[same], atol=2e-6, rtol=0)
    torch.testing.assert_close(fast.t_enter, ref.t_enter, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(fast.t_exit, ref.t_exit, atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("origin_point,share", [(True, True), (False, False)])
def test_triton_featurize_matches_numba_and_reference(origin_point, share):
    rng = np.random.default_rng(3)
    occ = rng.uniform(size=(8, 8, 8)) < 0.3
    o, d = _random_rays(rng, 160, occ)
    kw = dict(origin_point=origin_point, share_boundary_points=share)
    fast = featurize_rays_triton(o.to(DEVICE), d.to(DEVICE), torch.from_numpy(occ).to(DEVICE), 10, **kw)
    ref = featurize_rays_reference(o, d, occ, 10, **kw)
    _assert_same(featurize_rays_numba(o, d, occ, 10, **kw), ref)
    _assert_features_match(fast, ref)
    # the sample covers misses, inside starts (origin points), truncation and padding
    assert (ref.count == 0).any() and ref.truncated.any() and (ref.face_axis == ORIGIN_POINT).any() == origin_point


def test_triton_featurize_on_a_voxelized_mesh_and_degenerate_rays():
    occ, tris = _torus_occupancy(16)
    rng = np.random.default_rng(4)
    o, d = _random_rays(rng, 96, occ, tris)
    # NaN, zero and denormal directions, a start on the box face, a ray along a voxel plane
    o = torch.cat([o, torch.tensor([[np.nan, 0.5, 0.5], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0.0, 0.3, 0.4], [-1, 0.5, 0.5]])])
    d = torch.cat([d, torch.tensor([[1.0, 0, 0], [0, 0, 0], [1e-40, 0, 0], [1.0, 0.2, 0.1], [1.0, 0.0, 0.0]])])
    fast = featurize_rays_triton(o.to(DEVICE), d.to(DEVICE), torch.from_numpy(occ).to(DEVICE), 12)
    ref = featurize_rays_numba(o, d, occ, 12)
    _assert_features_match(fast, ref)
    assert (ref.count > 0).float().mean() > 0.3 and ref.count[-5:-2].tolist() == [0, 0, 0]


def test_featurize_dispatches_on_device_and_checks_input():
    occ = torch.ones(4, 4, 4, dtype=torch.bool, device=DEVICE)
    o = torch.tensor([[-0.5, 0.5, 0.5]], device=DEVICE)
    d = torch.tensor([[1.0, 0.01, 0.02]], device=DEVICE)
    f = featurize_rays(o, d, occ)
    assert f.points.device == o.device and f.count.item() == 5
    with pytest.raises(ValueError, match="cubic"):
        featurize_rays_triton(o, d, torch.ones(4, 4, 2, dtype=torch.bool, device=DEVICE))
    empty = featurize_rays_triton(o[:0], d[:0], occ)
    assert empty.points.shape == (0, 18, 3) and empty.count.device == o.device
    # The kernel's own checks are featurize_rays's: a short direction tensor would be read past its end.
    for bad, message in (((o, d[:0]), "must both be"), ((o[:, :2], d[:, :2]), "must both be")):
        with pytest.raises(ValueError, match=message):
            featurize_rays_triton(*bad, occ)
    with pytest.raises(ValueError, match="max_points must be >= 1"):
        featurize_rays_triton(o, d, occ, 0)
    # Rays of two dtypes walk in float64 each as given, as numba's walk does (not cast to the origins').
    rng = np.random.default_rng(5)
    occ_np = rng.uniform(size=(8, 8, 8)) < 0.3
    o64, d64 = _random_rays(rng, 64, occ_np)
    o32, d64 = o64.float(), d64.double() * 1.0000001
    mixed = featurize_rays_triton(o32.to(DEVICE), d64.to(DEVICE), torch.from_numpy(occ_np).to(DEVICE), 10)
    _assert_features_match(mixed, featurize_rays_numba(o32, d64, occ_np, 10))


# -- sparse hash grid -----------------------------------------------------------------------------


@pytest.mark.parametrize("resolutions,features,log2_size", [((32, 64), 3, 12), ((16, 32, 64), 2, 10)])
def test_triton_hash_grid_forward_and_backward_match_numba(resolutions, features, log2_size):
    from test_sparse_hash_grid import _featurized_points

    from neuralrt.neural.sparse_hash_grid import SparseHashGrid
    from neuralrt.neural.sparse_hash_grid_triton import sparse_hash_grid_triton

    f = _featurized_points(n=120, seed=5)  # face, origin and padding points
    grid = SparseHashGrid(resolutions=resolutions, features_per_level=features, log2_table_size=log2_size, init_scale=1.0)
    ref = grid(f.points, f.face_axis)  # numba, CPU
    table = grid.table.detach().to(DEVICE).requires_grad_()
    out = sparse_hash_grid_triton(f.points.to(DEVICE), f.face_axis.to(DEVICE), table, grid.resolutions)
    assert out.shape == ref.shape and out.device == table.device
    if CUDA:  # fused multiply-adds on the GPU
        torch.testing.assert_close(out.cpu(), ref, atol=1e-6, rtol=1e-5)
    else:
        assert torch.equal(out, ref)
    upstream = torch.randn_like(ref)
    (g_ref,) = torch.autograd.grad((ref * upstream).sum(), grid.table)
    (g,) = torch.autograd.grad((out * upstream.to(DEVICE)).sum(), table)
    assert (g_ref != 0).sum() > 100
    torch.testing.assert_close(g.cpu(), g_ref, atol=1e-5, rtol=1e-5)  # atomic adds: order varies


# -- fused featurize + encode + first layer ---------------------------------------------------------


class _Net(torch.nn.Module):
    """The LSNIF network's shape (``hidden`` leaky-ReLU layers, fp32 ``output``), random weights."""

    def __init__(self, inputs, width, layers, outputs, seed=0):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        widths = [inputs] + [width] * layers
        self.hidden = torch.nn.ModuleList(torch.nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.output = torch.nn.Linear(width, outputs)
        self.slope = 0.01
        with torch.no_grad():
            for p in self.parameters():
                p.copy_(torch.rand(p.shape, generator=g) * 0.4 - 0.2)

    def forward(self, x, compute_dtype=torch.float32):
        return self.reference(x, compute_dtype)

    def reference(self, x, dtype):
        x = x.to(dtype)
        for layer in self.hidden:
            x = torch.nn.functional.leaky_relu(torch.nn.functional.linear(x, layer.weight.to(dtype), layer.bias.to(dtype)), self.slope)
        return self.output(x.float())


# Interpreter: fp32 only (it reads bf16 dot operands as integers); compiled: the model's bf16 too.
FUSED_DTYPES = [torch.float32, torch.bfloat16] if CUDA else [torch.float32]


@pytest.mark.parametrize("dtype", FUSED_DTYPES)
@pytest.mark.parametrize(
    "max_points,width,layers,distances,origin_point,stage",
    [(10, 64, 2, True, True, "whole"), (6, 48, 3, False, False, "first_layer"), (6, 48, 3, False, False, "input")],
)
def test_fused_inference_matches_the_unfused_path(dtype, max_points, width, layers, distances, origin_point, stage):
    from neuralrt.methods.lsnif import point_local_distances
    from neuralrt.methods.lsnif_fused import fused_network_outputs
    from neuralrt.neural.sparse_hash_grid import SparseHashGrid

    occ, tris = _torus_occupancy(16)
    o, d = _random_rays(np.random.default_rng(6), 96, occ, tris)
    grid = SparseHashGrid(resolutions=(16, 32), log2_table_size=12, init_scale=1.0)
    net = _Net(grid.output_dim(max_points) + (max_points if distances else 0), width, layers, 11)
    fc = dict(origin_point=origin_point, share_boundary_points=True)
    with torch.no_grad():
        fp = featurize_rays_numba(o, d, occ, max_points, **fc)
        x = grid(fp.points, fp.face_axis)
        if distances:
            x = torch.cat([x, point_local_distances(fp, o, d)], 1)
        ref = net.reference(x, dtype)
        fused = fused_network_outputs(
            o.to(DEVICE), d.to(DEVICE), torch.from_numpy(occ).to(DEVICE), grid.to(DEVICE), net.to(DEVICE),
            max_points=max_points, point_distances=distances, compute_dtype=dtype, stage=stage, block=32, **fc,
        )  # fmt: skip
    out, count = fused.values.cpu(), fused.count.cpu()
    assert out.shape == ref.shape
    active = fp.count > 0
    assert active.sum() > 25 and (~active).sum() > 5
    same = count == fp.count  # all under the interpreter; on the GPU, see _assert_features_match
    assert same.float().mean() >= (0.999 if CUDA else 1.0)
    torch.testing.assert_close(fused.t_enter.cpu(), fp.t_enter, atol=1e-6, rtol=1e-6)
    tol = 2e-5 if dtype == torch.float32 else 3e-2  # bf16: layer 1 accumulates in fp32 here, bf16 GEMM there
    compared = active & same
    assert (out[compared] - ref[compared]).abs().max() <= tol * ref[compared].abs().max()


def test_lsnif_model_fused_answers_match_unfused():
    """The model's fused inference path (CUDA's) gives the answers of its featurize -> encode -> MLP path."""
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.lsnif import LSNIFModel
    from neuralrt.methods.lsnif_config import LSNIFConfig
    from neuralrt.rays import Rays

    dtype = "bf16" if CUDA else "fp32"
    config = LSNIFConfig.preset("lq", voxel={"resolution": 16}, encoding={"resolutions": (16, 32), "log2_table_size": 12},
                                inference={"compute_precision": dtype})  # fmt: skip
    model = LSNIFModel.from_mesh(sphere(2), config)
    with torch.no_grad():  # an untrained table is ~0: give the features some weight
        model.encoder.table.uniform_(-1, 1)
    model = model.to(DEVICE)
    g = torch.Generator().manual_seed(7)
    lo, hi = model.box.lo.cpu(), model.box.hi.cpu()
    origins = (torch.randn(64, 3, generator=g) * 2 + (lo + hi) / 2)
    targets = lo + torch.rand(64, 3, generator=g) * (hi - lo)
    rays = Rays(origins=origins, directions=targets - origins).to(DEVICE)
    prep = model._prepare(rays)
    with torch.no_grad():
        ref = model._raw_outputs(prep, model.compute_dtype())
        act, out, t_enter, t_exit, t_offset = model._network_answers_fused(rays)
    assert len(prep.active) > 15 and torch.equal(act, prep.active)
    torch.testing.assert_close(t_enter, prep.features.t_enter)
    torch.testing.assert_close(t_exit, prep.features.t_exit)
    tol = 3e-2 if CUDA else 2e-5
    assert (out - ref).abs().max() <= tol * ref.abs().max()


@pytest.mark.parametrize(
    "distances,origin_point,block,warps,dtype", [(True, True, 32, 1, torch.bfloat16), (False, False, 64, 2, torch.float32)]
)
def test_per_ray_kernel_writes_the_tiled_kernels_network_input(distances, origin_point, block, warps, dtype):
    """``input_per_ray`` (one ray per lane) and ``input`` (padded tile, checked against the unfused
    path above) write the same bytes; bf16 rows go out as packed pairs (neither stage has a dot
    product, so bf16 runs under the interpreter too) and are the fp32 rows rounded to bf16: to
    nearest even when compiled, truncated under Triton's interpreter (its casts truncate)."""
    from neuralrt.methods.lsnif_fused import pack_network, run_fused_kernel
    from neuralrt.neural.sparse_hash_grid import SparseHashGrid

    occ, tris = _torus_occupancy(16)
    o, d = _random_rays(np.random.default_rng(8), 48, occ, tris)
    grid = SparseHashGrid(resolutions=(16, 32), features_per_level=3, log2_table_size=12, init_scale=1.0).to(DEVICE)
    net = _Net(grid.output_dim(6) + (6 if distances else 0), 32, 2, 11).to(DEVICE)
    weights = pack_network(net, grid, 6, distances, dtype)
    occ_t, res = torch.from_numpy(occ).to(DEVICE), grid._resolutions_on(DEVICE)
    kw = dict(max_points=6, origin_point=origin_point, point_distances=distances)
    tiled = run_fused_kernel(o.to(DEVICE), d.to(DEVICE), occ_t, grid.table, res, weights, stage="input", block=32, **kw)
    per_ray = run_fused_kernel(o.to(DEVICE), d.to(DEVICE), occ_t, grid.table, res, weights, stage="input_per_ray",
                               block=block, num_warps=warps, **kw)  # fmt: skip
    assert torch.equal(per_ray.count, tiled.count) and (tiled.count == 6).any() and (tiled.count == 0).any()
    torch.testing.assert_close(per_ray.t_enter, tiled.t_enter, atol=0 if not CUDA else 1e-6, rtol=0 if not CUDA else 1e-6)
    torch.testing.assert_close(per_ray.t_exit, tiled.t_exit, atol=0 if not CUDA else 1e-6, rtol=0 if not CUDA else 1e-6)
    assert per_ray.values.dtype == dtype and (tiled.values != 0).float().mean() > 0.2
    if CUDA:  # two compiled kernels may contract multiply-adds differently (see _assert_features_match)
        close = dict(atol=1e-2, rtol=1e-2) if dtype == torch.bfloat16 else dict(atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(per_ray.values.float(), tiled.values.float(), **close)
    else:
        assert torch.equal(per_ray.values, tiled.values)
    if dtype == torch.bfloat16:
        wide = run_fused_kernel(o.to(DEVICE), d.to(DEVICE), occ_t, grid.table, res, pack_network(net, grid, 6, distances,
                                torch.float32), stage="input_per_ray", block=block, num_warps=warps, **kw).values  # fmt: skip
        nearest = wide.to(torch.bfloat16)
        truncated = (wide.view(torch.int32) & -65536).view(torch.float32).to(torch.bfloat16)
        assert not torch.equal(nearest, truncated)
        if CUDA:  # (two compiled kernels: an fp32 ulp may move a rare value across a rounding boundary)
            assert (per_ray.values == nearest).float().mean() > 0.99
        else:
            assert torch.equal(per_ray.values, truncated)


def test_fused_hits_equal_the_unfused_intersect():
    """`fused_hits` (fused input kernel, torch hidden layers, output layer + decoding in a kernel)
    answers as `_intersect_chunk`'s featurize -> encode -> MLP -> torch decoding path."""
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.lsnif import LSNIFModel
    from neuralrt.methods.lsnif_config import LSNIFConfig
    from neuralrt.rays import Hits, Rays

    config = LSNIFConfig.preset("lq", voxel={"resolution": 16}, encoding={"resolutions": (16, 32), "log2_table_size": 12},
                                inference={"compute_precision": "fp32"})  # fmt: skip
    shape = LSNIFModel.from_mesh(sphere(2), config)
    materials = [{"name": f"m{i}", "base_color": [0.5, 0.5, 0.5]} for i in range(3)]  # the argmax too
    model = LSNIFModel(config, shape.bounds, shape.occupancy, materials)
    with torch.no_grad():  # untrained weights answer ~0: spread the logits so that hits and misses both occur
        model.encoder.table.uniform_(-1, 1)
        model.network.output.weight.mul_(8)
    g = torch.Generator().manual_seed(9)
    lo, hi = model.box.lo, model.box.hi
    origins = torch.randn(72, 3, generator=g) * 2 + (lo + hi) / 2
    targets = lo + torch.rand(72, 3, generator=g) * (hi - lo)
    rays = Rays(origins=origins, directions=targets - origins)
    rays.t_max[:8] = 0.5  # some hits cut by t_max
    rays.origins[8] = float("nan")  # an invalid ray
    with torch.no_grad():
        model._network_answers = model._network_answers_unfused  # the reference: featurize -> encode -> MLP
        ref = model._intersect_chunk(rays)
        del model._network_answers
        model = model.to(DEVICE)
        hits = Hits.empty(len(rays), DEVICE)
        model._network_answers_fused_hits(rays.to(DEVICE), hits)
    hits = hits.to("cpu")
    assert 5 < int(ref.hit.sum()) < 60 and (ref.t[:8] == float("inf")).all()
    assert len(set(ref.material_id[ref.hit].tolist())) > 1
    # On a GPU a ray on a voxel plane can, rarely, walk the other column (see _assert_features_match).
    same = (hits.hit == ref.hit) & (hits.material_id == ref.material_id)
    assert int((~same).sum()) <= (1 if CUDA else 0)
    torch.testing.assert_close(hits.t[same], ref.t[same], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(hits.normal[same], ref.normal[same], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(hits.geometric_normal[same], ref.geometric_normal[same], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(hits.albedo[same], ref.albedo[same], atol=1e-5, rtol=1e-5)
