"""YAML run configs: every shipped config validates; every fault is one clear ConfigError line;
nothing in a config can run code."""
import copy
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bounds import bounded_example

import elimfast
from elimfast import problems
from elimfast.config import ConfigError, RunSpec, load_run, load_run_from_dict
from elimfast.integrate import Integration, SolverSettings

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
ALL_CONFIGS = sorted(CONFIGS.glob("*.yaml"))


@pytest.fixture(autouse=True)
def private_cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "elimfast-cache"))


def kepler_data():
    return yaml.safe_load((CONFIGS / "kepler.yaml").read_text())


def expressions_data():
    return yaml.safe_load((CONFIGS / "kepler_expressions.yaml").read_text())


def config_error(data, overrides=(), source="run.yaml") -> ConfigError:
    with pytest.raises(ConfigError) as info:
        load_run_from_dict(data, source=source, overrides=overrides)
    message = str(info.value)
    assert "\n" not in message and "Traceback" not in message
    assert message.startswith(f"{source}: ")
    return info.value


# --- the shipped configs ---------------------------------------------------------------

@pytest.mark.parametrize("path", ALL_CONFIGS, ids=[p.stem for p in ALL_CONFIGS])
@pytest.mark.usefixtures("allow_python")
def test_every_shipped_config_loads_and_validates(path):
    spec = load_run(path)
    assert isinstance(spec, RunSpec) and spec.source == str(path)
    if spec.step_control is None:
        assert spec.n_steps >= 1 and spec.h > 0 and math.isclose(spec.t0 + spec.n_steps * spec.h, spec.t_end)
    else:   # adaptive steps (docs/adaptive.md): the number of steps is the controller's
        assert spec.n_steps is None and spec.t_end > spec.t0
    run = Integration.from_spec(spec)
    assert run.conserve == spec.conserve
    assert isinstance(run, Integration) == (not spec.uses_adaptive_kernel)
    chunk = run.advance(3)
    assert chunk.status == 0 and np.all(np.isfinite(chunk.y))
    # The resolved config is plain YAML and describes the same run.
    again = load_run_from_dict(yaml.safe_load(yaml.safe_dump(spec.resolved, sort_keys=False)), source="resolved")
    assert again.n_steps == spec.n_steps and again.h == spec.h and again.method.name == spec.method.name
    assert again.step_control == spec.step_control and again.events == spec.events
    assert again.conserve == spec.conserve and np.array_equal(again.problem.y0, spec.problem.y0)
    np.testing.assert_array_equal(again.problem.params, spec.problem.params)


def test_every_builtin_problem_has_a_config():
    shipped = {yaml.safe_load(p.read_text())["problem"].get("builtin") for p in ALL_CONFIGS}
    assert set(problems.PROBLEMS) <= shipped


def test_kepler_config_is_the_make_run_config():
    spec = load_run(CONFIGS / "kepler.yaml")
    assert spec.method.name == "EHBVM(12,3)" and spec.conserve == ("angular_momentum", "lrl_y")
    assert (spec.h, spec.t0, spec.t_end, spec.n_steps) == (0.1, 0.0, 1000.0, 10000)
    assert (spec.output_path, spec.output_every) == ("out/kepler.h5", 10)
    # simplified Newton (solver 'auto' at n = 4) with the defaults of docs/solver.md (max_iter 30: ELIM
    # imposing invariants)
    assert spec.solver == SolverSettings(method="newton", max_iter=30)
    assert (spec.solver.method, spec.solver.max_iter, spec.solver.max_halvings) == ("newton", 30, 4)
    assert spec.problem.name == "kepler" and spec.problem.parameters == {"eccentricity": 0.6}


@pytest.mark.usefixtures("allow_python")
def test_user_problems_in_configs_are_the_builtin_kepler():
    builtin = problems.kepler(0.6)
    for name in ("kepler_expressions", "kepler_python"):
        spec = load_run(CONFIGS / f"{name}.yaml")
        np.testing.assert_allclose(spec.problem.y0, builtin.y0, rtol=0, atol=1e-15)
        assert spec.problem.invariant_names == builtin.invariant_names
        values, expected = spec.problem.invariant_values(builtin.y0), builtin.invariant_values(builtin.y0)
        for key in expected:
            assert values[key] == pytest.approx(expected[key], abs=1e-15)


def test_numbers_are_arithmetic_and_integration_matches_the_python_api():
    data = kepler_data()
    data["integration"] = {"h": "pi/30", "t_end": "20*pi"}
    data["solver"] = {"tol": "1e-15", "max_iter": "2*50", "method": "fixed_point", "max_halvings": "2+1"}
    spec = load_run_from_dict(data)
    assert spec.h == math.pi / 30 and spec.n_steps == 600 and spec.t_end == 20 * math.pi
    assert spec.solver == SolverSettings(method="fixed_point", tol=1e-15, max_iter=100, max_halvings=3)
    run = Integration.from_spec(spec)
    assert (run.h, run.n_steps, run.tol, run.store_every) == (math.pi / 30, 600, 1e-15, 10)
    assert run.solver is spec.solver


def test_overrides_are_yaml_values_and_validated():
    spec = load_run(CONFIGS / "kepler.yaml", overrides=["method.s=4", "integration.h=pi/60",
                                                         "integration.t_end=2*pi", "output.every=1",
                                                         "conserve=[angular_momentum]"])
    assert spec.method.name == "EHBVM(12,4)" and spec.h == math.pi / 60 and spec.n_steps == 120
    assert spec.conserve == ("angular_momentum",) and spec.output_every == 1
    spec = load_run(CONFIGS / "kepler.yaml", overrides=["integration.t_end=null", "integration.n_steps=7",
                                                         "problem.initial.p2=2.0"])
    assert spec.n_steps == 7 and spec.t_end == pytest.approx(0.7) and spec.problem.y0[3] == 2.0
    err = config_error(kepler_data(), overrides=["method.s=1"])
    assert err.key == "method.s" and str(err).endswith("(value from --set method.s=1)") and err.line is None


@pytest.mark.parametrize("overrides,top_key,match", [
    # a user trial: each was "internal error: IndexError: tuple index out of range" (exit 1)
    (["conserve[0]=lrl_x"], None, r"--set 'conserve\[0\]=lrl_x': 'conserve\[0\]' is not a key path .* set a list whole"),
    (["x[=1"], None, r"--set 'x\[=1': 'x\[' is not a key path"),
    # ... and a nested one "integration: unknown key; did you mean 'integration'?"
    (["integration.h[1]=2"], None, r"'integration\.h\[1\]' is not a key path"),
    # the example is the user's own key (it always said conserve=[...])
    (["output.times[0]=3"], None, r"set a list whole, e\.g\. --set output\.times=\[\.\.\.\]$"),
    (["[0]=3"], None, r"set a list whole, e\.g\. --set conserve=\[angular_momentum,lrl_y\]$"),
    ([], "x[0]", r": \(top level\): key 'x\[0\]': no config key has brackets; remove it"),
])
def test_keys_with_brackets_are_config_errors(overrides, top_key, match):
    data = kepler_data()
    if top_key:
        data[top_key] = 1
    with pytest.raises(ConfigError, match=match) as info:
        load_run_from_dict(data, source="k.yaml", overrides=overrides)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("name, key, text", [("gauss", "method.k", "does not apply: gauss(s) takes no k"),
                                               ("elim", "method.r", "is missing; elim(r, k, s) needs r, k, s")])
