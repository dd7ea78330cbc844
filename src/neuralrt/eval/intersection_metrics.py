"""How well a (neural) BLAS answers rays, against exact Embree hits on the source mesh.

`evaluate_model` draws held-out rays from the training distribution (a seed the training never
uses) and reports, separately for rays from outside and rays from the surface: hit/miss accuracy,
false positive and negative rates, |t error| relative to the box diagonal, normal angle error and
material accuracy; then it renders primary normal and depth images of the object from orbit
cameras, neural vs exact, and compares them with FLIP, and from those and six axis views (along
+-x, +-y, +-z, where a scene's camera most often looks, and where an undertrained model's holes
at the surface's extreme points show) the silhouettes' intersection over union. A model's memory
and speed against exact tracing come from `neuralrt.eval.costs`. The keys are the
`neuralrt eval --json` interface that scripts rely on.

Conventions: the exact shading normal is turned to face the ray (the model is trained that way);
the predicted normal is compared as returned, and ``normal_backfacing_fraction`` counts predicted
normals that point away from the ray. t errors are distances (``|dt| * |d|``) over the diagonal of
the object's AABB.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..accel.mesh_blas import MeshBLAS
from ..geometry.mesh import Mesh
from ..methods.base import is_neural
from ..rays import AABB, Hits, Rays, face_forward
from ..training.ray_distribution import BoxRayDistribution

__all__ = ["evaluate_model", "image_files", "ray_errors", "ray_metrics", "orbit_cameras", "axis_cameras", "render_normal_depth",
           "HELD_OUT_SEED", "ORBIT_CAMERAS"]

# Training seeds are small integers; held-out rays use a seed far from them.
HELD_OUT_SEED = 1_000_003
ORBIT_CAMERAS = 4  # orbit views of eval's image figures (besides the six axis views)


def _quantiles(x: Tensor) -> tuple[float, float]:
    if x.numel() == 0:
        return float("nan"), float("nan")
    q = torch.quantile(x.double()[: 1 << 24], torch.tensor([0.5, 0.9], dtype=torch.float64))
    return float(q[0]), float(q[1])


def ray_errors(pred: Hits, truth: Hits, rays: Rays, diagonal: float) -> tuple[Tensor, Tensor, Tensor]:
    """Of the rays both hit (CPU): |t error| as a distance over ``diagonal``, the normal's angle
    error in degrees, and the predicted unit normals."""
    both = pred.hit.cpu() & truth.hit.cpu()
    d = rays.directions.cpu()
    dist_err = ((pred.t.cpu() - truth.t.cpu()).abs() * d.norm(dim=-1))[both] / diagonal
    n_pred = torch.nn.functional.normalize(pred.normal.cpu()[both], dim=-1)
    n_true = face_forward(torch.nn.functional.normalize(truth.normal.cpu()[both], dim=-1), d[both])
    cos = (n_pred * n_true).sum(-1).clamp(-1, 1)
    return dist_err, torch.rad2deg(torch.acos(cos)), n_pred


def ray_metrics(pred: Hits, truth: Hits, rays: Rays, diagonal: float) -> dict:
    """Hit/miss, distance, normal and material errors of ``pred`` against ``truth`` for ``rays``."""
    ph, th = pred.hit.cpu(), truth.hit.cpu()
    n = len(th)
    pos, neg = int(th.sum()), int((~th).sum())
    both = ph & th
    d = rays.directions.cpu()
    dist_err, angle, n_pred = ray_errors(pred, truth, rays, diagonal)
    t_med, t_p90 = _quantiles(dist_err)
    a_med, a_p90 = _quantiles(angle)
    mat_ok = (pred.material_id.cpu() == truth.material_id.cpu())[both]
    return {
        "rays": n,
        "true_hit_fraction": pos / n if n else float("nan"),
        "accuracy": float((ph == th).float().mean()) if n else float("nan"),
        # NaN (JSON null) where the denominator is empty, as for every metric here: 0.0 read as "none wrong"
        "false_positive_rate": float((ph & ~th).sum()) / neg if neg else float("nan"),
        "false_negative_rate": float((~ph & th).sum()) / pos if pos else float("nan"),
        "t_error_median": t_med,
        "t_error_p90": t_p90,
        "normal_error_deg_median": a_med,
        "normal_error_deg_p90": a_p90,
        "normal_backfacing_fraction": float(((n_pred * d[both]).sum(-1) > 0).float().mean()) if both.any() else float("nan"),
        "material_accuracy": float(mat_ok.float().mean()) if both.any() else float("nan"),
        "albedo_error_mean": float((pred.albedo.cpu() - truth.albedo.cpu())[both].abs().mean()) if both.any() else float("nan"),
    }


def orbit_cameras(bounds: AABB, count: int = 4, resolution: int = 256, elevation_deg: float = 25.0, fov_y_degrees: float = 40.0):
    """``count`` cameras on a circle around the object (y up), framing its bounding sphere."""
    from ..render.camera import Camera

    center = bounds.center.double()
    radius = 0.5 * bounds.diagonal
    dist = radius / math.sin(math.radians(fov_y_degrees) * 0.5) * 1.05
    el = math.radians(elevation_deg)
    cams = []
    for k in range(count):
        az = 2 * math.pi * (k + 0.125) / count
        offset = torch.tensor([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)], dtype=torch.float64)
        cams.append(Camera.look_at((center + dist * offset).tolist(), center.tolist(), (0.0, 1.0, 0.0), fov_y_degrees, (resolution, resolution)))
    return cams


_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


def axis_cameras(bounds: AABB, resolution: int = 256, fov_y_degrees: float = 40.0) -> dict:
    """Cameras looking at the object from +-x, +-y and +-z (name -> camera), framing its bounding sphere."""
    from ..render.camera import Camera

    center = bounds.center.double()
    dist = 0.5 * bounds.diagonal / math.sin(math.radians(fov_y_degrees) * 0.5) * 1.05
    cams = {}
    for name, axis in _AXES.items():
        up = (0.0, 0.0, -float(axis[1])) if axis[1] else (0.0, 1.0, 0.0)  # (looking along y: z is up)
        eye = center + dist * torch.tensor(axis, dtype=torch.float64)
        cams[name] = Camera.look_at(eye.tolist(), center.tolist(), up, fov_y_degrees, (resolution, resolution))
    return cams


def image_files(out_dir: Path, cameras: int = ORBIT_CAMERAS) -> list[Path]:
    """Every file `evaluate_model` writes into ``out_dir`` (checked before it starts)."""
    views = [*map(str, range(cameras)), *_AXES]
    return [_view_image(out_dir, name, view, who) for view in views for name in ("normal", "depth") for who in ("exact", "neural")] \
        + [out_dir / _ERRORS_FIGURE, out_dir / _OVERVIEW_FIGURE]


_ERRORS_FIGURE, _OVERVIEW_FIGURE = "errors.png", "overview.png"


def _view_image(out_dir: Path, name: str, view: str, who: str) -> Path:
    """One view's image: ``normal_+x_exact.png`` (``name``: normal or depth; ``who``: exact or neural)."""
    return out_dir / f"{name}_{view}_{who}.png"


