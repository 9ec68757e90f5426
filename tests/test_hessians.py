"""hess_H of every problem (kernels.signatures: out (2m, 2m) = d^2 H/dy^2, q then p).

Each Hessian is compared with two independent references: central differences of the
problem's own grad_H (a naive loop here, not check.py), and sympy's exact Hessian of H
written out in this file, evaluated with 30 digits. Plus the interface the Newton solver
relies on: every compiled hess_H converts to ``HESS_H_TYPE``, writes every entry, and
is symmetric.
"""
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import sympy
from numba import njit, types

from elimfast import problems
from elimfast.kernels.signatures import HESS_H_SIGNATURE, HESS_H_TYPE, MATRIX, VECTOR, jit_hessian
from elimfast.problems.base import HESSIAN_SOURCES
from elimfast.problems.symbolic import problem_from_expressions
from elimfast.problems.user_file import problem_from_file

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
EPS = np.finfo(float).eps
EXACT_RTOL = 1e-13     # analytic vs sympy's exact Hessian: round-off of a few operations
FD_RTOL = 1e-6         # central differences with steps ~1e-5 of the scale: truncation ~1e-10


def three_body():
    return problems.nbody(masses=[1.0, 0.3, 0.1],
                          positions=[[0.0, 0.0, 0.0], [1.0, 0.2, 0.3], [-0.5, 1.6, -0.4]],
                          velocities=[[0.0, -0.1, 0.05], [0.1, 0.9, 0.3], [-0.6, -0.2, 0.35]], G=1.0)


CASES = {
    "kepler": lambda: problems.kepler(0.6),
    "kepler_e09": lambda: problems.kepler(0.9),
    "harmonic_oscillator": lambda: problems.harmonic_oscillator(1.7),
    "quartic_oscillator": lambda: problems.quartic_oscillator(),
    "central_quartic": lambda: problems.central_quartic(),
    "perturbed_kepler": lambda: problems.perturbed_kepler(0.6, 0.03),
    "henon_heiles": lambda: problems.henon_heiles(),
    "fpu_beta_periodic": lambda: problems.fpu_beta(5, 0.7),
    "fpu_beta_periodic_2": lambda: problems.fpu_beta(2, 0.7),   # two springs join the same pair
    "fpu_beta_fixed": lambda: problems.fpu_beta(5, 0.7, boundary="fixed"),
    "fpu_beta_fixed_2": lambda: problems.fpu_beta(2, 0.7, boundary="fixed"),
    "toda_3": lambda: problems.toda(3),
    "toda_5": lambda: problems.toda(5),
    "nbody_solar_system": lambda: problems.nbody(),
    "nbody_three_body": three_body,
    "pendulum": lambda: problems.pendulum(1.3),
}


@pytest.fixture(scope="module", params=list(CASES))
def case(request):
    return CASES[request.param]()


def points_near_y0(problem, seed, count=4):
    """(y0 and seeded points within ~5% of it per component, the per-component scales):
    a component's scale is max(|y0_i|, the rms of its block q or p)."""
    rng = np.random.default_rng(seed)
    y0 = problem.y0
    m = y0.size // 2
    block = np.concatenate([np.full(m, math.sqrt(np.mean(y0[s] ** 2)) or 1.0) for s in (slice(0, m), slice(m, None))])
    scales = np.maximum(np.abs(y0), block)
    return [y0.copy()] + [y0 + 0.05 * scales * rng.standard_normal(y0.size) for _ in range(count)], scales


# --- the interface -----------------------------------------------------------------------

def test_signature_names_for_the_newton_solver():
    assert HESS_H_SIGNATURE == types.void(VECTOR, VECTOR, MATRIX)
    assert HESS_H_TYPE == types.FunctionType(HESS_H_SIGNATURE)
    assert set(HESSIAN_SOURCES) == {"analytic", "symbolic", "user", "finite differences"}


@njit(types.void(HESS_H_TYPE, VECTOR, VECTOR, MATRIX), cache=False)
def _call_through_function_type(hess_H, y, params, out):
    hess_H(y, params, out)


def test_every_hessian_is_complete_symmetric_and_callable_as_hess_h_type(case):
    """A kernel receiving HESS_H_TYPE (as the Newton solver does) gets the same matrix; every
    entry is written (out starts as NaN) and the matrix is exactly symmetric."""
    assert case.hessian_source == "analytic"
    n = case.y0.size
    for y in points_near_y0(case, seed=3)[0]:
        out = np.full((n, n), np.nan)
        _call_through_function_type(case.hess_H, y, case.params, out)
        assert not np.isnan(out).any()
        np.testing.assert_array_equal(out, out.T)
        np.testing.assert_array_equal(out, case.hessian(y))