def test_a_method_parameter_error_names_the_set_of_the_method_it_comes_from(name, key, text):
    """A user trial: --set method.name=gauss was told only 'k.yaml:N: method.k: does not apply ...
    remove it', pointing at the file's k, which the --set had made wrong."""
    err = config_error(kepler_data(), overrides=[f"method.name={name}"])
    assert err.key == key and text in str(err) and str(err).endswith(f"(with --set method.name={name})"), str(err)


@pytest.mark.parametrize("h", ["1e-30", "0.0999"])
def test_a_step_count_error_names_the_set_of_h_it_comes_from(h):
    # the rule is t_end's (the file's line), the value at fault h's: both are named
    err = config_error(kepler_data(), overrides=[f"integration.h={h}"])
    assert err.key == "integration.t_end" and str(err).endswith(f"(with --set integration.h={h})")


def test_resolved_config_holds_evaluated_numbers_and_all_defaults():
    data = expressions_data()
    data["integration"] = {"h": "pi/30", "n_steps": 60}
    spec = load_run_from_dict(data)
    resolved = spec.resolved
    assert resolved["integration"] == {"h": math.pi / 30, "t0": 0.0, "t_end": 60 * (math.pi / 30), "n_steps": 60}
    assert resolved["problem"]["initial"] == {"q1": 0.4, "q2": 0.0, "p1": 0.0, "p2": math.sqrt(1.6 / 0.4)}
    assert resolved["method"] == {"name": "ehbvm", "k": 12, "s": 3}
    assert resolved["solver"] == {"method": "newton", "tol": 2.0 ** -52, "max_iter": 30, "max_halvings": 4,
                                  "predictor": True, "warm_start": True, "rhs": "stable", "accelerate": True,
                                  "lim_metric": "euclidean", "kernel": "shared"}
    yaml.safe_dump(resolved)


def test_the_resolved_config_records_the_solver_that_auto_chose():
    """solver.method 'auto' (the default) is resolved per problem, and the resolved config (stored in
    the output, compared by --resume) holds the choice: simplified Newton up to 48 state components,
    the fixed point above; an explicit choice is kept."""
    def chain(masses, **solver):
        data = {"problem": {"builtin": "fpu_beta", "parameters": {"n": masses}},
                "method": {"name": "hbvm", "k": 6, "s": 3}, "integration": {"h": 0.05, "n_steps": 5}}
        if solver:
            data["solver"] = solver
        return load_run_from_dict(data)
    assert chain(24).resolved["solver"]["method"] == "newton"          # n = 48
    assert chain(25).resolved["solver"]["method"] == "fixed_point"     # n = 50
    assert chain(25, method="auto").solver.method == "fixed_point"
    assert chain(25, method="newton").resolved["solver"]["method"] == "newton"
    assert chain(24, method="fixed_point").resolved["solver"]["method"] == "fixed_point"


def test_builtin_parameters_and_initial_overrides():
    data = {"problem": {"builtin": "fpu_beta", "parameters": {"n": "2*3", "beta": "1/2", "boundary": "fixed"},
                        "initial": {"q1": "0.1*pi"}},
            "method": {"name": "hbvm", "k": 6, "s": 3}, "integration": {"h": 0.1, "n_steps": 5}}
    spec = load_run_from_dict(data)
    assert spec.problem.parameters == {"n": 6, "beta": 0.5, "boundary": "fixed"}
    assert spec.problem.y0[0] == 0.1 * math.pi
    assert spec.problem.y0[1] == problems.fpu_beta(6, 0.5, "fixed").y0[1]
    data["problem"]["initial"] = {"q1": "1 - beta"}      # initial values may use the parameters
    assert load_run_from_dict(data).problem.y0[0] == 0.5


# --- one-line errors ----------------------------------------------------------------------

def _set(path, value):
    def change(data):
        node = data
        for part in path[:-1]:
            node = node.setdefault(part, {})
        if value is DELETE:
            node.pop(path[-1], None)
        else:
            node[path[-1]] = value
        return data
    return change


DELETE = object()

BAD = [
    ("unknown top key", _set(("metod",), {"name": "gauss"}), "metod", r"unknown key; did you mean 'method'"),
    ("unknown nested key", _set(("integration", "t_ned"), 5), "integration.t_ned", "did you mean 't_end'"),
    ("missing section", _set(("method",), DELETE), "method", "missing; add e.g. method:"),
    ("missing h", _set(("integration", "h"), DELETE), "integration.h", "missing; give the step size"),
    ("h wrong type", _set(("integration", "h"), [0.1]), "integration.h", "must be a number"),
    ("h bad expression", _set(("integration", "h"), "pi/"), "integration.h", "not a valid expression"),
    ("h negative", _set(("integration", "h"), "-pi/30"), "integration.h", "must be > 0"),
    ("t_end not whole steps", _set(("integration", "h"), 0.3), "integration.t_end", "not a whole number of steps"),
    # a user trial looked for backward runs here
    ("t_end before t0", _set(("integration", "t0"), 2000), "integration.t_end",
     r"must be after t0 .*; runs go forward in time \(a backward one: elimfast.integrate\(..., backward=True\)"),
    ("no t_end nor n_steps", _set(("integration", "t_end"), DELETE), "integration.t_end", "is missing; give t_end"),
    ("n_steps not integer", _set(("integration", "n_steps"), 10.5), "integration.n_steps", "whole number"),
    ("method unknown", _set(("method", "name"), "ehbmv"), "method.name", "did you mean 'ehbvm'"),
    ("method k < s", _set(("method", "k"), 2), "method.k", "must be >= s = 3"),
    ("method r < s", lambda d: {**d, "method": {"name": "elim", "r": 2, "k": 12, "s": 3}}, "method.r",
     "must be >= s = 3 .*got 2; raise r"),
    ("method s missing", _set(("method", "s"), DELETE), "method.s", r"ehbvm\(k, s\) needs k, s"),
    # a user trial: without h or rtol the missing k was named, whose fix (rtol makes k = 2s) was rtol's
    ("h and k missing", lambda d: _set(("method", "k"), DELETE)(_set(("integration", "h"), DELETE)(d)),
     "integration.h", "missing; give the step size, e.g. h: pi/30, or rtol: 1e-12 for adaptive steps"),
    ("method extra r", _set(("method", "r"), 12), "method.r", "takes no r"),
    # a user trial made an adaptive config without k fixed-step: "is missing; ... needs k, s" said not why
    ("k missing, fixed steps", _set(("method", "k"), DELETE), "method.k",
     r"is missing; ehbvm\(k, s\) needs k: k = 2s is the default of adaptive runs only .* \(e\.g\. k: 6\)"),
    # a user trial: s = -2 of an adaptive run without k was reported as "method.k: must be >= 1, got -4"
    ("adaptive s negative", lambda d: {**d, "method": {"name": "ehbvm", "s": -2},
                                       "integration": {"rtol": 1e-10, "t_end": 1}}, "method.s", "must be >= 1, got -2"),
    ("method k too large", _set(("method", "k"), 65), "method.k", "must be <= 64"),
    # a user trial: GAUSS(64) was refused as "--n must be <= 64 ..., got 65" (the predictor's s + 1 nodes)
    ("method s too large", lambda d: {**d, "method": {"name": "gauss", "s": 64}, "conserve": []}, "method.s",
     r"must be <= 63 \(the predictor's s \+ 1 Gauss-Legendre nodes are verified up to 64\), got 64"),
    ("method k bool", _set(("method", "k"), True), "method.k", "whole number"),
    ("s not above nu", _set(("method", "s"), 2), "method.s", r"at most s - 1 = 1.* raise s to 3"),
    ("conserve unknown", _set(("conserve",), ["angular_momentum", "lrl_z"]), "conserve[1]",
     "no invariant 'lrl_z'; did you mean 'lrl_y'"),
    ("conserve H", _set(("conserve",), ["H"]), "conserve[0]", "always conserved"),
    ("conserve twice", _set(("conserve",), ["lrl_y", "lrl_y"]), "conserve[1]", "twice"),
    ("conserve with gauss", lambda d: {**d, "method": {"name": "gauss", "s": 3}}, "conserve",
     "imposes no invariant .it keeps quadratic ones by itself"),
    ("conserve not names", _set(("conserve",), [1, 2]), "conserve[0]", "must be a string"),
    ("builtin unknown", _set(("problem", "builtin"), "keplr"), "problem.builtin", "did you mean 'kepler'"),
    ("builtin parameter unknown", _set(("problem", "parameters"), {"eccentricty": 0.5}),
     "problem.parameters.eccentricty", "did you mean 'eccentricity'"),
    ("builtin parameter rejected", _set(("problem", "parameters"), {"eccentricity": 1.5}),
     "problem.parameters.eccentricity", r"must be in \[0, 1\)"),
    ("initial unknown coordinate", _set(("problem", "initial"), {"q3": 1.0}), "problem.initial.q3",
     "no coordinate 'q3'"),
    ("initial bad value", _set(("problem", "initial"), {"q1": "sqrt(-1)"}), "problem.initial.q1", "not defined"),
    ("no problem kind", _set(("problem",), {"parameters": {}}), "problem", "no problem given"),
    ("two problem kinds", _set(("problem", "python"), "x.py"), "problem", "give only one of builtin, python"),
    ("check not bool", _set(("problem", "check"), "yes please"), "problem.check", "true or false"),
    ("rhs literal only", _set(("solver", "rhs"), "fancy"), "solver.rhs", "'stable' or 'literal'"),
    ("tol negative", _set(("solver", "tol"), -1), "solver.tol", "must be >= 0"),
    ("max_iter zero", _set(("solver", "max_iter"), 0), "solver.max_iter", "must be >= 1"),
    ("solver unknown", _set(("solver", "method"), "newtn"), "solver.method", r"must be auto \(the default: simplified Newton up to 48 state components, the fixed point above\), newton or fixed_point"),
    ("halvings too many", _set(("solver", "max_halvings"), 64), "solver.max_halvings", "must be <= 20"),
    ("every zero", _set(("output", "every"), 0), "output.every", "must be >= 1"),
    ("section not mapping", _set(("solver",), "fast"), "solver", "must be a mapping"),
    ("boolean key", _set(("problem", "initial"), {True: 1.0}), "problem.initial.True", "quote the key"),
    ("missing python file", lambda d: {**d, "problem": {"python": "no_such_file.py"}}, "problem.python",
     "does not exist"),
]


