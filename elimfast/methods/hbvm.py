"""GAUSS(s) and HBVM(k,s): spec section 2."""
from .base import Method, build


def hbvm(k: int, s: int) -> Method:
    """HBVM(k,s), k >= s >= 1: order 2s, energy-conserving for polynomial H of degree <= 2k/s."""
    return build("hbvm", k, k, s)


def gauss(s: int) -> Method:
    """GAUSS(s) = HBVM(s,s): the s-stage Gauss-Legendre collocation method, order 2s, symplectic."""
    return build("gauss", s, s, s)
