"""The path tracer against closed forms: white furnace, point light and area light over a diffuse
plane, an environment image over a plane (importance sampling + MIS), instance-transform
invariance, determinism, AOVs. Tolerances are stated from the measured noise level. Every test
runs with both shading implementations (torch ops and the CPU's numba kernels), and the two are
compared on the same random numbers."""

import math

import numpy as np
import pytest
import torch
import trimesh

from neuralrt.render import integrator
from neuralrt.render.integrator import render
from neuralrt.scene.loader import build_scene
from neuralrt.scene.schema import (
    CameraSpec,
    ConductorMaterialSpec,
    PlasticMaterialSpec,
    DiffuseMaterialSpec,
    EmissiveMaterialSpec,
    EnvironmentSpec,
    ObjectSpec,
    PointLightSpec,
    SceneSpec,
    TransformSpec,
)


@pytest.fixture(params=["torch", "numba"], autouse=True)
def shading(request, monkeypatch):
    """Run each test with the shading stages of one implementation, whatever the render asks for."""
    real = integrator.shading_stages_for
    monkeypatch.setattr(integrator, "shading_stages_for", lambda scene, settings, backend="auto": real(scene, settings, request.param))
    return request.param


def _quad_file(path, half=1.0, y=0.0, down=False):
    """A square of half-side ``half`` in the plane y = ``y``, facing +y (or -y)."""
    v = np.array([[-half, y, -half], [half, y, -half], [half, y, half], [-half, y, half]], np.float32)
    f = np.array([[0, 2, 1], [0, 3, 2]]) if not down else np.array([[0, 1, 2], [0, 2, 3]])
    trimesh.Trimesh(v, f, process=False).export(path)
    return str(path)


def _sphere_file(path, subdivisions=3):
    trimesh.creation.icosphere(subdivisions=subdivisions).export(path)
    return str(path)


def _furnace(tmp_path):
    return SceneSpec(
        camera=CameraSpec(position=(0, 0, 3), fov=45, resolution=(12, 12)),
        materials=[DiffuseMaterialSpec(name="white", albedo=(1, 1, 1))],
        objects=[ObjectSpec(mesh=_sphere_file(tmp_path / "s.ply"), material="white")],
        environment=EnvironmentSpec(color=(0.5, 0.5, 0.5)),
    )


def test_white_furnace_returns_the_environment(tmp_path):
    """An albedo-1 diffuse sphere in a constant environment is invisible: every pixel equals it."""
    scene = build_scene(_furnace(tmp_path))
    res = render(scene, spp=64, max_depth=64, seed=1, progress=False)
    hit = res.depth > 0
    assert hit.mean() > 0.3  # the sphere covers a good part of the image
    # Per-sample std measured 0.12 here; the mean over ~80 hit pixels x 64 spp has std ~0.002.
    assert float(res.image[hit].mean()) == pytest.approx(0.5, abs=0.01)
    assert np.abs(res.image[~hit] - 0.5).max() < 1e-6  # escaped camera rays see the environment exactly
    assert np.abs(res.image[hit] - 0.5).max() < 0.08  # no pixel far off (per-pixel std measured 0.016)


@pytest.mark.parametrize("material,low", [
    (ConductorMaterialSpec(name="white", albedo=(1, 1, 1), roughness=0.05), 0.485),
    (ConductorMaterialSpec(name="white", albedo=(1, 1, 1), roughness=0.3), 0.40),
    (PlasticMaterialSpec(name="white", albedo=(1, 1, 1), roughness=0.3), 0.40),
])
def test_glossy_furnace_never_brightens(tmp_path, material, low):
    """White metal / plastic spheres in the furnace: single-scattering GGX and a coat without internal
    reflections only lose energy (measured means 0.498, 0.440, 0.449), a near-mirror almost none."""
    spec = _furnace(tmp_path)
    spec.materials = [material]
    res = render(build_scene(spec), spp=64, max_depth=32, seed=1, progress=False)
    mean = float(res.image[res.depth > 0].mean())
    assert low < mean < 0.5 + 0.005  # std of the mean measured < 0.004
