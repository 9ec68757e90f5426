"""The Python API: arguments, errors, results, chunking."""
import math
import re
from pathlib import Path

import numpy as np
import pytest

import elimfast
from elimfast import Integration
from elimfast.integrate import SolverSettings
from elimfast.errors import ParameterError
from elimfast.methods import ehbvm, elim, gauss, ghbvm, hbvm


@pytest.mark.parametrize("kwargs,match", [
    (dict(method=ehbvm(12, 3), conserve=["angular_momentum", "lrl_x", "lrl_y"]), "at most s - 1 = 2"),
    (dict(method=ehbvm(12, 1), conserve=["angular_momentum"]), "raise s to 2"),
    (dict(method=ehbvm(12, 3), conserve=["energy"]), "no invariant 'energy'.*angular_momentum, lrl_x, lrl_y"),
    (dict(method=ehbvm(12, 3), conserve=["H"]), "leave it out"),
    (dict(method=hbvm(12, 3), conserve=["angular_momentum"]), "imposes no invariant besides H"),
    (dict(method=ghbvm(12, 3), conserve=["lrl_y", "lrl_y"]), "twice"),
    (dict(method=gauss(3), h=0.0), "h must be > 0"),
    (dict(method=gauss(3), h=-0.1), "h must be > 0"),
    (dict(method=gauss(3), h=float("nan")), "h must be > 0 and finite"),
    (dict(method=gauss(3), t_end=1.05, n_steps=None), "not a whole number of steps"),
    (dict(method=gauss(3), t_end=1.0, n_steps=11), "n_steps = 11 disagrees with t_end"),
    (dict(method=gauss(3), n_steps=0), "n_steps must be >= 1"),
    (dict(method=gauss(3), max_iter=0), "max_iter"),
    (dict(method=gauss(3), store_every=0), "store_every"),
    (dict(method=gauss(3), rhs="fancy"), "stable"),
    (dict(method="gauss3"), "elimfast Method"),
])
def test_bad_arguments_say_what_to_change(kepler, kwargs, match):
    arguments = dict(h=0.1, n_steps=10)
    arguments.update(kwargs)
    with pytest.raises((ValueError, TypeError), match=match):
        elimfast.integrate(kepler, **arguments)


def test_t_end_gives_round_number_of_steps(kepler):
    result = elimfast.integrate(kepler, gauss(2), math.pi / 30, t_end=2 * math.pi)
    assert result.n_steps == 60 and result.iterations.shape == (60,)
    assert abs(result.t_final - 2 * math.pi) < 1e-14
    assert result.t.shape == (61,) and result.y.shape == (61, 4)


def test_result_holds_every_invariant_imposed_or_not(kepler):
    result = elimfast.integrate(kepler, ehbvm(12, 3), 0.1, n_steps=20, conserve=["lrl_y"])
    assert set(result.invariants) == {"H", "angular_momentum", "lrl_x", "lrl_y"}
    assert result.invariants["H"][0] == pytest.approx(-0.5, abs=1e-15)
    assert result.invariants["angular_momentum"][0] == pytest.approx(math.sqrt(1 - 0.36), abs=1e-15)
    assert result.invariants["lrl_x"][0] == pytest.approx(0.6, abs=1e-15)
    assert result.alpha.shape == (20, 1) and result.lam is None
    assert result.status == "complete"
    np.testing.assert_array_equal(result.y[-1], result.y_final)
    lim_result = elimfast.integrate(kepler, ghbvm(12, 3), 0.1, n_steps=20, conserve=["lrl_y"])
    assert lim_result.lam.shape == (20, 2) and lim_result.alpha is None


def test_store_every_keeps_the_last_state(kepler):
    result = elimfast.integrate(kepler, gauss(2), 0.1, n_steps=25, store_every=10)
    np.testing.assert_allclose(result.t, [0.0, 1.0, 2.0, 2.5], atol=1e-14)
    full = elimfast.integrate(kepler, gauss(2), 0.1, n_steps=25)
    np.testing.assert_array_equal(result.y, full.y[[0, 10, 20, 25]])
    assert result.iterations.shape == (25,)


