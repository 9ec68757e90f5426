"""Interrupt a real ``elimfast run`` (SIGINT, SIGTERM, SIGKILL) mid-way, resume it, and
compare with an uninterrupted run: the final state and every stored row must be equal
bit for bit. A SIGKILLed file must open in h5py with every flushed chunk readable.
"""
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from elimfast.integrate import Integration
from elimfast.config import load_run
from elimfast_cli.main import cli
from runfiles import steps_on_disk

ROOT = Path(__file__).resolve().parents[1]
KEPLER = str(ROOT / "configs" / "kepler.yaml")
ELIMFAST = str(Path(sys.executable).with_name("elimfast"))
# EHBVM(12,3) steps for a few chunks of ~0.5 s each, so that a signal sent once the first chunk is on
# disk stops the run before its end: 150,000 steps took 2 s when this was written and 0.87 s on a later
# machine, where the signal sometimes came after the last chunk had started (exit 0, not 130).
OVERRIDES = ["integration.t_end=45000", "output.every=50"]
SET = [arg for item in OVERRIDES for arg in ("--set", item)]
STEPS_BEFORE_SIGNAL = 1000    # the first chunk (64 steps) and the next are on disk


@pytest.fixture(scope="module")
def reference():
    """The uninterrupted run, in this process (same compiled kernel as the subprocesses)."""
    spec = load_run(KEPLER, overrides=OVERRIDES)
    run = Integration.from_spec(spec)
    chunks = [run.initial_chunk(), run.advance(spec.n_steps)]
    return {"y_final": run.y.copy(), "clock": run.clock.copy(), "n_steps": spec.n_steps,
            "t": np.concatenate([c.t for c in chunks]), "y": np.concatenate([c.y for c in chunks]),
            "alpha": chunks[1].multipliers, "iterations": chunks[1].iterations}


