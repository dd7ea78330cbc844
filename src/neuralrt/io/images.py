"""Image files: linear HDR EXR, tone-mapped sRGB PNG, and reading EXR / PNG / JPG / Radiance .hdr.

Every array here is ``[H, W, 3]`` float32 *linear* RGB, row 0 at the top. Writes are atomic
(`neuralrt.io.files.write_atomically`), so a crash never leaves half a file.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import ImageError
from .files import input_file_problem, write_atomically

__all__ = ["write_exr", "write_png", "write_hdr", "read_image", "nonfinite_problem", "linear_to_srgb", "srgb_to_linear", "tone_map"]


# --- transfer functions ------------------------------------------------------------------------


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear [0, 1] to sRGB-encoded [0, 1] (IEC 61966-2-1 piecewise curve)."""
    c = np.clip(np.asarray(c, np.float32), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055).astype(np.float32)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] to linear."""
    c = np.asarray(c, np.float32)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def tone_map(linear_rgb: np.ndarray, exposure: float = 0.0, operator: str = "clamp") -> np.ndarray:
    """Scale by ``2**exposure`` then map to [0, 1]: ``"clamp"`` (default) or ``"reinhard"`` (x / (1 + x))."""
    x = np.maximum(np.nan_to_num(np.asarray(linear_rgb, np.float32), nan=0.0, posinf=1e4), 0.0) * np.float32(2.0**exposure)
    if operator == "reinhard":
        return x / (1.0 + x)
    if operator == "clamp":
        return np.clip(x, 0.0, 1.0)
    raise ValueError(f"unknown tone map operator {operator!r} (use 'clamp' or 'reinhard')")


# --- helpers -----------------------------------------------------------------------------------


def _as_rgb(image: np.ndarray, path: Path) -> np.ndarray:
    """Accept [H, W], [H, W, 1], [H, W, 3] or [H, W, 4] (alpha dropped); return contiguous float32 RGB."""
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ImageError(f"{path}: image must have shape [H, W, 3], got {tuple(np.shape(image))}")
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    return np.ascontiguousarray(a[..., :3])


def _atomic_write(path: Path, write_to) -> None:
    """`neuralrt.io.files.write_atomically`, with every failure as one `ImageError` naming ``path``."""
    path = Path(path)
    if not path.parent.exists():
        raise ImageError(f"{path}: folder {path.parent} does not exist")
    try:
        write_atomically(path, write_to)
    except ImageError:
        raise
    except Exception as exc:
        raise ImageError(f"{path}: cannot write image ({type(exc).__name__}: {exc})") from None


# --- writing -----------------------------------------------------------------------------------


def write_exr(path: str | Path, rgb: np.ndarray, half: bool = False) -> None:
    """Write linear RGB as an OpenEXR file (float32 by default, ``half=True`` for float16; ZIP)."""
    import OpenEXR

    path = Path(path)
    rgb = _as_rgb(rgb, path)
    pixels = rgb.astype(np.float16) if half else rgb
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def write(tmp: str) -> None:
        with OpenEXR.File(header, {"RGB": np.ascontiguousarray(pixels)}) as f:
            f.write(tmp)

    _atomic_write(path, write)


def write_png(path: str | Path, linear_rgb: np.ndarray, exposure: float = 0.0, tone: str = "clamp") -> None:
    """Write linear RGB as an 8-bit sRGB PNG: ``2**exposure`` scale, tone map (`tone_map`), sRGB curve."""
    path = Path(path)
    _write_png8(path, linear_to_srgb(tone_map(_as_rgb(linear_rgb, path), exposure, tone)))


def write_data_png(path: str | Path, values: np.ndarray) -> None:
    """Write RGB values in [0, 1] that are data, not colour (a normal map), as an 8-bit PNG: no
    sRGB curve, as a normal map is stored."""
    path = Path(path)
    _write_png8(path, np.clip(_as_rgb(values, path), 0.0, 1.0))


def _write_png8(path: Path, encoded01: np.ndarray) -> None:
    """Values in [0, 1], already encoded as they are to be stored, as an 8-bit RGB PNG (atomically)."""
    from PIL import Image

    pixels = np.round(encoded01 * 255.0).astype(np.uint8)
    _atomic_write(path, lambda tmp: Image.fromarray(pixels, "RGB").save(tmp, format="PNG"))


def write_hdr(path: str | Path, rgb: np.ndarray) -> None:
    """Write linear RGB as an uncompressed Radiance RGBE (.hdr) file."""
    path = Path(path)
    rgb = np.maximum(_as_rgb(rgb, path), 0.0)
    h, w = rgb.shape[:2]
    peak = rgb.max(axis=2)
    mantissa, exponent = np.frexp(peak)  # peak = mantissa * 2**exponent, mantissa in [0.5, 1)
    scale = np.where(peak > 1e-32, mantissa * 256.0 / np.where(peak > 1e-32, peak, 1.0), 0.0)
    rgbe = np.zeros((h, w, 4), np.uint8)
    rgbe[..., :3] = np.clip(rgb * scale[..., None], 0, 255).astype(np.uint8)
    rgbe[..., 3] = np.where(peak > 1e-32, np.clip(exponent + 128, 0, 255), 0).astype(np.uint8)
    header = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {h} +X {w}\n".encode("ascii")

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(header + rgbe.tobytes())

    _atomic_write(path, write)


# --- reading -----------------------------------------------------------------------------------


def nonfinite_problem(image: np.ndarray, name: str) -> str | None:
    """None when every pixel of ``image`` is finite, else the one-line problem naming ``name``."""
    finite = np.isfinite(np.asarray(image, np.float32))
    bad = int(np.count_nonzero(~finite.all(axis=-1) if finite.ndim == 3 else ~finite))  # pixels, not channels
    if bad == 0:
        return None
    return f"{name}: {bad} pixel{'s are' if bad != 1 else ' is'} NaN or infinite"


def read_image(path: str | Path) -> np.ndarray:
    """Read ``[H, W, 3]`` float32 linear RGB from EXR, Radiance .hdr, or PNG/JPG (sRGB decoded).

    Grey images are replicated to 3 channels and alpha is dropped. Errors name the file.
    """
    path = Path(path)
    problem = input_file_problem(path, "image file")
    if problem:
        raise ImageError(problem)
    suffix = path.suffix.lower()
    try:
        if suffix == ".exr":
            pixels = _read_exr(path)
        elif suffix in (".hdr", ".pic"):
            pixels = _read_hdr(path)
        else:
            pixels = _read_ldr(path)
    except ImageError:
        raise
    except Exception as exc:
        raise ImageError(f"{path}: cannot read image ({type(exc).__name__}: {exc})") from None
    if pixels.size == 0:  # (a 0 x 0 Radiance header: an environment map's traceback, a texture no lookup can read)
        raise ImageError(f"{path}: the image has no pixels ({pixels.shape[1]} x {pixels.shape[0]})")
    return pixels


def is_grey_image(path: str | Path) -> bool:
    """Whether the image file holds one channel (a grey EXR's ``Y``, a greyscale PNG), which
    `read_image` replicates to R, G and B; False for colour, and where its header cannot be read
    (`read_image` then names the problem)."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".exr":
            import OpenEXR

            with OpenEXR.File(str(path), header_only=True) as f:
                names = {c.name for c in f.header()["channels"]}
            return "Y" in names and not names & {"R", "G", "B"}
        if suffix in (".hdr", ".pic"):
            return False  # (RGBE: always three channels)
        from PIL import Image

        with Image.open(path) as im:
            return im.mode in ("1", "L", "LA", "I", "I;16", "I;16B", "I;16L", "F")
    except Exception:
        return False


_EXR_MAGIC = b"\x76\x2f\x31\x01"


def _read_exr(path: Path) -> np.ndarray:
    from .exr_chunks import exr_chunk_problem

    data = path.read_bytes()
    if data[:4] != _EXR_MAGIC:
        raise ImageError(f"{path}: not an OpenEXR file (no EXR magic number)")
    # Checked before decoding: OpenEXR only prints about a broken chunk, and may return partial pixels.
    problem = exr_chunk_problem(data)
    del data  # (not held while OpenEXR reads the file itself)
    if problem:
        raise ImageError(f"{path}: truncated or corrupt EXR file ({problem})")
    try:
        rgb = _read_exr_pixels(path)
    except ImageError:
        raise
    except Exception as exc:
        raise ImageError(f"{path}: truncated or corrupt EXR file ({exc})") from None
    return _as_rgb(rgb, path)


# Pixels an image may declare: PIL's decompression-bomb limit, for every format (a few hundred
# bytes of EXR or run-length HDR can declare gigabytes of pixels, allocated before any is read).
MAX_IMAGE_PIXELS = 2 * 89_478_485


def _check_pixel_count(path: Path, width: int, height: int) -> None:
    if width * height > MAX_IMAGE_PIXELS:
        raise ImageError(f"{path}: declares {width}x{height} pixels, over the {MAX_IMAGE_PIXELS:,} an image may hold "
                         "(a decompression bomb, or a corrupt header)")


def _read_exr_pixels(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path), header_only=True) as f:
        header = f.header()
        lo, hi = (np.asarray(v, np.int64) for v in header["dataWindow"])
        shown = [np.asarray(v, np.int64) for v in header.get("displayWindow", (lo, hi))]
    _check_pixel_count(path, int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1))
    _check_pixel_count(path, int(shown[1][0] - shown[0][0] + 1), int(shown[1][1] - shown[0][1] + 1))
    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "RGB" in channels:
            pixels = np.asarray(channels["RGB"].pixels, np.float32)
        elif "RGBA" in channels:
            pixels = np.asarray(channels["RGBA"].pixels, np.float32)[..., :3]
        elif all(c in channels for c in "RGB"):
            pixels = np.stack([np.asarray(channels[c].pixels, np.float32) for c in "RGB"], -1)
        elif "Y" in channels:
            pixels = np.asarray(channels["Y"].pixels, np.float32)
        else:
            raise ImageError(f"{path}: EXR has no RGB or Y channels (found {sorted(channels)})")
    return _in_display_window(pixels, lo, *shown)


