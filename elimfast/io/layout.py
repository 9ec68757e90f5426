"""The layout of a run group, shared by the run file and every run of a sweep file.

A run group (the root of a run file, /runs/<label> of a sweep file) holds, every growing
dataset chunked, compressed with the shuffle filter and gzip, checksummed with HDF5's
fletcher32 filter, and extended as the run goes:

    t                      (samples,)           time of each sample; a dimension scale ('t')
    component              (2m,) strings        the state's component names, q then p; a dimension scale
    y                      (samples, 2m)        the state, on dimensions (t, component)
    invariants/H           (samples,)           the Hamiltonian at each sample, on dimension t
    invariants/<name>      (samples,)           every invariant of the problem; attributes ``imposed``,
                                                ``scale`` (the size of its terms at t0, Problem.invariant_scales)
                                                and ``value_at_t0`` (I of the initial state: the reference of
                                                the invariant errors, also when the first sample is later;
                                                H has both too; absent in files written before it)
    steps/iterations       (steps_done,) int32  solver iterations of each step (every try and substep)
    steps/substeps         (steps_done,) int32  1, or the substeps of a step that was split
    steps/alpha            (steps_done, nu)     ELIM/EHBVM with nu >= 1 imposed invariants (NaN: a substep
                                                taken without imposing them, docs/solver.md)
    steps/lambda           (steps_done, nu+1)   LIM/GHBVM (H first, then the imposed invariants)
    steps/invariant        (nu or nu+1,)        which invariant each multiplier column belongs to
    method/A, b, c         the Runge-Kutta form (all but LIM/GHBVM; for ELIM/EHBVM the
                           underlying HBVM(k,s) tableau, i.e. eta = 1: attribute ``tableau``)
    method/quadrature_nodes, quadrature_weights                      k-point Gauss-Legendre on [0, 1]
    method/invariant_quadrature_nodes, invariant_quadrature_weights  the r points (ELIM/LIM)

Every dataset has HDF5 dimension scales (netCDF-4's convention), so that
``xarray.open_dataset(path, engine="h5netcdf")`` opens a run file with ``t`` and
``component`` as coordinates, and ``xarray.open_datatree`` opens every group (a sweep
file: one node per run; ``elimfast.open_datatree`` builds the same tree in time linear in
the runs, where h5netcdf's grows with their square: io/xarray_tree.py). Dimensions that are not variables (``step``, ``node``, ...) are
netCDF's "dimension but not a variable" scales: empty datasets that hold only a length.
Variables carry ``long_name``, and ``units`` where the problem states its units (the
built-in solar system: AU, days, solar masses; also the group attributes
``<quantity>_unit``).

Format history: 1 (no checksums), 2 (fletcher32, /state/record; the component names as
an attribute of /y named ``coordinates``, which CF reserves: still read), 3 (dimension
scales, ``component``, long_name and units). Yes/no attributes became int8 0/1 within format 3
(flag_attribute; read_flag reads both): readers took them by truth value before too, so no new version.
"""
from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from .safety import OutputError, _plain  # noqa: F401 (_plain: the attribute reader, re-exported for the readers)