def start_and_signal(path: Path, sig: int):
    process = subprocess.Popen([ELIMFAST, "run", KEPLER, "-o", str(path), *SET], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while steps_on_disk(path) < STEPS_BEFORE_SIGNAL:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "the run did not start in time"
        time.sleep(0.02)
    process.send_signal(sig)
    stdout, stderr = process.communicate(timeout=120)
    return process.returncode, stdout, stderr


def resume(path: Path):
    return subprocess.run([ELIMFAST, "run", KEPLER, "-o", str(path), *SET, "--resume"], capture_output=True,
                          text=True, timeout=300)


def assert_equal_to_reference(path: Path, reference):
    with h5py.File(path, "r") as f:      # a plain open: the resumed run closed the file properly
        assert f.attrs["status"] == "complete" and f.attrs["steps_done"] == reference["n_steps"]
        np.testing.assert_array_equal(f["state/y"][:], reference["y_final"])
        np.testing.assert_array_equal(f["state/clock"][:], reference["clock"])
        np.testing.assert_array_equal(f["t"][:], reference["t"])
        np.testing.assert_array_equal(f["y"][:], reference["y"])
        np.testing.assert_array_equal(f["steps/alpha"][:], reference["alpha"])
        np.testing.assert_array_equal(f["steps/iterations"][:], reference["iterations"])


# SIGHUP (the terminal closed): a user trial found it ended the run like kill -9, the file left "killed"
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_signal_stops_at_a_chunk_boundary_and_resume_is_exact(tmp_path, reference, sig):
    path = tmp_path / "run.h5"
    code, stdout, stderr = start_and_signal(path, sig)
    assert code == 130, stderr
    name = signal.Signals(sig).name
    assert stderr.strip().splitlines()[-1].startswith(f"interrupted by {name} at step ")
    assert "--resume" in stderr and "Traceback" not in stderr
    with h5py.File(path, "r") as f:      # closed cleanly: plain h5py opens it
        assert f.attrs["status"] == "interrupted"
        done = int(f.attrs["steps_done"])
        assert STEPS_BEFORE_SIGNAL <= done < reference["n_steps"]
        assert f["steps/iterations"].shape == (done,)
        np.testing.assert_array_equal(f["steps/alpha"][:], reference["alpha"][:done])

    resumed = resume(path)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resumed at step {done}" in resumed.stderr
    assert_equal_to_reference(path, reference)


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["SIGINT", "SIGTERM", "SIGHUP"])
def test_a_signal_while_a_run_starts_says_the_file_is_as_it_was(tmp_path, sig):
    """A user trial signalled `elimfast run --resume` during its start-up (imports, config, kernels):
    SIGTERM ended it silently with 143, Ctrl-C printed a blank line and 'interrupted'. The signal
    comes here from inside the start-up (announce_compilation), as the real one did."""
    path = tmp_path / "run.h5"
    assert CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5",
                                    "--quiet"]).exit_code == 0
    before = path.read_bytes()
    script = ("import os, signal, sys\n"
              "import elimfast_cli.main as main\n"
              f"main.announce_compilation = lambda: os.kill(os.getpid(), {int(sig)})\n"
              f"sys.argv = ['elimfast', 'run', {KEPLER!r}, '-o', {str(path)!r}, '--resume', '-q']\n"
              "main.cli()\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 130, done.stderr
    assert done.stderr == (f"error: interrupted while starting, before any step: {path} is as it was; run the same "
                           "command again to resume it\n")
    assert path.read_bytes() == before


def test_kill_9_leaves_a_readable_file_and_resume_is_exact(tmp_path, reference):
    path = tmp_path / "run.h5"
    code, _, _ = start_and_signal(path, signal.SIGKILL)
    assert code == -signal.SIGKILL
    # Every flushed chunk is readable (in SWMR mode: the killed writer's flags are still set).
    with h5py.File(path, "r", swmr=True) as f:
        done = int(f["state/steps_done"][()])
        samples = int(f["state/n_samples"][()])
        assert STEPS_BEFORE_SIGNAL <= done < reference["n_steps"] and f.attrs["status"] == "running"
        np.testing.assert_array_equal(f["y"][:samples], reference["y"][:samples])
        np.testing.assert_array_equal(f["steps/alpha"][:done], reference["alpha"][:done])
    inspect = CliRunner().invoke(cli, ["inspect", str(path)])
    assert inspect.exit_code == 0 and "status       killed" in inspect.stdout
    assert f"steps done   {done} / {reference['n_steps']}" in inspect.stdout

    resumed = resume(path)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resumed at step {done}" in resumed.stderr
    assert_equal_to_reference(path, reference)


def test_resume_of_a_complete_run_changes_nothing(tmp_path):
    path = tmp_path / "done.h5"
    args = ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5", "--quiet"]
    assert CliRunner().invoke(cli, args).exit_code == 0
    before = path.read_bytes()
    result = CliRunner().invoke(cli, [*args[:-1], "--resume"])
    assert result.exit_code == 0 and "already complete; nothing to resume" in result.stderr
    assert "--resume --set integration.t_end=LATER" in result.stderr
    assert path.read_bytes() == before


def test_a_run_continued_to_a_later_end_is_the_run_to_that_end(tmp_path):
    """--resume --set integration.t_end=LATER on a complete fixed-step run: the file is then,
    row for row and bit for bit, that of a run to the later end (output.every = 7 does not
    divide the first run's 50 steps: its extra last sample is dropped, as a failed run's is),
    and the root attributes and extension_history say so."""
    extended, whole = tmp_path / "extended.h5", tmp_path / "whole.h5"
    base = ["run", KEPLER, "--set", "output.every=7", "--quiet"]
    assert CliRunner().invoke(cli, [*base, "-o", str(extended), "--set", "integration.t_end=5"]).exit_code == 0
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(extended), "--resume", "--set", "output.every=7",
                                      "--set", "integration.t_end=12"])
    assert result.exit_code == 0, result.stderr
    assert "resumed at step 50, continued to t_end = 12 (its t_end was 5)" in result.stderr
    assert CliRunner().invoke(cli, [*base, "-o", str(whole), "--set", "integration.t_end=12"]).exit_code == 0
    with h5py.File(extended, "r") as a, h5py.File(whole, "r") as b:
        assert a.attrs["status"] == "complete" and a.attrs["t_end"] == 12.0 and a.attrs["n_steps"] == 120
        assert list(a.attrs["extension_history"]) == ["from step 50: t_end 12.0 (before: 5.0)"]
        for name in ("t", "y", "invariants/H", "invariants/angular_momentum", "steps/alpha", "steps/iterations",
                     "state/y", "state/y_comp", "state/clock", "state/coef"):
            np.testing.assert_array_equal(a[name][:], b[name][:], err_msg=name)
    # inspect says how the run was continued
    report = CliRunner().invoke(cli, ["inspect", str(extended)])
    assert "resumed      continued from step 50: t_end 12.0 (before: 5.0)\n" in report.stdout


