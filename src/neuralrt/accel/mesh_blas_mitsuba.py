"""`MeshBLAS` on CUDA: OptiX (hardware ray tracing) through Mitsuba 3's ``cuda_ad_rgb`` variant.

Mitsuba answers only the geometric query (``Scene.ray_intersect_preliminary``: distance, triangle,
barycentrics; ``Scene.ray_test`` for shadow rays); validation of the rays and the hit attributes
(`mesh_blas_attributes`) are ours, in torch on the device, under the same contract as
`EmbreeMeshBLAS`. Tensors cross between torch and Dr.Jit by DLPack without copies: rays go over as
seven contiguous float32 columns (a strided column view would be copied on the way).

The same class runs on CPU tensors with the ``llvm_ad_rgb`` variant (Dr.Jit's LLVM backend, with
Embree inside Mitsuba), so its logic is tested where no GPU is. Needs ``pip install mitsuba`` (the ``gpu`` extra).
"""

from __future__ import annotations

import functools
import importlib

import numpy as np
import torch
from torch import Tensor

from ..errors import DeviceError, NeuralRTError
from ..geometry.mesh import Mesh
from ..rays import Hits, Rays, check_rays, valid_ray_mask
from .mesh_blas import MeshBLAS
from .mesh_blas_attributes import MeshAttributeTables, closest_hit_records
from .mesh_blas_kernels import EMBREE_TFAR_MAX

__all__ = ["MitsubaMeshBLAS", "mitsuba_variant_available", "MITSUBA_VARIANTS"]

# Mitsuba variant per torch device type.
MITSUBA_VARIANTS = {"cuda": "cuda_ad_rgb", "cpu": "llvm_ad_rgb"}


@functools.cache
def _variant_available(device_type: str) -> bool:
    variant = MITSUBA_VARIANTS.get(device_type)
    if variant is None:
        return False
    try:
        import drjit

        # A trimmed install may list a variant it does not ship (seen: no llvm_ad_rgb in a CUDA bundle).
        importlib.import_module(f"mitsuba.{variant}")
    except ImportError:
        return False
    backend = drjit.JitBackend.CUDA if device_type == "cuda" else drjit.JitBackend.LLVM
    return bool(drjit.has_backend(backend))


def mitsuba_variant_available(device) -> bool:
    """Whether Mitsuba 3 is installed with a working variant for ``device`` (CUDA: ``cuda_ad_rgb``
    with a CUDA driver; CPU: ``llvm_ad_rgb`` with an LLVM library Dr.Jit can load)."""
    return _variant_available(torch.device(device).type)


class _VariantTypes:
    """The Dr.Jit / Mitsuba types of one variant, kept at construction: Mitsuba's variant is a
    process-wide setting that another BLAS (on another device) may change later."""

    def __init__(self, mi):
        self.Float, self.Int32, self.UInt32 = mi.Float, mi.Int32, mi.UInt32
        self.Point3f, self.Vector3f, self.Ray3f = mi.Point3f, mi.Vector3f, mi.Ray3f


def _build_scene(mesh: Mesh, variant: str):
    """A Mitsuba scene holding ``mesh`` alone, and the variant's types."""
    import mitsuba

    previous = mitsuba.variant()
    mitsuba.set_variant(variant)  # load_dict and traverse read the process-wide variant
    try:
        shape = mitsuba.Mesh(mesh.name or "mesh", len(mesh.vertices), len(mesh.faces))
        params = mitsuba.traverse(shape)
        params["vertex_positions"] = mitsuba.Float(np.ascontiguousarray(mesh.vertices, np.float32).reshape(-1))
        params["faces"] = mitsuba.UInt32(np.ascontiguousarray(mesh.faces, np.uint32).reshape(-1))
        params.update()
        scene = mitsuba.load_dict({"type": "scene", "shape": shape})
        return scene, _VariantTypes(mitsuba)
    finally:
        if previous is not None and previous != variant:
            mitsuba.set_variant(previous)


