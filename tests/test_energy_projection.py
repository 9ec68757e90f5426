"""solver.project_energy: after every step the state is moved along grad H back to H(y0)
(docs/methods.md#energy-projection; kernels/stepper.project_energy).

Against theory: without it H's round-off is a random walk, and the phase error it drives
grows like t^(3/2) (Brouwer's law), the floor of long runs (docs/adaptive.md); with it the
error left is the truncation's, which for a fixed sequence of steps per period grows
linearly in t. And the projection is bit-exact across chunks and resumes (its target is
H at t0, not at the resume).
"""
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

import elimfast
from elimfast.errors import ParameterError
from elimfast.integrate import Integration, SolverSettings
from elimfast.kernels.stepper import energy_projection_arrays, project_energy
from elimfast.methods import ehbvm, gauss
from elimfast.problems import harmonic_oscillator, kepler

L1, AX, AY = "angular_momentum", "lrl_x", "lrl_y"
PERIOD = 2.0 * math.pi
PROJECT = {"project_energy": True}
ELIMFAST = str(Path(sys.executable).with_name("elimfast"))


def final_error(result, problem):
    return float(np.max(np.abs(result.y_final - problem.y0)))


@pytest.fixture(scope="module")
def e09_thousand_periods():
    """Issue 11's run, time-reversible steps (epsilon 0.1), projected, sampled at 100 and 1000 periods."""
    p = kepler(0.9)
    return p, elimfast.integrate(p, ehbvm(8, 4), t_end=1000 * PERIOD, step_control="time_scale", epsilon=0.1,
                                 conserve=(L1, AY), solver=PROJECT, t_eval=[100 * PERIOD, 1000 * PERIOD])


def test_issue_11_final_error_within_1e_8_in_at_most_100_steps_per_period(e09_thousand_periods):
    """Issue 11: Kepler e = 0.9 over 1000 periods, EHBVM(8,4) imposing L and A_y, adaptive: at
    most 100 steps per period for a final error <= 1e-8, every invariant <= 1e-13. Measured
    2.9e-9 in 84 steps per period; the same run without the projection ends 4.1e-8 off."""
    p, r = e09_thousand_periods
    assert r.status == "complete"
    assert r.steps_done <= 100 * 1000
    assert final_error(r, p) <= 1e-8
    errors = r.invariant_errors()
    assert max(errors[name] for name in ("H", L1, AX, AY)) <= 1e-13


def test_the_error_left_grows_linearly_as_the_truncation_does(e09_thousand_periods):
    """From 100 to 1000 periods the projected run's error grows 10x (measured 10.2x: the
    truncation's phase error, the same each period); without the projection 72x, H's walk."""
    p, r = e09_thousand_periods
    at_100, at_1000 = (float(np.max(np.abs(y - p.y0))) for y in r.y[-2:])
    assert 8.0 <= at_1000 / at_100 <= 12.5, (at_100, at_1000)


def test_fixed_steps_keep_H_at_its_evaluation_round_off():
    """Fixed-step EHBVM(12,4), 200 steps per period over 300 periods: H at every sample within
    a few roundings of its evaluation at the pericentre, where |T| + |V| ~ 20 (measured 3.6e-15,
    16 eps); without the projection it walks (measured 4.3e-14 here)."""
    p = kepler(0.9)
    r = elimfast.integrate(p, ehbvm(12, 4), PERIOD / 200, n_steps=300 * 200, conserve=(L1, AY), store_every=100,
                           solver=PROJECT)
    H = np.asarray(r.invariants["H"])
    assert r.status == "complete"
    assert np.max(np.abs(H - H[0])) <= 40 * np.finfo(float).eps


def test_chunks_and_a_restored_state_continue_bit_for_bit():
    p, m = kepler(0.9), ehbvm(8, 4)
    settings = SolverSettings(project_energy=True)
    one = Integration(p, m, PERIOD / 100, 700, conserve=(L1, AY), solver=settings)
    one.advance(700)
    chunked = Integration(p, m, PERIOD / 100, 700, conserve=(L1, AY), solver=settings)
    for n in (1, 99, 300, 300):
        chunked.advance(n)
    np.testing.assert_array_equal(chunked.y, one.y)
    np.testing.assert_array_equal(chunked.y_comp, one.y_comp)
    first = Integration(p, m, PERIOD / 100, 700, conserve=(L1, AY), solver=settings)
    first.advance(250)
    second = Integration(p, m, PERIOD / 100, 700, conserve=(L1, AY), solver=settings)
    second.restore(first.state())
    second.advance(700)
    np.testing.assert_array_equal(second.y, one.y)
    # and the projection did act: the plain run differs
    plain = Integration(p, m, PERIOD / 100, 700, conserve=(L1, AY))
    plain.advance(700)
    assert not np.array_equal(plain.y, one.y)


