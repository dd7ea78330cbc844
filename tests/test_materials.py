"""BSDFs: densities integrate to the sampler's success rate, sampled pdfs match `pdf`, chi-square
agreement of samples with the density, reciprocity and energy conservation. Each runs on both
implementations: the torch `MaterialTable` and the numba kernels the CPU renderer uses."""

import math

import pytest
import torch
from scipy.stats import chi2

from neuralrt.render import shading_kernels
from neuralrt.render.materials import BSDFSample, MaterialKind, MaterialTable, fresnel_dielectric
from neuralrt.render.sampling import DiscreteDistribution, cosine_hemisphere, uniform_triangle

CASES = [
    ("diffuse", MaterialKind.DIFFUSE, 0.1),
    ("conductor-rough", MaterialKind.CONDUCTOR, 0.5),
    ("conductor-glossy", MaterialKind.CONDUCTOR, 0.15),
    ("plastic-rough", MaterialKind.PLASTIC, 0.4),
    ("plastic-glossy", MaterialKind.PLASTIC, 0.15),
]
WO_ANGLES = [10.0, 60.0]


class NumbaBSDF:
    """A `MaterialTable`'s BSDF methods answered by the numba kernels of `shading_kernels`."""

    def __init__(self, table: MaterialTable):
        self.table = table

    def _rows(self, material_id, albedo, n, wo):
        kind, alpha, ior = self.table._params(material_id)
        return [x.contiguous().numpy() for x in (kind, alpha, ior, albedo, n, wo)]

    def eval_pdf(self, material_id, albedo, n, wo, wi):
        value, pdf = torch.zeros(len(material_id), 3), torch.zeros(len(material_id))
        shading_kernels.bsdf_eval_rows(*self._rows(material_id, albedo, n, wo), wi.contiguous().numpy(), value.numpy(), pdf.numpy())
        return value, pdf

    def eval(self, *args):
        return self.eval_pdf(*args)[0]

    def pdf(self, *args):
        return self.eval_pdf(*args)[1]

    def sample(self, material_id, albedo, n, wo, u_lobe, u_dir):
        wi, weight, pdf = torch.zeros(len(material_id), 3), torch.zeros(len(material_id), 3), torch.zeros(len(material_id))
        shading_kernels.bsdf_sample_rows(*self._rows(material_id, albedo, n, wo), u_lobe.contiguous().numpy(), u_dir.contiguous().numpy(),
                                         wi.numpy(), weight.numpy(), pdf.numpy())
        return BSDFSample(wi, weight, pdf)


@pytest.fixture(params=["torch", "numba"], autouse=True)
def backend(request, monkeypatch):
    """Every test of this file runs with `_table` giving the torch table or its numba twin."""
    monkeypatch.setitem(_BACKEND, "name", request.param)
    return request.param


_BACKEND = {"name": "torch"}


def _table(kind, roughness, albedo=(0.7, 0.5, 0.3)):
    table = MaterialTable.single(kind, albedo=albedo, roughness=roughness)
    return NumbaBSDF(table) if _BACKEND["name"] == "numba" else table


def _setup(n, wo_deg, albedo=(0.7, 0.5, 0.3)):
    th = math.radians(wo_deg)
    wo = torch.tensor([[math.sin(th), 0.0, math.cos(th)]]).expand(n, 3).contiguous()
    normal = torch.tensor([[0.0, 0.0, 1.0]]).expand(n, 3).contiguous()
    return wo, normal, torch.zeros(n, dtype=torch.int64), torch.tensor([albedo]).expand(n, 3).contiguous()


def _sphere_grid(n_cos=400, n_phi=800):
    """Midpoint quadrature over the sphere in (cos theta, phi): directions and the cell solid angle."""
    c = -1 + (torch.arange(n_cos) + 0.5) * (2 / n_cos)
    p = (torch.arange(n_phi) + 0.5) * (2 * math.pi / n_phi)
    cc, pp = torch.meshgrid(c, p, indexing="ij")
    s = torch.sqrt(1 - cc**2)
    dirs = torch.stack([s * torch.cos(pp), s * torch.sin(pp), cc], -1).reshape(-1, 3)
    return dirs, (2 / n_cos) * (2 * math.pi / n_phi)


