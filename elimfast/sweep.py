"""Sweeps: a base config run over a grid of overrides, in parallel worker processes.

A sweep file (YAML, data only) names a base run config and the axes of a grid:

    base: ../kepler.yaml            # a run config (path relative to this file) or a mapping
    set:                            # overrides applied to every run (nested mappings merge)
      integration: {t_end: 20*pi}
    grid:                           # the cartesian product of the axes, in this order
      - name: method                # labelled variants: each sets several keys at once
        values:
          - {label: GAUSS3, set: {method: {name: gauss, s: 3}, conserve: []}}
          - {label: "EHBVM(12,3) L1", set: {method: {name: ehbvm, k: 12, s: 3}, conserve: [angular_momentum]}}
      - name: h                     # a plain axis: one key, a list of values
        key: integration.h
        values: [pi/30, pi/60, pi/120]
    error: {exact: initial}         # or {reference: {set: {...}}}, or omitted (no error column)
    order_axis: h                   # observed orders between successive values of this axis

An ensemble sweep runs one config from many initial states in the parallel Numba
kernel (elimfast.ensemble), not one process per run; it has no grid:

    base: ../henon_heiles.yaml
    ensemble: {n: 1000, seed: 1, spread: 0.01}   # y0 + spread * N(0, 1) per component, seeded
    # or: ensemble: {states: [[q1, q2, p1, p2], ...]}

A variant's ``set`` replaces whole top-level values it names (a method mapping is
replaced, not merged, so ``{name: gauss, s: 3}`` does not inherit ``k`` from the
base); the sweep-wide ``set`` merges into nested mappings, except a method that names
its family (``{name: hbvm, s: 4}`` replaces the base's method, as in a variant;
``{s: 4}`` changes only s).

Errors: ``exact: initial`` compares each run's final state with its initial state
(a periodic problem over a whole number of periods, e.g. Kepler over 10 periods, the
paper's Table 1); ``reference`` runs the base with the given overrides once and
compares every run's final state with it, so every run must have the reference's
problem (parameters, initial state) and interval (a sweep that varies them is refused).
The reference's ``set`` applies as the sweep-wide one does (``integration: {h: 0.001}``
keeps the t_end; ``method: {name: gauss, s: 6}`` is GAUSS(6), with no k from an EHBVM base). Its config is loaded
with the sweep file: one that does not load is refused before any run.

Orders: ``order_axis`` names a plain axis of positive numbers (an h axis only over fixed-step
runs: an adaptive run takes h as its first step only); the order column gives
log(e1/e2)/log(x1/x2) between each run and the one before it on that axis (the other
axes equal), x the value of the axis's key as the run resolved it: the order in h for
an axis of integration.h (column ``order``), in epsilon or rtol for those (column
``order in <axis>``: error ~ epsilon^6 for a sixth-order method under the time-scale
controller). An axis of variants, or a value that is no positive number, is refused.

Short forms of a run config work here too (``method: EHBVM(12,3)``, ``problem: kepler``;
config.write_out_shorthands). ``--resume`` (run_to_file) keeps the runs a file holds complete
and runs the rest; the sweep file may have been edited meanwhile where the edit leaves those
runs' configs as they were outside solver.* (solver_only_edit): more halvings for a failed
run, a failed run's h, added values.
"""
from __future__ import annotations

import contextlib
import copy
import gc
import itertools
import math
import multiprocessing
import os
import pickle
import re
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .errors import ConvergenceError, ElimfastError, closest, exact_time
from .io.layout import problem_file_attributes, problem_file_changed
from .io.safety import OutputError, _size   # _size: the one size formatter of the disk and memory messages


REFERENCE_LABEL = "\0reference"  # the reference run's label: no grid label can hold a NUL, so none collides
MAX_RUNS = 10_000                 # points of a grid: beyond that, split the sweep
MAX_LABEL_CHARACTERS = 200        # a label names an HDF5 group and a table row
MEMORY_FRACTION = 0.5             # of the memory available, what one sweep may plan to use
MAX_WORKERS_PER_CORE = 4          # worker processes: more than a few per core only costs memory
PYTHON_BYTES_PER_NODE = 120       # a config value as Python objects (dict slot, float or str), measured ~80-150


class SweepError(ElimfastError):
    """A sweep file that cannot be run; str() is one line naming the file and the key (and the
    key's line in the sweep file, where the error is one of load_sweep's): ``source`` and
    ``key`` keep the two apart for that."""

    def __init__(self, message: str, *, source: str | None = None, key: str | None = None):
        super().__init__(message)
        self.source, self.key = source, key


@dataclass
class SweepRun:
    """One point of the grid: its label, the coordinates along each axis, and its config."""

    label: str
    coordinates: dict[str, str]
    config: dict


@dataclass
class RunOutcome:
    """What a worker sends back: summary numbers and, to be stored, the run's Result."""

    label: str
    coordinates: dict[str, str]
    status: str                         # "complete" or "failed: <reason>"
    resolved: dict = field(default_factory=dict)
    n_steps: int = 0
    steps_done: int = 0
    h: float = math.nan
    wall_time: float = 0.0
    y_initial: np.ndarray | None = None
    y_final: np.ndarray | None = None
    t_final: float = math.nan
    iterations_total: int = 0
    grad_H_evaluations: int = 0         # the work users compare methods by (docs/adaptive.md)
    max_multiplier: float = math.nan    # max |alpha| (ELIM) or |lambda| (LIM), nan otherwise
    invariant_errors: dict[str, float] = field(default_factory=dict)
    initial_invariants: dict[str, float] = field(default_factory=dict)   # I(t0), for the relative errors
    invariant_scales: dict[str, float] = field(default_factory=dict)     # the size of each I's terms at t0
    result: Any = None                  # the Result integrate would return (kept when the runs are stored)
    config_error: bool = False          # failed before any step: its config (or problem file) did not load
    refused: bool = False               # not run: it would not fit in memory (a usage error too, exit 2)
    # What a run file of this run records beside its Result, for the sweep file's run group:
    # the config's end (an adaptive run's n_steps * h is no end) and, for runs of the adaptive
    # kernel, how the steps were chosen (AdaptiveIntegration.file_attributes).
    t_end: float | None = None
    file_attributes: dict = field(default_factory=dict)

    @property
    def relative_invariant_errors(self) -> dict[str, float]:
        """max |I - I0| / |I0| (relative to the size of I's terms where I0 vanishes against them), see
        integrate.relative_error."""
        from .integrate import relative_error
        return {name: relative_error(error, self.initial_invariants.get(name, 0.0),
                                     self.invariant_scales.get(name, 0.0))
                for name, error in self.invariant_errors.items()}

    @property
    def ok(self) -> bool:
        return self.status == "complete"

    @property
    def ended_before_t_end(self) -> bool:
        """Complete, but stopped by a terminal event before its t_end (t_final short of it by more
        than the rounding of n steps of h)."""
        if not self.ok or self.t_end is None or not math.isfinite(self.t_final):
            return False
        return self.t_end - self.t_final > 1e-9 * max(abs(self.t_end), 1.0)

    @property
    def status_text(self) -> str:
        """The status as the tables write it: a terminal event's end is said, as `elimfast run` says it."""
        if self.ended_before_t_end:
            return f"{self.status} (ended by a terminal event at t = {self.t_final:.10g})"
        return self.status


@dataclass
class SweepSpec:
    source: str
    runs: list[SweepRun]
    axes: list[str]
    error_mode: str | None              # None, "initial" or "reference"
    reference: dict | None              # the reference run's config
    order_axis: str | None
    ensemble: dict | None = None        # {"n", "seed", "spread"} or {"states"}; the base is the run
    base: dict | None = None
    axis_keys: dict[str, str] = field(default_factory=dict)   # plain axes: name -> the dotted key it sets
    base_file: str | None = None        # the base config's file, when base: names one

    def input_files(self) -> list[Path]:
        """The files the sweep reads: the sweep file, its base config's file, and every python:
        problem file its runs (and reference) name. -o must name none of them (a user trial: -o BASE.yaml
        --overwrite replaced the base config by HDF5, -o PROBLEM.py the problem file)."""
        folder = Path(self.source).parent
        files = [Path(self.source)] + ([Path(self.base_file)] if self.base_file else [])
        configs = [run.config for run in self.runs] + [self.base or {}, self.reference or {}]
        for config in configs:
            problem = config.get("problem") if isinstance(config, dict) else None
            if isinstance(problem, dict) and isinstance(problem.get("python"), str):
                files.append(folder / problem["python"])
        unique = []
        for file in files:
            if file not in unique:
                unique.append(file)
        return unique


# --- reading the sweep file ----------------------------------------------------------

def _fail(source, key, message):
    raise SweepError(f"{source}: {key}: {message}", source=source, key=key)


def _key_path(key: str) -> tuple:
    """A sweep error's key as a key path of parse_yaml_with_lines: 'grid[0].values[2]' ->
    ('grid', 0, 'values', 2); '(top level)' -> ()."""
    if key.startswith("("):
        return ()
    path = []
    for name, index in re.findall(r"([^.\[\]]+)|\[(\d+)\]", key):
        path.append(int(index) if index else name)
    return tuple(path)


def _with_line(err: SweepError, path: Path) -> SweepError:
    """err with the line of its key in the sweep file (the nearest key above it that the file
    writes: a run config's errors give theirs, and a sweep file's gave none, a user trial)."""
    from .config import ConfigError, parse_yaml_with_lines, read_text_file
    try:
        _, lines = parse_yaml_with_lines(read_text_file(path, str(path), what="sweep file"), str(path))
    except (ConfigError, OSError):
        return err
    key_path = _key_path(err.key)
    while key_path and key_path not in lines:
        key_path = key_path[:-1]
    prefix = f"{err.source}: "
    message = str(err)
    if not key_path or not message.startswith(prefix):
        return err
    return SweepError(f"{err.source}:{lines[key_path]}: {message[len(prefix):]}", source=err.source, key=err.key)


def _deep_merge(target: dict, overrides: dict) -> dict:
    for key, value in overrides.items():
        if isinstance(value, dict) and isinstance(target.get(key), dict):
            _deep_merge(target[key], value)
        else:
            target[key] = copy.deepcopy(value)
    return target


