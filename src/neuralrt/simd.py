"""Eight-lane vectors in numba kernels: ``f64x8`` (float64), ``i64x8`` (int64) and ``m8`` (a mask).

numba has no vector types. These are LLVM's ``<8 x double>``, ``<8 x i64>`` and ``<8 x i1>`` held
in registers, with the arithmetic and comparison operators, selects, and LLVM's generic
gather/scatter/expand/compress intrinsics. Where the CPU has AVX-512 each is one instruction (or
a few); elsewhere LLVM lowers the same code to scalar loops, so kernels written with them are
correct on every CPU and tested anywhere (`lsnif_walk_simd` is used where ``HAS_AVX512``).

Arithmetic is IEEE per lane without fast-math flags (no contraction into fused multiply-adds), so
a lane computes exactly what the scalar code with the same operations computes. ``vmin``/``vmax``
are numba's ``min``/``max`` (``b if b < a else a``), lane by lane. Arrays are 1D and contiguous;
indices are not bounds-checked.
"""

from __future__ import annotations

import operator

import llvmlite.binding as llvm
import numba
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, overload, register_model

__all__ = ["HAS_AVX512", "numba_targets", "broadcast", "contiguous_1d", "element_pointer", "vector_pointer", "vector_load", "vector_store", "prefetch",
           "prefix_mask", "f64x8", "i64x8", "m8", "splat_f64", "splat_i64", "splat_m8", "lane_index", "select", "vmin", "vmax", "bits8", "popcount8",
           "to_f64", "floor_i64", "load_f64", "gather_f64", "gather_i32", "scatter_i64", "expand_f64", "expand_i64", "compress_store_f32",
           "compress_store_f64", "compress_store_i64", "prefetch_row"]  # fmt: skip


def numba_targets(*features: str) -> bool:
    """Whether numba compiles for every one of ``features`` (LLVM names, e.g. ``"avx512f"``): the
    CPU features it targets, ``NUMBA_CPU_FEATURES`` where set (numba keys its cache on them, so a
    path can be forced off on any CPU without stale cached kernels), else the host's."""
    if numba.config.CPU_FEATURES is not None:
        targeted = numba.config.CPU_FEATURES.split(",")
        return all(f"+{name}" in targeted for name in features)
    try:
        host = llvm.get_host_cpu_features()
    except RuntimeError:  # features unknown on this host: the portable paths
        return False
    return all(host.get(name, False) for name in features)


# F, DQ for 64-bit integer multiplies, VL
HAS_AVX512 = numba_targets("avx512f", "avx512dq", "avx512vl")

_I1, _I8, _I32, _I64 = ir.IntType(1), ir.IntType(8), ir.IntType(32), ir.IntType(64)
_F64X8 = ir.VectorType(ir.DoubleType(), 8)
_F32X8 = ir.VectorType(ir.FloatType(), 8)
_I64X8 = ir.VectorType(_I64, 8)
_I32X8 = ir.VectorType(_I32, 8)
_M8 = ir.VectorType(_I1, 8)


class F64x8(types.Type):
    def __init__(self):
        super().__init__(name="f64x8")


class I64x8(types.Type):
    def __init__(self):
        super().__init__(name="i64x8")


class M8(types.Type):
    def __init__(self):
        super().__init__(name="m8")


f64x8, i64x8, m8 = F64x8(), I64x8(), M8()


def _model(ir_type):
    class _Model(models.PrimitiveModel):
        def __init__(self, dmm, fe_type):
            super().__init__(dmm, fe_type, ir_type)

    return _Model


register_model(F64x8)(_model(_F64X8))
register_model(I64x8)(_model(_I64X8))
register_model(M8)(_model(_M8))


def broadcast(builder, scalar, vector_type):
    """``scalar`` in every lane of ``vector_type`` (IR)."""
    lane0 = builder.insert_element(ir.Constant(vector_type, None), scalar, ir.Constant(_I32, 0))
    every_lane = ir.Constant(ir.VectorType(_I32, vector_type.count), [0] * vector_type.count)
    return builder.shuffle_vector(lane0, ir.Constant(vector_type, None), every_lane)


def contiguous_1d(array, dtype) -> bool:
    """Typing: ``array`` is a 1D C-contiguous numba array of ``dtype``."""
    return isinstance(array, types.Array) and array.ndim == 1 and array.layout == "C" and array.dtype == dtype


