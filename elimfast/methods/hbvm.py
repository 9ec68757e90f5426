"""GAUSS(s) and HBVM(k,s): docs/methods.md#hbvm."""
from .base import IMPOSES_NONE, Family, Method, build, register


def hbvm(k: int, s: int) -> Method:
    """HBVM(k,s), k >= s >= 1: order 2s, energy-conserving for polynomial H of degree <= 2k/s."""
    return build("hbvm", k, k, s)


def gauss(s: int) -> Method:
    """GAUSS(s) = HBVM(s,s): the s-stage Gauss-Legendre collocation method, order 2s, symplectic."""
    return build("gauss", s, s, s)


# The kernels run both as ELIM imposing nothing: with nu = 0 its map is HBVM's.
_NO_INVARIANTS = dict(kernel_map="elim", imposes=IMPOSES_NONE, multiplier=None, multiplier_counts_H=False,
                      imposes_linear=False, linear_refusal="", scales_tableau=False, has_runge_kutta_form=True)

register(Family(
    name="gauss", parameters=("s",), constructor=gauss, **_NO_INVARIANTS,
    description="s-stage Gauss-Legendre collocation, order 2s, symplectic; imposes no invariant",
    notes="Keeps quadratic invariants exactly and H only up to O(h^(2s)) oscillations; GAUSS(s) = HBVM(s,s).",
    docs="docs/methods.md#hbvm"))
register(Family(
    name="hbvm", parameters=("k", "s"), constructor=hbvm, **_NO_INVARIANTS,
    description="Hamiltonian BVM, order 2s, conserves polynomial H of degree <= 2k/s; imposes no invariant",
    notes="Keeps H to round-off when H is a polynomial of degree <= 2k/s, else up to the O(h^(2k+1)) quadrature "
          "error of its k nodes per step: raise k when H drifts.",
    docs="docs/methods.md#hbvm"))
