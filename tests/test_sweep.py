"""Sweeps (elimfast.sweep) and the paper's reproduction (elimfast.paper)."""
import math
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

from elimfast.io.hdf5 import OutputError

from elimfast import paper
from elimfast.archive import load
from elimfast.sweep import SweepError, load_sweep, orders_of, errors_of, run_sweep, table_rows, format_table

ROOT = Path(__file__).resolve().parents[1]
BASE = {
    "problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}},
    "method": {"name": "ehbvm", "k": 12, "s": 3},
    "conserve": ["angular_momentum"],
    "integration": {"h": "pi/30", "t_end": "2*pi"},
}


def write_sweep(tmp_path, data, name="sweep.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def test_grid_is_the_product_of_the_axes_and_variants_replace_whole_sections(tmp_path):
    path = write_sweep(tmp_path, {
        "base": BASE,
        "set": {"integration": {"t_end": "4*pi"}},
        "grid": [
            {"name": "method", "values": [{"label": "G2", "set": {"method": {"name": "gauss", "s": 2},
                                                                  "conserve": []}},
                                          {"label": "E", "set": {}}]},
            {"name": "h", "key": "integration.h", "values": ["pi/30", "pi/60", "pi/120"]},
        ],
        "error": {"exact": "initial"}, "order_axis": "h"})
    spec = load_sweep(path)
    assert [r.label for r in spec.runs] == ["G2/pi/30", "G2/pi/60", "G2/pi/120", "E/pi/30", "E/pi/60", "E/pi/120"]
    gauss_run = spec.runs[0].config
    assert gauss_run["method"] == {"name": "gauss", "s": 2}        # replaced: no k inherited
    assert gauss_run["integration"] == {"h": "pi/30", "t_end": "4*pi"}  # merged
    assert spec.runs[3].config["method"]["k"] == 12


def test_an_order_in_h_of_adaptive_runs_is_refused(tmp_path):
    """order_axis: h over runs with rtol gave an 'order' in their first step, which is all h is to
    them; such a sweep is refused when it is read, naming the run and the key."""
    grid = [{"name": "h", "key": "integration.h", "values": ["pi/30", "pi/60"]}]
    adaptive = {**BASE, "method": {"name": "ehbvm", "s": 4}, "integration": {"rtol": 1e-10, "t_end": "2*pi"}}
    with pytest.raises(SweepError, match=r"order_axis: the axis 'h' sets h, but run 'pi/30' has adaptive steps "
                                         r"\(integration.rtol\), where h is only the first step"):
        load_sweep(write_sweep(tmp_path, {"base": adaptive, "grid": grid, "order_axis": "h"}))
    assert load_sweep(write_sweep(tmp_path, {"base": BASE, "grid": grid, "order_axis": "h"}, "fixed.yaml")).order_axis == "h"


def test_a_sweep_wide_method_that_names_its_family_replaces_the_base_method(tmp_path):
    """A sweep-wide set: {method: {name: hbvm, s: 4}} over an EHBVM(12,3) base merged and ran
    HBVM(12,4), inheriting k. A method naming its family replaces the base's (as a variant's and
    the reference's do); one without a name changes only what it gives; other sections merge."""
    grid = [{"name": "h", "key": "integration.h", "values": ["pi/30"]}]
    whole = load_sweep(write_sweep(tmp_path, {"base": BASE, "set": {"method": {"name": "hbvm", "s": 4},
                                                                     "integration": {"t_end": "4*pi"}},
                                              "grid": grid}))
    assert whole.runs[0].config["method"] == {"name": "hbvm", "s": 4}
    assert whole.runs[0].config["integration"] == {"h": "pi/30", "t_end": "4*pi"}
    shorthand = load_sweep(write_sweep(tmp_path, {"base": BASE, "set": {"method": "GAUSS(2)", "conserve": []},
                                                  "grid": grid}, "shorthand.yaml"))
    assert shorthand.runs[0].config["method"] == {"name": "gauss", "s": 2}
    tweak = load_sweep(write_sweep(tmp_path, {"base": BASE, "set": {"method": {"s": 4}}, "grid": grid}, "tweak.yaml"))
    assert tweak.runs[0].config["method"] == {"name": "ehbvm", "k": 12, "s": 4}


@pytest.mark.parametrize("data,match", [
    ({"base": BASE, "grids": []}, "grids: unknown key"),
    ({"base": 3}, "base: give a run config"),
    ({"base": BASE, "grid": [{"name": "h"}]}, r"grid\[0\]: an axis is a mapping"),
    ({"base": BASE, "grid": [{"name": "m", "values": [{"label": "a", "set": {}}, {"label": "a", "set": {}}]}]},
     "same label 'a'"),
    # a repeated value of a plain axis: named (a user trial read only 'give the variants distinct labels'),
    # and so is one value written two ways (the last note: [0.1, 1/10] ran one run twice)
    ({"base": BASE, "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30", "pi/60", "pi/30"]}]},
     r"grid\[0\]\.values\[2\]: 'pi/30' is the value of grid\[0\]\.values\[0\] \('pi/30'\): the two runs would be"),
    ({"base": BASE, "grid": [{"name": "h", "key": "integration.h", "values": [0.1, "1/10"]}]},
     r"grid\[0\]\.values\[1\]: '1/10' is the value of grid\[0\]\.values\[0\] \(0\.1\): the two runs would be one"),
    ({"base": BASE, "grid": [{"name": "s", "key": "method.s", "values": [3, 4, 3.0], "labels": ["a", "b", "c"]}]},
     r"grid\[0\]\.values\[2\]: 3\.0 is the value of grid\[0\]\.values\[0\] \(3\)"),
    ({"base": BASE, "order_axis": "h"}, "order_axis: names no axis"),
    # the order is taken along the axis's values: an axis without sizes is refused, not left empty
    ({"base": BASE, "grid": [{"name": "m", "values": [{"label": "a", "set": {}}, {"label": "b", "set": {}}]}],
      "order_axis": "m"}, "order_axis: the axis 'm' is a list of variants"),
    ({"base": BASE, "grid": [{"name": "m", "key": "method.name", "values": ["ehbvm", "ghbvm"]}], "order_axis": "m"},
     r"order_axis: the axis 'm' has the value 'ehbvm' \(grid\[0\]\.values\[0\]\), not a positive number"),
    ({"base": BASE, "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30", "-pi/60"]}], "order_axis": "h"},
     r"order_axis: the axis 'h' has the value '-pi/60' \(grid\[0\]\.values\[1\]\), not a positive number"),
    ({"base": BASE, "error": {"exact": "period"}}, "error.exact"),
    # a misspelt axis key failed every run alike (one line each, exit 1), as if the integrations had failed
    ({"base": BASE, "grid": [{"name": "h", "key": "integration.hh", "values": ["pi/30"]}]},
     r"grid\[0\]\.key: integration\.hh: unknown key; did you mean 'h'\?"),
    # a user trial: an internal error (IndexError) before the configs' keys refused brackets
    ({"base": BASE, "grid": [{"name": "c", "key": "conserve[0]", "values": ["lrl_x"]}]},
     r"grid\[0\]\.key: conserve\[0\]: not a key path \(names joined by dots, no indices\)"),
    ({"base": BASE, "grid": [{"name": "s", "key": "methd.s", "values": [3]}]},
     r"grid\[0\]\.key: methd\.s: unknown key; did you mean 'method'\?"),
    # a user trial: misspelt keys of an axis or a variant were dropped silently (the axis then
    # named after its key, the variant labelled 0, 1, ...), and a repeated axis name was reported
    # as 'two runs get the same label'
    ({"base": BASE, "grid": [{"nme": "h", "key": "integration.h", "values": ["pi/30"]}]},
     r"grid\[0\]\.nme: unknown key; did you mean 'name'\? \(known: name, key, values, labels\)"),
    ({"base": BASE, "grid": [{"name": "m", "values": [{"lable": "a", "set": {}}]}]},
     r"grid\[0\]\.values\[0\]\.lable: unknown key; did you mean 'label'\?"),
    ({"base": BASE, "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30"]},
                             {"name": "h", "key": "integration.t_end", "values": ["2*pi"]}]},
     r"grid\[1\]\.name: repeats the axis name 'h' of grid\[0\]"),
    # a user trial: two axes on one key ran the later axis's values under the earlier one's labels
    ({"base": BASE, "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30"]},
                             {"name": "h2", "key": "integration.h", "values": ["pi/60"]}]},
     r"grid\[1\]\.key: integration\.h is also set by the axis 'h' \(grid\[0\], key integration\.h\)"),
    ({"base": BASE, "grid": [{"name": "s", "key": "method.s", "values": [3]},
                             {"name": "m", "key": "method", "values": ["GAUSS(2)"]}]},
     r"grid\[1\]\.key: method is also set by the axis 's'"),
    # ... so did a variant setting the section of a plain axis's key (h ran 0.05 under the labels 0.1, 0.2)
    ({"base": BASE, "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30", "pi/60"]},
                             {"name": "v", "values": [{"label": "x", "set": {"integration": {"h": 0.05}}}]}]},
     r"grid\[1\]: its variants set integration, which holds the key integration\.h of the axis 'h'"),
    # ... and a misspelt parameter of a problem by expressions, by an axis, a whole-section axis or the set
    ({"base": str(ROOT / "configs" / "kepler_expressions.yaml"),
      "grid": [{"name": "mu", "key": "problem.parameters.mux", "values": [1.0, 2.0]}]},
     r"problem\.parameters\.mux: \(run '1\.0', from the sweep's set or an axis\) no expression uses it.*"
     r"did you mean 'mu'"),
    ({"base": str(ROOT / "configs" / "kepler_expressions.yaml"),
      "grid": [{"name": "p", "key": "problem.parameters", "values": [{"mu": 1, "ecc": 0.5},
                                                                     {"mu": 1, "ecc": 0.5, "eccc": 0.7}],
                "labels": ["a", "b"]}]},
     r"problem\.parameters\.eccc: \(run 'b'.*did you mean 'ecc'"),
    ({"base": str(ROOT / "configs" / "kepler_expressions.yaml"), "set": {"problem": {"parameters": {"muu": 2}}}},
     r"problem\.parameters\.muu: .*no expression uses it"),
    # a variant replacing the problem (or the method) with a section naming none: every run failed with
    # "problem: no problem given", which did not say that the variant had replaced the whole section
    ({"base": BASE, "grid": [{"name": "e", "values": [{"label": "low", "set": {"problem": {"parameters": {
        "eccentricity": 0.3}}}}]}]},
     r"grid\[0\]\.values\[0\]\.set\.problem: replaces the base's whole problem section .* naming no problem "
     r"\(builtin, python, hamiltonian\); give the whole section, or vary problem\.parameters\.<key> with a plain axis"),
    ({"base": BASE, "grid": [{"name": "i", "values": [{"label": "b", "set": {"integration": {"t_end": 20}}}]}]},
     r"grid\[0\]\.values\[0\]\.set\.integration: replaces the base's whole integration section .* naming no "
     r"integration \(h, rtol, step_control, epsilon\)"),
    ({"base": BASE, "grid": [{"name": "m", "values": [{"label": "s4", "set": {"method": {"s": 4}}}]}]},
     r"grid\[0\]\.values\[0\]\.set\.method: replaces the base's whole method section .* naming no method \(name\)"),
    # variants under an axis with a key: every run failed with 'events.set.events: unknown key' (a user trial)
    ({"base": BASE, "grid": [{"name": "ev", "key": "events", "values": [
        {"label": "stop", "set": {"events": {"apo": {"expression": "q1*p1+q2*p2", "terminal": True}}}}]}]},
     r"grid\[0\]\.values\[0\]: is a variant \(\{label, set\}\), but the axis has a key \(events\), whose values "
     r"are that key's: remove 'key' to make it an axis of variants"),
])
def test_bad_sweep_files_give_one_line_errors(tmp_path, data, match):
    path = write_sweep(tmp_path, data)
    with pytest.raises(SweepError, match=match) as caught:
        load_sweep(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("kills", ["always", "once"])
def test_a_worker_that_dies_fails_only_its_run_and_the_sweep_goes_on(tmp_path, monkeypatch, kills):
    """A user trial: kill -9 of one sweep worker (as the out-of-memory killer would) ended the whole
    sweep in 'internal error: BrokenProcessPool', every other run dropped. Now the runs in flight are
    run again, one at a time; a run whose worker dies twice fails with that reason, and every other
    run completes as it would have (the same numbers as the serial sweep). A worker killed once (the
    user's kill) costs nothing: its run completes on the second try."""
    import os
    import signal
    from elimfast import sweep as sweeps

    path = write_sweep(tmp_path, {
        "base": BASE,
        "grid": [{"name": "h", "key": "integration.h", "values": ["2*pi/40", "2*pi/80", "2*pi/160", "2*pi/320"]}],
        "error": {"exact": "initial"}})
    spec = load_sweep(path)
    serial, _ = run_sweep(spec, workers=1)
    victim = serial[2].label        # not the shortest: that one runs in the parent before the pool forks
    marker = tmp_path / "killed-once"
    original = sweeps._execute

    def dying(label, *args):    # forked into the workers with the module
        if label == victim and (kills == "always" or not marker.exists()):
            marker.touch()
            os.kill(os.getpid(), signal.SIGKILL)
        return original(label, *args)

    monkeypatch.setattr(sweeps, "_execute", dying)
    seen, said = [], []
    outcomes, _ = run_sweep(spec, workers=2, on_done=lambda outcome, done, total: seen.append((done, total)),
                            on_message=said.append)
    assert said and all(line.startswith("a worker process died (killed, out of memory, or a crash) while running ")
                        for line in said), said
    assert victim in said[0] and said[0].endswith(("running them again, one at a time", "running it again, one at a time"))
    if kills == "always":   # the second death, the victim alone
        assert said[-1] == (f"a worker process died (killed, out of memory, or a crash) while running {victim}: "
                            f"{victim} failed: its worker died twice")
    else:
        assert len(said) == 1
    assert [o.label for o in outcomes] == [o.label for o in serial]
    assert seen == [(done, 4) for done in range(1, 5)]
    for before, after in zip(serial, outcomes):
        if after.label == victim and kills == "always":
            assert after.status.startswith(f"failed: {path} [{victim}]: its worker process died while running it, "
                                           "twice"), after.status
            assert after.y_final is None
        else:
            assert after.status == "complete", after.status
            np.testing.assert_array_equal(after.y_final, before.y_final)
            assert after.iterations_total == before.iterations_total


def test_sweep_runs_in_parallel_give_the_same_numbers_and_orders(tmp_path):
    path = write_sweep(tmp_path, {
        "base": BASE,
        "grid": [{"name": "h", "key": "integration.h", "values": ["2*pi/40", "2*pi/80", "2*pi/160"]}],
        "error": {"exact": "initial"}, "order_axis": "h"})
    spec = load_sweep(path)
    serial, _ = run_sweep(spec, workers=1)
    parallel, _ = run_sweep(spec, workers=2)
    for a, b in zip(serial, parallel):
        np.testing.assert_array_equal(a.y_final, b.y_final)
        assert a.iterations_total == b.iterations_total
    orders = orders_of(spec, serial, errors_of(spec, serial, None))
    assert all(abs(orders[o.label] - 6.0) < 0.3 for o in serial[1:])
    header, rows = table_rows(spec, serial, None)
    assert header[:3] == ["h", "error", "order"]
    markdown = format_table(header, rows)
    assert markdown.count("\n") == 2 + len(rows)
    csv_text = format_table(header, rows, "csv")
    assert csv_text.splitlines()[0].startswith("h,error,order")


def test_the_observed_order_is_taken_along_any_axis_of_numbers_and_named_after_it(tmp_path):
    """A user trial: order_axis: epsilon (the time-scale controller's) was accepted, and the order
    column came out empty, though the errors fell 64x per halving of epsilon (order 6): orders
    were taken in each run's h, which a time-scale run does not have. They are taken in the axis's
    values now, log(e1/e2)/log(x1/x2), in a column 'order in epsilon' (an axis of variants, or of
    values that are no positive numbers, is refused at load: test_bad_sweep_files_give_one_line_errors)."""
    base = {**BASE, "method": {"name": "gauss", "s": 3}, "conserve": [],
            "integration": {"step_control": "time_scale", "t_end": "2*pi"}}
    epsilons = [0.2, 0.1, 0.05]
    path = write_sweep(tmp_path, {"base": base, "grid": [
        {"name": "epsilon", "key": "integration.epsilon", "values": epsilons}],
        "error": {"exact": "initial"}, "order_axis": "epsilon"})
    spec = load_sweep(path)
    outcomes, _ = run_sweep(spec, workers=1)
    errors = errors_of(spec, outcomes, None)
    orders = orders_of(spec, outcomes, errors)
    for (e0, previous), (e1, current) in zip(zip(epsilons, outcomes), zip(epsilons[1:], outcomes[1:])):
        expected = math.log(errors[previous.label] / errors[current.label]) / math.log(e0 / e1)
        assert orders[current.label] == pytest.approx(expected, rel=1e-14)
        assert abs(orders[current.label] - 6.0) < 0.1, orders   # GAUSS3: error ~ epsilon^6
    assert math.isnan(orders[outcomes[0].label])
    header, rows = table_rows(spec, outcomes, None)
    assert header[:3] == ["epsilon", "error", "order in epsilon"]
    assert rows[0][2] == "" and all(float(row[2]) > 5 for row in rows[1:])
    csv_header, csv_rows = table_rows(spec, outcomes, None, "csv")
    column = csv_header.index("order in epsilon")
    assert [float(row[column]) for row in csv_rows[1:]] == [orders[o.label] for o in outcomes[1:]]


def test_the_order_next_to_a_run_without_an_error_is_taken_against_the_run_before_it(tmp_path):
    """A user trial: h = pi/30, 0.7 (refused: no whole number of steps), pi/60 left the pi/60 row's
    order empty, though the order between pi/30 and pi/60 is there to take."""
    base = {**BASE, "method": {"name": "gauss", "s": 2}, "conserve": [], "integration": {"t_end": "2*pi"}}
    path = write_sweep(tmp_path, {"base": base, "grid": [
        {"name": "h", "key": "integration.h", "values": ["pi/30", 0.7, "pi/60"]}],
        "error": {"exact": "initial"}, "order_axis": "h"})
    spec = load_sweep(path)
    outcomes, _ = run_sweep(spec, workers=1)
    assert [o.ok for o in outcomes] == [True, False, True]
    errors = errors_of(spec, outcomes, None)
    orders = orders_of(spec, outcomes, errors)
    expected = math.log(errors[outcomes[0].label] / errors[outcomes[2].label]) / math.log(2.0)
    assert orders[outcomes[2].label] == pytest.approx(expected, rel=1e-12) and abs(expected - 4.0) < 0.3   # GAUSS2
    assert math.isnan(orders[outcomes[0].label]) and math.isnan(orders[outcomes[1].label])


def test_a_failing_run_does_not_stop_the_others(tmp_path):
    path = write_sweep(tmp_path, {
        "base": {**BASE, "solver": {"max_iter": 30, "method": "fixed_point", "max_halvings": 0}},
        "grid": [{"name": "h", "key": "integration.h", "values": ["2*pi/40", "2*pi/4"]}],
        "error": {"reference": {"set": {"integration": {"h": "2*pi/200"}}}}})
    outcomes, reference = run_sweep(load_sweep(path), workers=2)
    assert outcomes[0].ok and reference.ok
    assert not outcomes[1].ok and outcomes[1].status.startswith("failed: ")
    assert "did not converge" in outcomes[1].status or "singular" in outcomes[1].status
    errors = errors_of(load_sweep(path), outcomes, reference)
    assert 0 < errors[outcomes[0].label] < 1e-3 and math.isnan(errors[outcomes[1].label])


@pytest.mark.parametrize("axis,key", [
    ({"name": "e", "key": "problem.parameters.eccentricity", "values": [0.6, 0.3]}, "problem.parameters.eccentricity"),
    ({"name": "T", "key": "integration.t_end", "values": ["2*pi", "4*pi"]}, "integration (its t0 and t_end)"),
    ({"name": "start", "values": [{"label": "other", "set": {"problem": {"builtin": "kepler", "initial": {
        "q1": 0.5, "q2": 0.0, "p1": 0.0, "p2": 1.5}}}}]}, "problem.initial"),
])
def test_a_reference_error_refuses_runs_of_another_problem_or_interval(tmp_path, axis, key):
    """The one reference run is the base's: a grid over the eccentricity was compared with the
    reference of e = 0.6, and the table showed errors of 0.3-2.6 (and orders of 1e-16) as if
    they were the method's. Such a sweep must be refused, naming the run and the key."""
    path = write_sweep(tmp_path, {"base": BASE, "grid": [axis],
                                  "error": {"reference": {"set": {"integration": {"h": "2*pi/200"}}}}})
    with pytest.raises(SweepError) as caught:
        load_sweep(path)
    message = str(caught.value)
    assert re.match(rf"{re.escape(str(path))}:\d+: error\.reference: run ", message) and f" differs from the reference run in {key}," \
        in message, message
    # runs of the base's problem and interval, whatever their h, method or steps, are fine
    same = write_sweep(tmp_path, {"base": {**BASE, "integration": {"h": "pi/30", "n_steps": 60}},
                                  "grid": [{"name": "n", "key": "integration.n_steps", "values": [60, 120]},
                                           {"name": "h", "key": "integration.h", "values": ["pi/30", "pi/60"]}],
                                  "error": {"reference": {"set": {"integration": {"h": "2*pi/200", "n_steps": 200}}}}},
                             "same.yaml")
    with pytest.raises(SweepError, match="run '60/pi/60' differs from the reference run in integration"):
        load_sweep(same)   # 60 steps of pi/60: half the interval


@pytest.mark.usefixtures("allow_python")
def test_a_reference_set_replaces_the_method_and_a_reference_that_does_not_load_is_refused_before_any_run(tmp_path):
    """A user trial (a Lennard-Jones sweep): error.reference.set's method {name: gauss, s: 6}
    merged into the base's {name: ehbvm, k: 12, s: 3}, kept its k, and failed with 'method.k: does
    not apply: gauss(s) takes no k; remove it', a key the sweep file did not have; that was found
    after all 16 grid runs had run (exit 1), and the message held a NUL byte ('[\\0reference]'). The
    reference's method replaces the base's, as a variant's does (the rest still merges); its config
    is loaded with the sweep file (exit 2, no run); no message names the run by its internal label."""
    from click.testing import CliRunner
    from elimfast_cli.main import cli
    from elimfast import sweep as sweeps

    reference_set = {"method": {"name": "gauss", "s": 6}, "conserve": [], "integration": {"h": "2*pi/200"}}
    grid = [{"name": "h", "key": "integration.h", "values": ["2*pi/40", "2*pi/80"]}]
    path = write_sweep(tmp_path, {"base": BASE, "grid": grid, "error": {"reference": {"set": reference_set}}})
    spec = load_sweep(path)
    assert spec.reference["method"] == {"name": "gauss", "s": 6}
    assert spec.reference["integration"] == {"h": "2*pi/200", "t_end": "2*pi"}   # merged, as before
    outcomes, reference = run_sweep(spec, workers=1)
    assert reference.ok and reference.resolved["method"] == {"name": "gauss", "s": 6}
    assert all(0 < error < 1e-4 for error in errors_of(spec, outcomes, reference).values())

    # a reference that does not load: one line naming the sweep file and the key, before any run
    bad_set = {**reference_set, "method": {"name": "gauss", "s": 6, "k": 12}}
    bad = write_sweep(tmp_path, {"base": BASE, "grid": grid, "error": {"reference": {"set": bad_set}}}, "bad.yaml")
    with pytest.raises(SweepError) as caught:
        load_sweep(bad)
    assert str(caught.value).startswith(f"{bad}: error.reference.set: method.k: does not apply: gauss(s) takes no k")
    out = tmp_path / "bad.h5"
    result = CliRunner().invoke(cli, ["sweep", str(bad), "-o", str(out), "--workers", "1"])
    assert result.exit_code == 2, result.output
    assert result.stderr == f"error: {caught.value}\n" and result.stdout == ""   # no run started, no table
    assert not out.exists()
    # the workers name the reference run so too (a python: file edited after the sweep was loaded)
    status = sweeps._execute(sweeps.REFERENCE_LABEL, {}, spec.reference | {"method": bad_set["method"]},
                             str(path), False).status
    assert status.startswith(f"failed: {path}: error.reference: method.k: ")
    assert not any(ord(c) < 32 for c in status + result.stderr.rstrip("\n"))
    # a fault of the base (a python: file the runs share) is the reference's too, said as the base's
    (tmp_path / "broken.py").write_text("def H(y, params):\n    return (\n")
    shared = write_sweep(tmp_path, {"base": {**BASE, "problem": {"python": "broken.py"}, "conserve": []},
                                    "grid": grid, "error": {"reference": {"set": reference_set}}}, "shared.yaml")
    with pytest.raises(SweepError, match=r"shared\.yaml: error\.reference: the reference run \(the base with "
                                         r"error\.reference\.set\) does not load: problem\.python: .*broken\.py.*SyntaxError"):
        load_sweep(shared)


def test_a_run_that_failed_at_its_first_step_shows_no_figures_never_zero_errors(tmp_path):
    """A run failing at step 1 kept only samples of its initial state, and the table showed
    0.000e+00 for every invariant error: a failed run read as a perfect one."""
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    path = write_sweep(tmp_path, {
        "base": {**BASE, "solver": {"max_iter": 30, "method": "fixed_point", "max_halvings": 0}},
        "grid": [{"name": "h", "key": "integration.h", "values": ["2*pi/40", "2*pi/4"]}],
        "error": {"reference": {"set": {"integration": {"h": "2*pi/200"}}}}, "order_axis": "h"})
    spec = load_sweep(path)
    outcomes, reference = run_sweep(spec, workers=1)
    complete, failed = outcomes
    assert complete.ok and failed.status.startswith("failed: ") and "at step 1 " in failed.status
    assert all(math.isnan(value) for value in failed.invariant_errors.values())   # no step: no figure
    header, rows = table_rows(spec, outcomes, reference)
    figures = [i for i, name in enumerate(header) if name.startswith("max ") or name in ("error", "order")]
    assert len(figures) == 3 + 2 * 4   # error, order, max |alpha|, then 2 per invariant (H, L, A_x, A_y)
    assert [rows[1][i] for i in figures] == ["failed"] * len(figures)
    assert "0.000e+00" not in " ".join(rows[1])
    assert all(float(rows[0][i]) > 0 for i in figures if header[i] not in ("order",))
    csv_header, csv_rows = table_rows(spec, outcomes, reference, "csv")
    assert [csv_rows[1][csv_header.index(header[i])] for i in figures] == [""] * len(figures)
    # one run of the sweep file, inspected
    out = tmp_path / "sweep.h5"
    result = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(out), "--workers", "1", "-q"])
    assert result.exit_code == 1, result.output
    inspected = CliRunner().invoke(cli, ["inspect", f"{out}:/runs/2*pi|4"])
    assert inspected.exit_code == 0, inspected.output
    assert ("invariants   no figures: the run failed at its first step, so no state after t0 to compare with I(t0)"
            in inspected.stdout)
    assert "0.000e+00" not in inspected.stdout


