"""Problems from expressions: sympy gradients, generated Numba source, compiled once per machine.

``problem_from_expressions`` turns the expression strings of a config into a Problem
whose five functions (H, grad_H, hess_H, invariants, grad_invariants) have exactly the
compiled signatures of ``kernels.signatures``, so the kernels run them as fast as a
hand-written built-in (``bench/user_problem.py``).

Pipeline (expressions are data, never code: see ``expressions.py``):

1. Parse and validate every expression (``ast`` whitelist); bound their number
   (``MAX_INVARIANTS``) and total size (``MAX_TOTAL_NODES``).
2. Input key = sha256 of (elimfast version, ``GENERATOR_VERSION``, coordinate and
   parameter names, the canonical form of each expression). If ``<cache>/keys/<key>``
   names a generated file whose content still hashes to its name, import it: a warm load
   needs neither sympy nor any compilation (Numba's cache beside the file is valid).
   The generator version is in the key and in the generated text, so files written by
   an older generator (before hess_H, say) are never loaded by this one.
3. Otherwise build sympy expressions node by node, differentiate (gradients, and the
   upper triangle of the Hessian of H, mirrored), eliminate common subexpressions
   (``sympy.cse``), print Python source with ``@njit(<signature>, cache=True)``
   functions, write it atomically to ``<cache>/problems/p_<sha256 of the source and
   version>.py``, record the key, and import it.

The symbolic work is bounded before it is done: differentiation of a product of n
factors that depend on a coordinate gives n terms of n - 1 factors, so the size of a
derivative is estimated from the expression tree (``_derivative_sizes``: sum, product,
chain and power rules applied to node counts) and the problem is refused when the
derivatives would exceed ``MAX_DERIVATIVE_NODES`` nodes in all: a product of 900 sines
is refused in about a second instead of after 30 s of differentiation.

The Hessian of abs(f) contains sympy's DiracDelta(f): it is replaced by 0, the derivative
almost everywhere (hess_H only builds the Newton iteration matrix, docs/solver.md).

The functions are compiled with ``error_model="numpy"``: a division by zero gives inf or
NaN (which the kernel reports as a non-finite failure at that step) instead of raising a
Python exception through the kernel, and saves the zero tests.

Parameters are read at run time from ``params[i]``, names sorted alphabetically; their values
are not in the code or the hash, so a parameter scan compiles once. The cost is nil:
a load from ``params`` is what the built-ins do, and the generated Kepler runs as fast as
the built-in one. Measured on this machine (2 shared cores, ``bench/user_problem.py``), Kepler
of ``configs/kepler_expressions.yaml`` loaded in a fresh process: cold (sympy import,
differentiation, cse, Numba compile of the four functions) 0.7-0.8 s; warm 0.03 s (no sympy,
four Numba cache hits); kernel time, EHBVM(12,3) over 10^4 steps: 0.97-0.98 x the built-in.
"""
from __future__ import annotations

import ast
import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .. import cache
from .base import Problem, invariant_name_clash
from .expressions import (ExpressionError, ProblemDefinitionError, canonical, check_name, did_you_mean,
                          evaluate_number, kinked_functions, node_count, non_ascii, parse, polynomial_degree, to_sympy)

GENERATOR_VERSION = 4   # 2: hess_H; 3: zero entries by a fill; 4: a few zeros one by one. Part of the cache key
#                         and of the generated text.
EXPLICIT_ZEROS = 32     # zero entries of a matrix written one by one; more: a fill of the whole matrix first
MODULE_PREFIX = "elimfast_generated_"   # + the file's name (its content's hash): the name a generated module has
FUNCTIONS = ("H", "grad_H", "hess_H", "invariants", "grad_invariants")   # what a generated module defines
# Bounds of the symbolic work (issue 9, point 6). Measured here: sympy differentiates about
# 45,000 nodes/s and cse handles about 100,000 nodes/s, so MAX_DERIVATIVE_NODES keeps an
# accepted problem under about 10 s of sympy; the estimate of a derivative's size is at
# or above sympy's result, within about 2x on large products. Building the sympy trees
# from MAX_TOTAL_NODES nodes of expressions takes about 3 s. The shipped example is far
# below: configs/kepler_expressions.yaml has 75 nodes and 439 estimated derivative nodes
# (sympy's derivatives have 231).
MAX_INVARIANTS = 64
MAX_TOTAL_NODES = 20_000          # expression nodes of H and all invariants together
MAX_DERIVATIVE_NODES = 300_000    # estimated nodes of grad H, hess H and the invariants' gradients
_GENERATED_NAME = re.compile(r"p_[0-9a-f]{64}\.py\Z")
_INVARIANT_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*\Z")
_MODULES: dict[str, object] = {}   # generated file path -> imported module, for this process