def test_a_run_is_never_continued_to_an_earlier_end(tmp_path):
    path = tmp_path / "done.h5"
    assert CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5",
                                    "--quiet"]).exit_code == 0
    before = path.read_bytes()
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--resume", "--set", "integration.t_end=3"])
    assert result.exit_code == 2
    assert "integration.t_end = 3 is before the end of the stored run, 5: --resume continues a run to a later" \
        in result.stderr and "Traceback" not in result.stderr
    assert path.read_bytes() == before


@pytest.mark.parametrize("change", ["integration.h=0.05", "integration.t0=1", "method.s=4"])
def test_resume_refuses_a_change_of_the_trajectory_by_name(tmp_path, change):
    """The stored config holds h, t_end and n_steps: a --set of h or t_end contradicted n_steps
    and was reported as that contradiction, not as what --resume allows."""
    path = tmp_path / "part.h5"
    args = ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5", "--quiet"]
    assert CliRunner().invoke(cli, args).exit_code == 0
    result = CliRunner().invoke(cli, [*args[:-1], "--resume", "--set", change])
    assert result.exit_code == 2
    assert result.stderr.endswith(f"only solver.* may change on --resume; {change.split('=')[0]} (value from --set "
                                  f"{change}) changes the trajectory: start a new run (-o NEW.h5), or replace this "
                                  "one with --overwrite\n"), result.stderr
    # a value repeated from the first run, and a solver setting, are no change
    repeated = CliRunner().invoke(cli, [*args[:-1], "--resume", "--set", "solver.max_halvings=6"])
    assert repeated.exit_code == 0, repeated.stderr


def test_resume_with_an_invalid_value_reports_the_value_not_the_resume_rule(tmp_path):
    """--resume --set events.p.direction=5 said 'only solver.* may change on --resume', as if 5
    were a valid change; the value is invalid whatever the resume, and its own message says so.
    (integration.h still gets the resume's rule: it contradicts the stored n_steps.)"""
    path = tmp_path / "events.h5"
    event = 'events={p: {expression: "q1*p1 + q2*p2", direction: 1}}'
    assert CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5", "--set", event,
                                    "--quiet"]).exit_code == 0
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--resume", "--set", event,
                                      "--set", "events.p.direction=5"])
    # one line of error; a cold Numba cache (no `make` warm-up) adds its one 'compiling ...' line
    lines = [line for line in result.stderr.splitlines() if not line.startswith("compiling ")]
    assert result.exit_code == 2 and len(lines) == 1, result.stderr
    assert "events.p.direction: must be 1" in result.stderr and "may change on --resume" not in result.stderr
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--resume", "--set", event, "--set",
                                      "integration.h=0.05"])
    assert result.exit_code == 2 and "only solver.* may change on --resume; integration.h" in result.stderr


def test_resume_allows_problem_check_to_change(tmp_path):
    """problem.check only decides whether grad L . J grad H = 0 is checked when the problem
    loads; a --resume that turned it off was refused as 'changes the trajectory'."""
    path, whole = tmp_path / "part.h5", tmp_path / "whole.h5"
    args = ["run", KEPLER, "--set", "integration.t_end=5", "--quiet"]
    assert CliRunner().invoke(cli, [*args, "-o", str(path)]).exit_code == 0
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--resume", "--set", "integration.t_end=8",
                                      "--set", "problem.check=false"])
    assert result.exit_code == 0, result.stderr
    assert CliRunner().invoke(cli, ["run", KEPLER, "-o", str(whole), "--set", "integration.t_end=8",
                                    "--quiet"]).exit_code == 0
    with h5py.File(path, "r") as a, h5py.File(whole, "r") as b:
        np.testing.assert_array_equal(a["y"][:], b["y"][:])