def test_chunked_run_is_bitwise_identical_to_one_call(kepler):
    one = elimfast.integrate(kepler, ehbvm(12, 3), 0.1, n_steps=103, conserve=["angular_momentum", "lrl_y"])
    run = Integration(kepler, ehbvm(12, 3), 0.1, 103, conserve=["angular_momentum", "lrl_y"])
    chunks = [run.advance(n) for n in (1, 7, 50, 1000)]
    np.testing.assert_array_equal(run.y, one.y_final)
    np.testing.assert_array_equal(np.concatenate([c.y for c in chunks]), one.y[1:])
    np.testing.assert_array_equal(np.concatenate([c.multipliers for c in chunks]), one.alpha)


def test_state_restore_continues_exactly(kepler):
    method = ehbvm(12, 3)
    full = Integration(kepler, method, 0.1, 80, conserve=["lrl_y"])
    full.advance(80)
    first = Integration(kepler, method, 0.1, 80, conserve=["lrl_y"])
    first.advance(33)
    second = Integration(kepler, method, 0.1, 80, conserve=["lrl_y"])
    second.restore(first.state())
    second.advance(80)
    np.testing.assert_array_equal(second.y, full.y)
    np.testing.assert_array_equal(second.clock, full.clock)


def test_non_convergence_raises_with_step_time_and_partial_result(kepler):
    with pytest.raises(elimfast.ConvergenceError) as caught:
        elimfast.integrate(kepler, hbvm(12, 3), 0.1, n_steps=50, max_iter=3)
    error = caught.value
    assert error.step == 1 and error.time == 0.0 and error.reason == "not converged"
    assert "step 1 (t = 0 -> 0.1" in str(error) and "max_iter = 3" in str(error)
    assert error.result.steps_done == 0 and error.result.y.shape == (1, 4)
    assert error.result.status.startswith("failed:")


def test_failure_mid_run_keeps_what_was_computed(kepler):
    # A step too large for the fixed-point iteration near perihelion, with step splitting
    # turned off: the first steps converge.
    with pytest.raises(elimfast.ConvergenceError) as caught:
        elimfast.integrate(kepler, gauss(3), 0.7, n_steps=40, solver="fixed_point", max_halvings=0)
    error = caught.value
    assert error.step > 1
    partial = error.result
    assert partial.steps_done == error.step - 1
    assert partial.t[-1] == pytest.approx(0.7 * partial.steps_done)
    assert partial.iterations.shape == (error.step,)  # the failed step's count is kept
    assert "t = " in str(error)


def test_the_step_engine_completes_the_run_the_fixed_point_could_not(kepler):
    """Spec 8: the same run with the defaults (simplified Newton, step splitting) completes,
    and keeps H to round-off at every sample (GAUSS(3) keeps only quadratic H exactly:
    here the check is that no step was accepted unconverged, so H stays bounded)."""
    result = elimfast.integrate(kepler, gauss(3), 0.7, n_steps=40)
    assert result.status == "complete" and result.split_steps >= 1
    assert result.invariant_errors()["angular_momentum"] < 1e-13   # quadratic: Gauss keeps it exactly


def test_singular_gamma_is_reported_not_nan(central_quartic):
    # Radial motion (q2 = p2 = 0): L = 0 all along, so phi_j^T gamma_j = 0 and Gamma is singular,
    # though grad L and grad H are independent at y0. Without the fallback (max_halvings = 0) that is
    # the run's failure, named as such; with it every step is taken unimposed, which keeps L = 0
    # exactly (docs/solver.md#a-substep-without-imposing), and the run says so (alpha NaN).
    with pytest.raises(elimfast.ConvergenceError) as caught:
        elimfast.integrate(central_quartic, ehbvm(6, 3), 0.1, n_steps=5, conserve=["angular_momentum"],
                           y0=[0.5, 0.0, 0.0, 0.0], max_halvings=0)
    assert caught.value.reason == "singular" and "Gamma" in str(caught.value)
    radial = elimfast.integrate(central_quartic, ehbvm(6, 3), 0.1, n_steps=5, conserve=["angular_momentum"],
                                y0=[0.5, 0.0, 0.0, 0.0])
    assert radial.status == "complete" and radial.unimposed_steps == 5
    assert radial.invariant_errors()["angular_momentum"] == 0.0
    # At the origin at rest nothing moves and grad H = 0: refused before the first step
    from elimfast.errors import ParameterError
    with pytest.raises(ParameterError, match=r"^conserve names 'angular_momentum', but grad H "
                                                            r"vanishes at y0 \(an equilibrium\)"):
        elimfast.integrate(central_quartic, ehbvm(6, 3), 0.1, n_steps=5, conserve=["angular_momentum"],
                           y0=[0.0, 0.0, 0.0, 0.0])