# sympy functions the printer knows (everything differentiation of the allowed functions yields)
_PRINTABLE_FUNCTIONS = {"exp", "log", "sin", "cos", "tan", "sinh", "cosh", "tanh", "asin", "acos", "atan",
                        "atan2", "Abs", "sign"}


def problem_from_expressions(coordinates: Mapping[str, Sequence[str]], hamiltonian: str,
                             invariants: Mapping[str, str] | None = None,
                             parameters: Mapping[str, float | str] | None = None,
                             initial: Mapping[str, float | str] | None = None,
                             name: str = "user", description: str = "", time_scale: str | None = None,
                             check: bool = True) -> Problem:
    """A Problem from expression strings.

    coordinates: {'q': [names], 'p': [names]} (m each); hamiltonian: H(q, p, parameters);
    invariants: {name: expression} (the problem's L_i, in this order); parameters:
    {name: value} (numbers or numeric strings such as 'pi/3'), passed as params[i] in
    alphabetical order of the names;
    initial: {coordinate: value} for every coordinate (values may use the parameters);
    time_scale: an expression for the local time scale sigma(y) of the motion (the
    time-reversible step control of docs/adaptive.md), e.g. "(q1**2 + q2**2)**0.75".
    check: test that each invariant is conserved by the flow of H at seeded points around the initial state
    (problems/check.py, as a config's problem.check does), InvariantCheckError if not: imposing
    one that is not makes no method keep it (the gradients come from the expressions, so they
    need no check).
    Raises ProblemDefinitionError / ExpressionError (``.key`` says which entry is wrong).
    """
    q_names, p_names = _coordinate_names(coordinates)
    coordinate_names = q_names + p_names
    parameters = dict(parameters or {})
    if not isinstance(parameters, dict):
        raise ProblemDefinitionError("parameters must be a mapping name -> value", key="parameters")
    param_names = []
    param_values = {}
    # Sorted: the params vector and the generated code do not depend on the mapping's order.
    for pname, value in sorted(parameters.items(), key=lambda item: str(item[0])):
        _checked(check_name, pname, "parameter name", key="parameters")
        if pname in coordinate_names:
            raise ProblemDefinitionError(f"parameter {pname!r} has the name of a coordinate; rename one of them",
                                         key=f"parameters.{pname}")
        param_values[pname] = _checked(evaluate_number, value, what=f"parameter {pname}",
                                       key=f"parameters.{pname}")
        param_names.append(pname)
    declared = tuple(coordinate_names) + tuple(param_names)

    if not isinstance(hamiltonian, str):
        raise ProblemDefinitionError(f"the Hamiltonian must be an expression string, got {hamiltonian!r}",
                                     key="hamiltonian")
    H_tree = _checked(parse, hamiltonian, declared, what="hamiltonian", key="hamiltonian")
    invariants = invariants or {}
    if not isinstance(invariants, Mapping):
        raise ProblemDefinitionError("invariants must be a mapping name -> expression", key="invariants")
    if len(invariants) > MAX_INVARIANTS:
        raise ProblemDefinitionError(f"{len(invariants)} invariants are too many (at most {MAX_INVARIANTS}); declare "
                                     "only those to impose or monitor, or write the problem as a python: file",
                                     key="invariants")
    invariant_trees = []
    for iname, text in invariants.items():
        if isinstance(iname, str) and non_ascii(iname):
            raise ProblemDefinitionError(f"invariant name {iname!r} contains the non-ASCII character "
                                         f"{non_ascii(iname)}; use ASCII letters, digits and '_'", key="invariants")
        if not isinstance(iname, str) or not _INVARIANT_NAME.match(iname) or iname == "H":
            raise ProblemDefinitionError(f"invariant name {iname!r} is not allowed: use letters, digits and '_', "
                                         "starting with a letter, and not 'H' (always conserved)", key="invariants")
        if invariant_name_clash(iname):
            raise ProblemDefinitionError(invariant_name_clash(iname), key="invariants")
        if not isinstance(text, str):
            raise ProblemDefinitionError(f"invariant {iname} must be an expression string, got {text!r}",
                                         key=f"invariants.{iname}")
        invariant_trees.append((iname, text, _checked(parse, text, declared, what=f"invariant {iname}",
                                                      key=f"invariants.{iname}")))

    total = node_count(H_tree) + sum(node_count(tree) for _, _, tree in invariant_trees)
    if total > MAX_TOTAL_NODES:
        raise ProblemDefinitionError(f"the Hamiltonian and invariants have {total} terms in all (at most "
                                     f"{MAX_TOTAL_NODES}); simplify them, or write the problem as a python: file",
                                     key="invariants" if invariant_trees else "hamiltonian")
    y0 = _initial_state(initial, coordinate_names, param_values)

    spec = {"q": q_names, "p": p_names, "parameters": param_names, "H": canonical(H_tree),
            "invariants": [[iname, canonical(tree)] for iname, _, tree in invariant_trees]}
    key = cache.content_hash(f"expressions-v{GENERATOR_VERSION}", json.dumps(spec, sort_keys=True))
    module = _load_by_key(key)
    if module is None:
        source = generate_source(q_names, p_names, param_names, (hamiltonian, H_tree),
                                 [(iname, text, tree) for iname, text, tree in invariant_trees], name=name)
        filename = f"p_{cache.content_hash(source)}.py"
        path = cache.problems_dir() / filename
        if not _is_intact(path):
            cache.write_atomic(path, source)
        cache.write_atomic(cache.keys_dir() / key, filename + "\n")
        module = _import(path)

    problem = Problem(
        name=name, q_names=q_names, p_names=p_names,
        H=module.H, grad_H=module.grad_H, hess_H=module.hess_H, hessian_source="symbolic",
        invariants=module.invariants, grad_invariants=module.grad_invariants,
        invariant_names=tuple(iname for iname, _, _ in invariant_trees),
        y0=y0, params=np.array([param_values[p] for p in param_names], dtype=np.float64),
        parameters=param_values, description=description or f"H = {' '.join(hamiltonian.split())}",
        hamiltonian_degree=polynomial_degree(H_tree, coordinate_names), hamiltonian_kinks=kinked_functions(H_tree),
    )
    if time_scale is not None:
        function = compile_state_functions(problem, {"time_scale": time_scale}, gradient=True, what="time scale",
                                           key_prefix="time_scale")
        problem = dataclasses.replace(problem, time_scale=function)
    if check and problem.invariant_names:
        # A user trial: a non-invariant imposed from Python ran, and the run's note blamed quadrature.
        from .check import PYTHON_SKIP, require_invariants
        require_invariants(problem, skip=PYTHON_SKIP)
    return problem


