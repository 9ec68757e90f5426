"""The driver: validates a run, calls the time-loop kernel chunk by chunk, collects results.

Data flow: (problem, method, h, ...) -> Integration -> kernels.stepper.time_loop -> Chunk
-> Result (``integrate``) or the HDF5 writer (the CLI). Kernels never see these objects.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

from .errors import ConvergenceError
from .kernels import stepper
from .methods import Method
from .problems import Problem

# Defaults of the fixed-point iteration (all tunables in one place).
DEFAULT_TOL = 2.0 ** -52          # relative stage increment at round-off (machine epsilon)
STAGNATION_THRESHOLD = 1e-10      # below this (relative), an increment that stops decreasing ends the iteration
DEFAULT_MAX_ITER = 100
DEFAULT_CHUNK_STEPS = 1 << 16     # steps per kernel call in integrate()
T_END_RELATIVE_TOLERANCE = 1e-9   # t_end must be a whole number of steps to this

_FAILURE_TEXT = {
    stepper.STATUS_NOT_CONVERGED: "the fixed-point iteration did not converge",
    stepper.STATUS_SINGULAR: "the small system is singular or badly conditioned",
    stepper.STATUS_NONFINITE: "the solution became NaN or infinite",
}
_FAILURE_ADVICE = {
    stepper.STATUS_NOT_CONVERGED: "reduce h or raise max_iter",
    stepper.STATUS_SINGULAR: ("Assumption 1 of the paper fails for these invariants here (Gamma, spec 3); "
                              "impose fewer or other invariants, or change h"),
    stepper.STATUS_NONFINITE: "reduce h; check the initial state and the problem's singularities",
}
STATUS_NAMES = {
    stepper.STATUS_OK: "ok",
    stepper.STATUS_NOT_CONVERGED: "not converged",
    stepper.STATUS_SINGULAR: "singular",
    stepper.STATUS_NONFINITE: "non-finite",
}


@dataclass
class Chunk:
    """What one kernel call produced: samples, per-step data and the status."""

    t: np.ndarray            # (samples,)
    y: np.ndarray            # (samples, 2m)
    invariants: np.ndarray   # (samples, 1 + n_inv): H, then the problem's invariants
    multipliers: np.ndarray  # (steps, n_mult): alpha (ELIM) or lambda (LIM)
    iterations: np.ndarray   # (steps,)
    first_step: int          # global index of the first step in this chunk
    status: int


@dataclass
class Result:
    """The outcome of ``integrate``.

    t (samples,), y (samples, 2m); invariants: name -> (samples,), always with 'H' and
    every invariant of the problem, imposed or not; alpha (n_steps, nu) for ELIM and
    lam (n_steps, nu+1) for LIM (None otherwise); iterations (n_steps,) per step;
    y_final, t_final: the last state; status: 'complete' or the failure reason.
    """

    problem: Problem
    method: Method
    h: float
    conserve: tuple[str, ...]
    t: np.ndarray
    y: np.ndarray
    invariants: dict[str, np.ndarray]
    alpha: np.ndarray | None
    lam: np.ndarray | None
    iterations: np.ndarray
    y_final: np.ndarray
    t_final: float
    n_steps: int
    steps_done: int
    status: str
    extra: dict = field(default_factory=dict)

    def invariant_errors(self) -> dict[str, float]:
        """max over samples of |I(t) - I(t0)| for H and every invariant."""
        return {name: float(np.max(np.abs(v - v[0]))) if v.size else 0.0 for name, v in self.invariants.items()}


def resolve_conserve(problem: Problem, method: Method, conserve: Iterable[str]) -> tuple[tuple[str, ...], np.ndarray]:
    """Check the invariants to impose against the problem and the method; return (names, indices)."""
    if isinstance(conserve, str):
        conserve = (conserve,)
    names = tuple(conserve)
    for name in names:
        if not isinstance(name, str):
            raise TypeError(f"conserve must be invariant names (strings), got {name!r}")
    unknown = [n for n in names if n not in problem.invariant_names]
    if unknown:
        known = ", ".join(problem.invariant_names) or "none"
        hint = " (H is always conserved by HBVM/ELIM/LIM: leave it out)" if "H" in unknown else ""
        raise ValueError(f"problem {problem.name!r} has no invariant {', '.join(map(repr, unknown))}{hint}; "
                         f"its invariants: {known}")
    if len(set(names)) != len(names):
        raise ValueError(f"conserve lists an invariant twice: {list(names)}")
    limit = method.max_conserved()
    if names and not method.imposes_invariants:
        raise ValueError(f"{method.name} cannot impose invariants (conserve={list(names)}); "
                         "use elim/ehbvm or lim/ghbvm, or set conserve=()")
    if limit is not None and len(names) > limit:
        raise ValueError(
            f"{method.name} can impose at most s-1 = {limit} invariant(s), got {len(names)}: each one takes "
            f"one of the coefficients gamma_1..gamma_(s-1) (gamma_0 fixes y1, spec 3); raise s above "
            f"{len(names)} or impose fewer")
    if method.family in ("elim", "ehbvm"):
        linear = [n for n in names if n in problem.linear_invariant_names]
        if linear:
            raise ValueError(
                f"{', '.join(linear)} {'is' if len(linear) == 1 else 'are'} linear: every Runge-Kutta method, "
                f"{method.name} included, keeps {'it' if len(linear) == 1 else 'them'} exactly, and ELIM cannot "
                "impose a linear invariant (its Gamma column vanishes, spec 3); leave it out of conserve "
                "(or impose it with lim/ghbvm)")
    indices = np.array([problem.invariant_names.index(n) for n in names], dtype=np.int64)
    return names, indices


def resolve_steps(h, t_end=None, n_steps=None, t0: float = 0.0) -> tuple[float, int]:
    """Validate h and exactly one of t_end / n_steps; return (h, n_steps)."""
    try:
        h = float(h)
    except (TypeError, ValueError):
        raise TypeError(f"h must be a number, got {h!r}") from None
    if not (math.isfinite(h) and h > 0.0):
        raise ValueError(f"h must be a positive finite step size, got {h!r} (use backward=True to integrate backwards)")
    if (t_end is None) == (n_steps is None):
        raise ValueError("give exactly one of t_end and n_steps")
    if n_steps is not None:
        if isinstance(n_steps, bool) or not float(n_steps).is_integer() or n_steps < 1:
            raise ValueError(f"n_steps must be a positive integer, got {n_steps!r}")
        return h, int(n_steps)
    span = float(t_end) - float(t0)
    if not (math.isfinite(span) and span > 0.0):
        raise ValueError(f"t_end must be a finite time after t0 = {t0}, got {t_end!r}")
    steps = round(span / h)
    if steps < 1 or abs(steps * h - span) > T_END_RELATIVE_TOLERANCE * span:
        raise ValueError(f"t_end - t0 = {span!r} is not a whole number of steps h = {h!r} "
                         f"({span / h:.12g} steps); adjust h or t_end, or give n_steps")
    return h, int(steps)


class Integration:
    """A run in progress: validated arguments, the kernel state, and ``advance``.

    ``advance(n)`` runs up to n more steps in one kernel call and returns a Chunk;
    consecutive calls continue the same run exactly (compensated y and t, last
    coefficients). The state can be saved and restored (``state`` / ``restore``) so a
    run resumed from it ends bit for bit where an uninterrupted one would.
    """

    def __init__(self, problem: Problem, method: Method, h: float, n_steps: int, conserve=(),
                 tol: float | None = None, max_iter: int = DEFAULT_MAX_ITER, store_every: int = 1,
                 rhs: str = "stable", warm_start: bool = True, t0: float = 0.0, y0=None,
                 backward: bool = False):
        if not isinstance(problem, Problem):
            raise TypeError(f"problem must be an elimfast Problem, got {type(problem).__name__}")
        if not isinstance(method, Method):
            raise TypeError(f"method must be an elimfast Method (e.g. elimfast.methods.ehbvm(12, 3)), "
                            f"got {type(method).__name__}")
        self.problem, self.method = problem, method
        self.conserve, self.conserve_idx = resolve_conserve(problem, method, conserve)
        self.h, self.n_steps = resolve_steps(h, n_steps=n_steps)
        self.backward = bool(backward)
        self.tol = DEFAULT_TOL if tol is None else float(tol)
        if not (self.tol >= 0.0 and math.isfinite(self.tol)):
            raise ValueError(f"tol must be a finite number >= 0, got {tol!r}")
        if isinstance(max_iter, bool) or not float(max_iter).is_integer() or max_iter < 1:
            raise ValueError(f"max_iter must be a positive integer, got {max_iter!r}")
        self.max_iter = int(max_iter)
        if isinstance(store_every, bool) or not float(store_every).is_integer() or store_every < 1:
            raise ValueError(f"store_every must be a positive integer, got {store_every!r}")
        self.store_every = int(store_every)
        if rhs not in ("stable", "literal"):
            raise ValueError(f"rhs must be 'stable' (spec 3b, the default) or 'literal' (the paper's), got {rhs!r}")
        self.rhs = rhs
        self.warm_start = bool(warm_start)

        n = 2 * problem.degrees_of_freedom
        self.y = np.array(problem.y0 if y0 is None else y0, dtype=np.float64)
        if self.y.shape != (n,) or not np.all(np.isfinite(self.y)):
            raise ValueError(f"the initial state must be {n} finite numbers ({', '.join(problem.coordinate_names)}), "
                             f"got {self.y!r}")
        self.y_comp = np.zeros(n)
        self.clock = np.array([float(t0), 0.0])
        self.t0 = float(t0)
        self.coef = np.zeros((method.s, n))
        nu = len(self.conserve)
        n_mult = nu + 1 if method.kernel_family == stepper.FAMILY_LIM else nu
        self.multipliers = np.zeros(n_mult)
        self.steps_done = 0
        self.status = stepper.STATUS_OK
        self._progress = np.zeros(2, dtype=np.int64)

    # --- state -------------------------------------------------------------------------
    @property
    def t(self) -> float:
        return float(self.clock[0])

    @property
    def finished(self) -> bool:
        return self.steps_done >= self.n_steps or self.status != stepper.STATUS_OK

    def state(self) -> dict[str, np.ndarray | int]:
        """Everything needed to continue the run exactly (for resume)."""
        return {"y": self.y.copy(), "y_comp": self.y_comp.copy(), "clock": self.clock.copy(),
                "coef": self.coef.copy(), "multipliers": self.multipliers.copy(), "steps_done": self.steps_done}

    def restore(self, state: dict) -> None:
        for key in ("y", "y_comp", "clock", "coef", "multipliers"):
            target = getattr(self, key)
            value = np.asarray(state[key], dtype=np.float64)
            if value.shape != target.shape:
                raise ValueError(f"saved state {key!r} has shape {value.shape}, expected {target.shape}")
            target[...] = value
        self.steps_done = int(state["steps_done"])

    def n_samples_between(self, first_step: int, n: int) -> int:
        """Samples stored by steps first_step+1 .. first_step+n (multiples of store_every, and the last)."""
        last = first_step + n
        count = last // self.store_every - first_step // self.store_every
        if last == self.n_steps and self.n_steps % self.store_every != 0:
            count += 1
        return count

    def initial_chunk(self) -> Chunk:
        """The sample at t0 (H and invariants at y0), with no steps."""
        p = self.problem
        values = np.empty(len(p.invariant_names))
        p.invariants(self.y, p.params, values)
        inv = np.concatenate(([p.H(self.y, p.params)], values))[None, :]
        return Chunk(np.array([self.t]), self.y[None, :].copy(), inv, np.zeros((0, self.multipliers.size)),
                     np.zeros(0, dtype=np.int64), self.steps_done, stepper.STATUS_OK)

    # --- stepping ----------------------------------------------------------------------
    def advance(self, max_steps: int) -> Chunk:
        """Run up to max_steps more steps in one kernel call."""
        p, m = self.problem, self.method
        n_run = int(min(max_steps, self.n_steps - self.steps_done))
        n_samples = self.n_samples_between(self.steps_done, n_run)
        dim = self.y.size
        t_out = np.empty(n_samples)
        y_out = np.empty((n_samples, dim))
        inv_out = np.empty((n_samples, 1 + len(p.invariant_names)))
        mult_out = np.empty((n_run, self.multipliers.size))
        iter_out = np.zeros(n_run, dtype=np.int64)
        if n_run <= 0 or self.status != stepper.STATUS_OK:
            return Chunk(t_out, y_out, inv_out, mult_out, iter_out, self.steps_done, self.status)
        h = -self.h if self.backward else self.h
        status = stepper.time_loop(
            p.H, p.grad_H, p.invariants, p.grad_invariants, p.params,
            m.kernel_family, len(p.invariant_names), int(self.rhs == "stable"), int(self.warm_start),
            h, m.projection, m.Is, m.projection_hat, m.Is_hat,
            self.conserve_idx, self.tol, STAGNATION_THRESHOLD, self.max_iter,
            self.y, self.y_comp, self.clock, self.coef, self.multipliers,
            self.steps_done, n_run, self.n_steps, self.store_every,
            t_out, y_out, inv_out, mult_out, iter_out, self._progress)
        done, samples = int(self._progress[0]), int(self._progress[1])
        first = self.steps_done
        self.steps_done += done
        self.status = int(status)
        # On failure keep the failed step's iteration count: it says how hard the step was.
        n_iter = done + (1 if status != stepper.STATUS_OK else 0)
        return Chunk(t_out[:samples], y_out[:samples], inv_out[:samples], mult_out[:done],
                     iter_out[:n_iter], first, int(status))

    def failure_message(self) -> str:
        """One line naming the step and time of a failure, and what to do."""
        step = self.steps_done + 1
        t_fail = self.t
        h = -self.h if self.backward else self.h
        what = _FAILURE_TEXT[self.status]
        if self.status == stepper.STATUS_NOT_CONVERGED:
            what += f" in max_iter = {self.max_iter} iterations"
        return (f"{self.method.name}: {what} at step {step} (t = {t_fail:.17g} -> {t_fail + h:.17g}); "
                f"{_FAILURE_ADVICE[self.status]}")


def integrate(problem: Problem, method: Method, h: float, t_end: float | None = None, n_steps: int | None = None,
              conserve: Iterable[str] = (), tol: float | None = None, max_iter: int = DEFAULT_MAX_ITER,
              store_every: int = 1, rhs: str = "stable", warm_start: bool = True, t0: float = 0.0,
              y0=None, backward: bool = False, chunk_steps: int = DEFAULT_CHUNK_STEPS) -> Result:
    """Integrate ``problem`` with ``method`` and constant step ``h``; return a Result.

    Give t_end (a whole number of steps after t0, to 1e-9 relative) or n_steps.
    conserve: names of the problem's invariants to impose (ELIM/EHBVM: fewer than s;
    LIM/GHBVM: any number; must be empty for GAUSS/HBVM). tol: stopping tolerance of the
    fixed-point iteration on the relative stage increment (default: machine epsilon);
    max_iter: iterations allowed per step. store_every: keep every n-th state (the
    last one always). rhs: 'stable' (spec 3b, default) or 'literal' (the paper's form).
    warm_start: start each step's iteration from the previous step's coefficients
    (else from y_n). backward: integrate towards t0 - n_steps h.

    Raises ConvergenceError (with the partial Result as ``.result``) when the
    iteration fails to converge, Gamma is singular, or the solution stops being finite.
    """
    if t_end is not None and backward:
        raise ValueError("with backward=True give n_steps, not t_end")
    h, n_steps = resolve_steps(h, t_end=t_end, n_steps=n_steps, t0=t0)
    run = Integration(problem, method, h, n_steps, conserve=conserve, tol=tol, max_iter=max_iter,
                      store_every=store_every, rhs=rhs, warm_start=warm_start, t0=t0, y0=y0, backward=backward)
    chunks = [run.initial_chunk()]
    while not run.finished:
        chunks.append(run.advance(chunk_steps))
    result = _collect(run, chunks)
    if run.status != stepper.STATUS_OK:
        message = run.failure_message()
        result.status = "failed: " + message
        raise ConvergenceError(message, step=run.steps_done + 1, time=run.t, result=result,
                               reason=STATUS_NAMES[run.status])
    return result


def _collect(run: Integration, chunks: list[Chunk]) -> Result:
    p, m = run.problem, run.method
    inv = np.concatenate([c.invariants for c in chunks])
    mult = np.concatenate([c.multipliers for c in chunks])
    is_lim = m.kernel_family == stepper.FAMILY_LIM
    invariants = {"H": inv[:, 0].copy()}
    for i, name in enumerate(p.invariant_names):
        invariants[name] = inv[:, 1 + i].copy()
    return Result(
        problem=p, method=m, h=run.h, conserve=run.conserve,
        t=np.concatenate([c.t for c in chunks]), y=np.concatenate([c.y for c in chunks]),
        invariants=invariants,
        alpha=mult if (m.imposes_invariants and not is_lim) else None,
        lam=mult if is_lim else None,
        iterations=np.concatenate([c.iterations for c in chunks]),
        y_final=run.y.copy(), t_final=run.t, n_steps=run.n_steps, steps_done=run.steps_done,
        status="complete" if run.status == stepper.STATUS_OK else STATUS_NAMES[run.status],
    )
