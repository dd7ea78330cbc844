"""LSNIF inference on the CPU: the fused numba pass against the unfused path, Embree and the MLP alone.

For each mesh and preset, one untrained model on the mesh's real occupancy (the speed does not
depend on the weights; the hash table is filled with random values so no feature is 0, then the
model is rounded to its storage precision as `train` returns it) answers
the same rays (`BoxRayDistribution`: half from a sphere around the box, half from the surface)
with ``intersect`` through the fused kernel (the CPU default; also with its fp32 per-ray first
layer, ``BF16_DOT_FIRST_LAYER = False``, the code before the bf16 dot products; and with the torch
decoding of the raw outputs, ``WRITE_HITS = False``, the code before the numba decoding pass; with
the first layer in the pass and torch's GEMMs for the hidden layers after it or those layers in
the decoding pass (``FIRST_LAYER_IN_PASS = True`` and ``HIDDEN_LAYERS_IN_DECODE`` False or
True); with the first layer as torch's GEMM on the inputs the pass writes (``FIRST_LAYER_IN_PASS
= False``; by default GEMMs where the CPU has AMX, every layer in numba passes elsewhere); with
the later layers and the
decoding in a pass after the fused one, ``DECODE_IN_PASS = False``; with the table's rows read
from its float32 values, ``HALF_TABLE = False``), with ``occluded`` (the
decision-only decoding) and through the unfused path
(featurize -> encode -> MLP), interleaved with Embree on the same rays, in the same process
(the machine is shared: read the ratios). Also the MLP alone on a chunk of random inputs at the
inference precision (interleaved, and back to back with ``intersect`` for a like-for-like fraction), and ``fused_network_outputs_cpu``'s time (the pass, the GEMMs, torch's output layer). Best of
``--repeats`` (and Embree ratios from the medians too). Writes benchmarks/results/lsnif_cpu.json.

    python benchmarks/bench_lsnif_cpu.py bunny00.off procedural:hairball:6 [--presets hq lq] [--rays 262144]
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first: it sets how OpenMP threads wait before torch loads OpenMP)
import numba
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import (ArgumentParser, check_mesh_spec, check_presets, description, positive_int,  # noqa: E402
                     print_table, result_name, run_main, write_results)
from bench_lsnif import resolve_mesh  # noqa: E402

from neuralrt.accel.mesh_blas import MeshBLAS  # noqa: E402
from neuralrt.methods.lsnif import LSNIFModel  # noqa: E402
from neuralrt.methods.lsnif_config import LSNIFConfig  # noqa: E402
from neuralrt.methods import lsnif_fused_cpu  # noqa: E402
from neuralrt.methods.lsnif_fused_cpu import fused_network_outputs_cpu  # noqa: E402
from neuralrt.training.ray_distribution import BoxRayDistribution  # noqa: E402

COLUMNS = ["mesh", "preset", "precision", "network_frac", "embree_Mrays/s", "fused_Mrays/s", "unfused_Mrays/s",
           "fused_vs_embree", "occluded_vs_embree", "fused_vs_embree_median", "occluded_vs_embree_median", "numba_decode_gain", "hidden_in_decode_gain", "first_layer_gemm_gain", "decode_in_pass_gain", "half_table_gain", "fused_fp32_l1_vs_embree", "bf16_l1_gain", "unfused_vs_embree", "fused_vs_unfused", "kernel_share", "fraction_of_mlp_limit", "fraction_of_mlp_limit_back_to_back",
           "load"]


def seconds(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def bench(spec: str, preset: str, n_rays: int, repeats: int) -> dict:
    mesh = resolve_mesh(spec)
    exact = MeshBLAS(mesh)
    model = LSNIFModel.from_mesh(mesh, LSNIFConfig.preset(preset))
    with torch.no_grad():
        model.encoder.table.uniform_(-1, 1, generator=torch.Generator().manual_seed(0))
    model.round_to_storage_precision_()  # as `train` returns a model and a file loads it (fp16 values by default)
    rays = BoxRayDistribution(exact, model.box, seed=4242, pool_size=1 << 16).sample(n_rays).rays
    def fused_intersect():
        model.intersect(rays)

    def intersect_with(**settings):
        """``intersect`` with the module switches ``lsnif_fused_cpu.<setting>`` set to the values
        given, then restored (a default may be host-dependent: None, by host)."""

        def intersect():
            defaults = {name: getattr(lsnif_fused_cpu, name) for name in settings}
            for name, value in settings.items():
                setattr(lsnif_fused_cpu, name, value)
            try:
                model.intersect(rays)
            finally:
                for name, value in defaults.items():
                    setattr(lsnif_fused_cpu, name, value)

        return intersect

    # the earlier fp32 per-ray first layer
    fused_fp32_first_layer_intersect = intersect_with(BF16_DOT_FIRST_LAYER=False)
    # decoded by torch ops (before the numba decoding)
    fused_torch_decode_intersect = intersect_with(WRITE_HITS=False)
    # the first layer in the pass, torch's GEMMs for the later layers (session 23's default on AMX)
    fused_torch_hidden_intersect = intersect_with(FIRST_LAYER_IN_PASS=True, HIDDEN_LAYERS_IN_DECODE=False)
    # every layer in a numba pass (the default without AMX)
    fused_decode_hidden_intersect = intersect_with(FIRST_LAYER_IN_PASS=True, HIDDEN_LAYERS_IN_DECODE=True)
    # the first layer too as torch's GEMM, on the inputs the pass writes (the default on AMX)
    fused_gemm_first_intersect = intersect_with(FIRST_LAYER_IN_PASS=False)
    # the later layers and the decoding in a pass of their own (before session 33)
    fused_decode_pass_intersect = intersect_with(DECODE_IN_PASS=False)
    # the table's rows read from its float32 values (before session 33)
    fused_f32_table_intersect = intersect_with(HALF_TABLE=False)

    def fused_occluded():
        model.occluded(rays)

    def unfused_intersect():  # featurize -> encode -> MLP, decoded by torch
        model._network_answers = model._network_answers_unfused  # the instance attribute wins over the method
        lsnif_fused_cpu.WRITE_HITS = False
        try:
            model.intersect(rays)
        finally:
            del model._network_answers
            lsnif_fused_cpu.WRITE_HITS = True

    unit = model._unit_rays(rays)
    fc, dtype = model.config.features, model.compute_dtype()

    def kernel_and_gemms():
        fused_network_outputs_cpu(unit.origins, unit.directions, model.occupancy, model.encoder, model.network,
                                  max_points=fc.max_points, origin_point=fc.origin_point,
                                  share_boundary_points=fc.share_boundary_points, point_distances=fc.point_distances,
                                  compute_dtype=dtype)  # fmt: skip

    x = torch.randn(model.config.inference.chunk_size, model.network_inputs)

    def mlp_only():
        with torch.no_grad():
            model.network(x, dtype)

    # Timed in this order in every repeat (interleaved: the machine is shared).
    timed = {"embree": lambda: exact.intersect(rays), "embree_occluded": lambda: exact.occluded(rays), "fused": fused_intersect,
             "fused_torch_decode": fused_torch_decode_intersect, "fused_torch_hidden": fused_torch_hidden_intersect,
             "fused_decode_hidden": fused_decode_hidden_intersect, "fused_gemm_first": fused_gemm_first_intersect,
             "fused_decode_pass": fused_decode_pass_intersect,
             "fused_f32_table": fused_f32_table_intersect, "occluded": fused_occluded, "fused_fp32_l1": fused_fp32_first_layer_intersect,
             "unfused": unfused_intersect, "fused_network": kernel_and_gemms, "mlp": mlp_only}  # fmt: skip
    for name, fn in timed.items():  # compile / warm caches
        if name not in ("embree", "embree_occluded", "fused_network"):
            fn()
    times = {name: [] for name in timed}
    for _ in range(repeats):
        for name, fn in timed.items():
            times[name].append(seconds(fn))
    best = {k: min(v) for k, v in times.items()}
    median = {k: statistics.median(v) for k, v in times.items()}
    # Also back to back, each warm with nothing between its calls: interleaved, torch's MLP runs
    # after numba's and Embree's threads (`hq`: ~12 or ~24 ms a call, bimodal, against 11-13 back
    # to back; `lq` ~10% slower), which flatters the interleaved fraction below.
    back_to_back = {name: min(seconds(timed[name]) for _ in range(repeats)) for name in ("fused", "mlp")}
    with torch.no_grad():
        active = len(model._network_answers_fused_cpu(rays)[0])
    network_fraction = active / n_rays
    rate = {k: n_rays / best[k] for k in timed if k != "mlp"}
    mlp_rate = len(x) / best["mlp"]
    return {
        "mesh": spec,
        "preset": preset,
        "precision": str(dtype).replace("torch.", ""),
        "rays": n_rays,
        "threads": numba.get_num_threads(),
        "network_frac": network_fraction,
        "embree_Mrays/s": rate["embree"] / 1e6,
        "fused_Mrays/s": rate["fused"] / 1e6,
        "unfused_Mrays/s": rate["unfused"] / 1e6,
        "fused_network_Mrays/s": rate["fused_network"] / 1e6,
        "mlp_only_Mrows/s": mlp_rate / 1e6,
        "fused_vs_embree": rate["fused"] / rate["embree"],
        "occluded_vs_embree": rate["occluded"] / rate["embree_occluded"],
        # the same from median times (this host's best-of ratios moved by ~15% between runs)
        "fused_vs_embree_median": median["embree"] / median["fused"],
        "occluded_vs_embree_median": median["embree_occluded"] / median["occluded"],
        # the numba decoding pass (with the output layer) over the torch decoding of the raw outputs
        "numba_decode_gain": rate["fused"] / rate["fused_torch_decode"],
        # the later hidden layers in the decoding pass over torch's GEMMs for them (either may be
        # the default: `HIDDEN_LAYERS_IN_DECODE` is off where the CPU has AMX)
        "hidden_layers_in_decode": lsnif_fused_cpu.later_layers_in_pass(),
        "hidden_in_decode_gain": rate["fused_decode_hidden"] / rate["fused_torch_hidden"],
        # the first layer as torch's GEMM on the pass's inputs over the first layer in the pass (both
        # with torch's later layers; `FIRST_LAYER_IN_PASS` is off where the CPU has AMX)
        "first_layer_in_pass": lsnif_fused_cpu.first_layer_in_pass(model.network_inputs, model.config.network.hidden_width),
        "first_layer_gemm_gain": rate["fused_gemm_first"] / rate["fused_torch_hidden"],
        # the decoding in the fused pass over a decoding pass after it (where the later layers run in numba)
        "decode_in_pass_gain": rate["fused"] / rate["fused_decode_pass"],
        # the rows read from the table's float16 copy over its float32 values (the model is at fp16 storage precision)
        "half_table_gain": rate["fused"] / rate["fused_f32_table"],
        "unfused_vs_embree": rate["unfused"] / rate["embree"],
        "fused_vs_unfused": rate["fused"] / rate["unfused"],
        # the same fused pass with the fp32 per-ray first layer (before the bf16 dot products)
        "fused_fp32_l1_vs_embree": rate["fused_fp32_l1"] / rate["embree"],
        "bf16_l1_gain": rate["fused"] / rate["fused_fp32_l1"],
        # share of intersect in fused_network_outputs_cpu (kernel + GEMMs + torch output layer; the
        # intersect path now runs the output layer in its decoding pass instead)
        "kernel_share": best["fused_network"] / best["fused"],
        # network rays/s of the whole pipeline over the MLP alone (as bench_lsnif.py)
        "fraction_of_mlp_limit": rate["fused"] * network_fraction / mlp_rate,
        # the same with both timed back to back (like for like: neither pays for what ran before it)
        "fraction_of_mlp_limit_back_to_back": (n_rays / back_to_back["fused"]) * network_fraction / (len(x) / back_to_back["mlp"]),
        "back_to_back_s": back_to_back,
        "load": os.getloadavg()[0],
        "times_s": times,
    }


def main() -> None:
    p = ArgumentParser(description=description(__doc__))
    p.add_argument("meshes", nargs="+", help="as bench_lsnif.py: a file in ../shared/meshes, a path, or procedural:NAME:DETAIL")
    p.add_argument("--presets", nargs="+", default=["hq", "lq"])
    p.add_argument("--rays", type=positive_int, default=1 << 18)
    p.add_argument("--repeats", type=positive_int, default=5)
    p.add_argument("--name", type=result_name, default="lsnif_cpu")
    args = p.parse_args()
    for spec in args.meshes:  # every check before the first mesh's work
        check_mesh_spec(spec)
    check_presets("lsnif", args.presets, "--presets")
    rows = []
    for spec in args.meshes:
        for preset in args.presets:
            rows.append(bench(spec, preset, args.rays, args.repeats))
            if len(args.meshes) * len(args.presets) > 1:  # (each row as it comes; the whole table once at the end)
                print_table(rows[-1:], COLUMNS)
    print_table(rows, COLUMNS)
    print(f"wrote {write_results(args.name, rows)}")


if __name__ == "__main__":
    run_main(main)
