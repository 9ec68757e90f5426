"""Adaptive runs through the CLI and their files (issue 11): /steps/h and /steps/t, events
in /events/<name>, the controller's state in the record, bit-exact resume after kill -9,
the config keys, and what inspect shows."""
import math
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

import elimfast
from elimfast.config import load_run, load_run_from_dict, ConfigError
from elimfast.integrate import Integration
from elimfast.io.hdf5 import RunFile
from elimfast_cli.main import cli
from runfiles import steps_on_disk

ELIMFAST = str(Path(sys.executable).with_name("elimfast"))
PERIOD = 2 * math.pi
CONFIG = {
    "problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.9}},
    "conserve": ["angular_momentum", "lrl_y"],
    "method": {"name": "ehbvm", "s": 4},
    "integration": {"rtol": 1e-13, "t_end": "600*pi"},
    "output": {"every": 20},
    "events": {"pericentre": {"expression": "q1*p1 + q2*p2", "direction": 1}},
}


def write_config(tmp_path, config=CONFIG) -> Path:
    path = tmp_path / "adaptive.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def kill_after(config: Path, out: Path, steps: int) -> None:
    """Start `elimfast run config -o out` and kill -9 it once ``steps`` steps are on disk."""
    process = subprocess.Popen([ELIMFAST, "run", str(config), "-o", str(out), "--quiet"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 600   # a cold Numba cache compiles the kernels first
    while steps_on_disk(out) < steps:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.01)
    process.send_signal(signal.SIGKILL)
    process.communicate(timeout=60)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted run, in this process, through the same driver as the CLI."""
    path = write_config(tmp_path_factory.mktemp("reference"))
    spec = load_run(path)
    run = Integration.from_spec(spec)
    chunks = [run.initial_chunk()]
    while not run.finished:
        chunks.append(run.advance(50_000))
    return {"y_final": run.y.copy(), "clock": run.clock.copy(), "steps": run.steps_done,
            "t": np.concatenate([c.t for c in chunks]), "y": np.concatenate([c.y for c in chunks]),
            "h": np.concatenate([c.step_h for c in chunks]), "alpha": np.concatenate([c.multipliers for c in chunks]),
            "events": np.concatenate([c.event_t for c in chunks]), "counters": run.counters.copy()}


def test_config_defaults_k_to_2s_and_records_the_step_control(tmp_path):
    spec = load_run(write_config(tmp_path))
    assert spec.method.name == "EHBVM(8,4)" and spec.step_control.rtol == 1e-13 and spec.n_steps is None
    assert spec.resolved["integration"]["step_control"] == "error"
    assert spec.resolved["events"]["pericentre"]["direction"] == 1


@pytest.mark.parametrize("change, key", [
    ({"integration": {"rtol": "x", "t_end": 10}}, "integration.rtol"),
    # n_steps named itself (a user trial was told 't_end is needed' beside its t_end)
    ({"integration": {"rtol": 1e-10, "n_steps": 10}}, "integration.n_steps"),
    ({"integration": {"rtol": 1e-10, "n_steps": 10, "t_end": 20}}, "integration.n_steps"),
    ({"integration": {"rtol": 1e-10}}, "integration.t_end"),
    ({"integration": {"step_control": "time_scale", "epsilon": 5, "t_end": 10}}, "integration.epsilon"),
    ({"output": {"times": {"start": 0, "stop": 1e9, "step": 1}}}, "output.times"),
    ({"events": {"p": {"expression": "q1", "direction": 5}}}, "events.p.direction"),
    ({"events": {"p": {"expression": "q1", "direction": "up"}}}, "events.p.direction"),
    ({"events": {"p": {"expression": "q1", "direction": 0.5}}}, "events.p.direction"),
    ({"events": {"p": {"expression": "open('x')"}}}, "events.p"),
])
def test_bad_adaptive_config_names_the_key(change, key):
    config = {**CONFIG, **change}
    with pytest.raises(ConfigError) as info:
        load_run_from_dict(config, source="run.yaml")
    assert str(info.value).startswith(f"run.yaml: {key}: "), str(info.value)
    assert "\n" not in str(info.value)
    if key.endswith("direction"):   # a user trial: 'up' was told "is not a number ... did you mean 'pi'?"
        assert "must be 1 (g increasing through 0), -1 (decreasing) or 0 (both), got" in str(info.value)


def test_a_time_scale_run_records_its_first_step_and_says_h_is_not_used(tmp_path):
    """configs/nbody.yaml has h: 50; run with --set integration.step_control=time_scale, its file
    said h = h_first = 50 while the first step taken was 36.49 (time-scale steps are all the
    controller's). The file records the step taken, and run and check say that h is not used."""
    nbody = Path(__file__).resolve().parents[1] / "configs" / "nbody.yaml"
    assert yaml.safe_load(nbody.read_text())["integration"]["h"] == 50
    switch = ["--set", "integration.step_control=time_scale", "--set", "integration.t_end=300"]
    out = tmp_path / "nbody.h5"
    result = CliRunner().invoke(cli, ["run", str(nbody), "-o", str(out), *switch])
    assert result.exit_code == 0, result.output
    with h5py.File(out, "r") as f:
        first = float(f["steps/h"][0])
        assert f.attrs["h_first"] == f.attrs["h"] == first and abs(first - 36.49) < 0.01
    assert elimfast.load(out).h == first
    assert (f"note: integration.h = 50.0 is not used: time-scale steps are all the controller's, the first too "
            f"({first!r} here)") in result.stderr
    checked = CliRunner().invoke(cli, ["check", str(nbody), *switch]).stdout.splitlines()[1]
    assert checked.endswith(f", first step h = {first!r}; integration.h = 50.0 is not used: time-scale steps are all "
                            "the controller's, the first too, epsilon / rho at y0: integration.epsilon sets their "
                            "size (docs/adaptive.md)"), checked
    # without h in the config, nothing to say
    quiet = CliRunner().invoke(cli, ["run", str(nbody), "-o", str(tmp_path / "no_h.h5"), *switch,
                                     "--set", "integration.h=null"])
    assert quiet.exit_code == 0 and "not used" not in quiet.stderr, quiet.output
    with h5py.File(tmp_path / "no_h.h5", "r") as f:
        assert f.attrs["h_first"] == f.attrs["h"] == first


def test_inspect_does_not_take_the_step_cut_to_land_on_t_end_for_the_smallest(tmp_path):
    """A user trial: on a near-circular orbit every time-scale step was 0.085-0.092, and inspect's
    'h min' read 5.2e-3, the last step, cut to land on t_end."""
    config = {"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.05}},
              "method": {"name": "hbvm", "s": 4},
              "integration": {"step_control": "time_scale", "epsilon": 0.05, "t_end": 10.005}}
    out = tmp_path / "circular.h5"
    assert CliRunner().invoke(cli, ["run", str(write_config(tmp_path, config)), "-o", str(out), "-q"]).exit_code == 0
    with h5py.File(out, "r") as f:
        sizes = f["steps/h"][:]
    assert sizes[-1] < 0.5 * sizes[:-1].min()
    line = next(line for line in CliRunner().invoke(cli, ["inspect", str(out)]).stdout.splitlines()
                if line.startswith("h "))
    assert line == (f"h            min {sizes[:-1].min():.3e}, median {np.median(sizes[:-1]):.3e}, max "
                    f"{sizes.max():.3e}; the last, cut to land on t_end, {sizes[-1]:.3e}")


def test_adaptive_run_file_layout_and_inspect(tmp_path, reference):
    config = write_config(tmp_path)
    out = tmp_path / "run.h5"
    result = CliRunner().invoke(cli, ["run", str(config), "-o", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    with h5py.File(out, "r") as f:
        assert f.attrs["status"] == "complete" and f.attrs["step_control"] == "error"
        np.testing.assert_array_equal(f["steps/h"][:], reference["h"])
        assert f["steps/t"][-1] == 600 * math.pi and f["t"][-1] == 600 * math.pi
        np.testing.assert_array_equal(f["events/pericentre/t"][:], reference["events"])
        assert f["events/pericentre/y"].shape == (300, 4)
    loaded = elimfast.load(out)
    np.testing.assert_array_equal(loaded.step_h, reference["h"])
    np.testing.assert_array_equal(loaded.events["pericentre"].t, reference["events"])
    assert loaded.stats["steps"] == reference["steps"] and loaded.stats["events"] == 300
    report = CliRunner().invoke(cli, ["inspect", str(out)])
    assert report.exit_code == 0
    assert "adaptive (error: rtol 1e-13" in report.output and "pericentre: 300 found" in report.output
    xr = pytest.importorskip("xarray")
    tree = xr.open_datatree(out, engine="h5netcdf")
    # the group's own t (its root's t is inherited in a datatree: ask for the node alone)
    events = tree["events/pericentre"].to_dataset(inherit=False)
    assert events["t"].dims == ("occurrence",) and events["y"].dims == ("occurrence", "component")
    np.testing.assert_array_equal(events["t"].values, reference["events"])
    alone = xr.open_dataset(out, engine="h5netcdf", group="events/pericentre")
    np.testing.assert_array_equal(alone["t"].values, reference["events"])
    # the group alone labels y's components too (the names were only in the root group)
    assert list(alone["y"].coords["component"].values) == ["q1", "q2", "p1", "p2"]
    assert tree["steps"].to_dataset(inherit=False)["h"].dims == ("step",)


@pytest.mark.slow
def test_kill_9_and_resume_equal_the_uninterrupted_run(tmp_path, reference):
    config = write_config(tmp_path)
    out = tmp_path / "run.h5"
    kill_after(config, out, 3000)
    done = steps_on_disk(out)
    assert 3000 <= done < reference["steps"]
    resumed = subprocess.run([ELIMFAST, "run", str(config), "-o", str(out), "--resume", "--quiet"],
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    with h5py.File(out, "r") as f:
        assert f.attrs["status"] == "complete"
        np.testing.assert_array_equal(f["state/y"][:], reference["y_final"])
        np.testing.assert_array_equal(f["state/clock"][:], reference["clock"])
        np.testing.assert_array_equal(f["state/counters"][:], reference["counters"])
        np.testing.assert_array_equal(f["t"][:], reference["t"])
        np.testing.assert_array_equal(f["y"][:], reference["y"])
        np.testing.assert_array_equal(f["steps/h"][:], reference["h"])
        np.testing.assert_array_equal(f["steps/alpha"][:], reference["alpha"])
        np.testing.assert_array_equal(f["events/pericentre/t"][:], reference["events"])


def test_output_times_in_config_give_samples_at_those_times(tmp_path):
    config = {**CONFIG, "integration": {"rtol": 1e-12, "t_end": "4*pi"},
              "output": {"times": {"start": 0, "stop": "4*pi", "n": 9}}}
    config.pop("events")
    out = tmp_path / "times.h5"
    result = CliRunner().invoke(cli, ["run", str(write_config(tmp_path, config)), "-o", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    loaded = elimfast.load(out)
    np.testing.assert_allclose(loaded.t, np.linspace(0, 4 * math.pi, 9), rtol=0, atol=1e-15)
    assert max(loaded.invariant_errors().values()) <= 1e-13


def test_inspect_says_a_terminal_event_ended_the_run(tmp_path):
    config = {**CONFIG, "integration": {"rtol": 1e-12, "t_end": 100},
              "events": {"apocentre": {"expression": "q1*p1 + q2*p2", "direction": -1, "terminal": True}}}
    out = tmp_path / "terminal.h5"
    result = CliRunner().invoke(cli, ["run", str(write_config(tmp_path, config)), "-o", str(out), "--quiet"])
    assert result.exit_code == 0, result.output
    loaded = elimfast.load(out)
    assert loaded.events["apocentre"].t.size == 1 and abs(loaded.events["apocentre"].t[0] - math.pi) < 1e-10
    assert loaded.status == "complete" and loaded.ended_by_event == "apocentre"   # a user trial looked for it
    report = CliRunner().invoke(cli, ["inspect", str(out)])
    status = next(line for line in report.output.splitlines() if line.startswith("status"))
    assert status.split(None, 1)[1] == f"complete (ended by a terminal event at t = {loaded.t_final:.10g})"
    assert abs(loaded.t_final - math.pi) < 1e-10
    assert "cut to land on t_end" not in report.output   # (the step to the apocentre is no shortest step)
    # A terminal pericentre: the last step, cut to land on it, is the shortest; inspect said 't_end' there
    # (a user trial)
    pericentre = {**config, "events": {"pericentre": {"expression": "q1*p1 + q2*p2", "direction": 1,
                                                      "terminal": True}}}
    ended = tmp_path / "pericentre.h5"
    assert CliRunner().invoke(cli, ["run", str(write_config(tmp_path, pericentre)), "-o", str(ended),
                                    "--quiet"]).exit_code == 0
    h_line = next(line for line in CliRunner().invoke(cli, ["inspect", str(ended)]).output.splitlines()
                  if line.startswith("h "))
    assert "the last, cut to land on the terminal event" in h_line and "t_end" not in h_line, h_line
    assert "after the last sample" not in report.output   # the event's state is the last sample
    # output times that stop before the event: the invariant figures say that they do not reach the end
    config["output"] = {"times": [1.0, 2.0, 50.0]}
    result = CliRunner().invoke(cli, ["run", str(write_config(tmp_path, config)), "-o", str(out), "--quiet",
                                      "--overwrite"])
    assert result.exit_code == 0, result.output
    report = CliRunner().invoke(cli, ["inspect", str(out)])
    invariants = next(line for line in report.output.splitlines() if line.startswith("invariants"))
    assert invariants.startswith(f"invariants   max |I(t) - I(t0)| over 2 samples (t <= 2; the run ended at "
                                 f"t = {loaded.t_final:.10g}, after the last sample)"), invariants
    # output times that all come after the event: no sample (a user trial was told that H and every
    # invariant were "NaN or infinite in some samples ... not defined on the whole orbit")
    config["output"] = {"times": [50.0, 60.0]}
    result = CliRunner().invoke(cli, ["run", str(write_config(tmp_path, config)), "-o", str(out), "--overwrite"])
    assert result.exit_code == 0, result.output
    said = f"no sample stored: the run ended at t = {loaded.t_final:.10g} before its first output time"
    assert f"note: {said}" in result.output and "NaN" not in result.output
    report = CliRunner().invoke(cli, ["inspect", str(out)])
    invariants = next(line for line in report.output.splitlines() if line.startswith("invariants"))
    assert invariants.startswith(f"invariants   no figures: {said}"), invariants


def test_fixed_step_run_with_events_keeps_its_steps(tmp_path):
    config = {"problem": {"builtin": "kepler"}, "method": {"name": "hbvm", "k": 6, "s": 3},
              "integration": {"h": 0.1, "n_steps": 200},
              "events": {"apocentre": {"expression": "q1*p1 + q2*p2", "direction": -1}}}
    spec = load_run_from_dict(config)
    run = Integration.from_spec(spec)
    chunks = [run.advance(1000)]
    plain = elimfast.integrate(spec.problem, spec.method, 0.1, n_steps=200)
    assert np.array_equal(run.y, plain.y_final)
    times = np.concatenate([c.event_t for c in chunks])
    assert times.size == 3 and np.allclose(times, PERIOD * (np.arange(3) + 0.5), atol=1e-6)


def test_section_plot_of_the_henon_heiles_config(tmp_path):
    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "section.h5"
    ran = CliRunner().invoke(cli, ["run", str(root / "configs" / "henon_heiles_section.yaml"), "-o", str(out),
                                   "--quiet", "--set", "integration.t_end=300"])
    assert ran.exit_code == 0, ran.output
    with h5py.File(out, "r") as f:
        states = f["events/section/y"][:]
    assert states.shape[0] >= 40 and np.max(np.abs(states[:, 0])) <= 1e-13 and np.all(states[:, 2] > 0)
    figure = tmp_path / "section.png"
    plotted = CliRunner().invoke(cli, ["plot", str(out), "--kind", "section", "-o", str(figure)])
    assert plotted.exit_code == 0, plotted.output
    assert figure.stat().st_size > 5000
    # a run without events: a clear one-line error, exit 2
    plain = tmp_path / "plain.h5"
    CliRunner().invoke(cli, ["run", str(root / "configs" / "henon_heiles_section.yaml"), "-o", str(plain),
                             "--quiet", "--set", "integration.t_end=10", "--set", "events=null"])
    refused = CliRunner().invoke(cli, ["plot", str(plain), "--kind", "section", "-o", str(tmp_path / "x.png")])
    assert refused.exit_code != 0 and "has no events" in refused.output and "Traceback" not in refused.output
    # A user trial: the section was always the first event, so a first event that never occurred (or
    # one that is no section) left no way to draw the others: --event chooses
    two = tmp_path / "two.h5"
    ran = CliRunner().invoke(cli, ["run", str(root / "configs" / "henon_heiles_section.yaml"), "-o", str(two),
                                   "--quiet", "--set", "integration.t_end=100", "--set",
                                   'events={never: "q1 - 100", section: {expression: q1, direction: 1}}'])
    assert ran.exit_code == 0, ran.output
    first = CliRunner().invoke(cli, ["plot", str(two), "--kind", "section", "-o", str(tmp_path / "n.png")])
    assert first.exit_code != 0 and "event 'never' never occurred" in first.output
    assert "choose another with --event ('section')" in first.output
    chosen = CliRunner().invoke(cli, ["plot", str(two), "--kind", "section", "--event", "section",
                                      "-o", str(tmp_path / "s.png")])
    assert chosen.exit_code == 0, chosen.output
    # A user trial: the plane was always the last q against the last p, so the section q2 = 0 drew q2
    # (pinned at 0) against p2. It is now the last degree of freedom the event leaves free.
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from elimfast_cli import plots
    q2 = tmp_path / "q2.h5"
    ran = CliRunner().invoke(cli, ["run", str(root / "configs" / "henon_heiles_section.yaml"), "-o", str(q2),
                                   "--quiet", "--set", "integration.t_end=100", "--set", "events.section.expression=q2"])
    assert ran.exit_code == 0, ran.output
    for path, plane in ((out, ("q2", "p2")), (q2, ("q1", "p1"))):
        figure, axes = plt.subplots()
        try:
            with RunFile(path) as run_file:
                plots._section(run_file, axes)
            assert (axes.get_xlabel(), axes.get_ylabel()) == plane
        finally:
            plt.close(figure)
    assert (tmp_path / "s.png").stat().st_size > 5000
    unknown = CliRunner().invoke(cli, ["plot", str(two), "--kind", "section", "--event", "sectoin",
                                       "-o", str(tmp_path / "u.png")])
    assert unknown.exit_code != 0 and "no event 'sectoin'; its events: never, section" in unknown.output
    wrong_kind = CliRunner().invoke(cli, ["plot", str(two), "--kind", "orbit", "--event", "section",
                                          "-o", str(tmp_path / "o.png")])
    assert wrong_kind.exit_code != 0 and "--event chooses the event of --kind section" in wrong_kind.output


def test_rtol_sweep_prints_error_against_work(tmp_path):
    from elimfast import sweep
    root = Path(__file__).resolve().parents[1]
    spec = sweep.load_sweep(root / "configs" / "sweeps" / "kepler_rtol.yaml")
    outcome = sweep.run_to_file(spec, tmp_path / "rtol.h5")
    header, rows = outcome.table("csv")
    column = {name: header.index(name) for name in ("rtol", "error", "steps", "grad H evals")}
    ehbvm = [row for row in rows if row[0].startswith("EHBVM")]
    errors = [float(row[column["error"]]) for row in ehbvm]
    work = [int(row[column["grad H evals"]]) for row in ehbvm]
    steps = [int(row[column["steps"]]) for row in ehbvm]
    assert len(ehbvm) == 6 and errors[-1] < errors[0] / 1000     # tighter rtol: smaller error ...
    assert steps == sorted(steps) and work[-1] > work[0]          # ... for more work


def test_a_long_output_grid_is_stored_as_its_grid_and_resolves_again():
    """output.times {start, stop, step} is stored in the run file's config as that grid, not
    as its times: 125,664 stored times made a config that --resume refused ("more than
    100000 entries"). Reloaded, the stored grid gives the same times bit for bit."""
    config = {**CONFIG, "integration": {"rtol": 1e-12, "t_end": "20000*pi"},
              "output": {"times": {"start": 0, "stop": "20000*pi", "step": 0.5}}}
    spec = load_run_from_dict(config)
    stored = spec.resolved["output"]["times"]
    assert stored == {"start": 0.0, "stop": 20000 * math.pi, "step": 0.5}
    again = load_run_from_dict(yaml.safe_load(yaml.safe_dump(spec.resolved)))
    assert again.t_eval.size == spec.t_eval.size > 100_000
    np.testing.assert_array_equal(again.t_eval, spec.t_eval)
    listed = load_run_from_dict({**config, "output": {"times": [0.0, 1.5, 3.0]}})
    assert listed.resolved["output"]["times"] == [0.0, 1.5, 3.0]


@pytest.mark.slow
def test_kill_9_and_resume_keep_every_sample_of_a_dense_output_grid(tmp_path):
    """Output times denser than the steps (here ~15 samples per step): resume used to cut the
    samples back to one per step (the fixed-step rule for a failed run's extra sample) and
    lost 18% of them."""
    config = {**CONFIG, "integration": {"rtol": 1e-13, "t_end": "200*pi"},
              "output": {"every": 1, "times": {"start": 0, "stop": "200*pi", "step": 0.004}}}
    config.pop("events")
    path = write_config(tmp_path, config)
    whole, out = tmp_path / "whole.h5", tmp_path / "run.h5"
    done = subprocess.run([ELIMFAST, "run", str(path), "-o", str(whole), "--quiet"], capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    kill_after(path, out, 2000)
    resumed = subprocess.run([ELIMFAST, "run", str(path), "-o", str(out), "--resume", "--quiet"],
                             capture_output=True, text=True, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    with h5py.File(whole, "r") as a, h5py.File(out, "r") as b:
        assert a["t"].shape[0] > 10 * a["steps/h"].shape[0]
        for name in ("t", "y", "invariants/H", "steps/h"):
            np.testing.assert_array_equal(b[name][:], a[name][:])


def test_an_adaptive_run_continued_to_a_later_end_with_more_output_times(tmp_path):
    """--resume --set integration.t_end=LATER --set output.times.stop=LATER: the times written
    are kept, the new ones follow, and the state is that of a run that stopped at the old end
    and went on (its last step was cut to land there): within 1e-9 of the uninterrupted run,
    whose own error is 1e-9 here; an output grid that changes the times written is refused."""
    config = {**CONFIG, "integration": {"rtol": 1e-13, "t_end": "20*pi"},
              "output": {"times": {"start": 0, "stop": "20*pi", "step": 0.25}}}
    config.pop("events")
    path = write_config(tmp_path, config)
    out, whole = tmp_path / "run.h5", tmp_path / "whole.h5"
    assert CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--quiet"]).exit_code == 0
    later = ["--set", "integration.t_end=40*pi", "--set", "output.times.stop=40*pi"]
    result = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", *later])
    assert result.exit_code == 0, result.stderr
    assert CliRunner().invoke(cli, ["run", str(path), "-o", str(whole), "--quiet", *later]).exit_code == 0
    with h5py.File(out, "r") as a, h5py.File(whole, "r") as b:
        assert a.attrs["output_times"] == b["t"].shape[0] == 503
        np.testing.assert_array_equal(a["t"][:], b["t"][:])
        np.testing.assert_allclose(a["y"][:], b["y"][:], rtol=0, atol=1e-9)
        assert np.max(np.abs(a["state/y"][:] - a["y"][0])) < 1e-8
    other_step = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--set",
                                          "integration.t_end=60*pi", "--set", "output.times.step=0.5"])
    assert other_step.exit_code == 2
    assert "output.times must keep the 503 times already written" in other_step.stderr
    removed = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--set",
                                       "integration.t_end=60*pi", "--set", "output.times=null"])
    assert removed.exit_code == 2 and "output.times cannot be removed on --resume" in removed.stderr
    # A user trial: a later t_end alone ran the extension without samples, and the advice printed then
    # (a later output.times.stop) was refused, the times being before the new end: refused up front now
    unsampled = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--set",
                                         "output.times.stop=40*pi", "--set", "integration.t_end=60*pi"])
    assert unsampled.exit_code == 2, unsampled.stderr
    assert ("output.times stops at 125.5, so the run continued to t_end = 188.49555921538757 "
            "would have no samples after 125.66370614359172") in unsampled.stderr
    with h5py.File(out, "r") as f:
        assert f.attrs["output_times"] == 503 and f["t"].shape[0] == 503


def test_output_times_given_as_a_list_are_told_to_grow_as_a_list(tmp_path):
    """A user trial: output times given as a list, continued to a later end without later times, were
    told to set output.times.stop, which a list does not have. The advice gives the whole list; it works."""
    config = {**CONFIG, "integration": {"rtol": 1e-12, "t_end": 10}, "output": {"times": [1, 2, 3.5, 9]}}
    config.pop("events")
    path = write_config(tmp_path, config)
    out = tmp_path / "run.h5"
    assert CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--quiet"]).exit_code == 0
    refused = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--set", "integration.t_end=20"])
    assert refused.exit_code == 2 and "output.times.stop" not in refused.stderr, refused.stderr
    advice = "--set 'output.times=[1, 2, 3.5, 9, 20]'"
    assert advice in refused.stderr, refused.stderr
    followed = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--quiet", "--set",
                                        "integration.t_end=20", "--set", "output.times=[1, 2, 3.5, 9, 20]"])
    assert followed.exit_code == 0, followed.stderr
    with h5py.File(out, "r") as f:
        np.testing.assert_array_equal(f["t"][:], [1, 2, 3.5, 9, 20])


def test_output_times_given_by_set_are_continued_by_a_set_of_their_stop(tmp_path):
    """A user trial: output.times given as a --set mapping, then --resume --set output.times.stop=LATER
    (what the refusal of an earlier output end advises) was refused with 'output.times.start: missing':
    the stored mapping was dropped for the given key under it. It stays, and the given key changes
    its stop: the file then holds the times of a run given the later grid from the start."""
    config = {**CONFIG, "integration": {"rtol": 1e-12, "t_end": "4*pi"}, "output": {"every": 1}}
    config.pop("events")
    path = write_config(tmp_path, config)
    out, whole = tmp_path / "run.h5", tmp_path / "whole.h5"
    first = ["--set", "output.times={start: 0, stop: 4*pi, step: 0.5}"]
    assert CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--quiet", *first]).exit_code == 0
    later = ["--set", "integration.t_end=8*pi", "--set", "output.times.stop=8*pi"]
    result = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--quiet", *later])
    assert result.exit_code == 0, result.stderr
    assert CliRunner().invoke(cli, ["run", str(path), "-o", str(whole), "--quiet", "--set",
                                    "output.times={start: 0, stop: 8*pi, step: 0.5}", *later[:2]]).exit_code == 0
    with h5py.File(out, "r") as a, h5py.File(whole, "r") as b:
        assert a["t"].shape[0] == 51
        np.testing.assert_array_equal(a["t"][:], b["t"][:])
    # a given mapping still replaces the stored one whole
    replaced = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--quiet", "--set",
                                        "integration.t_end=12*pi", "--set", "output.times={start: 0, step: 0.5}"])
    assert replaced.exit_code == 2 and "output.times.stop: missing" in replaced.stderr


