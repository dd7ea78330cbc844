"""bf16 dot products in numba kernels: 16 fp32 lanes, each accumulating a pair of bf16 products.

numba has no vector types and LLVM (through llvmlite) no ``bfloat`` type, so the AVX512-BF16
instruction ``vdpbf16ps`` is reached here through a small vector type (`neuralrt.simd16.f32x16`,
an LLVM ``<16 x float>`` held in registers) and inline assembly. On a CPU without AVX512-BF16 the same
intrinsic compiles to a portable emulation (the two bf16 halves widened to fp32 by shifts, two
fused multiply-adds), which is also available under its own name so that it is tested anywhere.
numba's cache is keyed on the CPU features it compiles for, so a kernel cached on one kind of CPU
is not reused on the other; ``NUMBA_CPU_FEATURES`` without ``+avx512bf16`` forces the emulation
(`neuralrt.simd.numba_targets`).

The layout: an input pair ``(x[2p], x[2p+1])`` is one uint32 (low half: ``x[2p]``, bf16 bits);
the weights of that pair for output column j are one uint32 ``w[p, j]`` (low half: the row
``2p``). ``acc[j] += x[2p] * w[2p, j] + x[2p+1] * w[2p+1, j]`` for 16 columns per instruction.
"""

from __future__ import annotations

import llvmlite.binding as llvm
import numba
import numpy as np
import torch
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, overload

from ..simd import broadcast, contiguous_1d, numba_targets, vector_pointer
from ..simd16 import f32x16, load16, store16

__all__ = ["HAS_AVX512_BF16", "f32x16", "zeros16", "load16", "store16", "dot_bf16_pairs", "dot_bf16_pairs_emulated",
           "bf16_bits", "bf16_pairs", "dot_rows_bf16", "fma_f32", "fma16", "bf16_value", "as_fp32", "add16",
           "leaky_relu16", "store_bf16x16", "load_bf16x16", "first_lanes16"]


# Where numba targets it (`numba_targets`), so ``NUMBA_CPU_FEATURES=<the host's, with -avx512bf16>``
# forces the emulation on any CPU, without stale cached kernels.
HAS_AVX512_BF16 = numba_targets("avx512bf16")
if HAS_AVX512_BF16:
    llvm.initialize_native_asmparser()  # numba's JIT does not: inline assembly needs it

_F32X16 = ir.VectorType(ir.FloatType(), 16)
_I32X16 = ir.VectorType(ir.IntType(32), 16)
_I16X16 = ir.VectorType(ir.IntType(16), 16)


@intrinsic
def zeros16(typingctx):
    """16 zero lanes."""

    def codegen(context, builder, sig, args):
        return ir.Constant(_F32X16, [0.0] * 16)

    return f32x16(), codegen


@intrinsic
def add16(typingctx, a, b):
    """``a + b`` per lane."""
    if not (a == f32x16 and b == f32x16):
        return None

    def codegen(context, builder, sig, args):
        return builder.fadd(args[0], args[1])

    return f32x16(f32x16, f32x16), codegen


@intrinsic
def leaky_relu16(typingctx, value, slope):
    """``value if value >= 0 else value * slope`` per lane (the scalar kernels' leaky ReLU; an fp32 ``slope``)."""
    if not (value == f32x16 and slope == types.float32):
        return None

    def codegen(context, builder, sig, args):
        v, s = args
        nonnegative = builder.fcmp_ordered(">=", v, ir.Constant(_F32X16, [0.0] * 16))
        return builder.select(nonnegative, v, builder.fmul(v, broadcast(builder, s, _F32X16)))

    return f32x16(f32x16, types.float32), codegen


