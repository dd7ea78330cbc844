"""Surface materials as one table of tensors, evaluated and sampled for whole batches of rays.

Kinds (``MaterialKind``):

- ``DIFFUSE``: Lambertian, ``f = albedo / pi``.
- ``CONDUCTOR``: rough metal, GGX microfacet (Walter et al. 2007) with Smith height-correlated
  masking-shadowing and Schlick's Fresnel with ``F0 = albedo`` (the metal's colour at normal
  incidence). Sampled with GGX visible normals (Heitz 2018).
- ``PLASTIC``: a diffuse base under a rough dielectric coat of index ``ior``: the GGX coat
  reflects ``F_dielectric(wo.h)``; the base gives ``albedo/pi (1 - F(cos_i)) (1 - F(cos_o))``
  (light refracts in and out of the coat; internal re-reflections are ignored, so it never creates
  energy). Sampling picks the coat with probability ``max(Fo / (Fo + (1 - Fo) lum(albedo)), 1/4)``
  (``Fo`` = Fresnel at ``cos_o``) and the cosine-weighted base otherwise; the pdf is the mixture.
- ``EMISSIVE``: emits ``emission`` (W m^-2 sr^-1) from the front face (where the geometric normal
  points) and reflects diffusely with ``albedo`` (0 by default).

Conventions: ``n`` is the unit shading normal already turned to the side of ``wo``; ``wo`` points
away from the surface towards the viewer, ``wi`` towards the light; both unit. Reflection only:
``eval`` and ``pdf`` are 0 unless both directions lie above ``n``. ``eval`` returns
``f(wo, wi) * cos(n, wi)``. ``roughness`` is the GGX ``alpha`` (Mitsuba's convention), clamped
to at least ``MIN_ALPHA`` because a perfect mirror has no finite density.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import torch
from torch import Tensor

from .sampling import cosine_hemisphere, luminance, orthonormal_basis, to_local, to_world

__all__ = ["MaterialKind", "MaterialTable", "BSDFSample", "MIN_ALPHA", "sample_texture"]

MIN_ALPHA = 1e-3
_MIN_COAT_PROBABILITY = 0.25


class MaterialKind(IntEnum):
    DIFFUSE = 0
    CONDUCTOR = 1
    PLASTIC = 2
    EMISSIVE = 3


@dataclass
class BSDFSample:
    """Sampled incident directions: ``weight = f cos / pdf`` (0 where the sample failed)."""

    wi: Tensor  # [N, 3] unit world direction
    weight: Tensor  # [N, 3]
    pdf: Tensor  # [N] solid-angle density (0 = invalid sample)


class MaterialTable:
    """The scene's materials, one row each; every method is batched over rays by ``material_id``.

    ``textures[k]`` (optional) is a [H, W, 3] linear texture multiplying row k's ``albedo``.
    """

    def __init__(
        self,
        kind: Tensor,  # [M] int64 MaterialKind
        albedo: Tensor,  # [M, 3] linear RGB (diffuse colour, metal F0, plastic base, emitter reflectance)
        roughness: Tensor,  # [M] GGX alpha
        ior: Tensor,  # [M] coat index of refraction (plastic)
        emission: Tensor,  # [M, 3] emitted radiance (emissive)
        textures: list[Tensor | None] | None = None,
        names: list[str] | None = None,
        device="cpu",
    ):
        dev = torch.device(device)
        self.device = dev
        self.kind = torch.as_tensor(kind, dtype=torch.int64, device=dev).reshape(-1)
        m = self.kind.numel()
        self.albedo = torch.as_tensor(albedo, dtype=torch.float32, device=dev).reshape(m, 3)
        self.roughness = torch.as_tensor(roughness, dtype=torch.float32, device=dev).reshape(m).clamp(min=MIN_ALPHA)
        self.ior = torch.as_tensor(ior, dtype=torch.float32, device=dev).reshape(m)
        self.emission = torch.as_tensor(emission, dtype=torch.float32, device=dev).reshape(m, 3)
        self.textures = [None if t is None else torch.as_tensor(t, dtype=torch.float32, device=dev) for t in (textures or [None] * m)]
        self.names = list(names) if names is not None else [f"material{k}" for k in range(m)]
        if len(self.textures) != m or len(self.names) != m:
            raise ValueError("textures and names must have one entry per material")

    def __len__(self) -> int:
        return self.kind.numel()

    @staticmethod
    def single(kind: MaterialKind, albedo=(0.8, 0.8, 0.8), roughness=0.1, ior=1.5, emission=(0, 0, 0), device="cpu") -> "MaterialTable":
        """A table holding one material (handy in tests)."""
        return MaterialTable([int(kind)], [albedo], [roughness], [ior], [emission], device=device)

    # -- per-hit lookups ------------------------------------------------------------------------
    def albedo_at(self, material_id: Tensor, uv: Tensor, surface_albedo: Tensor | None = None) -> Tensor:
        """Material albedo x texture(uv) x the surface's own colour factor (from the BLAS), [N, 3]."""
        mid = material_id.clamp(min=0)
        albedo = self.albedo[mid]
        for k, tex in enumerate(self.textures):  # loop over textured materials, not rays
            if tex is None:
                continue
            sel = material_id == k
            if sel.any():
                albedo[sel] = albedo[sel] * sample_texture(tex, uv[sel])
        if surface_albedo is not None:
            albedo = albedo * surface_albedo
        return albedo

    def emission_of(self, material_id: Tensor) -> Tensor:
        """Emitted radiance [N, 3] of each hit's material (0 for non-emitters and misses)."""
        e = self.emission[material_id.clamp(min=0)]
        return e * (material_id >= 0)[:, None]

    @property
    def emissive_mask(self) -> Tensor:
        """[M] bool: materials that emit."""
        return (self.kind == MaterialKind.EMISSIVE) & (self.emission.amax(-1) > 0)

    # -- BSDF ---------------------------------------------------------------------------------------
    def _params(self, material_id: Tensor):
        mid = material_id.clamp(min=0)
        return self.kind[mid], self.roughness[mid], self.ior[mid]

    def _lobes(self, kind: Tensor, alpha: Tensor, ior: Tensor, albedo: Tensor, lo: Tensor, li: Tensor):
        """Local-frame f*cos [N, 3] and pdf [N] for directions ``lo`` (out) and ``li`` (in).

        Diffuse rows take a short path; the GGX terms are computed only for glossy rows (conductor,
        plastic), which keeps the op count low in mostly-diffuse scenes.
        """
        cos_o, cos_i = lo[:, 2], li[:, 2]
        valid = (cos_o > 0) & (cos_i > 0)
        cos_i_pos = cos_i.clamp(min=0)
        is_diffuse = (kind == MaterialKind.DIFFUSE) | (kind == MaterialKind.EMISSIVE)
        value = albedo * (is_diffuse * cos_i_pos / math.pi)[:, None]
        pdf = torch.where(is_diffuse, cos_i_pos / math.pi, 0.0)
        glossy = torch.nonzero(~is_diffuse).reshape(-1)
        if glossy.numel():
            g_value, g_pdf = self._glossy_lobes(kind[glossy], alpha[glossy], ior[glossy], albedo[glossy], lo[glossy], li[glossy])
            value = value.index_copy(0, glossy, g_value)
            pdf = pdf.index_copy(0, glossy, g_pdf)
        return torch.where(valid[:, None], value, 0.0), torch.where(valid, pdf, 0.0)

    def _glossy_lobes(self, kind: Tensor, alpha: Tensor, ior: Tensor, albedo: Tensor, lo: Tensor, li: Tensor):
        """`_lobes` for conductor and plastic rows (validity is applied by the caller)."""
        cos_o, cos_i = lo[:, 2], li[:, 2]
        h = torch.nn.functional.normalize(lo + li, dim=-1)
        o_dot_h = (lo * h).sum(-1).clamp(min=0)
        d = ggx_d(h[:, 2], alpha)
        g2 = 1.0 / (1.0 + ggx_lambda(lo, alpha) + ggx_lambda(li, alpha))
        safe_cos_o = cos_o.clamp(min=1e-8)
        micro = d * g2 / (4.0 * safe_cos_o)  # D G / (4 cos_o): the microfacet f*cos without Fresnel
        is_conductor = kind == MaterialKind.CONDUCTOR
        f_conductor = schlick(albedo, o_dot_h)  # [N, 3]
        f_coat = fresnel_dielectric(o_dot_h, ior)[:, None]
        spec = torch.where(is_conductor[:, None], f_conductor, f_coat) * micro[:, None]
        # Plastic base: refracted in and out of the coat.
        transmit = (1.0 - fresnel_dielectric(cos_i, ior)) * (1.0 - fresnel_dielectric(cos_o, ior))
        diffuse = albedo * (torch.where(is_conductor, 0.0, transmit) * cos_i.clamp(min=0) / math.pi)[:, None]
        p_coat = self._coat_probability(kind, ior, albedo, cos_o)
        pdf_spec = ggx_g1(lo, alpha) * d / (4.0 * safe_cos_o)  # visible-normal density mapped to wi
        pdf = p_coat * pdf_spec + (1.0 - p_coat) * cos_i.clamp(min=0) / math.pi
        return spec + diffuse, pdf

    @staticmethod
    def _coat_probability(kind: Tensor, ior: Tensor, albedo: Tensor, cos_o: Tensor) -> Tensor:
        """Probability of sampling the GGX lobe: 1 for metals, 0 for diffuse, a mixture for plastic."""
        fo = fresnel_dielectric(cos_o.clamp(min=0), ior)
        kd = (1.0 - fo) * luminance(albedo)
        p_plastic = (fo / (fo + kd).clamp(min=1e-8)).clamp(min=_MIN_COAT_PROBABILITY, max=1.0)
        return torch.where(kind == MaterialKind.CONDUCTOR, 1.0, torch.where(kind == MaterialKind.PLASTIC, p_plastic, 0.0))

    def eval(self, material_id: Tensor, albedo: Tensor, n: Tensor, wo: Tensor, wi: Tensor) -> Tensor:
        """``f(wo, wi) * cos(n, wi)``, [N, 3]."""
        kind, alpha, ior = self._params(material_id)
        t, b = orthonormal_basis(n)
        return self._lobes(kind, alpha, ior, albedo, to_local(wo, t, b, n), to_local(wi, t, b, n))[0]

    def pdf(self, material_id: Tensor, albedo: Tensor, n: Tensor, wo: Tensor, wi: Tensor) -> Tensor:
        """Solid-angle density [N] with which `sample` picks ``wi``."""
        kind, alpha, ior = self._params(material_id)
        t, b = orthonormal_basis(n)
        return self._lobes(kind, alpha, ior, albedo, to_local(wo, t, b, n), to_local(wi, t, b, n))[1]

    def eval_pdf(self, material_id: Tensor, albedo: Tensor, n: Tensor, wo: Tensor, wi: Tensor) -> tuple[Tensor, Tensor]:
        """`eval` and `pdf` together (one pass)."""
        kind, alpha, ior = self._params(material_id)
        t, b = orthonormal_basis(n)
        return self._lobes(kind, alpha, ior, albedo, to_local(wo, t, b, n), to_local(wi, t, b, n))

    def sample(self, material_id: Tensor, albedo: Tensor, n: Tensor, wo: Tensor, u_lobe: Tensor, u_dir: Tensor) -> BSDFSample:
        """Draw ``wi`` from the material's mixture (``u_lobe`` [N] picks the lobe, ``u_dir`` [N, 2] the direction)."""
        kind, alpha, ior = self._params(material_id)
        t, b = orthonormal_basis(n)
        lo = to_local(wo, t, b, n)
        li = cosine_hemisphere(u_dir)
        glossy = torch.nonzero((kind == MaterialKind.CONDUCTOR) | (kind == MaterialKind.PLASTIC)).reshape(-1)
        if glossy.numel():  # coat / metal rows may take the GGX lobe instead
            lo_g = lo[glossy]
            p_coat = self._coat_probability(kind[glossy], ior[glossy], albedo[glossy], lo_g[:, 2])
            hm = ggx_sample_visible_normal(lo_g, alpha[glossy], u_dir[glossy])
            li_spec = 2.0 * (lo_g * hm).sum(-1, keepdim=True) * hm - lo_g  # mirror wo about the microfacet normal
            chosen = torch.where((u_lobe[glossy] < p_coat)[:, None], li_spec, li[glossy])
            li = li.index_copy(0, glossy, torch.nn.functional.normalize(chosen, dim=-1))
        value, pdf = self._lobes(kind, alpha, ior, albedo, lo, li)
        ok = pdf > 0
        weight = torch.where(ok[:, None], value / torch.where(ok, pdf, 1.0)[:, None], 0.0)
        return BSDFSample(to_world(li, t, b, n), weight, pdf)