def test_a_run_ended_by_a_terminal_event_is_not_continued_past_it(tmp_path):
    config = {**CONFIG, "integration": {"rtol": 1e-12, "t_end": "10*pi"},
              "events": {"apocentre": {"expression": "q1*p1 + q2*p2", "direction": -1, "terminal": True}}}
    path = write_config(tmp_path, config)
    out = tmp_path / "run.h5"
    assert CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--quiet"]).exit_code == 0
    result = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--set",
                                      "integration.t_end=20*pi"])
    assert result.exit_code == 2
    assert "was ended by a terminal event at t = 3.14159" in result.stderr


# Output times that start after t0: GAUSS(2) at h = 0.3 loses H, A_x, A_y at the 1e-2 level, so a
# reference taken at the first sample (t = 5) instead of t0 is off by far more than round-off.
LATE_TIMES = {"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}},
              "method": {"name": "gauss", "s": 2}, "integration": {"h": 0.3, "t_end": 30},
              "output": {"times": {"start": 5, "stop": 30, "step": 5}}}


def errors_against(values: dict, reference: dict) -> dict:
    return {name: float(np.max(np.abs(column - reference[name]))) for name, column in values.items()}


def test_invariant_errors_are_measured_against_the_initial_state_when_output_times_start_later(tmp_path):
    """With output times later than t0 the first sample was taken as I(t0): the errors (and
    lrl_y's relative error, 5.6 against the first sample's A_y instead of A_y(t0) = 0) were
    measured against the state at t = 5. They are measured against y0 at t0: in Result, in
    the run file (value_at_t0), in inspect, in the sweep table and in a Result loaded back."""
    from elimfast import sweep
    from elimfast.integrate import relative_error

    path = write_config(tmp_path, LATE_TIMES)
    spec = load_run(path)
    at_t0 = spec.problem.invariant_values(spec.problem.y0)
    result = elimfast.integrate(
        spec.problem, spec.method, h=0.3, t_end=30.0, t_eval=np.arange(5.0, 30.1, 5.0))
    assert result.t[0] == 5.0 and result.t0 == 0.0
    expected = errors_against(result.invariants, at_t0)
    against_first = errors_against(result.invariants, {n: v[0] for n, v in result.invariants.items()})
    assert all(abs(expected[n] - against_first[n]) > 1e-4 for n in ("H", "lrl_x", "lrl_y"))   # the test can fail
    assert result.invariant_errors() == expected
    assert result.initial_invariants() == at_t0
    # the run file: I(t0) stored, and what inspect prints
    out = tmp_path / "late.h5"
    ran = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--quiet"])
    assert ran.exit_code == 0, ran.output
    with h5py.File(out, "r") as f:
        assert {name: f["invariants"][name].attrs["value_at_t0"] for name in at_t0} == at_t0
    with RunFile(out) as stored:
        assert stored.invariant_drift() == expected and stored.reference_time() == 0.0
    text = CliRunner().invoke(cli, ["inspect", str(out)]).stdout
    assert "max |I(t) - I(t0)| over 6 samples, and relative to |I(t0)|" in text
    scales = spec.problem.invariant_scales(spec.problem.y0)
    for name in ("H", "lrl_x"):
        line = next(line for line in text.splitlines() if line.startswith(f"  {name} "))
        assert f"{expected[name]:.3e}  relative {relative_error(expected[name], at_t0[name], scales[name]):.3e}" \
            in line, line
    assert elimfast.load(out).invariant_errors() == expected
    # a sweep's table and its stored run
    sweep_file = tmp_path / "sweep.yaml"
    sweep_file.write_text(yaml.safe_dump({"base": LATE_TIMES, "grid": [{"name": "h", "key": "integration.h",
                                                                        "values": [0.3]}]}))
    outcome = sweep.run_to_file(sweep.load_sweep(sweep_file), tmp_path / "sweep.h5", workers=1)
    assert outcome.outcomes[0].invariant_errors == expected
    with h5py.File(tmp_path / "sweep.h5", "r") as f:
        run = f["runs/0.3"]
        assert run.attrs["t0"] == 0.0 and run["invariants/H"].attrs["value_at_t0"] == at_t0["H"]


