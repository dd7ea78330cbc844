"""Sixteen-lane vectors in numba kernels: ``f32x16`` (float32), ``i32x16`` (int32) and ``m16`` (a mask).

The 16-lane counterparts of `neuralrt.simd`'s 8-lane float64/int64 types (one AVX-512 register
each), for kernels whose values fit float32 and int32: twice the lanes per instruction. The same
conventions: IEEE arithmetic per lane without fast-math flags (no fused multiply-adds), ``vmin16``/
``vmax16`` as numba's ``min``/``max``, 1D contiguous arrays without bounds checks, and LLVM's
generic gather/scatter/expand/compress intrinsics (scalar loops where the CPU lacks AVX-512).
"""

from __future__ import annotations

import operator

import numba
from llvmlite import ir
from numba import types
from numba.extending import intrinsic, register_model

from .simd import (
    _bits, _compress_store, _expand, _lane_index, _llvm_function, _model, _popcount, _register_binary, _register_mask_not, _select,
    _splat, _splat_mask, contiguous_1d, i64x8, vector_load, vector_store,
)  # fmt: skip

__all__ = ["f32x16", "i32x16", "m16", "load16", "store16", "load16_i32", "store16_i32", "lane_index16", "splat_f32", "splat_i32",
           "splat_m16", "select16", "vmin16", "vmax16", "bits16", "popcount16", "to_f32", "gather16_i32", "gather16_f32",
           "scatter16_i32", "scatter16_f32", "scatter16_i64",
           "expand16_f32", "expand16_i32", "compress16_f32", "compress16_i32", "compress_store_i32"]  # fmt: skip

_I1, _I32, _I64 = ir.IntType(1), ir.IntType(32), ir.IntType(64)
_F32X16 = ir.VectorType(ir.FloatType(), 16)
_I32X16 = ir.VectorType(_I32, 16)
_I64X16 = ir.VectorType(_I64, 16)
_M16 = ir.VectorType(_I1, 16)
_I32X8 = ir.VectorType(_I32, 8)


class F32x16(types.Type):
    def __init__(self):
        super().__init__(name="f32x16")


class I32x16(types.Type):
    def __init__(self):
        super().__init__(name="i32x16")


class M16(types.Type):
    def __init__(self):
        super().__init__(name="m16")


f32x16, i32x16, m16 = F32x16(), I32x16(), M16()
register_model(F32x16)(_model(_F32X16))
register_model(I32x16)(_model(_I32X16))
register_model(M16)(_model(_M16))


load16 = vector_load(types.float32, f32x16, _F32X16, 4)
load16.__doc__ = "``array[start : start + 16]`` (1D contiguous fp32; no bounds check)."
load16_i32 = vector_load(types.int32, i32x16, _I32X16, 4)
load16_i32.__doc__ = "``array[start : start + 16]`` (1D contiguous int32; no bounds check)."

store16 = vector_store(types.float32, f32x16, _F32X16, 4)
store16.__doc__ = "``array[start : start + 16] = value`` (1D contiguous fp32; no bounds check)."
store16_i32 = vector_store(types.int32, i32x16, _I32X16, 4)
store16_i32.__doc__ = "``array[start : start + 16] = value`` (1D contiguous int32; no bounds check)."
lane_index16 = _lane_index(i32x16, _I32X16)


splat_f32 = _splat(types.Float, types.float32, f32x16, _F32X16)
splat_f32.__doc__ = "``x`` (a float, rounded to float32) in all 16 lanes."
splat_i32 = _splat(types.Integer, types.int32, i32x16, _I32X16)
splat_i32.__doc__ = "``x`` (an integer, as int32) in all 16 lanes."
splat_m16 = _splat_mask(m16, _M16)
splat_m16.__doc__ = "``x`` (a bool) in all 16 lanes."


_register_binary(operator.add, {f32x16: (f32x16, lambda b, x, y: b.fadd(x, y)), i32x16: (i32x16, lambda b, x, y: b.add(x, y))})
_register_binary(operator.sub, {f32x16: (f32x16, lambda b, x, y: b.fsub(x, y)), i32x16: (i32x16, lambda b, x, y: b.sub(x, y))})
_register_binary(operator.mul, {f32x16: (f32x16, lambda b, x, y: b.fmul(x, y)), i32x16: (i32x16, lambda b, x, y: b.mul(x, y))})
_register_binary(operator.truediv, {f32x16: (f32x16, lambda b, x, y: b.fdiv(x, y))})
_register_binary(operator.and_, {m16: (m16, lambda b, x, y: b.and_(x, y)), i32x16: (i32x16, lambda b, x, y: b.and_(x, y))})
_register_binary(operator.rshift, {i32x16: (i32x16, lambda b, x, y: b.lshr(x, y))})  # logical: for non-negative values
_register_binary(operator.or_, {m16: (m16, lambda b, x, y: b.or_(x, y))})
for _pyop, _predicate in ((operator.lt, "<"), (operator.gt, ">"), (operator.le, "<="), (operator.ge, ">="), (operator.eq, "=="),
                          (operator.ne, "!=")):  # fmt: skip
    # Ordered float comparisons: false where a lane is NaN
    _register_binary(_pyop, {f32x16: (m16, lambda b, x, y, p=_predicate: b.fcmp_ordered(p, x, y)),
                             i32x16: (m16, lambda b, x, y, p=_predicate: b.icmp_signed(p, x, y))})  # fmt: skip