def _checked(function, *args, key, **kwargs):
    try:
        return function(*args, **kwargs)
    except ProblemDefinitionError as err:
        if err.key is None:
            err.key = key
        raise


def _coordinate_names(coordinates) -> tuple[tuple[str, ...], tuple[str, ...]]:
    if not isinstance(coordinates, Mapping) or set(coordinates) != {"q", "p"}:
        raise ProblemDefinitionError("coordinates must be {q: [names], p: [names]}", key="coordinates")
    names = {}
    for side in ("q", "p"):
        entries = coordinates[side]
        if isinstance(entries, str) or not isinstance(entries, Sequence) or not entries:
            raise ProblemDefinitionError(f"coordinates.{side} must be a non-empty list of names",
                                         key=f"coordinates.{side}")
        for entry in entries:
            _checked(check_name, entry, "coordinate name", key=f"coordinates.{side}")
        names[side] = tuple(entries)
    if len(names["q"]) != len(names["p"]):
        raise ProblemDefinitionError(f"{len(names['q'])} q names but {len(names['p'])} p names: each q needs "
                                     "its conjugate momentum", key="coordinates")
    everything = names["q"] + names["p"]
    duplicates = sorted({n for n in everything if everything.count(n) > 1})
    if duplicates:
        raise ProblemDefinitionError(f"coordinate name(s) used twice: {', '.join(duplicates)}", key="coordinates")
    return names["q"], names["p"]


