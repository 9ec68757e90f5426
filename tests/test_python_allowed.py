"""A config is data: a python: problem file it names runs only when the user allowed it outside
the config (--allow-python, allow_python=True, ELIMFAST_ALLOW_PYTHON=1). A user trial ran a
config naming a file whose top-level code wrote where it liked, under `run` and under `check`.

Every test here takes the permission away first (the folder fixture: ELIMFAST_ALLOW_PYTHON unset).
"""
import yaml
import pytest
from click.testing import CliRunner

import elimfast
from cli.main import cli
from elimfast.config import (ALLOW_PYTHON_ENV, ConfigError, PythonNotAllowed, allowing_python, load_run,
                             load_run_from_dict, python_allowed)

# A harmonic oscillator whose import leaves a mark in the test's folder: the mark is what running
# it does (elimfast imports a copy of the file from its cache: hence the folder's path in the text).
OSCILLATOR = """import pathlib
pathlib.Path({mark!r}).write_text("ran")

Y0 = [1.0, 0.0]


def H(y, params):
    return 0.5 * y[0] ** 2 + 0.5 * y[1] ** 2


def grad_H(y, params, out):
    out[0] = y[0]
    out[1] = y[1]
"""
REST = {"method": {"name": "hbvm", "k": 6, "s": 3}, "integration": {"h": 0.1, "t_end": 1}}


@pytest.fixture
def not_allowed(monkeypatch):
    monkeypatch.delenv(ALLOW_PYTHON_ENV, raising=False)


@pytest.fixture
def folder(tmp_path, not_allowed):
    (tmp_path / "osc.py").write_text(OSCILLATOR.format(mark=str(tmp_path / "MARK")))
    (tmp_path / "osc.yaml").write_text(yaml.safe_dump({"problem": {"python": "osc.py"}, **REST}, sort_keys=False))
    (tmp_path / "short.yaml").write_text(yaml.safe_dump({"problem": "osc.py", **REST}, sort_keys=False))
    (tmp_path / "builtin.yaml").write_text(yaml.safe_dump({"problem": {"builtin": "harmonic_oscillator"}, **REST}))
    return tmp_path


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


@pytest.mark.parametrize("command", ["run", "check"])
@pytest.mark.parametrize("config,extra,line", [
    ("osc.yaml", [], ":2: problem.python: osc.py"),
    ("short.yaml", [], ":1: problem.python: osc.py"),       # problem: osc.py, the shorthand
    ("builtin.yaml", ["--set", "problem=osc.py"], ": problem.python: osc.py"),
])
def test_a_config_naming_a_python_file_is_refused_in_one_line_and_runs_nothing(folder, command, config, extra, line):
    out = folder / "o.h5"
    output = ["-o", out] if command == "run" else []
    refused = invoke(command, folder / config, *output, *extra)
    assert refused.exit_code == 2, refused.output
    assert refused.stderr.count("\n") == 1 and "Traceback" not in refused.stderr
    assert refused.stderr.startswith(f"error: {folder / config}")
    assert line in refused.stderr and "is a Python file" in refused.stderr
    assert "pass --allow-python" in refused.stderr and "allow_python=True" in refused.stderr
    assert not (folder / "MARK").exists() and not out.exists()
    # the user's permission is the only barrier
    allowed = invoke(command, folder / config, *output, *extra, "--allow-python")
    assert allowed.exit_code == 0, allowed.output
    assert (folder / "MARK").read_text() == "ran"


def test_a_missing_python_file_is_still_told_missing(folder):
    (folder / "osc.py").unlink()
    result = invoke("check", folder / "osc.yaml")
    assert result.exit_code == 2 and "osc.py does not exist; check the path" in result.stderr
    assert "--allow-python" not in result.stderr