def element_pointer(context, builder, array_type, array, start):
    """Pointer to ``array[start]`` (1D, contiguous; ``start`` an intp value) (IR)."""
    data = context.make_array(array_type)(context, builder, array)
    return builder.gep(data.data, [start])


def vector_pointer(context, builder, array_type, array, start, vector_type):
    """`element_pointer` as a pointer to ``vector_type`` (IR)."""
    return builder.bitcast(element_pointer(context, builder, array_type, array, start), vector_type.as_pointer())


def vector_load(element, vector, vector_type, align):
    """An intrinsic ``load(array, start)``: ``array[start : start + lanes]`` as one ``vector`` (the
    numba type; ``vector_type`` its IR type) from a 1D contiguous array of ``element``, no bounds
    check."""

    @intrinsic
    def load(typingctx, array, start):
        if not (contiguous_1d(array, element) and isinstance(start, types.Integer)):
            return None

        def codegen(context, builder, sig, args):
            return builder.load(vector_pointer(context, builder, sig.args[0], args[0], args[1], vector_type), align=align)

        return vector(array, types.intp), codegen

    return load


def vector_store(element, vector, vector_type, align):
    """An intrinsic ``store(array, start, value)``: ``array[start : start + lanes] = value`` (a
    ``vector``; ``vector_type`` its IR type) into a 1D contiguous array of ``element``, no bounds
    check: `vector_load`'s counterpart."""

    @intrinsic
    def store(typingctx, array, start, value):
        if not (contiguous_1d(array, element) and isinstance(start, types.Integer) and value == vector):
            return None

        def codegen(context, builder, sig, args):
            builder.store(args[2], vector_pointer(context, builder, sig.args[0], args[0], args[1], vector_type), align=align)
            return context.get_dummy_value()

        return types.void(array, types.intp, vector), codegen

    return store


def _lane_pointers(context, builder, array_type, array, index, element):
    """``&array[index[k]]`` per lane."""
    data = context.make_array(array_type)(context, builder, array)
    base = broadcast(builder, builder.ptrtoint(data.data, _I64), _I64X8)
    size = context.get_abi_sizeof(context.get_data_type(array_type.dtype))
    addresses = builder.add(base, builder.mul(index, ir.Constant(_I64X8, [size] * 8)))
    return builder.inttoptr(addresses, ir.VectorType(element.as_pointer(), 8))


def _llvm_function(builder, name, ret, arguments):
    return cgutils.get_or_insert_function(builder.module, ir.FunctionType(ret, arguments), name)


def prefetch(builder, pointer) -> None:
    """LLVM's prefetch of ``pointer``'s cache line: read, high temporal locality, data cache (IR)."""
    i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
    fn = _llvm_function(builder, "llvm.prefetch.p0i8", ir.VoidType(), [i8p, i32, i32, i32])
    builder.call(fn, [builder.bitcast(pointer, i8p), i32(0), i32(3), i32(1)])


@intrinsic
def prefetch_row(typingctx, array, row):
    """A hint: start loading the cache line of ``array[row, 0]`` (``array[row]`` for a 1D array)
    now (LLVM's prefetch: read, high temporal locality, data cache). Rows read in random order (a
    mesh's faces, a hash table's entries) otherwise each wait for memory in turn; issued a few rows
    ahead, their loads overlap."""
    if not (isinstance(array, types.Array) and isinstance(row, types.Integer)):
        return None

    def codegen(context, builder, sig, args):
        array_type = sig.args[0]
        data = context.make_array(array_type)(context, builder, args[0])
        index = [context.cast(builder, args[1], sig.args[1], types.intp)] + [context.get_constant(types.intp, 0)] * (array_type.ndim - 1)
        prefetch(builder, cgutils.get_item_pointer(context, builder, array_type, data, index, wraparound=False))
        return context.get_dummy_value()

    return types.void(array, row), codegen


def _splat(accepted, scalar_type, vector, vector_type):
    @intrinsic
    def splat(typingctx, x):
        if not isinstance(x, accepted):
            return None

        def codegen(context, builder, sig, args):
            return broadcast(builder, context.cast(builder, args[0], sig.args[0], scalar_type), vector_type)

        return vector(x), codegen

    return splat


