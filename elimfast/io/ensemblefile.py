"""The ensemble of an ensemble sweep file: /ensemble, written block by block, and its reader.

An ensemble sweep file has the root of a sweep file (``sweepfile.py``: format
``elimfast-sweep``, the sweep's text, an empty /runs) and the group /ensemble:

    component                 (2m,) strings  the state's component names; a dimension scale
    diagnostic                (6,) strings   the diagnostics' names (t, h, increment, condition, depth,
                                             iterations: kernels/stepper.py); a dimension scale
    trajectory                a netCDF dimension that is no variable (n)
    y0                        (n, 2m)        the initial states
    y_final                   (n, 2m)        the state after the last completed step
    t_final, max_multiplier   (n,)           end time; max |alpha| (ELIM) or |lambda| (LIM)
    iterations, status, steps_done, split_steps, unimposed_steps   (n,) int64   (status 0: complete)
    diagnostics               (n, 6)         of a failed step (kernels/stepper.py try_step)
    invariant_errors/<name>   (n,)           max |I(t) - I(0)|: H, then every invariant (NaN: no step done)
    stored                    (n,) uint8     the done record: 1 where the trajectory's row is written
                                             (status is -1, not_stored, until it is)
    method/...                the method's tables (layout.write_method)

Attributes of /ensemble: problem, method, h, n_steps, conserve, config (the resolved
YAML) and status: 'running' until every trajectory is stored, then 'complete', with
threads and failed (how many trajectories failed) written then (each trajectory's status
as a word: status's flag_meanings); ``<quantity>_unit`` where the problem states its units. Every dataset
has a ``long_name`` (ROW_LONG_NAMES), t_final its ``units``, and status CF's ``flag_values``
and ``flag_meanings`` (the words of its codes).

Every dataset is created with its final shape and its storage allocated at once
(contiguous; floats filled with NaN until written), so writing a block changes no
metadata: the writer writes the block's rows, flushes, sets their ``stored`` entries,
flushes. The file is written in HDF5's SWMR mode, so a killed writer leaves it
consistent, with every block marked stored readable, and ``elimfast sweep ... --resume``
runs only the trajectories not marked. Files written before the done record (the
ensemble whole, at the end) lack ``stored``, ``split_steps`` and ``diagnostics``; they
are read as complete. Files written before ``unimposed_steps`` was counted read it as -1 (not
recorded), and a resume of one leaves it so.
"""
from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from .layout import (LONG_NAMES, PROBLEM_FILE_DIGEST, _replace_attributes, _set_attributes, _small_dataset,
                     _string_dataset, attach, dimension, label, problem_file_attributes, problem_file_changed,
                     unit_attributes, write_method)
from .safety import OutputError, _damaged, _open, _plain, _writer_lock_held

GROUP = "ensemble"
STORED = "stored"
STATUS_RUNNING, STATUS_COMPLETE = "running", "complete"
# The status of a trajectory whose row is not written yet: the fill value of /ensemble/status (a user
# trial: a killed ensemble read with open_datatree showed its unwritten rows as status 0, 'ok').
NOT_STORED, NOT_STORED_WORD = -1, "not_stored"
# The per-trajectory dataset that files written by an earlier elimfast lack (read as -1, not recorded).
NOT_ALWAYS_STORED = "unimposed_steps"
READ_BLOCK_ROWS = 1 << 16     # rows per read where a reader scans a whole column (bounded memory)
# The labels of the diagnostic dimension, in the order of kernels/stepper.py's DIAG_* indices
# (not imported: the file layer loads no kernels; tests/test_ensemble_stream.py checks the order).
DIAGNOSTIC_NAMES = ("t", "h", "increment", "condition", "depth", "iterations")
# What xarray and h5py show of each per-trajectory dataset (run files label theirs in layout.py).
ROW_LONG_NAMES = {"y0": "initial state y = (q, p)", "y_final": "state after the last completed step",
                  "t_final": "time after the last completed step",
                  "iterations": "solver iterations summed over the steps (a failed step's included)",
                  "max_multiplier": "max |alpha| (ELIM) or |lambda| (LIM) over the steps",
                  "status": "0: complete; -1: not yet written to the file; otherwise why the trajectory stopped "
                            "(flag_meanings; EnsembleResult.failure_message(i) explains it)",
                  "steps_done": "steps completed", "split_steps": "steps split into substeps",
                  "unimposed_steps": "steps taken, or with a substep taken, without imposing the invariants "
                                     "(imposing failed there; -1: not recorded)",
                  "diagnostics": "the failed step's diagnostics (0 where the trajectory completed)"}


