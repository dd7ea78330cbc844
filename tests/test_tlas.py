"""Scene TLAS: instancing under transforms gives the hits of the transformed geometry."""

import numpy as np
import torch
import trimesh

from neuralrt import Mesh, MeshBLAS, Rays, Transform
from neuralrt.accel.tlas import Instance, SceneAccel
from neuralrt.geometry.mesh import MeshMaterial


def _torus_mesh():
    t = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=48, minor_sections=24)
    return Mesh(t.vertices, t.faces, name="torus")


def _random_rays(n, seed, radius=6.0):
    g = torch.Generator().manual_seed(seed)
    o = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1) * radius
    target = torch.rand(n, 3, generator=g) * 4 - 2
    return Rays(o, target - o)


XFORMS = [
    Transform.translate([1.5, 0, 0]) @ Transform.rotate([0, 1, 1], 40) @ Transform.scale([0.7, 1.3, 0.5]),
    Transform.translate([-1.2, 0.5, -0.3]) @ Transform.rotate([1, 0, 0], 75) @ Transform.scale(0.6),
]


def test_instances_match_baked_geometry():
    mesh = _torus_mesh()
    shared = MeshBLAS(mesh)
    accel = SceneAccel(
        [Instance(shared, xf, torch.tensor([k]), name=f"i{k}") for k, xf in enumerate(XFORMS)]
    )
    # the same world geometry, baked into one mesh
    baked_v = [xf.apply_points(torch.from_numpy(mesh.vertices)).numpy() for xf in XFORMS]
    baked = Mesh(
        np.concatenate(baked_v),
        np.concatenate([mesh.faces, mesh.faces + len(mesh.vertices)]),
        face_material_ids=np.repeat([0, 1], len(mesh.faces)),
        materials=[MeshMaterial("first"), MeshMaterial("second")],
    )
    ref = MeshBLAS(baked).intersect(rays := _random_rays(4000, 3))
    got = accel.intersect(rays)
    assert got.hit.sum() > 500
    assert torch.equal(got.hit, ref.hit)
    h = got.hit
    assert torch.allclose(got.t[h], ref.t[h], rtol=1e-4, atol=1e-5)
    assert torch.equal(got.material_id[h], ref.material_id[h])
    assert torch.equal(got.instance_id[h], ref.material_id[h])  # material k <-> instance k here
    # geometric normals agree up to orientation of the baked copy; shading normals close
    dots = (got.geometric_normal[h] * ref.geometric_normal[h]).sum(1)
    assert (dots > 0.999).float().mean() > 0.99
    assert torch.equal(accel.occluded(rays), ref.hit)


def test_instancing_shares_one_blas_and_counts_memory_once():
    blas = MeshBLAS(_torus_mesh())
    accel = SceneAccel([Instance(blas, xf, torch.tensor([0])) for xf in XFORMS * 3])
    assert len(accel.unique_blases) == 1
    assert accel.memory_bytes().parts["bvh_a"] == blas.memory_bytes().parts["bvh_a"]


def test_closest_of_overlapping_instances_and_t_max():
    blas = MeshBLAS(_torus_mesh())
    near = Instance(blas, Transform.translate([0, 0, 1.0]), torch.tensor([0]))
    far = Instance(blas, Transform.translate([0, 0, -1.0]), torch.tensor([1]))
    accel = SceneAccel([far, near])
    o = torch.tensor([[1.0, 0.0, 10.0], [1.0, 0.0, 10.0]])
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    h = accel.intersect(Rays(o, d, t_max=torch.tensor([100.0, 8.5])))
    assert h.hit.tolist() == [True, False]
    assert h.instance_id[0] == 1 and h.material_id[0] == 0
    assert abs(h.t[0].item() - (10 - 1.3)) < 1e-3
    assert torch.allclose(h.normal[0], torch.tensor([0.0, 0.0, 1.0]), atol=1e-2)


def test_camera_blas_answers_camera_rays_only():
    torus = MeshBLAS(_torus_mesh())
    sphere_tm = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    sphere = MeshBLAS(Mesh(sphere_tm.vertices, sphere_tm.faces))
    accel = SceneAccel([Instance(torus, Transform(), torch.tensor([0]), camera_blas=sphere)])
    rays = Rays(torch.tensor([[0.0, 0.0, 5.0]]), torch.tensor([[0.0, 0.0, -1.0]]))
    assert not accel.intersect(rays).hit[0]  # torus hole
    assert accel.intersect(rays, camera_rays=True).hit[0]  # sphere


def test_t_max_at_a_hit_keeps_it_through_transformed_instances():
    # The interval includes its end. The broad phase tests rays against rounded float32 world
    # boxes: a flat floor and rotated instances hit at grazing angles lost 2,690 of 11,982 hits
    # here before the boxes were grown (BROAD_PHASE_GROWTH).
    from neuralrt.scene.loader import load_scene

    accel = load_scene("builtin:instances?detail=0").accel
    g = torch.Generator().manual_seed(0)
    b = accel.bounds
    origins = b.center + 0.8 * b.diagonal * torch.nn.functional.normalize(torch.randn(20000, 3, generator=g), dim=1)
    targets = b.lo + torch.rand(20000, 3, generator=g) * (b.hi - b.lo)
    rays = Rays(origins.float(), (targets - origins).float())
    h = accel.intersect(rays)
    assert int(h.hit.sum()) > 10000
    at_hit = Rays(rays.origins, rays.directions, t_max=torch.where(h.hit, h.t, 1.0))
    kept = accel.intersect(at_hit)
    assert torch.equal(kept.hit, h.hit) and torch.equal(kept.t, h.t) and torch.equal(accel.occluded(at_hit), h.hit)