def test_a_file_written_before_the_values_at_t0_were_stored_says_which_reference_it_uses(tmp_path):
    """Older files keep reading: without value_at_t0 the first sample is the reference, and
    inspect says so when that sample is later than t0."""
    out = tmp_path / "old.h5"
    ran = CliRunner().invoke(cli, ["run", str(write_config(tmp_path, LATE_TIMES)), "-o", str(out), "--quiet"])
    assert ran.exit_code == 0, ran.output
    with h5py.File(out, "r+") as f:
        for name in f["invariants"]:
            del f["invariants"][name].attrs["value_at_t0"]
        first = {name: f["invariants"][name][0] for name in f["invariants"]}
        expected = errors_against({name: f["invariants"][name][:] for name in f["invariants"]}, first)
    with RunFile(out) as stored:
        assert stored.invariant_drift() == expected and stored.reference_time() == 5.0
    inspected = CliRunner().invoke(cli, ["inspect", str(out)])
    assert inspected.exit_code == 0, inspected.output
    assert ("invariants   max |I(t) - I(t = 5)| over 6 samples, and relative to it: the first sample, not t0 = 0.0 "
            "(the file predates storing I(t0))") in inspected.stdout
    plotted = CliRunner().invoke(cli, ["plot", str(out), "-o", str(tmp_path / "i.png")])
    assert plotted.exit_code == 0, plotted.output