def _allocated(group, name: str, shape: tuple, dtype, fill=None) -> h5py.Dataset:
    """A contiguous dataset of its final shape with its storage allocated now (``fill``, by default
    NaN for floats and 0 otherwise): writing into it later writes data only, never metadata."""
    dtype = np.dtype(dtype)
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_alloc_time(h5py.h5d.ALLOC_TIME_EARLY)
    if fill is None and dtype.kind == "f":
        fill = np.nan
    if fill is not None:
        dcpl.set_fill_value(np.array(fill, dtype=dtype))
    space = h5py.h5s.create_simple(tuple(int(length) for length in shape))
    return h5py.Dataset(h5py.h5d.create(group.id, name.encode(), h5py.h5t.py_create(dtype), space, dcpl=dcpl))


def status_flags(status_names: dict, dtype) -> dict:
    """CF's flag_values and flag_meanings of /ensemble/status (and of EnsembleResult.to_xarray's):
    the words of the codes, one word each, and of the fill of rows not yet written."""
    names = {NOT_STORED: NOT_STORED_WORD, **status_names}
    codes = sorted(names)
    return {"flag_values": np.array(codes, dtype=dtype),
            "flag_meanings": " ".join(names[code].replace(" ", "_") for code in codes)}


def bytes_on_disk(run, states: np.ndarray) -> int:
    """The bytes of /ensemble's per-trajectory datasets, all allocated when the file is
    created."""
    n, width = states.shape
    row = sum(dtype.itemsize * int(np.prod(shape)) for shape, dtype in run.row_layout().values())
    return n * (8 * (width + len(run.invariant_names)) + row + 1)


def create(parent, run, states: np.ndarray, config_text: str) -> h5py.Group:
    """Create /ensemble in ``parent`` for ``run`` (an elimfast.ensemble.EnsembleRun: problem,
    method, h, n_steps, conserve, invariant_names, and row_layout, the per-trajectory arrays
    of its results) from ``states`` (n, 2m): every dataset at its final shape, y0 written,
    nothing stored yet."""
    group = parent.create_group(GROUP)
    _set_attributes(group, {
        "problem": run.problem.name, "method": run.method.name, "h": run.h, "n_steps": run.n_steps,
        "conserve": list(run.conserve), "config": config_text, "status": STATUS_RUNNING})
    _set_attributes(group, unit_attributes(run.problem))
    _set_attributes(group, problem_file_attributes(run.problem))   # python: problems: --resume compares it
    time_unit = dict(getattr(run.problem, "units", {}) or {}).get("time")
    n = states.shape[0]
    component = _string_dataset(group, "component", run.problem.coordinate_names)
    component.make_scale("component")
    label(component, LONG_NAMES["component"])
    trajectory = dimension(group, "trajectory", n)
    y0 = _small_dataset(group, "y0", states)
    attach(y0, trajectory, component)
    label(y0, ROW_LONG_NAMES["y0"])
    for name, (shape, dtype) in run.row_layout().items():
        dataset = _allocated(group, name, (n,) + shape, dtype, NOT_STORED if name == "status" else None)
        if not shape:
            attach(dataset, trajectory)
        elif name == "y_final":
            attach(dataset, trajectory, component)
        elif name == "diagnostics":   # one per diagnostic, labelled as the component dimension is
            diagnostic = _string_dataset(group, "diagnostic", DIAGNOSTIC_NAMES[:shape[0]])
            diagnostic.make_scale("diagnostic")
            label(diagnostic, "diagnostic of the failed step (kernels/stepper.py try_step)")
            attach(dataset, trajectory, diagnostic)
        else:   # a row of its own kind of entries
            attach(dataset, trajectory, dimension(group, name.removesuffix("s"), shape[0]))
        label(dataset, ROW_LONG_NAMES.get(name), time_unit if name == "t_final" else None)
        if name == "status":
            _set_attributes(dataset, status_flags(run.status_names, dtype))
    errors = group.create_group("invariant_errors")
    _set_attributes(errors, {"order": list(run.invariant_names)})   # HDF5 lists members by name
    for name in run.invariant_names:
        dataset = _allocated(errors, name, (n,), "f8")
        attach(dataset, trajectory)
        label(dataset, f"max |{name}(t) - {name}(t0)| over the steps")
    stored = _allocated(group, STORED, (n,), "u1")
    attach(stored, trajectory)
    _set_attributes(stored, {"long_name": "1 where the trajectory's results are written (the rest are not yet)"})
    write_method(group.create_group("method"), run.method)
    return group


