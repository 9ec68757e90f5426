"""The command line: every command through click's CliRunner, and a real process for run/inspect/plot."""
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from elimfast import methods
from elimfast.config import load_run
from elimfast.problems import PROBLEMS
from elimfast_cli.main import cli

ROOT = Path(__file__).resolve().parents[1]
KEPLER = str(ROOT / "configs" / "kepler.yaml")
SHORT = ["--set", "integration.t_end=20"]          # 200 steps of the default config
ELIMFAST = str(Path(sys.executable).with_name("elimfast"))


def invoke(*args, env=None):
    return CliRunner().invoke(cli, [str(a) for a in args], env=env)


@pytest.fixture(scope="module")
def kepler_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "kepler.h5"
    result = invoke("run", KEPLER, "-o", path, *SHORT)
    assert result.exit_code == 0, result.output
    return path


def test_run_writes_the_file_and_a_summary_line(kepler_file):
    with h5py.File(kepler_file, "r") as f:
        assert f.attrs["status"] == "complete" and f.attrs["steps_done"] == 200
        assert f.attrs["method"] == "EHBVM(12,3)" and list(f.attrs["conserve"]) == ["angular_momentum", "lrl_y"]
        config = yaml.safe_load(f.attrs["config"])
        assert config["output"]["path"] == str(kepler_file) and config["integration"]["t_end"] == 20
        assert f["t"].shape == (21,)      # output.every = 10 in configs/kepler.yaml
        assert f["steps/alpha"].shape == (200, 2)


def test_a_run_whose_file_may_grow_large_says_so_before_it_starts(tmp_path, monkeypatch):
    """A user trial: 10^9 steps with output.every 1 (about 43 GB) began without a word. A run whose
    output may grow by more than LARGE_OUTPUT_BYTES says how much, before compression, and what
    makes it (here the threshold is lowered to 10 kB for a 2,000-step run; the default's 200 steps
    stay silent, as the test above checks); a disk without that room is named too."""
    from types import SimpleNamespace
    from elimfast import streaming
    monkeypatch.setattr(streaming, "LARGE_OUTPUT_BYTES", 1e4)
    path = tmp_path / "big.h5"
    result = invoke("run", KEPLER, "-o", path, "--set", "integration.t_end=200")
    assert result.exit_code == 0, result.output
    step_bytes = 8 + 8 * 2 + 8 * (1 + 4 + 1 + 3) / 10   # iterations and substeps, alpha, a tenth of a sample
    first = result.stderr.splitlines()[0]
    from elimfast.io.safety import _size
    assert first == (f"note: {path} may grow by up to {_size(2000 * step_bytes)}: 2,000 steps of up to "
                     f"{step_bytes:.0f} bytes each before compression (every step's iterations and multipliers, "
                     "and the samples; raise output.every or shorten the run for less)"), first
    assert "note:" not in invoke("run", KEPLER, "-o", path, "--overwrite", "--quiet",
                                 "--set", "integration.t_end=200").stderr
    writer = SimpleNamespace(path=tmp_path / "x.h5")
    free = os.statvfs(tmp_path).f_bavail * os.statvfs(tmp_path).f_frsize
    assert streaming.output_growth_note(writer, int(10 * free / 96), 96.0).endswith(
        "free: if it fills, the run stops there (resume it once there is room)")
    assert streaming.output_growth_note(writer, None, 96.0) is None      # adaptive steps: not known


def test_run_quiet_prints_nothing_and_the_default_prints_one_line(tmp_path):
    quiet = invoke("run", KEPLER, "-o", tmp_path / "q.h5", "--quiet", *SHORT)
    assert quiet.exit_code == 0 and quiet.stdout == "" and quiet.stderr == ""
    loud = invoke("run", KEPLER, "-o", tmp_path / "q.h5", "--overwrite", *SHORT)
    assert loud.exit_code == 0 and loud.stdout == ""
    assert loud.stderr.count("\n") == 1 and "complete, 200 steps" in loud.stderr and "steps/s" in loud.stderr
    # the rate is that of the figures beside it (a user trial: 41 steps, wall time 0.00384 s, 7,040 steps/s)
    import re
    wall, rate = re.search(r"wall time (\S+) s, ([\d,]+) steps/s", loud.stderr).groups()
    assert abs(200 / float(wall) / float(rate.replace(",", "")) - 1) < 0.01 + 1 / float(rate.replace(",", ""))
    # the step count as the rate and inspect write it (a user trial: "763336 steps ... 106,950 steps/s")
    thousands = invoke("run", KEPLER, "-o", tmp_path / "q.h5", "--overwrite", "--set", "integration.t_end=200")
    assert "complete, 2,000 steps" in thousands.stderr, thousands.stderr


def test_inspect_summary(kepler_file):
    result = invoke("inspect", kepler_file)
    assert result.exit_code == 0, result.output
    text = result.stdout
    for expected in ("problem      kepler (eccentricity = 0.6)", "method       EHBVM(12,3), order 6, imposing "
                     "angular_momentum, lrl_y", "h            0.1", "steps done   200 / 200", "status       complete",
                     "wall time", "steps/s", "max |I(t) - I(t0)| over 21 samples", "iterations   mean",
                     "max |alpha|"):
        assert expected in text, expected
    for name in ("H", "angular_momentum", "lrl_x", "lrl_y"):
        assert f"\n  {name} " in text
    # the numbers are those of the file
    with h5py.File(kepler_file, "r") as f:
        drift = np.max(np.abs(f["invariants/lrl_x"][:] - f["invariants/lrl_x"][0]))
        alpha = np.max(np.abs(f["steps/alpha"][:]), axis=0)
    assert f"lrl_x             {drift:.3e}" in text
    assert f"{alpha[0]:.3e} (angular_momentum), {alpha[1]:.3e} (lrl_y)" in text


