"""Run configs: YAML -> one validated, frozen ``RunSpec``.

The rules are the library's: ``methods.get`` checks the method, ``resolve_steps`` the
integration, ``SolverSettings`` the solver, ``resolve_conserve`` the invariants to
impose; each raises a ParameterError naming its parameter and the fix, and this module
puts the YAML key in front of it (``PARAMETER_KEYS``). What is checked here is only what
the YAML itself can get wrong: keys, types, sections, and the problem's definition.

Format (every section but ``problem``, ``method`` and ``integration`` is optional)::

    problem:
      builtin: kepler                  # a name in elimfast.problems.PROBLEMS, or
      # python: kepler_problem.py      # a problem file (relative to this config), or
      # coordinates: {q: [q1, q2], p: [p1, p2]}      # a problem by expressions:
      # hamiltonian: "(p1**2 + p2**2)/2 - mu/sqrt(q1**2 + q2**2)"
      # invariants: {angular_momentum: "q1*p2 - q2*p1"}
      # name: my_kepler                # expressions / python: the name in reports
      parameters: {eccentricity: 0.6}  # keyword parameters of the problem
      initial: {q1: 0.4, p2: 2.0}      # builtin/python: overrides of the default state;
                                       # expressions: every coordinate (may use parameters)
      check: true                      # check the derivatives and invariants at load (false: skip)
      time_scale: "(q1**2 + q2**2)**0.75"  # optional: sigma(y) for step_control: time_scale
    conserve: [angular_momentum, lrl_y]  # invariants to impose (ELIM/EHBVM: < s; LIM/GHBVM: any)
    method: {name: ehbvm, k: 12, s: 3}   # gauss(s) hbvm(k,s) elim(r,k,s) ehbvm(k,s) lim(r,k,s) ghbvm(k,s)
    integration: {h: pi/30, t_end: 20*pi, t0: 0}   # or n_steps instead of t_end (both: must agree)
    # integration: {rtol: 1e-12, t_end: 2000*pi}   # adaptive steps (docs/adaptive.md): rtol [atol, h (first
    #   step), h_max, verify], or step_control: time_scale with epsilon; method k defaults to 2s
    solver: {method: auto, max_halvings: 4}     # optional; see docs/solver.md (method: newton, fixed_point;
                                                #   tol, max_iter, predictor, warm_start, rhs, accelerate)
    output: {path: out/kepler.h5, every: 10}        # path as given (the CLI resolves it)
    #   times: {start: 0, stop: 100, step: 0.5}     # or a list: samples at these times (side steps)
    events:                                         # optional: g(y) = 0, located to the integrator's accuracy
      pericentre: {expression: "q1*p1 + q2*p2", direction: 1, terminal: false}

Numbers may be arithmetic on numbers, ``pi`` and ``e`` (``pi/30``, ``2*pi*10``, ``1e-15``),
evaluated in double precision exactly as Python would (``pi/30 == math.pi/30``); initial
values may also use the problem's parameters. Nothing in a config can run code: YAML is
read with a safe loader (no tags, no aliases; a key given twice is an error) and expressions
are parsed as data. A ``python:`` problem file is code, so a config naming one is refused
unless the user allowed Python files outside the config (``python_allowed``: the CLI's
``--allow-python``, ``allow_python=True`` in Python, or ELIMFAST_ALLOW_PYTHON=1), as
``numpy.load`` refuses pickles unless ``allow_pickle=True``.

The keys and types are validated by pydantic (config_schema.py); ``load_run`` keeps each
validation in elimfast's cache, so that a config run again skips pydantic (_Builder.validate).
Every error is a ``ConfigError`` whose text is one line, ``FILE:LINE: key.path: what is
wrong; what to do`` (LINE: where the key is, or its parent mapping for a missing key; no
line for data not read from a file, and a value given by ``--set`` names that option
instead). ``load_run(path, overrides)`` applies ``--set``-style overrides (``"method.s=4"``,
values parsed as YAML) before validating.
"""
from __future__ import annotations

import contextlib
import contextvars
import copy
import functools
import inspect
import json
import os
import pickle
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from .cache import CacheError, content_hash
from . import methods
from .errors import ElimfastError, ParameterError
from .integrate import (SolverSettings, resolve_conserve, resolve_initial_state, resolve_steps, resolve_store_every,
                        suggest)
from .integrate import compact_number as _count
from .integrate import compact_number
from .methods import Method
from .problems.base import Problem
from .problems.expressions import ProblemDefinitionError, did_you_mean, evaluate_number

MAX_FILE_BYTES = 1 << 20     # a config (or sweep, or python: problem file) larger than 1 MiB is a mistake
MAX_YAML_NODES = 100_000     # scalars + containers in one config
MAX_YAML_DEPTH = 20          # nesting of sections and lists
# Ranges of the numbers in a config, each with its reason (said in the error); the ranges
# of h, n_steps, output.every and the solver's settings are the library's (integrate.py).
MAX_SIZE_PARAMETER = 100_000  # an integer size parameter of a built-in (fpu_beta's n): a state of 2n numbers


class ConfigError(ElimfastError):
    """An invalid run config. ``str(err)`` is one line ``FILE:LINE: key.path: what is wrong; what
    to do`` (``FILE: key.path: ...`` where the key has no line: data not read from a file, a
    key missing at the top level, or a value given by ``--set``, which the message then names);
    ``messages`` holds every error found (the first one is ``str(err)``); ``key`` the dotted
    key; ``line`` its 1-based line in FILE, or None."""

    def __init__(self, message: str, messages: tuple[str, ...] = (), key: str | None = None,
                 line: int | None = None):
        message = " ".join(str(message).split())
        super().__init__(message)
        self.messages = tuple(" ".join(m.split()) for m in messages) or (message,)
        self.key = key
        self.line = line


# --- validated sections (config_schema.py holds their pydantic models) ---------------------

class Section:
    """One validated section of a config, as plain data: its fields as attributes (a
    sub-section a Section), ``model_dump()`` as pydantic's. What ``config_schema.RunConfig``
    validates, converted (config_schema.sections) or read back from the cache of validations."""

    __slots__ = ("_fields",)

    def __init__(self, fields: dict):
        self._fields = fields

    def __getattr__(self, name):
        try:
            return self._fields[name]
        except KeyError:
            raise AttributeError(name) from None

    def __reduce__(self):   # pickled with its fields (the default would call __getattr__ before they exist)
        return Section, (self._fields,)

    def __repr__(self) -> str:
        return f"Section({self._fields!r})"

    def model_dump(self) -> dict:
        return {name: _dump(value) for name, value in self._fields.items()}


