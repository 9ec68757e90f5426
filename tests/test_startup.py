"""Start-up (issue 12): what each entry point imports, the lazy problem registry, the one-line
compile notice and `elimfast cache warm`. No timings here: bench/end_to_end.py measures them."""
import json
import subprocess
import sys
import types
from pathlib import Path

import pytest
from click.testing import CliRunner

import elimfast
from elimfast import problems
from elimfast.problems.catalogue import BUILTINS, LISTING, listing_entry
from elimfast_cli.main import cli

ELIMFAST = str(Path(sys.executable).with_name("elimfast"))
ROOT = Path(__file__).resolve().parents[1]

# Runs the CLI (or an import) in a fresh interpreter, then reports which modules were loaded.
PROBE = """
import json, sys
{body}
heavy = sorted(m for m in sys.modules if m in ("numba", "pydantic") or m.startswith(("numba.", "elimfast.kernels", "h5py")))
loaded = sorted(m for m in sys.modules if m.startswith("elimfast.problems."))
print(json.dumps({{"heavy": heavy, "problems": loaded}}))
"""

CLI_BODY = """
sys.argv = ["elimfast", *{args!r}]
from elimfast_cli.main import cli
try:
    cli.main(sys.argv[1:], standalone_mode=False)
except SystemExit:
    pass
"""