@intrinsic
def first_lanes16(typingctx, value, count):
    """``value`` in lanes ``k < count``, zero in the others (``count`` an integer in [0, 16])."""
    if not (value == f32x16 and isinstance(count, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        n = broadcast(builder, context.cast(builder, args[1], sig.args[1], types.int32), _I32X16)
        kept = builder.icmp_signed("<", ir.Constant(_I32X16, list(range(16))), n)
        return builder.select(kept, args[0], ir.Constant(_F32X16, [0.0] * 16))

    return f32x16(f32x16, count), codegen


@intrinsic
def store_bf16x16(typingctx, array, start, value):
    """``array[start : start + 16] = value`` rounded to bf16 (the bits of `bf16_bits`, lane by
    lane; ``array`` 1D contiguous uint16, no bounds check)."""
    if not (contiguous_1d(array, types.uint16) and isinstance(start, types.Integer) and value == f32x16):
        return None

    def codegen(context, builder, sig, args):
        bits = builder.bitcast(args[2], _I32X16)
        sixteen = ir.Constant(_I32X16, [16] * 16)
        odd = builder.and_(builder.lshr(bits, sixteen), ir.Constant(_I32X16, [1] * 16))
        rounded = builder.lshr(builder.add(builder.add(bits, ir.Constant(_I32X16, [0x7FFF] * 16)), odd), sixteen)
        pointer = vector_pointer(context, builder, sig.args[0], args[0], args[1], _I16X16)
        builder.store(builder.trunc(rounded, _I16X16), pointer, align=2)
        return context.get_dummy_value()

    return types.void(array, types.intp, f32x16), codegen


@intrinsic
def load_bf16x16(typingctx, array, start):
    """``array[start : start + 16]`` (1D contiguous uint16, bf16 bits) widened to fp32 exactly (`bf16_value`)."""
    if not (contiguous_1d(array, types.uint16) and isinstance(start, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        halves = builder.load(vector_pointer(context, builder, sig.args[0], args[0], args[1], _I16X16), align=2)
        widened = builder.shl(builder.zext(halves, _I32X16), ir.Constant(_I32X16, [16] * 16))
        return builder.bitcast(widened, _F32X16)

    return f32x16(array, types.intp), codegen


@intrinsic
def fma16(typingctx, acc, x, array, start):
    """``acc + x * array[start : start + 16]`` per lane, one rounding (``x`` an fp32 scalar,
    broadcast; ``array`` 1D contiguous fp32; no bounds check)."""
    if not (acc == f32x16 and x == types.float32 and contiguous_1d(array, types.float32) and isinstance(start, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        acc_v, xs, array_v, start_v = args
        xv = broadcast(builder, xs, _F32X16)
        w = builder.load(vector_pointer(context, builder, sig.args[2], array_v, start_v, _F32X16), align=4)
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_F32X16, [_F32X16] * 3), "llvm.fma.v16f32")
        return builder.call(fma, [xv, w, acc_v])

    return f32x16(f32x16, types.float32, array, types.intp), codegen


@intrinsic
def fma_f32(typingctx, a, b, c):
    """``a * b + c`` in fp32 with one rounding (LLVM's fma; a vfmadd instruction on x86-64)."""
    if not (a == types.float32 and b == types.float32 and c == types.float32):
        return None

    def codegen(context, builder, sig, args):
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.FloatType(), [ir.FloatType()] * 3), "llvm.fma.f32")
        return builder.call(fma, list(args))

    return types.float32(types.float32, types.float32, types.float32), codegen


def _emulated(builder, acc, x, w):
    """``acc + lo(x) * lo(w) + hi(x) * hi(w)`` per lane, the bf16 halves widened to fp32 exactly
    (each product is exact in fp32; the order of the additions is vdpbf16ps's: high pair first)."""
    mask = ir.Constant(_I32X16, [0xFFFF0000] * 16)
    sixteen = ir.Constant(_I32X16, [16] * 16)
    lo_x, hi_x = builder.bitcast(builder.shl(x, sixteen), _F32X16), builder.bitcast(builder.and_(x, mask), _F32X16)
    lo_w, hi_w = builder.bitcast(builder.shl(w, sixteen), _F32X16), builder.bitcast(builder.and_(w, mask), _F32X16)
    fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_F32X16, [_F32X16] * 3), "llvm.fma.v16f32")
    return builder.call(fma, [lo_x, lo_w, builder.call(fma, [hi_x, hi_w, acc])])


