"""LSNIF kernels on a CUDA GPU: featurization, encoding, fused vs unfused inference, training step.

On hairball(6)-like rays (2^22 rays from a sphere around the object, aimed at random points of
its box; the model's occupancy is the real mesh's, its weights untrained: speed does not depend
on them), for the ``hq`` and ``lq`` presets:

- the device's two ceilings, measured (device-to-device copy bandwidth, bf16 GEMM rate), and the
  floors they give for a full ``intersect`` (rays in, hits out; MLP FLOPs of the active rays);
- `featurize_rays` (Triton) alone, and the numba kernel on the host's cores on the same rays;
- `SparseHashGrid` forward (Triton) on the featurized points; forward + backward on 2^18 rays;
- the unfused network answers (featurize -> encode -> bf16 MLP, as on the CPU) against the fused
  kernel (first layer only, rest as torch GEMMs; and whole MLP, over launch configurations);
- the model's full ``intersect`` (fused path) in rays/s, against the issue's targets;
- one training step at 2^18 rays (forward, backward, fused Adam; synthetic ground truth), and
  2,000 of them, the paper's scale.

Times are medians of `triton.testing.do_bench` (CUDA events, warm-up). Writes
benchmarks/results/lsnif_kernels_<device>.json (or ``--out PATH``). Needs a CUDA device (else one
error line), except ``--dry-run``.

    python benchmarks/bench_lsnif_kernels_cuda.py [--rays-log2 22] [--out FILE]

``--quick`` (<= ~2 min on an H100, Triton compiles included; the JSON is rewritten after every
measurement, so a cut-off run keeps what it measured): for ``hq`` and ``lq``, featurize, encode,
the fused kernel alone and with the MLP for the previous kernel (``input``, padded tile) and the
one-ray-per-lane kernel (``input_per_ray``) side by side, whether both write the same bytes, and
the full ``intersect`` with the shipped default, with each kernel's best launch, and with
`fused_hits` (output layer + decoding in a kernel). ``--dry-run`` runs the same code paths on the
CPU under ``TRITON_INTERPRET=1`` on a few rays (checks the script, not the speed).

    python benchmarks/bench_lsnif_kernels_cuda.py --quick --out lsnif_kernels.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import traceback
from pathlib import Path

if "--dry-run" in sys.argv:  # before triton is imported
    os.environ["TRITON_INTERPRET"] = "1"

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numba
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (RESULTS_DIR, ArgumentParser, check_output_file, description,  # noqa: E402
                     detail_level, fail, int_in, machine_info, positive_float, positive_int, run_main, write_json)

from neuralrt.geometry.procedural import hairball  # noqa: E402
from neuralrt.methods.lsnif import LSNIFModel  # noqa: E402
from neuralrt.methods.lsnif_config import LSNIFConfig  # noqa: E402
from neuralrt.methods.lsnif_features import featurize_rays, featurize_rays_numba  # noqa: E402
from neuralrt.rays import Hits, Rays  # noqa: E402

TARGETS_RAYS_PER_S = {"hq": 330e6, "lq": 1e9}  # issue 8, on an H100
TOP_CONFIGS: list = []  # the fastest launch configurations of the first preset, tried on the others
# (stage, rays per program, warps) of the fused kernel; register counts from ptxas for sm_90 (hq):
# whole 32/4: 229, 64/8: ~200; first_layer 64/8: 178; input 32/4: 125, 64/8: 128, 128/4: 235, 128/8: 166.
# input_per_ray 32/1: 88, 128/4: ~105 (packed bf16 stores).
LAUNCH_CONFIGS = [("whole", 32, 4), ("whole", 64, 8), ("first_layer", 64, 8), ("input", 32, 4), ("input", 64, 8),
                  ("input", 128, 4), ("input", 128, 8), ("input_per_ray", 32, 1), ("input_per_ray", 64, 2),
                  ("input_per_ray", 128, 4)]  # fmt: skip


# Imported by `_load_triton` once the arguments are checked (Triton: a CPU-only machine may lack it).
triton = do_bench = lsnif_fused = None

DEVICE = "cuda"  # --dry-run: "cpu" under TRITON_INTERPRET=1, tiny sizes, wall-clock times (checks the script only)


def ms(fn, rep: int = 200) -> float:
    if DEVICE != "cuda":
        return 1e3 * _wall(fn)
    return float(do_bench(fn, warmup=50, rep=rep, return_mode="median"))


def ceilings() -> dict:
    n = 1 << 28 if DEVICE == "cuda" else 1 << 20  # 1 GiB of float32
    a = torch.empty(n, device=DEVICE).uniform_()
    b = torch.empty_like(a)
    t_copy = ms(lambda: b.copy_(a))
    a = b = None  # (the GiB freed before the GEMM's inputs)
    m = 8192 if DEVICE == "cuda" else 256
    x = torch.randn(m, m, device=DEVICE, dtype=torch.bfloat16)
    y = torch.randn(m, m, device=DEVICE, dtype=torch.bfloat16)
    t_mm = ms(lambda: x @ y)
    return {"copy_GB_per_s": 2 * 4 * n / t_copy / 1e6, "bf16_gemm_TFLOP_per_s": 2 * m**3 / t_mm / 1e9}


def sphere_rays(model: LSNIFModel, n: int, seed: int = 0) -> Rays:
    """Origins on a sphere of radius one box diagonal around the box centre, aimed at random box points."""
    g = torch.Generator(device=DEVICE).manual_seed(seed)
    lo, hi = model.box.lo, model.box.hi
    centre, radius = (lo + hi) / 2, float((hi - lo).norm())
    u = torch.randn(n, 3, device=DEVICE, generator=g)
    origins = centre + radius * u / u.norm(dim=1, keepdim=True)
    targets = lo + torch.rand(n, 3, device=DEVICE, generator=g) * (hi - lo)
    d = targets - origins
    return Rays(origins=origins, directions=d / d.norm(dim=1, keepdim=True))


def floors(model: LSNIFModel, n: int, active: float, ceil: dict) -> dict:
    """Fewest bytes (rays in: origin, direction, t_min, t_max; Hits out) and MLP FLOPs of the active rays."""
    c = model.config
    w, layers, inputs, outputs = c.network.hidden_width, c.network.hidden_layers, model.network_inputs, 8 + model.num_materials
    flops = 2 * (inputs * w + (layers - 1) * w * w + w * outputs) * active * n
    hit_bytes = 1 + 4 + 12 + 12 + 8 + 12 + 8 + 8 + 8  # hit, t, normal, geometric normal, uv, albedo, 3 int64 ids
    bytes_ = n * (32 + hit_bytes)
    t_bytes = bytes_ / (ceil["copy_GB_per_s"] * 1e6)
    t_flops = flops / (ceil["bf16_gemm_TFLOP_per_s"] * 1e9)
    return {"floor_bytes_ms": t_bytes, "floor_flops_ms": t_flops, "floor_ms": max(t_bytes, t_flops),
            "floor_rays_per_s": n / max(t_bytes, t_flops) * 1e3, "mlp_GFLOP": flops / 1e9, "io_MB": bytes_ / 1e6}  # fmt: skip


def unfused_answers(model: LSNIFModel, rays: Rays):
    prep = model._prepare(rays)
    return model._raw_outputs(prep, model.compute_dtype())


def bench_preset(preset: str, mesh, n: int, ceil: dict, row: dict) -> None:
    config = LSNIFConfig.preset(preset, inference={"chunk_size": n})
    t0 = time.perf_counter()
    model = LSNIFModel.from_mesh(mesh, config).to(DEVICE).eval()
    row["model_build_s"] = time.perf_counter() - t0
    fc = config.features
    h = fc.max_points
    rays = sphere_rays(model, n)
    unit = model._unit_rays(rays)
    o, d = unit.origins, unit.directions
    occ = model.occupancy
    kw = dict(origin_point=fc.origin_point, share_boundary_points=fc.share_boundary_points)
    fp = featurize_rays(o, d, occ, h, **kw)
    active = float((fp.count > 0).float().mean())
    row.update(rays=n, H=h, hidden_width=config.network.hidden_width, occupied_voxels=int(occ.sum()),
               active_frac=active, mean_points_active=float(fp.count[fp.count > 0].float().mean()),
               truncated_frac=float(fp.truncated.float().mean()))  # fmt: skip
    row.update(floors(model, n, active, ceil))

    def record(name: str, fn, rep: int = 200) -> float:
        try:
            t = ms(fn, rep)
            row[f"{name}_ms"] = t
            row[f"{name}_Mrays_per_s"] = n / t / 1e3
            print(f"  {preset} {name}: {t:.3f} ms  {n / t / 1e3:,.1f} M rays/s", flush=True)
            return t
        except Exception as exc:  # keep measuring the rest; the error is part of the result
            row[f"{name}_error"] = f"{type(exc).__name__}: {exc}"[:500]
            traceback.print_exc()
            return float("inf")

    # -- featurization alone (Triton on the GPU; numba on the host's cores, same rays) -------------
    record("featurize_triton", lambda: featurize_rays(o, d, occ, h, **kw))
    o_cpu, d_cpu, occ_cpu = o.cpu(), d.cpu(), occ.cpu().numpy()
    featurize_rays_numba(o_cpu[:64], d_cpu[:64], occ_cpu, h, **kw)
    t_numba = min(_wall(lambda: featurize_rays_numba(o_cpu, d_cpu, occ_cpu, h, **kw)) for _ in range(2))
    row["featurize_numba_host_ms"], row["host_threads"] = 1e3 * t_numba, numba.get_num_threads()
    ref = featurize_rays_numba(o_cpu[: 1 << 18], d_cpu[: 1 << 18], occ_cpu, h, **kw)
    same = (ref.count == fp.count[: 1 << 18].cpu()) & (ref.face_axis == fp.face_axis[: 1 << 18].cpu()).all(1)
    row["featurize_rays_identical_to_numba_frac"] = float(same.float().mean())
    row["featurize_max_point_diff"] = float((ref.points[same] - fp.points[: 1 << 18].cpu()[same]).abs().max())

    # -- encoding alone ------------------------------------------------------------------------------
    with torch.no_grad():
        record("encode_fwd_triton", lambda: model.encoder(fp.points, fp.face_axis))
    b = 1 << 18
    pts, axes = fp.points[:b].contiguous(), fp.face_axis[:b].contiguous()

    def fwd_bwd():
        out = model.encoder(pts, axes)
        out.backward(torch.ones_like(out))
        model.encoder.table.grad = None

    try:
        t = ms(fwd_bwd)
        row["encode_fwd_bwd_2^18_ms"] = t
    except Exception as exc:
        row["encode_fwd_bwd_error"] = f"{type(exc).__name__}: {exc}"[:500]

    # -- unfused vs fused network answers --------------------------------------------------------------
    with torch.no_grad():
        record("unfused_answers", lambda: unfused_answers(model, rays), rep=100)
        dtype = model.compute_dtype()
        common = dict(max_points=h, point_distances=fc.point_distances, compute_dtype=dtype, **kw)
        configs = LAUNCH_CONFIGS if preset == "hq" else TOP_CONFIGS or LAUNCH_CONFIGS
        timed = []
        for stage, block, warps in configs:
            t = record(f"fused_{stage}_B{block}_W{warps}",
                       lambda: lsnif_fused.fused_network_outputs(o, d, occ, model.encoder, model.network,
                                                                 stage=stage, block=block, num_warps=warps, **common))  # fmt: skip
            timed.append((t, (stage, block, warps)))
        timed.sort()
        TOP_CONFIGS[:] = [c for _, c in timed[:3]]
        best = timed[0]
        row["fused_best_launch"] = best[1]
        lsnif_fused.DEFAULT_LAUNCH.update(stage=best[1][0], block=best[1][1], num_warps=best[1][2])
        # agreement of the fused answers (best configuration) with the unfused ones on 2^18 rays
        sub = slice(0, 1 << 18)
        prep = model._prepare(rays[sub])
        ref_out = model._raw_outputs(prep, dtype)
        fused = lsnif_fused.fused_network_outputs(o[sub], d[sub], occ, model.encoder, model.network, **common)
        keep = torch.nonzero(fused.count > 0).squeeze(1)
        if torch.equal(unit.index[keep], prep.active):
            diff = (fused.values[keep] - ref_out).abs().max() / ref_out.abs().max()
            row["fused_vs_unfused_max_rel_diff"] = float(diff)
            row["fused_vs_unfused_occlusion_agree_frac"] = float(((fused.values[keep, 0] > 0) == (ref_out[:, 0] > 0)).float().mean())
        else:
            row["fused_vs_unfused_active_mismatch"] = int((fused.count > 0).sum()) - len(prep.active)

        # -- the model's full intersect (fused path, best launch configuration) ---------------------------
        t = record("intersect", lambda: model.intersect(rays), rep=300)
        row["intersect_target_Mrays_per_s"] = TARGETS_RAYS_PER_S[preset] / 1e6
        row["intersect_target_met"] = bool(n / t * 1e3 >= TARGETS_RAYS_PER_S[preset])
        model.config.inference.chunk_size = 1 << 20
        record("intersect_chunk_2^20", lambda: model.intersect(rays), rep=300)
        model.config.inference.chunk_size = n
        hits = model.intersect(rays)
        row["hit_frac"] = float(hits.hit.float().mean())

    # -- one training step at the paper's batch --------------------------------------------------------
    if preset == "hq":
        train_step(model, rays, row)


# --quick: the previous kernel (padded [rays, levels, features] tile; its measured best launches)
# beside the one-ray-per-lane kernel, as (stage, rays per program, warps).
QUICK_CONFIGS = {
    "hq": [("input", 32, 4), ("input_per_ray", 32, 1), ("input_per_ray", 64, 2), ("input_per_ray", 128, 4)],
    "lq": [("input", 32, 4), ("input", 128, 4), ("input_per_ray", 32, 1), ("input_per_ray", 128, 4)],
}


class Budget:
    """Seconds left for measurements; past the end, `record` skips (and says so in the JSON)."""

    def __init__(self, seconds: float):
        self.end = time.perf_counter() + seconds

    def left(self) -> float:
        return self.end - time.perf_counter()


def _sync() -> None:
    if DEVICE == "cuda":
        torch.cuda.synchronize()


def bench_preset_quick(preset: str, mesh, n: int, row: dict, budget: Budget, save) -> None:
    """The --quick measurements of one preset into ``row``; ``save()`` after each one."""
    overrides = {"inference": {"chunk_size": n}}
    configs = QUICK_CONFIGS[preset]
    if DEVICE != "cuda":  # dry run: the interpreter has no bf16 dots and takes ~10 s per walk step of a block
        overrides = {"inference": {"chunk_size": n, "compute_precision": "fp32"}, "features": {"max_points": 3}}
        configs = [configs[0], configs[-1]]
    config = LSNIFConfig.preset(preset, **overrides)
    t0 = time.perf_counter()
    model = LSNIFModel.from_mesh(mesh, config).to(DEVICE).eval()
    row["model_build_s"] = time.perf_counter() - t0
    if DEVICE != "cuda":
        _route_through_fused(model)
    fc = config.features
    h = fc.max_points
    rays = sphere_rays(model, n)
    unit = model._unit_rays(rays)
    o, d, occ = unit.origins, unit.directions, model.occupancy
    kw = dict(origin_point=fc.origin_point, share_boundary_points=fc.share_boundary_points)
    dtype = model.compute_dtype()
    common = dict(max_points=h, point_distances=fc.point_distances, compute_dtype=dtype, **kw)
    fp = featurize_rays(o, d, occ, h, **kw)
    active = float((fp.count > 0).float().mean())
    row.update(rays=n, H=h, hidden_width=config.network.hidden_width, compute_dtype=str(dtype), active_frac=active,
               mean_points_active=float(fp.count[fp.count > 0].float().mean()) if active else 0.0,
               truncated_frac=float(fp.truncated.float().mean()))  # fmt: skip

    def record(name: str, fn, rep: int = 100) -> float:
        if budget.left() <= 0:
            row[f"{name}_skipped"] = "over the --budget-s time budget"
            print(f"  {preset} {name}: skipped (time budget)", flush=True)
            return float("inf")
        try:
            if DEVICE == "cuda":  # first call: Triton compile (if not cached) + one run
                t1 = time.perf_counter()
                fn()
                _sync()
                row[f"{name}_first_call_s"] = time.perf_counter() - t1
                t = float(do_bench(fn, warmup=25, rep=rep, return_mode="median"))
            else:
                t = 1e3 * _wall(fn)
            row[f"{name}_ms"] = t
            row[f"{name}_Mrays_per_s"] = n / t / 1e3
            print(f"  {preset} {name}: {t:.3f} ms  {n / t / 1e3:,.1f} M rays/s", flush=True)
            return t
        except Exception as exc:  # keep measuring the rest; the error is part of the result
            row[f"{name}_error"] = f"{type(exc).__name__}: {exc}"[:500]
            traceback.print_exc()
            return float("inf")
        finally:
            save()

    with torch.no_grad():
        record("featurize_triton", lambda: featurize_rays(o, d, occ, h, **kw))
        record("encode_fwd_triton", lambda: model.encoder(fp.points, fp.face_axis))
        weights = lsnif_fused._weights_for(model.network, model.encoder, h, fc.point_distances, dtype)
        res = model.encoder._resolutions_on(o.device)
        best: dict[str, tuple[float, tuple]] = {}
        for stage, block, warps in configs:
            launch = dict(stage=stage, block=block, num_warps=warps)
            tag = f"{stage}_B{block}_W{warps}"
            record(f"kernel_{tag}", lambda: lsnif_fused.run_fused_kernel(
                o, d, occ, model.encoder.table, res, weights, slope=model.network.slope, **launch, **common_kernel(common)))  # fmt: skip
            t = record(f"fused_{tag}", lambda: lsnif_fused.fused_network_outputs(
                o, d, occ, model.encoder, model.network, **launch, **common))  # fmt: skip
            if t < best.get(stage, (float("inf"),))[0]:
                best[stage] = (t, (stage, block, warps))
        row["fused_best_launch"] = {stage: list(c) for stage, (_, c) in best.items()}
        # Does the new kernel write the old one's bytes (network input, counts, box interval)?
        sub = slice(0, min(n, 1 << 18))
        try:
            outs = [lsnif_fused.run_fused_kernel(o[sub], d[sub], occ, model.encoder.table, res, weights, stage=stage, block=b,
                                                 num_warps=w, **common_kernel(common))
                    for stage, b, w in (configs[0], configs[-1])]  # fmt: skip
            same_rows = (outs[0].values == outs[1].values).all(1) & (outs[0].count == outs[1].count)
            row["per_ray_vs_tiled_identical_rows_frac"] = float(same_rows.float().mean())
            row["per_ray_vs_tiled_max_abs_diff"] = float((outs[0].values.float() - outs[1].values.float()).abs().max())
        except Exception as exc:
            row["per_ray_vs_tiled_error"] = f"{type(exc).__name__}: {exc}"[:500]
            traceback.print_exc()
        save()

        # -- full intersect: the shipped default, each kernel's best launch, and fused_hits ----------
        shipped = dict(lsnif_fused.DEFAULT_LAUNCH)
        row["default_launch"] = shipped
        try:
            ref_hits = model.intersect(rays)
            record("intersect_default", lambda: model.intersect(rays), rep=200)
            timed = {}
            for stage, (_, (st, b, w)) in best.items():
                lsnif_fused.DEFAULT_LAUNCH.update(stage=st, block=b, num_warps=w, write_hits=False)
                timed[stage] = record(f"intersect_best_{stage}", lambda: model.intersect(rays), rep=200)
            fastest = min(timed, key=timed.get) if timed else shipped["stage"]
            st, b, w = best[fastest][1] if fastest in best else (shipped["stage"], shipped["block"], shipped["num_warps"])
            lsnif_fused.DEFAULT_LAUNCH.update(stage=st, block=b, num_warps=w, write_hits=True)
            row["intersect_fused_hits_launch"] = [st, b, w]
            record("intersect_fused_hits", lambda: model.intersect(rays), rep=200)
            hits = model.intersect(rays)
            both = hits.hit & ref_hits.hit
            row["fused_hits_hit_agree_frac"] = float((hits.hit == ref_hits.hit).float().mean())
            row["fused_hits_t_max_rel_diff"] = float(((hits.t - ref_hits.t).abs() / ref_hits.t.abs()).where(both, 0).max())
            row["fused_hits_normal_max_diff"] = float((hits.normal - ref_hits.normal).abs().max())
            row["hit_frac"] = float(ref_hits.hit.float().mean())
        except Exception as exc:
            row["intersect_error"] = f"{type(exc).__name__}: {exc}"[:500]
            traceback.print_exc()
        finally:
            lsnif_fused.DEFAULT_LAUNCH.clear()
            lsnif_fused.DEFAULT_LAUNCH.update(shipped)
        times = {k: v for k, v in row.items() if k.startswith("intersect_") and k.endswith("_ms")}
        if times:
            fastest = min(times, key=times.get)
            row["intersect_best"] = fastest[: -len("_ms")]
            row["intersect_best_Mrays_per_s"] = n / times[fastest] / 1e3
            row["intersect_target_Mrays_per_s"] = TARGETS_RAYS_PER_S[preset] / 1e6
            row["intersect_target_met"] = bool(n / times[fastest] * 1e3 >= TARGETS_RAYS_PER_S[preset])
        save()


def _route_through_fused(model: LSNIFModel) -> None:
    """Dry run: send the CPU model's intersect down the CUDA path (fused kernels, interpreted), as
    `LSNIFModel._network_answers*` do on CUDA tensors, so that --dry-run executes that path."""

    def as_hits(rays: Rays, hits: Hits) -> bool:
        if not lsnif_fused.DEFAULT_LAUNCH["write_hits"]:
            return False
        model._network_answers_fused_hits(rays, hits)
        return True

    model._network_answers = model._network_answers_fused
    model._network_answers_as_hits = as_hits


def common_kernel(common: dict) -> dict:
    """`fused_network_outputs` keywords minus those `run_fused_kernel` does not take."""
    return {k: v for k, v in common.items() if k != "compute_dtype"}


def train_step(model: LSNIFModel, rays: Rays, row: dict, batch: int = 1 << 18) -> None:
    model.train()
    batch = min(batch, len(rays))
    r = rays[slice(0, batch)]
    g = torch.Generator(device=DEVICE).manual_seed(1)
    truth = Hits.empty(batch, DEVICE)
    truth.hit = torch.rand(batch, device=DEVICE, generator=g) < 0.3
    truth.t = torch.where(truth.hit, torch.rand(batch, device=DEVICE, generator=g) + 1, float("inf"))
    nrm = torch.randn(batch, 3, device=DEVICE, generator=g)
    truth.normal = nrm / nrm.norm(dim=1, keepdim=True)
    truth.albedo = torch.rand(batch, 3, device=DEVICE, generator=g)
    truth.material_id = torch.zeros(batch, dtype=torch.int64, device=DEVICE)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3, betas=(0.9, 0.99), eps=1e-15, fused=True)

    def step():
        result = model.training_step(r, truth)
        opt.zero_grad(set_to_none=True)
        result.loss.backward()
        opt.step()

    try:
        t = ms(step, rep=500)
        row["train_step_2^18_ms"] = t
        row["train_2000_steps_s_estimate"] = 2000 * t / 1e3
        print(f"  train step 2^18: {t:.2f} ms -> 2000 steps {2 * t:.1f} s (no ground-truth tracing)", flush=True)
    except Exception as exc:
        row["train_step_error"] = f"{type(exc).__name__}: {exc}"[:500]
        traceback.print_exc()
    model.eval()


def _wall(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def _load_triton() -> None:
    """Triton, its benchmark timer and the fused LSNIF kernels, as module globals (a one-line error without Triton)."""
    global triton, do_bench, lsnif_fused
    try:
        import triton as triton_module
        from triton.testing import do_bench as bench

        from neuralrt.methods import lsnif_fused as fused
    except ImportError as exc:
        fail(f"needs Triton ({exc})")
    triton, do_bench, lsnif_fused = triton_module, bench, fused


def launch(text: str) -> tuple[str, int, int]:
    """argparse type of ``--profile STAGE,BLOCK,WARPS``."""
    stages = list(dict.fromkeys(stage for stage, _, _ in LAUNCH_CONFIGS))
    parts = text.split(",")
    try:
        if len(parts) != 3 or parts[0] not in stages:
            raise ValueError
        block, warps = positive_int(parts[1]), positive_int(parts[2])
    except (ValueError, argparse.ArgumentTypeError):
        raise argparse.ArgumentTypeError(f"{text!r}: expected STAGE,BLOCK,WARPS with STAGE one of {', '.join(stages)} "
                                         "and BLOCK, WARPS integers >= 1, e.g. input_per_ray,64,2") from None
    return parts[0], block, warps


def main() -> None:
    parser = ArgumentParser(description=description(__doc__))
    parser.add_argument("--rays-log2", type=int_in(0, 30), default=22)
    parser.add_argument("--detail", type=detail_level("hairball"), default=6, help="hairball detail (6: 2.4M triangles)")
    parser.add_argument("--presets", nargs="+", default=["hq", "lq"], choices=list(TARGETS_RAYS_PER_S))
    parser.add_argument("--out", type=Path, default=None, help="JSON path (default benchmarks/results/lsnif_kernels_<device>.json)")
    parser.add_argument("--dry-run", action="store_true", help="CPU, Triton interpreter, tiny sizes: checks the script")
    parser.add_argument("--quick", action="store_true",
                        help="kernels old vs new and intersect only (<= ~2 min on an H100, compiles included)")
    parser.add_argument("--budget-s", type=positive_float, default=95.0,
                        help="--quick: seconds of measurements after the model builds; later ones are skipped")
    parser.add_argument("--profile", metavar="STAGE,BLOCK,WARPS", type=launch, default=None,
                        help="only run the fused kernel 3 times on hq (for ncu: --launch-skip 2 --launch-count 1)")
    args = parser.parse_args()
    # Every check before the first mesh is built.
    if args.profile and args.dry_run:
        parser.error("--profile times the kernel on a GPU: not with --dry-run")
    if args.out is not None:
        check_output_file(args.out, "results file")
    global DEVICE
    if args.dry_run:
        DEVICE = "cpu"
    elif not torch.cuda.is_available():
        why = "no CUDA device is available" if torch.backends.cuda.is_built() else f"this torch ({torch.__version__}) is built without CUDA"
        fail(f"needs a CUDA device ({why}); --dry-run checks the script on the CPU")
    _load_triton()
    if args.dry_run:  # the interpreter runs a few rays of a small hairball
        args.rays_log2 = min(args.rays_log2, 5)
        args.detail = min(args.detail, 2)
        args.budget_s = float("inf")
    n = 1 << args.rays_log2
    device_name = torch.cuda.get_device_name() if DEVICE == "cuda" else "cpu-dry-run"
    info = {"device": device_name, "torch": torch.__version__, "triton": triton.__version__,
            "cuda": torch.version.cuda, "machine": machine_info()}  # fmt: skip
    if args.profile:
        stage, block, warps = args.profile
        config = LSNIFConfig.preset(args.presets[0])
        model = LSNIFModel.from_mesh(hairball(args.detail), config).to(DEVICE).eval()
        unit = model._unit_rays(sphere_rays(model, n))
        fc = config.features
        with torch.no_grad():
            for _ in range(3):
                lsnif_fused.fused_network_outputs(
                    unit.origins, unit.directions, model.occupancy, model.encoder, model.network, max_points=fc.max_points,
                    point_distances=fc.point_distances, compute_dtype=model.compute_dtype(), stage=stage,
                    block=int(block), num_warps=int(warps))  # fmt: skip
        torch.cuda.synchronize()
        return
    if args.quick:
        return main_quick(args, n, device_name, info)
    ceil = ceilings()
    print(f"{device_name}: copy {ceil['copy_GB_per_s']:,.0f} GB/s, bf16 GEMM {ceil['bf16_gemm_TFLOP_per_s']:,.0f} TFLOP/s", flush=True)
    t0 = time.perf_counter()
    mesh = hairball(args.detail)
    info["mesh"] = {"name": mesh.name, "triangles": int(len(mesh.faces)), "build_s": time.perf_counter() - t0}
    rows = []
    for preset in args.presets:
        row = {"preset": preset, "mesh": mesh.name}
        rows.append(row)
        try:
            bench_preset(preset, mesh, n, ceil, row)
        except Exception as exc:
            row["error"] = f"{type(exc).__name__}: {exc}"[:1000]
            traceback.print_exc()
        torch.cuda.empty_cache()
    slug = "".join(c if c.isalnum() else "_" for c in device_name.lower()).strip("_")
    out = args.out or RESULTS_DIR / f"lsnif_kernels_{slug}.json"
    write_json(out, {"benchmark": "lsnif_kernels_cuda", **info, "ceilings": ceil, "rows": rows}, default=str)
    print(f"wrote {out}")
    for row in rows:
        keys = [k for k in row if k.endswith("_Mrays_per_s")]
        print(row["preset"], {k: round(row[k], 1) for k in keys})


def main_quick(args, n: int, device_name: str, info: dict) -> None:
    t_start = time.perf_counter()
    t0 = time.perf_counter()
    mesh = hairball(args.detail)
    info["mesh"] = {"name": mesh.name, "triangles": int(len(mesh.faces)), "build_s": time.perf_counter() - t0}
    out = args.out or RESULTS_DIR / "lsnif_kernels_quick.json"
    rows: list[dict] = []
    result = {"benchmark": "lsnif_kernels_cuda --quick", **info, "rows": rows}

    def save() -> None:
        result["total_s"] = time.perf_counter() - t_start
        write_json(out, result, default=str)

    budget = Budget(args.budget_s)
    for preset in args.presets:
        row = {"preset": preset, "mesh": mesh.name}
        rows.append(row)
        try:
            bench_preset_quick(preset, mesh, n, row, budget, save)
        except Exception as exc:
            row["error"] = f"{type(exc).__name__}: {exc}"[:1000]
            traceback.print_exc()
        save()
        if DEVICE == "cuda":
            torch.cuda.empty_cache()
    print(f"wrote {out} ({time.perf_counter() - t_start:.0f} s)")
    for row in rows:
        print(row["preset"], {k: round(row[k], 1) for k in row if k.endswith("_Mrays_per_s")})


if __name__ == "__main__":
    run_main(main)