def probe(body: str) -> dict:
    done = subprocess.run([sys.executable, "-c", PROBE.format(body=body)], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("args", [["--help"], ["--version"], ["problems"], ["methods"], ["run", "--help"],
                                  ["cache", "--help"]])
def test_listings_and_help_import_no_numba_kernels_h5py_pydantic_or_problem(args):
    loaded = probe(CLI_BODY.format(args=args))
    assert loaded["heavy"] == [], f"elimfast {' '.join(args)} imported {loaded['heavy'][:5]}"
    assert loaded["problems"] == [] or set(loaded["problems"]) <= {"elimfast.problems.base",
                                                                   "elimfast.problems.catalogue"}


def test_import_elimfast_loads_no_numba_and_the_api_still_works():
    loaded = probe("import elimfast, elimfast.methods, elimfast.problems")
    assert loaded["heavy"] == []
    assert set(loaded["problems"]) <= {"elimfast.problems.base", "elimfast.problems.catalogue"}
    # On first use: the function, the reader and the classes of before.
    from elimfast.integrate import Integration, Result, integrate
    assert elimfast.integrate is integrate and elimfast.Integration is Integration and elimfast.Result is Result
    from elimfast.archive import load
    assert elimfast.load is load
    assert {"integrate", "load", "Integration", "Result", "SolverSettings"} <= set(dir(elimfast))
    from elimfast.integrate import SolverSettings
    assert elimfast.SolverSettings is SolverSettings   # a user trial looked for it there (docs/solver.md)


RUN_KERNELS = ("elimfast.kernels.stepper", "elimfast.kernels.adaptive", "elimfast.kernels.ensemble")


@pytest.mark.parametrize("body", [
    # a config refused by its own checks: before this, `run` imported the fixed-step kernel first, and
    # on an empty cache (after every upgrade) the user waited 2 min for "events.x.direction: must be 1 ..."
    CLI_BODY.format(args=["run", "{bad}", "-o", "{out}"]),
    # the config machinery and the Python layer of each run kind, without running
    "import elimfast.config, elimfast.integrate, elimfast.adaptive, elimfast.ensemble, elimfast.sweep",
])
def test_checking_a_config_imports_no_run_kernel(body, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("problem: {builtin: kepler}\nmethod: {name: ehbvm, k: 8, s: 4}\n"
                   "integration: {h: 0.1, t_end: 10}\nevents:\n  x: {expression: q1, direction: up}\n")
    body = body.replace("{bad}", str(bad)).replace("{out}", str(tmp_path / "out.h5"))
    script = f"import sys\n{body}\nprint([m for m in sys.modules if m in {RUN_KERNELS!r}])"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"
    assert not (tmp_path / "out.h5").exists()


def test_a_parallel_sweep_whose_configs_are_refused_loads_no_run_kernel(tmp_path):
    """A user trial: on an empty cache, a grid of h = -0.1, -0.2 on 2 workers compiled the kernels
    for 2 minutes (the pool's preload before forking), then said that every run's config was refused."""
    sweep = tmp_path / "bad.yaml"
    sweep.write_text(f"base: {ROOT / 'configs' / 'kepler.yaml'}\n"
                     "grid: [{name: h, key: integration.h, values: [-0.1, -0.2]}]\n")
    body = CLI_BODY.format(args=["sweep", str(sweep), "--workers", "2"])
    script = f"import sys\n{body}\nprint([m for m in sys.modules if m in {RUN_KERNELS!r}])"
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert "every run of the sweep failed to load its config" in done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]"


def test_a_run_loads_only_the_problem_it_uses():
    loaded = probe(CLI_BODY.format(args=["check", "configs/pendulum.yaml"]))
    assert "elimfast.problems.pendulum" in loaded["problems"]
    assert not {"elimfast.problems.kepler", "elimfast.problems.nbody", "elimfast.problems.fpu_beta"} & set(
        loaded["problems"])


def test_lazy_registry_lists_every_builtin_in_order_and_builds_each():
    assert list(problems.PROBLEMS) == list(BUILTINS) == list(LISTING)
    assert len(problems.PROBLEMS) == 10 and "kepler" in problems.PROBLEMS and "nope" not in problems.PROBLEMS
    with pytest.raises(KeyError):
        problems.PROBLEMS["nope"]
    for name, constructor in problems.PROBLEMS.items():
        assert callable(constructor) and constructor().name == name
        assert getattr(problems, name) is constructor is problems.PROBLEMS[name]
        assert name in problems.__all__ and name in dir(problems)


def test_importing_a_builtin_module_keeps_the_package_attribute_the_constructor():
    import importlib
    module = importlib.import_module("elimfast.problems.toda")
    assert isinstance(module, types.ModuleType) and problems.toda is module.toda
    from elimfast.problems import toda
    assert toda is module.toda
    import elimfast.integrate as integrate_module  # noqa: F401 (the function stays the package attribute)
    assert callable(elimfast.integrate) and not isinstance(elimfast.integrate, types.ModuleType)


def test_the_builders_are_the_functions_themselves_loaded_on_first_use():
    """The last note: the lazy wrappers of the two builders took (*args, **kwargs), so help() showed
    no parameters. The package now hands out the builders themselves, imported on first use."""
    import inspect
    from elimfast.problems.symbolic import problem_from_expressions
    from elimfast.problems.user_file import problem_from_file
    assert problems.problem_from_expressions is problem_from_expressions
    assert problems.problem_from_file is problem_from_file
    assert "hamiltonian" in inspect.signature(problems.problem_from_expressions).parameters
    assert "path" in inspect.signature(problems.problem_from_file).parameters
    assert {"problem_from_expressions", "problem_from_file"} <= set(problems.__all__) & set(dir(problems))
    # the package alone loads neither builder; asking for one loads its module (and no kernel)
    alone = probe("import elimfast.problems")
    assert alone["heavy"] == [] and "elimfast.problems.symbolic" not in alone["problems"]
    asked = probe("import elimfast.problems as P\nP.problem_from_expressions")
    assert asked["heavy"] == [] and "elimfast.problems.symbolic" in asked["problems"]


@pytest.mark.parametrize("name", list(BUILTINS))
def test_listing_says_what_the_built_problem_says(name):
    """catalogue.LISTING is data (so `elimfast problems` compiles nothing): it must match the problem."""
    assert LISTING[name] == listing_entry(problems.PROBLEMS[name])


def test_problems_command_prints_the_listing_of_the_built_problems():
    output = CliRunner().invoke(cli, ["problems"]).output
    for name, entry in LISTING.items():
        assert f"{name}: {entry.description}\n" in output
    assert "coordinates: sun_x, sun_y, sun_z, jupiter_x, ... (30 more) ..., pluto_py, pluto_pz" in output


def test_methods_registry_needs_no_kernels_until_a_code_is_asked_for():
    from elimfast import methods
    from elimfast.kernels import codes
    assert methods.FAMILIES["ehbvm"].kernel_family == codes.FAMILY_ELIM
    assert methods.FAMILIES["gauss"].kernel_family == codes.FAMILY_ELIM
    assert methods.FAMILIES["ghbvm"].kernel_family == codes.FAMILY_LIM
    assert methods.ehbvm(12, 3).kernel_family == codes.FAMILY_ELIM


def test_warm_runs_print_no_compile_notice(tmp_path):
    """With the kernels in the cache (as after `make`), `elimfast run` loads them silently."""
    config = ROOT / "configs" / "kepler.yaml"
    first = subprocess.run([ELIMFAST, "run", str(config), "-o", str(tmp_path / "a.h5"), "--set",
                            "integration.t_end=1"], capture_output=True, text=True)
    assert first.returncode == 0, first.stderr
    again = subprocess.run([ELIMFAST, "run", str(config), "-o", str(tmp_path / "b.h5"), "--set",
                            "integration.t_end=1", "--quiet"], capture_output=True, text=True)
    assert again.returncode == 0 and again.stderr == ""


def test_compile_notice_is_one_line_on_a_cache_miss(tmp_path):
    """A problem never compiled before (expressions with a fresh cache) makes Numba compile:
    one line says so, however many functions are compiled, and says what compiles: the
    problem's functions, which `elimfast cache warm` cannot compile ahead (the line named
    the kernels and advised it)."""
    config = tmp_path / "osc.yaml"
    config.write_text("problem: {hamiltonian: 'p**2/2 + 1.2345*q**2/2', coordinates: {q: [q], p: [p]}, "
                      "initial: {q: 1.0, p: 0.0}}\nmethod: {name: gauss, s: 2}\n"
                      "integration: {h: 0.1, t_end: 0.5}\n")
    env = dict(__import__("os").environ, ELIMFAST_CACHE_DIR=str(tmp_path / "cache"))
    done = subprocess.run([ELIMFAST, "run", str(config), "-o", str(tmp_path / "o.h5"), "--quiet"],
                          capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert done.stderr == "compiling the problem's own functions (once: later runs load them from the cache) ...\n"
    again = subprocess.run([ELIMFAST, "run", str(config), "-o", str(tmp_path / "p.h5"), "--quiet"],
                           capture_output=True, text=True, env=env)
    assert again.returncode == 0 and again.stderr == ""


API_RUN = """
import logging, sys
from elimfast import integrate
from elimfast.methods import gauss
from elimfast.problems import problem_from_expressions
if sys.argv[1] == "silenced":
    logging.getLogger("elimfast").setLevel(logging.ERROR)
problem = problem_from_expressions({"q": ["q"], "p": ["p"]}, "p**2/2 + 2.3456*q**2/2", initial={"q": 1, "p": 0})
integrate(problem, gauss(2), h=0.1, t_end=0.5)
"""


def test_python_api_says_when_it_compiles(tmp_path):
    """A user trial: the Python API compiled for up to 2 minutes without a word (the command line
    said so). It now says the same line once on stderr, through the 'elimfast' logger, which a
    user can silence; a warm second process says nothing."""
    env = dict(__import__("os").environ, ELIMFAST_CACHE_DIR=str(tmp_path / "cache"))
    first = subprocess.run([sys.executable, "-c", API_RUN, "said"], capture_output=True, text=True, env=env)
    assert first.returncode == 0, first.stderr
    assert first.stderr == "compiling the problem's own functions (once: later runs load them from the cache) ...\n"
    again = subprocess.run([sys.executable, "-c", API_RUN, "said"], capture_output=True, text=True, env=env)
    assert again.returncode == 0 and again.stderr == ""
    env["ELIMFAST_CACHE_DIR"] = str(tmp_path / "other")
    silenced = subprocess.run([sys.executable, "-c", API_RUN, "silenced"], capture_output=True, text=True, env=env)
    assert silenced.returncode == 0 and silenced.stderr == ""


LOAD_CONFIG = """
import json, sys
from elimfast.config import load_run
spec = load_run(sys.argv[1], ["integration.t_end=2", "solver.max_halvings=3"])
print(json.dumps({"pydantic": "pydantic" in sys.modules, "resolved": spec.resolved,
                  "solver": repr(spec.solver), "steps": [spec.h, spec.n_steps, spec.t_end]}))
"""


def test_a_config_file_loaded_again_is_not_validated_again_and_loads_the_same(tmp_path):
    """load_run keeps each validation in elimfast's cache: the same config (and --set values)
    is then read back, without importing pydantic, and gives the same run; a damaged entry
    is validated again."""
    import os
    env = dict(os.environ, ELIMFAST_CACHE_DIR=str(tmp_path / "cache"))

    def load(config):
        done = subprocess.run([sys.executable, "-c", LOAD_CONFIG, str(config)], capture_output=True, text=True,
                              env=env)
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    results = {}
    for name in ("kepler.yaml", "kepler_adaptive.yaml", "henon_heiles_section.yaml"):
        first, again = load(ROOT / "configs" / name), load(ROOT / "configs" / name)
        assert first["pydantic"] and not again["pydantic"], name
        assert again == dict(first, pydantic=False), name
        results[name] = first
    stored = sorted((tmp_path / "cache" / "configs").iterdir())
    assert len(stored) == 3
    for path in stored:
        path.write_bytes(path.read_bytes()[:40])      # cut short: a miss, validated and stored again
    config = ROOT / "configs" / "henon_heiles_section.yaml"
    assert load(config) == results["henon_heiles_section.yaml"]
    assert not load(config)["pydantic"]


@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "configs").glob("*.yaml")))
def test_validated_sections_are_pydantics_as_plain_data(name):
    """config.Section (what the cache stores) holds exactly what the pydantic models hold."""
    import pickle

    from elimfast.config import Section, parse_yaml
    from elimfast.config_schema import RunConfig, sections
    model = RunConfig.model_validate(parse_yaml((ROOT / "configs" / name).read_text()))
    plain = sections(model)
    assert isinstance(plain, Section) and plain.model_dump() == model.model_dump()
    assert pickle.loads(pickle.dumps(plain)).model_dump() == model.model_dump()
    assert plain.solver.model_dump() == model.solver.model_dump() and plain.output.every == model.output.every


