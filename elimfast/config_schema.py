"""The schema of a run config: pydantic models of its sections, types and keys only (what
the values mean is checked in ``config._Builder``).

Imported only when pydantic validates a config. ``config.load_run`` keeps each validation
of a config file in elimfast's cache as ``config.Section`` objects, keyed by the config's
data, the text of this module and of the modules it takes rules from, and pydantic's
version (``config.SCHEMA_SOURCES``); a config run before is then not validated again and
pydantic is not imported (about 60 ms of CPU, a tenth of a warm ``elimfast run``).
"""
from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, StrictBool, ValidationError  # noqa: F401

from .config import Section, _short
from .integrate import DEFAULT_MAX_HALVINGS, DEFAULT_SOLVER
from .problems.expressions import ExpressionError, evaluate_number


# --- scalar types -------------------------------------------------------------------------

def _to_number(value):
    # A ValueError here is reported by pydantic as a value_error with this text.
    if not isinstance(value, str):
        return evaluate_number(value, what="the value")
    try:
        return evaluate_number(value, what="value")
    except ExpressionError as err:
        detail = err.detail
        raise ValueError(f"{_short(value)} is not a number ({detail}); write a number or arithmetic on numbers, "
                         "pi and e, e.g. pi/30") from None


def _to_int(value):
    if isinstance(value, bool):
        raise ValueError(f"must be a whole number, got {value!r}")
    if isinstance(value, int):
        return value
    number = _to_number(value)
    if not number.is_integer():
        raise ValueError(f"must be a whole number, got {value!r}")
    return int(number)


def _to_list_of_names(value):
    if value is None:
        return []
    return [value] if isinstance(value, str) else value


def _whole_number_or_as_given(value):
    # For keys whose rule belongs to the API's validator (an event's direction: adaptive.events),
    # which then names the values allowed: 'up' was told "is not a number ... did you mean 'pi'?".
    try:
        return _to_int(value)
    except ValueError:
        return value


Number = Annotated[float, BeforeValidator(_to_number)]
Integer = Annotated[int, BeforeValidator(_to_int)]
IntegerOrAsGiven = Annotated[Any, BeforeValidator(_whole_number_or_as_given)]


# --- the schema (types and keys only; meaning is checked in _Builder) ---------------------

class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=False)


class CoordinatesSection(_Section):
    q: list[str]
    p: list[str]


class ProblemSection(_Section):
    builtin: str | None = None
    python: str | None = None
    coordinates: CoordinatesSection | None = None
    hamiltonian: str | None = None
    invariants: dict[str, str] | None = None
    name: str | None = None
    parameters: dict[str, Any] | None = None
    initial: dict[str, Any] | None = None
    check: StrictBool = True
    time_scale: str | None = None


class MethodSection(_Section):
    name: str
    r: Integer | None = None
    k: Integer | None = None
    s: Integer | None = None


class IntegrationSection(_Section):
    h: Number | None = None
    t_end: Number | None = None
    n_steps: Integer | None = None
    t0: Number = 0.0
    # Adaptive steps (docs/adaptive.md): rtol (error control) or step_control: time_scale.
    rtol: Number | None = None
    atol: Number | None = None
    step_control: Literal["error", "time_scale"] | None = None
    epsilon: Number | None = None
    verify: StrictBool | None = None   # None: step doubling where the cheap estimate is not trusted
    h_max: Number | None = None


class TimesSection(_Section):
    start: Number
    stop: Number
    step: Number | None = None
    n: Integer | None = None


class EventSection(_Section):
    expression: str
    direction: IntegerOrAsGiven = 0
    terminal: StrictBool = False


def _event_shorthand(value):
    """events: {name: "<expression>"} is short for {name: {expression: "<expression>"}}, as in
    elimfast.integrate(events=...) (adaptive.EventSpec)."""
    if isinstance(value, dict):
        return {name: {"expression": entry} if isinstance(entry, str) else entry for name, entry in value.items()}
    return value


class SolverSection(_Section):
    method: str = DEFAULT_SOLVER
    tol: Number | None = None
    max_iter: Integer | None = None
    max_halvings: Integer = DEFAULT_MAX_HALVINGS
    predictor: StrictBool = True
    rhs: Literal["stable", "literal"] = "stable"
    warm_start: StrictBool = True
    accelerate: StrictBool = True
    lim_metric: Literal["euclidean", "scaled"] = "euclidean"
    kernel: Literal["shared", "per_problem"] = "shared"
    project_energy: StrictBool = False


class OutputSection(_Section):
    path: str | None = None
    every: Integer = 1
    times: TimesSection | list[Number] | None = None


class RunConfig(_Section):
    problem: ProblemSection
    conserve: Annotated[list[str], BeforeValidator(_to_list_of_names)] = []
    method: MethodSection
    integration: IntegrationSection
    solver: SolverSection = SolverSection()
    output: OutputSection = OutputSection()
    events: Annotated[dict[str, EventSection] | None, BeforeValidator(_event_shorthand)] = None


# The model of each section, by its key path (config._Builder.describe names the allowed keys); "*" stands
# for the name of an entry of a mapping of sections (an event).
SECTIONS = {(): RunConfig, ("problem",): ProblemSection, ("problem", "coordinates"): CoordinatesSection,
            ("method",): MethodSection, ("integration",): IntegrationSection, ("solver",): SolverSection,
            ("output",): OutputSection, ("output", "times"): TimesSection, ("events", "*"): EventSection}


def config_location(location: tuple) -> tuple:
    """A pydantic error's location as a config key path: without the parts by which pydantic
    names the member of a union an error is about (output.times.TimesSection.start,
    output.times.list[function-before[_to_number(), float]][1]), which no config key is."""
    members = {model.__name__ for model in SECTIONS.values()}
    return tuple(part for part in location if not (isinstance(part, str) and (part in members or "[" in part)))


def member_mismatch(error: dict) -> bool:
    """A pydantic error that only says the value is not of one member's type of a union
    (output.times given as a list: not a TimesSection). When the value fits another member,
    that member's error (output.times[1]: 'foo' is not a number) is the one to report; it
    was reported as 'must be a mapping'."""
    location = error["loc"]
    members = {model.__name__ for model in SECTIONS.values()}
    return (error["type"] in ("model_type", "model_attributes_type", "dict_type", "list_type") and bool(location)
            and isinstance(location[-1], str) and (location[-1] in members or "[" in location[-1]))


def sections(value):
    """A validated model as config.Section objects (plain data, no pydantic): each model a
    Section of its fields in declaration order, dicts and lists copied, scalars as they are."""
    if isinstance(value, BaseModel):
        return Section({name: sections(getattr(value, name)) for name in type(value).model_fields})
    if isinstance(value, dict):
        return {key: sections(item) for key, item in value.items()}
    if isinstance(value, list):
        return [sections(item) for item in value]
    return value