# --- microfacet and Fresnel helpers (local frame, z = normal) ------------------------------------


def ggx_d(cos_h: Tensor, alpha: Tensor) -> Tensor:
    """GGX normal distribution D(h) for cos(theta_h)."""
    a2 = alpha * alpha
    c2 = cos_h * cos_h
    denom = c2 * (a2 - 1.0) + 1.0
    return torch.where(cos_h > 0, a2 / (math.pi * denom * denom), 0.0)


def ggx_lambda(w: Tensor, alpha: Tensor) -> Tensor:
    """Smith Lambda for GGX: (-1 + sqrt(1 + alpha^2 tan^2 theta)) / 2."""
    z2 = (w[:, 2] * w[:, 2]).clamp(min=1e-12)
    tan2 = ((w[:, 0] * w[:, 0] + w[:, 1] * w[:, 1]) / z2)
    return 0.5 * (torch.sqrt(1.0 + alpha * alpha * tan2) - 1.0)


def ggx_g1(w: Tensor, alpha: Tensor) -> Tensor:
    return 1.0 / (1.0 + ggx_lambda(w, alpha))


def ggx_sample_visible_normal(wo: Tensor, alpha: Tensor, u: Tensor) -> Tensor:
    """Microfacet normals distributed as the GGX visible normals seen from ``wo`` (Heitz 2018)."""
    a = alpha[:, None]
    vh = torch.nn.functional.normalize(torch.cat([a * wo[:, :2], wo[:, 2:3].clamp(min=1e-6)], -1), dim=-1)
    lensq = vh[:, 0] ** 2 + vh[:, 1] ** 2
    inv = torch.rsqrt(lensq.clamp(min=1e-20))
    t1 = torch.where((lensq > 0)[:, None], torch.stack([-vh[:, 1] * inv, vh[:, 0] * inv, torch.zeros_like(inv)], -1),
                     torch.tensor([1.0, 0.0, 0.0], device=wo.device))
    t2 = torch.linalg.cross(vh, t1)
    r = torch.sqrt(u[:, 0])
    phi = 2.0 * math.pi * u[:, 1]
    p1 = r * torch.cos(phi)
    p2 = r * torch.sin(phi)
    s = 0.5 * (1.0 + vh[:, 2])
    p2 = (1.0 - s) * torch.sqrt((1.0 - p1 * p1).clamp(min=0)) + s * p2
    nh = p1[:, None] * t1 + p2[:, None] * t2 + torch.sqrt((1.0 - p1 * p1 - p2 * p2).clamp(min=0))[:, None] * vh
    return torch.nn.functional.normalize(torch.cat([a * nh[:, :2], nh[:, 2:3].clamp(min=1e-6)], -1), dim=-1)