def test_hessians_match_central_differences_of_grad_h(case):
    points, scales = points_near_y0(case, seed=1)
    n = case.y0.size
    for y in points:
        hessian = case.hessian(y)
        for j in range(n):
            step = 1e-5 * scales[j]
            plus, minus = y.copy(), y.copy()
            plus[j] += step
            minus[j] -= step
            g_plus, g_minus = case.gradient(plus), case.gradient(minus)
            column = (g_plus - g_minus) / (plus[j] - minus[j])
            rounding = 1e3 * EPS * np.maximum(np.abs(g_plus), np.abs(g_minus)) / step
            tolerance = FD_RTOL * np.max(np.abs(hessian[:, j])) + rounding
            bad = np.flatnonzero(np.abs(column - hessian[:, j]) > tolerance)
            assert bad.size == 0, (case.name, j, bad, hessian[bad, j], column[bad])


# --- against sympy ---------------------------------------------------------------------------

def _symbols(n):
    return sympy.symbols(f"y0:{n}", real=True)


def _sympy_H(name, problem):
    """H of the built-in as a sympy expression of y0..y(2m-1), from its documented formula."""
    n = problem.y0.size
    m = n // 2
    y = _symbols(n)
    q, p = y[:m], y[m:]
    kinetic = sum(pi ** 2 for pi in p) / 2
    params = [sympy.Float(float(v), 30) for v in problem.params]
    if name.startswith("kepler"):
        return y, kinetic - 1 / sympy.sqrt(q[0] ** 2 + q[1] ** 2)
    if name == "harmonic_oscillator":
        return y, kinetic + params[0] ** 2 * q[0] ** 2 / 2
    if name == "quartic_oscillator":
        return y, kinetic + q[0] ** 4 / 4
    if name == "central_quartic":
        return y, kinetic + (q[0] ** 2 + q[1] ** 2) ** 2 / 4
    if name == "perturbed_kepler":
        r = sympy.sqrt(q[0] ** 2 + q[1] ** 2)
        return y, kinetic - 1 / r - params[0] / (2 * r ** 3)
    if name == "henon_heiles":
        return y, kinetic + (q[0] ** 2 + q[1] ** 2) / 2 + q[0] ** 2 * q[1] - q[1] ** 3 / 3
    if name.startswith("fpu_beta"):
        beta = params[0]
        V = lambda r: r ** 2 / 2 + beta * r ** 4 / 4
        if "fixed" in name:
            chain = [0] + list(q) + [0]
            return y, kinetic + sum(V(chain[i + 1] - chain[i]) for i in range(m + 1))
        return y, kinetic + sum(V(q[(i + 1) % m] - q[i]) for i in range(m))
    if name.startswith("toda"):
        return y, kinetic + sum(sympy.exp(q[i] - q[(i + 1) % m]) for i in range(m))
    if name.startswith("nbody"):
        G, masses = params[0], params[1:]
        bodies = m // 3
        kinetic = sum((p[3 * i] ** 2 + p[3 * i + 1] ** 2 + p[3 * i + 2] ** 2) / (2 * masses[i]) for i in range(bodies))
        potential = sum(masses[i] * masses[j] / sympy.sqrt(sum((q[3 * i + c] - q[3 * j + c]) ** 2 for c in range(3)))
                        for i in range(bodies) for j in range(i + 1, bodies))
        return y, kinetic - G * potential
    if name == "pendulum":
        return y, kinetic - params[0] ** 2 * sympy.cos(q[0])
    raise KeyError(name)


@pytest.mark.parametrize("name", [n for n in CASES if n != "nbody_solar_system"])
def test_hessians_match_sympys_exact_hessian(name):
    problem = CASES[name]()
    y_symbols, H = _sympy_H(name, problem)
    exact = sympy.lambdify(y_symbols, sympy.hessian(H, y_symbols), modules="mpmath")
    import mpmath
    mpmath.mp.dps = 30
    for y in points_near_y0(problem, seed=5, count=2)[0]:
        reference = np.array(exact(*[mpmath.mpf(float(v)) for v in y]).tolist(), dtype=float)
        np.testing.assert_allclose(problem.hessian(y), reference, rtol=EXACT_RTOL,
                                   atol=EXACT_RTOL * np.max(np.abs(reference)), err_msg=name)


