"""The per-problem kernel (solver.kernel: per_problem; elimfast/per_problem.py, docs/solver.md#per-problem-kernel).

It is elimfast's fixed-step kernel compiled once more, with the problem's functions as
compile-time constants (kernels/static.py): the same arithmetic in the same order, so the
same steps bit for bit as the shared kernel, and cached by Numba (a second process loads
it). One compilation (about 100 s on a cold cache; conftest.py starts it in a process of its
own when the session's tests are collected, beside the other tests), shared by every test
below: Kepler from expressions, the user-defined case (its functions live in a module
generated into elimfast's cache, which the kernel module imports by name).
"""
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from numba import njit

import elimfast
from elimfast.config import load_run
from elimfast.errors import ParameterError
from elimfast.integrate import SolverSettings
from elimfast.methods import ehbvm, ghbvm
from elimfast.per_problem import kernel_source, time_loop_for
from elimfast.problems import kepler

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "kepler_expressions.yaml"
L, AY = "angular_momentum", "lrl_y"


@pytest.fixture(scope="module")
def user_kepler(per_problem_kernel_compiled):
    """Kepler from expressions; its per-problem kernel compiled (conftest: in a process beside the
    other tests) or loaded."""
    return load_run(CONFIG).problem


def _same_run(a, b):
    np.testing.assert_array_equal(a.y, b.y)
    np.testing.assert_array_equal(a.y_final, b.y_final)
    np.testing.assert_array_equal(a.iterations, b.iterations)
    np.testing.assert_array_equal(a.substeps, b.substeps)
    if a.alpha is not None or b.alpha is not None:
        np.testing.assert_array_equal(a.alpha, b.alpha)
    if a.lam is not None or b.lam is not None:
        np.testing.assert_array_equal(a.lam, b.lam)
    for name in a.invariants:
        np.testing.assert_array_equal(a.invariants[name], b.invariants[name])


@pytest.mark.slow
@pytest.mark.parametrize("make, conserve, solver", [
    (lambda: ehbvm(12, 3), (L, AY), "newton"),
    (lambda: ehbvm(12, 3), (L, AY), "fixed_point"),
    (lambda: ghbvm(12, 3), (L,), "newton"),
], ids=["EHBVM newton", "EHBVM fixed point", "GHBVM newton"])
@pytest.mark.usefixtures("allow_python")
def test_the_per_problem_kernel_takes_the_shared_kernels_steps_bit_for_bit(user_kepler, make, conserve, solver):
    """The README's run (EHBVM(12,3) imposing L and A_y, e = 0.6, h = 0.1) and LIM, with both
    solvers, in chunks (a kernel call continues the last exactly): every sample, iteration
    count and multiplier equal, as theirs are the same operations in the same order."""
    runs = {}
    for kernel in ("shared", "per_problem"):
        settings = SolverSettings(method=solver, kernel=kernel)
        runs[kernel] = elimfast.integrate(user_kepler, make(), 0.1, n_steps=3000, conserve=conserve, solver=settings,
                                          store_every=7, chunk_steps=1000)
    assert runs["per_problem"].solver.kernel == "per_problem" and runs["shared"].status == "complete"
    _same_run(runs["shared"], runs["per_problem"])


@pytest.mark.slow
@pytest.mark.usefixtures("allow_python")
def test_a_python_file_problem_runs_on_its_kernel_bit_for_bit(per_problem_kernel_compiled):
    """A user trial: a python: problem was refused ('H is not at the top of a module'): elimfast
    compiles such a file's functions itself (user_file._compile), so they are no attribute of their
    module. The kernel's module takes them through the same compilation (user_file.compiled_function);
    the run is the shared kernel's, bit for bit."""
    problem = load_run(ROOT / "configs" / "kepler_python.yaml").problem
    _, text = kernel_source(problem)
    assert "grad_H = StaticFunction(compiled_function('grad_H', importlib.import_module(" in text
    runs = [elimfast.integrate(problem, ehbvm(12, 3), 0.1, n_steps=2000, conserve=(L, AY),
                               solver=SolverSettings(method="newton", kernel=kernel), store_every=5)
            for kernel in ("shared", "per_problem")]
    _same_run(*runs)