FORMAT = "elimfast-run"
FORMAT_VERSION = 3            # 2: fletcher32 on every chunk, /state/record; 3: dimension scales, /component
# SWMR needs the 1.10 file format; bounding it at 1.10 keeps the files readable by any
# HDF5 >= 1.10 (tools linked against older 1.x libraries are common).
LIBVER = ("v110", "v110")
# gzip (readable by every HDF5 tool, unlike lzf) at level 1 after the shuffle filter:
# levels above 1 cost more time than they save bytes on these data.
GZIP_LEVEL = 1
# Small HDF5 chunks: every flush recompresses the last, partial chunk of each dataset,
# so this bounds the cost of a flush (256 KiB chunks made flushes 3x slower).
CHUNK_BYTES = 1 << 14      # target bytes per HDF5 chunk
MIN_CHUNK_ROWS = 64
# Disk space reserved ahead of the writes of a chunk: the chunk's raw bytes (compression
# only shrinks them) times this factor, plus SPACE_MARGIN per dataset (each flush rewrites
# the last partial HDF5 chunk of each dataset at a new address) and SPACE_BASE for
# metadata and for closing the file. A 10^4-step Kepler run grew by 0.55 bytes per raw byte.
SPACE_FACTOR = 1.25
SPACE_MARGIN = 2 * CHUNK_BYTES
SPACE_BASE = 64 << 10
VERIFY_BLOCK_BYTES = 16 << 20   # bytes per read when verifying or reducing long datasets
STATUS_RUNNING = "running"
STATUS_COMPLETE = "complete"
STATUS_INTERRUPTED = "interrupted"
STATUS_KILLED = "killed"
FAILED_PREFIX = "failed: "
STOPPED_PREFIX = "stopped: "
# netCDF-4 marks a dimension scale that is no variable by this NAME (h5netcdf, netCDF-C).
DIMENSION_ONLY = "This is a netCDF dimension but not a netCDF variable.%10d"
LONG_NAMES = {"t": "time", "component": "state component (positions q, then momenta p)",
              "y": "state y = (q, p)", "H": "Hamiltonian (energy)", "iterations": "solver iterations per step",
              "substeps": "substeps per step (1: not split)",
              "alpha": "ELIM multiplier alpha per step (NaN: a substep not imposed)",
              "lambda": "LIM multiplier lambda per step", "invariant": "invariant of each multiplier column",
              "step_t": "time at the end of each step", "step_h": "size of each step"}
# The run group's dimension scales t and component (create_run_group), which xarray's DataTree
# passes down to every group below it: a child group of that name (an event 't') made every
# DataTree reader fail ("parent events already contains a variable named t").
INHERITED_COORDINATES = ("t", "component")