def test_inspect_gives_a_finished_runs_wall_time_as_run_printed_it(kepler_file, tmp_path):
    """inspect showed the wall time of the last saved chunk (0.078 s) where `run` had printed the
    whole run's, which the root attribute holds (0.0807 s; a user trial's finding). A running or
    killed run has only its saved state's."""
    import shutil
    path = tmp_path / "timed.h5"
    shutil.copy(kepler_file, path)
    with h5py.File(path, "r+") as f:
        f.attrs["wall_time_s"] = 98.7
        f.attrs["kernel_time_s"] = 65.4
    assert "wall time    98.7 s, 2 steps/s; kernel 65.4 s, 3 steps/s" in invoke("inspect", path).stdout


def test_inspect_shows_every_solver_setting_that_decides_the_iteration(kepler_file, tmp_path):
    """inspect's solver line left out solver.accelerate (simplified Newton's secant steps, on by
    default), which changes the iteration counts the line above it reports. It is read from the
    stored config; a file written before the setting existed ran without acceleration."""
    import shutil
    solver_line = lambda path: next(line for line in invoke("inspect", path).stdout.splitlines()
                                    if line.startswith("solver "))
    assert solver_line(kepler_file) == "solver       newton, max_iter 30, max_halvings 4, predictor True, accelerate True"
    with h5py.File(kepler_file, "r") as f:
        config = yaml.safe_load(f.attrs["config"])
    for settings, shown in (({"accelerate": False}, "newton, max_iter 30, max_halvings 4, predictor True, "
                                                    "accelerate False"),
                            ({"accelerate": None}, "newton, max_iter 30, max_halvings 4, predictor True, "
                                                   "accelerate False"),
                            ({"method": "fixed_point", "max_iter": 100}, "fixed_point, max_iter 100, max_halvings 4, "
                             "predictor True, accelerate True (simplified Newton's only)")):
        path = tmp_path / "solver.h5"
        shutil.copy(kepler_file, path)
        solver = {**config["solver"], **settings}
        if settings.get("accelerate", "") is None:   # a file from before the setting
            del solver["accelerate"]
        with h5py.File(path, "r+") as f:
            f.attrs["config"] = yaml.safe_dump({**config, "solver": solver}, sort_keys=False)
        assert solver_line(path) == "solver       " + shown


def test_inspect_says_why_a_step_took_more_iterations_than_max_iter(kepler_file, tmp_path):
    """'max 68' beside 'max_iter 30' and no split step read as a contradiction (a user trial):
    a step's count is every solve it took. Said only when the maximum exceeds max_iter."""
    note = "a step counts every solve it took (max_iter bounds one)"
    assert note not in invoke("inspect", kepler_file).stdout
    path = tmp_path / "tight.h5"
    assert invoke("run", KEPLER, "-o", path, "--set", "integration.t_end=10", "--set", "solver.max_iter=5",
                  "--quiet").exit_code == 0
    report = invoke("inspect", path).stdout
    maximum = int(next(line for line in report.splitlines() if line.startswith("iterations ")).split("max ")[1]
                  .split(",")[0])
    assert maximum > 5 and note in report


def test_inspect_counts_steps_with_a_substep_taken_without_imposing(kepler_file, tmp_path):
    """A substep that cannot be solved imposing the invariants even at the deepest halving is taken
    without them when that keeps them to round-off; its step's alpha is NaN (docs/solver.md#a-substep-
    without-imposing; the kernel side: tests/test_step_engine.py). inspect and the end-of-run notes say
    how many, and max |alpha| stays that of the other steps (np.max made it nan)."""
    import shutil
    from elimfast.io.hdf5 import RunFile
    from elimfast_cli.report import run_notes
    path = tmp_path / "unimposed.h5"
    shutil.copy(kepler_file, path)
    with h5py.File(path, "r+") as f:
        alpha = f["steps/alpha"][:]
        f["steps/alpha"][5] = np.nan
    text = invoke("inspect", path).stdout
    assert "1 step(s) were taken, or had a substep taken, without imposing the invariants, because imposing failed there" in text
    # the invariants' tags say it too (a user trial read '(imposed)' where no step had imposed them)
    n_steps = len(alpha)
    assert f"(imposed; 1 of {n_steps:,} steps could not: see below)" in text and "  (imposed)" not in text, text
    largest = np.max(np.abs(np.delete(alpha, 5, axis=0)), axis=0)
    assert f"{largest[0]:.3e} (angular_momentum), {largest[1]:.3e} (lrl_y)" in text
    with RunFile(path) as run_file:
        assert any("without imposing the invariants, because imposing failed" in note for note in run_notes(run_file))
    assert "without imposing" not in invoke("inspect", kepler_file).stdout
    assert "degenerate along this orbit" not in text    # 1 of 200 steps: a transient zero of Gamma
    with h5py.File(path, "r+") as f:                    # most steps: L on a circular orbit did that
        f["steps/alpha"][:150] = np.nan
    text = invoke("inspect", path).stdout
    assert "150 step(s) were taken, or had a substep taken" in text and "degenerate along this orbit" in text
    assert "nearly planar system" in text and "GHBVM (LIM)" in text   # the other degenerate case, and the way out
    with h5py.File(path, "r+") as f:
        f["steps/alpha"][:] = np.nan
    assert "(imposed, but no step could: see the note below)" in invoke("inspect", path).stdout
    assert "too short for Gamma" not in text