_register_mask_not(m16)
select16 = _select(m16, (f32x16, i32x16, m16))


@numba.njit(inline="always")
def vmin16(a, b):
    """numba's ``min(a, b)`` per lane."""
    return select16(b < a, b, a)


@numba.njit(inline="always")
def vmax16(a, b):
    """numba's ``max(a, b)`` per lane."""
    return select16(b > a, b, a)


bits16, popcount16 = _bits(m16), _popcount(m16)


@intrinsic
def to_f32(typingctx, a):
    """``float32(a)`` per lane."""
    if a != i32x16:
        return None

    def codegen(context, builder, sig, args):
        return builder.sitofp(args[0], _F32X16)

    return f32x16(i32x16), codegen


class _VectorGEP(ir.Instruction):
    """``getelementptr`` with a vector of indices (llvmlite's builder takes scalar indices only):
    16 element pointers, which LLVM lowers to one gather/scatter with 32-bit indices."""

    def __init__(self, parent, pointer, index):
        super().__init__(parent, ir.VectorType(pointer.type, 16), "getelementptr", [pointer, index], name="")

    def descr(self, buf):
        pointer, index = self.operands
        buf.append(f"getelementptr inbounds {pointer.type.pointee}, {pointer.type} {pointer.get_reference()}, "
                   f"{index.type} {index.get_reference()}\n")  # fmt: skip


def _lane_pointers(context, builder, array_type, array, index):
    data = context.make_array(array_type)(context, builder, array)
    instruction = _VectorGEP(builder.block, data.data, index)
    builder._insert(instruction)
    return instruction


def _gather16(element, vector, vector_type, name):
    @intrinsic
    def gather(typingctx, array, index, mask):
        if not (contiguous_1d(array, element) and index == i32x16 and mask == m16):
            return None

        def codegen(context, builder, sig, args):
            pointers = _lane_pointers(context, builder, sig.args[0], args[0], args[1])
            fn = _llvm_function(builder, name, vector_type, [pointers.type, _I32, _M16, vector_type])
            return builder.call(fn, [pointers, ir.Constant(_I32, 4), args[2], ir.Constant(vector_type, [0] * 16)])

        return vector(array, i32x16, m16), codegen

    gather.__doc__ = f"``array[index[k]]`` ({element}) in the lanes of ``mask``, 0 elsewhere."
    return gather


gather16_i32 = _gather16(types.int32, i32x16, _I32X16, "llvm.masked.gather.v16i32.v16p0")
gather16_f32 = _gather16(types.float32, f32x16, _F32X16, "llvm.masked.gather.v16f32.v16p0")


def _scatter16(element, vector, vector_type, name):
    @intrinsic
    def scatter(typingctx, array, index, value, mask):
        if not (contiguous_1d(array, element) and index == i32x16 and value == vector and mask == m16):
            return None

        def codegen(context, builder, sig, args):
            pointers = _lane_pointers(context, builder, sig.args[0], args[0], args[1])
            fn = _llvm_function(builder, name, ir.VoidType(), [vector_type, pointers.type, _I32, _M16])
            builder.call(fn, [args[2], pointers, ir.Constant(_I32, 4), args[3]])
            return context.get_dummy_value()

        return types.void(array, i32x16, vector, m16), codegen

    scatter.__doc__ = f"``array[index[k]] = value[k]`` ({element}) in the lanes of ``mask`` (distinct indices)."
    return scatter


scatter16_f32 = _scatter16(types.float32, f32x16, _F32X16, "llvm.masked.scatter.v16f32.v16p0")
scatter16_i32 = _scatter16(types.int32, i32x16, _I32X16, "llvm.masked.scatter.v16i32.v16p0")


@intrinsic
def scatter16_i64(typingctx, array, index, value, mask):
    """``array[index[k]] = value[k]`` (widened to int64) in the lanes of ``mask`` (distinct indices)."""
    if not (contiguous_1d(array, types.int64) and index == i32x16 and value == i32x16 and mask == m16):
        return None

    def codegen(context, builder, sig, args):
        pointers = _lane_pointers(context, builder, sig.args[0], args[0], args[1])
        fn = _llvm_function(builder, "llvm.masked.scatter.v16i64.v16p0", ir.VoidType(), [_I64X16, pointers.type, _I32, _M16])
        builder.call(fn, [builder.sext(args[2], _I64X16), pointers, ir.Constant(_I32, 8), args[3]])
        return context.get_dummy_value()

    return types.void(array, i32x16, i32x16, m16), codegen


expand16_f32 = _expand(types.float32, _F32X16, f32x16, "llvm.masked.expandload.v16f32", m16, _M16)
expand16_i32 = _expand(types.int32, _I32X16, i32x16, "llvm.masked.expandload.v16i32", m16, _M16)


compress16_f32 = _compress_store(types.float32, f32x16, _F32X16, "llvm.experimental.vector.compress.v16f32", lambda b, v: v, m16, _M16)
compress16_i32 = _compress_store(types.int32, i32x16, _I32X16, "llvm.experimental.vector.compress.v16i32", lambda b, v: v, m16, _M16)
# int32 outputs from `neuralrt.simd`'s 8-lane int64 vectors (values that fit int32)
compress_store_i32 = _compress_store(types.int32, i64x8, _I32X8, "llvm.experimental.vector.compress.v8i32", lambda b, v: b.trunc(v, _I32X8))
