"""`neuralrt compare`: metrics on known images, JSON interface, heat map file, bad input."""

import json

import numpy as np
import pytest

from neuralrt.cli import main
from neuralrt.errors import ImageError, NeuralRTError
from neuralrt.eval.image_metrics import compare_images, psnr, relmse
from neuralrt.io.images import read_image, write_exr, write_png


def test_identical_images_have_zero_error():
    img = np.random.default_rng(0).random((32, 48, 3), dtype=np.float32)
    r = compare_images(img, img)
    assert r.flip == 0.0 and r.relmse == 0.0 and r.psnr == float("inf")


def test_psnr_and_relmse_closed_form():
    ref = np.full((8, 8, 3), 0.5, np.float32)
    test = np.full((8, 8, 3), 0.6, np.float32)
    assert relmse(ref, test) == pytest.approx(0.01 / (0.25 + 0.01), rel=1e-5)
    # PSNR over sRGB-encoded values
    from neuralrt.io.images import linear_to_srgb

    d = float(linear_to_srgb(np.float32(0.6)) - linear_to_srgb(np.float32(0.5)))
    assert psnr(ref, test) == pytest.approx(-20 * np.log10(abs(d)), rel=1e-4)


def test_flip_grows_with_error():
    rng = np.random.default_rng(1)
    ref = rng.random((64, 64, 3), dtype=np.float32)
    small = compare_images(ref, ref + rng.normal(0, 0.01, ref.shape).astype(np.float32)).flip
    large = compare_images(ref, ref + rng.normal(0, 0.1, ref.shape).astype(np.float32)).flip
    assert 0 < small < large < 1


