"""The small dense solves of docs/methods.md#elim (Gamma, partial pivoting) and #lim (the
Gram matrix, SPD)."""
import numpy as np
import pytest

from elimfast.kernels.linalg import cholesky_solve, invert, lu_factor, lu_factor_columns, lu_solve


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


def _factors(factor, a):
    a, pivots = np.array(a, dtype=float), np.zeros(len(a), dtype=np.int64)
    return factor(a, pivots), a, pivots


def test_lu_factor_columns_judges_each_pivot_against_its_column_and_factors_as_lu_factor():
    """ELIM's Gamma carries h^(2(nu-1-c)) in column c: in absolute time its columns can differ by
    more than lu_factor's floor (Kepler e = 0.99999 at pericentre: 1.4e-14) where the matrix is
    well conditioned once they are scaled. lu_factor_columns judges each pivot against its own
    column, so it is blind to column scaling; its factors are lu_factor's wherever that succeeds."""
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 5):
        for _ in range(20):
            a = rng.normal(size=(n, n))
            status, lu, pivots = _factors(lu_factor, a)
            status_c, lu_c, pivots_c = _factors(lu_factor_columns, a)
            assert status == status_c == 0
            assert np.array_equal(lu, lu_c) and np.array_equal(pivots, pivots_c)
            # columns scaled by powers of two (exact): the same factors, U's columns scaled
            scales = 2.0 ** -rng.integers(0, 80, size=n)
            status_s, lu_s, pivots_s = _factors(lu_factor_columns, a * scales)
            assert status_s == 0 and np.array_equal(pivots_s, pivots)
            assert np.array_equal(np.triu(lu_s), np.triu(lu) * scales)
            assert np.array_equal(np.tril(lu_s, -1), np.tril(lu, -1))
    scaled = np.array([[1.0, 3.0], [2.0, 1.0]]) * np.array([2.0 ** -50, 1.0])
    assert _factors(lu_factor, scaled)[0] == 1 and _factors(lu_factor_columns, scaled)[0] == 0
    # what no column scaling cures stays singular
    for singular in (np.zeros((2, 2)), [[1.0, 2.0], [2.0, 4.0]], [[1.0, 1.0], [1.0, 1.0 + 1e-15]],
                     [[1e-30, 1.0], [2e-30, 2.0]], [[np.nan, 0.0], [0.0, 1.0]]):
        assert _factors(lu_factor_columns, singular)[0] == 1


@pytest.mark.parametrize("a, row_scales, column_scales", [
    (np.random.default_rng(3).normal(size=(3, 3)), [1.0, 1.0, 1.0], [1.0, 1.0, 1.0]),
    (np.random.default_rng(4).normal(size=(2, 2)), [1e-5, 1.0], [1e-14, 1.0]),          # Kepler e = 0.99999's shape
    (np.array([[1.0, 2.0, 3.0], [2.0, 4.1, 6.0], [1.0, 0.0, 1.0]]), [1e3, 1.0, 1e-9], [1e8, 1e-4, 1.0]),
])
def test_equilibrated_condition_is_blind_to_row_and_column_scales(a, row_scales, column_scales):
    """maps.equilibrated_condition: cond_inf of Gamma with its columns, then its rows, scaled to unit
    size (numpy computes the same), within a factor n^2 of the same whatever scales the rows and
    columns carry (cond(Gamma) in the third case: 5e19), so large only for nearly dependent rows."""
    from types import SimpleNamespace
    from elimfast.kernels.maps import equilibrated_condition

    def equilibrated(matrix):
        n = matrix.shape[0]
        work = SimpleNamespace(small_copy=matrix.copy(), small_matrix=matrix.copy(), small_inverse=np.zeros((n, n)),
                               small_pivots=np.zeros(n, dtype=np.int64), small_rounding=np.zeros((1, n)))
        assert lu_factor_columns(work.small_matrix, work.small_pivots) == 0
        return equilibrated_condition.py_func(work, n)

    gamma = np.asarray(row_scales)[:, None] * a * np.asarray(column_scales)
    scaled = gamma / np.abs(gamma).max(axis=0)
    scaled = scaled / np.abs(scaled).max(axis=1)[:, None]
    assert equilibrated(gamma) == pytest.approx(np.linalg.cond(scaled, np.inf), rel=1e-8)
    n = a.shape[0]   # one pass of scaling each way: the same up to a factor of n^2 whatever the scales
    assert equilibrated(a) / n ** 2 <= equilibrated(gamma) <= n ** 2 * equilibrated(a)


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