def test_resume_says_what_a_changed_event_would_do(tmp_path):
    """--resume with a changed event said it "changes the trajectory", which only a terminal
    event does (it ends the run). One that is not terminal leaves every step as it is (checked
    here: a fresh run with the changed event has the same states bit for bit); what it would
    spoil is the file's events, found with the old definition. output.every changes the samples."""
    event = 'events={peri: {expression: "q1*p1 + q2*p2", direction: 1}}'
    path = tmp_path / "events.h5"
    args = ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=8", "--set", event, "--quiet"]
    assert CliRunner().invoke(cli, args).exit_code == 0
    refusal = f"error: {path}: was written from a different config; only solver.* may change on --resume; "
    advice = ": start a new run (-o NEW.h5), or replace this one with --overwrite\n"
    for change in ("events.peri.direction=-1", "events.peri.expression=q2",
                   'events.apo={expression: "q1*p1 + q2*p2", direction: -1}'):
        result = CliRunner().invoke(cli, [*args[:-1], "--resume", "--set", change])
        assert result.exit_code == 2
        assert result.stderr.endswith(refusal + f"{change.split('=')[0]} (value from --set {change}) leaves the "
                                 "trajectory as it is (an event that is not terminal only records where it occurs), "
                                 "but the events stored for the steps already done were found with the stored "
                                 "definition, so the file would hold events of two definitions" + advice), result.stderr
    other = tmp_path / "other.h5"
    assert CliRunner().invoke(cli, [*args[:2], "-o", str(other), *args[4:-1], "--quiet", "--set",
                                    "events.peri.direction=-1"]).exit_code == 0
    with h5py.File(path, "r") as a, h5py.File(other, "r") as b:
        np.testing.assert_array_equal(a["y"][:], b["y"][:])
        # the events differ: the pericentre at t = 2 pi, the apocentre at pi
        assert abs(a["events/peri/t"][0] - 2 * np.pi) < 1e-5 and abs(b["events/peri/t"][0] - np.pi) < 1e-5
    # a terminal event, or making one terminal, changes where the run ends
    for change in ("events.peri.terminal=true", 'events.apo={expression: "q1*p1 + q2*p2", terminal: true}'):
        result = CliRunner().invoke(cli, [*args[:-1], "--resume", "--set", change])
        assert result.stderr.endswith(refusal + f"{change.split('=')[0]} (value from --set {change}) changes where the "
                                 "run ends (a terminal event stops it), and so the trajectory" + advice), result.stderr
    result = CliRunner().invoke(cli, [*args[:-1], "--resume", "--set", "output.every=5"])
    assert result.stderr.endswith(refusal + "output.every (value from --set output.every=5) leaves the trajectory as "
                             "it is, but changes which states are sampled, so the file's samples would change their "
                             "spacing part-way" + advice)