def test_the_python_api_refuses_unless_allowed(folder, monkeypatch):
    with pytest.raises(ConfigError, match=r"problem\.python: osc\.py is a Python file.*allow_python=True"):
        load_run(folder / "osc.yaml")
    assert not (folder / "MARK").exists()
    assert load_run(folder / "osc.yaml", allow_python=True).problem.name == "osc"
    (folder / "MARK").unlink()
    monkeypatch.setenv(ALLOW_PYTHON_ENV, "1")
    assert python_allowed()
    with allowing_python(False), pytest.raises(ConfigError, match="is a Python file") as refused:
        load_run(folder / "osc.yaml")   # the caller's word before the environment's
    # ... and the message does not suggest the variable that is already set (a user trial)
    assert "allow_python=False" in str(refused.value) and f"set {ALLOW_PYTHON_ENV}" not in str(refused.value)
    with pytest.raises(ConfigError, match="given allow_python=False"):
        load_run(folder / "osc.yaml", allow_python=False)
    assert not (folder / "MARK").exists()
    assert load_run(folder / "osc.yaml").problem.name == "osc"


def test_a_sweep_runs_a_python_file_only_when_allowed_also_in_its_worker_processes(folder):
    sweep = folder / "sweep.yaml"
    sweep.write_text(yaml.safe_dump({"base": "builtin.yaml", "grid": [
        {"name": "problem", "values": [{"label": "osc", "set": {"problem": {"python": "osc.py"}}}]},
        {"name": "h", "key": "integration.h", "values": [0.1, 0.05]}]}))
    out = folder / "sweep.h5"
    refused = invoke("sweep", sweep, "--workers", "2", "-q", "-o", out)
    # before any run (a user trial: the other runs ran first, then the sweep stopped)
    assert refused.exit_code == 2 and refused.stdout == "" and not out.exists(), refused.output
    assert refused.stderr.startswith(f"error: {sweep} (run 'osc/0.1'): problem.python: "), refused.stderr
    assert "--allow-python" in refused.stderr and refused.stderr.count("\n") == 1
    assert not (folder / "MARK").exists()
    allowed = invoke("sweep", sweep, "--workers", "2", "-q", "--allow-python", "-o", out)
    assert allowed.exit_code == 0, allowed.output
    assert allowed.stdout.count("complete") == 2 and (folder / "MARK").exists()
    assert not python_allowed()   # the flag's leave ended with its command
    # --resume without the flag: the same refusal, not "the sweep was edited" (a user trial)
    again = invoke("sweep", sweep, "-q", "-o", out, "--resume")
    assert again.exit_code == 2 and "is a Python file" in again.stderr and "edited" not in again.stderr
    assert invoke("sweep", sweep, "-q", "-o", out, "--resume", "--allow-python").exit_code == 0


def test_a_dask_task_takes_the_clients_permission_not_the_workers_environment(folder):
    """distributed._task runs on a worker, whose environment has no --allow-python: the client's
    permission is an argument of every task."""
    from elimfast import distributed
    config = {"problem": {"python": "osc.py"}, **REST}
    source = str(folder / "sweep.yaml")
    refused = distributed._task("osc", {}, config, source, False, {}, False)
    assert refused.status.startswith("failed: ") and "--allow-python" in refused.status
    assert not (folder / "MARK").exists()
    assert distributed._task("osc", {}, config, source, False, {}, True).status == "complete"
    assert (folder / "MARK").exists()


def test_opening_a_run_file_runs_no_python_file_beside_it(folder):
    """elimfast.load rebuilds the problem from the stored config: opening a run file someone sent
    imported the python: file its config names, if one was at that path."""
    out = folder / "o.h5"
    assert invoke("run", folder / "osc.yaml", "-o", out, "-q", "--allow-python").exit_code == 0
    (folder / "MARK").unlink()
    with pytest.raises(PythonNotAllowed, match=r"cannot rebuild the run from its stored config: .*is a Python "
                                               r"file.*allow_python=True.*; or read the data without its problem: "
                                               r"elimfast.open_datatree\(path\)$"):
        elimfast.load(out)
    assert not (folder / "MARK").exists()
    result = elimfast.load(out, allow_python=True)   # (the module this process imported for the run)
    assert result.steps_done == 10 and result.problem.name == "osc"
    # the file changed since the run: said, since the permission was for the file that made it
    (folder / "osc.py").write_text((folder / "osc.py").read_text() + "\n# edited\n")
    with pytest.warns(UserWarning, match=r"o\.h5: the problem file .*osc\.py has changed since it was stored"):
        assert elimfast.load(out, allow_python=True).steps_done == 10


