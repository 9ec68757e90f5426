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
import pickle

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
    """types.Dispatcher whose value is never used: calls resolve at compile time.

    Pickled into the Numba cache indexes of every cached function a per-problem kernel calls
    with it (solver.newton_factor, stepper.restore_newton_matrix, ...), as part of their
    signatures. Numba unpickles a whole index to look up any one signature, so a type that
    cannot be rebuilt, because its function lives in a module that this process has not
    loaded (a ``python:`` file's or an expression problem's module in elimfast's cache),
    would make every later compilation that consults the index fail (a user trial: the
    per-problem kernel of built-in Kepler, after one for a ``python:`` file, "No module
    named 'elimfast_user_...'"). Such a type is rebuilt as an UnresolvedStaticFunctionType
    instead, which matches no live type: a cache miss for that entry, nothing more."""

    def __reduce__(self):
        function = getattr(self.dispatcher, "py_func", None)
        label = f"{getattr(function, '__module__', '?')}.{getattr(function, '__qualname__', '?')}"
        return _static_function_type, (pickle.dumps(super().__reduce__()), label)


class UnresolvedStaticFunctionType(types.Opaque):
    """A StaticFunctionType of an index entry whose function cannot be loaded in this process."""

    def __init__(self, label):
        super().__init__(f"unresolved static function {label}")


def _static_function_type(payload, label):
    try:
        rebuild, arguments = pickle.loads(payload)
        return rebuild(*arguments)
    except Exception:   # noqa: BLE001 -- any failure to rebuild it leaves an entry that matches nothing
        return UnresolvedStaticFunctionType(label)


@typeof_impl.register(StaticFunction)
def _typeof_static_function(value, context):
    return StaticFunctionType(value.dispatcher)


register_model(StaticFunctionType)(models.OpaqueModel)


@lower_constant(StaticFunctionType)
def _lower_static_function(context, builder, typ, value):
    # no address of a Python object in the code: the kernel stays cacheable
    return context.get_constant_null(typ)
