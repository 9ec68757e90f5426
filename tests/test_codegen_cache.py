"""User-defined problems: generated code is right, as fast to load as promised, cached on disk,
and a fresh process loading a seen problem compiles nothing."""
import json
import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import sympy

import elimfast
from elimfast import cache, problems
from elimfast.methods import ehbvm, gauss
from elimfast.problems.check import InvariantCheckError, check_invariants, require_invariants
from elimfast.problems.expressions import ProblemDefinitionError, evaluate, parse
from elimfast.problems.symbolic import problem_from_expressions
from elimfast.problems.user_file import UserProblemError, problem_from_file

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
KEPLER = dict(
    coordinates={"q": ["q1", "q2"], "p": ["p1", "p2"]},
    hamiltonian="(p1**2 + p2**2)/2 - mu/sqrt(q1**2 + q2**2)",
    invariants={"angular_momentum": "q1*p2 - q2*p1",
                "lrl_x": "p2*(q1*p2 - q2*p1) - mu*q1/sqrt(q1**2 + q2**2)",
                "lrl_y": "-p1*(q1*p2 - q2*p1) - mu*q2/sqrt(q1**2 + q2**2)"},
    parameters={"mu": 1.0},
    initial={"q1": 0.4, "q2": 0.0, "p1": 0.0, "p2": "sqrt(1.6/0.4)"},
    name="user_kepler",
)


@pytest.fixture()
def cache_root(tmp_path, monkeypatch):
    root = tmp_path / "cache"
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(root))
    return root


# --- the same trajectories as the built-in --------------------------------------------------

@pytest.mark.parametrize("source", ["expressions", "python"])
@pytest.mark.parametrize("method,conserve", [(ehbvm(12, 3), ("angular_momentum", "lrl_y")), (gauss(3), ())])
def test_user_kepler_gives_the_builtin_trajectory(cache_root, source, method, conserve):
    builtin = problems.kepler(0.6)
    user = (problem_from_expressions(**KEPLER) if source == "expressions"
            else problem_from_file(CONFIGS / "kepler_problem.py"))
    np.testing.assert_allclose(user.y0, builtin.y0, rtol=0, atol=1e-16)
    a = elimfast.integrate(builtin, method, 0.1, n_steps=100, conserve=conserve)
    b = elimfast.integrate(user, method, 0.1, n_steps=100, conserve=conserve)
    assert np.max(np.abs(a.y - b.y)) < 1e-13
    for name in ("H",) + builtin.invariant_names:
        assert np.max(np.abs(a.invariants[name] - b.invariants[name])) < 1e-13


def test_generated_functions_match_sympy_for_every_allowed_function(cache_root):
    H_text = ("p1**2/2 + p2**4/4 + sin(q1)*cos(p1) + tan(q1/3) + sinh(p2/2) + cosh(q2/2) + tanh(p1)"
              " + asin(q1/3) + arccos(p2/3) + atan(q1*p1) + arctan(q2) + atan2(q1, 2 + p1) + abs(q1 - p2)"
              " + exp(-p1**2)*log(2 + q2**2) + sqrt(3 + p1**2) + (2 + q1**2)**(1/3) + (1 + q2**2)**(-3/2)"
              " + q1**7 + 1/(1 + q2**2)**5 + a*pi*e*0.1*q2 + 2**q1 + q2**(p1**2 + 1)")
    problem = problem_from_expressions({"q": ["q1", "q2"], "p": ["p1", "p2"]}, H_text,
                                       invariants={"odd": "q1*p2 - q2*p1 + abs(p1)**3"},
                                       parameters={"a": "pi/7"}, initial={"q1": 0.3, "q2": 0.7, "p1": -0.4,
                                                                         "p2": 0.2}, name="all_functions",
                                       check=False)   # 'odd' is code to compare, no invariant
    names = ["q1", "q2", "p1", "p2"]
    symbols = {n: sympy.Symbol(n, real=True) for n in names + ["a"]}
    H = sympy.parse_expr(H_text.replace("arccos", "acos").replace("arctan", "atan"), local_dict={
        **symbols, "e": sympy.E, "pi": sympy.pi})   # the test's own reference, trusted text
    rng = np.random.default_rng(1)
    for y in [problem.y0] + [problem.y0 + 0.1 * rng.standard_normal(4) for _ in range(5)]:
        values = dict(zip(names, y.tolist()), a=math.pi / 7)
        point = {symbols[k]: sympy.Float(v, 30) for k, v in values.items()}
        exact_H = float(H.evalf(30, subs=point))
        assert problem.hamiltonian(y) == pytest.approx(exact_H, rel=1e-14)
        assert evaluate(parse(H_text, names + ["a"]), values) == pytest.approx(exact_H, rel=1e-14)
        exact_grad = [float(sympy.diff(H, symbols[n]).evalf(30, subs=point)) for n in names]
        np.testing.assert_allclose(problem.gradient(y), exact_grad, rtol=1e-13, atol=1e-15)
        L_grad = problem.invariant_gradients(y)[0]
        q1, q2, p1, p2 = y
        np.testing.assert_allclose(L_grad, [p2, -p1, 3 * p1 * abs(p1) - q2, q1], rtol=1e-14, atol=1e-15)