def _silhouette_iou(exact_hits: Hits, test_hits: Hits) -> float:
    """Intersection over union of the pixels each image's rays hit; NaN (JSON null) where neither
    hits any, as for the ray metrics' empty denominators (it read 1.0: a perfect score for a view
    that showed nothing)."""
    both, either = int((exact_hits.hit & test_hits.hit).sum()), int((exact_hits.hit | test_hits.hit).sum())
    return both / either if either else float("nan")


# Silhouettes compared, per pixel: neither hits, both hit, only exact (a hole in the model), only the model.
_SILHOUETTE_COLOURS = np.array([[0.0, 0.0, 0.0], [0.55, 0.55, 0.55], [0.9, 0.1, 0.1], [0.15, 0.35, 1.0]], np.float32)


def _silhouette_image(exact_hits: Hits, test_hits: Hits, height: int, width: int) -> np.ndarray:
    """[H, W, 3] display colours of each pixel's agreement (`_SILHOUETTE_COLOURS`)."""
    exact, test = exact_hits.hit.cpu().numpy(), test_hits.hit.cpu().numpy()
    kind = np.where(exact & test, 1, np.where(exact, 2, np.where(test, 3, 0)))
    return _SILHOUETTE_COLOURS[kind].reshape(height, width, 3)


def render_normal_depth(blas, camera, depth_range: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, Hits]:
    """Primary-ray images from pixel centres: normals (faced, as 0.5 + 0.5 n) and depth (near = bright)."""
    return _normal_depth_images(camera, *_pixel_hits(blas, camera), depth_range)


def _pixel_hits(blas, camera) -> tuple[Rays, Hits]:
    """``camera``'s rays through its pixel centres and ``blas``'s hits of them, on the CPU."""
    idx = torch.arange(camera.num_pixels)
    rays = camera.generate_rays(idx, torch.full((len(idx), 2), 0.5))
    return rays, blas.intersect(rays.to(getattr(blas, "device", rays.device))).to("cpu")  # cameras make CPU rays