def test_elim_with_r_different_from_k_conserves_polynomial_invariant(central_quartic):
    result = elimfast.integrate(central_quartic, elim(4, 6, 3), 0.1, n_steps=500, conserve=["angular_momentum"])
    assert result.invariant_errors()["angular_momentum"] < 1e-12


def test_linear_invariants_are_detected_and_refused_for_elim():
    from elimfast.problems import fpu_beta, kepler
    chain = fpu_beta(n=4)
    assert chain.linear_invariant_names == ("momentum",)
    assert kepler().linear_invariant_names == ()
    with pytest.raises(ValueError, match="'momentum', which is linear.*keeps linear invariants exactly.*lim/ghbvm"):
        elimfast.integrate(chain, ehbvm(8, 4), 0.1, n_steps=5, conserve=["momentum"])
    # LIM can impose it (pointlessly, but correctly)
    result = elimfast.integrate(chain, ghbvm(8, 4), 0.1, n_steps=5, conserve=["momentum"])
    assert result.invariant_errors()["momentum"] < 1e-14


def test_a_quadratic_invariant_of_a_quadratic_hamiltonian_is_refused_for_elim():
    """A user trial: a charged particle in a magnetic field (H and the canonical angular momentum
    both quadratic) imposing L with EHBVM(6,3) passed check, then split 9,995 of 10,000 steps and
    failed at a larger h with cond(Gamma) inf. With grad H and grad L affine and {L, H} = 0, every
    phi_j^T gamma_j vanishes whatever the stages, so Gamma is zero; and the HBVM step of a quadratic
    H is Gauss collocation, which keeps L anyway. LIM imposes it; a quadratic invariant of a
    non-quadratic H (Kepler's L) is imposed by ELIM as before."""
    from elimfast.problems import kepler, problem_from_expressions
    charged = problem_from_expressions(
        {"q": ["x", "y"], "p": ["px", "py"]}, "((px + B*y/2)**2 + (py - B*x/2)**2)/2 + k*(x**2 + y**2)/2",
        invariants={"energy_like": "(px**2 + py**2)/2 + x**2", "canonical_L": "x*py - y*px"},
        parameters={"B": 1.0, "k": 0.3}, initial={"x": 1.0, "y": 0.0, "px": 0.0, "py": 0.8}, check=False)
    assert charged.quadratic_invariant_names == ("energy_like", "canonical_L")   # quadratic, conserved or not
    assert kepler().quadratic_invariant_names == ()                              # H is not quadratic
    with pytest.raises(ParameterError, match=r"^conserve\[0\] names 'canonical_L', which is quadratic, as H is: "
                                             r"then EHBVM\(6,3\)'s HBVM step is Gauss collocation.*lim/ghbvm$"):
        elimfast.integrate(charged, ehbvm(6, 3), 0.05, n_steps=5, conserve=["canonical_L"])
    kept = elimfast.integrate(charged, hbvm(6, 3), 0.05, n_steps=2000)
    assert kept.invariant_errors()["canonical_L"] < 1e-14
    imposed = elimfast.integrate(charged, ghbvm(6, 3), 0.05, n_steps=200, conserve=["canonical_L"])
    assert imposed.status == "complete" and imposed.invariant_errors()["canonical_L"] < 1e-14