def _set_path(config: dict, dotted: str, value, source: str) -> None:
    node = config
    parts = dotted.split(".")
    for part in parts[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            _fail(source, dotted, f"{part!r} is not a mapping in the base config")
        node = child
    node[parts[-1]] = copy.deepcopy(value)


def _read_yaml(path: Path, what: str) -> Any:
    """The config files' reader (a regular file of at most 1 MiB, safe loader, no aliases or
    tags); its errors name the file and line."""
    from .config import ConfigError, parse_yaml, read_text_file

    try:
        text = read_text_file(path, str(path), what=what, example="a .yaml file")
        return parse_yaml(text, source=str(path))
    except ConfigError as error:
        raise SweepError(str(error)) from None


def memory_available() -> int | None:
    """Bytes this process could still allocate: MemAvailable, or the cgroup's limit minus its
    use where that is lower; None where neither is known."""
    values = []
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    values.append(int(line.split()[1]) * 1024)
                    break
    except (OSError, ValueError, IndexError):
        pass
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = open(limit_file).read().strip()
            usage = int(open(usage_file).read().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < 1 << 60:
            values.append(max(int(limit) - usage, 0))
        break
    return min(values) if values else None


def require_memory(needed: float, what: str, fix: str, source: str, key: str) -> None:
    """SweepError when ``needed`` bytes exceed the share of the available memory a sweep may use."""
    available = memory_available()
    if available is not None and needed > MEMORY_FRACTION * available:
        _fail(source, key, f"{what} would need {_size(needed)} of memory; this machine has {_size(available)} "
                           f"available (a sweep plans with at most {MEMORY_FRACTION:.0%} of it): {fix}")


def _nodes(value) -> int:
    """Scalars and containers in a YAML value (iteratively: a sweep file is data, maybe deep)."""
    count, stack = 0, [value]
    while stack:
        node = stack.pop()
        count += 1
        if isinstance(node, dict):
            stack.extend(node.values())
            count += len(node)
        elif isinstance(node, list):
            stack.extend(node)
    return count


def _check_label(source, key: str, label: str) -> str:
    bad = next((c for c in label if ord(c) < 32 or ord(c) == 127), None)
    if bad is not None:
        _fail(source, key, f"the label {label[:40]!r} contains the control character {bad!r} (a NUL ends an HDF5 "
                           "name); use printable text")
    if not label.strip():
        _fail(source, key, "an empty label; give each value a label of printable text")
    if len(label) > MAX_LABEL_CHARACTERS:
        _fail(source, key, f"the label is {len(label)} characters long; at most {MAX_LABEL_CHARACTERS}")
    return label


def _first_difference(a, b, prefix: str) -> str | None:
    """The first dotted key at which two config values differ (None: equal)."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in list(a) + [key for key in b if key not in a]:
            found = _first_difference(a.get(key), b.get(key), f"{prefix}.{key}")
            if found:
                return found
        return None
    return None if a == b else prefix


def _interval(config: dict) -> tuple[float, float] | None:
    """(t0, t_end) of a raw config (t_end from n_steps x h where it gives no t_end); None where
    it cannot tell (an expression or value its run's own validation will report)."""
    from .problems.expressions import evaluate_number
    try:
        integration = config.get("integration") or {}
        t0 = evaluate_number(integration.get("t0", 0.0))
        if integration.get("t_end") is not None:
            return t0, evaluate_number(integration["t_end"])
        return t0, t0 + int(integration["n_steps"]) * evaluate_number(integration["h"])
    except Exception:   # noqa: BLE001 -- only a consistency check; the run reports a bad value itself
        return None


def _check_same_problem(source: str, runs: list[SweepRun], reference: dict) -> None:
    """SweepError unless every run solves the reference run's problem from its initial state over
    its interval: a run of another eccentricity was compared with the base's reference, and the
    table showed errors of 0.3-2.6 as if they were the method's."""
    reference_interval = _interval(reference)
    for run in runs:
        key = _first_difference(run.config.get("problem"), reference.get("problem"), "problem")
        interval = _interval(run.config)
        if key is None and interval is not None and reference_interval is not None and \
                not np.allclose(interval, reference_interval, rtol=1e-12, atol=0.0):
            key = "integration (its t0 and t_end)"
        if key is not None:
            _fail(source, "error.reference", f"run {run.label!r} differs from the reference run in {key}, so its "
                                             "error against it would not measure the method; one reference run "
                                             "serves runs of one problem, initial state and interval: put the "
                                             "other values in sweeps of their own (or use error: {exact: initial} "
                                             "for an orbit over whole periods)")


def load_sweep(path: str | os.PathLike, *, allow_python: bool | None = None) -> SweepSpec:
    """Read and expand a sweep file (see the module docstring). Runs are validated later,
    each by the config loader, so that one bad point fails alone with its reason; the
    reference run, which every error needs, is loaded here, and so are the numbers of plain
    axes (SweepError, with the line of the key at fault). ``allow_python``: may the reference
    run's python: problem file be run (default: config.python_allowed())."""
    from .config import allowing_python
    try:
        with allowing_python(allow_python):
            return _load_sweep(Path(path))
    except SweepError as err:
        if err.key is None or err.source != str(Path(path)):
            raise
        raise _with_line(err, Path(path)) from None


def _load_sweep(path: Path) -> SweepSpec:
    source = str(path)
    data = _read_yaml(path, "sweep file")
    if not isinstance(data, dict):
        _fail(source, "(top level)", "a sweep file is a mapping with keys base, set, grid, error, order_axis")
    known = {"base", "set", "grid", "error", "order_axis", "description", "ensemble"}
    if "base" not in data and "problem" in data:
        _fail(source, "(top level)", f"a run config (it has problem: and no base:), not a sweep file; run it with "
                                     f"elimfast run {source}, or name it as the base: of a sweep file")
    unknown = sorted(set(data) - known)
    if unknown:
        _fail(source, unknown[0], f"unknown key; a sweep file has {', '.join(sorted(known))}")
    if data.get("ensemble") is not None:
        for key in ("grid", "error", "order_axis"):
            if data.get(key):
                _fail(source, key, "an ensemble sweep runs one config from many initial states: "
                                   "remove this key, or run the grid as a separate sweep")
    base = data.get("base")
    base_file = None
    if isinstance(base, str):
        base_path = (path.parent / base)
        base_file = str(base_path)
        if not base_path.exists():   # a user trial was told only "nosuch.yaml: no such file"
            _fail(source, "base", f"{base_path}: no such file; give the path of a run config, relative to "
                                  f"the sweep file's folder ({path.parent})")
        base = _read_yaml(base_path, "base config")
        if not isinstance(base, dict):
            _fail(source, "base", f"{base_path} does not hold a config mapping")
        base = _rebase_paths(_written_out(str(base_path), "", base), base_path.parent, path.parent)
    elif not isinstance(base, dict):
        _fail(source, "base", "give a run config: a path to a YAML file or an inline mapping")
    base = copy.deepcopy(_written_out(source, "base.", base))
    base_alone = copy.deepcopy(base)   # before the sweep's set: whose parameters are the base's own
    common = data.get("set") or {}
    if not isinstance(common, dict):
        _fail(source, "set", "must be a mapping of overrides, e.g. {integration: {t_end: 20*pi}}")
    base = _apply_set(base, _written_out(source, "set.", common))

    axes = data.get("grid") or []
    if not isinstance(axes, list):
        _fail(source, "grid", "must be a list of axes, each {name, values} or {name, key, values}")
    axis_points = []
    axis_names = []
    axis_keys = {}
    variant_sections: dict[str, list[str]] = {}
    for index, axis in enumerate(axes):
        key = f"grid[{index}]"
        if not isinstance(axis, dict) or "values" not in axis:
            _fail(source, key, "an axis is a mapping with 'values' (and 'name', and 'key' for a plain axis)")
        _known_keys(source, key, axis, AXIS_KEYS)   # a misspelt 'nme:' was dropped silently
        name = str(axis.get("name") or axis.get("key") or f"axis{index}")
        if name in axis_names:   # the runs' coordinates would merge, and every label would repeat
            _fail(source, f"{key}.name", f"repeats the axis name {name!r} of grid[{axis_names.index(name)}]; give "
                                         "each axis its own name")
        values = axis["values"]
        if not isinstance(values, list) or not values:
            _fail(source, f"{key}.values", "must be a non-empty list")
        points = []
        if "key" in axis:
            if not isinstance(axis["key"], str) or not all(axis["key"].split(".")):
                _fail(source, f"{key}.key", "must be a dotted key such as integration.h")
            for j, value in enumerate(values):
                if isinstance(value, dict) and "set" in value and set(value) <= set(VARIANT_KEYS):
                    # a user trial: each run failed with 'events.set.events: unknown key', labelled by the
                    # whole mapping
                    _fail(source, f"{key}.values[{j}]", f"is a variant ({{label, set}}), but the axis has a key "
                                                        f"({axis['key']}), whose values are that key's: remove "
                                                        "'key' to make it an axis of variants")
            _check_axis_key(source, f"{key}.key", base, axis["key"], values[0])
            _check_axis_numbers(source, key, base, axis["key"], values)
            parts = axis["key"].split(".")
            for other, other_key in axis_keys.items():
                shared = min(len(parts), len(other_key.split(".")))
                if parts[:shared] == other_key.split(".")[:shared]:
                    # the later axis overwrote the earlier one's value: runs labelled apart were the same
                    # run, and the earlier axis's column showed the later one's values (a user trial)
                    _fail(source, f"{key}.key", f"{axis['key']} is also set by the axis {other!r} "
                                                f"(grid[{axis_names.index(other)}], key {other_key}); one axis per key")
            labels = axis.get("labels") or [str(v) for v in values]
            if not isinstance(labels, list) or len(labels) != len(values):
                _fail(source, f"{key}.labels", f"has {len(labels) if isinstance(labels, list) else 'no list of'} "
                                               f"entries for {len(values)} values")
            for j, (label, value) in enumerate(zip(labels, values)):
                label = _check_label(source, f"{key}.labels[{j}]" if axis.get("labels") else f"{key}.values[{j}]",
                                     str(label))
                points.append((label, {"path": axis["key"], "value": value}))
            _refuse_equal_values(source, key, values)
        else:
            for j, variant in enumerate(values):
                if not isinstance(variant, dict) or "set" not in variant or not isinstance(variant["set"], dict):
                    _fail(source, f"{key}.values[{j}]", "a variant is {label: ..., set: {key: value, ...}}")
                _known_keys(source, f"{key}.values[{j}]", variant, VARIANT_KEYS)
                label = _check_label(source, f"{key}.values[{j}].label", str(variant.get("label", j)))
                replace = _written_out(source, f"{key}.values[{j}].set.", variant["set"])
                _refuse_partial_sections(source, f"{key}.values[{j}].set", replace)
                points.append((label, {"replace": replace}))
        axis_points.append(points)
        axis_names.append(name)
        if "key" in axis:
            axis_keys[name] = axis["key"]
        else:
            variant_sections[name] = sorted({top for _, change in points for top in change["replace"]})
    # A variant replaces whole sections: one that holds the key of a plain axis before it (the axes are
    # applied in order) overwrites that axis's value (a user trial: an integration.h axis, then a variant
    # setting integration, ran the same run under both h labels; a method.s axis, then a GAUSS(2)
    # variant, ran GAUSS(2) labelled s = 3). A plain axis after the variant sets its key on top.
    for variant_axis, sections in variant_sections.items():
        for plain_axis, dotted in axis_keys.items():
            if axis_names.index(plain_axis) < axis_names.index(variant_axis) and dotted.split(".")[0] in sections:
                index, other = axis_names.index(variant_axis), axis_names.index(plain_axis)
                _fail(source, f"grid[{index}]", f"its variants set {dotted.split('.')[0]}, which holds the key "
                                                f"{dotted} of the axis {plain_axis!r} (grid[{other}]) and would "
                                                "overwrite its values; one axis per key")

    # Count (and size) the grid before expanding it: the product of the axes' lengths grows
    # fast, and each point holds a copy of the base config.
    count = math.prod(len(points) for points in axis_points)
    if count > MAX_RUNS:
        lengths = " x ".join(str(len(points)) for points in axis_points)
        _fail(source, "grid", f"{count:,} runs ({lengths}), more than a sweep may hold ({MAX_RUNS:,}); split it into "
                              "smaller sweeps or use fewer values per axis")
    require_memory(count * (_nodes(base) + 2 * len(axis_points)) * PYTHON_BYTES_PER_NODE,
                   f"the grid's {count:,} run configs", "split the sweep or shrink the base config", source, "grid")
    runs = []
    for combination in itertools.product(*axis_points) if axis_points else [()]:
        config = copy.deepcopy(base)
        coordinates = {}
        for name, (label, change) in zip(axis_names, combination):
            coordinates[name] = label
            if "path" in change:
                _set_path(config, change["path"], change["value"], source)
            else:
                for top_key, value in change["replace"].items():
                    config[top_key] = copy.deepcopy(value)
        label = "/".join(f"{label}" for label in coordinates.values()) or "run"
        runs.append(SweepRun(label=label, coordinates=coordinates, config=config))
    _refuse_unused_parameters(source, base_alone, runs)
    labels = [r.label for r in runs]
    if len(set(labels)) != len(labels):
        repeated = next(label for label in labels if labels.count(label) > 1)
        _fail(source, "grid", f"two runs get the same label {repeated!r} (an axis repeats a value, or two variants "
                              "share a label); give each axis distinct values and the variants distinct labels")
    from .io.sweepfile import sweep_group_name
    groups: dict[str, str] = {}
    for label in labels:   # a sweep file stores each run under this name: 'a/b' and 'a|b' would collide
        other = groups.setdefault(sweep_group_name(label), label)
        if other != label:
            _fail(source, "grid", f"the runs {other!r} and {label!r} would be stored under the same name "
                                  f"{sweep_group_name(label)!r} (a '/' in a label is written '|', and a label of "
                                  "dots gets a leading '_'); give the variants distinct labels")

    error = data.get("error")
    error_mode, reference = None, None
    if error is not None:
        if not isinstance(error, dict) or len(error) != 1 or next(iter(error)) not in ("exact", "reference"):
            _fail(source, "error", "use {exact: initial} or {reference: {set: {...}}}")
        if "exact" in error:
            if error["exact"] != "initial":
                _fail(source, "error.exact", "the only exact solution known to sweeps is 'initial' "
                                             "(a periodic orbit over whole periods)")
            error_mode = "initial"
        else:
            ref = error["reference"]
            if not isinstance(ref, dict) or not isinstance(ref.get("set", {}), dict):
                _fail(source, "error.reference", "must be {set: {overrides of the base}}")
            reference_set = _written_out(source, "error.reference.set.", ref.get("set") or {})
            reference = _apply_set(base, reference_set)
            error_mode = "reference"
            _check_same_problem(source, runs, reference)
    order_axis = data.get("order_axis")
    if order_axis is not None and order_axis not in axis_names:
        _fail(source, "order_axis", f"names no axis; the axes are {', '.join(axis_names) or 'none'}")
    if order_axis is not None:
        _check_order_axis(source, order_axis, axes[axis_names.index(order_axis)], axis_names.index(order_axis))
        if axis_keys.get(order_axis) == "integration.h":
            _check_fixed_steps(source, order_axis, runs)
    if reference is not None:
        # Every error is taken against the reference run, which runs with the grid: a config it
        # could not load was reported after the whole grid had run (hours of a real sweep).
        try:
            _load_point(source, REFERENCE_LABEL, reference)
        except ElimfastError as failure:
            raise SweepError(_reference_failure(source, failure, reference_set)) from None
    ensemble = _check_ensemble(source, data["ensemble"]) if data.get("ensemble") is not None else None
    return SweepSpec(source=source, runs=runs, axes=axis_names, error_mode=error_mode,
                     reference=reference, order_axis=order_axis, ensemble=ensemble, base=base, axis_keys=axis_keys,
                     base_file=base_file)


def _apply_set(base: dict, overrides: dict) -> dict:
    """The base with a sweep-wide set (or error.reference.set) applied: merged into nested mappings
    (integration: {h: 0.001} keeps the base's t_end), except that a method naming its family
    replaces the base's method mapping, as a variant's does. A method's parameters are its
    family's: a user trial's reference {name: gauss, s: 6} kept the base's k = 12 and failed with
    'method.k: does not apply: gauss(s) takes no k; remove it', a key the sweep file did not have,
    and a sweep-wide {name: hbvm, s: 4} over an EHBVM(12,3) base ran HBVM(12,4). A method without
    a name ({s: 4}) changes only what it gives."""
    merged = copy.deepcopy(base)
    for key, value in overrides.items():
        if key == "method" and isinstance(value, dict) and "name" in value:
            merged[key] = copy.deepcopy(value)
        else:
            _deep_merge(merged, {key: value})
    return merged


def _reference_failure(source: str, failure: ElimfastError, reference_set: dict) -> str:
    """The one line of a reference run whose config does not load: at error.reference.set where
    the key at fault is in a section the set gives, else as the base's (a python: file they share)."""
    text = str(failure).removeprefix(f"{run_source(source, REFERENCE_LABEL)}: ")
    key = getattr(failure, "key", None)
    if key and key.split(".")[0] in reference_set:
        return f"{source}: error.reference.set: {text}"
    return f"{source}: error.reference: the reference run (the base with error.reference.set) does not load: {text}"


def _check_order_axis(source: str, name: str, axis: dict, index: int) -> None:
    """The observed order log(e1/e2)/log(x1/x2) is taken along the values x of the axis
    ``name``: refuse an axis without sizes (variants) or with a value that is no positive number."""
    why = "the observed order log(e1/e2)/log(x1/x2) needs a positive number x at each point of the axis"
    if "key" not in axis:
        _fail(source, "order_axis", f"the axis {name!r} is a list of variants (label and set), which have no size; "
                                    f"{why}: name a plain axis (name, key, values), such as h with key integration.h")
    from .problems.expressions import ExpressionError, evaluate_number
    for j, value in enumerate(axis["values"]):
        try:
            number = evaluate_number(value, what=f"grid[{index}].values[{j}]")
        except (ExpressionError, ValueError, TypeError):
            number = None
        if number is None or not number > 0:
            _fail(source, "order_axis", f"the axis {name!r} has the value {value!r} (grid[{index}].values[{j}]), "
                                        f"not a positive number; {why}; give order_axis an axis of such numbers, "
                                        "or leave it out")


def _check_fixed_steps(source: str, name: str, runs) -> None:
    """An order in h needs runs whose steps are h: one with adaptive steps (rtol, or a step_control)
    takes h as its first step only, and its 'order' was a number in that first step."""
    for run in runs:
        integration = run.config.get("integration") or {}
        adaptive = [key for key in ("rtol", "step_control") if integration.get(key) is not None]
        if adaptive:
            _fail(source, "order_axis", f"the axis {name!r} sets h, but run {run.label!r} has adaptive steps "
                                        f"(integration.{adaptive[0]}), where h is only the first step; give "
                                        "order_axis an axis of rtol or epsilon instead, or run those with fixed steps")


AXIS_KEYS = ("name", "key", "values", "labels")
VARIANT_KEYS = ("label", "set")


def _known_keys(source: str, where: str, mapping: dict, known: tuple[str, ...]) -> None:
    """Refuse a key of a grid axis or variant that sweeps do not read (with a suggestion)."""
    for name in mapping:
        if name not in known:
            close = closest(name, known)
            hint = f"did you mean {close!r}? " if close is not None else ""
            _fail(source, f"{where}.{name}", f"unknown key; {hint}(known: {', '.join(known)})")


def _written_out(source: str, where: str, config: dict) -> dict:
    """A sweep's base, set or variant with a run config's short forms written out
    (config.write_out_shorthands: method: EHBVM(12,3), problem: kepler), so that they merge
    with the rest as the long forms do."""
    from .config import _join, write_out_shorthands
    return write_out_shorthands(config, lambda path, text: SweepError(f"{source}: {where}{_join(path)}: {text}",
                                                                      source=source, key=f"{where}{_join(path)}"))


def _refuse_unused_parameters(source: str, base: dict, runs) -> None:
    """A parameter that the sweep (its set, an axis or a variant) gives a problem by expressions and
    that no expression uses changes nothing: a misspelt name, and every label would run the same run
    (a user trial). Refused, as --set refuses it (config.unused_parameters); parameters the base
    declares are the base's own business."""
    from .config import unused_parameter_text, unused_parameters
    base_problem = base.get("problem") if isinstance(base, dict) else None
    declared = set(map(str, (base_problem or {}).get("parameters") or {})) if isinstance(base_problem, dict) else set()
    for run in runs:
        problem = run.config.get("problem")
        if not (isinstance(problem, dict) and ("hamiltonian" in problem or "coordinates" in problem)
                and isinstance(problem.get("parameters") or {}, dict)):
            continue
        unused, used = unused_parameters(problem, run.config.get("events") if isinstance(run.config.get("events"),
                                                                                         dict) else None)
        for pname in unused:
            if pname not in declared:
                _fail(source, f"problem.parameters.{pname}", f"(run {run.label!r}, from the sweep's set or an axis) "
                                                             + unused_parameter_text(pname, used))


def _equal_value_key(value):
    """What two of an axis's values compare by: a number's value, whatever its spelling (0.1, '1/10'
    and '1e-1' are one run), or the value as written where it is no number (a method's name)."""
    from .problems.expressions import ExpressionError, evaluate_number
    try:
        return ("number", evaluate_number(value))
    except (ExpressionError, ValueError, TypeError):
        return ("as written", repr(value))


def _refuse_equal_values(source, key: str, values: list) -> None:
    """Two values of one plain axis that are the same value run the same run twice (a user trial:
    values [0.1, 1/10] on integration.h; [0.1, 0.1] was refused only through its repeated label)."""
    from .config import _short   # the config's way of quoting a value in a message
    seen: dict = {}
    for j, value in enumerate(values):
        first = seen.setdefault(_equal_value_key(value), j)
        if first != j:
            _fail(source, f"{key}.values[{j}]", f"{_short(value)} is the value of {key}.values[{first}] "
                                               f"({_short(values[first])}): the two runs would be one run twice; "
                                               "drop one")


def _check_axis_key(source, key: str, base: dict, dotted: str, value) -> None:
    """A plain axis sets ``dotted`` in every run: a key that no config has (integration.hh)
    would fail every run alike, one line each and exit code 1, so it is refused here as a
    fault of the sweep file. Only that: the values themselves are the runs' to judge."""
    from .config import unknown_key_text
    from .config_schema import RunConfig, ValidationError, config_location
    if "[" in dotted or "]" in dotted:
        _fail(source, key, f"{dotted}: not a key path (names joined by dots, no indices); vary a list whole, "
                           "e.g. key: conserve, values: [[angular_momentum], [lrl_y]]")
    config = copy.deepcopy(base)
    _set_path(config, dotted, value, source)
    try:
        RunConfig.model_validate(config)
    except ValidationError as err:
        for error in err.errors():
            location = config_location(error["loc"])
            if error["type"] == "extra_forbidden" and dotted.split(".")[:len(location)] == list(map(str, location)):
                _fail(source, key, f"{dotted}: {unknown_key_text(location)}")


def _check_axis_numbers(source, key: str, base: dict, dotted: str, values: list) -> None:
    """A plain axis of numbers whose value is a string that is no number ('abc' among h values)
    is refused here: that run alone failed, after the others had run (a user trial). Numbers
    are the axis's when the base holds one at the key or another value is one. Keys under
    problem are left to the runs (an initial value may name a parameter)."""
    from .problems.expressions import ExpressionError, evaluate_number
    if dotted.split(".")[0] == "problem":
        return
    node = base
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, dict) else None
    numeric = [v for v in [node, *values] if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if not numeric:
        return
    for j, value in enumerate(values):
        if isinstance(value, str):
            try:
                evaluate_number(value, what="value")
            except ExpressionError as err:
                _fail(source, f"{key}.values[{j}]", f"{err}, where the axis's other values of {dotted} are numbers; "
                                                    "write a number or arithmetic on numbers, pi and e, e.g. pi/30")


def _real_number(value) -> float | None:
    """A finite number given as 0.01, '1e-2' (YAML reads it as a string) or 'pi/100' (arithmetic,
    as in configs); None if it is none."""
    from .problems.expressions import ExpressionError, evaluate_number

    if isinstance(value, bool) or value is None:
        return None
    try:
        number = float(value) if isinstance(value, (int, float)) else evaluate_number(value, what="value")
    except (ExpressionError, ValueError, TypeError, OverflowError):
        return None
    return number if math.isfinite(number) else None


def _whole_number(value) -> int | None:
    """An integer given as 1000, 1e8, 1.0e8 or '10**8' (arithmetic, as in configs); None if it is none."""
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    number = _real_number(value)
    return int(number) if number is not None and number.is_integer() else None


def ensemble_bytes(n_trajectories: int, dimension: int, n_invariants: int, streamed: bool = False) -> int:
    """Memory an ensemble sweep holds at once. In memory (no output file, or keep_results): the
    states (as drawn, and the kernel's copy), the final states and their copy in the writer,
    invariant errors (kernel output and the result's per-name copies), and five per-trajectory
    numbers. Streamed to a file (``streamed``): the states and the kernel's copy, then the columns
    the summary table reads back (H's and each invariant's error, five per-trajectory numbers);
    the blocks in flight are a few seconds' rows. (Measured with tracemalloc, 4 coordinates, 10^6
    trajectories: 76 MB at the peak, this bound 112 MB; in memory 184 MB.)"""
    if streamed:
        return 8 * n_trajectories * (2 * dimension + (1 + n_invariants) + 5)
    return 8 * n_trajectories * (4 * dimension + 2 * (1 + n_invariants) + 5)


def _check_ensemble(source, ensemble) -> dict:
    if not isinstance(ensemble, dict):
        _fail(source, "ensemble", "must be {n: N, seed: S, spread: D} or {states: [[...], ...]}")
    unknown = sorted(set(ensemble) - {"n", "seed", "spread", "states"})
    if unknown:
        _fail(source, f"ensemble.{unknown[0]}", "unknown key; use n, seed, spread or states")
    if "states" in ensemble:
        if set(ensemble) != {"states"}:
            _fail(source, "ensemble", "give either states or n/seed/spread, not both")
        states = ensemble["states"]
        if not isinstance(states, list) or not states or not all(isinstance(r, list) for r in states):
            _fail(source, "ensemble.states", "must be a non-empty list of initial states (lists of numbers)")
        numbers = []
        for i, state in enumerate(states):
            numbers.append([_real_number(value) for value in state])
            for j, value in enumerate(numbers[-1]):
                if value is None:   # numbers as everywhere in configs: 1e-1 (a string to YAML), pi/4
                    _fail(source, f"ensemble.states[{i}][{j}]", f"must be a finite number (or arithmetic on "
                                                                f"numbers, pi and e), got {state[j]!r}")
        return {"states": numbers}
    n = _whole_number(ensemble.get("n"))
    if n is None or n < 1:
        _fail(source, "ensemble.n", f"must be a positive integer, got {ensemble.get('n')!r}")
    seed = _whole_number(ensemble.get("seed", 0))
    if seed is None or seed < 0:
        _fail(source, "ensemble.seed", f"must be a non-negative integer, got {ensemble.get('seed')!r}")
    spread = _real_number(ensemble.get("spread", 0.01))
    if spread is None or spread < 0:
        _fail(source, "ensemble.spread", f"must be a number >= 0, got {ensemble.get('spread', 0.01)!r}")
    return {"n": n, "seed": seed, "spread": spread}


def run_ensemble_sweep(spec: SweepSpec, threads: int | None = None, on_start: Callable[[int], None] | None = None):
    """Run an ensemble sweep in the parallel kernel, in one call: returns (RunSpec, Y0,
    EnsembleResult). ``on_start(n_trajectories)`` is called once the states are drawn, before
    the kernel. (``run_to_file`` with a path runs it in blocks, each stored as it ends.)"""
    run, states = ensemble_states(spec)
    ensemble = ensemble_run(spec, run, states, threads)
    if on_start is not None:
        on_start(states.shape[0])
    return run, states, ensemble.result(states, ensemble.rows(states))


def ensemble_run(spec: SweepSpec, run, states: np.ndarray, threads: int | None = None):
    """The ensemble.EnsembleRun of an ensemble sweep (its base's RunSpec ``run`` from ``states``),
    validated as integrate_ensemble validates; SweepError naming the sweep file if invalid."""
    from .ensemble import EnsembleRun, check_states

    try:
        return EnsembleRun.from_spec(run, check_states(run.problem, states)[0], n_threads=threads)
    except (ValueError, TypeError) as error:
        raise SweepError(f"{spec.source}: ensemble: {error}") from None


def block_line(rows: dict, start: int, stop: int, done: int, total: int, rate: float | None = None) -> str:
    """The progress line of an ensemble block just stored (or put in place); ``rate``: trajectories
    a second so far, for the time left (a user trial's 10^8 trajectories showed no end in sight)."""
    from .kernels.codes import STATUS_OK
    from .streaming import _duration   # a run's progress line writes its ETA so too
    failed = int(np.count_nonzero(rows["status"] != STATUS_OK))
    left = f", ETA {_duration((total - done) / rate)}" if rate and done < total else ""
    return f"[{done:,}/{total:,}] trajectories {start}-{stop - 1}: {failed} failed{left}"


def ensemble_states(spec: SweepSpec, streamed: bool = False):
    """(RunSpec of the base, Y0 (n_traj, 2m)) of an ensemble sweep: its explicit states, or
    ``n`` seeded perturbations of the base's initial state. ``streamed``: the results go to a file
    block by block and are read back lazily (the memory check's smaller bound, ensemble_bytes)."""
    from .config import load_run_from_dict
    from .integrate import Integration

    run = load_run_from_dict(copy.deepcopy(spec.base), source=spec.source, base_dir=Path(spec.source).parent)
    # The ensemble kernel takes fixed steps and keeps per trajectory its end only: a base with
    # step control, output times or events ran silently without them (or failed on 'h ... None').
    integration = spec.base.get("integration") if isinstance(spec.base.get("integration"), dict) else {}
    control = next((key for key in ("rtol", "atol", "step_control", "epsilon") if key in integration), "step_control")
    ignored = ((f"integration.{control}", "adaptive steps", run.step_control is not None),
               ("output.times", "output times", run.t_eval is not None), ("events", "events", bool(run.events)),
               ("solver.project_energy", "the energy projection (docs/methods.md#energy-projection)",
                bool(run.solver.project_energy)))
    for key, what, given in ignored:
        if given:
            raise SweepError(f"{spec.source}: base.{key}: an ensemble takes fixed steps h and keeps each trajectory's "
                             f"final state, invariant errors and status, without {what}; remove it, or run the "
                             "states as a grid sweep (one run per state)")
    y0 = Integration.from_spec(run).y
    if "states" in spec.ensemble:
        for index, state in enumerate(spec.ensemble["states"]):
            if len(state) != y0.size:
                raise SweepError(f"{spec.source}: ensemble.states[{index}]: has {len(state)}; each state needs "
                                 f"{y0.size} numbers ({', '.join(run.problem.coordinate_names)})")
        try:
            states = np.array(spec.ensemble["states"], dtype=np.float64)
        except (TypeError, ValueError):
            raise SweepError(f"{spec.source}: ensemble.states: every state must be a list of numbers") from None
    else:
        n = spec.ensemble["n"]
        require_memory(ensemble_bytes(n, y0.size, len(run.problem.invariant_names), streamed),
                       f"ensemble.n = {n:,} trajectories of {y0.size} coordinates", "lower n, or split the ensemble "
                       "into several sweeps with different seeds", spec.source, "ensemble.n")
        rng = np.random.default_rng(spec.ensemble["seed"])
        # In place: y0 + spread z with one array of n states at a time, not three (the same numbers)
        states = rng.standard_normal((n, y0.size))
        states *= spec.ensemble["spread"]
        states += y0
    return run, states


def ensemble_table(result, fmt: str = "markdown") -> tuple[list[str], list[list[str]]]:
    """One row per invariant (and H): max and median over trajectories of max |I(t) - I(0)|."""
    _fmt = (lambda value: _number(value, fmt == "csv"))  # noqa: E731
    ok = result.ok
    header = ["quantity", "max over trajectories", "median", "trajectories"]
    rows = []
    for name, errors in result.invariant_errors.items():
        values = errors[ok]
        rows.append([f"max err {name}", _fmt(float(values.max())) if values.size else "",
                     _fmt(float(np.median(values))) if values.size else "", f"{int(ok.sum())} ok"])
    iterations = result.iterations[ok]
    if iterations.size:
        rows.append(["iterations per trajectory", str(int(iterations.max())), str(int(np.median(iterations))),
                     f"{int(ok.sum())} ok"])
    # Steps split, or taken without imposing the invariants, are work and a warning the table shows
    # (a user trial: an LJ trimer at rest, 932 of 1000 steps unimposed, read only as 1540044 iterations).
    for name, what in (("split_steps", "split steps per trajectory"),
                       ("unimposed_steps", "steps not imposing the invariants, per trajectory")):
        counts = np.asarray(getattr(result, name))[ok]
        if counts.size and counts.max() > 0:
            rows.append([what, str(int(counts.max())), str(int(np.median(counts))),
                         f"{int((counts > 0).sum())} of {int(ok.sum())} ok have some"])
    multipliers = result.max_multiplier[ok]
    has_multipliers = result.method.multiplier_count(len(result.conserve)) > 0
    if has_multipliers and multipliers.size and not np.all(np.isnan(multipliers)):
        rows.append(["max |alpha|/|lambda|", _fmt(float(np.nanmax(multipliers))),
                     _fmt(float(np.nanmedian(multipliers))), f"{int(ok.sum())} ok"])
    rows.append(["failed trajectories", str(result.n_failed), "", f"of {result.n_trajectories}"])
    return header, rows


def _rebase_paths(config: dict, config_dir: Path, sweep_dir: Path) -> dict:
    """A base config's relative paths (python: problems) are relative to its own folder."""
    problem = config.get("problem")
    if isinstance(problem, dict) and isinstance(problem.get("python"), str):
        target = Path(problem["python"])
        if not target.is_absolute():
            problem["python"] = os.path.relpath(config_dir / target, sweep_dir)
    return config


# --- running ----------------------------------------------------------------------

# What changes the solver settings of a sweep's runs: a sweep has no --set. A grid sweep's
# --resume takes an edited sweep file whose runs stored complete keep their configs outside
# solver.* (solver_only_edit) and runs the failed ones with the new settings; an ensemble's
# refuses any edit of its config or ensemble: section (same_trajectories).
# (No example setting here: it followed advice such as "no h cures this; impose other invariants"
# with a solver setting that cannot help.)
SWEEP_RERUN_ADVICE = ("in a sweep, make that change in the sweep file and continue it with --resume (it keeps "
                      "the runs stored complete if their configs change only in solver.*)")
ENSEMBLE_RERUN_ADVICE = ("in an ensemble sweep, make that change in the sweep file and run it again with "
                         "--overwrite (--resume refuses an edit of an ensemble's config)")


def for_sweep(message: str, ensemble: bool = False) -> str:
    """A run's failure message (integrate.failure_message, which leaves --resume to run files)
    with what works in a sweep, or in an ensemble sweep, added."""
    return f"{message}; {ENSEMBLE_RERUN_ADVICE if ensemble else SWEEP_RERUN_ADVICE}"


def run_source(source: str, label: str) -> str:
    """How messages name the run ``label`` of the sweep file ``source``: ``SWEEP [label]``, and
    ``SWEEP: error.reference`` for the reference run, whose label (REFERENCE_LABEL, with a NUL)
    is never printed (a user trial's terminal showed '[ reference]', and grep called the
    output a binary file)."""
    return f"{source}: error.reference" if label == REFERENCE_LABEL else f"{source} [{label}]"


# What a section a variant replaces must name: the keys that say which problem, method or step it is.
_SECTION_IDENTITY = {"problem": ("builtin", "python", "hamiltonian"), "method": ("name",),
                     "integration": ("h", "rtol", "step_control", "epsilon")}


def _refuse_partial_sections(source: str, where: str, replace: dict) -> None:
    """A variant's set that replaces the problem, the method or the integration with a mapping naming
    none, no step (``set: {problem: {parameters: {eccentricity: 0.3}}}``, ``{integration: {t_end: 20}}``):
    every run of it failed with "problem: no problem given" or "integration.h: missing", which did not
    say that the variant had replaced the base's whole section."""
    for section, identity in _SECTION_IDENTITY.items():
        value = replace.get(section)
        if isinstance(value, dict) and not any(name in value for name in identity):
            inner = next(iter(value), None)
            nested = (f", or vary {section}.{inner}.<key> with a plain axis (key: {section}.{inner}.<key>)"
                      if isinstance(value.get(inner), dict) else "")
            _fail(source, f"{where}.{section}",
                  f"replaces the base's whole {section} section (a variant's set replaces the top-level values it "
                  f"names) with one naming no {section} ({', '.join(identity)}); give the whole section{nested}")


def _load_point(source: str, label: str, config: dict):
    """The RunSpec of the grid point ``label`` of the sweep file ``source`` (its errors name both;
    its python: paths were made relative to the sweep file's folder, _rebase_paths): how _execute
    loads a run, and how --resume compares a stored run with the edited sweep's."""
    from .config import load_run_from_dict  # in a worker: keeps the parent light
    return load_run_from_dict(copy.deepcopy(config), source=run_source(source, label), base_dir=Path(source).parent)


def other_sweep_file(written_by: str | None, source) -> bool:
    """Is ``written_by`` (a sweep file's stored source attribute) another file than ``source``? A
    resume from another sweep file was called an edit of it (a user trial)."""
    return bool(written_by) and Path(written_by) != Path(source).resolve()


def solver_only_edit(spec: SweepSpec, path) -> Callable[..., dict[str, int]]:
    """The rule by which ``--resume`` continues a grid sweep's file written by an earlier text
    of the sweep file (SweepWriter's accept_edit): every run stored complete must still be a
    run of ``spec`` (by its label), with the same resolved config outside solver.* and
    problem.check (the keys a run file's --resume may change too, streaming.SOLVER_SECTIONS):
    those runs are kept as they are; failed, missing and new runs run with the edited file.
    So a failed run can be run again with more halvings or another solver, and values can be
    added to an axis, without recomputing the rest. Raises OutputError naming the first run
    and key that would change; returns {label: place in the edited grid}."""
    from .config import PythonNotAllowed
    from .streaming import LOAD_ONLY_KEYS, SOLVER_SECTIONS, config_difference, step_solver_change

    def accept(stored: dict[str, str], written_by: str | None = None,
               digests: dict[str, str] | None = None) -> dict[str, int]:
        runs = {run.label: run for run in spec.runs}
        other = other_sweep_file(written_by, spec.source)
        edited = (f"{path}: was written by the sweep {written_by}, and this is {Path(spec.source).resolve()}"
                  if other else f"{path}: the sweep (its file or a config it names) was edited")
        elsewhere = "give this sweep another output file" if other else "write the edited sweep to another file"
        for label, config_text in stored.items():
            if label not in runs:
                raise OutputError(f"{edited}, and the run {label!r}, stored complete, is no longer in it: --resume "
                                  f"keeps every stored run; pass --overwrite to start again, or {elsewhere}")
            try:
                point = _load_point(spec.source, label, runs[label].config)
            except PythonNotAllowed:
                raise   # not an edit: the user did not allow the run's python: file (a user trial)
            except ElimfastError as error:
                raise OutputError(f"{edited}, and the stored run {label!r} no longer loads: {error}") from None
            current = _config_text(point.resolved)
            changed = problem_file_changed((digests or {}).get(label), point.problem)
            if changed:
                raise OutputError(f"{path}: {changed}, the file of the run {label!r}, stored complete: the stored runs "
                                  "and the new ones would come from two versions of the problem; undo the change, or "
                                  "pass --overwrite to run every run with the new file, or choose another output "
                                  "file")
            # A key the sweep writes is named before one that only follows from it (a user trial: an
            # edit of eccentricity was named problem.initial.p2, one of rtol integration.atol), as
            # run --resume names the keys its user changed first.
            key = (config_difference(config_text, current, ignore=SOLVER_SECTIONS, ignore_keys=LOAD_ONLY_KEYS,
                                     prefer=_written_keys(runs[label].config))
                   or step_solver_change(config_text, current))   # solver.lim_metric changes the steps too
            if key is not None:
                why = ("which changes the steps themselves, and --resume keeps the stored runs' steps"
                       if key.startswith("solver.") else
                       "and --resume may change only solver.* of stored runs (their steps are kept)")
                raise OutputError(f"{edited}: {key} of the run {label!r}, stored complete, changed, {why}; pass "
                                  f"--overwrite to start again, or {elsewhere}")
        return {run.label: index for index, run in enumerate(spec.runs)}

    return accept


def _written_keys(config, prefix: str = "") -> tuple[str, ...]:
    """The dotted keys a run's config (as the sweep writes it, before it is resolved) gives values
    to, in the order written."""
    if not isinstance(config, dict):
        return (prefix.rstrip("."),) if prefix else ()
    return tuple(key for name, value in config.items() for key in _written_keys(value, f"{prefix}{name}."))


def same_trajectories(spec: SweepSpec, path, config_text: str) -> Callable[[str, str | None], None]:
    """The rule by which ``--resume`` continues an ensemble sweep's file (SweepWriter's accept_edit
    for an ensemble): what decides the trajectories, the ensemble's resolved config ``config_text``
    (the base with set: applied) and the ensemble: section, must be as the file stores them;
    comments, description: and how the same values are written may change (a user trial: a comment
    added at the top was refused as 'a different sweep file'). Called with the stored sweep text and
    the stored ensemble's config (None: the file holds no ensemble yet); raises OutputError naming
    the first key that differs. ensemblefile.check_resumable then compares the states bit for bit."""
    from .config import ConfigError, parse_yaml
    from .streaming import config_difference

    def accept(stored_sweep: str, stored_config: str | None) -> None:
        try:
            stored = parse_yaml(stored_sweep, source=str(path))
            stored_ensemble = _check_ensemble(str(path), stored.get("ensemble"))
        except (ConfigError, SweepError, AttributeError):   # unreadable: it differs as a whole
            stored_ensemble = None
        key = _first_difference(stored_ensemble, spec.ensemble, "ensemble")
        if key is None and stored_config is not None:
            key = config_difference(stored_config, config_text)
        if key is not None:
            raise OutputError(f"{path}: {key} changed since its stored trajectories were run (the sweep file or its "
                              "base config was edited), and --resume keeps them as they are; undo the edit, pass "
                              "--overwrite to start again, or write the edited sweep to another file")

    return accept


def _execute(label: str, coordinates: dict, config: dict, source: str, store_arrays: bool) -> RunOutcome:
    """Worker: load one run's config, integrate it, summarise. Never raises for a run's
    own failure: a bad config or a failed integration becomes the outcome's status."""
    from .integrate import Integration
    from .integrate import _collect as collect_result

    outcome = RunOutcome(label=label, coordinates=coordinates, status="complete")
    try:
        spec = _load_point(source, label, config)
    except ElimfastError as error:
        outcome.status = f"failed: {error}"
        outcome.config_error = True
        return outcome
    outcome.resolved = spec.resolved
    outcome.h = spec.h
    outcome.n_steps = spec.n_steps
    run = Integration.from_spec(spec)
    outcome.t_end = spec.t_end
    # (with the python: problem file's digest, read here where the run's functions were loaded: a
    # --resume compares it, solver_only_edit)
    outcome.file_attributes = {**(run.file_attributes() if run.adaptive_kernel else {}),
                               **problem_file_attributes(spec.problem)}
    needed = 2 * run_bytes(run)    # the chunks, then their concatenation
    available = memory_available()
    if available is not None and needed > MEMORY_FRACTION * available:
        outcome.status = (f"failed: {run_source(source, label)}: the run's {spec.n_steps:,} steps would need "
                          f"{_size(needed)} of memory in a sweep, which keeps every step; {_size(available)} are "
                          "available: raise output.every, shorten the run, or run it alone with elimfast run (which "
                          "streams to disk)")
        outcome.refused = True
        return outcome
    outcome.y_initial = run.y.copy()
    chunks = [run.initial_chunk()]
    start = time.perf_counter()
    try:
        while not run.finished:
            before = run.steps_done
            with kernel_call():
                chunks.append(run.advance(1 << 16))
    except Exception as error:   # noqa: BLE001 -- a problem function raised inside the kernel
        problem = spec.problem
        where = (getattr(problem, "source_file", None) or spec.resolved["problem"].get("python")
                 or f"problem {problem.name!r}")
        from .integrate import steps_before_raise
        step = before + steps_before_raise(run) + 1
        text = " ".join(str(error).split()) or "(no message)"
        outcome.wall_time = time.perf_counter() - start
        outcome.steps_done = before
        outcome.status = (f"failed: {where}: a problem function raised {type(error).__name__}: {text[:200]} at step "
                          f"{step} (t = {exact_time(run.t)})")
        return outcome
    outcome.wall_time = time.perf_counter() - start
    outcome.steps_done = run.steps_done
    outcome.y_final = run.y.copy()
    outcome.t_final = run.t
    result = run.result(chunks) if run.adaptive_kernel else collect_result(run, chunks)
    if run.status != 0:
        outcome.status = result.status = "failed: " + for_sweep(run.failure_message())
    _summarise(outcome, result, spec.solver)
    if store_arrays:
        outcome.result = result
    return outcome


def _summarise(outcome: RunOutcome, result, solver) -> None:
    """The table's numbers of one run, from its Result (fresh, or read back from a sweep file), run
    with ``solver`` (its SolverSettings)."""
    # An adaptive run's stats count every iteration (rejected steps' and side steps' too), as its grad H
    # evaluations do; its per-step record has the accepted steps' only. A row had 2495 iterations beside
    # 22,952 evaluations for k = 8 (a user trial): both now count the same iterations.
    outcome.iterations_total = int(result.stats.get("iterations", result.iterations.sum()))
    if "grad_H_evaluations" in result.stats:   # adaptive runs count their own
        outcome.grad_H_evaluations = int(result.stats["grad_H_evaluations"])
    else:   # fixed steps: the iterations', and the energy projection's one a step (stepper.project_energy)
        outcome.grad_H_evaluations = outcome.iterations_total * result.method.evaluations_per_iteration(
            len(result.conserve), solver.rhs == "stable")[0] + (result.steps_done if solver.project_energy else 0)
    outcome.n_steps = result.n_steps
    multipliers = result.alpha if result.alpha is not None else result.lam
    if multipliers is not None and multipliers.size:
        outcome.max_multiplier = float(np.fmax.reduce(np.abs(multipliers), axis=None))   # NaN: a step not imposed
    outcome.invariant_errors = result.invariant_errors()
    outcome.initial_invariants = result.initial_invariants()
    outcome.invariant_scales = result.invariant_scales()


def stored_outcome(path, run: SweepRun, group_name: str, keep_result: bool = False) -> RunOutcome:
    """The outcome of a run a sweep file already holds complete (``--resume`` skips it): the
    numbers of the table, from the stored run, as ``_execute`` computed them."""
    from .archive import load
    from .config import load_run_from_dict, parse_yaml
    from .io.runfile import RunFile

    with RunFile(Path(path), run=f"/runs/{group_name}") as stored:
        config_text = str(stored.attrs.get("config", ""))
        wall_time_s = float(stored.attrs.get("wall_time_s", 0.0))
    result = load(path, run=f"/runs/{group_name}")
    resolved = load_run_from_dict(parse_yaml(config_text, str(path)), source=str(path),
                                  base_dir=Path(path).parent)
    outcome = RunOutcome(label=run.label, coordinates=run.coordinates, status="complete",
                         resolved=resolved.resolved, n_steps=result.n_steps, steps_done=result.steps_done,
                         h=resolved.h, wall_time=wall_time_s, y_initial=result.y0.copy(),
                         y_final=result.y_final.copy(), t_final=result.t_final, t_end=resolved.t_end)
    _summarise(outcome, result, resolved.solver)
    if keep_result:
        outcome.result = result
    return outcome


_PR_SET_PDEATHSIG = 1   # linux/prctl.h


# Set in a worker by _worker_init: where it says which run it starts (_execute_noting_start).
_STARTED = None


def _execute_noting_start(label: str, coordinates: dict, config: dict, source: str, store_arrays: bool) -> RunOutcome:
    """_execute in a pool's worker, first telling the parent (through _STARTED) that this run
    began: if the worker dies, the parent knows which runs it may have died of (run_sweep)."""
    if _STARTED is not None:
        _STARTED.put(label)
    return _execute(label, coordinates, config, source, store_arrays)


def _worker_init(parent: int | None = None, allow_python: bool = False, started=None) -> None:
    """A forked worker starts with Python's default signal handling, not the parent's watchdog,
    and dies with its parent ``parent``: after a kill -9 of the sweep, orphaned workers waited
    forever on the pool's queue and, sharing the forked output file's descriptor, held its
    writer lock, so --resume and inspect refused the file until they were found and killed.
    ``allow_python``: the parent's config.python_allowed() (its allowing_python, if that is what
    allowed it, is not inherited by a process). ``started``: the pool's queue of runs begun."""
    import signal
    global _STARTED
    _STARTED = started
    from .config import ALLOW_PYTHON_ENV
    if allow_python:
        os.environ[ALLOW_PYTHON_ENV] = "1"
    else:   # the parent's answer, also where it said no to an inherited ELIMFAST_ALLOW_PYTHON
        os.environ.pop(ALLOW_PYTHON_ENV, None)
    with contextlib.suppress(ValueError, OSError):
        signal.set_wakeup_fd(-1)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGHUP, signal.SIG_DFL)   # the parent stops on it (StopOnSignals); a worker need not
    if parent is not None:
        with contextlib.suppress(OSError, AttributeError):
            import ctypes
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        if os.getppid() != parent:   # the parent died before prctl took effect
            os._exit(1)


def run_bytes(run) -> int:
    """Memory of one sweep run's results: per-step iterations and multipliers, per-sample t, y
    and invariants."""
    if run.n_steps is None:   # adaptive steps: their number is not known in advance
        return 0
    if run.adaptive_kernel:   # fixed steps with output times or events (adaptive.AdaptiveIntegration)
        samples = run.t_eval.size + 1 if run.t_eval.size else run.n_steps // run.store_every + 2
    else:
        samples = run.n_samples_between(0, run.n_steps) + 1
    per_sample = 8 * (1 + run.y.size + 1 + len(run.problem.invariant_names))
    return run.n_steps * 8 * (1 + run.multipliers.size) + samples * per_sample


def kernel_call():
    """The kernel-call marker of the command line's interrupt watchdog, if one is installed."""
    from . import streaming
    watchdog = streaming.current_watchdog()
    return watchdog.kernel_call() if watchdog is not None else contextlib.nullcontext()


def default_workers() -> int:
    return max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1))