LAZY_LINKING_PROBE = """
import json
from elimfast.kernels import _cache, stepper
compiled = stepper.time_loop.overloads[stepper.time_loop.signatures[0]]
library, fndesc = compiled.library, compiled.fndesc
own = (fndesc.llvm_func_name, fndesc.llvm_cpython_wrapper_name, fndesc.llvm_cfunc_wrapper_name)
out = {"lazy": isinstance(library, _cache._LazyLinkingLibrary), "unparsed": library._linking_bitcode is not None}
module = library._get_module_for_linking()   # what linking it into new code asks for: parses
defined = sorted(f.name for f in module.functions if not f.is_declaration)
out["defines_own"] = set(own) <= set(defined)
out["pointers"] = all(library.get_pointer_to_function(name) != 0 for name in own + tuple(defined[:5]))
print(json.dumps(out))
"""


def test_the_time_loop_loads_without_parsing_its_linking_bitcode_which_is_parsed_when_needed():
    """A warm load keeps time_loop's linking bitcode unparsed (_cache._LazyLinkingLibrary);
    linking the library, or asking for any of its symbols, still works: it is parsed then.
    (Twice: the first process compiles, on a cold cache.)"""
    for _ in range(2):
        done = subprocess.run([sys.executable, "-c", LAZY_LINKING_PROBE], capture_output=True, text=True, cwd=ROOT)
        assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == {"lazy": True, "unparsed": True, "defines_own": True, "pointers": True}


