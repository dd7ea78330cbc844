"""Triton kernels of N-BVH (hash grid, cut traversal) against the numba kernels and the references.

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

from neuralrt.neural.hash_grid import HashGrid, hash_grid_reference  # noqa: E402
from neuralrt.neural.hash_grid_triton import hash_grid_triton  # noqa: E402
from test_nbvh import random_answers, wavefront_rays  # noqa: E402

DEVICE = torch.device("cuda" if CUDA else "cpu")
# The interpreter runs a launch's programs one after another, each op at a fixed cost: larger
# blocks (fewer programs) where the kernels take a block size.
BLOCK = 128 if CUDA else 512
# The interpreter computes masked-off lanes too: numpy warns about them.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")
if not CUDA and os.environ.get("TRITON_INTERPRET") != "1":
    pytest.skip("no GPU and TRITON_INTERPRET is not 1", allow_module_level=True)


# -- hash grid --------------------------------------------------------------------------------------


def _points(n, p, seed):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(n, p, 3, generator=g) * 1.2 - 0.1  # some outside the cube: clamped
    pts[0, 0] = torch.tensor([1.0, 1.0, 1.0])  # the far corner (clamped vertex index)
    pts[0, 1] = torch.tensor([0.0, 0.0, 0.0])
    pts[1, 0] = torch.tensor([0.5, 0.25, 0.75])  # on vertex planes of every level
    return pts


@pytest.mark.parametrize("levels,base,features,log2_table", [(8, 8, 4, 12), (5, 4, 3, 9)])
def test_triton_hash_grid_matches_numba_and_reference(levels, base, features, log2_table):
    """N-BVH's 8 levels x 4 features (dense 8^3, 16^3, hashed above at 2^12) and an odd shape."""
    grid = HashGrid(levels=levels, base_resolution=base, features_per_level=features, log2_table_size=log2_table,
                    init_scale=1.0, seed=3)  # fmt: skip
    assert any(grid.layout.dense) and not all(grid.layout.dense)
    pts = _points(150, 3, 1)
    numba_out = grid(pts)  # CPU float32: the numba kernel
    table = grid.table.detach().to(DEVICE).requires_grad_()
    out = hash_grid_triton(pts.to(DEVICE), table, grid.layout, block=BLOCK)
    assert out.shape == numba_out.shape == (150, 3 * levels * features) and out.device == table.device
    if CUDA:  # fused multiply-adds on the GPU round the vertex positions otherwise: each side is within
        # ~eps * res of the float64 reference (below), so they differ by up to twice that (measured on
        # an H100: up to 6.3e-6, on 0.1% of the elements)
        bound = 4 * np.finfo(np.float32).eps * max(grid.layout.resolutions)
        torch.testing.assert_close(out.detach().cpu(), numba_out.detach(), atol=bound, rtol=0)
    else:
        assert torch.equal(out.detach(), numba_out.detach())
    ref = hash_grid_reference(pts.numpy(), grid.table.detach().numpy(), grid.layout)
    # float32 vertex positions x * (res - 1) + 0.5 are rounded to ~res * eps: so are the weights.
    assert np.abs(out.detach().cpu().numpy() - ref).max() < 2 * np.finfo(np.float32).eps * max(grid.layout.resolutions)
    # Backward: atomic adds (order varies) against numba's per-thread tables.
    upstream = torch.randn(numba_out.shape, generator=torch.Generator().manual_seed(4))
    (g_ref,) = torch.autograd.grad((numba_out * upstream).sum(), grid.table)
    (g,) = torch.autograd.grad((out * upstream.to(DEVICE)).sum(), table)
    assert (g_ref != 0).sum() > 200
    torch.testing.assert_close(g.cpu(), g_ref, atol=1e-5, rtol=1e-5)


def test_triton_hash_grid_edge_cases():
    grid = HashGrid(levels=3, base_resolution=4, features_per_level=4, log2_table_size=6, seed=0)
    table = grid.table.detach().to(DEVICE)
    assert hash_grid_triton(torch.zeros(0, 3, 3, device=DEVICE), table, grid.layout).shape == (0, 36)
    with pytest.raises(ValueError, match="rows"):
        hash_grid_triton(torch.zeros(2, 3, 3, device=DEVICE), table[:-1], grid.layout)


