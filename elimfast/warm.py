"""Compile every kernel once into Numba's cache: ``elimfast cache warm``, which ``make`` runs
right after installing, so that the first ``elimfast run`` loads instead of compiling.

Compiling elimfast's kernels from nothing takes one to a few minutes on a 2-core machine
(``bench/end_to_end.py`` measures it); loading them from the cache takes a fraction of a
second. The cache is keyed by the kernels' sources (``kernels/_cache.py``), so a warm-up
stays valid until elimfast, Numba or a kernel changes; then the next run compiles again
(``elimfast run`` says so in one line).

What is compiled: the three kernels (fixed steps, adaptive steps, ensembles; their
explicit signatures compile at import), the functions of every built-in problem, and
whatever the Python layer calls with types known only at the call (the quadrature that
builds the method tables): a few steps of every family and solver, of both step
controls and of an ensemble call those with the types a real run uses. Problems given by
expressions or Python files are compiled per problem, on their first run.
"""
from __future__ import annotations

import importlib
import time
from typing import Callable


def _import(name: str) -> Callable[[], None]:
    return lambda: importlib.import_module(name)


def _builtin_problems() -> None:
    from .problems import PROBLEMS
    for name in PROBLEMS:
        PROBLEMS[name]()


def _short_runs() -> None:
    """A few steps of each path from Python into the kernels, with the types real runs use."""
    import numpy as np

    from . import methods
    from .ensemble import integrate_ensemble
    from .integrate import integrate
    from .problems import kepler

    problem = kepler(0.6)
    for solver in ("fixed_point", "newton"):
        integrate(problem, methods.gauss(2), h=0.1, n_steps=4, solver=solver)
        integrate(problem, methods.ehbvm(4, 2), h=0.1, n_steps=4, solver=solver, conserve=["angular_momentum"])
        integrate(problem, methods.elim(5, 4, 3), h=0.1, n_steps=4, solver=solver,
                  conserve=["angular_momentum", "lrl_y"])
        integrate(problem, methods.ghbvm(4, 2), h=0.1, n_steps=4, solver=solver,
                  conserve=["angular_momentum", "lrl_y"])
    integrate(problem, methods.ehbvm(4, 2), t_end=0.5, rtol=1e-6, conserve=["angular_momentum"])
    integrate(problem, methods.ghbvm(4, 2), t_end=0.5, step_control="time_scale", epsilon=0.05,
              conserve=["angular_momentum"])
    integrate_ensemble(problem, methods.gauss(2), h=0.1, Y0=np.tile(problem.y0, (2, 1)), n_steps=4, n_threads=1)


STEPS = (
    ("fixed-step kernel", _import("elimfast.kernels.stepper")),
    ("adaptive-step kernel", _import("elimfast.kernels.adaptive")),
    ("ensemble kernel", _import("elimfast.kernels.ensemble")),
    ("built-in problems", _builtin_problems),
    ("method tables and a few steps of every family, solver and step control", _short_runs),
)


def warm(on_step: Callable[[str, float], None] | None = None) -> float:
    """Compile (or load, if already cached) every kernel; on_step(what, seconds) after each
    part. Returns the total seconds.

    One process, in order: the adaptive and ensemble kernels reuse much of what the
    fixed-step kernel compiled (the step's solver and maps). Compiled in three processes
    at once instead, they took 119, 223 and 102 s (wall, with other work on the machine)
    against 163 s in all one after the other."""
    start = time.perf_counter()
    for what, step in STEPS:
        began = time.perf_counter()
        step()
        if on_step is not None:
            on_step(what, time.perf_counter() - began)
    return time.perf_counter() - start
