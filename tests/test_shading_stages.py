"""The two shading implementations (`shading_stages`: torch ops, numba kernels) against each other:
the same random numbers in give the same answers out, stage by stage and for whole renders."""

import numpy as np
import pytest
import torch
import trimesh

from neuralrt.render import shading_kernels
from neuralrt.render.integrator import render
from neuralrt.render.lights import AreaLights, Environment, LightSet, PointLights
from neuralrt.render.shading_stages import _light_tables
from neuralrt.scene.loader import build_scene
from neuralrt.scene.schema import (
    CameraSpec,
    ConductorMaterialSpec,
    DiffuseMaterialSpec,
    EmissiveMaterialSpec,
    EnvironmentSpec,
    GeneratorSpec,
    ObjectSpec,
    PlasticMaterialSpec,
    PointLightSpec,
    SceneSpec,
    TransformSpec,
)
from test_integrator import _furnace, _quad_file, _sphere_file


def _every_feature_scene(tmp_path):
    """All material kinds (one textured), an area light, a point light and a rotated environment image."""
    from neuralrt.io.images import write_exr

    rng = np.random.default_rng(3)
    write_exr(tmp_path / "env.exr", (rng.random((8, 16, 3)) ** 3 * 4).astype(np.float32))
    write_exr(tmp_path / "tex.exr", rng.random((4, 4, 3)).astype(np.float32))
    box = trimesh.creation.box(extents=(0.8, 0.8, 0.8))
    box.export(tmp_path / "box.ply")
    return SceneSpec(
        camera=CameraSpec(position=(0, 1.0, 3.5), look_at=(0, 0, 0), fov=45, resolution=(24, 20)),
        materials=[DiffuseMaterialSpec(name="floor", albedo="tex.exr"),
                   ConductorMaterialSpec(name="metal", albedo=(0.9, 0.6, 0.3), roughness=0.2),
                   PlasticMaterialSpec(name="plastic", albedo=(0.2, 0.4, 0.8), roughness=0.1),
                   EmissiveMaterialSpec(name="light", emission=(6, 6, 6))],
        objects=[ObjectSpec(generator=GeneratorSpec(name="plane", params={"size": 6.0}), material="floor",  # (UVs: the texture shows)
                            transform=TransformSpec(translate=(0, -0.5, 0))),
                 ObjectSpec(mesh=_sphere_file(tmp_path / "s.ply", 2), material="metal", transform=TransformSpec(translate=(-0.6, 0, 0), scale=0.45)),
                 ObjectSpec(mesh=str(tmp_path / "box.ply"), material="plastic", transform=TransformSpec(translate=(0.6, -0.1, 0), rotate=(0, 30, 0))),
                 ObjectSpec(mesh=_quad_file(tmp_path / "light.ply", half=0.3, y=1.6, down=True), material="light")],
        lights=[PointLightSpec(position=(1.0, 1.5, 1.0), intensity=(2.0, 2.0, 2.0))],
        environment=EnvironmentSpec(image="env.exr", rotate_y=40.0),
    )