def test_problem_without_invariants_or_parameters(cache_root):
    pendulum = problem_from_expressions({"q": ["theta"], "p": ["omega"]}, "omega**2/2 - cos(theta)",
                                        initial={"theta": 1, "omega": 0})
    assert pendulum.invariant_names == () and pendulum.params.size == 0
    builtin = problems.pendulum(1.0)
    a = elimfast.integrate(builtin, gauss(2), 0.1, n_steps=50)
    b = elimfast.integrate(pendulum, gauss(2), 0.1, n_steps=50)
    assert np.max(np.abs(a.y - b.y)) < 1e-13


# --- the cache ------------------------------------------------------------------------------

def generated_files(root: Path):
    return sorted((root / cache.PROBLEMS_SUBDIR).glob("p_*.py"))


def test_generated_code_is_named_by_its_hash_and_reused(cache_root):
    problem = problem_from_expressions(**KEPLER)
    files = generated_files(cache_root)
    assert len(files) == 1
    assert files[0].name == f"p_{cache.content_hash(files[0].read_text())}.py"
    assert not list((cache_root / cache.PROBLEMS_SUBDIR).glob(".tmp*"))
    # Another parameter value, other spacing, other parameter order: the same code.
    other = problem_from_expressions(**{**KEPLER, "parameters": {"mu": 2.0},
                                        "hamiltonian": "( p1**2+p2**2 )/2 - mu/sqrt(q1**2+q2**2)"})
    assert generated_files(cache_root) == files
    assert other.H is problem.H and list(other.params) == [2.0]
    assert other.hamiltonian(other.y0) == pytest.approx(0.5 * 4.0 - 2.0 / 0.4)
    # A different expression: a new file.
    problem_from_expressions(**{**KEPLER, "invariants": {"angular_momentum": "q1*p2 - q2*p1"}})
    assert len(generated_files(cache_root)) == 2


def key_files(root: Path):
    return sorted((root / cache.KEYS_SUBDIR).iterdir())


def test_the_cache_key_and_file_change_with_the_generator_version(cache_root, monkeypatch):
    """Code generated by another generator version (e.g. before hess_H) is never loaded."""
    from elimfast.problems import symbolic
    problem_from_expressions(**KEPLER)
    (key,), (path,) = key_files(cache_root), generated_files(cache_root)
    assert f"Generator version {symbolic.GENERATOR_VERSION}." in path.read_text()
    monkeypatch.setattr(symbolic, "GENERATOR_VERSION", symbolic.GENERATOR_VERSION + 1)
    symbolic._MODULES.clear()                       # as in a new process
    problem_from_expressions(**KEPLER)
    assert len(key_files(cache_root)) == 2 and len(generated_files(cache_root)) == 2
    (new_path,) = set(generated_files(cache_root)) - {path}
    assert f"Generator version {symbolic.GENERATOR_VERSION}." in new_path.read_text()