splat_f64 = _splat(types.Float, types.float64, f64x8, _F64X8)
splat_f64.__doc__ = "``x`` (a float) in all 8 lanes."
splat_i64 = _splat(types.Integer, types.int64, i64x8, _I64X8)
splat_i64.__doc__ = "``x`` (an integer) in all 8 lanes."


def _splat_mask(mask, mask_type):
    @intrinsic
    def splat(typingctx, x):
        if not isinstance(x, types.Boolean):
            return None

        def codegen(context, builder, sig, args):
            bit = builder.icmp_unsigned("!=", context.cast(builder, args[0], sig.args[0], types.int8), ir.Constant(_I8, 0))
            return broadcast(builder, bit, mask_type)

        return mask(x), codegen

    return splat


splat_m8 = _splat_mask(m8, _M8)
splat_m8.__doc__ = "``x`` (a bool) in all 8 lanes."


def _lane_index(vector, vector_type):
    @intrinsic
    def lane_index(typingctx):
        def codegen(context, builder, sig, args):
            return ir.Constant(vector_type, list(range(vector_type.count)))

        return vector(), codegen

    lane_index.__doc__ = f"0, 1, ..., {vector_type.count - 1}: each lane's index."
    return lane_index


lane_index = _lane_index(i64x8, _I64X8)


def _binary_intrinsic(operand, result, emit):
    @intrinsic
    def op(typingctx, a, b):
        if not (a == operand and b == operand):
            return None

        def codegen(context, builder, sig, args):
            return emit(builder, args[0], args[1])

        return result(operand, operand), codegen

    return op


def _register_binary(pyop, cases):
    """``pyop`` on two vectors of one type: ``cases`` maps the type to (result type, IR emitter)."""
    table = {operand: _binary_intrinsic(operand, result, emit) for operand, (result, emit) in cases.items()}

    @overload(pyop)
    def _overload(a, b):
        fn = table.get(a)
        if fn is not None and a == b:
            return lambda a, b: fn(a, b)


_register_binary(operator.add, {f64x8: (f64x8, lambda b, x, y: b.fadd(x, y)), i64x8: (i64x8, lambda b, x, y: b.add(x, y))})
_register_binary(operator.sub, {f64x8: (f64x8, lambda b, x, y: b.fsub(x, y)), i64x8: (i64x8, lambda b, x, y: b.sub(x, y))})
_register_binary(operator.mul, {f64x8: (f64x8, lambda b, x, y: b.fmul(x, y)), i64x8: (i64x8, lambda b, x, y: b.mul(x, y))})
_register_binary(operator.truediv, {f64x8: (f64x8, lambda b, x, y: b.fdiv(x, y))})
_register_binary(operator.and_, {m8: (m8, lambda b, x, y: b.and_(x, y)), i64x8: (i64x8, lambda b, x, y: b.and_(x, y))})
_register_binary(operator.rshift, {i64x8: (i64x8, lambda b, x, y: b.lshr(x, y))})  # logical: for non-negative values
_register_binary(operator.or_, {m8: (m8, lambda b, x, y: b.or_(x, y))})
for _pyop, _predicate in ((operator.lt, "<"), (operator.gt, ">"), (operator.le, "<="), (operator.ge, ">="), (operator.eq, "=="),
                          (operator.ne, "!=")):  # fmt: skip
    # Ordered float comparisons: false where a lane is NaN, as Python's (``!=`` too, unlike Python; unused on NaN here)
    _register_binary(_pyop, {f64x8: (m8, lambda b, x, y, p=_predicate: b.fcmp_ordered(p, x, y)),
                             i64x8: (m8, lambda b, x, y, p=_predicate: b.icmp_signed(p, x, y))})  # fmt: skip


def _register_mask_not(mask):
    """``~a`` on masks of type ``mask``."""

    @intrinsic
    def mask_not(typingctx, a):
        if a != mask:
            return None

        def codegen(context, builder, sig, args):
            return builder.not_(args[0])

        return mask(mask), codegen

    @overload(operator.invert)
    def _invert(a):
        if a == mask:
            return lambda a: mask_not(a)


_register_mask_not(m8)


def _select(mask, vectors):
    @intrinsic
    def select(typingctx, m, a, b):
        if not (m == mask and a == b and a in vectors):
            return None

        def codegen(context, builder, sig, args):
            return builder.select(args[0], args[1], args[2])

        return a(mask, a, a), codegen

    select.__doc__ = "``a`` where ``mask``, else ``b``, per lane."
    return select