def _closed_form_plane_pixels(scene, radiance_at, k=8):
    """Pixel means of ``radiance_at(points on y = 0)`` over a k x k grid of positions in each pixel."""
    cam = scene.camera
    n = cam.num_pixels
    js = (torch.arange(k) + 0.5) / k
    jitter = torch.stack(torch.meshgrid(js, js, indexing="ij"), -1).reshape(-1, 2)
    total = torch.zeros(n, 3, dtype=torch.float64)
    for j in jitter:
        rays = cam.generate_rays(torch.arange(n), j.expand(n, 2))
        t = -rays.origins[:, 1] / rays.directions[:, 1]
        total += radiance_at(rays.origins + t[:, None] * rays.directions).double()
    return (total / len(jitter)).reshape(cam.height, cam.width, 3).numpy()


def test_point_light_over_diffuse_plane_matches_closed_form(tmp_path):
    """L = albedo / pi * I cos(theta) / r^2 (direct lighting only; noise only from pixel jitter)."""
    albedo, intensity, light = 0.6, 4.0, torch.tensor([0.3, 1.5, -0.2])
    spec = SceneSpec(
        camera=CameraSpec(position=(0, 3, 2), look_at=(0, 0, 0), fov=40, resolution=(40, 32)),
        materials=[DiffuseMaterialSpec(name="m", albedo=(albedo,) * 3)],
        objects=[ObjectSpec(mesh=_quad_file(tmp_path / "p.ply", half=5.0), material="m")],
        lights=[PointLightSpec(position=tuple(light.tolist()), intensity=(intensity,) * 3)],
    )
    scene = build_scene(spec)
    res = render(scene, spp=32, max_depth=3, progress=False)

    def closed_form(p):
        d = light - p
        r2 = (d * d).sum(-1)
        cos = d[:, 1] / r2.sqrt()
        return (albedo / math.pi * intensity * cos / r2)[:, None].expand(-1, 3)

    expected = _closed_form_plane_pixels(scene, closed_form)
    # Only pixel-jitter noise (32 random vs 64 grid positions per pixel): measured over 3 seeds, the
    # per-pixel relative error has std 0.45% and max 2.3%; the image mean is within 1e-4.
    np.testing.assert_allclose(res.image, expected, rtol=0.04)
    assert float(res.image.mean()) == pytest.approx(float(expected.mean()), rel=1e-3)


def test_a_far_bright_point_light_does_not_starve_a_near_one(tmp_path):
    """A sun-like light (1,000 scene radii away, as bright on the plane as the near light) beside a
    near one: lights are picked by the irradiance they give the scene, not by intensity (which would
    pick the near one once in 10^7 samples: a black image with a few white pixels)."""
    albedo, near, near_intensity = 0.6, torch.tensor([0.3, 1.5, -0.2]), 4.0
    direction = torch.tensor([1.0, 2.0, 1.0]) / math.sqrt(6.0)
    far = direction * 7000.0
    far_intensity = 0.8 * near_intensity / 1.5**2 * 7000.0**2  # 0.8x the near light's irradiance below it
    spec = SceneSpec(
        camera=CameraSpec(position=(0, 3, 2), look_at=(0, 0, 0), fov=40, resolution=(40, 32)),
        materials=[DiffuseMaterialSpec(name="m", albedo=(albedo,) * 3)],
        objects=[ObjectSpec(mesh=_quad_file(tmp_path / "p.ply", half=5.0), material="m")],
        lights=[PointLightSpec(position=tuple(light.tolist()), intensity=(i,) * 3)
                for light, i in ((near, near_intensity), (far, far_intensity))],
    )
    scene = build_scene(spec)
    res = render(scene, spp=64, max_depth=1, progress=False, seed=3)

    def closed_form(p):
        total = torch.zeros(p.shape[0])
        for light, intensity in ((near, near_intensity), (far, far_intensity)):
            d = light - p
            r2 = (d * d).sum(-1)
            total += albedo / math.pi * intensity * (d[:, 1] / r2.sqrt()).clamp(min=0) / r2
        return total[:, None].expand(-1, 3)

    expected = _closed_form_plane_pixels(scene, closed_form)
    # The near light is picked in about 1 sample of 8: its share of each pixel is noisy, the image mean is not.
    assert float(res.image.mean()) == pytest.approx(float(expected.mean()), rel=0.02)
    np.testing.assert_allclose(res.image.mean(axis=(0, 1)), expected.mean(axis=(0, 1)), rtol=0.02)
    assert float(np.median(np.abs(res.image - expected) / expected)) < 0.15


