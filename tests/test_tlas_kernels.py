"""The TLAS's two stage implementations (numba on CPU arrays, torch on any device) answer
bit-identically: both run here on CPU tensors."""

from dataclasses import fields

import numpy as np
import pytest
import torch
import trimesh

from neuralrt import Mesh, MeshBLAS, Rays, Transform
from neuralrt.accel.tlas import Instance, SceneAccel
from neuralrt.geometry.mesh import MeshMaterial
from neuralrt.accel.tlas_stages import InstanceTable, NumbaTLASStages, TorchTLASStages
from neuralrt.rays import ray_box_intervals, valid_ray_mask
from neuralrt.accel import tlas_kernels


@pytest.fixture(scope="module")
def blases():
    rng = np.random.default_rng(0)
    t = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=32, minor_sections=16)
    torus = MeshBLAS(Mesh(t.vertices, t.faces, face_material_ids=rng.integers(0, 3, len(t.faces)),
                          materials=[MeshMaterial(name) for name in "abc"]))
    s = trimesh.creation.icosphere(subdivisions=2, radius=0.7)
    return torus, MeshBLAS(Mesh(s.vertices, s.faces))


MOVED = Transform.translate([1.5, 0, 0]) @ Transform.rotate([0, 1, 1], 40) @ Transform.scale([0.7, 1.3, 0.5])
TILTED = Transform.translate([-1.2, 0.5, -0.3]) @ Transform.rotate([1, 0, 0], 75) @ Transform.scale(0.6)
GRID = [Transform.translate([2.5 * x, 2.5 * y, 0.0]) for x in range(-2, 2) for y in range(-2, 2)]


def _scene(kind, torus, sphere, stages=None):
    layouts = {
        "identity": [(torus, Transform(), [0, 1, 2])],
        "moved": [(torus, MOVED, [2, 0, 1])],
        "grid16": [(torus, xf, [k % 3]) for k, xf in enumerate(GRID)],
        "mixed": [(torus, Transform(), [0]), (sphere, TILTED, [1]), (torus, MOVED, [2]), (sphere, Transform(), [3])],
    }
    return SceneAccel([Instance(b, xf, torch.tensor(m), name=str(i)) for i, (b, xf, m) in enumerate(layouts[kind])], stages=stages)


def _rays(n, seed, inside=False, bad_rays=True):
    """Rays from a sphere of radius 6 through [-3, 3]^3 (or from near the origin), with bad rays
    and finite intervals mixed in."""
    g = np.random.default_rng(seed)
    if inside:
        o, d = g.normal(size=(n, 3)) * 0.2, g.normal(size=(n, 3))
    else:
        o = g.normal(size=(n, 3))
        o = 6.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
        d = g.uniform(-3, 3, (n, 3)) - o
    t_min = np.where(g.uniform(size=n) < 0.2, g.uniform(0, 0.5, n), 0.0)
    t_max = np.where(g.uniform(size=n) < 0.2, g.uniform(0.5, 1.5, n), np.inf)
    bad = g.permutation(n)[:400].reshape(4, 100) if bad_rays else np.zeros((4, 0), np.int64)
    o[bad[0], 0] = np.nan
    d[bad[1]] = 0.0
    t_max[bad[2]] = np.nan
    d[bad[3], 1:] = 0.0  # axis-parallel: slab planes with zero direction components
    return Rays(*(torch.from_numpy(np.asarray(x, np.float32)) for x in (o, d, t_min, t_max)))


@pytest.mark.parametrize("kind", ["identity", "moved", "grid16", "mixed"])
@pytest.mark.parametrize("inside,bad_rays", [(False, True), (True, True), (True, False)])
def test_numba_stages_match_torch_stages(kind, inside, bad_rays, blases):
    """Outside rays: gathered (ray, instance) pairs. Inside rays: one box overlapped by all rays
    (no gathers) or by all valid ones (the invalid ones masked)."""
    accel = _scene(kind, *blases)
    assert isinstance(accel.stages, NumbaTLASStages)  # the CPU default, chosen at construction
    rays = _rays(6000, seed=1, inside=inside, bad_rays=bad_rays)
    if kind == "moved" and inside:
        rays = MOVED.apply_rays(rays)  # every ray overlaps the one box: the no-gather path
    fast, fast_occ = accel.intersect(rays), accel.occluded(rays)
    torch_accel = _scene(kind, *blases, stages=TorchTLASStages)
    ref, ref_occ = torch_accel.intersect(rays), torch_accel.occluded(rays)
    assert ref.hit.sum() > 200
    for f in fields(ref):
        assert torch.equal(getattr(fast, f.name), getattr(ref, f.name)), f.name
    assert torch.equal(fast_occ, ref_occ)