def test_an_unknown_solver_is_named_by_integrates_keyword():
    """A user trial's finding: integrate(..., solver='newtn') said 'method must be one of newton,
    fixed_point', while integrate's method is the integrator (ehbvm(8, 4))."""
    from elimfast.errors import ParameterError
    problem = elimfast.problems.kepler(0.6)
    for run in (lambda: elimfast.integrate(problem, ehbvm(8, 4), h=0.1, n_steps=2, solver="newtn"),
                lambda: elimfast.integrate(problem, ehbvm(8, 4), rtol=1e-10, t_end=1.0, solver="newtn"),
                lambda: Integration(problem, ehbvm(8, 4), h=0.1, n_steps=2, solver="newtn")):
        with pytest.raises(ParameterError) as info:
            run()
        assert str(info.value).startswith("solver must be auto (the default: simplified Newton up to 48 state "
                                          "components, the fixed point above), newton or fixed_point, got 'newtn'"), \
            str(info.value)
        assert info.value.parameter == "solver"
    # the solver section of a config as a dict (a user trial: TypeError: unhashable type: 'dict')
    as_dict = elimfast.integrate(problem, ehbvm(8, 4), h=0.1, n_steps=5, solver={"method": "fixed_point", "max_iter": 50})
    assert (as_dict.solver.method, as_dict.solver.max_iter) == ("fixed_point", 50)
    with pytest.raises(ParameterError, match=r"^solver has no key 'methd'; did you mean 'method'\?"):
        elimfast.integrate(problem, ehbvm(8, 4), h=0.1, n_steps=5, solver={"methd": "fixed_point"})


@pytest.mark.parametrize("adaptive", [False, True])
def test_solver_keywords_beside_solver_settings_are_kept_or_refused(adaptive):
    """A user trial: integrate(..., solver=SolverSettings(...) or {...}, rhs='literal') ran the stable
    form, the keyword silently dropped. With a dict they are merged; a contradiction is refused."""
    problem = elimfast.problems.kepler(0.6)
    span = {"rtol": 1e-8, "t_end": 0.5} if adaptive else {"h": 0.1, "n_steps": 5}
    merged = elimfast.integrate(problem, ehbvm(8, 4), conserve=["angular_momentum"], solver={"method": "newton"},
                                rhs="literal", max_halvings=3, max_iter=40, **span)
    assert (merged.solver.method, merged.solver.rhs, merged.solver.max_halvings, merged.solver.max_iter) == \
        ("newton", "literal", 3, 40)
    with pytest.raises(ParameterError, match=r"^rhs is 'literal' but the solver dict says 'rhs': 'stable'; give it "
                                             r"once$"):
        elimfast.integrate(problem, ehbvm(8, 4), solver={"rhs": "stable"}, rhs="literal", **span)
    settings = SolverSettings(method="newton")
    for keyword in ({"rhs": "literal"}, {"max_halvings": 2}, {"max_iter": 7}, {"tol": 1e-12}, {"predictor": False},
                    {"warm_start": False}):
        (name, value), = keyword.items()
        with pytest.raises(ParameterError) as info:
            elimfast.integrate(problem, ehbvm(8, 4), solver=settings, **keyword, **span)
        assert info.value.parameter == name
        assert f"set it in the settings (dataclasses.replace(settings, {name}={value!r}))" in str(info.value)
    # the same value twice is no contradiction
    same = elimfast.integrate(problem, ehbvm(8, 4), solver=SolverSettings(rhs="literal"), rhs="literal", **span)
    assert same.solver.rhs == "literal"


@pytest.mark.parametrize("y0, detail", [
    (np.array([0.4, 0.0, 0.0, 2.0 + 1e-3j]), "must be real numbers, got complex values"),
    ([0.4, 0.0, 0.0, 2.0 + 1e-3j], "must be real numbers, got complex values"),
    ("abc", "must be a list of real numbers, got 'abc'"),
    ([0.4, 0.0, "x", 2.0], "must be a list of real numbers, got [0.4, 0.0, 'x', 2.0]"),
    ([[0.4, 0.0], [0.0]], "must be a list of real numbers"),
    ([0.4, 0.0, 0.0], "must be 4 finite numbers (q1, q2, p1, p2)"),
])
def test_an_initial_state_that_is_not_real_numbers_is_refused_naming_y0(kepler, y0, detail):
    """A complex y0 was run on its real part with only numpy's ComplexWarning (the imaginary part
    dropped), and y0='abc' said "could not convert string to float: 'abc'", naming nothing. Every
    way of giving a state refuses them by name (the problem's shape check says its own words), and
    without a warning first."""
    import dataclasses
    import warnings
    from elimfast.errors import ParameterError
    from elimfast.problems.check import check_derivatives
    runs = {"integrate": lambda: elimfast.integrate(kepler, gauss(2), h=0.1, n_steps=2, y0=y0),
            "adaptive integrate": lambda: elimfast.integrate(kepler, ehbvm(8, 4), rtol=1e-8, t_end=0.5, y0=y0),
            "Integration": lambda: Integration(kepler, gauss(2), h=0.1, n_steps=2, y0=y0),
            "with_initial": lambda: kepler.with_initial(y0),
            "Problem": lambda: dataclasses.replace(kepler, y0=y0),
            "check_derivatives": lambda: check_derivatives(kepler, y0=y0)}
    for name, run in runs.items():
        if name in ("with_initial", "Problem", "check_derivatives") and "finite numbers" in detail:
            continue   # the Problem says its shape its own way (4 entries)
        with warnings.catch_warnings():
            warnings.simplefilter("error")   # no ComplexWarning on the way to the error
            with pytest.raises(ParameterError) as info:
                run()
        assert info.value.parameter == "y0", name
        message = str(info.value)
        assert message.startswith("y0 of problem 'kepler' " if name == "Problem" else "y0 "), (name, message)
        assert detail in message and "\n" not in message, (name, message)