@pytest.mark.parametrize("label,change,key,match", BAD, ids=[b[0] for b in BAD])
def test_each_fault_is_one_line_naming_file_key_and_fix(label, change, key, match):
    err = config_error(change(kepler_data()))
    assert err.key == key, str(err)
    assert str(err).startswith(f"run.yaml: {key}: "), str(err)
    assert __import__("re").search(match, str(err)), str(err)


EXPRESSION_BAD = [
    ("unknown name", ("hamiltonian",), "p1**2/2 - mu/sqrt(q1**2 + q3**2)", "problem.hamiltonian",
     "unknown name 'q3'"),
    ("syntax", ("hamiltonian",), "p1**2/2 +", "problem.hamiltonian", "not a valid expression"),
    ("invariant bad", ("invariants", "lrl_y"), "p1.real", "problem.invariants.lrl_y", "attribute access"),
    ("misprinted LRL", ("invariants", "lrl_y"), "p1*(q1*p2 - q2*p1) - q2/sqrt(q1**2 + q2**2)",
     "problem.invariants.lrl_y", r"not conserved by the flow of H: .* = [0-9.]+e-0[0-9]"),
    ("missing initial", ("initial", "p2"), DELETE, "problem.initial", "no initial value for p2"),
    ("initial unknown", ("initial", "q3"), 0.0, "problem.initial.q3", "not a coordinate"),
    ("unequal coordinates", ("coordinates", "p"), ["p1"], "problem.coordinates", "2 q names but 1 p names"),
    ("reserved name", ("coordinates", "q"), ["q1", "pi"], "problem.coordinates.q", "reserved"),
    ("parameter junk", ("parameters", "mu"), "1 +", "problem.parameters.mu", "not a valid expression"),
    ("missing hamiltonian", ("hamiltonian",), DELETE, "problem.hamiltonian", "missing"),
    ("invariant named H", ("invariants", "H"), "q1", "problem.invariants", "not 'H'"),
    # a user trial: an invariant 'y' replaced the state in Result.to_xarray; 't' made xarray fail
    ("invariant named y", ("invariants", "y"), "q1*p2 - q2*p1", "problem.invariants",
     "invariant name 'y' is taken by other data of a run"),
    ("invariant named t", ("invariants", "t"), "q1*p2 - q2*p1", "problem.invariants",
     "invariant name 't' is taken by other data of a run"),
]


@pytest.mark.parametrize("label,path,value,key,match", EXPRESSION_BAD, ids=[b[0] for b in EXPRESSION_BAD])
def test_expression_problem_faults(label, path, value, key, match):
    data = _set(("problem",) + path, value)(expressions_data())
    err = config_error(data)
    assert err.key == key, str(err)
    assert __import__("re").search(match, str(err)), str(err)


def test_a_misspelt_parameter_by_set_is_refused_and_one_an_event_or_time_scale_uses_is_not():
    """A user trial: --set problem.parameters.eccc=0.7 on a problem by expressions added a parameter
    that no expression uses, and the run went on with the config's ecc. The refusal reads every
    expression a parameter can appear in: the time scale and the events too."""
    err = config_error(expressions_data(), overrides=["problem.parameters.eccc=0.7"])
    assert err.key == "problem.parameters.eccc", str(err)
    assert re.search("no expression uses it .*did you mean 'ecc'", str(err)), str(err)
    data = expressions_data()
    data["problem"]["time_scale"] = "(q1**2 + q2**2)**w"
    data["events"] = {"crossing": {"expression": "q1**2 + q2**2 - r0**2"}}
    data["integration"] = {"rtol": 1e-10, "t_end": 10}
    spec = load_run_from_dict(data, overrides=["problem.parameters.w=0.75", "problem.parameters.r0=0.5"])
    assert spec.problem.parameters["r0"] == 0.5
    del data["events"]
    with pytest.raises(ConfigError, match="problem.parameters.r0: no expression uses it"):
        load_run_from_dict(data, overrides=["problem.parameters.w=0.75", "problem.parameters.r0=0.5"])


# --- errors name the line of the key --------------------------------------------------------

LINED = """\
problem:
  builtin: kepler
  parameters:
    eccentricity: 0.6
conserve:
  - angular_momentum
  - lrl_y
method:
  name: ehbvm
  k: 12
  s: 3
integration:
  h: 0.1
  t_end: 100
output:
  every: 10
"""
EVENTS = """\
events:
  pericentre:
    expression: "q1*p1 + q2*p2"
    directoin: 1
"""
TIMES = """\
  times:
    - 0.5
    - x
"""


