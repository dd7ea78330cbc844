"""`neuralrt compare`: metrics on known images, JSON interface, heat map file, bad input."""

import json

import numpy as np
import pytest

from neuralrt.cli import main
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
