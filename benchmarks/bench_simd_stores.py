"""ns per 16-lane compress store, expand load, gather and scatter on this CPU, each form timed
alone in a loop (one thread), so that a CPU where one form is microcoded shows at once.

    python benchmarks/bench_simd_stores.py [--ops 1048576] [--repeats 5] [--name simd_stores]

A compress store in its memory form (``llvm.masked.compressstore``: ``vcompressps m{k}, zmm``)
against the form `neuralrt.simd16.compress16_f32` emits (a register compress, then a store masked
to the first ``popcount(mask)`` lanes); an expand load in its memory form
(`neuralrt.simd16.expand16_f32`) against a prefix-masked load and a register expand (x86's
intrinsic: only where numba targets AVX-512); and `gather16_i32` / `scatter16_i32` for scale. On
the 2-core Zen 4 of session 41 the memory-form compress took 22 ns, the register form 1.5 ns
(`--name simd_stores_zen4_s41`; docs/lsnif.md, "Session 41"). Each loop also does a vector load and a mask from a table (~1 ns).
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import neuralrt  # noqa: F401  (first, as in the other benchmarks: it sets how OpenMP threads wait)
import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import (ArgumentParser, description, positive_int, print_table, result_name, run_main,  # noqa: E402
                     write_results)

from neuralrt.simd import HAS_AVX512, _llvm_function, element_pointer, prefix_mask  # noqa: E402
from neuralrt.simd16 import (  # noqa: E402
    compress16_f32, expand16_f32, f32x16, gather16_i32, lane_index16, load16, load16_i32, m16, popcount16, scatter16_i32, splat_f32, splat_i32,
    store16,
)  # fmt: skip

_I32 = ir.IntType(32)
_F32X16 = ir.VectorType(ir.FloatType(), 16)
_M16 = ir.VectorType(ir.IntType(1), 16)


@intrinsic
def _compress_store_memory_form(typingctx, array, start, value, mask):
    """``llvm.masked.compressstore``: what `neuralrt.simd` emitted before session 41."""

    def codegen(context, builder, sig, args):
        pointer = element_pointer(context, builder, sig.args[0], args[0], args[1])
        fn = _llvm_function(builder, "llvm.masked.compressstore.v16f32", ir.VoidType(), [_F32X16, pointer.type, _M16])
        builder.call(fn, [args[2], pointer, args[3]])
        return context.get_dummy_value()

    return types.void(array, types.intp, f32x16, m16), codegen


@intrinsic
def _expand_register_form(typingctx, array, start, mask, passthru):
    """A load masked to the first ``popcount(mask)`` lanes, then x86's register expand."""

    def codegen(context, builder, sig, args):
        pointer = element_pointer(context, builder, sig.args[0], args[0], args[1])
        load = _llvm_function(builder, "llvm.masked.load.v16f32.p0", _F32X16, [pointer.type, _I32, _M16, _F32X16])
        packed = builder.call(load, [pointer, _I32(4), prefix_mask(builder, args[2]), ir.Constant(_F32X16, ir.Undefined)])
        expand = _llvm_function(builder, "llvm.x86.avx512.mask.expand.v16f32", _F32X16, [_F32X16, _F32X16, _M16])
        return builder.call(expand, [packed, args[3], args[2]])

    return f32x16(array, types.intp, m16, f32x16), codegen


@numba.njit(inline="always")
def _mask(bits):
    return (lane_index16() * splat_i32(bits) & splat_i32(8)) == splat_i32(8)  # about half the lanes


@numba.njit
def _compress_loop(source, out, masks, register_form):
    e = 0
    for i in range(len(masks)):
        v, m = load16(source, 16 * (i & 63)), _mask(masks[i])
        if register_form:
            compress16_f32(out, e, v, m)
        else:
            _compress_store_memory_form(out, e, v, m)
        e += popcount16(m)
        if e > len(out) - 32:
            e = 0
    return e


@numba.njit
def _expand_loop(source, masks, register_form):
    total, start = splat_f32(0.0), 0
    for i in range(len(masks)):
        m = _mask(masks[i])
        total = total + (_expand_register_form(source, start, m, total) if register_form else expand16_f32(source, start, m, total))
        start = (start + popcount16(m)) & 1023
    out = np.empty(16, np.float32)
    store16(out, 0, total)
    return out[0]


@numba.njit
def _gather_scatter_loop(table, indices, masks, scatter):
    total = splat_i32(0)
    for i in range(len(masks)):
        index, m = load16_i32(indices, 16 * (i & 255)), _mask(masks[i])
        if scatter:
            scatter16_i32(table, index, index, m)
        else:
            total = total + gather16_i32(table, index, m)
    return popcount16(total == splat_i32(0))


def main() -> None:
    ap = ArgumentParser(description=description(__doc__))
    ap.add_argument("--ops", type=positive_int, default=1 << 20)
    ap.add_argument("--repeats", type=positive_int, default=5)
    ap.add_argument("--name", type=result_name, default="simd_stores")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    source = rng.random(2048, dtype=np.float32)
    out = np.zeros(1 << 16, np.float32)
    table = np.zeros(1 << 16, np.int32)
    indices = rng.integers(0, len(table), 4096, dtype=np.int32)
    masks = rng.integers(1, 1000, args.ops, dtype=np.int32)
    cases = {"compress store, memory form": lambda m: _compress_loop(source, out, m, False),
             "compress store, register form (neuralrt.simd)": lambda m: _compress_loop(source, out, m, True),
             "expand load, memory form (neuralrt.simd)": lambda m: _expand_loop(source, m, False),
             "gather16_i32": lambda m: _gather_scatter_loop(table, indices, m, False),
             "scatter16_i32": lambda m: _gather_scatter_loop(table, indices, m, True)}
    if HAS_AVX512:  # x86's expand intrinsic does not compile for other targets
        cases["expand load, register form"] = lambda m: _expand_loop(source, m, True)
    times = {name: [] for name in cases}
    for run in cases.values():
        run(masks[:16])  # compile
    for _ in range(args.repeats):  # interleaved
        for name, run in cases.items():
            t0 = time.perf_counter()
            run(masks)
            times[name].append((time.perf_counter() - t0) / args.ops * 1e9)
    rows = [{"operation": name, "ns_median": round(statistics.median(t), 3), "ns_min": round(min(t), 3)} for name, t in times.items()]
    print_table(rows, ["operation", "ns_median", "ns_min"])
    path = write_results(args.name, rows, {"settings": {"ops": args.ops, "repeats": args.repeats, "avx512": HAS_AVX512,
                                                        "numba_threads": numba.get_num_threads()}})  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    run_main(main)
