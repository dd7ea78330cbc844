"""Exact ray/triangle intersection with Embree (through `embreex`): the classical baseline and the
ground truth every neural model is trained against."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..geometry.mesh import Mesh
from ..rays import AABB, Hits, Rays, valid_ray_mask
from .blas import MemoryReport

__all__ = ["MeshBLAS"]

# Embree works in float32; "infinite" t_max is passed as a large finite value.
_EMBREE_TFAR_MAX = 1e37


class MeshBLAS:
    """Exact closest-hit and any-hit queries over one triangle mesh, in the mesh's own space.

    Built once per mesh (instances share it through the scene TLAS). Rays with NaN/Inf origins or
    directions, zero directions or empty intervals are reported as misses.
    """

    def __init__(self, mesh: Mesh):
        from embreex import mesh_construction, rtcore_scene

        self.mesh = mesh
        self._scene = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(self._scene, np.ascontiguousarray(mesh.triangles(), dtype=np.float32))
        lo, hi = mesh.bounds
        self.bounds = AABB(torch.from_numpy(lo.copy()), torch.from_numpy(hi.copy()))
        # Offset for secondary rays: a few float32 ulps of the object's extent.
        self.secondary_offset = float(1e-4 * max(self.bounds.diagonal, 1e-12))
        self._face_normals = mesh.face_normals()
        self._memory: MemoryReport | None = None

    def __repr__(self) -> str:
        return f"MeshBLAS({self.mesh.name!r}, {self.mesh.num_triangles} triangles)"

    # -- queries ---------------------------------------------------------------------------------
    def _embree_inputs(self, rays: Rays) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """float32 numpy origins (advanced to t_min), directions, tfar; valid mask; t_min."""
        valid = valid_ray_mask(rays).cpu().numpy()
        o = rays.origins.detach().cpu().numpy().astype(np.float32, copy=False)
        d = rays.directions.detach().cpu().numpy().astype(np.float32, copy=False)
        t_min = rays.t_min.detach().cpu().numpy().astype(np.float32, copy=False)
        t_max = rays.t_max.detach().cpu().numpy().astype(np.float32, copy=False)
        # Embree always starts at tnear = 0: move the origin to t_min instead.
        # Invalid rays become harmless placeholders (reported as misses below).
        direction = np.where(valid[:, None], d, [1.0, 0.0, 0.0]).astype(np.float32)
        start = np.where(valid & np.isfinite(t_min), t_min, 0).astype(np.float32)
        shifted = np.where(valid[:, None], o, 0).astype(np.float32) + start[:, None] * direction
        tfar = np.where(valid, np.minimum(t_max - t_min, _EMBREE_TFAR_MAX), -1.0).astype(np.float32)
        tfar = np.where(valid & ~np.isfinite(tfar), _EMBREE_TFAR_MAX, tfar).astype(np.float32)
        return np.ascontiguousarray(shifted), np.ascontiguousarray(direction), np.ascontiguousarray(tfar), valid, t_min

    def intersect(self, rays: Rays) -> Hits:
        """Closest hit per ray: t, triangle, shading/geometric normal, UV, albedo, material id."""
        n = len(rays)
        if n == 0:
            return Hits.empty(0, rays.device)
        o, d, tfar, valid, t_min = self._embree_inputs(rays)
        res = self._scene.run(o, d, dists=tfar.copy(), output=1)  # embreex writes into dists
        prim = res["primID"].astype(np.int64)
        hit = (prim >= 0) & valid
        prim = np.where(hit, prim, -1)
        t = np.where(hit, res["tfar"] + t_min, np.inf).astype(np.float32)

        m = self.mesh
        idx = np.nonzero(hit)[0]
        faces = m.faces[prim[idx]]
        # Embree's (u, v) weight vertices 1 and 2 of the triangle.
        bu, bv = res["u"][idx, None], res["v"][idx, None]
        bw = 1.0 - bu - bv

        def interp(attr: np.ndarray) -> np.ndarray:
            return bw * attr[faces[:, 0]] + bu * attr[faces[:, 1]] + bv * attr[faces[:, 2]]

        normal = np.zeros((n, 3), np.float32)
        geo = np.zeros((n, 3), np.float32)
        uv = np.zeros((n, 2), np.float32)
        albedo = np.ones((n, 3), np.float32)
        mat = np.full(n, -1, np.int64)
        geo[idx] = self._face_normals[prim[idx]]
        sn = interp(m.vertex_normals)
        length = np.linalg.norm(sn, axis=1, keepdims=True)
        normal[idx] = np.where(length > 1e-12, sn / np.maximum(length, 1e-12), geo[idx])
        mat[idx] = m.face_material_ids[prim[idx]]
        if m.uvs is not None:
            uv[idx] = interp(m.uvs)
        albedo[idx] = self._surface_albedo(mat[idx], uv[idx], interp(m.vertex_colors) if m.vertex_colors is not None else None)

        dev = rays.device
        return Hits(
            hit=torch.from_numpy(hit).to(dev),
            t=torch.from_numpy(t).to(dev),
            normal=torch.from_numpy(normal).to(dev),
            geometric_normal=torch.from_numpy(geo).to(dev),
            uv=torch.from_numpy(uv).to(dev),
            albedo=torch.from_numpy(albedo).to(dev),
            material_id=torch.from_numpy(mat).to(dev),
            primitive_id=torch.from_numpy(prim).to(dev),
            instance_id=torch.full((n,), -1, dtype=torch.int64, device=dev),
        )

    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: does any triangle lie within (t_min, t_max)?"""
        if len(rays) == 0:
            return torch.zeros(0, dtype=torch.bool, device=rays.device)
        o, d, tfar, valid, _ = self._embree_inputs(rays)
        geom = self._scene.run(o, d, dists=tfar.copy(), query="OCCLUDED")
        return torch.from_numpy((geom >= 0) & valid).to(rays.device)

    def _surface_albedo(self, mat: np.ndarray, uv: np.ndarray, vertex_color: np.ndarray | None) -> np.ndarray:
        """Base colour x texture (bilinear, wrapped) x vertex colour, per hit."""
        m = self.mesh
        base = np.stack([np.asarray(x.base_color, np.float32) for x in m.materials])
        albedo = base[np.clip(mat, 0, len(base) - 1)]
        for k, material in enumerate(m.materials):
            if material.texture is None:
                continue
            sel = mat == k
            if sel.any():
                albedo[sel] *= sample_texture_bilinear(material.texture, uv[sel])
        if vertex_color is not None:
            albedo *= vertex_color
        return np.clip(albedo, 0.0, 1.0).astype(np.float32)

    # -- memory ------------------------------------------------------------------------------------
    def memory_bytes(self) -> MemoryReport:
        """Vertex/index buffers plus the SAH BVH (the LSNIF paper's "BVH A") we build for this mesh."""
        if self._memory is None:
            from .classical_memory import classical_memory

            report = classical_memory(self.mesh)
            self._memory = MemoryReport({"mesh": report.mesh_bytes, "bvh_a": report.bvh_a_bytes})
        return self._memory


def sample_texture_bilinear(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with wrap-around; ``texture`` row 0 is v = 1 (image convention)."""
    h, w = texture.shape[:2]
    x = (uv[:, 0] % 1.0) * w - 0.5
    y = (1.0 - uv[:, 1] % 1.0) * h - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0, x1 = x0 % w, (x0 + 1) % w
    y0, y1 = y0 % h, (y0 + 1) % h
    top = texture[y0, x0] * (1 - fx) + texture[y0, x1] * fx
    bottom = texture[y1, x0] * (1 - fx) + texture[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)