def _initial_state(initial, coordinate_names, param_values) -> np.ndarray:
    initial = initial if initial is not None else {}
    if not isinstance(initial, Mapping):
        raise ProblemDefinitionError("initial must be a mapping coordinate -> value", key="initial")
    for cname in initial:
        if cname not in coordinate_names:
            hint = did_you_mean(str(cname), coordinate_names)
            raise ProblemDefinitionError(f"{cname!r} is not a coordinate{hint} (coordinates: "
                                         f"{', '.join(coordinate_names)})", key=f"initial.{cname}")
    missing = [c for c in coordinate_names if c not in initial]
    if missing:
        raise ProblemDefinitionError(f"no initial value for {', '.join(missing)}; give every coordinate a value",
                                     key="initial")
    return np.array([_checked(evaluate_number, initial[c], param_values, what=f"initial value of {c}",
                              key=f"initial.{c}") for c in coordinate_names])


# --- the cache -----------------------------------------------------------------------------

def _is_intact(path: Path) -> bool:
    """The file exists and its content still hashes to its name (not truncated or edited)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return False
    return path.name == f"p_{cache.content_hash(text)}.py"


def _load_by_key(key: str):
    try:
        filename = (cache.cache_dir() / cache.KEYS_SUBDIR / key).read_text(encoding="utf-8").strip()
    except (OSError, UnicodeDecodeError):
        return None
    if not _GENERATED_NAME.match(filename):
        return None
    path = cache.cache_dir() / cache.PROBLEMS_SUBDIR / filename
    if str(path) in _MODULES:
        return _MODULES[str(path)]
    if not _is_intact(path):
        return None
    module = _import(path)
    # The key includes GENERATOR_VERSION, so this holds; checked anyway, as a file lacking
    # a function would fail only when the solver calls it.
    return module if all(hasattr(module, name) for name in FUNCTIONS) else None


def _import(path: Path):
    if str(path) in _MODULES:
        return _MODULES[str(path)]
    try:
        module = cache.import_file(path, f"{MODULE_PREFIX}{path.stem}")
    except Exception as err:
        from numba.core.errors import NumbaError
        if isinstance(err, NumbaError):
            detail = " ".join(str(err).split())[:300]
            raise ProblemDefinitionError(f"the code generated from the expressions does not compile ({detail}); "
                                         f"this is an elimfast bug: please report it with the expressions "
                                         f"(generated file: {path})") from None
        raise
    _MODULES[str(path)] = module
    cache.kernel_folder_used(in_package=False)   # its compiled code is in elimfast's cache (cache.py)
    return module


# --- code generation -----------------------------------------------------------------------

def generate_source(q_names, p_names, param_names, hamiltonian, invariants, name: str = "user") -> str:
    """Python source of H, grad_H, hess_H, invariants, grad_invariants for the validated trees.

    hamiltonian: (text, tree); invariants: [(name, text, tree)]. Coordinates are read
    from y[i] (q then p), parameters from params[i]; user names become ``v_<name>``
    locals and common subexpressions ``t<n>``, so no user name can clash with the code.
    Raises ExpressionError before differentiating when the derivatives would exceed
    MAX_DERIVATIVE_NODES (module docstring).
    """
    import sympy

    from .. import __version__

    coordinate_names = tuple(q_names) + tuple(p_names)
    symbols = {n: sympy.Symbol(n, real=True) for n in (*coordinate_names, *param_names)}
    variables = [symbols[n] for n in coordinate_names]
    h_text, h_tree = hamiltonian
    H = to_sympy(h_tree, symbols, what="hamiltonian", text=h_text)
    L = []
    for iname, text, tree in invariants:
        try:
            L.append(to_sympy(tree, symbols, what=f"invariant {iname}", text=text))
        except ExpressionError as err:
            err.key = err.key or f"invariants.{iname}"
            raise
    n = len(coordinate_names)

    # Estimated sizes first (cheap), then the derivatives, each within the budget.
    budget = _DerivativeBudget()
    budget.add("the derivatives of the hamiltonian", "hamiltonian",
               sum(sum(sizes.values()) for sizes in _derivative_sizes([H], variables)))
    budget.add("the derivatives of the invariants", "invariants",
               sum(sum(sizes.values()) for sizes in _derivative_sizes(L, variables)))
    grad_H = [sympy.diff(H, v) for v in variables]
    grad_L = [[sympy.diff(f, v) for v in variables] for f in L]
    _require_closed_form(grad_H, variables, "the derivative of the hamiltonian", "hamiltonian", h_text)
    for (iname, text, _), row in zip(invariants, grad_L):
        _require_closed_form(row, variables, f"the derivative of invariant {iname}", f"invariants.{iname}", text)
    upper = [(i, j) for i in range(n) for j in range(i, n)]
    gradient_sizes = _derivative_sizes(grad_H, variables)
    budget.add("the second derivatives of the hamiltonian (for hess_H)", "hamiltonian",
               sum(gradient_sizes[i].get(variables[j], 0) for i, j in upper))
    # d^2/dx^2 abs(x) = 2 DiracDelta(x): 0 almost everywhere (module docstring)
    hess_H = [sympy.diff(grad_H[i], variables[j]).replace(lambda e: isinstance(e, sympy.DiracDelta),
                                                          lambda e: sympy.S.Zero) for i, j in upper]
    _require_closed_form(hess_H, [f"{variables[i]} and {variables[j]}" if i != j else f"{variables[i]} twice"
                                  for i, j in upper],
                         "the second derivative of the hamiltonian (for the Newton solver)", "hamiltonian", h_text)

    local = {symbols[n]: f"y[{i}]" for i, n in enumerate(coordinate_names)}
    local.update({symbols[n]: f"params[{i}]" for i, n in enumerate(param_names)})
    printer = _NumbaPrinter({s: f"v_{s.name}" for s in symbols.values()})

    def body(exprs, targets, key):
        return _body_lines(exprs, targets, key, symbols, local, printer)

    h_body = body([H], ["return "], "hamiltonian")
    g_body = body(grad_H, [f"out[{i}] = " for i in range(n)], "hamiltonian")
    def sparse_body(exprs, entries, key, symmetric=False):
        # Every entry is written: a zero fill, then the nonzero ones. A chain's Hessian is mostly
        # zeros, and one line each made a function whose compilation grew with the square of its
        # size (a user trial: an FPU chain of 12 masses written as expressions took 10 s, of 64 was
        # killed after 170 s at 2.8 GB).
        # A few zeros are written one by one instead: the fill's stores cannot be dropped by the
        # compiler (out might alias y), and Kepler's grad_invariants, all twelve entries nonzero,
        # spent a loop of twelve stores on each of the kernel's calls.
        # symmetric: entries are the upper triangle, and a zero there is a zero below it too.
        targets = [f"out[{i}, {j}] = " for i, j in entries]
        kept = [(target, expr) for target, expr in zip(targets, exprs) if expr != 0]
        zeros = [f"    out[{i}, {j}] = 0.0" for (i, j), expr in zip(entries, exprs) if expr == 0]
        zeros += [f"    out[{j}, {i}] = 0.0" for (i, j), expr in zip(entries, exprs) if expr == 0 and symmetric and i != j]
        fill = (zeros if len(zeros) <= EXPLICIT_ZEROS else
                ["    for i in range(out.shape[0]):", "        for j in range(out.shape[1]):",
                 "            out[i, j] = 0.0"])
        if not kept:
            return fill or ["    return"]
        return fill + body([e for _, e in kept], [target for target, _ in kept], key)

    hess_body = sparse_body(hess_H, upper, "hamiltonian", symmetric=True)
    hess_body += [f"    out[{j}, {i}] = out[{i}, {j}]" for (i, j), expr in zip(upper, hess_H)   # symmetric
                  if i != j and expr != 0]
    i_body = body(L, [f"out[{a}] = " for a in range(len(L))], "invariants") if L else ["    return"]
    gi_body = (sparse_body([d for row in grad_L for d in row], [(a, i) for a in range(len(L)) for i in range(n)],
                           "invariants")
               if L else ["    return"])

    doc = [f"elimfast {__version__}: problem {name!r}, generated from expressions; do not edit.",
           f"Generator version {GENERATOR_VERSION}. The file is named by the sha256 of its text and the elimfast "
           "version.",
           "",
           "y = (" + ", ".join(coordinate_names) + ")",
           "params = (" + ", ".join(param_names) + ")",
           f"H = {sympy.sstr(H)}"]
    doc += [f"{iname} = {sympy.sstr(f)}" for (iname, _, _), f in zip(invariants, L)]
    doc = [line.replace("\\", "\\\\").replace('"""', r'\"\"\"') for line in doc]
    out = ['"""' + doc[0], *doc[1:], '"""',
           "import math",
           "",
           "from numba import njit",
           "",
           "from elimfast.kernels.signatures import (GRAD_H_SIGNATURE, GRAD_INVARIANTS_SIGNATURE, H_SIGNATURE,",
           "                                         HESS_H_SIGNATURE, INVARIANTS_SIGNATURE)",
           "",
           "",
           "@njit(H_SIGNATURE, cache=True, error_model=\"numpy\")",
           "def H(y, params):", *h_body,
           "",
           "",
           "@njit(GRAD_H_SIGNATURE, cache=True, error_model=\"numpy\")",
           "def grad_H(y, params, out):", *g_body,
           "",
           "",
           "@njit(HESS_H_SIGNATURE, cache=True, error_model=\"numpy\")",
           "def hess_H(y, params, out):", *hess_body,
           "",
           "",
           "@njit(INVARIANTS_SIGNATURE, cache=True, error_model=\"numpy\")",
           "def invariants(y, params, out):", *i_body,
           "",
           "",
           "@njit(GRAD_INVARIANTS_SIGNATURE, cache=True, error_model=\"numpy\")",
           "def grad_invariants(y, params, out):", *gi_body,
           ""]
    return "\n".join(out)