def test_torch_and_numba_shading_agree_on_the_same_random_numbers(tmp_path):
    """Same seed -> the same paths through both implementations: images and AOVs equal to float
    tolerance. A path may rarely take another branch where float32 (torch) and float64 (numba)
    rounding of a direction straddles a threshold or grazes an edge (measured: no pixel here over
    3 seeds; 0.4% of the pixels of the thin-tubed hairball), and only that path changes: each
    path's uniforms are its own."""
    scene = build_scene(_every_feature_scene(tmp_path), base_dir=tmp_path)
    assert set(scene.lights.kinds) == {"area", "point", "environment"}
    a = render(scene, spp=8, seed=4, max_depth=6, progress=False, shading="torch")
    b = render(scene, spp=8, seed=4, max_depth=6, progress=False, shading="numba")
    assert a.image.mean() > 0.05
    np.testing.assert_allclose(b.albedo, a.albedo, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(b.normal, a.normal, atol=1e-5)
    np.testing.assert_allclose(b.depth, a.depth, rtol=1e-5)
    close = np.isclose(b.image, a.image, rtol=1e-3, atol=1e-4).all(-1)
    assert close.mean() > 0.995, f"{(~close).sum()} pixels differ"
    assert float(b.image.mean()) == pytest.approx(float(a.image.mean()), rel=1e-3)
    c = render(scene, spp=8, seed=5, max_depth=6, progress=False, shading="numba")
    assert not np.isclose(c.image, a.image, rtol=1e-3, atol=1e-4).all(-1).mean() > 0.5  # another seed differs


def test_unknown_shading_backend_is_refused_before_rendering(tmp_path):
    scene = build_scene(_furnace(tmp_path))
    with pytest.raises(ValueError, match="shading must be one of"):
        render(scene, spp=1, shading="cuda-magic", progress=False)


def _light_set(rotate_y=25.0):
    g = torch.Generator().manual_seed(9)
    tris = torch.rand(5, 3, 3, generator=g) * 2 - 1 + torch.tensor([0.0, 2.0, 0.0])
    normals = torch.nn.functional.normalize(torch.linalg.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), dim=-1)
    emission = torch.rand(5, 3, generator=g) * 4
    area = AreaLights(tris, normals, emission, torch.tensor([1, 1, 1, 2, 2]), torch.tensor([0, 3, 4, 1, 0]), [2, 6, 3])
    points = PointLights(torch.rand(3, 3, generator=g), torch.rand(3, 3, generator=g) * 5)
    env = Environment(image=torch.rand(8, 16, 3, generator=g) ** 3 * 4, rotate_y=rotate_y)
    return LightSet(area, points, env)