def test_area_light_over_diffuse_plane_matches_closed_form(tmp_path):
    """A square Lambertian emitter of half-side a at height h: E = 4 L (a/s) atan(a/s), s = sqrt(a^2 + h^2),
    below its centre; the plane reflects albedo/pi * E. Light sampling and BSDF sampling both
    contribute (MIS); the camera views the spot below the centre through a narrow field of view."""
    a, h, le, albedo = 0.5, 1.0, 3.0, 0.8
    spec = SceneSpec(
        camera=CameraSpec(position=(4, 0.6, 0), look_at=(0, 0, 0), fov=0.2, resolution=(4, 4)),
        materials=[DiffuseMaterialSpec(name="m", albedo=(albedo,) * 3), EmissiveMaterialSpec(name="light", emission=(le,) * 3)],
        objects=[
            ObjectSpec(mesh=_quad_file(tmp_path / "p.ply", half=20.0), material="m"),
            ObjectSpec(mesh=_quad_file(tmp_path / "l.ply", half=a, y=h, down=True), material="light"),
        ],
    )
    scene = build_scene(spec)
    res = render(scene, spp=1024, max_depth=1, progress=False)
    s = math.hypot(a, h)
    expected = albedo / math.pi * 4 * le * (a / s) * math.atan(a / s)
    # 16 pixels x 1024 spp; per-sample relative std measured 0.18 -> std of the mean ~0.15%.
    assert float(res.image.mean()) == pytest.approx(expected, rel=0.01)


def test_deeper_paths_add_nothing_where_no_indirect_light_exists(tmp_path):
    """Plane + one-sided black-backed emitter: light bounced from the plane only reaches the light's
    back (albedo 0), so max_depth 4 must equal max_depth 1 (catches double-counted emission)."""
    a, h, le, albedo = 0.5, 1.0, 3.0, 0.8
    spec = SceneSpec(
        camera=CameraSpec(position=(4, 0.6, 0), look_at=(0, 0, 0), fov=0.2, resolution=(4, 4)),
        materials=[DiffuseMaterialSpec(name="m", albedo=(albedo,) * 3), EmissiveMaterialSpec(name="light", emission=(le,) * 3)],
        objects=[
            ObjectSpec(mesh=_quad_file(tmp_path / "p.ply", half=20.0), material="m"),
            ObjectSpec(mesh=_quad_file(tmp_path / "l.ply", half=a, y=h, down=True), material="light"),
        ],
    )
    scene = build_scene(spec)
    d1 = render(scene, spp=1024, max_depth=1, seed=3, progress=False).image.mean()
    d4 = render(scene, spp=1024, max_depth=4, seed=4, progress=False).image.mean()
    # Indirect light: plane -> back of the light (albedo 0) -> nothing; so depth 4 adds only noise.
    assert float(d4) == pytest.approx(float(d1), rel=0.03)


