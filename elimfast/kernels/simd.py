"""Four doubles in one vector register: lane-wise IEEE operations for the maps' hot loops.

Numba leaves LLVM's SLP vectorizer off (numba.core.config.SLP_VECTORIZE = 0), and its loop
vectorizer does not take the maps' loops (short runtime trip counts, and the sums are
reductions it may not reorder without fastmath). So four independent sums written as four
scalar accumulators (maps.project) compiled to scalar code. ``Double4`` is LLVM's
``<4 x double>``: each lane does exactly the scalar operation (an IEEE multiply or add,
never fused or reordered), so the results are the scalar code's, bit for bit, in about
half the instructions. Measured (maps.project, the three projections of EHBVM(12,3) on
Kepler): 456 -> 210 ns per map evaluation.

Each operation is a plain Python function (what runs under NUMBA_DISABLE_JIT=1: NumPy
arrays of 4, elementwise, the same IEEE operations) with a compiled overload (an intrinsic
emitting the vector instruction). Loads and stores take 4 consecutive elements of a
C-contiguous float64 array (no bounds check, no negative-index wraparound: the callers'
indices are in range by construction).
"""
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, overload, register_model


class Double4(types.Type):
    """Four float64 lanes (LLVM <4 x double>)."""

    def __init__(self):
        super().__init__(name="Double4")


double4 = Double4()
_VECTOR = ir.VectorType(ir.DoubleType(), 4)


@register_model(Double4)
class _Double4Model(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, _VECTOR)


def _pointer(context, builder, array_type, array, indices):
    view = context.make_array(array_type)(context, builder, array)
    pointer = cgutils.get_item_pointer(context, builder, array_type, view, indices, wraparound=False,
                                       boundscheck=False)
    return builder.bitcast(pointer, _VECTOR.as_pointer())


def _is_float_array(array, ndim):
    return (isinstance(array, types.Array) and array.ndim == ndim and array.dtype == types.float64
            and array.layout == "C")


@intrinsic
def _load(typingctx, array, index):
    if not _is_float_array(array, 1):
        return None

    def codegen(context, builder, signature, args):
        return builder.load(_pointer(context, builder, signature.args[0], args[0], [args[1]]), align=8)
    return double4(array, index), codegen


@intrinsic
def _load_row(typingctx, array, row, index):
    if not _is_float_array(array, 2):
        return None

    def codegen(context, builder, signature, args):
        return builder.load(_pointer(context, builder, signature.args[0], args[0], [args[1], args[2]]), align=8)
    return double4(array, row, index), codegen


@intrinsic
def _store_row(typingctx, array, row, index, value):
    if not _is_float_array(array, 2) or value != double4:
        return None

    def codegen(context, builder, signature, args):
        builder.store(args[3], _pointer(context, builder, signature.args[0], args[0], [args[1], args[2]]), align=8)
        return context.get_dummy_value()
    return types.void(array, row, index, value), codegen


@intrinsic
def _store(typingctx, array, index, value):
    if not _is_float_array(array, 1) or value != double4:
        return None

    def codegen(context, builder, signature, args):
        builder.store(args[2], _pointer(context, builder, signature.args[0], args[0], [args[1]]), align=8)
        return context.get_dummy_value()
    return types.void(array, index, value), codegen


@intrinsic
def _splat(typingctx, x):
    if not isinstance(x, types.Float):
        return None

    def codegen(context, builder, signature, args):
        value = context.cast(builder, args[0], signature.args[0], types.float64)
        undefined = ir.Constant(_VECTOR, ir.Undefined)
        first = builder.insert_element(undefined, value, ir.Constant(ir.IntType(32), 0))
        return builder.shuffle_vector(first, undefined, ir.Constant(ir.VectorType(ir.IntType(32), 4), [0, 0, 0, 0]))
    return double4(x), codegen


@intrinsic
def _mul(typingctx, a, b):
    if a != double4 or b != double4:
        return None

    def codegen(context, builder, signature, args):
        return builder.fmul(args[0], args[1])
    return double4(a, b), codegen


@intrinsic
def _add(typingctx, a, b):
    if a != double4 or b != double4:
        return None

    def codegen(context, builder, signature, args):
        return builder.fadd(args[0], args[1])
    return double4(a, b), codegen


def _is_complex_array(array, ndim):
    return (isinstance(array, types.Array) and array.ndim == ndim and array.dtype == types.complex128
            and array.layout == "C")


@intrinsic
def _load_pair_row(typingctx, array, row, index):
    if not _is_complex_array(array, 2):
        return None

    def codegen(context, builder, signature, args):
        return builder.load(_pointer(context, builder, signature.args[0], args[0], [args[1], args[2]]), align=8)
    return double4(array, row, index), codegen


