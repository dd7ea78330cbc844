"""Image I/O: EXR / PNG / HDR round trips, sRGB curve, atomic writes, one-line errors."""

import os

import numpy as np
import pytest

from neuralrt.errors import ImageError
from neuralrt.io.images import linear_to_srgb, read_image, srgb_to_linear, write_exr, write_hdr, write_png


def _hdr_image(h=5, w=9):
    rng = np.random.default_rng(1)
    return (rng.random((h, w, 3)) * np.logspace(-2, 2, w)[None, :, None]).astype(np.float32)


def test_exr_round_trip_is_exact(tmp_path):
    img = _hdr_image()
    write_exr(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(read_image(tmp_path / "a.exr"), img)


def test_exr_half_round_trip(tmp_path):
    img = _hdr_image()
    write_exr(tmp_path / "h.exr", img, half=True)
    np.testing.assert_allclose(read_image(tmp_path / "h.exr"), img, rtol=1e-3, atol=1e-4)


def test_png_round_trip_within_quantisation(tmp_path):
    img = np.random.default_rng(2).random((6, 7, 3)).astype(np.float32)
    write_png(tmp_path / "a.png", img)
    back = read_image(tmp_path / "a.png")
    # 8-bit sRGB steps are at most 1/255 in encoded space.
    np.testing.assert_allclose(linear_to_srgb(back), linear_to_srgb(img), atol=0.5 / 255 + 1e-6)


def test_png_exposure_and_clamp(tmp_path):
    img = np.full((2, 2, 3), 0.25, np.float32)
    write_png(tmp_path / "e.png", img, exposure=1.0)  # 0.25 * 2 = 0.5
    np.testing.assert_allclose(read_image(tmp_path / "e.png"), 0.5, atol=3e-3)
    write_png(tmp_path / "c.png", img * 100)
    np.testing.assert_allclose(read_image(tmp_path / "c.png"), 1.0)


def test_srgb_curve_inverse():
    x = np.linspace(0, 1, 101, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-6)
    assert linear_to_srgb(np.float32(0.5)) == pytest.approx(0.7353569, abs=1e-6)


def test_hdr_flat_round_trip_within_rgbe_precision(tmp_path):
    img = _hdr_image()
    write_hdr(tmp_path / "a.hdr", img)
    back = read_image(tmp_path / "a.hdr")
    # RGBE keeps 8 mantissa bits relative to the brightest channel of each pixel.
    assert (np.abs(back - img) <= img.max(-1, keepdims=True) / 128).all()


def _write_rle_hdr(path, rgbe):
    """A new-style run-length-encoded RGBE file (one repeat run + literal runs per channel)."""
    h, w, _ = rgbe.shape
    out = bytearray(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + f"-Y {h} +X {w}\n".encode())
    for y in range(h):
        out += bytes([2, 2, w >> 8, w & 255])
        for c in range(4):
            row = rgbe[y, :, c]
            out += bytes([128 + 4, row[0]])  # a run of 4 equal values
            rest = row[4:]
            for i in range(0, len(rest), 128):
                chunk = rest[i : i + 128]
                out += bytes([len(chunk)]) + chunk.tobytes()
    path.write_bytes(bytes(out))


def test_hdr_rle_decoding(tmp_path):
    rng = np.random.default_rng(3)
    rgbe = rng.integers(1, 255, (3, 20, 4), dtype=np.uint8)
    rgbe[..., 3] = rng.integers(120, 136, (3, 20))
    rgbe[:, :4] = rgbe[:, :1]  # the first 4 pixels form a run
    _write_rle_hdr(tmp_path / "r.hdr", rgbe)
    back = read_image(tmp_path / "r.hdr")
    expected = (rgbe[..., :3] + 0.5) * np.ldexp(1.0, rgbe[..., 3].astype(np.int32) - 136)[..., None]
    np.testing.assert_allclose(back, expected, rtol=1e-6)


def test_errors_name_the_file(tmp_path):
    with pytest.raises(ImageError, match="missing.exr: image file not found"):
        read_image(tmp_path / "missing.exr")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"not an image")
    with pytest.raises(ImageError, match="bad.png"):
        read_image(bad)
    bad_hdr = tmp_path / "bad.hdr"
    bad_hdr.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 4\n\x00")
    with pytest.raises(ImageError, match="bad.hdr: truncated"):
        read_image(bad_hdr)
    with pytest.raises(ImageError, match="does not exist"):
        write_exr(tmp_path / "nope" / "x.exr", np.zeros((2, 2, 3)))
    with pytest.raises(ImageError, match=r"shape \[H, W, 3\]"):
        write_png(tmp_path / "x.png", np.zeros((2, 2, 5)))