def test_environment_image_over_plane_matches_quadrature(tmp_path):
    """A diffuse plane under a lat-long image: L = albedo/pi * integral of L_env cos over the upper
    hemisphere (computed by quadrature of the bilinear lookup). Exercises importance sampling + MIS."""
    from neuralrt.io.images import write_exr

    h_img, w_img = 16, 32
    rng = np.random.default_rng(0)
    image = (rng.random((h_img, w_img, 3)) ** 4 * 5).astype(np.float32)  # spiky: importance sampling matters
    image[3, 5] = 200.0  # a small bright "sun"
    write_exr(tmp_path / "env.exr", image)
    albedo = 0.7
    spec = SceneSpec(
        camera=CameraSpec(position=(0, 2, 2), look_at=(0, 0, 0), fov=1.0, resolution=(4, 4)),
        materials=[DiffuseMaterialSpec(name="m", albedo=(albedo,) * 3)],
        objects=[ObjectSpec(mesh=_quad_file(tmp_path / "p.ply", half=50.0), material="m")],
        environment=EnvironmentSpec(image="env.exr"),
    )
    scene = build_scene(spec, base_dir=tmp_path)
    res = render(scene, spp=2048, max_depth=1, progress=False)
    # Quadrature: sub-sample each texel 16 x 16 in (u, v); solid angle dA = 2 pi^2 sin(theta) du dv.
    sub = 16
    u = (np.arange(w_img * sub) + 0.5) / (w_img * sub)
    v = (np.arange(h_img * sub) + 0.5) / (h_img * sub)
    theta = np.pi * v
    cos = np.clip(np.cos(theta), 0, None)  # y = cos(theta): upper hemisphere only
    weight = (cos * np.sin(theta))[:, None] * np.ones_like(u)[None] * (2 * np.pi**2) / (w_img * sub * h_img * sub)
    # The environment is looked up bilinearly between texel centres (wrapping in u, clamped in v).
    x, y = u * w_img - 0.5, v * h_img - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[None, :, None], (y - y0)[:, None, None]
    xa, xb = x0 % w_img, (x0 + 1) % w_img
    ya, yb = np.clip(y0, 0, h_img - 1), np.clip(y0 + 1, 0, h_img - 1)
    lookup = (image[ya][:, xa] * (1 - fx) + image[ya][:, xb] * fx) * (1 - fy) + (image[yb][:, xa] * (1 - fx) + image[yb][:, xb] * fx) * fy
    expected = albedo / np.pi * (lookup * weight[..., None]).sum((0, 1))
    # The plane is huge, so the lower hemisphere is blocked; camera pixels are near the origin.
    # Std of the 16-pixel mean measured 0.3-0.5% at 4096 spp (so ~0.6% here; heavy-tailed from the sun).
    np.testing.assert_allclose(res.image.mean((0, 1)), expected, rtol=0.025)


def _box_scene(tmp_path, object_mesh, transform, name="scene"):
    return SceneSpec(
        camera=CameraSpec(position=(0, 0, 3.9), look_at=(0, 0, 0), fov=40, resolution=(16, 16)),
        materials=[DiffuseMaterialSpec(name="white", albedo=(0.7, 0.7, 0.7)), DiffuseMaterialSpec(name="obj", albedo=(0.6, 0.3, 0.2)),
                   EmissiveMaterialSpec(name="light", emission=(8, 8, 8))],
        objects=[
            ObjectSpec(mesh=_quad_file(tmp_path / "floor.ply", half=3.0, y=-1.0), material="white"),
            ObjectSpec(mesh=_quad_file(tmp_path / "light.ply", half=0.4, y=1.5, down=True), material="light"),
            ObjectSpec(mesh=object_mesh, material="obj", transform=transform),
        ],
        environment=EnvironmentSpec(color=(0.1, 0.1, 0.1)),
    )


def test_image_unchanged_when_geometry_moves_into_the_instance_transform(tmp_path):
    """Baking the transform into the mesh vertices and using the identity gives the same image (noise)."""
    box = trimesh.creation.box(extents=(1.0, 0.6, 0.8))
    box.export(tmp_path / "box.ply")
    t = TransformSpec(translate=(0.2, -0.5, 0.1), rotate=(10, 35, 0), scale=(0.9, 1.2, 1.0))
    baked = box.copy()
    baked.apply_transform(t.to_transform().tolist())
    baked.export(tmp_path / "baked.ply")
    # A third, different split of the same world geometry: half the scale in the mesh, the rest in the instance.
    half = box.copy()
    half.apply_scale(0.5)
    half.export(tmp_path / "half.ply")
    t_half = TransformSpec(translate=(0.2, -0.5, 0.1), rotate=(10, 35, 0), scale=(1.8, 2.4, 2.0))
    moved = TransformSpec(translate=(0.3, -0.5, 0.1), rotate=(10, 35, 0), scale=(0.9, 1.2, 1.0))  # negative control
    # The same seed for all: the paths only diverge where float rounding differs, so the noise is
    # correlated and a tight tolerance still holds (different seeds differ by ~1% in the mean here).
    images = [
        render(build_scene(_box_scene(tmp_path, str(mesh), tf)), spp=64, max_depth=4, seed=5, progress=False).image
        for mesh, tf in ((tmp_path / "box.ply", t), (tmp_path / "baked.ply", TransformSpec()), (tmp_path / "half.ply", t_half),
                         (tmp_path / "box.ply", moved))
    ]
    blocks = [im.reshape(4, 4, 4, 4, 3).mean((1, 3)) for im in images]  # 4x4-pixel block means
    for other in blocks[1:3]:
        np.testing.assert_allclose(other, blocks[0], rtol=0.03, atol=2e-3)
    assert not np.allclose(blocks[3], blocks[0], rtol=0.03, atol=2e-3)  # moving the box by 0.1 is visible


