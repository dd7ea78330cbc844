"""Lights and camera: environment importance sampling (density integrates to one, matches its
samples), area-light densities, hit -> light lookup, lat-long mapping, camera rays."""

import math

import pytest
import torch
from scipy.stats import chi2

from neuralrt.render.camera import Camera
from neuralrt.render.lights import AreaLights, Environment
from neuralrt.render.sampling import luminance


def _env_image(h=8, w=16):
    g = torch.Generator().manual_seed(0)
    img = torch.rand(h, w, 3, generator=g) ** 3 * 4
    img[2, 11] = 50.0
    return img


def test_latlong_mapping():
    d = torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    uv = Environment.direction_to_uv(d)
    torch.testing.assert_close(uv[0], torch.tensor([0.5, 0.5]))
    assert float(uv[1, 1]) == pytest.approx(0.0, abs=1e-6)
    torch.testing.assert_close(uv[2], torch.tensor([0.75, 0.5]))
    g = torch.Generator().manual_seed(1)
    uv = torch.rand(1000, 2, generator=g) * 0.98 + 0.01
    torch.testing.assert_close(Environment.direction_to_uv(Environment.uv_to_direction(uv)), uv, atol=1e-5, rtol=0)


@pytest.mark.parametrize("kind", ["image", "rotated image", "constant"])
def test_environment_pdf_integrates_to_one_and_matches_samples(kind):
    env = Environment(color=(1, 2, 3)) if kind == "constant" else Environment(image=_env_image(), rotate_y=70.0 if "rotated" in kind else 0.0)
    # Midpoint quadrature over the sphere in (theta, phi): d omega = sin(theta) d theta d phi.
    n = 800
    th = (torch.arange(n, dtype=torch.float64) + 0.5) * (math.pi / n)
    p = (torch.arange(2 * n, dtype=torch.float64) + 0.5) * (math.pi / n)
    tt, pp = torch.meshgrid(th, p, indexing="ij")
    dirs = torch.stack([torch.sin(tt) * torch.cos(pp), torch.cos(tt), torch.sin(tt) * torch.sin(pp)], -1).reshape(-1, 3)
    integral = float((env.pdf(dirs.float()).double() * torch.sin(tt).reshape(-1)).sum()) * (math.pi / n) ** 2
    assert integral == pytest.approx(1.0, abs=2e-3)
    g = torch.Generator().manual_seed(2)
    d, pdf = env.sample(torch.rand(20000, generator=g), torch.rand(20000, 2, generator=g))
    torch.testing.assert_close(torch.linalg.norm(d, dim=-1), torch.ones(20000), atol=1e-5, rtol=0)
    torch.testing.assert_close(pdf, env.pdf(d), rtol=1e-3, atol=1e-6)


def _texel_means_of_lookup(env, h, w, sub=8):
    """[H, W] luminance of `Environment.radiance` averaged over each texel by a sub x sub midpoint
    rule (exact for the piecewise-bilinear lookup: the sub-cells do not straddle texel centres)."""
    u = (torch.arange(w * sub) + 0.5) / (w * sub)
    v = (torch.arange(h * sub) + 0.5) / (h * sub)
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    lum = luminance(env.radiance(Environment.uv_to_direction(torch.stack([uu, vv], -1).reshape(-1, 2))))
    return lum.reshape(h, sub, w, sub).double().mean((1, 3))