def write_rows(group, start: int, stop: int, rows: dict) -> None:
    """Write the rows [start, stop) of every per-trajectory dataset (not yet marked stored):
    ``rows`` maps each dataset's name to its rows, invariant_errors to {name: rows}."""
    for name, values in rows.items():
        if name == "invariant_errors":
            for invariant, errors in values.items():
                group["invariant_errors"][invariant][start:stop] = errors
        elif name in group or name != NOT_ALWAYS_STORED:
            group[name][start:stop] = values


def mark_stored(group, start: int, stop: int) -> None:
    group[STORED][start:stop] = 1


def unstored_ranges(group) -> list[tuple[int, int]]:
    """[start, stop) of each run of consecutive trajectories not marked stored, in order."""
    stored = group[STORED]
    ranges, open_start, previous = [], None, False   # previous: whether the row before is unstored
    for first in range(0, stored.shape[0], READ_BLOCK_ROWS):
        unstored = stored[first:first + READ_BLOCK_ROWS] == 0
        padded = np.concatenate(([previous], unstored))
        for edge in np.flatnonzero(padded[1:] != padded[:-1]) + first:   # each edge opens or closes a range
            if open_start is None:
                open_start = int(edge)
            else:
                ranges.append((open_start, int(edge)))
                open_start = None
        previous = bool(unstored[-1])
    if open_start is not None:
        ranges.append((open_start, stored.shape[0]))
    return ranges


def stored_count(group) -> int:
    stored = group[STORED]
    return sum(int(np.count_nonzero(stored[first:first + READ_BLOCK_ROWS]))
               for first in range(0, stored.shape[0], READ_BLOCK_ROWS))


def finish(group, *, threads: int, ok_status: int) -> None:
    """Mark /ensemble complete (every trajectory stored): threads, failed, status.

    Each trajectory's status as a word is the status dataset's flag_meanings (status_flags), not
    an attribute: the ``reasons`` attribute that listed it, one string per trajectory, was read
    whole by every opening of the group (60 MB of Python strings per million trajectories;
    10^8 would have taken gigabytes at finish and at every read)."""
    failed = 0
    for first in range(0, group["status"].shape[0], READ_BLOCK_ROWS):
        failed += int(np.count_nonzero(group["status"][first:first + READ_BLOCK_ROWS] != ok_status))
    values = {"threads": int(threads), "failed": failed, "status": STATUS_COMPLETE}
    _replace_attributes(group, values)


def check_resumable(path: Path, group, run, states: np.ndarray, config_text: str) -> None:
    """OutputError unless /ensemble holds the ensemble about to be run: the same resolved
    config, the same initial states (compared bit for bit, in blocks), a record of stored rows."""
    if STORED not in group:
        raise OutputError(f"{path}: its ensemble was written by an elimfast without the record of stored "
                          "trajectories, so --resume cannot tell what is done; pass --overwrite to run it again")
    if str(_plain(group.attrs.get("config", ""))) != config_text:
        raise OutputError(f"{path}: its ensemble was run with another config (the base config changed since); "
                          "pass --overwrite to start again, or choose another output file")
    changed = problem_file_changed(group.attrs.get(PROBLEM_FILE_DIGEST), run.problem)
    if changed:
        raise OutputError(f"{path}: {changed}: its stored trajectories and the others would come from two versions "
                          "of the problem; undo the change, or pass --overwrite to run every trajectory with the new "
                          "file, or choose another output file")
    y0 = group["y0"]
    if y0.shape != states.shape:
        raise OutputError(f"{path}: holds an ensemble of {y0.shape[0]:,} trajectories, this sweep has "
                          f"{states.shape[0]:,}; pass --overwrite to start again, or choose another output file")
    for first in range(0, states.shape[0], READ_BLOCK_ROWS):
        if not np.array_equal(y0[first:first + READ_BLOCK_ROWS], states[first:first + READ_BLOCK_ROWS]):
            raise OutputError(f"{path}: its ensemble's initial states differ from those drawn now (another numpy "
                              "or seed?); pass --overwrite to start again, or choose another output file")


