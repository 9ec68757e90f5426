"""Does the flow conserve the declared invariants? A numerical check at load time.

For an invariant L of y' = J grad H(y), dL/dt = grad L(y)^T J grad H(y) = 0 everywhere
(spec section 1). ``check_invariants`` evaluates that product at y0 and at seeded random
points near y0, relative to |grad L| |grad H| (a cosine: 0 for a true invariant, round-off
~1e-16 in practice, O(1) for a wrong one such as the paper's misprinted LRL component
``p1*L1 - q2/r`` for the attractive Kepler problem, spec section 5).
``require_invariants`` raises ``InvariantCheckError`` showing the residual.

The points: y0 + radius * max(|y0|_inf, 1) * N(0, 1) per component, with
``numpy.random.default_rng(seed)``; points where a function is not finite (a
singularity) are skipped, y0 never is.
"""
from __future__ import annotations

import numpy as np

from .base import Problem
from .expressions import ProblemDefinitionError

DEFAULT_POINTS = 8          # random points besides y0
DEFAULT_RADIUS = 0.05       # relative size of the neighbourhood of y0
DEFAULT_TOLERANCE = 1e-8    # relative residual above which an invariant is rejected


class InvariantCheckError(ProblemDefinitionError):
    """A declared invariant that the flow of H does not conserve (``residuals``: name -> value)."""

    def __init__(self, message: str, residuals: dict, key: str | None = None):
        super().__init__(message, key=key)
        self.residuals = residuals


def _poisson_bracket(grad_L: np.ndarray, grad_H: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """grad L^T J grad H for each row of grad_L, and the scale |grad L| |grad H|."""
    J_grad_H = np.concatenate((grad_H[m:], -grad_H[:m]))
    return grad_L @ J_grad_H, np.linalg.norm(grad_L, axis=1) * np.linalg.norm(grad_H)


def check_invariants(problem: Problem, n_points: int = DEFAULT_POINTS, seed: int = 0,
                     radius: float = DEFAULT_RADIUS, y0=None) -> dict[str, float]:
    """{invariant name: max over the points of |grad L^T J grad H| / (|grad L| |grad H|)}.

    Points: y0 (the problem's, or the one given) and n_points seeded random points near
    it. A point where grad H or grad L is zero contributes 0 (nothing to compare); at y0
    a non-finite value is an error (the initial state sits on a singularity).
    """
    names = problem.invariant_names
    m = problem.degrees_of_freedom
    centre = np.array(problem.y0 if y0 is None else y0, dtype=np.float64)
    rng = np.random.default_rng(seed)
    scale = radius * max(float(np.max(np.abs(centre))) if centre.size else 0.0, 1.0)
    points = [centre] + [centre + scale * rng.standard_normal(centre.size) for _ in range(n_points)]
    worst = dict.fromkeys(names, 0.0)
    grad_H = np.empty(2 * m)
    grad_L = np.empty((len(names), 2 * m))
    for index, y in enumerate(points):
        y = np.ascontiguousarray(y)
        try:
            with np.errstate(all="ignore"):
                problem.grad_H(y, problem.params, grad_H)
                problem.grad_invariants(y, problem.params, grad_L)
                bracket, norms = _poisson_bracket(grad_L, grad_H, m)
        except ArithmeticError:  # functions compiled with Numba's default error model raise on 1/0
            grad_H[:] = np.nan
        if not (np.all(np.isfinite(grad_H)) and np.all(np.isfinite(grad_L))):
            if index == 0:
                raise ProblemDefinitionError(
                    f"problem {problem.name!r}: grad H or an invariant's gradient is not finite at the initial "
                    f"state {centre.tolist()}; choose an initial state away from the singularity", key="initial")
            continue
        for i, name in enumerate(names):
            if norms[i] > 0.0:
                worst[name] = max(worst[name], abs(float(bracket[i])) / float(norms[i]))
    return worst


def require_invariants(problem: Problem, tolerance: float = DEFAULT_TOLERANCE, n_points: int = DEFAULT_POINTS,
                       seed: int = 0, radius: float = DEFAULT_RADIUS, y0=None) -> dict[str, float]:
    """``check_invariants``, raising InvariantCheckError for the first invariant whose residual
    exceeds ``tolerance``; returns the residuals when all pass."""
    residuals = check_invariants(problem, n_points=n_points, seed=seed, radius=radius, y0=y0)
    bad = [name for name, value in residuals.items() if not value <= tolerance]
    if bad:
        name = bad[0]
        others = f" (also failing: {', '.join(bad[1:])})" if len(bad) > 1 else ""
        raise InvariantCheckError(
            f"invariant {name!r} of problem {problem.name!r} is not conserved by the flow of H: "
            f"|grad L^T J grad H| / (|grad L| |grad H|) = {residuals[name]:.3e} near the initial state "
            f"(tolerance {tolerance:.0e}){others}; fix its expression, or set problem.check: false to skip "
            "this check", residuals=residuals, key=f"invariants.{name}")
    return residuals