def test_solar_system_hessian_matches_sympy_in_its_own_units():
    """The solar system's entries span 1e-15 (planet-planet q blocks) to 1e8 (Pluto's 1/m):
    compared block by block, each relative to its own size."""
    problem = problems.nbody()
    y_symbols, H = _sympy_H("nbody", problem)
    exact = sympy.lambdify(y_symbols, sympy.hessian(H, y_symbols), modules="mpmath")
    import mpmath
    mpmath.mp.dps = 30
    reference = np.array(exact(*[mpmath.mpf(float(v)) for v in problem.y0]).tolist(), dtype=float)
    hessian = problem.hessian(problem.y0)
    for a in range(12):
        for b in range(12):
            block = (slice(3 * a, 3 * a + 3), slice(3 * b, 3 * b + 3))
            size = np.max(np.abs(reference[block]))
            np.testing.assert_allclose(hessian[block], reference[block], rtol=0, atol=EXACT_RTOL * size)


# --- expression problems: sympy's Hessian, generated ------------------------------------------

@pytest.fixture()
def cache_root(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(root))
    return root


def test_generated_hessian_matches_sympy_for_every_allowed_function(cache_root):
    H_text = ("p1**2/2 + p2**4/4 + sin(q1)*cos(p1) + tan(q1/3) + sinh(p2/2) + cosh(q2/2) + tanh(p1)"
              " + asin(q1/3) + arccos(p2/3) + atan(q1*p1) + arctan(q2) + atan2(q1, 2 + p1) + abs(q1 - p2)**3"
              " + exp(-p1**2)*log(2 + q2**2) + sqrt(3 + p1**2) + (2 + q1**2)**(1/3) + (1 + q2**2)**(-3/2)"
              " + q1**7 + 1/(1 + q2**2)**5 + a*pi*e*0.1*q2*p2 + 2**q1 + q2**(p1**2 + 1)")
    problem = problem_from_expressions({"q": ["q1", "q2"], "p": ["p1", "p2"]}, H_text, parameters={"a": "pi/7"},
                                       initial={"q1": 0.3, "q2": 0.7, "p1": -0.4, "p2": 0.2})
    assert problem.hessian_source == "symbolic"
    names = ["q1", "q2", "p1", "p2"]
    symbols = {n: sympy.Symbol(n, real=True) for n in names + ["a"]}
    H = sympy.parse_expr(H_text.replace("arccos", "acos").replace("arctan", "atan"),
                         local_dict={**symbols, "e": sympy.E, "pi": sympy.pi})   # the test's own trusted text
    exact = sympy.hessian(H, [symbols[n] for n in names])
    rng = np.random.default_rng(2)
    for y in [problem.y0] + [problem.y0 + 0.1 * rng.standard_normal(4) for _ in range(4)]:
        point = {symbols[k]: sympy.Float(v, 30) for k, v in zip(names, y.tolist())}
        point[symbols["a"]] = sympy.pi / 7
        reference = np.array(exact.evalf(30, subs=point).tolist(), dtype=float)
        hessian = problem.hessian(y)
        np.testing.assert_array_equal(hessian, hessian.T)
        np.testing.assert_allclose(hessian, reference, rtol=1e-12, atol=1e-13)


def test_the_hessian_of_abs_is_zero_at_its_kink(cache_root):
    """d^2|q|/dq^2 = 2 DiracDelta(q): the generated code uses 0, the derivative almost everywhere."""
    problem = problem_from_expressions({"q": ["q"], "p": ["p"]}, "p**2/2 + abs(q) + q**2", initial={"q": 0, "p": 1})
    for q in (0.0, 0.3, -0.3):
        np.testing.assert_array_equal(problem.hessian([q, 0.5]), [[2.0, 0.0], [0.0, 1.0]])


def test_user_kepler_hessian_by_expressions_equals_the_builtin(cache_root):
    problem = problem_from_expressions({"q": ["q1", "q2"], "p": ["p1", "p2"]},
                                       "(p1**2 + p2**2)/2 - 1/sqrt(q1**2 + q2**2)",
                                       initial={"q1": 0.4, "q2": 0.0, "p1": 0.0, "p2": 2.0})
    builtin = problems.kepler(0.6)
    for y in points_near_y0(builtin, seed=4)[0]:
        np.testing.assert_allclose(problem.hessian(y), builtin.hessian(y), rtol=1e-14, atol=1e-14)


