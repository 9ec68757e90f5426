"""The built-in problems as data: where each constructor lives, and what ``elimfast problems`` lists.

Importing a built-in module compiles (or loads from Numba's cache) its five functions,
a few milliseconds each and Numba's own start-up before the first: about 0.4 s for the
whole library. So the library is a lazy registry (``elimfast.problems.PROBLEMS``) that
imports a module on first use, and the listing of ``elimfast problems`` is read from
``LISTING`` below without importing any of them (no Numba at all).

A new built-in problem is its module plus one line in ``BUILTINS`` and one entry in
``LISTING``; tests/test_startup.py builds every problem and checks that ``LISTING``
says exactly what the built problem says (``listing_entry``), so the two cannot drift.
This module imports nothing heavy.
"""
from __future__ import annotations

import inspect
from typing import NamedTuple

# name -> "module:constructor" inside elimfast.problems, in the order listings show them.
BUILTINS = {
    "kepler": "kepler:kepler",
    "harmonic_oscillator": "oscillators:harmonic_oscillator",
    "quartic_oscillator": "oscillators:quartic_oscillator",
    "central_quartic": "oscillators:central_quartic",
    "perturbed_kepler": "perturbed_kepler:perturbed_kepler",
    "henon_heiles": "henon_heiles:henon_heiles",
    "fpu_beta": "fpu_beta:fpu_beta",
    "toda": "toda:toda",
    "nbody": "nbody:nbody",
    "pendulum": "pendulum:pendulum",
}


class Entry(NamedTuple):
    """What a listing says about a built-in built with its defaults.

    description: the problem's one-line description; parameters: (name, default) of the
    constructor's parameters, in order; coordinates: q names then p names; invariants:
    the declared invariants besides H.
    """

    description: str
    parameters: tuple[tuple[str, object], ...]
    coordinates: tuple[str, ...]
    invariants: tuple[str, ...]


def _numbered(letter: str, n: int) -> tuple[str, ...]:
    return tuple(f"{letter}{i}" for i in range(1, n + 1))


_PLANE = ("q1", "q2", "p1", "p2")
_BODIES = ("sun", "jupiter", "saturn", "uranus", "neptune", "pluto")   # nbody.SOLAR_SYSTEM_BODIES

LISTING = {
    "kepler": Entry("planar Kepler problem, H = |p|^2/2 - 1/|q|, period 2 pi", (("eccentricity", 0.6),), _PLANE,
                    ("angular_momentum", "lrl_x", "lrl_y")),
    "harmonic_oscillator": Entry("H = p^2/2 + omega^2 q^2/2", (("omega", 1.0),), ("q", "p"), ()),
    "quartic_oscillator": Entry("H = p^2/2 + q^4/4", (), ("q", "p"), ()),
    "central_quartic": Entry("H = |p|^2/2 + |q|^4/4 in the plane", (), _PLANE, ("angular_momentum",)),
    "perturbed_kepler": Entry("perturbed Kepler problem, H = |p|^2/2 - 1/|q| - delta/(2|q|^3)",
                              (("eccentricity", 0.6), ("delta", 0.01)), _PLANE, ("angular_momentum",)),
    "henon_heiles": Entry("Henon-Heiles, H = |p|^2/2 + |q|^2/2 + q1^2 q2 - q2^3/3", (("energy", 0.125),), _PLANE,
                          ()),
    "fpu_beta": Entry("FPU-beta chain, 8 masses, periodic ends, V(r) = r^2/2 + beta r^4/4",
                      (("n", 8), ("beta", 1.0), ("boundary", "periodic")), _numbered("q", 8) + _numbered("p", 8),
                      ("momentum",)),
    "toda": Entry("periodic Toda lattice, 4 particles, H = |p|^2/2 + sum exp(q_i - q_(i+1))", (("n", 4),),
                  _numbered("q", 4) + _numbered("p", 4), ("trace_L1", "trace_L3", "trace_L4")),
    "nbody": Entry("gravitational 6-body problem in 3D, barycentric frame (outer solar system, HLW I.2.4)",
                   (("masses", None), ("positions", None), ("velocities", None), ("G", 2.95912208286e-4),
                    ("frame", "barycentric")),
                   tuple(f"{body}_{c}" for body in _BODIES for c in "xyz")
                   + tuple(f"{body}_p{c}" for body in _BODIES for c in "xyz"),
                   ("linear_momentum_x", "linear_momentum_y", "linear_momentum_z",
                    "angular_momentum_x", "angular_momentum_y", "angular_momentum_z")),
    "pendulum": Entry("mathematical pendulum, H = p^2/2 - omega^2 cos q", (("omega", 1.0),), ("q", "p"), ()),
}


def listing_entry(constructor) -> Entry:
    """The Entry of a constructor found by building its problem with the defaults (compiles it)."""
    problem = constructor()
    description = problem.description or " ".join((constructor.__doc__ or "").strip().split("\n")[0].split())
    parameters = tuple((p.name, p.default) for p in inspect.signature(constructor).parameters.values())
    return Entry(description, parameters, tuple(problem.coordinate_names), tuple(problem.invariant_names))
