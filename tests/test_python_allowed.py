"""A config is data: a python: problem file it names runs only when the user allowed it outside
the config (--allow-python, allow_python=True, ELIMFAST_ALLOW_PYTHON=1). A user trial ran a
config naming a file whose top-level code wrote where it liked, under `run` and under `check`.

Every test here takes the permission away first (monkeypatch: the CLI's flag sets the variable
in this process too, and monkeypatch puts the old value back).
"""
import yaml
import pytest
from click.testing import CliRunner

import elimfast
from cli.main import cli
from elimfast.config import ALLOW_PYTHON_ENV, ConfigError, allowing_python, load_run, python_allowed

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
    with allowing_python(False), pytest.raises(ConfigError, match="is a Python file"):
        load_run(folder / "osc.yaml")   # the caller's word before the environment's
    assert not (folder / "MARK").exists()
    assert load_run(folder / "osc.yaml").problem.name == "osc"


def test_a_sweep_runs_a_python_file_only_when_allowed_also_in_its_worker_processes(folder):
    sweep = folder / "sweep.yaml"
    sweep.write_text(yaml.safe_dump({"base": "builtin.yaml", "grid": [
        {"name": "problem", "values": [{"label": "osc", "set": {"problem": {"python": "osc.py"}}}]},
        {"name": "h", "key": "integration.h", "values": [0.1, 0.05]}]}))
    refused = invoke("sweep", sweep, "--workers", "2", "-q")
    assert refused.exit_code == 2 and "--allow-python" in refused.stderr, refused.output
    assert not (folder / "MARK").exists()
    allowed = invoke("sweep", sweep, "--workers", "2", "-q", "--allow-python")
    assert allowed.exit_code == 0, allowed.output
    assert allowed.stdout.count("complete") == 2 and (folder / "MARK").exists()


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
    del __import__("os").environ[ALLOW_PYTHON_ENV]    # set by the flag, in this process
    with pytest.raises(elimfast.ElimfastError, match=r"cannot rebuild the run from its stored config: .*"
                                                     r"is a Python file.*allow_python=True"):
        elimfast.load(out)
    assert not (folder / "MARK").exists()
    result = elimfast.load(out, allow_python=True)   # (the module this process imported for the run)
    assert result.steps_done == 10 and result.problem.name == "osc"
