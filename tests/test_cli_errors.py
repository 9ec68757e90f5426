"""Bad input at the command line: exit code 2 and one line on stderr, never a traceback.

Table-driven through click's CliRunner; two cases again through a real process. Also
exit 1 for a failed run and for an internal error (with the ELIMFAST_DEBUG hint).
"""
import subprocess
import sys
from pathlib import Path

import h5py
import pytest
from click.testing import CliRunner

from elimfast_cli.main import cli

ROOT = Path(__file__).resolve().parents[1]
KEPLER = str(ROOT / "configs" / "kepler.yaml")
ELIMFAST = str(Path(sys.executable).with_name("elimfast"))

GOOD = """\
problem: {builtin: kepler}
conserve: [angular_momentum, lrl_y]
method: {name: ehbvm, k: 6, s: 3}
integration: {h: 0.1, n_steps: 20}
"""
EVIL_MARK = "/tmp/elimfast-owned-by-test"


def write(directory: Path, name: str, text: str) -> str:
    path = directory / name
    path.write_text(text)
    return str(path)


def make_case(name, tmp: Path):
    """(arguments, a fragment of the expected message) for each bad input."""
    existing = tmp / "exists.h5"
    existing.write_bytes(b"")
    a_file = tmp / "a_file"
    a_file.write_text("x")
    foreign = tmp / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["data"] = [1.0, 2.0]
    cases = {
        "missing file": (["run", tmp / "nope.yaml", "-o", tmp / "o.h5"], "no such file"),
        "bad yaml": (["run", write(tmp, "bad.yaml", "problem: {builtin: kepler\nmethod: [\n"), "-o", tmp / "o.h5"],
                     "invalid YAML"),
        "python file as config": (["check", write(tmp, "prob.py", "import math\n\ndef H(y, params):\n    return 0.0\n")],
                                  "a Python file, not a YAML config; a problem written in Python is run from a "
                                  "config that names it: problem: {python: prob.py}"),
        "unknown key": (["run", write(tmp, "key.yaml", GOOD + "solver: {tolerance: 1e-15}\n"), "-o", tmp / "o.h5"],
                        "unknown key"),
        "unknown key by --set": (["run", write(tmp, "g.yaml", GOOD), "-o", tmp / "o.h5", "--set", "method.kk=3"],
                                 "unknown key"),
        "bad expression": (["run", write(tmp, "expr.yaml", GOOD.replace(
            "problem: {builtin: kepler}",
            "problem:\n  coordinates: {q: [q1], p: [p1]}\n"
            f"  hamiltonian: \"__import__('os').system('touch {EVIL_MARK}')\"\n"
            "  initial: {q1: 1.0, p1: 0.0}").replace("conserve: [angular_momentum, lrl_y]\n", "")),
            "-o", tmp / "o.h5"], "hamiltonian"),
        "bad number": (["run", write(tmp, "num.yaml", GOOD.replace("h: 0.1", "h: pi/")), "-o", tmp / "o.h5"],
                       "integration.h"),
        "impossible method s <= nu": (["run", write(tmp, "s.yaml", GOOD.replace("s: 3", "s: 2")), "-o", tmp / "o.h5"],
                                      "at most s - 1 = 1"),
        "existing output": (["run", write(tmp, "g.yaml", GOOD), "-o", existing], "already exists; pass --overwrite"),
        "unwritable path": (["run", write(tmp, "g.yaml", GOOD), "-o", a_file / "o.h5"], "is a file, not a directory"),
        "unwritable file system": (["run", write(tmp, "g.yaml", GOOD), "-o", "/proc/elimfast/o.h5"],
                                   "choose another output path"),
        "no output path": (["run", write(tmp, "g.yaml", GOOD)], "no output file: give -o"),
        "overwrite and resume": (["run", KEPLER, "-o", tmp / "o.h5", "--overwrite", "--resume"], "contradict"),
        "inspect a text file": (["inspect", a_file], "not an HDF5 file"),
        "inspect a foreign hdf5 file": (["inspect", foreign], "not an elimfast run file"),
        "inspect a missing file": (["inspect", tmp / "missing.h5"], "no such file"),
        "plot a foreign file": (["plot", foreign], "not an elimfast run file"),
        "check a bad config": (["check", write(tmp, "key2.yaml", GOOD + "extra: 1\n")], "unknown key"),
        "unknown command": (["integrate"], "No such command"),
        "unknown option": (["run", KEPLER, "--fast"], "No such option"),
        "tableau without k": (["tableau", "hbvm", "--s", "2"], "--k is missing"),
        "tableau of lim": (["tableau", "ghbvm", "--k", "3", "--s", "2"], "no fixed Runge-Kutta form"),
        "tableau k < s": (["tableau", "hbvm", "--k", "2", "--s", "3"], "k must be >= s"),
        "tableau bad eta": (["tableau", "ehbvm", "--k", "3", "--s", "2", "--eta", "x"], "not a number"),
        "tableau nan eta": (["tableau", "ehbvm", "--k", "3", "--s", "2", "--eta", "nan"], "not a finite number"),
        "tableau without r and k": (["tableau", "elim", "--s", "3"], "--r is missing, and so is k;"),
        "empty output path": (["run", write(tmp, "g.yaml", GOOD), "-o", ""], "the output path is empty"),
        "duplicate section": (["run", write(tmp, "dup.yaml", GOOD + "integration: {h: 0.2, n_steps: 5}\n"), "-o",
                               tmp / "o.h5"], "dup.yaml:5: duplicate key 'integration' at the top level (first at "
                                              "line 4)"),
        "duplicate key in a flow mapping": (["run", write(tmp, "dup2.yaml", GOOD.replace("s: 3}", "s: 3, s: 4}")),
                                             "-o", tmp / "o.h5"], "dup2.yaml:3: duplicate key 's' in method"),
        "misspelt section": (["run", write(tmp, "methd.yaml", GOOD.replace("method:", "methd:")), "-o", tmp / "o.h5"],
                             "methd.yaml:3: methd: unknown key; did you mean 'method'?"),
        "misspelt event key": (["run", write(tmp, "ev.yaml", GOOD + "events: {x: {expression: q1, dir: 1}}\n"),
                                "-o", tmp / "o.h5"], "events.x.dir: unknown key; did you mean 'direction'?"),
        "run a sweep file": (["run", write(tmp, "sw.yaml", "base: g.yaml\ngrid: []\n"), "-o", tmp / "o.h5"],
                             "a sweep file (it has base: and no problem:), not a run config; run it with elimfast "
                             "sweep"),
        "check a sweep file": (["check", write(tmp, "sw.yaml", "base: g.yaml\nset: {}\n")], "elimfast sweep"),
        "sweep a run config": (["sweep", write(tmp, "g.yaml", GOOD)], "a run config (it has problem: and no base:), "
                                                                       "not a sweep file; run it with elimfast run"),
        # a user trial: -o CONFIG --overwrite replaced the YAML by HDF5 (also through output.path)
        "output onto the config": (["run", write(tmp, "g.yaml", GOOD), "-o", tmp / "g.yaml", "--overwrite"],
                                   "is the config file itself, which writing would replace"),
        "output.path onto the config": (["run", write(tmp, "self.yaml", GOOD + f"output: {{path: {tmp}/self.yaml}}\n"),
                                         "--overwrite"], "is the config file itself"),
        # a user trial: -o PROBLEM.py --overwrite replaced the python: problem file by HDF5
        # (a copy of configs/kepler_problem.py: a failing test must not replace the repository's)
        "output onto the problem file": (["run", write(tmp, "py.yaml", "problem: {python: kp.py}\n"
                                                                       "method: {name: hbvm, k: 6, s: 3}\n"
                                                                       "integration: {h: 0.1, n_steps: 5}\n"),
                                          "-o", write(tmp, "kp.py", (ROOT / "configs" / "kepler_problem.py").read_text()),
                                          "--overwrite"], "is the problem file itself"),
        "output onto the sweep file": (["sweep", write(tmp, "sw2.yaml", "base: g.yaml\ngrid: []\n"), "-o",
                                        tmp / "sw2.yaml", "--overwrite"], "is the sweep file itself"),
        "sweep --overwrite without -o": (["sweep", KEPLER.replace("kepler.yaml", "paper/table1.yaml"), "--overwrite"],
                                         "--overwrite replaces the file given with -o OUT.h5, and there is none"),
    }
    return cases[name]