class MitsubaMeshBLAS(MeshBLAS):
    """`MeshBLAS` through Mitsuba 3: OptiX on CUDA (``cuda_ad_rgb``), Dr.Jit's LLVM backend on the
    CPU (``llvm_ad_rgb``, for tests). Rays must be on this BLAS's device."""

    def __init__(self, mesh: Mesh, device=None, threads: int | None = None):
        self._init_common(mesh, device)
        if self.device.type == "cuda" and self.device.index is None:
            self.device = torch.device("cuda", torch.cuda.current_device())
        if not mitsuba_variant_available(self.device):
            raise NeuralRTError(
                f"Mitsuba 3 with a working {MITSUBA_VARIANTS.get(self.device.type, 'variant')} for {self.device} "
                "is not available (pip install mitsuba: the gpu extra)"
            )
        self.backend = MITSUBA_VARIANTS[self.device.type]
        self._scene, self._types = _build_scene(mesh, self.backend)
        self._tables = MeshAttributeTables(mesh, self.device)
        self._placeholder = torch.tensor([[1.0], [0.0], [0.0]], device=self.device)  # direction of invalid rays
        self._zero, self._minus_one = torch.tensor(0.0, device=self.device), torch.tensor(-1.0, device=self.device)
        self._infinity = torch.tensor(float("inf"), device=self.device)

    # -- queries ---------------------------------------------------------------------------------
    def _check_device(self, rays: Rays, where: str) -> None:
        check_rays(rays, where)
        if rays.device.type != self.device.type:
            raise DeviceError(f"rays are on {rays.device} but this exact BLAS is on {self.device}: move them with rays.to()")

    def _trace_inputs(self, rays: Rays) -> tuple[Tensor, Tensor, Tensor]:
        """[7, N] contiguous float32 columns (origin moved to t_min, direction, t_far), the start
        [N] (t_min, 0 where it is -inf) and the length [N] (t_far's interval). Invalid rays get
        origin 0, direction +x and t_far = -1, and are not traced (the rules of
        `mesh_blas_kernels.embree_ray`). Mitsuba's ``maxt`` excludes its end and the interval
        includes it (as Embree's): t_far is one float32 step past the length, and closest hits
        beyond the length are dropped (`closest_hits`)."""
        o, d, t_min, t_max = rays.origins, rays.directions, rays.t_min, rays.t_max
        valid = valid_ray_mask(rays)
        start = torch.where(torch.isfinite(t_min), t_min, 0.0)
        length = t_max - t_min
        length = torch.where(length <= EMBREE_TFAR_MAX, length, float(EMBREE_TFAR_MAX))  # inf, NaN: the maximum
        columns = torch.empty(7, len(rays), device=self.device)
        torch.where(valid, o.T + start * d.T, self._zero, out=columns[:3])
        torch.where(valid, d.T, self._placeholder, out=columns[3:6])
        torch.where(valid, torch.nextafter(length, self._infinity), self._minus_one, out=columns[6])
        return columns, start, length

    def _ray(self, columns: Tensor):
        """A Dr.Jit ray sharing the memory of ``columns`` (which must outlive the query), and the
        mask of rays to trace."""
        ty = self._types
        c = [ty.Float(columns[k]) for k in range(7)]
        ray = ty.Ray3f(ty.Point3f(c[0], c[1], c[2]), ty.Vector3f(c[3], c[4], c[5]))
        ray.maxt = c[6]
        return ray, c[6] > 0

    def intersect(self, rays: Rays) -> Hits:
        """Closest hit per ray: t, triangle, shading/geometric normal, UV, albedo, material id."""
        self._check_device(rays, "intersect")
        if len(rays) == 0:
            return Hits.empty(0, rays.device)
        return closest_hit_records(self._tables, *self.closest_hits(rays))

    def closest_hits(self, rays: Rays) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The geometric query alone: triangle [N] int32 (-1 on miss), t [N], barycentrics u, v [N]
        (t, u, v undefined on misses), on the rays' device. `intersect` adds the attributes."""
        import drjit as dr

        columns, start, length = self._trace_inputs(rays)
        ray, active = self._ray(columns)
        found = self._scene.ray_intersect_preliminary(ray, coherent=False, active=active)
        prim = dr.select(active & found.is_valid(), self._types.Int32(found.prim_index), -1)
        t, u, v = found.t, found.prim_uv.x, found.prim_uv.y
        dr.eval(prim, t, u, v)  # one kernel: trace and write the four columns
        t_local = t.torch()
        prim = torch.where(t_local <= length, prim.torch(), -1)  # (in the one step t_far adds: past t_max)
        return prim, t_local + start, u.torch(), v.torch()

    def occluded(self, rays: Rays) -> Tensor:
        """[N] bool: does any triangle lie within [t_min, t_max]?"""
        import drjit as dr

        self._check_device(rays, "occluded")
        if len(rays) == 0:
            return torch.zeros(0, dtype=torch.bool, device=rays.device)
        columns, _, _ = self._trace_inputs(rays)
        ray, active = self._ray(columns)
        blocked = dr.select(active & self._scene.ray_test(ray, active=active), self._types.Int32(1), 0)
        dr.eval(blocked)
        return blocked.torch() > 0