@intrinsic
def _store_pair_row(typingctx, array, row, index, value):
    if not _is_complex_array(array, 2) or value != double4:
        return None

    def codegen(context, builder, signature, args):
        builder.store(args[3], _pointer(context, builder, signature.args[0], args[0], [args[1], args[2]]), align=8)
        return context.get_dummy_value()
    return types.void(array, row, index, value), codegen


@intrinsic
def _swap_pairs(typingctx, a):
    if a != double4:
        return None

    def codegen(context, builder, signature, args):
        mask = ir.Constant(ir.VectorType(ir.IntType(32), 4), [1, 0, 3, 2])
        return builder.shuffle_vector(args[0], ir.Constant(_VECTOR, ir.Undefined), mask)
    return double4(a), codegen


@intrinsic
def _addsub(typingctx, a, b):
    if a != double4 or b != double4:
        return None

    def codegen(context, builder, signature, args):
        difference = builder.fsub(args[0], args[1])
        total = builder.fadd(args[0], args[1])
        mask = ir.Constant(ir.VectorType(ir.IntType(32), 4), [0, 5, 2, 7])
        return builder.shuffle_vector(difference, total, mask)
    return double4(a, b), codegen


@intrinsic
def _load_dup_row(typingctx, array, row, index):
    if not _is_float_array(array, 2):
        return None

    def codegen(context, builder, signature, args):
        view = context.make_array(signature.args[0])(context, builder, args[0])
        pointer = cgutils.get_item_pointer(context, builder, signature.args[0], view, [args[1], args[2]],
                                           wraparound=False, boundscheck=False)
        pair_type = ir.VectorType(ir.DoubleType(), 2)
        pair = builder.load(builder.bitcast(pointer, pair_type.as_pointer()), align=8)
        mask = ir.Constant(ir.VectorType(ir.IntType(32), 4), [0, 0, 1, 1])
        return builder.shuffle_vector(pair, ir.Constant(pair_type, ir.Undefined), mask)
    return double4(array, row, index), codegen


@intrinsic
def _pair(typingctx, a, b):
    if not isinstance(a, types.Float) or not isinstance(b, types.Float):
        return None

    def codegen(context, builder, signature, args):
        vector = ir.Constant(_VECTOR, ir.Undefined)
        first = context.cast(builder, args[0], signature.args[0], types.float64)
        second = context.cast(builder, args[1], signature.args[1], types.float64)
        for lane, value in enumerate((first, second, first, second)):
            vector = builder.insert_element(vector, value, ir.Constant(ir.IntType(32), lane))
        return vector
    return double4(a, b), codegen


@intrinsic
def _abs(typingctx, a):
    if a != double4:
        return None

    def codegen(context, builder, signature, args):
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_VECTOR, [_VECTOR]), "llvm.fabs.v4f64")
        return builder.call(fabs, [args[0]])
    return double4(a), codegen


@intrinsic
def _raise_to(typingctx, largest, value):
    if largest != double4 or value != double4:
        return None

    def codegen(context, builder, signature, args):
        keep = builder.fcmp_ordered("<=", args[1], args[0])
        return builder.select(keep, args[0], args[1])
    return double4(largest, value), codegen


@intrinsic
def _sub(typingctx, a, b):
    if a != double4 or b != double4:
        return None

    def codegen(context, builder, signature, args):
        return builder.fsub(args[0], args[1])
    return double4(a, b), codegen


@intrinsic
def _div(typingctx, a, b):
    if a != double4 or b != double4:
        return None

    def codegen(context, builder, signature, args):
        return builder.fdiv(args[0], args[1])
    return double4(a, b), codegen


def load4(array, index):
    """array[index:index + 4] (1-D)."""
    return np.array(array[index:index + 4])


def load4_row(array, row, index):
    """array[row, index:index + 4] (2-D)."""
    return np.array(array[row, index:index + 4])


def store4_row(array, row, index, value):
    """array[row, index:index + 4] = value (2-D)."""
    array[row, index:index + 4] = value


def store4(array, index, value):
    """array[index:index + 4] = value (1-D)."""
    array[index:index + 4] = value


def load_pair_row(array, row, index):
    """array[row, index:index + 2] of a complex array, as (re, im, re, im)."""
    return np.array(array[row, index:index + 2]).view(np.float64).copy()


def store_pair_row(array, row, index, value):
    """array[row, index:index + 2] = value, a complex pair given as (re, im, re, im)."""
    array[row, index:index + 2] = np.ascontiguousarray(value, dtype=np.float64).view(np.complex128)


def swap_pairs4(a):
    """(a1, a0, a3, a2)."""
    return np.array([a[1], a[0], a[3], a[2]])


def addsub4(a, b):
    """(a0 - b0, a1 + b1, a2 - b2, a3 + b3): the parts of a complex product of two lanes' pairs."""
    return np.array([a[0] - b[0], a[1] + b[1], a[2] - b[2], a[3] + b[3]])