def reference_key(spec: SweepSpec) -> str:
    """Which reference run a sweep has: its config, as canonical text. A resumed file's stored
    reference (SweepWriter.add_reference) serves only a sweep with the same key."""
    import json
    return json.dumps(spec.reference, sort_keys=True, default=str)


def _stored_reference(spec: SweepSpec, stored: dict | None) -> RunOutcome | None:
    """The reference run a resumed sweep file holds, as an outcome, when it is this sweep's and
    complete; else None (it runs again)."""
    if spec.reference is None or not stored or stored.get("key") != reference_key(spec) \
            or stored.get("status") != "complete":
        return None
    t_end = float(stored.get("t_end", math.nan))
    return RunOutcome(label=REFERENCE_LABEL, coordinates={}, status="complete",
                      y_final=np.asarray(stored.get("y_final"), dtype=np.float64),
                      t_final=float(stored.get("t_final", math.nan)), t_end=t_end if math.isfinite(t_end) else None)


def sweep_jobs(spec: SweepSpec, skip=frozenset()) -> list[tuple[str, dict, dict]]:
    """(label, coordinates, config) of every run to do: the grid's points not in ``skip``
    (runs a resumed file holds), then the reference run, if any."""
    jobs = [(run.label, run.coordinates, run.config) for run in spec.runs if run.label not in skip]
    if spec.reference is not None and REFERENCE_LABEL not in skip:   # (skipped: a resumed file holds it)
        jobs.append((REFERENCE_LABEL, {}, spec.reference))
    return jobs