def test_a_chain_by_expressions_writes_only_its_nonzero_second_derivatives(cache_root):
    """A user trial: an FPU chain written as expressions compiled for 10 s at 12 masses and was killed
    after 170 s (2.8 GB) at 64: its generated hess_H wrote every one of the n(n+1)/2 entries, most of
    them zero, one line each. The entries are now a zero fill and the nonzero ones (3 per mass in
    the q block, 1 in the p block): the same Hessian as the built-in chain, and the same gradients
    of the invariants, in code whose size grows like n."""
    from elimfast import cache
    masses = 12
    q = [f"q{i}" for i in range(1, masses + 1)]
    p = [f"p{i}" for i in range(1, masses + 1)]
    springs = " + ".join(f"({q[(i + 1) % masses]} - {q[i]})**2/2 + ({q[(i + 1) % masses]} - {q[i]})**4/4"
                         for i in range(masses))
    problem = problem_from_expressions({"q": q, "p": p}, " + ".join(f"{x}**2/2" for x in p) + " + " + springs,
                                       invariants={"momentum": " + ".join(p)},
                                       initial={name: 0.1 * i for i, name in enumerate(q + p)})
    builtin = problems.fpu_beta(masses, 1.0, "periodic")
    rng = np.random.default_rng(7)
    for _ in range(3):
        y = rng.normal(size=2 * masses)
        np.testing.assert_allclose(problem.hessian(y), builtin.hessian(y), rtol=1e-14, atol=1e-14)
        mine, theirs = np.zeros((1, 2 * masses)), np.zeros((1, 2 * masses))
        problem.grad_invariants(y, problem.params, mine)
        builtin.grad_invariants(y, builtin.params, theirs)
        np.testing.assert_array_equal(mine, theirs)
    source = max(cache.problems_dir().glob("p_*.py"), key=lambda path: path.stat().st_mtime).read_text()
    hessian = source.split("def hess_H(y, params, out):")[1].split("def invariants")[0]
    assignments = [line for line in hessian.splitlines() if line.strip().startswith("out[")]
    assert "out[i, j] = 0.0" in hessian and not any(line.rstrip().endswith("= 0") for line in assignments)
    assert len(assignments) <= 5 * masses + 2 * masses   # q block: diagonal and one neighbour (mirrored); p block


# --- python: files: their own hess_H, or central differences of grad_H -----------------------------

KEPLER_FILE = (CONFIGS / "kepler_problem.py").read_text()
KEPLER_HESSIAN = '''

def hess_H(y, params, out):
    mu = params[0]
    r2 = y[0] * y[0] + y[1] * y[1]
    mu_r3 = mu / (r2 * math.sqrt(r2))
    mu_r5 = mu_r3 / r2
    for i in range(4):
        for j in range(4):
            out[i, j] = 0.0
    out[0, 0] = mu_r3 - 3.0 * y[0] * y[0] * mu_r5
    out[1, 1] = mu_r3 - 3.0 * y[1] * y[1] * mu_r5
    out[0, 1] = out[1, 0] = -3.0 * y[0] * y[1] * mu_r5
    out[2, 2] = out[3, 3] = 1.0
'''


def test_python_file_without_hess_h_gets_central_differences_of_grad_h(cache_root):
    problem = problem_from_file(CONFIGS / "kepler_problem.py")
    assert problem.hessian_source == "finite differences"
    assert problem.hessian_description.startswith("finite differences of grad_H")
    assert problem.source_file == str((CONFIGS / "kepler_problem.py").resolve())
    builtin = problems.kepler(0.6)
    for y in points_near_y0(builtin, seed=6)[0] + [np.array([0.05, 0.02, 3.0, -1.0])]:   # near the singularity too
        hessian = problem.hessian(y)
        np.testing.assert_array_equal(hessian, hessian.T)                                  # symmetrised
        reference = builtin.hessian(y)
        # Truncation ~ (step/r)^2 relative, step = eps^(1/3) max(|y_j|, 1), r = |q| the scale of
        # variation of grad H; rounding ~ eps^(2/3) ~ 4e-11. 10x both.
        r = math.hypot(y[0], y[1])
        tolerance = 10.0 * ((EPS ** (1 / 3) / r) ** 2 + EPS ** (2 / 3)) * np.max(np.abs(reference))
        np.testing.assert_allclose(hessian, reference, rtol=0, atol=tolerance)
    out = np.full((4, 4), np.nan)
    _call_through_function_type(problem.hess_H, problem.y0.copy(), problem.params, out)
    np.testing.assert_array_equal(out, problem.hessian(problem.y0))


