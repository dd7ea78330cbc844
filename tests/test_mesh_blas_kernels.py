"""MeshBLAS's fused kernels and threaded chunks against a plain numpy reference of the same query."""

import numpy as np
import pytest
import torch
import trimesh

from neuralrt import Mesh, MeshBLAS, Rays, host_threads
from neuralrt.accel.mesh_blas import sample_texture_bilinear
from neuralrt.geometry.mesh import MeshMaterial


def embreex_scene(mesh: Mesh):
    """The same mesh in embreex's own Embree scene: an independent path to the same library."""
    from embreex import mesh_construction, rtcore_scene

    scene = rtcore_scene.EmbreeScene()
    mesh_construction.TriangleMesh(scene, mesh.vertices.astype(np.float32), mesh.faces.astype(np.int32))
    return scene


def reference_intersect(blas: MeshBLAS, rays: Rays) -> dict[str, np.ndarray]:
    """Unfused numpy: validate, shift origins to t_min, one call to embreex (not our Embree
    bindings), interpolate attributes."""
    o, d, t_min, t_max = (x.numpy() for x in (rays.origins, rays.directions, rays.t_min, rays.t_max))
    valid = (np.isfinite(o).all(1) & np.isfinite(d).all(1) & (np.abs(d).max(1) > 0)
             & ~np.isnan(t_min) & ~np.isnan(t_max) & (t_max > t_min))  # fmt: skip
    direction = np.where(valid[:, None], d, [1.0, 0.0, 0.0]).astype(np.float32)
    start = np.where(valid & np.isfinite(t_min), t_min, 0).astype(np.float32)
    shifted = (np.where(valid[:, None], o, 0).astype(np.float32) + start[:, None] * direction).astype(np.float32)
    tfar = np.where(valid, np.minimum(t_max - t_min, np.float32(1e37)), -1.0).astype(np.float32)
    tfar = np.where(valid & ~np.isfinite(tfar), np.float32(1e37), tfar).astype(np.float32)
    res = embreex_scene(blas.mesh).run(shifted, direction, dists=tfar, output=1)
    prim = res["primID"].astype(np.int64)
    hit = (prim >= 0) & valid
    prim = np.where(hit, prim, -1)
    m, idx = blas.mesh, np.nonzero(hit)[0]
    faces = m.faces[prim[idx]]
    bu, bv = res["u"][idx, None], res["v"][idx, None]
    bw = 1.0 - bu - bv

    def interp(attr):
        return bw * attr[faces[:, 0]] + bu * attr[faces[:, 1]] + bv * attr[faces[:, 2]]

    n = len(o)
    out = {"hit": hit, "t": np.where(hit, res["tfar"] + start, np.inf).astype(np.float32), "primitive_id": prim,
           "normal": np.zeros((n, 3), np.float32), "geometric_normal": np.zeros((n, 3), np.float32),
           "uv": np.zeros((n, 2), np.float32), "albedo": np.ones((n, 3), np.float32),
           "material_id": np.full(n, -1, np.int64)}  # fmt: skip
    geo = m.face_normals()[prim[idx]]
    out["geometric_normal"][idx] = geo
    sn = interp(m.vertex_normals)
    length = np.linalg.norm(sn, axis=1, keepdims=True)
    out["normal"][idx] = np.where(length > 1e-12, sn / np.maximum(length, 1e-12), geo)
    mat = m.face_material_ids[prim[idx]].astype(np.int64)
    out["material_id"][idx] = mat
    if m.uvs is not None:
        out["uv"][idx] = interp(m.uvs)
    base = np.stack([np.asarray(x.base_color, np.float32) for x in m.materials])
    albedo = base[np.clip(mat, 0, len(base) - 1)]
    for k, material in enumerate(m.materials):
        if material.texture is not None and (mat == k).any():
            albedo[mat == k] *= sample_texture_bilinear(material.texture, out["uv"][idx][mat == k])
    if m.vertex_colors is not None:
        albedo *= interp(m.vertex_colors)
    out["albedo"][idx] = np.clip(albedo, 0, 1)
    return out


def _mesh(kind: str) -> Mesh:
    rng = np.random.default_rng(5)
    s = trimesh.creation.icosphere(subdivisions=3)
    v, f = s.vertices, s.faces
    textured = MeshMaterial("tex", np.array([0.8, 0.5, 1.3], np.float32), rng.uniform(size=(8, 16, 3)).astype(np.float32))
    materials = [MeshMaterial("a", np.array([1.4, 0.2, 0.6], np.float32)), textured, MeshMaterial("b")]
    face_mats = rng.integers(0, 3, len(f))  # ids into the 3 materials (into 2 for "colours", below)
    uvs = rng.uniform(-2, 2, (len(v), 2))
    colors = rng.uniform(0, 1.5, (len(v), 3))
    if kind == "plain":
        return Mesh(v, f)
    if kind == "colours":
        return Mesh(v, f, uvs=uvs, vertex_colors=colors, face_material_ids=face_mats % 2, materials=materials[::2])
    normals = np.where(rng.uniform(size=(len(v), 1)) < 0.3, 0.0, s.vertex_normals)  # some vanish
    return Mesh(v, f, vertex_normals=normals, uvs=uvs, vertex_colors=colors, face_material_ids=face_mats, materials=materials)