CASES = ["missing file", "bad yaml", "unknown key", "unknown key by --set", "bad expression", "bad number",
         "impossible method s <= nu", "existing output", "unwritable path", "unwritable file system",
         "no output path", "overwrite and resume", "inspect a text file", "inspect a foreign hdf5 file",
         "inspect a missing file", "plot a foreign file", "check a bad config", "unknown command", "unknown option",
         "tableau without k", "tableau of lim", "tableau k < s", "tableau bad eta", "tableau without r and k",
         "empty output path", "duplicate section", "duplicate key in a flow mapping", "misspelt section",
         "misspelt event key", "run a sweep file", "check a sweep file", "sweep a run config",
         "output onto the config", "output.path onto the config", "output onto the problem file",
         "output onto the sweep file",
         "sweep --overwrite without -o", "tableau nan eta", "python file as config"]


def assert_one_line_error(stderr: str, fragment: str):
    assert "Traceback" not in stderr
    lines = stderr.splitlines()
    assert len(lines) == 1, stderr
    assert lines[0].startswith("error: ") and fragment in lines[0], lines[0]


@pytest.mark.parametrize("name", CASES)
@pytest.mark.usefixtures("allow_python")
def test_bad_input_exits_2_with_one_line(name, tmp_path):
    args, fragment = make_case(name, tmp_path)
    result = CliRunner().invoke(cli, [str(a) for a in args])
    assert result.exit_code == 2, (result.exit_code, result.output, result.exception)
    assert result.stdout == ""
    assert_one_line_error(result.stderr, fragment)
    assert not Path(EVIL_MARK).exists()
    assert not (tmp_path / "o.h5").exists()          # nothing computed, nothing written


