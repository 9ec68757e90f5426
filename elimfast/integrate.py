"""The driver: validates a run, calls the time-loop kernel chunk by chunk, collects results.

Data flow: (problem, method, h, ...) -> Integration -> kernels.stepper.time_loop -> Chunk
-> Result (``integrate``) or the HDF5 writer (the CLI). Kernels never see these objects.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Callable, Iterable, Mapping

import numpy as np

from .cache import kernel_folder_used
from .errors import ConvergenceError, ParameterError, closest, exact_time, real_number
from .function_addresses import remembered_addresses
from .kernels import codes
from .kernels.solver import NEARLY_SINGULAR_GAMMA   # a stall above it is blamed on Gamma, not on h
from . import methods
from .methods import Method
from .methods.base import IMPOSES_NONE
from .problems import Problem
from .problems.base import real_state, require_problem_object

# The kernels are loaded (or compiled) from their key folder: mark it used, and prune the
# key folders of old kernels if it is new (cache.py). Once per process, a few system calls.
kernel_folder_used(in_package=True)

# Defaults of the step solver (all tunables in one place; docs/solver.md).
SOLVERS = {"newton": codes.SOLVER_NEWTON, "fixed_point": codes.SOLVER_FIXED_POINT}
# 'auto' (the default) is resolved per problem (SolverSettings.resolved_for): simplified Newton up to
# AUTO_NEWTON_MAX_DIMENSION state components, the fixed point above. Newton pays a dense
# factorisation per step (n^3) and a dense solve per iteration (n^2) to save iterations; the map
# costs about n (chains) to n^2 (N bodies) per node. Measured, us per step, Newton against the fixed
# point (HBVM(6,3)): fpu_beta h = 0.05, n = 16: 7 / 5, 64: 28 / 8, 256: 210 / 16, 512: 766 / 24;
# N bodies in a cold cluster, h = 0.002, n = 36: 18 / 5, 120: 92 / 21, 240: 605 / 115; where the
# steps are hard Newton wins at small n: Kepler e = 0.6, h = 0.1 (n = 4) 1.55x faster, the solar
# system at h = 50 (n = 36) 1.15x, the pendulum 1.1x.
SOLVER_CHOICES = ("auto", *SOLVERS)
KERNEL_CHOICES = ("shared", "per_problem")   # SolverSettings.kernel (per_problem.py)
DEFAULT_SOLVER = "auto"
AUTO_NEWTON_MAX_DIMENSION = 48
DEFAULT_TOL = 2.0 ** -52          # relative increment at round-off (machine epsilon): accept at once
MAX_TOL = 1e-8                    # a looser tol would accept iterates far from the solution
LOOSE_TOL = 1e-14                 # above it, a run's loss of H is first the tol's (energy_note)
# Iterations per solve (docs/solver.md). 100, except simplified Newton on ELIM imposing
# invariants: there a step that needs more than 30 is one whose alpha system is
# ill-conditioned (nearly symmetric about a pericentre), and its solution carries
# rounding noise of ~1e-12 (Kepler e = 0.9, h = 0.05, EHBVM(24,3) imposing L, 2e4 time
# units: H error 2.9e-12 with a cap of 100, 8.2e-13 with 30, the steps over the cap split
# in two, 0.16% of them; rounding draws, docs/solver.md). Elsewhere slow convergence only means the Jacobian changes
# fast within the step, and splitting would cost what it does not need to: HBVM(24,3)
# on the same orbit keeps its (not imposed) L error bounded at 2.2e-4 without splits,
# and lets it drift to 1e-3 in 6000 time units when 30 splits 7 steps.
DEFAULT_MAX_ITER = 100
DEFAULT_MAX_ITER_ELIM_NEWTON = 30
MAX_MAX_ITER = 10_000             # bounds the work of one kernel call (simplified Newton needs 5-15)
DEFAULT_MAX_HALVINGS = 4          # step splitting depth (docs/solver.md: one level always sufficed)
MAX_MAX_HALVINGS = 20             # 2^20 substeps per step at most
DEFAULT_CHUNK_STEPS = 1 << 16     # steps per kernel call in integrate()
T_END_RELATIVE_TOLERANCE = 1e-9   # t_end must be a whole number of steps to this
MAX_STEPS = 10 ** 10              # hours to days even at 1 us per step, and 40 GB of per-step records
H_WARNING_RELATIVE = 1e-12        # an H error above this (relative) means k is too small for this h

_FAILURE_TEXT = {
    codes.STATUS_NOT_CONVERGED: "the iteration did not converge",
    codes.STATUS_SINGULAR: "the small system is singular or badly conditioned",
    codes.STATUS_NONFINITE: "the solution became NaN or infinite",
    codes.STATUS_TIME_SCALE: "the problem's time scale collapsed (time-reversible steps h = epsilon sigma(y))",
}
# The method where ELIM's Gamma degenerates: every advice on a singular Gamma ends with it.
_TAKE_GHBVM = "take GHBVM (LIM), whose Gram matrix does not degenerate with Gamma (docs/methods.md#lim"
_FAILURE_ADVICE = {
    codes.STATUS_NOT_CONVERGED: "reduce h or raise solver.max_halvings",
    codes.STATUS_SINGULAR: ("Assumption 1 of the paper fails for these invariants here (Gamma, docs/methods.md); "
                            f"impose fewer or other invariants, or change h, or {_TAKE_GHBVM})"),
    codes.STATUS_NONFINITE: "reduce h; check the initial state and the problem's singularities",
}
# Adaptive runs choose h themselves: the step control has shrunk it already.
_ADAPTIVE_FAILURE_ADVICE = {
    codes.STATUS_NOT_CONVERGED: "the step control found no step that converges; raise solver.max_iter",
    codes.STATUS_SINGULAR: ("Assumption 1 of the paper fails for these invariants here (Gamma, docs/methods.md); "
                            f"impose fewer or other invariants, or {_TAKE_GHBVM})"),
    codes.STATUS_NONFINITE: "check the initial state and the problem's singularities",
    codes.STATUS_TIME_SCALE: ("sigma must stay positive and finite along the whole orbit: take a power of a "
                              "distance, e.g. (q1**2 + q2**2)**0.75, or use step_control: error "
                              "(docs/adaptive.md#time-reversible-steps-step_controltime_scale)"),
}
ADAPTIVE_MEASURED_S = 6   # docs/adaptive.md: the range of s measured for adaptive runs; above it, advise a lower s
# LIM has no Gamma and no Assumption 1: its small system is the Gram matrix of the gradients of H and
# the imposed invariants (docs/methods.md#lim), singular where they are linearly dependent.
_LIM_SINGULAR_ADVICE = ("the gradients of H and the imposed invariants are (nearly) linearly dependent here "
                        "(LIM's Gram matrix, docs/methods.md#lim; e.g. angular momentum on a circular orbit); "
                        "impose fewer or other invariants")
# The paper's right-hand side of the multipliers' system cancels O(h^2) terms down to O(h^(2s)):
# its rounding turns alpha into noise as h shrinks (docs/methods.md#stable-right-hand-side), so a
# smaller h or more halvings make it worse: EHBVM(12,3) imposing L and A_y fails at h = 1e-5 on
# Kepler e = 0.6, after 4 halvings (tests/test_step_engine.py).
_LITERAL_RHS_ADVICE = ("the literal right-hand side's multipliers are rounding noise at small steps: use the stable "
                       "one (solver.rhs: stable, the default; docs/methods.md#stable-right-hand-side)")
# s from which the paper's literal sum for alpha's right-hand side is noise that slows or stalls the solve
# (docs/methods.md#stable-right-hand-side; s <= 3, the paper's, stays clean)
LITERAL_SUM_NOISY_S = 4


def literal_sum_note(family: str, r, k, s, rhs: str) -> str | None:
    """Why an imposing method whose right-hand side is the paper's literal sum (solver.rhs: literal,
    or r > k, where no stable form exists) at s >= LITERAL_SUM_NOISY_S splits or leaves unimposed
    so many steps; None for every other method. A user trial ran ELIM(16,12,6): every step was
    split and taken unimposed, at 917 iterations a step, and the note blamed the invariants."""
    kind = methods.FAMILIES.get(family)
    if kind is None or kind.imposes == IMPOSES_NONE or s is None or int(s) < LITERAL_SUM_NOISY_S:
        return None
    if rhs == "literal" and int(r) <= int(k):
        return _LITERAL_RHS_ADVICE
    if int(r) > int(k):
        return (f"with r > k (r = {int(r)}, k = {int(k)}) alpha's right-hand side is the paper's literal sum, whose "
                f"rounding at s >= {LITERAL_SUM_NOISY_S} makes alpha noise at small steps "
                "(docs/methods.md#stable-right-hand-side): take r <= k, or s <= 3")
    return None


_NEARLY_SINGULAR_ADVICE = ("Gamma is nearly singular here: Assumption 1 of the paper fails for these invariants at "
                           "this point of the orbit (docs/methods.md), which smaller steps do not cure; impose "
                           f"other invariants, whose gradients stay independent along the orbit, or {_TAKE_GHBVM})")
STATUS_NAMES = {
    codes.STATUS_OK: "ok",
    codes.STATUS_NOT_CONVERGED: "not converged",
    codes.STATUS_SINGULAR: "singular",
    codes.STATUS_NONFINITE: "non-finite",
    codes.STATUS_TIME_SCALE: "time scale",
}


def compact_number(value) -> str:
    """A number as a user wrote it: 1e30 and 1e10, not thirty-one and eleven digits."""
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) \
            and math.isfinite(float(value)) and abs(value) >= 1e9:
        mantissa, exponent = f"{float(value):.3g}".split("e")
        return f"{mantissa}e{int(exponent)}"
    return repr(value) if isinstance(value, str) else str(value)


def _whole_number(name: str, value, low: int, high: int, why: str = "") -> int:
    """value as an int in [low, high], or a ParameterError naming the parameter and the range."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(value)) or not float(value).is_integer():
        raise ParameterError(name, f"must be a whole number from {low} to {high}, got {compact_number(value)}")
    as_int = int(value)
    if as_int < low:
        raise ParameterError(name, f"must be >= {low}, got {compact_number(as_int)}")
    if as_int > high:
        raise ParameterError(name, f"must be <= {compact_number(high)}, got {compact_number(value)}{why}")
    return as_int