def test_environment_samples_follow_the_lookup_times_solid_angle():
    """Chi-square: texel hit counts vs the texel probabilities (the lookup's texel mean luminance x
    sin theta, normalised); the estimator of the mean radiance is unbiased."""
    img = _env_image()
    env = Environment(image=img)
    h, w = img.shape[:2]
    g = torch.Generator().manual_seed(3)
    n = 100_000
    d, _ = env.sample(torch.rand(n, generator=g), torch.rand(n, 2, generator=g))
    uv = Environment.direction_to_uv(d)
    texel = (uv[:, 1] * h).long().clamp(max=h - 1) * w + (uv[:, 0] * w).long().clamp(max=w - 1)
    observed = torch.bincount(texel, minlength=h * w).double()
    sin_theta = torch.sin((torch.arange(h) + 0.5) * math.pi / h).double()
    p = (_texel_means_of_lookup(env, h, w) * sin_theta[:, None]).reshape(-1)
    expected = p / p.sum() * n
    keep = expected >= 5
    stat = float((((observed - expected) ** 2 / expected)[keep]).sum())
    assert chi2.sf(stat, int(keep.sum()) - 1) > 1e-3
    # E[L / pdf] / 4 pi is the lookup's mean over the sphere (dense quadrature); L / pdf varies
    # within a texel now (std/mean 0.61 measured, 2.4 for uniform sphere sampling): std of the
    # mean ~0.2%.
    ratio = luminance(env.radiance(d)) / env.pdf(d)
    assert float(ratio.std() / ratio.mean()) < 1.0
    n_q = 1200
    th = (torch.arange(n_q, dtype=torch.float64) + 0.5) * (math.pi / n_q)
    ph = (torch.arange(2 * n_q, dtype=torch.float64) + 0.5) * (math.pi / n_q)
    tt, pp = torch.meshgrid(th, ph, indexing="ij")
    dirs = torch.stack([torch.sin(tt) * torch.cos(pp), torch.cos(tt), torch.sin(tt) * torch.sin(pp)], -1).reshape(-1, 3)
    mean = float((luminance(env.radiance(dirs.float())).double() * torch.sin(tt).reshape(-1)).sum()) * (math.pi / n_q) ** 2 / (4 * math.pi)
    assert float(ratio.double().mean()) / (4 * math.pi) == pytest.approx(mean, rel=6e-3)
    assert env.mean_radiance == pytest.approx(mean, rel=5e-3)  # midpoint rule in sin theta per texel row


def test_environment_lookup_is_continuous_and_wraps_in_azimuth():
    """No texel steps (the banding of a nearest-texel lookup): sweeping a direction across texels
    changes the radiance by small steps, also across the u = 0 / 1 seam."""
    img = _env_image()
    env = Environment(image=img)
    for u, v in ((torch.linspace(0.0, 1.0, 4001), torch.full((4001,), 0.4)),
                 (torch.full((4001,), 0.3), torch.linspace(0.07, 0.93, 4001))):
        lum = luminance(env.radiance(Environment.uv_to_direction(torch.stack([u, v], -1))))
        assert float((lum[1:] - lum[:-1]).abs().max()) < 0.05 * float(lum.max())
    seam = luminance(env.radiance(Environment.uv_to_direction(torch.tensor([[1e-6, 0.4], [1 - 1e-6, 0.4]]))))
    assert float(seam[0]) == pytest.approx(float(seam[1]), rel=1e-3)
    centre = Environment.uv_to_direction(torch.tensor([[(11 + 0.5) / 16, (2 + 0.5) / 8]]))  # texel centres are exact
    torch.testing.assert_close(env.radiance(centre)[0], img[2, 11], rtol=1e-4, atol=1e-4)


def test_environment_density_is_positive_wherever_the_lookup_is():
    """One bright texel in a black sky: the interpolated light spills into its neighbours, and so
    must the sampling density, or L / pdf explodes there (fireflies)."""
    img = torch.zeros(8, 16, 3)
    img[3, 5] = 100.0
    env = Environment(image=img)
    uv = torch.rand(200_000, 2, generator=torch.Generator().manual_seed(5))
    d = Environment.uv_to_direction(uv)
    lum = luminance(env.radiance(d))
    lit = lum > 0
    assert lit.sum() > 1000 and (env.pdf(d)[lit] > 0).all()
    ratio = lum[lit] / env.pdf(d)[lit]
    integral = 4 * math.pi * env.mean_radiance
    assert float(ratio.max()) < 40 * integral


def _two_quads():
    """Two unit-area emitting squares (4 triangles) facing -y at y = 1 and y = 2, in instances 0 and 2."""
    def quad(y, x0):
        v = torch.tensor([[x0, y, 0.0], [x0 + 1, y, 0.0], [x0 + 1, y, 1.0], [x0, y, 1.0]])
        return torch.stack([v[[0, 1, 2]], v[[0, 2, 3]]])
    tris = torch.cat([quad(1.0, -0.5), quad(2.0, 0.5)])
    normals = torch.tensor([[0.0, -1.0, 0.0]]).expand(4, 3)
    emission = torch.tensor([[1.0, 1.0, 1.0]] * 2 + [[3.0, 3.0, 3.0]] * 2)
    return AreaLights(tris, normals, emission, torch.tensor([0, 0, 2, 2]), torch.tensor([4, 5, 0, 1]), [6, 3, 2])


