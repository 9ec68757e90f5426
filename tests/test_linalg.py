"""The small dense solves of docs/methods.md#elim (Gamma, partial pivoting) and #lim (the
Gram matrix, SPD)."""
import numpy as np
import pytest

from elimfast.kernels.linalg import cholesky_solve, invert, lu_solve


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_lu_solve_matches_numpy_for_random_systems(n):
    rng = np.random.default_rng(n)
    for _ in range(20):
        a = rng.normal(size=(n, n))
        x = rng.normal(size=n)
        expected = np.linalg.solve(a, x)
        work, out = a.copy(), x.copy()
        assert lu_solve(work, out) == 0
        np.testing.assert_allclose(out, expected, rtol=1e-10, atol=1e-12)


def test_lu_solve_needs_pivoting_and_is_scale_invariant():
    # a zero leading entry: plain elimination divides by zero
    a = np.array([[0.0, 1.0], [1.0, 1.0]])
    for scale in (1.0, 1e-12, 1e-24):  # Gamma is O(h^(2s-2)): a relative test only
        out = np.array([1.0, 2.0]) * scale
        assert lu_solve(a * scale, out) == 0
        np.testing.assert_allclose(out, [1.0, 1.0], rtol=1e-15)


@pytest.mark.parametrize("a", [
    np.zeros((2, 2)),
    np.array([[1.0, 2.0], [2.0, 4.0]]),
    np.array([[1.0, 1.0], [1.0, 1.0 + 1e-15]]),        # condition ~ 1e15: no correct digit
    np.array([[np.nan, 0.0], [0.0, 1.0]]),
    np.array([[np.inf, 0.0], [0.0, 1.0]]),
])
def test_lu_solve_reports_singular_or_badly_conditioned(a):
    assert lu_solve(a.copy(), np.ones(2)) == 1


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_cholesky_solve_matches_numpy_for_gram_matrices(n):
    rng = np.random.default_rng(10 + n)
    for _ in range(20):
        phi = rng.normal(size=(4, n))
        gram = phi.T @ phi
        x = rng.normal(size=n)
        out = x.copy()
        assert cholesky_solve(gram.copy(), out) == 0
        np.testing.assert_allclose(out, np.linalg.solve(gram, x), rtol=1e-9, atol=1e-12)


def test_cholesky_solve_rejects_non_positive_definite():
    assert cholesky_solve(np.array([[1.0, 2.0], [2.0, 1.0]]), np.ones(2)) == 1
    assert cholesky_solve(np.array([[1.0, 1.0], [1.0, 1.0]]), np.ones(2)) == 1
    assert cholesky_solve(np.zeros((1, 1)), np.ones(1)) == 1


def test_cholesky_accepts_a_badly_scaled_gram_matrix_and_rejects_by_angle():
    """The singularity test is relative to each pivot's own diagonal entry (the squared sine
    of the angle between a column and the earlier ones), so scaling the columns changes
    nothing: Kepler e = 0.999 at pericentre has |grad H| ~ 1e6 beside |grad L| ~ 45."""
    rng = np.random.default_rng(7)
    columns = rng.normal(size=(4, 3))
    columns[:, 1] = columns[:, 0] + 3e-5 * columns[:, 1]          # sin(angle) ~ 1e-5: well within eps^(-1/2)
    for scales in ([1.0, 1.0, 1.0], [1e6, 45.0, 1e3], [1e-8, 1e8, 1.0]):
        phi = columns * np.array(scales)
        gram = phi.T @ phi
        solution = np.array([1.0, -2.0, 0.5]) / np.array(scales)    # phi @ solution does not depend on the scales
        out = gram @ solution
        assert cholesky_solve(gram.copy(), out) == 0, scales
        # accurate to cond(columns' Gram) * eps ~ 3e9 * 1e-16 in the scaled unknowns, whatever the scaling
        np.testing.assert_allclose(out * np.array(scales), [1.0, -2.0, 0.5], rtol=1e-5)
    parallel = columns.copy()
    parallel[:, 1] = 2.0 * parallel[:, 0]                         # a multiple of the first: dependent
    for scales in ([1.0, 1.0, 1.0], [1e-6, 1e6, 1.0]):
        phi = parallel * np.array(scales)
        assert cholesky_solve((phi.T @ phi).copy(), np.ones(3)) == 1, scales


@pytest.mark.parametrize("dtype", [np.float64, np.complex128])
@pytest.mark.parametrize("n", [1, 2, 4, 8])
def test_invert_matches_numpy_for_random_matrices(n, dtype):
    """The Gauss-Jordan inverse of the Newton blocks (docs/solver.md, "Block form"), real and complex."""
    rng = np.random.default_rng(10 * n + (dtype is np.complex128))
    for _ in range(20):
        a = rng.normal(size=(n, n)).astype(dtype)
        if dtype is np.complex128:
            a += 1j * rng.normal(size=(n, n))
        inverse = np.full((n, n), np.nan, dtype=dtype)
        assert invert(a.copy(), inverse) == 0
        np.testing.assert_allclose(inverse @ a, np.eye(n), atol=1e-11 * np.linalg.cond(a))


def test_invert_needs_pivoting():
    a = np.array([[0.0, 1.0], [1.0, 1.0]], dtype=np.complex128)
    inverse = np.zeros((2, 2), dtype=np.complex128)
    assert invert(a.copy(), inverse) == 0
    np.testing.assert_array_equal(inverse, [[-1.0, 1.0], [1.0, 0.0]])


@pytest.mark.parametrize("a", [
    np.zeros((2, 2)),
    np.array([[1.0, 2.0], [2.0, 4.0]]),
    np.array([[1.0, 1.0], [1.0, 1.0 + 1e-15]]),
    np.array([[np.nan, 0.0], [0.0, 1.0]]),
    np.array([[1.0, 1j], [-1j, 1.0]]),                 # complex and singular: (1)(1) - (1j)(-1j) = 0
])
def test_invert_reports_singular_or_badly_conditioned(a):
    a = a.astype(np.complex128)
    assert invert(a.copy(), np.zeros_like(a)) == 1