# -- cut traversal ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ball_model():
    from test_nbvh import CENTER, RADIUS, _random_cut

    from neuralrt.geometry.mesh import Mesh
    from neuralrt.geometry.procedural import sphere
    from neuralrt.methods.nbvh import NBVHConfig, NBVHModel

    base = sphere(subdivisions=3)
    ball = Mesh(base.vertices * RADIUS + CENTER, base.faces, vertex_normals=base.vertex_normals, name="ball")
    # 3 grid levels (8^3 and 16^3 dense, 32^3 hashed at 2^14): the interpreter's time grows with the levels
    model = NBVHModel.from_mesh(ball, NBVHConfig.preset("cpu", encoding={"levels": 3}))
    _random_cut(model, seed=1)
    return model


def _cut_on(cut, device):
    from neuralrt.methods.nbvh_traversal import CutArrays

    return CutArrays(*(getattr(cut, f).to(device) for f in ("lo", "hi", "children", "lod", "live")))


def _assert_same_traversal(o, d, t_max, cut, lvl, dil):
    from neuralrt.methods.nbvh_traversal import first_leaves, list_leaves
    from neuralrt.methods.nbvh_traversal_triton import first_leaves_triton, list_leaves_triton

    ref = list_leaves(o, d, t_max, cut, lvl, dil)  # numba
    dev = [x.to(DEVICE) for x in (o, d, t_max)] + [_cut_on(cut, DEVICE)] + [x.to(DEVICE) for x in (lvl, dil)]
    got = list_leaves_triton(*dev)
    for field in ("start", "node", "t0", "t1"):
        assert torch.equal(getattr(got, field).cpu(), getattr(ref, field)), field
    node, t0, t1 = first_leaves_triton(*dev)
    rn, r0, r1 = first_leaves(o, d, t_max, cut, lvl, dil)
    assert torch.equal(node.cpu(), rn) and torch.equal(t0.cpu(), r0) and torch.equal(t1.cpu(), r1)
    return ref, rn