def _normal_depth_images(camera, rays: Rays, hits: Hits, depth_range: tuple[float, float]):
    """`render_normal_depth`'s images from hits already traced (and the hits)."""
    h, w = camera.height, camera.width
    n = face_forward(torch.nn.functional.normalize(hits.normal, dim=-1), rays.directions) if len(hits) else hits.normal
    normal_img = torch.where(hits.hit[:, None], 0.5 + 0.5 * n, torch.zeros_like(n)).reshape(h, w, 3)
    near, far = depth_range
    depth = (1.0 - (hits.t - near) / max(far - near, 1e-12)).clamp(0, 1)
    depth_img = torch.where(hits.hit, 0.1 + 0.9 * depth, torch.zeros_like(depth)).reshape(h, w, 1).expand(h, w, 3)
    return normal_img.numpy().astype(np.float32), depth_img.numpy().astype(np.float32), hits


def _image_metrics(blas, exact: MeshBLAS, bounds: AABB, cameras: int, resolution: int, out_dir: Path | None,
                   view_done=lambda view: None) -> tuple[dict, dict]:
    """The image figures, and (with ``out_dir``) each view's images for the overview: view ->
    (normal exact, normal neural, depth exact, depth neural, silhouettes compared).
    ``view_done(view)`` after each view."""
    from ..eval.image_metrics import compare_images
    from ..io.images import srgb_to_linear, write_png

    cams = orbit_cameras(bounds, cameras, resolution)
    axes = axis_cameras(bounds, resolution)
    views = {**{str(k): c for k, c in enumerate(cams)}, **axes}
    exact_hits = {view: _pixel_hits(exact, cam) for view, cam in views.items()}  # (traced once: range and images)
    # Depth range from the exact hits (one range for all views, so images are comparable).
    ranges = [(float(h.t[h.hit].min()), float(h.t[h.hit].max())) for _, h in exact_hits.values() if h.hit.any()]
    near = min((r[0] for r in ranges), default=0.0)
    far = max((r[1] for r in ranges), default=1.0)
    flips = {"normal": [], "depth": []}
    ious, shown = {}, {}
    for view, cam in views.items():
        ref_n, ref_d, ref_hits = _normal_depth_images(cam, *exact_hits.pop(view), (near, far))
        test_n, test_d, test_hits = render_normal_depth(blas, cam, (near, far))
        ious[view] = _silhouette_iou(ref_hits, test_hits)
        if out_dir is not None:
            shown[view] = (ref_n, test_n, ref_d, test_d, _silhouette_image(ref_hits, test_hits, cam.height, cam.width))
        for name, ref, test in (("normal", ref_n, test_n), ("depth", ref_d, test_d)):
            if view not in axes:  # (the axis views count in the IoU; FLIP stays the orbit views', comparable across runs)
                # The arrays are display values: pass them as linear values whose sRGB encoding they are.
                flips[name].append(compare_images(srgb_to_linear(ref), srgb_to_linear(test)).flip)
            if out_dir is not None:
                out_dir.mkdir(parents=True, exist_ok=True)
                write_png(_view_image(out_dir, name, view, "exact"), srgb_to_linear(ref))
                write_png(_view_image(out_dir, name, view, "neural"), srgb_to_linear(test))
        view_done(view)
    shown_ious = [v for v in ious.values() if not math.isnan(v)]  # (NaN: a view neither image shows)
    return {
        "cameras": len(cams),
        "resolution": resolution,
        "normal_flip": float(np.mean(flips["normal"])),
        "depth_flip": float(np.mean(flips["depth"])),
        "normal_flip_per_view": flips["normal"],
        "depth_flip_per_view": flips["depth"],
        "silhouette_iou": float(np.mean(shown_ious)) if shown_ious else float("nan"),
        "silhouette_iou_min": float(min(shown_ious, default=float("nan"))),
        "silhouette_iou_per_view": ious,
    }, shown


