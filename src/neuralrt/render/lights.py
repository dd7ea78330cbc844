"""Light sources for next-event estimation, with the densities multiple importance sampling needs.

- `AreaLights`: every emissive triangle of the scene in world space, picked with probability
  proportional to ``area x luminance(emission)`` (by area when all emit alike), then a uniform
  point on it; densities are converted to solid angle (``d^2 / |cos_light|``). Emission is
  one-sided: from the face the geometric normal points out of.
- `PointLights`: isotropic points of radiant intensity ``I`` (W/sr), picked by luminance of I;
  delta lights (no MIS: a BSDF sample never hits them).
- `Environment`: radiance from infinitely far away, a constant colour or a lat-long image looked
  up bilinearly (wrapping in azimuth, clamped at the poles) so a directly seen sky shows no texel
  steps. Importance sampling picks a texel with probability ~ ``luminance x sin(theta)`` of the
  lookup's *average over that texel* (the image filtered by [1/8, 3/4, 1/8] in each direction),
  then a uniform point in it: wherever the interpolated radiance is non-zero the density is too.
  Lat-long mapping: ``u = 0.5 + atan2(x, -z) / 2pi``, ``v = acos(y) / pi`` (row 0 = straight up,
  the image centre is seen looking down -z).
- `LightSet`: chooses among the kinds present with equal probability, samples one light, and gives
  the MIS densities of emitters that BSDF-sampled rays hit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rays import AABB
from .sampling import DiscreteDistribution, luminance, uniform_triangle

__all__ = ["AreaLights", "PointLights", "Environment", "LightSet", "LightSample"]


@dataclass
class LightSample:
    """One sampled light per shading point."""

    wi: Tensor  # [N, 3] unit direction from the shading point towards the light
    distance: Tensor  # [N] distance to the light point (inf for the environment)
    radiance: Tensor  # [N, 3] incident radiance (point lights: I / d^2, i.e. already irradiance-scaled)
    pdf: Tensor  # [N] solid-angle density incl. the light-selection probability (delta lights: the probability)
    is_delta: Tensor  # [N] bool: no MIS (point lights)


class AreaLights:
    """Emissive triangles in world space."""

    def __init__(self, triangles: Tensor, normals: Tensor, emission: Tensor, instance_ids: Tensor, primitive_ids: Tensor,
                 instance_face_counts: list[int], device="cpu"):
        """``triangles`` [L, 3, 3] world vertices, ``normals`` [L, 3] unit world geometric normals,
        ``emission`` [L, 3]; ``instance_ids``/``primitive_ids`` [L] say where each triangle lives, and
        ``instance_face_counts[i]`` is instance i's triangle count (to map hits back to lights)."""
        dev = torch.device(device)
        self.triangles = triangles.float().to(dev)
        self.normals = normals.float().to(dev)
        self.emission = emission.float().to(dev)
        e1 = self.triangles[:, 1] - self.triangles[:, 0]
        e2 = self.triangles[:, 2] - self.triangles[:, 0]
        self.area = 0.5 * torch.linalg.norm(torch.linalg.cross(e1, e2), dim=-1)
        self.distribution = DiscreteDistribution(self.area * luminance(self.emission)).to(dev)
        self._area_pdf = self.distribution.pmf / self.area.clamp(min=1e-30)  # [L] density per unit area
        # (instance, primitive) -> light index, only for instances that hold emitters.
        inst = instance_ids.long().to(dev)
        counts = torch.tensor(instance_face_counts, dtype=torch.int64, device=dev)
        holds = torch.zeros(len(instance_face_counts), dtype=torch.bool, device=dev)
        holds[inst] = True
        sizes = torch.where(holds, counts, 0)
        self._base = torch.cumsum(sizes, 0) - sizes  # [I] first slot of each instance
        self._holds = holds
        self._lookup = torch.full((int(sizes.sum()),), -1, dtype=torch.int64, device=dev)
        self._lookup[self._base[inst] + primitive_ids.long().to(dev)] = torch.arange(len(inst), device=dev)

    def __len__(self) -> int:
        return self.area.numel()

    @property
    def instance_ids(self) -> Tensor:
        """[K] int64: the scene instances that hold emissive triangles, ascending."""
        return torch.nonzero(self._holds).reshape(-1)

    @property
    def power(self) -> float:
        """Emitted flux (one-sided Lambertian emitter: pi * L * area), summed, luminance."""
        return float(math.pi * (self.area * luminance(self.emission)).sum())

    def light_index(self, instance_id: Tensor, primitive_id: Tensor) -> Tensor:
        """[N] light index of hit triangles, -1 where the hit is not an area light (or has no triangle id)."""
        ok = (instance_id >= 0) & (primitive_id >= 0)
        inst = instance_id.clamp(min=0)
        ok = ok & self._holds[inst]
        slot = (self._base[inst] + primitive_id.clamp(min=0)).clamp(max=max(self._lookup.numel() - 1, 0))
        return torch.where(ok, self._lookup[slot], -1)

    def sample(self, p: Tensor, u_select: Tensor, u_point: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Points on lights for shading points ``p``: (light index, point, wi, solid-angle pdf)."""
        idx = self.distribution.sample(u_select)
        bary = uniform_triangle(u_point)
        y = (bary[:, :, None] * self.triangles[idx]).sum(1)
        to_light = y - p
        dist = torch.linalg.norm(to_light, dim=-1).clamp(min=1e-12)
        wi = to_light / dist[:, None]
        pdf = self.pdf(idx, dist, wi)
        return idx, y, wi, pdf

    def pdf(self, idx: Tensor, distance: Tensor, wi: Tensor) -> Tensor:
        """Solid-angle density of reaching light ``idx`` along ``wi`` at ``distance`` (0 on its back)."""
        cos_l = -(wi * self.normals[idx]).sum(-1)
        return torch.where(cos_l > 0, self._area_pdf[idx] * distance * distance / cos_l.clamp(min=1e-12), 0.0)


class PointLights:
    """Point lights, one picked per sample in proportion to the irradiance it gives the scene
    (with ``scene_bounds``; by intensity alone without): intensity / (d^2 + r^2 / 3), d the light's
    distance to the centre of the scene's bounding ball, r its radius. (The mean of 1 / distance^2
    over the ball is 3 / r^2 from its centre and tends to 1 / d^2 from far away.) By intensity
    alone, a far and bright light (glTF's sun, imported as a point light 100 scene radii away)
    would be picked nearly always while lighting the scene as much as a dim near one."""

    def __init__(self, positions: Tensor, intensities: Tensor, device="cpu", scene_bounds: AABB | None = None):
        dev = torch.device(device)
        self.positions = torch.as_tensor(positions, dtype=torch.float32).reshape(-1, 3).to(dev)
        self.intensities = torch.as_tensor(intensities, dtype=torch.float32).reshape(-1, 3).to(dev)
        weights = luminance(self.intensities).double()
        if scene_bounds is not None:
            centre = ((scene_bounds.lo + scene_bounds.hi) / 2).to(dev).double()
            radius = float(torch.linalg.norm((scene_bounds.hi - scene_bounds.lo).double()) / 2)
            distance_sq = ((self.positions.double() - centre) ** 2).sum(-1)
            weights = weights / (distance_sq + radius * radius / 3).clamp(min=1e-300)
        self.distribution = DiscreteDistribution(weights).to(dev)

    def __len__(self) -> int:
        return self.positions.shape[0]

    def sample(self, p: Tensor, u_select: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """(wi, distance, I / d^2, selection probability)."""
        idx = self.distribution.sample(u_select)
        to_light = self.positions[idx] - p
        dist = torch.linalg.norm(to_light, dim=-1).clamp(min=1e-12)
        return to_light / dist[:, None], dist, self.intensities[idx] / (dist * dist)[:, None], self.distribution.pmf[idx]


class Environment:
    """Infinitely distant lighting: ``color`` (constant) or a lat-long ``image`` [H, W, 3], times ``scale``,
    turned by ``rotate_y`` degrees about +y (right-handed: what the image shows at direction e is
    seen at R_y(rotate_y) e)."""

    def __init__(self, color=None, image: Tensor | None = None, scale: float = 1.0, device="cpu", rotate_y: float = 0.0):
        dev = torch.device(device)
        self.device = dev
        self._cos, self._sin = math.cos(math.radians(rotate_y)), math.sin(math.radians(rotate_y))
        if (color is None) == (image is None):
            raise ValueError("an environment needs exactly one of color or image")
        self.image = None
        self.color = None
        if color is not None:
            self.color = torch.as_tensor(color, dtype=torch.float32, device=dev).reshape(3) * scale
            if float(luminance(self.color)) < 0:
                raise ValueError("environment colour must be non-negative")
        else:
            img = torch.as_tensor(image, dtype=torch.float32, device=dev)
            if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
                raise ValueError(f"environment image must be [H, W, 3], got {tuple(img.shape)}")
            self.image = img.clamp(min=0) * scale
            h = img.shape[0]
            sin_theta = torch.sin((torch.arange(h, device=dev, dtype=torch.float32) + 0.5) * math.pi / h)
            self._texel_means = luminance(_bilinear_texel_means(self.image))  # [H, W]
            weights = self._texel_means * sin_theta[:, None]
            self.distribution = DiscreteDistribution(weights.reshape(-1) + 1e-12).to(dev)

    @property
    def is_constant(self) -> bool:
        return self.color is not None

    @property
    def mean_radiance(self) -> float:
        """Luminance of `radiance` averaged over the sphere (texel means weighted by sin theta)."""
        if self.color is not None:
            return float(luminance(self.color))
        h = self.image.shape[0]
        sin_theta = torch.sin((torch.arange(h, device=self.device, dtype=torch.float32) + 0.5) * math.pi / h)
        return float((self._texel_means * sin_theta[:, None]).sum() / (sin_theta.sum() * self.image.shape[1]))

    # -- direction <-> image coordinates --------------------------------------------------------
    @staticmethod
    def direction_to_uv(d: Tensor) -> Tensor:
        u = 0.5 + torch.atan2(d[:, 0], -d[:, 2]) / (2 * math.pi)
        v = torch.acos(d[:, 1].clamp(-1, 1)) / math.pi
        return torch.stack([torch.remainder(u, 1.0), v], -1)

    @staticmethod
    def uv_to_direction(uv: Tensor) -> Tensor:
        phi = 2 * math.pi * (uv[:, 0] - 0.5)
        theta = math.pi * uv[:, 1]
        s = torch.sin(theta)
        return torch.stack([s * torch.sin(phi), torch.cos(theta), -s * torch.cos(phi)], -1)

    def _to_env(self, d: Tensor) -> Tensor:
        """World direction -> the image's frame (rotate by -rotate_y about +y)."""
        if self._sin == 0.0 and self._cos == 1.0:
            return d
        c, s = self._cos, self._sin
        return torch.stack([c * d[:, 0] - s * d[:, 2], d[:, 1], s * d[:, 0] + c * d[:, 2]], -1)

    def _from_env(self, d: Tensor) -> Tensor:
        if self._sin == 0.0 and self._cos == 1.0:
            return d
        c, s = self._cos, self._sin
        return torch.stack([c * d[:, 0] + s * d[:, 2], d[:, 1], -s * d[:, 0] + c * d[:, 2]], -1)

    def radiance(self, d: Tensor) -> Tensor:
        """Radiance [N, 3] arriving from unit directions ``d`` [N, 3]: bilinear between texel centres,
        wrapping in azimuth (u) and clamped at the poles (v)."""
        if self.color is not None:
            return self.color.expand(d.shape[0], 3)
        h, w = self.image.shape[:2]
        uv = self.direction_to_uv(self._to_env(d))
        x = uv[:, 0] * w - 0.5  # texel centres at integer x, y
        y = uv[:, 1] * h - 0.5
        x0, y0 = torch.floor(x), torch.floor(y)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        x0 = x0.long()
        y0 = y0.long()
        xa, xb = torch.remainder(x0, w), torch.remainder(x0 + 1, w)
        ya, yb = y0.clamp(0, h - 1), (y0 + 1).clamp(0, h - 1)
        img = self.image
        top = img[ya, xa] * (1 - fx) + img[ya, xb] * fx
        bottom = img[yb, xa] * (1 - fx) + img[yb, xb] * fx
        return top * (1 - fy) + bottom * fy

    def sample(self, u_pixel: Tensor, u_dir: Tensor) -> tuple[Tensor, Tensor]:
        """(unit direction, solid-angle pdf) for uniforms ``u_pixel`` [N] and ``u_dir`` [N, 2]."""
        if self.color is not None:
            z = 1.0 - 2.0 * u_dir[:, 0]
            r = torch.sqrt((1.0 - z * z).clamp(min=0))
            phi = 2 * math.pi * u_dir[:, 1]
            d = torch.stack([r * torch.cos(phi), z, r * torch.sin(phi)], -1)
            return d, torch.full_like(z, 1.0 / (4 * math.pi))
        h, w = self.image.shape[:2]
        pix = self.distribution.sample(u_pixel)
        uv = torch.stack([((pix % w).float() + u_dir[:, 0]) / w, (torch.div(pix, w, rounding_mode="floor").float() + u_dir[:, 1]) / h], -1)
        d = self._from_env(self.uv_to_direction(uv))
        return d, self.pdf(d)

    def pdf(self, d: Tensor) -> Tensor:
        """Solid-angle density of `sample` producing ``d``: pdf_uv / (2 pi^2 sin theta)."""
        if self.color is not None:
            return torch.full((d.shape[0],), 1.0 / (4 * math.pi), device=d.device)
        h, w = self.image.shape[:2]
        d = self._to_env(d)
        uv = self.direction_to_uv(d)
        x = (uv[:, 0] * w).long().clamp(0, w - 1)
        y = (uv[:, 1] * h).long().clamp(0, h - 1)
        pdf_uv = self.distribution.pmf[y * w + x] * (h * w)
        # sin(theta) from x and z: sqrt(1 - y^2) rounds to 0 in float32 within ~3e-4 rad of the poles.
        sin_theta = torch.sqrt(d[:, 0] * d[:, 0] + d[:, 2] * d[:, 2])
        return torch.where(sin_theta > 0, pdf_uv / (2 * math.pi * math.pi * sin_theta.clamp(min=1e-30)), 0.0)


def _bilinear_texel_means(image: Tensor) -> Tensor:
    """[H, W, C]: the mean over each texel of `Environment.radiance`'s bilinear lookup. Over one texel
    the tent weights of it and its two neighbours average to 3/4 and 1/8 each, per axis; azimuth
    wraps, the pole rows repeat themselves (the lookup clamps there)."""
    up = torch.cat([image[:1], image[:-1]], 0)
    down = torch.cat([image[1:], image[-1:]], 0)
    rows = 0.75 * image + 0.125 * (up + down)
    return 0.75 * rows + 0.125 * (torch.roll(rows, 1, dims=1) + torch.roll(rows, -1, dims=1))


class LightSet:
    """All lights of a scene. Each NEE sample first picks a kind (area / point / environment) uniformly."""

    def __init__(self, area: AreaLights | None = None, points: PointLights | None = None, environment: Environment | None = None):
        self.area = area if area is not None and len(area) else None
        self.points = points if points is not None and len(points) else None
        self.environment = environment
        self.kinds = [k for k, v in (("area", self.area), ("point", self.points), ("environment", self.environment)) if v is not None]

    def __bool__(self) -> bool:
        return bool(self.kinds)

    @property
    def kind_probability(self) -> float:
        return 1.0 / max(len(self.kinds), 1)

    def sample(self, p: Tensor, u: Tensor) -> LightSample:
        """One light sample per shading point ``p`` [N, 3]; ``u`` [N, 4] uniforms."""
        kinds = len(self.kinds)
        kind = torch.clamp((u[:, 0] * kinds).long(), max=kinds - 1)
        # Reuse u[:, 0] within the chosen kind's interval so the streams stay independent.
        u_sel = (u[:, 0] * kinds - kind.float()).clamp(0, 1 - 1e-7)
        if kinds == 1:
            return self._sample_kind(self.kinds[0], p, u_sel, u[:, 1:3])
        n, dev = p.shape[0], p.device
        out = LightSample(torch.zeros(n, 3, device=dev), torch.full((n,), float("inf"), device=dev),
                          torch.zeros(n, 3, device=dev), torch.zeros(n, device=dev), torch.zeros(n, dtype=torch.bool, device=dev))
        for k, name in enumerate(self.kinds):  # a handful of kinds, each batched over its rays
            idx = torch.nonzero(kind == k).reshape(-1)
            if idx.numel() == 0:
                continue
            part = self._sample_kind(name, p[idx], u_sel[idx], u[idx, 1:3])
            for f in ("wi", "distance", "radiance", "pdf", "is_delta"):
                setattr(out, f, getattr(out, f).index_copy(0, idx, getattr(part, f)))
        return out

    def _sample_kind(self, name: str, p: Tensor, u_sel: Tensor, u2: Tensor) -> LightSample:
        """Samples of one light kind; pdfs include the kind-selection probability."""
        pk = self.kind_probability
        if name == "area":
            idx, y, wi, pa = self.area.sample(p, u_sel, u2)  # pa = 0 on an emitter's back: unusable
            return LightSample(wi, torch.linalg.norm(y - p, dim=-1), self.area.emission[idx], pa * pk,
                               torch.zeros(p.shape[0], dtype=torch.bool, device=p.device))
        if name == "point":
            wi, d, li, pmf = self.points.sample(p, u_sel)
            return LightSample(wi, d, li, pmf * pk, torch.ones(p.shape[0], dtype=torch.bool, device=p.device))
        wi, pe = self.environment.sample(u_sel, u2)
        return LightSample(wi, torch.full_like(pe, float("inf")), self.environment.radiance(wi), pe * pk,
                           torch.zeros(p.shape[0], dtype=torch.bool, device=p.device))

    def area_pdf(self, light_idx: Tensor, distance: Tensor, wi: Tensor) -> Tensor:
        """MIS density of having sampled area light ``light_idx`` (>= 0) along ``wi``."""
        if self.area is None:
            return torch.zeros_like(distance)
        return self.area.pdf(light_idx.clamp(min=0), distance, wi) * self.kind_probability * (light_idx >= 0)

    def environment_pdf(self, d: Tensor) -> Tensor:
        if self.environment is None:
            return torch.zeros(d.shape[0], device=d.device)
        return self.environment.pdf(d) * self.kind_probability