def test_adaptive_chunks_are_bit_identical_and_count_the_projection():
    p = kepler(0.9)
    kwargs = dict(t_end=4 * PERIOD, rtol=1e-12, conserve=(L1, AY), solver=PROJECT)
    whole = elimfast.integrate(p, ehbvm(8, 4), **kwargs)
    chunked = elimfast.integrate(p, ehbvm(8, 4), chunk_steps=7, **kwargs)
    assert np.array_equal(whole.y, chunked.y) and np.array_equal(whole.step_h, chunked.step_h)
    plain = elimfast.integrate(p, ehbvm(8, 4), t_end=4 * PERIOD, rtol=1e-12, conserve=(L1, AY))
    # one grad H for every state checked (every accepted step, here) on top of the iterations'
    assert whole.stats["energy_projections"] == whole.stats["steps"] and plain.stats["energy_projections"] == 0
    assert whole.stats["grad_H_evaluations"] - whole.stats["energy_projections"] == \
        whole.stats["iterations"] * plain.stats["grad_H_evaluations"] // plain.stats["iterations"]


def projected(problem, y, target, conserve_idx=()):
    """One call of the kernel's projection on a copy of y: (y + comp) after it."""
    conserve_idx = np.array(conserve_idx, dtype=np.int64)
    y, comp = np.array(y, dtype=float), np.zeros(len(y))
    arrays = energy_projection_arrays(len(y), len(problem.invariant_names), conserve_idx.size)
    project_energy(problem.H, problem.grad_H, problem.grad_invariants, problem.params, conserve_idx, y, comp, target,
                   arrays)
    return y, comp


def test_the_kernel_step_moves_onto_the_target_and_leaves_round_off_alone():
    p = kepler(0.9)
    y0 = np.array([0.3, 0.4, -1.1, 0.7])
    target = p.H(y0, p.params)
    g0, G = np.empty(4), np.empty((3, 4))
    p.grad_H(y0, p.params, g0)
    p.grad_invariants(y0, p.params, G)
    start = y0 + 1e-9 * g0 / np.dot(g0, g0)   # 1e-9 off H
    # nothing imposed: along grad H, back to within the rounding of H's evaluation
    y, comp = projected(p, start, target)
    moved = (y - start) + comp
    assert abs(p.H(y, p.params) + np.dot(g0, comp) - target) <= 4 * np.finfo(float).eps
    assert np.dot(moved, g0) / (np.linalg.norm(moved) * np.linalg.norm(g0)) == pytest.approx(-1.0, abs=1e-6)
    # L and A_y imposed (rows 0 and 2): the move leaves them unchanged to first order
    y, comp = projected(p, start, target, conserve_idx=(0, 2))
    moved = (y - start) + comp
    assert abs(p.H(y, p.params) - target) <= 4 * np.finfo(float).eps
    for row in (0, 2):
        assert abs(np.dot(G[row], moved)) <= 1e-6 * np.linalg.norm(G[row]) * np.linalg.norm(moved)
    assert abs(np.dot(G[1], moved)) > 1e-3 * np.linalg.norm(G[1]) * np.linalg.norm(moved)   # A_x, not imposed
    # NaN: off; a deviation within the evaluation's rounding: nothing moves
    for off_target in (math.nan, target + 1e-17):
        y, comp = projected(p, y0, off_target)
        assert np.array_equal(y, y0) and not comp.any()


