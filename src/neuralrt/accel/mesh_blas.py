"""Exact ray/triangle intersection: the classical baseline and the ground truth every neural model
is trained against.

`MeshBLAS(mesh, device=...)` picks the backend for the device once, at construction: Embree (through
`embreex`) on the CPU; on CUDA, OptiX through Mitsuba 3 (`mesh_blas_mitsuba.py`, the optional
``gpu`` extra), or Embree on the host with a one-line notice when Mitsuba is missing.
Every backend answers the same contract, tested against each other in tests/test_mesh_blas_backends.py.
"""

from __future__ import annotations

import sys
from abc import ABC, abstractmethod

import numpy as np
import torch
from torch import Tensor

from ..devices import check_device
from ..errors import ConfigError
from ..fork_guard import check_not_forked
from ..geometry.mesh import Mesh, check_float32_extent
from ..geometry.tangents import vertex_tangents
from ..arguments import check_count
from ..host_threads import numba_threads
from ..rays import AABB, Hits, Rays, check_rays
from . import mesh_blas_kernels as kernels
from .blas import MemoryReport
from .embree_api import TriangleScene
from .normal_mapping import interpolate_numpy, mapped_normals_numpy

__all__ = ["MeshBLAS", "EmbreeMeshBLAS"]

# Stands in for a missing per-vertex attribute (the kernels take arrays, never None).
_NO_ATTRIBUTE = np.zeros((1, 3), np.float32)


_fallback_noticed = False  # the CUDA-without-Mitsuba notice is printed once per process

FALLBACK_NOTICE = ("neuralrt: note: Mitsuba 3 is not installed (pip install mitsuba: the gpu extra): "
                   "exact rays on {device} are traced by Embree on the host")


def _rays_as_numpy(rays: Rays) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """float32 CPU numpy views of origins, directions, t_min, t_max (no copies on CPU)."""
    return tuple(x.detach().cpu().numpy().astype(np.float32, copy=False)
                 for x in (rays.origins, rays.directions, rays.t_min, rays.t_max))  # fmt: skip


def _checked_arguments(mesh, device) -> torch.device:
    """The BLAS's device (`check_device`), after one-line errors for a ``mesh`` that is not a `Mesh`
    (a path, None) or a device this process cannot use: raised before a backend is picked."""
    if not isinstance(mesh, Mesh):
        raise ConfigError(f"mesh: expected a neuralrt.Mesh, got {type(mesh).__name__} (read a mesh file with neuralrt.load_mesh(path))")
    check_float32_extent(mesh)  # else rays would silently miss it (Embree and OptiX trace in float32)
    return check_device("cpu" if device is None else device)


def _backend_for(device: torch.device) -> type["MeshBLAS"]:
    """The `MeshBLAS` implementation for ``device``: decided once, when a BLAS is built."""
    if device.type != "cuda":
        return EmbreeMeshBLAS
    from . import mesh_blas_mitsuba

    if mesh_blas_mitsuba.mitsuba_variant_available(device):
        return mesh_blas_mitsuba.MitsubaMeshBLAS
    global _fallback_noticed
    if not _fallback_noticed:
        _fallback_noticed = True
        print(FALLBACK_NOTICE.format(device=device.type), file=sys.stderr)
    return EmbreeMeshBLAS