def test_a_run_stopped_short_keeps_no_event_found_after_its_saved_state(tmp_path):
    """A run stopped short (a problem function raising, a disk full) is cut back to its last saved
    state by RunWriter.finish: samples and steps were, the events found after it were not (the
    writer's record of the saved state had no event counts), so the file kept events of steps
    it no longer held (found by reading the code, helper-37)."""
    from elimfast.io.hdf5 import RunWriter
    spec = load_run(write_config(tmp_path))
    run = Integration.from_spec(spec)
    path = tmp_path / "short.h5"
    writer = RunWriter.create(path, run, config_text="{}", t_end=spec.t_end)
    writer.append(run.advance(200))
    writer.save_state(run.state(), wall_time_s=0.0, kernel_time_s=0.0)
    saved_steps, saved_events = run.steps_done, int(run.event_counts.sum())
    chunk = run.advance(400)        # appended, never saved: a chunk cut short
    assert chunk.event_t.size > 0
    writer.append(chunk)
    writer.finish("stopped: test", steps_done=run.steps_done, wall_time_s=0.0, kernel_time_s=0.0)
    with h5py.File(path, "r") as f:
        assert f["steps/iterations"].shape[0] == saved_steps
        assert sum(f["events"][name]["t"].shape[0] for name in f["events"]) == saved_events
        assert all(f["events"][name]["y"].shape[0] == f["events"][name]["t"].shape[0] for name in f["events"])
    # a writer reopened by --resume (or just created) knows its saved events too, before any chunk
    writer, saved = RunWriter.resume(path)
    writer.finish("stopped: test", steps_done=saved["steps_done"], wall_time_s=0.0, kernel_time_s=0.0)
    with h5py.File(path, "r") as f:
        assert sum(f["events"][name]["t"].shape[0] for name in f["events"]) == saved_events