@pytest.mark.usefixtures("allow_python")
def test_resume_with_an_edited_python_problem_file_says_so_and_records_it(tmp_path):
    """A user trial's finding: the config names a python: problem by its path only, so a file
    edited between a kill and --resume (H scaled by 1.01 in H, grad_H and hess_H) was continued
    silently with the new H, and the run file mixed two problems (H 'kept' to 1e-2, status
    complete, nothing said). Editing the file is also the documented way on after a function
    raised, so the resume goes on, says so, and records it (problem_file_sha256, _history)."""
    import hashlib
    source = (ROOT / "configs" / "kepler_problem.py").read_text()
    problem = tmp_path / "problem.py"
    problem.write_text(source)
    config = tmp_path / "run.yaml"
    config.write_text("problem: {python: problem.py}\nconserve: [angular_momentum]\n"
                      "method: {name: ehbvm, k: 12, s: 3}\nintegration: {h: 0.1, t_end: 5}\n")
    path = tmp_path / "run.h5"
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--quiet"]).exit_code == 0
    digest = hashlib.sha256(source.encode()).hexdigest()
    with h5py.File(path, "r") as f:
        assert f.attrs["problem_file_sha256"] == digest and "problem_file_history" not in f.attrs
    later = ["run", str(config), "-o", str(path), "--resume", "--set"]
    same = CliRunner().invoke(cli, [*later, "integration.t_end=7"])
    assert same.exit_code == 0 and "problem file" not in same.stderr, same.stderr
    edited = source.replace("import math", "import math  # edited")
    problem.write_text(edited)
    result = CliRunner().invoke(cli, [*later, "integration.t_end=10", "--quiet"])
    assert result.exit_code == 0, result.stderr
    # Said first, and under --quiet too (it used to be in the summary line only, which -q drops).
    assert result.stderr == (f"note: the problem file {problem.resolve()} has changed since the run began: the 70 "
                             "steps before used the old one (problem_file_history)\n")
    new = hashlib.sha256(edited.encode()).hexdigest()
    with h5py.File(path, "r") as f:
        assert f.attrs["problem_file_sha256"] == new
        assert list(f.attrs["problem_file_history"]) == [f"from step 70: sha256 {new[:16]} (before: {digest[:16]})"]
    report = CliRunner().invoke(cli, ["inspect", str(path)])
    assert f"resumed      problem file changed from step 70: sha256 {new[:16]} (before: {digest[:16]})\n" \
        in report.stdout


def test_resume_without_a_file_starts_a_new_run_and_says_so_even_when_quiet(tmp_path):
    """Resume-or-start serves job scripts; a mistyped path restarted a long run silently under
    -q (a user trial), so the line is printed first, also with --quiet. A missing CONFIG is an
    error as for a new run (it was accepted on --resume of an existing file)."""
    path = tmp_path / "new.h5"
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5", "--resume",
                                      "-q"])
    assert result.exit_code == 0
    assert result.stderr == f"note: no file {path} to resume: starting a new run\n"
    missing = CliRunner().invoke(cli, ["run", str(tmp_path / "nothere.yaml"), "-o", str(path), "--resume"])
    assert missing.exit_code == 2 and missing.stderr.count("\n") == 1 and "nothere.yaml" in missing.stderr


def test_resume_with_another_config_is_refused_naming_the_change(tmp_path):
    """A CONFIG describing another problem used to be ignored without a word (a user trial's
    finding), then noted while the stored run went on; CONFIG's differences now count as --set
    ones, so another problem is refused, naming the first key that differs and the file."""
    path = tmp_path / "kepler.h5"
    assert CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5",
                                    "--quiet"]).exit_code == 0
    pendulum = str(ROOT / "configs" / "pendulum.yaml")
    other = CliRunner().invoke(cli, ["run", pendulum, "-o", str(path), "--resume"])
    assert other.exit_code == 2 and other.stderr.count("\n") == 1, other.stderr
    assert "only solver.* may change on --resume; " in other.stderr
    # the problem first: a user trial was told "method.name ... changes the trajectory" (keys in alphabetical order)
    assert f"--resume; problem.builtin (in {pendulum}) changes the trajectory" in other.stderr
    same = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5", "--resume"])
    assert same.exit_code == 0 and "already complete" in same.stderr, same.stderr


ADAPTIVE = ("problem: {builtin: kepler, parameters: {eccentricity: 0.6}}\nconserve: [angular_momentum]\n"
            "method: {name: ehbvm, s: 3}\nintegration: {rtol: 1e-10, t_end: 3}\n")


