"""Wavefront unidirectional path tracer with next-event estimation and multiple importance sampling.

All paths of a wavefront advance together as tensors. Each bounce runs the same named whole-batch
stages (pbrt-v4's wavefront integrator):

    generate_camera_rays -> intersect -> handle_escaped -> emission_at_hits (MIS) ->
    [record AOVs at the first hit] -> sample_lights (NEE shadow rays, MIS) -> sample_bsdf ->
    russian_roulette -> compact (finished paths drop out by mask)

MIS uses the power heuristic between light sampling and BSDF sampling for area and environment
lights; point lights are delta lights (light sampling only). ``max_depth`` counts bounces: 1 gives
direct lighting only (emission seen directly plus one scattering event).

Secondary rays start at the hit point moved along the face-forwarded geometric normal by the hit
instance's `Scene.instance_offsets` (its BLAS ``secondary_offset`` scaled to world); shadow rays
stop short of their light point by a relative ``1e-3`` of its distance. The integrator only calls
``scene.accel.intersect`` / ``occluded``: it never knows which kind of BLAS answered.
Randomness comes from one torch generator per wavefront seeded from (``seed``, wavefront index),
so a given seed and settings give the same image.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from torch import Tensor

from ..rays import Hits, Rays, resolve_device
from .film import Film, RenderResult
from .sampling import make_generator, power_heuristic, uniform

__all__ = ["render", "IntegratorSettings", "PathTracer"]

_SHADOW_T_MAX = 1.0 - 1e-3  # shadow rays (direction = light point - origin) stop at this t


@dataclass
class IntegratorSettings:
    """Path tracer settings (defaults: pbrt-v4's path integrator, except ``max_depth``)."""

    max_depth: int = 5  # maximum number of bounces (1 = direct lighting)
    rr_depth: int = 3  # Russian roulette starts after this many bounces
    rr_max_survival: float = 0.95  # survival probability cap, so no path lives forever
    max_paths: int = 1 << 18  # paths per wavefront (memory bound; several samples per pixel fit when the image is small)
    # Who answers camera rays for objects with both a mesh and a neural model: "exact" (the mesh,
    # standing in for the paper's rasterized G-buffer) or "neural" (the model answers every ray).
    primary: str = "exact"


@dataclass
class _Paths:
    """The state of the live paths of a wavefront (one row per path)."""

    rays: Rays  # current ray segment (unit directions)
    sample: Tensor  # [n] int64 row in the wavefront's sample arrays
    throughput: Tensor  # [n, 3] path throughput so far
    prev_bsdf_pdf: Tensor  # [n] solid-angle pdf of the BSDF sample that produced `rays` (MIS)

    def select(self, index: Tensor) -> "_Paths":
        """The paths at ``index`` (int64 indices or a bool mask)."""
        return _Paths(self.rays[index], self.sample[index], self.throughput[index], self.prev_bsdf_pdf[index])


@dataclass
class _Shading:
    """Hit-point geometry of the live paths that hit something."""

    p: Tensor  # [n, 3] world hit point
    wo: Tensor  # [n, 3] unit, towards where the ray came from
    ng: Tensor  # [n, 3] geometric normal turned to the side of wo
    ns: Tensor  # [n, 3] shading normal, same side as ng (ng where the shading normal faces away from wo)
    front: Tensor  # [n] bool: wo is on the side the (unflipped) geometric normal points to
    albedo: Tensor  # [n, 3] material albedo x texture x surface colour
    offset: Tensor  # [n] world-space ray offset of the hit instance


class PathTracer:
    """The stages of one wavefront, over a `neuralrt.scene.Scene`."""

    def __init__(self, scene, settings: IntegratorSettings):
        self.scene = scene
        self.settings = settings
        self.materials = scene.materials
        self.lights = scene.lights
        self._has_emitters = bool(self.materials.emissive_mask.any())

    # -- stage: camera rays ------------------------------------------------------------------------
    def generate_camera_rays(self, pixel: Tensor, g: torch.Generator) -> _Paths:
        n, dev = pixel.numel(), pixel.device
        rays = self.scene.camera.generate_rays(pixel, uniform((n, 2), g, dev))
        return _Paths(rays, torch.arange(n, device=dev), torch.ones(n, 3, device=dev), torch.zeros(n, device=dev))

    # -- stage: escaped rays ------------------------------------------------------------------------
    def handle_escaped(self, paths: _Paths, radiance: Tensor, first: bool) -> None:
        env = self.lights.environment
        if env is None or paths.sample.numel() == 0:
            return
        d = paths.rays.directions
        le = env.radiance(d)
        w = torch.ones_like(paths.prev_bsdf_pdf) if first else power_heuristic(paths.prev_bsdf_pdf, self.lights.environment_pdf(d))
        radiance.index_add_(0, paths.sample, paths.throughput * le * w[:, None])

    # -- stage: shading geometry ----------------------------------------------------------------------
    def shading(self, paths: _Paths, hits: Hits) -> _Shading:
        d = paths.rays.directions
        p = paths.rays.origins + hits.t[:, None] * d
        wo = -d
        ng_raw = hits.geometric_normal
        front = (ng_raw * wo).sum(-1) > 0
        ng = torch.where(front[:, None], ng_raw, -ng_raw)
        ns = hits.normal
        ns = torch.where(((ns * ng).sum(-1) < 0)[:, None], -ns, ns)
        ns = torch.where(((ns * wo).sum(-1) <= 0)[:, None], ng, ns)
        albedo = self.materials.albedo_at(hits.material_id, hits.uv, hits.albedo)
        offset = self.scene.instance_offsets[hits.instance_id.clamp(min=0)]
        return _Shading(p, wo, ng, ns, front, albedo, offset)

    # -- stage: emission at hits -----------------------------------------------------------------------
    def emission_at_hits(self, paths: _Paths, hits: Hits, sh: _Shading, radiance: Tensor, first: bool) -> None:
        if not self._has_emitters:
            return
        le = self.materials.emission_of(hits.material_id) * sh.front[:, None]
        idx = torch.nonzero(le.amax(-1) > 0).reshape(-1)  # only rows that see emission
        if idx.numel() == 0:
            return
        le = le[idx]
        if first:
            w = torch.ones_like(le[:, 0])
        else:
            light = self.lights.area.light_index(hits.instance_id[idx], hits.primitive_id[idx]) if self.lights.area is not None \
                else torch.full_like(idx, -1)
            light_pdf = self.lights.area_pdf(light, hits.t[idx], paths.rays.directions[idx])
            w = power_heuristic(paths.prev_bsdf_pdf[idx], light_pdf)
        radiance.index_add_(0, paths.sample[idx], paths.throughput[idx] * le * w[:, None])

    # -- stage: next-event estimation -------------------------------------------------------------------
    def sample_lights(self, paths: _Paths, hits: Hits, sh: _Shading, radiance: Tensor, g: torch.Generator) -> None:
        n, dev = paths.sample.numel(), sh.p.device
        if not self.lights or n == 0:
            return
        u = uniform((n, 4), g, dev)
        ls = self.lights.sample(sh.p, u)
        f, bsdf_pdf = self.materials.eval_pdf(hits.material_id, sh.albedo, sh.ns, sh.wo, ls.wi)
        usable = (ls.pdf > 0) & ((ls.wi * sh.ng).sum(-1) > 0) & (f.amax(-1) > 0) & (ls.radiance.amax(-1) > 0)
        if not usable.any():
            return
        idx = torch.nonzero(usable).reshape(-1)
        origin = sh.p[idx] + sh.ng[idx] * sh.offset[idx, None]
        # Finite lights: aim from the offset origin at the light point itself, stopping just short of it.
        finite = torch.isfinite(ls.distance[idx])
        target = sh.p[idx] + ls.wi[idx] * torch.where(finite, ls.distance[idx], 0.0)[:, None]
        direction = torch.where(finite[:, None], target - origin, ls.wi[idx])
        t_max = torch.where(finite, _SHADOW_T_MAX, float("inf"))
        blocked = self.scene.accel.occluded(Rays(origin, direction, torch.zeros_like(t_max), t_max))
        idx = idx[~blocked]
        w = torch.where(ls.is_delta[idx], 1.0, power_heuristic(ls.pdf[idx], bsdf_pdf[idx]))
        contrib = paths.throughput[idx] * f[idx] * ls.radiance[idx] * (w / ls.pdf[idx])[:, None]
        radiance.index_add_(0, paths.sample[idx], contrib)

    # -- stage: BSDF sampling + Russian roulette --------------------------------------------------------
    def sample_bsdf(self, paths: _Paths, hits: Hits, sh: _Shading, bounce: int, g: torch.Generator) -> _Paths:
        n, dev = paths.sample.numel(), sh.p.device
        u = uniform((n, 4), g, dev)
        s = self.materials.sample(hits.material_id, sh.albedo, sh.ns, sh.wo, u[:, 0], u[:, 1:3])
        throughput = paths.throughput * s.weight
        alive = (s.pdf > 0) & ((s.wi * sh.ng).sum(-1) > 0) & (throughput.amax(-1) > 0)
        # Russian roulette: survive with probability ~ throughput (capped), reweight survivors.
        if bounce + 1 >= self.settings.rr_depth:
            q = throughput.amax(-1).clamp(max=self.settings.rr_max_survival)
            alive &= u[:, 3] < q
            throughput = throughput / torch.where(alive, q, 1.0)[:, None]
        idx = torch.nonzero(alive).reshape(-1)
        origin = sh.p[idx] + sh.ng[idx] * sh.offset[idx, None]
        return _Paths(Rays(origin, s.wi[idx]), paths.sample[idx], throughput[idx], s.pdf[idx])

    # -- one wavefront -----------------------------------------------------------------------------------
    def trace(self, pixel: Tensor, g: torch.Generator) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Radiance, albedo, normal [n, 3], depth [n] and camera-ray hit [n] bool for one sample
        through each entry of ``pixel`` [n]."""
        n, dev = pixel.numel(), pixel.device
        radiance = torch.zeros(n, 3, device=dev)  # per-sample radiance accumulator
        aov_albedo = torch.zeros(n, 3, device=dev)
        aov_normal = torch.zeros(n, 3, device=dev)
        aov_depth = torch.zeros(n, device=dev)
        aov_hit = torch.zeros(n, dtype=torch.bool, device=dev)  # camera ray hit something
        paths = self.generate_camera_rays(pixel, g)
        for bounce in range(self.settings.max_depth + 1):
            first = bounce == 0
            # Find closest intersections along live rays
            hits = self.scene.accel.intersect(paths.rays, camera_rays=first and self.settings.primary == "exact")
            self.handle_escaped(paths.select(torch.nonzero(~hits.hit).reshape(-1)), radiance, first)
            hit_idx = torch.nonzero(hits.hit).reshape(-1)  # index once, gather every field with it
            paths, hits = paths.select(hit_idx), hits[hit_idx]
            if paths.sample.numel() == 0:
                break
            sh = self.shading(paths, hits)
            self.emission_at_hits(paths, hits, sh, radiance, first)
            if first:
                aov_albedo[paths.sample] = sh.albedo
                aov_normal[paths.sample] = sh.ns
                aov_depth[paths.sample] = hits.t
                aov_hit[paths.sample] = True
            if bounce == self.settings.max_depth:
                break
            self.sample_lights(paths, hits, sh, radiance, g)
            paths = self.sample_bsdf(paths, hits, sh, bounce, g)
            if paths.sample.numel() == 0:
                break
        return radiance, aov_albedo, aov_normal, aov_depth, aov_hit


def render(
    scene,
    spp: int | None = None,
    seed: int = 0,
    max_depth: int | None = None,
    resolution: tuple[int, int] | None = None,
    device=None,
    progress: bool = True,
    max_paths: int | None = None,
    settings: IntegratorSettings | None = None,
    primary: str | None = None,
) -> RenderResult:
    """Render ``scene`` (a `neuralrt.scene.Scene`) progressively and return the pixel means.

    Each setting comes from, in order: its keyword argument, then ``settings`` (an
    `IntegratorSettings`, never modified), then the scene (``spp`` / ``max_depth`` from its
    ``render`` section), then the `IntegratorSettings` defaults. ``resolution`` (width, height)
    overrides the camera's. Samples are taken in passes of ``k`` samples per pixel, with
    ``k * pixels <= max_paths`` paths alive at once (at least one pixel row's worth); a progress
    bar counts samples per pixel. ``device`` defaults to the scene's. ``primary`` ("exact" or
    "neural", default: what the scene was loaded for) picks who answers camera rays for neural
    objects; "exact" needs a scene loaded with ``primary="exact"`` (their meshes kept).
    """
    from dataclasses import replace

    if settings is None:
        settings = IntegratorSettings(max_depth=scene.settings.max_depth, primary=scene.primary)
    overrides = {"max_depth": max_depth, "max_paths": max_paths, "primary": primary}
    settings = replace(settings, **{k: v for k, v in overrides.items() if v is not None})  # never mutate the caller's
    if settings.primary not in ("exact", "neural"):
        raise ValueError(f"primary must be 'exact' or 'neural', got {settings.primary!r}")
    if settings.primary == "exact" and scene.primary == "neural":
        raise ValueError("the scene was loaded with primary='neural' (its neural objects kept no mesh for camera rays): "
                         "load it with primary='exact' to render that way")
    spp = int(spp if spp is not None else scene.settings.spp)
    if spp < 1 or settings.max_depth < 1 or settings.max_paths < 1:
        raise ValueError("spp, max_depth and max_paths must be >= 1")
    camera = scene.camera.with_resolution(resolution) if resolution is not None else scene.camera
    dev = resolve_device(device) if device is not None else scene.device
    if dev != scene.device:
        raise ValueError(f"scene was built on {scene.device}; load it with device={dev} to render there")
    tracer = PathTracer(_with_camera(scene, camera), settings)
    film = Film(camera.width, camera.height, dev)
    n_pixels = camera.num_pixels
    per_pass = max(1, min(spp, settings.max_paths // n_pixels))  # samples per pixel in one wavefront
    chunk = min(n_pixels * per_pass, max(settings.max_paths, camera.width))

    from tqdm.auto import tqdm

    start = time.perf_counter()
    done = 0
    wavefront = 0
    with tqdm(total=spp, unit="spp", desc="render", disable=not progress, leave=False) as bar:
        while done < spp:
            k = min(per_pass, spp - done)
            samples = torch.arange(n_pixels, device=dev).repeat(k)  # pixel index of each path
            for lo in range(0, samples.numel(), chunk):
                g = make_generator(seed * 1_000_003 + wavefront, dev)
                wavefront += 1
                pixel = samples[lo:lo + chunk]
                film.add(pixel, *tracer.trace(pixel, g))
            done += k
            bar.update(k)
    return film.result(spp, time.perf_counter() - start)


def _with_camera(scene, camera):
    if camera is scene.camera:
        return scene
    from dataclasses import replace

    return replace(scene, camera=camera)