def _sample(table, wo, normal, mid, albedo, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = wo.shape[0]
    return table.sample(mid, albedo, normal, wo, torch.rand(n, generator=g), torch.rand(n, 2, generator=g))


@pytest.mark.parametrize("name,kind,roughness", CASES)
@pytest.mark.parametrize("wo_deg", WO_ANGLES)
def test_pdf_integrates_to_sampling_success_rate(name, kind, roughness, wo_deg):
    """The density over the sphere sums to the fraction of samples that land above the surface (1 for
    diffuse; slightly less for GGX whose mirrored microfacet directions can point below)."""
    table = _table(kind, roughness)
    dirs, cell = _sphere_grid()
    wo, normal, mid, albedo = _setup(dirs.shape[0], wo_deg)
    integral = float(table.pdf(mid, albedo, normal, wo, dirs).sum()) * cell
    # The grid integral changes by < 1e-4 from 400 x 800 to 800 x 1600 cells for these roughnesses.
    s = _sample(table, *_setup(200_000, wo_deg))
    success = float((s.pdf > 0).float().mean())
    assert integral == pytest.approx(success, abs=0.01)
    assert integral <= 1.0 + 0.005
    if kind == MaterialKind.DIFFUSE:
        assert integral == pytest.approx(1.0, abs=2e-3)


@pytest.mark.parametrize("name,kind,roughness", CASES)
def test_sample_pdf_and_weight_agree_with_eval(name, kind, roughness):
    table = _table(kind, roughness)
    wo, normal, mid, albedo = _setup(20_000, 40.0)
    s = _sample(table, wo, normal, mid, albedo)
    ok = s.pdf > 0
    f, pdf = table.eval_pdf(mid[ok], albedo[ok], normal[ok], wo[ok], s.wi[ok])
    torch.testing.assert_close(pdf, s.pdf[ok], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(f / pdf[:, None], s.weight[ok], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(table.pdf(mid, albedo, normal, wo, s.wi)[ok], s.pdf[ok], rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("name,kind,roughness", CASES)
def test_chi_square_samples_follow_pdf(name, kind, roughness):
    """Histogram of 200k samples over (cos theta, phi) cells vs the integrated density (Mitsuba-style)."""
    table = _table(kind, roughness)
    n = 200_000
    s = _sample(table, *_setup(n, 35.0), seed=1)
    wi = s.wi[s.pdf > 0]
    n_cos, n_phi, sub = 10, 20, 24
    ci = ((wi[:, 2].clamp(0, 1 - 1e-7)) * n_cos).long()
    pi = (torch.remainder(torch.atan2(wi[:, 1], wi[:, 0]), 2 * math.pi) / (2 * math.pi) * n_phi).long().clamp(max=n_phi - 1)
    observed = torch.bincount(ci * n_phi + pi, minlength=n_cos * n_phi).double()
    # Expected counts: integrate the pdf over each cell with a sub x sub midpoint rule.
    c = (torch.arange(n_cos * sub) + 0.5) / (n_cos * sub)
    p = (torch.arange(n_phi * sub) + 0.5) / (n_phi * sub) * 2 * math.pi
    cc, pp = torch.meshgrid(c, p, indexing="ij")
    sn = torch.sqrt(1 - cc**2)
    dirs = torch.stack([sn * torch.cos(pp), sn * torch.sin(pp), cc], -1).reshape(-1, 3)
    wo, normal, mid, albedo = _setup(dirs.shape[0], 35.0)
    dens = table.pdf(mid, albedo, normal, wo, dirs).double().reshape(n_cos, sub, n_phi, sub)
    expected = dens.sum((1, 3)).reshape(-1) * (1 / (n_cos * sub)) * (2 * math.pi / (n_phi * sub)) * n
    keep = expected >= 5  # pool the sparse cells (standard chi-square practice)
    obs = torch.cat([observed[keep], observed[~keep].sum().reshape(1)])
    exp = torch.cat([expected[keep], expected[~keep].sum().reshape(1)])
    stat = float(((obs - exp) ** 2 / exp.clamp(min=1e-9)).sum())
    dof = int(keep.sum())
    p_value = chi2.sf(stat, dof)
    assert p_value > 1e-3, f"chi2={stat:.1f} dof={dof} p={p_value:.2e}"


@pytest.mark.parametrize("name,kind,roughness", CASES)
def test_reciprocity(name, kind, roughness):
    table = _table(kind, roughness)
    g = torch.Generator().manual_seed(2)
    n = 2000
    a = cosine_hemisphere(torch.rand(n, 2, generator=g))
    b = cosine_hemisphere(torch.rand(n, 2, generator=g))
    _, normal, mid, albedo = _setup(n, 0.0)
    f_ab = table.eval(mid, albedo, normal, a, b) / b[:, 2:3]
    f_ba = table.eval(mid, albedo, normal, b, a) / a[:, 2:3]
    torch.testing.assert_close(f_ab, f_ba, rtol=2e-3, atol=1e-5)


@pytest.mark.parametrize("name,kind,roughness", CASES + [("conductor-smooth", MaterialKind.CONDUCTOR, 0.02)])
@pytest.mark.parametrize("wo_deg", [0.0, 45.0, 80.0])
def test_energy_at_most_one_for_white_albedo(name, kind, roughness, wo_deg):
    """Directional albedo E[f cos / pdf] <= 1 with albedo 1 (within 4 standard errors); 1 for diffuse."""
    table = _table(kind, roughness, albedo=(1.0, 1.0, 1.0))
    s = _sample(table, *_setup(100_000, wo_deg, albedo=(1.0, 1.0, 1.0)), seed=3)
    w = s.weight[:, 0].double()
    mean, se = float(w.mean()), float(w.std() / math.sqrt(w.numel()))
    assert mean <= 1.0 + 4 * se + 1e-4
    if kind == MaterialKind.DIFFUSE:
        assert mean == pytest.approx(1.0, abs=1e-5)
    if kind == MaterialKind.CONDUCTOR and roughness <= 0.02 and wo_deg < 50:
        assert mean > 0.97  # a near-mirror white metal loses almost nothing to masking


def test_plastic_reflects_fresnel_at_normal_incidence_when_base_is_black():
    """A smooth black plastic reflects F(0) = ((n-1)/(n+1))^2 = 0.04 for n = 1.5."""
    table = MaterialTable.single(MaterialKind.PLASTIC, albedo=(0, 0, 0), roughness=0.01, ior=1.5)
    s = _sample(table, *_setup(50_000, 0.0, albedo=(0.0, 0.0, 0.0)), seed=4)
    assert float(s.weight[:, 0].mean()) == pytest.approx(0.04, rel=0.03)
    assert float(fresnel_dielectric(torch.tensor([1.0]), torch.tensor([1.5]))) == pytest.approx(0.04, abs=1e-6)


def test_discrete_distribution_and_triangle_sampling():
    g = torch.Generator().manual_seed(5)
    dist = DiscreteDistribution(torch.tensor([1.0, 0.0, 3.0]))
    idx = dist.sample(torch.rand(100_000, generator=g))
    counts = torch.bincount(idx, minlength=3).double() / idx.numel()
    assert counts[1] == 0
    assert float(counts[2]) == pytest.approx(0.75, abs=0.01)
    bary = uniform_triangle(torch.rand(100_000, 2, generator=g))
    assert (bary >= 0).all() and torch.allclose(bary.sum(-1), torch.ones(100_000))
    assert torch.allclose(bary.mean(0), torch.full((3,), 1 / 3), atol=5e-3)  # centroid of uniform area samples
    with pytest.raises(ValueError):
        DiscreteDistribution(torch.zeros(3))


def test_mixed_batch_equals_single_material_batches():
    """One table, rows of every kind interleaved: each row matches a table holding only its material."""
    specs = [(MaterialKind.DIFFUSE, 0.1), (MaterialKind.CONDUCTOR, 0.3), (MaterialKind.PLASTIC, 0.2), (MaterialKind.EMISSIVE, 0.1)]
    table = MaterialTable([int(k) for k, _ in specs], [(0.7, 0.5, 0.3)] * 4, [r for _, r in specs], [1.5] * 4, [(0, 0, 0)] * 3 + [(1, 1, 1)])
    n = 4000
    g = torch.Generator().manual_seed(6)
    mid = torch.randint(0, 4, (n,), generator=g)
    wo, normal, _, albedo = _setup(n, 50.0)
    u_lobe, u_dir = torch.rand(n, generator=g), torch.rand(n, 2, generator=g)
    if _BACKEND["name"] == "numba":
        table = NumbaBSDF(table)
    s = table.sample(mid, albedo, normal, wo, u_lobe, u_dir)
    for k, (kind, rough) in enumerate(specs):
        sel = mid == k
        single = _table(kind, rough)
        zero = torch.zeros(int(sel.sum()), dtype=torch.int64)
        ref = single.sample(zero, albedo[sel], normal[sel], wo[sel], u_lobe[sel], u_dir[sel])
        torch.testing.assert_close(s.wi[sel], ref.wi)
        torch.testing.assert_close(s.weight[sel], ref.weight)
        torch.testing.assert_close(table.pdf(mid, albedo, normal, wo, s.wi)[sel], single.pdf(zero, albedo[sel], normal[sel], wo[sel], ref.wi))


@pytest.mark.parametrize("wo_deg", [5.0, 50.0, 85.0])
def test_numba_bsdf_equals_torch_for_the_same_uniforms(wo_deg):
    """Same material rows, directions and uniforms in -> same directions, weights and densities out."""
    specs = [(MaterialKind.DIFFUSE, 0.1), (MaterialKind.CONDUCTOR, 0.05), (MaterialKind.CONDUCTOR, 0.4), (MaterialKind.PLASTIC, 0.1),
             (MaterialKind.PLASTIC, 0.6), (MaterialKind.EMISSIVE, 0.1)]
    table = MaterialTable([int(k) for k, _ in specs], [(0.9, 0.5, 0.2)] * 6, [r for _, r in specs], [1.5, 1.5, 1.5, 1.3, 1.8, 1.5],
                          [(0, 0, 0)] * 5 + [(1, 1, 1)])
    n = 6000
    g = torch.Generator().manual_seed(11)
    mid = torch.randint(0, len(specs), (n,), generator=g)
    normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    # wo at wo_deg from the normal, about a random axis
    axis = torch.nn.functional.normalize(torch.linalg.cross(normal, torch.randn(n, 3, generator=g)), dim=-1)
    th = math.radians(wo_deg)
    wo = math.cos(th) * normal + math.sin(th) * axis
    albedo = torch.rand(n, 3, generator=g)
    u_lobe, u_dir = torch.rand(n, generator=g), torch.rand(n, 2, generator=g)
    ref = table.sample(mid, albedo, normal, wo, u_lobe, u_dir)
    got = NumbaBSDF(table).sample(mid, albedo, normal, wo, u_lobe, u_dir)
    assert (ref.pdf > 0).float().mean() > 0.5  # most samples are valid: the comparison means something
    torch.testing.assert_close(got.wi, ref.wi, rtol=1e-3, atol=2e-4)  # float64 vs float32 arithmetic: measured max 7e-5
    torch.testing.assert_close(got.pdf, ref.pdf, rtol=1e-3, atol=1e-5)
    torch.testing.assert_close(got.weight, ref.weight, rtol=1e-3, atol=1e-5)
    wi = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    f_ref, pdf_ref = table.eval_pdf(mid, albedo, normal, wo, wi)
    f_got, pdf_got = NumbaBSDF(table).eval_pdf(mid, albedo, normal, wo, wi)
    assert (pdf_ref > 0).float().mean() > 0.3
    torch.testing.assert_close(f_got, f_ref, rtol=1e-3, atol=1e-5)
    torch.testing.assert_close(pdf_got, pdf_ref, rtol=1e-3, atol=1e-5)