def test_a_scene_far_from_the_origin_renders_as_at_the_origin(tmp_path):
    """Secondary rays leave a hit by at least a few float32 ulps of its coordinates: a unit sphere
    on a floor under a point light, all moved to x = 1e4, shadowed itself where the point's
    rounding (1e-3) passed its offset (1e-4 of its size): 2.1% darker before, with acne."""
    sphere = _sphere_file(tmp_path / "s.ply")
    floor = _quad_file(tmp_path / "f.ply", half=4.0, y=-1.0)

    def image(x: float):
        spec = SceneSpec(
            camera=CameraSpec(position=(x, 1.5, 4), look_at=(x, 0, 0), fov=45, resolution=(24, 24)),
            materials=[DiffuseMaterialSpec(name="m", albedo=(0.7,) * 3)],
            objects=[ObjectSpec(mesh=sphere, material="m", transform=TransformSpec(translate=(x, 0, 0))),
                     ObjectSpec(mesh=floor, material="m", transform=TransformSpec(translate=(x, 0, 0)))],
            lights=[PointLightSpec(position=(x + 1.0, 3.0, 2.0), intensity=(20.0,) * 3)],
        )
        return render(build_scene(spec), spp=8, max_depth=2, seed=3, progress=False).image

    near, far = image(0.0), image(1e4)
    assert float(far.mean()) == pytest.approx(float(near.mean()), rel=0.01)
    # (pixels of acne are dark specks: none where the render at the origin is lit)
    lit = near.mean(-1) > 0.05
    assert float((far.mean(-1)[lit] < 0.5 * near.mean(-1)[lit]).mean()) < 0.01


def test_deterministic_for_a_seed_and_aovs(tmp_path):
    spec = _box_scene(tmp_path, _sphere_file(tmp_path / "s.ply", 2), TransformSpec(scale=0.5))
    scene = build_scene(spec)
    a = render(scene, spp=2, seed=7, progress=False)
    b = render(scene, spp=2, seed=7, progress=False)
    c = render(scene, spp=2, seed=8, progress=False)
    np.testing.assert_array_equal(a.image, b.image)
    assert not np.array_equal(a.image, c.image)
    assert a.spp == 2 and a.seconds > 0 and a.image.dtype == np.float32 and a.image.shape == (16, 16, 3)
    # Centre pixels see the sphere (radius 0.5 at the origin; facets at subdivision 2 lie up to 0.06
    # inside it) from z = 3.9: depth in [3.4, 3.46], normal ~+z.
    centre = a.depth[7:9, 7:9]
    assert ((centre > 3.399) & (centre < 3.46)).all()
    # Samples in these pixels lie up to ~0.2 radius off the axis (12 deg) on facets up to ~10 deg
    # from the sphere's normal: z above cos(22 deg) = 0.93 (0.95 held for one random stream only).
    assert (a.normal[7:9, 7:9, 2] > 0.92).all()
    np.testing.assert_allclose(a.albedo[7:9, 7:9], np.broadcast_to([0.6, 0.3, 0.2], (2, 2, 3)), atol=1e-6)
    assert render(scene, spp=1, resolution=(8, 4), progress=False).image.shape == (4, 8, 3)
    written = a.save(tmp_path / "out.exr")
    assert {p.name for p in written} >= {"out.exr", "out.png", "out_albedo.exr", "out_normal.png", "out_depth.exr", "out_coverage.exr"}