def _edit(line, text):
    """LINED with its line ``line`` (1-based) replaced by text (None: deleted)."""
    def change(config):
        rows = config.splitlines(keepends=True)
        rows[line - 1:line] = [] if text is None else [text + "\n"]
        return "".join(rows)
    return change


LINE_FAULTS = [
    # label, the change to LINED, the key, its line (None: no line), what the message says
    ("unknown key two levels down", lambda c: c + EVENTS, "events.pericentre.directoin", 20, "unknown key"),
    ("wrong type", _edit(13, "  h: [0.1]"), "integration.h", 13, "must be a number .*, got list"),
    ("wrong type in a nested mapping", _edit(4, "    eccentricity: {a: 1}"), "problem.parameters.eccentricity", 4,
     "must be a number .*, got dict"),
    ("bad list item (library)", _edit(7, "  - lrl_z"), "conserve[1]", 7, "no invariant 'lrl_z'"),
    ("bad list item (schema)", _edit(6, "  - [angular_momentum]"), "conserve[0]", 6, "must be a string"),
    ("bad value", _edit(11, "  s: 2"), "method.s", 11, "raise s to 3"),
    ("unknown built-in", _edit(2, "  builtin: keplr"), "problem.builtin", 2, "did you mean 'kepler'"),
    ("key not a string", _edit(4, "    yes: 0.6"), "problem.parameters.True", 4, "quote the key"),
    ("missing key: its section's line", _edit(13, None), "integration.h", 12, "missing; give the step size"),
    ("missing section: no line", lambda c: c.replace("method:\n  name: ehbvm\n  k: 12\n  s: 3\n", ""), "method",
     None, "missing; add e.g. method:"),
    ("misspelt section: the unknown key before the missing one", _edit(8, "methd:"), "methd", 8,
     "unknown key; did you mean 'method'"),
    ("abbreviated key", lambda c: c + EVENTS.replace("directoin", "dir"), "events.pericentre.dir", 20,
     "unknown key; did you mean 'direction'"),
]


@pytest.mark.parametrize("label,change,key,line,match", LINE_FAULTS, ids=[f[0] for f in LINE_FAULTS])
def test_errors_name_the_line_of_the_key(tmp_path, label, change, key, line, match):
    path = write(tmp_path, change(LINED))
    with pytest.raises(ConfigError) as info:
        load_run(path)
    message, where = str(info.value), str(path) if line is None else f"{path}:{line}"
    assert message.startswith(f"{where}: {key}: "), message
    assert re.search(match, message) and "\n" not in message, message
    assert info.value.line == line and info.value.key == key
    if line is not None:    # the line named holds the key (a list item, or for a missing key its section)
        named = path.read_text().splitlines()[line - 1].strip()
        last = info.value.key.split(".")[-1]
        expected = "- " if last.endswith("]") else "yes:" if last == "True" else f"{last}:"
        if label.startswith("missing key"):
            expected = "integration:"
        assert named.startswith(expected), named


def test_a_misspelt_section_is_reported_before_the_section_it_leaves_missing(tmp_path):
    with pytest.raises(ConfigError) as info:
        load_run(write(tmp_path, _edit(8, "methd:")(LINED)))
    assert [m.split(": ", 1)[1] for m in info.value.messages] == [
        "methd: unknown key; did you mean 'method'? (allowed here: problem, conserve, method, integration, solver, "
        "output, events)", "method: missing; add e.g. method: {name: ehbvm, k: 12, s: 3}"]


@pytest.mark.parametrize("change,line,message", [
    (lambda c: c + "integration:\n  h: 0.2\n  t_end: 10\n", 17,
     "duplicate key 'integration' at the top level (first at line 12)"),
    (_edit(11, "  s: 3\n  s: 4"), 12, "duplicate key 's' in method (first at line 11)"),
    (_edit(4, "    eccentricity: 0.6\n    eccentricity: 0.7"), 5,
     "duplicate key 'eccentricity' in problem.parameters (first at line 4)"),
    (lambda c: c.replace("method:\n  name: ehbvm\n  k: 12\n  s: 3", "method: {name: ehbvm, k: 12, s: 3, s: 4}"), 8,
     "duplicate key 's' in method (first at column 30 of this line)"),
], ids=["section", "key", "nested key", "flow mapping"])
def test_a_key_given_twice_is_refused_naming_both_places(tmp_path, change, line, message):
    """YAML loaders keep the last of two equal keys silently: two integration sections ran the
    second, and s: 3, s: 4 ran s = 4."""
    path = write(tmp_path, change(LINED))
    with pytest.raises(ConfigError) as info:
        load_run(path)
    assert str(info.value) == f"{path}:{line}: {message}; keep one of them"
    assert info.value.line == line


def test_a_sweep_file_given_as_a_run_config_says_to_use_sweep(tmp_path):
    path = write(tmp_path, "base: kepler.yaml\ngrid:\n  - {name: h, key: integration.h, values: [0.1]}\n")
    with pytest.raises(ConfigError) as info:
        load_run(path)
    assert str(info.value) == (f"{path}: a sweep file (it has base: and no problem:), not a run config; run it with "
                               f"elimfast sweep {path}")


def test_every_schema_error_of_a_file_names_a_line(tmp_path):
    text = LINED.replace("  k: 12", "  k: twelve").replace("  every: 10", "  every: 10\n  evry: 3") + TIMES + EVENTS
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as info:
        load_run(path)
    found = {re.match(rf"{re.escape(str(path))}:(\d+): (.+?): ", m).groups() for m in info.value.messages}
    # output.times is a mapping or a list: pydantic reports both readings (and named the member in the
    # key, output.times.TimesSection, which is no key of a config)
    assert found == {("10", "method.k"), ("17", "output.evry"), ("18", "output.times"), ("20", "output.times[1]"),
                     ("24", "events.pericentre.directoin")}, info.value.messages


@pytest.mark.parametrize("times,key,match", [
    ({"step": 0.5}, "output.times.start", "missing"),
    ({"start": 0, "stop": 10, "stepp": 1}, "output.times.stepp", r"unknown key; did you mean 'step'\?"),
    ([0.5, "x"], "output.times[1]", r"'x' is not a number"),
    ([0.5, float("nan")], "output.times[1]", "must be finite"),
    ({"start": 5, "stop": 1, "step": 1}, "output.times", r"stop 1(\.0)? is before start 5(\.0)?; give stop >= start$"),
    # a user trial: it gave [0] alone, silently
    ({"start": 0, "stop": 10, "n": 1}, "output.times", r"n = 1 gives start alone .* times: \[10(\.0)?\]$"),
    ({"start": 0, "stop": 100, "step": 200}, "output.times", r"step 200(\.0)? is longer than stop - start = 100(\.0)?: "
                                                           "it gives start alone"),
    # a user trial: "gives 1000000000002 times", one more than start to stop gives
    ({"start": 0, "stop": 1000, "step": 1e-9}, "output.times", r"gives 1e\+12 times; at most 10,000,000: give a "
                                                              "larger step"),
], ids=["missing start", "misspelt step", "list item not a number", "list item nan", "stop before start", "n = 1",
        "step > span", "too many"])
