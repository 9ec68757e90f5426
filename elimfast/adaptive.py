"""Runs with varying steps, output at requested times and events (docs/adaptive.md).

Data flow as for fixed steps: (problem, method, StepControl, ...) -> AdaptiveIntegration
-> kernels.adaptive.adaptive_loop -> AdaptiveChunk -> Result. The step control's rules
(which controller, tolerances, the first step) live in StepControl; the kernel only
applies them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Mapping

import numpy as np

from .errors import ParameterError, exact_time, real_number
from .function_addresses import remembered_addresses
from .kernels import codes
from .kernels.signatures import no_invariants
from .methods import Method
from .problems import Problem

CONTROLLERS = {"error": codes.CONTROL_ERROR, "time_scale": codes.CONTROL_TIME_SCALE}
DEFAULT_EPSILON = 0.05
MIN_EPSILON = 1e-6   # time-scale steps: below it, ~10^6 steps per time scale buy no accuracy
MAX_RTOL = 1e-2
MIN_RTOL = 1e-16
EVENT_DIRECTIONS = (-1, 0, 1)
EVENT_CHECK_SAMPLES = 64   # samples of each chunk at which the events are checked to be finite
# The cheap error estimate is trusted up to this s (docs/adaptive.md, "When the estimate is
# checked by step doubling"): above it, HBVM and LIM at loose rtol took steps where its
# leading term no longer dominates (Kepler e = 0.9, 10 periods, rtol 1e-6: HBVM(12,6) ended
# 0.37 from the exact state, GHBVM(12,6) 4.4; with step doubling 2e-5 and 1.8e-4).
CHEAP_ESTIMATE_MAX_S = 5


def state_function_values(function, problem: Problem, y, size: int) -> np.ndarray:
    """out (size,) of a compiled function of the state (the INVARIANTS signature: a time scale,
    events) at y; NaN where it raises an ArithmeticError."""
    y = np.array(y, dtype=np.float64)   # writable, C-contiguous
    out = np.full(size, np.nan)
    with np.errstate(all="ignore"):
        try:
            function(y, problem.params, out)
        except ArithmeticError:
            pass
    return out


def time_scale_at(problem: Problem, y) -> float:
    """sigma(y) of a problem's time scale (docs/adaptive.md); NaN where it raises an ArithmeticError."""
    return float(state_function_values(problem.time_scale, problem, y, np.size(y) + 1)[0])   # sigma, its gradient


# A time scale below this fraction of its value at t0 where a time-reversible run fails: the orbit
# is falling into what sigma measures the distance to (failure_message says so).
COLLAPSED_TIME_SCALE = 0.05
SMALLER_TIME_SCALE = 0.5   # a failure on time-reversible steps gives sigma's figures below this times sigma(y0)


def require_defined_at_start(parameter: str, value: float, y, why: str, positive: bool = False) -> None:
    """The rule for a function of the state that steers or watches a run (a time scale, an
    event): finite at the initial state y, and positive if ``positive``; else a ParameterError
    naming ``parameter``, the value there and y, and ``why`` it must be so. It is checked
    before the run: a time scale that is not positive ran backwards from t0 without end; an
    event that is NaN at y0 (sqrt(q1 - 10) where q1 < 10) never changes sign, and a run found
    none of it and said nothing (a user trial)."""
    if math.isfinite(value) and (value > 0.0 or not positive):
        return
    must = "positive and finite" if positive else "finite"
    raise ParameterError(parameter, f"is {value!r} at the initial state {np.asarray(y).tolist()}; it must be {must} "
                                    f"along the orbit {why}")


_EPSILON_WITH_ERROR_CONTROL = "belongs to step_control = 'time_scale'; the error controller takes rtol (and atol)"


# The failure of steps that collapsed says so; --resume, which reads it from the file, then advises no
# other solver settings (streaming.py; a user trial followed that advice and failed the same way).
NO_SETTING_GETS_THROUGH = "no tolerance or solver setting gets through"


