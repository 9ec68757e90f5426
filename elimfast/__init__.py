"""elimfast: invariant-conserving Hamiltonian integrators (GAUSS, HBVM, ELIM/EHBVM, LIM/GHBVM).

    import elimfast
    from elimfast.methods import ehbvm
    from elimfast.problems import kepler
    result = elimfast.integrate(kepler(0.6), ehbvm(12, 3), h=0.1, t_end=1000.0,
                                conserve=["angular_momentum", "lrl_y"])
"""
from importlib.metadata import PackageNotFoundError, version as _version

try:
    __version__ = _version("elimfast")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

from . import methods, problems
from .errors import ConvergenceError, ElimfastError
from .archive import load
from .integrate import Integration, Result, integrate

__all__ = ["__version__", "integrate", "load", "Integration", "Result", "ConvergenceError", "ElimfastError",
           "methods", "problems"]