def _chunk_rows(row_bytes: int) -> int:
    return max(MIN_CHUNK_ROWS, CHUNK_BYTES // max(row_bytes, 1))


def _growing(group, name: str, width: int | None, dtype) -> "_Growing":
    """An empty dataset, chunked, compressed and checksummed, resizable along its first axis.

    Created through h5py's low-level API: the high-level one re-derives the filter
    pipeline for every dataset and costs more than writing a whole short run. fletcher32
    comes last in the pipeline, so it checksums the stored (compressed) bytes.
    """
    dtype = np.dtype(dtype)
    tail = () if width is None else (int(width),)
    rows = _chunk_rows(dtype.itemsize * (width or 1))
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk((rows,) + tail)
    dcpl.set_shuffle()
    dcpl.set_deflate(GZIP_LEVEL)
    dcpl.set_fletcher32()
    space = h5py.h5s.create_simple((0,) + tail, (h5py.h5s.UNLIMITED,) + tail)
    dataset_id = h5py.h5d.create(group.id, name.encode(), h5py.h5t.py_create(dtype), space, dcpl=dcpl)
    return _Growing(dataset_id)


class _Growing:
    """A dataset extended along its first axis by low-level writes (no h5py selection machinery)."""

    __slots__ = ("id", "rows", "tail", "dtype")

    def __init__(self, dataset_id):
        self.id = dataset_id
        shape = dataset_id.shape
        self.rows, self.tail = shape[0], tuple(shape[1:])
        self.dtype = dataset_id.dtype

    @property
    def attrs(self):
        return h5py.Dataset(self.id).attrs

    @property
    def row_bytes(self) -> int:
        return self.dtype.itemsize * int(np.prod(self.tail, dtype=np.int64))

    def append(self, data) -> None:
        count = len(data)
        if count == 0:
            return
        data = np.ascontiguousarray(data, dtype=self.dtype)
        start = self.rows
        self.id.set_extent((start + count,) + self.tail)
        file_space = self.id.get_space()
        file_space.select_hyperslab((start,) + (0,) * len(self.tail), (count,) + self.tail)
        self.id.write(h5py.h5s.create_simple((count,) + self.tail), file_space, data)
        self.rows = start + count

    def truncate(self, rows: int) -> None:
        self.id.set_extent((rows,) + self.tail)
        self.rows = rows




VALUE_AT_T0 = "value_at_t0"   # attribute of /invariants/<name>: I(t0), the reference of the invariant errors
# Attributes stats_<name> of a run through the adaptive kernel (run file root, sweep run): its
# Result.stats (steps, rejections, evaluations), labelled where /state/counters is a bare vector.
STATS_PREFIX = "stats_"


def stats_attributes(stats: dict) -> dict:
    """{stats_<name>: count} of a run's Result.stats (STATS_PREFIX)."""
    return {STATS_PREFIX + key: int(value) for key, value in stats.items()}

# The per-step datasets of /steps that are not multipliers (adaptive runs add h and t).
PER_STEP_RECORDS = ("iterations", "substeps", "h", "t")
STEP_SCALES = ("step", "invariant")   # the dimension scales of /steps


def multiplier_name(integration) -> str | None:
    """The name of the run's per-step multipliers ('alpha', 'lambda'), or None: the method's."""
    return integration.method.multiplier_name(len(integration.conserve))


def multiplier_datasets(steps) -> list[str]:
    """The per-step multipliers stored in /steps: every dataset but the per-step records. The
    file names them by the method's multiplier (alpha, lambda), so no reader lists families."""
    return [name for name in steps if name not in PER_STEP_RECORDS + STEP_SCALES]


PROBLEM_FILE_DIGEST = "problem_file_sha256"   # root attribute: the python: problem file the steps used
# Root attribute: the --set values the run was made with (JSON list of KEY=VALUE, the latest last),
# applied again over CONFIG on --resume so that they need not be given again while an edit of
# CONFIG still counts. Files written before it have none.
SET_OVERRIDES = "set_overrides"


def set_overrides_attribute(overrides) -> dict:
    """{SET_OVERRIDES: the JSON text of the --set values} ({} for None: a run made without the command line)."""
    import json
    return {} if overrides is None else {SET_OVERRIDES: json.dumps([str(item) for item in overrides])}


def stored_set_overrides(attrs) -> list[str] | None:
    """The --set values a run file's root attributes record (set_overrides_attribute), None if none."""
    import json
    text = attrs.get(SET_OVERRIDES)
    if text is None:
        return None
    try:
        values = json.loads(str(text))
    except ValueError:
        return None
    return [str(item) for item in values] if isinstance(values, list) else None


def problem_file_attributes(problem) -> dict:
    """{PROBLEM_FILE_DIGEST: the sha256 of a python: problem's file} ({} for other problems, or an
    unreadable file): the config names only the file's path, and --resume compares the two."""
    import hashlib

    source = getattr(problem, "source_file", None)
    try:
        return {PROBLEM_FILE_DIGEST: hashlib.sha256(Path(source).read_bytes()).hexdigest()} if source else {}
    except OSError:
        return {}


def problem_file_changed(stored_digest, problem) -> str | None:
    """What changed, when ``stored_digest`` (a stored PROBLEM_FILE_DIGEST) is not the digest of
    ``problem``'s python: file now ('the problem file F has changed since ...'), else None (the same
    file, no record, or not a python: problem). A sweep's or an ensemble's --resume refuses it: its
    stored runs and the new ones would come from two versions of the problem (a user trial: the table
    mixed them, exit 0); a run file's --resume records it and goes on (one run, two segments)."""
    if stored_digest is None:
        return None
    now = problem_file_attributes(problem).get(PROBLEM_FILE_DIGEST)
    stored = str(_plain(stored_digest))
    if now is None or now == stored:
        return None
    return (f"the problem file {problem.source_file} has changed since it was stored (sha256 {stored[:16]} then, "
            f"{now[:16]} now)")


def version_attributes() -> dict:
    import numba

    from .. import __version__
    return {"elimfast_version": __version__, "numba_version": numba.__version__,
            "numpy_version": np.__version__, "h5py_version": h5py.__version__,
            "hdf5_version": h5py.version.hdf5_version}

# (HDF5 2.0 segfaults), so its objects are kept here, never released; the file on disk is
# then as a killed writer leaves it, consistent and resumable.
_ABANDONED: list = []


def _write_method(group, method) -> None:
    if method.has_runge_kutta_form:
        A, b, c = method.butcher()
        for name, table in (("A", A), ("b", b), ("c", c)):
            _small_dataset(group, name, table)
        if method.kind.scales_tableau:
            tableau = (f"the underlying HBVM({method.k},{method.s}) tableau (eta = 1); each ELIM step scales it "
                       "with eta_j = 1 - h^(2(s-1-j)) alpha_j (docs/methods.md#elim)")
        else:
            tableau = f"{method.name}: A, b, c of its Runge-Kutta form"
    else:
        tableau = f"{method.name} has no fixed Runge-Kutta form (its correction acts through phi_0, docs/methods.md#lim)"
    _set_attributes(group, {"order": method.order, "tableau": tableau,
                            "quadrature": f"{method.k}-point Gauss-Legendre on [0, 1] for H"
                                          + (f", {method.r}-point for the invariants" if method.imposes_invariants
                                             else "")})
    _small_dataset(group, "quadrature_nodes", method.c)
    _small_dataset(group, "quadrature_weights", method.b)
    if method.imposes_invariants:
        _small_dataset(group, "invariant_quadrature_nodes", method.chat)
        _small_dataset(group, "invariant_quadrature_weights", method.bhat)


def _replace_attributes(obj, values: dict) -> None:
    for name in values:
        if name in obj.attrs:
            del obj.attrs[name]
    _set_attributes(obj, values)


def flag_attribute(value) -> np.int8:
    """A yes/no attribute (imposed, verify, terminal, stored) as written: int8 0 or 1. netCDF has
    no boolean type: xarray's to_netcdf refused HDF5 booleans and netCDF-C dropped them."""
    return np.int8(1 if value else 0)


def read_flag(attrs, name: str, default: bool = False) -> bool:
    """A yes/no attribute: int8 0/1 (flag_attribute), or an HDF5 boolean (files written before)."""
    return bool(_plain(attrs.get(name, default)))


def _set_attributes(obj, values: dict) -> None:
    """Create attributes through h5py's low-level API (numbers, strings, lists of strings, arrays;
    booleans as flag_attribute)."""
    for name, value in values.items():
        if isinstance(value, (bool, np.bool_)):
            value = flag_attribute(value)
        if isinstance(value, str) or (isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)):
            data = np.array(value, dtype=h5py.string_dtype())
        else:
            data = np.asarray(value)
        space = h5py.h5s.create(h5py.h5s.SCALAR) if data.ndim == 0 else h5py.h5s.create_simple(data.shape)
        attribute = h5py.h5a.create(obj.id, name.encode(), h5py.h5t.py_create(data.dtype, logical=True), space)
        attribute.write(data, mtype=h5py.h5t.py_create(data.dtype))