def _expected_work(config: dict) -> float:
    """A rough measure of a run's work for ordering a pool's jobs: steps x quadrature nodes,
    from the raw config; infinite when it cannot tell (adaptive steps, n_steps from
    elsewhere, an expression it cannot read), so that such runs start first."""
    from .problems.expressions import evaluate_number
    try:
        integration = config.get("integration") or {}
        if integration.get("rtol") is not None or integration.get("step_control") is not None:
            return math.inf
        steps = abs(evaluate_number(integration["t_end"]) - evaluate_number(integration.get("t0", 0.0)))
        steps /= abs(evaluate_number(integration["h"]))
        method = config.get("method") or {}
        nodes = max(int(method.get(key) or 0) for key in ("k", "r", "s"))
        return steps * max(nodes, 1)
    except Exception:   # noqa: BLE001 -- only an ordering hint; the worker reports real errors
        return math.inf


def _stop_pool(pool) -> None:
    """Kill a pool's workers now and let it go (a worker inside a kernel call cannot run a signal
    handler)."""
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        with contextlib.suppress(Exception):
            process.kill()
    pool.shutdown(wait=False, cancel_futures=True)


def run_sweep(spec: SweepSpec, workers: int | None = None, store_arrays: bool = True,
              on_done: Callable[[RunOutcome, int, int], None] | None = None,
              skip=frozenset(), on_message: Callable[[str], None] | None = None
              ) -> tuple[list[RunOutcome], RunOutcome | None]:
    """Run every point (and the reference run, if any) in ``workers`` processes.

    Returns the outcomes in grid order and the reference outcome. ``on_done(outcome,
    done, total)`` is called in the parent as each run finishes (progress, writing).
    Workers are forked where the platform allows it: they inherit the loaded kernels
    instead of importing and loading them again. Runs labelled in ``skip`` are not run
    (nor returned). A worker that dies is replaced, and the runs it may have died of run again
    one at a time (``on_message`` says so); a run whose worker dies twice fails.
    """
    workers = default_workers() if workers is None else int(workers)
    if workers < 1:
        raise SweepError("--workers must be at least 1")
    if workers > MAX_WORKERS_PER_CORE * default_workers():
        raise SweepError(f"--workers {workers}: at most {MAX_WORKERS_PER_CORE * default_workers()} ("
                         f"{MAX_WORKERS_PER_CORE} per core; each worker is a process running one kernel at a time)")
    jobs = sweep_jobs(spec, skip)
    total = len(jobs)
    results: dict[str, RunOutcome] = {}
    if total == 0:
        pass
    elif workers == 1:
        for done, (label, coordinates, config) in enumerate(jobs, start=1):
            outcome = _execute(label, coordinates, config, spec.source, store_arrays)
            results[label] = outcome
            if on_done:
                on_done(outcome, done, total)
    else:
        # Longest runs first: the pool hands out the next job as a worker frees up, so the
        # long runs no longer come last and leave one worker busy while the other idles
        # (Table 1 in grid order ended with its two longest runs).
        jobs = sorted(jobs, key=lambda job: -_expected_work(job[2]))
        # A warm pool: the shortest run here, before forking. Its first run costs a process
        # about 0.04 s of CPU (Table 1: the problem's functions, the quadrature of the method
        # tables, the kernel's first call), which every worker then inherits instead of
        # paying again.
        # Pickling names each Numba function of the outcome (Numba gives a function its id when
        # it is first pickled). Named before forking, the workers share the names, and their
        # results unpickle here onto the functions loaded already; named in each worker, every
        # result's problem functions were rebuilt here and compiled from source (Numba caches
        # no rebuilt function): about 0.2 s each, 1.2 s of Table 1 with 2 workers. Before
        # on_done, which may drop the arrays once it has stored them. A run whose config is
        # refused names nothing (a user trial: the shortest run refused, the stored results
        # compiled here, "compiling Numba kernels" on a warm cache): the next shortest then runs
        # here too, until one loads (refusals cost no steps).
        done = 0
        while True:
            outcome = _execute(*jobs.pop(), spec.source, store_arrays)
            results[outcome.label] = outcome
            pickle.dumps(outcome)
            done += 1
            if on_done:
                on_done(outcome, done, total)
            if not outcome.config_error or not jobs:
                break
        # Load the kernels and the config machinery before forking: every worker then
        # inherits them instead of loading them again. Not when the first run's config was
        # refused: on an empty cache the sweep compiled for 2 minutes, then reported that every
        # run's config was refused (a user trial); the runs that load compile in their workers.
        from . import config
        if not outcome.config_error:
            from .kernels import stepper  # noqa: F401
        method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        context = multiprocessing.get_context(method)
        # Freeze what is loaded while the workers fork: a worker's garbage collector then never
        # walks (and so never copies, page by page) the parent's Numba objects.
        allowed = config.python_allowed()
        pending = {label: (label, coordinates, config) for label, coordinates, config in jobs}
        order = [label for label, _, _ in jobs]
        deaths: dict[str, int] = {}
        unexplained = 0
        alone: list[str] = []   # runs that were in flight when a worker died: each run by itself next
        while pending:
            # A worker that dies (the out-of-memory killer, a kill, a crash in compiled code) breaks
            # the pool and every run in flight (a user trial: the whole sweep ended in an internal
            # error). The runs it may have died of are run again, one at a time, and a run whose
            # worker dies twice fails with that reason; the others go on in a new pool.
            batch = [alone.pop(0)] if alone else [label for label in order if label in pending]
            started = context.SimpleQueue()
            gc.freeze()
            pool = ProcessPoolExecutor(max_workers=max(1, min(workers, len(batch))), mp_context=context,
                                       initializer=_worker_init, initargs=(os.getpid(), allowed, started))
            try:
                futures = {pool.submit(_execute_noting_start, *pending[label], spec.source, store_arrays): label
                           for label in batch}
                gc.unfreeze()   # the workers are forked (all at the first submit)
                for future in as_completed(futures):
                    outcome = future.result()
                    results[outcome.label] = outcome
                    pending.pop(outcome.label, None)
                    done += 1
                    if on_done:
                        on_done(outcome, done, total)
            except BrokenProcessPool:
                _stop_pool(pool)
                begun = set()
                while not started.empty():
                    begun.add(started.get())
                suspects = [label for label in order if label in begun and label in pending]
                for label in suspects:
                    deaths[label] = deaths.get(label, 0) + 1
                again = [label for label in suspects if deaths[label] < 2]
                given_up = [label for label in suspects if deaths[label] >= 2]
                if on_message is not None:
                    parts = [f"running {'them' if len(again) > 1 else 'it'} again, one at a time"] if again else []
                    parts += [f"{', '.join(given_up)} failed: its worker died twice"] if given_up else []
                    on_message(f"a worker process died (killed, out of memory, or a crash) while running "
                               f"{', '.join(suspects) or 'no run yet'}: {'; '.join(parts) or 'starting another'}")
                if not suspects:   # died before it began a run: that is not a run's doing
                    unexplained += 1
                    if unexplained >= 3:
                        raise SweepError("the sweep's worker processes died three times before they began a run "
                                         "(killed, or out of memory at start); run it with --workers 1, or resume "
                                         "it once the machine has room") from None
                for label in suspects:
                    if label in given_up:
                        outcome = RunOutcome(label=label, coordinates=pending.pop(label)[1], status=(
                            f"failed: {run_source(spec.source, label)}: its worker process died while running "
                            "it, twice (killed: by the out-of-memory killer, a kill, or a crash); run it alone "
                            "with elimfast run to see why, or resume the sweep to try it again"))
                        results[label] = outcome
                        done += 1
                        if on_done:
                            on_done(outcome, done, total)
                    elif label not in alone:
                        alone.append(label)
                continue
            except BaseException:
                # Ctrl-C, SIGTERM or an error: the workers stop now (a worker inside a kernel call
                # cannot run a signal handler, so it is killed), unfinished runs are dropped.
                _stop_pool(pool)
                raise
            pool.shutdown(wait=True)
    reference = results.pop(REFERENCE_LABEL, None) if spec.reference is not None else None
    return [results[run.label] for run in spec.runs if run.label in results], reference