def test_an_initial_state_of_exact_numbers_is_taken(kepler):
    """Fractions were taken and decimal.Decimal refused ('must be a list of real numbers'): it is
    no numbers.Real, but a real number all the same."""
    from decimal import Decimal
    from fractions import Fraction
    exact = [Decimal("0.4"), 0, Fraction(0), Decimal(2)]
    run = elimfast.integrate(kepler, gauss(2), h=0.1, n_steps=3, y0=exact)
    np.testing.assert_array_equal(run.y, elimfast.integrate(kepler, gauss(2), h=0.1, n_steps=3, y0=kepler.y0).y)


def test_an_ensemble_and_a_python_problem_refuse_complex_initial_states(kepler, tmp_path):
    """The same check for an ensemble's Y0 and a python problem file's Y0 (numpy's conversion
    dropped the imaginary part there too)."""
    import warnings
    from elimfast.ensemble import integrate_ensemble
    from elimfast.errors import ParameterError
    from elimfast.problems.user_file import UserProblemError, problem_from_file
    states = np.array([kepler.y0, kepler.y0 + 1e-3j])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ParameterError, match=r"^Y0 must be real numbers, got complex values") as info:
            integrate_ensemble(kepler, gauss(2), h=0.1, Y0=states, n_steps=2)
    assert info.value.parameter == "Y0"
    source = (Path(__file__).resolve().parents[1] / "configs" / "kepler_problem.py").read_text()
    assert "\nY0 = [" in source
    path = tmp_path / "complex_problem.py"
    path.write_text(source + "\nimport numpy\nY0 = numpy.array(Y0) + 1e-3j\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(UserProblemError, match=r": Y0 must be real numbers, got complex values") as info:
            problem_from_file(path)
    assert "\n" not in str(info.value)


def test_a_run_whose_dense_matrices_do_not_fit_is_refused_and_the_fixed_point_has_none(monkeypatch):
    """A user trial: fpu_beta with 10^5 masses (n = 2 10^5) died of a MemoryError blamed on the
    problem's functions: simplified Newton's n x n matrices would take 1.8 TB, and the fixed
    point's workspace allocated two n x n arrays it never used (640 GB). Runs whose dense
    arrays do not fit in the memory available are refused up front naming the fix, and the
    fixed point allocates none: that chain now takes its steps in a few hundred MB."""
    import importlib

    from elimfast.errors import ParameterError
    driver = importlib.import_module("elimfast.integrate")   # the module: elimfast.integrate is the function
    from elimfast.methods import hbvm
    from elimfast.problems import fpu_beta
    chain = fpu_beta(n=100_000)
    result = elimfast.integrate(chain, hbvm(6, 3), 0.05, n_steps=2, solver="fixed_point")
    assert result.status == "complete" and result.iterations.min() >= 1
    small = fpu_beta(n=40)   # n = 80: Newton's arrays 307 kB, the adaptive kernel's Hessian 51 kB
    monkeypatch.setattr(driver, "available_memory", lambda: 100_000)
    with pytest.raises(ParameterError, match=r"^solver cannot run here: simplified Newton stores dense n x n "
                                             r"matrices, 0.0 GB at n = 80, .*use the fixed point"):
        elimfast.integrate(small, hbvm(6, 3), 0.05, n_steps=2, solver="newton")
    # the default ('auto') takes the fixed point at this size
    assert elimfast.integrate(small, hbvm(6, 3), 0.05, n_steps=2).status == "complete"
    assert elimfast.integrate(small, hbvm(6, 3), 0.05, n_steps=2, solver="fixed_point").status == "complete"
    assert elimfast.integrate(small, hbvm(6, 3), t_end=0.1, rtol=1e-8, solver="fixed_point").status == "complete"
    monkeypatch.setattr(driver, "available_memory", lambda: 10_000)
    with pytest.raises(ParameterError, match=r"adaptive steps, output times and events store a dense n x n Hessian"):
        elimfast.integrate(small, hbvm(6, 3), t_end=0.1, rtol=1e-8, solver="fixed_point")
    assert driver.dense_matrix_bytes(200_000, hbvm(6, 3), driver.SolverSettings(method="newton"), adaptive=False) > 1.5e12


def test_a_problem_that_raises_mid_run_gives_the_steps_before_it():
    """A user trial: integrate with a python: problem whose gradient raises at t = 1.4 raised the bare
    ValueError, and the 14 steps before it were lost (the CLI keeps them in its file). The problem's
    exception is still what is raised (code catching ValueError still does), and now carries them
    as .result, with the step, the time and a note: the same steps as a run stopped just before,
    fixed or adaptive."""
    problem = elimfast.problems.problem_from_file(Path(__file__).parent / "data" / "kepler_raising_late.py")
    for options in ({"h": 0.1, "t_end": 10.0}, {"t_end": 10.0, "rtol": 1e-10}):
        with pytest.raises(ValueError, match=r"^negative q1") as info:
            elimfast.integrate(problem, "HBVM(6,3)", **options)
        error = info.value
        assert len(error.__notes__) == 1
        assert re.match(r"^elimfast: the problem raised ValueError: negative q1 at step \d+ \(t = 1\.4\d*\); its "
                        r"\.result holds the \d+ steps before it$", error.__notes__[0]), error.__notes__
        partial = error.result
        assert error.step == partial.steps_done + 1 >= 10 and partial.t[-1] == error.time
        assert partial.status.startswith("failed: the problem raised ValueError")
        if "h" in options:   # the same steps as a run of exactly that many
            before = elimfast.integrate(problem, "HBVM(6,3)", 0.1, n_steps=partial.steps_done)
            np.testing.assert_array_equal(partial.y_final, before.y_final)


def test_a_step_below_the_resolution_of_the_times_is_refused():
    """A user trial: t0 = 1e20 with h = 0.1 ran, and every stored t was 1e20."""
    from elimfast.errors import ParameterError
    from elimfast.methods import hbvm
    with pytest.raises(ParameterError, match=r"^h = 0.1 is below the resolution of the times at t0 = 1e\+20"):
        elimfast.integrate(elimfast.problems.kepler(0.6), hbvm(6, 3), 0.1, n_steps=10, t0=1e20)
    assert elimfast.integrate(elimfast.problems.kepler(0.6), hbvm(6, 3), 0.1, n_steps=10, t0=1e6).t[-1] == 1e6 + 1.0


def test_the_default_solver_is_newton_for_small_problems_and_the_fixed_point_for_large_ones():
    """A user trial: fpu_beta with 256 masses (n = 512) ran 32x slower with the default simplified
    Newton than with the fixed point (766 against 24 us per step): Newton's dense solves and
    factorisations grow like n^2 and n^3, the map like n. solver 'auto', the default, takes Newton
    up to 48 state components and the fixed point above; the run is then bit for bit the run of
    the explicit choice. An unresolved 'auto' never reaches a kernel."""
    import importlib
    driver = importlib.import_module("elimfast.integrate")
    from elimfast.methods import hbvm
    from elimfast.problems import fpu_beta
    method = hbvm(6, 3)
    assert driver.SolverSettings().method == "auto" == driver.DEFAULT_SOLVER
    assert driver.SolverSettings().resolved_for(method, 0, 48).method == "newton"
    assert driver.SolverSettings().resolved_for(method, 0, 50).method == "fixed_point"
    assert driver.SolverSettings(method="newton").resolved_for(method, 0, 4096).method == "newton"
    with pytest.raises(ValueError, match="not resolved"):
        driver.SolverSettings().code
    for masses, expected in ((24, "newton"), (25, "fixed_point")):
        chain = fpu_beta(n=masses)
        chosen = elimfast.integrate(chain, method, 0.05, n_steps=20)
        explicit = elimfast.integrate(chain, method, 0.05, n_steps=20, solver=expected)
        assert chosen.solver.method == expected
        np.testing.assert_array_equal(chosen.y_final, explicit.y_final)
        np.testing.assert_array_equal(chosen.iterations, explicit.iterations)
    adaptive = elimfast.integrate(fpu_beta(n=25), method, t_end=0.5, rtol=1e-10)
    assert adaptive.status == "complete" and adaptive.solver.method == "fixed_point"
    # a step the fixed point cannot solve names Newton in its advice (auto may have chosen the fixed point)
    from elimfast.errors import ConvergenceError
    with pytest.raises(ConvergenceError, match=r"; reduce h, or allow more step halvings \(solver.max_halvings = 0 "
                                               r"now\), or use simplified Newton \(solver.method: newton\)$"):
        elimfast.integrate(elimfast.problems.kepler(0.9), method, 1.0, n_steps=4, solver="fixed_point",
                           max_halvings=0)


def test_messages_give_times_in_their_shortest_exact_form():
    """A user trial: 't = 0.20000000000000001', 't = 46838.800000000003' (17 digits)."""
    from elimfast.errors import exact_time
    assert [exact_time(t) for t in (0.0, 0.1 + 0.1, 0.1 + 0.2, 50.0, 46838.8, -1.5, float("inf"))] == \
        ["0", "0.2", "0.30000000000000004", "50", "46838.8", "-1.5", "inf"]


@pytest.mark.parametrize("extra,parameter", [({"t_end": 10.0, "h": 0.1}, "t_end"),
                                             ({"t_end": 10.0, "rtol": 1e-10}, "backward")])
def test_what_a_backward_run_cannot_take_is_a_parameter_error(extra, parameter):
    # a user trial: both were plain ValueErrors, unlike every other fault of a parameter
    with pytest.raises(ParameterError) as info:
        elimfast.integrate(elimfast.problems.kepler(0.6), elimfast.methods.ehbvm(8, 4), backward=True, **extra)
    assert info.value.parameter == parameter



def test_conserve_on_a_method_that_imposes_nothing_says_what_it_keeps():
    """A user trial: GAUSS was said to 'cannot impose invariants besides H', as if it kept any H."""
    from elimfast.errors import ParameterError
    from elimfast.methods import gauss, hbvm
    from elimfast.problems import kepler
    for method, keeps in ((gauss(3), "it keeps quadratic ones by itself, H only when H is quadratic"),
                          (hbvm(6, 3), "it imposes no invariant besides H")):
        with pytest.raises(ParameterError, match=f"conserve must be empty for {re.escape(method.name)}: .*"
                                                 f"{re.escape(keeps)}"):
            elimfast.integrate(kepler(0.6), method, 0.1, n_steps=2, conserve=["angular_momentum"])


@pytest.mark.parametrize("keyword", ["h", "t_end", "t0", "tol", "rtol"])
def test_a_number_given_as_a_string_is_refused_alike(keyword):
    """A user trial: integrate(h='0.1') ran while h='pi/30' was refused; every real number of the API
    now refuses a string alike (errors.real_number), saying to pass the number."""
    from elimfast.errors import ParameterError
    from elimfast.methods import gauss, hbvm
    from elimfast.problems import kepler
    given = {"h": 0.1, "t_end": 1.0, **({"rtol": 1e-8, "h": None} if keyword == "rtol" else {})}
    given[keyword] = "0.5"
    with pytest.raises(ParameterError, match=f"^{keyword} must be a number, got the string '0.5': pass the number"):
        elimfast.integrate(kepler(0.6), hbvm(6, 3) if keyword == "rtol" else gauss(3), **given)


@pytest.mark.parametrize("builder, parameter", [("kepler", "eccentricity"), ("perturbed_kepler", "delta"),
                                                ("henon_heiles", "energy"), ("nbody", "G"), ("toda", "n")])
def test_a_builtin_problems_parameter_given_as_a_string_is_refused_like_integrates(builder, parameter):
    """The last note: kepler(eccentricity='0.9') was taken where integrate(h='0.1') is refused. A
    config's strings are expressions it reads first ('9/10'), so only the API meets this."""
    from elimfast.errors import ParameterError
    with pytest.raises(ParameterError, match=f"^{parameter} must be a number, got the string '4': pass the number"):
        getattr(elimfast.problems, builder)(**{parameter: "4"})


def test_a_problem_given_by_its_name_is_told_how_to_build_it():
    """A user trial: integrate("kepler", "GAUSS(2)", ...) raised "problem must be an elimfast Problem,
    got str", where a method may be given by its name."""
    from elimfast.ensemble import integrate_ensemble
    with pytest.raises(TypeError, match=r"got str \(build it: elimfast\.problems\.kepler\(\)\)$"):
        elimfast.integrate("kepler", "GAUSS(2)", h=0.1, n_steps=2)
    with pytest.raises(TypeError, match=r"got str \(build it: elimfast\.problems\.kepler\(\)\)$"):
        elimfast.integrate("kepler", "GAUSS(2)", rtol=1e-8, t_end=1.0)
    with pytest.raises(TypeError, match=r"got str \(build one with elimfast\.problems\.<name>\(\), "):
        integrate_ensemble("kepleer", ehbvm(8, 4), 0.1, np.zeros((1, 4)), n_steps=2)


def test_conserve_none_imposes_nothing_and_a_non_list_is_one_line():
    """A user trial: conserve=None raised TypeError: 'NoneType' object is not iterable (integrate and
    integrate_ensemble alike)."""
    from elimfast.ensemble import integrate_ensemble
    problem = elimfast.problems.kepler(0.6)
    fixed = elimfast.integrate(problem, ehbvm(8, 4), h=0.1, n_steps=3, conserve=None)
    adaptive = elimfast.integrate(problem, ehbvm(8, 4), rtol=1e-8, t_end=0.3, conserve=None)
    ensemble = integrate_ensemble(problem, ehbvm(8, 4), 0.1, np.array([problem.y0, problem.y0]), n_steps=3,
                                  conserve=None)
    assert fixed.conserve == adaptive.conserve == ensemble.conserve == ()
    np.testing.assert_array_equal(fixed.y, elimfast.integrate(problem, ehbvm(8, 4), h=0.1, n_steps=3).y)
    with pytest.raises(ParameterError, match=r"^conserve must be a list of invariant names, got 3$"):
        elimfast.integrate(problem, ehbvm(8, 4), h=0.1, n_steps=3, conserve=3)


@pytest.mark.parametrize("adaptive", [False, True])
def test_ctrl_c_in_python_keeps_the_steps_done_as_the_interrupts_result(monkeypatch, adaptive):
    """A user trial: Ctrl-C in elimfast.integrate lost every step done (a ConvergenceError carries
    them as .result, an interrupt carried nothing). The interrupt now carries them, consistent with
    the state of its chunks whether it lands inside a kernel call or after one."""
    import importlib
    from elimfast.problems import kepler
    from elimfast.methods import ehbvm
    module = importlib.import_module("elimfast.adaptive" if adaptive else "elimfast.integrate")
    cls = module.AdaptiveIntegration if adaptive else module.Integration
    advance, calls = cls.advance, []

    def interrupted(self, steps):
        calls.append(steps)
        if len(calls) == 3:
            advance(self, steps)            # the kernel's steps are taken, then the interrupt lands
            raise KeyboardInterrupt
        return advance(self, steps)
    monkeypatch.setattr(cls, "advance", interrupted)
    options = dict(t_end=200.0, rtol=1e-10) if adaptive else dict(h=0.1, n_steps=2000)
    with pytest.raises(KeyboardInterrupt) as caught:
        elimfast.integrate(kepler(0.6), ehbvm(8, 4), conserve=["angular_momentum"], chunk_steps=100, **options)
    partial = caught.value.result
    assert partial.steps_done == 200 and partial.status.startswith("interrupted at step 201")
    monkeypatch.setattr(cls, "advance", advance)
    options = dict(t_end=200.0, rtol=1e-10) if adaptive else dict(h=0.1, n_steps=200)
    whole = elimfast.integrate(kepler(0.6), ehbvm(8, 4), conserve=["angular_momentum"], chunk_steps=100, **options)
    np.testing.assert_array_equal(partial.y, whole.y[:partial.y.shape[0]])
    if not adaptive:
        np.testing.assert_array_equal(partial.y_final, whole.y_final)
