"""The path tracer's shading and sampling for one bounce, in two implementations with one contract.

`NumbaShadingStages` runs fused numba passes (`shading_kernels`) on CPU tensors; `TorchShadingStages`
runs torch ops on any device. `PathTracer` picks one at construction (`shading_stages_for`) and never
branches on the device again. Both take the same random numbers in the same roles, so they give
the same answers to float tolerance (the tests run both on CPU tensors). The numba passes run over
chunks of rows on numba's thread count (they release the GIL); the result does not depend on it.

The contract, for the live paths of a wavefront and their closest hits:

- ``uniforms(seed)``: the random stream of one wavefront (``.uniform(shape)`` float32 tensors); both
  implementations give the same numbers (`rng`).
- ``camera_paths(pixel, jitter)``: paths starting with the camera rays through pixels ``pixel``
  [n] (row-major) at offsets ``jitter`` [n, 2] (`Camera.generate_rays`), sample ``k`` in row k.
- ``shade(paths, hits, u, bounce, film)``: adds escaped radiance (environment, MIS) and emission
  seen at hits (MIS) to ``film.radiance``, records the AOVs at the first bounce, and, when ``u``
  is given (``bounce < max_depth``), samples one light per hit (NEE) and the BSDF with Russian
  roulette. Returns ``(shadow, next_paths)``: the NEE shadow rays with the contribution each adds
  if unoccluded (None when there are none), and the surviving paths (None when nothing scatters).
- ``add_unoccluded(film, shadow, blocked)``: adds the contributions of the shadow rays not blocked.

``u`` is [n_samples, 8] uniforms, one row per sample of the wavefront, read at each path's
``sample``: ``u[:, 0]`` picks the light kind and the light, ``[:, 1:3]`` the point on it (``3`` is
unused); ``u[:, 4]`` picks the BSDF lobe, ``[:, 5:7]`` the direction, ``[:, 7]`` decides Russian
roulette.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..host_threads import chunk_slices, run_chunks
from ..rays import Hits, Rays
from .lights import LightSet
from .materials import MaterialTable
from .rng import NumbaUniforms, TorchUniforms
from .sampling import power_heuristic
from .shading_kernels import POSITION_OFFSET, SHADOW_T_MAX

__all__ = ["PathState", "ShadowQueries", "WavefrontFilm", "TorchShadingStages", "NumbaShadingStages", "shading_stages_for",
           "SHADOW_T_MAX"]



@dataclass
class PathState:
    """The state of the live paths of a wavefront (one row per path)."""

    rays: Rays  # current ray segment (unit directions)
    sample: Tensor  # [n] int64 row in the wavefront's sample arrays
    throughput: Tensor  # [n, 3] path throughput so far
    prev_bsdf_pdf: Tensor  # [n] solid-angle pdf of the BSDF sample that produced `rays` (MIS)

    def select(self, index: Tensor) -> "PathState":
        """The paths at ``index`` (int64 indices or a bool mask)."""
        return PathState(self.rays[index], self.sample[index], self.throughput[index], self.prev_bsdf_pdf[index])


@dataclass
class ShadowQueries:
    """NEE shadow rays and what each adds to its sample's radiance if nothing blocks it."""

    rays: Rays  # [m] from the offset hit point towards the light (t_max just short of a finite light)
    sample: Tensor  # [m] int64 sample row
    contribution: Tensor  # [m, 3] throughput x f x L x MIS weight / pdf


@dataclass
class WavefrontFilm:
    """Per-sample accumulators of one wavefront (one row per sample)."""

    radiance: Tensor  # [n, 3]
    albedo: Tensor  # [n, 3] first-hit albedo
    normal: Tensor  # [n, 3] first-hit shading normal
    depth: Tensor  # [n] first-hit distance
    hit: Tensor  # [n] bool: the camera ray hit something

    @staticmethod
    def zeros(n: int, device) -> "WavefrontFilm":
        return WavefrontFilm(torch.zeros(n, 3, device=device), torch.zeros(n, 3, device=device), torch.zeros(n, 3, device=device),
                             torch.zeros(n, device=device), torch.zeros(n, dtype=torch.bool, device=device))


SHADING_BACKENDS = ("auto", "torch", "numba")


def shading_stages_for(scene, settings, backend: str = "auto"):
    """The stages for ``scene``'s device: numba on the CPU, torch elsewhere; ``backend`` ("torch" or
    "numba") forces one (numba needs a CPU scene)."""
    if backend == "auto":
        backend = "numba" if scene.device.type == "cpu" else "torch"
    if backend == "numba":
        if scene.device.type != "cpu":
            raise ValueError(f"the numba shading stages run on the CPU; the scene is on {scene.device}")
        return NumbaShadingStages(scene, settings)
    if backend == "torch":
        return TorchShadingStages(scene, settings)
    raise ValueError(f"shading backend must be 'auto', 'torch' or 'numba', got {backend!r}")


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