def test_a_refused_resume_names_the_key_the_user_changed_and_where(tmp_path):
    """A user trial: --resume --set integration.rtol=1e-12 on an adaptive run was refused naming
    'integration.atol (in k09_times.yaml)': atol only changed because it defaults to rtol, and
    the file had not been edited. The refusal names the key the user changed, a --set one first
    with its --set, then one CONFIG writes out, before one that follows from them."""
    config, path = tmp_path / "adaptive.yaml", tmp_path / "a.h5"
    config.write_text(ADAPTIVE)
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--quiet"]).exit_code == 0
    before = path.read_bytes()
    refusal = f"error: {path}: was written from a different config; only solver.* may change on --resume; "
    advice = " changes the trajectory: start a new run (-o NEW.h5), or replace this one with --overwrite\n"
    by_set = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume", "--set",
                                      "integration.rtol=1e-9"])
    assert by_set.exit_code == 2 and by_set.stderr == (
        refusal + "integration.rtol (value from --set integration.rtol=1e-9)" + advice), by_set.stderr
    # an edit of CONFIG names the edited key, and the file; a --set beside it comes first
    config.write_text(ADAPTIVE.replace("rtol: 1e-10", "rtol: 1e-9"))
    edited = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert edited.exit_code == 2 and edited.stderr == refusal + f"integration.rtol (in {config})" + advice, \
        edited.stderr
    both = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume", "--set", "method.s=4"])
    assert both.exit_code == 2 and both.stderr == refusal + "method.s (value from --set method.s=4)" + advice, \
        both.stderr
    assert path.read_bytes() == before


def test_inspect_names_the_solver_settings_a_run_was_resumed_with(tmp_path):
    path = tmp_path / "failed.h5"
    first = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5", "--set",
                                     "solver.max_iter=3", "--quiet"])
    assert first.exit_code == 1   # 3 iterations are too few, even after 4 halvings
    assert CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--resume", "--set", "solver.max_iter=30",
                                    "--quiet"]).exit_code == 0
    report = CliRunner().invoke(cli, ["inspect", str(path)])
    assert "resumed      solver from step 0: max_iter 30 (before: 3)\n" in report.stdout


FAILING = ("problem: {builtin: kepler, parameters: {eccentricity: 0.95}}\nconserve: [angular_momentum, lrl_y]\n"
           "method: {name: ehbvm, k: 12, s: 3}\nintegration: {h: 0.5, t_end: 20}\nsolver: {max_halvings: 1}\n"
           "output: {every: 10}\n")


def test_resume_of_a_run_whose_steps_collapsed_advises_no_other_solver_settings(tmp_path):
    """A user trial: a radial fall into Kepler's centre stopped with 'the steps collapsed ... which no
    tolerance or solver setting gets through'; --resume then advised '--set solver.max_halvings=8', and
    following that failed the same way. The refusal now says to start again from another state."""
    config, path = tmp_path / "fall.yaml", tmp_path / "fall.h5"
    config.write_text("problem: {builtin: kepler, initial: {q1: 1.0, q2: 0.0, p1: -0.1, p2: 0.0}}\n"
                      "method: {name: hbvm, s: 3}\nintegration: {rtol: 1e-10, t_end: 10}\n")
    failed = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--quiet"])
    assert failed.exit_code == 1 and "the steps collapsed" in failed.stderr, failed.stderr
    refused = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert refused.exit_code == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert "resuming it would fail the same way: start again with --overwrite, from another initial state" \
        in refused.stderr and "max_halvings" not in refused.stderr, refused.stderr


