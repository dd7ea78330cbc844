"""Fused LSNIF inference on the CPU (`lsnif_fused_cpu`): the same answers as featurize -> encode -> MLP."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralrt.accel.mesh_blas import MeshBLAS
from neuralrt.geometry.procedural import statue
from neuralrt.methods.lsnif import LSNIFConfig, LSNIFModel, point_local_distances
from neuralrt.methods.lsnif_features import featurize_rays_numba
from neuralrt.methods import lsnif_fused_cpu as fused
from neuralrt.methods.lsnif_fused_cpu import fused_network_outputs_cpu
from neuralrt.neural.sparse_hash_grid import HALF_READS
from neuralrt.rays import Rays
from neuralrt.training.ray_distribution import BoxRayDistribution

PRECISION = {"fp32": torch.float32, "bf16": torch.bfloat16}


@pytest.fixture(scope="module")
def figure():
    """A non-convex mesh (arms, legs, a pedestal): rays cross several occupied stretches."""
    return statue(0)


def _model(mesh, precision: str, max_points: int = 8, hidden_width: int = 32, features_per_level: int = 3, **features) -> LSNIFModel:
    config = LSNIFConfig.preset(
        "hq", voxel={"resolution": 16},
        encoding={"resolutions": (16, 32), "log2_table_size": 12, "features_per_level": features_per_level},
        network={"hidden_width": hidden_width}, features={"max_points": max_points, **features},
        inference={"compute_precision": precision},
    )  # fmt: skip
    model = LSNIFModel.from_mesh(mesh, config)
    with torch.no_grad():  # an untrained table is ~0: give the features weight, so a wrong read shows
        model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(3))
    return model


def _unfused(model: LSNIFModel, rays: Rays):
    """featurize -> encode -> MLP, decoded by torch (not by `fused_hits_cpu`)."""
    model._network_answers = model._network_answers_unfused  # the instance attribute wins over the method
    write_hits, fused.WRITE_HITS = fused.WRITE_HITS, False
    try:
        return model.intersect(rays)
    finally:
        del model._network_answers
        fused.WRITE_HITS = write_hits


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
    "precision,max_points,point_distances,origin_point,features_per_level",
    # (4 features per entry: the pass's scalar reads, not its 3-feature vector reads)
    [("fp32", 8, True, True, 3), ("fp32", 3, False, False, 3), ("bf16", 8, True, True, 3), ("fp32", 8, True, True, 4)],
)
def test_fused_outputs_match_featurize_encode_mlp(figure, precision, max_points, point_distances, origin_point, features_per_level,
                                                 monkeypatch):  # fmt: skip
    model = _model(figure, precision, max_points, features_per_level=features_per_level, point_distances=point_distances,
                   origin_point=origin_point)  # fmt: skip
    unit = model._unit_rays(_mixed_rays(model, 600, seed=1))
    o, d = unit.origins, unit.directions
    dtype = PRECISION[precision]
    with torch.no_grad():
        fp = featurize_rays_numba(o, d, model.occupancy, max_points, origin_point=origin_point)
        x = model.encoder(fp.points, fp.face_axis)
        if point_distances:
            x = torch.cat([x, point_local_distances(fp, o, d)], dim=1)
        reference = model.network(x, dtype)
    active = fp.count > 0
    assert 100 < active.sum() < len(active) - 100 and fp.truncated.sum() > 10  # misses, hits and truncation all occur
    scale = reference[active].abs().max()
    for simd_walk in (True, False):
        monkeypatch.setattr(fused, "SIMD_WALK", simd_walk)
        with torch.no_grad():
            outputs = fused_network_outputs_cpu(o, d, model.occupancy, model.encoder, model.network, max_points=max_points,
                                                origin_point=origin_point, point_distances=point_distances, compute_dtype=dtype)  # fmt: skip
        assert torch.equal(outputs.count, fp.count)
        assert torch.equal(outputs.t_enter, fp.t_enter) and torch.equal(outputs.t_exit, fp.t_exit)
        assert torch.equal(outputs.active, torch.nonzero(active).squeeze(1))
        # fp32: the summation order of the first layer differs (walk_ray: the same points), and the
        # 16-lane walk's points differ by their float32 rounding; bf16: fp32 accumulation here, a bf16 GEMM there
        tol = (3e-5 if simd_walk else 1e-6) if precision == "fp32" else 3e-2
        assert (outputs.values - reference[active]).abs().max() <= tol * scale


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


@pytest.mark.parametrize("write_hits", [True, False])
def test_rays_crossing_no_occupied_voxel_never_reach_the_network(figure, write_hits, monkeypatch):
    monkeypatch.setattr(fused, "WRITE_HITS", write_hits)
    model = _model(figure, "fp32")
    rays = _mixed_rays(model, 400, seed=9)
    # and rays that pass beside the box, parallel to an axis
    beside = Rays(origins=model.box.hi + torch.tensor([[0.5, 0.5, 0.0]]).expand(50, 3).clone() * float(model.box.diagonal),
                  directions=torch.tensor([[0.0, 0.0, -1.0]]).expand(50, 3).clone())  # fmt: skip
    rays = Rays(origins=torch.cat([rays.origins, beside.origins]), directions=torch.cat([rays.directions, beside.directions]))
    rows = []  # rows reaching the GEMMs after the first layer (both decodings run them)
    layers = fused.hidden_layers
    monkeypatch.setattr(fused, "hidden_layers", lambda network, hidden, active, *args: rows.append(len(active)) or layers(network, hidden, active, *args))
    hits = model.intersect(rays)
    crossing_rows, rows[:] = sum(rows), []  # (the threaded pipeline: one call per part)
    miss_only = model.intersect(beside)
    unit = model._unit_rays(rays)
    count = featurize_rays_numba(unit.origins, unit.directions, model.occupancy, 8).count
    crossing = torch.zeros(len(rays), dtype=torch.bool)
    crossing[unit.index] = count > 0
    assert 0 < crossing.sum() < len(rays) - 60
    assert crossing_rows == int(crossing.sum())  # only rays with points reached the GEMMs
    assert sum(rows) == 0  # a batch that crosses nothing: no network rows at all
    assert not hits.hit[~crossing].any() and not miss_only.hit.any()


def test_fp32_answers_do_not_depend_on_the_thread_split(figure):
    """Rays are split into chunks per thread and walked in groups, two groups in flight per chunk:
    answers must not change."""
    import numba

    from neuralrt.methods.lsnif_fused_cpu import _CHUNKS_PER_THREAD, _GROUP

    model = _model(figure, "fp32")
    # Not a multiple of any group size; with all threads or one, each chunk holds several groups.
    rays = _mixed_rays(model, 2 * _CHUNKS_PER_THREAD * numba.get_num_threads() * _GROUP + 301, seed=11)
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


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_simd_walk_and_walk_ray_give_the_same_points_to_float32_rounding(figure, precision, monkeypatch):
    """The pass with the 16-lane float32 walk (points unordered) and with `walk_ray` per ray (points
    in ray order, float64): the same rays reach the network with the same counts and intervals, and
    their inputs differ only by the float32 rounding of the points' coordinates (`lsnif_walk_simd`),
    so the outputs agree to ~1e-5 (both walks run on any CPU: without AVX-512, LLVM lowers the
    vector code to scalar loops)."""
    model = _model(figure, precision, origin_point=True)
    unit = model._unit_rays(_mixed_rays(model, 1500, seed=5))
    args = (unit.origins, unit.directions, model.occupancy, model.encoder, model.network)
    outputs = {}
    for simd in (True, False):
        monkeypatch.setattr(fused, "SIMD_WALK", simd)
        with torch.no_grad():
            outputs[simd] = fused_network_outputs_cpu(*args, max_points=8, compute_dtype=PRECISION[precision])
    for name in ("active", "count", "t_enter", "t_exit"):
        assert torch.equal(getattr(outputs[True], name), getattr(outputs[False], name)), name
    values, reference = outputs[True].values, outputs[False].values
    scale = float(reference.abs().max())
    assert (values - reference).abs().max() <= (1e-4 if precision == "fp32" else 2e-2) * scale
    assert outputs[True].active.numel() > 100


def test_grids_whose_size_is_not_a_power_of_two_keep_walk_ray(figure, monkeypatch):
    """V = 12: the planes k / V are not exact in float32, so the pass walks with `walk_ray` whatever
    `SIMD_WALK` says (the same bits either way)."""
    config = LSNIFConfig.preset("hq", voxel={"resolution": 12}, encoding={"resolutions": (24, 36), "log2_table_size": 12},
                                network={"hidden_width": 32}, features={"max_points": 8})  # fmt: skip
    model = LSNIFModel.from_mesh(figure, config)
    with torch.no_grad():
        model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(3))
    unit = model._unit_rays(_mixed_rays(model, 1500, seed=6))
    outputs = {}
    for simd in (True, False):
        monkeypatch.setattr(fused, "SIMD_WALK", simd)
        with torch.no_grad():
            outputs[simd] = fused_network_outputs_cpu(unit.origins, unit.directions, model.occupancy, model.encoder, model.network,
                                                      max_points=8)  # fmt: skip
    assert outputs[True].active.numel() > 100
    for name in ("active", "values", "count", "t_enter", "t_exit"):
        assert torch.equal(getattr(outputs[True], name), getattr(outputs[False], name)), name


def test_face_point_hashing_equals_the_encoders():
    """The branch-free face-point path (`face_rows`, which the fused pass runs as SIMD code over a
    group's points) reads the same table rows with the same weights as the encoder's."""
    import numba

    from neuralrt.neural.sparse_hash_grid import _point_level
    from neuralrt.neural.sparse_hash_grid import face_point_level as _face_point_level

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


def test_vector_input_rounding_equals_the_scalar_pairs_and_zeroes_stale_inputs():
    """`_inputs_bf16` (16 inputs per instruction, the first layer's pairs in the pass) writes the
    bits of `_input_pairs` (scalar, the GEMM's inputs) for every input count, and zeros up to
    ``n_out`` however stale the row past the ray's inputs is."""
    import numba

    @numba.njit
    def both(xs, counts, n_out):
        vector = np.full((len(counts), xs.shape[1] // 2), 0xFFFFFFFF, np.uint32)  # stale bits to overwrite
        scalar = np.zeros((len(counts), n_out // 2), np.uint32)
        for r in range(len(counts)):
            fused._inputs_bf16(xs[r], counts[r], n_out, vector[r].view(np.uint16))
            fused._input_pairs(xs[r], counts[r], scalar[r])
        return vector, scalar

    rng = np.random.default_rng(3)
    xs = (rng.standard_normal((200, 128)) * 10.0 ** rng.integers(-5, 5, (200, 128))).astype(np.float32)
    xs[:, 0] = 1.00390625  # a tie: rounds to even
    counts = np.concatenate([np.arange(0, 97), rng.integers(0, 97, 103)]).astype(np.int64)
    vector, scalar = both(xs, counts, 96)
    assert np.array_equal(vector[:, :48], scalar)
    assert np.all(vector[:, 48:] == 0xFFFFFFFF)  # nothing written past n_out
    assert np.all(vector[0, :48] == 0) and vector[95, 47] >> 16 == 0 and vector[94, 47] == 0  # zeros past the inputs


@pytest.mark.parametrize("precision,simd_walk", [("fp32", True), ("bf16", True), ("bf16", False)])
def test_the_pass_maps_rays_into_the_unit_box_as_unit_box_rays(figure, precision, simd_walk, monkeypatch):
    """The fused pass maps object-space rays into the unit box itself: for every valid ray the
    same counts, intervals, t_min shift and first hidden layer, bit for bit, as the pass on
    `unit_box_rays`' rays; invalid rays (NaN, zero direction, t_min >= t_max) get no points.
    With either walk (both run on any CPU; the default is the 8-lane one where numba targets AVX-512)."""
    monkeypatch.setattr(fused, "SIMD_WALK", simd_walk)
    model = _model(figure, precision)
    rays = _mixed_rays(model, 2000, seed=4)
    g = torch.Generator().manual_seed(5)
    t_min = torch.where(torch.rand(2000, generator=g) < 0.3, torch.rand(2000, generator=g), torch.zeros(2000))
    t_min[:10] = float("inf")  # an infinite t_min: no shift, and t_min >= t_max
    t_max = torch.where(torch.rand(2000, generator=g) < 0.2, torch.rand(2000, generator=g) * 0.5, torch.full((2000,), float("inf")))
    origins, directions = rays.origins.clone(), rays.directions.clone()
    origins[10:20, 2] = float("nan")
    directions[20:30] = 0.0
    rays = Rays(origins=origins, directions=directions, t_min=t_min, t_max=t_max)
    fc = model.config.features
    p = fused._prepare_pass(model.occupancy, model.encoder, model.network, max_points=fc.max_points, origin_point=fc.origin_point,
                            share_boundary_points=fc.share_boundary_points, point_distances=fc.point_distances,
                            compute_dtype=model.compute_dtype())  # fmt: skip
    world = fused._first_hidden_layer(p, fused._rays_numpy(rays.origins, rays.directions, fc.max_points, rays.t_min, rays.t_max,
                                                           model.box_lo, model.box_extent))  # fmt: skip
    hidden, counts, t_enter, t_exit, t_offset = (x.copy() if isinstance(x, np.ndarray) else x.clone() for x in world)
    unit = model._unit_rays(rays)
    u_hidden, u_counts, u_enter, u_exit, _ = fused._first_hidden_layer(p, fused._rays_numpy(unit.origins, unit.directions, fc.max_points))
    valid = unit.index.numpy()
    invalid = np.setdiff1d(np.arange(2000), valid)
    assert len(invalid) >= 30 and (t_min[valid] < t_max[valid]).all()
    assert np.array_equal(counts[valid], u_counts) and not counts[invalid].any()
    assert np.array_equal(t_enter[valid], u_enter) and np.array_equal(t_exit[valid], u_exit)
    assert np.array_equal(t_offset[valid], unit.t_offset.numpy()) and (t_offset > 0).sum() > 300
    rows = u_counts > 0
    assert rows.sum() > 500 and torch.equal(hidden[valid[rows]], u_hidden[torch.from_numpy(np.flatnonzero(rows))])


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


@pytest.mark.parametrize("first_layer", ["pass", "gemm"])
@pytest.mark.parametrize("width", [64, 128])
def test_bf16_first_layer_matches_the_fp32_first_layer_and_the_unfused_path(figure, width, first_layer, monkeypatch):
    """The bf16 first layer -- in the pass (`dot_rows_bf16`: 64-column passes; hq and lq widths)
    or as torch's GEMM on the inputs the pass writes (`FIRST_LAYER_IN_PASS` False, the default on
    AMX) -- against the fp32 per-ray one and the unfused bf16 GEMMs: outputs within bf16 rounding
    of the inputs and weights, hits flip only where the occlusion logit is within that of the
    threshold."""
    monkeypatch.setattr(fused, "FIRST_LAYER_IN_PASS", first_layer == "pass")
    config = LSNIFConfig.preset(
        "hq", voxel={"resolution": 16}, encoding={"resolutions": (16, 32), "log2_table_size": 12},
        network={"hidden_width": width}, features={"max_points": 9}, inference={"compute_precision": "bf16"},
    )  # fmt: skip
    model = LSNIFModel.from_mesh(figure, config)
    with torch.no_grad():
        model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(3))
    unit = model._unit_rays(_mixed_rays(model, 800, seed=11))

    def outputs(bf16_first_layer: bool):
        monkeypatch.setattr(fused, "BF16_DOT_FIRST_LAYER", bf16_first_layer)
        return fused_network_outputs_cpu(unit.origins, unit.directions, model.occupancy, model.encoder, model.network,
                                         max_points=9, compute_dtype=torch.bfloat16)  # fmt: skip

    calls = []  # the first layer's GEMM: called on the network rays alone, or not at all
    gemm = fused.first_layer_gemm
    monkeypatch.setattr(fused, "first_layer_gemm", lambda *args: calls.append(1) or gemm(*args))
    dot, per_ray = outputs(True), outputs(False)
    assert len(calls) == (first_layer == "gemm")
    assert torch.equal(dot.active, per_ray.active) and len(dot.active) > 200
    scale = per_ray.values.abs().max()
    assert not torch.equal(dot.values, per_ray.values)  # the two paths are both run
    assert (dot.values - per_ray.values).abs().max() <= 3e-2 * scale
    monkeypatch.setattr(fused, "BF16_DOT_FIRST_LAYER", True)
    monkeypatch.setattr(fused, "FIRST_LAYER_IN_PASS", first_layer == "pass")
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


@pytest.fixture(scope="module")
def trained_cornell():
    """A small model trained briefly on a mesh with 4 materials (argmax over material logits)."""
    from neuralrt.geometry.procedural import cornell_box
    from neuralrt.training.api import train

    config = LSNIFConfig.preset(
        "hq", voxel={"resolution": 16}, encoding={"resolutions": (16, 32), "log2_table_size": 12},
        network={"hidden_width": 32}, features={"max_points": 8},
    ).with_training(steps=100, batch_size=2048, seed=0, lr_decay_final=1.0)  # fmt: skip
    model = train(cornell_box(), config, progress=False)
    assert model.num_materials == 4
    return model


def _decoding_rays(model: LSNIFModel, n: int, seed: int) -> Rays:
    """`_mixed_rays` with ray intervals that cut hits off (t_max short, t_min long), and rays with
    NaN origins and zero directions."""
    rays = _mixed_rays(model, n, seed)
    g = torch.Generator().manual_seed(seed + 1)
    t_max = torch.where(torch.rand(n, generator=g) < 0.2, torch.rand(n, generator=g) * 2, torch.full((n,), float("inf")))
    t_min = torch.where(torch.rand(n, generator=g) < 0.2, torch.rand(n, generator=g) * 0.5, torch.zeros(n))
    origins, directions = rays.origins.clone(), rays.directions.clone()
    origins[:20, 1] = float("nan")
    directions[20:40] = 0.0
    return Rays(origins=origins, directions=directions, t_min=t_min, t_max=t_max)


def _hits_with(model, rays, monkeypatch, **flags):
    for name, value in flags.items():
        monkeypatch.setattr(fused, name, value)
    return model.intersect(rays), model.occluded(rays)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_numba_decoding_matches_the_torch_decoding(trained_cornell, precision, monkeypatch):
    """`fused_hits_cpu` (numba decoding, with the output layer in torch or in the decoding pass)
    against `_intersect_chunk`'s torch decoding of `fused_network_outputs_cpu`'s outputs.
    From the same raw outputs: hits, normals and materials bit-equal, t and albedo within the
    sigmoid's 3 ulp (libm exp here, torch's vectorised exp there). With the output layer in numba
    (another summation order): hits and materials equal except where the deciding logits are
    within 1e-4 of each other, t, normals and albedo within 1e-5."""
    model, dtype = trained_cornell, PRECISION[precision]
    monkeypatch.setattr(model, "compute_dtype", lambda training=False: dtype)
    rays = _decoding_rays(model, 6000, seed=21)
    reference, reference_occluded = _hits_with(model, rays, monkeypatch, WRITE_HITS=False)
    assert torch.equal(reference_occluded, reference.hit)  # the base class's occluded: intersect's hits
    with torch.no_grad():
        act, raw, t_enter, t_exit, t_offset = model._network_answers_fused_cpu(rays)
    logit = torch.full((len(rays),), float("inf"))
    logit[act] = raw[:, 0] - math.log(model.config.inference.occlusion_threshold / (1 - model.config.inference.occlusion_threshold))
    t_raw = torch.full((len(rays),), float("inf"))
    t_raw[act] = t_offset + t_enter + torch.sigmoid(raw[:, 1]) * (t_exit - t_enter)
    top2 = torch.full((len(rays),), float("inf"))
    top2[act] = raw[:, 8:].topk(2, dim=1).values.diff(dim=1).abs().squeeze(1)
    # misses of every kind occur: no occupied voxel, NaN/zero rays, cut off by the interval, predicted misses
    cut = (logit > 0) & ((t_raw >= rays.t_max) | (t_raw <= rays.t_min))
    assert len(act) < len(rays) - 500 and cut.sum() > 50 and ((logit < 0) & torch.isfinite(logit)).sum() > 50
    assert reference.hit.sum() > 500 and len(reference.material_id[reference.hit].unique()) >= 3
    scale = float(rays.t_max[torch.isfinite(rays.t_max)].max())
    near_limit = ((t_raw - rays.t_max).abs() <= 1e-5 * scale) | ((t_raw - rays.t_min).abs() <= 1e-5 * scale)
    for output_layer_in_decode in (False, True):
        # (the hidden layers stay torch's here: `test_hidden_layers_in_the_decoding_pass_...` checks them)
        hits, occluded = _hits_with(model, rays, monkeypatch, WRITE_HITS=True, OUTPUT_LAYER_IN_DECODE=output_layer_in_decode,
                                    HIDDEN_LAYERS_IN_DECODE=False)
        assert torch.equal(occluded, hits.hit)  # the decision alone: the same as intersect's
        differ = hits.hit != reference.hit
        if output_layer_in_decode:
            assert not (differ & ~(near_limit | (logit.abs() < 1e-4))).any()
        else:
            assert not (differ & ~near_limit).any()
        assert differ.sum() <= 2
        both = hits.hit & reference.hit
        miss = ~hits.hit
        assert torch.isinf(hits.t[miss]).all() and (hits.material_id[miss] == -1).all()
        assert (hits.normal[miss] == 0).all() and (hits.geometric_normal[miss] == 0).all() and (hits.albedo[miss] == 1).all()
        assert (hits.primitive_id == -1).all() and (hits.uv == 0).all()
        assert torch.equal(hits.normal, hits.geometric_normal)
        if output_layer_in_decode:
            t_tol, tol = 1e-5 * scale, 1e-5
            tie = top2 < 1e-4
            assert torch.equal(hits.material_id[both & ~tie], reference.material_id[both & ~tie])
        else:
            t_tol, tol = 4 * 1.2e-7 * scale, 4 * 1.2e-7  # 3 ulp of the sigmoid, times the span
            assert torch.equal(hits.material_id[both], reference.material_id[both])
            assert torch.equal(hits.normal[both], reference.normal[both])
        assert (hits.t[both] - reference.t[both]).abs().max() <= t_tol
        assert (hits.normal[both] - reference.normal[both]).abs().max() <= tol
        assert (hits.albedo[both] - reference.albedo[both]).abs().max() <= tol


def _bf16_model(width: int, layers: int) -> LSNIFModel:
    """A small untrained bf16 model on statue(0) with random table values and biases, whose
    network rays both hit and miss."""
    from neuralrt.geometry.procedural import statue

    config = LSNIFConfig.preset(
        "hq", voxel={"resolution": 16}, encoding={"resolutions": (16, 32), "log2_table_size": 12},
        network={"hidden_width": width, "hidden_layers": layers}, features={"max_points": 8},
        inference={"compute_precision": "bf16"},
    )  # fmt: skip
    model = LSNIFModel.from_mesh(statue(0), config)
    with torch.no_grad():
        model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(3))
        for layer in model.network.hidden:  # biases start at zero: give them values, so a dropped one shows
            layer.bias.uniform_(-0.3, 0.3, generator=torch.Generator().manual_seed(4))
        model.network.output.bias[0] = 0.5  # network rays both hit and miss
    return model


@pytest.mark.parametrize("width, layers", [(32, 2), (64, 3), (128, 2)])
def test_hidden_layers_in_the_decoding_pass_match_torchs_gemms(width, layers, monkeypatch):
    """bf16, widths of 16s: the hidden layers after the first in the decoding pass (4 rays per
    weight pass) against torch's bf16 GEMMs: the same hits except where the occlusion logit is
    within bf16 rounding of the threshold, t, normals and albedo within it; torch's layers are
    not called."""
    model = _bf16_model(width, layers)
    rays = _decoding_rays(model, 5000, seed=31)
    monkeypatch.setattr(fused, "FIRST_LAYER_IN_PASS", True)  # (the pass's later layers start from its first)
    reference, reference_occluded = _hits_with(model, rays, monkeypatch, HIDDEN_LAYERS_IN_DECODE=False)
    with torch.no_grad():
        act, raw, *_ = model._network_answers_fused_cpu(rays)  # raw outputs through torch's layers
    monkeypatch.setattr(fused, "hidden_layers", lambda *args: pytest.fail("torch's hidden layers ran"))
    hits, occluded = _hits_with(model, rays, monkeypatch, HIDDEN_LAYERS_IN_DECODE=True)
    assert 300 < int(reference.hit.sum()) < len(rays) - 1000
    logit = torch.full((len(rays),), float("inf"))
    logit[act] = raw[:, 0]
    for got, ref in ((hits.hit, reference.hit), (occluded, reference_occluded)):
        differ = got != ref
        assert not (differ & ~(logit.abs() < 5e-2)).any()
        assert differ.sum() <= max(2, 0.002 * len(rays))
    both = hits.hit & reference.hit
    assert not torch.equal(hits.t[both], reference.t[both])  # both paths ran
    assert ((hits.t[both] - reference.t[both]).abs() / float(model.box.diagonal)).max() <= 1e-2
    assert (hits.normal[both] - reference.normal[both]).abs().max() <= 5e-2
    assert (hits.albedo[both] - reference.albedo[both]).abs().max() <= 2e-2


@pytest.mark.parametrize("width, layers", [(32, 2), (64, 3)])
def test_decoding_in_the_fused_pass_gives_the_decoding_passs_bits(width, layers, monkeypatch):
    """bf16, the later layers in numba: the fused pass decoding each group of rays after its first
    layer (`DECODE_IN_PASS`) writes the same records, bit for bit, as the decoding pass after it,
    for `intersect` and `occluded`, over several chunks (rows offset in the records) and groups;
    the decoding pass does not run."""
    model = _bf16_model(width, layers)
    rays = _decoding_rays(model, 5000, seed=33)
    monkeypatch.setattr(model.config.inference, "chunk_size", 1500)  # (chunks that end inside a group)
    monkeypatch.setattr(fused, "MIN_RAYS_PER_THREAD", 0)
    monkeypatch.setattr(fused, "FIRST_LAYER_IN_PASS", True)
    monkeypatch.setattr(fused, "HIDDEN_LAYERS_IN_DECODE", True)
    reference, reference_occluded = _hits_with(model, rays, monkeypatch, DECODE_IN_PASS=False)
    monkeypatch.setattr(fused, "_decode", lambda *args: pytest.fail("the decoding pass ran"))
    hits, occluded = _hits_with(model, rays, monkeypatch, DECODE_IN_PASS=True)
    assert 300 < int(reference.hit.sum()) < len(rays) - 1000
    assert torch.equal(occluded, reference_occluded) and torch.equal(occluded, hits.hit)
    for name in ("hit", "t", "normal", "geometric_normal", "albedo", "material_id", "uv", "primitive_id"):
        assert torch.equal(getattr(hits, name), getattr(reference, name)), name


@pytest.mark.parametrize("decode_in_pass", [True, False])
def test_the_pass_writes_every_record_whatever_the_records_held(decode_in_pass, monkeypatch):
    """`fused_hits_cpu` and `fused_occluded_cpu` write every row, misses included (so `intersect`
    and `occluded` allocate their records without a fill): records holding garbage on entry come
    out as records that held misses (`Hits.empty`), bit for bit, with the decoding in the fused
    pass or in the decoding pass after it, over several chunks."""
    from dataclasses import fields

    from neuralrt.rays import Hits

    model = _bf16_model(32, 2)
    rays = _decoding_rays(model, 3000, seed=41)
    monkeypatch.setattr(fused, "FIRST_LAYER_IN_PASS", True)
    monkeypatch.setattr(fused, "HIDDEN_LAYERS_IN_DECODE", True)
    monkeypatch.setattr(fused, "DECODE_IN_PASS", decode_in_pass)
    decoding_passes = []
    decode = fused._decode
    monkeypatch.setattr(fused, "_decode", lambda *args: decoding_passes.append(1) or decode(*args))
    args, kwargs = model._fused_cpu_arguments(rays)
    clean, garbage = Hits.empty(len(rays)), Hits.uninitialized(len(rays))
    for f in fields(garbage):
        column = getattr(garbage, f.name)
        column.copy_(torch.full_like(column, float("nan")) if column.dtype.is_floating_point else torch.ones_like(column) * 7)
    for hits in (clean, garbage):
        fused.fused_hits_cpu(*args, hits=hits, num_materials=model.num_materials, **kwargs)
    assert 300 < int(clean.hit.sum()) < len(rays) - 300
    assert bool(decoding_passes) == (not decode_in_pass)  # (the pass decoded, or the decoding pass after it)
    for f in fields(clean):
        assert torch.equal(getattr(garbage, f.name), getattr(clean, f.name)), f.name
    hit = torch.ones(len(rays), dtype=torch.bool)
    fused.fused_occluded_cpu(*args, hit=hit, **kwargs)
    assert torch.equal(hit, clean.hit)
    monkeypatch.setattr(model.config.inference, "chunk_size", 1024)  # `intersect`'s records over several chunks
    monkeypatch.setattr(fused, "MIN_RAYS_PER_THREAD", 0)
    empty = Hits.empty  # (`Hits.uninitialized` takes its shapes and dtypes from an empty one)
    monkeypatch.setattr(Hits, "empty", staticmethod(lambda n, device=None: empty(n, device) if n == 0 else pytest.fail("filled")))
    chunked = model.intersect(rays)
    for f in fields(clean):
        assert torch.equal(getattr(chunked, f.name), getattr(clean, f.name)), f.name


def test_occluded_makes_one_pass_per_chunk_and_answers_every_ray(trained_cornell, monkeypatch):
    """More rays than a chunk: `occluded` (the decision-only pass) gives intersect's hits for all."""
    model = trained_cornell
    rays = _decoding_rays(model, 3000, seed=23)
    monkeypatch.setattr(model.config.inference, "chunk_size", 1024)
    monkeypatch.setattr(fused, "MIN_RAYS_PER_THREAD", 0)
    calls = []
    original = fused.fused_occluded_cpu
    monkeypatch.setattr(fused, "fused_occluded_cpu", lambda *a, **k: calls.append(1) or original(*a, **k))
    occluded = model.occluded(rays)
    assert len(calls) == 3
    assert torch.equal(occluded, model.intersect(rays).hit) and occluded.sum() > 300


def test_a_cpu_chunk_holds_at_least_min_rays_per_thread(trained_cornell, monkeypatch):
    """The fused CPU pass takes `MIN_RAYS_PER_THREAD` rays per numba thread at a time (at most
    `MAX_RAYS_BY_THREADS`) where that is more than ``chunk_size`` (fewer parallel regions on many
    threads); the torch path and a larger ``chunk_size`` keep ``chunk_size``."""
    import numba

    model = trained_cornell
    cpu = torch.device("cpu")
    monkeypatch.setattr(model.config.inference, "chunk_size", 1024)
    monkeypatch.setattr(fused, "MIN_RAYS_PER_THREAD", 1536)
    chunk = model.rays_per_chunk(cpu)
    assert chunk == 1536 * numba.get_num_threads()
    calls = []
    original = fused.fused_occluded_cpu
    monkeypatch.setattr(fused, "fused_occluded_cpu", lambda *a, **k: calls.append(len(a[0])) or original(*a, **k))
    rays = _decoding_rays(model, 3000, seed=31)
    model.occluded(rays)
    assert calls == [min(chunk, 3000 - start) for start in range(0, 3000, chunk)]
    monkeypatch.setattr(fused, "MAX_RAYS_BY_THREADS", 2000)  # (the rule's cap)
    assert model.rays_per_chunk(cpu) == max(1024, min(1536 * numba.get_num_threads(), 2000))
    monkeypatch.setattr(model.config.inference, "chunk_size", 1 << 20)
    assert model.rays_per_chunk(cpu) == 1 << 20
    monkeypatch.setattr(fused, "WRITE_HITS", False)
    monkeypatch.setattr(model.config.inference, "chunk_size", 1024)
    assert model.rays_per_chunk(cpu) == 1024


def test_chunks_from_the_task_queue_answer_as_the_static_split(trained_cornell, monkeypatch):
    """The fused pass's chunks taken from the task queue (`DYNAMIC_CHUNKS`, the default) or one per
    prange iteration give the same records (`intersect`, `occluded`) and raw outputs."""
    from dataclasses import fields

    model = trained_cornell
    rays = _decoding_rays(model, 3000, seed=37)
    unit, fc = model._unit_rays(rays), model.config.features

    def raw_outputs():
        return fused.fused_network_outputs_cpu(unit.origins, unit.directions, model.occupancy, model.encoder, model.network,
                                               max_points=fc.max_points, compute_dtype=model.compute_dtype())  # fmt: skip

    reference, reference_occluded = _hits_with(model, rays, monkeypatch, DYNAMIC_CHUNKS=False)
    reference_raw = raw_outputs()
    hits, occluded = _hits_with(model, rays, monkeypatch, DYNAMIC_CHUNKS=True)
    raw = raw_outputs()
    assert reference.hit.sum() > 300 and torch.equal(occluded, reference_occluded)
    for f in fields(hits):
        assert torch.equal(getattr(hits, f.name), getattr(reference, f.name)), f.name
    assert len(raw.active) > 1000
    for f in fields(raw):
        assert torch.equal(getattr(raw, f.name), getattr(reference_raw, f.name)), f.name


@pytest.mark.parametrize("write_hits", [True, False])
def test_chunks_written_in_place_answer_as_one_chunk(trained_cornell, write_hits, monkeypatch):
    """More rays than a chunk: each chunk's records are written into the batch's rows in place (the
    fused pass) or copied there (the torch decoding); every field equals the one-chunk answer."""
    from dataclasses import fields

    model = trained_cornell
    monkeypatch.setattr(fused, "WRITE_HITS", write_hits)
    rays = _decoding_rays(model, 3000, seed=29)
    whole = model.intersect(rays)
    monkeypatch.setattr(model.config.inference, "chunk_size", 1024)
    monkeypatch.setattr(fused, "MIN_RAYS_PER_THREAD", 0)
    chunked = model.intersect(rays)
    assert whole.hit.sum() > 300
    for f in fields(whole):
        assert torch.equal(getattr(chunked, f.name), getattr(whole, f.name)), f.name


_EMULATED_RUN = """
import sys, numpy as np, torch
sys.path.insert(0, {tests!r})
from neuralrt.neural import bf16_dot
from neuralrt.geometry.procedural import statue
from test_lsnif_fused_cpu import _model, _mixed_rays
assert not bf16_dot.HAS_AVX512_BF16
model = _model(statue(0), "bf16", max_points=9, hidden_width=64)
hits = model.intersect(_mixed_rays(model, 3000, seed=31))
np.savez({out!r}, t=hits.t.numpy(), normal=hits.normal.numpy(), hit=hits.hit.numpy())
"""


def test_bf16_dot_emulation_gives_the_instructions_bits_end_to_end(figure, tmp_path):
    """The fused pass compiled without AVX512-BF16 (``NUMBA_CPU_FEATURES`` with ``-avx512bf16``, a
    fresh process: the path of CPUs without the instruction) answers as this process does, bit for
    bit (the emulation is exact; on a host without the instruction both runs emulate)."""
    import os
    import subprocess
    import sys

    import llvmlite.binding as llvm
    import numba

    # The features this process compiles for (NUMBA_CPU_FEATURES where set, else the host's), less
    # AVX512-BF16: the rest (e.g. whether the 16-lane walk runs) stays as here
    if numba.config.CPU_FEATURES is not None:
        targeted = [(f[1:], f[0] == "+") for f in numba.config.CPU_FEATURES.split(",") if f]
    else:
        targeted = list(llvm.get_host_cpu_features().items())
    features = ",".join(f"-{name}" if name == "avx512bf16" else f"{'+' if on else '-'}{name}" for name, on in targeted)
    out = tmp_path / "emulated.npz"
    env = {**os.environ, "NUMBA_CPU_FEATURES": features}
    script = _EMULATED_RUN.format(tests=os.path.dirname(__file__), out=str(out))
    subprocess.run([sys.executable, "-c", script], env=env, check=True, timeout=600)
    model = _model(figure, "bf16", max_points=9, hidden_width=64)
    hits = model.intersect(_mixed_rays(model, 3000, seed=31))
    emulated = np.load(out)
    assert hits.hit.sum() > 100
    assert np.array_equal(emulated["hit"], hits.hit.numpy())
    assert np.array_equal(emulated["t"].view(np.uint32), hits.t.numpy().view(np.uint32))
    assert np.array_equal(emulated["normal"].view(np.uint32), hits.normal.numpy().view(np.uint32))


@pytest.mark.skipif(not Path("/proc/cpuinfo").exists(), reason="needs Linux's /proc/cpuinfo")
def test_amx_detection_agrees_with_the_kernels_cpu_flags():
    """The first layer leaves the fused pass and the later hidden layers the decoding pass for
    torch's GEMMs where the CPU has AMX (`first_layer_in_pass`, `later_layers_in_pass`): the
    check reads llvmlite's host features, whose name for it must match the kernel's flag."""
    flags = next((line.split(":", 1)[1].split() for line in Path("/proc/cpuinfo").read_text().splitlines()
                  if line.startswith("flags")), [])  # fmt: skip
    from neuralrt.neural.mlp_rows_cpu import host_has_amx

    assert host_has_amx() == ("amx_bf16" in flags)
    if fused.HIDDEN_LAYERS_IN_DECODE is None:  # (the default)
        assert fused.later_layers_in_pass() == ("amx_bf16" not in flags)
    if fused.FIRST_LAYER_IN_PASS is None:
        assert fused.first_layer_in_pass(126, 128) == ("amx_bf16" not in flags)


def test_the_first_layer_leaves_the_pass_only_on_amx_and_for_inputs_within_bounds(monkeypatch):
    """By default a GEMM only where the CPU has AMX and the inputs' buffer stays within
    GEMM_INPUTS_PER_WIDTH times the activations'; the switch forces either way."""
    monkeypatch.setattr(fused, "FIRST_LAYER_IN_PASS", None)
    for amx in (False, True):
        monkeypatch.setattr(fused, "HOST_HAS_AMX", amx)
        assert fused.first_layer_in_pass(126, 128) == (not amx)
        assert fused.first_layer_in_pass(70, 64) == (not amx)
        assert fused.first_layer_in_pass(fused.GEMM_INPUTS_PER_WIDTH * 64 + 1, 64)
    for forced in (False, True):
        monkeypatch.setattr(fused, "FIRST_LAYER_IN_PASS", forced)
        assert fused.first_layer_in_pass(10_000, 16) == forced


def test_prepared_pass_is_kept_until_a_tensor_or_setting_changes(figure, monkeypatch):
    """The pass's prepared weights and grids are reused across calls, and rebuilt after an in-place
    update of the table, a layer or the occupancy, or a switch: answers after each change equal a
    model built from scratch with the changed values."""
    model = _model(figure, "bf16", hidden_width=32)
    rays = _mixed_rays(model, 400, seed=9)
    model.intersect(rays)
    kept = model.network._fused_cpu_pass[1]
    model.intersect(rays)
    assert model.network._fused_cpu_pass[1] is kept

    def fresh_answers():
        clone = _model(figure, "bf16", hidden_width=32)
        clone.load_state_dict(model.state_dict())
        return clone.intersect(rays)

    with torch.no_grad():
        changes = (lambda: model.encoder.table.mul_(-1.0), lambda: model.network.hidden[0].bias.add_(0.5),
                   lambda: model.network.output.weight.mul_(2.0), lambda: model.occupancy[:, :, :8].zero_())  # fmt: skip
        for change in changes:
            before = model.intersect(rays)
            change()
            after = model.intersect(rays)
            assert model.network._fused_cpu_pass[1] is not kept
            kept = model.network._fused_cpu_pass[1]
            expected = fresh_answers()
            assert torch.equal(after.hit, expected.hit) and torch.equal(after.t, expected.t)
            assert not (torch.equal(after.hit, before.hit) and torch.equal(after.t, before.t))
    monkeypatch.setattr(fused, "BF16_DOT_FIRST_LAYER", False)
    model.intersect(rays)
    assert model.network._fused_cpu_pass[1] is not kept and not model.network._fused_cpu_pass[1].pairs


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_models_at_fp16_storage_precision_read_the_half_table_with_the_same_bits(figure, precision, monkeypatch):
    """A model rounded to its fp16 storage precision (as `train` returns it) has the pass read its
    table's float16 copy (where numba targets F16C), and answers bit for bit as from the float32
    table; a table float16 does not hold exactly is read in float32."""
    model = _model(figure, precision)
    rays = _mixed_rays(model, 2000, seed=12)
    model.intersect(rays)
    assert model.network._fused_cpu_pass[1].table_flat.dtype == np.float32  # U(-1, 1): not float16 values
    model.round_to_storage_precision_()
    hits, occluded = model.intersect(rays), model.occluded(rays)
    assert model.network._fused_cpu_pass[1].table_flat.dtype == (np.uint16 if HALF_READS else np.float32)
    monkeypatch.setattr(fused, "HALF_TABLE", False)
    reference, reference_occluded = model.intersect(rays), model.occluded(rays)
    assert model.network._fused_cpu_pass[1].table_flat.dtype == np.float32
    assert int(reference.hit.sum()) > 100 and torch.equal(occluded, reference_occluded)
    for name in ("hit", "t", "normal", "albedo", "material_id"):
        assert torch.equal(getattr(hits, name), getattr(reference, name)), name
