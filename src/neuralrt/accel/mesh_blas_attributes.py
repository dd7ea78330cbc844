"""Hit attributes in torch, on the device of the hits: what `EmbreeMeshBLAS`'s numba pass computes
(`mesh_blas_kernels.surface_at` plus its texture and normal-map steps), for backends that report only
triangle index, distance and barycentrics (`MitsubaMeshBLAS`). Same rules, same order of float32
operations where it matters; results agree with the numba pass to rounding.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..geometry.mesh import Mesh
from ..geometry.tangents import vertex_tangents
from ..rays import Hits
from .normal_mapping import mapped_normals_torch
from ..render.materials import sample_texture  # the renderer's lookup: exact hits shade as the renderer samples

__all__ = ["MeshAttributeTables", "closest_hit_records"]

_NORMAL_EPS = 1e-12  # as mesh_blas_kernels: below it the interpolated normal counts as vanished


class MeshAttributeTables:
    """A mesh's per-vertex and per-face arrays as tensors on one device, built once per BLAS.

    Materials (base colours, textures) are read from ``mesh.materials`` on every call, since they
    may be edited; textures are uploaded once per texture array.
    """

    def __init__(self, mesh: Mesh, device: torch.device):
        def upload(array: np.ndarray | None) -> Tensor | None:
            return None if array is None else torch.from_numpy(np.ascontiguousarray(array)).to(device)

        self.mesh = mesh
        self.device = device
        self.faces = upload(mesh.faces.astype(np.int64))  # [F, 3]
        self.face_normals = upload(mesh.face_normals())  # [F, 3] unit
        self.vertex_normals = upload(mesh.vertex_normals)  # [V, 3]
        self.face_material_ids = upload(mesh.face_material_ids.astype(np.int64))  # [F]
        self.uvs = upload(mesh.uvs)  # [V, 2] or None
        self.vertex_colors = upload(mesh.vertex_colors)  # [V, 3] or None
        self._textures: dict[int, tuple[np.ndarray, Tensor]] = {}  # id(array) -> (array, tensor)
        self._tangents: Tensor | None = None  # [V, 4], built when a material first has a normal map

    def material_albedo(self) -> Tensor:
        """[M, 3] base colour per material, on the device."""
        base = np.stack([np.asarray(x.base_color, np.float32).reshape(3) for x in self.mesh.materials])
        return torch.from_numpy(base).to(self.device)

    def texture(self, array: np.ndarray) -> Tensor:
        """``array`` [H, W, 3] on the device (uploaded on first use; the array is kept so its id stays unique)."""
        entry = self._textures.get(id(array))
        if entry is None or entry[0] is not array:
            entry = (array, torch.from_numpy(np.ascontiguousarray(array, np.float32)).to(self.device))
            self._textures[id(array)] = entry
        return entry[1]

    def tangents(self) -> Tensor:
        """[V, 4] vertex tangent frames on the device (`geometry.tangents.vertex_tangents`)."""
        if self._tangents is None:
            m = self.mesh
            self._tangents = torch.from_numpy(vertex_tangents(m.vertices, m.faces, m.vertex_normals, m.uvs)).to(self.device)
        return self._tangents

    def nbytes(self) -> int:
        tensors = (self.faces, self.face_normals, self.vertex_normals, self.face_material_ids, self.uvs, self.vertex_colors)
        return sum(x.numel() * x.element_size() for x in tensors if x is not None)


def closest_hit_records(tables: MeshAttributeTables, prim: Tensor, t: Tensor, bary_u: Tensor, bary_v: Tensor) -> Hits:
    """`Hits` from a backend's raw answer, on its device.

    ``prim`` [N] integer triangle index, -1 on miss; ``t`` [N] float32 distance (any value on
    miss); ``bary_u``, ``bary_v`` [N] the barycentric weights of the triangle's vertices 1 and 2.
    Misses get t = inf, zero normals and uv, albedo 1, material and primitive id -1.
    """
    n = prim.shape[0]
    hit = prim >= 0
    p = torch.where(hit, prim, 0).long()  # misses read triangle 0; their rows are overwritten below
    corners = tables.faces[p]  # [N, 3]
    bw = 1.0 - bary_u - bary_v

    def interpolate(attribute: Tensor) -> Tensor:
        # bw * a + u * b + v * c, in this order (as the numba pass)
        at = attribute[corners]  # [N, 3, C]
        return bw[:, None] * at[:, 0] + bary_u[:, None] * at[:, 1] + bary_v[:, None] * at[:, 2]

    hit3 = hit[:, None]
    geometric = tables.face_normals[p]
    shading = interpolate(tables.vertex_normals)
    length = (shading * shading).sum(1, keepdim=True).sqrt()
    shading = torch.where(length > _NORMAL_EPS, shading / length, geometric)
    material = tables.face_material_ids[p]
    uv = interpolate(tables.uvs) if tables.uvs is not None else torch.zeros(n, 2, device=prim.device)

    base = tables.material_albedo()
    albedo = base[material.clamp(0, base.shape[0] - 1)]
    for k, entry in enumerate(tables.mesh.materials):
        if entry.texture is not None:
            textured = albedo * sample_texture(tables.texture(entry.texture), uv)
            albedo = torch.where((material == k)[:, None], textured, albedo)
    if tables.vertex_colors is not None:
        albedo = albedo * interpolate(tables.vertex_colors)
    albedo = albedo.clamp(0.0, 1.0)
    if tables.uvs is not None:
        for k, entry in enumerate(tables.mesh.materials):
            if entry.normal_map is not None:
                mapped = mapped_normals_torch(shading, interpolate(tables.tangents()), sample_texture(tables.texture(entry.normal_map), uv))
                shading = torch.where((material == k)[:, None], mapped, shading)

    zero, minus_one = torch.zeros((), device=prim.device), torch.full((), -1, dtype=torch.int64, device=prim.device)
    return Hits(
        hit=hit,
        t=torch.where(hit, t, torch.full((), float("inf"), device=prim.device)),
        normal=torch.where(hit3, shading, zero),
        geometric_normal=torch.where(hit3, geometric, zero),
        uv=torch.where(hit3, uv, zero),
        albedo=torch.where(hit3, albedo, torch.ones((), device=prim.device)),
        material_id=torch.where(hit, material, minus_one),
        primitive_id=torch.where(hit, p, minus_one),
        instance_id=minus_one.expand(n).clone(),
    )