def test_instance_overlaps_kernel_matches_slab_test():
    rays = _rays(3000, seed=4)
    lo = torch.tensor([[-1.0, -1.0, -1.0], [0.5, -2.0, 0.0], [0.0, 0.0, 0.0]])
    hi = torch.tensor([[1.0, 1.0, 1.0], [2.5, 2.0, 0.0], [0.0, 3.0, 1.0]])  # flat and degenerate boxes too
    t_limit = torch.minimum(rays.t_max, torch.full_like(rays.t_max, 7.0))
    t0, t1 = ray_box_intervals(rays.origins[:, None], rays.directions[:, None], lo[None], hi[None])
    expected = (t0 <= t1) & (t1 >= rays.t_min[:, None]) & (t0 <= t_limit[:, None]) & valid_ray_mask(rays)[:, None]
    got = np.empty((len(rays), 3), np.bool_)
    count = tlas_kernels.instance_overlaps(
        *(x.numpy() for x in (rays.origins, rays.directions, rays.t_min, rays.t_max, t_limit, lo, hi)), got
    )
    assert torch.equal(torch.from_numpy(got), expected) and count == int(expected.sum())
    assert 0 < count < expected.numel()


@pytest.mark.parametrize("stages", [NumbaTLASStages, TorchTLASStages])
def test_exact_ties_go_to_the_later_instance(blases, stages):
    torus, _ = blases
    accel = SceneAccel([Instance(torus, Transform(), torch.tensor([0])), Instance(torus, Transform(), torch.tensor([1]))], stages=stages)
    h = accel.intersect(_rays(4000, seed=2))
    assert h.hit.sum() > 100
    assert (h.instance_id[h.hit] == 1).all() and (h.material_id[h.hit] == 1).all()


@pytest.mark.parametrize("stages", [NumbaTLASStages, TorchTLASStages])
def test_empty_batch(blases, stages):
    accel = _scene("mixed", *blases, stages=stages)
    empty = Rays(torch.zeros(0, 3), torch.zeros(0, 3))
    assert len(accel.intersect(empty)) == 0 and accel.occluded(empty).numel() == 0


def test_rays_on_another_device_are_one_line_errors(blases):
    from neuralrt.errors import DeviceError

    accel = _scene("mixed", *blases)
    with pytest.raises(DeviceError, match="^device='meta': unsupported device type 'meta' \\(use cpu or cuda\\)$") as info:
        _rays(1000, seed=3).to("meta")  # (Rays refuse a device no BLAS computes on, before any scene sees them)
    assert "\n" not in str(info.value)
    if torch.cuda.is_available():  # rays on another device than the scene's
        rays = _rays(1000, seed=3).to("cuda")
        for query in (accel.intersect, accel.occluded):
            with pytest.raises(DeviceError, match="rays are on cuda:0 but the scene is on cpu") as info:
                query(rays)
            assert "\n" not in str(info.value)


class _HostBLAS:
    """Answers on the host whatever device the rays are on: isolates the TLAS stages on a device."""

    def __init__(self, blas):
        self.blas, self.bounds, self.secondary_offset = blas, blas.bounds, blas.secondary_offset

    def intersect(self, rays):
        return self.blas.intersect(rays.to("cpu")).to(rays.device)

    def occluded(self, rays):
        return self.blas.occluded(rays.to("cpu")).to(rays.device)