def load4_dup_row(array, row, index):
    """(array[row, index], array[row, index], array[row, index + 1], array[row, index + 1]) (2-D)."""
    return np.repeat(array[row, index:index + 2], 2)


def pair4(a, b):
    """(a, b, a, b)."""
    return np.array([a, b, a, b], dtype=np.float64)


def abs4(a):
    """|a| lane by lane (exact)."""
    return np.abs(a)


def raise4(largest, value):
    """Lane by lane, largest if value <= largest else value (so value where it is NaN): the
    scalar loops' ``if not (value <= largest): largest = value``."""
    return np.where(value <= largest, largest, value)


def splat4(x):
    """x in every lane."""
    return np.full(4, x)


def mul4(a, b):
    """a * b lane by lane (one IEEE product each)."""
    return a * b


def add4(a, b):
    """a + b lane by lane (one IEEE sum each)."""
    return a + b


def sub4(a, b):
    """a - b lane by lane (one IEEE difference each)."""
    return a - b


def div4(a, b):
    """a / b lane by lane (one IEEE quotient each)."""
    return a / b


# Plain overloads, compiled as small functions of their own that LLVM inlines (the same machine
# code as inlined ones, measured). Not inline="always": with Numba's inlining of overloads, a
# benchmark calling maps.elim_map lost its own writes to work.h_powers made before the call (zeros
# read back at once), while the same code with these plain overloads is right.
# Each implementation is a function with a name of its own, never a lambda: Numba names a compiled
# function by its qualified name, argument types and a counter of the process that compiled it, and
# links cached functions by those names. Lambdas all share the name <lambda>, and two of them with
# the same argument types, compiled in two processes sharing a cache (a test run beside a kernel
# warm-up), can get the same name: the linker then keeps one body for both. Measured: raise4 read
# from such a cache ran div4's code (0 / value), and _secant_update returned d = 0.
_OPTIONS = {"cache": True}


def _load4_impl(array, index):
    return _load(array, index)


overload(load4, jit_options=_OPTIONS)(lambda array, index: _load4_impl)


def _load4_row_impl(array, row, index):
    return _load_row(array, row, index)


overload(load4_row, jit_options=_OPTIONS)(lambda array, row, index: _load4_row_impl)


def _store4_row_impl(array, row, index, value):
    return _store_row(array, row, index, value)


overload(store4_row, jit_options=_OPTIONS)(lambda array, row, index, value: _store4_row_impl)


def _splat4_impl(x):
    return _splat(x)


overload(splat4, jit_options=_OPTIONS)(lambda x: _splat4_impl)


def _mul4_impl(a, b):
    return _mul(a, b)


overload(mul4, jit_options=_OPTIONS)(lambda a, b: _mul4_impl)


def _add4_impl(a, b):
    return _add(a, b)


overload(add4, jit_options=_OPTIONS)(lambda a, b: _add4_impl)


def _store4_impl(array, index, value):
    return _store(array, index, value)


overload(store4, jit_options=_OPTIONS)(lambda array, index, value: _store4_impl)


def _sub4_impl(a, b):
    return _sub(a, b)


overload(sub4, jit_options=_OPTIONS)(lambda a, b: _sub4_impl)


def _div4_impl(a, b):
    return _div(a, b)


overload(div4, jit_options=_OPTIONS)(lambda a, b: _div4_impl)


def _load_pair_row_impl(array, row, index):
    return _load_pair_row(array, row, index)


overload(load_pair_row, jit_options=_OPTIONS)(lambda array, row, index: _load_pair_row_impl)


def _store_pair_row_impl(array, row, index, value):
    return _store_pair_row(array, row, index, value)


overload(store_pair_row, jit_options=_OPTIONS)(lambda array, row, index, value: _store_pair_row_impl)


def _swap_pairs4_impl(a):
    return _swap_pairs(a)


overload(swap_pairs4, jit_options=_OPTIONS)(lambda a: _swap_pairs4_impl)


def _addsub4_impl(a, b):
    return _addsub(a, b)


overload(addsub4, jit_options=_OPTIONS)(lambda a, b: _addsub4_impl)


def _load4_dup_row_impl(array, row, index):
    return _load_dup_row(array, row, index)


overload(load4_dup_row, jit_options=_OPTIONS)(lambda array, row, index: _load4_dup_row_impl)


def _pair4_impl(a, b):
    return _pair(a, b)


overload(pair4, jit_options=_OPTIONS)(lambda a, b: _pair4_impl)


def _abs4_impl(a):
    return _abs(a)


overload(abs4, jit_options=_OPTIONS)(lambda a: _abs4_impl)


def _raise4_impl(largest, value):
    return _raise_to(largest, value)


overload(raise4, jit_options=_OPTIONS)(lambda largest, value: _raise4_impl)
