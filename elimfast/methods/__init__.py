"""Methods as data: ``gauss(s)``, ``hbvm(k, s)``, ``elim(r, k, s)``, ``ehbvm(k, s)``,
``lim(r, k, s)``, ``ghbvm(k, s)``; ``FAMILIES`` maps each name to what the family does
(``Family``), ``METHODS`` to its constructor. A new family is one module here that
declares its ``Family`` (and its kernel map)."""
import difflib
import re

from ..errors import ParameterError
from .base import (FAMILIES, IMPOSES_ANY, IMPOSES_FEWER_THAN_S, IMPOSES_NONE, MAX_NODES, Family, Method,
                   integrates_exactly, legendre_tables, quadrature)
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
            # related: a --set of the name that made it so is named (a user trial: --set method.name=gauss
            # was told only to edit the file's k)
            raise ParameterError(parameter, f"does not apply: {signature} takes no {parameter}; remove it",
                                 related=("name",))
    missing = [parameter for parameter in kind.parameters if parameter not in parameters]
    if missing:
        also = f", and so {'is' if len(missing) == 2 else 'are'} {' and '.join(missing[1:])}" if missing[1:] else ""
        raise ParameterError(missing[0], f"is missing{also}; {signature} needs {', '.join(kind.parameters)}",
                             related=("name",))
    return kind.constructor(**parameters)


__all__ = ["FAMILIES", "METHODS", "MAX_NODES", "Family", "Method", "family", "get", "gauss", "hbvm", "elim",
           "ehbvm", "lim", "ghbvm", "quadrature", "legendre_tables", "IMPOSES_NONE", "IMPOSES_FEWER_THAN_S",
           "IMPOSES_ANY", "integrates_exactly", "from_notation", "as_method"]


_NOTATION = re.compile(r"\s*([A-Za-z]+)\s*\(([^()]*)\)\s*")


def _notation_example(name: str, kind: Family) -> str:
    """``name`` with example numbers for the family's parameters, e.g. EHBVM(12,3), ELIM(8,12,3)."""
    return f"{name}({','.join(str(n) for n in (8, 12, 3)[-len(kind.parameters):])})"


def _malformed_notation(text: str) -> str:
    """What is wrong with ``text``, which has parentheses but not the paper's notation, and the
    form expected (the family's own where ``text`` begins with a known name)."""
    opened, closed = text.count("("), text.count(")")
    if opened != closed:
        fault = f"is unbalanced: a {')' if opened > closed else '('!r} is missing"
    else:
        fault = "is malformed"
    start = re.match(r"\s*([A-Za-z]+)", text)
    kind = FAMILIES.get(start.group(1).lower()) if start else None
    if kind is not None:
        name = start.group(1).upper()
        form = f"{name}({','.join(kind.parameters)}), e.g. {_notation_example(name, kind)}"
    else:
        form = "NAME(s), NAME(k,s) or NAME(r,k,s), e.g. EHBVM(12,3)"
    return f"{text.strip()!r} {fault}; expected {form}"


def from_notation(text: str) -> dict | None:
    """A method written as the paper writes it, ``EHBVM(12,3)``, ``GAUSS(4)``, ``ELIM(8,12,3)``
    (any case, spaces allowed), as ``{"name": family, parameter: value, ...}`` in the order of
    the family's parameters (Family.parameters); None when ``text`` has no parentheses (a
    family's name, say). ParameterError('name', ...) for parentheses that do not make the
    notation (unbalanced or malformed), an unknown family or numbers that do not fit its parameters."""
    if not isinstance(text, str):
        return None
    match = _NOTATION.fullmatch(text)
    if match is None:
        if "(" in text or ")" in text:
            raise ParameterError("name", _malformed_notation(text))
        return None
    kind = family(match.group(1))
    numbers = [part.strip() for part in match.group(2).split(",")]
    if len(numbers) != len(kind.parameters) or not all(part.isdigit() for part in numbers):
        raise ParameterError("name", f"{text.strip()!r}: {kind.signature()} takes {len(kind.parameters)} whole "
                                     f"number{'s' if len(kind.parameters) > 1 else ''} ({', '.join(kind.parameters)}), "
                                     f"e.g. {_notation_example(match.group(1), kind)}")
    return {"name": match.group(1).strip().lower(), **{name: int(part) for name, part in zip(kind.parameters, numbers)}}


def as_method(value) -> Method:
    """``value`` if it is a Method, else the method a string names in the paper's notation
    (``"EHBVM(12,3)"``, from_notation): what integrate and integrate_ensemble take. Other values
    are returned as they are (the caller's type check names them)."""
    if isinstance(value, str):
        try:
            parameters = from_notation(value)
        except ParameterError as err:   # named as the caller's argument
            raise ParameterError("method", err.detail) from None
        if parameters is None:
            if value.strip().lower() not in FAMILIES:
                raise ParameterError("method", f"{value!r} is not a method: give an elimfast Method (e.g. "
                                               "elimfast.methods.ehbvm(12, 3)) or one in the paper's notation, "
                                               "e.g. 'EHBVM(12,3)'")
            kind = family(value)   # a bare family name: say what it needs
            raise ParameterError("method", f"{value!r} names the family, not a method: write its parameters as the "
                                           f"paper does, e.g. {kind.signature()} as "
                                           f"'{_notation_example(value.strip().upper(), kind)}'")
        return get(**parameters)
    return value