def test_the_cli_flag_allows_for_its_command_only(folder):
    """A user trial: --allow-python wrote ELIMFAST_ALLOW_PYTHON=1 into this process's environment for
    good, so that a later elimfast.load in the same notebook ran the file of a run file it opened."""
    from cli.main import cli as command
    command.main(["check", str(folder / "osc.yaml"), "--allow-python"], standalone_mode=False)
    assert not python_allowed() and ALLOW_PYTHON_ENV not in __import__("os").environ


@pytest.mark.parametrize("name,reason", [("a\x00.py", "null"), ("~no_such_user_zz9/x.py", "home"),
                                         ("x" * 300 + ".py", "too long"), ("\ud800.py", "encode")])
def test_a_path_that_cannot_be_a_file_is_one_config_error(folder, name, reason):
    """A user trial: a NUL in the path, a lone surrogate or ~nosuchuser was an internal error; a name
    too long for the file system named neither the config nor the key."""
    with pytest.raises(ConfigError, match=rf"problem\.python: .* is not a usable path \(.*{reason}.*\); give the "
                                          r"path of a \.py file"):
        load_run_from_dict({"problem": {"python": name}, **REST}, source="c.yaml", allow_python=True)


def test_a_run_file_cannot_choose_the_python_file_its_resume_runs(folder):
    """A user trial: a run file's stored --set values (plain JSON in it) are applied at --resume, so an
    edited file could name another Python file, which then ran under the --allow-python given for the
    config's own file. Only the config and the --set given now may name it."""
    import json

    import h5py
    (folder / "evil.py").write_text(OSCILLATOR.format(mark=str(folder / "EVIL")))
    out = folder / "o.h5"
    assert invoke("run", folder / "osc.yaml", "-o", out, "-q", "--allow-python",
                  "--set", "integration.t_end=0.5").exit_code == 0
    with h5py.File(out, "r+") as f:
        f.attrs["set_overrides"] = json.dumps([f"problem={folder / 'evil.py'}"])
    refused = invoke("run", folder / "osc.yaml", "-o", out, "--resume", "--allow-python", "-q")
    assert refused.exit_code == 2 and "a run file cannot choose code to run" in refused.stderr, refused.output
    assert not (folder / "EVIL").exists()
    with h5py.File(out, "r+") as f:   # the stored config's own file, with the stored --set put back
        f.attrs["set_overrides"] = json.dumps(["integration.t_end=0.5"])
        f.attrs["config"] = str(f.attrs["config"]).replace(str(folder / "osc.py"), str(folder / "evil.py"))
    refused = invoke("run", folder / "osc.yaml", "-o", out, "--resume", "--allow-python", "-q")
    assert refused.exit_code == 2 and "problem.python" in refused.stderr, refused.output
    assert not (folder / "EVIL").exists()


def test_the_resume_command_a_run_prints_repeats_the_allowance(folder):
    """A user trial: the 'continue with' command of a python: problem's stopped run left out
    --allow-python, and run as printed it was refused."""
    (folder / "late.py").write_text(OSCILLATOR.format(mark=str(folder / "MARK")).replace(
        "    out[0] = y[0]\n", "    if y[0] < -0.9:\n        raise ValueError('late')\n    out[0] = y[0]\n"))
    (folder / "late.yaml").write_text(yaml.safe_dump({"problem": {"python": "late.py"}, **REST,
                                                      "integration": {"h": 0.1, "t_end": 4}}))
    failed = invoke("run", folder / "late.yaml", "-o", folder / "late.h5", "--allow-python")
    assert failed.exit_code == 1, failed.output
    assert f"--resume --allow-python" in failed.stderr, failed.stderr


def test_load_sweep_takes_the_allowance_its_reference_run_needs(folder):
    sweep = folder / "ref.yaml"
    sweep.write_text(yaml.safe_dump({"base": "osc.yaml", "grid": [{"name": "h", "key": "integration.h",
                                                                    "values": [0.1, 0.05]}],
                                     "error": {"reference": {"set": {"integration": {"h": 0.01}}}}}))
    from elimfast.sweep import load_sweep
    with pytest.raises(Exception, match="is a Python file"):
        load_sweep(sweep)
    assert not (folder / "MARK").exists()
    assert len(load_sweep(sweep, allow_python=True).runs) == 2
