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


def load4(array, index):
    """array[index:index + 4] (1-D)."""
    return np.array(array[index:index + 4])


def load4_row(array, row, index):
    """array[row, index:index + 4] (2-D)."""
    return np.array(array[row, index:index + 4])


def store4_row(array, row, index, value):
    """array[row, index:index + 4] = value (2-D)."""
    array[row, index:index + 4] = value


def splat4(x):
    """x in every lane."""
    return np.full(4, x)


def mul4(a, b):
    """a * b lane by lane (one IEEE product each)."""
    return a * b


def add4(a, b):
    """a + b lane by lane (one IEEE sum each)."""
    return a + b


# Plain overloads, compiled as small functions of their own that LLVM inlines (the same machine
# code as inlined ones, measured). Not inline="always": with Numba's inlining of overloads, a
# benchmark calling maps.elim_map lost its own writes to work.h_powers made before the call (zeros
# read back at once), while the same code with these plain overloads is right.
_OPTIONS = {"cache": True}
overload(load4, jit_options=_OPTIONS)(lambda array, index: lambda array, index: _load(array, index))
overload(load4_row, jit_options=_OPTIONS)(
    lambda array, row, index: lambda array, row, index: _load_row(array, row, index))
overload(store4_row, jit_options=_OPTIONS)(
    lambda array, row, index, value: lambda array, row, index, value: _store_row(array, row, index, value))
overload(splat4, jit_options=_OPTIONS)(lambda x: lambda x: _splat(x))
overload(mul4, jit_options=_OPTIONS)(lambda a, b: lambda a, b: _mul(a, b))
overload(add4, jit_options=_OPTIONS)(lambda a, b: lambda a, b: _add(a, b))