def test_a_sweep_of_fixed_steps_with_output_times_runs(tmp_path):
    """Fixed h with output.times (or events) runs through the adaptive kernel, whose run has
    no n_samples_between: the sweep's memory estimate raised AttributeError, an internal error."""
    path = write_sweep(tmp_path, {"base": {**BASE, "output": {"times": {"start": 1, "stop": "2*pi", "n": 4}}},
                                  "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30", "pi/60"]}]})
    outcomes, _ = run_sweep(load_sweep(path), workers=1)
    assert [o.status for o in outcomes] == ["complete", "complete"]
    assert [o.result.t.size for o in outcomes] == [4, 4] and outcomes[0].result.t[0] == 1.0


@pytest.fixture(scope="module")
def reproduction(tmp_path_factory):
    return paper.reproduce(ROOT / "configs" / "paper", tmp_path_factory.mktemp("paper-out"), workers=2)


def test_paper_tables_1_and_3_are_reproduced(reproduction):
    for h, column, value, published, relative, order in reproduction["table1"]:
        if h not in paper.ROUND_OFF_ROWS:
            assert abs(relative) < paper.TOLERANCE, (h, column, value, published)
            assert math.isnan(order) or abs(order - 6.0) < 0.2
    for h, column, value, published, relative in reproduction["table3"]:
        if h not in paper.ROUND_OFF_ROWS:
            assert abs(relative) < paper.TOLERANCE, (h, column, value, published)
    for h, column, total, published in reproduction["table2"]:
        if h == "pi/30":
            assert abs(total / published - 1.0) < 0.15


