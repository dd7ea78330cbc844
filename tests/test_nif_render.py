"""NIF inside the renderer: collecting changes no pixel, the stand-in accelerator's two-stage answer
equals each instance evaluated on its own (instances of one mesh share its grids), bad ``--nif``
arguments are one-line errors before rendering, and an online-trained render answers shadow rays
far better than calling every NIF ray visible."""

import numpy as np
import pytest
import torch

from neuralrt.cli import main
from neuralrt.errors import ConfigError
from neuralrt.geometry.procedural import box, plane, sphere
from neuralrt.methods.nif import NIFNetworks, NIFPairs
from neuralrt.methods.nif_config import NIFConfig, NIFTrainingConfig
from neuralrt.methods.nif_training import NIFTrainer
from neuralrt.rays import Rays
from neuralrt.render.integrator import render
from neuralrt.render.nif_render import render_nif, select_nif_instances
from neuralrt.render.nif_shadows import NIFShadowAccel
from neuralrt.scene.loader import load_dict


def _scene(res=(24, 16)):
    ball, cube = sphere(subdivisions=2), box()
    return load_dict({
        "camera": {"position": [0, 1.5, 5], "look_at": [0, 0, 0], "resolution": list(res)},
        "materials": [{"name": "white", "type": "diffuse", "albedo": [0.7, 0.7, 0.7]},
                      {"name": "lamp", "type": "emissive", "emission": [8, 8, 8]}],
        "objects": [
            {"name": "ball", "mesh": ball, "material": "white", "transform": {"translate": [-0.8, 0, 0], "scale": 0.5}},
            {"name": "ball", "mesh": ball, "material": "white", "transform": {"translate": [0.8, 0, 0], "scale": 0.5}},
            {"name": "cube", "mesh": cube, "material": "white", "transform": {"translate": [0, 0, -0.8], "scale": 0.6}},
            {"name": "floor", "mesh": plane(size=6.0), "material": "white", "transform": {"translate": [0, -0.6, 0]}},
            {"name": "lamp", "mesh": plane(size=1.0), "material": "lamp", "transform": {"translate": [0, 2.5, 0], "rotate": [180, 0, 0]}},
        ],
    })


def _shadows(scene, names, seed=0, init_scale=1e-4, every_hit=False):
    cfg = NIFConfig(training=NIFTrainingConfig(seed=seed, init_scale=init_scale), compute_precision="fp32")
    chosen = select_nif_instances(scene, names, cfg)
    blases = list({id(scene.accel.instances[k].blas): scene.accel.instances[k].blas for k in chosen}.values())
    net = NIFNetworks(cfg, [b.bounds.inflated(cfg.box_inflation) for b in blases])
    return NIFShadowAccel(scene.accel, chosen, net, NIFTrainer(net), every_hit=every_hit), chosen, blases


def test_collecting_changes_no_pixel_and_labels_every_pair():
    from dataclasses import replace

    scene = _scene()
    shadows, _, _ = _shadows(scene, "ball,cube")
    exact = render(scene, spp=2, seed=3, progress=False)
    collected = render(replace(scene, accel=shadows), spp=2, seed=3, progress=False)
    assert np.array_equal(exact.image, collected.image)
    st = shadows.stats["collect"]
    assert st.shadow_rays > 0 and st.outer > 0 and st.inner > 0
    assert shadows.trainer.stats.outer_pairs == st.outer and shadows.trainer.stats.inner_pairs == st.inner


def test_nif_takes_the_shadow_rays_of_the_first_hits_unless_told_every_hit():
    # The paper uses NIF for direct light at the camera rays' hits (Sec. 4); it took every bounce's.
    from dataclasses import replace

    scene = _scene()
    stats, images = {}, {}
    for every_hit in (False, True):
        shadows, _, _ = _shadows(scene, "ball,cube", every_hit=every_hit)
        images[every_hit] = render(replace(scene, accel=shadows), spp=2, seed=3, max_depth=3, progress=False).image
        stats[every_hit] = shadows.stats["collect"]
    first, every = stats[False], stats[True]
    assert first.exact_only_rays > 0 and every.exact_only_rays == 0 and first.shadow_rays > 0
    assert first.shadow_rays + first.exact_only_rays == every.shadow_rays  # (collecting answers exactly: the same paths)
    assert first.pairs < every.pairs and np.array_equal(images[False], images[True])
    assert NIFConfig().shadow_rays == "first_hit"