def _small_dataset(group, name: str, value, checksum: bool = True):
    """A dataset written at once (tables, /state, an ensemble's y0); returns its low-level id.
    Checksummed like the growing ones (fletcher32, which needs chunks: chunks of at most
    SMALL_CHUNK_BYTES); a scalar or an empty array is contiguous, as HDF5 requires. A user
    trial flipped a bit of /method/b (0.1167 read 1.868) and inspect said every checksum held.
    ``checksum=False``: contiguous (the named /state datasets, which mirror the CRC-checked
    /state/record: a checksum there would make a damaged mirror stop a resume that the record
    serves)."""
    data = np.array(value, order="C")   # (ascontiguousarray would make a scalar 1-d)
    space = h5py.h5s.create(h5py.h5s.SCALAR) if data.ndim == 0 else h5py.h5s.create_simple(data.shape)
    dcpl = None
    if checksum and data.ndim > 0 and data.size > 0:
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        row_bytes = data.itemsize * int(np.prod(data.shape[1:], dtype=np.int64))
        dcpl.set_chunk((max(1, min(data.shape[0], SMALL_CHUNK_BYTES // max(row_bytes, 1))),) + data.shape[1:])
        dcpl.set_fletcher32()
    dataset_id = h5py.h5d.create(group.id, name.encode(), h5py.h5t.py_create(data.dtype), space, dcpl=dcpl)
    dataset_id.write(h5py.h5s.ALL, h5py.h5s.ALL, data)
    return dataset_id


def _state_dataset(group, name: str, value):
    """A named /state dataset: contiguous, unchecksummed (_small_dataset's checksum=False)."""
    return _small_dataset(group, name, value, checksum=False)


SMALL_CHUNK_BYTES = 1 << 20   # _small_dataset's chunks (HDF5 allows up to 4 GB; an ensemble's y0 may be larger)


# --- dimension scales (netCDF-4 / xarray) ------------------------------------------------------
def _dataset(obj) -> h5py.Dataset:
    """A high-level dataset of a Dataset, a low-level DatasetID or a _Growing."""
    if isinstance(obj, h5py.Dataset):
        return obj
    return h5py.Dataset(obj if isinstance(obj, h5py.h5d.DatasetID) else obj.id)


def dimension(group, name: str, length: int | None = None) -> h5py.Dataset:
    """The dimension scale ``name`` of ``group``, created when missing as a netCDF dimension
    that is no variable: an empty dataset of ``length`` entries (None: unlimited, its length
    the longest of the datasets attached to it) that stores no data."""
    if name in group:
        return group[name]
    if length is None:
        dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
        dcpl.set_chunk((MIN_CHUNK_ROWS,))
        space = h5py.h5s.create_simple((0,), (h5py.h5s.UNLIMITED,))
    else:
        dcpl = None
        space = h5py.h5s.create_simple((int(length),))
    scale = h5py.Dataset(h5py.h5d.create(group.id, name.encode(), h5py.h5t.py_create(np.dtype("f4")), space,
                                         dcpl=dcpl))
    scale.make_scale(DIMENSION_ONLY % (0 if length is None else int(length)))
    return scale


def attach(dataset, *scales) -> None:
    """Put ``dataset`` on the given dimension scales, one per axis (None: leave that axis)."""
    dataset = _dataset(dataset)
    for axis, scale in enumerate(scales):
        if scale is not None:
            dataset.dims[axis].attach_scale(_dataset(scale))


def label(dataset, long_name: str | None = None, units: str | None = None) -> None:
    values = {}
    if long_name:
        values["long_name"] = long_name
    if units:
        values["units"] = units
    _set_attributes(_dataset(dataset), values)


def _string_dataset(group, name: str, values) -> h5py.Dataset:
    """A small dataset of UTF-8 strings (names), through h5py's high-level API (its string types)."""
    return group.create_dataset(name, data=np.array([str(v) for v in values], dtype=h5py.string_dtype()))


def unit_attributes(problem) -> dict:
    """``<quantity>_unit`` attributes of a problem that states its units (e.g. time_unit = 'day')."""
    return {f"{quantity}_unit": unit for quantity, unit in dict(getattr(problem, "units", {}) or {}).items()}


# --- the run group ------------------------------------------------------------------------------
def create_run_group(group, *, problem, method, conserve, n_multipliers: int, multiplier: str | None,
                     attributes: dict, adaptive_steps: bool = False, events=None, scales=None,
                     values_at_t0=None) -> dict:
    """Create the layout of a run in ``group`` (the module doc) with its attributes; return
    the growing datasets {"t", "y", "invariants": [H, ...], "iterations", "substeps",
    "multipliers"} (empty, to be extended by ``append_rows``). The one writer of a run
    group: the run file (``runfile.RunWriter``) and each run of a sweep file use it. scales:
    {name: the size of the invariant's terms at t0} (Problem.invariant_scales), stored as each
    invariant's attribute ``scale``, the reference of its relative error where I(t0) ~ 0.
    values_at_t0: {name: I(t0) of the initial state} (Problem.invariant_values), stored as
    ``value_at_t0``, the reference of the invariant errors (output times may start after t0).
    events: {name: {"expression", "direction", "terminal"}}, a group /events/<name> for each,
    with the definition as its attributes (so that the group says what it found)."""
    units = dict(getattr(problem, "units", {}) or {})
    _set_attributes(group, {**attributes, **unit_attributes(problem)})
    names = list(problem.coordinate_names)
    t = _growing(group, "t", None, "f8")
    t_dataset = h5py.Dataset(t.id)
    t_dataset.make_scale("t")
    label(t_dataset, LONG_NAMES["t"], units.get("time"))
    component = _string_dataset(group, "component", names)
    component.make_scale("component")
    label(component, LONG_NAMES["component"])
    y = _growing(group, "y", len(names), "f8")
    attach(y, t_dataset, component)
    label(y, LONG_NAMES["y"])
    invariant_names = ("H",) + tuple(problem.invariant_names)
    inv = group.create_group("invariants")
    _set_attributes(inv, {"order": list(invariant_names)})
    invariants = []
    for name in invariant_names:
        dataset = _growing(inv, name, None, "f8")
        attach(dataset, t_dataset)
        _set_attributes(h5py.Dataset(dataset.id), {"imposed": name in conserve,
                                                   "long_name": LONG_NAMES["H"] if name == "H" else
                                                   f"invariant {name}",
                                                   **({"scale": float(scales[name])}
                                                      if scales and name in scales else {}),
                                                   **({VALUE_AT_T0: float(values_at_t0[name])}
                                                      if values_at_t0 and name in values_at_t0 else {})})
        invariants.append(dataset)
    steps = group.create_group("steps")
    step = dimension(steps, "step")
    iterations = _growing(steps, "iterations", None, "i4")
    substeps = _growing(steps, "substeps", None, "i4")
    for dataset, name in ((iterations, "iterations"), (substeps, "substeps")):
        attach(dataset, step)
        label(dataset, LONG_NAMES[name])
    multipliers = None
    if multiplier is not None:
        imposed = tuple(method.multiplier_components(tuple(conserve)))
        column = _string_dataset(steps, "invariant", imposed)
        column.make_scale("invariant")
        label(column, LONG_NAMES["invariant"])
        multipliers = _growing(steps, multiplier, n_multipliers, "f8")
        attach(multipliers, step, column)
        _set_attributes(h5py.Dataset(multipliers.id), {"invariants": list(imposed),
                                                       "long_name": LONG_NAMES[multiplier]})
    datasets = {"t": t, "y": y, "invariants": invariants, "iterations": iterations, "substeps": substeps,
                "multipliers": multipliers}
    if adaptive_steps:   # docs/adaptive.md: the end time and size of every step
        for name in ("t", "h"):
            dataset = _growing(steps, name, None, "f8")
            attach(dataset, step)
            label(dataset, LONG_NAMES[f"step_{name}"], units.get("time"))
            datasets[f"step_{name}"] = dataset
    if events:
        events_group = group.create_group("events")
        _set_attributes(events_group, {"order": list(events)})
        datasets["events"] = []
        for name, definition in events.items():
            event = events_group.create_group(name)
            if definition:
                _set_attributes(event, {"expression": str(definition.get("expression", "")),
                                        "direction": int(definition.get("direction", 0)),
                                        "terminal": bool(definition.get("terminal", False))})
            occurrence = dimension(event, "occurrence")
            event_t = _growing(event, "t", None, "f8")
            event_y = _growing(event, "y", len(names), "f8")
            # its own copy of the component names: xarray.open_dataset(group="events/<name>") reads
            # one group's coordinates only, and without it y's columns were unlabelled
            event_component = _string_dataset(event, "component", names)
            event_component.make_scale("component")
            label(event_component, LONG_NAMES["component"])
            attach(event_t, occurrence)
            attach(event_y, occurrence, event_component)
            label(event_t, f"time of event {name}", units.get("time"))
            label(event_y, f"state at event {name}")
            datasets["events"].append((event_t, event_y))
    write_method(group.create_group("method"), method)
    return datasets


def append_rows(datasets: dict, *, t, y, invariants, iterations, substeps, multipliers, step_t=None, step_h=None,
                event_index=None, event_t=None, event_y=None) -> None:
    """Extend a run group's datasets: samples (t, y, invariants as columns H, ...), steps
    (and for adaptive runs their end times and sizes), and events found (event_index says
    which of the group's events each row is)."""
    if datasets.get("step_t") is not None and step_t is not None:
        datasets["step_t"].append(step_t)
        datasets["step_h"].append(step_h)
    if datasets.get("events") and event_index is not None:
        for which, (dataset_t, dataset_y) in enumerate(datasets["events"]):
            rows = event_index == which
            if np.any(rows):
                dataset_t.append(event_t[rows])
                dataset_y.append(event_y[rows])
    datasets["t"].append(t)
    datasets["y"].append(y)
    for column, dataset in enumerate(datasets["invariants"]):
        dataset.append(invariants[:, column])
    datasets["iterations"].append(iterations)
    if datasets.get("substeps") is not None:
        datasets["substeps"].append(substeps)
    if datasets.get("multipliers") is not None:
        datasets["multipliers"].append(multipliers)


def write_method(group, method) -> None:
    """The method's tables (``_write_method``) on their dimensions: stage and node (k), invariant_node (r)."""
    _write_method(group, method)
    for name, axes in (("A", ("stage", "node")), ("b", ("node",)), ("c", ("stage",)),
                       ("quadrature_nodes", ("node",)), ("quadrature_weights", ("node",)),
                       ("invariant_quadrature_nodes", ("invariant_node",)),
                       ("invariant_quadrature_weights", ("invariant_node",))):
        if name in group:
            dataset = group[name]
            attach(dataset, *(dimension(group, axis, length) for axis, length in zip(axes, dataset.shape)))


def component_names(group) -> list[str]:
    """The state's component names: /component (format 3), else the attribute of /y (format 1, 2)."""
    if "component" in group:
        return [str(name) for name in _plain(group["component"][()])]
    return [str(name) for name in _plain(group["y"].attrs.get("coordinates", []))]


INITIAL_GIVEN = "problem.initial"   # attribute initial_state: the state given, not the problem's default
INITIAL_DEFAULT = "default"


STEP_CONTROL_FIXED = "fixed"   # the attribute step_control of a fixed-step run (adaptive: error, time_scale)


def run_attributes(problem, method, *, h: float, t0: float, n_steps: int, t_end: float | None,
                   output_every: int, conserve) -> dict:
    """The attributes that describe a run, alike in a run file and in each run of a sweep file.
    ``initial_state``: where y0 came from, 'problem.initial' when it replaced the problem's
    default state (Problem.initial_given: the parameters that chose the default then do not
    describe the orbit), else 'default' (files written before it: absent). ``step_control``:
    'fixed' here; a run through the adaptive kernel overrides it with its own
    (AdaptiveIntegration.file_attributes: error, time_scale, or fixed with output times or
    events). Plain fixed-step files written before it was always written have none: readers
    take its absence as 'fixed' (a user trial's script read attrs["step_control"], KeyError)."""
    return {"problem": problem.name, "step_control": STEP_CONTROL_FIXED,
            "initial_state": INITIAL_GIVEN if getattr(problem, "initial_given", False) else INITIAL_DEFAULT,
            "method": method.name, "family": method.family, "r": method.r, "k": method.k,
            "s": method.s, "h": float(h), "t0": float(t0),
            "t_end": float(t_end) if t_end is not None else float(t0) + n_steps * float(h),
            # 0: not known in advance (adaptive steps, docs/adaptive.md)
            "n_steps": int(n_steps) if n_steps is not None else 0, "output_every": int(output_every),
            "conserve": list(conserve),
            # -1: H is not a polynomial, or its degree is not known (Problem.hamiltonian_degree)
            "hamiltonian_degree": -1 if getattr(problem, "hamiltonian_degree", None) is None
            else int(problem.hamiltonian_degree)}


# A sweep file: its root's format, and the group of its runs, each a run group (run files have theirs at the root).
SWEEP_FORMAT = "elimfast-sweep"
RUNS_GROUP = "runs"


def split_run_path(path, run: str | None = None) -> tuple[Path, str | None]:
    """(file, run label) of ``file.h5`` or ``file.h5:/runs/<label>`` (a run of a sweep file;
    ``file.h5:runs/<label>``, as h5py writes group paths relative to the root, too). A run given
    as a number (run=0.1, a sweep over h) is its text."""
    text = os.fspath(path)
    if run is not None and not isinstance(run, str):
        run = str(run)
    if run is None and not os.path.exists(text):
        for marker in (f":/{RUNS_GROUP}/", f":{RUNS_GROUP}/"):
            at = text.find(marker)
            while at > 0:
                if os.path.isfile(text[:at]):
                    return Path(text[:at]), text[at + len(marker):]
                at = text.find(marker, at + 1)
        at = text.find(":")
        while at > 0:   # FILE:/something else: the file exists, the part after it names no run
            if os.path.isfile(text[:at]):
                raise OutputError(f"{text}: {text[:at]} exists, but {text[at + 1:]!r} is no run of it; one run "
                                  f"of a sweep file is {text[:at]}:/{RUNS_GROUP}/<label>, a run or ensemble file "
                                  "is given alone")
            at = text.find(":", at + 1)
    return Path(text), run

# The attribute of /events/<name> with the first sample time where the event was NaN or infinite
# (a user trial: the run said so, the file did not; RunWriter.finish, RunFile.events_not_finite).
NOT_FINITE_FROM = "not_finite_from"
