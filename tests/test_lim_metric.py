"""LIM's scaled metric (solver.lim_metric: scaled, docs/methods.md#the-metric-of-the-correction)
and its stable right-hand side: the invariants stay kept, the order stays 2s, the step stays
symmetric, the solar system's accuracy becomes HBVM's, and --resume may not switch the metric."""
import math

import numpy as np
import pytest
from click.testing import CliRunner

import elimfast
from elimfast.integrate import SolverSettings
from elimfast.methods import ghbvm, hbvm
from elimfast.problems import kepler, nbody

SCALED = SolverSettings(lim_metric="scaled")
L1, AY = "angular_momentum", "lrl_y"


def test_the_scaled_metric_keeps_the_invariants_and_the_order_and_is_symmetric():
    p = kepler(0.6)
    run = elimfast.integrate(p, ghbvm(12, 3), 0.1, t_end=100.0, conserve=(L1, AY), solver=SCALED)
    errors = run.relative_invariant_errors()
    assert max(errors["H"], errors[L1], errors[AY]) < 1e-13, errors
    # order 2s = 6 over one period: halving h divides the error by about 64
    coarse, fine = (elimfast.integrate(p, ghbvm(12, 3), 2 * math.pi / n, t_end=2 * math.pi, conserve=(L1, AY),
                                       solver=SCALED) for n in (40, 80))
    ratio = np.max(np.abs(coarse.y_final - p.y0)) / np.max(np.abs(fine.y_final - p.y0))
    assert 40 < ratio < 100, ratio
    # symmetric: 200 steps forward, then 200 back, return to y0 to rounding
    forward = elimfast.integrate(p, ghbvm(12, 3), 0.1, n_steps=200, conserve=(L1, AY), solver=SCALED)
    back = elimfast.integrate(p, ghbvm(12, 3), 0.1, n_steps=200, conserve=(L1, AY), solver=SCALED,
                              y0=forward.y_final, backward=True)
    assert np.max(np.abs(back.y_final - p.y0)) < 1e-12


def test_on_the_solar_system_the_scaled_metric_is_as_accurate_as_hbvm_and_the_euclidean_is_not():
    """The spec's Euclidean correction spreads the angular momenta's correction over all momenta
    by the positions (10-30 AU): Pluto's momentum, ~1e-11, took 5e-10 of itself per step at
    h = 50, and the run erred ~1000x HBVM's. The scaled one errs as HBVM does."""
    p = nbody()
    t_end = 1e4
    reference = elimfast.integrate(p, hbvm(12, 3), 6.25, t_end=t_end).y_final
    six = ("linear_momentum_x", "linear_momentum_y", "linear_momentum_z",
           "angular_momentum_x", "angular_momentum_y", "angular_momentum_z")
    error = {}
    for name, method, conserve, solver in (("hbvm", hbvm(12, 3), (), "newton"),
                                           ("euclidean", ghbvm(12, 3), six, "newton"),
                                           ("scaled", ghbvm(12, 3), six, SCALED)):
        run = elimfast.integrate(p, method, 50.0, t_end=t_end, conserve=conserve, solver=solver)
        error[name] = float(np.max(np.abs(run.y_final - reference)))
        if conserve:
            assert max(run.relative_invariant_errors()[c] for c in six) < 1e-12, name
    assert error["scaled"] < 2 * error["hbvm"] and error["euclidean"] > 100 * error["hbvm"], error


def test_resume_may_not_switch_the_metric(tmp_path):
    from elimfast_cli.main import cli
    config = tmp_path / "lim.yaml"
    config.write_text("problem: {builtin: kepler}\nconserve: [angular_momentum]\nmethod: {name: ghbvm, k: 6, s: 3}\n"
                      "integration: {h: 0.1, n_steps: 20}\n")
    out = tmp_path / "lim.h5"
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(out), "-q"]).exit_code == 0
    resumed = CliRunner().invoke(cli, ["run", str(config), "-o", str(out), "--resume", "--set",
                                       "integration.n_steps=40", "--set", "solver.lim_metric=scaled"])
    assert resumed.exit_code == 2, resumed.output
    assert "solver.lim_metric changes the steps themselves" in resumed.stderr, resumed.stderr
    more_halvings = CliRunner().invoke(cli, ["run", str(config), "-o", str(out), "--resume", "--set",
                                             "integration.n_steps=40", "--set", "solver.max_halvings=6", "-q"])
    assert more_halvings.exit_code == 0, more_halvings.output


def test_a_config_s_metric_is_stored_shown_and_resumed_with(tmp_path):
    """solver.lim_metric was left out of the resolved config a run file stores: inspect did not
    show it, and --resume of configs/nbody.yaml would have gone on with the Euclidean metric."""
    from elimfast_cli.main import cli
    config = tmp_path / "lim.yaml"
    config.write_text("problem: {builtin: kepler}\nconserve: [angular_momentum]\nmethod: {name: ghbvm, k: 6, s: 3}\n"
                      "solver: {lim_metric: scaled}\nintegration: {h: 0.1, n_steps: 40}\n")
    whole, part = tmp_path / "whole.h5", tmp_path / "part.h5"
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(whole), "-q"]).exit_code == 0
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(part), "-q", "--set",
                                    "integration.n_steps=20"]).exit_code == 0
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(part), "-q", "--resume", "--set",
                                    "integration.n_steps=40"]).exit_code == 0
    assert np.array_equal(elimfast.load(part).y_final, elimfast.load(whole).y_final)
    assert "lim_metric scaled" in CliRunner().invoke(cli, ["inspect", str(whole)]).stdout


def test_the_metric_is_refused_on_a_method_without_lims_correction(tmp_path):
    """A user trial: solver.lim_metric: scaled on EHBVM was accepted and silently ignored."""
    from elimfast_cli.main import cli
    from elimfast.errors import ParameterError
    config = tmp_path / "elim.yaml"
    config.write_text("problem: {builtin: kepler}\nconserve: [angular_momentum]\nmethod: {name: ehbvm, k: 6, s: 3}\n"
                      "solver: {lim_metric: scaled}\nintegration: {h: 0.1, n_steps: 4}\n")
    refused = CliRunner().invoke(cli, ["run", str(config), "-o", str(tmp_path / "e.h5")])
    assert refused.exit_code == 2, refused.output
    assert (f"{config}:4: solver.lim_metric: 'scaled' applies to LIM and GHBVM only" in refused.stderr
            and "EHBVM(6,3) has none" in refused.stderr), refused.stderr
    assert not (tmp_path / "e.h5").exists()
    # a user trial: "leave lim_metric out" cannot be done by --set on a config that sets it (configs/nbody.yaml),
    # and --set solver.lim_metric=null is refused; the value that undoes it is named, and works
    assert "or set it to 'euclidean' (the default)" in refused.stderr
    undone = CliRunner().invoke(cli, ["run", str(config), "-o", str(tmp_path / "e.h5"), "-q",
                                      "--set", "solver.lim_metric=euclidean"])
    assert undone.exit_code == 0, undone.output
    for method in (elimfast.methods.ehbvm(6, 3), elimfast.methods.gauss(3)):
        with pytest.raises(ParameterError, match="lim_metric 'scaled' applies to LIM and GHBVM only"):
            elimfast.integrate(kepler(0.6), method, 0.1, n_steps=2, solver=SCALED)
