"""Intersection metrics: exact against itself is perfect; known perturbations give known errors."""

import math

import numpy as np
import pytest
import torch

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.eval.intersection_metrics import evaluate_model, ray_metrics
from neuralrt.geometry.procedural import sphere
from neuralrt.rays import Hits, Rays


def test_exact_against_itself_is_perfect():
    mesh = sphere(subdivisions=2)
    r = evaluate_model(MeshBLAS(mesh), mesh, rays=4096, cameras=2, resolution=32)
    for group in ("outside", "surface"):
        g = r[group]
        assert g["accuracy"] == 1.0 and g["false_positive_rate"] == 0.0
        # (surface rays of a convex mesh never hit it: no true hit, a false-negative rate of nothing)
        assert g["false_negative_rate"] == 0.0 or (math.isnan(g["false_negative_rate"]) and g["true_hit_fraction"] == 0)
    o = r["outside"]
    assert o["t_error_median"] == 0.0 and o["t_error_p90"] == 0.0 and o["normal_error_deg_p90"] < 1e-2
    assert o["material_accuracy"] == 1.0 and 0.1 < o["true_hit_fraction"] < 0.9
    assert r["images"]["normal_flip"] == 0.0 and r["images"]["depth_flip"] == 0.0
    assert r["images"]["silhouette_iou"] == r["images"]["silhouette_iou_min"] == 1.0
    assert list(r["images"]["silhouette_iou_per_view"]) == ["0", "1", "+x", "-x", "+y", "-y", "+z", "-z"]


def test_a_hole_at_the_top_shows_in_the_view_from_above():
    # An undertrained model's holes sit where the surface meets its box, at the extreme points an
    # axis-aligned camera sees first; the orbit views and the held-out rays hardly see them.
    mesh = sphere(subdivisions=3)
    exact = MeshBLAS(mesh)

    class Holed:  # the sphere, but rays hitting within 0.3 of its top (y > 0.95) miss
        bounds, secondary_offset, material_names = exact.bounds, exact.secondary_offset, ["default"]

        def intersect(self, rays):
            hits = exact.intersect(rays)
            top = hits.hit & ((rays.origins + hits.t[:, None] * rays.directions)[:, 1] > 0.95)
            hits.hit[top] = False
            return hits

    r = evaluate_model(Holed(), mesh, rays=4096, cameras=4, resolution=48, timing=False)["images"]["silhouette_iou_per_view"]
    assert r["+y"] < 0.9 and min(r[v] for v in ("0", "1", "2", "3", "+x", "-x", "+z", "-z")) > 0.95  # (0.86; 0.97)


def test_the_overview_shows_a_hole_as_exact_only_pixels():
    from neuralrt.eval.intersection_metrics import _SILHOUETTE_COLOURS, _silhouette_image

    exact, test = Hits.empty(4), Hits.empty(4)
    exact.hit[:] = torch.tensor([True, True, False, False])
    test.hit[:] = torch.tensor([True, False, True, False])
    image = _silhouette_image(exact, test, 2, 2)
    np.testing.assert_array_equal(image.reshape(4, 3), _SILHOUETTE_COLOURS[[1, 2, 3, 0]])  # both, hole, extra, neither


def test_known_errors():
    n = 4
    rays = Rays(torch.zeros(n, 3), torch.tensor([[0.0, 0, 2.0]] * n))  # |d| = 2
    truth = Hits.empty(n)
    truth.hit[:] = torch.tensor([True, True, True, False])
    truth.t[:3] = 1.0
    truth.normal[:3] = torch.tensor([0.0, 0, 1.0])  # faces away from the ray: gets flipped to -z
    truth.material_id[:3] = 0
    pred = Hits.empty(n)
    pred.hit[:] = torch.tensor([True, True, False, True])
    pred.t[:2] = torch.tensor([1.1, 1.0])
    pred.t[3] = 5.0
    pred.normal[:2] = torch.tensor([[0.0, 0, -1.0], [0.0, math.sin(0.1), -math.cos(0.1)]])
    pred.material_id[:2] = torch.tensor([0, 1])
    m = ray_metrics(pred, truth, rays, diagonal=0.4)
    assert m["accuracy"] == 0.5 and m["false_negative_rate"] == pytest.approx(1 / 3) and m["false_positive_rate"] == 1.0
    # |dt| * |d| / diagonal = 0.1 * 2 / 0.4 for ray 0, 0 for ray 1: median of [0, 0.5] (linear) = 0.25.
    assert m["t_error_median"] == pytest.approx(0.25, rel=1e-5)
    assert m["normal_error_deg_median"] == pytest.approx(math.degrees(0.1) / 2, rel=1e-3)
    assert m["material_accuracy"] == 0.5 and m["normal_backfacing_fraction"] == 0.0