def test_paper_markdown_shows_each_value_beside_the_paper(reproduction, tmp_path_factory):
    out = reproduction["figures"][0].parent
    table = (out / "table1.md").read_text()
    assert "| pi/30 | GAUSS3 | 1.941" in table and "1.942e-03" in table
    assert "**(!)**" not in table.split("pi/240")[0]
    for name in ("table2.md", "table3.md", "long_run.md"):
        assert (out / name).stat().st_size > 200


def test_paper_figures_are_drawn_and_show_what_the_paper_says(reproduction):
    import matplotlib.image
    assert len(reproduction["figures"]) == 4
    for path in reproduction["figures"]:
        pixels = matplotlib.image.imread(path)
        assert pixels.std() > 0.05, path  # not blank
    summary = reproduction["long_run"]
    # Figure 2: GAUSS3 keeps H bounded but not to round-off
    first, last = summary["GAUSS3"]["H"]
    assert first > 1e-8 and last < 1.5 * first
    # Figure 3: HBVM keeps H, its angular-momentum error is bounded
    first, last = summary["HBVM(12,3)"]["angular_momentum"]
    assert summary["HBVM(12,3)"]["H"][1] < 1e-12 and 1e-10 < last < 1.5 * first
    # Figure 4: the LRL vector drifts unless imposed
    for method in ("GAUSS3", "HBVM(12,3)", "EHBVM(12,3) L1", "GHBVM(12,3) L1"):
        first, last = summary[method]["lrl"]
        assert last > 3 * first, method
    for method in ("EHBVM(12,3) L1,L2", "GHBVM(12,3) L1,L2"):
        assert summary[method]["lrl"][1] < 1e-11, method


def test_cli_sweep_stores_every_run_marks_the_failed_one_and_exits_1(tmp_path):
    import h5py
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    path = write_sweep(tmp_path, {
        "base": {**BASE, "solver": {"max_iter": 30, "method": "fixed_point", "max_halvings": 0}},
        "grid": [{"name": "h", "key": "integration.h", "values": ["2*pi/40", "2*pi/4"], "labels": ["small", "huge"]}],
        "error": {"reference": {"set": {"integration": {"h": "2*pi/200"}}}}})
    out = tmp_path / "sweep.h5"
    result = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(out), "--workers", "2", "--format", "csv", "-q"])
    assert result.exit_code == 1, result.output
    lines = result.stdout.strip().splitlines()
    # CSV: h as a number at full precision, beside it as written and the run's label
    assert lines[0].startswith("h,h_expression,h_label,error,") and "failed:" in lines[2]
    assert lines[1].startswith(f"{2 * math.pi / 40!r},2*pi/40,small,")
    assert "1 of 2 runs failed" in result.stderr
    with h5py.File(out) as f:
        assert f.attrs["format"] == "elimfast-sweep"
        assert set(f["runs"]) == {"small", "huge"}
        assert f["runs/small"].attrs["status"] == "complete"
        assert f["runs/small/steps/alpha"].shape == (40, 1)
        assert f["runs/small/y"].shape == (41, 4)
        assert str(f["runs/huge"].attrs["status"]).startswith("failed:")


def test_cli_sweep_bad_file_is_one_line_exit_2(tmp_path):
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    path = write_sweep(tmp_path, {"base": BASE, "order_axis": "h"})
    result = CliRunner().invoke(cli, ["sweep", str(path)])
    assert result.exit_code == 2
    assert result.stderr.count("\n") == 1 and "order_axis" in result.stderr and "Traceback" not in result.stderr


def test_ensemble_sweep_runs_in_the_parallel_kernel_and_matches_single_runs(tmp_path):
    import h5py
    from click.testing import CliRunner

    import elimfast
    from elimfast.sweep import run_ensemble_sweep
    from elimfast_cli.main import cli

    path = write_sweep(tmp_path, {"base": {**BASE, "integration": {"h": "2*pi/60", "t_end": "2*pi"}},
                                  "ensemble": {"n": 12, "seed": 3, "spread": 0.02}})
    spec = load_sweep(path)
    run, states, result = run_ensemble_sweep(spec, threads=2)
    assert states.shape == (12, 4) and result.n_failed == 0
    for i in (0, 7):
        single = elimfast.integrate(run.problem, run.method, run.h, n_steps=run.n_steps, conserve=run.conserve,
                                    y0=states[i])
        np.testing.assert_array_equal(result.y_final[i], single.y_final)
        assert result.iterations[i] == single.iterations.sum()
    assert np.max(result.invariant_errors["angular_momentum"]) < 1e-14   # imposed
    out = tmp_path / "ensemble.h5"
    cli_result = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(out), "--workers", "1", "-q"])
    assert cli_result.exit_code == 0, cli_result.output
    assert "max err angular_momentum" in cli_result.stdout and "12 ok" in cli_result.stdout
    with h5py.File(out) as f:
        np.testing.assert_array_equal(f["ensemble/y0"][()], states)
        np.testing.assert_array_equal(f["ensemble/y_final"][()], result.y_final)   # same with 1 thread
        assert f["ensemble/invariant_errors/H"].shape == (12,)


@pytest.mark.parametrize("ensemble,extra,match", [
    ({"n": 0}, {}, "ensemble.n"),
    ({"n": 5, "spreed": 0.1}, {}, "ensemble.spreed: unknown key"),
    ({"states": [[1, 2]]}, {}, None),
    ({"n": 5}, {"order_axis": "h"}, "order_axis: an ensemble sweep"),
    ({"n": 5, "spread": "x"}, {}, "ensemble.spread: must be a number >= 0, got 'x'"),
    ({"n": 5, "spread": -1}, {}, "ensemble.spread: must be a number >= 0"),
    ({"n": 5, "seed": 0.5}, {}, "ensemble.seed: must be a non-negative integer"),
    ({"states": [[0.4, 0, "q1", 2]]}, {}, r"ensemble.states\[0\]\[2\]: must be a finite number"),
])
def test_bad_ensemble_sweeps_are_refused(tmp_path, ensemble, extra, match):
    from elimfast.sweep import run_ensemble_sweep
    path = write_sweep(tmp_path, {"base": BASE, "ensemble": ensemble, **extra})
    if match is not None:
        with pytest.raises(SweepError, match=match):
            load_sweep(path)
    else:
        with pytest.raises(SweepError, match="each state needs 4 numbers"):
            run_ensemble_sweep(load_sweep(path))


def test_an_ensemble_sweep_prints_csv_a_reader_takes_whole(tmp_path):
    """A user trial: `--format csv` of an ensemble sweep printed its title line on stdout before
    the header, and pandas read the title as the header. The title goes to stderr for csv."""
    import csv
    import io

    from click.testing import CliRunner

    from elimfast_cli.main import cli
    path = write_sweep(tmp_path, {"base": {**BASE, "integration": {"h": "2*pi/60", "t_end": "2*pi"}},
                                  "ensemble": {"n": 3, "seed": 3, "spread": 0.02}})
    result = CliRunner().invoke(cli, ["sweep", str(path), "--workers", "1", "-q", "--format", "csv"])
    assert result.exit_code == 0, result.output
    rows = list(csv.reader(io.StringIO(result.stdout)))
    assert rows[0][0] == "quantity" and len({len(row) for row in rows}) == 1, result.stdout
    assert "3 trajectories" in result.stderr


