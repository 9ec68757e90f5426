"""Problems: the Problem object and the built-in library (``PROBLEMS`` maps names to constructors).

The built-ins load lazily: ``PROBLEMS["kepler"]``, ``elimfast.problems.kepler`` or
``from elimfast.problems import kepler`` imports (and so compiles, or loads from Numba's
cache) that one module on first use; ``import elimfast.problems`` imports no Numba at all.
Where each constructor lives and what listings say about it: ``catalogue.py``.
"""
import importlib
import sys
import types
from collections.abc import Mapping

from .base import Problem
from .catalogue import BUILTINS


def _constructor(name: str):
    module, _, function = BUILTINS[name].partition(":")
    return getattr(importlib.import_module(f"{__name__}.{module}"), function)


class BuiltinProblems(Mapping):
    """name -> constructor of every built-in problem, in listing order; a module is imported
    on the first lookup of one of its constructors (``targets`` says where each lives)."""

    targets = BUILTINS

    def __getitem__(self, name):
        if name not in BUILTINS:
            raise KeyError(name)
        return _constructor(name)

    def __iter__(self):
        return iter(BUILTINS)

    def __len__(self):
        return len(BUILTINS)

    def __contains__(self, name):
        return name in BUILTINS

    def __repr__(self):
        return f"BuiltinProblems({', '.join(BUILTINS)})"


PROBLEMS = BuiltinProblems()

__all__ = ["Problem", "PROBLEMS", *BUILTINS]


# The two builders of problems not built in -> their modules, imported on first use (sympy's
# module, and the kernels' signatures, cost start-up). The functions themselves are handed out, so
# help() shows their signatures (wrappers taking *args, **kwargs showed none).
BUILDERS = {"problem_from_expressions": "symbolic", "problem_from_file": "user_file"}


def __getattr__(name):
    """elimfast.problems.kepler etc.: the constructor, imported on first use; likewise the builders."""
    if name in BUILTINS or name in BUILDERS:
        constructor = (_constructor(name) if name in BUILTINS
                       else getattr(importlib.import_module(f"{__name__}.{BUILDERS[name]}"), name))
        globals()[name] = constructor
        return constructor
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(BUILTINS) | set(BUILDERS))


class _Package(types.ModuleType):
    """Keeps ``elimfast.problems.<name>`` the constructor (as the eager imports of before made it):
    importing the submodule ``elimfast.problems.kepler`` would otherwise set the package's
    attribute ``kepler`` to the module."""

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and name in BUILTINS and hasattr(value, name):
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


__all__ += list(BUILDERS)