def _dot_intrinsic(native: bool):
    def typer(typingctx, acc, x_pair, w_pairs, start):
        """``acc + x_pair . w_pairs[start : start + 16]`` per lane: ``x_pair`` a uint32 (two bf16),
        broadcast to all lanes; ``w_pairs`` 1D contiguous uint32 (two bf16 per column)."""
        if not (acc == f32x16 and isinstance(x_pair, types.Integer) and contiguous_1d(w_pairs, types.uint32)
                and isinstance(start, types.Integer)):  # fmt: skip
            return None

        def codegen(context, builder, sig, args):
            acc_v, x, w_array, start_v = args
            x32 = context.cast(builder, x, sig.args[1], types.uint32)
            xv = broadcast(builder, x32, _I32X16)
            w = builder.load(vector_pointer(context, builder, sig.args[2], w_array, start_v, _I32X16), align=4)
            if native:
                # AT&T order: vdpbf16ps src2, src1, dst  (dst += src1 . src2); $3 (acc) is tied to $0.
                fnty = ir.FunctionType(_F32X16, [_I32X16, _I32X16, _F32X16])
                return builder.asm(fnty, "vdpbf16ps $2, $1, $0", "=v,v,v,0", [xv, w, acc_v], False, name="dpbf16")
            return _emulated(builder, acc_v, xv, w)

        return f32x16(f32x16, x_pair, w_pairs, types.intp), codegen

    return typer


dot_bf16_pairs = intrinsic(_dot_intrinsic(HAS_AVX512_BF16))
dot_bf16_pairs.__doc__ = "``vdpbf16ps`` where the host has AVX512-BF16, else `dot_bf16_pairs_emulated`."
dot_bf16_pairs_emulated = intrinsic(_dot_intrinsic(False))