class MeshBLAS(ABC):
    """Exact closest-hit and any-hit queries over one triangle mesh, in the mesh's own space.

    ``MeshBLAS(mesh, device=None, threads=None)`` builds the backend for ``device`` (default CPU):
    an `EmbreeMeshBLAS` on the CPU, a `MitsubaMeshBLAS` (OptiX) on CUDA when Mitsuba 3 is installed.
    ``threads``: the CPU threads a query uses (Embree's calls and the numba passes around them;
    default: numba's thread count, all cores).
    Built once per mesh (instances share it through the scene TLAS). A ``mesh`` that is not a `Mesh`
    raises `ConfigError`, a device this process cannot use (``cuda`` on a CPU-only torch) `DeviceError`.

    Contract, whatever the backend: ``intersect(rays)`` returns `Hits` on ``rays.device`` (the
    closest hit in ``[t_min, t_max]``: t in units of the direction's length, triangle index,
    shading normal interpolated from ``mesh.vertex_normals``, unit face normal, UV, albedo =
    material base colour x texture x vertex colour clipped to [0, 1], material id);
    ``occluded(rays)`` returns [N] bool. Rays with NaN/Inf origins or directions, zero directions
    or empty/NaN intervals are misses.
    """

    mesh: Mesh
    bounds: AABB
    secondary_offset: float
    device: torch.device
    backend: str  # "embree", or the Mitsuba variant ("cuda_ad_rgb", "llvm_ad_rgb")

    def __new__(cls, mesh: Mesh, device=None, threads: int | None = None):
        check_count("threads", threads)  # (0, -1, "2" and 2.5 were clamped or cast silently)
        check_not_forked("MeshBLAS")
        checked = _checked_arguments(mesh, device)
        if cls is MeshBLAS:
            cls = _backend_for(checked)
        return super().__new__(cls)

    def _init_common(self, mesh: Mesh, device) -> None:
        """What every backend shares: the mesh, its bounds (CPU tensors), the secondary-ray offset."""
        self.mesh = mesh
        self.device = _checked_arguments(mesh, device)
        lo, hi = mesh.bounds
        self.bounds = AABB(torch.from_numpy(lo.copy()), torch.from_numpy(hi.copy()))
        # Offset for secondary rays: a few float32 ulps of the object's extent.
        self.secondary_offset = float(1e-4 * max(self.bounds.diagonal, 1e-12))
        self._memory: MemoryReport | None = None

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.mesh.name!r}, {self.mesh.num_triangles} triangles, {self.backend})"

    def __reduce__(self):
        """copy, deepcopy and pickle rebuild the backend from the mesh (Embree's scene and Mitsuba's
        are native objects that cannot be copied); `__new__` needs the mesh to pick the backend."""
        return type(self), (self.mesh, self.device, getattr(self, "threads", None))

    @abstractmethod
    def intersect(self, rays: Rays) -> Hits:
        """Closest hit per ray (the backend's)."""

    @abstractmethod
    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: any hit within [t_min, t_max] (the backend's)."""

    @property
    def material_names(self) -> list[str]:
        """Material slot names of the mesh, in ``material_id`` order (the BLAS contract)."""
        return [m.name for m in self.mesh.materials]

    def _material_albedo(self) -> np.ndarray:
        """[M, 3] float32 base colour per material (read per call: materials may be edited)."""
        return np.stack([np.asarray(x.base_color, np.float32).reshape(3) for x in self.mesh.materials])

    # -- memory ------------------------------------------------------------------------------------
    def memory_bytes(self) -> MemoryReport:
        """Vertex/index buffers plus the SAH BVH (the LSNIF paper's "BVH A") we build for this mesh:
        a backend-independent figure (Embree's and OptiX's own layouts are not exposed)."""
        if self._memory is None:
            from .classical_memory import classical_memory

            report = classical_memory(self.mesh)
            self._memory = MemoryReport({"mesh": report.mesh_bytes, "bvh_a": report.bvh_a_bytes})
        return self._memory


class _HitArrays:
    """Uninitialised numpy outputs of `MeshBLAS.intersect`; the kernel fills every row."""

    def __init__(self, n: int, barycentrics: bool):
        self.hit = np.empty(n, np.bool_)
        self.t = np.empty(n, np.float32)
        self.normal = np.empty((n, 3), np.float32)
        self.geo = np.empty((n, 3), np.float32)
        self.uv = np.empty((n, 2), np.float32)
        self.albedo = np.empty((n, 3), np.float32)
        self.mat = np.empty(n, np.int64)
        self.prim = np.empty(n, np.int64)
        self.instance = np.full(n, -1, np.int64)  # a mesh on its own: no instance
        # Embree's (u, v), kept only where textures are applied afterwards.
        self.bary_u = np.empty(n if barycentrics else 0, np.float32)
        self.bary_v = np.empty(n if barycentrics else 0, np.float32)

    def records(self) -> tuple[np.ndarray, ...]:
        """The kernel's outputs, in its argument order."""
        return self.hit, self.t, self.normal, self.geo, self.uv, self.albedo, self.mat, self.prim, self.instance, self.bary_u, self.bary_v

    def hits(self, device) -> Hits:
        """The records as `Hits` on ``device``."""
        return Hits(*(torch.from_numpy(x).to(device) for x in (self.hit, self.t, self.normal, self.geo, self.uv, self.albedo,
                                                               self.mat, self.prim, self.instance)))  # fmt: skip


class EmbreeMeshBLAS(MeshBLAS):
    """`MeshBLAS` on the CPU: Embree 4 through its C API (`embree_api`), each query one parallel
    numba pass (validate, trace, interpolate) on ``threads`` threads. Answers rays on any device
    (moved to the host and back)."""

    backend = "embree"

    def __init__(self, mesh: Mesh, device=None, threads: int | None = None):
        self._init_common(mesh, device)
        # Shared vertices and an index buffer (18 B per triangle in Embree's copy) instead of a
        # [F, 3, 3] triangle soup (36 B, plus as much again for the soup we would build for it).
        self._scene = TriangleScene(mesh.vertices, mesh.faces)
        self._face_normals = mesh.face_normals()
        self.threads = threads  # threads of a query; None: numba.get_num_threads()
        self._tangents: np.ndarray | None = None  # [V, 4], built when a material first has a normal map

    # -- queries ---------------------------------------------------------------------------------
    def intersect(self, rays: Rays) -> Hits:
        """Closest hit per ray: t, triangle, shading/geometric normal, UV, albedo, material id."""
        check_rays(rays, "intersect")
        n = len(rays)
        if n == 0:
            return Hits.empty(0, rays.device)
        textured = self.textured
        out = _HitArrays(n, barycentrics=textured)
        with numba_threads(self.threads):
            kernels.intersect_rays(self._scene.handle, kernels.embree_workers(n), *_rays_as_numpy(rays),
                                   *self.surface_tables(), not textured, *out.records())  # fmt: skip
        if textured:
            self._apply_textures_(out.albedo, out.hit, out.mat, out.uv, out.prim, out.bary_u, out.bary_v)
            self._apply_normal_maps_(out.normal, out.hit, out.mat, out.uv, out.prim, out.bary_u, out.bary_v)
        return out.hits(rays.device)

    # -- raw queries (the scene TLAS's fused path: attributes only for the closest hit over all instances)
    @property
    def textured(self) -> bool:
        """Does a hit need per-material work after the kernel (a texture, or a normal map)?"""
        return any(material.texture is not None or material.normal_map is not None for material in self.mesh.materials)

    @property
    def scene_handle(self) -> int:
        """The Embree scene the scene TLAS's fused kernels trace (`embree_api.TriangleScene.handle`)."""
        return self._scene.handle

    def trace_closest(self, shifted: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> tuple[np.ndarray, ...]:
        """Embree's closest hits of prepared rays (`tlas_kernels.pair_embree_rays`' preparation:
        origin moved to t_min, interval length; all valid): primID (-1: miss), t_far from the
        shifted origin, u, v; ``tfar`` is overwritten."""
        n = shifted.shape[0]
        prim, u, v = np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32)
        with numba_threads(self.threads):
            kernels.closest_prepared(self._scene.handle, kernels.embree_workers(n), shifted, directions, tfar, prim, u, v)
        return prim, tfar, u, v

    def trace_occluded(self, shifted: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> np.ndarray:
        """`trace_closest` for shadow rays: int32 per ray, >= 0 where blocked."""
        geom = np.empty(shifted.shape[0], np.int32)
        with numba_threads(self.threads):
            kernels.occluded_prepared(self._scene.handle, kernels.embree_workers(len(geom)), shifted, directions, tfar, geom)
        return geom

    def surface_tables(self) -> tuple:
        """The mesh arrays the hit attributes read after ``(p, u, v)`` (`tlas_kernels.finish_hits`): faces, face
        normals, vertex normals, face material ids, uvs, vertex colours, material base colours (read
        now: materials may be edited), use_uvs, use_vertex_colors."""
        m = self.mesh
        return (m.faces, self._face_normals, m.vertex_normals, m.face_material_ids,
                m.uvs if m.uvs is not None else _NO_ATTRIBUTE, m.vertex_colors if m.vertex_colors is not None else _NO_ATTRIBUTE,
                self._material_albedo(), m.uvs is not None, m.vertex_colors is not None)  # fmt: skip

    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: does any triangle lie within [t_min, t_max]?"""
        check_rays(rays, "occluded")
        n = len(rays)
        if n == 0:
            return torch.zeros(0, dtype=torch.bool, device=rays.device)
        blocked = np.empty(n, np.bool_)
        with numba_threads(self.threads):
            kernels.occluded_rays(self._scene.handle, kernels.embree_workers(n), *_rays_as_numpy(rays), blocked)
        return torch.from_numpy(blocked).to(rays.device)

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
            colour *= interpolate_numpy(m.vertex_colors, m.faces[prim[idx]], bary_u[idx], bary_v[idx])
        albedo[idx] = np.clip(colour, 0.0, 1.0)

    def _apply_normal_maps_(self, normal, hit, mat, uv, prim, bary_u, bary_v) -> None:
        """Materials with a normal map: turn the shading normals in ``normal`` at their hits, in place."""
        m = self.mesh
        idx = np.nonzero(hit)[0]
        for k, material in enumerate(m.materials):
            if material.normal_map is None or m.uvs is None:
                continue
            sel = idx[mat[idx] == k]
            if len(sel):
                tangent = interpolate_numpy(self.tangents(), m.faces[prim[sel]], bary_u[sel], bary_v[sel])
                texel = sample_texture_bilinear(material.normal_map, uv[sel])
                normal[sel] = mapped_normals_numpy(normal[sel], tangent, texel)

    def tangents(self) -> np.ndarray:
        """[V, 4] vertex tangent frames (`geometry.tangents.vertex_tangents`), built on first use."""
        if self._tangents is None:
            m = self.mesh
            self._tangents = vertex_tangents(m.vertices, m.faces, m.vertex_normals, m.uvs)
        return self._tangents


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
