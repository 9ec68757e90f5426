"""LIM(r,k,s) and GHBVM(k,s) = LIM(k,k,s): spec section 4 (Brugnano & Iavernaro 2012)."""
from .base import Method, build


def lim(r: int, k: int, s: int) -> Method:
    """LIM(r,k,s): HBVM(k,s) with a correction -c h phi_0 lambda imposing H and the chosen invariants."""
    return build("lim", r, k, s)


def ghbvm(k: int, s: int) -> Method:
    """GHBVM(k,s) = LIM(k,k,s)."""
    return build("ghbvm", k, k, s)