def test_python_file_with_hess_h_uses_it(cache_root, tmp_path):
    path = tmp_path / "kepler_with_hessian.py"
    path.write_text(KEPLER_FILE + KEPLER_HESSIAN)
    problem = problem_from_file(path, parameters={"mu": 1.0})
    assert problem.hessian_source == "user"
    builtin = problems.kepler(0.6)
    for y in points_near_y0(builtin, seed=7)[0]:
        np.testing.assert_allclose(problem.hessian(y), builtin.hessian(y), rtol=1e-15, atol=1e-15)


def test_python_file_hess_h_that_leaves_entries_unwritten_is_refused(cache_root, tmp_path):
    from elimfast.problems.user_file import UserProblemError
    path = tmp_path / "partial.py"
    path.write_text(KEPLER_FILE + KEPLER_HESSIAN.replace("            out[i, j] = 0.0", "            pass"))
    with pytest.raises(UserProblemError, match=r"hess_H left out\[0, 2\] unwritten"):
        problem_from_file(path)


# --- the Problem fields ----------------------------------------------------------------------

def test_problem_fields_are_validated():
    kepler = problems.kepler()
    with pytest.raises(ValueError, match="hessian_source must be one of"):
        replace(kepler, hessian_source="numerical")
    with pytest.raises(ValueError, match="units must map"):
        replace(kepler, units={"length": 1.0})
    assert kepler.units == {} and kepler.source_file is None
    assert replace(kepler, units={"length": "m"}).units == {"length": "m"}


@jit_hessian
def _zero_hessian(y, params, out):
    out[:] = 0.0


def test_jit_hessian_compiles_with_the_signature():
    assert _zero_hessian.signatures == [HESS_H_SIGNATURE.args]


@pytest.mark.parametrize("n_masses", [2, 12])
def test_generated_matrices_write_every_entry_whatever_out_held(cache_root, n_masses):
    """The generated hess_H and grad_invariants write every entry, the zeros too: one by one when
    they are few (Kepler's grad_invariants has none, its Hessian 10; a fill of the whole matrix
    cost each kernel call a loop of stores), by a fill of the whole matrix when many (a chain of
    12 masses). Checked on out arrays full of NaN, against sympy's matrices."""
    q = [f"q{i}" for i in range(1, n_masses + 1)]
    p = [f"p{i}" for i in range(1, n_masses + 1)]
    H = " + ".join(f"{x}**2/2" for x in p) + " + " + " + ".join(
        f"({b} - {a})**4/4" for a, b in zip(q, q[1:])) + f" + {q[0]}**4/4"
    momentum = " + ".join(p)
    problem = problem_from_expressions({"q": q, "p": p}, H, invariants={"P": momentum, "Q": f"{q[0]}*{p[-1]}"},
                                       initial={**{x: 0.1 * i for i, x in enumerate(q)}, **{x: 0.3 for x in p}},
                                       check=False)   # Q is generated code to read, no invariant
    generated = problem.grad_H.py_func.__module__
    import sys
    source = open(sys.modules[generated].__spec__.origin).read()
    assert ("for i in range(out.shape[0])" in source) == (n_masses == 12)
    y = problem.y0.copy()
    n = y.size
    hessian = np.full((n, n), np.nan)
    problem.hess_H(y, problem.params, hessian)
    gradients = np.full((2, n), np.nan)
    problem.grad_invariants(y, problem.params, gradients)
    symbols = sympy.symbols(q + p)
    expr = sympy.sympify(H)
    exact_hessian = np.array(sympy.hessian(expr, symbols).subs(dict(zip(symbols, y))).evalf(), dtype=float)
    np.testing.assert_allclose(hessian, exact_hessian, rtol=1e-14, atol=1e-14)
    exact_gradients = np.array([[float(sympy.diff(sympy.sympify(f), s).subs(dict(zip(symbols, y)))) for s in symbols]
                                for f in (momentum, f"{q[0]}*{p[-1]}")])
    np.testing.assert_array_equal(gradients, exact_gradients)