def test_output_times_errors_name_the_key_as_written_in_the_config(tmp_path, times, key, match):
    """A mapping of output.times was reported as output.times.TimesSection.start, the name
    of pydantic's model in the key path, and a misspelt key in it as 'unknown key; remove it';
    a list with an item that is no number as 'output.times: must be a mapping (key: value)'."""
    path = write(tmp_path, LINED + "  times: " + json.dumps(times).replace("NaN", ".nan") + "\n")
    with pytest.raises(ConfigError) as info:
        load_run(path)
    assert info.value.key == key and re.search(match, str(info.value)), str(info.value)
    assert "TimesSection" not in str(info.value) and "\n" not in str(info.value)


def test_output_every_with_output_times_is_refused_not_ignored(tmp_path):
    """The samples are the output times; output.every was silently ignored beside them."""
    path = write(tmp_path, LINED.replace("every: 10", "every: 5") + "  times: {start: 0, stop: 10, step: 1}\n")
    with pytest.raises(ConfigError) as info:
        load_run(path)
    assert info.value.key == "output.every", str(info.value)
    assert re.search(r":\d+: output\.every: does not apply with output times .*remove one of the two, or make "
                     r"it 1 \(got 5\)$", str(info.value)), str(info.value)
    load_run(write(tmp_path, LINED.replace("every: 10", "every: 1") + "  times: {start: 0, stop: 10, step: 1}\n"))
    with pytest.raises(elimfast.errors.ParameterError, match="store_every does not apply with output times"):
        elimfast.integrate(problems.kepler(0.6), elimfast.methods.ehbvm(8, 4), h=0.1, t_end=1.0, t_eval=[0.5],
                           store_every=5)


def test_an_override_error_names_the_set_option_not_a_line(tmp_path):
    path = write(tmp_path, LINED)
    cases = [
        (["method.k=[12]"], "method.k", "must be a number", "method.k=[12]"),
        (["method={name: ehbvm, k: 12, s: x}"], "method.s", "'x' is not a number",
         "method={name: ehbvm, k: 12, s: x}"),
        # the later override of the section replaces the earlier one of its key
        (["method.s=4", "method={name: ehbvm, k: 12, s: 1}"], "method.s", "raise s to 3",
         "method={name: ehbvm, k: 12, s: 1}"),
        (["solver.max_iter=0"], "solver.max_iter", "must be >= 1", "solver.max_iter=0"),   # no solver in the file
    ]
    for overrides, key, match, item in cases:
        with pytest.raises(ConfigError) as info:
            load_run(path, overrides=overrides)
        message = str(info.value)
        assert message.startswith(f"{path}: {key}: ") and match in message, message
        assert message.endswith(f"(value from --set {item})") and info.value.line is None, message
    # A built-in's parameter refused by its constructor: at its own key (it was "problem.parameters:
    # kepler: ..." at the section's line, and a list "float() argument must be ... not 'list'")
    with pytest.raises(ConfigError) as info:
        load_run(path, overrides=["problem.parameters.eccentricity=1.5"])
    assert str(info.value) == (f"{path}: problem.parameters.eccentricity: must be in [0, 1) for a periodic orbit, "
                               "got 1.5 (value from --set problem.parameters.eccentricity=1.5)")
    with pytest.raises(ConfigError) as info:
        load_run(path, overrides=["problem.parameters.eccentricity=[0.5]"])
    assert str(info.value).startswith(f"{path}: problem.parameters.eccentricity: must be a number, got [0.5]")
    # A key below the error set by --set: the file's line, and the option;
    # several below it: each is named (the error may come from any: here stop; a user trial saw only start)
    adaptive = CONFIGS / "kepler_adaptive.yaml"
    with pytest.raises(ConfigError) as info:
        load_run(adaptive, overrides=["output.every=1", "output.times.start=0", "output.times.stop=2000",
                                      "output.times.step=1"])
    assert str(info.value).endswith("(with --set output.times.start=0, --set output.times.stop=2000, "
                                    "--set output.times.step=1)")
    # s too small for a conserve given by --set: the file's method.s line, and the option that caused it
    with pytest.raises(ConfigError) as info:
        load_run(CONFIGS / "kepler.yaml", overrides=["conserve=[angular_momentum,lrl_x,lrl_y]"])
    assert "method.s: must be >= 4 to impose 3 invariant(s)" in str(info.value)
    assert str(info.value).endswith("(with --set conserve=[angular_momentum,lrl_x,lrl_y])"), str(info.value)
    # An override elsewhere leaves the file's lines in place
    with pytest.raises(ConfigError) as info:
        load_run(write(tmp_path, LINED.replace("  h: 0.1", "  h: [0.1]")), overrides=["method.k=8"])
    assert str(info.value).startswith(f"{path}:13: integration.h: must be a number")


def test_cached_validations_load_and_their_errors_keep_the_line(tmp_path, monkeypatch):
    """config.load_run keeps validations in <cache>/configs, keyed by the data: a config run
    again loads from there, a changed file validates again, and the lines (not cached) follow
    the file as it is now."""
    from elimfast import config as config_module
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(tmp_path / "cache"))
    hits = []
    read = config_module._read_validated
    monkeypatch.setattr(config_module, "_read_validated", lambda key: hits.append(read(key)) or hits[-1])
    stored = lambda: sorted(p.name for p in (tmp_path / "cache" / "configs").iterdir())  # noqa: E731

    path = write(tmp_path, LINED)
    first = load_run(path)
    again = load_run(path)
    assert hits[0] is None and hits[1] is not None and len(stored()) == 1
    assert again.resolved == first.resolved and again.method.name == "EHBVM(12,3)"
    path.write_text(LINED.replace("  s: 3", "  s: 4"))
    changed = load_run(path)
    assert hits[2] is None and len(stored()) == 2 and changed.method.name == "EHBVM(12,4)"

    # A schema-valid file the builder refuses: its validation is cached, its line is not
    path.write_text(LINED.replace("  builtin: kepler", "  builtin: keplr"))
    for _ in range(2):
        with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}:2: problem.builtin: unknown problem"):
            load_run(path)
    assert hits[-2] is None and hits[-1] is not None
    path.write_text("# moved down\n\n" + LINED.replace("  builtin: kepler", "  builtin: keplr"))
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}:4: problem.builtin: unknown problem"):
        load_run(path)
    assert hits[-1] is not None and len(stored()) == 3


def test_yaml_lines_come_from_the_safe_loader():
    from elimfast.config import parse_yaml_with_lines
    data, lines = parse_yaml_with_lines("a:\n  b: [1,\n     2]\n  c:\n    - {d: 1}\n<<: {e: 3}\n", "x.yaml")
    assert data == {"a": {"b": [1, 2], "c": [{"d": 1}]}, "e": 3}
    assert lines == {("a",): 1, ("a", "b"): 2, ("a", "b", 0): 2, ("a", "b", 1): 3, ("a", "c"): 4,
                     ("a", "c", 0): 5, ("a", "c", 0, "d"): 5, ("e",): 6}
    with pytest.raises(ConfigError, match="x.yaml: .*invalid YAML .*python/name"):
        parse_yaml_with_lines("a: !!python/name:os.system\n", "x.yaml")


def test_check_false_lets_a_wrong_invariant_through():
    data = expressions_data()
    data["problem"]["invariants"]["lrl_y"] = "p1*(q1*p2 - q2*p1) - q2/sqrt(q1**2 + q2**2)"
    data["problem"]["check"] = False
    spec = load_run_from_dict(data)
    assert spec.resolved["problem"]["check"] is False


# --- files and YAML -----------------------------------------------------------------------