def test_area_light_pdf_matches_samples_and_integrates_to_one():
    lights = _two_quads()
    assert lights.distribution.pmf.tolist() == pytest.approx([0.125, 0.125, 0.375, 0.375])
    p = torch.zeros(50_000, 3)
    g = torch.Generator().manual_seed(4)
    idx, y, wi, pdf = lights.sample(p, torch.rand(50_000, generator=g), torch.rand(50_000, 2, generator=g))
    dist = torch.linalg.norm(y - p, dim=-1)
    torch.testing.assert_close(pdf, lights.pdf(idx, dist, wi), rtol=1e-5, atol=0)
    # The solid-angle densities integrate to one: E[1 / pdf] over samples = total solid angle seen, and
    # E_uniform-sphere[pdf] * 4 pi = 1 (both lights fully visible from the origin, no overlap in direction).
    u = torch.rand(400_000, 2, generator=g)
    z = 1 - 2 * u[:, 0]
    r = torch.sqrt(1 - z * z)
    dirs = torch.stack([r * torch.cos(2 * math.pi * u[:, 1]), z, r * torch.sin(2 * math.pi * u[:, 1])], -1)
    # Which light (if any) each direction reaches: intersect with the planes y = 1 and y = 2.
    dens = torch.zeros(len(dirs))
    for k, (yy, x0) in enumerate(((1.0, -0.5), (2.0, 0.5))):
        t = yy / dirs[:, 1]
        q = dirs * t[:, None]
        inside = (t > 0) & (q[:, 0] >= x0) & (q[:, 0] <= x0 + 1) & (q[:, 2] >= 0) & (q[:, 2] <= 1)
        tri = torch.where(q[:, 0] - x0 >= q[:, 2], 2 * k, 2 * k + 1)  # triangle 0 lies below the diagonal x = z
        d = lights.pdf(tri, t, dirs)
        dens += torch.where(inside, d, 0.0)
    assert float(dens.mean()) * 4 * math.pi == pytest.approx(1.0, abs=0.02)


def test_area_light_index_from_hits():
    lights = _two_quads()
    inst = torch.tensor([0, 0, 2, 2, 1, 0, -1])
    prim = torch.tensor([4, 5, 0, 1, 0, 0, -1])
    assert lights.light_index(inst, prim).tolist() == [0, 1, 2, 3, -1, -1, -1]


def test_camera_rays():
    cam = Camera.look_at((0, 0, 5), (0, 0, 0), (0, 1, 0), fov_y_degrees=90, resolution=(4, 2))
    # Pixel corners: jitter 0 at pixel 0 is the top-left image corner: tan(45) = 1 up, aspect 2 left.
    rays = cam.generate_rays(torch.tensor([0, 7]), torch.tensor([[0.0, 0.0], [1.0, 1.0]]))
    d = rays.directions / -rays.directions[:, 2:3]
    torch.testing.assert_close(d, torch.tensor([[-2.0, 1.0, -1.0], [2.0, -1.0, -1.0]]), atol=1e-5, rtol=0)
    torch.testing.assert_close(rays.origins, torch.tensor([[0.0, 0, 5], [0.0, 0, 5]]))
    torch.testing.assert_close(torch.linalg.norm(rays.directions, dim=-1), torch.ones(2))


def test_environment_rotation_turns_the_image():
    """rotate_y = 90: what the image shows straight ahead (-z) is seen at R_y(90)(-z) = -x."""
    plain, turned = Environment(image=_env_image()), Environment(image=_env_image(), rotate_y=90.0)
    g = torch.Generator().manual_seed(7)
    d = torch.nn.functional.normalize(torch.randn(1000, 3, generator=g), dim=-1)
    rotated = torch.stack([d[:, 2], d[:, 1], -d[:, 0]], -1)  # R_y(90) d
    same = (turned.radiance(rotated) == plain.radiance(d)).all(-1)
    assert float(same.float().mean()) > 0.99  # a few directions on texel borders may round to the neighbour
    torch.testing.assert_close(turned.pdf(rotated)[same], plain.pdf(d)[same], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(turned.radiance(torch.tensor([[-1.0, 0.0, 0.0]])), plain.radiance(torch.tensor([[0.0, 0.0, -1.0]])))