select = _select(m8, (f64x8, i64x8, m8))


@numba.njit(inline="always")
def vmin(a, b):
    """numba's ``min(a, b)`` per lane."""
    return select(b < a, b, a)


@numba.njit(inline="always")
def vmax(a, b):
    """numba's ``max(a, b)`` per lane."""
    return select(b > a, b, a)


def _mask_bits(builder, mask):
    """A mask (IR, up to 64 lanes) as an i64, lane k in bit k."""
    return builder.zext(builder.bitcast(mask, ir.IntType(mask.type.count)), _I64)


def _mask_reduction(mask, emit, doc):
    @intrinsic
    def reduce(typingctx, m):
        if m != mask:
            return None

        def codegen(context, builder, sig, args):
            return emit(builder, _mask_bits(builder, args[0]))

        return types.int64(mask), codegen

    reduce.__doc__ = doc
    return reduce


def _bits(mask):
    return _mask_reduction(mask, lambda builder, bits: bits, "The mask as an integer, lane k in bit k.")


def _popcount(mask):
    return _mask_reduction(mask, lambda builder, bits: builder.call(_llvm_function(builder, "llvm.ctpop.i64", _I64, [_I64]), [bits]),
                           "The number of lanes set.")  # fmt: skip


bits8, popcount8 = _bits(m8), _popcount(m8)


@intrinsic
def to_f64(typingctx, a):
    """``float(a)`` per lane."""
    if a != i64x8:
        return None

    def codegen(context, builder, sig, args):
        return builder.sitofp(args[0], _F64X8)

    return f64x8(i64x8), codegen


@intrinsic
def floor_i64(typingctx, a):
    """``int(floor(a))`` per lane (finite lanes; others undefined)."""
    if a != f64x8:
        return None

    def codegen(context, builder, sig, args):
        return builder.fptosi(builder.call(_llvm_function(builder, "llvm.floor.v8f64", _F64X8, [_F64X8]), [args[0]]), _I64X8)

    return i64x8(f64x8), codegen


load_f64 = vector_load(types.float64, f64x8, _F64X8, 8)
load_f64.__doc__ = "``array[start : start + 8]`` (float64)."


@intrinsic
def gather_f64(typingctx, array, index, mask, passthru):
    """``array[index[k]]`` in the lanes of ``mask``, ``passthru``'s elsewhere (float64)."""
    if not (contiguous_1d(array, types.float64) and index == i64x8 and mask == m8 and passthru == f64x8):
        return None

    def codegen(context, builder, sig, args):
        pointers = _lane_pointers(context, builder, sig.args[0], args[0], args[1], ir.DoubleType())
        fn = _llvm_function(builder, "llvm.masked.gather.v8f64.v8p0", _F64X8, [pointers.type, _I32, _M8, _F64X8])
        return builder.call(fn, [pointers, ir.Constant(_I32, 8), args[2], args[3]])

    return f64x8(array, i64x8, m8, f64x8), codegen


@intrinsic
def gather_i32(typingctx, array, index, mask):
    """``array[index[k]]`` (int32, widened) in the lanes of ``mask``, 0 elsewhere."""
    if not (contiguous_1d(array, types.int32) and index == i64x8 and mask == m8):
        return None

    def codegen(context, builder, sig, args):
        pointers = _lane_pointers(context, builder, sig.args[0], args[0], args[1], _I32)
        fn = _llvm_function(builder, "llvm.masked.gather.v8i32.v8p0", _I32X8, [pointers.type, _I32, _M8, _I32X8])
        return builder.sext(builder.call(fn, [pointers, ir.Constant(_I32, 4), args[2], ir.Constant(_I32X8, [0] * 8)]), _I64X8)

    return i64x8(array, i64x8, m8), codegen


@intrinsic
def scatter_i64(typingctx, array, index, value, mask):
    """``array[index[k]] = value[k]`` in the lanes of ``mask`` (int64; distinct indices)."""
    if not (contiguous_1d(array, types.int64) and index == i64x8 and value == i64x8 and mask == m8):
        return None

    def codegen(context, builder, sig, args):
        pointers = _lane_pointers(context, builder, sig.args[0], args[0], args[1], _I64)
        fn = _llvm_function(builder, "llvm.masked.scatter.v8i64.v8p0", ir.VoidType(), [_I64X8, pointers.type, _I32, _M8])
        builder.call(fn, [args[2], pointers, ir.Constant(_I32, 8), args[3]])
        return context.get_dummy_value()

    return types.void(array, i64x8, i64x8, m8), codegen


