"""elimfast: invariant-conserving Hamiltonian integrators (GAUSS, HBVM, ELIM/EHBVM, LIM/GHBVM).

    import elimfast
    from elimfast.methods import ehbvm
    from elimfast.problems import kepler
    result = elimfast.integrate(kepler(0.6), ehbvm(12, 3), h=0.1, t_end=1000.0,
                                conserve=["angular_momentum", "lrl_y"])
"""
import sys
import types
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("elimfast")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

from . import methods, problems
from .errors import ConvergenceError, ElimfastError

__all__ = ["__version__", "integrate", "load", "open_datatree", "Integration", "Result", "SolverSettings",
           "ConvergenceError", "ElimfastError", "methods", "problems"]

# Imported on first use: they import the Numba kernels (about 0.2-0.4 s with a warm cache),
# which `import elimfast`, the CLI's listings and --help never need (open_datatree: xarray).
_LAZY = {"integrate": "integrate", "Integration": "integrate", "Result": "integrate", "load": "archive",
         "open_datatree": "io.xarray_tree", "SolverSettings": "integrate"}   # SolverSettings: integrate(solver=)


def __getattr__(name):
    if name in _LAZY:
        import importlib
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


class _Package(types.ModuleType):
    """Keeps ``elimfast.integrate`` the function (as the eager import of before made it): importing
    the submodule elimfast.integrate (elimfast.config does) would otherwise set the package's
    attribute to the module."""

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and _LAZY.get(name) == name:
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