@pytest.mark.slow
@pytest.mark.usefixtures("allow_python")
def test_the_per_problem_kernel_is_cached_and_named_in_the_file(user_kepler, tmp_path):
    """Compiled in this process (the test above, or here), it loads in another without compiling:
    `elimfast run` prints no compile line, and inspect names the kernel."""
    time_loop_for(user_kepler)   # compiled (or loaded) here first
    out = tmp_path / "k.h5"
    ran = subprocess.run([sys.executable, "-m", "elimfast_cli.main", "run", str(CONFIG), "-o", str(out),
                          "--set", "solver.kernel=per_problem", "--set", "integration.t_end=100"],
                         capture_output=True, text=True, timeout=300, env={**os.environ, "PYTHONHASHSEED": "0"})
    assert ran.returncode == 0, ran.stderr
    assert "compiling" not in ran.stderr, ran.stderr
    inspected = subprocess.run([sys.executable, "-m", "elimfast_cli.main", "inspect", str(out)],
                               capture_output=True, text=True, timeout=300)
    assert "kernel per_problem" in inspected.stdout, inspected.stdout


@pytest.mark.usefixtures("allow_python")
def test_the_kernel_module_follows_the_problems_functions(user_kepler):
    """The module imports the problem's functions by module and name; its digest (the file's and
    the cache's name) covers the text they come from, so another problem is another kernel and
    the same problem the same one."""
    digest, text = kernel_source(user_kepler)
    module = user_kepler.grad_H.py_func.__module__
    assert module.startswith("elimfast_generated_")
    assert f"grad_H = StaticFunction(importlib.import_module({module!r}).grad_H)" in text
    assert kernel_source(load_run(CONFIG).problem)[0] == digest
    builtin_digest, builtin_text = kernel_source(kepler(0.6))
    assert builtin_digest != digest
    assert "importlib.import_module('elimfast.problems.kepler').hess_H" in builtin_text
    assert kernel_source(kepler(0.9))[0] == builtin_digest   # parameters are arguments, not code


@njit
def _local_grad_H(y, params, out):   # pragma: no cover - never called
    out[:] = y


def test_a_problem_whose_functions_are_not_importable_is_refused():
    def make():
        @njit
        def grad_H(y, params, out):   # pragma: no cover - never called
            out[:] = y
        return grad_H

    for function in (make(), lambda y, params, out: None):
        problem = replace(kepler(0.6), grad_H=function)
        with pytest.raises(ParameterError) as info:
            kernel_source(problem)
        assert info.value.parameter == "kernel" and "leave solver.kernel out" in str(info.value)


@pytest.mark.parametrize("call", [
    lambda: elimfast.integrate(kepler(0.9), ehbvm(8, 4), t_end=10.0, rtol=1e-10, solver={"kernel": "per_problem"}),
    lambda: elimfast.integrate(kepler(0.6), ehbvm(12, 3), 0.1, t_end=10.0, t_eval=[1.0, 2.0],
                               solver={"kernel": "per_problem"}),
], ids=["adaptive", "output times"])
def test_runs_on_the_other_kernels_refuse_it(call):
    with pytest.raises(ParameterError) as info:
        call()
    assert info.value.parameter == "kernel" and "leave solver.kernel out" in str(info.value)


def test_the_setting_is_validated():
    with pytest.raises(ParameterError, match="must be 'shared'"):
        SolverSettings(kernel="fast")
    assert SolverSettings().as_dict()["kernel"] == "shared"


def test_a_config_asking_for_it_with_adaptive_steps_is_refused_at_the_key():
    from elimfast.config import ConfigError, load_run_from_dict
    import yaml
    data = yaml.safe_load(CONFIG.read_text())
    data["integration"] = {"rtol": 1e-12, "t_end": 10}
    data["solver"] = {"kernel": "per_problem"}
    with pytest.raises(ConfigError) as info:
        load_run_from_dict(data, source="run.yaml")
    assert str(info.value).startswith("run.yaml: solver.kernel: per_problem compiles the kernel of fixed steps"), \
        str(info.value)
    assert "adaptive steps (integration.rtol) run on other kernels" in str(info.value)   # what conflicts, named


def test_a_python_file_loaded_again_elsewhere_still_gives_its_kernel(tmp_path, monkeypatch):
    """On a clean clone a python: problem was refused ('H is not at the top of a module') after an
    earlier test had loaded the same file from another cache folder: its module name (the content's
    hash) then named the later module object. Content-named modules hold the same code under the
    name, so the kernel's module may import them by it."""
    from elimfast.problems import problem_from_file
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(tmp_path / "first"))
    first = problem_from_file(ROOT / "configs" / "kepler_problem.py")
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(tmp_path / "second"))
    second = problem_from_file(ROOT / "configs" / "kepler_problem.py")
    assert first.grad_H.py_func is not second.grad_H.py_func   # two loads of the same file
    assert kernel_source(first)[0] == kernel_source(second)[0]