def test_many_unimposed_steps_of_an_adaptive_run_name_its_shortest_steps(tmp_path):
    """A user trial: Kepler e = 0.99 under the time-scale controller (epsilon 0.05) took pericentre
    steps without imposing (80 of 458 steps over two periods), and was told that its imposed
    invariants were degenerate along the orbit, which is not so. The note names the short steps too.
    (At e = 0.99 and 0.9995 those steps are now taken imposed: they were split on cond(Gamma) alone,
    and then taken unimposed, docs/solver.md; at e = 0.9999 too, since cond(Gamma) is taken with its
    columns scaled, and at e = 0.99999 and beyond since its pivots are judged per column. With
    s = 8, whose Gamma holds Legendre coefficients of index 6 and 7 (~h^6, h^7), 47 of 573
    pericentre steps of e = 0.99 at epsilon 0.02 are too short for Gamma.)"""
    import yaml
    config = tmp_path / "e099.yaml"
    config.write_text(yaml.safe_dump({
        "problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.99}},
        "conserve": ["angular_momentum", "lrl_y"], "method": {"name": "ehbvm", "k": 16, "s": 8},
        "integration": {"step_control": "time_scale", "epsilon": 0.02, "t_end": "2*pi"}}))
    out = tmp_path / "e099.h5"
    ran = invoke("run", config, "-o", out)
    assert ran.exit_code == 0, ran.output
    assert "too short for Gamma" in ran.stderr and "larger epsilon or rtol" in ran.stderr, ran.stderr
    assert "too short for Gamma" in invoke("inspect", out).stdout


def test_elim_with_r_above_k_at_s_4_or_more_is_told_its_literal_sum_not_degenerate_invariants(tmp_path):
    """A user trial: ELIM(16,12,6) (r > k: the paper's literal sum, the only form there) imposing L
    on Kepler split every step and took it unimposed, at ~900 iterations a step; the note blamed L as
    degenerate along the orbit (EHBVM(12,6) imposes it there with no split), and inspect gave
    max |alpha| 0.000e+00 where every alpha is NaN."""
    import yaml
    config = tmp_path / "elim.yaml"
    config.write_text(yaml.safe_dump({"problem": {"builtin": "kepler"}, "method": "ELIM(16,12,6)",
                                      "conserve": ["angular_momentum"],
                                      "integration": {"h": "pi/20", "t_end": "2*pi"},
                                      "solver": {"method": "fixed_point"}}))
    out = tmp_path / "elim.h5"
    ran = invoke("run", config, "-o", out)
    assert ran.exit_code == 0, ran.output
    literal = "with r > k (r = 16, k = 12) alpha's right-hand side is the paper's literal sum"
    assert literal in ran.stderr and "degenerate along this orbit" not in ran.stderr, ran.stderr
    text = invoke("inspect", out).stdout
    assert literal in text and "max |alpha|  none (no step imposed it) (angular_momentum)" in text, text


def test_inspect_says_which_iterations_its_figures_count(tmp_path):
    """A user trial: inspect's total for an adaptive run (the accepted steps') differed from the sweep
    table's (every solve, rejected and side steps too, as grad H counts them), and neither said which."""
    out = tmp_path / "adaptive.h5"
    done = invoke("run", str(ROOT / "configs" / "kepler_adaptive.yaml"), "-o", out, "--set", "integration.t_end=20*pi",
                  "--quiet")
    assert done.exit_code == 0, done.output
    line = next(line for line in invoke("inspect", out).stdout.splitlines() if line.startswith("iterations "))
    with h5py.File(out, "r") as f:
        every, accepted = int(f.attrs["stats_iterations"]), int(f["steps/iterations"][:].sum())
    assert every > accepted, (every, accepted)   # rejected steps and side steps (the events') solve too
    assert line.startswith("iterations   of the accepted steps: mean ") and f"total {accepted:,}; all solves, " \
        f"rejected and side steps too: {every:,}" in line, line


def test_inspect_says_the_initial_state_comes_from_problem_initial(kepler_file, tmp_path):
    """problem.initial replaces the state kepler's eccentricity chooses: inspect said
    'kepler (eccentricity = 0.6)' as if the parameter described the orbit."""
    path = tmp_path / "given.h5"
    done = invoke("run", KEPLER, "-o", path, *SHORT, "--set", "problem.initial={q1: 0.5, p2: 1.2}", "--quiet")
    assert done.exit_code == 0, done.output
    lines = invoke("inspect", path).stdout.splitlines()
    assert lines[1] == ("problem      kepler (eccentricity = 0.6); initial state from problem.initial, not the "
                        "default of these parameters: q1 = 0.5, q2 = 0.0, p1 = 0.0, p2 = 1.2")
    with h5py.File(path, "r") as f:
        assert f.attrs["initial_state"] == "problem.initial"
    # the default state, also when problem.initial repeats it, is described by the parameters alone
    same = tmp_path / "same.h5"
    assert invoke("run", KEPLER, "-o", same, *SHORT, "--set", "problem.initial={q1: 0.4}", "--quiet").exit_code == 0
    for default in (kepler_file, same):
        assert invoke("inspect", default).stdout.splitlines()[1] == "problem      kepler (eccentricity = 0.6)"