def _expand(dtype, vector_type, vector, name, mask=m8, mask_type=_M8):
    @intrinsic
    def expand(typingctx, array, start, m, passthru):
        if not (contiguous_1d(array, dtype) and isinstance(start, types.Integer) and m == mask and passthru == vector):
            return None

        def codegen(context, builder, sig, args):
            pointer = element_pointer(context, builder, sig.args[0], args[0], args[1])
            fn = _llvm_function(builder, name, vector_type, [pointer.type, mask_type, vector_type])
            return builder.call(fn, [pointer, args[2], args[3]])

        return vector(array, types.intp, mask, vector), codegen

    expand.__doc__ = (f"The lanes of ``mask`` take ``array[start], array[start + 1], ...`` in lane order ({dtype}), the "
                      "others ``passthru``'s: the inverse of a compress.")  # fmt: skip
    return expand


expand_f64 = _expand(types.float64, _F64X8, f64x8, "llvm.masked.expandload.v8f64")
expand_i64 = _expand(types.int64, _I64X8, i64x8, "llvm.masked.expandload.v8i64")


def prefix_mask(builder, mask):
    """The mask of the first ``popcount(mask)`` lanes of ``mask`` (an ``<N x i1>`` value) (IR)."""
    lanes = mask.type.count
    bits_type, wide = ir.IntType(lanes), ir.IntType(2 * lanes)  # (1 << count) - 1 with count == lanes in range
    count = builder.call(_llvm_function(builder, f"llvm.ctpop.i{lanes}", bits_type, [bits_type]), [builder.bitcast(mask, bits_type)])
    prefix = builder.sub(builder.shl(wide(1), builder.zext(count, wide)), wide(1))
    return builder.bitcast(builder.trunc(prefix, bits_type), mask.type)


def _compress_store(dtype, vector, store_type, name, convert, mask=m8, mask_type=_M8):
    """A compress store as LLVM's generic register compress, then a store masked to the first
    ``popcount(mask)`` lanes, rather than ``llvm.masked.compressstore``: AVX-512's memory form
    (``vpcompressd m, k, zmm``) is microcoded on AMD Zen 4: 22 ns a store against 1.5 ns for the
    register form and a masked store (`benchmarks/bench_simd_stores.py`, session 41; the memory
    form took ~3 cycles on Zen 5, session 37). ``name`` is the compress's LLVM intrinsic."""
    suffix = name.rsplit(".", 1)[1]  # the vector type's, e.g. v16f32

    @intrinsic
    def compress_store(typingctx, array, start, value, m):
        if not (contiguous_1d(array, dtype) and isinstance(start, types.Integer) and value == vector and m == mask):
            return None

        def codegen(context, builder, sig, args):
            pointer = element_pointer(context, builder, sig.args[0], args[0], args[1])
            compress = _llvm_function(builder, name, store_type, [store_type, mask_type, store_type])
            packed = builder.call(compress, [convert(builder, args[2]), args[3], ir.Constant(store_type, ir.Undefined)])
            store = _llvm_function(builder, f"llvm.masked.store.{suffix}.p0", ir.VoidType(), [store_type, pointer.type, _I32, mask_type])
            builder.call(store, [packed, pointer, ir.Constant(_I32, dtype.bitwidth // 8), prefix_mask(builder, args[3])])
            return context.get_dummy_value()

        return types.void(array, types.intp, vector, mask), codegen

    compress_store.__doc__ = (f"``array[start : start + popcount(mask)]`` = the lanes of ``mask``, in lane order ({dtype}); "
                              "nothing else is written.")  # fmt: skip
    return compress_store


compress_store_f64 = _compress_store(types.float64, f64x8, _F64X8, "llvm.experimental.vector.compress.v8f64", lambda b, v: v)
compress_store_i64 = _compress_store(types.int64, i64x8, _I64X8, "llvm.experimental.vector.compress.v8i64", lambda b, v: v)
# float32 outputs from float64 lanes, rounded to nearest (as numba's float64 -> float32 casts)
compress_store_f32 = _compress_store(types.float32, f64x8, _F32X8, "llvm.experimental.vector.compress.v8f32", lambda b, v: b.fptrunc(v, _F32X8))
