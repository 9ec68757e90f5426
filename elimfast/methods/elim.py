"""ELIM(r,k,s) and EHBVM(k,s) = ELIM(k,k,s): spec section 3 (the paper's new methods)."""
from .base import Method, build


def elim(r: int, k: int, s: int) -> Method:
    """ELIM(r,k,s): HBVM(k,s) whose last nu coefficients are scaled to conserve nu < s invariants."""
    return build("elim", r, k, s)


def ehbvm(k: int, s: int) -> Method:
    """EHBVM(k,s) = ELIM(k,k,s)."""
    return build("ehbvm", k, k, s)
