"""Wavefront unidirectional path tracer with next-event estimation and multiple importance sampling.

All paths of a wavefront advance together as tensors. Each bounce runs the same whole-batch
stages (pbrt-v4's wavefront integrator):

    generate_camera_rays -> intersect -> shade: escaped rays, emission at hits (MIS),
    [AOVs at the first hit], light sample (NEE, MIS), BSDF sample, Russian roulette, compaction
    -> occluded (the NEE shadow rays) -> add the unoccluded light samples

``shade`` and the accumulation are `shading_stages`: fused numba kernels on the CPU, torch ops on
other devices, chosen once per render (``IntegratorSettings.shading``); both draw the same
uniforms (one row per sample and bounce), so they give the same images to float tolerance.

MIS uses the power heuristic between light sampling and BSDF sampling for area and environment
lights; point lights are delta lights (light sampling only). ``max_depth`` counts bounces: 1 gives
direct lighting only (emission seen directly plus one scattering event).

Secondary rays start at the hit point moved along the face-forwarded geometric normal by the hit
instance's `Scene.instance_offsets` (its BLAS ``secondary_offset`` scaled to world), and by at least
`shading_kernels.POSITION_OFFSET` of the point's largest coordinate (its float32 rounding); shadow rays
stop short of their light point by a relative ``1e-3`` of its distance. The integrator only calls
``scene.accel.intersect`` / ``occluded``: it never knows which kind of BLAS answered.
Randomness comes from one stream per wavefront seeded from a hash of (``seed``, wavefront index,
`rng.wavefront_seed`): a torch
generator's, drawn by torch or, with the numba stages, the same numbers by a numba pass
(`rng`), so a given seed and settings give the same image on one device (CUDA's generator is
Philox, the CPU's MT19937: the noise differs between them); each bounce draws one row of 8 uniforms per
sample of the wavefront, so a path's random numbers do not depend on the other paths.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import torch
from torch import Tensor

from ..arguments import check_count, check_flags, seed_or_default
from ..errors import ConfigError, DeviceError
from ..fork_guard import check_not_forked
from .film import Film, RenderResult
from .rng import wavefront_seed
from .shading_stages import SHADING_BACKENDS, PathState, WavefrontFilm, shading_stages_for

__all__ = ["render", "IntegratorSettings", "PathTracer"]


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
    # Shading and sampling implementation: "auto" (numba kernels on the CPU, torch elsewhere),
    # "torch" or "numba" (the same answers to float tolerance; see `shading_stages`).
    shading: str = "auto"


class PathTracer:
    """One wavefront's bounces over a `neuralrt.scene.Scene`: ray queries here, shading and sampling
    in the `shading_stages` implementation chosen once for the scene's device."""

    def __init__(self, scene, settings: IntegratorSettings):
        self.scene = scene
        self.settings = settings
        self.stages = shading_stages_for(scene, settings, settings.shading)

    def generate_camera_rays(self, pixel: Tensor, g) -> PathState:
        return self.stages.camera_paths(pixel, g.uniform((pixel.numel(), 2)))

    def trace(self, pixel: Tensor, g) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Radiance, albedo, normal [n, 3], depth [n] and camera-ray hit [n] bool for one sample
        through each entry of ``pixel`` [n], drawing from ``g`` (the stages' ``uniforms(seed)``)."""
        n, dev = pixel.numel(), pixel.device
        film = WavefrontFilm.zeros(n, dev)
        paths = self.generate_camera_rays(pixel, g)
        for bounce in range(self.settings.max_depth + 1):
            first = bounce == 0
            # Find closest intersections along live rays
            hits = self.scene.accel.intersect(paths.rays, camera_rays=first and self.settings.primary == "exact")
            u = None
            if bounce < self.settings.max_depth and bool(hits.hit.any()):
                # One row of uniforms per sample of the wavefront, looked up by the path's sample: a
                # path's random numbers do not depend on which other paths are still alive.
                u = g.uniform((n, 8))
            shadow, paths = self.stages.shade(paths, hits, u, bounce, film)
            if shadow is not None:
                blocked = self.scene.accel.occluded(shadow.rays, camera_hits=first)  # NEE shadow rays: the one visibility query
                self.stages.add_unoccluded(film, shadow, blocked)
            if paths is None or paths.sample.numel() == 0:
                break
        return film.radiance, film.albedo, film.normal, film.depth, film.hit


WARM_UP_RESOLUTION = (8, 8)  # enough pixels to reach every bounce kind of a scene; ~10 ms once warm


def warm_up(scene, primary: str | None = None, max_depth: int | None = None) -> float:
    """Render a few pixels of ``scene`` at 1 spp, untimed, and return the seconds it took: the first
    render in a process loads the compiled kernels it uses (~0.3 s on the 2-core CPU, whatever the
    image size), so a timed render that follows measures its sample passes only."""
    start = time.perf_counter()
    render(scene, spp=1, resolution=WARM_UP_RESOLUTION, progress=False, primary=primary, max_depth=max_depth)
    return time.perf_counter() - start


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
    shading: str | None = None,
    progress_label: str = "render",
) -> RenderResult:
    """Render ``scene`` (a `neuralrt.scene.Scene`) progressively and return the pixel means.

    Each setting comes from, in order: its keyword argument, then ``settings`` (an
    `IntegratorSettings`, never modified), then the scene (``spp`` / ``max_depth`` from its
    ``render`` section), then the `IntegratorSettings` defaults. ``resolution`` (width, height)
    overrides the camera's. Samples are taken in passes of ``k`` samples per pixel, with
    ``k * pixels <= max_paths`` paths alive at once (at least one pixel row's worth); a progress
    bar counts samples per pixel. ``device`` defaults to the scene's. ``primary`` ("exact" or
    "neural", default: what the scene was loaded for) picks who answers camera rays for neural
    objects; "exact" needs a scene loaded with ``primary="exact"`` (their meshes kept). ``shading``
    ("auto", "torch" or "numba") picks the shading implementation (`IntegratorSettings.shading`);
    ``progress_label`` names the progress bar.
    """
    from dataclasses import replace

    from ..devices import check_device, check_memory
    from ..scene.scene import Scene
    from ..scene.schema import MAX_DEPTH, MAX_SPP, check_resolution

    check_not_forked("render")
    if not isinstance(scene, Scene):  # (a path or builtin:NAME is api.render's, or load it with load_scene)
        raise ConfigError(f"scene: expected a loaded neuralrt Scene (load_scene, load_dict), got {type(scene).__name__}")
    if settings is None:
        settings = IntegratorSettings(max_depth=scene.settings.max_depth, primary=scene.primary)
    elif not isinstance(settings, IntegratorSettings):
        raise ConfigError(f"settings: expected an IntegratorSettings (or give its fields as keyword arguments: spp=, "
                          f"max_depth=, ...), got {type(settings).__name__}")
    overrides = {"max_depth": max_depth, "max_paths": max_paths, "primary": primary, "shading": shading}
    settings = replace(settings, **{k: v for k, v in overrides.items() if v is not None})  # never mutate the caller's
    check_flags(progress=progress)
    spp = check_count("spp", spp, maximum=MAX_SPP)  # a scene file's bounds
    # (as Python ints, which the checks return: a numpy integer's fixed-width arithmetic would overflow)
    settings = replace(settings, max_depth=check_count("max_depth", settings.max_depth, maximum=MAX_DEPTH),
                       max_paths=check_count("max_paths", settings.max_paths))
    seed = seed_or_default("seed", seed)
    if settings.primary not in ("exact", "neural"):
        raise ConfigError(f"primary must be 'exact' or 'neural', got {settings.primary!r}")
    if settings.shading not in SHADING_BACKENDS:
        raise ConfigError(f"shading must be one of {', '.join(map(repr, SHADING_BACKENDS))}, got {settings.shading!r}")
    if settings.primary == "exact" and scene.primary == "neural":
        raise ConfigError("the scene was loaded with primary='neural' (its neural objects kept no mesh for camera rays): "
                         "load it with primary='exact' to render that way")
    spp = spp if spp is not None else scene.settings.spp
    camera = scene.camera.with_resolution(check_resolution(resolution)) if resolution is not None else scene.camera
    dev = check_device(device) if device is not None else scene.device
    if dev != scene.device:
        raise DeviceError(f"scene was built on {scene.device}; load it with device={dev} to render there")
    n_pixels = camera.num_pixels
    per_pass = max(1, min(spp, settings.max_paths // n_pixels))  # samples per pixel in one wavefront
    chunk = min(n_pixels * per_pass, max(settings.max_paths, camera.width))
    # The film's sums, a pass's pixel indices (int64) and the finished images (float32: 11 channels).
    check_memory(f"a {camera.width}x{camera.height} render", n_pixels * (Film.BYTES_PER_PIXEL + 8 * per_pass + 11 * 4), dev,
                 "render at a lower resolution")
    tracer = PathTracer(_with_camera(scene, camera), settings)
    film = Film(camera.width, camera.height, dev)

    from ..progress import progress_bar

    start = time.perf_counter()
    done = 0
    wavefront = 0
    with progress_bar(total=spp, unit="spp", desc=progress_label, disable=not progress, leave=False) as bar:
        while done < spp:
            k = min(per_pass, spp - done)
            samples = torch.arange(n_pixels, device=dev).repeat(k)  # pixel index of each path
            for lo in range(0, samples.numel(), chunk):
                g = tracer.stages.uniforms(wavefront_seed(seed, wavefront))
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
