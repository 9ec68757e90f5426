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


def __getattr__(name):
    """elimfast.problems.kepler etc.: the constructor, imported on first use."""
    if name in BUILTINS:
        constructor = _constructor(name)
        globals()[name] = constructor
        return constructor
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(BUILTINS))


class _Package(types.ModuleType):
    """Keeps ``elimfast.problems.<name>`` the constructor (as the eager imports of before made it):
    importing the submodule ``elimfast.problems.kepler`` would otherwise set the package's
    attribute ``kepler`` to the module."""

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and name in BUILTINS and hasattr(value, name):
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


def problem_from_expressions(*args, **kwargs) -> Problem:
    """A Problem from expression strings (see elimfast.problems.symbolic); sympy is imported only here."""
    from .symbolic import problem_from_expressions as build
    return build(*args, **kwargs)


def problem_from_file(*args, **kwargs) -> Problem:
    """A Problem from a user's Python file (see elimfast.problems.user_file)."""
    from .user_file import problem_from_file as build
    return build(*args, **kwargs)


__all__ += ["problem_from_expressions", "problem_from_file"]