def _in_display_window(pixels: np.ndarray, data_lo, shown_lo, shown_hi) -> np.ndarray:
    """An EXR's pixels placed in its display window, the image it stands for: a cropped render or
    an overscan one (data window smaller or larger) was stretched over the whole image as a
    texture or environment map. Outside the data window: 0; outside the display window: cut."""
    height, width = int(shown_hi[1] - shown_lo[1] + 1), int(shown_hi[0] - shown_lo[0] + 1)
    x0, y0 = int(data_lo[0] - shown_lo[0]), int(data_lo[1] - shown_lo[1])
    if (x0, y0) == (0, 0) and pixels.shape[:2] == (height, width):
        return pixels
    placed = np.zeros((height, width, *pixels.shape[2:]), np.float32)
    ys, xs = slice(max(y0, 0), min(y0 + pixels.shape[0], height)), slice(max(x0, 0), min(x0 + pixels.shape[1], width))
    if ys.start < ys.stop and xs.start < xs.stop:
        placed[ys, xs] = pixels[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0]
    return placed


def _read_ldr(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            im.load()
            bits16 = im.mode in ("I;16", "I;16B", "I")
            arr = np.asarray(im.convert("I") if bits16 else im.convert("RGB"), np.float32)
    except UnidentifiedImageError:
        raise ImageError(f"{path}: not a recognised image format") from None
    arr = arr / (65535.0 if bits16 else 255.0)
    if not bits16 and _png_colour_depth(path) == 16:
        import warnings

        from ..errors import outside_stacklevel

        warnings.warn(f"{path}: a 16-bit colour PNG, read at 8 bits per channel (Pillow reads colour PNGs no deeper; "
                      "grey ones keep 16): save it as EXR to keep its precision", stacklevel=outside_stacklevel())
    return srgb_to_linear(_as_rgb(arr, path))


def _png_colour_depth(path: Path) -> int | None:
    """A colour PNG's bits per channel, from its header (IHDR: depth at byte 24, colour type 2 or 6 at
    25); None for anything else."""
    with path.open("rb") as f:
        head = f.read(26)
    if len(head) < 26 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR" or head[25] not in (2, 6):
        return None
    return head[24]


_HDR_SIZE = re.compile(rb"^([-+])Y (\d+) ([-+])X (\d+)$")


def _read_hdr(path: Path) -> np.ndarray:
    """Radiance RGBE reader: flat and new-style run-length-encoded scanlines, -Y/+Y, +X/-X orders."""
    data = path.read_bytes()
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise ImageError(f"{path}: not a Radiance .hdr file (missing #?RADIANCE header)")
    pos = data.find(b"\n\n")
    if pos < 0:
        raise ImageError(f"{path}: truncated .hdr header")
    header = data[:pos].split(b"\n")
    for line in header:
        if line.startswith(b"FORMAT=") and line.strip() != b"FORMAT=32-bit_rle_rgbe":
            raise ImageError(f"{path}: unsupported .hdr format {line[7:].decode(errors='replace')} (need 32-bit_rle_rgbe)")
    end = data.find(b"\n", pos + 2)
    m = _HDR_SIZE.match(data[pos + 2 : end].strip())
    if end < 0 or m is None:
        raise ImageError(f"{path}: bad .hdr resolution line")
    h, w = int(m.group(2)), int(m.group(4))
    _check_pixel_count(path, w, h)
    buf = np.frombuffer(data, np.uint8, offset=end + 1)
    rgbe = _decode_rgbe(buf, h, w, path)
    exponent = rgbe[..., 3].astype(np.int32)
    scale = np.where(exponent > 0, np.ldexp(1.0, exponent - 136), 0.0).astype(np.float32)  # 2**(e-128) / 256
    rgb = (rgbe[..., :3].astype(np.float32) + 0.5) * scale[..., None]
    if m.group(1) == b"+":
        rgb = rgb[::-1]
    if m.group(3) == b"-":
        rgb = rgb[:, ::-1]
    return np.ascontiguousarray(rgb, dtype=np.float32)


def _decode_rgbe(buf: np.ndarray, h: int, w: int, path: Path) -> np.ndarray:
    out = np.empty((h, w, 4), np.uint8)
    # Flat file (no RLE): exactly h*w*4 bytes, or scanlines too short/long for RLE.
    if w < 8 or w > 0x7FFF or len(buf) < 4 or not (buf[0] == 2 and buf[1] == 2 and buf[2] < 128):
        if len(buf) < h * w * 4:
            raise ImageError(f"{path}: truncated .hdr pixel data")
        return buf[: h * w * 4].reshape(h, w, 4).copy()
    pos = 0
    data = buf.tobytes()
    for y in range(h):  # per scanline and per run: the format is sequential, not per ray
        if pos + 4 > len(data) or data[pos] != 2 or data[pos + 1] != 2 or (data[pos + 2] << 8 | data[pos + 3]) != w:
            raise ImageError(f"{path}: corrupt run-length scanline {y}")
        pos += 4
        for c in range(4):
            x = 0
            row = out[y, :, c]
            while x < w:
                if pos >= len(data):
                    raise ImageError(f"{path}: truncated .hdr pixel data")
                count = data[pos]
                pos += 1
                if count > 128:
                    count -= 128
                    if x + count > w or pos >= len(data):
                        raise ImageError(f"{path}: corrupt run in scanline {y}")
                    row[x : x + count] = data[pos]
                    pos += 1
                else:
                    if count == 0 or x + count > w or pos + count > len(data):
                        raise ImageError(f"{path}: corrupt run in scanline {y}")
                    row[x : x + count] = np.frombuffer(data, np.uint8, count, pos)
                    pos += count
                x += count
    return out