def schlick(f0: Tensor, cos: Tensor) -> Tensor:
    """Schlick's Fresnel approximation, [N, 3]."""
    return f0 + (1.0 - f0) * ((1.0 - cos.clamp(0, 1)) ** 5)[:, None]


def fresnel_dielectric(cos_i: Tensor, eta: Tensor) -> Tensor:
    """Unpolarised Fresnel reflectance entering a dielectric of relative index ``eta`` from outside."""
    cos_i = cos_i.clamp(0.0, 1.0)
    sin_t2 = (1.0 - cos_i * cos_i) / (eta * eta)
    cos_t = torch.sqrt((1.0 - sin_t2).clamp(min=0.0))
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t).clamp(min=1e-12)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t).clamp(min=1e-12)
    return torch.where(sin_t2 >= 1.0, 1.0, 0.5 * (rs * rs + rp * rp))


def sample_texture(texture: Tensor, uv: Tensor) -> Tensor:
    """Bilinear, wrapped texture lookup; ``texture`` [H, W, 3] has row 0 at v = 1 (image convention)."""
    h, w = texture.shape[:2]
    x = torch.remainder(uv[:, 0], 1.0) * w - 0.5
    y = (1.0 - torch.remainder(uv[:, 1], 1.0)) * h - 0.5
    x0f, y0f = torch.floor(x), torch.floor(y)
    fx, fy = (x - x0f)[:, None], (y - y0f)[:, None]
    x0, y0 = x0f.long() % w, y0f.long() % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    top = texture[y0, x0] * (1 - fx) + texture[y0, x1] * fx
    bottom = texture[y1, x0] * (1 - fx) + texture[y1, x1] * fx
    return top * (1 - fy) + bottom * fy