@pytest.mark.parametrize("name", ["bad yaml", "inspect a foreign hdf5 file"])
def test_bad_input_in_a_real_process(name, tmp_path):
    args, fragment = make_case(name, tmp_path)
    done = subprocess.run([ELIMFAST, *map(str, args)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and done.stdout == ""
    assert_one_line_error(done.stderr, fragment)


def test_a_failed_run_exits_1_and_keeps_its_data(tmp_path):
    out = tmp_path / "fail.h5"
    result = CliRunner().invoke(cli, ["run", write(tmp_path, "g.yaml", GOOD), "-o", str(out),
                                      "--set", "solver.max_iter=3", "--set", "solver.max_halvings=0"])
    assert result.exit_code == 1
    assert_one_line_error(result.stderr, "run failed: EHBVM(6,3): the simplified Newton did not converge "
                                         "(max_iter = 3) at step 1")
    # a run file is continued with --resume and other solver settings (the Python API is not told so)
    assert "continued with --resume after changing solver settings" in result.stderr
    with h5py.File(out, "r") as f:
        assert f.attrs["status"].startswith("failed: EHBVM(6,3)")
    inspect = CliRunner().invoke(cli, ["inspect", str(out)])
    assert inspect.exit_code == 0 and "status       failed: " in inspect.stdout
    # no step done: no invariant figures (they were 0.000e+00, a perfect result)
    assert "invariants   no figures: the run failed at its first step" in inspect.stdout
    assert "0.000e+00" not in inspect.stdout
    plotted = CliRunner().invoke(cli, ["plot", str(out), "-o", str(tmp_path / "i.png")])
    assert plotted.exit_code == 2 and "no step done" in plotted.stderr


def test_an_internal_error_is_one_line_with_a_hint(tmp_path, monkeypatch):
    import elimfast.streaming

    def broken(*args, **kwargs):
        raise RuntimeError("something\nunexpected")
    monkeypatch.setattr(elimfast.streaming, "run_to_file", broken)
    args = ["run", write(tmp_path, "g.yaml", GOOD), "-o", str(tmp_path / "x.h5")]
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == 1
    assert_one_line_error(result.stderr, "internal error: RuntimeError: something unexpected")
    assert "ELIMFAST_DEBUG=1" in result.stderr
    debug = CliRunner().invoke(cli, args, env={"ELIMFAST_DEBUG": "1"})
    assert isinstance(debug.exception, RuntimeError)     # the traceback is there for developers


def test_an_error_after_a_signal_is_the_interruption(tmp_path, monkeypatch):
    """A user trial: Ctrl-C while a problem's functions compiled was swallowed inside a ctypes callback
    of Numba's compiler ('Exception ignored on calling ctypes callback function'), and the compile then
    failed with 'internal error: RuntimeError: no compiled object yet ...', exit 1 (1 try in 7). After a
    signal any error is the interruption's: one line, exit 130; an unraisable _Interrupted is dropped."""
    import elimfast.streaming
    from elimfast_cli import main as cli_main

    def compile_failed(*args, **kwargs):
        cli_main._SIGNALLED.append(2)      # the handler ran; its exception went nowhere
        raise RuntimeError("no compiled object yet for <Library 'grad_H'>")
    monkeypatch.setattr(cli_main, "_SIGNALLED", [])
    monkeypatch.setattr(elimfast.streaming, "run_to_file", compile_failed)
    result = CliRunner().invoke(cli, ["run", write(tmp_path, "g.yaml", GOOD), "-o", str(tmp_path / "x.h5")])
    assert result.exit_code == 130, result.output
    assert "internal error" not in result.stderr and result.stderr.startswith("error: interrupted")
    seen = []
    hook = cli_main._unraisable(seen.append)
    hook(type("U", (), {"exc_type": cli_main._Interrupted})())
    hook(type("U", (), {"exc_type": ValueError})())
    assert [u.exc_type for u in seen] == [ValueError]


def test_run_refuses_to_resume_a_sweep_file_or_to_write_into_one(tmp_path, monkeypatch):
    """A user trial: `run ... -o SWEEP.h5 --resume` advised naming a run as SWEEP.h5:/runs/<label>,
    and `run ... -o SWEEP.h5:/runs/<label> --resume` then made a folder 'SWEEP.h5:' and started a
    new run in it. Both now say how a sweep is continued, exit 2, and write nothing."""
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text("base:\n" + "".join(f"  {line}\n" for line in GOOD.splitlines())
                     + "grid: [{name: h, key: integration.h, values: [0.1, 0.05]}]\n"
                     + "set: {integration: {t_end: 2.0, n_steps: null}}\n")
    out = tmp_path / "sweep.h5"
    assert CliRunner().invoke(cli, ["sweep", str(sweep), "-o", str(out), "--workers", "1", "-q"]).exit_code == 0
    config = write(tmp_path, "g.yaml", GOOD)
    for target, fragment in ((out, f"a sweep's file, which elimfast run does not continue: continue the sweep with "
                                    f"elimfast sweep {sweep} -o {out} --resume"),
                             (f"{out}:/runs/0.1", "names a group inside the file")):
        result = CliRunner().invoke(cli, ["run", config, "-o", str(target), "--resume"])
        assert result.exit_code == 2, result.output
        assert_one_line_error(result.stderr, fragment)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.yaml", "sweep.h5", "sweep.yaml"]
    # A sweep run from its own folder with a relative path: the hint, read from another folder,
    # quoted that relative path (a user trial: no such file). It is the sweep file's absolute path.
    with monkeypatch.context() as patched:
        patched.chdir(tmp_path)
        assert CliRunner().invoke(cli, ["sweep", "sweep.yaml", "-o", "rel.h5", "--workers", "1", "-q"]).exit_code == 0
    result = CliRunner().invoke(cli, ["run", config, "-o", str(tmp_path / "rel.h5"), "--resume"])
    assert_one_line_error(result.stderr, f"continue the sweep with elimfast sweep {sweep.resolve()} -o "
                                         f"{tmp_path / 'rel.h5'} --resume")


def test_a_reader_that_goes_away_is_no_failure():
    """A user trial: `elimfast check CONFIG | head -1` exited 1 (click's answer to a broken pipe),
    the code of a failed integration. The reader leaving is not an error of elimfast's: 0."""
    import subprocess
    import sys
    from pathlib import Path
    config = Path(__file__).resolve().parents[1] / "configs" / "kepler.yaml"
    process = subprocess.Popen([sys.executable, "-m", "elimfast_cli.main", "check", str(config)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.readline()
    process.stdout.close()   # as head -1 does
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 0, stderr
    assert b"Traceback" not in stderr