@dataclass(frozen=True)
class SolverSettings:
    """How each step's nonlinear system is solved (docs/solver.md).

    method: 'auto' (the default: simplified Newton for problems of at most
    AUTO_NEWTON_MAX_DIMENSION = 48 state components, the fixed point above, docs/solver.md#settings),
    'newton' (simplified Newton) or 'fixed_point' (the paper's iteration, whose counts Table 2
    reports); resolved_for replaces 'auto' by the choice; tol: accept an iterate whose relative
    increment is at most this (default: machine epsilon; the rounding band of the
    stopping rule accepts at round-off level in any case); max_iter: iterations per
    solve; max_halvings: how often a failing step may be split in two (0: never);
    predictor: start from the previous step's polynomial carried over; warm_start: start
    from the previous step at all (False: every step cold, from y_n); rhs: 'stable'
    (docs/methods.md#stable-right-hand-side, the default) or 'literal' (the paper's right-hand side);
    accelerate: simplified Newton's secant acceleration (docs/solver.md#secant-acceleration;
    False: the plain iteration of the spec; the fixed point is never accelerated);
    lim_metric: LIM's correction W phi_0 lambda, 'euclidean' (W = I, the spec's and the
    2012 paper's) or 'scaled' (W = diag of each component's mean square over the step:
    invariant under rescaling the components, docs/methods.md#lim);
    kernel: 'shared' (the default: one compiled kernel for every problem) or 'per_problem'
    (fixed steps only: the kernel compiled once more for the problem's functions and cached,
    about 90 s the first time; the same steps bit for bit, each iteration about 10% cheaper:
    elimfast/per_problem.py, docs/solver.md#per-problem-kernel);
    project_energy: after every step, move the state along grad H back to H(y0)
    (docs/methods.md#energy-projection): removes the random walk of H's round-off, whose phase
    error grows like t^(3/2) and is the floor of long runs; one H and one grad H evaluation a step.
    """

    method: str = DEFAULT_SOLVER
    tol: float = DEFAULT_TOL
    max_iter: int | None = None        # None: chosen with the method (resolved_for)
    max_halvings: int = DEFAULT_MAX_HALVINGS
    predictor: bool = True
    warm_start: bool = True
    rhs: str = "stable"
    accelerate: bool = True
    lim_metric: str = "euclidean"
    kernel: str = "shared"
    project_energy: bool = False

    def __post_init__(self):
        if self.method not in SOLVER_CHOICES:
            raise ParameterError("method", f"must be auto (the default: simplified Newton up to "
                                           f"{AUTO_NEWTON_MAX_DIMENSION} state components, the fixed point above), "
                                           f"newton or fixed_point, got {self.method!r}")
        tol = DEFAULT_TOL if self.tol is None else real_number("tol", self.tol)
        if not tol >= 0.0:
            raise ParameterError("tol", f"must be >= 0, got {compact_number(self.tol)}; leave it out for machine epsilon")
        if not tol <= MAX_TOL:
            raise ParameterError("tol", f"must be <= {MAX_TOL:g}, got {compact_number(self.tol)}: it is the round-off "
                                        "stopping tolerance on the relative increment, and a larger one accepts "
                                        "unconverged steps, so H and the invariants are no longer kept; leave it out "
                                        "for machine epsilon")
        object.__setattr__(self, "tol", tol)
        if self.max_iter is not None:
            object.__setattr__(self, "max_iter", _whole_number(
                "max_iter", self.max_iter, 1, MAX_MAX_ITER, ": a solve that has not converged by then will not; a step "
                "over the cap is split in two instead (max_halvings)"))
        object.__setattr__(self, "max_halvings", _whole_number(
            "max_halvings", self.max_halvings, 0, MAX_MAX_HALVINGS, f" (2^{MAX_MAX_HALVINGS} substeps per step)"))
        if self.rhs not in ("stable", "literal"):
            raise ParameterError("rhs", f"must be 'stable' (the default, docs/methods.md#stable-right-hand-side) or "
                                        "'literal' (the paper's), "
                                        f"got {self.rhs!r}")
        if self.lim_metric not in ("euclidean", "scaled"):
            raise ParameterError("lim_metric", "must be 'euclidean' (the spec's, the default) or 'scaled' "
                                               f"(docs/methods.md#lim), got {self.lim_metric!r}")
        if self.kernel not in KERNEL_CHOICES:
            raise ParameterError("kernel", "must be 'shared' (the default: one compiled kernel for every problem) or "
                                           "'per_problem' (compiled for the problem once, about 90 s; then faster: "
                                           f"docs/solver.md#per-problem-kernel), got {self.kernel!r}")
        for name in ("predictor", "warm_start", "accelerate", "project_energy"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ParameterError(name, f"must be true or false, got {getattr(self, name)!r}")
            object.__setattr__(self, name, bool(getattr(self, name)))

    @property
    def rhs_code(self) -> int:
        """The kernels' settings.stable_rhs: bit 0 the stable right-hand side, bit 1 LIM's scaled metric."""
        return int(self.rhs == "stable") | (2 if self.lim_metric == "scaled" else 0)

    def resolved_for(self, method: Method, n_imposed: int, dimension: int) -> "SolverSettings":
        """These settings for a problem with this many state components: 'auto' replaced by the
        solver it chooses (AUTO_NEWTON_MAX_DIMENSION), and max_iter chosen for the method when it
        was left out (see DEFAULT_MAX_ITER). ParameterError for lim_metric 'scaled' on a method
        that is not LIM (a user trial: accepted and ignored)."""
        if self.lim_metric != "euclidean" and method.kernel_family != codes.FAMILY_LIM:
            raise ParameterError("lim_metric", f"{self.lim_metric!r} applies to LIM and GHBVM only (the metric of "
                                               "their correction W phi_0 lambda, docs/methods.md#the-metric-of-the-"
                                               f"correction); {method.name} has none: leave lim_metric out or set it "
                                               "to 'euclidean' (the default), or use a LIM method")
        settings = self
        if settings.method == "auto":
            settings = replace(settings, method="newton" if dimension <= AUTO_NEWTON_MAX_DIMENSION else "fixed_point")
        if settings.max_iter is not None:
            return settings
        elim_newton = (settings.method == "newton" and method.kernel_family == codes.FAMILY_ELIM and n_imposed > 0)
        return replace(settings, max_iter=DEFAULT_MAX_ITER_ELIM_NEWTON if elim_newton else DEFAULT_MAX_ITER)

    def as_dict(self) -> dict:
        """The settings as plain data (the resolved config's solver section)."""
        return {"method": self.method, "tol": self.tol, "max_iter": self.max_iter, "max_halvings": self.max_halvings,
                "predictor": self.predictor, "warm_start": self.warm_start, "rhs": self.rhs,
                "accelerate": self.accelerate, "lim_metric": self.lim_metric, "kernel": self.kernel,
                # only when on: the config stored by every earlier run stays what it was
                **({"project_energy": True} if self.project_energy else {})}

    def energy_target(self, problem: Problem, method: Method, y0) -> float:
        """The H the energy projection keeps (H(y0) of the run, whose y0 is the state at t0 also
        for a resumed run), or NaN when it is off: the kernels' H_target. ParameterError where
        the method cannot take it (refuse_energy_projection)."""
        if not self.project_energy:
            return math.nan
        refuse_energy_projection(problem, method)
        return float(problem.H(np.ascontiguousarray(y0, dtype=np.float64), problem.params))

    @property
    def code(self) -> int:
        if self.method not in SOLVERS:
            raise ValueError(f"solver method {self.method!r} is not resolved: call resolved_for first")
        if self.method == "newton" and self.accelerate:
            return codes.SOLVER_NEWTON_ACCELERATED
        return SOLVERS[self.method]

    @property
    def description(self) -> str:
        return "simplified Newton" if self.method == "newton" else "fixed-point iteration"


def refuse_energy_projection(problem: Problem, method: Method) -> None:
    """ParameterError for solver.project_energy with a method of k = s (GAUSS(s), HBVM(s,s)) on an H
    that its s-node quadrature does not integrate exactly: such a method does not keep H, but keeps
    every quadratic and linear invariant (L of Kepler, the momenta of N bodies), and projecting H
    back would spend them at the size of its own error of H (a user trial: GAUSS(2) on Kepler, L
    from 2e-16 to 4e-6; docs/methods.md#energy-projection)."""
    if method.k == method.s and not methods.integrates_exactly(problem.hamiltonian_degree, method.k, method.s):
        raise ParameterError("project_energy", f"{method.name} does not keep this H (its {method.s} nodes integrate "
                                               "it inexactly) but keeps every quadratic and linear invariant, which "
                                               "projecting H would spend (docs/methods.md#energy-projection): take "
                                               f"HBVM(k,{method.s}) with k > {method.s}, or leave project_energy out")


@dataclass
class Chunk:
    """What one kernel call produced: samples, per-step data and the status."""

    t: np.ndarray            # (samples,)
    y: np.ndarray            # (samples, 2m)
    invariants: np.ndarray   # (samples, 1 + n_inv): H, then the problem's invariants
    multipliers: np.ndarray  # (steps, n_mult): alpha (ELIM) or lambda (LIM)
    iterations: np.ndarray   # (steps,), plus the failed step's count when status is a failure
    substeps: np.ndarray     # (steps,): 1, or the substeps of a split step
    first_step: int          # global index of the first step in this chunk
    status: int


@dataclass
class Result:
    """The outcome of ``integrate``.

    t (samples,), y (samples, 2m); invariants: name -> (samples,), always with 'H' and
    every invariant of the problem, imposed or not; alpha (n_steps, nu) for ELIM and
    lam (n_steps, nu+1) for LIM (None otherwise); iterations (n_steps,) per step, every
    try and substep counted; substeps (n_steps,): 1, or how many substeps a split step
    took (docs/solver.md#when-a-step-fails-retry-then-split); y_final, t_final: the last state; status: 'complete' or
    the failure reason; solver: the SolverSettings used; y0, t0: the initial state and
    time, the reference of the invariant errors (the first sample need not be at t0: output
    times may start later). None in Results built without them: the first sample then.
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
    substeps: np.ndarray
    y_final: np.ndarray
    t_final: float
    n_steps: int
    steps_done: int
    status: str
    solver: SolverSettings = field(default_factory=SolverSettings)
    extra: dict = field(default_factory=dict)
    # Runs through the adaptive kernel (docs/adaptive.md): the end time and size of every
    # step, the step control used (None: fixed steps), counts of steps and evaluations,
    # and the events found (name -> EventRecord with .t and .y).
    step_t: np.ndarray | None = None
    step_h: np.ndarray | None = None
    step_control: object = None
    stats: dict = field(default_factory=dict)
    events: dict = field(default_factory=dict)
    y0: np.ndarray | None = None
    t0: float | None = None
    # name -> the first sample time where the event was NaN or infinite (no crossing can be
    # found there; AdaptiveIntegration.check_events_finite)
    events_not_finite: dict = field(default_factory=dict)

    @property
    def ended_by_event(self) -> str | None:
        """The name of the terminal event that ended a complete run (at t_final, before the t_end it
        was given: docs/adaptive.md), else None. status stays 'complete' (a user trial looked for it)."""
        if self.status != "complete":
            return None
        for name, record in self.events.items():
            if getattr(record, "terminal", False) and record.t.size and record.t[-1] == self.t_final:
                return name
        return None

    def _initial_state(self) -> np.ndarray | None:
        """y0, else the first sample (a Result built without y0), else None."""
        if self.y0 is not None:
            return self.y0
        return self.y[0] if self.y.shape[0] else None

    def initial_invariants(self) -> dict[str, float]:
        """H and every invariant at t0, of the initial state y0: the reference I(t0) of the
        invariant errors (a Result without y0: the first sample's; NaN without samples)."""
        state = self._initial_state()
        if state is None:
            return {name: math.nan for name in self.invariants}
        return self.problem.invariant_values(state)

    def invariant_errors(self) -> dict[str, float]:
        """max over samples of |I(t) - I(t0)| for H and every invariant, I(t0) of the initial
        state; NaN when no step was done (``invariant_drift``)."""
        initial = self.initial_invariants()
        return {name: invariant_drift([v], initial[name], self.steps_done) for name, v in self.invariants.items()}

    def invariant_scales(self) -> dict[str, float]:
        """The size of the terms of H and of every invariant at t0 (Problem.invariant_scales
        of y0, or of the first sample for a Result without y0; empty without either)."""
        state = self._initial_state()
        return self.problem.invariant_scales(state) if state is not None else {}

    def relative_invariant_errors(self) -> dict[str, float]:
        """max over samples of |I(t) - I(t0)| / |I(t0)|, relative to the size of I's terms where
        I(t0) vanishes against them, see ``relative_error``."""
        scales, initial = self.invariant_scales(), self.initial_invariants()
        return {name: relative_error(error, initial[name], scales.get(name, 0.0))
                for name, error in self.invariant_errors().items()}

    def to_xarray(self):
        """An xarray.Dataset: y on (t, component), H and every invariant on t, the per-step data
        on step; attributes as in a run file (``elimfast.io.xarray_view``; needs xarray)."""
        from .io.xarray_view import result_dataset
        return result_dataset(self)

    @property
    def split_steps(self) -> int:
        """How many steps were split into substeps (docs/solver.md#when-a-step-fails-retry-then-split)."""
        return int(np.count_nonzero(self.substeps > 1))

    @property
    def unimposed_steps(self) -> int:
        """How many steps had a substep taken without imposing the invariants, which kept them to
        round-off (their alpha is NaN; docs/solver.md#a-substep-without-imposing)."""
        return 0 if self.alpha is None else int(np.count_nonzero(np.isnan(self.alpha).any(axis=1)))

    @property
    def alpha_spikes(self) -> int:
        """How many steps of an ELIM run have an alpha far above both its neighbours': steps next
        to a zero of Gamma, where ELIM loses accuracy (count_alpha_spikes; docs/solver.md#when-
        gamma-passes-through-zero). 0 for the other families."""
        if self.alpha is None or self.method.multiplier_name(len(self.conserve)) != "alpha":
            return 0
        h = self.step_h if self.step_h is not None else self.h
        return count_alpha_spikes([(self.alpha[:self.steps_done], h)])

    def energy_warning(self) -> str | None:
        """A note when H or an imposed invariant drifts above round-off (k or r too small for
        the steps, energy_note), else None."""
        if self.steps_done < 1:
            return None
        errors = self.relative_invariant_errors()
        names = [name for name in ("H", *self.conserve) if name in errors]
        scales, initial = self.invariant_scales(), self.initial_invariants()
        steps = int(self.substeps[:self.steps_done].sum()) if self.substeps is not None else self.steps_done
        return energy_note(self.method.name, self.method.k, self.method.r, self.h,
                           {name: errors[name] for name in names},
                           adaptive=self.step_control is not None, s=self.method.s,
                           degree=self.problem.hamiltonian_degree, steps=steps,
                           hand_written=self.problem.source_file is not None,
                           kinks=self.problem.hamiltonian_kinks, family=self.method.family,
                           roundoff={name: roundoff_allowance(steps, initial[name], scales.get(name, 0.0))
                                     for name in names},
                           tol=self.solver.tol if self.solver is not None else None,
                           peak=lambda: terms_peak(self.problem, self.y, self.t, scales.get("H", 0.0)))

    def __repr__(self) -> str:
        errors = ", ".join(f"{name} {value:.2e}" for name, value in self.invariant_errors().items())
        if self.step_control is not None:
            steps = f"{self.steps_done} adaptive steps ({self.step_control.controller})"
        else:
            steps = f"h = {self.h:g}, {self.steps_done}/{self.n_steps} steps"
        return (f"<Result {self.method.name} on {self.problem.name}, {steps}, {self.status}; "
                f"max |I - I0|: {errors}>")


# docs/solver.md#when-gamma-passes-through-zero. alpha = O(h^2) (docs/methods.md#elim) and varies
# smoothly from step to step; where Gamma passes through zero it has a pole, and the one or two
# steps next to it take an alpha far above both neighbours', where the correction, larger than the
# method's own truncation term, costs ELIM its order (a 7-atom Lennard-Jones cluster imposing L_z,
# h = 0.005: one step with alpha 0.19 between -3.3e-4 and 3.9e-4 made the error at t = 2 ten times
# HBVM's). Measured, steps whose |alpha| / h^2 is more than ALPHA_SPIKE times both neighbours': that
# cluster 34 of 2e4 (t = 100), the solar system imposing L_z at h = 50 2 of 4e4, Kepler (e = 0.6 and
# 0.9, fixed and adaptive steps) none (at most 13x there).
ALPHA_SPIKE = 30.0
# ... counted only where the correction itself matters: |h^(2(nu-1-c)) alpha_c| above this.
ALPHA_SPIKE_FLOOR = 1e-6


def count_alpha_spikes(blocks) -> int:
    """Steps of an ELIM run whose alpha spikes (ALPHA_SPIKE): |alpha_c| / h^2 above ALPHA_SPIKE times
    that of both neighbouring steps, for some c, with |h^(2(nu-1-c)) alpha_c| > ALPHA_SPIKE_FLOOR.

    ``blocks``: (alpha (m, nu), h) pairs in step order, h a float or the steps' sizes (m,); the
    blocks a RunFile reads, or one pair for a Result. Steps with a NaN alpha (a substep taken without
    imposing) and their neighbours are not judged; neither are the first and last steps."""
    count = 0
    tail = None
    for alpha, h in blocks:
        alpha = np.abs(np.asarray(alpha, dtype=np.float64))
        if alpha.size == 0:
            continue
        h = np.broadcast_to(np.abs(np.asarray(h, dtype=np.float64)), alpha.shape[:1])
        nu = alpha.shape[1]
        weights = h[:, None] ** (2 * (nu - 1 - np.arange(nu)))[None, :]
        rows = np.concatenate([alpha / (h[:, None] ** 2), alpha * weights], axis=1)
        rows = rows if tail is None else np.concatenate([tail, rows])
        if rows.shape[0] >= 3:
            scaled, corrections = rows[:, :nu], rows[:, nu:]
            middle = scaled[1:-1]
            with np.errstate(invalid="ignore"):
                neighbours = np.maximum(scaled[:-2], scaled[2:])
                spike = (middle > ALPHA_SPIKE * neighbours) & (corrections[1:-1] > ALPHA_SPIKE_FLOOR)
            judged = ~(np.isnan(scaled[:-2]) | np.isnan(scaled[2:]) | np.isnan(middle)).any(axis=1, keepdims=True)
            count += int(np.count_nonzero((spike & judged).any(axis=1)))
        tail = rows[-2:]
    return count


def alpha_spike_note(count: int, steps: int) -> str:
    """The end-of-run and inspect note for count_alpha_spikes."""
    return (f"{count:,} of {steps:,} steps have an alpha more than {ALPHA_SPIKE:g}x that of both neighbouring steps: "
            "Gamma passes through zero next to them (Assumption 1 of the paper fails there), and ELIM's correction, "
            "larger than its truncation term at such a step, can cost accuracy (docs/solver.md#when-gamma-passes-"
            "through-zero); GHBVM (LIM) imposes the same invariants without Gamma, and a smaller h confines it to "
            "shorter steps")


def invariant_drift(blocks: Iterable[np.ndarray], reference: float, steps_done: int) -> float:
    """max |I(t) - I(t0)| over the samples of a run, ``blocks`` its values of I (one array, or
    the blocks RunFile reads them in) and ``reference`` I(t0): the invariant errors of
    Result, of run files (inspect, the energy note) and of the sweep tables.

    NaN, no figure, when no step was done: the samples then hold only the initial state (a
    run that failed at its first step keeps a sample of its last good state, t0 again), and
    an error of 0 would read as a perfect result. Also NaN without samples."""
    if steps_done <= 0:
        return math.nan
    largest = math.nan
    for block in blocks:
        if block.size:
            block_largest = float(np.max(np.abs(np.asarray(block, dtype=np.float64) - reference)))
            largest = block_largest if math.isnan(largest) else max(largest, block_largest)
    return largest


# I(t0) counts as zero when it is below this fraction of the size of its terms
# (Problem.invariant_scales): a cancellation, whose relative error would mean nothing.
ZERO_FRACTION = 1e-10


def relative_reference(initial: float, scale: float = 0.0) -> tuple[float, str]:
    """What |I - I0| is divided by, and how to say it: (|I0|, "I(t0)") normally; (S, "terms")
    where I0 vanishes against the size S of its terms (|I0| <= ZERO_FRACTION S, e.g. the solar
    system's linear momenta, ~1e-21 from terms of 1e-5); (1.0, "absolute") where both are 0
    or unknown (scale 0 or NaN: files and results from before the scales were stored)."""
    initial, scale = abs(float(initial)), float(scale) if scale == scale else 0.0
    if initial > ZERO_FRACTION * scale and initial > 0.0:
        return initial, "I(t0)"
    if scale > 0.0:
        return scale, "terms"
    return 1.0, "absolute"


def relative_error(error: float, initial: float, scale: float = 0.0) -> float:
    """|I - I0| / |I0|; where I0 is a cancellation to round-off, |I - I0| / S with S the size of
    its terms; else the absolute error (see relative_reference): the relative errors of
    inspect, the plots, the sweep tables and the energy note."""
    return float(error) / relative_reference(initial, scale)[0]


# Rounding alone moves an invariant by about this many eps times the size of its terms per
# step at most (docs/solver.md: the stopping rule accepts an iterate within a few eps of the
# solution, the stages' rounding is carried by h J, and an ill-conditioned Gamma amplifies the
# rounding of alpha), in a random walk: after N steps up to ROUNDOFF_PER_STEP eps sqrt(N) S.
# Measured over 4e5 steps: Kepler e = 0.9, h = 0.05, EHBVM(24,3) imposing L: H 1.3e-12 relative,
# 2.1e-12 with k = 48 (S/|H| = 58 at the pericentre, so 0.16 eps sqrt(N) S); the Toda lattice of
# configs/toda.yaml: imposed traces 1.4e-12 to 6.6e-12 whatever k (k = 24: 1.5e-12 to 5.0e-12),
# 2.4 to 5.4 eps sqrt(N) S (Gamma 3 x 3, 69 split steps).
ROUNDOFF_PER_STEP = 10.0


def roundoff_allowance(steps: int, initial: float, scale: float) -> float:
    """The relative error (as relative_error measures it) that rounding alone may accumulate
    over ``steps`` steps in an invariant whose value at t0 is ``initial`` and whose terms have
    the size ``scale`` (Problem.invariant_scales): ROUNDOFF_PER_STEP eps sqrt(steps) scale,
    relative. 0 where the scale is not known."""
    scale = float(scale) if scale == scale else 0.0
    if not steps or scale <= 0.0:
        return 0.0
    return ROUNDOFF_PER_STEP * np.finfo(float).eps * math.sqrt(steps) * scale / relative_reference(initial, scale)[0]


GROWN_TERMS = 100.0      # H's terms this many times their size at t0: rounding there may be the loss
PEAK_SAMPLES = 100_000   # states terms_peak looks at, at most (strided beyond)


def peak_stride(n_states: int) -> int:
    """The stride that leaves at most PEAK_SAMPLES of n_states (terms_peak's, and a file reader's)."""
    return max(1, -(-n_states // PEAK_SAMPLES))


def terms_peak(problem: Problem, states, times, reference: float) -> tuple[float, float] | None:
    """(the largest size of H's terms over ``states`` against ``reference``, their size at t0,
    and the time of that largest; Problem.invariant_scales), None without states or a
    positive reference. At most PEAK_SAMPLES states are looked at (every one up to that, evenly strided
    beyond, so a short close encounter between samples may be missed: the note then
    keeps its quadrature advice first)."""
    states, times = np.asarray(states), np.asarray(times)
    if states.ndim != 2 or states.shape[0] == 0 or not (reference > 0.0):
        return None
    stride = peak_stride(states.shape[0])
    try:
        with np.errstate(all="ignore"):
            sizes = problem.H_term_sizes(states[::stride])
    except Exception:   # noqa: BLE001 -- a python: file's own raise at a sample: no peak to tell of
        return None
    if not np.any(np.isfinite(sizes)):
        return None
    largest = int(np.nanargmax(sizes))
    return float(sizes[largest] / reference), float(times[::stride][largest])


def energy_note(method_name: str, k, r, h, relative: Mapping[str, float], adaptive: bool,
                s=None, degree=None, roundoff: Mapping[str, float] | None = None, steps: int = 0,
                tol: float | None = None, hand_written: bool = False, unchecked: bool = False,
                kinks: tuple = (), family: str | None = None,
                peak: Callable[[], tuple[float, float] | None] | None = None) -> str | None:
    """Spec 8, "Quadrature of H": HBVM(k,s) and its relatives keep H only up to the O(h^(2k+1))
    quadrature error of their k nodes when H is not a polynomial of degree <= 2k/s, and ELIM
    and LIM keep an imposed invariant up to that of their r nodes (docs/methods.md). A one-line
    note naming the relative errors (``relative``: H's and the imposed invariants') above
    H_WARNING_RELATIVE, else None; for Result.energy_warning and the run files' summaries
    (cli/report.py). An adaptive run's h is only its first step: there the largest steps,
    which rtol (or epsilon) and h_max bound, lose them.

    ``degree``: H is a polynomial of at most this degree (Problem.hamiltonian_degree; None or
    negative: not known). Where degree s <= 2k the quadrature is exact and H's error is round-off,
    which more nodes or smaller steps do not remove: the note says so instead. (The FPU chain of
    configs/fpu_beta.yaml drifts at 0.1 per unit of time: after 10^6 steps its positions are
    ~5000 while H depends on their differences, and H had lost 3e-11; the note said to raise k.)

    ``roundoff``: {name: roundoff_allowance} over the run's ``steps``. Errors within it are
    what rounding accumulates over that many steps, and the note says so instead of naming k or
    h (Kepler e = 0.9 over 4e5 steps lost H to 1.3e-12 with k = 24 and 2.1e-12 with k = 48,
    and the note said to raise k). Where r = k (EHBVM, GHBVM) the advice names k only.

    ``tol``: the solver's; one loosened above LOOSE_TOL accepts iterates that far from the
    solution, and the invariants are kept only to about that: the note names it first (a user
    trial: solver.tol = 1e-8 lost H to 1.3e-8 with k = 12 and with k = 24, and the note said to
    raise k).

    The quadrature advice adds what else a loss that a larger k leaves unchanged is: round-off
    where H's terms grow far beyond their size at t0, which the rounding allowance cannot see (a
    user trial: the Pythagorean three-body problem lost 1e-8 at a close encounter, r = 4e-4, with
    k 8 to 16 and epsilon 0.02 to 0.005 alike), and, for ``hand_written`` gradients (a python:
    file's), a grad_H that is not H's gradient (another: a 1% error in grad_H with the check off
    lost 7.7e-6 whatever k and h). ``unchecked``: the problem's check (grad L . J grad H = 0) was
    switched off, so an imposed invariant may not be one (a user trial imposed q . p on Kepler
    with problem.check: false and was told of quadrature, k and h). ``kinks``: functions with a
    kink that H calls (Problem.hamiltonian_kinks): named first where H is lost (a user trial's
    p**2/2 + abs(x) lost H to 1.6e-2 and was told to raise k). ``family``: the method's registry
    name; LIM(r,k,s) keeps H through its r nodes, not k (Family.nodes_keeping_H).

    ``peak``: called only where H's loss would get the quadrature advice, returns terms_peak of
    the run's samples. Where H's terms grew GROWN_TERMS times or more and one step's rounding of
    terms that size explains the loss (ROUNDOFF_PER_STEP eps of them), the note leads with
    that, and the quadrature advice follows as the other reading (a user trial: the Pythagorean
    three-body problem, terms 2e7 times their size at t0 at a close encounter, lost H to 4e-10
    with k = 8, 2e-10 with 12 and 2.5e-10 with 16, and was told first to raise k)."""
    above = {name: value for name, value in relative.items() if value > H_WARNING_RELATIVE}
    if not above:
        return None
    if tol is not None and tol > LOOSE_TOL:
        listed_errors = ", ".join(f"{name} {value:.1e}" for name, value in above.items())
        return (f"{listed_errors} (relative) above round-off: solver.tol = {tol:g} accepts iterates about that far "
                "from the solution, and H and the imposed invariants are kept only to about that; leave tol out "
                "(machine epsilon) to keep them to round-off")
    kind = methods.FAMILIES.get(str(family).lower()) if family is not None else None
    h_label, h_nodes = kind.nodes_keeping_H(r, k) if kind is not None else ("k", k)
    if methods.integrates_exactly(degree, h_nodes, s) and set(above) == {"H"}:
        return (f"H error {above['H']:.1e} (relative) is above round-off, but {method_name} integrates this H (a "
                f"polynomial of degree {int(degree)} <= 2{h_label}/s) exactly: it is round-off, which grows with the number "
                "of steps and with the size of the state against the differences H depends on (a drifting "
                "system's positions, say); more nodes or smaller steps do not reduce it")
    def listed(errors):
        return ", ".join(f"{name} {value:.1e}" if len(errors) > 1 else f"{name} error {value:.1e}"
                         for name, value in errors.items())

    roundoff = roundoff or {}
    if all(value <= roundoff.get(name, 0.0) for name, value in above.items()):
        bound = max(roundoff[name] for name in above)
        return (f"{listed(above)} (relative) {'are' if len(above) > 1 else 'is'} above 1e-12 but within what rounding "
                f"can accumulate over {steps:,} (sub)steps (up to {bound:.0e} here: {ROUNDOFF_PER_STEP:g} eps "
                "sqrt(steps) times the size of the terms at t0, a random walk): if it is rounding, more nodes or "
                f"smaller steps do not reduce it; a run with a larger {h_label} tells")
    above = {name: value for name, value in above.items() if value > roundoff.get(name, 0.0)}
    imposed = [name for name in above if name != "H"]
    # EHBVM, GHBVM: r = k; LIM keeps H through its r nodes too
    same_nodes = h_label == "r" or (r is not None and k is not None and int(r) == int(k))
    kept = []
    if "H" in above and imposed and h_label == "r":   # LIM: one quadrature keeps both
        kept.append(f"H and the imposed invariants only up to the quadrature error of its r = {r} nodes")
    elif "H" in above:
        kept.append(f"H only up to the quadrature error of its {h_label} = {h_nodes} nodes")
    if imposed and not ("H" in above and h_label == "r"):
        kept.append(f"{'and ' if kept else ''}the imposed invariants only up to "
                    f"{'that' if kept else 'the quadrature error'} of its r = {r} nodes"
                    + (" (the same)" if same_nodes and kept else ""))
    nodes = " and ".join(([h_label] if "H" in above or same_nodes else [])
                         + (["r"] if imposed and not same_nodes else []))
    if str(method_name).upper().startswith("GAUSS("):   # k = s is GAUSS's: more nodes is HBVM(k,s)
        nodes = f"k (HBVM(k,{str(method_name)[6:-1]}) with k > {str(method_name)[6:-1]})"
    where = (f"at h = {h:g}; raise {nodes} or reduce h" if not adaptive
             else f"at the largest steps the step control allows; raise {nodes}, tighten rtol (or epsilon) or "
                  "set h_max")
    otherwise = (f"; if a larger {nodes if nodes in ('k', 'r') else h_label} leaves it unchanged, it is not quadrature but round-off where H's terms grow far "
                 "beyond their size at t0 (a close encounter)"
                 + (", or a grad_H that is not the gradient of H (elimfast check compares them)" if hand_written
                    else "")
                 + (", or an imposed quantity that the flow of H does not conserve (problem.check is off: "
                    "elimfast check tests it)" if unchecked and imposed else ""))
    grown = peak() if peak is not None and "H" in above and not kinks and roundoff.get("H", 0.0) > 0.0 else None
    # what one step's rounding loses where the terms are that large: ROUNDOFF_PER_STEP eps of them (the
    # allowance without its sqrt(steps), which would credit every step with the encounter's size)
    at_peak = roundoff.get("H", 0.0) / math.sqrt(max(steps, 1)) * (grown[0] if grown is not None else 0.0)
    if grown is not None and grown[0] >= GROWN_TERMS and above["H"] <= at_peak:
        others = otherwise.split(" (a close encounter)", 1)[1]   # the file's gradient, an unchecked invariant
        return (f"{listed(above)} (relative) {'are' if len(above) > 1 else 'is'} above round-off. H's terms grew to "
                f"{grown[0]:.0e} times their size at t0 (largest at t = {grown[1]:.6g}: a close encounter?), where "
                f"one step's rounding alone can lose up to {at_peak:.0e} of H, whatever k and h; if a larger "
                f"{nodes if nodes in ('k', 'r') else h_label} leaves it unchanged, it is that. Else {method_name} "
                f"keeps {', '.join(kept)} {where}{others}")
    if kinks and "H" in above:   # named first: a kink is lost whatever k and h
        from .problems.expressions import kink_note
        return (f"{listed(above)} (relative) {'are' if len(above) > 1 else 'is'} above round-off. {kink_note(kinks)}; "
                f"else: {method_name} keeps {', '.join(kept)} {where}{otherwise}")
    return (f"{listed(above)} (relative) {'are' if len(above) > 1 else 'is'} above round-off: {method_name} keeps "
            f"{', '.join(kept)} {where}{otherwise}")


def resolve_conserve(problem: Problem, method: Method, conserve: Iterable[str],
                     y0=None) -> tuple[tuple[str, ...], np.ndarray]:
    """Check the invariants to impose against the problem, the method and, when given, the
    initial state y0 (require_independent_gradients); return (names, indices).

    Raises ParameterError naming the parameter (``conserve`` and the entry at fault, or the
    method's ``s`` when it is too small for the count) and the fix.
    """
    if conserve is None:
        conserve = ()    # nothing to impose (a user trial: TypeError: 'NoneType' object is not iterable)
    if isinstance(conserve, str):
        conserve = (conserve,)
    try:
        names = tuple(conserve)
    except TypeError:
        raise ParameterError("conserve", f"must be a list of invariant names, got {conserve!r}") from None
    for index, name in enumerate(names):
        if not isinstance(name, str):
            raise ParameterError("conserve", f"must be invariant names (strings), got {name!r}", index=index)
        if name not in problem.invariant_names:
            if name == "H":
                fix = "H is always conserved by HBVM/ELIM/LIM: leave it out"
            else:
                fix = suggest(name, problem.invariant_names, "its invariants")
            raise ParameterError("conserve", f"names {name!r}, but problem {problem.name!r} has no invariant "
                                             f"{name!r}; {fix}", index=index)
        if name in names[:index]:
            raise ParameterError("conserve", f"lists {name!r} twice; list each invariant once", index=index)
    method.require_imposable(len(names))
    if not method.kind.imposes_linear:
        for index, name in enumerate(names):
            if name in problem.linear_invariant_names:
                raise ParameterError("conserve", f"names {name!r}, which is linear: "
                                     + method.kind.linear_refusal.format(method=method.name), index=index)
            if method.kind.linear_refusal and name in problem.quadratic_invariant_names:
                # (a user trial: a charged particle in a magnetic field imposing its canonical angular
                # momentum split 9,995 of 10,000 steps and failed at a larger h, cond(Gamma) inf)
                raise ParameterError("conserve", f"names {name!r}, which is quadratic, as H is: then {method.name}'s "
                                     "HBVM step is Gauss collocation, which keeps every quadratic invariant exactly, "
                                     "and ELIM cannot impose one (Gamma vanishes, docs/methods.md#linear-invariants); "
                                     "leave it out of conserve (it is kept anyway), or impose it with lim/ghbvm",
                                     index=index)
    indices = np.array([problem.invariant_names.index(n) for n in names], dtype=np.int64)
    if names and y0 is not None:
        require_independent_gradients(problem, names, indices, y0)
    return names, indices


# The smallest singular value of the unit gradients of H and the imposed invariants at y0
# below which they count as linearly dependent (about 5000 eps). Kepler's circular orbit,
# imposing angular momentum: 5.6e-17 (a rounding of zero); at a small eccentricity e about 0.35 e. Measured (EHBVM(12,3),
# h = 0.1, [0, 1000]): e = 1e-10 completes at 1024 iterations per step, e = 1e-8 at 104,
# e = 1e-6 at 11 (e = 0.01: 4.7); e = 0 took ~2,100 per step for 2,849 steps and then failed
# (cond(Gamma) inf). GHBVM fails at its first step from e = 1e-8 down (Gram matrix).
DEPENDENT_GRADIENTS = 1e-12


def _scaled_gradients(problem: Problem, indices, y) -> np.ndarray | None:
    """grad H and the gradients of the invariants ``indices`` at y, as rows, each gradient's q part
    times |q| and its p part times |p| (the terms of the invariant's change, as in
    Problem.invariant_scales), so that tests on them do not depend on the units of q and p (a
    user trial: Kepler in SI units, q ~ 1e11 m, p ~ 1e29 kg m/s, e = 0.6, was refused for L at
    1.5e-19, as was the same orbit after the canonical change q -> 1e7 q); None where one is not
    finite (a singularity, which the run reports itself)."""
    y = np.asarray(y, dtype=float)
    rows = np.vstack([problem.gradient(y), problem.invariant_gradients(y)[indices]])
    if not np.all(np.isfinite(rows)):
        return None
    m = problem.degrees_of_freedom
    size_q, size_p = float(np.max(np.abs(y[:m]))), float(np.max(np.abs(y[m:])))
    return rows * np.repeat([size_q or size_p or 1.0, size_p or size_q or 1.0], m)


# At a failing step whose Gamma is nearly singular (cond > NEARLY_SINGULAR_GAMMA after halving),
# the smallest singular value of the unit gradients of H and the imposed invariants there (scaled
# as _scaled_gradients) below which the invariants are degenerate at that point of the orbit, which
# no step size cures; above it, cond(Gamma) is its scaling. Measured along whole orbits: Kepler's L
# with A_x started 1 time unit along the e = 0.6 orbit (A_y = 2e-6): 6.9e-7 to 1.9e-6; L with A_y
# at e = 0.6, 0.9, 0.99: 0.16 to 0.54. A user trial at e = 0.99, h = 0.1 (cond(Gamma) 1.4e9, which
# h = 0.01 or max_halvings 8 get through) was told that smaller steps do not cure it.
DEGENERATE_AT_FAILURE = 1e-3


def gradients_independence(problem: Problem, indices, y) -> float | None:
    """The smallest singular value of the unit gradients of H and of the invariants ``indices`` at
    y (scaled as _scaled_gradients): 0 where they are linearly dependent, 1 for orthogonal ones;
    None where it cannot be judged (a gradient not finite or zero, nothing imposed)."""
    if len(indices) == 0 or y is None:
        return None
    try:
        with np.errstate(all="ignore"):
            scaled = _scaled_gradients(problem, indices, y)
            if scaled is None:
                return None
            sizes = np.linalg.norm(scaled, axis=1)
            if not np.all(sizes > 0.0):
                return None
            return float(np.linalg.svd(scaled / sizes[:, None], compute_uv=False)[-1])
    except Exception:   # noqa: BLE001 -- for a failure's message: a problem function that raises there
        return None     # (a python: file's, which the run reports itself) leaves it unjudged


def _dependent_around(problem: Problem, indices: np.ndarray, y0, tries: int = 4) -> bool:
    """Whether grad H and the gradients of the invariants ``indices`` are linearly dependent at every one
    of ``tries`` states 1% around y0 (seeded): a relation between the functions, not a property of y0."""
    rng = np.random.default_rng(20261204)
    y0 = np.asarray(y0, dtype=float)
    size = float(np.max(np.abs(y0))) or 1.0
    with np.errstate(all="ignore"):
        for _ in range(tries):
            y = y0 + 0.01 * (np.abs(y0) + 0.1 * size) * rng.standard_normal(y0.shape)
            try:
                scaled = _scaled_gradients(problem, indices, y)
            except Exception:   # noqa: BLE001 -- a problem function that fails there: no judgement
                return False
            if scaled is None:
                return False
            sizes = np.linalg.norm(scaled, axis=1)
            if not np.all(sizes > 0.0) or not np.all(np.isfinite(scaled)):
                return False
            if float(np.linalg.svd(scaled / sizes[:, None], compute_uv=False)[-1]) >= DEPENDENT_GRADIENTS:
                return False
    return True


def require_independent_gradients(problem: Problem, names: tuple[str, ...], indices: np.ndarray, y0) -> None:
    """Refuse to impose invariants whose gradients at y0 are linearly dependent on grad H and
    on those of the invariants listed before them (ParameterError naming ``conserve[i]``),
    judged on the gradients scaled by the size of q and of p (independent of units).

    There ELIM's Gamma and LIM's Gram matrix are singular (Assumption 1 of the paper,
    docs/methods.md): each step fails imposed, and a run either stops at once (LIM) or
    crawls for thousands of steps before it stops (ELIM). A gradient that is not finite at
    y0 (a singularity, which the run reports itself) is not judged here.
    """
    scaled = _scaled_gradients(problem, indices, y0)
    if scaled is None:
        return
    rows, gradients = [scaled[0]], scaled[1:]
    size_H = float(np.linalg.norm(rows[0]))
    if size_H == 0.0:
        raise ParameterError("conserve", f"names {', '.join(map(repr, names))}, but grad H vanishes at y0 (an "
                             "equilibrium): no invariant can be imposed there (Gamma is singular, docs/methods.md); "
                             "leave conserve empty or start from another state")
    rows[0] = rows[0] / size_H
    for index, (name, gradient) in enumerate(zip(names, gradients)):
        size = float(np.linalg.norm(gradient))
        if size == 0.0:
            raise ParameterError("conserve", f"names {name!r}, whose gradient vanishes at y0: it cannot be imposed "
                                 "there (Gamma is singular, docs/methods.md); leave it out or start from another "
                                 "state", index=index)
        rows.append(gradient / size)
        smallest = float(np.linalg.svd(np.vstack(rows), compute_uv=False)[-1])
        if smallest < DEPENDENT_GRADIENTS:
            others = "grad H" + "".join(f" and grad {other}" for other in names[:index])
            if _dependent_around(problem, indices[:index + 1], y0):
                # a relation between them holds everywhere (a user trial: Kepler's H, L, A_x, A_y, tied by
                # |A|^2 = 1 + 2 H L^2, was told to start from another state, which was refused the same way)
                raise ParameterError(
                    "conserve",
                    f"names {name!r}, whose gradient depends linearly on {others} at y0 and at every state tried "
                    f"around it (smallest singular value of the unit gradients {smallest:.1e}): a relation ties "
                    "these invariants (Kepler's H, L and LRL vector: |A|^2 = 1 + 2 H L^2), so no state helps; "
                    "Gamma (LIM: the Gram matrix) is singular: leave it out, the method keeps it with the others "
                    "(docs/methods.md)", index=index)
            example = "; angular momentum on a circular orbit, say, is a function of H" if index == 0 else ""
            raise ParameterError(
                "conserve",
                f"names {name!r}, whose gradient at y0 depends linearly on {others} (smallest singular value of the "
                f"unit gradients {smallest:.1e}{example}): Gamma (LIM: the Gram matrix) is singular there, so it "
                "cannot be imposed (docs/methods.md); leave it out, or start from another state", index=index)


def suggest(word, options, label: str) -> str:
    """'did you mean 'x'? (label: a, b, c)' or 'label: a, b, c' (for the fix of an unknown name)."""
    options = [str(o) for o in options]
    listed = ", ".join(options) or "none"
    match = closest(word, options)
    close = [match] if match is not None else []
    if not close:   # an abbreviation (dir for direction) is too short for difflib's ratio
        close = [o for o in options if len(str(word)) >= 2 and o.startswith(str(word))][:2]
        close = close if len(close) == 1 else []
    return f"did you mean {close[0]!r}? ({label}: {listed})" if close else f"{label}: {listed}"


# Why a run may take at most MAX_STEPS steps (said in the error).
STEPS_COST = ("that many steps take hours to days even at a microsecond each, and their per-step records "
              "alone 40 GB")
STEPS_REASON = f"{STEPS_COST}; raise h or shorten the run"   # (adaptive.resolve_span's h_max: raise h_max)


def resolve_t0(t0) -> float:
    """The initial time as a finite float, else a ParameterError naming t0 (a NaN t0 was
    reported as a bad t_end)."""
    value = real_number("t0", t0)
    if not math.isfinite(value):
        raise ParameterError("t0", f"must be a finite number, got {t0!r}")
    return value


def resolve_steps(h, t_end=None, n_steps=None, t0: float = 0.0) -> tuple[float, int]:
    """Validate h and t_end or n_steps (both: they must agree); return (h, n_steps).

    Raises ParameterError naming h, t0, t_end or n_steps and the fix.
    """
    t0 = resolve_t0(t0)
    h = real_number("h", h)
    if not (math.isfinite(h) and h > 0.0):
        raise ParameterError("h", f"must be > 0 and finite, got {h!r}")
    if t0 + h == t0:
        # (a user trial: t0 = 1e20 with h = 0.1 ran, every stored t equal to t0)
        raise ParameterError("h", f"= {h!r} is below the resolution of the times at t0 = {t0!r} (t0 + h == t0 in "
                                  "doubles); measure time from a nearer origin (t0 = 0)")
    if t_end is None and n_steps is None:
        raise ParameterError("t_end", "is missing; give t_end (the final time) or n_steps")
    if n_steps is not None:
        n_steps = _whole_number("n_steps", n_steps, 1, MAX_STEPS, f": {STEPS_REASON}")
    if t_end is None:
        if not math.isfinite(float(t0) + n_steps * h):
            raise ParameterError("h", f"gives t0 + n_steps h = {t0!r} + {n_steps} * {h!r}, not a finite number; "
                                      "lower h or n_steps")
        return h, n_steps
    span = real_number("t_end", t_end) - t0
    if not (math.isfinite(span) and span > 0.0):
        # (a user trial looked for backward runs here: only the Python API's backward=True makes one)
        raise ParameterError("t_end", f"must be after t0 = {t0!r} (and finite), got {t_end!r}; runs go forward in "
                                      "time (a backward one: elimfast.integrate(..., backward=True) in Python)",
                             related=("t0",))
    if not span / h <= MAX_STEPS:
        raise ParameterError("t_end", f"(t_end - t0)/h = {span / h:.3g} steps, more than "
                                      f"{compact_number(MAX_STEPS)}: {STEPS_REASON}", related=("h", "t0"))
    steps = round(span / h)
    if steps < 1 or abs(steps * h - span) > T_END_RELATIVE_TOLERANCE * span:
        raise ParameterError("t_end", f"gives t_end - t0 = {span!r}, not a whole number of steps of h = {h!r} "
                                      f"({span / h:.12g} steps); adjust h or t_end, or give n_steps instead",
                             related=("h", "t0"))
    if n_steps is not None and n_steps != steps:
        raise ParameterError("n_steps", f"= {n_steps} disagrees with t_end: (t_end - t0)/h = {steps}; give only "
                                        "one of them")
    return h, int(steps)


def resolve_initial_state(problem: Problem, y0=None) -> np.ndarray:
    """The run's initial state: y0, or the problem's; 2m finite real numbers (a fresh copy)
    where H and the problem's invariants are finite, else a ParameterError naming y0.

    H itself is checked, not only its gradient: an expression H = p^2/2 + log(x) at x = -1
    has the finite gradient 1/x, so the steps are taken (for log|x|), while H, the one number
    the method keeps, was NaN in every sample of a run that said "complete" (a user trial;
    a python: file's H was refused at load already)."""
    n = 2 * problem.degrees_of_freedom
    y = real_state(problem.y0 if y0 is None else y0)
    if y.shape != (n,) or not np.all(np.isfinite(y)):
        raise ParameterError("y0", f"must be {n} finite numbers ({', '.join(problem.coordinate_names)}), "
                                   f"got {y!r}")
    undefined = undefined_at(problem, y)
    if undefined is not None:
        raise ParameterError("y0", f"gives {undefined} at the initial state {y.tolist()}: it is not "
                                   "defined there; choose an initial state away from its singularities")
    return y


def undefined_at(problem: Problem, y) -> str | None:
    """'H = nan' (or "the invariant 'L' = inf") when H or an invariant is not finite at y, else None:
    resolve_initial_state's refusal, and an ensemble trajectory's failure at its first step."""
    try:
        with np.errstate(all="ignore"):
            values = problem.invariant_values(y)
    except ArithmeticError:   # 1/0 under Numba's default error model (a python: file's own functions)
        values = {"H": math.nan}
    for name, value in values.items():
        if not math.isfinite(value):
            return f"H = {value}" if name == "H" else f"the invariant {name!r} = {value}"
    return None


def available_memory() -> int | None:
    """Bytes of memory the system can give a new allocation (Linux: MemAvailable), or None."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def dense_matrix_bytes(n: int, method: Method, solver: "SolverSettings", adaptive: bool) -> int:
    """The bytes of a run's n x n arrays (kernels/workspace.py make_workspace): simplified
    Newton's Hessian, Jacobian and factorised blocks (or its whole (s n)^2 matrix), twice in an
    adaptive run (its side steps have a workspace of their own), and the adaptive error
    estimate's Hessian; the fixed point has none but that last one."""
    from .kernels.workspace import workspace_dense_bytes
    # the kernels' n_eigenvalues (stepper.newton_eigenvalues): -1 for the fixed point
    eigenvalues = -1 if solver.method == "fixed_point" else method.newton_values.shape[0]
    workspaces = 2 if adaptive else 1
    return workspaces * workspace_dense_bytes(n, method.s, eigenvalues) + (8 * n * n if adaptive else 0)


def require_memory(problem: Problem, method: Method, solver: "SolverSettings", adaptive: bool) -> None:
    """Refuse (ParameterError naming solver) a run whose dense n x n arrays do not fit in the
    memory available, before any is allocated: fpu_beta with 10^5 masses died of a MemoryError
    that was blamed on the problem's functions."""
    n = 2 * problem.degrees_of_freedom
    needed, available = dense_matrix_bytes(n, method, solver, adaptive), available_memory()
    if available is None or needed <= available:
        return
    what = (f"simplified Newton stores dense n x n matrices, {needed / 2 ** 30:.1f} GB at n = {n:,}"
            if solver.method != "fixed_point" else
            f"adaptive steps, output times and events store a dense n x n Hessian, {needed / 2 ** 30:.1f} GB at "
            f"n = {n:,}")
    fix = ("use the fixed point (solver: {method: fixed_point}; in Python solver='fixed_point'), whose work and "
           "memory grow like n" if solver.method != "fixed_point" else
           "use fixed steps (h, without output times or events) with the fixed point")
    raise ParameterError("solver", f"cannot run here: {what}, more than the {available / 2 ** 30:.1f} GB of memory "
                                   f"available; {fix}")


def resolve_store_every(store_every) -> int:
    """Validate the sampling interval (keep every n-th state): a whole number from 1 to MAX_STEPS."""
    return _whole_number("store_every", store_every, 1, MAX_STEPS,
                         " (the most steps a run may take); to keep only the first and last states, set it to the "
                         "number of steps")


def predictor_extra_state(method: Method, n: int) -> np.ndarray:
    """The run state's coef_extra: the last step's Legendre terms gamma_s.. that the predictor
    carries over besides its coefficients (docs/solver.md); as many rows as
    kernels/stepper.py predictor_extra_rows gives the ensemble kernel's trajectories."""
    return np.zeros((min(method.k - method.s, codes.PREDICTOR_EXTRA_ROWS), n))


def restore_predictor_extra(state: dict, target: np.ndarray) -> None:
    """Give a saved state without coef_extra (saved before the predictor kept extra terms) zero
    rows, in place: its first step is then predicted from the coefficients alone, as that
    version predicted it (bit for bit), and the later steps with the extra terms. Such a
    resumed run is therefore not bit for bit an uninterrupted run of this version; a state
    saved by this version is."""
    if "coef_extra" not in state:
        state["coef_extra"] = np.zeros(target.shape)


class Integration:
    """A run in progress: validated arguments, the kernel state, and ``advance``.

    ``advance(n)`` runs up to n more steps in one kernel call and returns a Chunk;
    consecutive calls continue the same run exactly (compensated y and t, last
    coefficients, the predictor's last step size). The state can be saved and restored
    (``state`` / ``restore``) so a run resumed from it ends bit for bit where an
    uninterrupted one would. The solver settings may differ between the saved run and
    the resumed one (a failed run continues with, say, more halvings); they only decide
    how each step's system is solved, not which steps are taken.
    """

    def __init__(self, problem: Problem, method: Method, h: float, n_steps: int, conserve=(),
                 tol: float | None = None, max_iter: int | None = None, store_every: int = 1,
                 rhs: str = "stable", warm_start: bool = True, t0: float = 0.0, y0=None,
                 backward: bool = False, solver: str | SolverSettings = DEFAULT_SOLVER,
                 predictor: bool = True, max_halvings: int = DEFAULT_MAX_HALVINGS, check_y0: bool = True):
        require_problem_object(problem)
        if not isinstance(method, Method):
            raise TypeError(f"method must be an elimfast Method (e.g. elimfast.methods.ehbvm(12, 3)), "
                            f"got {type(method).__name__}")
        self.problem, self.method = problem, method
        self.y = resolve_initial_state(problem, y0)
        # check_y0 False: the invariants' gradients at y0 are not judged (an ensemble's
        # trajectories each fail alone, in their own status, where they cannot be imposed).
        self.conserve, self.conserve_idx = resolve_conserve(problem, method, conserve, self.y if check_y0 else None)
        self.h, self.n_steps = resolve_steps(h, n_steps=n_steps)
        self.backward = bool(backward)
        solver = _solver_settings(solver, tol, max_iter, max_halvings, predictor, warm_start, rhs)
        self.solver = solver.resolved_for(method, len(self.conserve), 2 * problem.degrees_of_freedom)
        require_memory(problem, method, self.solver, adaptive=False)
        self.store_every = resolve_store_every(store_every)
        self._time_loop = None   # loaded at first use (prepare_kernel)

        n = 2 * problem.degrees_of_freedom
        self.y0 = self.y.copy()   # the state at t0, the reference of the invariant errors (Result.y0)
        self.y_comp = np.zeros(n)
        self.clock = np.array([float(t0), 0.0])
        self.t0 = float(t0)
        self.coef = np.zeros((method.s, n))
        self.coef_extra = predictor_extra_state(method, n)
        self.multipliers = np.zeros(method.multiplier_count(len(self.conserve)))
        self.last_h = np.array([self.signed_h])
        self.newton_base = np.zeros(n + 3)   # where the Newton matrix was factorised (kernels/stepper.py)
        self.H_target = self.solver.energy_target(problem, method, self.y0)
        self.steps_done = 0
        self.status = codes.STATUS_OK
        self.diagnostics = np.zeros(codes.N_DIAGNOSTICS)
        self._progress = np.zeros(2, dtype=np.int64)

    @classmethod
    def from_spec(cls, spec) -> "Integration":
        """A fresh run of a validated config (``elimfast.config.RunSpec``); store_every = output.every.
        A config with adaptive steps, output times or events gets the run of the adaptive
        kernel instead (``elimfast.adaptive.AdaptiveIntegration``, driven alike)."""
        if getattr(spec, "uses_adaptive_kernel", False):
            from .adaptive import AdaptiveIntegration
            return AdaptiveIntegration.from_spec(spec)
        return cls(spec.problem, spec.method, spec.h, spec.n_steps, conserve=spec.conserve, solver=spec.solver,
                   store_every=spec.output_every, t0=spec.t0)

    adaptive_kernel = False   # fixed steps through stepper.time_loop (elimfast.adaptive: the other kernel)

    @property
    def complete(self) -> bool:
        return self.steps_done >= self.n_steps and self.status == codes.STATUS_OK

    @property
    def remaining_steps(self) -> int:
        return self.n_steps - self.steps_done

    # Settings kept as attributes for callers that read them (and old pickles of runs).
    tol = property(lambda self: self.solver.tol)
    max_iter = property(lambda self: self.solver.max_iter)
    rhs = property(lambda self: self.solver.rhs)
    warm_start = property(lambda self: self.solver.warm_start)

    @property
    def signed_h(self) -> float:
        return -self.h if self.backward else self.h

    # --- state -------------------------------------------------------------------------
    @property
    def t(self) -> float:
        return float(self.clock[0])

    @property
    def finished(self) -> bool:
        return self.steps_done >= self.n_steps or self.status != codes.STATUS_OK

    def state(self) -> dict[str, np.ndarray | int]:
        """Everything needed to continue the run exactly (for resume)."""
        return {"y": self.y.copy(), "y_comp": self.y_comp.copy(), "clock": self.clock.copy(),
                "coef": self.coef.copy(), "coef_extra": self.coef_extra.copy(), "multipliers": self.multipliers.copy(),
                "last_h": self.last_h.copy(), "newton_base": self.newton_base.copy(), "steps_done": self.steps_done}

    def restore(self, state: dict) -> None:
        """Continue from a saved state. A state saved before the step engine has no last_h and
        no newton_base: the previous step is then taken to have been a whole step (theta =
        1), and the first step factorises its Newton matrix afresh. One saved before the
        predictor kept extra terms has no coef_extra (see restore_predictor_extra)."""
        state = dict(state)
        state.setdefault("last_h", np.array([self.signed_h]))
        state.setdefault("newton_base", np.zeros(self.newton_base.size))
        restore_predictor_extra(state, self.coef_extra)
        for key in ("y", "y_comp", "clock", "coef", "coef_extra", "multipliers", "last_h", "newton_base"):
            target = getattr(self, key)
            value = np.asarray(state[key], dtype=np.float64)
            if value.shape != target.shape:
                raise ValueError(f"saved state {key!r} has shape {value.shape}, expected {target.shape}")
            target[...] = value
        self.steps_done = int(state["steps_done"])
        self.status = codes.STATUS_OK

    def n_samples_between(self, first_step: int, n: int) -> int:
        """Samples stored by steps first_step+1 .. first_step+n (multiples of store_every, and the last)."""
        last = first_step + n
        count = last // self.store_every - first_step // self.store_every
        if last == self.n_steps and self.n_steps % self.store_every != 0:
            count += 1
        return count

    def initial_chunk(self) -> Chunk:
        """The sample of the current state (at t0: H and invariants at y0), with no steps."""
        p = self.problem
        values = np.empty(len(p.invariant_names))
        p.invariants(self.y, p.params, values)
        inv = np.concatenate(([p.H(self.y, p.params)], values))[None, :]
        return Chunk(np.array([self.t]), self.y[None, :].copy(), inv, np.zeros((0, self.multipliers.size)),
                     np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), self.steps_done, codes.STATUS_OK)

    # --- stepping ----------------------------------------------------------------------
    def kernel_settings(self) -> tuple:
        """The problem's functions, the solver settings and the method's tables, in the order
        of the kernels' signatures (stepper.time_loop and ensemble.ensemble_loop)."""
        p, m, solver = self.problem, self.method, self.solver
        return (p.H, p.grad_H, p.hess_H, p.invariants, p.grad_invariants, p.params,
                m.kernel_family, solver.code, solver.rhs_code, int(solver.warm_start),
                int(solver.predictor), solver.tol, solver.max_iter, solver.max_halvings,
                self.signed_h, m.projection, m.Is, m.projection_hat, m.Is_hat, m.X, m.abs_projection_hat,
                m.predictor_nodes, m.predictor_basis, m.newton_values, m.newton_vectors, m.newton_inverse,
                m.newton_weights, m.Is_low, m.Is_hat_low, self.conserve_idx)

    def prepare_kernel(self) -> None:
        """Load the kernel, compiling it on an empty cache; the first advance does it otherwise.
        Not at import or construction: checking a config must not wait for a compilation (minutes
        after an upgrade), and an ensemble runs another kernel. The shared kernel
        (kernels.stepper.time_loop), or the per-problem one (solver.kernel: per_problem, about 90 s
        the first time for this problem)."""
        if self._time_loop is None:
            if self.solver.kernel == "shared":
                from .kernels import stepper
                self._time_loop = stepper.time_loop
            else:
                from .per_problem import time_loop_for
                self._time_loop = time_loop_for(self.problem)

    def advance(self, max_steps: int) -> Chunk:
        """Run up to max_steps more steps in one kernel call."""
        p = self.problem
        n_run = int(min(max_steps, self.n_steps - self.steps_done))
        n_samples = self.n_samples_between(self.steps_done, n_run)
        dim = self.y.size
        t_out = np.empty(n_samples)
        y_out = np.empty((n_samples, dim))
        inv_out = np.empty((n_samples, 1 + len(p.invariant_names)))
        mult_out = np.empty((n_run, self.multipliers.size))
        iter_out = np.zeros(n_run, dtype=np.int64)
        substeps_out = np.zeros(n_run, dtype=np.int64)
        if n_run <= 0 or self.status != codes.STATUS_OK:
            return Chunk(t_out, y_out, inv_out, mult_out, iter_out, substeps_out, self.steps_done, self.status)
        self.prepare_kernel()
        with remembered_addresses():
            status = self._time_loop(
                *self.kernel_settings(),
                self.y, self.y_comp, self.clock, self.coef, self.coef_extra, self.multipliers, self.last_h,
                self.newton_base, self.H_target, self.steps_done, n_run, self.n_steps, self.store_every,
                t_out, y_out, inv_out, mult_out, iter_out, substeps_out, self._progress, self.diagnostics)
        done, samples = int(self._progress[0]), int(self._progress[1])
        first = self.steps_done
        self.steps_done += done
        self.status = int(status)
        # On failure keep the failed step's iteration count: it says how hard the step was.
        n_iter = done + (1 if status != codes.STATUS_OK else 0)
        t_out, y_out, inv_out = t_out[:samples], y_out[:samples], inv_out[:samples]
        if status != codes.STATUS_OK and self.steps_done % self.store_every != 0:
            # The failure fell between samples: keep one of the last good state (resume drops it again).
            last = self.initial_chunk()
            t_out, y_out, inv_out = (np.concatenate([t_out, last.t]), np.concatenate([y_out, last.y]),
                                     np.concatenate([inv_out, last.invariants]))
        return Chunk(t_out, y_out, inv_out, mult_out[:done], iter_out[:n_iter], substeps_out[:done], first,
                     int(status))

    def failure_message(self, run_file: bool = False) -> str:
        """One line naming the step and time of a failure, what the solver saw, and what to do
        (run_file: the run is in a run file, which --resume continues)."""
        return failure_message(self.method, self.solver, self.status, self.steps_done + 1, self.t, self.signed_h,
                               self.diagnostics, run_file=run_file, y=self.y, y0=self.y0,
                               independence=gradients_independence(self.problem, self.conserve_idx, self.y),
                               problem=self.problem, imposed=len(self.conserve_idx))


# A failing step whose state has grown this much beyond the initial one says so: the orbit is
# likely leaving every bounded region, which no step size or solver setting gets through.
GROWN_STATE = 1e3


def max_iter_below_defaults(solver: SolverSettings) -> bool:
    """Is solver.max_iter set below every default? Then it is the likelier cause of a solve that does
    not converge than the step or the problem."""
    return solver.max_iter is not None and solver.max_iter < DEFAULT_MAX_ITER_ELIM_NEWTON


def raise_max_iter(solver: SolverSettings) -> str:
    return (f"raise solver.max_iter (= {solver.max_iter} now; the default is {DEFAULT_MAX_ITER_ELIM_NEWTON} or "
            f"{DEFAULT_MAX_ITER})")


def gradient_not_finite(problem: Problem, y, t: float, h: float) -> str | None:
    """For a step that went NaN or infinite: probe grad H along the step's way (forward Euler
    from its start, y + tau h f(y), tau = 0, 1/16, ..., 1). A gradient that is not finite where H
    is finite is the problem's gradient's doing, not the step's (a user trial: a python: file's
    grad_H returning NaN was advised 'reduce h'). Returns the clause that says so, else None."""
    m = problem.degrees_of_freedom
    y = np.asarray(y, dtype=np.float64)
    try:
        with np.errstate(all="ignore"):
            gradient = problem.gradient(y)
            flow = np.concatenate([gradient[m:], -gradient[:m]])
            for tau in np.linspace(0.0, 1.0, 17):
                point = y + (tau * h) * flow if tau > 0 else y
                if not np.all(np.isfinite(point)):
                    return None
                value, gradient = problem.hamiltonian(point), problem.gradient(point)
                if not np.all(np.isfinite(gradient)):
                    if not math.isfinite(value):
                        return None   # a singularity of H itself (a collision): the general advice
                    bad = int(np.flatnonzero(~np.isfinite(gradient))[0])
                    return (f"grad H is not finite there while H is: dH/d{problem.coordinate_names[bad]} = "
                            f"{gradient[bad]} at y = {point.tolist()} (about t = {t + tau * h:.6g}), where H = "
                            f"{value:.6g}; check the problem's gradient there (a mistake in grad_H, or a "
                            "singularity H does not show)")
    except ArithmeticError:   # a python: file's function raised (Numba's default error model)
        return None
    return None


def failure_message(method: Method, solver: SolverSettings, status: int, step: int, t: float, h: float,
                    diagnostics, adaptive: bool = False, run_file: bool = False, y=None, y0=None,
                    advise: bool = True, independence: float | None = None, problem: Problem | None = None,
                    imposed: int | None = None) -> str:
    """The one-line report of a step that failed at every level of splitting (docs/solver.md);
    adaptive: the run chose its steps (docs/adaptive.md), so the advice is not about h;
    run_file: the run is in a run file, which `elimfast run --resume` continues with other
    solver settings (not said to the Python API or a sweep, which cannot); y, y0: the state
    where it failed and the initial one (a state grown beyond GROWN_STATE times is named);
    advise: False leaves the advice out, where the caller knows that no setting helps;
    independence: gradients_independence at y (None: not known), which tells a Gamma nearly singular
    because the invariants are degenerate there from one that is only badly scaled; problem: the
    run's, whose gradient a non-finite step probes (gradient_not_finite); imposed: how many invariants
    the run imposes (None: not known; 0 makes ELIM and LIM an HBVM, with no Gamma to blame)."""
    from .kernels import solver as solver_rules   # the stopping rule's band (loaded: a run got here)
    what = _FAILURE_TEXT[status]
    if status == codes.STATUS_NOT_CONVERGED:
        what = f"the {solver.description} did not converge (max_iter = {solver.max_iter})"
    d = diagnostics
    depth = int(d[codes.DIAG_DEPTH])
    where = f"at step {step} (t = {exact_time(t)} -> {exact_time(t + h)})"
    if depth > 0:
        where += f", in its substep from t = {exact_time(d[codes.DIAG_TIME])} of h = {d[codes.DIAG_STEP]:.6g} " \
                 f"after {depth} halving{'s' if depth > 1 else ''}"
    lim = method.kind.kernel_map == "lim"   # its small system is the Gram matrix, not Gamma
    seen = [f"last relative increment {d[codes.DIAG_INCREMENT]:.2e}"]
    if status == codes.STATUS_NOT_CONVERGED and 0.0 < d[codes.DIAG_INCREMENT] <= solver_rules.BAND_CAP:
        # An increment of 5e-16 read as a contradiction of "did not converge" (the last note): the
        # iterates stopped at rounding's size, but above the band of this step's own rounding.
        seen[0] += (" (rounding's size, but above the band of this step's own rounding that the stopping rule "
                    "accepts: docs/solver.md#when-to-stop)")
    newton_matrix = False
    if status == codes.STATUS_SINGULAR and d[codes.DIAG_INCREMENT] == math.inf:
        seen = ["before any increment"]   # the solve's d before its first one: the first map failed
        # ... or, where no invariant can be imposed (GAUSS, HBVM), the Newton matrix did not factorise
        # (a user trial: EHBVM imposing nothing was told that Assumption 1 fails for its invariants)
        newton_matrix = (method.kind.imposes == IMPOSES_NONE or imposed == 0) and solver.method == "newton"
        if newton_matrix:
            what = "the simplified Newton matrix I - h X (x) J Hess(H) is singular"
    if status == codes.STATUS_TIME_SCALE:   # the adaptive kernel leaves sigma(y) in the increment's slot
        seen = [f"sigma(y) = {d[codes.DIAG_INCREMENT]:.3g} there, next step h = {d[codes.DIAG_STEP]:.3g}"]
    elif d[codes.DIAG_CONDITION] != 0.0 and lim:
        seen.append("Gram matrix not positive definite")
    elif d[codes.DIAG_CONDITION] != 0.0:
        seen.append(f"cond(Gamma) {d[codes.DIAG_CONDITION]:.2e}")
    advice = (_ADAPTIVE_FAILURE_ADVICE if adaptive else _FAILURE_ADVICE)[status]
    if newton_matrix:
        advice = "use the fixed point (solver.method: fixed_point), or change h"
    elif status == codes.STATUS_SINGULAR and lim:   # no step size or s makes dependent gradients independent
        advice = _LIM_SINGULAR_ADVICE
    elif (adaptive and status not in (codes.STATUS_NONFINITE, codes.STATUS_TIME_SCALE)
            and method.s > ADAPTIVE_MEASURED_S):
        # at s <= 6 a lower s was advice that did not help (LIM(6,6,3) imposing L, A_x, A_y: singular at t0)
        advice += f", or use a lower s (docs/adaptive.md measures s <= {ADAPTIVE_MEASURED_S})"
    nearly_singular = (status == codes.STATUS_NOT_CONVERGED and d[codes.DIAG_CONDITION] > NEARLY_SINGULAR_GAMMA
                       and depth > 0)
    independent = independence is not None and independence >= DEGENERATE_AT_FAILURE
    independent_text = (f"the invariants' gradients independent here (smallest singular value {independence:.2g})"
                        if independent else "")
    if nearly_singular and independent:
        # Gamma's condition grows with its scaling too (near a pericentre of e = 0.99 cond ~ 1/h): with
        # the gradients independent here, smaller steps are the cure, not other invariants.
        seen.append(independent_text)
        nearly_singular = False
    if (status == codes.STATUS_SINGULAR and not lim and imposed != 0 and independent
            and d[codes.DIAG_INCREMENT] <= solver_rules.BAND_CAP and math.isfinite(d[codes.DIAG_CONDITION])):
        # Converged, but Gamma too degenerate for alpha (finite cond: not exactly singular, as on a
        # radial orbit, where L's Gamma vanishes by symmetry), where the invariants' gradients are
        # independent: a (sub)step too short for Gamma, whose entries (Legendre coefficients of size
        # ~h^j) fall below the rounding of the sums that form them; halving made it worse (a user trial:
        # Kepler e = 0.9 imposing L and A_y at h = 1e-5, after 4 halvings, was told that Assumption 1
        # fails and to impose other invariants; GHBVM completes; docs/solver.md#a-substep-without-imposing)
        seen.append(independent_text)
        shorter = "loosen rtol or raise epsilon" if adaptive else (
            "take a larger h" + (", or fewer halvings (solver.max_halvings)" if depth > 0 else ""))
        advice = (f"a step of {d[codes.DIAG_STEP]:.3g} is too short for ELIM's Gamma here: its entries, of size about "
                  "h^j, fall below their own rounding, and halving makes it worse "
                  f"(docs/solver.md#a-substep-without-imposing); {shorter}, or {_TAKE_GHBVM})")
    elif nearly_singular:
        # Still nearly singular after halving, and the invariants degenerate here (or not known):
        # not a step symmetric about a pericentre (docs/solver.md), whose halves are well-conditioned.
        advice = _NEARLY_SINGULAR_ADVICE
    elif status == codes.STATUS_NOT_CONVERGED and solver.max_halvings < MAX_MAX_HALVINGS and not adaptive:
        advice = f"reduce h, or allow more step halvings (solver.max_halvings = {solver.max_halvings} now)"
    if solver.rhs == "literal" and method.kind.imposes != IMPOSES_NONE and method.r <= method.k and \
            status in (codes.STATUS_NOT_CONVERGED, codes.STATUS_SINGULAR):
        advice = _LITERAL_RHS_ADVICE
    elif status in (codes.STATUS_NOT_CONVERGED, codes.STATUS_SINGULAR) and method.r > method.k:
        advice = literal_sum_note(method.family, method.r, method.k, method.s, solver.rhs) or advice
    if status == codes.STATUS_NOT_CONVERGED and max_iter_below_defaults(solver):
        # a cap set below any default is the likelier cause (a user trial: max_iter = 1 was told to reduce h)
        advice = f"{raise_max_iter(solver)}, or " + advice.removesuffix("; raise solver.max_iter")
    if status == codes.STATUS_NOT_CONVERGED and solver.method == "fixed_point":
        # simplified Newton gets through steps the fixed point cannot (docs/solver.md); 'auto' takes
        # the fixed point for large systems without the user having asked for it
        advice += ", or use simplified Newton (solver.method: newton)"
    if y is not None and y0 is not None:
        size, start = float(np.max(np.abs(y))), float(np.max(np.abs(y0)))
        if start > 0 and size > GROWN_STATE * start:
            # a user trial: a Henon-Heiles variant with an unbounded potential was told to reduce h
            # Not "likely": a system drifting as a whole grows too (the Toda ring of configs/toda.yaml, 100x
            # longer at h = 0.05, was told that its orbit was escaping)
            advice = (f"the state has grown to {size:.3g} ({size / start:.2g} times its initial size): if the orbit is "
                      f"escaping to infinity, or its momenta blowing up in a fall into a singularity of H, no step "
                      f"size gets through (a system drifting as a whole grows too, without either); otherwise {advice}")
    if status == codes.STATUS_NOT_CONVERGED and solver.max_halvings < MAX_MAX_HALVINGS and not adaptive and run_file:
        advice += "; a failed run can be continued with --resume after changing solver settings"
    if status == codes.STATUS_NONFINITE and problem is not None and y is not None:
        cause = gradient_not_finite(problem, y, t, h)
        if cause is not None:
            advice = cause
    return f"{method.name}: {what} {where}; {', '.join(seen)}" + (f"; {advice}" if advise else "")


def integrate(problem: Problem, method: Method, h: float | None = None, t_end: float | None = None,
              n_steps: int | None = None,
              conserve: Iterable[str] = (), tol: float | None = None, max_iter: int | None = None,
              store_every: int = 1, rhs: str = "stable", warm_start: bool = True, t0: float = 0.0,
              y0=None, backward: bool = False, chunk_steps: int = DEFAULT_CHUNK_STEPS,
              solver: str | SolverSettings = DEFAULT_SOLVER, predictor: bool = True,
              max_halvings: int = DEFAULT_MAX_HALVINGS, rtol: float | None = None, atol: float | None = None,
              step_control: str | None = None, epsilon: float | None = None, verify: bool | None = None,
              h_max: float | None = None, t_eval=None, events=None) -> Result:
    """Integrate ``problem`` with ``method``; return a Result.

    Fixed steps: give h. Adaptive steps (docs/adaptive.md): give rtol (error-controlled
    steps; atol defaults to rtol, h is then only the first step, chosen from the problem
    when absent; verify=True estimates by step doubling, verify=False by the cheap estimate,
    the default None by step doubling where the cheap estimate is not trusted: s > 5, unless
    ELIM imposes invariants), or step_control='time_scale'
    with epsilon (time-reversible steps for problems with a time scale; the controller takes
    every step, the first too, so h is not used). Result.h of an adaptive run is its first
    step (StepControl.first_step). Adaptive runs
    take t_end and land on it exactly. t_eval: times at which to sample the solution
    (side steps of the method itself: the integrator's accuracy, every invariant kept);
    events: {name: {"expression": "...", "direction": 1|-1|0, "terminal": bool}}, found
    to the integrator's accuracy (Result.events[name].t, .y). h_max bounds the steps.

    Give t_end (a whole number of steps after t0, to 1e-9 relative) or n_steps. y0: the
    initial state, 2m finite real numbers (q, then p; default: the problem's own).
    conserve: names of the problem's invariants to impose (ELIM/EHBVM: fewer than s;
    LIM/GHBVM: any number; must be empty for GAUSS/HBVM). store_every: keep every n-th
    state (the last one always). backward: integrate towards t0 - n_steps h (fixed steps only,
    without t_eval or events; configs run forward).

    How each step is solved (docs/solver.md): solver 'auto' (the default: simplified Newton
    up to 48 state components, the fixed point above), 'newton' (simplified Newton),
    'fixed_point' (the paper's iteration), or a SolverSettings; tol: the
    round-off acceptance on the relative increment (default machine epsilon, at most
    1e-8); max_iter: iterations per solve (default 100, 30 for Newton on ELIM imposing
    invariants; a step that needs more is split); predictor: start from the previous step's
    polynomial carried over; warm_start: start from the previous step at all (else from
    y_n); max_halvings: a step that fails is retried from the unextrapolated guess, then
    split into two half-steps, recursively to this depth (0: no splitting); rhs: 'stable'
    (docs/methods.md#stable-right-hand-side, default) or 'literal' (the paper's form).

    ``method`` may be written as the paper writes it, e.g. "EHBVM(12,3)" (methods.as_method).

    Raises ConvergenceError (with the partial Result as ``.result``) when a step fails at
    every depth, Gamma is singular, or the solution stops being finite. A problem function's
    own exception is re-raised as it is, with the steps before it as its ``.result``.
    """
    method = methods.as_method(method)
    # (a user trial: chunk_steps = 0 appended empty chunks until the machine's 24 GB were gone; -5 gave
    # NumPy's 'negative dimensions are not allowed')
    chunk_steps = _whole_number("chunk_steps", chunk_steps, 1, MAX_STEPS)
    adaptive = rtol is not None or atol is not None or step_control is not None or epsilon is not None
    if not adaptive and (verify is not None or h_max is not None):
        # as the config refuses integration.verify and h_max without rtol: they were silently ignored
        raise ParameterError("verify" if verify is not None else "h_max",
                             "applies to adaptive steps only; give rtol (or step_control='time_scale')")
    if adaptive or t_eval is not None or events:
        return _integrate_with_adaptive_kernel(
            problem, method, h=h, t_end=t_end, n_steps=n_steps, conserve=conserve, store_every=store_every, t0=t0,
            y0=y0, backward=backward, chunk_steps=chunk_steps,
            solver=_solver_settings(solver, tol, max_iter, max_halvings, predictor, warm_start, rhs),
            control=(_step_control(step_control, rtol, atol, epsilon, verify, h, h_max) if adaptive else None),
            t_eval=t_eval, events=events)
    if h is None:
        raise ParameterError("h", "is missing: give h (fixed steps), or rtol for adaptive steps (docs/adaptive.md)")
    if t_end is not None and backward:
        raise ParameterError("t_end", "does not go with backward=True: give n_steps (the run goes from t0 back by "
                                      "n_steps h)")
    h, n_steps = resolve_steps(h, t_end=t_end, n_steps=n_steps, t0=t0)
    run = Integration(problem, method, h, n_steps, conserve=conserve, tol=tol, max_iter=max_iter,
                      store_every=store_every, rhs=rhs, warm_start=warm_start, t0=t0, y0=y0, backward=backward,
                      solver=solver, predictor=predictor, max_halvings=max_halvings)
    chunks = [run.initial_chunk()]
    _run_to_end(run, chunks, chunk_steps, lambda: _collect(run, chunks))
    result = _collect(run, chunks)
    if run.status != codes.STATUS_OK:
        message = run.failure_message()
        result.status = "failed: " + message
        raise ConvergenceError(message, step=run.steps_done + 1, time=run.t, result=result,
                               reason=STATUS_NAMES[run.status])
    return result


def steps_before_raise(run) -> int:
    """How many steps the kernel call that raised had completed (its progress counter)."""
    progress = getattr(run, "_progress", None)
    try:
        return int(progress[0]) if progress is not None else 0
    except (TypeError, ValueError, IndexError):
        return 0


def _run_to_end(run, chunks: list, chunk_steps: int, partial_result) -> None:
    """Advance run (Integration or AdaptiveIntegration) to its end, appending its chunks.

    Where a problem function raises inside the kernel (a python: problem's own exception), the
    steps the call completed before it are taken again from the state before the call (a kernel
    call is deterministic, as resume relies on; its output died with the exception), and the
    exception, re-raised as it is (code that catches the problem's own exception type still
    does), carries them as ``.result`` (partial_result()), with ``.step`` and ``.time`` and a note
    saying so. (A user trial: integrate raised the bare ValueError, the steps lost.)"""
    while not run.finished:
        before_state = run.state()
        before, n_chunks = run.steps_done, len(chunks)
        try:
            chunks.append(run.advance(chunk_steps))
        except KeyboardInterrupt as stop:
            # Ctrl-C: the steps done so far are the interrupt's .result, as a failure's are the
            # ConvergenceError's (a user trial: they were lost). The interrupt may land between the
            # kernel's return and the append: the run then goes back to the state of its chunks.
            if len(chunks) == n_chunks and run.steps_done != before:
                run.restore(before_state)
            result = partial_result()
            result.status = f"interrupted at step {run.steps_done + 1} (t = {exact_time(run.t)})"
            stop.result = result
            stop.add_note(f"elimfast: interrupted; its .result holds the {run.steps_done} steps before it")
            raise
        except Exception as err:   # noqa: BLE001 -- a problem function raised inside the kernel
            n_done, t_raised = steps_before_raise(run), run.t
            run.restore(before_state)
            if n_done > 0:
                try:
                    chunks.append(run.advance(n_done))
                except Exception:   # noqa: BLE001 -- the steps before it raise too (an invariant on the last sample)
                    run.restore(before_state)
            step = before + n_done + 1
            text = " ".join(str(err).split()) or "(no message)"
            result = partial_result()
            message = (f"the problem raised {type(err).__name__}: {text[:200]} at step {step} "
                       f"(t = {exact_time(t_raised)}); its .result holds the {run.steps_done} steps before it")
            result.status = "failed: " + message
            try:
                err.result, err.step, err.time = result, step, t_raised
            except AttributeError:   # an exception type that takes no attributes: the note still says it
                pass
            err.add_note(f"elimfast: {message}")
            raise


def _collect(run: Integration, chunks: list[Chunk]) -> Result:
    p, m = run.problem, run.method
    inv = np.concatenate([c.invariants for c in chunks])
    mult = np.concatenate([c.multipliers for c in chunks])
    invariants = {"H": inv[:, 0].copy()}
    for i, name in enumerate(p.invariant_names):
        invariants[name] = inv[:, 1 + i].copy()
    return Result(
        problem=p, method=m, h=run.h, conserve=run.conserve,
        t=np.concatenate([c.t for c in chunks]), y=np.concatenate([c.y for c in chunks]),
        invariants=invariants,
        alpha=mult if m.kind.multiplier == "alpha" else None,    # Result's fields for the family's multipliers
        lam=mult if m.kind.multiplier == "lambda" else None,
        iterations=np.concatenate([c.iterations for c in chunks]),
        substeps=np.concatenate([c.substeps for c in chunks]),
        y_final=run.y.copy(), t_final=run.t, n_steps=run.n_steps, steps_done=run.steps_done,
        status="complete" if run.status == codes.STATUS_OK else STATUS_NAMES[run.status],
        solver=run.solver, y0=run.y0.copy(), t0=run.t0,
    )


def _solver_settings(solver, tol, max_iter, max_halvings, predictor, warm_start, rhs) -> SolverSettings:
    # integrate's own solver keywords that the caller set (their defaults are integrate's signature's)
    given = {name: value for name, value, unset in (
        ("tol", tol, tol is None), ("max_iter", max_iter, max_iter is None),
        ("max_halvings", max_halvings, max_halvings == DEFAULT_MAX_HALVINGS), ("predictor", predictor, predictor is True),
        ("warm_start", warm_start, warm_start is True), ("rhs", rhs, rhs == "stable")) if not unset}
    if isinstance(solver, SolverSettings):
        # A keyword beside settings that say otherwise was silently dropped (a user trial: rhs='literal'
        # with solver=SolverSettings(...) ran the stable form).
        for name, value in given.items():
            if getattr(solver, name) != value:
                raise ParameterError(name, f"is {value!r} but solver=SolverSettings(...) says {name}="
                                           f"{getattr(solver, name)!r}; set it in the settings "
                                           f"(dataclasses.replace(settings, {name}={value!r})), or drop one")
        return solver
    if isinstance(solver, Mapping):
        # a config's solver section as a dict (a user trial: TypeError: unhashable type: 'dict')
        known = SolverSettings.__dataclass_fields__
        unknown = [key for key in solver if key not in known]
        if unknown:
            raise ParameterError("solver", f"has no key {unknown[0]!r}; {suggest(unknown[0], known, 'keys')}")
        for name, value in given.items():
            if name in solver and solver[name] != value:
                raise ParameterError(name, f"is {value!r} but the solver dict says {name!r}: {solver[name]!r}; "
                                           "give it once")
        return SolverSettings(**{**given, **solver})
    try:
        return SolverSettings(method=solver, tol=DEFAULT_TOL if tol is None else tol, max_iter=max_iter,
                              max_halvings=max_halvings, predictor=predictor, warm_start=warm_start, rhs=rhs)
    except ParameterError as err:
        if err.parameter != "method":
            raise
        # integrate's keyword is solver=; its 'method' is the integrator (ehbvm(12, 3), ...)
        raise ParameterError("solver", err.detail) from None


def _step_control(step_control, rtol, atol, epsilon, verify, h, h_max):
    from .adaptive import StepControl
    if isinstance(step_control, StepControl):
        return step_control
    return StepControl(controller=step_control, rtol=rtol, atol=atol, epsilon=epsilon, verify=verify, h=h,
                       h_max=h_max)


def _integrate_with_adaptive_kernel(problem, method, h, t_end, n_steps, conserve, store_every, t0, y0, backward,
                                    chunk_steps, solver, control, t_eval, events) -> Result:
    """Adaptive steps, or fixed steps with output times or events (elimfast.adaptive)."""
    from .adaptive import AdaptiveIntegration, EventSpec, resolve_span, resolve_t_eval

    require_problem_object(problem)
    if not isinstance(method, Method):
        raise TypeError(f"method must be an elimfast Method, got {type(method).__name__}")
    if backward:
        raise ParameterError("backward", "runs take fixed steps without t_eval or events (or rtol, step_control); "
                                         "integrate forwards with t_end")
    y_start = resolve_initial_state(problem, y0)
    names, conserve_idx = resolve_conserve(problem, method, conserve, y_start)
    solver = solver.resolved_for(method, len(names), 2 * problem.degrees_of_freedom)
    store_every = resolve_store_every(store_every)
    if control is not None:
        control = control.for_method(method, len(names))
        t_end = resolve_span(t0, t_end, n_steps, control.h_max)
    else:
        h, n_steps = resolve_steps(h, t_end=t_end, n_steps=n_steps, t0=t0)
        t_end = t0 + n_steps * h
    if control is not None:
        control.check_problem(problem, y_start)
    if t_eval is not None:
        t_eval = resolve_t_eval(t_eval, float(t0), t_end, store_every)
    event_spec = EventSpec.build(problem, events, y_start) if events else None
    run = AdaptiveIntegration(problem, method, conserve_idx, names, solver, control, t_end=t_end, t0=t0,
                              y0=y_start, t_eval=t_eval, events=event_spec, store_every=store_every, h=h,
                              n_steps=n_steps)
    chunks = [run.initial_chunk()]
    _run_to_end(run, chunks, chunk_steps, lambda: run.result(chunks))
    result = run.result(chunks)
    if run.status != codes.STATUS_OK:
        message = run.failure_message()
        result.status = "failed: " + message
        raise ConvergenceError(message, step=run.steps_done + 1, time=run.t, result=result,
                               reason=STATUS_NAMES[run.status])
    return result