def test_a_cached_module_without_hess_h_is_regenerated(cache_root):
    """Even if a key led to an intact file from an older generator, one lacking a function
    is not used: the problem is generated again."""
    from elimfast.problems import symbolic
    problem_from_expressions(**KEPLER)
    (key,), (path,) = key_files(cache_root), generated_files(cache_root)
    text = path.read_text()
    start = text.index('@njit(HESS_H_SIGNATURE')
    end = text.index('@njit(INVARIANTS_SIGNATURE')
    old_text = text[:start] + text[end:]                # as generator version 1 wrote it: no hess_H
    old_path = path.with_name(f"p_{cache.content_hash(old_text)}.py")
    old_path.write_text(old_text)
    key.write_text(old_path.name + "\n")
    symbolic._MODULES.clear()
    problem = problem_from_expressions(**KEPLER)
    assert problem.hessian_source == "symbolic"
    np.testing.assert_allclose(problem.hessian(problem.y0), problems.kepler(0.6).hessian(problem.y0), rtol=1e-14)
    assert key.read_text().strip() == path.name


def test_a_corrupted_cache_file_is_regenerated(cache_root):
    problem_from_expressions(**KEPLER)
    (path,) = generated_files(cache_root)
    path.write_text(path.read_text()[:200])       # truncated: its hash no longer matches its name
    from elimfast.problems import symbolic
    symbolic._MODULES.clear()                       # as in a new process
    problem = problem_from_expressions(**KEPLER)
    assert problem.hamiltonian(problem.y0) == pytest.approx(-0.5, abs=1e-15)
    assert path.name == f"p_{cache.content_hash(path.read_text())}.py"


def test_cache_info_and_clear_touch_only_our_files(cache_root):
    assert cache.cache_dir() == cache_root
    assert cache.cache_info() == {"path": str(cache_root), "entries": 0, "kernels": 0, "bytes": 0}
    problem_from_expressions(**KEPLER)
    problem_from_file(CONFIGS / "kepler_problem.py")
    info = cache.cache_info()
    assert info["entries"] == 2 and info["bytes"] > 1000
    foreign = cache_root / "someone_elses.txt"
    foreign.write_text("keep me")
    removed = cache.clear_cache()
    assert removed >= 2 + 10 + 1    # two sources, Numba's index and data for their 10 functions, a key
    assert cache.cache_info()["entries"] == 0 and foreign.read_text() == "keep me"
    assert cache.clear_cache() == 0


def test_cache_dir_default_is_the_user_cache_dir(monkeypatch):
    import platformdirs
    monkeypatch.delenv("ELIMFAST_CACHE_DIR", raising=False)
    assert cache.cache_dir() == Path(platformdirs.user_cache_dir("elimfast"))


def test_write_atomic_replaces_whole_files(tmp_path):
    target = tmp_path / "a" / "file.py"
    cache.write_atomic(target, "one")
    cache.write_atomic(target, "two")
    assert target.read_text() == "two" and sorted(p.name for p in target.parent.iterdir()) == ["file.py"]


LOAD_AND_RUN = textwrap.dedent("""
    import json, sys
    from numba.core import event
    with event.install_recorder("numba:compile") as recorder:
        import elimfast
        from elimfast.config import load_run
        report = {}
        for name in sys.argv[1:]:
            spec = load_run(name)
            run = elimfast.Integration.from_spec(spec)
            run.advance(5)
            stats = [f.stats for f in (spec.problem.H, spec.problem.grad_H, spec.problem.hess_H,
                                       spec.problem.invariants, spec.problem.grad_invariants)]
            report[name] = [sum(sum(s.cache_hits.values()) for s in stats),
                            sum(sum(s.cache_misses.values()) for s in stats)]
    compiled = sorted({str(event.data.get("dispatcher", "?")) for _, event in recorder.buffer
                       if isinstance(event.data, dict)})
    print(json.dumps({"functions": report, "compile_events": len(recorder.buffer), "compiled": compiled,
                      "sympy": "sympy" in sys.modules}))
""")


