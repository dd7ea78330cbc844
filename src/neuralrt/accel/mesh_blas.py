"""Exact ray/triangle intersection with Embree (through `embreex`): the classical baseline and the
ground truth every neural model is trained against."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..geometry.mesh import Mesh
from ..rays import AABB, Hits, Rays
from . import mesh_blas_kernels as kernels
from .blas import MemoryReport

__all__ = ["MeshBLAS"]

# Stands in for a missing per-vertex attribute (the kernels take arrays, never None).
_NO_ATTRIBUTE = np.zeros((1, 3), np.float32)


def _as_float32_numpy(x: Tensor) -> np.ndarray:
    """A float32 CPU numpy view of ``x`` (no copy when it already is one)."""
    return x.detach().cpu().numpy().astype(np.float32, copy=False)


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
        """float32 numpy origins (advanced to t_min), directions, tfar; valid mask; t_min.

        Invalid rays become harmless placeholders (origin 0, direction +x, tfar -1): misses.
        """
        o, d, t_min, t_max = (_as_float32_numpy(x) for x in (rays.origins, rays.directions, rays.t_min, rays.t_max))
        n = len(o)
        shifted = np.empty((n, 3), np.float32)
        tfar = np.empty(n, np.float32)
        valid = np.empty(n, np.bool_)
        n_invalid = kernels.prepare_embree_rays(o, d, t_min, t_max, shifted, tfar, valid)
        if n_invalid or not d.flags.c_contiguous:
            # Embree gets no NaN/zero directions; valid rays keep theirs (no copy when all are).
            direction = np.empty((n, 3), np.float32)
            kernels.placeholder_directions(d, valid, direction)
            d = direction
        return shifted, d, tfar, valid, t_min

    def intersect(self, rays: Rays) -> Hits:
        """Closest hit per ray: t, triangle, shading/geometric normal, UV, albedo, material id."""
        n = len(rays)
        if n == 0:
            return Hits.empty(0, rays.device)
        o, d, tfar, valid, t_min = self._embree_inputs(rays)
        res = self._scene.run(o, d, dists=tfar, output=1)  # embreex writes the hit distance into dists

        m = self.mesh
        textured = any(material.texture is not None for material in m.materials)
        hit = np.empty(n, np.bool_)
        t = np.empty(n, np.float32)
        normal = np.empty((n, 3), np.float32)
        geo = np.empty((n, 3), np.float32)
        uv = np.empty((n, 2), np.float32)
        albedo = np.empty((n, 3), np.float32)
        mat = np.empty(n, np.int64)
        prim = np.empty(n, np.int64)
        kernels.closest_hit_attributes(
            res["primID"], res["tfar"], res["u"], res["v"], valid, t_min,
            m.faces, self._face_normals, m.vertex_normals, m.face_material_ids,
            m.uvs if m.uvs is not None else _NO_ATTRIBUTE, m.vertex_colors if m.vertex_colors is not None else _NO_ATTRIBUTE,
            self._material_albedo(), m.uvs is not None, m.vertex_colors is not None, not textured,
            hit, t, normal, geo, uv, albedo, mat, prim,
        )  # fmt: skip
        if textured:
            self._apply_textures_(albedo, hit, mat, uv, prim, res["u"], res["v"])

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
        geom = self._scene.run(o, d, dists=tfar, query="OCCLUDED")
        blocked = np.empty(len(valid), np.bool_)
        kernels.occlusion_result(geom, valid, blocked)
        return torch.from_numpy(blocked).to(rays.device)

    def _material_albedo(self) -> np.ndarray:
        """[M, 3] float32 base colour per material (read per call: materials may be edited)."""
        return np.stack([np.asarray(x.base_color, np.float32).reshape(3) for x in self.mesh.materials])

    def _apply_textures_(self, albedo, hit, mat, uv, prim, bary_u, bary_v) -> None:
        """Textured meshes: multiply the base colours in ``albedo`` by texture (and vertex colour)
        at the hits, then clip, in place (the kernel left these steps to us)."""
        m = self.mesh
        idx = np.nonzero(hit)[0]
        hit_mat, hit_uv = mat[idx], uv[idx]
        colour = albedo[idx]
        for k, material in enumerate(m.materials):
            if material.texture is None:
                continue
            sel = hit_mat == k
            if sel.any():
                colour[sel] *= sample_texture_bilinear(material.texture, hit_uv[sel])
        if m.vertex_colors is not None:
            faces = m.faces[prim[idx]]
            bu, bv = bary_u[idx, None], bary_v[idx, None]
            bw = 1.0 - bu - bv
            vc = m.vertex_colors
            colour *= bw * vc[faces[:, 0]] + bu * vc[faces[:, 1]] + bv * vc[faces[:, 2]]
        albedo[idx] = np.clip(colour, 0.0, 1.0)

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