def test_scene_on_each_device_answers_like_the_cpu(blases, device):
    """The stages chosen for ``device`` (torch off the CPU) give the CPU's answers there."""
    torus, sphere = (_HostBLAS(b) for b in blases)
    layout = [(torus, Transform(), [0]), (sphere, TILTED, [1]), (torus, MOVED, [2])] + [(torus, xf, [3]) for xf in GRID[:4]]
    instances = [Instance(b, xf, torch.tensor(m)) for b, xf, m in layout]
    rays = _rays(5000, seed=6)
    ref, ref_occ = SceneAccel(instances).intersect(rays), SceneAccel(instances).occluded(rays)
    accel = SceneAccel(instances, device=device)
    got, occ = accel.intersect(rays.to(device)), accel.occluded(rays.to(device))
    assert ref.hit.sum() > 500 and got.t.device.type == device.type
    same = got.hit.cpu() == ref.hit
    assert same.float().mean() > 0.999  # rays grazing a triangle edge may flip with float rounding
    both = same & ref.hit
    torch.testing.assert_close(got.t.cpu()[both], ref.t[both], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got.normal.cpu()[both], ref.normal[both], rtol=1e-4, atol=1e-5)
    assert torch.equal(got.instance_id.cpu()[both], ref.instance_id[both]) and torch.equal(got.material_id.cpu()[both], ref.material_id[both])
    assert (occ.cpu() == ref_occ).float().mean() > 0.999


def _box_table(n_boxes, seed):
    """Random instance boxes, with repeated, flat and point-like ones among them."""
    g = np.random.default_rng(seed)
    lo = g.uniform(-3, 2.5, (n_boxes, 3)).astype(np.float32)
    hi = (lo + g.uniform(0.05, 1.5, (n_boxes, 3))).astype(np.float32)
    hi[1, 2] = lo[1, 2]  # flat
    hi[2] = lo[2]  # a point
    lo[3], hi[3] = lo[4], hi[4]  # repeated
    lo[5:9], hi[5:9] = lo[5], hi[5]  # coincident centroids: the build halves such ranges
    table_lo, table_hi = torch.from_numpy(lo), torch.from_numpy(hi)
    return InstanceTable(table_lo, table_hi, torch.eye(4).expand(n_boxes, 4, 4).contiguous(),
                         torch.zeros(n_boxes, 1, dtype=torch.int64), torch.ones(n_boxes, dtype=torch.bool))


@pytest.mark.parametrize("n_boxes", [9, 37])
def test_bvh_broad_phase_gives_the_brute_force_pairs(n_boxes):
    """The numba stages' BVH walk lists the same (ray, instance) pairs, in the same order, as every
    ray against every box (numba) and as the torch stages, bad and axis-parallel rays included."""
    table = _box_table(n_boxes, seed=n_boxes)
    rays = _rays(5000, seed=5)
    g = np.random.default_rng(1)
    t_limit = torch.minimum(rays.t_max, torch.from_numpy(g.uniform(2, 12, len(rays)).astype(np.float32)))
    # A group: every instance, or some of them (the others belong to other BLASes).
    ids = torch.arange(n_boxes) if n_boxes < 10 else torch.from_numpy(np.sort(g.permutation(n_boxes)[:30]))
    bvh_stages = NumbaTLASStages(table)
    pairs = bvh_stages.candidate_pairs(rays, ids, t_limit, None)
    assert bvh_stages._bvhs, "the BVH walk answered"
    brute = NumbaTLASStages(table, broad_phase="all_boxes").candidate_pairs(rays, ids, t_limit, None)
    ref = TorchTLASStages(table).candidate_pairs(rays, ids, t_limit, None)
    assert 500 < pairs[0].numel() < len(rays) * len(ids) // 4
    for got, other in ((pairs, brute), (pairs, ref)):
        assert torch.equal(got[0], other[0]) and torch.equal(got[1], other[1]) and got[2] is None and other[2] is None


def test_unknown_broad_phase_is_refused():
    with pytest.raises(ValueError, match="broad_phase must be"):
        NumbaTLASStages(_box_table(9, seed=0), broad_phase="grid")