# --- tables -------------------------------------------------------------------------

def errors_of(spec: SweepSpec, outcomes: list[RunOutcome], reference: RunOutcome | None) -> dict[str, float]:
    """max-norm error of each run's final state (nan where there is no error to compute: a run
    that a terminal event stopped before its t_end has no state at t_end to compare; a user trial
    got 'error 2.5, order 0.00' for runs stopped at the apocentre, compared with y0)."""
    errors = {}
    if reference is not None and reference.ended_before_t_end:
        reference = None
    for outcome in outcomes:
        value = math.nan
        if outcome.ok and outcome.y_final is not None and not outcome.ended_before_t_end:
            if spec.error_mode == "initial":
                value = float(np.max(np.abs(outcome.y_final - outcome.y_initial)))
            elif spec.error_mode == "reference" and reference is not None and reference.ok:
                value = float(np.max(np.abs(outcome.y_final - reference.y_final)))
        errors[outcome.label] = value
    return errors


# An order taken from an error at rounding's size measures rounding, not the method (a user trial's
# HBVM(8,4) column read -1.60 and 0.43 unflagged): the table says so. Rounding's size: this many eps
# of the state per square root of the steps (a random walk's). Kepler e = 0.6 over one period,
# HBVM(8,4) at 50..800 steps: errors 1.1e-7 .. 1.8e-12 give orders 7.9-8.0, unflagged; 7.9e-15 at
# 400 steps (7.82) and 1.9e-14 at 800 (-1.26) are flagged.
ROUNDOFF_EPS = 10.0


