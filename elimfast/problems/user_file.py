"""``python: path/to/file.py`` problems: plain Python functions, compiled with the fixed signatures.

A Python problem file is code, run because the user explicitly names it (a YAML config
itself can never run code: its expressions are data, see ``expressions.py``). The file
defines, at module level:

Required
    ``H(y, params) -> float``            the Hamiltonian
    ``grad_H(y, params, out)``           write dH/dy into out (2m,): dH/dq, then dH/dp
Optional
    ``hess_H(y, params, out)``           write d^2 H/dy^2 into out (2m, 2m), rows and columns
                                         q then p (every entry); without it, central
                                         differences of grad_H are used (below)
    ``invariants(y, params, out)``       write L_i(y) into out (n_inv,)
    ``grad_invariants(y, params, out)``  write grad L_i(y) into row i of out (n_inv, 2m)
    ``INVARIANT_NAMES``                  names of the L_i, in order (required with invariants)
    ``Y0``                               default initial state, 2m numbers (q, then p)
    ``Q_NAMES``, ``P_NAMES``             coordinate names (default q1..qm, p1..pm)
    ``PARAMETERS``                       {name: default value}; the functions read them
                                         as params[0], params[1], ... in this order
    ``NAME``, ``DESCRIPTION``            for reports (default: the file name; the docstring)
    ``HAMILTONIAN_DEGREE``               H is a polynomial in y of at most this total degree
                                         (Problem.hamiltonian_degree: check and the end-of-run
                                         note then know when the quadrature of H is exact)

``y``, ``params`` and ``out`` are C-contiguous float64 arrays; the functions must be
Numba-compilable (``math`` and NumPy on scalars; helpers they call must be decorated
with ``numba.njit``). They may be plain functions or already ``@njit``-decorated: either
way elimfast compiles them with exactly the signatures of ``kernels.signatures``
(``njit(signature, cache=True, error_model="numpy")``), so they run as fast as a built-in;
a division by zero gives inf/NaN, which the kernel reports as a non-finite failure. Each function is
first called once in plain Python at the initial state with arrays of the right shape,
so an out-of-range index or an output left unwritten is reported instead of corrupting
memory in compiled code. The checks at load (``check.py``) then compare grad_H, the
invariants' gradients and hess_H with central differences, and test the invariants.

The Hessian (needed by the simplified Newton solver, docs/solver.md): the file's own
``hess_H`` when it defines one (``Problem.hessian_source == "user"``); otherwise central
differences of the compiled grad_H, symmetrised (``"finite differences"``): column j is
(grad_H(y + h_j e_j) - grad_H(y - h_j e_j)) / 2h_j with h_j = eps^(1/3) max(|y_j|, 1)
(the reasons are beside ``FD_HESSIAN_SOURCE``), accurate to about 1e-10 relative for
smooth H, ample for the Newton iteration matrix, at the price of 2m calls of grad_H.
That function is appended to the cached copy of the file (below), and compiled and
cached like the file's own functions.

Caching: the file's text, followed by elimfast's finite-difference Hessian, is copied to
``<cache>/problems/u_<sha256>.py`` (named by that content and the elimfast version) and
imported from there with ``__file__`` still the original path (``Problem.source_file``
too, so that messages name the user's file). So Numba's cache lives in elimfast's cache
directory, an edit of the file (or of the appended Hessian) simply makes a new entry,
and a second process loading the same file compiles nothing. Imports of sibling modules
of the file are not supported (use installed packages).

Example: ``configs/kepler_problem.py``.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .. import cache
from ..kernels import signatures
from ..errors import ParameterError
from .base import Problem, invariant_name_clash, real_state
from .expressions import ProblemDefinitionError, check_name, did_you_mean, evaluate_number

# Appended to the cached copy of every python: problem file (after its last line, so its
# line numbers are unchanged); compiled only when the file defines no hess_H, with
# FD_GRAD_H_GLOBAL bound to the compiled grad_H first. Central differences of grad_H:
# error h^2 |g'''|/6 (truncation) + ~eps |g|/h (rounding), smallest for h ~ eps^(1/3) s
# where s is the scale over which g varies. That scale is unknown; max(|y_j|, 1) is a
# relative step for large components and an absolute 6e-6 near 0, where a component has
# no scale of its own. The error is then ~eps^(2/3) ~ 4e-11 relative for smooth H, far
# below what the Newton iteration matrix needs (it only sets the contraction rate). The
# argument difference (y_j + h) - (y_j - h) as represented divides, not 2h. Two vectors
# are allocated per call: hess_H runs once per step, beside 2m calls of grad_H.
FD_GRAD_H_GLOBAL = "_elimfast_grad_H"
FD_HESS_H_NAME = "_elimfast_fd_hess_H"
FD_HESSIAN_SOURCE = """