def _rays(n: int, seed: int) -> Rays:
    """Rays around a unit sphere, with every kind of invalid ray and interval spread through."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3)) * 1.5
    d = rng.uniform(-1, 1, (n, 3)) - o  # towards the sphere's box
    t_min = np.where(rng.uniform(size=n) < 0.3, rng.uniform(-1, 2, n), 0.0)
    t_max = np.where(rng.uniform(size=n) < 0.3, rng.uniform(0, 4, n), np.inf)
    bad = rng.permutation(n)[:700].reshape(7, 100)
    o[bad[0], 0] = np.nan
    d[bad[1], 1] = np.inf
    d[bad[2]] = 0.0
    t_min[bad[3]] = np.nan
    t_max[bad[4]] = np.nan
    t_min[bad[5]] = -np.inf  # valid: starts at the origin
    t_max[bad[6]] = -1.0  # empty interval
    return Rays(*(torch.from_numpy(np.asarray(x, np.float32)) for x in (o, d, t_min, t_max)))


@pytest.mark.parametrize("kind", ["plain", "colours", "textured"])
def test_intersect_bit_identical_to_numpy_reference(kind):
    rays = _rays(3 * host_threads.CHUNK_ROWS + 123, seed=1)  # several chunks, a partial last one
    blas = MeshBLAS(_mesh(kind), threads=2)
    got, ref = blas.intersect(rays), reference_intersect(blas, rays)
    assert 0.2 < ref["hit"].mean() < 0.8
    for name, expected in ref.items():
        value = getattr(got, name).numpy()
        assert value.dtype == expected.dtype, name
        np.testing.assert_array_equal(value, expected, err_msg=name)
    assert (got.instance_id == -1).all()
    assert torch.equal(blas.occluded(rays), torch.from_numpy(ref["hit"]))


def test_thread_count_does_not_change_results():
    mesh, rays = _mesh("colours"), _rays(2 * host_threads.CHUNK_ROWS + 7, seed=2)
    one, four = MeshBLAS(mesh, threads=1), MeshBLAS(mesh, threads=4)
    a, b = one.intersect(rays), four.intersect(rays)
    for name in ("hit", "t", "normal", "uv", "albedo", "material_id", "primitive_id"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert torch.equal(one.occluded(rays), four.occluded(rays))


@pytest.mark.parametrize("n, threads", [(0, 2), (1, 16), (5000, 2), (1 << 18, 2), (1 << 18, 16), (3 * (1 << 15) + 5, 1)])
def test_chunks_cover_the_batch_and_feed_every_thread(n, threads):
    chunks = host_threads.chunk_slices(n, threads)
    bounds = [0] + [c.stop for c in chunks]
    assert [c.start for c in chunks] == bounds[:-1] and bounds[-1] == n  # consecutive, whole batch
    assert all(c.stop - c.start <= host_threads.CHUNK_ROWS for c in chunks)
    if n >= 2 * threads * host_threads.MIN_CHUNK_ROWS:
        assert len(chunks) >= 2 * threads  # 2^18 rays on 16 threads: 32 chunks, not 8
    sizes = [c.stop - c.start for c in chunks]
    assert not sizes or max(sizes) - min(sizes) <= 1  # equal to a row: 5,000 rays on 2 threads are 2,500 + 2,500


def test_strided_inputs_match_contiguous():
    blas = MeshBLAS(_mesh("plain"))
    rays = _rays(5000, seed=3)
    strided = Rays(rays.origins.t().contiguous().t(), rays.directions.t().contiguous().t(), rays.t_min, rays.t_max)
    # (Rays keeps contiguous rows: each other layout compiled the kernel again, ~4 s)
    assert strided.origins.is_contiguous() and strided.directions.is_contiguous()
    a, b = blas.intersect(rays), blas.intersect(strided)
    assert torch.equal(a.t, b.t) and torch.equal(a.primitive_id, b.primitive_id)
    shared_direction = Rays(rays.origins, torch.tensor([[0.3, -0.2, 1.0]]).expand(5000, 3))  # stride 0
    assert torch.equal(
        blas.intersect(shared_direction).t,
        blas.intersect(Rays(rays.origins, shared_direction.directions.contiguous())).t,
    )


def test_rays_through_vertices_as_embreex_answers_them():
    """Our Embree scene is built as embreex builds its own (robust mode): rays aimed exactly at a
    mesh's vertices, where a non-robust scene lets some through, get the same
    hits and distances as embreex's scene gives them."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    mesh = Mesh(sphere.vertices, sphere.faces)
    eyes = np.random.default_rng(3).normal(size=(8, 1, 3)) * 3
    origins = np.broadcast_to(eyes, (8, len(mesh.vertices), 3)).reshape(-1, 3).astype(np.float32)
    directions = (np.tile(mesh.vertices, (8, 1)) - origins).astype(np.float32)
    n = len(origins)
    rays = Rays(torch.from_numpy(origins), torch.from_numpy(directions), torch.zeros(n), torch.full((n,), 3.0))
    hits = MeshBLAS(mesh).intersect(rays)
    ref = embreex_scene(mesh).run(origins, directions, dists=np.full(n, 3.0, np.float32), output=1)
    assert torch.equal(hits.hit, torch.from_numpy(ref["primID"] >= 0))
    np.testing.assert_array_equal(hits.t.numpy()[hits.hit.numpy()], ref["tfar"][ref["primID"] >= 0])