@pytest.mark.usefixtures("allow_python")
def test_a_fresh_process_loading_a_seen_problem_compiles_nothing(tmp_path):
    env = dict(os.environ, ELIMFAST_CACHE_DIR=str(tmp_path / "cache"))
    configs = [str(CONFIGS / "kepler_expressions.yaml"), str(CONFIGS / "kepler_python.yaml")]

    def fresh_process():
        out = subprocess.run([sys.executable, "-c", LOAD_AND_RUN, *configs], env=env, capture_output=True,
                             text=True, timeout=600, cwd=ROOT)
        assert out.returncode == 0, out.stderr[-2000:]
        return json.loads(out.stdout.strip().splitlines()[-1])

    cold = fresh_process()
    # five functions each: H, grad_H, hess_H (sympy's, or central differences of the python file's grad_H),
    # invariants, grad_invariants
    assert all(misses == 5 for _, misses in cold["functions"].values()), cold   # really compiled the first time
    warm = fresh_process()
    assert all(counts == [5, 0] for counts in warm["functions"].values()), warm  # 5 cache hits, 0 compilations
    assert warm["compile_events"] == 0, warm["compiled"]                         # nothing else compiled either
    assert warm["sympy"] is False                                               # warm load skips sympy


# --- the invariant check -----------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(problems.PROBLEMS))
def test_builtin_invariants_pass_the_check(name):
    residuals = require_invariants(problems.PROBLEMS[name]())
    assert all(value < 1e-12 for value in residuals.values()), residuals


def test_the_papers_misprinted_lrl_is_rejected_showing_the_residual(cache_root):
    misprinted = "p1*(q1*p2 - q2*p1) - q2/sqrt(q1**2 + q2**2)"     # sign of p1 L1 dropped (docs/methods.md)
    problem = problem_from_expressions(**{**KEPLER, "invariants": {**KEPLER["invariants"], "lrl_y": misprinted}},
                                       check=False)   # checked below
    residuals = check_invariants(problem)
    assert residuals["lrl_y"] > 0.1 and residuals["angular_momentum"] < 1e-14 and residuals["lrl_x"] < 1e-14
    with pytest.raises(InvariantCheckError, match=r"'lrl_y' .* not conserved .* = [0-9.]+e-0\d") as info:
        require_invariants(problem)
    assert info.value.key == "invariants.lrl_y" and info.value.residuals == residuals


def test_check_is_seeded_and_rejects_a_singular_initial_state(cache_root):
    problem = problem_from_expressions(**KEPLER)
    assert check_invariants(problem, seed=3) == check_invariants(problem, seed=3)
    with pytest.raises(ProblemDefinitionError, match="not finite at the initial state"):
        check_invariants(problem, y0=np.zeros(4))


# --- python: files ----------------------------------------------------------------------------

KEPLER_FILE = (CONFIGS / "kepler_problem.py").read_text()