def _require_closed_form(derivatives, variables, what, key, text) -> None:
    """A derivative sympy leaves unevaluated (d/dq re(sqrt(q)) in the derivative of abs(sqrt(q)),
    which it takes to be complex for q < 0) has no code: say so, naming the expression."""
    import sympy

    for derivative, variable in zip(derivatives, variables):
        if derivative.has(sympy.Derivative):
            raise ProblemDefinitionError(
                f"{what} ({text!r}) with respect to {variable} has no closed form for sympy "
                f"(it is complex where an argument of sqrt, log or a power is negative, e.g. abs(sqrt(q))); "
                f"rewrite it for the domain you integrate on, e.g. sqrt(abs(q)) or q**2 instead of abs(q)**2",
                key=key)


class _DerivativeBudget:
    """The running total of estimated derivative nodes, refused above MAX_DERIVATIVE_NODES."""

    def __init__(self):
        self.total = 0

    def add(self, what: str, key: str, estimate: int) -> None:
        self.total += estimate
        if self.total > MAX_DERIVATIVE_NODES:
            others = f", {self.total:,} with the others" if self.total != estimate else ""
            raise ExpressionError(f"{what} have about {estimate:,} terms{others} (at most {MAX_DERIVATIVE_NODES:,} "
                                  "in all, estimated before differentiating); simplify "
                                  "the expressions (fewer factors that depend on the same coordinate), or write the "
                                  "problem as a python: file", key=key)