def test_resume_applies_the_config_files_edits_as_set_would(tmp_path):
    """A user trial: a run failed with max_halvings: 1; the user edited the YAML to 8 and ran
    --resume, which refused 'resuming with the same solver settings would fail the same way'
    (the edit was ignored; --set worked), and an edit of method.s or t_end was ignored without a
    word. CONFIG's differences from the stored config now go through the rule of --set."""
    config, path = tmp_path / "fail.yaml", tmp_path / "f.h5"
    config.write_text(FAILING)
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--quiet"]).exit_code == 1
    before = path.read_bytes()
    config.write_text(FAILING.replace("s: 3}", "s: 4}").replace("max_halvings: 1", "max_halvings: 8"))
    refused = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert refused.exit_code == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert f"only solver.* may change on --resume; method.s (in {config}) changes the trajectory" in refused.stderr
    assert path.read_bytes() == before
    config.write_text(FAILING.replace("max_halvings: 1", "max_halvings: 8"))
    fixed = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert fixed.exit_code == 0, fixed.stderr
    assert f"with {config}'s changes: solver.max_halvings=8" in fixed.stderr
    assert "resumed at step 0 with new solver settings" in fixed.stderr
    config.write_text(FAILING.replace("max_halvings: 1", "max_halvings: 8").replace("t_end: 20", "t_end: 30"))
    later = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert later.exit_code == 0, later.stderr
    assert "continued to t_end = 30 (its t_end was 20)" in later.stderr
    with h5py.File(path, "r") as f:
        assert f.attrs["status"] == "complete" and f.attrs["steps_done"] == 60


def test_resume_applies_the_first_runs_set_values_again_and_the_config_files_edits_too(tmp_path):
    """Reading CONFIG again on --resume had made the first run's --set values count as changes:
    they had to be given again (a --resume without them was refused as an earlier end). They are
    stored in the file and applied again over CONFIG; an edit of CONFIG still counts, and a key
    given by --set changes only by --set."""
    config, path, direct = tmp_path / "fail.yaml", tmp_path / "f.h5", tmp_path / "direct.h5"
    config.write_text(FAILING)
    first = ["--set", "integration.t_end=30", "--set", "output.every=5"]
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(path), *first, "--quiet"]).exit_code == 1
    with h5py.File(path, "r") as f:
        assert json.loads(f.attrs["set_overrides"]) == ["integration.t_end=30", "output.every=5"]
    config.write_text(FAILING.replace("max_halvings: 1", "max_halvings: 8"))   # the fix, in the file
    resumed = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert resumed.exit_code == 0, resumed.stderr
    assert f"with {config}'s changes: solver.max_halvings=8" in resumed.stderr
    done = CliRunner().invoke(cli, ["run", str(config), "-o", str(direct), *first, "--quiet"])
    assert done.exit_code == 0, done.stderr
    with h5py.File(path, "r") as resumed_file, h5py.File(direct, "r") as direct_file:
        assert resumed_file.attrs["steps_done"] == direct_file.attrs["steps_done"] == 60
        assert np.array_equal(resumed_file["y"][...], direct_file["y"][...])
        assert json.loads(resumed_file.attrs["set_overrides"]) == ["integration.t_end=30", "output.every=5"]
    # a later end by --set replaces the stored one, and is kept for the next resume
    later = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume", "--set",
                                     "integration.t_end=40"])
    assert later.exit_code == 0 and "continued to t_end = 40" in later.stderr, later.stderr
    again = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert again.exit_code == 0 and "already complete" in again.stderr, again.stderr
    with h5py.File(path, "r") as f:
        assert json.loads(f.attrs["set_overrides"]) == ["output.every=5", "integration.t_end=40"]


def test_resume_ignores_differences_of_the_config_files_form(tmp_path):
    """Comments, block style, the order of keys and defaults written out are no change: the
    resolved configs are compared, not the text."""
    config, path = tmp_path / "k.yaml", tmp_path / "k.h5"
    config.write_text("problem: {builtin: kepler, parameters: {eccentricity: 0.6}}\nconserve: [angular_momentum]\n"
                      "method: {name: ehbvm, k: 12, s: 3}\nintegration: {h: 0.1, t_end: 5}\n")
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--quiet"]).exit_code == 0
    config.write_text("# the same run, written otherwise\nmethod:\n  name: EHBVM\n  s: 3\n  k: 12\n"
                      "integration:\n  t_end: 5.0   # a comment\n  h: 0.1\n  t0: 0\n"
                      "problem:\n  builtin: kepler\n  parameters:\n    eccentricity: 0.6\n"
                      "conserve: [angular_momentum]\noutput: {every: 1}\n")
    result = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert result.exit_code == 0 and "already complete" in result.stderr, result.stderr
    assert "changes the stored run's config" not in result.stderr