@pytest.fixture(scope="module")
def coloured_blases():
    """A torus with uvs, vertex colours and coloured materials, and the same torus textured."""
    rng = np.random.default_rng(3)
    t = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=24, minor_sections=12)
    v = np.asarray(t.vertices, np.float32)
    extra = dict(face_material_ids=rng.integers(0, 2, len(t.faces)), uvs=rng.uniform(0, 1, (len(v), 2)).astype(np.float32),
                 vertex_colors=rng.uniform(0.2, 1.4, (len(v), 3)).astype(np.float32))
    plain = [MeshMaterial("a", np.array([0.9, 0.5, 0.2], np.float32)), MeshMaterial("b", np.array([0.3, 1.2, 0.6], np.float32))]
    texture = rng.uniform(0, 1, (8, 8, 3)).astype(np.float32)
    textured = [plain[0], MeshMaterial("b", np.array([0.3, 1.2, 0.6], np.float32), texture)]
    return MeshBLAS(Mesh(v, t.faces, materials=plain, **extra)), MeshBLAS(Mesh(v, t.faces, materials=textured, **extra))


@pytest.mark.parametrize("kind", ["identity", "moved", "grid16", "mixed"])
@pytest.mark.parametrize("inside", [False, True])
def test_fused_mesh_path_matches_group_by_group(kind, inside, blases, coloured_blases):
    """`NumbaTLASStages.intersect_fused` (Embree's raw answers merged, attributes of the final hits
    only) gives the Hits of the group-by-group stages bit for bit, `occluded_fused` their shadow answers: one-instance groups, gathered
    pairs (grid16: a BVH over 16 boxes; mixed: every box), uvs and vertex colours; a scene of
    textured meshes alone takes the group-by-group path."""
    coloured, textured = coloured_blases
    table = _scene(kind, coloured, blases[1]).table
    rays = _rays(6000, seed=7, inside=inside)
    if kind == "moved" and inside:
        rays = MOVED.apply_rays(rays)
    fused = NumbaTLASStages(table)
    assert fused.fused_meshes and fused.intersect_fused(rays, _scene(kind, coloured, blases[1])._groups[False]) is not None
    fused_scene = _scene(kind, coloured, blases[1], stages=NumbaTLASStages)
    ref_scene = _scene(kind, coloured, blases[1], stages=lambda t: NumbaTLASStages(t, fused_meshes=False))
    got, ref = fused_scene.intersect(rays), ref_scene.intersect(rays)
    assert ref.hit.sum() > 200 and (ref.albedo[ref.hit] != ref.albedo[ref.hit][:1]).any(dim=1).any()
    for f in fields(ref):
        assert torch.equal(getattr(got, f.name), getattr(ref, f.name)), f.name
    # Shadow rays: finite intervals ending short of and beyond the surfaces.
    shadow = Rays(rays.origins, rays.directions, rays.t_min, torch.where(torch.arange(len(rays)) % 2 == 0, ref.t * 0.999, ref.t * 1.5 + 0.1))
    assert fused_scene.stages.occluded_fused(shadow, fused_scene._groups[False]) is not None
    blocked = ref_scene.occluded(shadow)
    assert 100 < int(blocked.sum()) < len(rays) - 100
    assert torch.equal(fused_scene.occluded(shadow), blocked)
    assert torch.equal(fused_scene.occluded(rays), ref_scene.occluded(rays))
    with_texture = _scene(kind, textured, blases[1])
    assert (with_texture.stages.intersect_fused(rays, with_texture._groups[False]) is None) == (kind != "mixed")


@pytest.fixture(scope="module")
def neural_blas():
    """An untrained LSNIF model of a sphere (random table): a BLAS the fused path does not trace."""
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel

    s = trimesh.creation.icosphere(subdivisions=3, radius=0.8)
    config = LSNIFConfig.preset("lq", voxel={"resolution": 16}, encoding={"resolutions": (16, 32), "log2_table_size": 12},
                                features={"max_points": 8})  # fmt: skip
    model = LSNIFModel.from_mesh(Mesh(s.vertices, s.faces), config)
    with torch.no_grad():  # network rays both hit (~55%) and miss
        model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(3))
        model.network.output.bias[0] = 0.3
    return model