@dataclass(frozen=True)
class StepControl:
    """How the step size is chosen (docs/adaptive.md).

    controller 'error' (the default, also for None: then an epsilon without rtol or atol asks
    for 'time_scale', which it belongs to): local error estimate with tolerances rtol (and atol,
    default rtol) and Gustafsson's controller; verify: estimate by step doubling instead
    (exact to 0.2%, three steps' work); None (the default) lets ``for_method`` choose it
    where the cheap estimate is not trusted; h: the first step (None: chosen from the problem).
    controller 'time_scale': Hairer & Soderlind's time-reversible steps h ~ epsilon
    sigma(y), for problems that define a time scale sigma; every step, the first too, is the
    controller's, so h is not used (``first_step`` gives the one it takes). h_max: the
    largest step.
    """

    controller: str | None = None
    rtol: float | None = None
    atol: float | None = None
    epsilon: float | None = None
    verify: bool | None = None
    h: float | None = None
    h_max: float | None = None

    def __post_init__(self):
        given = self.controller is not None
        if not given:
            object.__setattr__(self, "controller", "error")
        if self.controller not in CONTROLLERS:
            raise ParameterError("step_control", f"must be one of {', '.join(CONTROLLERS)} (the error estimate, the "
                                                 f"default, or time-reversible steps from the problem's time scale), "
                                                 f"got {self.controller!r}")
        if self.controller == "error":
            # Without rtol, name what was given (a user trial was told only that rtol was needed):
            # an epsilon meant the time-reversible steps, an atol lacks the rtol beside it.
            if self.rtol is None:
                if self.atol is not None:
                    raise ParameterError("atol", "is given without rtol, which error-controlled steps need: add "
                                                 "rtol, e.g. rtol = 1e-10")
                if self.epsilon is not None and not given:
                    raise ParameterError("epsilon", "applies to time-reversible steps: add step_control = "
                                                    "'time_scale', or give rtol instead for error-controlled steps")
                if self.epsilon is None and given:
                    # named at the key given (a --set integration.step_control=error on a fixed-step
                    # config was told only 'integration.rtol: is needed', at the file's line)
                    raise ParameterError("step_control", "asks for error-controlled steps, which need rtol: add "
                                                         "rtol, e.g. rtol = 1e-10")
                if self.epsilon is None:
                    raise ParameterError("rtol", "is needed for error-controlled steps, e.g. rtol = 1e-10")
                raise ParameterError("epsilon", _EPSILON_WITH_ERROR_CONTROL)
            rtol = _positive("rtol", self.rtol)
            if not MIN_RTOL <= rtol <= MAX_RTOL:
                raise ParameterError("rtol", f"must be between {MIN_RTOL:g} and {MAX_RTOL:g}, got {rtol:g}")
            object.__setattr__(self, "rtol", rtol)
            if self.atol is not None and self.atol == 0:
                raise ParameterError("atol", "must be positive: with atol = 0 a component that is zero at both ends "
                                             "of a step has no scale; leave it out (atol = rtol) or give a small "
                                             "positive value")
            object.__setattr__(self, "atol", rtol if self.atol is None else _positive("atol", self.atol))
            if self.epsilon is not None:
                raise ParameterError("epsilon", _EPSILON_WITH_ERROR_CONTROL)
        else:
            if self.rtol is not None or self.atol is not None:
                name = "rtol" if self.rtol is not None else "atol"
                raise ParameterError(name, f"belongs to step_control = 'error'; time-scale steps take epsilon: "
                                           f"leave {name} out (on the command line: --set integration.{name}=null)")
            if self.verify:
                raise ParameterError("verify", "belongs to step_control = 'error' (step doubling checks its "
                                               "estimate)")
            epsilon = DEFAULT_EPSILON if self.epsilon is None else _positive("epsilon", self.epsilon)
            if epsilon > 1.0:
                raise ParameterError("epsilon", f"must be at most 1 (a fraction of the local time scale per step), "
                                                f"got {epsilon:g}; 0.05 is a good start")
            if epsilon < MIN_EPSILON:
                # (a user trial: epsilon = 1e-9 ran 400 steps and failed, ELIM's Gamma too short for such steps;
                # an error 1e-24 per step needs epsilon ~1e-3 at order 8)
                raise ParameterError("epsilon", f"must be at least {MIN_EPSILON:g}: a run takes about 1/epsilon steps "
                                                f"per time scale, and no accuracy needs more than 1/{MIN_EPSILON:g} of "
                                                f"them; got {epsilon:g}; 0.05 is a good start")
            object.__setattr__(self, "epsilon", epsilon)
        for name in ("h", "h_max"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _positive(name, getattr(self, name)))
        if self.verify is not None:
            if not isinstance(self.verify, (bool, np.bool_)):
                raise ParameterError("verify", f"must be true or false, got {self.verify!r}")
            object.__setattr__(self, "verify", bool(self.verify))

    @property
    def code(self) -> int:
        return CONTROLLERS[self.controller]

    def as_dict(self) -> dict:
        return {"controller": self.controller, "rtol": self.rtol, "atol": self.atol, "epsilon": self.epsilon,
                "verify": self.verify, "h": self.h, "h_max": self.h_max}

    def for_method(self, method: Method, n_imposed: int) -> "StepControl":
        """This control for a method imposing n_imposed invariants: verify decided when it was
        left to elimfast (None) and the method checked.

        verify None means step doubling where the cheap estimate is not trusted: s above
        CHEAP_ESTIMATE_MAX_S, except ELIM imposing invariants, whose steps the solver keeps
        small (its errors stayed within 10x of step doubling's) and for which step doubling
        failed at s >= 7 (docs/adaptive.md). The cheap estimate needs gamma_s, which k = s
        nodes cannot give (P_s vanishes there).
        """
        if self.controller != "error":
            return replace(self, verify=False)
        verify = self.verify
        if verify is None:
            elim_imposing = method.kernel_family == codes.FAMILY_ELIM and n_imposed > 0
            verify = method.s > CHEAP_ESTIMATE_MAX_S and not elim_imposing
        if not verify and method.k <= method.s:
            raise ParameterError("method", f"{method.name} has k = s = {method.s}: the error estimate needs k > s "
                                           f"(use HBVM(2s,s), the default for adaptive runs: "
                                           f"{'hbvm' if method.family in ('gauss', 'hbvm') else method.family}"
                                           f"(k={2 * method.s}, s={method.s})), or verify = true (step doubling)")
        return replace(self, verify=verify)

    def first_step(self, problem: Problem, method: Method, y0, span: float) -> float:
        """The first step the kernel tries from y0 on a run of length span = t_end - t0 (a run
        file's h_first, Result.h): error control's h, else initial_step's guess (the controller
        may reject it and take a smaller one); time-scale steps' epsilon / rho_1/2, rho_1/2 =
        1/sigma(y0) + epsilon G(y0)/2 (h is not used). Then, as kernels/adaptive.py takes it:
        at most h_max, and the whole span when it would leave less than 1% of itself."""
        y = np.array(y0, dtype=np.float64)   # writable, C-contiguous
        if self.controller == "time_scale":
            # kernels/adaptive.py _time_scale_rate and its rho_1/2, operation for operation, so that
            # h_first is bit for bit the kernel's first step
            n, m = y.size, y.size // 2
            out, grad = np.zeros(n + 1), np.zeros(n)
            with np.errstate(all="ignore"):
                problem.time_scale(y, problem.params, out)
                problem.grad_H(y, problem.params, grad)
                acc = 0.0
                for p in range(m):
                    acc += float(out[1 + p]) * float(grad[m + p]) - float(out[1 + m + p]) * float(grad[p])
                sigma = float(out[0])
                h = self.epsilon / (1.0 / sigma + 0.5 * self.epsilon * (-acc / sigma))
        else:
            h = self.h if self.h is not None else initial_step(problem, method, y, self.rtol, self.atol)
        if self.h_max is not None:
            h = min(h, self.h_max)
        if h >= span or span - h < 0.01 * h:   # the kernel's "no sliver of a step at the end"
            h = span
        return float(h)

    def check_problem(self, problem: Problem, y0=None) -> None:
        """Refuse a problem this control cannot step: no time scale, or one that is not positive
        and finite at the initial state y0 (problem.y0 by default). The kernel steps by epsilon
        sigma(y): a negative sigma ran backwards from t0 forever, a zero one failed at the
        first step with a message about Gamma."""
        if self.controller == "time_scale" and problem.time_scale is not None:
            y = np.array(problem.y0 if y0 is None else y0, dtype=np.float64)   # writable, C-contiguous
            require_defined_at_start("time_scale", time_scale_at(problem, y), y, positive=True,
                                     why="(the steps are epsilon times it), e.g. a positive power of a distance")
        if self.controller == "time_scale" and problem.time_scale is None:
            from .problems import PROBLEMS
            if problem.name in PROBLEMS and problem.hessian_source == "analytic":
                # a built-in takes no time_scale key: only kepler, perturbed_kepler and nbody define one
                raise ParameterError("step_control", f"'time_scale' needs a time scale, which the built-in problem "
                                                     f"{problem.name!r} does not define: "
                                                     "use step_control = 'error' with rtol, or give it one: "
                                                     "time_scale: \"<expression>\" in the config's problem "
                                                     "(in Python: problem.with_time_scale(\"<expression>\"))")
            raise ParameterError("step_control", f"'time_scale' needs a time scale, which problem {problem.name!r} "
                                                 "does not define: declare "
                                                 "time_scale: \"<expression>\" in the problem (in Python: "
                                                 "problem.with_time_scale(\"<expression>\")), or use "
                                                 "step_control = 'error' with rtol")