@pytest.mark.parametrize("change,match", [
    (lambda s: s.replace("def H(", "def energy("), "defines no H"),
    (lambda s: s.replace("out[3] = y[3]", "out[4] = y[3]"), r"grad_H\(y, params, out\) .* IndexError"),
    (lambda s: s.replace("    out[3] = y[3]\n", ""), r"grad_H left out\[3\] unwritten"),
    (lambda s: s.replace('INVARIANT_NAMES = ("angular_momentum", "lrl_x", "lrl_y")',
                         'INVARIANT_NAMES = ("angular_momentum", "lrl_x")'), "IndexError"),
    (lambda s: s.replace("def grad_invariants(", "def gradient_of_invariants("), "define both"),
    (lambda s: s.replace("import math", "import math\nraise RuntimeError('boom')"),
     r"running it raised RuntimeError at line \d+: boom"),
    (lambda s: s + "\ndef broken(:\n", r"SyntaxError at line \d+"),
    # a sys.exit() in the file ended elimfast silently with its code (a user trial)
    (lambda s: s.replace("import math", "import math\nimport sys\nsys.exit(0)"),
     r"running it raised SystemExit at line \d+: 0; fix the file"),
    (lambda s: s.replace("import math", "import fractions\nimport math").replace(
        "mu = params[0]\n    return", "mu = params[0] * float(fractions.Fraction(1, 1))\n    return"),
     r"Numba cannot compile H as H\(y, params\) -> float \(line 19\): Unknown attribute 'Fraction'"),
    (lambda s: s.replace("Y0 = [0.4, 0.0, 0.0, 2.0]", "Y0 = [0.4, 0.0, 0.0, 2.0]\nHAMILTONIAN_DEGREE = 2.5"),
     "HAMILTONIAN_DEGREE must be a whole number >= 0"),
    (lambda s: s.replace("Y0 = [0.4, 0.0, 0.0, 2.0]", "Y0 = [0.4, 0.0, 0.0]"), "Y0 has 3 entries"),
])
def test_python_file_faults_are_reported_in_one_line(cache_root, tmp_path, change, match):
    path = tmp_path / "problem.py"
    path.write_text(change(KEPLER_FILE))
    with pytest.raises(UserProblemError, match=match) as info:
        problem_from_file(path)
    assert "\n" not in str(info.value)


def test_a_python_file_using_np_dot_without_scipy_says_so_in_one_line(cache_root, tmp_path):
    """Numba compiles np.dot through SciPy: without it, "internal error: ImportError: scipy 0.16+ is
    required for linear algebra" named neither the file nor the function (a user trial)."""
    import importlib.util
    if importlib.util.find_spec("scipy") is not None:
        pytest.skip("SciPy is installed: np.dot compiles")
    path = tmp_path / "problem.py"
    path.write_text(KEPLER_FILE.replace("import math", "import math\nimport numpy as np").replace(
        "0.5 * (y[2] * y[2] + y[3] * y[3])", "0.5 * np.dot(y[2:], y[2:])"))
    assert "np.dot" in path.read_text()
    with pytest.raises(UserProblemError, match=r"problem\.py: Numba compiles H's np\.dot, @ or np\.linalg through "
                                               r"SciPy, which is not installed; pip install scipy") as info:
        problem_from_file(path)
    assert "\n" not in str(info.value)


def test_python_file_may_declare_the_degree_of_its_polynomial_H(cache_root, tmp_path):
    path = tmp_path / "problem.py"
    path.write_text(KEPLER_FILE)
    assert problem_from_file(path).hamiltonian_degree is None
    quartic = tmp_path / "quartic.py"
    quartic.write_text("Y0 = [1.0, 0.5]\nHAMILTONIAN_DEGREE = 4\n\ndef H(y, params):\n    return 0.5 * y[1] ** 2 + "
                       "0.25 * y[0] ** 4\n\ndef grad_H(y, params, out):\n    out[0] = y[0] ** 3\n    out[1] = y[1]\n")
    assert problem_from_file(quartic).hamiltonian_degree == 4
    # a degree that H exceeds is refused, not taken on trust (a user trial: a Lennard-Jones H declared of
    # degree 4 made check say it was kept to round-off); a higher bound is true and taken
    quartic.write_text(quartic.read_text().replace("HAMILTONIAN_DEGREE = 4", "HAMILTONIAN_DEGREE = 3"))
    with pytest.raises(UserProblemError, match=r"HAMILTONIAN_DEGREE = 3, but H is not a polynomial of degree <= 3: "
                                               r"along a line through the initial state its difference of order 4"):
        problem_from_file(quartic)
    quartic.write_text(quartic.read_text().replace("HAMILTONIAN_DEGREE = 3", "HAMILTONIAN_DEGREE = 6"))
    assert problem_from_file(quartic).hamiltonian_degree == 6
    path.write_text(KEPLER_FILE.replace("Y0 = [0.4, 0.0, 0.0, 2.0]", "Y0 = [0.4, 0.0, 0.0, 2.0]\nHAMILTONIAN_DEGREE = 8"))
    with pytest.raises(UserProblemError, match="HAMILTONIAN_DEGREE = 8, but H is not a polynomial"):
        problem_from_file(path)