def test_ensemble_numbers_are_written_as_everywhere_in_configs(tmp_path):
    """A user trial: spread: 1e-2 (a string to YAML), pi/100, seed: 1e3 and states holding 1e-1
    or pi/4 were refused ('must be a number'), where every other number of a config takes them."""
    from elimfast.sweep import ensemble_states
    written = (tmp_path / "w.yaml")
    written.write_text(yaml.safe_dump({"base": BASE}) + "ensemble: {n: 4, seed: 1e3, spread: 1e-2}\n")
    plain = write_sweep(tmp_path, {"base": BASE, "ensemble": {"n": 4, "seed": 1000, "spread": 0.01}}, "p.yaml")
    np.testing.assert_array_equal(ensemble_states(load_sweep(written))[1], ensemble_states(load_sweep(plain))[1])
    arithmetic = write_sweep(tmp_path, {"base": BASE, "ensemble": {"n": 4, "seed": 1000, "spread": "pi/100"}}, "a.yaml")
    assert load_sweep(arithmetic).ensemble["spread"] == math.pi / 100
    states = (tmp_path / "s.yaml")
    states.write_text(yaml.safe_dump({"base": BASE}) + "ensemble: {states: [[4e-1, 0, 0, 2], [pi/8, 0, 0, 2]]}\n")
    np.testing.assert_array_equal(ensemble_states(load_sweep(states))[1], [[0.4, 0, 0, 2], [math.pi / 8, 0, 0, 2]])


@pytest.mark.parametrize("change,key", [
    ({"integration": {"rtol": 1e-10, "t_end": "2*pi"}}, "base.integration.rtol: an ensemble takes fixed steps h"),
    ({"integration": {"step_control": "time_scale", "t_end": "2*pi"}}, "base.integration.step_control: "),
    ({"events": {"peri": {"expression": "q1*p1 + q2*p2", "direction": 1}}}, "base.events: "),
    ({"output": {"times": [1.0, 2.0]}}, "base.output.times: "),
    # it was refused as "ensemble: project_energy is not available ...", naming no key of the file
    ({"solver": {"project_energy": True}}, "base.solver.project_energy: "),
])
def test_an_ensemble_refuses_what_its_kernel_would_silently_drop(tmp_path, change, key):
    """An ensemble's base with events (or output times) ran without them and said nothing: a
    user asking for each orbit's pericentre times got none. One with rtol failed on
    'ensemble: h must be a number, got None'. Both must be refused, naming the key."""
    from elimfast.sweep import run_ensemble_sweep
    path = write_sweep(tmp_path, {"base": {**BASE, **change}, "ensemble": {"n": 3}})
    with pytest.raises(SweepError) as caught:
        run_ensemble_sweep(load_sweep(path))
    assert str(caught.value).startswith(f"{path}: {key}"), str(caught.value)
    ragged = write_sweep(tmp_path, {"base": BASE, "ensemble": {"states": [[0.4, 0, 0, 2], [0.4, 0, 2]]}}, "r.yaml")
    with pytest.raises(SweepError, match=r"ensemble.states\[1\]: has 3; each state needs 4 numbers"):
        run_ensemble_sweep(load_sweep(ragged))   # it said 'every state must be a list of numbers'


def test_sweep_files_are_read_like_configs_no_aliases(tmp_path):
    path = tmp_path / "aliases.yaml"
    path.write_text("a: &x [1, 2]\nb: [*x, *x, *x]\nbase: {}\n")
    with pytest.raises(SweepError, match="aliases.yaml"):
        load_sweep(path)
    path.write_text("base: [unclosed\n")
    with pytest.raises(SweepError, match="line 2"):
        load_sweep(path)


def test_a_failed_run_of_a_sweep_advises_what_works_in_a_sweep(tmp_path):
    """A run file continues with --resume --set solver.*=...; a sweep has no --set, so its failed
    runs say to edit the sweep file and --resume (solver_only_edit, below)."""
    from elimfast.sweep import SWEEP_RERUN_ADVICE

    path = write_sweep(tmp_path, {"base": {**BASE, "solver": {"max_iter": 3, "max_halvings": 1}},
                                  "grid": [{"name": "h", "key": "integration.h", "values": ["2*pi/4"]}]})
    (outcome,), _ = run_sweep(load_sweep(path), workers=1)
    assert outcome.status.startswith("failed: EHBVM(12,3): the simplified Newton did not converge")
    assert "allow more step halvings (solver.max_halvings = 1 now)" in outcome.status
    assert "continued with --resume" not in outcome.status
    assert outcome.status.endswith(f"; {SWEEP_RERUN_ADVICE}") and "--resume" in SWEEP_RERUN_ADVICE


def _group(path, label):
    """Every dataset and attribute of one run of a sweep file (tests/runfiles.contents)."""
    from runfiles import contents
    from elimfast.io.sweepfile import sweep_group_name
    prefix = f"runs/{sweep_group_name(label)}"
    return {key: value for key, value in contents(path).items() if key.startswith(prefix)}


def _same(a: dict, b: dict, leave_out=()) -> bool:
    keys = sorted(key for key in a if not key.endswith(tuple(leave_out)))
    return keys == sorted(key for key in b if not key.endswith(tuple(leave_out))) and all(
        np.array_equal(np.asarray(a[key]), np.asarray(b[key])) for key in keys)


EDIT_BASE = {**BASE, "solver": {"max_halvings": 0}}
EDIT_GRID = [{"name": "h", "key": "integration.h", "values": ["2*pi/4", "pi/30"]}]


def test_resume_runs_the_failed_runs_of_a_sweep_again_with_an_edited_solver_section(tmp_path):
    """A sweep whose run failed: the user raises solver.max_halvings in the sweep file and
    --resumes. The failed run runs again with it; the complete run is kept as stored (not
    recomputed), and the table is the one the edited sweep gives from scratch. Before, --resume
    refused any edit, and the advice was to recompute the whole sweep with --overwrite."""
    from elimfast import sweep as sweeps
    from elimfast.io.sweepfile import RUN_INDEX

    path = write_sweep(tmp_path, {"base": EDIT_BASE, "grid": EDIT_GRID, "error": {"exact": "initial"}})
    out = tmp_path / "out.h5"
    first = sweeps.run_to_file(path, out, workers=1)
    assert [o.status.split(":")[0] for o in first.outcomes] == ["failed", "complete"]
    kept = _group(out, "pi/30")
    edited = write_sweep(tmp_path, {"base": {**EDIT_BASE, "solver": {"max_halvings": 8}}, "grid": EDIT_GRID,
                                    "error": {"exact": "initial"}})
    messages = []
    resumed = sweeps.run_to_file(edited, out, resume=True, workers=1, on_message=messages.append)
    assert [o.status for o in resumed.outcomes] == ["complete", "complete"]
    assert messages == [f"resume: 1 of 2 runs are complete in {out} (the sweep file was edited: the runs stored "
                        "complete keep the settings they were solved with, the others run with this file's); "
                        "running the other 1"]
    assert _same(_group(out, "pi/30"), kept)   # not recomputed: its config still says max_halvings 0
    with h5py.File(out, "r") as f:
        assert f.attrs["sweep"] == edited.read_text()
        assert "max_halvings: 8" in f["runs/2*pi|4"].attrs["config"]
        assert "max_halvings: 0" in f["runs/pi|30"].attrs["config"]
        assert [int(f["runs"][name].attrs[RUN_INDEX]) for name in ("2*pi|4", "pi|30")] == [0, 1]
    fresh = sweeps.run_to_file(edited, tmp_path / "fresh.h5", workers=1)
    assert resumed.table() == fresh.table()   # (no step of the kept run was split: max_halvings did not matter)


def test_a_stored_run_keeps_its_final_state_when_its_output_times_end_before_t_end(tmp_path):
    """A user trial: output.times ending before t_end (every 3 up to 20 pi), error against the initial
    state. The sweep printed 6.5e-8 and 1.3e-9; --resume, which reads the stored runs back, printed 2.494
    for both, the last sample's distance from y0, and load(run=...) gave t_final 60. The final state is
    stored with each run (attributes t_final, y_final) and read back."""
    from elimfast import sweep as sweeps
    base = {"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}}, "method": {"name": "hbvm", "s": 3},
            "integration": {"rtol": 1e-10, "t_end": "4*pi"}, "output": {"times": {"start": 0, "stop": "4*pi", "step": 3}}}
    path = write_sweep(tmp_path, {"base": base, "grid": [{"name": "rtol", "key": "integration.rtol",
                                                          "values": [1e-10, 1e-12]}], "error": {"exact": "initial"}})
    out = tmp_path / "out.h5"
    first = sweeps.run_to_file(path, out, workers=1)
    resumed = sweeps.run_to_file(path, out, resume=True, workers=1)
    assert resumed.table() == first.table()
    stored = load(out, run="1e-12")
    assert stored.t_final == pytest.approx(4 * math.pi, rel=1e-14) and stored.t[-1] == 12.0
    assert np.max(np.abs(stored.y_final - stored.y0)) < 1e-7


def test_resume_refuses_a_base_config_file_edited_under_an_unedited_sweep_file(tmp_path):
    """A sweep's base: may be a config file of its own. Edited after some runs were stored, with
    the sweep file's text unchanged, --resume compared only that text: the kept runs and the new
    ones came from different configs without a word. Now the stored runs are checked as for an
    edit of the sweep file."""
    from elimfast import sweep as sweeps
    base = tmp_path / "base.yaml"
    base.write_text(yaml.safe_dump(EDIT_BASE))
    path = write_sweep(tmp_path, {"base": "base.yaml", "grid": EDIT_GRID, "error": {"exact": "initial"}})
    out = tmp_path / "out.h5"
    first = sweeps.run_to_file(path, out, workers=1)
    assert [o.status.split(":")[0] for o in first.outcomes] == ["failed", "complete"]
    before = out.read_bytes()
    base.write_text(yaml.safe_dump({**EDIT_BASE, "integration": {**EDIT_BASE["integration"], "t_end": "4*pi"}}))
    with pytest.raises(OutputError, match=r"the sweep \(its file or a config it names\) was edited: "
                                          r"integration.t_end of the run 'pi/30', stored complete, changed"):
        sweeps.run_to_file(path, out, resume=True, workers=1)
    assert out.read_bytes() == before
    base.write_text(yaml.safe_dump({**EDIT_BASE, "solver": {"max_halvings": 8}}))   # solver.* is taken
    resumed = sweeps.run_to_file(path, out, resume=True, workers=1)
    assert [o.status for o in resumed.outcomes] == ["complete", "complete"]