# --- appended by elimfast (problems/user_file.py), not part of the file it follows: the Hessian
# by central differences of grad_H, used when the file defines no hess_H.
import numpy as _elimfast_numpy


def _elimfast_fd_hess_H(y, params, out):
    n = y.shape[0]
    shifted = y.copy()
    minus = _elimfast_numpy.empty(n)
    for j in range(n):
        centre = y[j]
        step = 6.055454452393343e-06 * max(abs(centre), 1.0)   # eps ** (1/3) * max(|y_j|, 1)
        shifted[j] = centre + step
        _elimfast_grad_H(shifted, params, out[j])
        shifted[j] = centre - step
        _elimfast_grad_H(shifted, params, minus)
        width = (centre + step) - (centre - step)
        shifted[j] = centre
        for i in range(n):
            out[j, i] = (out[j, i] - minus[i]) / width
    for i in range(n):
        for j in range(i + 1, n):
            mean = 0.5 * (out[i, j] + out[j, i])
            out[i, j] = mean
            out[j, i] = mean
"""


class UserProblemError(ProblemDefinitionError):
    """A ``python:`` problem file that cannot be loaded, compiled or used."""


_MODULES: dict[str, object] = {}
_COMPILED: dict[tuple[str, str], object] = {}

MODULE_PREFIX = "elimfast_user_"   # + its content's hash: the name a copied python: file has

_SIGNATURES = {
    "H": (signatures.H_SIGNATURE, "H(y, params) -> float"),
    "grad_H": (signatures.GRAD_H_SIGNATURE, "grad_H(y, params, out)"),
    "hess_H": (signatures.HESS_H_SIGNATURE, "hess_H(y, params, out)"),
    "invariants": (signatures.INVARIANTS_SIGNATURE, "invariants(y, params, out)"),
    "grad_invariants": (signatures.GRAD_INVARIANTS_SIGNATURE, "grad_invariants(y, params, out)"),
}


def problem_from_file(path, parameters=None, initial=None, name: str | None = None, check: bool = True) -> Problem:
    """The Problem defined by a Python file (see the module docstring for what it must define).

    parameters: {name: value} overriding PARAMETERS; initial: {coordinate: value} overriding
    Y0 entries (every coordinate when the file has no Y0). Values may be numeric strings
    ('pi/3'); initial values may use the parameter names. check: test the file's gradients
    against central differences and its invariants against the flow of H at seeded points around the initial state
    (problems/check.py, as a config's problem.check does): DerivativeCheckError or
    InvariantCheckError if one is wrong.
    """
    problem = _build_from_file(path, parameters, initial, name)
    if check:
        from .check import PYTHON_SKIP, require_problem
        require_problem(problem, skip=PYTHON_SKIP)
    return problem


def missing_file_text(path) -> str:
    """The one error for a python: problem file that is not there (here and config's gate)."""
    return (f"python problem file {path} does not exist; check the path (relative paths are relative to the "
            "config file)")


def _build_from_file(path, parameters, initial, name) -> Problem:
    path = Path(path).expanduser()
    label = str(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise UserProblemError(missing_file_text(label), key="python") from None
    except (OSError, UnicodeDecodeError) as err:
        raise UserProblemError(f"python problem file {label} cannot be read ({err})", key="python") from None
    module = _load_module(path, text)

    def get(attribute, default=None):
        return module.__dict__.get(attribute, default)

    functions = {}
    for fname in ("H", "grad_H", "hess_H", "invariants", "grad_invariants"):
        value = get(fname)
        if value is not None and not callable(value):
            raise UserProblemError(f"{label}: {fname} must be a function {_SIGNATURES[fname][1]}", key="python")
        functions[fname] = value
    for required in ("H", "grad_H"):
        if functions[required] is None:
            raise UserProblemError(f"{label} defines no {required}; define a function {_SIGNATURES[required][1]}",
                                   key="python")
    if (functions["invariants"] is None) != (functions["grad_invariants"] is None):
        raise UserProblemError(f"{label}: define both invariants and grad_invariants, or neither", key="python")
    invariant_names = tuple(get("INVARIANT_NAMES", ()))
    for iname in invariant_names:
        try:
            check_name(iname, "invariant name")
        except ProblemDefinitionError as err:
            raise UserProblemError(f"{label}: INVARIANT_NAMES: {err}", key="python") from None
        if invariant_name_clash(iname):
            raise UserProblemError(f"{label}: INVARIANT_NAMES: {invariant_name_clash(iname)}", key="python")
    if functions["invariants"] is not None and not invariant_names:
        raise UserProblemError(f"{label}: invariants is defined but INVARIANT_NAMES is not; list their names",
                               key="python")
    if functions["invariants"] is None and invariant_names:
        raise UserProblemError(f"{label}: INVARIANT_NAMES is given but no invariants function", key="python")

    default_parameters = get("PARAMETERS", {}) or {}
    if not isinstance(default_parameters, dict):
        raise UserProblemError(f"{label}: PARAMETERS must be a dict name -> value", key="python")
    param_values = {}
    for pname, value in default_parameters.items():
        try:
            check_name(pname, "parameter name")
        except ProblemDefinitionError as err:
            raise UserProblemError(f"{label}: PARAMETERS: {err}", key="python") from None
        param_values[pname] = _number(value, f"{label}: PARAMETERS[{pname!r}]", "python")
    for pname, value in (parameters or {}).items():
        if pname not in param_values:
            known = ", ".join(param_values) or "none"
            raise UserProblemError(f"{label} has no parameter {pname!r}{did_you_mean(str(pname), param_values)} "
                                   f"(its PARAMETERS: {known})", key=f"parameters.{pname}")
        param_values[pname] = _number(value, f"parameter {pname}", f"parameters.{pname}")

    q_names, p_names, y0 = _coordinates(label, get("Q_NAMES"), get("P_NAMES"), get("Y0"), initial, param_values)
    n = 2 * len(q_names)
    params = np.array(list(param_values.values()), dtype=np.float64)
    _dry_run(label, functions, y0, params, n, len(invariant_names))

    compiled = {fname: _compile(label, path, fname, function) for fname, function in functions.items()
                if function is not None}
    hessian_source = "user"
    if "hess_H" not in compiled:
        hessian_source = "finite differences"
        module.__dict__[FD_GRAD_H_GLOBAL] = compiled["grad_H"]   # resolved when the Hessian compiles
        compiled["hess_H"] = _compile(label, path, "hess_H", module.__dict__[FD_HESS_H_NAME])
    doc = (get("__doc__") or "").strip().splitlines()
    degree = get("HAMILTONIAN_DEGREE")
    if degree is not None and (isinstance(degree, bool) or not isinstance(degree, int) or degree < 0):
        raise UserProblemError(f"{label}: HAMILTONIAN_DEGREE must be a whole number >= 0 (the total degree of H as a "
                               f"polynomial in y), got {degree!r}; leave it out if H is not a polynomial", key="python")
    if degree is not None:
        _require_degree(label, functions["H"], y0, params, degree)
    return Problem(
        name=name or str(get("NAME", path.stem)), q_names=q_names, p_names=p_names,
        H=compiled["H"], grad_H=compiled["grad_H"], hess_H=compiled["hess_H"], hessian_source=hessian_source,
        source_file=str(path.resolve()),
        invariants=compiled.get("invariants", signatures.no_invariants),
        grad_invariants=compiled.get("grad_invariants", signatures.no_invariant_gradients),
        invariant_names=invariant_names, y0=y0, params=params, parameters=param_values,
        description=str(get("DESCRIPTION", doc[0] if doc else f"python problem {path.name}")),
        hamiltonian_degree=degree,
    )


# The declared degree is tested on this many seeded lines through y0 (_require_degree).
DEGREE_LINES = 3


def _require_degree(label, H, y0, params, degree: int) -> None:
    """HAMILTONIAN_DEGREE = d is taken only if H is a polynomial of degree <= d along DEGREE_LINES
    seeded lines through y0: the (d+1)-th difference of H(y0 + j delta v), j = 0..d+1, vanishes up to
    the rounding of its 2^(d+1) terms (a user trial: a Lennard-Jones H declared of degree 4 made
    'check' say it was kept to round-off; the energy note then hid its quadrature error)."""
    from math import comb

    H = getattr(H, "py_func", H)
    rng = np.random.default_rng(20141)
    step = 0.25 * max(1.0, float(np.max(np.abs(y0))))
    for _ in range(DEGREE_LINES):
        direction = rng.standard_normal(y0.size)
        direction /= np.linalg.norm(direction)
        with np.errstate(all="ignore"):
            try:
                values = np.array([float(H(y0 + j * step * direction, params)) for j in range(degree + 2)])
            except ArithmeticError:
                values = np.array([np.nan])
        difference = sum((-1) ** (degree + 1 - j) * comb(degree + 1, j) * value for j, value in enumerate(values))
        allowed = 1e3 * 2.0 ** (degree + 1) * np.finfo(float).eps * float(np.max(np.abs(values)))
        if not (abs(difference) <= allowed):
            raise UserProblemError(
                f"{label}: HAMILTONIAN_DEGREE = {degree}, but H is not a polynomial of degree <= {degree}: along a "
                f"line through the initial state its difference of order {degree + 1} is {difference:.3g}, where "
                f"rounding allows {allowed:.1e}; give H's true degree, or leave HAMILTONIAN_DEGREE out if H is not a "
                "polynomial", key="python")


def _number(value, what, key) -> float:
    try:
        return evaluate_number(value, what=what)
    except ProblemDefinitionError as err:
        raise UserProblemError(str(err), key=key) from None


def _load_module(path: Path, text: str):
    text = text + ("" if text.endswith("\n") else "\n") + FD_HESSIAN_SOURCE
    digest = cache.content_hash("python-file-v2", text)
    copy = cache.problems_dir() / f"u_{digest}.py"
    if str(copy) in _MODULES and copy.exists():
        return _MODULES[str(copy)]
    cache.write_if_changed(copy, text)
    module_name = f"{MODULE_PREFIX}{digest[:32]}"

    def own_location(module):   # the user's code sees its own location
        module.__file__ = str(path.resolve())

    try:
        module = cache.import_file(copy, module_name, prepare=own_location)
    except (Exception, SystemExit) as err:  # the user's file: report whatever it raised, in one line
        # SystemExit too: a sys.exit() in the file ended elimfast silently with its code (0 or 3, no
        # message, no file); KeyboardInterrupt is the user's Ctrl-C and stays one
        where = ""
        tb = err.__traceback__
        while tb is not None:
            if tb.tb_frame.f_code.co_filename == str(copy):
                where = f" at line {tb.tb_lineno}"
            tb = tb.tb_next
        if isinstance(err, SyntaxError):
            where = f" at line {err.lineno}"
            message = err.msg
        else:
            message = str(err).splitlines()[0] if str(err) else ""
        raise UserProblemError(f"python problem file {path}: running it raised {type(err).__name__}{where}: "
                               f"{message}; fix the file", key="python") from None
    _cache_helpers(module)
    _MODULES[str(copy)] = module
    cache.kernel_folder_used(in_package=False)   # its functions compile into elimfast's cache (cache.py)
    return module


def _cache_helpers(module) -> None:
    """Cache the file's own @njit helpers with its functions: a helper compiled without cache=True
    compiled again in every process, and with it every function that calls it (a user trial's
    Lennard-Jones file with @numba.njit pair potentials said 'compiling the problem's own
    functions (once: ...)' on every run, 2.5 s each). Only dispatchers defined in the file itself
    (in elimfast's cached copy of it, whose cache folder is keyed); imported ones are left alone."""
    from numba.core.caching import NullCache
    from numba.core.registry import CPUDispatcher

    for value in list(vars(module).values()):
        if isinstance(value, CPUDispatcher) and isinstance(getattr(value, "_cache", None), NullCache) \
                and getattr(value.py_func, "__module__", None) == module.__name__:
            value.enable_caching()


def _coordinates(label, q_names, p_names, default_y0, initial, param_values):
    if default_y0 is not None:
        try:
            default_y0 = real_state(default_y0, "Y0").ravel()
        except ParameterError as err:
            raise UserProblemError(f"{label}: {err}", key="python") from None
    if q_names is None and p_names is None:
        if default_y0 is None:
            raise UserProblemError(f"{label}: define Y0 (the default initial state) or Q_NAMES and P_NAMES",
                                   key="python")
        if default_y0.size % 2 or default_y0.size == 0:
            raise UserProblemError(f"{label}: Y0 must have an even, positive number of entries (q, then p), "
                                   f"got {default_y0.size}", key="python")
        m = default_y0.size // 2
        q_names = [f"q{i + 1}" for i in range(m)]
        p_names = [f"p{i + 1}" for i in range(m)]
    if q_names is None or p_names is None:
        raise UserProblemError(f"{label}: define both Q_NAMES and P_NAMES, or neither", key="python")
    q_names, p_names = tuple(q_names), tuple(p_names)
    for cname in q_names + p_names:
        try:
            check_name(cname, "coordinate name")
        except ProblemDefinitionError as err:
            raise UserProblemError(f"{label}: Q_NAMES/P_NAMES: {err}", key="python") from None
    names = q_names + p_names
    if len(q_names) != len(p_names) or not q_names or len(set(names)) != len(names):
        raise UserProblemError(f"{label}: Q_NAMES and P_NAMES must be distinct names, as many of each",
                               key="python")
    if default_y0 is not None and default_y0.size != len(names):
        raise UserProblemError(f"{label}: Y0 has {default_y0.size} entries for {len(names)} coordinates",
                               key="python")
    initial = dict(initial or {})
    for cname in initial:
        if cname not in names:
            raise UserProblemError(f"{cname!r} is not a coordinate of {label}{did_you_mean(str(cname), names)} "
                                   f"(coordinates: {', '.join(names)})", key=f"initial.{cname}")
    if default_y0 is None:
        missing = [c for c in names if c not in initial]
        if missing:
            raise UserProblemError(f"{label} has no Y0, so every coordinate needs an initial value; missing: "
                                   f"{', '.join(missing)}", key="initial")
        default_y0 = np.zeros(len(names))
    y0 = default_y0.copy()
    for i, cname in enumerate(names):
        if cname in initial:
            try:
                y0[i] = evaluate_number(initial[cname], param_values, what=f"initial value of {cname}")
            except ProblemDefinitionError as err:
                raise UserProblemError(str(err), key=f"initial.{cname}") from None
    if not np.all(np.isfinite(y0)):
        raise UserProblemError(f"{label}: the initial state must be finite, got {y0.tolist()}", key="python")
    return q_names, p_names, y0


def _dry_run(label, functions, y0, params, n, n_inv) -> None:
    """Call the plain Python functions once with exact-size arrays: catches wrong indices and
    unwritten outputs before compiled code could write out of bounds."""
    outputs = {"grad_H": np.full(n, np.nan), "hess_H": np.full((n, n), np.nan), "invariants": np.full(n_inv, np.nan),
               "grad_invariants": np.full((n_inv, n), np.nan)}
    for fname, function in functions.items():
        if function is None:
            continue
        py_function = getattr(function, "py_func", function)
        args = (y0.copy(), params.copy()) + ((outputs[fname],) if fname != "H" else ())
        try:
            with np.errstate(all="ignore"):
                value = py_function(*args)
        except Exception as err:
            first = str(err).splitlines()[0] if str(err) else ""
            raise UserProblemError(f"{label}: calling {_SIGNATURES[fname][1]} at the initial state raised "
                                   f"{type(err).__name__}: {first} (y has {n} entries, params {params.size}"
                                   + (f", {n_inv} invariants" if fname.endswith("invariants") else "")
                                   + ")", key="python") from None
        if fname == "H":
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise UserProblemError(f"{label}: H must return a number, got {value!r}", key="python") from None
            if not np.isfinite(value):   # a singularity: grad_H's NaN would read as an unwritten output
                raise UserProblemError(f"{label}: H = {value} at the initial state {y0.tolist()}; choose an initial "
                                       "state away from the singularity", key="initial")
        elif np.isnan(outputs[fname]).any():
            index = tuple(int(i) for i in np.argwhere(np.isnan(outputs[fname]))[0])
            raise UserProblemError(f"{label}: {fname} left out{list(index)} unwritten (or NaN) at the initial "
                                   f"state; it must fill all of out, shape {outputs[fname].shape}", key="python")


def compiled_function(fname, function):
    """A python: file's function compiled as the problem's ``fname`` (H, grad_H, ...): the dispatcher
    the problem itself has once it is loaded in this process. The per-problem kernel's module
    (per_problem.py) takes the file's functions through it, with the same code."""
    return _compile(f"the per-problem kernel's {fname}", None, fname, function)


def _compile(label, path, fname, function):
    from numba import njit
    from numba.core.errors import NumbaError

    py_function = getattr(function, "py_func", function)
    key = (str(getattr(py_function, "__code__", None) and py_function.__code__.co_filename), fname)
    if key in _COMPILED and _COMPILED[key].py_func is py_function:
        return _COMPILED[key]
    signature, text = _SIGNATURES[fname]
    try:
        compiled = njit(signature, cache=True, error_model="numpy")(py_function)
    except NumbaError as err:
        message = str(err)
        where = re.search(r'File "[^"]*", line (\d+)', message)
        lines = [line.strip() for line in message.splitlines()
                 if line.strip() and not line.startswith("Failed in nopython") and "During:" not in line
                 and not line.strip().startswith("File ")]
        detail = " ".join(lines[:1])[:300]
        at = f" (line {where.group(1)})" if where else ""
        raise UserProblemError(f"{label}: Numba cannot compile {fname} as {text}{at}: {detail}; only Numba-"
                               "supported Python (math, NumPy on scalars, @njit helpers) can be used",
                               key="python") from None
    except ImportError as err:
        # Numba's np.dot, @ and np.linalg call SciPy's BLAS and LAPACK, and elimfast does not need
        # SciPy: without it, "ImportError: scipy 0.16+ is required for linear algebra" was an internal error
        if "scipy" not in str(err).lower():
            raise
        raise UserProblemError(f"{label}: Numba compiles {fname}'s np.dot, @ or np.linalg through SciPy, which is "
                               "not installed; pip install scipy, or write the sums out (loops or "
                               "np.sum(a * b))", key="python") from None
    _COMPILED[key] = compiled
    return compiled
