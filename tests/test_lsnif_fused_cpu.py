"""Fused LSNIF inference on the CPU (`lsnif_fused_cpu`): the same answers as featurize -> encode -> MLP."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.geometry.procedural import statue
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel, point_local_distances
from neuralrt.methods.lsnif_features import featurize_rays_numba
from neuralrt.methods import lsnif_fused_cpu as fused
from neuralrt.methods.lsnif_fused_cpu import fused_network_outputs_cpu
from neuralrt.rays import Rays
from neuralrt.training.ray_distribution import BoxRayDistribution

PRECISION = {"fp32": torch.float32, "bf16": torch.bfloat16}


@pytest.fixture(scope="module")
def figure():
    """A non-convex mesh (arms, legs, a pedestal): rays cross several occupied stretches."""
    return statue(0)


def _model(mesh, precision: str, max_points: int = 8, **features) -> LSNIFModel:
    config = LSNIFConfig.preset(
        "hq", voxel={"resolution": 16}, encoding={"resolutions": (16, 32), "log2_table_size": 12},
        network={"hidden_width": 32}, features={"max_points": max_points, **features},
        inference={"compute_precision": precision},
    )  # fmt: skip
    model = LSNIFModel.from_mesh(mesh, config)
    with torch.no_grad():  # an untrained table is ~0: give the features weight, so a wrong read shows
        model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(3))
    return model


def _unfused(model: LSNIFModel, rays: Rays):
    model._network_answers = model._network_answers_unfused  # the instance attribute wins over the method
    try:
        return model.intersect(rays)
    finally:
        del model._network_answers


def _mixed_rays(model: LSNIFModel, n: int, seed: int) -> Rays:
    """Rays from a sphere around the box aimed into it, and rays starting anywhere inside the box
    (in occupied voxels too: origin points), in every direction."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = model.box.lo, model.box.hi
    centre, radius = (lo + hi) / 2, (hi - lo).norm()
    outside = centre + torch.nn.functional.normalize(torch.randn(n // 2, 3, generator=g), dim=1) * radius
    targets = lo + torch.rand(n // 2, 3, generator=g) * (hi - lo)
    inside = lo + torch.rand(n - n // 2, 3, generator=g) * (hi - lo)
    origins = torch.cat([outside, inside])
    directions = torch.cat([targets - outside, torch.randn(n - n // 2, 3, generator=g)])
    return Rays(origins=origins, directions=directions)


@pytest.mark.parametrize(
    "precision,max_points,point_distances,origin_point",
    [("fp32", 8, True, True), ("fp32", 3, False, False), ("bf16", 8, True, True)],
)
def test_fused_outputs_match_featurize_encode_mlp(figure, precision, max_points, point_distances, origin_point):
    model = _model(figure, precision, max_points, point_distances=point_distances, origin_point=origin_point)
    unit = model._unit_rays(_mixed_rays(model, 600, seed=1))
    o, d = unit.origins, unit.directions
    dtype = PRECISION[precision]
    with torch.no_grad():
        fp = featurize_rays_numba(o, d, model.occupancy, max_points, origin_point=origin_point)
        x = model.encoder(fp.points, fp.face_axis)
        if point_distances:
            x = torch.cat([x, point_local_distances(fp, o, d)], dim=1)
        reference = model.network(x, dtype)
        fused = fused_network_outputs_cpu(o, d, model.occupancy, model.encoder, model.network, max_points=max_points,
                                          origin_point=origin_point, point_distances=point_distances, compute_dtype=dtype)  # fmt: skip
    active = fp.count > 0
    assert 100 < active.sum() < len(active) - 100 and fp.truncated.sum() > 10  # misses, hits and truncation all occur
    assert torch.equal(fused.count, fp.count)
    assert torch.equal(fused.t_enter, fp.t_enter) and torch.equal(fused.t_exit, fp.t_exit)
    assert torch.equal(fused.active, torch.nonzero(active).squeeze(1))
    # fp32: only the summation order of the first layer differs; bf16: fp32 accumulation here, a bf16 GEMM there
    tol = 1e-5 if precision == "fp32" else 3e-2
    scale = reference[active].abs().max()
    assert (fused.values - reference[active]).abs().max() <= tol * scale


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_model_answers_match_the_unfused_path(figure, precision):
    """Outside and surface rays of the training distribution: hits equal except rays whose
    occlusion logit sits at the threshold; t and normals within the precision's tolerance."""
    model = _model(figure, precision)
    exact = MeshBLAS(figure)
    batch = BoxRayDistribution(exact, model.box, seed=5, pool_size=4096).sample(4000)
    rays = batch.rays
    assert batch.from_surface.any() and (~batch.from_surface).any()
    fused = model.intersect(rays)  # the CPU default: the fused kernel
    unfused = _unfused(model, rays)
    with torch.no_grad():
        prep = model._prepare(rays)
        logits = torch.zeros(len(rays))
        logits[prep.active] = model._raw_outputs(prep, PRECISION[precision])[:, 0]
    differ = fused.hit != unfused.hit
    near_threshold = logits.abs() < (1e-4 if precision == "fp32" else 5e-2)
    assert not (differ & ~near_threshold).any()
    assert differ.sum() <= max(2, 0.002 * len(rays))  # counted: a tiny fraction
    both = fused.hit & unfused.hit
    for subset in (batch.from_surface, ~batch.from_surface):
        assert (both & subset).sum() > 40
    diagonal = float(model.box.diagonal)
    t_tol, n_tol = (1e-5, 1e-4) if precision == "fp32" else (2e-2, 5e-2)
    assert ((fused.t[both] - unfused.t[both]).abs() / diagonal).max() <= t_tol
    assert (fused.normal[both] - unfused.normal[both]).norm(dim=1).max() <= n_tol
    assert torch.isinf(fused.t[~fused.hit]).all()


def test_rays_crossing_no_occupied_voxel_never_reach_the_network(figure):
    model = _model(figure, "fp32")
    rays = _mixed_rays(model, 400, seed=9)
    # and rays that pass beside the box, parallel to an axis
    beside = Rays(origins=model.box.hi + torch.tensor([[0.5, 0.5, 0.0]]).expand(50, 3).clone() * float(model.box.diagonal),
                  directions=torch.tensor([[0.0, 0.0, -1.0]]).expand(50, 3).clone())  # fmt: skip
    rays = Rays(origins=torch.cat([rays.origins, beside.origins]), directions=torch.cat([rays.directions, beside.directions]))
    rows = []
    hook = model.network.output.register_forward_hook(lambda module, inputs, output: rows.append(len(inputs[0])))
    try:
        hits = model.intersect(rays)
        miss_only = model.intersect(beside)
    finally:
        hook.remove()
    unit = model._unit_rays(rays)
    count = featurize_rays_numba(unit.origins, unit.directions, model.occupancy, 8).count
    crossing = torch.zeros(len(rays), dtype=torch.bool)
    crossing[unit.index] = count > 0
    assert 0 < crossing.sum() < len(rays) - 60
    assert rows[0] == int(crossing.sum())  # only rays with points reached the GEMMs
    assert rows[1:] in ([], [0])  # a batch that crosses nothing: no network rows at all
    assert not hits.hit[~crossing].any() and not miss_only.hit.any()


def test_fp32_answers_do_not_depend_on_the_thread_split(figure):
    """Rays are split into chunks per thread and walked in groups: answers must not change."""
    import numba

    model = _model(figure, "fp32")
    rays = _mixed_rays(model, 301, seed=11)  # not a multiple of any group size
    unit = model._unit_rays(rays)
    args = (unit.origins, unit.directions, model.occupancy, model.encoder, model.network)
    threads = numba.get_num_threads()
    with torch.no_grad():
        whole = fused_network_outputs_cpu(*args, max_points=8)
        numba.set_num_threads(1)
        try:
            single = fused_network_outputs_cpu(*args, max_points=8)
            part = fused_network_outputs_cpu(unit.origins[7:], unit.directions[7:], *args[2:], max_points=8)
        finally:
            numba.set_num_threads(threads)
    assert torch.equal(whole.values, single.values) and torch.equal(whole.count, single.count)
    keep = whole.active >= 7
    torch.testing.assert_close(part.values, whole.values[keep], atol=1e-6, rtol=1e-6)  # GEMMs of another size
    assert np.array_equal(part.active.numpy() + 7, whole.active[keep].numpy())


def test_face_point_hashing_equals_the_encoders():
    """The branch-free face-point path reads the same table rows with the same weights as the encoder's."""
    import numba

    from neuralrt.methods.lsnif_fused_cpu import _face_point_level
    from neuralrt.neural.sparse_hash_grid import _point_level

    @numba.njit
    def both(points, codes, res, mask, base):
        out = np.zeros((len(codes), 2, 8), np.int64)
        w = np.zeros((len(codes), 2, 8), np.float32)
        for i in range(len(codes)):
            p = points[i]
            _point_level(p[0], p[1], p[2], codes[i], res, mask, base, out[i, 0], w[i, 0])
            _face_point_level(p[0], p[1], p[2], codes[i], res, mask, base, out[i, 1], w[i, 1])
        return out, w

    rng = np.random.default_rng(2)
    points = rng.random((3000, 3)).astype(np.float32)
    codes = rng.integers(0, 3, 3000).astype(np.int8)
    points[np.arange(3000), codes] = rng.integers(0, 33, 3000) / np.float32(32)  # on a voxel face plane
    points[:10] = [0.0, 1.0, 1.0]  # box corners: clamped at both ends
    slots, weights = both(points, codes, 64, 4095, 4096)
    assert np.array_equal(slots[:, 0], slots[:, 1]) and np.array_equal(weights[:, 0], weights[:, 1])
    assert len(np.unique(slots[:, 0, :4])) > 2000


def test_hidden_buffer_is_reused_per_thread_and_large_ones_are_not_kept():
    from neuralrt.methods import lsnif_fused_cpu as fused

    a = fused._hidden_buffer(100, 16, np.uint16)
    b = fused._hidden_buffer(50, 16, np.uint16)
    assert b.base is a.base or np.shares_memory(a, b)  # the same memory, no new pages to fault in
    big = fused._hidden_buffer(fused._KEPT_BYTES // 16 + 1, 4, np.float32)
    again = fused._hidden_buffer(10, 4, np.float32)
    assert big.shape == (fused._KEPT_BYTES // 16 + 1, 4) and not np.shares_memory(big, again)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_rest_of_network_is_the_mlps_layers_bit_for_bit_and_its_result_outlives_the_buffers(figure, precision):
    network, dtype = _model(figure, precision).network, PRECISION[precision]
    g = torch.Generator().manual_seed(5)
    x = torch.randn(300, network.hidden[0].in_features, generator=g)
    with torch.no_grad():
        w, b = (network.hidden[0].weight, network.hidden[0].bias) if dtype == torch.float32 else network._cast_weights(dtype)[0]
        first = torch.nn.functional.leaky_relu(torch.nn.functional.linear(x.to(dtype), w, b), network.slope)
        active = torch.arange(0, 300, 3)
        values = fused.rest_of_network(network, first, active, dtype)
        assert torch.equal(values, network(x[active], dtype))
        kept = values.clone()
        fused.rest_of_network(network, -first, torch.arange(300), dtype)  # reuses the per-thread buffers
    assert torch.equal(values, kept)


@pytest.mark.parametrize("width", [64, 128])
def test_bf16_dot_first_layer_matches_the_fp32_first_layer_and_the_unfused_path(figure, width, monkeypatch):
    """The bf16 first layer (`dot_rows_bf16`: 64-column passes; hq and lq widths) against the
    fp32 per-ray one and the unfused bf16 GEMMs: outputs within bf16 rounding of the inputs and
    weights, hits flip only where the occlusion logit is within that of the threshold."""
    config = LSNIFConfig.preset(
        "hq", voxel={"resolution": 16}, encoding={"resolutions": (16, 32), "log2_table_size": 12},
        network={"hidden_width": width}, features={"max_points": 9}, inference={"compute_precision": "bf16"},
    )  # fmt: skip
    model = LSNIFModel.from_mesh(figure, config)
    with torch.no_grad():
        model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(3))
    unit = model._unit_rays(_mixed_rays(model, 800, seed=11))

    def outputs(pairs: bool):
        monkeypatch.setattr(fused, "BF16_DOT_FIRST_LAYER", pairs)
        return fused_network_outputs_cpu(unit.origins, unit.directions, model.occupancy, model.encoder, model.network,
                                         max_points=9, compute_dtype=torch.bfloat16)  # fmt: skip

    dot, per_ray = outputs(True), outputs(False)
    assert torch.equal(dot.active, per_ray.active) and len(dot.active) > 200
    scale = per_ray.values.abs().max()
    assert not torch.equal(dot.values, per_ray.values)  # the two paths are both run
    assert (dot.values - per_ray.values).abs().max() <= 3e-2 * scale
    monkeypatch.setattr(fused, "BF16_DOT_FIRST_LAYER", True)
    rays = BoxRayDistribution(MeshBLAS(figure), model.box, seed=5, pool_size=4096).sample(4000).rays
    hits, unfused = model.intersect(rays), _unfused(model, rays)
    with torch.no_grad():
        prep = model._prepare(rays)
        logits = torch.zeros(len(rays))
        logits[prep.active] = model._raw_outputs(prep, torch.bfloat16)[:, 0]
    differ = hits.hit != unfused.hit
    assert not (differ & ~(logits.abs() < 5e-2)).any()
    assert differ.sum() <= max(2, 0.002 * len(rays))
    both = hits.hit & unfused.hit
    assert both.sum() > 100
    assert ((hits.t[both] - unfused.t[both]).abs() / float(model.box.diagonal)).max() <= 2e-2