def _dump(value):
    if isinstance(value, Section):
        return value.model_dump()
    if isinstance(value, dict):
        return {key: _dump(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_dump(item) for item in value]
    return value


VALIDATED_FORMAT = "validated-config-v1"


@functools.lru_cache(maxsize=1)
def _schema_stamp() -> str:
    """pydantic's version and the text of the schema's sources (SCHEMA_SOURCES), read without
    importing pydantic: its version.py (0.5 ms; importlib.metadata takes 3 ms to find it)."""
    from importlib.util import find_spec

    found = find_spec("pydantic")
    parts = [Path(found.origin).with_name("version.py").read_text(encoding="utf-8")] if found and found.origin else []
    package = Path(__file__).resolve().parent
    parts += [(package / name).read_text(encoding="utf-8") for name in SCHEMA_SOURCES]
    return content_hash(*parts)


# What a validation depends on besides the data and pydantic: the models, the defaults they
# take (integrate.py) and the evaluation of numbers (problems/expressions.py).
SCHEMA_SOURCES = ("config_schema.py", "integrate.py", "problems/expressions.py")


def _validation_key(data) -> str | None:
    """The cache key of validating ``data`` (None: not cached; data holding YAML types that
    JSON has not, such as dates, is validated every time)."""
    try:
        text = json.dumps(data, allow_nan=True)
    except (TypeError, ValueError):
        return None
    try:
        return content_hash(VALIDATED_FORMAT, _schema_stamp(), text)
    except OSError:
        return None


def _validated_path(key: str) -> Path:
    from .cache import VALIDATED_SUBDIR, cache_dir
    return cache_dir() / VALIDATED_SUBDIR / key


def _read_validated(key: str) -> Section | None:
    """The sections stored for key, or None (none stored, or unreadable: validated again)."""
    try:
        stored_key, config = pickle.loads(_validated_path(key).read_bytes())
    except Exception:   # noqa: BLE001 -- missing, cut short or garbage: a miss
        return None
    return config if stored_key == key and isinstance(config, Section) else None


def _write_validated(key: str, config: Section) -> None:
    """Store a validation; best effort (an unwritable cache only costs the next run the validation)."""
    from .cache import write_atomic
    try:
        # Not synced: a file cut short by a crash fails to load (or to match its key), a miss.
        write_atomic(_validated_path(key), pickle.dumps((key, config)), sync=False)
    except (OSError, pickle.PicklingError):
        pass


_EXAMPLES = {
    "problem": "add e.g. problem: {builtin: kepler}",
    "method": "add e.g. method: {name: ehbvm, k: 12, s: 3}",
    "integration": "add e.g. integration: {h: 0.1, t_end: 1000} (or {rtol: 1e-12, t_end: 1000}, adaptive)",
    "integration.h": "give the step size, e.g. h: pi/30, or rtol: 1e-12 for adaptive steps",
    "method.name": f"name one of {', '.join(methods.FAMILIES)}",
}

# The YAML key of each parameter of the library's validators. Solver settings live under
# solver.<parameter> (SolverSettings' own names, see _Builder.solver).
PARAMETER_KEYS = {
    "name": ("method", "name"), "r": ("method", "r"), "k": ("method", "k"), "s": ("method", "s"),
    "h": ("integration", "h"), "t_end": ("integration", "t_end"), "n_steps": ("integration", "n_steps"),
    "t0": ("integration", "t0"), "store_every": ("output", "every"), "conserve": ("conserve",),
    "rtol": ("integration", "rtol"), "atol": ("integration", "atol"), "step_control": ("integration", "step_control"),
    "epsilon": ("integration", "epsilon"), "verify": ("integration", "verify"), "h_max": ("integration", "h_max"),
    "method": ("method",), "t_eval": ("output", "times"), "events": ("events",),
    "time_scale": ("problem", "time_scale"), "y0": ("problem", "initial"),
}


# --- the result -------------------------------------------------------------------------

@dataclass(frozen=True)
class RunSpec:
    """A validated run: everything the driver needs, and the resolved config for the record."""

    source: str
    problem: Problem
    method: Method
    conserve: tuple[str, ...]
    h: float
    n_steps: int
    t0: float
    t_end: float
    solver: SolverSettings
    output_path: str | None
    output_every: int
    resolved: dict
    # Adaptive steps (docs/adaptive.md): the step control (None: fixed steps h), the
    # requested output times (None: every output_every steps) and the events.
    step_control: Any = None
    t_eval: Any = None
    events: dict | None = None

    @property
    def uses_adaptive_kernel(self) -> bool:
        return self.step_control is not None or self.t_eval is not None or bool(self.events)



# --- running a python: problem file: the user's decision, never the config's ------------------

ALLOW_PYTHON_ENV = "ELIMFAST_ALLOW_PYTHON"
# Set for one call (allowing_python): a Dask worker runs the tasks of several clients at once.
_allow_python = contextvars.ContextVar("elimfast_allow_python", default=None)


def python_allowed(allow: bool | None = None) -> bool:
    """May a config's ``python:`` problem file be run? ``allow`` when given (a caller's
    ``allow_python=``), else the innermost ``allowing_python`` (the CLI's ``--allow-python``, for
    its command), else ELIMFAST_ALLOW_PYTHON=1 in the environment (the user's standing leave; a
    sweep's worker processes are given the parent's answer, sweep._worker_init)."""
    if allow is not None:
        return bool(allow)
    here = _allow_python.get()
    if here is not None:
        return here
    return _env_allows_python()


def _env_allows_python() -> bool:
    return os.environ.get(ALLOW_PYTHON_ENV, "").strip().lower() in ("1", "true", "yes", "on")


@contextlib.contextmanager
def allowing_python(allow: bool | None = True):
    """``python_allowed`` is ``allow`` inside (None: unchanged)."""
    if allow is None:
        yield
        return
    token = _allow_python.set(bool(allow))
    try:
        yield
    finally:
        _allow_python.reset(token)


PYTHON_REFUSED = ("is a Python file: running it runs its code, and a config alone never runs code; if you trust "
                  "the file, pass --allow-python (Python: allow_python=True; or set ELIMFAST_ALLOW_PYTHON=1)")
# When the environment allows it, only a caller's allow_python=False refuses: the variable is no fix.
PYTHON_REFUSED_BY_CALLER = ("is a Python file: running it runs its code, and this call was given allow_python=False "
                            f"(which overrides {ALLOW_PYTHON_ENV}); if you trust the file, pass allow_python=True")


def python_refused_text() -> str:
    """Why a python: file was refused, with the fix that applies: PYTHON_REFUSED, or
    PYTHON_REFUSED_BY_CALLER when the environment allows Python files (only a caller's
    allow_python=False refuses then, and setting the variable is no fix)."""
    return PYTHON_REFUSED_BY_CALLER if _env_allows_python() else PYTHON_REFUSED


class PythonNotAllowed(ConfigError):
    """A config names a python: problem file that the user has not allowed (python_allowed): no
    fault of the config, so callers that read a config failing to load as an edit (a sweep's
    --resume) pass it on as it is."""


def python_file_named(data, overrides=(), base_dir=None, source: str = "<dict>") -> Path | None:
    """The python: problem file (resolved) that config data names with the --set items
    ``overrides`` applied, or None; read without loading anything (load_run_from_dict's rules:
    the shorthand ``problem: file.py``, paths relative to ``base_dir``)."""
    try:
        data, _ = _apply_overrides(copy.deepcopy(data), overrides, source)
    except ConfigError:
        return None
    problem = data.get("problem") if isinstance(data, dict) else None
    name = problem if isinstance(problem, str) and problem.endswith(".py") else (
        problem.get("python") if isinstance(problem, dict) else None)
    if not isinstance(name, str):
        return None
    try:
        path = Path(name).expanduser()
        base = Path(base_dir) if base_dir is not None else Path.cwd()
        return (path if path.is_absolute() else base / path).resolve()
    except (OSError, RuntimeError, ValueError):
        return None


# --- entry points -------------------------------------------------------------------------

def load_run(path, overrides=(), *, allow_python: bool | None = None) -> RunSpec:
    """Read, override and validate a YAML run config; raise ConfigError (one line) on any fault.
    ``allow_python``: may a ``python:`` problem file it names be run (default: python_allowed())."""
    source = str(path)
    file_path = Path(path)
    text = read_text_file(file_path, source, what="config file", example="a .yaml file")
    data, lines = parse_yaml_with_lines(text, source)
    if data is None:
        raise ConfigError(f"{source}: the file is empty; a config needs problem, method and integration sections")
    return load_run_from_dict(data, source=source, overrides=overrides, base_dir=file_path.resolve().parent,
                              remember=True, lines=lines, allow_python=allow_python)


def load_run_from_dict(data, source: str = "<dict>", overrides=(), *, base_dir=None, remember: bool = False,
                       lines: dict | None = None, allow_python: bool | None = None) -> RunSpec:
    """Validate config data (as yaml.safe_load returns it); ``base_dir``: where relative
    ``python:`` paths start (default: the current directory). ``remember``: keep the
    validation in elimfast's cache and take it from there when this data comes again
    (load_run does, for config files; a sweep's runs do not: one file per run, while
    their process validates them all with one import of pydantic). ``lines``: the line of
    each key path in ``source`` (parse_yaml_with_lines), for the errors to name.
    ``allow_python``: may a ``python:`` problem file be run (default: python_allowed())."""
    data, overridden = _apply_overrides(copy.deepcopy(data), overrides, source)
    return _Builder(source, overridden, Path(base_dir) if base_dir is not None else Path.cwd(),
                    remember=remember, lines=lines, allow_python=python_allowed(allow_python)).build(data)


def read_text_file(path, source: str, *, what: str = "file", example: str = "a .yaml file",
                   limit: int = MAX_FILE_BYTES) -> str:
    """The UTF-8 text of a regular file of at most ``limit`` bytes; ConfigError otherwise.

    A device (/dev/zero), a FIFO or a socket is refused before reading from it (opened
    non-blocking, checked with fstat), and at most limit + 1 bytes are ever read, so no
    input makes this take long or use much memory.
    """
    import os
    import stat

    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise ConfigError(f"{source}: no such file; check the path") from None
    except IsADirectoryError:
        raise ConfigError(f"{source}: is a directory, not a {what}; give {example}") from None
    except (OSError, TypeError, ValueError) as err:
        reason = getattr(err, "strerror", None) or f"{type(err).__name__}: {err}"
        raise ConfigError(f"{source}: cannot be read ({reason}); check the path and permissions") from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise ConfigError(f"{source}: is a directory, not a {what}; give {example}")
        if not stat.S_ISREG(info.st_mode):
            raise ConfigError(f"{source}: not a regular file (a device, FIFO or socket); give {example}")
        if info.st_size > limit:
            raise ConfigError(f"{source}: the file is {info.st_size} bytes, more than a {what} can be ({limit} "
                              "bytes); check that it is the right file")
        os.set_blocking(fd, True)
        chunks, size = [], 0
        while size <= limit:
            chunk = os.read(fd, limit + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as err:
        raise ConfigError(f"{source}: cannot be read ({err.strerror}); check the path and permissions") from None
    finally:
        os.close(fd)
    if size > limit:
        raise ConfigError(f"{source}: the file is more than {limit} bytes, more than a {what} can be; check that it "
                          "is the right file")
    raw = b"".join(chunks)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(f"{source}: not UTF-8 text (byte {err.start}); save the {what} as UTF-8") from None


# --- YAML ---------------------------------------------------------------------------------

class _SafeLoader(yaml.SafeLoader):
    """yaml.SafeLoader (no tags that build objects) without aliases: configs need none, and
    alias bombs would expand exponentially in validation."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(None, None, "YAML aliases (*name) are not supported; write the value "
                                              "out", event.start_mark)
        return super().compose_node(parent, index)


def parse_yaml(text: str, source: str = "<text>"):
    """yaml safe-load of text; YAML errors become a ConfigError with the line and column."""
    return parse_yaml_with_lines(text, source)[0]


def parse_yaml_with_lines(text: str, source: str = "<text>"):
    """(data, lines): parse_yaml's data, and the 1-based line of every key of the document,
    by key path (mapping keys and list indexes, as ``_Builder`` paths name them: a key that
    is not a string by ``str(key)``). What ``yaml.load`` does (compose the node tree, then
    construct it with the safe loader), keeping the tree to read its marks."""
    try:
        loader = _SafeLoader(text)
        try:
            node = loader.get_single_node()
            _refuse_duplicate_keys(loader, node, source)
            data = loader.construct_document(node) if node is not None else None
            lines = _key_lines(loader, node)
        finally:
            loader.dispose()
        return data, lines
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None) or getattr(err, "context_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(err, "problem", None) or getattr(err, "context", None) or str(err)
        if str(source).endswith(".py"):   # a user trial gave a problem's Python file where a config goes
            raise ConfigError(f"{source}: a Python file, not a YAML config; a problem written in Python is run "
                              f"from a config that names it: problem: {{python: {Path(source).name}}} "
                              "(configs/kepler_python.yaml)") from None
        raise ConfigError(f"{source}: {where}invalid YAML ({problem}); fix the syntax there") from None
    except (RecursionError, MemoryError):
        raise ConfigError(f"{source}: the YAML is nested too deeply; simplify the file") from None
    except ValueError as err:
        # Python refuses to read an integer of more than 4300 digits (a user trial's h: 1000...0 gave an
        # internal error); no number of a config needs that many
        if "integer string conversion" not in str(err):
            raise
        raise ConfigError(f"{source}: a whole number of more than 4300 digits, which Python does not read and "
                          "no config value needs; write numbers with an exponent, e.g. 1e30") from None


def _refuse_duplicate_keys(loader: yaml.SafeLoader, root, source: str) -> None:
    """ConfigError for the first key (in file order) given twice in one mapping: YAML's
    loaders keep the last silently, so a second ``integration:`` section or ``s: 4`` after
    ``s: 3`` would quietly replace the first. Merge keys (<<) are left to the loader (an
    explicit key overrides a merged one, as YAML says)."""
    found = []   # (line and column of the repeat, key, key path of the mapping, mark of the first)
    stack = [(root, ())] if root is not None else []
    while stack:
        node, path = stack.pop()
        if isinstance(node, yaml.MappingNode):
            first = {}
            for key_node, value_node in node.value:
                if isinstance(key_node, yaml.ScalarNode) and key_node.tag != "tag:yaml.org,2002:merge":
                    key = loader.construct_object(key_node)
                    key = key if isinstance(key, str) else str(key)
                    mark = key_node.start_mark
                    if key in first:
                        found.append((mark.line + 1, mark.column, key, path, first[key]))
                    else:
                        first[key] = mark
                    stack.append((value_node, path + (key,)))
                else:
                    stack.append((value_node, path))
        elif isinstance(node, yaml.SequenceNode):
            stack.extend((item, path + (index,)) for index, item in enumerate(node.value))
    if found:
        line, _, key, path, first = min(found, key=lambda item: item[:2])
        where = f"in {_join(path)}" if path else "at the top level"
        earlier = f"line {first.line + 1}" if first.line + 1 != line else f"column {first.column + 1} of this line"
        raise ConfigError(f"{source}:{line}: duplicate key {key!r} {where} (first at {earlier}); keep one of them",
                          key=_join(path + (key,)), line=line)


def _key_lines(loader: yaml.SafeLoader, root) -> dict:
    """{key path: line} of the nodes under root (iterative: depth is bounded later, by check_keys)."""
    lines = {}
    stack = [(root, ())] if root is not None else []
    while stack:
        node, path = stack.pop()
        if isinstance(node, yaml.MappingNode):
            for key_node, value_node in node.value:   # merge keys (<<) are flattened by now
                if not isinstance(key_node, yaml.ScalarNode):
                    continue   # a list or mapping as key: refused by check_keys, which has no line for it
                key = loader.construct_object(key_node)
                key = key if isinstance(key, str) else str(key)
                lines[path + (key,)] = key_node.start_mark.line + 1   # repeats only by << (explicit wins, as in data)
                stack.append((value_node, path + (key,)))
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                lines[path + (index,)] = item.start_mark.line + 1
                stack.append((item, path + (index,)))
    return lines


def _apply_overrides(data, overrides, source):
    """(data with the overrides applied, {key path: the --set item that set it}); a later
    override of a path or of a section above it replaces the record of the earlier ones."""
    if isinstance(overrides, str):
        overrides = (overrides,)
    overridden = {}
    for item in overrides or ():
        if not isinstance(item, str) or "=" not in item:
            raise ConfigError(f"{source}: --set {item!r}: expected KEY=VALUE, e.g. method.s=4")
        key, _, text = item.partition("=")
        parts = key.strip().split(".")
        if not all(parts):
            raise ConfigError(f"{source}: --set {item!r}: {key!r} is not a key path; write e.g. integration.h=pi/60")
        if "[" in key or "]" in key:
            # (conserve[0]=lrl_x was an internal error: IndexError). The example is the user's own
            # key where it has one before the bracket (a trial: output.times[0] was told of conserve).
            listed = key.strip().partition("[")[0]
            example = (f"--set {listed}=[...]" if listed and all(listed.split(".")) and "]" not in listed
                       else "--set conserve=[angular_momentum,lrl_y]")
            raise ConfigError(f"{source}: --set {item!r}: {key.strip()!r} is not a key path (names joined by dots, "
                              f"no indices); set a list whole, e.g. {example}")
        value = parse_yaml(text, f"{source}: --set {key.strip()}") if text.strip() else None
        if data is None:
            data = {}
        if not isinstance(data, dict):
            break  # reported below as "the config must be a mapping"
        node = data
        for depth, part in enumerate(parts[:-1]):
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if depth == 0 and part in ("method", "problem") and isinstance(child, str):
                # a short form (method: EHBVM(12,3), problem: kepler) written out, so that a key under
                # it can be set, as a sweep's set can (a user trial: --set method.s=4 was refused)
                data = node = write_out_shorthands(
                    data, lambda where, text: ConfigError(f"{source}: {_join(where)}: {text}"))
                child = node[part]
            if not isinstance(child, dict):
                raise ConfigError(f"{source}: --set {item!r}: {'.'.join(parts[:depth + 1])} is not a section, so it "
                                  "has no keys; set it as a whole instead")
            node = child
        if value is None:
            # --set KEY=null (or KEY=) leaves the key out, in every section: the messages that say
            # "leave it out" are followed from the command line (a user trial: solver.lim_metric=null
            # was refused as "an empty value", where integration's keys took it)
            node.pop(parts[-1], None)
        else:
            node[parts[-1]] = value
        path = tuple(parts)
        for earlier in [o for o in overridden if o[:len(path)] == path]:
            del overridden[earlier]
        overridden[path] = item.strip()
    return data, overridden


# --- validation ----------------------------------------------------------------------------

def _short(value, limit: int = 60) -> str:
    if value is None:   # YAML's null: what an empty value reads as (key: or --set key=)
        return "an empty value (null)"
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _join(path) -> str:
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


_suggest = suggest


def unknown_key_text(location: tuple) -> str:
    """What to say of a key no config section has, at ``location`` (a config key path): the
    keys allowed there, and the nearest of them."""
    from .config_schema import SECTIONS
    if not location:
        return "unknown key; remove it"
    parent = tuple(p for p in location[:-1] if isinstance(p, str))
    if parent == ("method",) and "(" in str(location[-1]):
        # method: {EHBVM(12,3)}: YAML's braces make the comma split the notation into two keys (a user trial)
        return ("unknown key: braces make YAML read the method's notation as keys split at its comma; write "
                "method: EHBVM(12,3) without braces (quoted in a flow mapping: {method: 'EHBVM(12,3)'}), or "
                "method: {name: ehbvm, k: 12, s: 3}")
    model = SECTIONS.get(parent) or SECTIONS.get(parent[:-1] + ("*",))   # events.<name>: ("events", "*")
    allowed = list(model.model_fields) if model else []
    return f"unknown key; {_suggest(location[-1], allowed, 'allowed here')}" if allowed else "unknown key; remove it"


def _clip(text: str, limit: int = 60) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def write_out_shorthands(data: dict, error) -> dict:
    """A run config (or a sweep's base or set) with its short forms written out: ``method:
    EHBVM(12,3)`` (the paper's notation, methods.from_notation; also as method.name) and
    ``problem: kepler`` (a built-in's name) or ``problem: FILE.py``; the resolved config records
    the long forms. ``error(path, text)`` makes the exception raised for a bad short form."""
    data = dict(data)
    method = data.get("method")
    name = method.get("name") if isinstance(method, dict) else method
    if isinstance(name, str) and ("(" in name or ")" in name):
        # YAML's flow mapping {name: EHBVM(12,3)} splits it at the comma: name 'EHBVM(12' and a
        # key '3)'; so does a sweep's set: {method: ELIM(4,8,3), conserve: []}, beside method.
        # Without that key the notation itself is wrong (from_notation says how).
        in_mapping = isinstance(method, dict)
        rest = [key for key in (method if in_mapping else data) if key not in ("name", "method")]
        if ")" not in name and any(str(key).rstrip().endswith(")") for key in rest):
            quoted = 'name: "EHBVM(12,3)"' if in_mapping else 'method: "EHBVM(12,3)"'
            raise error(("method", "name") if in_mapping else ("method",),
                        f"{name!r} is cut off: inside {{...}} YAML splits an unquoted EHBVM(12,3) at its comma; "
                        f"quote it ({quoted}), or write method: EHBVM(12,3) on its own line")
        try:
            expanded = methods.from_notation(name)
        except ParameterError as err:
            raise error(("method", "name") if isinstance(method, dict) else ("method",), err.detail) from None
        if expanded is not None:
            if isinstance(method, dict) and set(method) - {"name"}:
                extra = sorted(set(method) - {"name"})[0]
                raise error(("method", extra), f"give the method either as {name} or by its name and parameters, "
                            "not both; remove it")
            data["method"] = expanded
    elif isinstance(method, str):
        data["method"] = {"name": method}   # methods.get then says which parameters it needs
    problem = data.get("problem")
    if isinstance(problem, str):
        from .problems.catalogue import BUILTINS
        if problem in BUILTINS:
            data["problem"] = {"builtin": problem}
        elif problem.endswith(".py"):
            data["problem"] = {"python": problem}
        else:
            import difflib
            close = difflib.get_close_matches(problem, list(BUILTINS), n=1, cutoff=0.5)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise error(("problem",), f"{problem!r} is not a built-in problem{hint}; give a built-in's name "
                        "(problem: kepler, or {builtin: kepler, parameters: {...}}), a file (problem: "
                        "my_problem.py), or the expressions (coordinates:, hamiltonian:)")
    return data


class _Builder:
    def __init__(self, source: str, overridden: dict, base_dir: Path, remember: bool = False,
                 lines: dict | None = None, allow_python: bool = False):
        self.source, self.overridden, self.base_dir, self.remember = source, overridden, base_dir, remember
        self.lines = lines or {}
        self.allow_python = allow_python

    # errors
    def override_of(self, path) -> str | None:
        """The --set item that gave the value at path (the most specific one), or None."""
        keys = tuple(p for p in path if isinstance(p, str))
        found = [o for o in self.overridden if keys[:len(o)] == o]
        return self.overridden[max(found, key=len)] if found else None

    def line_of(self, path) -> int | None:
        """The line of the deepest key of path that is in the file (None: none is, or the value
        came from --set). Parts not in the file are skipped: a missing key (its parent's line)
        and the union member pydantic names in a location (``output.times`` as a list)."""
        if self.override_of(path) is not None:
            return None
        line, found = None, ()
        for part in path:
            if found + (part,) in self.lines:
                found += (part,)
                line = self.lines[found]
        return line

    def message(self, path, text: str, sets: bool = True) -> str:
        """``text`` at the key ``path``, with the --set that gave it or those below it (sets=False:
        none, for an error no value can cause: the cache's)."""
        override = self.override_of(path) if sets else None
        if override is not None:
            return f"{self.source}: {_join(path)}: {text} (value from --set {_clip(override)})"
        line = self.line_of(path)
        where = f"{self.source}:{line}" if line is not None else self.source
        keys = tuple(p for p in path if isinstance(p, str))
        below = [item for o, item in self.overridden.items() if sets and keys and o[:len(keys)] == keys]
        # every --set below the key: the error may be any of them (output.times.stop, not .start)
        suffix = f" (with --set {', --set '.join(_clip(item) for item in below)})" if below else ""
        return f"{where}: {_join(path)}: {text}{suffix}"

    def error(self, path, text: str, sets: bool = True):
        return ConfigError(self.message(path, text, sets), key=_join(path), line=self.line_of(path))

    def parameter_error(self, err: ParameterError, section: tuple = ()):
        """A library validator's error at the parameter's YAML key (section: where its
        parameters live when they are not in PARAMETER_KEYS, e.g. ("solver",))."""
        path = section + (err.parameter,) if section else PARAMETER_KEYS.get(err.parameter, (err.parameter,))
        if err.index is not None:
            path = path + (err.index,)
        # the --set of another parameter the rule depends on (--set integration.h=1e-30 made t_end's
        # step count too large, and the message pointed at the file's t_end line alone)
        related = [self.override_of(section + (name,) if section else PARAMETER_KEYS.get(name, (name,)))
                   for name in err.related]
        related = [item for item in dict.fromkeys(related) if item and item != self.override_of(path)]
        suffix = f" (with --set {', --set '.join(_clip(item) for item in related)})" if related else ""
        return self.error(path, err.detail + suffix)

    def build(self, data) -> RunSpec:
        if not isinstance(data, dict):
            raise ConfigError(f"{self.source}: the config must be a mapping of sections (problem, method, "
                              f"integration, ...), got {type(data).__name__}")
        if "base" in data and "problem" not in data:   # the sweep's key, where a run config has its problem
            raise ConfigError(f"{self.source}: a sweep file (it has base: and no problem:), not a run config; run it "
                              f"with elimfast sweep {self.source}", key="base", line=self.lines.get(("base",)))
        self.check_keys(data)
        data = write_out_shorthands(data, self.error)
        config = self.validate(data)

        # Everything that needs no problem first: building the problem may compile code.
        integration = config.integration
        adaptive = any(getattr(integration, key) is not None for key in ("rtol", "atol", "step_control", "epsilon"))
        try:
            method_parameters = {p: getattr(config.method, p) for p in ("r", "k", "s")
                                 if getattr(config.method, p) is not None}
            kind = methods.family(config.method.name)
            k_left_out = "k" in kind.parameters and "k" not in method_parameters and "s" in method_parameters
            if adaptive and k_left_out:
                # docs/adaptive.md: k = 2s keeps H at round-off with the small steps of an adaptive run
                # (of an s that is one: s = -2 was reported as 'method.k: must be >= 1, got -4', a user trial)
                method_parameters["k"] = 2 * max(method_parameters["s"], 1)
                if "r" in kind.parameters and "r" not in method_parameters:
                    method_parameters["r"] = method_parameters["k"]
            if not adaptive and integration.h is None:
                # before the method: without h or rtol, a missing k is not the fix (rtol makes k = 2s)
                raise self.error(("integration", "h"), f"missing; {_EXAMPLES['integration.h']}")
            if not adaptive and k_left_out:
                # a user trial made an adaptive config of no k fixed-step (--set integration.rtol=null)
                raise self.error(("method", "k"), f"is missing; {kind.signature()} needs k: k = 2s is the default of "
                                                  f"adaptive runs only (rtol or step_control), so give k (e.g. k: "
                                                  f"{2 * method_parameters['s']})")
            method = methods.get(config.method.name, **method_parameters)
            if adaptive:
                step_control = self.step_control(integration).for_method(method, len(config.conserve))
                from .adaptive import resolve_span
                t0 = integration.t0
                t_end = resolve_span(t0, integration.t_end, integration.n_steps, step_control.h_max)
                h, n_steps = step_control.h, None
            else:
                step_control = None
                if integration.verify or integration.h_max is not None:
                    raise ParameterError("verify" if integration.verify else "h_max",
                                         "applies to adaptive steps only; give rtol (or step_control: time_scale)")
                if integration.h is None:
                    raise self.error(("integration", "h"), f"missing; {_EXAMPLES['integration.h']}")
                h, n_steps = resolve_steps(integration.h, t_end=integration.t_end, n_steps=integration.n_steps,
                                           t0=integration.t0)
                t0 = integration.t0
                t_end = integration.t_end if integration.t_end is not None else t0 + n_steps * h
            every = resolve_store_every(config.output.every)
            try:
                method.require_imposable(len(config.conserve))
            except ParameterError as err:
                error = self.parameter_error(err)
                conserve_set = self.override_of(("conserve",))
                if conserve_set is None:
                    raise error from None
                # a user trial's --set conserve=[...] was blamed on the config's method.s line alone
                raise ConfigError(f"{error} (with --set {_clip(conserve_set)})", key=error.key,
                                  line=error.line) from None
            t_eval = self.output_times(config.output.times, t0, t_end, every)
        except ParameterError as err:
            raise self.parameter_error(err) from None
        solver = self.solver(config.solver)
        if config.output.path is not None and not config.output.path.strip():
            raise self.error(("output", "path"), "is empty; give a file name such as out/run.h5, or leave it out")

        problem, resolved_problem = self.problem(config.problem, config.events)
        try:
            resolve_initial_state(problem)
            conserve = resolve_conserve(problem, method, config.conserve, problem.y0)[0]
            if step_control is not None:
                step_control.check_problem(problem)
        except ParameterError as err:
            raise self.parameter_error(err) from None
        events = self.events(problem, config.events)
        if solver.kernel == "per_problem":
            from .per_problem import kernel_source, refuse
            try:   # what the run would refuse, named at solver.kernel with its line
                given = [what for what, present in (
                    (f"adaptive steps (integration.{'step_control' if integration.step_control else 'rtol'})",
                     step_control is not None),
                    ("output times (output.times)", t_eval is not None), ("events (events)", bool(events))) if present]
                if given:   # named, as a user trial asked: the one line was the same for all three
                    refuse(solver, " and ".join(given))
                kernel_source(problem)   # the problem's functions can be imported by the kernel's module
            except ParameterError as err:
                raise self.parameter_error(err, ("solver",)) from None
        if solver.project_energy:   # refused with its line, as the run would refuse it
            from .integrate import refuse_energy_projection
            try:
                refuse_energy_projection(problem, method)
            except ParameterError as err:
                raise self.parameter_error(err, ("solver",)) from None
        try:
            solver = solver.resolved_for(method, len(conserve), 2 * problem.degrees_of_freedom)
        except ParameterError as err:
            raise self.parameter_error(err, ("solver",)) from None
        integration_record = {"h": h, "t0": t0, "t_end": t_end, "n_steps": n_steps}
        if step_control is not None:
            integration_record.update({k: v for k, v in step_control.as_dict().items() if v is not None
                                       and k != "h"})
            integration_record["step_control"] = integration_record.pop("controller")
        output_record = {"path": config.output.path, "every": every}
        if t_eval is not None:
            output_record["times"] = self.times_record(config.output.times, t_eval)
        resolved = {
            "problem": resolved_problem,
            "conserve": list(conserve),
            "method": {"name": method.family, **method.parameters},
            "integration": integration_record,
            "solver": solver.as_dict(),
            "output": output_record,
        }
        if config.events:
            resolved["events"] = {name: event.model_dump() for name, event in config.events.items()}
        return RunSpec(source=self.source, problem=problem, method=method, conserve=conserve, h=h, n_steps=n_steps,
                       t0=t0, t_end=t_end, solver=solver, output_path=config.output.path,
                       output_every=every, resolved=resolved, step_control=step_control, t_eval=t_eval,
                       events=resolved.get("events"))

    def validate(self, data) -> Section:
        """The config's sections as config_schema.RunConfig validates them. With ``remember``,
        from the cache of validations when this data was validated before (no pydantic
        then), else validated and stored there."""
        key = _validation_key(data) if self.remember else None
        if key is not None:
            config = _read_validated(key)
            if config is not None:
                return config
        from .config_schema import RunConfig, ValidationError, config_location, member_mismatch, sections
        try:
            config = sections(RunConfig.model_validate(data))
        except ValidationError as err:
            # An unknown key first: a misspelt section (methd:) also makes its section missing,
            # and the misspelling is the thing to fix. A union member the value is not of last.
            errors = sorted(({**e, "loc": config_location(e["loc"]), "mismatch": member_mismatch(e)}
                             for e in err.errors()),
                            key=lambda e: (e["type"] != "extra_forbidden", e["mismatch"]))
            messages = tuple(self.message(e["loc"], self.describe(e)) for e in errors)
            raise ConfigError(messages[0], messages=messages, key=_join(errors[0]["loc"]),
                              line=self.line_of(errors[0]["loc"])) from None
        if key is not None:
            _write_validated(key, config)
        return config

    def step_control(self, integration: Section):
        """The integration section's adaptive keys, validated by StepControl (their one owner)."""
        from .adaptive import StepControl
        return StepControl(controller=integration.step_control, rtol=integration.rtol,
                           atol=integration.atol, epsilon=integration.epsilon, verify=integration.verify,
                           h=integration.h, h_max=integration.h_max)

    def output_times(self, times, t0: float, t_end: float, every: int = 1):
        """output.times: a list, or {start, stop, step} / {start, stop, n}; None when absent
        (every: output.every, which output times leave no say)."""
        import numpy as np

        if times is None:
            return None
        from .adaptive import MAX_OUTPUT_TIMES, resolve_t_eval
        if isinstance(times, list):
            values = np.array(times, dtype=float)
        else:
            if (times.step is None) == (times.n is None):
                raise ParameterError("t_eval", "give exactly one of step and n, e.g. times: {start: 0, stop: 100, "
                                               "step: 0.5}")
            if times.n is not None:
                if not 1 <= times.n <= MAX_OUTPUT_TIMES:
                    raise ParameterError("t_eval", f"n must be from 1 to {MAX_OUTPUT_TIMES}, got {times.n}")
                if times.n == 1 and times.stop != times.start:
                    # (it gave start alone, silently: n counts start and stop)
                    raise ParameterError("t_eval", f"n = 1 gives start alone (n counts the times from start to stop, "
                                                   f"both included); give n >= 2, or one time as a list, e.g. "
                                                   f"times: [{compact_number(times.stop)}]")
                values = np.linspace(times.start, times.stop, times.n)
            else:
                if not times.step > 0:
                    raise ParameterError("t_eval", f"step must be > 0, got {compact_number(times.step)}")
                if not times.stop >= times.start:
                    raise ParameterError("t_eval", f"stop {compact_number(times.stop)} is before start "
                                                   f"{compact_number(times.start)}; give stop >= start")
                count = int(np.floor((times.stop - times.start) / times.step * (1 + 1e-12))) + 1
                if not 1 <= count <= MAX_OUTPUT_TIMES:
                    # (the count's slack for rounding, 1e-12 relative, is a whole time at 10^12: said as a
                    # round figure, not a count one off)
                    raise ParameterError("t_eval", f"gives {(times.stop - times.start) / times.step + 1:,.4g} times; at "
                                                   f"most {MAX_OUTPUT_TIMES:,}: give a larger step")
                if count == 1 and times.stop != times.start:
                    # (it gave start alone, silently, as n = 1 did)
                    raise ParameterError("t_eval", f"step {compact_number(times.step)} is longer than stop - start = "
                                                   f"{compact_number(times.stop - times.start)}: it gives start alone; "
                                                   "give a smaller step, or the times as a list")
                values = times.start + times.step * np.arange(count)
                # start + (count - 1) step meant as stop rounds off it: {start: 0, stop: 0.7, step: 0.1}
                # sampled at 0.7000000000000001, past the stop asked for (a user trial). The last time is
                # stop where it is within rounding of it (the count's own slack above).
                if abs(values[-1] - times.stop) <= 1e-12 * (times.stop - times.start):
                    values[-1] = times.stop
        return resolve_t_eval(values, t0, t_end, every)

    @staticmethod
    def times_record(times, t_eval) -> list | dict:
        """output.times as the resolved config stores it: a grid as its {start, stop, step|n}
        (the numbers evaluated), which reproduces the same times bit for bit; a list as the
        times. Expanded, a grid of 125,664 times made a stored config that --resume refused
        (more entries than a config may have)."""
        if isinstance(times, list):
            return t_eval.tolist()
        record = {"start": float(times.start), "stop": float(times.stop)}
        if times.n is not None:
            record["n"] = int(times.n)
        else:
            record["step"] = float(times.step)
        return record

    def events(self, problem: Problem, events):
        """The events section compiled for the problem (EventSpec owns the rules); None when absent."""
        if not events:
            return None
        from .adaptive import EventSpec
        try:
            return EventSpec.build(problem, {name: event.model_dump() for name, event in events.items()})
        except ParameterError as err:
            raise self.error(("events",) + tuple(err.parameter.split(".")[1:]), err.detail) from None
        except ProblemDefinitionError as err:
            raise self.error(tuple((err.key or "events").split(".")), str(err)) from None

    def solver(self, section: Section) -> SolverSettings:
        """The solver section, validated by SolverSettings (the one owner of its rules)."""
        try:
            return SolverSettings(**section.model_dump())
        except ParameterError as err:
            raise self.parameter_error(err, ("solver",)) from None

    def check_keys(self, data) -> None:
        """Mapping keys must be strings (YAML reads yes/no/on/off/1 as other types); bounded size and depth."""
        stack = [(data, ())]
        count = 0
        while stack:
            node, path = stack.pop()
            count += 1
            if count > MAX_YAML_NODES:
                raise self.error((), f"the config has more than {MAX_YAML_NODES} entries; it cannot be a run config")
            if len(path) > MAX_YAML_DEPTH:
                raise self.error(path[:MAX_YAML_DEPTH], f"nested more than {MAX_YAML_DEPTH} levels deep; no config "
                                                        "entry needs that")
            if isinstance(node, dict):
                for key, value in node.items():
                    if not isinstance(key, str):
                        hint = " (YAML reads yes/no/on/off/true/false as booleans: quote the key)" \
                            if isinstance(key, bool) else ""
                        raise self.error(path + (str(key),), f"key {key!r} must be a string{hint}")
                    if "[" in key or "]" in key:
                        # no config key has brackets, and pydantic's locations use them for union members,
                        # which config_location drops: such a key was an internal error (IndexError)
                        raise self.error(path, f"key {key!r}: no config key has brackets; remove it (a list is "
                                               "given whole, e.g. conserve: [angular_momentum, lrl_y])")
                    stack.append((value, path + (key,)))
            elif isinstance(node, list):
                stack.extend((value, path + (index,)) for index, value in enumerate(node))

    def describe(self, error) -> str:
        kind, value, loc = error["type"], error.get("input"), error["loc"]
        if kind == "extra_forbidden":
            return unknown_key_text(loc)
        if kind == "missing":
            return f"missing; {_EXAMPLES.get(_join(loc), 'add it')}"
        if kind in ("model_type", "model_attributes_type", "dict_type"):
            return f"must be a mapping (key: value), got {_short(value)}"
        if kind == "list_type":
            return f"must be a list, e.g. [a, b], got {_short(value)}"
        if kind == "string_type":
            return f"must be a string, got {_short(value)}"
        if kind == "bool_type":
            return f"must be true or false, got {_short(value)}"
        if kind == "literal_error":
            return f"must be one of {error['ctx']['expected']}, got {_short(value)}"
        if kind in ("int_type", "int_parsing", "int_from_float"):
            return f"must be a whole number, got {_short(value)}"
        if kind in ("float_type", "float_parsing"):
            return f"must be a number, got {_short(value)}"
        if kind == "value_error":
            text = str(error["ctx"]["error"])
            return text.replace("the value ", "", 1) if text.startswith("the value ") else text
        return f"{error['msg']}, got {_short(value)}"

    # problem
    def problem(self, section: Section, events=None):
        modes = [m for m, present in (("builtin", section.builtin is not None), ("python", section.python is not None),
                                      ("expressions", section.hamiltonian is not None or section.coordinates
                                       is not None)) if present]
        if not modes:
            raise self.error(("problem",), "no problem given; add builtin: NAME, python: FILE.py, or coordinates "
                                           "and hamiltonian")
        if len(modes) > 1:
            keys = {"builtin": "builtin", "python": "python", "expressions": "coordinates/hamiltonian"}
            raise self.error(("problem",), f"give only one of {', '.join(keys[m] for m in modes)}; they are "
                                           "different ways to define the problem")
        mode = modes[0]
        if mode != "expressions" and section.invariants is not None:
            raise self.error(("problem", "invariants"), f"only a problem by expressions takes invariants; "
                                                        f"a {mode} problem defines its own: remove it")
        if mode == "builtin" and section.name is not None:
            raise self.error(("problem", "name"), "a built-in problem keeps its name; remove name")
        if mode == "expressions":
            self.unused_parameters(section, events)
        try:
            if mode == "builtin":
                problem, resolved = self.builtin(section)
            elif mode == "python":
                problem, resolved = self.python_file(section)
            else:
                problem, resolved = self.expressions(section)
            if section.time_scale is not None:
                problem = problem.with_time_scale(section.time_scale)
                resolved["time_scale"] = section.time_scale
            if section.check:
                from .problems.check import require_problem
                require_problem(problem)
        except CacheError as err:   # the machine's, not a value's (a user trial: "(with --set problem.parameters.mu=...)")
            raise self.error(("problem",), str(err), sets=False) from None
        except ProblemDefinitionError as err:
            if (mode == "expressions" and err.key) or err.key == "time_scale":
                path = ("problem", *err.key.split("."))
            elif err.key and err.key.split(".")[0] in ("parameters", "initial"):
                path = ("problem", *err.key.split("."))
            else:
                path = ("problem", "builtin" if mode == "builtin" else "python" if mode == "python" else "hamiltonian")
            raise self.error(path, str(err)) from None
        resolved["check"] = section.check
        return problem, resolved

    def unused_parameters(self, section: Section, events):
        """Refuse a parameter of a problem by expressions that a --set gives and no expression uses: a
        misspelt name (--set problem.parameters.eccc=0.7 where the config says ecc) would otherwise add
        a parameter that changes nothing, and the run would go on with the config's value. (A misspelt
        parameter in the config itself leaves the expressions' name unknown, which is refused; a
        resolved config keeps parameters its evaluated initial values no longer show.)"""
        texts = {"hamiltonian": section.hamiltonian, "time_scale": section.time_scale,
                 "invariants": section.invariants, "initial": section.initial,
                 "parameters": section.parameters}
        unused, used = unused_parameters(texts, {name: {"expression": event.expression}
                                                 for name, event in (events or {}).items()})
        for pname in unused:
            if self.override_of(("problem", "parameters", pname)) is not None:
                raise self.error(("problem", "parameters", pname), unused_parameter_text(pname, used))

    def builtin(self, section: Section):
        from . import problems as library

        name = section.builtin
        constructors = library.PROBLEMS
        if name not in constructors:
            raise self.error(("problem", "builtin"),
                             f"unknown problem {name!r}; {_suggest(name, sorted(constructors), 'built-in')}")
        constructor = constructors[name]
        accepted = inspect.signature(constructor).parameters
        kwargs = {}
        for pname, value in (section.parameters or {}).items():
            if pname not in accepted:
                raise self.error(("problem", "parameters", pname),
                                 f"{name} has no parameter {pname!r}; {_suggest(pname, accepted, 'its parameters')}")
            kwargs[pname] = self.parameter_value(value, accepted[pname].default, ("problem", "parameters", pname))
            default = accepted[pname].default
            if (isinstance(default, int) and not isinstance(default, bool) and isinstance(kwargs[pname], (int, float))
                    and not isinstance(kwargs[pname], bool) and abs(kwargs[pname]) > MAX_SIZE_PARAMETER):
                raise self.error(("problem", "parameters", pname),
                                 f"must be at most {MAX_SIZE_PARAMETER}, got {_count(kwargs[pname])}: it sizes the "
                                 "problem (the state has 2n numbers, and every step's work and memory grow with it)")
        try:
            problem = constructor(**kwargs)
        except ParameterError as err:   # at the parameter's own key (and line)
            raise self.error(("problem", "parameters", err.parameter), err.detail) from None
        except Exception as err:  # a built-in rejecting user values; report it, never a traceback
            detail = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise self.error(("problem", "parameters"), f"{name}: {detail}") from None
        problem = self.apply_initial(problem, section.initial)
        parameters = {k: _plain(v) for k, v in problem.parameters.items() if k in accepted}
        for k, v in kwargs.items():
            parameters.setdefault(k, _plain(v))
        return problem, {"builtin": name, "parameters": parameters, "initial": _initial_dict(problem)}

    def parameter_value(self, value, default, path):
        """Numbers (or numeric strings) stay numbers, ints where the default is an int; strings
        stay strings where the default is one; lists are converted entry by entry."""
        if isinstance(value, list):
            return [self.parameter_value(v, None, path + (i,)) for i, v in enumerate(value)]
        if isinstance(value, str) and isinstance(default, str):
            return value
        if isinstance(value, bool):
            return value
        if isinstance(value, int) and not isinstance(default, float):
            return value
        try:
            number = evaluate_number(value, what="value")
        except ProblemDefinitionError as err:
            raise self.error(path, str(err).replace("value ", "", 1)) from None
        if isinstance(default, int) and not isinstance(default, bool) and number.is_integer():
            return int(number)
        return number

    def apply_initial(self, problem: Problem, initial) -> Problem:
        if not initial:
            return problem
        names = problem.coordinate_names
        values = {k: float(v) for k, v in problem.parameters.items()
                  if isinstance(v, (int, float)) and not isinstance(v, bool)}
        y0 = problem.y0.copy()
        for cname, value in initial.items():
            if cname not in names:
                raise self.error(("problem", "initial", cname), f"problem {problem.name!r} has no coordinate "
                                                                f"{cname!r}; {_suggest(cname, names, 'coordinates')}")
            try:
                y0[names.index(cname)] = evaluate_number(value, values, what="value")
            except ProblemDefinitionError as err:
                raise self.error(("problem", "initial", cname), str(err).replace("value ", "", 1)) from None
        return problem.with_initial(y0)

    def python_file(self, section: Section):
        from .problems.user_file import missing_file_text, problem_from_file

        try:
            path = Path(section.python).expanduser()
            if not path.is_absolute():
                path = self.base_dir / path
            if b"\0" in os.fsencode(path):   # Path.exists says False, and open raises ValueError
                raise ValueError("embedded null byte")
            exists = path.exists()
        except (OSError, RuntimeError, ValueError) as err:   # a NUL, a lone surrogate, ~nosuchuser, too long
            reason = getattr(err, "strerror", None) or str(err)
            raise self.error(("problem", "python"), f"{section.python!r} is not a usable path ({reason}); give "
                                                    "the path of a .py file") from None
        if not exists:   # told here, so that nothing is ever read from a path checked before it existed
            raise self.error(("problem", "python"), missing_file_text(path))
        try:
            read_text_file(path, str(path), what="python problem file", example="a .py file")
        except ConfigError as err:
            raise self.error(("problem", "python"), str(err)) from None
        if not self.allow_python:   # the file's own faults first, and nothing is imported
            error = self.error(("problem", "python"), f"{section.python} {python_refused_text()}")
            raise PythonNotAllowed(str(error), key=error.key, line=error.line)
        problem = problem_from_file(path, parameters=section.parameters, initial=section.initial, name=section.name,
                                    check=False)   # checked below with the other modes (problem.check)
        return problem, {"python": str(path.resolve()), "name": problem.name,
                         "parameters": {k: _plain(v) for k, v in problem.parameters.items()},
                         "initial": _initial_dict(problem)}

    def expressions(self, section: Section):
        from .problems.symbolic import problem_from_expressions

        if section.coordinates is None:
            raise self.error(("problem", "coordinates"), "missing; declare them, e.g. coordinates: {q: [q1, q2], "
                                                         "p: [p1, p2]}")
        if section.hamiltonian is None:
            raise self.error(("problem", "hamiltonian"), "missing; give H as an expression of the coordinates and "
                                                         "parameters")
        name = section.name or (Path(self.source).stem if self.source != "<dict>" else "user")
        coordinates = {"q": section.coordinates.q, "p": section.coordinates.p}
        problem = problem_from_expressions(coordinates=coordinates, hamiltonian=section.hamiltonian,
                                           invariants=section.invariants, parameters=section.parameters,
                                           initial=section.initial, name=name, check=False)
        return problem, {"name": name, "coordinates": {k: list(v) for k, v in coordinates.items()},
                         "hamiltonian": section.hamiltonian, "invariants": dict(section.invariants or {}),
                         "parameters": dict(problem.parameters), "initial": _initial_dict(problem)}


def unused_parameters(problem: dict, events: dict | None) -> tuple[list[str], list[str]]:
    """(unused, used): the parameters of a problem by expressions (a config's problem section as
    data) that no expression names (hamiltonian, invariants, initial, time_scale, events), and those
    that one does. Parameters cannot use each other, so a parameter no expression names changes
    nothing: a misspelt name, which _Builder.unused_parameters and the sweep refuse."""
    texts = [problem.get("hamiltonian"), problem.get("time_scale")]
    for key in ("invariants", "initial"):
        texts += list((problem.get(key) or {}).values()) if isinstance(problem.get(key), dict) else []
    texts += [event.get("expression") if isinstance(event, dict) else event for event in (events or {}).values()]
    named = set()
    for text in texts:
        if isinstance(text, str):
            named.update(re.findall(r"[A-Za-z_][A-Za-z_0-9]*", text))
    parameters = [str(name) for name in (problem.get("parameters") or {})]
    return [p for p in parameters if p not in named], [p for p in parameters if p in named]


def unused_parameter_text(pname: str, used) -> str:
    """The refusal of a parameter no expression uses (unused_parameters), with the closest used name."""
    return (f"no expression uses it (hamiltonian, invariants, initial, time_scale, events); remove it or fix "
            f"its name{did_you_mean(str(pname), sorted(used))}")


def _initial_dict(problem: Problem) -> dict:
    return {name: float(value) for name, value in zip(problem.coordinate_names, problem.y0)}


def _plain(value):
    """YAML-dumpable plain data: numpy scalars and arrays, tuples -> floats, ints, lists."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):
        return _plain(value.tolist())
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value)
    return str(value)
