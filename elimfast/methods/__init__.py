"""Methods as data: ``gauss(s)``, ``hbvm(k, s)``, ``elim(r, k, s)``, ``ehbvm(k, s)``,
``lim(r, k, s)``, ``ghbvm(k, s)``; ``FAMILIES`` maps each name to what the family does
(``Family``), ``METHODS`` to its constructor. A new family is one module here that
declares its ``Family`` (and its kernel map)."""
import difflib

from ..errors import ParameterError
from .base import (FAMILIES, IMPOSES_ANY, IMPOSES_FEWER_THAN_S, IMPOSES_NONE, MAX_NODES, Family, Method,
                   legendre_tables, quadrature)
# Imported in the order the registry lists the families (listings, `elimfast methods`).
from .hbvm import gauss, hbvm  # noqa: I001
from .elim import ehbvm, elim
from .lim import ghbvm, lim

METHODS = {name: family.constructor for name, family in FAMILIES.items()}


def family(name: str) -> Family:
    """The family registered under name (any case); ParameterError('name', ...) naming the known ones."""
    key = name.strip().lower() if isinstance(name, str) else name
    if key not in FAMILIES:
        known = ", ".join(FAMILIES)
        close = difflib.get_close_matches(str(key), list(FAMILIES), n=1, cutoff=0.6)
        hint = f"did you mean {close[0]!r}? (known: {known})" if close else f"known: {known}"
        raise ParameterError("name", f"is not a known method: {name!r}; {hint}")
    return FAMILIES[key]


def get(name: str, **parameters) -> Method:
    """Build a method by registry name, e.g. ``get("ehbvm", k=12, s=3)``.

    Every fault is a ParameterError naming the parameter (name, r, k or s) and the fix.
    """
    kind = family(name)
    signature = kind.signature()
    for parameter in parameters:
        if parameter not in kind.parameters:
            raise ParameterError(parameter, f"does not apply: {signature} takes no {parameter}; remove it")
    missing = [parameter for parameter in kind.parameters if parameter not in parameters]
    if missing:
        also = f", and so {'is' if len(missing) == 2 else 'are'} {' and '.join(missing[1:])}" if missing[1:] else ""
        raise ParameterError(missing[0], f"is missing{also}; {signature} needs {', '.join(kind.parameters)}")
    return kind.constructor(**parameters)


__all__ = ["FAMILIES", "METHODS", "MAX_NODES", "Family", "Method", "family", "get", "gauss", "hbvm", "elim",
           "ehbvm", "lim", "ghbvm", "quadrature", "legendre_tables", "IMPOSES_NONE", "IMPOSES_FEWER_THAN_S",
           "IMPOSES_ANY"]