MAX_OUTPUT_TIMES = 10_000_000   # samples at requested times (t_eval, output.times)


def resolve_span(t0: float, t_end, n_steps=None, h_max=None) -> float:
    """An adaptive run's t_end: given, finite and after t0 (n_steps does not apply), and no more
    than MAX_STEPS steps of h_max, when given, after it."""
    from .integrate import MAX_STEPS, STEPS_COST, compact_number, resolve_t0
    t0 = resolve_t0(t0)
    if n_steps is not None:   # named itself: a user trial was told 't_end is needed' beside its t_end
        raise ParameterError("n_steps", "does not apply to adaptive steps: the controller decides how many it "
                                        "takes; remove it and give t_end")
    if t_end is None:
        raise ParameterError("t_end", "is needed for adaptive steps (n_steps does not apply: the number of "
                                      "steps is what the controller decides)")
    t_end = float(t_end)
    if not (math.isfinite(t_end) and t_end > t0):
        raise ParameterError("t_end", f"must be a finite time after t0 = {t0:g}, got {t_end!r}", related=("t0",))
    if h_max is not None and not (t_end - t0) / h_max <= MAX_STEPS:
        # a fixed h was bounded so, h_max not (a user trial: h_max = 1e-9 over t = 100 wrote 217 MB in 20 s,
        # on its way to 2 TB)
        raise ParameterError("h_max", f"gives (t_end - t0)/h_max = {(t_end - t0) / h_max:.3g} steps at least, more "
                                      f"than {compact_number(MAX_STEPS)}: {STEPS_COST}; raise h_max or shorten the run",
                             related=("t_end", "t0"))
    return t_end


def resolve_t_eval(times, t0: float, t_end: float, store_every: int = 1) -> np.ndarray:
    """Requested output times: 1 to MAX_OUTPUT_TIMES finite, strictly increasing times in [t0, t_end].
    They are the samples, so a store_every other than 1 (output.every) is refused: it was ignored."""
    if store_every != 1:
        raise ParameterError("store_every", f"does not apply with output times (t_eval, output.times), which "
                                            f"are the samples; remove one of the two, or make it 1 (got {store_every})",
                             related=("t_eval",))   # a --set of output.times that made it so is named
    values = np.asarray(times, dtype=np.float64)
    if values.ndim > 1:
        raise ParameterError("t_eval", f"must be a list of times (1-d), got an array of shape {values.shape}")
    values = values.ravel()
    if values.size == 0 or values.size > MAX_OUTPUT_TIMES:
        raise ParameterError("t_eval", f"must list 1 to {MAX_OUTPUT_TIMES} times")
    if not np.all(np.isfinite(values)) or np.any(np.diff(values) <= 0):
        raise ParameterError("t_eval", "must be finite and strictly increasing")
    # t_end's own rounding (t0 + n h) may put the last requested time an ulp past it; the margin is
    # relative to |t_end| (t_end * (1 + 1e-15) fell below t_end for t_end < 0 and refused t_end itself)
    if values[0] < t0 or values[-1] > t_end + 1e-15 * abs(t_end) + 1e-300:
        raise ParameterError("t_eval", f"must lie within the run, [{exact_time(t0)}, {exact_time(t_end)}], "
                                       f"got [{exact_time(values[0])}, {exact_time(values[-1])}]")
    return values


def _positive(name: str, value) -> float:
    number = real_number(name, value)
    if not (math.isfinite(number) and number > 0.0):
        raise ParameterError(name, f"must be a positive finite number, got {value!r}")
    return number