@pytest.mark.parametrize("kind", ["orbit", "invariants", "alpha", "iterations"])
def test_plot_is_not_blank(kepler_file, tmp_path, kind):
    from matplotlib.image import imread
    figure = tmp_path / f"{kind}.png"
    result = invoke("plot", kepler_file, "--kind", kind, "-o", figure)
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == str(figure)
    pixels = imread(figure)[..., :3]
    assert pixels.shape[0] > 200 and pixels.shape[1] > 300
    assert pixels.var() > 1e-3                                    # not one flat colour
    assert (np.abs(pixels - 1.0).sum(axis=2) > 0.3).mean() > 0.01  # ink on more than 1% of the canvas
    again = invoke("plot", kepler_file, "--kind", kind, "-o", figure)
    assert again.exit_code == 2 and "--overwrite" in again.stderr


def test_invariant_plot_of_a_run_with_two_samples_shows_its_points(tmp_path):
    """A run that kept only t0 and t_end has one finite error per invariant (t0's is 0, not
    on a log scale): drawn as a line, nothing appeared (a user trial's finding)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from elimfast.io.hdf5 import RunFile
    from elimfast_cli.plots import _invariants

    path = tmp_path / "two.h5"
    assert invoke("run", KEPLER, "-o", path, "--set", "integration.t_end=5", "--set", "output.every=50",
                  "--quiet").exit_code == 0
    figure, axes = plt.subplots()
    with RunFile(path) as run_file:
        assert run_file.n_samples == 2
        _invariants(run_file, axes)
    for line in axes.get_lines():
        shown = np.isfinite(line.get_ydata()).sum()
        label = line.get_label()
        if shown == 0:   # exactly kept at both samples: said in the legend
            assert label.endswith("(= I(t0) at every sample)"), label
        else:
            assert shown >= 2 or line.get_marker() not in (None, "None", ""), label
    plt.close(figure)


@pytest.mark.parametrize("adaptive", [False, True])
def test_plots_of_long_runs_keep_each_windows_peak(tmp_path, monkeypatch, adaptive):
    """Curves longer than MAX_POINTS were every n-th row: a user trial's alpha spike of 0.32 drew as
    0.058. Each window of n rows now gives its largest |value| at its own time (alpha, iterations and
    the invariant errors; adaptive runs' step times are stored)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from elimfast.io.hdf5 import RunFile
    from elimfast_cli import plots

    path = tmp_path / "run.h5"
    extra = ["--set", "integration.rtol=1e-10", "--set", "integration.t_end=30"] if adaptive else []
    assert invoke("run", KEPLER, "-o", path, "--set", "output.every=1", *SHORT, *extra, "--quiet").exit_code == 0
    monkeypatch.setattr(plots, "MAX_POINTS", 7)    # windows of several rows, and a partial last one
    monkeypatch.setattr(plots, "PEAK_BLOCK_WINDOWS", 3)   # blocks of several windows
    with RunFile(path) as run_file:
        alpha, iterations = run_file.multipliers(1), run_file.iterations(1)
        times = run_file.step_times(1) if adaptive else run_file.attrs["h"] * (np.arange(run_file.steps_done) + 1)
        samples_t = run_file.t(1)
        errors = {name: np.abs(run_file.invariant(name, 1) - run_file.initial_invariants()[name])
                  for name in run_file.invariant_names}
        assert plots._stride(run_file.steps_done) > 1 and run_file.steps_done % plots._stride(run_file.steps_done)
        drawn, labels = {}, {}
        for kind, draw in (("alpha", plots._multipliers), ("iterations", plots._iterations),
                           ("invariants", plots._invariants)):
            figure, axes = plt.subplots()
            draw(run_file, axes)
            drawn[kind] = [(line.get_xdata(), line.get_ydata()) for line in axes.get_lines()]
            labels[kind] = axes.get_ylabel()
            plt.close(figure)
        # the axes say that their points are window peaks (the last note: nothing said so)
        steps, samples = plots._stride(run_file.steps_done), plots._stride(run_file.n_samples)
        assert labels["alpha"].endswith(f"\n(largest of each {steps} steps, by magnitude)")
        assert labels["iterations"].endswith(f"\n(largest of each {steps} steps)")
        assert labels["invariants"].endswith(f"\n(largest of each {samples} samples)")
    for column, (t, values) in enumerate(drawn["alpha"]):
        largest = int(np.argmax(np.abs(alpha[:, column])))
        assert np.abs(values).max() == abs(alpha[largest, column]) and times[largest] in t
        assert len(t) < len(times)
    t, values = drawn["iterations"][0]
    assert values.max() == iterations.max() and times[int(np.argmax(iterations))] in t
    for (t, values), error in zip(drawn["invariants"], errors.values()):
        assert np.nanmax(values) == error.max() and samples_t[int(np.argmax(error))] in t


def test_iterations_plot_names_the_solver_that_iterated(kepler_file, tmp_path):
    """A user trial's finding: the axis read 'fixed-point iterations per step' for the default
    simplified Newton solver too."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from elimfast.io.hdf5 import RunFile
    from elimfast_cli.plots import draw

    fixed = tmp_path / "fixed.h5"
    assert invoke("run", KEPLER, "-o", fixed, "--set", "integration.t_end=5", "--set", "solver.method=fixed_point",
                  "--quiet").exit_code == 0
    labels = {}
    for name, path in (("newton", kepler_file), ("fixed", fixed)):
        with RunFile(path) as run_file:
            figure = draw(run_file, "iterations")
            labels[name] = figure.axes[0].get_ylabel()
            plt.close(figure)
    assert invoke("run", KEPLER, "-o", fixed, "--resume", "--set", "integration.t_end=10", "--set",
                  "solver.method=newton", "--quiet").exit_code == 0
    with RunFile(fixed) as run_file:
        figure = draw(run_file, "iterations")
        labels["changed"] = figure.axes[0].get_ylabel()
        plt.close(figure)
    assert labels == {"newton": "simplified Newton iterations per step", "fixed": "fixed-point iterations per step",
                      "changed": "solver iterations per step"}
    # max_iter is stored resolved: a resume that changes the solver gets the new solver's default where
    # the stored one was the old default (a user trial: fixed_point kept Newton's 30 on ELIM), and keeps
    # a max_iter that was set
    import yaml
    for set_first, expected in (([], 30), (["--set", "solver.max_iter=40"], 40)):
        path = tmp_path / f"max_iter_{expected}.h5"
        assert invoke("run", KEPLER, "-o", path, "--set", "integration.t_end=5", "--set",
                      "solver.method=fixed_point", *set_first, "--quiet").exit_code == 0
        assert invoke("run", KEPLER, "-o", path, "--resume", "--set", "integration.t_end=10", "--set",
                      "solver.method=newton", "--quiet").exit_code == 0
        with h5py.File(path, "r") as f:
            assert yaml.safe_load(f.attrs["config"])["solver"]["max_iter"] == expected


def test_orbit_plot_of_the_solar_system_draws_every_body_in_the_plane(tmp_path):
    """A user trial's finding: the built-in nbody names its coordinates sun_x, sun_y, ..., which the
    orbit plot did not take for bodies: it drew the first 12 of 18 coordinates against t, Neptune
    and Pluto left out without a word."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from elimfast.io.hdf5 import RunFile
    from elimfast_cli.plots import draw

    path = tmp_path / "nbody.h5"
    assert invoke("run", ROOT / "configs" / "nbody.yaml", "-o", path, "--set", "integration.t_end=2000",
                  "--quiet").exit_code == 0
    with RunFile(path) as run_file:
        figure = draw(run_file, "orbit")
    axes = figure.axes[0]
    assert [line.get_label() for line in axes.get_lines()] == ["sun", "jupiter", "saturn", "uranus", "neptune", "pluto"]
    assert (axes.get_xlabel(), axes.get_ylabel()) == ("x", "y")
    plt.close(figure)


def test_plot_default_name(kepler_file):
    result = invoke("plot", kepler_file)
    expected = kepler_file.with_name("kepler_invariants.png")
    assert result.exit_code == 0 and result.stdout.strip() == str(expected) and expected.stat().st_size > 1000


def test_plot_creates_missing_directories_as_run_does(kepler_file, tmp_path):
    """run -o some/missing/dir/OUT.h5 makes the directories; plot -o some/missing/dir/FIG.png did not."""
    figure = tmp_path / "some" / "missing" / "dir" / "fig.png"
    result = invoke("plot", kepler_file, "-o", figure)
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == str(figure) and figure.stat().st_size > 1000


def test_plot_into_a_directory_that_cannot_be_made_is_one_line_naming_the_path(kepler_file, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    figure = a_file / "dir" / "fig.png"
    result = invoke("plot", kepler_file, "-o", figure)
    assert result.exit_code == 2 and result.stdout == ""
    assert result.stderr == f"error: {figure}: {a_file} is a file, not a directory; choose another output path\n"


def test_check_prints_the_resolved_config_as_yaml():
    result = invoke("check", KEPLER, "--set", "method.s=4")
    assert result.exit_code == 0, result.output
    spec = load_run(KEPLER, overrides=["method.s=4"])
    assert yaml.safe_load(result.stdout) == spec.resolved
    assert "# invariant check" in result.stdout
    for name in ("angular_momentum", "lrl_x", "lrl_y"):
        assert any(line.startswith(f"#   {name}") and line.endswith("ok") for line in result.stdout.splitlines())
    assert "EHBVM(12,4) imposing angular_momentum, lrl_y, 10000 steps" in result.stdout


@pytest.mark.parametrize("config,overrides,line", [
    ("fpu_beta.yaml", [], "# H: a polynomial of degree 4, which the k = 6 nodes of HBVM(6,3) integrate exactly "
                          "(degree <= 2k/s = 4): kept to round-off"),
    ("fpu_beta.yaml", ["method.k=5"], "# H: a polynomial of degree 4 > 2k/s = 3.33: HBVM(5,3) keeps it up to the "
                                      "quadrature error of its k = 5 nodes, O(h^11) per step"),
    ("kepler.yaml", [], "# H: not a polynomial: EHBVM(12,3) keeps it up to the quadrature error of its k = 12 nodes"),
    ("kepler_python.yaml", [], "# H: not known to be a polynomial (a python: problem): EHBVM(12,3) keeps it"),
    # LIM imposes H through its r nodes (a user trial: 'k = 6 nodes' for LIM(24,6,3), which keeps H to 3e-14)
    ("kepler.yaml", ["method=LIM(24,6,3)"], "# H: not a polynomial: LIM(24,6,3) keeps it up to the quadrature "
                                            "error of its r = 24 nodes"),
    ("central_quartic.yaml", ["method=LIM(2,4,2)"], "# H: a polynomial of degree 4 > 2r/s = 2: LIM(2,4,2) keeps it "
                                                    "up to the quadrature error of its r = 2 nodes"),
    ("kepler.yaml", ["method=GHBVM(12,3)"], "# H: not a polynomial: GHBVM(12,3) keeps it up to the quadrature "
                                            "error of its k = 12 nodes"),
])
@pytest.mark.usefixtures("allow_python")
def test_check_says_whether_the_method_keeps_H_exactly(config, overrides, line):
    result = invoke("check", ROOT / "configs" / config, *[item for o in overrides for item in ("--set", o)])
    assert result.exit_code == 0, result.output
    assert any(text.startswith(line) for text in result.stdout.splitlines()), result.stdout


def test_check_describes_an_adaptive_run_by_its_step_control(tmp_path):
    result = invoke("check", ROOT / "configs" / "kepler_adaptive.yaml")
    assert result.exit_code == 0, result.output
    line = result.stdout.splitlines()[1]
    assert line == ("# problem kepler, EHBVM(8,4) imposing angular_momentum, lrl_y, adaptive (error: rtol 1e-13, "
                    f"atol 1e-13; docs/adaptive.md) from t = 0.0 to {200 * np.pi!r}"), line
    first = invoke("check", ROOT / "configs" / "kepler_adaptive.yaml", "--set", "integration.h=0.01")
    assert first.stdout.splitlines()[1].endswith(", first step h = 0.01")
    # h_max decides the steps as rtol does: check and inspect name it (inspect left it out)
    capped = invoke("check", ROOT / "configs" / "kepler_adaptive.yaml", "--set", "integration.h_max=0.1")
    assert "adaptive (error: rtol 1e-13, atol 1e-13, h_max 0.1; docs/adaptive.md)" in capped.stdout
    out = tmp_path / "capped.h5"
    assert invoke("run", ROOT / "configs" / "kepler_adaptive.yaml", "-o", out, "--set", "integration.h_max=0.1",
                  "--set", "integration.t_end=4*pi", "--quiet").exit_code == 0
    assert "adaptive (error: rtol 1e-13, atol 1e-13, h_max 0.1; docs/adaptive.md)" in invoke("inspect", out).stdout


def test_a_loose_adaptive_run_is_told_which_invariants_its_steps_lose(tmp_path):
    """A tester's run at rtol 1e-6 lost H to 2e-9 and the imposed A_y to 2e-10 (relative): the
    end-of-run note and inspect must name both and say what bounds the steps (not h)."""
    out = tmp_path / "loose.h5"
    result = invoke("run", ROOT / "configs" / "kepler_adaptive.yaml", "-o", str(out), "--set", "integration.rtol=1e-6",
                    "--set", "integration.t_end=4*pi", "--set", "events={}")
    assert result.exit_code == 0, result.output
    note = [line for line in result.output.splitlines() if "above round-off" in line]
    assert len(note) == 1 and "H " in note[0] and "lrl_y" in note[0] and "rtol" in note[0], result.output
    inspect = invoke("inspect", str(out))
    assert any(line.startswith("note") and "lrl_y" in line and "r = 8" in line for line in inspect.stdout.splitlines())


def test_problems_lists_the_library():
    result = invoke("problems")
    assert result.exit_code == 0, result.output
    for name in PROBLEMS:
        assert f"\n{name}: " in "\n" + result.stdout
    assert "invariants:  H, angular_momentum, lrl_x, lrl_y" in result.stdout
    assert "parameters:  eccentricity = 0.6" in result.stdout


def test_methods_lists_the_families():
    result = invoke("methods")
    assert result.exit_code == 0
    for signature in ("gauss(s)", "hbvm(k, s)", "elim(r, k, s)", "ehbvm(k, s)", "lim(r, k, s)", "ghbvm(k, s)"):
        assert signature in result.stdout


def parse_tableau(text):
    rows = [line for line in text.splitlines() if not line.startswith("#") and "-+-" not in line]
    c, A = [], []
    for line in rows[:-1]:
        left, right = line.split("|")
        c.append(float(left))
        A.append([float(x) for x in right.split()])
    b = [float(x) for x in rows[-1].split("|")[1].split()]
    return np.array(A), np.array(b), np.array(c)


@pytest.mark.parametrize("args, method, eta", [
    (["gauss", "--s", "3"], methods.gauss(3), None),
    (["hbvm", "--k", "5", "--s", "3"], methods.hbvm(5, 3), None),
    (["ehbvm", "--k", "4", "--s", "3", "--eta", "0.99", "--eta", "1.01"], methods.ehbvm(4, 3), [0.99, 1.01]),
    (["elim", "--r", "5", "--k", "4", "--s", "3", "--eta", "1,0.9,1.1"], methods.elim(5, 4, 3), [1, 0.9, 1.1]),
    (["HBVM(5,3)"], methods.hbvm(5, 3), None),   # the paper's notation
])
def test_tableau_is_printed_exactly(args, method, eta):
    result = invoke("tableau", *args)
    assert result.exit_code == 0, result.output
    A, b, c = parse_tableau(result.stdout)
    A_ref, b_ref, c_ref = method.butcher(eta)
    # bit for bit: repr round-trips every double
    assert A.tobytes() == np.asarray(A_ref, dtype=float).tobytes()
    assert b.tobytes() == b_ref.tobytes() and c.tobytes() == c_ref.tobytes()
    assert method.name in result.stdout


def test_tableau_in_the_papers_notation_takes_no_parameter_options():
    result = invoke("tableau", "HBVM(4,2)", "--k", "3")
    assert result.exit_code == 2 and "--k does not apply: HBVM(4,2) gives the parameters already" in result.output
    result = invoke("tableau", "HBVM(4)")
    assert result.exit_code == 2 and "NAME 'HBVM(4)': hbvm(k, s) takes 2 whole numbers" in result.output


def test_tableau_with_several_values_after_one_eta_says_how_to_give_them():
    result = invoke("tableau", "elim", "--r", "3", "--k", "3", "--s", "3", "--eta", "1", "1", "0.99")
    assert result.exit_code == 2 and result.output.count("\n") == 1, result.output
    assert "--eta 1 --eta 1 --eta 0.99" in result.output and "--eta 1,1,0.99" in result.output
    both = [invoke("tableau", "elim", "--r", "3", "--k", "3", "--s", "3", *form) for form in
            (["--eta", "1", "--eta", "1", "--eta", "0.99"], ["--eta", "1,1,0.99"])]
    assert both[0].exit_code == 0 and both[0].stdout == both[1].stdout and "eta = 1.0, 1.0, 0.99" in both[0].stdout
    # the order 2s is the method's, whose eta change with each step; fixed eta other than 1 give a lower one
    assert "order 6 only as the method" in both[0].stdout
    assert "stages, order 6; eta = 1.0, 1.0, 1.0" in invoke("tableau", "elim", "--r", "3", "--k", "3", "--s", "3",
                                                              "--eta", "1,1,1").stdout
    assert invoke("tableau", "GAUSS(1)").stdout.startswith("# GAUSS(1): Butcher tableau, 1 stage, ")   # not "1 stages"


def test_version():
    result = invoke("--version")
    import elimfast
    assert result.exit_code == 0 and result.stdout.startswith(f"elimfast {elimfast.__version__} (numba ")


@pytest.mark.parametrize("command", [[], ["run"], ["check"], ["inspect"], ["plot"], ["problems"], ["methods"],
                                     ["tableau"], ["cache"], ["cache", "info"], ["cache", "clear"]])
def test_every_command_has_help_with_an_example(command):
    result = invoke(*command, "--help")
    assert result.exit_code == 0
    assert "Example" in result.stdout and "elimfast " in result.stdout.split("Example", 1)[1]


def test_no_command_prints_help():
    result = invoke()
    assert result.exit_code == 0 and "Commands:" in result.stdout


def test_cache_info_and_clear(tmp_path):
    env = {"ELIMFAST_CACHE_DIR": str(tmp_path / "cache")}
    problems_dir = tmp_path / "cache" / "problems"
    problems_dir.mkdir(parents=True)
    (problems_dir / "p_0123.py").write_text("# generated\n")
    (problems_dir / "k_4567.py").write_text("# a per-problem kernel\n")   # counted apart (a user trial)
    info = invoke("cache", "info", env=env)
    assert info.exit_code == 0 and str(tmp_path / "cache") in info.stdout
    assert "(1 generated problems, 1 per-problem kernels, " in info.stdout, info.stdout
    # each kernel folder with its own files (a user trial: the one folder named did not exist, and the
    # files counted beside it were in the package's own __pycache__)
    from unittest import mock

    from elimfast.cache import kernel_cache_files
    with mock.patch.dict(os.environ, env):
        roots, files = kernel_cache_files()
    if "NUMBA_CACHE_DIR" not in os.environ:
        assert len(roots) == 2 and roots[0].parent.name == "__pycache__"
    for root in roots:
        mine = [f for f in files if root in f.parents]
        assert f"{root}  ({len(mine)} Numba files, " in info.stdout, info.stdout
    assert sum(info.stdout.count(f"{root}  (") for root in roots) == len(roots)
    cleared = invoke("cache", "clear", env=env)
    assert cleared.exit_code == 0 and "removed 2 files" in cleared.stdout
    assert not (problems_dir / "p_0123.py").exists() and not (problems_dir / "k_4567.py").exists()


def test_a_real_process_runs_inspects_and_plots(tmp_path):
    """The installed console script, as users call it (stderr is a pipe: plain progress lines)."""
    out = tmp_path / "out" / "k.h5"      # the directory is created
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    run = subprocess.run([ELIMFAST, "run", KEPLER, "-o", str(out), *SHORT], capture_output=True, text=True,
                         env=env, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout == "" and "complete, 200 steps" in run.stderr and "Traceback" not in run.stderr
    chained = subprocess.run(f"{ELIMFAST} inspect {out} && {ELIMFAST} plot {out} --kind orbit -o {tmp_path / 'o.png'}",
                             shell=True, capture_output=True, text=True, timeout=300)
    assert chained.returncode == 0, chained.stderr
    assert "status       complete" in chained.stdout and (tmp_path / "o.png").stat().st_size > 1000


def test_a_terminal_gets_a_progress_bar(tmp_path):
    """stderr is a terminal (a pty of 100 columns): tqdm's bar with steps/s and ETA."""
    import fcntl
    import pty
    import struct
    import termios

    pid, fd = pty.fork()
    if pid == 0:   # the child: a terminal of 40 x 100
        fcntl.ioctl(0, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 100, 0, 0))
        os.execv(ELIMFAST, [ELIMFAST, "run", KEPLER, "-o", str(tmp_path / "tty.h5"), *SHORT])
    output = b""
    while True:
        try:
            data = os.read(fd, 4096)
        except OSError:
            break
        if not data:
            break
        output += data
    _, status = os.waitpid(pid, 0)
    text = output.decode(errors="replace")
    assert os.waitstatus_to_exitcode(status) == 0, text
    assert "EHBVM(12,3) kepler: 100%|" in text and "200/200" in text and "step/s" in text and "<00:00" in text


def test_cache_clear_kernels_removes_only_elimfasts_numba_files(tmp_path):
    from numba.core.caching import UserProvidedCacheLocator

    import elimfast.kernels.stepper as stepper
    from elimfast.kernels._cache import cache_key
    numba_dir = tmp_path / "numba"
    # elimfast's own folder in NUMBA_CACHE_DIR, keyed by its kernels' sources (kernels/_cache.py)
    ours = (numba_dir / "elimfast-kernels" / cache_key()
            / UserProvidedCacheLocator.get_suitable_cache_subpath(stepper.__file__))
    ours.mkdir(parents=True)
    (ours / "stepper.time_loop-1.py311.nbi").write_bytes(b"")
    (ours / "stepper.time_loop-1.py311.1.nbc").write_bytes(b"")
    other = numba_dir / "someone_else_0123"
    other.mkdir()
    (other / "f-1.py311.nbi").write_bytes(b"")
    env = {"NUMBA_CACHE_DIR": str(numba_dir), "ELIMFAST_CACHE_DIR": str(tmp_path / "cache")}
    info = invoke("cache", "info", env=env)
    assert info.exit_code == 0 and "(2 Numba files" in info.stdout
    cleared = invoke("cache", "clear", "--kernels", env=env)
    assert cleared.exit_code == 0 and "removed 2 Numba files" in cleared.stdout
    assert not ours.exists() and (other / "f-1.py311.nbi").exists()


def test_a_slow_run_reports_seconds_per_step_not_zero_steps_per_second():
    """A user trial: fpu_beta with 10^4 masses, 10 steps in 66.7 s, read '0 steps/s'."""
    from elimfast_cli.report import _rate
    assert _rate(10, 66.7) == "6.67 s/step"
    assert _rate(200, 0.1) == "2,000 steps/s"


def test_a_run_whose_steps_mostly_go_unimposed_hears_it_during_the_run(tmp_path):
    """A user trial: EHBVM(12,4) imposing the solar system's three angular momenta took every
    step without imposing them, at a fifth of GHBVM's speed, and heard so only at the end. Once
    200 steps are taken and most went so, a note says it during the run, once; a run that
    imposes them says nothing of it."""
    nbody = ROOT / "configs" / "nbody.yaml"
    result = invoke("run", nbody, "-o", tmp_path / "e.h5", "--set", "method=EHBVM(12,4)", "--set",
                    "conserve=[angular_momentum_x, angular_momentum_y, angular_momentum_z]", "--set",
                    "integration.t_end=4e4", "--set", "solver.lim_metric=null")
    assert result.exit_code == 0, result.output
    lines = result.stderr.splitlines()
    during = [i for i, line in enumerate(lines) if "steps taken so far went without imposing the invariants" in line]
    end = [i for i, line in enumerate(lines) if line.startswith(f"{tmp_path / 'e.h5'}: complete")]
    assert len(during) == 1 and during[0] < end[0], result.stderr
    plain = invoke("run", nbody, "-o", tmp_path / "g.h5", "--set", "integration.t_end=4e4")
    assert plain.exit_code == 0 and "went without imposing" not in plain.stderr
    # --quiet prints errors only: not this note either (a user trial)
    quiet = invoke("run", nbody, "-o", tmp_path / "q.h5", "--set", "method=EHBVM(12,4)", "--set",
                   "conserve=[angular_momentum_x, angular_momentum_y, angular_momentum_z]", "--set",
                   "integration.t_end=4e4", "--set", "solver.lim_metric=null", "--quiet")
    assert quiet.exit_code == 0 and quiet.stderr == "" and quiet.stdout == "", quiet.output