def test_repair_cuts_a_killed_runs_events_back_to_its_saved_state(tmp_path):
    """A writer killed between flushing a chunk and saving its state leaves the chunk's rows on disk;
    repair cut samples and steps back to the saved state but kept the chunk's events (as finish did)."""
    config = write_config(tmp_path)
    path = tmp_path / "killed.h5"
    script = f"""
import os
import numpy as np
from elimfast.config import load_run
from elimfast.integrate import Integration
from elimfast.io.hdf5 import RunWriter
spec = load_run({str(config)!r})
run = Integration.from_spec(spec)
writer = RunWriter.create({str(path)!r}, run, config_text="{{}}", t_end=spec.t_end)
writer.append(run.advance(200))
writer.save_state(run.state(), wall_time_s=0.0, kernel_time_s=0.0)
print(int(run.steps_done), int(run.event_counts.sum()))
chunk = run.advance(400)
assert chunk.event_t.size > 0
writer.append(chunk)
writer._file.flush()        # the chunk is on disk, its state is not: then the writer dies
os._exit(0)
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    saved_steps, saved_events = map(int, done.stdout.split())
    from elimfast.io.repair import repair
    repair(path)
    with h5py.File(path, "r") as f:
        assert f.attrs["steps_done"] == f["steps/iterations"].shape[0] == saved_steps
        assert sum(f["events"][name]["t"].shape[0] for name in f["events"]) == saved_events


def test_run_names_an_event_that_turns_nan(tmp_path):
    """The end-of-run line names an event that was NaN at samples of the run (a user trial's
    sqrt(q1 + 0.5) on Kepler e = 0.9 found nothing, and nothing was said)."""
    config = {**CONFIG, "integration": {"rtol": 1e-12, "t_end": "4*pi"},
              "events": {"nan": {"expression": "sqrt(q1 + 0.5)"}}}
    path = write_config(tmp_path, config)
    ran = CliRunner().invoke(cli, ["run", str(path), "-o", str(tmp_path / "nan.h5")])
    assert ran.exit_code == 0, ran.output
    assert "event 'nan' (first at t = " in ran.stderr and "NaN or infinite at samples of this run" in ran.stderr


def test_an_event_nan_before_a_kill_is_named_after_the_resume(tmp_path):
    """An event NaN or infinite is written to /events/<name> when a run ends: a run killed after
    seeing it, then resumed, lost it (the resumed part may never see it again). The resume now
    checks the stored samples again, so the file names the first time from before the kill."""
    config = write_config(tmp_path, {**CONFIG, "integration": {"rtol": 1e-10, "t_end": "4000*pi"},
                                     "events": {"nan": {"expression": "sqrt(q1 + 0.5)"}}})
    out = tmp_path / "nan.h5"
    kill_after(config, out, 2000)
    with h5py.File(out, "r", swmr=True) as f:
        assert "not_finite_from" not in f["events/nan"].attrs
    with RunFile(out) as stored:
        killed_at = float(stored.t()[-1])   # the last sample the killed run stored
    assert subprocess.run([ELIMFAST, "run", str(config), "-o", str(out), "--resume", "--quiet"]).returncode == 0
    resumed = elimfast.load(out)
    first = resumed.events_not_finite["nan"]
    index = int(np.searchsorted(resumed.t, first))
    assert first < killed_at and resumed.t[index] == first and resumed.y[index, 0] < -0.5   # a stored sample's time


def test_resume_to_an_earlier_end_with_output_times_says_why(tmp_path):
    """A user trial: --resume --set integration.t_end=<earlier> of a run with output.times was refused
    as 'output.times: must lie within the run', a new run's rule, not the resume's: 'never an earlier one'."""
    config = {**CONFIG, "integration": {"rtol": 1e-10, "t_end": "4*pi"},
              "output": {"times": {"start": 0, "stop": "4*pi", "step": "pi/2"}}}
    path, out = write_config(tmp_path, config), tmp_path / "run.h5"
    assert CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "-q"]).exit_code == 0
    done = CliRunner().invoke(cli, ["run", str(path), "-o", str(out), "--resume", "--set", "integration.t_end=2*pi"])
    assert done.exit_code == 2
    assert done.stderr == (f"error: {out}: integration.t_end = 6.283185307 is before the end of the stored run, "
                           "12.56637061: --resume continues a run to a later t_end, never an earlier one; start a new "
                           "run (-o NEW.h5) for a shorter one\n")


@pytest.mark.parametrize("start, stop, step", [(0, 0.7, 0.1), (0.1, 0.7, 0.1), (0, 0.3, 0.1), (0, 1.1, 0.1),
                                               (0, "20000*pi", "pi/4")])
def test_an_output_grid_ends_on_its_stop_not_a_rounding_past_it(start, stop, step):
    """output.times {start, stop, step} whose stop is on the grid samples at stop itself:
    {0, 0.7, 0.1} sampled at 0.7000000000000001 (0.1 * 7 rounds up), past the stop asked for
    (a user trial). The other times are start + i step, as before."""
    config = {**CONFIG, "integration": {"rtol": 1e-10, "t_end": stop},
              "output": {"times": {"start": start, "stop": stop, "step": step}}}
    spec = load_run_from_dict(config)
    stop_value, start_value = spec.resolved["output"]["times"]["stop"], float(start)
    step_value = spec.resolved["output"]["times"]["step"]
    assert spec.t_eval[-1] == stop_value
    expected = start_value + step_value * np.arange(spec.t_eval.size)
    np.testing.assert_array_equal(spec.t_eval[:-1], expected[:-1])
    assert abs(expected[-1] - stop_value) < 1e-12 * stop_value
