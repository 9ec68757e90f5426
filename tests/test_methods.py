"""Methods as data: validation, names, the registry and the Butcher tableaux (docs/methods.md#hbvm, #elim)."""
import math

import numpy as np
import pytest

from elimfast import methods
from elimfast.methods import METHODS, ehbvm, elim, gauss, ghbvm, hbvm, lim

import reference


def gauss_collocation_tableau(s):
    """The s-stage Gauss method from its definition: A[i, j] = int_0^{c_i} l_j, b_j = int_0^1 l_j."""
    c, _ = reference.gauss_legendre(s)
    A = np.zeros((s, s))
    b = np.zeros(s)
    for j in range(s):
        others = np.delete(c, j)
        basis = (np.polynomial.Polynomial.fromroots(others) if others.size else np.polynomial.Polynomial([1.0]))
        basis = basis / np.prod(c[j] - others)
        primitive = basis.integ()
        A[:, j] = primitive(c) - primitive(0.0)
        b[j] = primitive(1.0) - primitive(0.0)
    return A, b, c


@pytest.mark.parametrize("method", [gauss(1), gauss(3), hbvm(6, 2), hbvm(12, 3), elim(8, 12, 3), ehbvm(20, 7),
                                    hbvm(40, 10)], ids=lambda m: m.name)
def test_tableau_properties(method):
    A, b, c = method.butcher()
    assert A.shape == (method.k, method.k)
    assert abs(b.sum() - 1.0) <= 1e-14
    np.testing.assert_allclose(A @ np.ones(method.k), c, rtol=1e-14, atol=1e-14)
    # order conditions: the quadrature integrates polynomials of degree < 2k exactly
    for q in range(1, 2 * method.k + 1):
        assert abs(b @ c ** (q - 1) - 1.0 / q) <= 1e-13


@pytest.mark.parametrize("s", range(1, 7))
def test_hbvm_s_s_is_the_gauss_method(s):
    A, b, c = hbvm(s, s).butcher()
    A_ref, b_ref, c_ref = gauss_collocation_tableau(s)
    np.testing.assert_allclose(A, A_ref, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(b, b_ref, rtol=1e-13)
    np.testing.assert_allclose(c, c_ref, rtol=1e-13)
    np.testing.assert_allclose(gauss(s).butcher()[0], A_ref, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("eta1", [1.0, 0.7, -0.3, 1.9])
@pytest.mark.parametrize("r", [2, 3, 5])
def test_paper_elim_r22_tableau(r, eta1):
    """The closed form printed in the paper (section 2.3) for ELIM(r,2,2)."""
    A, b, c = elim(r, 2, 2).butcher(eta=[eta1])
    q = math.sqrt(3.0)
    expected = np.array([[0.25 + (eta1 - 1) * q / 12, 0.25 - (eta1 + 1) * q / 12],
                         [0.25 + (eta1 + 1) * q / 12, 0.25 - (eta1 - 1) * q / 12]])
    np.testing.assert_allclose(A, expected, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(b, [0.5, 0.5], rtol=1e-15)
    np.testing.assert_allclose(c, [0.5 - q / 6, 0.5 + q / 6], rtol=1e-15)


def test_butcher_matches_reference_construction():
    for method, eta in [(hbvm(12, 3), None), (ehbvm(12, 3), [1.0, 0.98, 0.9])]:
        A, _, _ = method.butcher(eta)
        A_ref, _, _ = reference.butcher_hbvm(method.k, method.s, None if eta is None else np.array(eta))
        np.testing.assert_allclose(A, A_ref, rtol=1e-12, atol=1e-14)


def test_names_and_orders():
    assert gauss(3).name == "GAUSS(3)"
    assert hbvm(12, 3).name == "HBVM(12,3)"
    assert ehbvm(12, 3).name == "EHBVM(12,3)"
    assert ghbvm(12, 3).name == "GHBVM(12,3)"
    assert elim(8, 12, 3).name == "ELIM(8,12,3)"
    assert lim(8, 12, 3).name == "LIM(8,12,3)"
    assert [m.order for m in (gauss(1), hbvm(12, 3), ehbvm(9, 4))] == [2, 6, 8]


def test_methods_compare_by_family_and_parameters():
    """A user trial: ehbvm(12, 3) == ehbvm(12, 3) was False (identity). Methods built alike are
    equal and hash alike (one dict entry, one set member); other parameters or another family
    name are not."""
    assert ehbvm(12, 3) == ehbvm(12, 3) == methods.as_method("EHBVM(12,3)")
    assert len({ehbvm(12, 3), ehbvm(12, 3), methods.get("ehbvm", k=12, s=3)}) == 1
    assert ehbvm(12, 3) != ehbvm(12, 4) and ehbvm(12, 3) != hbvm(12, 3) and elim(8, 12, 3) != elim(12, 12, 3)
    assert ehbvm(12, 3) != elim(12, 12, 3)   # the same method, named apart
    assert gauss(3) != "GAUSS(3)" and gauss(3) != hbvm(3, 3)   # a string is not built; HBVM(3,3) is named apart


def test_registry_builds_every_family():
    assert set(METHODS) == {"gauss", "hbvm", "elim", "ehbvm", "lim", "ghbvm"}
    assert methods.get("ehbvm", k=12, s=3).name == "EHBVM(12,3)"
    assert methods.get("GAUSS", s=2).name == "GAUSS(2)"
    with pytest.raises(ValueError, match="not a known method: 'rk4'"):
        methods.get("rk4", s=4)
    with pytest.raises(ValueError, match="s is missing"):
        methods.get("hbvm", k=4)


@pytest.mark.parametrize("build,match", [
    (lambda: hbvm(2, 3), "k must be >= s"),
    (lambda: hbvm(3, 0), "s must be >= 1"),
    (lambda: elim(2, 4, 3), "r must be >= s"),
    (lambda: lim(1, 4, 2), "r must be >= s"),
    (lambda: hbvm(65, 3), "<= 64"),
    (lambda: gauss(2.5), "integer"),
    (lambda: gauss(True), "integer"),
])
def test_invalid_methods_are_rejected_with_a_reason(build, match):
    with pytest.raises((ValueError, TypeError), match=match):
        build()


def test_lim_has_no_fixed_runge_kutta_form():
    with pytest.raises(ValueError, match="no fixed Runge-Kutta form"):
        ghbvm(12, 3).butcher()