def _derivative_sizes(exprs, variables) -> list[dict]:
    """For each sympy expression, {v: estimated node count of d expr/dv} for the variables
    v it depends on, without differentiating.

    Node counts are those of ``sympy.preorder_traversal``; S is the size of a node, D_v
    the estimate of its derivative's. Rules (what sympy's diff builds):
    sum: 1 + sum of the D_v of its terms; product: one term per factor that depends on v,
    each the other factors and that factor's derivative (S - S_k + D_k); power b^x:
    x b^(x-1) b' (S_b + 2 S_x + D_b + 4) or, when x depends on v, b^x (x' log b + x b'/b);
    function f(args): f'(args) (at most 2 S + 8 nodes for the allowed functions) times D
    of each argument; atoms: 1 for v itself.
    """
    targets = frozenset(variables)
    memo: dict = {}

    def visit(expr):
        known = memo.get(expr)
        if known is not None:
            return known
        if not expr.args:
            result = (1, {expr: 1} if expr in targets else {})
        else:
            children = [visit(arg) for arg in expr.args]
            size = 1 + sum(child[0] for child in children)
            sizes: dict = {}
            if expr.is_Add:
                for _, child in children:
                    for v, d in child.items():
                        sizes[v] = sizes.get(v, 1) + d
            elif expr.is_Mul:
                for child_size, child in children:
                    for v, d in child.items():
                        sizes[v] = sizes.get(v, 1) + size - child_size + d
            elif expr.is_Pow:
                (base_size, base), (exponent_size, exponent) = children
                for v in base.keys() | exponent.keys():
                    if v in exponent:
                        sizes[v] = size + 2 * base_size + exponent_size + base.get(v, 0) + exponent[v] + 7
                    else:
                        sizes[v] = base_size + 2 * exponent_size + base[v] + 4
            else:
                for _, child in children:
                    for v, d in child.items():
                        sizes[v] = sizes.get(v, 1) + 2 * size + 8 + d
            result = (size, sizes)
        memo[expr] = result
        return result

    return [visit(expr)[1] for expr in exprs]