def test_resume_refuses_an_edit_that_would_change_a_stored_run_and_leaves_the_file_as_it_was(tmp_path):
    from elimfast import sweep as sweeps
    from elimfast.io.safety import OutputError
    from runfiles import contents

    path = write_sweep(tmp_path, {"base": EDIT_BASE, "grid": EDIT_GRID})
    out = tmp_path / "out.h5"
    sweeps.run_to_file(path, out, workers=1)
    before = contents(out)
    for change, message in [
            ({"base": {**EDIT_BASE, "conserve": ["lrl_y"]}, "grid": EDIT_GRID},
             f"{out}: the sweep (its file or a config it names) was edited: conserve of the run 'pi/30', stored complete, changed, and --resume "
             "may change only solver.* of stored runs (their steps are kept); pass --overwrite to start again, or "
             "write the edited sweep to another file"),
            ({"base": EDIT_BASE, "grid": [{"name": "h", "key": "integration.h", "values": ["2*pi/4"]}]},
             f"{out}: the sweep (its file or a config it names) was edited, and the run 'pi/30', stored complete, is no longer in it: --resume "
             "keeps every stored run; pass --overwrite to start again, or write the edited sweep to another file"),
            ({"base": {**EDIT_BASE, "method": {"name": "ehbvm", "k": 12, "s": 3, "r": 2}}, "grid": EDIT_GRID},
             f"{out}: the sweep (its file or a config it names) was edited, and the stored run 'pi/30' no longer loads: "),
            # the user changed t_end; n_steps follows from it and was named instead (a user trial)
            ({"base": {**EDIT_BASE, "integration": {"h": "pi/30", "t_end": "4*pi"}}, "grid": EDIT_GRID},
             f"{out}: the sweep (its file or a config it names) was edited: integration.t_end of the run 'pi/30', stored complete, changed"),
            # ... and the eccentricity, whose initial state follows from it: problem.initial.p2 was named
            ({"base": {**EDIT_BASE, "problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.7}}},
              "grid": EDIT_GRID},
             f"{out}: the sweep (its file or a config it names) was edited: problem.parameters.eccentricity of the run "
             "'pi/30', stored complete, changed")]:
        with pytest.raises(OutputError) as caught:
            sweeps.run_to_file(write_sweep(tmp_path, change), out, resume=True, workers=1)
        assert str(caught.value).startswith(message), str(caught.value)
        after = contents(out)   # the failed run is still there too: nothing was removed
        assert sorted(after) == sorted(before) and all(np.array_equal(np.asarray(after[key]), np.asarray(value))
                                                       for key, value in before.items())


def test_resume_refuses_a_grid_sweep_onto_an_ensemble_s_file_and_the_reverse(tmp_path):
    """A user trial: `sweep table1.yaml -o ENSEMBLE.h5 --resume` ran the 30 grid runs into the
    ensemble's file (it had no complete grid runs, so the grid took it for an edit of itself),
    replacing its sweep text and axes. Either way round the file is now refused, untouched."""
    from elimfast import sweep as sweeps
    from elimfast.io.safety import OutputError
    from runfiles import contents

    ensemble = write_sweep(tmp_path, {"base": {**BASE, "integration": {"h": "2*pi/60", "t_end": "2*pi"}},
                                      "ensemble": {"n": 3, "seed": 3, "spread": 0.02}}, name="ensemble.yaml")
    grid = write_sweep(tmp_path, {"base": EDIT_BASE, "grid": EDIT_GRID}, name="grid.yaml")
    ensemble_out, grid_out = tmp_path / "ensemble.h5", tmp_path / "grid.h5"
    sweeps.run_to_file(ensemble, ensemble_out, workers=1)
    sweeps.run_to_file(grid, grid_out, workers=1)
    for sweep, out, message in ((grid, ensemble_out, "holds an ensemble sweep, and this is a grid sweep"),
                                (ensemble, grid_out, "holds a grid sweep, and this is an ensemble sweep")):
        before = contents(out)
        with pytest.raises(OutputError, match=f"^{out}: {message}: --resume continues the sweep that wrote the file"):
            sweeps.run_to_file(sweep, out, resume=True, workers=1)
        after = contents(out)
        assert sorted(after) == sorted(before) and all(np.array_equal(np.asarray(after[key]), np.asarray(value))
                                                       for key, value in before.items())


def test_resume_of_a_sweep_with_a_value_added_to_an_axis_runs_only_the_new_runs(tmp_path):
    """An edit that adds runs keeps the stored ones and renumbers them in the edited grid
    (inspect lists the runs by run_index)."""
    from elimfast import sweep as sweeps
    from elimfast.io.sweepfile import RUN_INDEX, RUNS_PLANNED

    grid = [{"name": "h", "key": "integration.h", "values": ["pi/30", "pi/60"]}]
    out = tmp_path / "out.h5"
    sweeps.run_to_file(write_sweep(tmp_path, {"base": BASE, "grid": grid}), out, workers=1)
    stored = {label: _group(out, label) for label in ("pi/30", "pi/60")}
    wider = [{"name": "h", "key": "integration.h", "values": ["pi/15", "pi/30", "pi/60"]}]
    messages = []
    resumed = sweeps.run_to_file(write_sweep(tmp_path, {"base": BASE, "grid": wider}), out, resume=True, workers=1,
                                 on_message=messages.append)
    assert [o.status for o in resumed.outcomes] == ["complete"] * 3
    assert " 2 of 3 runs are complete" in messages[0] and messages[0].endswith("running the other 1")
    for label, group in stored.items():
        assert _same(_group(out, label), group, leave_out=(f"@{RUN_INDEX}",))
    with h5py.File(out, "r") as f:
        assert int(f.attrs[RUNS_PLANNED]) == 3
        assert [int(f["runs"][name].attrs[RUN_INDEX]) for name in ("pi|15", "pi|30", "pi|60")] == [0, 1, 2]


def test_duplicate_keys_in_a_sweep_file_are_refused(tmp_path):
    path = tmp_path / "dup.yaml"
    path.write_text("base: kepler.yaml\nset:\n  integration: {t_end: 10}\n  integration: {t_end: 20}\n")
    with pytest.raises(SweepError) as caught:
        load_sweep(path)
    assert str(caught.value) == (f"{path}:4: duplicate key 'integration' in set (first at line 3); keep one of "
                                 "them")


def test_a_run_config_given_as_a_sweep_file_says_to_use_run(tmp_path):
    path = write_sweep(tmp_path, BASE, name="run.yaml")
    with pytest.raises(SweepError, match=r"run.yaml: \(top level\): a run config .*elimfast run .*run.yaml"):
        load_sweep(path)


def small_sweep(tmp_path, values, t_end="2*pi"):
    return write_sweep(tmp_path, {"base": BASE, "set": {"integration": {"t_end": t_end}},
                                  "grid": [{"name": "h", "key": "integration.h", "values": values}]})


def test_single_run_readers_given_a_sweep_file_name_its_runs(tmp_path):
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    import elimfast
    from elimfast.io.hdf5 import NotAnElimfastFile, RunFile
    from elimfast.sweep import run_to_file

    out = tmp_path / "sw.h5"
    run_to_file(small_sweep(tmp_path, ["2*pi/40", "2*pi/60"]), out, workers=1)
    expected = (f"{out}: a sweep file, not a single run: give one of its runs as '{out}:/runs/2*pi/40' (in Python: "
                f"elimfast.load('{out}', run='2*pi/40')); 2 of 2 runs stored (2*pi/40, 2*pi/60)")
    for read in (RunFile, elimfast.load):
        with pytest.raises(NotAnElimfastFile) as caught:
            read(out)
        assert str(caught.value) == expected
    inspected = CliRunner().invoke(cli, ["inspect", f"{out}:/runs/2*pi/40"])
    assert inspected.exit_code == 0
    # the run is named by its label, as the user writes it (its group name is 2*pi|40)
    assert inspected.stdout.startswith(f"file         {out}:/runs/2*pi/40\n")
    # and found without the leading slash, as h5py writes group paths
    assert CliRunner().invoke(cli, ["inspect", f"{out}:runs/2*pi/40"]).stdout == inspected.stdout


def test_the_runs_a_sweep_file_message_lists_are_in_the_grid_s_order(tmp_path):
    """A user trial: the killed-sweep message listed 'pi/240' before 'pi/30' (HDF5 lists groups by
    name); the message names the runs, and its example, in the grid's order, as inspect does."""
    import elimfast
    from elimfast.io.hdf5 import NotAnElimfastFile
    from elimfast.sweep import run_to_file

    out = tmp_path / "sw.h5"
    run_to_file(small_sweep(tmp_path, ["2*pi/60", "2*pi/400"]), out, workers=1)
    with pytest.raises(NotAnElimfastFile) as caught:
        elimfast.load(out)
    assert str(caught.value).endswith("2 of 2 runs stored (2*pi/60, 2*pi/400)")
    assert f"give one of its runs as '{out}:/runs/2*pi/60'" in str(caught.value)


def test_labels_stored_under_one_name_are_refused_and_a_dot_label_is_found(tmp_path):
    """Labels 'a/b' and 'a|b' (a '/' is stored as '|') crashed the sweep after its runs were
    computed ('internal error: ... name already exists'); now refused when the sweep loads. A
    run labelled '.' (stored as '_.') was not found by its label: '.' named the runs group itself."""
    import elimfast
    from elimfast.sweep import run_to_file

    def labelled(*labels, name):
        return write_sweep(tmp_path, {"base": BASE, "set": {"integration": {"t_end": "2*pi", "h": "2*pi/20"}},
                                      "grid": [{"name": "variant", "values": [{"label": label, "set": {}}
                                                                              for label in labels]}]}, name=name)

    with pytest.raises(SweepError, match=r"the runs 'a/b' and 'a\|b' would be stored under the same name 'a\|b'"):
        load_sweep(labelled("a/b", "a|b", name="clash.yaml"))
    with pytest.raises(SweepError, match="same name '_.'"):
        load_sweep(labelled(".", "_.", name="dots.yaml"))
    out = tmp_path / "dot.h5"
    run_to_file(labelled(".", "x", name="dot.yaml"), out, workers=1)
    assert elimfast.load(out, run=".").steps_done == 20
    assert elimfast.load(f"{out}:/runs/.").steps_done == 20


def test_inspect_of_a_sweep_file_summarises_its_runs(tmp_path):
    """`elimfast inspect SWEEP.h5` was an error ('a sweep file, not a single run'); it now
    summarises the sweep: every stored run's status, steps, iterations per step and largest
    relative invariant error (as inspect of that run gives them), a failed run counted, and for
    a sweep stopped before every run was stored, how to complete it."""
    import h5py
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    import elimfast
    from elimfast.sweep import run_to_file

    sweep = write_sweep(tmp_path, {"base": BASE, "set": {"integration": {"t_end": "2*pi", "h": "2*pi/40"}},
                                   "grid": [{"name": "iterations", "key": "solver.max_iter", "values": [30, 2]},
                                            {"name": "halvings", "key": "solver.max_halvings", "values": [0]}]})
    out = tmp_path / "sw.h5"
    run_to_file(sweep, out, workers=1)
    result = CliRunner().invoke(cli, ["inspect", str(out)])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[0] == f"file         {out}" and lines[2] == "runs         2 of 2 stored, 1 failed"
    rows = {line.split("|")[1].strip(): [cell.strip() for cell in line.split("|")[2:-1]]
            for line in lines if line.startswith("| ") and not line.startswith("| run ")}
    assert list(rows) == ["30/0", "2/0"] and rows["2/0"][0].startswith("failed")   # the grid's order, not HDF5's
    full = CliRunner().invoke(cli, ["inspect", f"{out}:/runs/30/0"]).stdout
    good = elimfast.load(out, run="30/0")
    assert rows["30/0"][:3] == ["complete", f"{good.steps_done:,}", f"{good.iterations.mean():.2f}"]
    worst = max(good.relative_invariant_errors().items(), key=lambda item: item[1])
    assert rows["30/0"][3] == f"{worst[1]:.2e} ({worst[0]})" and "relative" in full
    assert "--resume" in lines[-1] and f"elimfast inspect {out}:/runs/30/0;" in lines[-1]   # a run with data
    # a run that failed before storing any data (h does not divide t_end) has a row too
    bad = write_sweep(tmp_path, {"base": BASE, "set": {"integration": {"t_end": 2}},
                                 "grid": [{"name": "h", "key": "integration.h", "values": [0.1, 0.3]}]}, name="bad.yaml")
    bad_out = tmp_path / "bad.h5"
    run_to_file(bad, bad_out, workers=1)
    summary = CliRunner().invoke(cli, ["inspect", str(bad_out)])
    assert summary.exit_code == 0, summary.output
    assert "runs         2 of 2 stored, 1 failed" in summary.stdout
    assert [line for line in summary.stdout.splitlines() if line.startswith("| 0.3 ")][0].split("|")[3].strip() == "-"
    with h5py.File(out, "a") as f:        # as if the sweep had stopped before storing this run
        f["runs/2|0"].attrs["stored"] = False
    stopped = CliRunner().invoke(cli, ["inspect", str(out)]).stdout.splitlines()
    assert stopped[2] == "runs         1 of 2 stored, none failed"
    assert stopped[3].startswith("status       incomplete: complete it with elimfast sweep ") and "--resume" in stopped[3]


def test_a_file_with_a_path_that_is_no_run_is_not_called_missing(tmp_path):
    """`elimfast inspect SWEEP.h5:/run/GAUSS3/pi/30` (a typo) or `ENSEMBLE.h5:/ensemble` said
    'no such file' of a file that exists. It must say the file exists and how to name a run."""
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    import elimfast
    from elimfast.io.hdf5 import OutputError
    from elimfast.sweep import run_to_file

    out = tmp_path / "sw.h5"
    run_to_file(small_sweep(tmp_path, ["2*pi/40"]), out, workers=1)
    expected = (f"{out}:/run/2*pi/40: {out} exists, but '/run/2*pi/40' is no run of it; one run of a sweep file "
                f"is {out}:/runs/<label>, a run or ensemble file is given alone")
    for command in ("inspect", "plot"):
        result = CliRunner().invoke(cli, [command, f"{out}:/run/2*pi/40"])
        assert result.exit_code == 2 and result.stderr == f"error: {expected}\n", result.output
    with pytest.raises(OutputError, match="is no run of it"):
        elimfast.load(f"{out}:/ensemble")
    assert CliRunner().invoke(cli, ["inspect", str(tmp_path / "none.h5")]).stderr.endswith("none.h5: no such file\n")


def test_a_killed_sweep_file_is_read_as_it_is_and_called_interrupted_with_the_command_that_completes_it(tmp_path):
    """kill -9 leaves a grid sweep's file (written outside SWMR mode) marked open for writing:
    HDF5 refuses it, yet every run stored before is whole and --resume completes it. Readers
    read the stored runs (as a killed run's file is read) and say the sweep was interrupted;
    before, inspect, load and open_datatree refused the file (exit 2) and pointed to repair."""
    import signal
    import subprocess
    import sys

    from click.testing import CliRunner
    from elimfast_cli.main import cli

    import elimfast
    from elimfast.io.hdf5 import OutputError, RunFile, consistency_flags
    from elimfast.sweep import run_to_file

    path = small_sweep(tmp_path, [f"2*pi/{n}" for n in (100, 110, 120, 130)], t_end="500*pi")
    out = tmp_path / "killed.h5"
    process = subprocess.Popen([str(Path(sys.executable).with_name("elimfast")), "sweep", str(path), "-o", str(out),
                                "--workers", "1"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    for line in process.stderr:
        if line.startswith("[2/"):
            process.send_signal(signal.SIGKILL)
            break
    process.wait(timeout=120)
    assert process.returncode == -signal.SIGKILL and consistency_flags(out)
    command = f"elimfast sweep {path} -o {out} --resume"
    for read in (RunFile, elimfast.load):   # the file, where one run is wanted: what it holds, and how to go on
        with pytest.raises(OutputError) as caught:
            read(out)
        message = str(caught.value)
        assert message.startswith(f"{out}: an interrupted sweep (its writer was killed): ") and \
            " of 4 runs stored (2*pi/100, " in message, message
        assert f"complete it with {command}" in message and "--overwrite" not in message
        assert "damaged" not in message and "repair" not in message and "\n" not in message
    stored = elimfast.load(out, run="2*pi/100")
    assert stored.status == "complete" and stored.steps_done > 0
    result = CliRunner().invoke(cli, ["inspect", str(out)])
    assert result.exit_code == 0, result.output
    assert f"status       interrupted (its writer was killed): complete it with {command}" in result.stdout
    # other HDF5 tools refuse the killed writer's file (a user trial found h5py did): inspect names repair
    assert f"; other HDF5 tools open it after elimfast repair {out}" in result.stdout
    assert "| 2*pi/100 " in result.stdout
    assert CliRunner().invoke(cli, ["inspect", f"{out}:/runs/2*pi/100"]).exit_code == 0
    with elimfast.open_datatree(out) as tree:
        np.testing.assert_array_equal(tree["runs/2*pi|100"]["y"].values, stored.y)
    assert consistency_flags(out)   # reading touched nothing
    # A user trial: a script that loads a run of the killed file and opens its tree, leaving both open,
    # crashed at its exit (segmentation fault): HDF5's close at exit called back into a view already gone.
    script = (f"import elimfast; r = elimfast.load({str(out)!r}, run='2*pi/100'); "
              f"t = elimfast.open_datatree({str(out)!r}); print(t['runs/2*pi|100']['y'].shape)")
    ran = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert ran.returncode == 0 and ran.stdout.strip() == str(stored.y.shape), (ran.returncode, ran.stderr[-500:])
    run_to_file(path, out, resume=True, workers=1)
    np.testing.assert_array_equal(elimfast.load(out, run="2*pi/100").y, stored.y)
    with pytest.raises(OutputError, match="4 of 4 runs stored"):
        RunFile(out)


def test_the_workers_of_a_killed_sweep_die_with_it_and_free_its_file(tmp_path):
    """kill -9 of `elimfast sweep --workers 2` left its two forked workers waiting forever on
    the pool's queue, holding the output file's descriptor (and so its writer lock): --resume
    and inspect refused the file ('is open in another process') until the user found and
    killed them. The workers must die with the sweep, and --resume complete the file."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from elimfast.sweep import run_to_file

    path = small_sweep(tmp_path, [f"2*pi/{n}" for n in (100, 110, 120, 130, 140, 150)], t_end="500*pi")
    out = tmp_path / "killed.h5"
    process = subprocess.Popen([str(Path(sys.executable).with_name("elimfast")), "sweep", str(path), "-o", str(out),
                                "--workers", "2"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    for line in process.stderr:
        if line.startswith("[2/"):   # the pool's first run: the workers are forked
            workers = [int(pid) for task in Path(f"/proc/{process.pid}/task").iterdir()
                       for pid in (task / "children").read_text().split()]
            process.send_signal(signal.SIGKILL)
            break
    process.wait(timeout=120)
    assert process.returncode == -signal.SIGKILL and len(workers) == 2
    deadline = time.monotonic() + 10
    while any(Path(f"/proc/{pid}").exists() for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    alive = [pid for pid in workers if Path(f"/proc/{pid}").exists()
             and "Z" not in Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[:1]]
    for pid in alive:   # leave no process behind when the test fails
        os.kill(pid, signal.SIGKILL)
    assert not alive
    outcome = run_to_file(path, out, resume=True, workers=1)
    assert [o.status for o in outcome.outcomes] == ["complete"] * 6


def test_ctrl_c_of_a_sweep_says_how_to_resume(tmp_path, monkeypatch):
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    import elimfast.sweep

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt
    monkeypatch.setattr(elimfast.sweep, "run_to_file", interrupted)
    path, out = small_sweep(tmp_path, ["2*pi/40"]), tmp_path / "sw.h5"
    result = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(out)])
    assert result.exit_code == 130
    # a grid sweep's line says nothing of ensembles (a user trial: '(of an ensemble: its stored blocks)')
    assert result.stderr == (f"error: interrupted; the finished runs are in {out}; "
                             f"run the rest with: elimfast sweep {path} -o {out} --resume\n")

    def ensemble_interrupted(*args, on_start=None, **kwargs):   # an ensemble's sweep calls on_start
        on_start(40)
        raise KeyboardInterrupt
    monkeypatch.setattr(elimfast.sweep, "run_to_file", ensemble_interrupted)
    result = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(out), "-q"])
    assert result.exit_code == 130
    assert result.stderr == (f"error: interrupted; the ensemble's stored blocks are in {out}; "
                             f"run the rest with: elimfast sweep {path} -o {out} --resume\n")


def test_ctrl_c_of_a_sweep_without_output_prints_the_finished_runs(tmp_path, monkeypatch):
    """A user trial: Ctrl-C after 10 of 12 runs of a sweep without -o printed 'nothing was stored' and
    no table: the finished runs were lost. Their rows are printed now, and the line says so."""
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    import elimfast.sweep
    real = elimfast.sweep.run_to_file

    def interrupted_after_two(*args, on_done=None, **kwargs):
        def done(outcome, count, total):
            on_done(outcome, count, total)
            if outcome.label != elimfast.sweep.REFERENCE_LABEL and count >= 2:
                raise KeyboardInterrupt
        return real(*args, on_done=done, **kwargs)
    monkeypatch.setattr(elimfast.sweep, "run_to_file", interrupted_after_two)
    path = small_sweep(tmp_path, ["2*pi/40", "2*pi/60", "2*pi/80", "2*pi/100"])
    result = CliRunner().invoke(cli, ["sweep", str(path), "--workers", "1", "--quiet", "--format", "csv"])
    assert result.exit_code == 130
    rows = [line for line in result.stdout.splitlines()[1:] if line]
    assert 1 <= len(rows) <= 2 and all("complete" in row for row in rows), result.stdout
    assert result.stderr.startswith(f"error: interrupted: the {len(rows)} runs finished are the rows above "
                                    "(no -o OUT.h5: nothing was stored"), result.stderr


@pytest.mark.usefixtures("allow_python")
def test_a_sweep_whose_every_run_fails_to_load_is_one_error(tmp_path):
    """A user trial: a base naming a python: file with a syntax error, over 200 grid values, printed a
    200-row table of 'failed', exited 1, and said '200 of 200 runs failed (see the status column)'.
    When every run failed to load its config, the sweep says the first error once and exits 2; a
    sweep where some runs load still prints its table."""
    from click.testing import CliRunner
    from elimfast_cli.main import cli
    (tmp_path / "broken.py").write_text("def H(y, params):\n    return (\n")
    base = {**BASE, "problem": {"python": "broken.py"}, "conserve": []}
    path = write_sweep(tmp_path, {"base": base, "grid": [{"name": "h", "key": "integration.h",
                                                          "values": ["2*pi/40", "2*pi/60", "2*pi/80"]}]})
    result = CliRunner().invoke(cli, ["sweep", str(path), "--workers", "1", "--quiet"])
    assert result.exit_code == 2 and result.stdout == ""
    assert result.stderr.startswith("error: every run of the sweep failed to load its config, the first with: ")
    assert "broken.py" in result.stderr and "SyntaxError" in result.stderr and result.stderr.count("\n") == 1
    some = write_sweep(tmp_path, {"base": BASE, "grid": [{"name": "h", "key": "integration.h",
                                                          "values": ["2*pi/40", -1]}]}, name="some.yaml")
    mixed = CliRunner().invoke(cli, ["sweep", str(some), "--workers", "1", "--quiet"])
    # a refused config is a usage error, even beside runs that completed (a later user trial: exit 1 read
    # as a failed integration)
    assert mixed.exit_code == 2 and "complete" in mixed.stdout and "1 of 2 runs failed" in mixed.stderr


def adaptive_sweep(tmp_path):
    """A sweep of one fixed-step and two adaptive runs (one with output times and an event)."""
    times = {"start": 0, "stop": "2*pi", "step": "pi/4"}
    event = {"expression": "q2", "direction": 1}
    return write_sweep(tmp_path, {
        "base": {**BASE, "integration": {"rtol": 1e-8, "t_end": "2*pi"}},
        "grid": [{"name": "steps", "values": [
            {"label": "fixed", "set": {"integration": {"h": "pi/30", "t_end": "2*pi"}}},
            {"label": "rtol", "set": {"integration": {"rtol": 1e-8, "t_end": "2*pi"}}},
            {"label": "rtol_times", "set": {"integration": {"rtol": 1e-8, "t_end": "2*pi"},
                                            "output": {"times": times}, "events": {"up": event}}}]}]})


def test_a_sweep_run_has_the_attributes_of_the_same_run_in_a_run_file(tmp_path):
    """An adaptive run of a sweep file was stored with t_end = t0 + steps x first step (7.7
    for a run to 20 pi) and without its step control: inspect showed it as a fixed-step run
    of h = its first step. Each run group must say what the run file of the same config says."""
    import h5py
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    from elimfast.sweep import run_to_file

    out = tmp_path / "sw.h5"
    run_to_file(adaptive_sweep(tmp_path), out, workers=1)
    keys = ("t0", "t_end", "n_steps", "steps_done", "h", "step_control", "rtol", "atol", "verify", "h_first",
            "output_times", "output_every")
    for label in ("fixed", "rtol", "rtol_times"):
        with h5py.File(out) as f:
            group = f["runs"][label]
            config, stored = str(group.attrs["config"]), {key: group.attrs.get(key) for key in keys}
        (tmp_path / f"{label}.yaml").write_text(config)
        single = tmp_path / f"{label}.h5"
        result = CliRunner().invoke(cli, ["run", str(tmp_path / f"{label}.yaml"), "-o", str(single), "-q"])
        assert result.exit_code == 0, result.output
        with h5py.File(single) as f:
            expected = {key: f.attrs.get(key) for key in keys}
        assert stored == expected, label
    inspected = CliRunner().invoke(cli, ["inspect", f"{out}:/runs/rtol"])
    assert "steps        adaptive (error: rtol 1e-08" in inspected.stdout
    assert f"t_end = {2 * math.pi!r}" in inspected.stdout
    # and its stats, stored as attributes (a run file has them as counters)
    with h5py.File(out) as f:
        rejected = int(f["runs"]["rtol"].attrs["stats_rejected_steps"])
    assert f"stats        {rejected:,} rejected, " in inspected.stdout


def test_a_resumed_sweep_prints_the_table_of_the_uninterrupted_one(tmp_path):
    """The runs a resumed sweep reads back from its file must give the numbers they gave
    when they ran: an adaptive run's stats (grad H evaluations count side steps and rejected
    steps) were not stored, and its row read 27496 evaluations instead of 32560."""
    import elimfast
    from elimfast.sweep import run_to_file

    path, out = adaptive_sweep(tmp_path), tmp_path / "sw.h5"
    fresh = run_to_file(path, out, workers=1, keep_results=True)
    resumed = run_to_file(path, out, workers=1, resume=True)   # every run read back
    assert resumed.table() == fresh.table()
    for outcome in fresh.outcomes:
        assert elimfast.load(out, run=outcome.label).stats == outcome.result.stats, outcome.label


def test_a_sweep_takes_the_short_forms_of_a_run_config(tmp_path):
    """method: EHBVM(12,3) and problem: kepler in a base, a set and a variant are written out
    before they merge: a key axis (method.k) then sets k of the paper-notation base method."""
    path = write_sweep(tmp_path, {
        "base": {"problem": "kepler", "method": "EHBVM(12,3)", "conserve": ["angular_momentum"],
                 "integration": {"h": "pi/30", "t_end": "2*pi"}},
        "grid": [{"name": "method", "values": [{"label": "G", "set": {"method": "GHBVM(12,3)"}},
                                               {"label": "E", "set": {}}]},
                 {"name": "k", "key": "method.k", "values": [12, 16]}]})
    spec = load_sweep(path)
    assert [run.config["method"] for run in spec.runs] == [
        {"name": "ghbvm", "k": 12, "s": 3}, {"name": "ghbvm", "k": 16, "s": 3},
        {"name": "ehbvm", "k": 12, "s": 3}, {"name": "ehbvm", "k": 16, "s": 3}]
    assert all(run.config["problem"] == {"builtin": "kepler"} for run in spec.runs)
    # what YAML reads from an unquoted {name: EHBVM(12,3)}: the split leaves the key '3)'
    bad = write_sweep(tmp_path, {"base": {**BASE, "method": {"name": "EHBVM(12", "3)": None}}}, "bad.yaml")
    with pytest.raises(SweepError, match=r"bad.yaml:\d+: base.method.name: 'EHBVM\(12' is cut off"):
        load_sweep(bad)
    # ... and from set: {method: ELIM(4,8,3), conserve: []}: the pieces land beside method (the
    # message said only "'ELIM(4' is unbalanced")
    variant = (tmp_path / "variant.yaml")
    variant.write_text("base: {problem: kepler, method: \"EHBVM(12,3)\", integration: {h: 0.1, t_end: 1}}\n"
                       "grid:\n  - name: m\n    values:\n"
                       "      - {label: a, set: {method: ELIM(4,8,3), conserve: [angular_momentum]}}\n")
    with pytest.raises(SweepError, match=r"variant.yaml:5: grid\[0\].values\[0\].set.method: 'ELIM\(4' is cut off: "
                                         r"inside \{...\} YAML splits .* quote it \(method: "):
        load_sweep(variant)


def test_an_adaptive_runs_row_counts_the_iterations_its_grad_H_evaluations_count(tmp_path):
    """A user trial: a sweep row of adaptive EHBVM(8,4) showed 2495 iterations beside 22,952 grad H
    evaluations, 9.2 per iteration for k = 8: the iterations were the accepted steps' record, the
    evaluations counted the rejected steps' iterations too. Both count every iteration now, and a
    fixed-step row is as before (its record holds every iteration)."""
    from elimfast.sweep import run_to_file
    outcome = run_to_file(adaptive_sweep(tmp_path), None, workers=1, keep_results=True)
    rows = {o.label: o for o in outcome.outcomes}
    adaptive = rows["rtol"]
    assert adaptive.result.stats["iterations"] > adaptive.result.iterations.sum()   # rejected steps' too
    assert adaptive.grad_H_evaluations == 12 * adaptive.iterations_total   # EHBVM(12,3): k per iteration
    assert adaptive.iterations_total == adaptive.result.stats["iterations"]
    assert rows["fixed"].iterations_total == int(rows["fixed"].result.iterations.sum())


def test_a_missing_base_file_is_named_at_the_sweep_files_key(tmp_path):
    """A user trial: `base: nosuch.yaml` was told only 'nosuch.yaml: no such file', naming neither
    the sweep file nor the key, nor where a relative path is looked for."""
    path = write_sweep(tmp_path, {"base": "nosuch.yaml", "grid": [{"key": "integration.h", "values": [0.1]}]})
    with pytest.raises(SweepError) as info:
        load_sweep(path)
    assert str(info.value).startswith(f"{path}:1: base: {tmp_path / 'nosuch.yaml'}: no such file; give the path of "
                                      "a run config, relative to the sweep file's folder"), str(info.value)


def test_a_run_whose_config_is_refused_makes_the_sweep_a_usage_error(tmp_path):
    """A user trial: a grid value h = -0.05 was refused for its run, and the sweep exited 1, the code
    of a failed integration. The other runs are in the table; the exit code is 2."""
    from click.testing import CliRunner

    from elimfast_cli.main import cli
    path = write_sweep(tmp_path, {"base": {**BASE, "integration": {"h": 0.1, "t_end": 2}},
                                  "grid": [{"key": "integration.h", "values": [0.1, -0.05]}]})
    result = CliRunner().invoke(cli, ["sweep", str(path), "--workers", "1", "-q"])
    assert result.exit_code == 2, result.output
    assert "integration.h: must be > 0" in result.stdout and "| complete" in result.stdout


def test_runs_a_terminal_event_ended_early_have_no_error_and_say_why(tmp_path):
    """A user trial: a sweep with error {exact: initial} whose runs a terminal event stopped at
    the apocentre (t = pi) printed 'error 2.500e+00, order 0.00', status 'complete': y(pi)
    against y0. Such a run has no state at t_end to compare: its error and order are empty, and
    its status says where it ended, as `elimfast run` does; a run to t_end keeps its error."""
    from elimfast.sweep import run_to_file

    sweep = {"base": {"problem": "kepler", "method": "HBVM(12,3)", "integration": {"h": "pi/60", "t_end": "20*pi"}},
             "grid": [{"name": "events",
                       "values": [{"label": "stop", "set": {"events": {"apo": {
                                       "expression": "q1*p1+q2*p2", "direction": -1, "terminal": True}}}},
                                  {"label": "count", "set": {"events": {"apo": {
                                      "expression": "q1*p1+q2*p2", "direction": -1}}}}]},
                      {"name": "h", "key": "integration.h", "values": ["pi/60", "pi/120"]}],
             "error": {"exact": "initial"}, "order_axis": "h"}
    path, out = write_sweep(tmp_path, sweep), tmp_path / "ev.h5"
    done = run_to_file(path, out, workers=1)
    header, rows = done.table()
    column = {name: header.index(name) for name in ("events", "h", "error", "order", "status")}
    by_label = {(row[column["events"]], row[column["h"]]): row for row in rows}
    for h in ("pi/60", "pi/120"):
        stopped = by_label[("stop", h)]
        assert stopped[column["error"]] == "-" and stopped[column["order"]] == ""
        assert stopped[column["status"]].startswith("complete (ended by a terminal event at t = 3.14159")
        counted = by_label[("count", h)]
        assert float(counted[column["error"]]) < 1e-5 and counted[column["status"]] == "complete"
    assert float(by_label[("count", "pi/120")][column["order"]]) > 5
    resumed = run_to_file(path, out, workers=1, resume=True)   # read back: the same table
    assert resumed.table() == (header, rows)


def test_a_pool_whose_shortest_run_is_refused_compiles_nothing_on_a_warm_cache(tmp_path):
    """A user trial: with -o and 2 workers, a sweep whose shortest run's config was refused (h = 0.7
    is no whole number of steps) said 'compiling Numba kernels' on a warm cache: nothing had named
    the problem's Numba functions before forking, so every stored result's functions were rebuilt
    and compiled in the parent. The parent now runs the next shortest run too, until one loads."""
    import subprocess
    import sys
    sweep = {"base": {"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.9}},
                      "method": {"name": "hbvm", "k": 6, "s": 3}, "integration": {"h": 0.5, "t_end": "20*pi"}},
             "grid": [{"name": "h", "key": "integration.h", "values": ["pi/5", 0.7, "pi/10", "pi/40"]}],
             "error": {"exact": "initial"}}
    path = write_sweep(tmp_path, sweep)
    elimfast = str(Path(sys.executable).with_name("elimfast"))
    for _ in range(2):   # the first may compile the problem's functions on a cold cache; the second must not
        done = subprocess.run([elimfast, "sweep", str(path), "--workers", "2", "-o", str(tmp_path / "s.h5"),
                               "--overwrite", "-q"], capture_output=True, text=True)
    assert done.returncode == 2, done.stderr   # the refused run
    assert "compiling" not in done.stderr, done.stderr


def test_a_reference_a_terminal_event_ended_early_is_said(tmp_path):
    """A user trial: a reference run stopped by a terminal event left every error '-', exit 0,
    nothing said. The sweep now says why there are no errors, as for a failed reference."""
    from elimfast.sweep import run_to_file
    sweep = {"base": {"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}},
                      "method": {"name": "hbvm", "k": 6, "s": 3}, "integration": {"h": 0.1, "t_end": 10}},
             "grid": [{"name": "h", "key": "integration.h", "values": [0.1, 0.05]}],
             "error": {"reference": {"set": {"integration": {"h": 0.01}, "events": {
                 "apo": {"expression": "q1*p1+q2*p2", "direction": -1, "terminal": True}}}}}}
    done = run_to_file(write_sweep(tmp_path, sweep), None, workers=1)
    assert done.failures() == ["the reference run was ended by a terminal event at t = 3.141592654, before its t_end, "
                               "so there are no errors: give the reference no terminal event"]


def test_resume_without_a_file_is_refused_from_python(tmp_path):
    """A user trial: elimfast.sweep.run(SWEEP, resume=True) with no path ran every run again,
    stored nothing and said nothing (the command line refuses --resume without -o)."""
    from elimfast.sweep import run_to_file
    path = write_sweep(tmp_path, {"base": BASE, "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30"]}]})
    with pytest.raises(SweepError, match="resume=True continues a sweep stored in a file: give its path"):
        run_to_file(path, None, resume=True)


def test_python_errors_name_keywords_not_the_command_lines_flags(tmp_path):
    """A user trial: elimfast.sweep.run's errors said "pass --overwrite" and "--workers must be at
    least 1", flags a Python caller has not got; client=object() raised a bare AttributeError."""
    from elimfast import sweep as sweeps
    path = write_sweep(tmp_path, {"base": BASE, "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30"]}]})
    out = tmp_path / "out.h5"
    sweeps.run(path, out, workers=1)
    with pytest.raises(OutputError) as refused:
        sweeps.run(path, out, workers=1)
    assert "pass overwrite=True to replace it or resume=True to continue it" in str(refused.value)
    with pytest.raises(SweepError, match="^workers must be at least 1$"):
        sweeps.run(path, None, workers=0)
    with pytest.raises(TypeError, match="client must be a dask.distributed.Client .* got object"):
        sweeps.run(path, None, client=object())
    # The command line's wording is unchanged, and a quoted command keeps its flags in Python too
    with pytest.raises(OutputError, match="pass --overwrite to replace it or --resume"):
        sweeps.run_to_file(path, out, workers=1)
    assert (sweeps.python_wording("complete it with elimfast sweep s.yaml -o o.h5 --resume; or pass --overwrite")
            == "complete it with elimfast sweep s.yaml -o o.h5 --resume; or pass overwrite=True")