def at_roundoff(outcome: RunOutcome, error: float) -> bool:
    """Is ``error`` (a run's error) within rounding of its state: ROUNDOFF_EPS eps sqrt(steps) max |y0|?"""
    if outcome.y_initial is None:
        return False
    size = float(np.max(np.abs(outcome.y_initial)))
    return error <= ROUNDOFF_EPS * 2.0 ** -52 * math.sqrt(max(outcome.steps_done, 1)) * size


def orders_of(spec: SweepSpec, outcomes: list[RunOutcome], errors: dict[str, float],
              roundoff: set | None = None) -> dict[str, float]:
    """Observed order log(e1/e2)/log(x1/x2) between successive points of order_axis, x the
    axis's value in each run (order_axis_value: h for an h axis, epsilon for an epsilon axis).
    It was always taken in the runs' h, which an epsilon axis leaves unset: a user trial's
    order column was empty where the errors fell 64x per halving of epsilon. ``roundoff``, if
    given, gets the labels whose order was taken from an error at rounding's size (at_roundoff)."""
    orders = {o.label: math.nan for o in outcomes}
    if spec.order_axis is None:
        return orders
    groups: dict[tuple, list[RunOutcome]] = {}
    for outcome in outcomes:
        key = tuple((a, outcome.coordinates[a]) for a in spec.axes if a != spec.order_axis)
        groups.setdefault(key, []).append(outcome)
    written = {run.label: run.config for run in spec.runs}
    for members in groups.values():
        # Against the last run before it that has an error and a value: a failed or refused run in
        # between left the next row's order empty (a user trial: h = pi/30, 0.7 refused, pi/60).
        usable = None
        for current in members:
            e1, x1 = errors[current.label], order_axis_value(spec, current, written.get(current.label))
            if not (current.ok and e1 > 0 and x1 > 0):
                continue
            if usable is not None and usable[1] != x1:
                orders[current.label] = math.log(usable[0] / e1) / math.log(usable[1] / x1)
                if roundoff is not None and (usable[2] or at_roundoff(current, e1)):
                    roundoff.add(current.label)
            usable = (e1, x1, at_roundoff(current, e1))
    return orders