def _check_event_name(name: str, problem: Problem) -> None:
    """ParameterError for an event name that readers of the run would see clash with other data."""
    from .io.layout import INHERITED_COORDINATES   # (here, not at the top: h5py only when events are given)
    # The file's group /events/<name> sits below the run's coordinates t and component, which
    # xarray's DataTree passes down to it: an event 't' made every DataTree reader of the file fail.
    if name in INHERITED_COORDINATES:
        raise ParameterError(f"events.{name}", f"'{name}' is a coordinate of the run's file, which xarray passes "
                                               "down to the group of each event; give the event another name")
    # Result.to_xarray names an event's times and states <name>_t and <name>_y, on the dimension
    # <name>_occurrence, beside the step times step_t, step_h and the invariants: an event 'step'
    # replaced step_t, and an invariant x_occurrence became a stray coordinate for an event x
    taken = {f"{name}_t", f"{name}_y", f"{name}_occurrence"} & {"step_t", *problem.invariant_names}
    if taken:
        raise ParameterError(f"events.{name}", f"its times or states would be {min(taken)}, the name of "
                                               "other data of the run in xarray; give the event another name")


@dataclass(frozen=True)
class EventSpec:
    """Events g(y) = 0 of a run: names, expressions, directions (+1 up, -1 down, 0 both),
    terminal flags; ``function`` is their compiled g (problems.symbolic)."""

    names: tuple[str, ...]
    expressions: tuple[str, ...]
    directions: np.ndarray
    terminal: np.ndarray
    function: object = field(repr=False, default=None)

    @classmethod
    def build(cls, problem: Problem, events: Mapping | None, y0=None) -> "EventSpec":
        """The events compiled for the problem, each checked to be finite at the initial state
        y0 (problem.y0 by default; require_defined_at_start, the time scale's rule)."""
        from .problems.symbolic import compile_state_functions

        if events is not None and not isinstance(events, Mapping):
            # dict() of a list of strings reads each string's characters as (key, value) pairs: events=["q1"]
            # became an event 'q' of expression '1' that never fired (a user trial)
            raise ParameterError("events", "must be a mapping of event names to expressions, e.g. "
                                           "{'pericentre': 'q1*p1 + q2*p2'} or {'pericentre': {'expression': "
                                           f"'q1*p1 + q2*p2', 'direction': 1}}}}, got {type(events).__name__}")
        events = dict(events or {})
        names, expressions, directions, terminal = [], [], [], []
        for name, entry in events.items():
            if not isinstance(name, str) or not name.isidentifier():
                raise ParameterError("events", f"event names must be identifiers, got {name!r}")
            _check_event_name(name, problem)
            if isinstance(entry, str):
                entry = {"expression": entry}
            if not isinstance(entry, Mapping) or "expression" not in entry:
                raise ParameterError(f"events.{name}", "must be a mapping with an 'expression' (and optional "
                                                       "'direction': 1, -1 or 0, and 'terminal': true/false)")
            unknown = set(entry) - {"expression", "direction", "terminal"}
            if unknown:
                raise ParameterError(f"events.{name}", f"unknown key(s) {', '.join(sorted(map(str, unknown)))}; "
                                                       "allowed: expression, direction, terminal")
            direction = entry.get("direction", 0)
            if isinstance(direction, bool) or direction not in EVENT_DIRECTIONS:
                raise ParameterError(f"events.{name}.direction", f"must be 1 (g increasing through 0), -1 "
                                                                 f"(decreasing) or 0 (both), got {direction!r}")
            term = entry.get("terminal", False)
            if not isinstance(term, (bool, np.bool_)):
                raise ParameterError(f"events.{name}.terminal", f"must be true or false, got {term!r}")
            names.append(name)
            expressions.append(entry["expression"])
            directions.append(int(direction))
            terminal.append(int(bool(term)))
        function = (compile_state_functions(problem, dict(zip(names, expressions)), what="event",
                                            key_prefix="events") if names else no_invariants)
        if names:
            y = problem.y0 if y0 is None else y0
            for name, value in zip(names, state_function_values(function, problem, y, len(names))):
                require_defined_at_start(f"events.{name}", float(value), y,
                                         why="(an event is where it changes sign, which a NaN or an infinity "
                                             "never shows): write it so that it is defined wherever the orbit "
                                             "goes, e.g. no sqrt or log of a negative number")
        return cls(tuple(names), tuple(expressions), np.array(directions, dtype=np.int64),
                   np.array(terminal, dtype=np.int64), function)

    def definitions(self) -> dict:
        """{name: {"expression", "direction", "terminal"}}, as a config's events section."""
        return {name: {"expression": expression, "direction": int(direction), "terminal": bool(terminal)}
                for name, expression, direction, terminal in zip(self.names, self.expressions, self.directions,
                                                                 self.terminal)}


@dataclass
class EventRecord:
    """The occurrences of one event: times t (n,) and states y (n, 2m), and the event as it
    was given (EventSpec.definitions: expression, direction, terminal), which Result.to_xarray
    carries as a run file's /events/<name> does."""

    t: np.ndarray
    y: np.ndarray
    expression: str = ""
    direction: int = 0
    terminal: bool = False

    def __repr__(self) -> str:
        return f"<EventRecord {self.t.size} occurrence(s)>"


@dataclass
class AdaptiveChunk:
    """What one adaptive kernel call produced."""

    t: np.ndarray
    y: np.ndarray
    invariants: np.ndarray
    step_t: np.ndarray
    step_h: np.ndarray
    multipliers: np.ndarray
    iterations: np.ndarray
    substeps: np.ndarray
    event_index: np.ndarray
    event_t: np.ndarray
    event_y: np.ndarray
    first_step: int
    status: int


# Steps that collapsed (below 4 eps of t_end) while still this fraction of the run's first step or more:
# the run is too long for steps the solution needs, not nearing a singularity (failure_message).
FAR_END_STEP = 1e-3


