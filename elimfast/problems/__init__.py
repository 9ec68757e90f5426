"""Problems: the Problem object and the built-in library (``PROBLEMS`` maps names to constructors)."""
from .base import Problem
from .fpu_beta import fpu_beta
from .henon_heiles import henon_heiles
from .kepler import kepler
from .nbody import nbody
from .oscillators import central_quartic, harmonic_oscillator, quartic_oscillator
from .pendulum import pendulum
from .perturbed_kepler import perturbed_kepler
from .toda import toda

PROBLEMS = {
    "kepler": kepler,
    "harmonic_oscillator": harmonic_oscillator,
    "quartic_oscillator": quartic_oscillator,
    "central_quartic": central_quartic,
    "perturbed_kepler": perturbed_kepler,
    "henon_heiles": henon_heiles,
    "fpu_beta": fpu_beta,
    "toda": toda,
    "nbody": nbody,
    "pendulum": pendulum,
}

__all__ = ["Problem", "PROBLEMS", "kepler", "harmonic_oscillator", "quartic_oscillator", "central_quartic",
           "perturbed_kepler", "henon_heiles", "fpu_beta", "toda", "nbody", "pendulum"]


def problem_from_expressions(*args, **kwargs) -> Problem:
    """A Problem from expression strings (see elimfast.problems.symbolic); sympy is imported only here."""
    from .symbolic import problem_from_expressions as build
    return build(*args, **kwargs)


def problem_from_file(*args, **kwargs) -> Problem:
    """A Problem from a user's Python file (see elimfast.problems.user_file)."""
    from .user_file import problem_from_file as build
    return build(*args, **kwargs)


__all__ += ["problem_from_expressions", "problem_from_file"]