def write(tmp_path, text, name="run.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("text,match", [
    ("problem: {builtin: kepler\nmethod: x", r"line \d+, column \d+: invalid YAML"),
    ("problem:\n  builtin: kepler\n   method: 3\n", r"line 3, column \d+: invalid YAML"),
    ("", "the file is empty"),
    ("- a\n- b\n", "must be a mapping of sections"),
    ("a: &x [1]\nb: *x\n", "aliases .* not supported"),
    ("problem: !!python/object/apply:os.system ['true']\n", "invalid YAML .*python/object/apply"),
    ("problem: !!python/name:os.system\n", "invalid YAML"),
    ("problem: !custom 3\n", "invalid YAML"),
    # a user trial: an integer of 5000 digits gave an internal error (Python's int conversion limit)
    ("problem: kepler\nintegration: {h: 1" + "0" * 5000 + ", t_end: 1}\n", "a whole number of more than 4300 digits"),
])
def test_yaml_faults_are_config_errors_with_line_numbers(tmp_path, text, match):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=match) as info:
        load_run(path)
    assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)


def test_file_faults_are_config_errors(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_run(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="is a directory"):
        load_run(tmp_path)
    (tmp_path / "binary.yaml").write_bytes(b"\xff\xfe\x00junk")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_run(tmp_path / "binary.yaml")
    with pytest.raises(ConfigError, match="expected KEY=VALUE"):
        load_run(CONFIGS / "kepler.yaml", overrides=["method.s"])
    with pytest.raises(ConfigError, match="invalid YAML"):
        load_run(CONFIGS / "kepler.yaml", overrides=["method.s=[1"])


@pytest.mark.usefixtures("allow_python")
def test_python_problem_path_is_relative_to_the_config(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "problem.py").write_text((CONFIGS / "kepler_problem.py").read_text())
    path = write(tmp_path / "sub", "problem: {python: problem.py, parameters: {mu: 2}, initial: {p2: sqrt(2*mu)}}\n"
                                   "method: {name: gauss, s: 2}\nintegration: {h: 0.1, n_steps: 3}\n")
    spec = load_run(path)
    assert spec.problem.name == "kepler_python" and list(spec.problem.params) == [2.0]
    assert spec.problem.y0[3] == 2.0
    assert spec.resolved["problem"]["python"] == str(tmp_path / "sub" / "problem.py")


# --- nothing runs -------------------------------------------------------------------------

def malicious_configs(target):
    command = f"__import__('os').system('touch {target}')"
    expressions = expressions_data()
    yield "hamiltonian", _set(("problem", "hamiltonian"), command)(copy.deepcopy(expressions))
    yield "invariant", _set(("problem", "invariants", "lrl_y"), command)(copy.deepcopy(expressions))
    yield "parameter", _set(("problem", "parameters", "mu"), command)(copy.deepcopy(expressions))
    yield "initial", _set(("problem", "initial", "q1"), command)(copy.deepcopy(expressions))
    yield "h", _set(("integration", "h"), command)(kepler_data())
    yield "builtin parameter", _set(("problem", "parameters", "eccentricity"), command)(kepler_data())
    yield "method k", _set(("method", "k"), command)(kepler_data())
    yield "dunder", _set(("problem", "hamiltonian"), "q1.__class__.__base__.__subclasses__()")(
        copy.deepcopy(expressions))
    yield "lambda", _set(("problem", "hamiltonian"), f"(lambda: {command})()")(copy.deepcopy(expressions))
    yield "builtins", _set(("problem", "hamiltonian"), "__builtins__")(copy.deepcopy(expressions))
    yield "coordinate name", _set(("problem", "coordinates", "q"), ["q1", "__import__"])(copy.deepcopy(expressions))


def test_malicious_configs_are_rejected_and_have_no_effect(tmp_path):
    target = tmp_path / "owned"
    for label, data in malicious_configs(target):
        err = config_error(data)
        assert err.key and err.key != "(top level)", label
    yaml_text = f"problem: !!python/object/apply:os.system ['touch {target}']\n"
    with pytest.raises(ConfigError):
        load_run(write(tmp_path, yaml_text))
    with pytest.raises(ConfigError):
        load_run(CONFIGS / "kepler.yaml", overrides=[f"problem=!!python/object/apply:os.system ['touch {target}']"])
    assert not target.exists()


# --- junk: only ConfigError ----------------------------------------------------------------

KEYS = ["problem", "method", "integration", "solver", "output", "conserve", "builtin", "python", "coordinates",
        "hamiltonian", "invariants", "parameters", "initial", "check", "name", "k", "s", "r", "h", "t_end",
        "n_steps", "t0", "tol", "max_iter", "max_halvings", "predictor", "rhs", "warm_start", "path", "every", "q",
        "p", "eccentricity",
        "q1", "p2", "junk"]
SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(-5, 100), st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["kepler", "ehbvm", "gauss", "lim", "stable", "pi/30", "1e-15", "q1*p2", "__import__('os')",
                     "sqrt(-1)", "1/0", "angular_momentum", "lrl_y", "toda", "nbody", "q1", "x.py", "p1**2/2",
                     "", "10**10**10", "(((", "pendulum"]),
    st.text(max_size=12),
)
JUNK = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                   st.dictionaries(st.sampled_from(KEYS), inner, max_size=5)),
                    max_leaves=20)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(st.sampled_from(KEYS), JUNK, max_size=7))
@bounded_example
def test_junk_configs_raise_only_config_errors(data):
    try:
        load_run_from_dict(data, source="junk.yaml")
    except ConfigError as err:
        assert "\n" not in str(err) and str(err).startswith("junk.yaml: ")


SECTIONS = {
    "problem": st.fixed_dictionaries({"builtin": st.sampled_from(["kepler", "pendulum", "toda", "keplr"])},
                                     optional={"parameters": st.dictionaries(st.sampled_from(["eccentricity", "n",
                                                                                              "omega", "x"]),
                                                                             SCALARS, max_size=2),
                                               "initial": st.dictionaries(st.sampled_from(["q1", "q", "p2", "x"]),
                                                                          SCALARS, max_size=2),
                                               "check": SCALARS}),
    "method": st.fixed_dictionaries({"name": st.sampled_from(["gauss", "hbvm", "ehbvm", "elim", "lim", "ghbvm"])},
                                    optional={"k": SCALARS, "s": SCALARS, "r": SCALARS}),
    "integration": st.fixed_dictionaries({"h": SCALARS}, optional={"t_end": SCALARS, "n_steps": SCALARS,
                                                                     "t0": SCALARS}),
    "conserve": st.lists(st.sampled_from(["angular_momentum", "lrl_x", "lrl_y", "trace_L3", "H", "x"]), max_size=3),
}


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.fixed_dictionaries(SECTIONS))
@bounded_example
def test_nearly_valid_configs_raise_only_config_errors(data):
    try:
        spec = load_run_from_dict(data, source="near.yaml")
    except ConfigError as err:
        assert "\n" not in str(err) and str(err).startswith("near.yaml: ")
    else:
        assert spec.n_steps >= 1 and spec.h > 0


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.text(max_size=200))
@bounded_example
def test_junk_yaml_text_raises_only_config_errors(text):
    from elimfast.config import parse_yaml
    try:
        data = parse_yaml(text, "junk.yaml")
        load_run_from_dict(data, source="junk.yaml")
    except ConfigError as err:
        assert "\n" not in str(err)


def test_config_error_is_an_elimfast_error():
    assert issubclass(ConfigError, elimfast.ElimfastError)


