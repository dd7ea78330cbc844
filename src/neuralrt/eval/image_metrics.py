"""Image comparison: FLIP (NVIDIA's `flip-evaluator`), PSNR and relMSE, plus a FLIP heat map.

Conventions (the same for every figure neuralrt reports):
- FLIP is computed in LDR mode on the images as the PNGs show them: linear values clamped to
  [0, 1] and sRGB-encoded. ``hdr=True`` uses HDR-FLIP on the linear values instead.
- PSNR is over the same clamped sRGB values (peak 1).
- relMSE is mean((test - ref)^2 / (ref^2 + 0.01)) over linear values and channels.
- Identical images give PSNR ``float("inf")`` (zero error), FLIP 0 and relMSE 0.
- Images with NaN or infinite pixels are refused (`ImageError`): any figure on them would mislead.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..devices import memory_shortfall
from ..errors import ImageError, outside_stacklevel
from ..io.files import check_output_file
from ..io.images import is_grey_image, linear_to_srgb, nonfinite_problem, read_image, tone_map

__all__ = ["ImageComparison", "compare_images", "compare_files", "relmse", "psnr", "nonfinite_problem", "check_heatmap_path"]

_RELMSE_EPSILON = 1e-2


@dataclass
class ImageComparison:
    flip: float
    psnr: float  # float("inf") for identical images
    relmse: float
    flip_map: np.ndarray  # [H, W, 3] magma-coloured FLIP error, sRGB-encoded in [0, 1]

    def as_dict(self) -> dict:
        return {"flip": self.flip, "psnr": self.psnr, "relmse": self.relmse}


def _finite(image: np.ndarray) -> np.ndarray:
    return np.nan_to_num(np.asarray(image, np.float32), nan=0.0, posinf=1e4, neginf=0.0)


def psnr(reference: np.ndarray, test: np.ndarray) -> float:
    """PSNR in dB over clamped sRGB-encoded values; inf for identical images."""
    ref = linear_to_srgb(tone_map(reference))
    tst = linear_to_srgb(tone_map(test))
    mse = float(np.mean((ref.astype(np.float64) - tst) ** 2))
    return float("inf") if mse == 0 else float(10 * np.log10(1.0 / mse))


def relmse(reference: np.ndarray, test: np.ndarray) -> float:
    ref, tst = _finite(reference).astype(np.float64), _finite(test).astype(np.float64)
    return float(np.mean((tst - ref) ** 2 / (ref**2 + _RELMSE_EPSILON)))


# What FLIP takes on top of the two images, a pixel (measured on 2000x2000: 172 bytes LDR, 199 HDR).
FLIP_BYTES_PER_PIXEL = 200


def compare_images(reference: np.ndarray, test: np.ndarray, hdr: bool = False,
                   names: tuple[str, str] = ("reference image", "test image")) -> ImageComparison:
    """Compare two linear RGB images of the same shape; ``names`` label them in errors.

    Raises `ImageError` when the sizes differ or either image has a NaN or infinite pixel (the
    metrics would silently treat those as black or give absurd values). Identical images give
    ``psnr == float("inf")``.
    """
    import flip_evaluator

    for image, name in zip((reference, test), names):
        problem = nonfinite_problem(image, name)
        if problem:
            raise ImageError(problem)
    reference, test = np.asarray(reference, np.float32), np.asarray(test, np.float32)
    if reference.shape != test.shape:
        raise ImageError(f"images differ in size: reference {reference.shape[1]}x{reference.shape[0]} vs test "
                         f"{test.shape[1]}x{test.shape[0]} (width x height)")
    shortfall = memory_shortfall(reference.shape[0] * reference.shape[1] * FLIP_BYTES_PER_PIXEL, "cpu")
    if shortfall:  # (a pair of large renders: refused in one line, not ended by the kernel's OOM killer)
        raise ImageError(f"comparing {reference.shape[1]}x{reference.shape[0]} images with FLIP {shortfall}: compare "
                         "crops of them, or on a machine with more memory")
    if hdr:
        flip_map, mean_flip = _hdr_flip(np.maximum(reference, 0), np.maximum(test, 0))
    else:
        ref_srgb = linear_to_srgb(tone_map(reference))
        test_srgb = linear_to_srgb(tone_map(test))
        flip_map, mean_flip, _ = flip_evaluator.evaluate(ref_srgb, test_srgb, "LDR")
    return ImageComparison(float(mean_flip), psnr(reference, test), relmse(reference, test), np.asarray(flip_map, np.float32))


def _hdr_flip(reference: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, float]:
    """HDR-FLIP's (map, mean). Its exposure range comes from the reference's luminance, and on an
    all-black reference flip_evaluator ends the process ("Start exposure must be smaller than stop
    exposure!", exit 255): there the test image's range is used, and two black images are 0."""
    import flip_evaluator

    if reference.max(initial=0.0) > 0:
        flip_map, mean_flip, _ = flip_evaluator.evaluate(reference, test, "HDR")
        return flip_map, mean_flip
    if test.max(initial=0.0) <= 0:  # (the map of no error, in FLIP's colours: two equal lit images give it)
        flip_map, _, _ = flip_evaluator.evaluate(np.ones_like(reference), np.ones_like(test), "HDR")
        return flip_map, 0.0
    _, _, exposures = flip_evaluator.evaluate(test, test, "HDR")
    flip_map, mean_flip, _ = flip_evaluator.evaluate(reference, test, "HDR", parameters={
        "startExposure": exposures["startExposure"], "stopExposure": exposures["stopExposure"]})
    return flip_map, mean_flip


def check_heatmap_path(path: str | Path) -> None:
    """A one-line error unless the FLIP heat map can be written to ``path``, checked before any
    image is read: the map is always PNG (another suffix would put PNG bytes under a misleading
    name), and its folder must exist or be creatable, and take files."""
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ImageError(f"{path}: the heat map is written as PNG, so its name must end in .png")
    check_output_file(path, "heat map")


def _write_heatmap(path: str | Path, flip_map: np.ndarray) -> None:
    """Create the folder if needed (only once there is a map to write), then write the PNG atomically."""
    folder = Path(path).parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ImageError(f"{path}: cannot create folder {folder} ({exc.strerror or exc})") from None
    write_srgb_png(path, flip_map)  # atomic: `write_png` goes through `write_atomically`


_LINEAR_SUFFIXES = (".exr", ".hdr")  # (images of radiance; PNG and JPEG hold display values)


def compare_files(reference: str | Path, test: str | Path, heatmap: str | Path | None = None, hdr: bool = False) -> ImageComparison:
    """Compare two image files (EXR, PNG, JPG, HDR); optionally write the FLIP heat map as PNG.

    Errors (unreadable file, NaN/Inf pixels, sizes differ, heat map name not ``.png``) are one
    `ImageError` naming the file, raised before any metric is computed or file written.
    Identical images give ``psnr == float("inf")``.
    """
    if heatmap is not None:
        check_heatmap_path(heatmap)
    kinds = [Path(p).suffix.lower() in _LINEAR_SUFFIXES for p in (reference, test)]
    if kinds[0] != kinds[1]:  # (render writes both: the .png is the .exr tone-mapped, clamped to [0, 1])
        display, linear = (test, reference) if kinds[0] else (reference, test)
        warnings.warn(f"{display} is a display image (tone-mapped, [0, 1]) and {linear} linear radiance: the figures "
                      "compare unlike things (compare .exr with .exr, or .png with .png)", stacklevel=outside_stacklevel())
    images = read_image(reference), read_image(test)  # (first: a missing EXR's header read printed OpenEXR's own line)
    grey = [is_grey_image(p) for p in (reference, test)]
    if grey[0] != grey[1]:  # (read as R = G = B: a colour image is judged against a grey one's replicated channel)
        one, other = (reference, test) if grey[0] else (test, reference)
        warnings.warn(f"{one} is a grey image (one channel, read as R = G = B) and {other} a colour one: the figures "
                      "count every colour difference as error", stacklevel=outside_stacklevel())
    result = compare_images(*images, hdr=hdr, names=(str(reference), str(test)))
    if heatmap is not None:
        _write_heatmap(heatmap, result.flip_map)
    return result


def write_srgb_png(path: str | Path, srgb: np.ndarray) -> None:
    """Write an already sRGB-encoded [0, 1] image (e.g. a colour-mapped heat map) as PNG."""
    from ..io.images import srgb_to_linear, write_png

    write_png(path, srgb_to_linear(np.clip(srgb, 0, 1)))