def _body_lines(exprs, targets, key, symbols, local, printer) -> list[str]:
    """The lines of a generated function's body: the inputs it uses (local: symbol -> y[i] or
    params[i]), common subexpressions (sympy.cse), then ``<target><expression>`` each."""
    import sympy

    for expr in exprs:
        _check_printable(expr, key)
    temporaries, reduced = sympy.cse(exprs, symbols=sympy.numbered_symbols("t"), order="none")
    used = set()
    for expr in [e for _, e in temporaries] + list(reduced):
        used |= expr.free_symbols
    lines = [f"    v_{s.name} = {local[s]}" for s in symbols.values() if s in used and s in local]
    lines += [f"    {printer.doprint(t)} = {printer.doprint(e)}" for t, e in temporaries]
    lines += [f"    {target}{printer.doprint(e)}" for target, e in zip(targets, reduced)]
    return lines


def _check_printable(expr, key) -> None:
    import sympy

    for node in sympy.preorder_traversal(expr):
        if isinstance(node, (sympy.Derivative, sympy.Integral, sympy.Subs)):   # unevaluated: no code
            raise ExpressionError(f"cannot generate code for the unevaluated {type(node).__name__} in "
                                  f"{sympy.sstr(expr)[:80]}", key=key)
        if isinstance(node, sympy.Function) and type(node).__name__ not in _PRINTABLE_FUNCTIONS:
            raise ExpressionError(f"cannot generate code for {type(node).__name__}(...) in {sympy.sstr(expr)[:80]}",
                                  key=key)
        if node.is_Number and not node.is_Rational and not math.isfinite(float(node)):
            raise ExpressionError(f"the constant {node} is not finite", key=key)


def _printer_base():
    from sympy.printing.pycode import PythonCodePrinter
    return PythonCodePrinter


class _NumbaPrinter:
    """sympy -> Python/Numba expression text: exact floats, powers as multiplications and sqrt."""

    def __init__(self, names):
        base = _printer_base()
        names_map = names

        class Printer(base):
            def _print_Symbol(self, expr):
                return names_map.get(expr, expr.name)

            def _print_Float(self, expr):
                return repr(float(expr))

            def _print_Rational(self, expr):
                return repr(float(expr))

            def _print_Integer(self, expr):
                return repr(float(expr)) if abs(int(expr)) > 2 ** 53 else str(int(expr))

            def _print_Exp1(self, expr):
                return "math.e"

            def _print_Pi(self, expr):
                return "math.pi"

            def _print_sign(self, expr):
                x = self._print(expr.args[0])
                return f"(0.0 if {x} == 0.0 else math.copysign(1.0, {x}))"

            def _print_Abs(self, expr):
                return f"abs({self._print(expr.args[0])})"

            def _print_Pow(self, expr, rational=False):
                base, exponent = expr.args
                b = self._print(base)
                if not (base.is_Symbol or (base.is_Number and base >= 0)):
                    b = f"({b})"
                if exponent.is_Integer or (exponent.is_Rational and exponent.q == 2):
                    twice = int(exponent * 2)
                    whole, half = divmod(abs(twice), 2)
                    factors = [b] * whole if whole <= 4 else [f"{b}**{whole}"]
                    if half:
                        factors.append(f"math.sqrt({self._print(base)})")
                    if not factors:
                        return "1.0"
                    product = "*".join(factors)
                    if twice < 0:
                        return f"(1.0/({product}))" if len(factors) > 1 else f"(1.0/{product})"
                    return f"({product})" if len(factors) > 1 else product
                return f"{b}**({self._print(exponent)})"

        self._printer = Printer({"fully_qualified_modules": True, "standard": "python3"})

    def doprint(self, expr) -> str:
        return self._printer.doprint(expr)


# --- functions of the state for a run: events and time scales ---------------------------------