def test_states_between_steps_and_at_a_terminal_event_are_projected_too():
    """Output times inside a step and event states come from side steps (docs/adaptive.md); they
    are projected as the steps' ends are (a review: 336 eps at output times, 16 at step ends)."""
    p = kepler(0.9)
    times = np.linspace(0.0, 100 * PERIOD, 4001)[1:]
    r = elimfast.integrate(p, ehbvm(8, 4), PERIOD / 200, n_steps=100 * 200, conserve=(L1, AY), solver=PROJECT,
                           t_eval=times)
    H = np.asarray(r.invariants["H"])
    assert np.max(np.abs(H - H[0])) <= 40 * np.finfo(float).eps
    stop = elimfast.integrate(p, ehbvm(8, 4), t_end=50 * PERIOD, rtol=1e-12, conserve=(L1, AY), solver=PROJECT,
                              events={"q1": {"expression": "q1 + 0.5", "direction": -1, "terminal": True}})
    assert stop.status == "complete" and stop.t[-1] < 1.5 * PERIOD
    H0 = p.H(p.y0.copy(), p.params)
    assert abs(p.H(np.array(stop.y_final), p.params) - H0) <= 40 * np.finfo(float).eps
    event_states = np.array(stop.events["q1"].y)
    assert len(event_states) == 1
    assert abs(p.H(event_states[0].copy(), p.params) - H0) <= 40 * np.finfo(float).eps


def test_gauss_on_an_H_it_does_not_keep_is_refused_and_on_a_quadratic_one_taken():
    """GAUSS(s) keeps every quadratic and linear invariant but not a non-quadratic H: projecting H
    would spend them (a user trial: L of Kepler from 2e-16 to 4e-6 with GAUSS(2)). On a
    quadratic H, which it keeps, the projection only removes the walk of rounding."""
    with pytest.raises(ParameterError, match=r"project_energy GAUSS\(2\) does not keep this H.*HBVM\(k,2\)"):
        elimfast.integrate(kepler(0.6), gauss(2), 0.05, n_steps=10, solver=PROJECT)
    oscillator = harmonic_oscillator()
    r = elimfast.integrate(oscillator, gauss(2), 0.1, n_steps=20000, store_every=100, solver=PROJECT)
    H = np.asarray(r.invariants["H"])
    assert np.max(np.abs(H - H[0])) <= 4 * np.finfo(float).eps * abs(H[0])


def test_ensembles_refuse_it():
    from elimfast.ensemble import integrate_ensemble
    p = kepler(0.6)
    with pytest.raises(ParameterError, match="project_energy.*ensembles"):
        integrate_ensemble(p, ehbvm(12, 3), 0.1, np.array([p.y0, p.y0]), n_steps=10,
                           solver=SolverSettings(project_energy=True))
    with pytest.raises(ParameterError, match="project_energy must be true or false"):
        SolverSettings(project_energy="yes")


def config(tmp_path, **integration):
    text = {"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.9}},
            "conserve": [L1, AY], "method": {"name": "ehbvm", "k": 8, "s": 4},
            "integration": {"h": "2*pi/100", **integration}, "solver": {"project_energy": True},
            "output": {"every": 50}}
    path = tmp_path / "projected.yaml"
    path.write_text(yaml.safe_dump(text))
    return path


