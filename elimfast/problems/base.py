"""The Problem object: a Hamiltonian system with its invariants, as compiled functions.

A problem carries five compiled functions with the fixed signatures of
``elimfast.kernels.signatures`` (H, grad_H, hess_H, invariants, grad_invariants), its
parameter vector, default initial state, names and units. Kernels never see the Problem:
the driver passes its functions and arrays, so new problems (built-in, generated
from expressions, or user files) never touch the kernels.
"""
from __future__ import annotations

import decimal
import numbers
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np

from ..errors import ParameterError, real_number

# Where a problem's hess_H comes from -> how reports say it.
HESSIAN_SOURCES = {
    "analytic": "analytic (written by hand in the built-in problem)",
    "symbolic": "symbolic (sympy's second derivatives of the expression for H)",
    "user": "the python file's own hess_H",
    "finite differences": "finite differences of grad_H (the python file defines no hess_H)",
}


def real_parameter(parameter: str, value) -> float:
    """A built-in problem's real parameter as a float, or a ParameterError naming it (float() of a
    list said "float() argument must be a string or a real number, not 'list'", naming nothing).
    A string is refused as errors.real_number refuses it: the API takes numbers (kepler(eccentricity=
    '0.9') was taken where integrate(h='0.1') is refused); a config reads its expressions first."""
    if isinstance(value, str):
        real_number(parameter, value)   # raises, with the API's one message for a string
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, decimal.Decimal, np.generic)):
        raise ParameterError(parameter, f"must be a number, got {_shown(value)}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ParameterError(parameter, f"must be a number, got {_shown(value)}") from None


def require_problem_object(problem) -> None:
    """TypeError unless ``problem`` is a Problem; a name of a built-in one says how to build it (a
    user trial passed "kepler", as a method may be passed by its name)."""
    if isinstance(problem, Problem):
        return
    hint = ""
    if isinstance(problem, str):
        from .catalogue import BUILTINS
        hint = (f" (build it: elimfast.problems.{problem}())" if problem in BUILTINS
                else " (build one with elimfast.problems.<name>(), problem_from_expressions or problem_from_file)")
    raise TypeError(f"problem must be an elimfast Problem, got {type(problem).__name__}{hint}")


def real_state(value, parameter: str = "y0") -> np.ndarray:
    """An initial state as a fresh float64 array, or a ParameterError naming ``parameter``.

    The one check of what a state is made of (Problem's y0, ``with_initial``, integrate's y0,
    an ensemble's Y0, a python problem's Y0; the shape is checked by each): real numbers
    only. numpy's own conversion dropped the imaginary part of a complex state with only a
    ComplexWarning, and a string got "could not convert string to float", naming nothing.
    """
    try:
        array = np.asarray(value)
    except (TypeError, ValueError):   # ragged nesting
        array = None
    if array is not None and array.dtype == object:   # Python objects: Fractions, or None, or ...
        items = list(array.flat)
        # decimal.Decimal is no numbers.Real (it refuses mixing with floats), but is a real number
        if all((isinstance(v, (numbers.Real, decimal.Decimal))) and not isinstance(v, bool) for v in items):
            array = np.array(items, dtype=np.float64).reshape(array.shape)
        elif any(isinstance(v, numbers.Complex) and not isinstance(v, numbers.Real) for v in items):
            array = np.zeros(0, dtype=complex)   # refused as complex below
    if array is not None and array.dtype.kind == "c":
        raise ParameterError(parameter, f"must be real numbers, got complex values {_shown(value)}: the state of "
                                        "a Hamiltonian system is real; pass the real part (numpy.real) if that is "
                                        "what you mean")
    if array is None or array.dtype.kind not in "iuf":
        raise ParameterError(parameter, f"must be a list of real numbers, got {_shown(value)}")
    return np.array(array, dtype=np.float64)


# The names of a run's other data, in its file and in Result.to_xarray (io/layout.py,
# io/xarray_view.py), where each invariant is a variable of its own name: an invariant 'y'
# replaced the state there, and 't', 'component' or 'invariant' made xarray fail.
DATA_NAMES = frozenset({"t", "component", "y", "step", "invariant", "iterations", "substeps", "alpha", "lambda",
                        "step_t", "step_h"})


def invariant_name_clash(name) -> str | None:
    """Why ``name`` cannot name an invariant (other data of the run has it), or None."""
    if name in DATA_NAMES:
        return (f"invariant name {name!r} is taken by other data of a run (in its file and in xarray: t, y, "
                "component, step, invariant, iterations, substeps, alpha, lambda, step_t, step_h); choose another name")
    return None


def _shown(value, limit: int = 60) -> str:
    with np.printoptions(threshold=8):   # a large array's repr is summarised, not built whole
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _vector(y) -> np.ndarray:
    # A fresh writable copy: the compiled functions' signatures take writable C arrays.
    return np.array(y, dtype=np.float64, order="C")


def _terms_size(gradient, y, m: int):
    """|grad_q I|_1 |q|_inf + |grad_p I|_1 |p|_inf along the last axis (Problem.invariant_scales)."""
    q_size, p_size = np.max(np.abs(y[..., :m]), axis=-1), np.max(np.abs(y[..., m:]), axis=-1)
    return np.sum(np.abs(gradient[..., :m]), axis=-1) * q_size + np.sum(np.abs(gradient[..., m:]), axis=-1) * p_size


def _point_near(y0: np.ndarray, rng) -> np.ndarray:
    """A seeded state near y0 for the structural tests of a problem's functions (linear or quadratic
    invariants): each component moved by 10% of itself and by a tenth of the state's size (at least
    0.1), so that zero components move too."""
    spread = 0.1 * max(1.0, float(np.max(np.abs(y0))))
    return y0 * (1.0 + 0.1 * rng.standard_normal(y0.size)) + spread * rng.standard_normal(y0.size)


def _affine_rows(gradients, y0) -> list[bool]:
    """For each row of gradients(y) (rows: functions' gradients), whether it is affine in y (the
    function quadratic or linear): at three seeded pairs of points around y0 (_point_near), every
    component of the gradient at their midpoint is their mean, to 1e-12 of that component's own
    size. Each component on its own: the solar system's potential gradient, 1e-17 of its kinetic
    one (Pluto's p / m), passed a test against the row's largest. A component that cancels to far
    below its terms may fail the test though affine: the safe side, where ELIM is tried as before.
    False where a gradient is not finite; a function that raises there (outside its domain) raises
    here."""
    rng = np.random.default_rng(20141202)
    affine = None
    for _ in range(3):
        a, b = _point_near(y0, rng), _point_near(y0, rng)
        ga, gb, gm = gradients(a), gradients(b), gradients(0.5 * (a + b))
        with np.errstate(invalid="ignore", over="ignore"):
            size = np.maximum(np.maximum(np.abs(ga), np.abs(gb)), np.abs(gm))
            here = np.all(np.abs(ga + gb - 2.0 * gm) <= 1e-12 * size, axis=1)
        here &= np.all(np.isfinite(ga) & np.isfinite(gb) & np.isfinite(gm), axis=1)
        affine = here if affine is None else affine & here
    return [bool(value) for value in affine]


@dataclass(frozen=True, eq=False)
class Problem:
    """y' = J grad H(y), y = (q, p), with named invariants L_i (grad L_i^T J grad H = 0).

    name: short identifier; q_names, p_names: coordinate names (m each);
    H, grad_H, hess_H, invariants, grad_invariants: compiled functions (see
    kernels.signatures; hess_H is d^2 H/dy^2, needed by the simplified Newton solver of
    docs/solver.md); invariant_names: names of the invariants, in the order ``invariants``
    writes them; y0: default initial state (2m,);
    hessian_source: where hess_H comes from, a key of ``HESSIAN_SOURCES``;
    params: parameter vector passed to every function;
    parameters: the named parameters the problem was built with (for reports);
    units: {quantity: unit} when the problem has physical units, e.g. {"length": "AU",
    "time": "day", "mass": "solar mass"}, else empty;
    source_file: the user's own file of a ``python:`` problem (error messages name it
    rather than its copy in the cache), else None;
    time_scale: a compiled ``time_scale(y, params, out)`` writing out[0] = sigma(y), the
    local time scale of the motion, and out[1:] = grad sigma(y) (the time-reversible step
    control of docs/adaptive.md), or None when the problem defines none;
    initial_given: y0 was given in place of the problem's default state (a config's
    problem.initial, ``with_initial``) and differs from it, so the parameters that chose the
    default (kepler's eccentricity) no longer describe the orbit (reports say so);
    hamiltonian_degree: H is a polynomial in y of at most this total degree, or None (not one,
    or not known): HBVM(k,s) and its relatives integrate it exactly when degree <= 2k/s, so an
    H error above round-off is then not the quadrature's (integrate.energy_note);
    hamiltonian_kinks: the functions with a kink that H (from expressions) calls, e.g. ("abs",)
    (expressions.KINKED): reports name them where H is lost.
    """

    name: str
    q_names: tuple[str, ...]
    p_names: tuple[str, ...]
    H: Any = field(repr=False)
    grad_H: Any = field(repr=False)
    hess_H: Any = field(repr=False)
    invariants: Any = field(repr=False)
    grad_invariants: Any = field(repr=False)
    invariant_names: tuple[str, ...]
    y0: np.ndarray = field(repr=False)
    hessian_source: str
    params: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    parameters: dict = field(default_factory=dict)
    description: str = ""
    units: dict = field(default_factory=dict)
    source_file: str | None = None
    time_scale: Any = field(repr=False, default=None)
    initial_given: bool = False
    hamiltonian_degree: int | None = None
    hamiltonian_kinks: tuple = ()

    def __post_init__(self):
        if len(self.q_names) != len(self.p_names):
            raise ValueError(f"problem {self.name!r}: {len(self.q_names)} q names but {len(self.p_names)} p names")
        try:
            y0 = np.ascontiguousarray(real_state(self.y0))
        except ParameterError as err:
            raise ParameterError("y0", f"of problem {self.name!r} {err.detail}") from None
        if y0.shape != (2 * len(self.q_names),):
            raise ValueError(f"problem {self.name!r}: y0 must have {2 * len(self.q_names)} entries, got shape {y0.shape}")
        y0.setflags(write=False)
        # Not read-only: Numba types read-only arrays differently from the kernels' signatures.
        params = np.ascontiguousarray(self.params, dtype=np.float64).copy()
        object.__setattr__(self, "y0", y0)
        object.__setattr__(self, "params", params)
        object.__setattr__(self, "q_names", tuple(self.q_names))
        object.__setattr__(self, "p_names", tuple(self.p_names))
        object.__setattr__(self, "invariant_names", tuple(self.invariant_names))
        if len(set(self.invariant_names)) != len(self.invariant_names) or "H" in self.invariant_names:
            raise ValueError(f"problem {self.name!r}: invariant names must be distinct and not 'H'")
        for name in self.invariant_names:
            if invariant_name_clash(name):
                raise ValueError(f"problem {self.name!r}: {invariant_name_clash(name)}")
        if self.hessian_source not in HESSIAN_SOURCES:
            raise ValueError(f"problem {self.name!r}: hessian_source must be one of "
                             f"{', '.join(map(repr, HESSIAN_SOURCES))}, got {self.hessian_source!r}")
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in dict(self.units).items()):
            raise ValueError(f"problem {self.name!r}: units must map quantity names to unit names (strings)")
        object.__setattr__(self, "units", dict(self.units))

    @property
    def degrees_of_freedom(self) -> int:
        return len(self.q_names)

    @property
    def hessian_description(self) -> str:
        """Where hess_H comes from, in words (for ``elimfast check`` and reports)."""
        return HESSIAN_SOURCES[self.hessian_source]

    @property
    def coordinate_names(self) -> tuple[str, ...]:
        """Names of the 2m components of y: the q names, then the p names."""
        return self.q_names + self.p_names

    def with_initial(self, y0) -> "Problem":
        """The same problem from another initial state (``initial_given`` when it differs from y0)."""
        y0 = real_state(y0)
        given = self.initial_given or y0.shape != self.y0.shape or not np.array_equal(y0, self.y0)
        return replace(self, y0=y0, initial_given=given)

    def with_time_scale(self, expression: str) -> "Problem":
        """The same problem with the time scale sigma(y) of time-reversible steps
        (``step_control="time_scale"``, docs/adaptive.md) given as an expression in its
        coordinates and numeric parameters, e.g. ``"(q1**2 + q2**2)**0.75"``: what the config
        key ``problem.time_scale`` declares, for any problem (built-in, expressions or a
        ``python:`` file). Compiled and cached like a problem's expressions; raises
        ExpressionError naming ``time_scale``."""
        from .symbolic import compile_state_functions
        function = compile_state_functions(self, {"time_scale": expression}, gradient=True, what="time scale",
                                           key_prefix="time_scale")
        return replace(self, time_scale=function)

    # Convenience evaluations from Python (the kernels call the compiled functions directly).
    def hamiltonian(self, y) -> float:
        return float(self.H(_vector(y), self.params))

    def gradient(self, y) -> np.ndarray:
        out = np.empty(2 * self.degrees_of_freedom)
        self.grad_H(_vector(y), self.params, out)
        return out

    def hessian(self, y) -> np.ndarray:
        """(2m, 2m): d^2 H / dy^2 at y, rows and columns q then p."""
        n = 2 * self.degrees_of_freedom
        out = np.empty((n, n))
        self.hess_H(_vector(y), self.params, out)
        return out

    def invariant_values(self, y) -> dict[str, float]:
        """{'H': H(y), name: L_i(y), ...}."""
        values = np.empty(len(self.invariant_names))
        self.invariants(_vector(y), self.params, values)
        return {"H": self.hamiltonian(y), **dict(zip(self.invariant_names, values.tolist()))}

    def invariant_scales(self, y) -> dict[str, float]:
        """{'H': S_H, name: S_i, ...}: the size of the terms whose sum is each invariant at y,
        S = |grad_q I|_1 |q|_inf + |grad_p I|_1 |p|_inf (a bound of sum_j |y_j dI/dy_j| that
        stays positive where the state has zeros, e.g. Kepler's A_y at pericentre; q and p are
        each in one unit).

        The reference of a relative error where I(y) is itself a cancellation to round-off
        (``integrate.relative_error``): the solar system's linear momenta sum to ~1e-21
        from terms of ~1e-5, and an error of 1e-19 is round-off there, not 100 times I.
        """
        y = _vector(y)
        m = self.degrees_of_freedom
        scales = {"H": float(_terms_size(self.gradient(y), y, m))}
        if self.invariant_names:
            for name, row in zip(self.invariant_names, self.invariant_gradients(y)):
                scales[name] = float(_terms_size(row, y, m))
        return scales

    def H_term_sizes(self, states) -> np.ndarray:
        """invariant_scales' 'H' at each row of ``states`` (n_states, 2m), at one grad_H call
        a row (integrate.terms_peak looks at a run's samples with it)."""
        states = np.ascontiguousarray(states, dtype=np.float64)
        gradients = np.empty_like(states)
        for row in range(states.shape[0]):
            self.grad_H(states[row], self.params, gradients[row])
        return _terms_size(gradients, states, self.degrees_of_freedom)

    @cached_property
    def linear_invariant_names(self) -> tuple[str, ...]:
        """Invariants whose gradient is the same at y0 and at two seeded points near it.

        ELIM cannot impose these (phi_j = 0 for j >= 1, so Gamma has a zero column),
        and needs not: every Runge-Kutta method keeps linear invariants exactly.
        """
        if not self.invariant_names:
            return ()
        rng = np.random.default_rng(20140611)
        points = [self.y0] + [_point_near(self.y0, rng) for _ in range(2)]
        gradients = [self.invariant_gradients(point) for point in points]
        linear = []
        for i, name in enumerate(self.invariant_names):
            reference_row = gradients[0][i]
            size = max(float(np.max(np.abs(reference_row))), 1e-300)
            if all(np.max(np.abs(g[i] - reference_row)) <= 1e-13 * size for g in gradients[1:]):
                linear.append(name)
        return tuple(linear)

    @cached_property
    def quadratic_invariant_names(self) -> tuple[str, ...]:
        """Invariants that are quadratic when H is quadratic too (their gradients affine at seeded
        points near y0, _affine_rows), else (). Linear ones are linear_invariant_names'.

        ELIM cannot impose these either: with grad H and grad L affine and {L, H} = 0, every
        phi_j^T gamma_j vanishes whatever the stages (docs/methods.md#linear-invariants), so Gamma
        is zero; and it needs not: on a quadratic H the HBVM step is Gauss collocation, which keeps
        every quadratic invariant."""
        if not self.invariant_names:
            return ()
        gradient = np.empty(2 * self.degrees_of_freedom)

        def grad_H(y):
            self.grad_H(_vector(y), self.params, gradient)
            return gradient[None, :].copy()

        try:
            if not _affine_rows(grad_H, self.y0)[0]:
                return ()
            affine = _affine_rows(self.invariant_gradients, self.y0)
        except Exception:   # noqa: BLE001 -- a user's function outside its domain near y0: no answer, so none
            return ()
        return tuple(name for name, is_affine in zip(self.invariant_names, affine)
                     if is_affine and name not in self.linear_invariant_names)

    def invariant_gradients(self, y) -> np.ndarray:
        """(n_inv, 2m): row i is grad L_i(y)."""
        out = np.empty((len(self.invariant_names), 2 * self.degrees_of_freedom))
        self.grad_invariants(_vector(y), self.params, out)
        return out