@intrinsic
def _f32_bits(typingctx, value):
    """The bits of an fp32 ``value`` as a uint32."""
    if value != types.float32:
        return None

    def codegen(context, builder, sig, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.uint32(types.float32), codegen


@intrinsic
def _bits_f32(typingctx, bits):
    """The fp32 value of the low 32 bits of the integer ``bits`` (32 or 64 bits wide)."""
    if not (isinstance(bits, types.Integer) and bits.bitwidth >= 32):
        return None

    def codegen(context, builder, sig, args):
        return builder.bitcast(builder.trunc(args[0], ir.IntType(32)) if bits.bitwidth > 32 else args[0], ir.FloatType())

    return types.float32(bits), codegen


@numba.njit(cache=True, inline="always")
def bf16_value(bits):
    """The fp32 value of bf16 ``bits`` (a uint16): exact, as torch's bf16 -> fp32."""
    return _bits_f32(np.uint32(bits) << np.uint32(16))  # (numba widens the shift to 64 bits)


def as_fp32(x):
    """``x`` as fp32 in a numba kernel that takes fp32 or bf16 arrays: fp32 as is, bf16 bits
    (uint16) widened exactly (`bf16_value`). Typed per call site by the overload below; plain
    Python never calls it."""
    raise NotImplementedError("as_fp32 is for numba kernels (an @overload)")


@overload(as_fp32, inline="always")
def _as_fp32_overload(x):
    if x == types.uint16:
        return lambda x: bf16_value(x)
    return lambda x: x


@numba.njit(cache=True, inline="always")
def bf16_bits(value):
    """The bf16 bits (a uint32 below 2^16) of fp32 ``value``, rounded to nearest even as torch's
    float -> bf16 (finite values)."""
    bits = _f32_bits(value)
    return (bits + np.uint32(0x7FFF) + ((bits >> np.uint32(16)) & np.uint32(1))) >> np.uint32(16)


def bf16_pairs(rows: np.ndarray) -> np.ndarray:
    """``[K, W]`` fp32 -> ``[ceil(K / 2), W]`` uint32: rows 2p and 2p + 1 rounded to bf16 (as torch)
    and packed into one word per column, row 2p in the low half (a zero row pads an odd K)."""
    k, width = rows.shape
    padded = np.zeros((k + k % 2, width), np.float32)
    padded[:k] = rows
    bits = torch.from_numpy(padded).to(torch.bfloat16).view(torch.int16).numpy().view(np.uint16).astype(np.uint32)
    return np.ascontiguousarray(bits[0::2] | (bits[1::2] << np.uint32(16)))


@numba.njit(cache=True)
def dot_rows_bf16(xp, rows, n_pairs, w, w_start, width, out):
    """``out[i * width + j] = sum(p < n_pairs) xp[rows[i], p] . w[w_start + p * width + j]`` for the
    4 rows ``rows[0..3]`` of ``xp`` (``[G, P]`` uint32 input pairs; a row may repeat) and ``width`` (a
    multiple of 16) columns of the weights at ``w_start`` of ``w`` (flat uint32 weight pairs, ``[P *
    width]`` from there: a layer of several stored in one array); ``out`` flat fp32.

    Register-blocked: 4 rows x 64 columns (16 accumulators) per pass over the pairs, so each
    weight vector loaded serves 4 rows (the weights are read once per 4 rows, not once per row)."""
    r0, r1, r2, r3 = rows[0], rows[1], rows[2], rows[3]
    c = 0
    while c + 64 <= width:
        a00, a01, a02, a03 = zeros16(), zeros16(), zeros16(), zeros16()
        a10, a11, a12, a13 = zeros16(), zeros16(), zeros16(), zeros16()
        a20, a21, a22, a23 = zeros16(), zeros16(), zeros16(), zeros16()
        a30, a31, a32, a33 = zeros16(), zeros16(), zeros16(), zeros16()
        for p in range(n_pairs):
            k = w_start + p * width + c
            x0, x1, x2, x3 = xp[r0, p], xp[r1, p], xp[r2, p], xp[r3, p]
            a00, a01 = dot_bf16_pairs(a00, x0, w, k), dot_bf16_pairs(a01, x0, w, k + 16)
            a02, a03 = dot_bf16_pairs(a02, x0, w, k + 32), dot_bf16_pairs(a03, x0, w, k + 48)
            a10, a11 = dot_bf16_pairs(a10, x1, w, k), dot_bf16_pairs(a11, x1, w, k + 16)
            a12, a13 = dot_bf16_pairs(a12, x1, w, k + 32), dot_bf16_pairs(a13, x1, w, k + 48)
            a20, a21 = dot_bf16_pairs(a20, x2, w, k), dot_bf16_pairs(a21, x2, w, k + 16)
            a22, a23 = dot_bf16_pairs(a22, x2, w, k + 32), dot_bf16_pairs(a23, x2, w, k + 48)
            a30, a31 = dot_bf16_pairs(a30, x3, w, k), dot_bf16_pairs(a31, x3, w, k + 16)
            a32, a33 = dot_bf16_pairs(a32, x3, w, k + 32), dot_bf16_pairs(a33, x3, w, k + 48)
        store16(out, c, a00), store16(out, c + 16, a01), store16(out, c + 32, a02), store16(out, c + 48, a03)
        o = width + c
        store16(out, o, a10), store16(out, o + 16, a11), store16(out, o + 32, a12), store16(out, o + 48, a13)
        o += width
        store16(out, o, a20), store16(out, o + 16, a21), store16(out, o + 32, a22), store16(out, o + 48, a23)
        o += width
        store16(out, o, a30), store16(out, o + 16, a31), store16(out, o + 32, a32), store16(out, o + 48, a33)
        c += 64
    while c + 16 <= width:
        a0, a1, a2, a3 = zeros16(), zeros16(), zeros16(), zeros16()
        for p in range(n_pairs):
            k = w_start + p * width + c
            a0, a1 = dot_bf16_pairs(a0, xp[r0, p], w, k), dot_bf16_pairs(a1, xp[r1, p], w, k)
            a2, a3 = dot_bf16_pairs(a2, xp[r2, p], w, k), dot_bf16_pairs(a3, xp[r3, p], w, k)
        store16(out, c, a0), store16(out, width + c, a1), store16(out, 2 * width + c, a2), store16(out, 3 * width + c, a3)
        c += 16
