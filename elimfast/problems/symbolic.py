"""Problems from expressions: sympy gradients, generated Numba source, compiled once per machine.

``problem_from_expressions`` turns the expression strings of a config into a Problem
whose four functions have exactly the compiled signatures of ``kernels.signatures``,
so the kernels run them as fast as a hand-written built-in (``bench/user_problem.py``).

Pipeline (expressions are data, never code: see ``expressions.py``):

1. Parse and validate every expression (``ast`` whitelist).
2. Input key = sha256 of (elimfast version, coordinate and parameter names, the
   canonical form of each expression). If ``<cache>/keys/<key>`` names a generated
   file whose content still hashes to its name, import it: a warm load needs neither
   sympy nor any compilation (Numba's cache beside the file is valid).
3. Otherwise build sympy expressions node by node, differentiate, eliminate common
   subexpressions (``sympy.cse``), print Python source with ``@njit(<signature>,
   cache=True)`` functions, write it atomically to ``<cache>/problems/p_<sha256 of the
   source and version>.py``, record the key, and import it.

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

import importlib.util
import json
import math
import re
import sys
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from .. import cache
from .base import Problem
from .expressions import (ExpressionError, ProblemDefinitionError, canonical, check_name, did_you_mean,
                          evaluate_number, parse, to_sympy)

MAX_DERIVATIVE_NODES = 300_000   # bounds the time of cse and the size of the generated code
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
                             name: str = "user", description: str = "") -> Problem:
    """A Problem from expression strings.

    coordinates: {'q': [names], 'p': [names]} (m each); hamiltonian: H(q, p, parameters);
    invariants: {name: expression} (the problem's L_i, in this order); parameters:
    {name: value} (numbers or numeric strings such as 'pi/3'), passed as params[i] in
    alphabetical order of the names;
    initial: {coordinate: value} for every coordinate (values may use the parameters).
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
    invariant_trees = []
    for iname, text in invariants.items():
        if not isinstance(iname, str) or not _INVARIANT_NAME.match(iname) or iname == "H":
            raise ProblemDefinitionError(f"invariant name {iname!r} is not allowed: use letters, digits and '_', "
                                         "starting with a letter, and not 'H' (always conserved)", key="invariants")
        if not isinstance(text, str):
            raise ProblemDefinitionError(f"invariant {iname} must be an expression string, got {text!r}",
                                         key=f"invariants.{iname}")
        invariant_trees.append((iname, text, _checked(parse, text, declared, what=f"invariant {iname}",
                                                      key=f"invariants.{iname}")))

    y0 = _initial_state(initial, coordinate_names, param_values)

    spec = {"q": q_names, "p": p_names, "parameters": param_names, "H": canonical(H_tree),
            "invariants": [[iname, canonical(tree)] for iname, _, tree in invariant_trees]}
    key = cache.content_hash("expressions-v1", json.dumps(spec, sort_keys=True))
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

    return Problem(
        name=name, q_names=q_names, p_names=p_names,
        H=module.H, grad_H=module.grad_H, invariants=module.invariants, grad_invariants=module.grad_invariants,
        invariant_names=tuple(iname for iname, _, _ in invariant_trees),
        y0=y0, params=np.array([param_values[p] for p in param_names], dtype=np.float64),
        parameters=param_values, description=description or f"H = {' '.join(hamiltonian.split())}",
    )


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
    return _import(path)


def _import(path: Path):
    if str(path) in _MODULES:
        return _MODULES[str(path)]
    module_name = f"elimfast_generated_{path.stem}"
    spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as err:
        sys.modules.pop(module_name, None)
        from numba.core.errors import NumbaError
        if isinstance(err, NumbaError):
            detail = " ".join(str(err).split())[:300]
            raise ProblemDefinitionError(f"the code generated from the expressions does not compile ({detail}); "
                                         f"this is an elimfast bug: please report it with the expressions "
                                         f"(generated file: {path})") from None
        raise
    _MODULES[str(path)] = module
    return module


# --- code generation -----------------------------------------------------------------------

def generate_source(q_names, p_names, param_names, hamiltonian, invariants, name: str = "user") -> str:
    """Python source of H, grad_H, invariants, grad_invariants for the validated trees.

    hamiltonian: (text, tree); invariants: [(name, text, tree)]. Coordinates are read
    from y[i] (q then p), parameters from params[i]; user names become ``v_<name>``
    locals and common subexpressions ``t<n>``, so no user name can clash with the code.
    """
    import sympy

    from .. import __version__

    coordinate_names = tuple(q_names) + tuple(p_names)
    symbols = {n: sympy.Symbol(n, real=True) for n in (*coordinate_names, *param_names)}
    variables = [symbols[n] for n in coordinate_names]
    h_text, h_tree = hamiltonian
    H = to_sympy(h_tree, symbols, what="hamiltonian", text=h_text)
    grad_H = [sympy.diff(H, v) for v in variables]
    L = []
    for iname, text, tree in invariants:
        try:
            L.append(to_sympy(tree, symbols, what=f"invariant {iname}", text=text))
        except ExpressionError as err:
            err.key = err.key or f"invariants.{iname}"
            raise
    grad_L = [[sympy.diff(f, v) for v in variables] for f in L]
    for key, exprs in (("hamiltonian", grad_H), ("invariants", [d for row in grad_L for d in row])):
        size = 0
        for expr in exprs:
            size += sum(1 for _ in sympy.preorder_traversal(expr))
        if size > MAX_DERIVATIVE_NODES:
            raise ExpressionError(f"the derivatives of the {key} have {size} terms (at most {MAX_DERIVATIVE_NODES}); "
                                  "simplify the expressions, or write the problem as a python: file", key=key)

    local = {symbols[n]: f"y[{i}]" for i, n in enumerate(coordinate_names)}
    local.update({symbols[n]: f"params[{i}]" for i, n in enumerate(param_names)})
    printer = _NumbaPrinter({s: f"v_{s.name}" for s in symbols.values()})

    def body(exprs, targets, key):
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

    n = len(coordinate_names)
    h_body = body([H], ["return "], "hamiltonian")
    g_body = body(grad_H, [f"out[{i}] = " for i in range(n)], "hamiltonian")
    i_body = body(L, [f"out[{a}] = " for a in range(len(L))], "invariants") if L else ["    return"]
    gi_body = (body([d for row in grad_L for d in row],
                    [f"out[{a}, {i}] = " for a in range(len(L)) for i in range(n)], "invariants")
               if L else ["    return"])

    doc = [f"elimfast {__version__}: problem {name!r}, generated from expressions; do not edit.",
           "The file is named by the sha256 of its text and the elimfast version.",
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
           "                                         INVARIANTS_SIGNATURE)",
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
           "@njit(INVARIANTS_SIGNATURE, cache=True, error_model=\"numpy\")",
           "def invariants(y, params, out):", *i_body,
           "",
           "",
           "@njit(GRAD_INVARIANTS_SIGNATURE, cache=True, error_model=\"numpy\")",
           "def grad_invariants(y, params, out):", *gi_body,
           ""]
    return "\n".join(out)


def _check_printable(expr, key) -> None:
    import sympy

    for node in sympy.preorder_traversal(expr):
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
