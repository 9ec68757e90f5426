"""maps.project and maps.stages compute four components at a time in vector registers
(kernels/simd.py): each lane must do the scalar code's operations in its order, so that the
results are the scalar loops' bit for bit (the runs' trajectories and resume depend on it),
for every size (a multiple of 4, the scalar tail, both), compiled and in the interpreter."""
import numpy as np
import pytest
from numba import njit

from elimfast.kernels.maps import project, stages


@njit(cache=False, error_model="numpy")
def scalar_project(projection, values, n_degrees, out):
    for j in range(n_degrees):
        for i in range(values.shape[1]):
            acc = 0.0
            for l in range(values.shape[0]):
                acc += projection[j, l] * values[l, i]
            out[j, i] = acc


@njit(cache=False, error_model="numpy")
def scalar_stages(y, comp, scaled, scaled_low, coef, n_coef, out):
    for l in range(out.shape[0]):
        for i in range(y.shape[0]):
            small = comp[i] + scaled_low[l, 0] * coef[0, i]
            for j in range(1, n_coef):
                small += scaled[l, j] * coef[j, i]
            out[l, i] = y[i] + (scaled[l, 0] * coef[0, i] + small)


@njit(cache=False, error_model="numpy")
def compiled_project(projection, values, n_degrees, out):
    project(projection, values, n_degrees, out)


@njit(cache=False, error_model="numpy")
def compiled_project_rows(projection, values, n_degrees, out):
    """As the maps call it on the invariants: rows of 3-D arrays."""
    for a in range(values.shape[0]):
        project(projection, values[a], n_degrees, out[a])


@njit(cache=False, error_model="numpy")
def compiled_stages(y, comp, scaled, scaled_low, coef, n_coef, out):
    stages(y, comp, scaled, scaled_low, coef, n_coef, out)


def _values(rng, shape):
    # widely spread magnitudes and signs, so that every rounding shows
    return rng.normal(size=shape) * 10.0 ** rng.integers(-12, 4, size=shape)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 8, 9, 12, 36])
@pytest.mark.parametrize("n_nodes, n_degrees", [(1, 1), (3, 2), (12, 12), (12, 3), (12, 7), (10, 9)])
def test_project_is_the_scalar_sum_bit_for_bit(n, n_nodes, n_degrees):
    rng = np.random.default_rng(100 * n + n_degrees)
    projection = _values(rng, (n_nodes + 2, n_nodes))
    values = _values(rng, (n_nodes, n))
    expected = np.full((n_nodes + 2, n), np.nan)
    scalar_project(projection, values, n_degrees, expected)
    for function in (compiled_project, project.py_func):
        out = np.full((n_nodes + 2, n), np.nan)
        function(projection, values, n_degrees, out)
        assert out.tobytes() == expected.tobytes(), function
    rows = _values(rng, (3, n_nodes, n))
    expected_rows = np.full((3, n_nodes + 2, n), np.nan)
    for a in range(3):
        scalar_project(projection, rows[a], n_degrees, expected_rows[a])
    out_rows = np.full((3, n_nodes + 2, n), np.nan)
    compiled_project_rows(projection, rows, n_degrees, out_rows)
    assert out_rows.tobytes() == expected_rows.tobytes()


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 8, 9, 36])
@pytest.mark.parametrize("k, s", [(1, 1), (4, 2), (12, 3), (12, 6), (5, 5)])
def test_stages_are_the_scalar_sums_bit_for_bit(n, k, s):
    rng = np.random.default_rng(100 * n + 10 * k + s)
    y = _values(rng, n)
    comp = _values(rng, n) * 1e-17
    scaled = _values(rng, (k, s))
    scaled_low = _values(rng, (k, s)) * 1e-17
    coef = _values(rng, (s, n))
    for n_coef in sorted({1, s}):
        expected = np.full((k, n), np.nan)
        scalar_stages(y, comp, scaled, scaled_low, coef, n_coef, expected)
        for function in (compiled_stages, stages.py_func):
            out = np.full((k, n), np.nan)
            function(y, comp, scaled, scaled_low, coef, n_coef, out)
            assert out.tobytes() == expected.tobytes(), (function, n_coef)
