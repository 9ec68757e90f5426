"""The small dense solves of docs/methods.md#elim (Gamma, partial pivoting) and #lim (the
Gram matrix, SPD)."""
import numpy as np
import pytest

from elimfast.kernels.linalg import cholesky_solve, lu_solve


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