def test_a_run_refused_for_memory_is_a_usage_error(tmp_path, monkeypatch):
    """A user trial: a sweep whose runs would not fit in memory exited 1, as a failed integration;
    like a refused config, it is the input's size (exit 2), and the message says what to change."""
    from click.testing import CliRunner
    from cli.main import cli
    from elimfast import sweep as sweeps
    long_run = {**BASE, "integration": {"h": 0.1, "n_steps": 10 ** 8}}   # ~10^8 samples: ~4 GB
    path = write_sweep(tmp_path, {"base": long_run, "grid": [{"name": "h", "key": "integration.h", "values": [0.1]}]})
    monkeypatch.setattr(sweeps, "memory_available", lambda: 2 ** 30)
    done = CliRunner().invoke(cli, ["sweep", str(path), "--workers", "1", "-q"])
    assert done.exit_code == 2, done.output
    assert "of memory in a sweep" in done.stdout and "raise output.every" in done.stdout   # its status cell


def test_resume_from_another_sweep_file_says_so(tmp_path):
    """A user trial: --resume of a file with another sweep file than the one that wrote it was
    called an edit ("the sweep file was edited"); it now names the file that wrote it."""
    from elimfast import sweep as sweeps
    path = write_sweep(tmp_path, {"base": EDIT_BASE, "grid": EDIT_GRID, "error": {"exact": "initial"}})
    out = tmp_path / "out.h5"
    sweeps.run_to_file(path, out, workers=1)
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump({"base": {**EDIT_BASE, "conserve": ["lrl_y"]}, "grid": EDIT_GRID}))
    with pytest.raises(OutputError) as caught:
        sweeps.run_to_file(other, out, resume=True, workers=1)
    assert str(caught.value).startswith(f"{out}: was written by the sweep {path.resolve()}, and this is "
                                        f"{other.resolve()}: conserve of the run 'pi/30', stored complete, changed")
    other.write_text(yaml.safe_dump({"base": {**EDIT_BASE, "solver": {"max_halvings": 8}}, "grid": EDIT_GRID,
                                     "error": {"exact": "initial"}}))
    messages = []
    sweeps.run_to_file(other, out, resume=True, workers=1, on_message=messages.append)
    assert messages[0] == (f"resume: 1 of 2 runs are complete in {out} (it was written by the sweep {path.resolve()}: "
                           "the runs stored complete keep the settings they were solved with, the others run with "
                           "this file's); running the other 1")