def test_triton_traversal_lists_the_numba_leaves(ball_model, monkeypatch):
    """Random rays (outside, inside leaves, axis-parallel, unbounded) against a random cut: LoD 0,
    LoD 3 and the live cut, one level per ray."""
    from test_nbvh import _unit_rays

    import neuralrt.methods.nbvh_traversal_triton as kernels

    if not CUDA:  # one program walking 2 blocks of 128 rays in turn (the persistent grid's loop)
        monkeypatch.setattr(kernels, "_BLOCK", 128)
        monkeypatch.setattr(kernels, "_PROGRAMS", 1)

    n = 240
    o, d = _unit_rays(n, 2)
    t_max = torch.full((n,), 0.9)
    t_max[:20] = float("inf")
    lvl = torch.tensor([0, 3, -1], dtype=torch.int8).repeat(n // 3)
    dil = torch.full((n,), 1e-5)
    ref, first = _assert_same_traversal(o, d, t_max, ball_model.cut_arrays(), lvl, dil)
    assert len(ref.node) > n and (ref.counts >= 4).sum() > 10  # several leaves per ray: the sort is exercised
    assert (first < 0).any() and (first >= 0).any()


def test_triton_traversal_of_a_tree_deeper_than_its_short_stack(monkeypatch):
    """A caterpillar tree 12 levels deep (node 2k + 2 splits again, 2k + 1 is a leaf), rays from
    the far end, where every spine node is entered before its leaf: the walks go deeper than the
    short stack (8 here, 64 in use: the interpreter is slow), so the kernels are run again with
    numba's 256."""
    import neuralrt.methods.nbvh_traversal_triton as kernels
    from neuralrt.methods.nbvh_traversal import NO_LOD, CutArrays

    stacks = []
    with_stack = kernels._with_stack
    monkeypatch.setattr(kernels, "_with_stack", lambda *a: stacks.append(with_stack(*a)) or stacks[-1])
    monkeypatch.setattr(kernels, "_SHORT_STACK", 8)
    depth = 12
    m = 2 * depth + 1
    children = torch.full((m, 2), -1, dtype=torch.int32)
    lo, hi = torch.zeros(m, 3), torch.ones(m, 3)
    for k in range(depth):  # interior 2k (spine) -> spine 2k + 2 (popped first), leaf 2k + 1 (a slice at x ~ k / depth)
        children[2 * k] = torch.tensor([2 * k + 2, 2 * k + 1])
        lo[2 * k + 1, 0], hi[2 * k + 1, 0] = k / depth, (k + 1.5) / depth
        lo[2 * k + 2, 0] = (k + 1) / depth
    cut = CutArrays(lo, hi, children, torch.full((m,), NO_LOD, dtype=torch.int8), torch.zeros(m, dtype=torch.bool))
    g = torch.Generator().manual_seed(0)
    n = 8
    o = torch.cat([torch.full((n, 1), 1.1), torch.rand(n, 2, generator=g)], 1)
    d = torch.nn.functional.normalize(torch.cat([-torch.ones(n, 1), 0.05 * torch.randn(n, 2, generator=g)], 1), dim=1)
    ref, first = _assert_same_traversal(o, d, torch.full((n,), float("inf")), cut, torch.zeros(n, dtype=torch.int8),
                                        torch.full((n,), 1e-5))  # fmt: skip
    assert ref.counts.max() > 8 and (first == 2 * depth - 1).all()  # the deepest leaf is entered first
    assert stacks == [256, 256]  # list and first-leaf walks both overflowed the short stack


def _assert_same_hits(t, t_ref, rtol=1e-5):
    """Same hit/miss and distances. Compiled, fused multiply-adds move features and outputs by
    float32 rounding, which may flip an answer right at the acceptance threshold: 1 ray in 64."""
    t, hit_ref = t.cpu(), torch.isfinite(t_ref)
    hit = torch.isfinite(t)
    if CUDA:
        assert (hit != hit_ref).sum() <= max(1, len(t) // 64)
    else:
        assert torch.equal(hit, hit_ref)
    both = hit & hit_ref
    torch.testing.assert_close(t[both], t_ref[both], rtol=rtol, atol=1e-6)
    return both


def test_model_answers_the_same_through_the_triton_kernels(ball_model, monkeypatch):
    """`intersect` through what CUDA runs (Triton leaf lists, Triton wavefront steps; without a GPU
    on CPU tensors) against the numba path: the same leaves and features, so the same answers up to
    the MLP's float rounding. The cut is the random one of the traversal test. (`occluded` is the
    same loop stopping at the first accepted hit: the wavefront test checks it.)"""
    import copy

    import neuralrt.methods.nbvh as nbvh_module
    from test_nbvh import _sphere_rays

    from neuralrt.methods.nbvh_traversal_triton import list_leaves_triton
    from neuralrt.methods.nbvh_wavefront_triton import closest_hits_triton

    cpu_model = random_answers(copy.deepcopy(ball_model))
    rays = _sphere_rays(48, 11)
    cpu = cpu_model.intersect(rays)
    assert 0.2 < cpu.hit.float().mean() < 0.9
    calls = []

    def counted(*args):
        calls.append(1)
        return closest_hits_triton(*args)

    # What CUDA rays take anyway: the torch answer around the Triton leaf lists and wavefront (CPU
    # rays would go through the numba `answers_cpu`, which calls neither).
    monkeypatch.setattr(nbvh_module, "list_leaves", list_leaves_triton)
    monkeypatch.setattr(nbvh_module.NBVHModel, "_closest", counted)
    monkeypatch.setattr(nbvh_module.NBVHModel, "_answer", nbvh_module.NBVHModel._answer_torch)
    model = copy.deepcopy(cpu_model).to(DEVICE)
    tri = model.intersect(rays.to(DEVICE))
    assert calls  # the Triton wavefront answered
    both = _assert_same_hits(torch.where(tri.hit, tri.t, torch.inf), torch.where(cpu.hit, cpu.t, torch.inf))
    torch.testing.assert_close(tri.normal.cpu()[both], cpu.normal[both], rtol=1e-4, atol=1e-5)


def test_triton_wavefront_answers_as_the_torch_loop(ball_model):
    """The CUDA wavefront (step kernels around the MLP) against the torch loop, both on the same
    leaf lists, for closest and any hits; rays from outside and from inside leaves (reversed chords)."""
    import copy

    from neuralrt.methods.nbvh_wavefront_triton import closest_hits_triton

    model = random_answers(copy.deepcopy(ball_model))
    on_device = copy.deepcopy(model).to(DEVICE)
    n = 64
    o, d, t_max = wavefront_rays(n)
    for any_hit in (False, True):
        ref_t, ref_out = model._closest_torch(o, d, t_max, any_hit)
        t, out = closest_hits_triton(on_device, o.to(DEVICE), d.to(DEVICE), t_max.to(DEVICE), any_hit)
        assert 0.2 < torch.isfinite(ref_t).float().mean() < 0.95
        both = _assert_same_hits(t, ref_t)
        torch.testing.assert_close(out.cpu()[both], ref_out[both], rtol=1e-4, atol=1e-5)