class TorchShadingStages:
    """The stages as whole-batch torch ops: any device."""

    def __init__(self, scene, settings):
        self.scene = scene
        self.settings = settings
        self.materials: MaterialTable = scene.materials
        self.lights: LightSet = scene.lights
        self._has_emitters = bool(self.materials.emissive_mask.any())

    def uniforms(self, seed: int) -> TorchUniforms:
        return TorchUniforms(seed, self.scene.device)

    def camera_paths(self, pixel: Tensor, jitter: Tensor) -> PathState:
        n, dev = pixel.numel(), pixel.device
        rays = self.scene.camera.generate_rays(pixel, jitter)
        return PathState(rays, torch.arange(n, device=dev), torch.ones(n, 3, device=dev), torch.zeros(n, device=dev))

    def shade(self, paths: PathState, hits: Hits, u: Tensor | None, bounce: int,
              film: WavefrontFilm) -> tuple[ShadowQueries | None, PathState | None]:
        first = bounce == 0
        self._escaped(paths.select(torch.nonzero(~hits.hit).reshape(-1)), film.radiance, first)
        hit_idx = torch.nonzero(hits.hit).reshape(-1)  # index once, gather every field with it
        paths, hits = paths.select(hit_idx), hits[hit_idx]
        if paths.sample.numel() == 0:
            return None, None
        sh = self._shading(paths, hits)
        self._emission_at_hits(paths, hits, sh, film.radiance, first)
        if first:
            film.albedo[paths.sample] = sh.albedo
            film.normal[paths.sample] = sh.ns
            film.depth[paths.sample] = hits.t
            film.hit[paths.sample] = True
        if u is None:
            return None, None
        u = u[paths.sample]
        shadow = self._light_samples(paths, hits, sh, u[:, 0:4]) if self.lights else None
        return shadow, self._sample_bsdf(paths, hits, sh, bounce, u[:, 4:8])

    def add_unoccluded(self, film: WavefrontFilm, shadow: ShadowQueries, blocked: Tensor) -> None:
        keep = torch.nonzero(~blocked).reshape(-1)
        film.radiance.index_add_(0, shadow.sample[keep], shadow.contribution[keep])

    # -- escaped rays ----------------------------------------------------------------------------------
    def _escaped(self, paths: PathState, radiance: Tensor, first: bool) -> None:
        env = self.lights.environment
        if env is None or paths.sample.numel() == 0:
            return
        d = paths.rays.directions
        le = env.radiance(d)
        w = torch.ones_like(paths.prev_bsdf_pdf) if first else power_heuristic(paths.prev_bsdf_pdf, self.lights.environment_pdf(d))
        radiance.index_add_(0, paths.sample, paths.throughput * le * w[:, None])

    # -- shading geometry ------------------------------------------------------------------------------
    def _shading(self, paths: PathState, hits: Hits) -> _Shading:
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
        offset = torch.maximum(self.scene.instance_offsets[hits.instance_id.clamp(min=0)],
                               POSITION_OFFSET * p.abs().amax(-1))  # (`shading_kernels.POSITION_OFFSET`)
        return _Shading(p, wo, ng, ns, front, albedo, offset)

    # -- emission at hits --------------------------------------------------------------------------------
    def _emission_at_hits(self, paths: PathState, hits: Hits, sh: _Shading, radiance: Tensor, first: bool) -> None:
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

    # -- next-event estimation ---------------------------------------------------------------------------
    def _light_samples(self, paths: PathState, hits: Hits, sh: _Shading, u: Tensor) -> ShadowQueries | None:
        ls = self.lights.sample(sh.p, u)
        f, bsdf_pdf = self.materials.eval_pdf(hits.material_id, sh.albedo, sh.ns, sh.wo, ls.wi)
        usable = (ls.pdf > 0) & ((ls.wi * sh.ng).sum(-1) > 0) & (f.amax(-1) > 0) & (ls.radiance.amax(-1) > 0)
        idx = torch.nonzero(usable).reshape(-1)
        if idx.numel() == 0:
            return None
        origin = sh.p[idx] + sh.ng[idx] * sh.offset[idx, None]
        # Finite lights: aim from the offset origin at the light point itself, stopping just short of it.
        finite = torch.isfinite(ls.distance[idx])
        target = sh.p[idx] + ls.wi[idx] * torch.where(finite, ls.distance[idx], 0.0)[:, None]
        direction = torch.where(finite[:, None], target - origin, ls.wi[idx])
        t_max = torch.where(finite, SHADOW_T_MAX, float("inf"))
        w = torch.where(ls.is_delta[idx], 1.0, power_heuristic(ls.pdf[idx], bsdf_pdf[idx]))
        contribution = paths.throughput[idx] * f[idx] * ls.radiance[idx] * (w / ls.pdf[idx])[:, None]
        return ShadowQueries(Rays(origin, direction, torch.zeros_like(t_max), t_max), paths.sample[idx], contribution)

    # -- BSDF sampling + Russian roulette ----------------------------------------------------------------
    def _sample_bsdf(self, paths: PathState, hits: Hits, sh: _Shading, bounce: int, u: Tensor) -> PathState:
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
        return PathState(Rays(origin, s.wi[idx]), paths.sample[idx], throughput[idx], s.pdf[idx])