@pytest.mark.usefixtures("allow_python")
def test_resume_refuses_a_python_problem_file_changed_since_its_runs_were_stored(tmp_path):
    """A user trial: a sweep of a python: problem killed after 2 of 6 runs, the file's H and grad_H
    changed, then --resume: the 4 other runs ran with the new file and the table mixed the two
    versions, every run 'complete', exit 0 (a run file's --resume notes the change). Each stored run
    now records the file's sha256, and --resume refuses a changed file."""
    from elimfast import sweep as sweeps
    problem = tmp_path / "osc.py"
    source = ("Y0 = [1.0, 0.0]\n\ndef H(y, params):\n    return 0.5 * y[1] ** 2 + 0.5 * W * y[0] ** 2\n\n"
              "def grad_H(y, params, out):\n    out[0] = W * y[0]\n    out[1] = y[1]\n")
    problem.write_text("W = 1.0\n" + source)
    path = write_sweep(tmp_path, {"base": {"problem": {"python": "osc.py"}, "method": {"name": "hbvm", "k": 6, "s": 3},
                                           "integration": {"h": 0.1, "t_end": 1}},
                                  "grid": [{"name": "h", "key": "integration.h", "values": [0.1, 0.05]}]})
    out = tmp_path / "out.h5"
    sweeps.run_to_file(path, out, workers=1)
    with h5py.File(out, "r") as f:
        assert all(len(str(f["runs"][name].attrs["problem_file_sha256"])) == 64 for name in f["runs"])
    sweeps.run_to_file(path, out, resume=True, workers=1)          # unchanged: resumes
    problem.write_text("W = 2.0\n" + source)
    with pytest.raises(OutputError, match=r"the problem file .*osc\.py has changed since it was stored \(sha256 "
                                          r"\w{16} then, \w{16} now\), the file of the run '0\.(1|05)', stored complete"):
        sweeps.run_to_file(path, out, resume=True, workers=1)