def initial_step(problem: Problem, method: Method, y0: np.ndarray, rtol: float, atol: float) -> float:
    """A first step from the problem (Hairer, Norsett & Wanner, Solving ODEs I, II.4): the
    controller corrects it within a few steps.

    A component that starts at zero (Kepler's q2 and p1) is weighed at least by 1e-3 of the
    state's size: with a tiny atol its weight alone made the guess 1e-9 (atol 1e-20), a step
    at which ELIM's Gamma underflows; the kernel's norm, which takes max(|y0|, |y1|), needs
    no such floor after the first step."""
    weights = np.maximum(atol + rtol * np.abs(y0), 1e-3 * rtol * np.max(np.abs(y0)))
    m = problem.degrees_of_freedom

    def f(y):
        g = problem.gradient(y)
        return np.concatenate((g[m:], -g[:m]))

    f0 = f(y0)
    d0 = np.max(np.abs(y0) / weights)
    d1 = np.max(np.abs(f0) / weights)
    h0 = 1e-6 if d0 < 1e-5 or d1 < 1e-5 else 0.01 * d0 / d1
    f1 = f(y0 + h0 * f0)
    d2 = np.max(np.abs(f1 - f0) / weights) / h0
    order = 2 * method.s
    h1 = max(1e-6, h0 * 1e-3) if max(d1, d2) <= 1e-15 else (0.01 / max(d1, d2)) ** (1.0 / (order + 1))
    return float(min(100.0 * h0, h1))


def counted_stats(counters) -> dict:
    """The stats (AdaptiveIntegration.stats) that the kernel's counters give by themselves, without
    the method: all but the gradient evaluations. Also what inspect reads from a run file's state
    (a file written before the last counters were added has fewer: they count 0)."""
    c = np.zeros(codes.N_COUNTERS, dtype=np.int64)
    given = np.asarray(counters, dtype=np.int64)[:codes.N_COUNTERS]
    c[:given.size] = given
    return {
        "steps": int(c[codes.CNT_STEPS]), "rejected_steps": int(c[codes.CNT_REJECTED]),
        "failed_solves": int(c[codes.CNT_FAILED]), "split_steps": int(c[codes.CNT_SPLIT]),
        "side_steps": int(c[codes.CNT_SIDE_STEPS]),
        "iterations": int(c[codes.CNT_ITERATIONS] + c[codes.CNT_SIDE_ITERATIONS]),
        "hessian_evaluations": int(c[codes.CNT_FACTORISATIONS] + c[codes.CNT_ESTIMATE_HESSIANS]),
        "events": int(c[codes.CNT_EVENTS]), "polynomial_samples": int(c[codes.CNT_SIDE_FALLBACKS]),
        "energy_projections": int(c[codes.CNT_ENERGY_PROJECTIONS]),
    }