def test_a_resumed_run_projects_onto_H_at_t0_bit_for_bit(tmp_path):
    """`--resume --set integration.t_end=LATER` equals the run made to LATER at once: the target
    is H(y0) of the run, not H where it resumed. inspect names the setting."""
    path = config(tmp_path, t_end="20*pi")
    whole, part = tmp_path / "whole.h5", tmp_path / "part.h5"
    run = [ELIMFAST, "run", str(path), "--quiet"]
    assert subprocess.run(run + ["-o", str(whole)], capture_output=True, text=True).returncode == 0
    done = subprocess.run(run + ["-o", str(part), "--set", "integration.t_end=7*pi"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    resumed = subprocess.run(run + ["-o", str(part), "--resume", "--set", "integration.t_end=20*pi"],
                             capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    import h5py
    with h5py.File(whole, "r") as a, h5py.File(part, "r") as b:
        np.testing.assert_array_equal(a["state/y"][:], b["state/y"][:])
        np.testing.assert_array_equal(a["y"][:], b["y"][:])
    shown = subprocess.run([ELIMFAST, "inspect", str(whole)], capture_output=True, text=True)
    assert "project_energy true" in shown.stdout


def test_a_setting_that_is_not_a_boolean_is_one_line_naming_the_key(tmp_path):
    path = config(tmp_path, t_end="2*pi")
    bad = subprocess.run([ELIMFAST, "run", str(path), "-o", str(tmp_path / "x.h5"), "--set",
                          "solver.project_energy=sometimes"], capture_output=True, text=True)
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1 and "solver.project_energy" in bad.stderr and "Traceback" not in bad.stderr


@pytest.mark.parametrize("first, then", [(True, False), (False, True)])
def test_resume_may_not_switch_it(tmp_path, first, then):
    """It changes the states the run goes on from (and, for a method that does not keep H, the
    steps), so --resume refuses a change of it either way, as of solver.lim_metric (a user trial:
    switched off at --resume, it was silently kept on)."""
    path = config(tmp_path, t_end="4*pi")
    out = tmp_path / "run.h5"
    run = [ELIMFAST, "run", str(path), "-o", str(out), "--quiet"]
    assert subprocess.run(run + ["--set", f"solver.project_energy={str(first).lower()}"], capture_output=True,
                          text=True).returncode == 0
    again = subprocess.run(run + ["--resume", "--set", "integration.t_end=8*pi", "--set",
                                  f"solver.project_energy={str(then).lower()}"], capture_output=True, text=True)
    assert again.returncode != 0
    assert "solver.project_energy changes the steps themselves" in again.stderr and "Traceback" not in again.stderr


def test_a_sweep_counts_the_projection_in_fixed_step_runs(tmp_path):
    sweep = {"base": {"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}},
                      "method": {"name": "ehbvm", "k": 8, "s": 4}, "integration": {"h": "2*pi/100", "t_end": "2*pi"}},
             "grid": [{"name": "projection", "key": "solver.project_energy", "values": [False, True]}]}
    path = tmp_path / "sweep.yaml"
    path.write_text(yaml.safe_dump(sweep))
    done = subprocess.run([ELIMFAST, "sweep", str(path), "--workers", "1", "--format", "csv"], capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr
    import csv
    import io
    rows = {row["projection"]: row for row in csv.DictReader(io.StringIO(done.stdout))}
    assert set(rows) == {"False", "True"}   # a boolean axis is written as such (True was 1.0)
    per_iteration = 8   # EHBVM(8,4) imposing nothing: k grad H a fixed-point or Newton iteration
    for label, extra in (("False", 0), ("True", 100)):
        row = rows[label]
        assert int(row["grad H evals"]) == per_iteration * int(row["iterations"]) + extra, row


def test_an_index_entry_whose_function_cannot_be_loaded_unpickles_as_a_miss(tmp_path):
    """A per-problem kernel leaves StaticFunctionType entries in the Numba indexes of the kernels'
    helpers; in a process that has not loaded their module (a python: file's, in elimfast's
    cache) they must unpickle to a type that matches nothing, not raise (a user trial: the
    per-problem kernel of built-in Kepler failed with "No module named 'elimfast_user_...'")."""
    import pickle
    from elimfast.kernels.static import UnresolvedStaticFunctionType

    # a plain function compiled by elimfast, as a python: file's are (per_problem._compiled): Numba
    # pickles it by reference to its module, which a fresh process cannot import
    (tmp_path / "elimfast_gone_module.py").write_text("SCALE = 2.0\n\n\ndef f(x):\n    return SCALE * x\n")
    script = (
        "import pickle, sys\n"
        f"sys.path.insert(0, {str(tmp_path)!r})\n"
        "import elimfast_gone_module\n"
        "from numba import njit, types\n"
        "from elimfast.kernels.static import StaticFunctionType\n"
        "compiled = njit('float64(float64)')(elimfast_gone_module.f)\n"
        "typed = StaticFunctionType(compiled) if sys.argv[1] == 'static' else types.Dispatcher(compiled)\n"
        "sys.stdout.buffer.write(pickle.dumps(typed))\n")
    payloads = {kind: subprocess.run([sys.executable, "-c", script, kind], capture_output=True, check=True).stdout
                for kind in ("static", "plain")}
    with pytest.raises(ModuleNotFoundError):   # what the Numba index held before
        pickle.loads(payloads["plain"])
    rebuilt = pickle.loads(payloads["static"])   # this process cannot import the module either
    assert isinstance(rebuilt, UnresolvedStaticFunctionType)
    assert "elimfast_gone_module.f" in rebuilt.name