FUNCTIONS_GENERATOR_VERSION = 1


def compile_state_functions(problem: Problem, expressions: Mapping[str, str], gradient: bool = False,
                            what: str = "event", key_prefix: str = "events"):
    """A compiled ``values(y, params, out)`` (the INVARIANTS signature) for expressions in the
    problem's coordinates: out[i] = the i-th expression; with ``gradient`` (one expression),
    out[0] = its value and out[1:] = its gradient with respect to y (a time scale,
    docs/adaptive.md). Numeric parameters of the problem may be used by name: their values
    are written into the code as constants (they are fixed for a run). Expressions are
    data: parsed and validated like a problem's (expressions.py). Compiled once per
    machine and cached by content, like the problems. Raises ExpressionError naming
    ``<key_prefix>.<name>``."""
    import sympy

    coordinate_names = tuple(problem.q_names) + tuple(problem.p_names)
    constants = {name: float(value) for name, value in problem.parameters.items()
                 if isinstance(value, (int, float)) and not isinstance(value, bool) and name not in coordinate_names}
    declared = coordinate_names + tuple(constants)
    trees = []
    def label(name):   # 'time scale', not 'time scale time_scale', for a lone expression named as its key
        return what if key_prefix == name else f"{what} {name}"

    for name, text in expressions.items():
        if not isinstance(text, str):
            raise ExpressionError(f"{label(name)} must be an expression string, got {text!r}",
                                  key=key_prefix if key_prefix == name else f"{key_prefix}.{name}")
        key = key_prefix if key_prefix == name else f"{key_prefix}.{name}"
        trees.append((name, text, _checked(parse, text, declared, what=label(name), key=key)))
    # Only the constants the expressions use: a parameter scan with an event on the state alone
    # compiles it once (a tester's eccentricity scan compiled the same event module per value).
    used = {node.id for _, _, tree in trees for node in ast.walk(tree) if isinstance(node, ast.Name)}
    constants = {name: value for name, value in constants.items() if name in used}
    spec = {"y": coordinate_names, "constants": sorted(constants.items()), "gradient": bool(gradient),
            "expressions": [[name, canonical(tree)] for name, _, tree in trees]}
    key = cache.content_hash(f"state-functions-v{FUNCTIONS_GENERATOR_VERSION}", json.dumps(spec, sort_keys=True))
    path = cache.problems_dir() / f"f_{key}.py"   # f_: functions of the state (cache.py counts them)
    if str(path) in _MODULES:
        return _MODULES[str(path)].values
    if not path.exists() or not _state_module_intact(path, key):
        symbols = {n: sympy.Symbol(n, real=True) for n in declared}
        exprs = []
        for name, text, tree in trees:
            # a value error found only here (sqrt(-1), q1/0) names the expression's key, as a parse error does
            expr = _checked(to_sympy, tree, symbols, what=label(name), text=text,
                            key=key_prefix if key_prefix == name else f"{key_prefix}.{name}")
            exprs.append(expr.subs({symbols[c]: sympy.Float(v, 17) for c, v in constants.items()}))
        targets = [f"out[{i}] = " for i in range(len(exprs))]
        if gradient:
            exprs = exprs[:1] + [sympy.diff(exprs[0], symbols[c]) for c in coordinate_names]
            targets = [f"out[{i}] = " for i in range(len(exprs))]
        printer = _NumbaPrinter({s: f"v_{s.name}" for s in symbols.values()})
        local = {symbols[n]: f"y[{i}]" for i, n in enumerate(coordinate_names)}
        body = _body_lines(exprs, targets, f"{key_prefix}.{trees[0][0] if trees else ''}", symbols, local, printer)
        source = "\n".join([
            f'"""elimfast: {what} functions generated from expressions; do not edit. Key {key}."""',
            "import math", "", "from numba import njit", "",
            "from elimfast.kernels.signatures import INVARIANTS_SIGNATURE", "", "",
            "@njit(INVARIANTS_SIGNATURE, cache=True, error_model=\"numpy\")",
            "def values(y, params, out):", *(body or ["    return"]), ""])
        cache.write_atomic(path, source)
    return _import(path).values


def _state_module_intact(path: Path, key: str) -> bool:
    try:
        return f"Key {key}." in path.read_text(encoding="utf-8").splitlines()[0]
    except (OSError, UnicodeDecodeError, IndexError):
        return False