def order_axis_value(spec: SweepSpec, outcome: RunOutcome, config: dict | None) -> float:
    """The value of the order axis's key in a run: as the run resolved it (the h it took, which
    fits the interval), else as the sweep file wrote it (``config``, the run's); nan if neither
    is a number."""
    from .problems.expressions import evaluate_number
    key = spec.axis_keys.get(spec.order_axis)
    if key is None:
        return math.nan
    for source in (outcome.resolved, config):
        value = _axis_value(source, key) if source else None
        try:
            return evaluate_number(value)
        except Exception:   # noqa: BLE001 -- not a number here (None, a mapping): try the next
            continue
    return math.nan


def order_column(spec: SweepSpec) -> str:
    """The table's order column: 'order' along h (the usual sense), 'order in <axis>' otherwise."""
    return "order" if spec.axis_keys.get(spec.order_axis) == "integration.h" else f"order in {spec.order_axis}"


def _axis_value(resolved: dict, dotted: str):
    """The resolved value of a plain axis's key (a number where the config evaluated one)."""
    node = resolved
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def table_rows(spec: SweepSpec, outcomes: list[RunOutcome], reference: RunOutcome | None,
               fmt: str = "markdown") -> tuple[list[str], list[list[str]]]:
    """The sweep's summary table: one row per run, formatted for ``fmt``.

    markdown: numbers to 4 digits, an axis by its label (pi/30). csv: numbers at full
    precision (repr: they read back exactly), a plain axis by its value, with the value
    as the sweep file writes it in a column ``<axis>_expression`` beside it (and the
    label in ``<axis>_label`` where the axis names its values otherwise). Each invariant's max |I - I0| comes
    with its relative error max |I - I0| / |I0| (relative to the size of I's terms where I0 ~ 0,
    integrate.relative_reference).
    """
    errors = errors_of(spec, outcomes, reference)
    roundoff: set[str] = set()
    orders = orders_of(spec, outcomes, errors, roundoff)
    csv = fmt == "csv"
    invariant_names = []
    for outcome in outcomes:
        for name in outcome.invariant_errors:
            if name not in invariant_names:
                invariant_names.append(name)
    expanded = [a for a in spec.axes if csv and a in spec.axis_keys]
    written = {run.label: {axis: _axis_value(run.config, spec.axis_keys[axis]) for axis in expanded}
               for run in spec.runs}   # each plain axis's value as the sweep file writes it (pi/30)
    labelled = [a for a in expanded if any(o.coordinates.get(a) != str(written.get(o.label, {}).get(a))
                                           for o in outcomes)]
    header = []
    for axis in spec.axes:
        header += [axis, f"{axis}_expression"] + ([f"{axis}_label"] if axis in labelled else []) \
            if axis in expanded else [axis]
    header += (["error"] if spec.error_mode else []) + ([order_column(spec)] if spec.order_axis else []) \
        + ["steps", "iterations", "grad H evals", "max |alpha|/|lambda|"]
    for name in invariant_names:
        header += [f"max err {name}", f"max rel err {name}"]
    header.append("status")
    rows = []
    for outcome in outcomes:
        row = []
        for axis in spec.axes:
            label = outcome.coordinates.get(axis, "")
            if axis in expanded:
                value = _axis_value(outcome.resolved, spec.axis_keys[axis])
                as_written = str(written.get(outcome.label, {}).get(axis, label))
                number = isinstance(value, (int, float)) and not isinstance(value, bool)   # True is not 1.0
                row += [_number(value, csv) if number else as_written, as_written]
                row += [label] if axis in labelled else []
            else:
                row.append(label)
        figure = _figure_cell(outcome, csv)
        if spec.error_mode:
            row.append(figure(errors[outcome.label]))
        if spec.order_axis:
            order = orders[outcome.label]
            row.append(figure(math.nan) if not outcome.ok else "" if math.isnan(order)
                       else repr(order) if csv else f"{order:.2f}" + (" (round-off)" if outcome.label in roundoff
                                                                      else ""))
        row.append(str(outcome.steps_done) if outcome.steps_done else "")
        row.append(str(outcome.iterations_total) if outcome.steps_done else "")
        row.append(str(outcome.grad_H_evaluations) if outcome.steps_done else "")
        row.append(figure(outcome.max_multiplier))
        relative = outcome.relative_invariant_errors
        for name in invariant_names:
            row += [figure(outcome.invariant_errors.get(name, math.nan)), figure(relative.get(name, math.nan))]
        row.append(outcome.status_text)
        rows.append(row)
    return header, rows


FAILED_CELL = "failed"   # a failed run's figures in a markdown table (CSV: empty, its status column says why)
NO_FIGURE_CELL = "-"     # a figure that does not exist (no step done), in a markdown table (CSV: empty)


def _figure_cell(outcome: RunOutcome, csv: bool) -> Callable[[float], str]:
    """How a run's figures (error, max |alpha|, invariant errors) are written in the table.

    A failed run shows none: its figures cover only the steps before the failure (none at
    all when it failed at its first step, where they were 0.000e+00), so beside complete
    runs they read as a result, often a better one. NaN, a figure that does not exist, is
    written as such, never as a number."""
    def cell(value) -> str:
        if not outcome.ok:
            return "" if csv else FAILED_CELL
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "" if csv else NO_FIGURE_CELL
        return _number(value, csv)
    return cell