class AdaptiveIntegration:
    """A run with the adaptive kernel: varying steps, or fixed steps with output times or
    events. Mirrors integrate.Integration: ``advance``, ``state``/``restore`` (the
    controller's state and counters included, so a resumed run is bit for bit the
    uninterrupted one), ``initial_chunk``, ``failure_message``; the run file writer and
    the streaming loop drive both alike."""

    adaptive_kernel = True

    def __init__(self, problem: Problem, method: Method, conserve_idx, conserve, solver, control: StepControl | None,
                 t_end: float, t0: float, y0, t_eval=None, events: EventSpec | None = None,
                 store_every: int = 1, h: float | None = None, n_steps: int | None = None):
        self.problem, self.method, self.solver = problem, method, solver
        from .per_problem import refuse
        refuse(solver, "adaptive steps, output times and events")
        from .integrate import require_memory
        require_memory(problem, method, solver, adaptive=True)   # this kernel's arrays, whatever the steps
        self.conserve, self.conserve_idx = conserve, conserve_idx
        if control is not None:
            control = control.for_method(method, len(conserve))   # idempotent; resolves verify = None
        self.control = control
        self.t0, self.t_end = float(t0), float(t_end)
        self.events = events or EventSpec((), (), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
                                          no_invariants)
        self.events_not_finite: dict[str, float] = {}   # check_events_finite
        self.store_every = store_every
        n = 2 * problem.degrees_of_freedom
        self.y = np.array(y0, dtype=np.float64)
        self.y0 = self.y.copy()   # the state at t0, the reference of the invariant errors (Result.y0)
        self.y_comp = np.zeros(n)
        self.clock = np.array([self.t0, 0.0])
        self.coef = np.zeros((method.s, n))
        from .integrate import predictor_extra_state
        self.coef_extra = predictor_extra_state(method, n)
        nu = len(conserve)
        self.multipliers = np.zeros(nu + 1 if method.kernel_family == codes.FAMILY_LIM else nu)
        self.newton_base = np.zeros(n + 3)
        self.control_state = np.zeros(codes.N_CONTROL_STATE)
        self.counters = np.zeros(codes.N_COUNTERS, dtype=np.int64)
        self.t_eval = np.zeros(0) if t_eval is None else np.ascontiguousarray(t_eval, dtype=np.float64)
        if control is None:   # fixed steps (with output times or events)
            self.n_steps = int(n_steps)
            self.h = float(h)
            self.controls = np.array([0.0, 0.0, 0.0, self.t0 + self.n_steps * self.h, np.inf, math.nan])
            self.options = np.array([codes.CONTROL_FIXED, 0, store_every, self.n_steps], dtype=np.int64)
        else:
            self.n_steps = None
            self.h = control.first_step(problem, method, self.y, self.t_end - self.t0)
            self.controls = np.array([control.rtol or 0.0, control.atol or 0.0, control.epsilon or 0.0, self.t_end,
                                      np.inf if control.h_max is None else control.h_max, math.nan])
            self.options = np.array([control.code, int(control.verify), store_every, 0], dtype=np.int64)
        self.controls[codes.CTL_H_TARGET] = solver.energy_target(problem, method, self.y0)
        self.last_h = np.array([self.h if self.h > 0 else 1.0])
        self.status = codes.STATUS_OK
        self.finished_flag = False
        self.diagnostics = np.zeros(codes.N_DIAGNOSTICS)
        self._adaptive_loop = None   # loaded at first use (prepare_kernel)
        self._progress = np.zeros(codes.N_PROGRESS, dtype=np.int64)
        self.event_counts = np.zeros(self.events.directions.size, dtype=np.int64)

    @classmethod
    def from_spec(cls, spec) -> "AdaptiveIntegration":
        """The run a validated config describes (config.RunSpec with step control, output
        times or events)."""
        from .integrate import resolve_conserve
        names, idx = resolve_conserve(spec.problem, spec.method, spec.conserve, spec.problem.y0)
        events = EventSpec.build(spec.problem, spec.events) if spec.events else None
        return cls(spec.problem, spec.method, idx, names, spec.solver, spec.step_control, t_end=spec.t_end,
                   t0=spec.t0, y0=spec.problem.y0, t_eval=spec.t_eval, events=events,
                   store_every=spec.output_every, h=spec.h, n_steps=spec.n_steps)

    @property
    def event_names(self) -> tuple[str, ...]:
        return self.events.names

    def file_attributes(self) -> dict:
        """Root attributes of its run file: how the steps are chosen."""
        control = self.control
        values = {"step_control": control.controller if control is not None else "fixed"}
        if control is not None:
            # h: the first step (run_attributes), not a time-scale run's unused h
            values.update({key: value for key, value in control.as_dict().items()
                           if value is not None and key not in ("controller", "h")})
            values["h_first"] = float(self.h)
        if self.t_eval.size:
            values["output_times"] = int(self.t_eval.size)
        return values

    @property
    def complete(self) -> bool:
        return self.finished_flag and self.status == codes.STATUS_OK

    @property
    def remaining_steps(self) -> int | None:
        """Steps left: known for fixed steps, None for adaptive ones."""
        return None if self.n_steps is None else self.n_steps - self.steps_done

    def initial_chunk(self) -> AdaptiveChunk:
        t, y, inv = self.initial_samples()
        n_mult = self.multipliers.size
        return AdaptiveChunk(t, y, inv, np.zeros(0), np.zeros(0), np.zeros((0, n_mult)), np.zeros(0, dtype=np.int64),
                             np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0),
                             np.zeros((0, self.y.size)), self.steps_done, codes.STATUS_OK)

    def result(self, chunks: list[AdaptiveChunk]):
        """The Result of this run from its chunks (the initial one first), as integrate returns it."""
        from .integrate import STATUS_NAMES, Result

        problem, method = self.problem, self.method
        inv = np.concatenate([c.invariants for c in chunks])
        invariants = {"H": inv[:, 0].copy()}
        for i, name in enumerate(problem.invariant_names):
            invariants[name] = inv[:, 1 + i].copy()
        is_lim = method.kernel_family == codes.FAMILY_LIM
        mult = np.concatenate([c.multipliers for c in chunks])
        index = np.concatenate([c.event_index for c in chunks])
        times = np.concatenate([c.event_t for c in chunks])
        states = np.concatenate([c.event_y for c in chunks])
        given = self.events.definitions()
        found = {name: EventRecord(times[index == i], states[index == i], **given[name])
                 for i, name in enumerate(self.event_names)}
        return Result(
            problem=problem, method=method, h=float(self.h), conserve=self.conserve,
            t=np.concatenate([c.t for c in chunks]), y=np.concatenate([c.y for c in chunks]), invariants=invariants,
            alpha=mult if (method.imposes_invariants and not is_lim) else None, lam=mult if is_lim else None,
            iterations=np.concatenate([c.iterations for c in chunks]),
            substeps=np.concatenate([c.substeps for c in chunks]),
            y_final=self.y.copy(), t_final=self.t, n_steps=self.steps_done if self.n_steps is None else self.n_steps,
            steps_done=self.steps_done,
            status="complete" if self.status == codes.STATUS_OK else STATUS_NAMES[self.status],
            solver=self.solver, step_t=np.concatenate([c.step_t for c in chunks]),
            step_h=np.concatenate([c.step_h for c in chunks]), step_control=self.control, stats=self.stats(),
            events=found, y0=self.y0.copy(), t0=self.t0, events_not_finite=dict(self.events_not_finite))

    def collapsed_steps(self) -> bool:
        """Whether the run failed because the error controller's steps collapsed (the kernel's check
        with COLLAPSED_STEP: a failure with no iterations, at a step below 4 eps max(|t|, |t_end|))."""
        d = self.diagnostics
        return (self.control is not None and self.control.controller != "time_scale"
                and self.status == codes.STATUS_NOT_CONVERGED and d[codes.DIAG_ITERATIONS] == 0
                and not abs(d[codes.DIAG_STEP]) > codes.COLLAPSED_STEP * max(abs(self.t), abs(self.t_end)))

    def failure_message(self, run_file: bool = False) -> str:
        from .integrate import failure_message, gradients_independence, max_iter_below_defaults, raise_max_iter
        d = self.diagnostics
        if self.collapsed_steps():
            collapse = (f"{self.method.name}: the steps collapsed at step {self.steps_done + 1} (t = "
                        f"{exact_time(self.t)}): the error controller came down to h = {d[codes.DIAG_STEP]:.3g}, "
                        f"below 4 eps of t_end = {self.t_end:.6g}: at that size t_end is more than 10^15 steps away; ")
            if max_iter_below_defaults(self.solver):
                # A user trial: max_iter = 2 made every solve fail, and the steps collapsed; the message
                # blamed a singularity of H, 'which no solver setting gets through'.
                return collapse + (f"no step converged within solver.max_iter = {self.solver.max_iter} iterations, "
                                   f"below every default: {raise_max_iter(self.solver)}")
            if abs(d[codes.DIAG_STEP]) >= FAR_END_STEP * abs(self.h):
                # Steps the size of the run's first, measured against a far t_end: t_end is out of reach, the
                # solution is not singular (a user trial: Lennard-Jones scattering with t_end = 1e14, and
                # Kepler e = 0.9 with t_end = 1e15, were told of a singularity at step 1). Falling into a
                # singularity, the steps shrink by orders of magnitude first (1e-113 in a user trial).
                return collapse + (f"steps of this size suit the solution here, but t_end - t0 = "
                                   f"{self.t_end - self.t0:.3g} is too far for them: shorten the run (integration."
                                   f"t_end; one run should take at most ~10^10 steps), or loosen rtol")
            return collapse + ("the solution is likely nearing a singularity of H (a collision, or a fall into a "
                               f"centre), which {NO_SETTING_GETS_THROUGH}; check the initial state and the "
                               "problem's parameters")
        # the failed step's h: DIAG_STEP is its failed substep's, 2^depth times smaller (a user trial read
        # "t = 12.5663689 -> 12.5663691, in its substep from t = 12.5663705": h/16 for the step)
        step = float(d[codes.DIAG_STEP]) * 2.0 ** int(d[codes.DIAG_DEPTH])
        if self.control is None:
            # fixed steps (with output times or events): the step is h, DIAG_STEP its failed substep's
            # (a user trial read "t = 6.45 -> 6.453125, in its substep from t = 6.471875")
            step = math.copysign(self.h, step) if step else self.h
        notes = ""
        collapsed = False
        if self.control is not None and self.control.controller == "time_scale" \
                and self.status != codes.STATUS_TIME_SCALE:
            # The steps are epsilon sigma(y): a sigma that nears zero along the orbit makes them collapse
            # until some solve fails, with a message about the solver or Gamma (a time scale q1 on an orbit
            # crossing q1 = 0 failed at h = 2.6e-10 with "Assumption 1 fails"). The figures show it.
            # Only where sigma has shrunk: with sigma as at t0 the figures are noise beside the message (a
            # user trial: Kepler e = 0.999, Gamma singular at a pericentre, sigma 3.17e-5 against 3.16e-5).
            here, start = time_scale_at(self.problem, self.y), time_scale_at(self.problem, self.y0)
            if not here >= SMALLER_TIME_SCALE * start:
                notes += (f" (time scale sigma(y) = {here:.3g} there, {start:.3g} at t0: steps are epsilon sigma; "
                          "a sigma that nears zero along the orbit makes them collapse)")
            collapsed = here < COLLAPSED_TIME_SCALE * start
            if collapsed:
                # A user trial: perturbed Kepler e = 0.9, delta = 0.01 falls into the centre (its -delta/r^3
                # wins at r = 0.1); the run failed at t = 0.037 and was told to raise solver.max_iter, which a
                # later trial found still said beside this note: the solver's advice is left out here.
                notes += (f"; sigma has fallen to {here / start:.2g} of its value at t0: the orbit is nearing "
                          f"where sigma vanishes (a collision or a fall into a singularity of H), which "
                          f"{NO_SETTING_GETS_THROUGH}; check the initial state and the problem's parameters")
        return failure_message(self.method, self.solver, self.status, self.steps_done + 1, self.t,
                               step, self.diagnostics, adaptive=self.control is not None, run_file=run_file,
                               y=self.y, y0=self.y0, advise=not collapsed,
                               independence=gradients_independence(self.problem, self.conserve_idx, self.y),
                               problem=self.problem, imposed=len(self.conserve_idx)) + notes

    @property
    def t(self) -> float:
        return float(self.clock[0])

    @property
    def steps_done(self) -> int:
        return int(self.counters[codes.CNT_STEPS])

    @property
    def finished(self) -> bool:
        return self.finished_flag or self.status != codes.STATUS_OK

    def state(self) -> dict:
        return {"y": self.y.copy(), "y_comp": self.y_comp.copy(), "clock": self.clock.copy(),
                "coef": self.coef.copy(), "coef_extra": self.coef_extra.copy(), "multipliers": self.multipliers.copy(),
                "last_h": self.last_h.copy(), "newton_base": self.newton_base.copy(),
                "control_state": self.control_state.copy(),
                "counters": self.counters.copy(), "finished": int(self.finished_flag),
                "event_counts": self.event_counts.copy(), "steps_done": self.steps_done}

    def restore(self, state: dict) -> None:
        """Continue from a saved state (one without coef_extra: integrate.restore_predictor_extra)."""
        from .integrate import restore_predictor_extra
        state = dict(state)
        restore_predictor_extra(state, self.coef_extra)
        for key in ("y", "y_comp", "clock", "coef", "coef_extra", "multipliers", "last_h", "newton_base",
                    "control_state", "counters"):
            target = getattr(self, key)
            value = np.asarray(state[key], dtype=target.dtype)
            if key == "counters" and value.ndim == 1 and value.size < target.size:
                # saved before the last counters were added (counted_stats): they start at 0
                value = np.concatenate([value, np.zeros(target.size - value.size, dtype=target.dtype)])
            if value.shape != target.shape:
                raise ValueError(f"saved state {key!r} has shape {value.shape}, expected {target.shape}")
            target[...] = value
        self.finished_flag = bool(state.get("finished", 0))
        if "event_counts" in state:
            self.event_counts[...] = np.asarray(state["event_counts"], dtype=np.int64)
        self.status = codes.STATUS_OK

    def initial_samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sample at t0 when it is wanted (always without t_eval; with t_eval when it lists t0)."""
        p = self.problem
        values = np.empty(len(p.invariant_names))
        p.invariants(self.y, p.params, values)
        inv = np.concatenate(([p.H(self.y, p.params)], values))[None, :]
        if self.t_eval.size and self.t_eval[0] != self.t0:
            return np.zeros(0), np.zeros((0, self.y.size)), np.zeros((0, inv.shape[1]))
        return np.array([self.t]), self.y[None, :].copy(), inv

    def prepare_kernel(self) -> None:
        """Load the adaptive kernel (kernels.adaptive.adaptive_loop), compiling it on an empty cache;
        the first advance does it otherwise. Not at import: checking a config must not wait for it."""
        from .kernels import adaptive
        self._adaptive_loop = adaptive.adaptive_loop

    def advance(self, max_steps: int) -> AdaptiveChunk:
        p, m, solver = self.problem, self.method, self.solver
        if self._adaptive_loop is None:
            self.prepare_kernel()
        n_eval_left = int(self._kernel_t_eval.size - self.counters[codes.CNT_NEXT_EVAL])
        # Every requested time of the rest of the run fits: one step may cover many of them.
        capacity = n_eval_left + 1 if self.t_eval.size else max_steps // self.store_every + 2
        n_events = self.events.directions.size
        event_capacity = 64 * n_events + n_events
        dim = self.y.size
        t_out, y_out = np.empty(capacity), np.empty((capacity, dim))
        inv_out = np.empty((capacity, 1 + len(p.invariant_names)))
        step_t, step_h = np.empty(max_steps), np.empty(max_steps)
        mult_out = np.empty((max_steps, self.multipliers.size))
        iter_out = np.zeros(max_steps, dtype=np.int64)
        substeps_out = np.zeros(max_steps, dtype=np.int64)
        event_out = np.zeros(event_capacity, dtype=np.int64)
        event_t, event_y = np.empty(event_capacity), np.empty((event_capacity, dim))
        first = self.steps_done
        with remembered_addresses():
            status = self._adaptive_loop(
                p.H, p.grad_H, p.hess_H, p.invariants, p.grad_invariants, p.params,
                p.time_scale if p.time_scale is not None else no_invariants, self.events.function,
                m.kernel_family, solver.code, solver.rhs_code, int(solver.warm_start),
                int(solver.predictor),
                solver.tol, solver.max_iter, solver.max_halvings,
                self.h, m.projection, m.Is, m.projection_hat, m.Is_hat, m.X, m.abs_projection_hat,
                m.predictor_nodes, m.predictor_basis, m.newton_values, m.newton_vectors, m.newton_inverse,
                m.newton_weights, m.Is_low, m.Is_hat_low, self.conserve_idx,
                self.controls, self.options, self._kernel_t_eval, self.events.directions, self.events.terminal,
                self.y, self.y_comp, self.clock, self.coef, self.coef_extra, self.multipliers, self.last_h,
                self.newton_base, self.control_state, self.counters, max_steps,
                step_t, step_h, mult_out, iter_out, substeps_out, t_out, y_out, inv_out, event_out, event_t, event_y,
                self._progress, self.diagnostics)
        done, samples, found, finished = (int(v) for v in self._progress)
        self.status = int(status)
        self.finished_flag = bool(finished)
        self.event_counts += np.bincount(event_out[:found], minlength=self.event_counts.size)
        if n_events and samples:
            self.check_events_finite(t_out[:samples], y_out[:samples])
        return AdaptiveChunk(t_out[:samples], y_out[:samples], inv_out[:samples], step_t[:done], step_h[:done],
                             mult_out[:done], iter_out[:done], substeps_out[:done], event_out[:found],
                             event_t[:found], event_y[:found], first, int(status))

    def check_events_finite(self, t: np.ndarray, y: np.ndarray) -> None:
        """Record in events_not_finite (name -> first time) the events that are NaN or infinite at
        some of these samples (at most EVENT_CHECK_SAMPLES of them, evenly spread): no crossing can
        be found where an event is not finite, and the kernel says nothing of it (a user trial:
        sqrt(q1 + 0.5) on Kepler e = 0.9, NaN on most of the orbit, found 0 events, status
        complete). Only an event NaN at t0 is refused (events_for)."""
        rows = np.unique(np.linspace(0, t.size - 1, min(t.size, EVENT_CHECK_SAMPLES)).round().astype(np.int64))
        values = np.empty(self.events.directions.size)
        for row in rows:
            self.events.function(np.ascontiguousarray(y[row]), self.problem.params, values)
            for name, value in zip(self.events.names, values):
                if not math.isfinite(value) and name not in self.events_not_finite:
                    self.events_not_finite[name] = float(t[row])

    @property
    def _kernel_t_eval(self) -> np.ndarray:
        """The requested times after t0 (a requested t0 is the initial sample). When t0 was the only
        one: [inf], a time no step reaches, since an empty t_eval tells the kernel to sample every
        store_every steps (t_eval = [t0] stored every step)."""
        if self.t_eval.size and self.t_eval[0] == self.t0:
            return self.t_eval[1:] if self.t_eval.size > 1 else np.array([np.inf])
        return self.t_eval

    def stats(self, counters=None) -> dict:
        """What users compare methods by: steps, rejections and evaluations (docs/adaptive.md), of
        the run's counters or of ``counters`` (a saved state's: what its file holds)."""
        stats = counted_stats(self.counters if counters is None else counters)
        per_grad_H, per_grad_L = self.method.evaluations_per_iteration(len(self.conserve), self.solver.rhs == "stable")
        ordered = {}
        for key, value in stats.items():   # the evaluations follow the iterations they count
            ordered[key] = value
            if key == "iterations":
                ordered["grad_H_evaluations"], ordered["grad_L_evaluations"] = per_grad_H * value, per_grad_L * value
                # one grad H for each state the energy projection checked (stepper.project_energy)
                ordered["grad_H_evaluations"] += stats["energy_projections"]
        return ordered