def evaluate_model(
    model_blas,
    mesh: Mesh,
    rays: int = 1 << 17,
    seed: int = HELD_OUT_SEED,
    *,
    images: bool = True,
    cameras: int = ORBIT_CAMERAS,
    resolution: int = 256,
    image_dir: str | Path | None = None,
    timing: bool = True,
    progress: bool = False,
) -> dict:
    """Held-out metrics of ``model_blas`` on ``mesh`` (see module docstring); a JSON-able dict.

    Keys: ``outside`` and ``surface`` (each from `ray_metrics`), ``images`` (``normal_flip``,
    ``depth_flip``), for models with voxel features ``features`` (how often H truncates), for
    models ``memory`` (against BVH A / B, `neuralrt.eval.costs`), and with ``timing`` ``speed``
    (rays/s of the model and of exact tracing on held-out rays, in this run). ``progress``: a bar
    over those stages (on stderr).
    """
    from ..progress import progress_bar

    neural = is_neural(model_blas)
    out_dir = Path(image_dir) if image_dir and images else None
    stages = 1 + neural + timing + (cameras + len(_AXES) if images else 0) + (out_dir is not None)
    bar = progress_bar(total=stages, desc="eval", unit="stage", disable=not progress, dynamic_ncols=True)

    def stage(name: str) -> None:
        bar.set_postfix_str(name, refresh=True)

    try:
        stage("held-out rays")
        device = model_blas.device if neural else torch.device("cpu")
        exact = MeshBLAS(mesh, device=device)
        # Held-out rays aim at the region the model answers in, on the model's device.
        box = model_blas.box if neural else exact.bounds.inflated(0.005)
        distribution = BoxRayDistribution(exact, box, seed=seed, pool_size=min(1 << 18, max(rays, 1024)), device=device)
        batch = distribution.sample(rays)
        pred = model_blas.intersect(batch.rays)
        diag = exact.bounds.diagonal
        parts = (("outside", ~batch.from_surface), ("surface", batch.from_surface))
        result: dict = {"rays": rays, "seed": seed}
        for name, sel in parts:
            result[name] = ray_metrics(pred[sel], batch.truth[sel], batch.rays[sel], diag)
        if not bool(batch.truth.hit.any()):
            _measured_nothing(f"none of the {rays:,} held-out rays meets the mesh (it covers little of its box): "
                              "the ray figures count misses only", mesh)
        if neural and hasattr(model_blas, "feature_statistics"):
            result["features"] = {name: model_blas.feature_statistics(batch.rays[sel], batch.truth[sel]) for name, sel in parts}
        bar.update(1)
        if neural:
            from .costs import memory_against_bvh

            stage("memory (BVH A / B)")
            result["memory"] = memory_against_bvh(model_blas, mesh)
            bar.update(1)
        if timing:
            stage("speed")
            result["speed"] = _speed(model_blas, exact, distribution, batch)
            bar.update(1)
        if images:
            stage("orbit and axis views")
            result["images"], shown = _image_metrics(model_blas, exact, exact.bounds, cameras, resolution, out_dir,
                                                     lambda view: bar.update(1))
            if all(math.isnan(v) for v in result["images"]["silhouette_iou_per_view"].values()):
                _measured_nothing(f"no pixel of any view at {resolution}x{resolution} shows the mesh or the model (thinner "
                                  "than a pixel): the image figures compare empty images", mesh)
            if out_dir is not None:
                from ..io.plots import write_eval_errors, write_eval_overview

                stage("figures")
                errors = {name: ray_errors(pred[sel], batch.truth[sel], batch.rays[sel], diag)[:2] for name, sel in parts}
                ious = result["images"]["silhouette_iou_per_view"]
                result["images"]["figures"] = {"errors": str(write_eval_errors(out_dir / _ERRORS_FIGURE, errors, ious)),
                                               "overview": str(write_eval_overview(out_dir / _OVERVIEW_FIGURE, shown, ious))}
                bar.update(1)
    finally:
        bar.close()
    return result


def _measured_nothing(what: str, mesh: Mesh) -> None:
    """Warn that a figure measured nothing (a needle's held-out rays and views all missed it, and
    eval printed a perfect score)."""
    import warnings

    from ..errors import outside_stacklevel

    warnings.warn(f"{mesh.name}: {what}", stacklevel=outside_stacklevel())


def _speed(model_blas, exact: MeshBLAS, distribution: BoxRayDistribution, batch) -> dict:
    """`same_run_speed` on `TIMING_RAYS` held-out rays: a fixed count, whatever eval's own ray count
    is (10 rays would time call overhead, 4M take minutes), with the fraction of them that hit."""
    from .costs import TIMING_RAYS, same_run_speed

    n = len(batch.rays)
    if n < TIMING_RAYS:
        timed = distribution.sample(TIMING_RAYS)
        timed_rays, timed_hits = timed.rays, timed.truth.hit
    else:
        every = torch.linspace(0, n - 1, TIMING_RAYS, device=batch.truth.hit.device).long()
        timed_rays, timed_hits = batch.rays[every], batch.truth.hit[every]
    return {**same_run_speed(model_blas, exact, timed_rays), "exact_hit_fraction": float(timed_hits.float().mean())}