def test_an_event_may_be_given_by_its_expression_alone_as_in_python():
    """events: {peri: "q1*p1 + q2*p2"} said only 'must be a mapping', though
    elimfast.integrate(events={"peri": "q1*p1 + q2*p2"}) takes it (a user trial's finding)."""
    from elimfast.config import load_run_from_dict
    base = {"problem": {"builtin": "kepler"}, "method": {"name": "ehbvm", "s": 4},
            "integration": {"rtol": 1e-10, "t_end": 1}}
    short = load_run_from_dict({**base, "events": {"peri": "q1*p1 + q2*p2"}}, source="run.yaml")
    full = load_run_from_dict({**base, "events": {"peri": {"expression": "q1*p1 + q2*p2"}}}, source="run.yaml")
    assert short.events == full.events == {"peri": {"expression": "q1*p1 + q2*p2", "direction": 0, "terminal": False}}


def test_epsilon_or_atol_without_rtol_is_named_with_its_set_not_told_rtol_is_needed(tmp_path):
    """A user trial: --set integration.epsilon=0.1 (and --set integration.atol=1e-10) on the
    fixed-step configs/kepler.yaml said 'configs/kepler.yaml:9: integration.rtol: is needed for
    error-controlled steps', naming neither the key given nor the --set. epsilon alone meant
    the time-reversible steps, and is told how to ask for them (as elimfast.integrate said);
    atol alone is told that it needs rtol; each names its --set, or its line in the file.
    --set integration.step_control=error alone is named at step_control, with its --set.
    StepControl states the rule once, for the config and the API."""
    from click.testing import CliRunner
    from elimfast.errors import ParameterError
    from elimfast_cli.main import cli
    kepler = str(CONFIGS / "kepler.yaml")
    for given, message in [
            ("integration.epsilon=0.1", "integration.epsilon: applies to time-reversible steps: add step_control = "
                                        "'time_scale', or give rtol instead for error-controlled steps (value from "
                                        "--set integration.epsilon=0.1)"),
            ("integration.atol=1e-10", "integration.atol: is given without rtol, which error-controlled steps need: "
                                       "add rtol, e.g. rtol = 1e-10 (value from --set integration.atol=1e-10)"),
            ("integration.step_control=error", "integration.step_control: asks for error-controlled steps, which need "
                                               "rtol: add rtol, e.g. rtol = 1e-10 (value from --set "
                                               "integration.step_control=error)")]:
        with pytest.raises(ConfigError) as caught:
            load_run(kepler, overrides=[given])
        assert str(caught.value) == f"{kepler}: {message}"
        result = CliRunner().invoke(cli, ["run", kepler, "-o", str(tmp_path / "x.h5"), "--set", given])
        assert result.exit_code == 2 and result.stderr == f"error: {kepler}: {message}\n", result.stderr
    # in the file: its line; with step_control: error given, epsilon is told where it belongs
    path = write(tmp_path, "problem: kepler\nmethod: {name: ehbvm, s: 4}\nintegration:\n  t_end: 1\n"
                           "  atol: 1e-10\n", "atol.yaml")
    with pytest.raises(ConfigError, match=r"atol.yaml:5: integration.atol: is given without rtol"):
        load_run(path)
    with pytest.raises(ConfigError, match=r"kepler.yaml: integration.epsilon: belongs to step_control = 'time_scale'"):
        load_run(kepler, overrides=["integration.step_control=error", "integration.epsilon=0.1"])
    with pytest.raises(ConfigError, match=r"kepler.yaml: integration.atol: belongs to step_control = 'error'"):
        load_run(kepler, overrides=["integration.step_control=time_scale", "integration.atol=1e-10"])
    with pytest.raises(ParameterError, match=r"^atol is given without rtol"):
        elimfast.integrate(problems.kepler(0.6), "EHBVM(8,4)", t_end=1.0, atol=1e-10)


# --- short forms: the paper's notation for methods, a built-in's name for problems ---------

@pytest.mark.parametrize("text,expected", [
    ("EHBVM(12,3)", {"name": "ehbvm", "k": 12, "s": 3}), ("gauss(4)", {"name": "gauss", "s": 4}),
    (" ELIM( 8, 12 , 3 ) ", {"name": "elim", "r": 8, "k": 12, "s": 3}), ("GHBVM(24,3)", {"name": "ghbvm", "k": 24, "s": 3}),
    ("ehbvm", None), ("EHBVM 12 3", None)])
def test_methods_are_read_in_the_papers_notation(text, expected):
    from elimfast.methods import from_notation
    assert from_notation(text) == expected


@pytest.mark.parametrize("text,message", [
    ("EHBVM(12)", "'EHBVM(12)': ehbvm(k, s) takes 2 whole numbers (k, s), e.g. EHBVM(12,3)"),
    ("HBVM(12,3.5)", "'HBVM(12,3.5)': hbvm(k, s) takes 2 whole numbers (k, s), e.g. HBVM(12,3)"),
    ("FOO(3)", "is not a known method: 'FOO'")])
def test_the_papers_notation_with_wrong_numbers_is_refused_by_name(text, message):
    from elimfast.errors import ParameterError
    from elimfast.methods import from_notation
    with pytest.raises(ParameterError) as caught:
        from_notation(text)
    assert caught.value.parameter == "name" and caught.value.detail.startswith(message), caught.value.detail


def test_a_config_may_name_its_method_as_the_paper_does_and_its_problem_by_name(tmp_path):
    """`method: EHBVM(12,3)` was refused ('must be a mapping'), and `method: {name: EHBVM(12,3)}`
    unquoted said 'method.3): unknown key' (YAML splits it at the comma inside {...})."""
    long = write(tmp_path, "problem: {builtin: kepler}\nmethod: {name: ehbvm, k: 12, s: 3}\n"
                           "conserve: [angular_momentum]\nintegration: {h: 0.1, t_end: 1}\n", "long.yaml")
    for short in ("problem: kepler\nmethod: EHBVM(12,3)\n", "problem: kepler\nmethod: {name: \"ehbvm(12, 3)\"}\n"):
        path = write(tmp_path, short + "conserve: [angular_momentum]\nintegration: {h: 0.1, t_end: 1}\n", "short.yaml")
        assert load_run(path).resolved == load_run(long).resolved
    assert load_run(long, overrides=["method=GHBVM(12,3)"]).method.name == "GHBVM(12,3)"
    for text, message in [
            ("problem: kepler\nmethod: {name: EHBVM(12,3)}\n",
             "short.yaml:2: method.name: 'EHBVM(12' is cut off: inside {...} YAML splits an unquoted EHBVM(12,3) at "
             "its comma; quote it"),
            ("problem: kepler\nmethod: {name: \"EHBVM(12,3)\", k: 12}\n",
             "short.yaml:2: method.k: give the method either as EHBVM(12,3) or by its name and parameters, not both"),
            ("problem: kepler\nmethod: EHBVM(12)\n", "short.yaml:2: method: 'EHBVM(12)': ehbvm(k, s) takes 2"),
            ("problem: kepler\nmethod: ehbvm\n", "short.yaml:2: method.k: is missing, and so is s"),
            ("problem: keplr\nmethod: EHBVM(12,3)\n",
             "short.yaml:1: problem: 'keplr' is not a built-in problem (did you mean 'kepler'?); give a built-in's name")]:
        path = write(tmp_path, text + "integration: {h: 0.1, t_end: 1}\n", "short.yaml")
        with pytest.raises(ConfigError) as caught:
            load_run(path)
        assert str(caught.value).startswith(f"{path.parent}/{message}"), str(caught.value)