@pytest.mark.parametrize("constant_environment", [False, True])
def test_light_samples_equal_torch_for_the_same_uniforms(constant_environment):
    """Area (by power), point and environment (importance-sampled image, rotated) light samples:
    direction, distance, radiance, pdf (with the kind choice) and the delta flag agree."""
    lights = _light_set()
    if constant_environment:
        lights = LightSet(lights.area, lights.points, Environment(color=(0.3, 0.4, 0.5)))
    n = 20_000
    g = torch.Generator().manual_seed(10)
    p = torch.rand(n, 3, generator=g) * 2 - 1
    u = torch.rand(n, 4, generator=g)
    ref = lights.sample(p, u)
    wi, dist, radiance, pdf = torch.zeros(n, 3), torch.zeros(n), torch.zeros(n, 3), torch.zeros(n)
    delta = torch.zeros(n, dtype=torch.bool)
    shading_kernels.light_sample_rows(*_light_tables(lights), p.numpy(), u[:, :3].contiguous().numpy(), wi.numpy(), dist.numpy(),
                                      radiance.numpy(), pdf.numpy(), delta.numpy())
    assert 0.2 < float(ref.is_delta.float().mean()) < 0.45  # a third of the samples pick the point lights
    torch.testing.assert_close(delta, ref.is_delta)
    torch.testing.assert_close(wi, ref.wi, rtol=1e-4, atol=2e-5)
    torch.testing.assert_close(dist, ref.distance, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(radiance, ref.radiance, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(pdf, ref.pdf, rtol=1e-3, atol=1e-6)


def test_environment_lookup_and_density_equal_torch():
    env = _light_set(rotate_y=-70.0).environment
    d = torch.nn.functional.normalize(torch.randn(20_000, 3, generator=torch.Generator().manual_seed(12)), dim=-1)
    radiance, pdf = torch.zeros(len(d), 3), torch.zeros(len(d))
    shading_kernels.environment_rows(_light_tables(LightSet(environment=env))[3], d.numpy(), radiance.numpy(), pdf.numpy())
    torch.testing.assert_close(radiance, env.radiance(d), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(pdf, env.pdf(d), rtol=1e-4, atol=1e-6)


def test_camera_paths_equal_torch(tmp_path):
    """The numba camera rays are the torch ones (float32 arithmetic in both) for an off-axis camera."""
    from neuralrt.render.shading_stages import NumbaShadingStages, TorchShadingStages

    spec = _every_feature_scene(tmp_path)
    spec.camera = CameraSpec(position=(0.3, 1.2, 3.0), look_at=(-0.2, 0, 0), fov=55, resolution=(37, 23))
    scene = build_scene(spec, base_dir=tmp_path)
    g = torch.Generator().manual_seed(13)
    pixel = torch.randint(0, 37 * 23, (5000,), generator=g)
    jitter = torch.rand(5000, 2, generator=g)
    ref = TorchShadingStages(scene, None).camera_paths(pixel, jitter)
    got = NumbaShadingStages(scene, None).camera_paths(pixel, jitter)
    torch.testing.assert_close(got.rays.origins, ref.rays.origins)
    torch.testing.assert_close(got.rays.directions, ref.rays.directions, rtol=0, atol=3e-7)
    assert torch.equal(got.sample, ref.sample) and torch.equal(got.throughput, ref.throughput)


def test_film_sums_equal_torch():
    """`Film.add` on the CPU (numba) and as torch ops: the same float64 sums, NaN/Inf samples counted as 0."""
    from neuralrt.render.film import Film

    g = torch.Generator().manual_seed(14)
    n = 5000
    pixel = torch.randint(0, 12, (n,), generator=g)
    radiance = torch.rand(n, 3, generator=g)
    radiance[::97, 1] = float("nan")
    radiance[::89, 2] = float("inf")
    albedo, normal, depth = torch.rand(n, 3, generator=g), torch.randn(n, 3, generator=g), torch.rand(n, generator=g) * 5
    hit = torch.rand(n, generator=g) < 0.7
    numba_film, torch_film = Film(4, 3), Film(4, 3)
    torch_film._add = torch_film._add_torch
    for film in (numba_film, torch_film):
        film.add(pixel, radiance, albedo, normal, depth, hit)
        film.add(pixel[:100], radiance[:100], albedo[:100], normal[:100], depth[:100], hit[:100])
    assert numba_film.nonfinite_samples == torch_film.nonfinite_samples > 50
    for name in ("radiance", "albedo", "normal", "depth", "hits", "count"):
        torch.testing.assert_close(getattr(numba_film, name), getattr(torch_film, name), rtol=1e-12, atol=1e-9)


def test_row_chunks_on_threads_give_the_same_image(tmp_path):
    """Wavefronts larger than one chunk run their numba passes on several threads: the image is the
    same bit for bit as on one thread (each chunk writes its own rows; outputs keep row order)."""
    import numba

    from neuralrt import host_threads

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("numba runs one thread here")
    scene = build_scene(_every_feature_scene(tmp_path), base_dir=tmp_path)
    kwargs = dict(spp=8, seed=2, max_depth=4, resolution=(96, 80), progress=False, shading="numba")  # 61,440 paths
    assert len(host_threads.chunk_slices(96 * 80 * 8, 2)) >= 4
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = render(scene, **kwargs)
    finally:
        numba.set_num_threads(threads)
    numba.set_num_threads(2)
    try:
        several = render(scene, **kwargs)
    finally:
        numba.set_num_threads(threads)
    np.testing.assert_array_equal(several.image, one.image)
    np.testing.assert_array_equal(several.depth, one.depth)


def test_stages_are_chosen_by_device(tmp_path):
    """auto: numba kernels for a CPU scene (torch for any other device); numba refuses a non-CPU scene."""
    from types import SimpleNamespace

    from neuralrt.render.integrator import IntegratorSettings
    from neuralrt.render.shading_stages import NumbaShadingStages, TorchShadingStages, shading_stages_for

    scene = build_scene(_furnace(tmp_path))
    assert isinstance(shading_stages_for(scene, IntegratorSettings()), NumbaShadingStages)
    assert isinstance(shading_stages_for(scene, IntegratorSettings(), "torch"), TorchShadingStages)
    with pytest.raises(ValueError, match="run on the CPU"):
        shading_stages_for(SimpleNamespace(device=torch.device("meta")), IntegratorSettings(), "numba")
