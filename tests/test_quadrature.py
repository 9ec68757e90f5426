"""Gauss-Legendre nodes and weights against mpmath at 30+ digits, and the Legendre
tables against an independent NumPy construction (docs/methods.md#notation)."""
import mpmath as mp
import numpy as np
import pytest

from elimfast.methods import legendre_tables, quadrature

import reference

mp.mp.dps = 40


def mpmath_root(n, guess):
    """Polish a root of the shifted Legendre polynomial with Newton at 40 digits."""
    x = mp.mpf(2 * guess - 1)
    for _ in range(8):
        p, q = mp.legendre(n, x), mp.legendre(n - 1, x)
        x -= p / (n * (x * p - q) / (x * x - 1))
    q = mp.legendre(n - 1, x)
    return (x + 1) / 2, (1 - x * x) / (n * q) ** 2  # node and weight on [0, 1]


@pytest.mark.parametrize("n", range(1, 65))
def test_nodes_and_weights_match_mpmath_to_a_few_ulp(n):
    nodes, weights = quadrature(n)
    assert np.all(np.diff(nodes) > 0) and nodes[0] > 0 and nodes[-1] < 1
    for i in range(n):
        c_exact, w_exact = mpmath_root(n, nodes[i])
        # relative error in units of eps; a few ulp allowed, we get < 1 (correctly rounded)
        assert abs(float((mp.mpf(nodes[i]) - c_exact) / c_exact)) <= 2 * np.finfo(float).eps, (n, i)
        assert abs(float((mp.mpf(weights[i]) - w_exact) / w_exact)) <= 2 * np.finfo(float).eps, (n, i)
    # Newton from our node must land on a distinct root: nodes are sorted and n of them
    assert abs(weights.sum() - 1.0) <= 4 * n * np.finfo(float).eps


def test_quadrature_rejects_bad_n():
    with pytest.raises(ValueError, match="n must be <= 64"):
        quadrature(65)
    with pytest.raises(ValueError):
        quadrature(0)


@pytest.mark.parametrize("k,s", [(1, 1), (3, 2), (12, 3), (20, 7)])
def test_legendre_tables_match_numpy_polynomials(k, s):
    c, _ = quadrature(k)
    Ps, Is = legendre_tables(c, k, s)
    for j in range(k):
        np.testing.assert_allclose(Ps[:, j], reference.legendre_P(j, c), rtol=1e-13, atol=1e-13)
    for j in range(s):
        np.testing.assert_allclose(Is[:, j], reference.legendre_P_integral(j, c), rtol=1e-12, atol=1e-14)


def test_legendre_basis_is_orthonormal_under_gauss_quadrature():
    c, b = quadrature(12)
    Ps, _ = legendre_tables(c, 12, 1)
    np.testing.assert_allclose(Ps.T @ np.diag(b) @ Ps, np.eye(12), atol=1e-13)


@pytest.mark.parametrize("k,s", [(2, 2), (5, 5), (12, 3), (24, 6), (64, 8)])
def test_the_methods_integral_tables_are_the_exact_integrals_as_double_doubles(k, s):
    """docs/methods.md#round-off-over-long-times: a method's Is + Is_low is int_0^{c_l} P_j at the exact
    Gauss node to double-double accuracy (Is rounded to doubles made GAUSS(2)'s H drift), and Is is
    that value rounded, within an ulp (the kernels' stages add the low part of the leading term)."""
    from elimfast.methods.base import integral_tables

    nodes, _ = quadrature(k)
    high, low = integral_tables(nodes, s)
    for l in range(k):
        node, _ = mpmath_root(k, nodes[l])
        for j in range(s):
            exact = node if j == 0 else (mp.legendre(j + 1, 2 * node - 1) - mp.legendre(j - 1, 2 * node - 1)) / (
                2 * mp.sqrt(2 * j + 1))
            assert abs(mp.mpf(high[l, j]) + mp.mpf(low[l, j]) - exact) <= mp.mpf(1e-30) * max(1, abs(exact)), (l, j)
            assert abs(float(exact - mp.mpf(high[l, j]))) <= np.spacing(abs(high[l, j])), (l, j)
