"""A compiled function as a compile-time constant of a kernel that Numba can still cache.

The per-problem kernel (elimfast/per_problem.py, docs/solver.md#per-problem-kernel) compiles
``stepper.time_loop`` once more with the problem's functions as constants instead of
``FunctionType`` arguments, so that LLVM may inline them into the stages and the map. Numba
types a global dispatcher passed as an argument as ``types.Dispatcher``: every call through
it is a direct call to the compiled function, but Numba also lowers the dispatcher *value*,
as the address of the Python object (``add_dynamic_addr``), and a function holding such an
address "uses dynamic globals" and is never cached: 100 s of compilation in every process.

``StaticFunction(dispatcher)`` is typed as ``StaticFunctionType``, a ``types.Dispatcher`` in
all but its constant: calls type and lower as the dispatcher's own (the same compiled
function, the same code), and its value is a null pointer that no call reads. A kernel must
not use such a value other than by calling it (no boxing to Python, no conversion to a
``FunctionType``): the null would then be dereferenced. elimfast's kernels only call them.
"""
from numba.core import types
from numba.core.datamodel import models
from numba.core.imputils import lower_constant
from numba.extending import register_model, typeof_impl


class StaticFunction:
    """A Numba dispatcher to be typed as a compile-time constant (StaticFunctionType)."""

    __slots__ = ("dispatcher",)

    def __init__(self, dispatcher):
        self.dispatcher = dispatcher


class StaticFunctionType(types.Dispatcher):
    """types.Dispatcher whose value is never used: calls resolve at compile time."""


@typeof_impl.register(StaticFunction)
def _typeof_static_function(value, context):
    return StaticFunctionType(value.dispatcher)


register_model(StaticFunctionType)(models.OpaqueModel)


@lower_constant(StaticFunctionType)
def _lower_static_function(context, builder, typ, value):
    # no address of a Python object in the code: the kernel stays cacheable
    return context.get_constant_null(typ)