def test_two_stage_answer_equals_each_instance_on_its_own():
    scene = _scene()
    shadows, chosen, blases = _shadows(scene, "ball,cube", init_scale=1.0)  # large features: varied answers
    assert len(chosen) == 3 and len(blases) == 2  # two balls share one mesh: one NIF object
    shadows.mode = "answer"
    g = torch.Generator().manual_seed(0)
    n = 4000
    o = (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([4.0, 1.0, 3.0])
    target = torch.tensor([0.0, 2.5, 0.0]) + (torch.rand(n, 3, generator=g) - 0.5) * torch.tensor([1.0, 0.0, 1.0])
    rays = Rays(o, target - o, torch.zeros(n), torch.full((n,), 0.999))
    answer = shadows.occluded(rays, camera_hits=True)  # (the shadow rays NIF takes by default)
    # By hand: the exact objects, then every NIF instance alone (its own object-space rays).
    expected = shadows.exact.occluded(rays).clone()
    blas_index = {id(b): k for k, b in enumerate(blases)}
    for k in chosen:
        inst = scene.accel.instances[k]
        local = inst.transform.inverse().apply_rays(rays)
        pairs = NIFPairs(torch.full((n,), blas_index[id(inst.blas)]), local.origins, local.directions, local.t_min, local.t_max)
        hit = shadows.networks.occluded(pairs)
        # only where the world box test lets the pair through (the stand-in's stage 1)
        lo, hi = inst.world_bounds.lo, inst.world_bounds.hi
        from neuralrt.rays import ray_box_intervals

        t0, t1 = ray_box_intervals(rays.origins, rays.directions, lo, hi)
        overlap = (t0 <= t1) & (t1 >= 0) & (t0 <= rays.t_max)
        expected |= hit & overlap & ~shadows.exact.occluded(rays)
    # The stand-in's stage-2 inputs come from the fused numba pass on the CPU: equal up to rounding,
    # so a logit within rounding of 0 may flip.
    assert int((answer != expected).sum()) <= 2
    st = shadows.stats["answer"]
    assert st.outer > 100 and st.inner > 0 and 0 < int(answer.sum()) < n


@pytest.mark.parametrize("nif, message", [
    ("statue", "no object of that name"),
    ("ball,lamp", "emissive"),
    ("auto", "no object has more than 100,000 triangles"),
    ("ball,", "object names separated by commas"),
])
def test_bad_nif_arguments_are_one_line_errors(nif, message):
    with pytest.raises(ConfigError, match=message):
        select_nif_instances(_scene(), nif)


def test_auto_picks_objects_above_the_triangle_count():
    scene = _scene()
    chosen = select_nif_instances(scene, "auto", NIFConfig(auto_min_triangles=100))
    assert [scene.accel.instances[k].name for k in chosen] == ["ball", "ball"]  # sphere(2): 320 triangles; cube: 12


def test_train_spp_must_leave_samples_for_nif():
    with pytest.raises(ConfigError, match="below spp"):
        render_nif(_scene(), "ball", spp=4, train_spp=4, progress=False)


def test_cli_rejects_bad_nif_before_rendering(tmp_path, capsys):
    out = tmp_path / "img.exr"
    args = ["render", "builtin:cornell-statue?detail=0", "-o", str(out), "--spp", "4", "--res", "16x12", "--quiet"]
    assert main(args + ["--nif", "box"]) == 2  # the Cornell box holds the ceiling light
    err = capsys.readouterr().err
    assert err.startswith("neuralrt: error: --nif box") and "emissive" in err and err.count("\n") == 1
    assert main(args + ["--nif", "nothing"]) == 2
    assert main(args + ["--nif", "statue", "--nif-train-spp", "4"]) == 2
    assert main(args + ["--nif-train-spp", "2"]) == 2  # without --nif it means nothing
    assert not out.parent.exists() or not any(out.parent.iterdir())


def test_online_trained_render_answers_far_better_than_visible(tmp_path):
    scene = _scene(res=(64, 48))
    cfg = NIFConfig(training=NIFTrainingConfig(passes_per_spp=8, pair_fraction=1.0))  # small image, few pairs: more passes, every pair (docs/nif.md)
    result, report = render_nif(scene, "ball,cube", spp=36, train_spp=32, config=cfg, progress=False, audit=True)
    st = report["shadow_rays"]
    baseline = st["audit_blocked_by_nif_objects_only"]  # errors of answering every NIF pair "visible"
    assert baseline > 500
    assert st["audit_disagreements"] < 0.5 * baseline, (st["audit_disagreements"], baseline)  # measured: 338 of 918
    assert result.spp == 36 and np.isfinite(result.image).all()
    assert report["training"]["outer_steps"] > 0 and report["training_seconds_per_spp"] > 0
    assert 0 < st["outer_share"] < 1 and 0 < st["inner_share"] < 1
    assert report["memory"]["paper_bytes"] == 2 * (4 * 256**2 + 4 * 128**2)
    # The same samples with exact shadow rays: the reference that differs only in who answered.
    reference, _ = render_nif(scene, "ball,cube", spp=36, train_spp=32, config=cfg, progress=False, answer="exact")
    diff = np.abs(np.clip(result.image, 0, 1) - np.clip(reference.image, 0, 1))
    assert 0 < diff.mean() < 0.01


def test_cli_render_with_nif_reports_it(tmp_path, capsys):
    import json

    out = tmp_path / "img.exr"
    args = ["render", "builtin:cornell-statue?detail=0", "-o", str(out), "--spp", "3", "--res", "24x16", "--quiet", "--json",
            "--nif", "statue", "--nif-train-spp", "2"]
    assert main(args) == 0
    captured = capsys.readouterr()
    result = json.loads(captured.out)
    nif = result["nif"]
    steps = nif["training"]["outer_steps"] + nif["training"]["inner_steps"]  # (24 x 16 pixels x 2 spp: a few)
    assert f"NIF: the networks trained only {nif['training']['outer_steps']} outer" in captured.err and 0 < steps < 20
    assert nif["warmup_seconds"] > 0 and nif["render_seconds"]["total"] == pytest.approx(result["seconds"])
    assert result["spp"] == 3 and nif["objects"] == ["statue"] and nif["train_spp"] == 2 and nif["pair_fraction"] == 0.5
    assert nif["shadow_rays"]["shadow_rays"] > 0 and nif["training"]["outer_pairs"] + nif["training"]["inner_pairs"] > 0
    assert nif["memory"]["paper_bytes_per_object"] == 327_680 and out.exists()
    plot = tmp_path / "img_nif_training.png"
    assert str(plot) in result["files"] and plot.stat().st_size > 0  # the per-round losses, beside the image
    assert len(nif["training"]["loss_outer"]) == nif["training"]["rounds"] >= 1


def test_cli_render_sets_nif_settings(tmp_path, capsys):
    import json

    args = ["render", "builtin:cornell-statue?detail=0", "-o", str(tmp_path / "img.exr"), "--spp", "3", "--res", "16x8",
            "--quiet", "--json", "--nif", "statue", "--nif-train-spp", "2"]
    assert main(args + ["--set", "nif.shadow_rays=every_hit"]) == 0
    out = capsys.readouterr().out
    assert json.loads(out)["nif"]["shadow_rays_of"] == "every_hit"
    assert main(args + ["--set", "nif.shadow_rays=all"]) == 2
    assert "neuralrt: error: nif config: shadow_rays: Input should be 'first_hit' or 'every_hit'" in capsys.readouterr().err
    assert main(args[:-4] + ["--set", "nif.shadow_rays=every_hit"]) == 2
    assert "neuralrt: error: --set nif.KEY=VALUE needs --nif OBJECTS|auto" in capsys.readouterr().err


def test_a_nif_plot_that_cannot_be_written_stops_the_render_before_it_starts(tmp_path, capsys):
    (tmp_path / "img_nif_training.png").mkdir()  # a folder where the plot goes
    args = ["render", "builtin:cornell-statue?detail=0", "-o", str(tmp_path / "img.exr"), "--spp", "3", "--res", "24x16",
            "--quiet", "--nif", "statue", "--nif-train-spp", "2"]
    assert main(args) == 2
    assert "img_nif_training.png: is a folder, not a render output" in capsys.readouterr().err
    assert not (tmp_path / "img.exr").exists()