def _number(value, full: bool = False) -> str:
    """A table's number: 4 significant digits, or full precision (repr) for CSV; '' for none."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    if isinstance(value, int) and not isinstance(value, bool):
        return str(value)
    return repr(float(value)) if full else f"{float(value):.3e}"


def _fmt(value: float) -> str:
    return _number(value)


def format_table(header: list[str], rows: list[list[str]], fmt: str = "markdown") -> str:
    if fmt == "csv":
        import csv
        import io
        buffer = io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(rows)
        return buffer.getvalue()
    # A '|' inside a cell would end it: markdown writes it as '\|'.
    header = [cell.replace("|", "\\|") for cell in header]
    rows = [[str(cell).replace("|", "\\|") for cell in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(header)]
    line = lambda cells: "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"  # noqa: E731
    return "\n".join([line(header), "|" + "|".join("-" * (w + 2) for w in widths) + "|", *map(line, rows)]) + "\n"


# --- a sweep into its file ------------------------------------------------------------------
@dataclass
class SweepOutcome:
    """What ``run_to_file`` did: the grid's outcomes and the reference run (a grid sweep), or
    the ensemble (an ensemble sweep); the file they were stored in (None: not stored)."""

    spec: SweepSpec
    path: Path | None
    outcomes: list[RunOutcome] = field(default_factory=list)
    reference: RunOutcome | None = None
    ensemble: Any = None                # elimfast.ensemble's result of an ensemble sweep

    def table(self, fmt: str = "markdown") -> tuple[list[str], list[list[str]]]:
        if self.ensemble is not None:
            return ensemble_table(self.ensemble, fmt)
        return table_rows(self.spec, self.outcomes, self.reference, fmt)

    def config_error(self) -> str | None:
        """The first run's error when every run of a grid sweep failed to load its config (an error of
        the base or of a problem file they share, not of a run): a bad input, said once."""
        runs = [o for o in self.outcomes if o.label != REFERENCE_LABEL]
        if self.ensemble is not None or not runs or not all(o.config_error for o in runs):
            return None
        return runs[0].status.removeprefix("failed: ")

    def failures(self) -> list[str]:
        """One line per thing that failed (empty when everything completed)."""
        if self.ensemble is not None:
            result = self.ensemble
            if not result.n_failed:
                return []
            return [f"{result.n_failed} of {result.n_trajectories} trajectories failed: "
                    f"{for_sweep(result.failure_message(int(result.ok.argmin())), ensemble=True)}"]
        lines = []
        if self.reference is not None and not self.reference.ok:
            lines.append(f"the reference run failed, so there are no errors: {self.reference.status}")
        elif self.reference is not None and self.reference.ended_before_t_end:
            # (a user trial: every error empty, exit 0, nothing said)
            lines.append(f"the reference run was ended by a terminal event at t = {self.reference.t_final:.10g}, "
                         "before its t_end, so there are no errors: give the reference no terminal event")
        failed = [o for o in self.outcomes if not o.ok]
        if failed:
            lines.append(f"{len(failed)} of {len(self.outcomes)} runs failed (see the status column)")
        return lines


def _config_text(resolved: dict) -> str:
    import yaml
    return yaml.safe_dump(resolved or {}, sort_keys=False, default_flow_style=None, width=100)


def refuse_python_not_allowed(spec: SweepSpec) -> None:
    """PythonNotAllowed, before any run, naming the first run (or an ensemble's base) whose config
    names an existing python: problem file that the user has not allowed (config.python_allowed):
    a user trial's sweep ran every other run first, then stopped on that one with exit 2."""
    from .config import PythonNotAllowed, python_allowed, python_file_named, python_refused_text
    if python_allowed():
        return
    configs = [("", spec.base)] if spec.ensemble is not None else [(run.label, run.config) for run in spec.runs]
    for label, config in configs:
        named = python_file_named(config, base_dir=Path(spec.source).parent)
        if named is not None and named.is_file():
            where = f" (run {label!r})" if label else ""
            raise PythonNotAllowed(f"{spec.source}{where}: problem.python: {named} {python_refused_text()}",
                                   key="problem.python")


def run_to_file(sweep, path=None, *, workers: int | None = None, overwrite: bool = False,
                resume: bool = False, keep_results: bool = False, client=None, scheduler: str | None = None,
                on_start: Callable[[int], None] | None = None,
                on_done: Callable[[RunOutcome, int, int], None] | None = None,
                on_message: Callable[[str], None] | None = None) -> SweepOutcome:
    """Run a sweep (a SweepSpec or the path of a sweep file) and store every run in the HDF5
    file ``path`` (None: store nothing), one /runs/<label> group per run as each finishes.

    A grid sweep runs in ``workers`` processes (``run_sweep``); an ensemble sweep runs in
    the parallel kernel on ``workers`` threads, and its file is created only once the
    ensemble is known to fit (``on_start(n_trajectories)`` is called then). ``on_done``:
    as in run_sweep, after the run is stored. The Results are dropped once stored, unless
    ``keep_results``. Raises SweepError for a bad sweep file, OutputError for an output
    that cannot be written; the runs' own failures are in the outcome (``failures()``).

    An ensemble with a ``path`` runs in blocks, each stored (and marked stored) as it ends
    or arrives, so that only the blocks in flight are in memory and a killed sweep keeps
    every stored block (io/ensemblefile.py). Its outcome's ``ensemble`` is then read from
    the file, each array when first used (all at once with ``keep_results``). Without a
    path, an ensemble runs in one kernel call (on a cluster: its blocks gathered in memory).

    ``resume``: ``path`` may exist and hold some of this sweep's runs (a sweep that was
    stopped or killed); those that are complete there are read back, not run again, and
    the others run and are added. For an ensemble: the trajectories marked stored are
    kept, the others run; the file ends as an uninterrupted run's, bit for bit.

    On a Dask cluster (docs/dask.md): ``client`` (a ``dask.distributed.Client``) runs the
    runs as Dask tasks, an ensemble as blocks of trajectories; or ``scheduler``, an
    address (``tcp://host:8786``) to connect to, or ``"local"`` for a LocalCluster of
    ``workers`` processes (default: one per core). Results are the same, bit for bit;
    this process stays the only writer of ``path``. ``on_message(line)``: what is being
    done (cluster, resume), for the progress display.
    """
    from .io.sweepfile import RUNS_PLANNED, SweepWriter

    if client is not None and scheduler is not None:
        raise SweepError("give either a Dask client or a scheduler address, not both")
    if resume and path is None:   # (a user trial: the whole sweep ran again, stored nothing, said nothing)
        raise SweepError("resume=True continues a sweep stored in a file: give its path")
    if scheduler is not None:
        from .distributed import check_scheduler
        check_scheduler(scheduler, workers)   # before any work: dask installed, address well formed
    if path is not None:   # before reading the sweep: an unwritable output is reported before any work
        from .io.safety import check_output_path
        path = check_output_path(Path(path).expanduser(), overwrite=overwrite and not resume, resume=resume)
    spec = sweep if isinstance(sweep, SweepSpec) else load_sweep(sweep)
    if path is not None:
        target = Path(path).expanduser().resolve()
        for read in spec.input_files():
            if read.exists() and read.resolve() == target:
                what = ("sweep file" if read == Path(spec.source) else "base config" if str(read) == spec.base_file
                        else "problem file")
                raise OutputError(f"{path}: is the sweep's {what} itself, which writing would replace; give another "
                                  "output file, e.g. out/sweep.h5")
    refuse_python_not_allowed(spec)
    say = on_message or (lambda line: None)
    writer = None

    def open_writer(ensemble=None):
        nonlocal writer
        if path is not None:
            writer = SweepWriter(path, sweep_text=Path(spec.source).read_text(errors="replace"),
                                 # absolute: the hints that quote it ("continue the sweep with elimfast
                                 # sweep SOURCE ...") are read from other folders (a user trial ran the
                                 # quoted relative path from another one: no such file)
                                 attributes={"source": str(Path(spec.source).resolve()),
                                             "axes": list(spec.axes) or [""],
                                             RUNS_PLANNED: len(spec.runs)},
                                 overwrite=overwrite or resume, resume=resume, ensemble=ensemble,
                                 accept_edit=solver_only_edit(spec, path) if ensemble is None else
                                 same_trajectories(spec, path, ensemble[2]))

    with contextlib.ExitStack() as stack:
        if scheduler is not None:
            from .distributed import connect
            client = stack.enter_context(connect(scheduler, workers, on_message=say))
        try:
            if spec.ensemble is not None and path is None:   # in memory: one kernel call, or blocks gathered
                if client is not None:
                    from .distributed import run_ensemble_on
                    _, _, result = run_ensemble_on(client, spec, on_start=on_start, on_message=say)
                else:
                    _, _, result = run_ensemble_sweep(spec, threads=workers, on_start=on_start)
                return SweepOutcome(spec=spec, path=path, ensemble=result)
            if spec.ensemble is not None:
                run, states = ensemble_states(spec, streamed=not keep_results)
                ensemble = ensemble_run(spec, run, states, None if client is not None else workers)
                if on_start is not None:
                    on_start(states.shape[0])
                if not resume or not path.exists():   # (a user trial's n = 10^8: 17.7 GB, without a word)
                    from .io.ensemblefile import bytes_on_disk
                    say(f"{path}: {states.shape[0]:,} trajectories take {_size(bytes_on_disk(ensemble, states))} "
                        "on disk, allocated as the file is created")
                open_writer((ensemble, states, _config_text(run.resolved)))
                _stream_ensemble(spec, writer, ensemble, states, client, say)
                writer.close()
                from .archive import load_ensemble
                return SweepOutcome(spec=spec, path=path, ensemble=load_ensemble(path, lazy=not keep_results))

            open_writer()
            done_before: dict[str, RunOutcome] = {}
            if writer is not None and writer.complete:
                for run in spec.runs:
                    if run.label in writer.complete:
                        try:
                            done_before[run.label] = stored_outcome(path, run, writer.complete[run.label],
                                                                    keep_result=keep_results)
                        except ElimfastError:   # cannot be read back (its python: file moved): run it again
                            writer.forget(run.label)
                edit = ""
                if writer.edited:
                    what = (f"it was written by the sweep {writer.written_by}"
                            if other_sweep_file(writer.written_by, spec.source) else "the sweep file was edited")
                    edit = (f" ({what}: the runs stored complete keep the settings they were solved with, the others "
                            "run with this file's)")
                say(f"resume: {len(done_before)} of {len(spec.runs)} runs are complete in {path}{edit}; "
                    f"running the other {len(spec.runs) - len(done_before)}")
            stored_reference = _stored_reference(spec, writer.stored_reference if writer is not None else None)
            if stored_reference is not None:
                say(f"resume: the reference run is stored in {path}: not run again")
            skip = set(done_before) | ({REFERENCE_LABEL} if stored_reference is not None else set())

            run_index = {run.label: index for index, run in enumerate(spec.runs)}

            def stored(outcome, done, total):
                if writer is not None and outcome.label == REFERENCE_LABEL:
                    writer.add_reference(key=reference_key(spec), status=outcome.status, y_final=outcome.y_final,
                                         t_final=outcome.t_final, t_end=outcome.t_end)
                elif writer is not None:
                    writer.add_run(outcome.label, outcome.result, status=outcome.status,
                                   config_text=_config_text(outcome.resolved), coordinates=outcome.coordinates,
                                   wall_time_s=outcome.wall_time, t_end=outcome.t_end,
                                   file_attributes=outcome.file_attributes, run_index=run_index.get(outcome.label))
                if not keep_results:
                    outcome.result = None   # stored: the parent keeps only the summary of each run
                if on_done is not None:
                    on_done(outcome, done, total)

            store_arrays = writer is not None or keep_results
            if client is not None:
                from .distributed import run_sweep_on
                outcomes, reference = run_sweep_on(client, spec, on_done=stored, store_arrays=store_arrays,
                                                   skip=skip, on_message=say)
            else:
                outcomes, reference = run_sweep(spec, workers=workers, on_done=stored, store_arrays=store_arrays,
                                                skip=skip, on_message=say)
            reference = reference if reference is not None else stored_reference
            ran = {outcome.label: outcome for outcome in outcomes}
            outcomes = [done_before.get(run.label) or ran[run.label] for run in spec.runs]
            return SweepOutcome(spec=spec, path=path, outcomes=outcomes, reference=reference)
        finally:
            if writer is not None:
                writer.close()


def _stream_ensemble(spec: SweepSpec, writer, ensemble, states: np.ndarray, client,
                     say: Callable[[str], None]) -> None:
    """Run the trajectories ``writer`` lacks (all, or what a resumed file lacks) in blocks,
    on ``client``'s cluster or here (ensemble.run_in_blocks), storing each block as it
    arrives; then mark the ensemble complete. Only the blocks in flight are held."""
    from .ensemble import STATUS_NAMES, run_in_blocks
    from .kernels.codes import STATUS_OK

    n = states.shape[0]
    todo = writer.ensemble_todo
    done = n - sum(stop - start for start, stop in todo)
    if done:
        say(f"resume: {done:,} of {n:,} trajectories are stored in {writer.path}; running the other {n - done:,}")
    if client is not None:
        from .distributed import ensemble_blocks_on
        blocks = ensemble_blocks_on(client, spec, states, todo, on_message=say)
    else:
        blocks = run_in_blocks(ensemble, states, todo)
    threads = 0   # of the blocks run now (0: none, a resumed file that held them all)
    began, done_before = time.perf_counter(), done
    with contextlib.closing(blocks):
        for start, stop, rows, block_threads in blocks:
            writer.add_ensemble_rows(start, stop, rows)
            threads, done = max(threads, block_threads), done + stop - start
            say(block_line(rows, start, stop, done, n, (done - done_before) / max(time.perf_counter() - began, 1e-9)))
    if not writer.ensemble_complete:
        writer.finish_ensemble(threads=threads, ok_status=STATUS_OK)


# The command line's flags that run_to_file's messages name, as run's keywords: in Python,
# "pass --overwrite" sent a user trial looking for a flag. Quoted commands ("elimfast sweep ...
# --resume") are left as they are.
_PYTHON_WORDING = ((re.compile(r"--(overwrite|resume)\b"), r"\1=True"), (re.compile(r"--workers (\d+)"), r"workers=\1"),
                   (re.compile(r"--(workers|scheduler)\b"), r"\1"))
_QUOTED_COMMAND = re.compile(r"elimfast (?:run|sweep|repair)\b[^;)]*")


def python_wording(message: str) -> str:
    """``message`` with the command line's flags (--overwrite, --resume, --workers, --scheduler)
    named as run's keywords, outside quoted elimfast commands."""
    pieces, last = [], 0
    for quoted in _QUOTED_COMMAND.finditer(message):
        pieces += [(message[last:quoted.start()], True), (quoted.group(), False)]
        last = quoted.end()
    pieces.append((message[last:], True))
    out = []
    for text, translate in pieces:
        if translate:
            for pattern, replacement in _PYTHON_WORDING:
                text = pattern.sub(replacement, text)
        out.append(text)
    return "".join(out)


def run(spec, path=None, *, client=None, allow_python: bool | None = None, **options) -> SweepOutcome:
    """Run a sweep (a SweepSpec or a sweep file's path), storing it in ``path`` if given;
    on the Dask cluster of ``client`` (a ``dask.distributed.Client``) if given, else in
    local worker processes. ``allow_python``: may the python: problem files its configs name
    be run (default: config.python_allowed(); the CLI's --allow-python). The options are those of
    ``run_to_file``; its errors name them as keywords (overwrite=True), where the command line's
    name its flags (--overwrite)."""
    from .config import allowing_python
    if client is not None and not (callable(getattr(client, "submit", None))
                                   and callable(getattr(client, "wait_for_workers", None))):
        raise TypeError(f"client must be a dask.distributed.Client (or None for local worker processes), got "
                        f"{type(client).__name__}; for a scheduler's address pass scheduler='tcp://host:8786'")
    try:
        with allowing_python(allow_python):
            return run_to_file(spec, path, client=client, **options)
    except ElimfastError as error:
        worded = python_wording(str(error))
        if worded != str(error):
            error.args = (worded,)
        raise
