"""Shared fixtures. Problems and methods are built once per session: the kernel is
compiled once (cached), and every test reuses it."""
import math

import numpy as np
import pytest

from elimfast import methods, problems

TWO_PI = 2.0 * math.pi
EPS = np.finfo(float).eps


@pytest.fixture(scope="session")
def kepler():
    return problems.kepler(0.6)


@pytest.fixture(scope="session")
def quartic():
    return problems.quartic_oscillator()


@pytest.fixture(scope="session")
def central_quartic():
    return problems.central_quartic()


def max_error(a, b):
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))))


# --- the per-problem kernel, compiled beside the other tests ------------------------------------
# tests/test_per_problem_kernel.py needs elimfast's fixed-step kernel compiled for two problems
# (from expressions, from a Python file): about 90 s each on a cold cache (CI's), on one core.
# They are compiled in a process of their own from the start of the session, on the second core
# (CI has two), while the other tests run; that module waits for it (per_problem_kernel_compiled)
# and then loads the kernels from the cache.
PER_PROBLEM_CONFIGS = ("configs/kepler_expressions.yaml", "configs/kepler_python.yaml")
_per_problem_compile = []


def pytest_collection_finish(session):
    import subprocess
    import sys
    from pathlib import Path

    if any(item.nodeid.startswith("tests/test_per_problem_kernel.py") for item in session.items):
        root = Path(__file__).resolve().parents[1]
        code = ("from elimfast.config import load_run; from elimfast.per_problem import time_loop_for\n"
                + "".join(f"time_loop_for(load_run({str(root / config)!r}, allow_python=True).problem)\n"
                          for config in PER_PROBLEM_CONFIGS))
        _per_problem_compile.append(subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL,
                                                     stderr=subprocess.PIPE))


@pytest.fixture
def allow_python(monkeypatch):
    """The user allowed python: problem files (ELIMFAST_ALLOW_PYTHON=1, which --allow-python sets):
    for tests of what such a problem does, not of the permission (tests/test_python_allowed.py)."""
    from elimfast.config import ALLOW_PYTHON_ENV
    monkeypatch.setenv(ALLOW_PYTHON_ENV, "1")


@pytest.fixture(scope="session")
def per_problem_kernel_compiled():
    """Wait for the compilation started at collection (if any); its failure is the tests' to see."""
    for process in _per_problem_compile:
        _, stderr = process.communicate(timeout=1800)
        assert process.returncode == 0, stderr.decode(errors="replace")[-2000:]


def pytest_sessionfinish(session, exitstatus):
    for process in _per_problem_compile:
        if process.poll() is None:
            process.kill()