def test_cache_warm_is_listed_and_runs_on_a_warm_cache():
    result = CliRunner().invoke(cli, ["cache", "warm"])
    assert result.exit_code == 0, result.output
    assert "kernels ready in" in result.output
    from elimfast import warm
    assert [what for what, _ in warm.STEPS][0] == "fixed-step kernel"


SMALL_SWEEP = """
description: start-up test sweep
base:
  problem: {builtin: kepler, parameters: {eccentricity: 0.6}}
  method: {name: gauss, s: 2}
  integration: {h: pi/30, t_end: 2*pi}
  output: {every: 10}
grid:
  - name: method
    values:
      - {label: GAUSS2, set: {method: {name: gauss, s: 2}}}
      - {label: "EHBVM(6,3) L1", set: {method: {name: ehbvm, k: 6, s: 3}, conserve: [angular_momentum]}}
  - name: h
    key: integration.h
    values: [pi/30, pi/60, pi/120]
error: {exact: initial}
order_axis: h
"""


def test_sweep_pool_runs_the_shortest_first_longest_next_and_matches_one_worker(tmp_path):
    """2 workers: the shortest run in the parent first (the warm pool), the rest longest first;
    outcomes in grid order and bit for bit those of 1 worker."""
    from elimfast.sweep import _expected_work, load_sweep, run_sweep
    path = tmp_path / "sweep.yaml"
    path.write_text(SMALL_SWEEP)
    spec = load_sweep(path)
    order = []
    from numba.core import event

    class Count(event.Listener):
        compiled = 0

        def on_start(self, ev):
            Count.compiled += 1

        def on_end(self, ev):
            pass

    counter = Count()
    event.register("numba:compile", counter)
    try:   # the results' problem functions unpickle onto the loaded ones: nothing is recompiled here
        pooled, _ = run_sweep(spec, workers=2, on_done=lambda outcome, done, total: order.append(outcome.label))
    finally:
        event.unregister("numba:compile", counter)
    assert Count.compiled == 0
    alone, _ = run_sweep(spec, workers=1)
    assert order[0] == "GAUSS2/pi/30" and sorted(order) == sorted(run.label for run in spec.runs)
    assert [o.label for o in pooled] == [o.label for o in alone] == [run.label for run in spec.runs]
    for a, b in zip(pooled, alone):
        assert a.status == b.status == "complete" and a.iterations_total == b.iterations_total
        assert a.y_final.tobytes() == b.y_final.tobytes()
    work = {run.label: _expected_work(run.config) for run in spec.runs}
    assert max(work, key=work.get) == "EHBVM(6,3) L1/pi/120" and min(work, key=work.get) == "GAUSS2/pi/30"
    assert _expected_work({"integration": {"rtol": 1e-8, "t_end": 1}}) == float("inf")
