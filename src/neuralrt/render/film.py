"""Film: per-pixel sums of path radiance and AOVs, and the finished `RenderResult` with its files."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ..errors import ConfigError

__all__ = ["Film", "RenderResult", "output_files", "AOV_SUFFIXES"]


class Film:
    """Accumulates samples per pixel (row-major pixel index); every value is a running sum.

    `add` runs as one numba pass on the CPU (`shading_kernels.film_add`) and as torch ops
    elsewhere, chosen at construction; both give the same sums."""

    BYTES_PER_PIXEL = 12 * 8  # the float64 sums below

    def __init__(self, width: int, height: int, device="cpu"):
        self.width, self.height = width, height
        n = width * height
        dev = torch.device(device)
        self.radiance = torch.zeros(n, 3, dtype=torch.float64, device=dev)  # float64 sums: many passes stay exact
        self.albedo = torch.zeros(n, 3, dtype=torch.float64, device=dev)
        self.normal = torch.zeros(n, 3, dtype=torch.float64, device=dev)
        self.depth = torch.zeros(n, dtype=torch.float64, device=dev)  # summed over samples that hit only
        self.hits = torch.zeros(n, dtype=torch.float64, device=dev)  # samples whose camera ray hit
        self.count = torch.zeros(n, dtype=torch.float64, device=dev)
        self.nonfinite_samples = 0  # samples whose radiance was NaN/Inf (dropped to 0, counted)
        self._add = self._add_numba if dev.type == "cpu" else self._add_torch

    def add(self, pixel: Tensor, radiance: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor, hit: Tensor) -> None:
        """Add one sample per entry of ``pixel`` [n] (pixels may repeat): ``radiance``, ``albedo``,
        ``normal`` [n, 3], first-hit ``depth`` [n] and whether the camera ray hit, ``hit`` [n] bool.
        A NaN/Inf radiance sample (e.g. from a degenerate hit record) counts as 0 so it cannot
        poison the pixel; it is counted."""
        self._add(pixel, radiance, albedo, normal, depth, hit)

    def _add_torch(self, pixel: Tensor, radiance: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor, hit: Tensor) -> None:
        bad = ~torch.isfinite(radiance).all(-1)
        if bool(bad.any()):
            self.nonfinite_samples += int(bad.sum())
            radiance = torch.where(bad[:, None], 0.0, radiance)
        self.radiance.index_add_(0, pixel, radiance.double())
        self.albedo.index_add_(0, pixel, albedo.double())
        self.normal.index_add_(0, pixel, normal.double())
        self.depth.index_add_(0, pixel, torch.where(hit, depth.double(), 0.0))
        self.hits.index_add_(0, pixel, hit.double())
        self.count.index_add_(0, pixel, torch.ones_like(depth, dtype=torch.float64))

    def _add_numba(self, pixel: Tensor, radiance: Tensor, albedo: Tensor, normal: Tensor, depth: Tensor, hit: Tensor) -> None:
        from .shading_kernels import film_add

        def c(t):
            return t.detach().contiguous().numpy()

        self.nonfinite_samples += int(film_add(c(pixel), c(radiance), c(albedo), c(normal), c(depth), c(hit), self.radiance.numpy(),
                                               self.albedo.numpy(), self.normal.numpy(), self.depth.numpy(), self.hits.numpy(),
                                               self.count.numpy()))

    def _mean(self, total: Tensor, over: Tensor | None = None) -> np.ndarray:
        """Per-pixel ``total / over`` (default: over all samples; 0 where ``over`` is 0) as [H, W, ...]."""
        c = (self.count if over is None else self.hits).clamp(min=1).reshape(-1, *([1] * (total.ndim - 1)))
        shape = (self.height, self.width) + tuple(total.shape[1:])
        return (total / c).float().reshape(shape).cpu().numpy()

    def result(self, spp: int, seconds: float) -> "RenderResult":
        normal = self.normal / torch.linalg.norm(self.normal, dim=-1, keepdim=True).clamp(min=1e-12)
        return RenderResult(image=self._mean(self.radiance), albedo=self._mean(self.albedo), normal=normal.float().reshape(self.height, self.width, 3).cpu().numpy(),
                            depth=self._mean(self.depth, over=self.hits), coverage=self._mean(self.hits), spp=spp, seconds=seconds,
                            stats={"nonfinite_samples": self.nonfinite_samples})


_FARTHEST_SHOWN = 0.2  # the depth PNG's farthest hit, apart from the background's 0
AOV_SUFFIXES = ("", "_albedo", "_normal", "_depth", "_coverage")  # the image, then each AOV, as `RenderResult.save` writes them


def check_render_output(path) -> Path:
    """``path`` as a `Path`; a one-line `ConfigError` unless it names an ``.exr`` file (any case: its
    PNG and AOVs are named from its stem, and a ``.png`` name would be written twice, EXR then PNG)."""
    from ..devices import check_path

    path = check_path("output", path)
    if path.suffix.lower() != ".exr":
        raise ConfigError(f"{path}: output must be an .exr file (a .png and AOVs are written beside it)")
    return path


def output_files(path: str | Path) -> list[Path]:
    """The files `RenderResult.save` writes for ``path``, in order: ``path`` itself (the EXR, its name
    as given), its PNG, then ``<stem>_<aov>.exr`` and ``.png`` for each AOV (checked up front by
    ``api.render``: a folder or unwritable file in the way stops the render before it starts)."""
    path = Path(path)
    stem = path.with_suffix("")
    return [name for aov in AOV_SUFFIXES for name in (path if not aov else Path(f"{stem}{aov}.exr"), Path(f"{stem}{aov}.png"))]


@dataclass(eq=False)  # (identity: arrays have no single truth value)
class RenderResult:
    """A finished render: linear HDR image and first-hit AOVs (pixel means), as numpy float32.

    ``albedo`` is the first hit's surface albedo, ``normal`` its unit world-space shading normal
    (turned towards the camera): both averaged over all samples (escaped rays count as 0).
    ``depth`` is the first hit's distance from the camera averaged over the samples that hit
    (0 where none did), and ``coverage`` the fraction of samples whose camera ray hit, so a pixel
    on a silhouette keeps its surface's depth instead of a blend with 0.
    """

    image: np.ndarray  # [H, W, 3] linear radiance
    albedo: np.ndarray  # [H, W, 3]
    normal: np.ndarray  # [H, W, 3]
    depth: np.ndarray  # [H, W] mean over samples that hit
    coverage: np.ndarray  # [H, W] in [0, 1]
    spp: int
    seconds: float
    stats: dict = field(default_factory=dict)

    def __repr__(self) -> str:  # (the dataclass's printed every array)
        h, w = self.image.shape[:2]
        return f"RenderResult({w}x{h}, {self.spp} spp, {self.seconds:.3g} s)"

    def save(self, path: str | Path, exposure: float = 0.0) -> list[Path]:
        """Write ``<stem>.exr`` (linear HDR) and ``<stem>.png`` (sRGB), plus ``<stem>_albedo``,
        ``<stem>_normal``, ``<stem>_depth`` and ``<stem>_coverage`` as EXR (exact values) and PNG
        (to look at; the depth PNG shows the nearest hit white and the farthest 20% grey over a black
        background, faded by coverage at silhouettes).
        Missing folders are created here, once there is something to write (a failed render
        leaves no empty folders behind). Returns the paths written."""
        from ..io.images import write_exr, write_png

        path = check_render_output(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        names = iter(output_files(path))
        out: list[Path] = []

        def both(suffix: str, linear: np.ndarray, png: np.ndarray, png_exposure: float = 0.0) -> None:
            exr, png_path = next(names), next(names)
            write_exr(exr, linear)
            write_png(png_path, png, exposure=png_exposure)
            out.extend([exr, png_path])

        from ..io.files import written_together
        from ..io.images import srgb_to_linear

        with written_together():  # (all ten files, or none: never some new beside an earlier render's)
            both("", self.image, self.image, exposure)
            both("_albedo", self.albedo, self.albedo)
            # Normals in [-1, 1] shown as colours 0.5 + 0.5 n (stored linear so the PNG shows that mapping).
            both("_normal", self.normal, srgb_to_linear(0.5 + 0.5 * self.normal))
            hit = self.coverage > 0
            # Over the hits' own range: 1 - depth / farthest left objects 5.5-6 units away at 0-10% grey.
            near, far = (float(self.depth[hit].min()), float(self.depth[hit].max())) if hit.any() else (0.0, 1.0)
            near_bright = (_FARTHEST_SHOWN + (1.0 - _FARTHEST_SHOWN) * np.clip((far - self.depth) / max(far - near, 1e-30), 0.0, 1.0)
                           ) * self.coverage
            both("_depth", np.repeat(self.depth[..., None], 3, -1), srgb_to_linear(np.repeat(near_bright[..., None], 3, -1)))
            both("_coverage", np.repeat(self.coverage[..., None], 3, -1), np.repeat(self.coverage[..., None], 3, -1))
        return out