def test_eval_figures_show_every_view_and_both_ray_sets(tmp_path):
    from PIL import Image

    mesh = sphere(subdivisions=2)
    exact = MeshBLAS(mesh)
    r = evaluate_model(exact, mesh, rays=2048, cameras=2, resolution=32, image_dir=tmp_path)["images"]
    assert r["figures"] == {"errors": str(tmp_path / "errors.png"), "overview": str(tmp_path / "overview.png")}
    with Image.open(tmp_path / "overview.png") as overview, Image.open(tmp_path / "errors.png") as errors:
        assert 1.5 * overview.height < overview.width < 2.5 * overview.height  # eight views across, four images down
        assert errors.width > 1000

    class NeverHits:  # a model that answers no hit: nothing to draw errors of, the figure still comes
        bounds, secondary_offset, material_names = exact.bounds, exact.secondary_offset, ["default"]

        def intersect(self, rays):
            return Hits.empty(len(rays))

    r = evaluate_model(NeverHits(), mesh, rays=1024, cameras=2, resolution=16, image_dir=tmp_path / "none",
                       timing=False)["images"]
    assert r["silhouette_iou"] == 0.0 and (tmp_path / "none" / "errors.png").stat().st_size > 0


def test_a_mesh_no_held_out_ray_or_pixel_meets_is_said_to_measure_nothing(tmp_path):
    # A needle thinner than a pixel: eval printed accuracy 1, FLIP 0 and IoU 1 from rays and
    # views that all missed both the mesh and the model.
    from neuralrt.geometry.mesh import Mesh
    from neuralrt.geometry.procedural import box

    unit = box()
    needle = Mesh(unit.vertices * np.array([1e-4, 1e-4, 10.0], np.float32), unit.faces, name="needle")
    with pytest.warns(UserWarning) as caught:
        r = evaluate_model(MeshBLAS(needle), needle, rays=1024, cameras=2, resolution=16, image_dir=tmp_path,
                           timing=False)
    assert "surface points (the mesh covers little of its box)" in str(caught[0].message)  # (the held-out rays')
    assert [str(w.message) for w in caught[1:]] == [
        "needle: none of the 1,024 held-out rays meets the mesh (it covers little of its box): the ray figures count "
        "misses only",
        "needle: no pixel of any view at 16x16 shows the mesh or the model (thinner than a pixel): the image figures "
        "compare empty images"]
    assert r["outside"]["true_hit_fraction"] == r["surface"]["true_hit_fraction"] == 0.0
    images = r["images"]
    assert math.isnan(images["silhouette_iou"]) and math.isnan(images["silhouette_iou_min"])
    assert all(math.isnan(v) for v in images["silhouette_iou_per_view"].values())
    assert (tmp_path / "overview.png").stat().st_size > 0 and (tmp_path / "errors.png").stat().st_size > 0


def test_speed_and_memory_are_measured_against_exact_tracing_in_the_same_run():
    from neuralrt.eval.costs import same_run_speed
    from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel

    mesh = sphere(subdivisions=3)
    exact = MeshBLAS(mesh)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset("lq")).eval()
    r = evaluate_model(model, mesh, rays=2048, images=False)
    assert r["memory"]["model_bytes"] == model.memory_bytes().total and r["memory"]["bvh_a_bytes"] > 0
    assert r["memory"]["bvh_a_over_model"] == pytest.approx(r["memory"]["bvh_a_bytes"] / r["memory"]["model_bytes"])
    speed = r["speed"]
    # a fixed count of rays, whatever --rays is (2,048 calls would time their overhead)
    assert speed["rays"] == 1 << 17 and speed["exact_backend"] == "embree" and speed["device"] == "cpu"
    assert 0.1 < speed["exact_hit_fraction"] < 0.9
    for query in ("intersect", "occluded"):
        q = speed[query]
        assert q["neural_rays_per_second"] > 0 and q["exact_rays_per_second"] > 0
        assert q["neural_over_exact"] == pytest.approx(q["neural_rays_per_second"] / q["exact_rays_per_second"])
    assert "speed" not in evaluate_model(model, mesh, rays=256, images=False, timing=False)

    class Slow:  # exact tracing made 20 ms slower a call: the ratio follows
        bounds, backend = exact.bounds, "slowed"

        def intersect(self, rays):
            import time

            time.sleep(0.02)
            return exact.intersect(rays)

        occluded = intersect

    rays = Rays(torch.zeros(64, 3), torch.tensor([[0.0, 0.0, 1.0]]).expand(64, 3).contiguous())
    timed = same_run_speed(exact, Slow(), rays, repeats=3)
    assert timed["exact_backend"] == "slowed" and timed["intersect"]["neural_over_exact"] > 5
    assert timed["intersect"]["exact_rays_per_second"] < 64 / 0.02