def test_output_may_not_be_a_file_the_sweep_reads(tmp_path):
    """A user trial: `sweep SWEEP -o BASE.yaml --overwrite` replaced the sweep's base config by HDF5,
    and `-o PROBLEM.py` its python: problem file (the sweep file itself was refused already)."""
    from click.testing import CliRunner
    from cli.main import cli
    from elimfast import sweep as sweeps
    (tmp_path / "osc.py").write_text("Y0 = [1.0, 0.0]\n\ndef H(y, params):\n    return 0.5 * y[1] ** 2 + 0.5 * y[0] ** 2\n"
                                     "\ndef grad_H(y, params, out):\n    out[0] = y[0]\n    out[1] = y[1]\n")
    (tmp_path / "base.yaml").write_text(yaml.safe_dump({"problem": {"python": "osc.py"},
                                                        "method": {"name": "hbvm", "k": 6, "s": 3},
                                                        "integration": {"h": 0.1, "t_end": 1}}))
    path = write_sweep(tmp_path, {"base": "base.yaml", "grid": [{"name": "h", "key": "integration.h", "values": [0.1]}]})
    before = {name: (tmp_path / name).read_bytes() for name in ("osc.py", "base.yaml", "sweep.yaml")}
    for name, what in (("base.yaml", "base config"), ("osc.py", "problem file"), ("sweep.yaml", "sweep file")):
        with pytest.raises(OutputError, match=rf"is the sweep's {what} itself, which writing would replace"):
            sweeps.run_to_file(path, tmp_path / name, overwrite=True, workers=1)
        done = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(tmp_path / name), "--overwrite", "-q"])
        assert done.exit_code == 2 and "itself, which writing would replace" in done.stderr, done.output
    assert {name: (tmp_path / name).read_bytes() for name in before} == before


def test_orders_taken_from_errors_at_rounding_are_flagged(tmp_path):
    """A user trial: orders computed from errors at round-off (HBVM(8,4): -1.60, 0.43) were printed
    as plainly as the method's. HBVM(8,4) on one period of Kepler: order 8 down to 200 steps a period,
    then rounding."""
    sweep = {"base": {**BASE, "method": {"name": "hbvm", "k": 8, "s": 4}, "conserve": [],
                      "integration": {"h": 0.1, "t_end": "2*pi"}},
             "grid": [{"name": "h", "key": "integration.h", "values": ["2*pi/100", "2*pi/200", "2*pi/800"]}],
             "error": {"exact": "initial"}, "order_axis": "h"}
    spec = load_sweep(write_sweep(tmp_path, sweep))
    outcomes, reference = run_sweep(spec, workers=1)
    header, rows = table_rows(spec, outcomes, reference, "markdown")
    order = header.index("order")
    assert [row[order] for row in rows][:2] == ["", f"{orders_of(spec, outcomes, errors_of(spec, outcomes, None))['2*pi/200']:.2f}"]
    assert 7.5 < float(rows[1][order]) < 8.5
    assert rows[2][order].endswith(" (round-off)")
    header, rows = table_rows(spec, outcomes, reference, "csv")   # a number in CSV
    float(rows[2][header.index("order")])


def test_sweep_file_errors_give_the_line_and_a_word_among_numbers_is_refused_before_any_run(tmp_path):
    """A user trial: a sweep file's errors named the key but not its line (a run config's name
    both), and an h axis [0.1, 0.05, abc, 0.02] ran three runs before the fourth failed on 'abc'.
    Now the line is given, and a value of a numbers axis that is no number is refused at once."""
    path = tmp_path / "sweep.yaml"
    path.write_text("base:\n  problem: {builtin: kepler}\n  method: {name: hbvm, k: 4, s: 2}\n"
                    "  integration: {h: 0.1, t_end: 2*pi}\n"
                    "grid:\n  - name: h\n    key: integration.h\n    values: [0.1, 0.05, abc, pi/100]\n"
                    "error: {exact: initial}\n")
    with pytest.raises(SweepError) as info:
        load_sweep(path)
    assert str(info.value) == (f"{path}:8: grid[0].values[2]: value 'abc': unknown name 'abc' (known: e, pi), where "
                               "the axis's other values of integration.h are numbers; write a number or arithmetic on "
                               "numbers, pi and e, e.g. pi/30")
    path.write_text(path.read_text().replace("abc", "0.02").replace("error: {exact: initial}", "error: {exact: zero}"))
    with pytest.raises(SweepError, match=rf"^{re.escape(str(path))}:9: error.exact: the only exact solution"):
        load_sweep(path)
    # words are left alone on an axis of words, and under problem (a parameter's name may be one)
    path.write_text(path.read_text().replace("{exact: zero}", "{exact: initial}")
                    .replace("key: integration.h\n    values: [0.1, 0.05, 0.02, pi/100]",
                             "key: method.name\n    values: [hbvm, ehbvm]"))
    assert [run.config["method"]["name"] for run in load_sweep(path).runs] == ["hbvm", "ehbvm"]


def test_a_resumed_sweep_reads_its_reference_run_back_instead_of_running_it_again(tmp_path, monkeypatch):
    """A user trial: every --resume ran the reference run again (23 s there), as it was not stored.
    Its summary is stored now (root attributes reference_*, the key last), and a resume of the same
    sweep reads it back: the table is the uninterrupted one's. A sweep whose reference differs (its
    key) or whose stored reference failed runs it again."""
    from elimfast import sweep as sweeps
    from elimfast.io.sweepfile import REFERENCE_KEY

    path = write_sweep(tmp_path, {"base": BASE, "grid": [{"name": "h", "key": "integration.h",
                                                          "values": ["pi/20", "pi/30"]}],
                                  "error": {"reference": {"set": {"integration": {"h": "pi/120"}}}}})
    out = tmp_path / "sw.h5"
    fresh = sweeps.run_to_file(path, out, workers=1)
    with h5py.File(out, "r") as f:
        assert f.attrs[REFERENCE_KEY] == sweeps.reference_key(load_sweep(path))
        np.testing.assert_array_equal(f.attrs["reference_y_final"], fresh.reference.y_final)
    ran, said = [], []
    real_execute = sweeps._execute
    monkeypatch.setattr(sweeps, "_execute", lambda label, *args: ran.append(label) or real_execute(label, *args))
    with h5py.File(out, "a") as f:   # the second run as if killed: it runs again, the reference does not
        del f["runs"][sorted(f["runs"])[-1]]
    resumed = sweeps.run_to_file(path, out, workers=1, resume=True, on_message=said.append)
    assert sweeps.REFERENCE_LABEL not in ran and len(ran) == 1
    assert any("the reference run is stored" in line for line in said)
    assert resumed.table() == fresh.table()
    np.testing.assert_array_equal(resumed.reference.y_final, fresh.reference.y_final)

    stored = {"key": sweeps.reference_key(load_sweep(path)), "status": "complete", "t_final": 2 * math.pi,
              "t_end": 2 * math.pi, "y_final": fresh.reference.y_final}
    spec = load_sweep(path)
    assert sweeps._stored_reference(spec, stored) is not None
    assert sweeps._stored_reference(spec, {**stored, "key": "{}"}) is None
    assert sweeps._stored_reference(spec, {**stored, "status": "failed: x"}) is None
    assert sweeps._stored_reference(spec, None) is None
