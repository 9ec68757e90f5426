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