def test_python_file_at_a_singular_initial_state_says_so(cache_root, tmp_path):
    """A user trial's finding: an initial state on H's singularity (two bodies at one place) was
    reported as 'grad_H left out[0] unwritten (or NaN) ...; it must fill all of out', which sends
    the user to a grad_H that is right."""
    path = tmp_path / "problem.py"
    path.write_text(KEPLER_FILE)
    with pytest.raises(UserProblemError) as info:
        problem_from_file(path, initial={"q1": 0})
    assert str(info.value) == (f"{path}: H = -inf at the initial state [0.0, 0.0, 0.0, 2.0]; choose an initial "
                               "state away from the singularity")
    assert info.value.key == "initial"


def test_python_file_copy_carries_the_finite_difference_hessian_after_the_users_lines(cache_root):
    from elimfast.problems import user_file
    problem = problem_from_file(CONFIGS / "kepler_problem.py")
    (copy,) = (cache_root / cache.PROBLEMS_SUBDIR).glob("u_*.py")
    text = copy.read_text()
    assert text.startswith(KEPLER_FILE) and text.endswith(user_file.FD_HESSIAN_SOURCE)   # user lines unchanged
    assert copy.name == f"u_{cache.content_hash('python-file-v2', text)}.py"
    assert problem.hessian_source == "finite differences"
    assert problem.hess_H.py_func is user_file._MODULES[str(copy)].__dict__[user_file.FD_HESS_H_NAME]


def test_python_file_parameters_and_initial_overrides(cache_root):
    problem = problem_from_file(CONFIGS / "kepler_problem.py", parameters={"mu": "2"}, initial={"p2": "sqrt(mu*5)"})
    assert list(problem.params) == [2.0] and problem.y0[3] == math.sqrt(10.0)
    with pytest.raises(UserProblemError, match="no parameter 'm'; did you mean 'mu'"):
        problem_from_file(CONFIGS / "kepler_problem.py", parameters={"m": 1})
    with pytest.raises(UserProblemError, match="'x1' is not a coordinate"):
        problem_from_file(CONFIGS / "kepler_problem.py", initial={"x1": 1})


def test_derivatives_that_explode_are_refused(cache_root, monkeypatch):
    from elimfast.problems import symbolic
    monkeypatch.setattr(symbolic, "MAX_DERIVATIVE_NODES", 500)
    H = "*".join(f"sin(q + {i})" for i in range(40)) + " + p**2/2"
    with pytest.raises(ProblemDefinitionError, match="derivatives of the hamiltonian have .* python: file") as info:
        problem_from_expressions({"q": ["q"], "p": ["p"]}, H, initial={"q": 0, "p": 1})
    assert info.value.key == "hamiltonian"


@pytest.mark.usefixtures("allow_python")
def test_an_unwritable_cache_is_a_config_error(tmp_path, monkeypatch):
    from elimfast.config import ConfigError, load_run
    blocker = tmp_path / "not_a_directory"
    blocker.write_text("")
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(blocker))
    for name in ("kepler_expressions", "kepler_python"):
        with pytest.raises(ConfigError, match="problem: cannot write the elimfast cache .* set ELIMFAST_CACHE_DIR"):
            load_run(CONFIGS / f"{name}.yaml")
    # no --set is to blame (a user trial was told "(with --set problem.parameters.mu=1.0000001)")
    with pytest.raises(ConfigError) as refused:
        load_run(CONFIGS / "kepler_expressions.yaml", overrides=["problem.parameters.mu=1.0000001"])
    assert str(refused.value).endswith("set ELIMFAST_CACHE_DIR to a writable directory"), str(refused.value)