@pytest.mark.parametrize("layout", ["neural_first", "neural_between", "grid_and_neural", "textured_and_neural"])
def test_fused_path_with_other_blases_matches_group_by_group(layout, blases, coloured_blases, neural_blas):
    """Scenes mixing Embree meshes with neural models (and textured meshes) answer through the fused
    path, the other groups taking their group-by-group step in their turn: the same Hits bit for
    bit and the same shadow answers as group by group, whatever the groups' order."""
    coloured, textured = coloured_blases
    sphere = blases[1]
    layouts = {
        "neural_first": [(neural_blas, Transform(), [0]), (coloured, MOVED, [1, 2]), (sphere, TILTED, [3])],
        "neural_between": [(coloured, Transform(), [0, 1]), (neural_blas, MOVED, [2]), (neural_blas, TILTED, [3]),
                           (sphere, Transform.translate([0.3, -0.4, 0.2]), [1])],
        "grid_and_neural": [(coloured, xf, [k % 3]) for k, xf in enumerate(GRID[:6])]
                           + [(neural_blas, xf, [3]) for xf in GRID[6:]],
        "textured_and_neural": [(textured, TILTED, [0, 1]), (neural_blas, Transform(), [2]), (coloured, MOVED, [3, 1])],
    }

    def scene(fused: bool) -> SceneAccel:
        instances = [Instance(b, xf, torch.tensor(m), name=str(i)) for i, (b, xf, m) in enumerate(layouts[layout])]
        return SceneAccel(instances, stages=lambda t: NumbaTLASStages(t, fused_meshes=fused))

    fused_scene, ref_scene = scene(True), scene(False)
    for inside in (False, True):
        rays = _rays(6000, seed=11, inside=inside)
        assert fused_scene.stages.intersect_fused(rays, fused_scene._groups[False]) is not None
        got, ref = fused_scene.intersect(rays), ref_scene.intersect(rays)
        from_model = torch.tensor([isinstance(fused_scene.instances[int(k)].blas, type(neural_blas)) for k in ref.instance_id[ref.hit]])
        assert int(from_model.sum()) > 30 and int((~from_model).sum()) > 30  # both kinds win rays
        for f in fields(ref):
            assert torch.equal(getattr(got, f.name), getattr(ref, f.name)), f.name
        t_end = torch.where(ref.hit, ref.t, 5.0)
        shadow = Rays(rays.origins, rays.directions, rays.t_min, torch.where(torch.arange(len(rays)) % 2 == 0, t_end * 0.999, t_end * 1.5 + 0.1))
        assert fused_scene.stages.occluded_fused(shadow, fused_scene._groups[False]) is not None
        blocked = ref_scene.occluded(shadow)
        assert 100 < int(blocked.sum()) < len(rays) - 100
        assert torch.equal(fused_scene.occluded(shadow), blocked)
        assert torch.equal(fused_scene.occluded(rays), ref_scene.occluded(rays))


def test_torch_stages_write_each_ray_once_and_take_empty_batches(blases, monkeypatch):
    # A CUDA scatter with repeated indices keeps any one of the writes (per field): tied instances
    # must be resolved before it, as the CPU's last write is.
    from neuralrt.rays import Hits

    torus, _ = blases
    scatter = Hits.scatter_

    def unique_rows(self, index, other):
        assert index.numel() == index.unique().numel(), "a ray written twice"
        return scatter(self, index, other)

    monkeypatch.setattr(Hits, "scatter_", unique_rows)
    accel = SceneAccel([Instance(torus, Transform(), torch.tensor([0])), Instance(torus, Transform(), torch.tensor([1]))],
                       stages=TorchTLASStages)
    h = accel.intersect(_rays(4000, seed=2))
    assert h.hit.sum() > 100 and (h.instance_id[h.hit] == 1).all()
    empty = Rays(torch.zeros(0, 3), torch.zeros(0, 3))
    ray_idx, inst_idx, _ = accel.stages.candidate_pairs(empty, torch.tensor([0, 1]), torch.zeros(0), None)
    assert ray_idx.numel() == 0 and inst_idx.numel() == 0
