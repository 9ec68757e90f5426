"""Load-time checks of a problem's compiled functions: its derivatives and its invariants.

Both checks look at y0, at seeded random points near it and at a few farther ones
(``check_points``): y0 + radius * max(|y0|_inf, 1) * N(0, 1) per component, radius
DEFAULT_RADIUS = 0.05 for the near points and FAR_RADIUS = 1 for the far ones, with
``numpy.random.default_rng(seed)``; points where a function is not finite (a
singularity) or raises (a ``python:`` file's own ``raise`` outside its domain) are
skipped, y0 never is. The far points are there for terms that are small near y0: a user
trial's grad_H with a coupling term 2 k x y^2 off by 0.03% passed at y = 0 and the points
near it (an error of 1e-7 of the entry, below RTOL), then lost H at 2e-4 in the run; at
the far points it fails 12-130 times over. They raise no false alarm: over 20 seeds, every
shipped config's problem, Kepler up to e = 0.999 and the tests' Lennard-Jones clusters stay
below 0.04 of the derivative threshold at radius 1 and 3 alike, and their invariants below
1 eps (the limit is 1000 eps).

**Derivatives** (``check_derivatives``, ``require_derivatives``). grad_H is compared with
central differences of H, each invariant's gradient with central differences of
``invariants``, and hess_H with central differences of grad_H (not when hess_H is itself
finite differences of grad_H). A wrong sign or factor in a hand-written gradient
otherwise goes unnoticed: the integrator then solves another system, and conserves
*its* energy, so a run "completes" with an error of 1e8 in H (issue 10, point 7).

The threshold follows the error of a central difference. With step h_j along y_j,
D(h) = (F(y + h e_j) - F(y - h e_j)) / 2h = F'(y) + h^2 F'''/6 + O(h^4) + rounding,
rounding <= c eps |F| / h (c: the rounding of one evaluation of F, in units of eps |F|).
h_j = eps^(1/3) * s_j balances the two for a component of scale s_j
(s_j = max(|y_j|, the rms of its block q or p at y0)). The truncation term is measured
rather than guessed: D(2h) - D(h) = 3 h^2 F'''/6 + ..., so |D(2h) - D(h)| / 3 estimates it
(and it also sees rounding noise, which differs between the two steps). An entry fails when

    |analytic - D(h)| > MARGIN * (|D(2h) - D(h)| + ROUNDING * eps * S / h) + RTOL * |analytic|,

S = max(|F| near y, sum_j |dF/dy_j| |y_j|): the rounding of an F computed with cancellation is
eps times its terms, at least what y's own rounding carries in (a Lennard-Jones hexagon's
grad_H has components of 1e-15 from terms of ~100).

MARGIN = 10 is a margin of 30 over the truncation estimate; ROUNDING = 16 allows an
evaluation of F sixteen times less accurate than one operation; RTOL = 1e-6 covers a
truncation estimate that vanishes by accident (h^2 F''' cancelling h^4 F^(5): then the
error itself is O(h^4), ~1e-20 relative). For the smooth built-ins the error is ~1e-10 of
the entry, so they pass by orders of magnitude; a sign error is a relative error of 2 and
a factor 2 one of 0.5 or 1, which fail in every entry that central differences resolve
(|F'| above ~1e-9 of |F|/s_j). Where F is not smooth within 2h (abs at its kink),
|D(2h) - D(h)| is as large as the difference itself, and no false alarm is raised.
Every component is differenced at y0 (above Y0_COMPONENTS, that many chosen by the seeded
generator); at each nearby point, at most NEARBY_COMPONENTS of them: fpu_beta with 1000
masses (n = 2000) is checked in 0.47 s instead of 2.3 s for every component at all 9 points (the
far points add about a third: 0.72 -> 0.97 s side by side on a loaded machine).
hess_H is checked up to n = HESSIAN_CHECK_MAX_N (each evaluation fills an n x n array).

**Invariants** (``check_invariants``, ``require_invariants``). For an invariant L of
y' = J grad H(y), dL/dt = grad L(y)^T J grad H(y) = 0 everywhere (docs/methods.md#notation). The
residual is that product relative to |grad L| |grad H| (a cosine: 0 for a true invariant,
O(1) for a wrong one such as the paper's misprinted LRL component ``p1*L1 - q2/r`` of the
attractive Kepler problem, docs/methods.md#typos-in-the-paper). For a true invariant the computed product is
round-off: each computed component of grad L and grad H is off by about eps times the
size of the terms it is computed from, which for well-scaled code is |grad L| or |grad H|,
so the residual is a few eps. It is rejected above INVARIANT_TOLERANCE = 1000 eps
(2.2e-13): the built-ins stay below 10 eps (the worst seen, 9.4 eps: Kepler e = 0.9,
lrl_y, over 30 seeds), and the stray term of L + 1e-7 q1 for Kepler, which the former
fixed tolerance 1e-8 let through at 8.2e-10 (issue 9, point 10), is 3.7e6 eps.
Scaling by eps sum_i |t_i|, t_i = (grad L)_i (J grad H)_i, instead would be tighter but is
not a bound of the round-off: a component computed with cancellation (for lrl_y,
p1^2 - 1/r + q2^2/r^3 near q1 = 0) carries an error of eps times its terms, not eps times
itself; measured, 2474 eps sum_i |t_i| at a seeded point near Kepler's e = 0.9 state,
growing like 1/q1^2.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .base import Problem, real_state
from .expressions import ProblemDefinitionError

DEFAULT_POINTS = 8          # random points near y0
DEFAULT_RADIUS = 0.05       # relative size of the neighbourhood of y0
FAR_POINTS = 4              # random points farther out, after the near ones (module docstring)
FAR_RADIUS = 1.0
EPS = float(np.finfo(np.float64).eps)
INVARIANT_TOLERANCE = 1000.0 * EPS   # relative residual above which an invariant is rejected (module docstring)
DEFAULT_TOLERANCE = INVARIANT_TOLERANCE

# The derivative check (module docstring).
STEP = EPS ** (1.0 / 3.0)   # h_j = STEP * s_j
MARGIN = 10.0
ROUNDING = 16.0
RTOL = 1e-6
NEARBY_COMPONENTS = 64      # differenced components per nearby point (all of them at y0 up to Y0_COMPONENTS)
# At y0 every component is differenced up to this many, else this many seeded ones: each
# difference evaluates the function, whose cost grows with n, so all of them cost O(n^2)
# (toda with n = 10^5 checked for over 10 minutes, silently; n = 1000 took 12 s).
Y0_COMPONENTS = 512
# hess_H is checked up to this n: each evaluation fills an n x n array (n = 2 10^5: 320 GB).
HESSIAN_CHECK_MAX_N = 4000


class InvariantCheckError(ProblemDefinitionError):
    """A declared invariant that the flow of H does not conserve (``residuals``: name -> value)."""

    def __init__(self, message: str, residuals: dict, key: str | None = None):
        super().__init__(message, key=key)
        self.residuals = residuals


class DerivativeCheckError(ProblemDefinitionError):
    """grad_H, an invariant's gradient or hess_H that is not the derivative of its function
    (``report``: the DerivativeReport of the worst entry)."""

    def __init__(self, message: str, report: "DerivativeReport", key: str | None = None):
        super().__init__(message, key=key)
        self.report = report


def check_points(problem: Problem, n_points: int = DEFAULT_POINTS, seed: int = 0, radius: float = DEFAULT_RADIUS,
                 y0=None, far_points: int = FAR_POINTS) -> list[np.ndarray]:
    """y0 (the problem's, or the one given), n_points seeded random points near it, then
    far_points farther ones (FAR_RADIUS; is_far tells them apart by index)."""
    centre = real_state(problem.y0 if y0 is None else y0)
    rng = np.random.default_rng(seed)
    size = max(float(np.max(np.abs(centre))) if centre.size else 0.0, 1.0)
    # (the near points are drawn first, so that they are the same as before the far ones were added)
    return ([centre] + [centre + radius * size * rng.standard_normal(centre.size) for _ in range(n_points)]
            + [centre + FAR_RADIUS * size * rng.standard_normal(centre.size) for _ in range(far_points)])


def is_far(point: int, n_points: int = DEFAULT_POINTS) -> bool:
    """Whether check_points' point of this index is one of the far ones."""
    return point > n_points


def _singular_initial_state(problem: Problem, centre: np.ndarray, what: str) -> ProblemDefinitionError:
    return ProblemDefinitionError(
        f"problem {problem.name!r}: {what} is not finite at the initial state {centre.tolist()}; choose an "
        "initial state away from the singularity", key="initial")


def _raised_at_initial_state(problem: Problem, centre: np.ndarray, what: str, err: Exception) -> ProblemDefinitionError:
    text = " ".join(str(err).split()) or "(no message)"
    where = problem.source_file or f"problem {problem.name!r}"
    return ProblemDefinitionError(
        f"{where}: {what} raised {type(err).__name__}: {text[:200]} at the initial state {centre.tolist()}; fix "
        "the function, or choose an initial state where it is defined", key="initial")


# --- invariants ---------------------------------------------------------------------------

def _poisson_bracket(grad_L: np.ndarray, grad_H: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """grad L^T J grad H for each row of grad_L, and the scale |grad L| |grad H|."""
    J_grad_H = np.concatenate((grad_H[m:], -grad_H[:m]))
    return grad_L @ J_grad_H, np.linalg.norm(grad_L, axis=1) * np.linalg.norm(grad_H)


def check_invariants(problem: Problem, n_points: int = DEFAULT_POINTS, seed: int = 0,
                     radius: float = DEFAULT_RADIUS, y0=None, far_points: int = FAR_POINTS) -> dict[str, float]:
    """{invariant name: max over the points of |grad L^T J grad H| / (|grad L| |grad H|)}.

    Points: ``check_points``. A point where grad H or grad L is zero contributes 0
    (nothing to compare); at y0 a non-finite value is an error (the initial state sits on
    a singularity).
    """
    names = problem.invariant_names
    m = problem.degrees_of_freedom
    points = check_points(problem, n_points, seed, radius, y0, far_points)
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
        except Exception as err:   # noqa: BLE001 -- 1/0 under Numba's default error model, or the user's raise
            if index == 0 and not isinstance(err, ArithmeticError):
                raise _raised_at_initial_state(problem, points[0], "grad_H or grad_invariants", err) from None
            grad_H[:] = np.nan
        if not (np.all(np.isfinite(grad_H)) and np.all(np.isfinite(grad_L))):
            if index == 0:
                raise _singular_initial_state(problem, points[0], "grad H or an invariant's gradient")
            continue
        for i, name in enumerate(names):
            if norms[i] > 0.0:
                worst[name] = max(worst[name], abs(float(bracket[i])) / float(norms[i]))
    return worst


# How a config skips the checks; the Python API's builders say check=False instead (PYTHON_SKIP).
CONFIG_SKIP = "set problem.check: false to skip this check"
PYTHON_SKIP = "pass check=False to skip this check"


def require_invariants(problem: Problem, tolerance: float = INVARIANT_TOLERANCE, n_points: int = DEFAULT_POINTS,
                       seed: int = 0, radius: float = DEFAULT_RADIUS, y0=None, skip: str = CONFIG_SKIP
                       ) -> dict[str, float]:
    """``check_invariants``, raising InvariantCheckError for the first invariant whose residual
    exceeds ``tolerance``; returns the residuals when all pass. skip: how the message says to skip it."""
    residuals = check_invariants(problem, n_points=n_points, seed=seed, radius=radius, y0=y0)
    bad = [name for name, value in residuals.items() if not value <= tolerance]
    if bad:
        name = bad[0]
        others = f" (also failing: {', '.join(bad[1:])})" if len(bad) > 1 else ""
        raise InvariantCheckError(
            f"invariant {name!r} of problem {problem.name!r} is not conserved by the flow of H: "
            f"|grad L^T J grad H| / (|grad L| |grad H|) = {residuals[name]:.3e} around the initial state "
            f"({residuals[name] / EPS:.1e} eps; round-off stays below {tolerance:.1e} = {tolerance / EPS:.0f} eps)"
            f"{others}; fix its expression, or {skip}",
            residuals=residuals, key=f"invariants.{name}")
    return residuals


def require_problem(problem: Problem, skip: str = CONFIG_SKIP) -> None:
    """The checks a problem passes before it runs (a config's problem.check, the Python builders'
    check=True): its derivatives, then its invariants, which trust the gradients."""
    require_derivatives(problem, skip=skip)
    require_invariants(problem, skip=skip)


# --- derivatives --------------------------------------------------------------------------

@dataclass(frozen=True)
class DerivativeReport:
    """The worst entry of one compiled derivative against central differences.

    function: 'grad_H', 'grad_invariants' or 'hess_H'; name: a short name for tables
    ('grad_H', 'grad lrl_y', 'hess_H'); label: how messages name it (e.g. "the gradient of
    invariant 'lrl_y' (grad_invariants row 2)"); of: the differenced function; ratio:
    |analytic - differences| / allowed (fails above 1); relative_error: |analytic -
    differences| / |differences| there; point: index in check_points (0 = y0); entry: the
    derivative's name, e.g. 'dH/dp1'; analytic, differences: the two values; key: where in
    a problem description the fault is (for config messages).
    """

    function: str
    name: str
    label: str
    of: str
    ratio: float = 0.0
    relative_error: float = 0.0
    point: int = 0
    entry: str = ""
    analytic: float = 0.0
    differences: float = 0.0
    key: str | None = None

    @property
    def ok(self) -> bool:
        return self.ratio <= 1.0


def _step_scales(centre: np.ndarray) -> np.ndarray:
    """Per component: the rms of its block (q or p) at the centre, or of all of y if that
    block is zero, or 1: the scale below which |y_j| is not a good scale of variation."""
    m = centre.size // 2
    overall = float(np.sqrt(np.mean(centre * centre))) if centre.size else 0.0
    scales = np.empty_like(centre)
    for block in (slice(0, m), slice(m, 2 * m)):
        scales[block] = float(np.sqrt(np.mean(centre[block] ** 2))) or overall or 1.0
    return scales


def _compare(evaluate, analytic: np.ndarray, y: np.ndarray, scales: np.ndarray, columns):
    """The worst entry of each row of the Jacobian ``analytic`` (k, n) of ``evaluate``
    (y -> (k,)) at y against central differences with steps h and 2h along the given
    columns (module docstring): arrays (ratio, relative error, column, analytic value,
    difference quotient), each (k,); or None when F is not finite near y."""
    k = analytic.shape[0]
    ratio, relative = np.zeros(k), np.zeros(k)
    column = np.zeros(k, dtype=int)
    exact_at, differences_at = np.zeros(k), np.zeros(k)
    # The rounding of F_i is eps times the size of the terms it is computed from, not eps |F_i|
    # where they cancel: at least what the rounding of y alone carries in, sum_j |dF_i/dy_j| |y_j|
    # (a user trial: the grad_H of a Lennard-Jones hexagon has components of 1e-15 from terms of
    # ~100, and a correct hess_H entry of 7e-15 that differences cannot see was refused with a
    # relative error inf).
    with np.errstate(all="ignore"):
        terms = np.abs(analytic) @ np.abs(y)
    size = np.maximum(np.abs(evaluate(y)), np.where(np.isfinite(terms), terms, 0.0))
    for j in columns:
        h = STEP * max(abs(float(y[j])), float(scales[j]))
        quotients = []
        for multiple in (1.0, 2.0):
            plus, minus = y.copy(), y.copy()
            plus[j] += multiple * h
            minus[j] -= multiple * h
            f_plus, f_minus = evaluate(plus), evaluate(minus)
            quotients.append((f_plus - f_minus) / (plus[j] - minus[j]))   # the steps as represented
            size = np.maximum(size, np.maximum(np.abs(f_plus), np.abs(f_minus)))
        differences, coarse = quotients
        if not (np.all(np.isfinite(differences)) and np.all(np.isfinite(coarse))):
            return None
        exact = analytic[:, j]
        error = np.abs(exact - differences)
        allowed = MARGIN * (np.abs(coarse - differences) + ROUNDING * EPS * size / h) + RTOL * np.abs(exact)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratios = np.where(error > 0.0, error / allowed, 0.0)   # 0/0: both exactly equal
            relatives = np.where(error > 0.0, error / np.abs(differences), 0.0)
        worse = ratios > ratio
        ratio[worse], relative[worse], column[worse] = ratios[worse], relatives[worse], j
        exact_at[worse], differences_at[worse] = exact[worse], differences[worse]
    return ratio, relative, column, exact_at, differences_at


def check_derivatives(problem: Problem, n_points: int = DEFAULT_POINTS, seed: int = 0,
                      radius: float = DEFAULT_RADIUS, y0=None, far_points: int = FAR_POINTS
                      ) -> list[DerivativeReport]:
    """One DerivativeReport per compiled derivative: grad_H, one per invariant's gradient,
    and hess_H (left out when it is finite differences of grad_H itself), each with its
    worst entry over y0 and the seeded points around it (check_points)."""
    points = check_points(problem, n_points, seed, radius, y0, far_points)
    scales = _step_scales(points[0])
    n = 2 * problem.degrees_of_freedom
    rng = np.random.default_rng(seed)
    columns = ([range(n) if n <= Y0_COMPONENTS else np.sort(rng.choice(n, Y0_COMPONENTS, False))]
               + [range(n) if n <= NEARBY_COMPONENTS else np.sort(rng.choice(n, NEARBY_COMPONENTS, False))
                  for _ in points[1:]])
    names = problem.coordinate_names
    params = problem.params
    inv_names = problem.invariant_names

    def call(function, shape):
        def evaluate(y):
            out = np.empty(shape)
            function(y, params, out)
            return out
        return evaluate

    grad_H = call(problem.grad_H, n)
    # (function, what it differentiates, y -> F(y), y -> its Jacobian, report names and labels,
    # entry names, keys): one report per invariant; grad_H and hess_H have one for all their rows
    checks = [("grad_H", "H", lambda y: np.array([problem.H(y, params)]), lambda y: grad_H(y)[None, :],
               [("grad_H", "grad_H")], lambda i, j: f"dH/d{names[j]}", ["hamiltonian"])]
    if inv_names:
        checks.append(("grad_invariants", "invariants", call(problem.invariants, len(inv_names)),
                       call(problem.grad_invariants, (len(inv_names), n)),
                       [(f"grad {name}", f"the gradient of invariant {name!r} (grad_invariants row {row})")
                        for row, name in enumerate(inv_names)],
                       lambda i, j: f"d{inv_names[i]}/d{names[j]}", [f"invariants.{name}" for name in inv_names]))
    if problem.hessian_source != "finite differences" and n <= HESSIAN_CHECK_MAX_N:
        checks.append(("hess_H", "grad_H", grad_H, call(problem.hess_H, (n, n)), [("hess_H", "hess_H")],
                       lambda i, j: f"d2H/d{names[i]}d{names[j]}", ["hamiltonian"]))

    reports = []
    for function, of, evaluate, jacobian, labels, entry_name, keys in checks:
        rows = len(labels)
        worst = [None] * rows
        for index, y in enumerate(points):
            y = np.ascontiguousarray(y)
            with np.errstate(all="ignore"):
                try:
                    exact = jacobian(y)
                    finite = bool(np.all(np.isfinite(exact)))
                    # None: F is not finite within 2h of y (an edge of its domain): nothing to compare
                    result = _compare(evaluate, exact, y, scales, columns[index]) if finite else None
                except Exception as err:   # noqa: BLE001 -- 1/0 under Numba's default error model, or the user's raise
                    if index == 0 and not isinstance(err, ArithmeticError):
                        raise _raised_at_initial_state(problem, points[0], f"{function} or {of}", err) from None
                    finite, result = False, None   # a point outside the functions' domain: skipped
            if not finite and index == 0:
                raise _singular_initial_state(problem, points[0], function)
            if result is None:
                continue
            ratio, relative, column, exact_at, differences_at = result
            groups = [[r] for r in range(rows)] if rows > 1 else [list(range(ratio.size))]
            for row, members in enumerate(groups):
                i = members[int(np.argmax(ratio[members]))]
                # the first point where it fails (y0 when it does), else the largest ratio
                if worst[row] is None or (worst[row].ok and ratio[i] > worst[row].ratio):
                    worst[row] = DerivativeReport(
                        function=function, name=labels[row][0], label=labels[row][1], of=of, ratio=float(ratio[i]),
                        relative_error=float(relative[i]), point=index, entry=entry_name(i, int(column[i])),
                        analytic=float(exact_at[i]), differences=float(differences_at[i]), key=keys[row])
        reports += [report or DerivativeReport(function=function, name=name, label=label, of=of, key=key,
                                               entry="(not finite near any check point: nothing compared)")
                    for report, (name, label), key in zip(worst, labels, keys)]
    return reports


def require_derivatives(problem: Problem, n_points: int = DEFAULT_POINTS, seed: int = 0,
                        radius: float = DEFAULT_RADIUS, y0=None, skip: str = CONFIG_SKIP,
                        far_points: int = FAR_POINTS) -> list[DerivativeReport]:
    """``check_derivatives``, raising DerivativeCheckError for the first derivative that does
    not match its central differences; returns the reports when all pass. skip: as require_invariants'."""
    reports = check_derivatives(problem, n_points=n_points, seed=seed, radius=radius, y0=y0, far_points=far_points)
    for report in reports:
        if not report.ok:
            points = check_points(problem, n_points, seed, radius, y0, far_points)
            raise DerivativeCheckError(_mismatch_message(problem, report, points[report.point], skip,
                                                         far=is_far(report.point, n_points)),
                                       report=report, key=report.key)
    return reports


def _mismatch_message(problem: Problem, report: DerivativeReport, y: np.ndarray, skip: str, far: bool = False
                      ) -> str:
    values = ", ".join(f"{v:.6g}" for v in y[:8]) + (", ..." if y.size > 8 else "")
    where = ("the initial state" if report.point == 0
             else f"seeded check point {report.point} {'farther from' if far else 'near'} the initial state "
                  f"(y = [{values}])")
    in_file = f" in {problem.source_file}" if problem.source_file else ""
    found = (f"{report.label} of problem {problem.name!r} does not match central differences of {report.of} at "
             f"{where}: {report.entry} = {report.analytic:.6e} from {report.function}, {report.differences:.6e} "
             f"from the differences, relative error {report.relative_error:.1e} ({report.ratio:.1e} times what "
             f"the differences allow)")
    if problem.hessian_source in ("analytic", "symbolic"):
        # A built-in's derivatives are written by hand and tested, an expression problem's are sympy's:
        # differences that miss them mean that H changes faster than they can follow, near a
        # singularity (a user trial: bodies 1e-17 apart were told to fix nbody's grad_H)
        return (f"{found}: its {report.function} is {'tested' if problem.hessian_source == 'analytic' else 'exact'}"
                f", so the state is near a singularity of H, where H changes faster than differences can follow "
                f"(bodies nearly coincident, a coordinate near a pole); move the initial state away from it, or "
                f"{skip}")
    return (f"{found}; fix {report.function}{in_file} so that it is the derivative of {report.of} "
            f"(a wrong sign or factor?), or {skip}")