def _random_expressions():
    from hypothesis import strategies as st
    return st.recursive(
        st.sampled_from(["q", "p", "a", "pi", "e", "0", "1", "2", "3", "0.5", "1e-3"]),
        lambda inner: st.one_of(
            st.tuples(inner, st.sampled_from(["+", "-", "*", "/", "**"]), inner).map(
                lambda t: f"({t[0]}{t[1]}{t[2]})"),
            st.tuples(st.sampled_from(["sqrt", "exp", "log", "sin", "cos", "tan", "sinh", "cosh", "tanh", "asin",
                                       "acos", "atan", "abs", "-"]), inner).map(lambda t: f"{t[0]}({t[1]})"),
            st.tuples(inner, inner).map(lambda t: f"atan2({t[0]}, {t[1]})")),
        max_leaves=8)


def test_a_derivative_sympy_cannot_write_is_a_clear_error(tmp_path, monkeypatch):
    """abs(sqrt(q)) is complex for q < 0 to sympy: its second derivative keeps an unevaluated
    d/dq re(sqrt(q)), which has no code (found by the random test below: a printer traceback)."""
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(tmp_path / "cache"))
    with pytest.raises(ProblemDefinitionError, match=r"second derivative of the hamiltonian .* with respect to q "
                                                     r"twice has no closed form") as caught:
        problem_from_expressions({"q": ["q"], "p": ["p"]}, "p**2/2 + abs(sqrt(q))", initial={"q": 0.3, "p": 0.6})
    assert caught.value.key == "hamiltonian"
    # an invariant needs first derivatives only, and abs(sqrt(q))'s first derivative has code
    problem_from_expressions({"q": ["q"], "p": ["p"]}, "p**2/2", invariants={"L": "abs(sqrt(q)) * p"},
                             initial={"q": 0.3, "p": 0.6}, check=False)   # code, not an invariant
    # the real-valued spelling of the same thing compiles
    problem = problem_from_expressions({"q": ["q"], "p": ["p"]}, "p**2/2 + sqrt(abs(q))", initial={"q": 0.3, "p": 0.6})
    assert problem.gradient(np.array([0.25, 0.6]))[0] == pytest.approx(0.5 / 0.5)


def test_random_problems_compile_and_agree_with_the_float_evaluator(tmp_path, monkeypatch):
    """Generated code for random expressions: either a clear ProblemDefinitionError, or code
    that compiles and whose H equals the double-precision evaluation of the text."""
    from hypothesis import HealthCheck, given, settings

    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(tmp_path / "cache"))
    y = np.array([0.3, 0.6])

    @settings(max_examples=12, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(_random_expressions(), _random_expressions())
    def check(H, L):
        try:
            # check=False: random L are no invariants, and the check would turn them away unevaluated
            problem = problem_from_expressions({"q": ["q"], "p": ["p"]}, H, invariants={"L": L},
                                               parameters={"a": 0.7}, initial={"q": 0.3, "p": 0.6}, check=False)
        except ProblemDefinitionError:
            return
        with np.errstate(all="ignore"):
            value = problem.hamiltonian(y)
            try:
                expected = evaluate(parse(H, ["q", "p", "a"]), {"q": 0.3, "p": 0.6, "a": 0.7})
            except ProblemDefinitionError:
                return
            assert math.isclose(value, expected, rel_tol=1e-9, abs_tol=1e-12), (H, value, expected)
            problem.gradient(y), problem.invariant_values(y), problem.invariant_gradients(y)

    check()