def test_small_wavefronts_give_the_same_estimate(tmp_path):
    """Splitting each pass into several wavefronts (max_paths < pixels) changes the random stream only:
    the furnace still returns the environment."""
    scene = build_scene(_furnace(tmp_path))
    res = render(scene, spp=16, seed=2, max_paths=50, max_depth=16, progress=False)  # 3 wavefronts per pass
    hit = res.depth > 0
    # 16 spp x ~80 hit pixels, per-sample std 0.12: std of the mean ~0.0035.
    assert float(res.image[hit].mean()) == pytest.approx(0.5, abs=0.015)
    assert np.abs(res.image[~hit] - 0.5).max() < 1e-6


def test_film_drops_and_counts_nonfinite_samples():
    from neuralrt.render.film import Film

    film = Film(2, 1)
    pixel = torch.tensor([0, 0, 1])
    radiance = torch.tensor([[1.0, 1.0, 1.0], [float("nan"), 0.0, 0.0], [2.0, float("inf"), 2.0]])
    zeros = torch.zeros(3, 3)
    film.add(pixel, radiance, zeros, zeros, torch.zeros(3), torch.zeros(3, dtype=torch.bool))
    res = film.result(spp=1, seconds=1.0)
    np.testing.assert_allclose(res.image[0], [[0.5, 0.5, 0.5], [0.0, 0.0, 0.0]])
    assert res.stats["nonfinite_samples"] == 2


def test_settings_are_honoured_and_keywords_override_them(tmp_path, monkeypatch):
    """``settings`` gives max_depth and max_paths unless a keyword overrides them; the caller's
    settings object is never modified."""
    from neuralrt.render.integrator import IntegratorSettings, PathTracer

    scene = build_scene(_furnace(tmp_path))
    seen = []
    real_trace = PathTracer.trace
    monkeypatch.setattr(PathTracer, "trace", lambda self, pixel, g: seen.append((pixel.numel(), self.settings.max_depth))
                        or real_trace(self, pixel, g))
    mine = IntegratorSettings(max_depth=2, max_paths=36)
    render(scene, spp=1, settings=mine, progress=False)
    assert {n for n, _ in seen} == {36} and {d for _, d in seen} == {2}  # 144 pixels in wavefronts of 36
    seen.clear()
    render(scene, spp=1, settings=mine, max_depth=3, max_paths=72, progress=False)
    assert {n for n, _ in seen} == {72} and {d for _, d in seen} == {3}
    assert (mine.max_depth, mine.max_paths) == (2, 36)
    seen.clear()
    render(scene, spp=1, progress=False)  # the scene's render defaults, the default wavefront size
    assert seen == [(144, scene.settings.max_depth)]


def test_depth_averages_over_hits_and_coverage_counts_them():
    """A pixel whose samples half miss keeps its surface's depth (misses are not averaged in as 0,
    which showed as near-white dots in the depth PNG); coverage says how many samples hit."""
    from neuralrt.render.film import Film

    film = Film(3, 1)
    pixel = torch.tensor([0, 0, 0, 0, 1, 1, 2])
    depth = torch.tensor([2.0, 4.0, 0.0, 0.0, 5.0, 5.0, 0.0])
    hit = torch.tensor([True, True, False, False, True, True, False])
    zeros = torch.zeros(7, 3)
    film.add(pixel, zeros, zeros, zeros, depth, hit)
    res = film.result(spp=1, seconds=1.0)
    np.testing.assert_allclose(res.depth, [[3.0, 5.0, 0.0]])
    np.testing.assert_allclose(res.coverage, [[0.5, 1.0, 0.0]])


def test_silhouette_pixels_keep_the_surface_depth(tmp_path):
    """Rendered: every pixel that any sample hits has a depth within the sphere's depth range."""
    res = render(build_scene(_furnace(tmp_path)), spp=8, seed=1, max_depth=1, progress=False)
    edge = (res.coverage > 0) & (res.coverage < 1)
    assert edge.sum() >= 8
    seen = res.coverage > 0
    # Unit sphere seen from distance 3: depths from 2 (front) to sqrt(8) = 2.83 (silhouette).
    assert res.depth[seen].min() > 1.99 and res.depth[seen].max() < 2.84
    assert (res.depth[~seen] == 0).all()