def test_writes_are_atomic_and_leave_no_temporaries(tmp_path):
    write_exr(tmp_path / "a.exr", np.ones((2, 2, 3)))
    write_png(tmp_path / "a.png", np.ones((2, 2, 3)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.png"]


def _truncated_exr(tmp_path, name="trunc.exr"):
    """A valid multi-chunk EXR cut short, the way an interrupted copy leaves it."""
    write_exr(tmp_path / "full.exr", np.random.default_rng(4).random((64, 48, 3), dtype=np.float32))
    data = (tmp_path / "full.exr").read_bytes()
    (tmp_path / name).write_bytes(data[: len(data) // 2])
    return tmp_path / name


def test_truncated_exr_is_one_error_and_no_library_noise(tmp_path, capfd):
    path = _truncated_exr(tmp_path)
    with pytest.raises(ImageError, match=r"trunc\.exr: truncated or corrupt EXR file"):
        read_image(path)
    out, err = capfd.readouterr()  # fd-level: OpenEXR writes below Python's sys.stderr
    assert out == "" and err == ""


def test_exr_reader_restores_stdout_and_stderr(tmp_path, capfd):
    with pytest.raises(ImageError):
        read_image(_truncated_exr(tmp_path))
    os.write(1, b"still here\n")
    os.write(2, b"and here\n")
    assert capfd.readouterr() == ("still here\n", "and here\n")


def test_a_chunk_that_does_not_inflate_is_one_error_and_no_library_noise(tmp_path, capfd):
    # OpenEXR prints its decoder's failure (C core on fd 2, binding on stdout) before it raises.
    smooth = np.broadcast_to(np.linspace(0, 1, 48, dtype=np.float32)[None, :, None], (64, 48, 3))  # compresses
    write_exr(tmp_path / "full.exr", smooth, half=True)
    data = bytearray((tmp_path / "full.exr").read_bytes())
    data[len(data) - 20] ^= 0x10  # inside the last chunk's zlib stream
    (tmp_path / "flip.exr").write_bytes(bytes(data))
    with pytest.raises(ImageError, match=r"flip\.exr: truncated or corrupt EXR file \(chunk 3 of 4 does not decompress"):
        read_image(tmp_path / "flip.exr")
    assert capfd.readouterr() == ("", "")


def test_exr_reads_leave_other_threads_output_alone(tmp_path, capfd):
    # Reads used to point fds 1-2 and sys.stdout at a capture file: other threads' lines vanished,
    # and one printing OpenEXR's failure text made a sound file fail.
    import threading

    write_exr(tmp_path / "a.exr", np.random.default_rng(5).random((256, 256, 3), dtype=np.float32))
    done, failures = threading.Event(), []

    def read_many():
        try:
            for _ in range(20):
                read_image(tmp_path / "a.exr")
        except Exception as exc:  # noqa: BLE001 (any failure is the finding)
            failures.append(exc)
        done.set()

    reader = threading.Thread(target=read_many)
    reader.start()
    lines = 0
    while not done.is_set() or lines < 200:
        print(f"line {lines}: Exception raised reading pixel data")
        lines += 1
    reader.join()
    out, _ = capfd.readouterr()
    assert not failures and out.count("\n") == lines


def test_tiled_exr_of_partial_tiles_reads(tmp_path):
    import OpenEXR

    img = np.random.default_rng(6).random((37, 50, 3), dtype=np.float32)
    tiles = OpenEXR.TileDescription()
    tiles.xSize, tiles.ySize, tiles.mode = 16, 16, OpenEXR.ONE_LEVEL
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.tiledimage, "tiles": tiles}
    with OpenEXR.File(header, {"RGB": img}) as f:
        f.write(str(tmp_path / "tiled.exr"))
    np.testing.assert_array_equal(read_image(tmp_path / "tiled.exr"), img)


def test_non_exr_bytes_under_exr_name(tmp_path):
    write_png(tmp_path / "a.png", np.ones((2, 2, 3)))
    os.replace(tmp_path / "a.png", tmp_path / "png.exr")
    (tmp_path / "empty.exr").write_bytes(b"")
    for name in ("png.exr", "empty.exr"):
        with pytest.raises(ImageError, match=rf"{name}: not an OpenEXR file"):
            read_image(tmp_path / name)


def test_an_image_declaring_more_pixels_than_any_may_hold_is_refused_before_allocating(tmp_path):
    """A few bytes of run-length .hdr declared 10^10 pixels, allocated before any was read (PNG had
    PIL's limit; EXR and HDR none): every format now refuses PIL's decompression-bomb count."""
    from neuralrt.errors import ImageError
    from neuralrt.io.images import MAX_IMAGE_PIXELS, read_image

    bomb = tmp_path / "bomb.hdr"
    bomb.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 100000\n" + b"\x02\x02\x00\x08" * 4)
    with pytest.raises(ImageError, match=r"bomb.hdr: declares 100000x100000 pixels, over the 178,956,970"):
        read_image(bomb)
    assert MAX_IMAGE_PIXELS == 2 * 89_478_485  # (PIL's Image.MAX_IMAGE_PIXELS, doubled: where PIL errors)


@pytest.mark.parametrize("data_lo, data_hi", [((8, 4), (63, 31)), ((-4, -2), (67, 33))])
def test_an_exr_is_read_as_its_display_window(tmp_path, data_lo, data_hi):
    # (a cropped render, data window inside the display window, read as the crop alone: a texture or
    # environment map made of it was stretched; an overscan one, larger, was squeezed)
    import OpenEXR

    height, width = 32, 64
    rows, cols = np.meshgrid(np.arange(-10, height + 10), np.arange(-10, width + 10), indexing="ij")
    world = np.stack([cols, rows, np.ones_like(cols)], -1).astype(np.float32) + 1  # (a pixel's own coordinates, + 1)
    (x0, y0), (x1, y1) = data_lo, data_hi
    header = {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION,
              "displayWindow": (np.array([0, 0], np.int32), np.array([width - 1, height - 1], np.int32)),
              "dataWindow": (np.array(data_lo, np.int32), np.array(data_hi, np.int32))}
    with OpenEXR.File(header, {"RGB": world[y0 + 10:y1 + 11, x0 + 10:x1 + 11].copy()}) as f:
        f.write(str(tmp_path / "w.exr"))
    pixels = read_image(tmp_path / "w.exr")
    expected = world[10:10 + height, 10:10 + width].copy()
    expected[:max(y0, 0)], expected[:, :max(x0, 0)] = 0, 0  # (outside the data window: black)
    assert pixels.shape == (height, width, 3) and np.array_equal(pixels, expected)


def _png16_rgb(path, pixels):
    """A 16-bit colour PNG (Pillow writes none): IHDR depth 16, colour type 2, rows unfiltered."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    height, width, _ = pixels.shape
    rows = b"".join(b"\0" + pixels[y].astype(">u2").tobytes() for y in range(height))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 16, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
    return path


def test_a_16_bit_colour_png_is_said_to_be_read_at_8_bits(tmp_path):
    # (Pillow reads it as 8-bit RGB: a 16-bit texture or normal map lost its precision silently)
    pixels = (np.arange(4 * 5 * 3).reshape(4, 5, 3) * 1000).astype(np.uint16)
    with pytest.warns(UserWarning, match=r"a 16-bit colour PNG, read at 8 bits per channel .* save it as EXR"):
        image = read_image(_png16_rgb(tmp_path / "deep.png", pixels))
    assert image.shape == (4, 5, 3)
    write_png(tmp_path / "plain.png", np.full((2, 2, 3), 0.5))
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_image(tmp_path / "plain.png")  # (an 8-bit one: no word)