# --- the reader -----------------------------------------------------------------------------------
def is_ensemble_file(path) -> bool:
    """Whether ``path`` is an HDF5 file holding an ensemble sweep's /ensemble (False for anything else)."""
    try:
        with _open(Path(path)) as f:
            return GROUP in f and str(_plain(f.attrs.get("format", ""))) == "elimfast-sweep"
    except Exception:   # noqa: BLE001 -- not ours, damaged, busy: the caller's own reader says what
        return False


def read_status(path, written) -> str:
    """What /ensemble's status attribute ``written`` means to a reader: 'complete', 'running' (its
    writer holds the file) or 'incomplete' (stopped or killed before every block was written: the
    attribute still says 'running')."""
    if str(written) == STATUS_COMPLETE:
        return STATUS_COMPLETE
    return STATUS_RUNNING if _writer_lock_held(Path(path)) else "incomplete"


class EnsembleFile:
    """An ensemble sweep file opened for reading (a killed writer's file in SWMR mode).

    ``attrs`` (of /ensemble, plain values), ``root_attrs``, ``n_trajectories``,
    ``stored`` (how many are written), ``status``: 'complete', 'running' (its writer
    holds the file) or 'incomplete' (stopped or killed before every block was written).
    ``column(name, start, stop)`` reads a dataset's rows (name: a dataset of /ensemble or
    ``invariant_errors/<name>``); ``stored_mask`` the done record as booleans.
    """

    def __init__(self, path):
        self.path = Path(path)
        self._file = _open(self.path)
        try:
            if GROUP not in self._file:
                raise OutputError(f"{self.path}: holds no ensemble (/{GROUP}); give the file of an ensemble sweep")
            self._group = self._file[GROUP]
            self.root_attrs = {key: _plain(value) for key, value in self._file.attrs.items()}
            self.attrs = {key: _plain(value) for key, value in self._group.attrs.items()}
            self.n_trajectories = int(self._group["y0"].shape[0])
            errors = self._group["invariant_errors"]
            order = _plain(errors.attrs.get("order", ["H"] + sorted(name for name in errors if name != "H")))
            self.invariant_names = [str(name) for name in order]
            legacy = STORED not in self._group   # written whole at the end (before the done record)
            self.stored = self.n_trajectories if legacy else stored_count(self._group)
            self.status = read_status(self.path, self.attrs.get("status", STATUS_COMPLETE if legacy else STATUS_RUNNING))
        except OutputError:
            self.close()
            raise
        except (KeyError, OSError, RuntimeError, ValueError) as err:
            self.close()
            raise _damaged(self.path, f"/{GROUP}", err) from None

    @property
    def swmr(self) -> bool:
        """Opened in SWMR mode: its writer is running or did not close it."""
        return bool(self._file.swmr_mode)

    def has(self, name: str) -> bool:
        return name in self._group

    def column(self, name: str, start: int = 0, stop: int | None = None) -> np.ndarray:
        if name == NOT_ALWAYS_STORED and name not in self._group:   # written before it was counted
            stop = self.n_trajectories if stop is None else stop
            return np.full(stop - start, -1, dtype=np.int64)
        try:
            return np.asarray(self._group[name][start:stop])
        except (KeyError, OSError, RuntimeError, ValueError) as err:
            raise _damaged(self.path, f"/{GROUP}/{name}", err) from None

    def stored_mask(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        if STORED not in self._group:
            stop = self.n_trajectories if stop is None else stop
            return np.ones(stop - start, dtype=bool)
        return self.column(STORED, start, stop) != 0

    def blocks(self):
        """[start, stop) pairs covering every trajectory, READ_BLOCK_ROWS at a time."""
        return [(first, min(first + READ_BLOCK_ROWS, self.n_trajectories))
                for first in range(0, self.n_trajectories, READ_BLOCK_ROWS)]

    def close(self) -> None:
        if self._file.id.valid:
            self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


__all__ = ["EnsembleFile", "bytes_on_disk", "check_resumable", "create", "finish", "is_ensemble_file",
           "mark_stored", "stored_count", "unstored_ranges", "write_rows"]