@pytest.mark.parametrize("change", ["integration.t_end=20.05", "integration.n_steps=100"])
def test_resume_refuses_an_end_for_the_reason_a_new_run_gives(tmp_path, change):
    """A user trial: --resume --set integration.t_end=20.05 with h = 0.1 was refused as 'only
    solver.* may change on --resume; integration.t_end changes the trajectory', contradicting
    the documented extension; the reason is the fractional number of steps, which a new run
    names. (--set integration.n_steps=100 was refused naming the stored integration.t_end.)"""
    path = tmp_path / "part.h5"
    args = ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=10"]
    assert CliRunner().invoke(cli, [*args, "--quiet"]).exit_code == 0
    new = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(tmp_path / "new.h5"), "--set", change])
    resumed = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--resume", "--set", change])
    assert new.exit_code == resumed.exit_code == 2 and resumed.stderr.count("\n") == 1
    assert resumed.stderr == new.stderr and "may change on --resume" not in resumed.stderr


def test_resume_of_a_run_a_terminal_event_ended_gives_no_hint_to_extend_it(tmp_path):
    """A user trial: a run ended by a terminal event said 'already complete; nothing to resume;
    to continue it to a later end: --resume --set integration.t_end=LATER', and following that
    hint was refused ('ended by a terminal event')."""
    path = tmp_path / "event.h5"
    args = ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=20", "--set",
            'events={peri: {expression: "q1*p1 + q2*p2", direction: 1, terminal: true}}']
    assert CliRunner().invoke(cli, [*args, "--quiet"]).exit_code == 0
    result = CliRunner().invoke(cli, [*args, "--resume"])
    assert result.exit_code == 0, result.stderr
    assert "already complete: it ended at its terminal event at t = 6.28" in result.stderr
    assert "integration.t_end=LATER" not in result.stderr


def test_a_default_that_follows_from_a_set_value_is_not_called_the_configs_change(tmp_path):
    """A user trial: --resume --set solver.method=fixed_point reported "with kepler.yaml's changes:
    solver.max_iter=100": kepler.yaml has no solver section; max_iter's default follows from the
    method given by --set. The change is applied, and not said to be the config's."""
    path = tmp_path / "k.h5"
    short = ["--set", "integration.t_end=10"]
    assert CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), *short, "-q"]).exit_code == 0
    resumed = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--resume", "--set", "solver.method=fixed_point",
                                       "--set", "integration.t_end=11"])
    assert resumed.exit_code == 0, resumed.stderr
    assert "'s changes" not in resumed.stderr and "with new solver settings" in resumed.stderr, resumed.stderr
    with h5py.File(path, "r") as f:
        assert "max_iter: 100" in f.attrs["config"]


def test_resume_with_another_config_does_not_blame_a_set_the_file_stored(tmp_path):
    """A user trial resumed a file written from one Kepler config (with --set integration.t_end=...)
    with another (other h): the stored --set, applied again to that config, was refused as if the user
    had typed it ('not a whole number of steps ... (value from --set integration.t_end=...)'). The
    message now says that the file's stored --set does not fit that config, and what to do."""
    import yaml
    first, other = tmp_path / "first.yaml", tmp_path / "other.yaml"
    base = {"problem": {"builtin": "kepler"}, "method": "HBVM(6,3)", "integration": {"h": 0.1, "t_end": 1}}
    first.write_text(yaml.safe_dump(base))
    other.write_text(yaml.safe_dump({**base, "integration": {"h": 0.3, "t_end": 0.9}}))
    out = tmp_path / "run.h5"
    made = CliRunner().invoke(cli, ["run", str(first), "-o", str(out), "--quiet", "--set", "integration.t_end=1.6"])
    assert made.exit_code == 0, made.output
    resumed = CliRunner().invoke(cli, ["run", str(other), "-o", str(out), "--resume"])
    assert resumed.exit_code == 2, resumed.output
    message = resumed.stderr
    assert "the --set integration.t_end=1.6 that its earlier run stored" in message, message
    assert f"does not fit {other}" in message and "another config" in message and message.count("\n") == 1