def test_cli_json_and_heatmap(tmp_path, capsys):
    rng = np.random.default_rng(2)
    ref = rng.random((16, 16, 3), dtype=np.float32)
    write_exr(tmp_path / "ref.exr", ref)
    write_png(tmp_path / "test.png", ref * 0.8)
    heat = tmp_path / "flip.png"
    assert main(["compare", str(tmp_path / "ref.exr"), str(tmp_path / "test.png"), "--json", "--heatmap", str(heat)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"flip", "psnr", "relmse"} <= out.keys() and out["flip"] > 0
    assert read_image(heat).shape == (16, 16, 3)


def test_cli_errors_are_one_line(tmp_path, capsys):
    write_exr(tmp_path / "a.exr", np.zeros((4, 4, 3), np.float32))
    write_exr(tmp_path / "b.exr", np.zeros((5, 4, 3), np.float32))
    assert main(["compare", str(tmp_path / "a.exr"), str(tmp_path / "b.exr")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("neuralrt: error:") and "size" in err and "\n" not in err
    assert main(["compare", str(tmp_path / "missing.exr"), str(tmp_path / "b.exr")]) == 2
    assert "missing.exr" in capsys.readouterr().err


def _one_error_line(err: str) -> str:
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("neuralrt: error:"), err
    return lines[0]


def _pair(tmp_path):
    img = np.random.default_rng(3).random((16, 16, 3), dtype=np.float32)
    write_exr(tmp_path / "ref.exr", img)
    write_exr(tmp_path / "test.exr", img * 0.9)
    return str(tmp_path / "ref.exr"), str(tmp_path / "test.exr")


def test_cli_truncated_exr_prints_one_line_and_no_library_noise(tmp_path, capfd):
    ref, test = _pair(tmp_path)
    data = (tmp_path / "test.exr").read_bytes()
    (tmp_path / "trunc.exr").write_bytes(data[: len(data) // 2])
    assert main(["compare", ref, str(tmp_path / "trunc.exr")]) == 2
    out, err = capfd.readouterr()  # fd-level: OpenEXR's own messages bypass sys.stderr
    assert out == ""
    assert "trunc.exr: truncated or corrupt EXR" in _one_error_line(err)
    # A missing EXR: OpenEXR's "Unable to open file for read" line came first (the grey-image check
    # read its header before the file was checked).
    assert main(["compare", str(tmp_path / "missing.exr"), ref]) == 2
    out, err = capfd.readouterr()
    assert out == "" and "missing.exr: image file not found" in _one_error_line(err)


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("which", ["reference", "test"])
def test_cli_refuses_nan_and_inf_pixels_naming_the_image(tmp_path, capsys, bad_value, which):
    ref, test = _pair(tmp_path)
    bad = read_image(ref if which == "reference" else test)
    bad[2:5, 3:7, 1] = bad_value  # 12 pixels, one channel each
    write_exr(tmp_path / "bad.exr", bad)
    args = [str(tmp_path / "bad.exr"), test] if which == "reference" else [ref, str(tmp_path / "bad.exr")]
    assert main(["compare", *args]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert _one_error_line(err).endswith("bad.exr: 12 pixels are NaN or infinite")


def test_all_nan_image_is_refused_not_scored_as_black():
    ref = np.zeros((8, 8, 3), np.float32)
    with pytest.raises(ImageError, match="test image: 64 pixels are NaN or infinite"):
        compare_images(ref, np.full_like(ref, np.nan))


@pytest.mark.parametrize("name", ["flip.exr", "flip.txt", "flip"])
def test_cli_heatmap_must_be_png_checked_before_any_work(tmp_path, capsys, name):
    ref, _ = _pair(tmp_path)
    nan_image = np.full((16, 16, 3), np.nan, np.float32)
    write_exr(tmp_path / "nan.exr", nan_image)  # the heat map name is refused before the images are read
    assert main(["compare", ref, str(tmp_path / "nan.exr"), "--heatmap", str(tmp_path / name)]) == 2
    assert "must end in .png" in _one_error_line(capsys.readouterr().err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nan.exr", "ref.exr", "test.exr"]


def test_cli_heatmap_folder_is_created_but_a_file_in_its_way_fails_up_front(tmp_path, capsys):
    ref, test = _pair(tmp_path)
    assert main(["compare", ref, test, "--heatmap", str(tmp_path / "new" / "flip.png")]) == 0
    assert read_image(tmp_path / "new" / "flip.png").shape == (16, 16, 3)
    capsys.readouterr()
    assert main(["compare", ref, test, "--heatmap", str(tmp_path / "ref.exr" / "flip.png")]) == 2
    assert "ref.exr: is a file, not a folder" in _one_error_line(capsys.readouterr().err)
    from neuralrt.eval.image_metrics import compare_files  # the library call checks it too, up front

    with pytest.raises(NeuralRTError, match="ref.exr: is a file, not a folder"):
        compare_files(ref, str(tmp_path / "nan-never-read.exr"), heatmap=tmp_path / "ref.exr" / "flip.png")


def test_heatmap_write_is_atomic_and_psnr_of_identical_files_is_inf(tmp_path, monkeypatch):
    from neuralrt.eval.image_metrics import compare_files
    from neuralrt.io import images

    ref, _ = _pair(tmp_path)
    heat = tmp_path / "flip.png"
    result = compare_files(ref, ref, heatmap=heat)
    assert result.psnr == float("inf") and result.flip == 0.0 and result.relmse == 0.0
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left
    # A write that fails half-way leaves the previous heat map, not a partial file.
    before = heat.read_bytes()

    real = images.write_atomically

    def fail_half_way(path, write_to):
        def partial(tmp):
            with open(tmp, "wb") as f:
                f.write(b"\x89PNG partial")
            raise OSError("disk full")

        return real(path, partial)

    monkeypatch.setattr(images, "write_atomically", fail_half_way)
    with pytest.raises(ImageError, match="flip.png: cannot write image"):
        compare_files(ref, ref, heatmap=heat)
    assert heat.read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_hdr_flip_of_an_all_black_reference_is_a_number_not_the_end_of_the_process(tmp_path, capsys):
    """flip_evaluator's HDR mode takes its exposures from the reference and, for a black one, ended
    the process (exit 255, no error line): two black images are 0, a lit test is measured over its own range."""
    black, grey = np.zeros((8, 8, 3), np.float32), np.full((8, 8, 3), 0.3, np.float32)
    assert compare_images(black, black, hdr=True).flip == 0.0
    assert compare_images(black, grey, hdr=True).flip == pytest.approx(compare_images(grey, black, hdr=True).flip)
    assert 0.5 < compare_images(black, grey, hdr=True).flip <= 1.0
    write_exr(tmp_path / "black.exr", black)
    assert main(["compare", str(tmp_path / "black.exr"), str(tmp_path / "black.exr"), "--hdr", "--json",
                 "--heatmap", str(tmp_path / "map.png")]) == 0
    assert json.loads(capsys.readouterr().out)["flip"] == 0.0 and (tmp_path / "map.png").is_file()


def test_a_display_image_against_a_linear_one_is_a_warning(tmp_path):
    from neuralrt.eval.image_metrics import compare_files

    write_exr(tmp_path / "a.exr", np.full((8, 8, 3), 2.0, np.float32))
    write_png(tmp_path / "a.png", np.full((8, 8, 3), 0.5, np.float32))
    with pytest.warns(UserWarning, match=r"a.png is a display image \(tone-mapped, \[0, 1\]\) and .*a.exr linear radiance"):
        compare_files(tmp_path / "a.exr", tmp_path / "a.png")
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        compare_files(tmp_path / "a.exr", tmp_path / "a.exr")
        compare_files(tmp_path / "a.png", tmp_path / "a.png")


def test_images_flip_has_no_memory_for_are_refused_in_one_line(tmp_path, capsys, monkeypatch):
    # Two 6000x6000 renders took 6.3 GB: where that is more than the machine has, the OOM killer ended it.
    from neuralrt import devices
    from neuralrt.eval.image_metrics import FLIP_BYTES_PER_PIXEL

    img = np.full((40, 50, 3), 0.5, np.float32)
    write_exr(tmp_path / "a.exr", img)
    write_exr(tmp_path / "b.exr", img)
    monkeypatch.setattr(devices, "available_bytes", lambda device: 40 * 50 * FLIP_BYTES_PER_PIXEL - 1)
    assert main(["compare", str(tmp_path / "a.exr"), str(tmp_path / "b.exr")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("neuralrt: error: comparing 50x40 images with FLIP needs 400,000 bytes of memory, 399,999 bytes is "
                          "available on cpu: compare crops") and err.count("\n") == 1
    monkeypatch.setattr(devices, "available_bytes", lambda device: 40 * 50 * FLIP_BYTES_PER_PIXEL)
    assert compare_images(img, img).flip == 0.0


def test_a_grey_image_against_a_colour_one_is_a_warning(tmp_path):
    # A grey EXR (one Y channel) is read as R = G = B: against a colour render every hue counts as error, silently.
    import warnings

    import OpenEXR
    from PIL import Image

    from neuralrt.eval.image_metrics import compare_files

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": np.full((8, 8), 0.5, np.float32)}) as f:
        f.write(str(tmp_path / "grey.exr"))
    write_exr(tmp_path / "colour.exr", np.full((8, 8, 3), 0.5, np.float32))
    Image.new("L", (8, 8), 128).save(tmp_path / "grey.png")
    write_png(tmp_path / "colour.png", np.full((8, 8, 3), 0.5, np.float32))
    with pytest.warns(UserWarning, match=r"grey.exr is a grey image \(one channel, read as R = G = B\) and .*colour.exr a colour one"):
        compare_files(tmp_path / "colour.exr", tmp_path / "grey.exr")
    with pytest.warns(UserWarning, match=r"grey.png is a grey image"):
        compare_files(tmp_path / "grey.png", tmp_path / "colour.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert compare_files(tmp_path / "grey.exr", tmp_path / "grey.exr").flip == 0.0
        compare_files(tmp_path / "colour.exr", tmp_path / "colour.exr")