# --- numba ---------------------------------------------------------------------------------------------


def _np(t: Tensor, dtype) -> np.ndarray:
    return np.ascontiguousarray(t.detach().cpu().numpy(), dtype=dtype)


def _material_table(materials: MaterialTable) -> tuple:
    """(kind, albedo, roughness, ior, emission, texture offset [M] (-1: none), texture size [M, 2],
    texels [T, 3]): every texture flattened into one array."""
    m = len(materials)
    offsets = np.full(m, -1, np.int64)
    sizes = np.zeros((m, 2), np.int64)
    texels = [np.zeros((1, 3), np.float32)]
    start = 1
    for k, tex in enumerate(materials.textures):
        if tex is None:
            continue
        h, w = tex.shape[:2]
        offsets[k], sizes[k] = start, (h, w)
        texels.append(_np(tex, np.float32).reshape(h * w, 3))
        start += h * w
    return (_np(materials.kind, np.int64), _np(materials.albedo, np.float32), _np(materials.roughness, np.float32),
            _np(materials.ior, np.float32), _np(materials.emission, np.float32), offsets, sizes, np.concatenate(texels))


def _light_tables(lights: LightSet) -> tuple:
    """(kinds [K] codes in `LightSet.kinds` order, area, points, environment) tuples for the kernels;
    absent kinds get one-row placeholders the kernels never read."""
    codes = {"area": 0, "point": 1, "environment": 2}
    kinds = np.array([codes[k] for k in lights.kinds], np.int64)
    a = lights.area
    if a is not None:
        area = (_np(a.triangles, np.float32), _np(a.normals, np.float32), _np(a.emission, np.float32),
                _np(a.distribution.cdf, np.float64), _np(a.distribution.pmf, np.float32), _np(a._area_pdf, np.float32),
                _np(a._base, np.int64), _np(a._holds, np.bool_), _np(a._lookup, np.int64))
    else:
        area = (np.zeros((1, 3, 3), np.float32), np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32), np.ones(1),
                np.ones(1, np.float32), np.zeros(1, np.float32), np.zeros(1, np.int64), np.zeros(1, np.bool_), np.full(1, -1, np.int64))
    pl = lights.points
    if pl is not None:
        points = (_np(pl.positions, np.float32), _np(pl.intensities, np.float32), _np(pl.distribution.cdf, np.float64),
                  _np(pl.distribution.pmf, np.float32))
    else:
        points = (np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32), np.ones(1), np.ones(1, np.float32))
    e = lights.environment
    if e is None:
        env = (np.zeros(3, np.float32), np.zeros((1, 1, 3), np.float32), np.ones(1), np.ones(1, np.float32), True, 1.0, 0.0, False)
    elif e.is_constant:
        env = (_np(e.color, np.float32), np.zeros((1, 1, 3), np.float32), np.ones(1), np.ones(1, np.float32), True, e._cos, e._sin, True)
    else:
        env = (np.zeros(3, np.float32), _np(e.image, np.float32), _np(e.distribution.cdf, np.float64), _np(e.distribution.pmf, np.float32),
               False, e._cos, e._sin, True)
    return kinds, area, points, env


