"""Methods as data: ``gauss(s)``, ``hbvm(k, s)``, ``elim(r, k, s)``, ``ehbvm(k, s)``,
``lim(r, k, s)``, ``ghbvm(k, s)``, and the registry ``METHODS`` mapping names to them."""
import inspect

from .base import MAX_NODES, Method, legendre_tables, quadrature
from .elim import ehbvm, elim
from .hbvm import gauss, hbvm
from .lim import ghbvm, lim

METHODS = {
    "gauss": gauss,
    "hbvm": hbvm,
    "elim": elim,
    "ehbvm": ehbvm,
    "lim": lim,
    "ghbvm": ghbvm,
}


def get(name: str, **parameters) -> Method:
    """Build a method by registry name, e.g. ``get("ehbvm", k=12, s=3)``."""
    try:
        constructor = METHODS[name.lower()]
    except (KeyError, AttributeError):
        raise ValueError(f"unknown method {name!r}; known: {', '.join(METHODS)}") from None
    expected = list(inspect.signature(constructor).parameters)
    missing = [p for p in expected if p not in parameters]
    extra = [p for p in parameters if p not in expected]
    if missing or extra:
        raise ValueError(f"{name}({', '.join(expected)}) takes exactly {', '.join(expected)}"
                         + (f"; missing {', '.join(missing)}" if missing else "")
                         + (f"; unexpected {', '.join(extra)}" if extra else ""))
    return constructor(**parameters)


__all__ = ["METHODS", "MAX_NODES", "Method", "get", "gauss", "hbvm", "elim", "ehbvm", "lim",
           "ghbvm", "quadrature", "legendre_tables"]
