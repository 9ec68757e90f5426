"""Problems: the Problem object and the built-in library (``PROBLEMS`` maps names to constructors)."""
from .base import Problem
from .kepler import kepler
from .oscillators import central_quartic, harmonic_oscillator, quartic_oscillator

PROBLEMS = {
    "kepler": kepler,
    "harmonic_oscillator": harmonic_oscillator,
    "quartic_oscillator": quartic_oscillator,
    "central_quartic": central_quartic,
}

__all__ = ["Problem", "PROBLEMS", "kepler", "harmonic_oscillator", "quartic_oscillator", "central_quartic"]