def test_a_method_whose_parentheses_do_not_make_the_notation_is_called_so_not_a_yaml_split(tmp_path):
    """A user trial: --set "method=EHBVM(12,3" (a ')' missing) was explained as 'inside {...}
    YAML splits an unquoted EHBVM(12,3) at its comma; quote it', which had not happened; other
    malformed forms said 'must be a mapping'. The split is named only where YAML made one (the
    key '3)' beside name); otherwise the notation is called unbalanced or malformed, with the
    form expected."""
    from click.testing import CliRunner
    from elimfast_cli.main import cli
    path = write(tmp_path, "problem: kepler\nmethod: {name: ehbvm, k: 12, s: 3}\n"
                           "integration: {h: 0.1, t_end: 1}\n", "run.yaml")
    for given, message in [
            ("method=EHBVM(12,3", "method: 'EHBVM(12,3' is unbalanced: a ')' is missing; expected EHBVM(k,s), e.g. "
                                  "EHBVM(12,3) (value from --set method=EHBVM(12,3)"),
            ("method=elim(8,12,3", "method: 'elim(8,12,3' is unbalanced: a ')' is missing; expected ELIM(r,k,s), "
                                   "e.g. ELIM(8,12,3)"),
            ("method=EHBVM 12,3)", "method: 'EHBVM 12,3)' is unbalanced: a '(' is missing; expected EHBVM(k,s)"),
            ("method=EHBVM(12,3)x", "method: 'EHBVM(12,3)x' is malformed; expected EHBVM(k,s), e.g. EHBVM(12,3)"),
            ("method.name=FOO((1)", "method.name: 'FOO((1)' is unbalanced: a ')' is missing; expected NAME(s), "
                                    "NAME(k,s) or NAME(r,k,s), e.g. EHBVM(12,3)"),
            ("method={name: EHBVM(12,3)}", "method.name: 'EHBVM(12' is cut off: inside {...} YAML splits an unquoted "
                                           "EHBVM(12,3) at its comma; quote it")]:
        with pytest.raises(ConfigError) as caught:
            load_run(path, overrides=[given])
        assert str(caught.value).startswith(f"{path}: {message}"), str(caught.value)
        assert "YAML splits" not in str(caught.value) or "{" in given
    result = CliRunner().invoke(cli, ["check", str(path), "--set", "method=EHBVM(12,3"])
    assert result.exit_code == 2 and result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert result.stderr.startswith(f"error: {path}: method: 'EHBVM(12,3' is unbalanced"), result.stderr
    from elimfast.errors import ParameterError
    with pytest.raises(ParameterError, match=r"^method 'EHBVM\(12,3' is unbalanced: a '\)' is missing"):
        elimfast.integrate(problems.kepler(0.6), "EHBVM(12,3", 0.1, n_steps=5)


def test_integrate_takes_a_method_in_the_papers_notation():
    from elimfast.errors import ParameterError
    from elimfast.methods import ehbvm
    from elimfast.ensemble import integrate_ensemble
    p = problems.kepler(0.6)
    named = elimfast.integrate(p, "EHBVM(12,3)", 0.1, n_steps=20, conserve=("angular_momentum",))
    built = elimfast.integrate(p, ehbvm(12, 3), 0.1, n_steps=20, conserve=("angular_momentum",))
    np.testing.assert_array_equal(named.y, built.y)
    ensemble = integrate_ensemble(p, "gauss(3)", 0.1, np.array([p.y0]), n_steps=5)
    assert ensemble.method.name == "GAUSS(3)"
    with pytest.raises(ParameterError, match=r"^method 'ehbvm' names the family, not a method: .* 'EHBVM\(12,3\)'"):
        elimfast.integrate(p, "ehbvm", 0.1, n_steps=5)
    with pytest.raises(ParameterError, match=r"^method 'EHBVM\(12\)': ehbvm\(k, s\) takes 2 whole numbers"):
        elimfast.integrate(p, "EHBVM(12)", 0.1, n_steps=5)


def test_a_method_in_braces_is_told_to_drop_them():
    """A user trial: method: {EHBVM(12,3)} (YAML reads two keys, 'EHBVM(12' and '3)') was told
    'method.EHBVM(12: unknown key; allowed here: name, r, k, s'."""
    data = kepler_data()
    data["method"] = yaml.safe_load("{EHBVM(12,3)}")
    assert set(data["method"]) == {"EHBVM(12", "3)"}
    err = config_error(data)
    assert err.key == "method.EHBVM(12" and "braces make YAML read the method's notation as keys" in str(err)
    assert "write method: EHBVM(12,3) without braces" in str(err)


def test_set_null_leaves_a_key_out_in_every_section():
    """A user trial: solver.lim_metric: 'scaled' on a non-LIM method says 'leave lim_metric out',
    but --set solver.lim_metric=null was refused as 'an empty value (null)' (solver's and output's
    keys), while integration's took it. --set KEY=null now leaves the key out, everywhere."""
    nbody = yaml.safe_load((CONFIGS / "nbody.yaml").read_text())
    assert nbody["solver"]["lim_metric"] == "scaled"
    spec = load_run_from_dict(nbody, source="nbody.yaml", overrides=[
        "method=EHBVM(12,4)", "conserve=[angular_momentum_z]", "solver.lim_metric=null"])
    assert spec.solver.lim_metric == "euclidean" and spec.method.name == "EHBVM(12,4)"
    gauss = load_run_from_dict(kepler_data(), source="k.yaml", overrides=["method.name=gauss", "method.k=null",
                                                                           "conserve=[]"])
    assert gauss.method.name == "GAUSS(3)"
    err = config_error(kepler_data(), overrides=["integration.h=null"])   # a required key: missing, said so
    assert err.key == "integration.h" and "missing" in str(err) and str(err).endswith("(value from --set integration.h=null)")


def test_set_reaches_keys_under_the_short_forms_of_method_and_problem():
    """A user trial: on a config with method: EHBVM(12,3) and problem: kepler (the README's short
    forms), --set method.s=4 and --set problem.parameters.eccentricity=0.9 were refused ('method is
    not a section'), while a sweep's set reached them. They are written out first, as a sweep does."""
    short = {"problem": "kepler", "method": "EHBVM(12,3)", "conserve": ["angular_momentum"],
             "integration": {"h": 0.1, "t_end": 1}}
    spec = load_run_from_dict(short, source="short.yaml",
                              overrides=["method.s=4", "problem.parameters.eccentricity=0.9"])
    assert spec.method.name == "EHBVM(12,4)" and spec.problem.parameters["eccentricity"] == 0.9
    err = config_error({**short, "method": "EHBVM(12"}, overrides=["method.s=4"])   # a bad short form: said
    assert str(err).startswith("run.yaml: method: ") and "EHBVM(12" in str(err), str(err)
    err = config_error({**short, "integration": 5}, overrides=["integration.h=0.1"])   # not a section: as before
    assert "integration is not a section, so it has no keys" in str(err)


def test_output_every_refused_beside_output_times_names_their_set():
    """A user trial: --set 'output.times=[...]' on configs/kepler_adaptive.yaml (output.every: 10)
    was told of the file's output.every line only, not of the --set that made the conflict."""
    data = yaml.safe_load((CONFIGS / "kepler_adaptive.yaml").read_text())
    assert data["output"]["every"] == 10
    err = config_error(data, overrides=["output.times=[1, 2, 3]"])
    assert err.key == "output.every" and str(err).endswith("make it 1 (got 10) (with --set output.times=[1, 2, 3])")