class NumbaShadingStages:
    """The stages as fused numba passes over CPU tensors (zero-copy numpy views)."""

    def __init__(self, scene, settings):
        from . import shading_kernels

        self.kernels = shading_kernels
        self.settings = settings
        self.materials = _material_table(scene.materials)
        self.instance_offsets = _np(scene.instance_offsets, np.float32)
        self.kinds, self.area, self.points, self.env = _light_tables(scene.lights)
        self.has_emitters = bool(scene.materials.emissive_mask.any())
        self.has_area = scene.lights.area is not None
        self.has_lights = bool(scene.lights)
        self.camera = scene.camera

    def uniforms(self, seed: int) -> NumbaUniforms:
        return NumbaUniforms(seed)

    def camera_paths(self, pixel: Tensor, jitter: Tensor) -> PathState:
        n, cam = pixel.numel(), self.camera
        origins, directions = torch.empty(n, 3), torch.empty(n, 3)
        self.kernels.camera_rays(_c(pixel), _c(jitter), cam.width, cam.height, math.tan(math.radians(cam.fov_y_degrees) * 0.5),
                                 cam.width / cam.height, _np(cam.camera_to_world.matrix, np.float32), origins.numpy(),
                                 directions.numpy())
        return PathState(Rays(origins, directions), torch.arange(n), torch.ones(n, 3), torch.zeros(n))

    def shade(self, paths: PathState, hits: Hits, u: Tensor | None, bounce: int,
              film: WavefrontFilm) -> tuple[ShadowQueries | None, PathState | None]:
        n = len(paths.sample)
        scatter = u is not None
        m = n if scatter else 0  # output rows (at most one shadow ray and one next path per row)
        shadow_out = (np.empty((m, 3), np.float32), np.empty((m, 3), np.float32), np.empty(m, np.float32), np.empty(m, np.int64),
                      np.empty((m, 3), np.float32))  # origin, direction, t_max, sample, contribution
        next_out = (np.empty((m, 3), np.float32), np.empty((m, 3), np.float32), np.empty(m, np.int64), np.empty((m, 3), np.float32),
                    np.empty(m, np.float32))  # origin, direction, sample, throughput, pdf
        rays = paths.rays
        rows = [_c(x) for x in (rays.origins, rays.directions, paths.sample, paths.throughput, paths.prev_bsdf_pdf, hits.hit, hits.t,
                                hits.normal, hits.geometric_normal, hits.uv, hits.albedo, hits.material_id, hits.instance_id,
                                hits.primitive_id)]
        shared = (_c(u) if scatter else np.zeros((0, 8), np.float32), self.materials, self.instance_offsets, self.kinds, self.area,
                  self.points, self.env, bounce == 0, scatter, scatter and self.has_lights, self.has_emitters, self.has_area,
                  bounce + 1 >= self.settings.rr_depth, float(self.settings.rr_max_survival),
                  film.radiance.numpy(), film.albedo.numpy(), film.normal.numpy(), film.depth.numpy(), film.hit.numpy())

        def run(lo: int, hi: int) -> tuple[int, int]:
            # Rows [lo, hi) write their outputs compacted from row lo on; samples differ between
            # rows, so chunks never write the same accumulator.
            return self.kernels.shade_and_sample(*(x[lo:hi] for x in rows), *shared, *(x[lo:hi] for x in shadow_out),
                                                 *(x[lo:hi] for x in next_out))

        chunks = _run_in_chunks(run, n)
        shadow = None
        if sum(c[0][0] for c in chunks):
            origin, direction, t_max, sample, contribution = (_gather(x, chunks, 0) for x in shadow_out)
            shadow = ShadowQueries(Rays(origin, direction, torch.zeros_like(t_max), t_max), sample, contribution)
        if not scatter:
            return shadow, None
        origin, direction, sample, throughput, pdf = (_gather(x, chunks, 1) for x in next_out)
        return shadow, PathState(Rays(origin, direction), sample, throughput, pdf)

    def add_unoccluded(self, film: WavefrontFilm, shadow: ShadowQueries, blocked: Tensor) -> None:
        self.kernels.add_unoccluded(film.radiance.numpy(), _c(shadow.sample), _c(shadow.contribution), _c(blocked))


def _c(t: Tensor) -> np.ndarray:
    """A contiguous numpy view of a CPU tensor (a copy only where the tensor is strided)."""
    return t.detach().contiguous().numpy()


def _run_in_chunks(run, n: int) -> list[tuple[tuple[int, int], int]]:
    """``run(lo, hi)`` over consecutive row chunks on numba's thread count (the kernels release the
    GIL); returns each chunk's ``run`` result with its first row, in row order. One chunk (or one
    thread) runs on the calling thread."""
    import numba

    threads = numba.get_num_threads()
    chunks = chunk_slices(n, threads) if threads > 1 else []
    if len(chunks) <= 1:
        chunks = [slice(0, n)]
    return [(result, chunk.start) for result, chunk in
            zip(run_chunks(lambda c: run(c.start, c.stop), chunks, threads, "shading"), chunks)]


def _gather(out: np.ndarray, chunks: list[tuple[tuple[int, int], int]], which: int) -> Tensor:
    """The rows each chunk wrote (``counts[which]`` rows from its first row on), in order, as a tensor."""
    if len(chunks) == 1:
        (counts, lo), = chunks
        return torch.from_numpy(out[lo:lo + counts[which]])
    return torch.from_numpy(np.concatenate([out[lo:lo + counts[which]] for counts, lo in chunks]))
