"""The run file: its writer (streaming, crash-safe, resumable) and its reader.

Layout (format ``elimfast-run``): the run group of ``layout.py`` at the root, plus

    /state/...              what resume needs, rewritten after every flushed chunk:
                            y, y_comp (Kahan compensation), clock = [t, its compensation],
                            coef (s, 2m) last step's coefficients, coef_extra (e, 2m) its
                            Legendre terms gamma_s.. for the predictor (absent in files written
                            before the predictor kept them), multipliers, last_h,
                            newton_base, steps_done, n_samples, wall_time_s, kernel_time_s
    /state/record           (2, L) float64: the same state as one row, written alternately
                            into row 0 and row 1 (see "Saved state" below)

Root attributes: elimfast_version, numba_version, numpy_version, h5py_version,
hdf5_version, created (UTC, ISO 8601), config (the resolved YAML), problem, initial_state
('problem.initial' when the state replaced the problem's default, else 'default'), method,
family, r, k, s, h, t0, t_end, n_steps, output_every, conserve, steps_done, status
(running | complete | interrupted | killed | stopped: <reason> | failed: <reason>),
wall_time_s, kernel_time_s, format = 'elimfast-run', format_version, and
``<quantity>_unit`` where the problem states its units. 'stopped' (the disk filled up, a
problem function raised) can be resumed; 'failed' (the numerics failed) only with other
solver settings; 'killed' is what ``repair`` writes into the file of a killed writer.

The file is written in SWMR mode (``safety.py``): root attributes cannot change then, so
they are final only once the run ends (the writer then reopens the file normally);
while a run is going, or after a kill, ``status`` still says ``running`` and /state holds
the truth. Data rows beyond the saved state may exist after a kill; they belong to the
chunk being written; resume and ``repair`` drop them.

Saved state. The named /state datasets are written one by one, so a kill between two
of those writes would leave them mixed (y of one chunk, steps_done of the one before).
The record is written in one piece, alternately into its two rows, each row with a
sequence number and a CRC-32 of its values (and HDF5's fletcher32 on each row): the
valid row with the higher sequence number is the state, and if a kill or a damaged
sector spoils one row, the other still holds the state of the chunk before.

Damage. A resume first reads all it builds on and refuses a damaged file, leaving it
as it was; every read error names the file and the place (``DamagedFileError``).

The reader also opens one run of a sweep file (``RunFile("sweep.h5:/runs/<label>")``),
whose group has the same layout without /state.
"""
from __future__ import annotations

import contextlib
import datetime
import itertools
import math
import os
import socket
import zlib
from pathlib import Path

import h5py
import numpy as np

from ..errors import DiskFullError, ElimfastError
from .layout import (FORMAT, FORMAT_VERSION, LIBVER, NOT_FINITE_FROM, SPACE_BASE, SPACE_FACTOR, SPACE_MARGIN,
                     STATS_PREFIX, STATUS_RUNNING, VALUE_AT_T0, read_flag, stats_attributes, VERIFY_BLOCK_BYTES,
                     _Growing, _plain,
                     _replace_attributes, _set_attributes, _state_dataset, append_rows, attach, component_names,
                     create_run_group, dimension, multiplier_datasets, multiplier_name, PER_STEP_RECORDS,
                     RUNS_GROUP, run_attributes, split_run_path, SWEEP_FORMAT,
                     PROBLEM_FILE_DIGEST, problem_file_attributes, SET_OVERRIDES, set_overrides_attribute,
                     version_attributes)
from .safety import (_DAMAGE_ADVICE, READ_ERRORS, DamagedFileError, FileBusyError, NotAnElimfastFile, OutputError,
                     _abandon, _close_quietly, _damaged, _FileGuard, _free_bytes, _hdf5_reason,
                     _one_line, _open, _process_alive, _publish, _regular_file, _size, _temporary_path,
                     _writer_lock_held, clear_consistency_flags, consistency_flags, create_parent_directories,
                     damaged_row_ranges, ensure_not_busy, extended_to_recorded_end, no_room, open_unflagged,
                     refuse_netcdf_copy, reopen_for_writing, rows_text, set_consistency_flags)



def _now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def samples_on_grid(steps_done: int, output_every: int) -> int:
    """Samples a run holds after steps_done steps when it stopped between samples: t0 and
    every multiple of output_every (a failed run adds one of its last good state)."""
    return 1 + int(steps_done) // max(int(output_every), 1)


def _state_dimensions(f, state, record) -> None:
    """Dimension scales of /state (so that xarray.open_datatree reads the whole file)."""
    component = f["component"]
    datasets = {name: h5py.Dataset(state[name].id) for name in state}
    attach(datasets["y"], component)
    attach(datasets["y_comp"], component)
    attach(datasets["coef"], dimension(state, "coefficient", datasets["coef"].shape[0]), component)
    if "coef_extra" in datasets:
        attach(datasets["coef_extra"], dimension(state, "extra_coefficient", datasets["coef_extra"].shape[0]),
               component)
    for name, axis in (("clock", "clock_term"), ("multipliers", "multiplier"), ("last_h", "last_h_entry"),
                       ("newton_base", "newton_base_entry"), ("control_state", "control_entry"),
                       ("counters", "counter"), ("event_counts", "event")):
        if name in datasets:
            attach(datasets[name], dimension(state, axis, datasets[name].shape[0]))
    record = h5py.Dataset(record)
    attach(record, dimension(state, "record_slot", record.shape[0]), dimension(state, "record_field", record.shape[1]))


def _sweep_run_group(path: Path, f, label: str):
    """The group of the sweep run ``label`` (its label or its group name), or an OutputError listing the runs."""
    from .sweepfile import sweep_group_name
    try:
        fmt = _plain(f.attrs.get("format", ""))
        runs = f[RUNS_GROUP] if RUNS_GROUP in f else None
    except (OSError, RuntimeError, KeyError, ValueError) as err:
        raise _damaged(path, "its root", err) from None
    if fmt != SWEEP_FORMAT or runs is None:
        raise NotAnElimfastFile(f"{path}: not an elimfast sweep file, so it has no run {label!r}; give the file "
                                "alone for a run file")
    # its group name first: '.' itself names the runs group (the label '.' is stored as '_.')
    for name in (sweep_group_name(label), label):
        if name not in (".", "..") and name in runs:
            group = runs[name]
            missing = [member for member in ("t", "y", "invariants", "steps/iterations") if member not in group]
            if missing:
                status = _plain(group.attrs.get("status", "?"))
                raise OutputError(f"{path}:/{RUNS_GROUP}/{name}: the run stored no data ({status})")
            return group
    labels = [str(_plain(runs[name].attrs.get("label", name))) for name in runs]
    shown = ", ".join(labels[:8]) + (", ..." if len(labels) > 8 else "")
    raise OutputError(f"{path}: has no run {label!r}; its runs: {shown or 'none'}")


def _saved_record(state: dict, n_samples: int) -> dict:
    """A writer's record of its last saved state (create, resume, save_state): where finish
    cuts a run stopped short back to, its events too."""
    return {"steps_done": int(state["steps_done"]), "n_samples": int(n_samples),
            "t": float(np.asarray(state["clock"])[0]), "counters": state.get("counters"),
            "event_counts": np.array(state.get("event_counts", ()), np.int64)}


def _cut_back(f, n_samples: int, steps_done: int, event_counts=()) -> None:
    """Drop the rows written after the saved state: samples, steps, and events found."""
    for d in _sample_datasets(f):
        if d.shape[0] > n_samples:
            d.resize(n_samples, axis=0)
    for d in _step_datasets(f):
        if d.shape[0] > steps_done:
            d.resize(steps_done, axis=0)
    for name, count in zip(_event_names(f), event_counts):
        for member in ("t", "y"):
            if f["events"][name][member].shape[0] > int(count):
                f["events"][name][member].resize(int(count), axis=0)


def _merged(ranges: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Row ranges of damage found block by block, adjacent ones (across a block's end) joined."""
    merged: list[tuple[int, int]] = []
    for first, last in ranges:
        if merged and merged[-1][1] >= first - 1:
            merged[-1] = (merged[-1][0], max(last, merged[-1][1]))
        else:
            merged.append((first, last))
    return merged


_RECORD_HEADER = ("sequence", "steps_done", "n_samples", "wall_time_s", "kernel_time_s")


# Adaptive runs (docs/adaptive.md) add to the record, in this order: the controller's state,
# the counters, whether the run is finished, and how many of each event were found.
_ADAPTIVE_STATE = ("control_state", "counters", "finished", "event_counts")


def _record_length(n: int, s: int, n_mult: int, extras: int = 0) -> int:
    return len(_RECORD_HEADER) + 2 + 2 * n + s * n + n_mult + 1 + (n + 3) + extras + 1


def _record_tail(state: dict) -> list[np.ndarray]:
    """The record's tail after newton_base: the adaptive state, then coef_extra (the predictor's
    extra terms, last: a file written before them has a record without it, and keeps it so)."""
    tail = []
    if "control_state" in state:
        tail = [np.asarray(state[key], dtype=np.float64).ravel() for key in _ADAPTIVE_STATE]
    if "coef_extra" in state:
        tail.append(np.asarray(state["coef_extra"], dtype=np.float64).ravel())
    return tail


def _pack_record(state: dict, sequence: int, n_samples: int, wall_time_s: float, kernel_time_s: float) -> np.ndarray:
    body = np.concatenate([
        np.array([sequence, state["steps_done"], n_samples, wall_time_s, kernel_time_s], dtype=np.float64),
        np.asarray(state["clock"], dtype=np.float64).ravel(), np.asarray(state["y"], dtype=np.float64).ravel(),
        np.asarray(state["y_comp"], dtype=np.float64).ravel(), np.asarray(state["coef"], dtype=np.float64).ravel(),
        np.asarray(state["multipliers"], dtype=np.float64).ravel(), np.asarray(state["last_h"], dtype=np.float64).ravel(),
        np.asarray(state["newton_base"], dtype=np.float64).ravel(), *_record_tail(state)])
    return np.append(body, float(zlib.crc32(body.astype("<f8").tobytes())))


def _unpack_record(row: np.ndarray, n: int, s: int, n_mult: int, adaptive=None,
                   n_extra: int | None = None) -> dict | None:
    """The state in a record row, or None if its CRC does not match (a torn or damaged row).
    adaptive: (n_control_state, n_counters, n_events) for an adaptive run, else None;
    n_extra: the rows of coef_extra, None for a file written before it was kept."""
    extras = 0 if adaptive is None else adaptive[0] + adaptive[1] + 1 + adaptive[2]
    extras += 0 if n_extra is None else n_extra * n
    if row.shape != (_record_length(n, s, n_mult, extras),) or not np.all(np.isfinite(row[:5])):
        return None
    if float(zlib.crc32(row[:-1].astype("<f8").tobytes())) != row[-1]:
        return None
    header = dict(zip(_RECORD_HEADER, row[:5].tolist()))
    at = len(_RECORD_HEADER)
    parts = {}
    for key, size, shape in (("clock", 2, (2,)), ("y", n, (n,)), ("y_comp", n, (n,)), ("coef", s * n, (s, n)),
                             ("multipliers", n_mult, (n_mult,)), ("last_h", 1, (1,)), ("newton_base", n + 3, (n + 3,))):
        parts[key] = row[at:at + size].reshape(shape).copy()
        at += size
    if adaptive is not None:
        for key, size, dtype in (("control_state", adaptive[0], np.float64), ("counters", adaptive[1], np.int64),
                                 ("finished", 1, np.int64), ("event_counts", adaptive[2], np.int64)):
            parts[key] = row[at:at + size].astype(dtype)
            at += size
        parts["finished"] = int(parts["finished"][0])
    if n_extra is not None:
        parts["coef_extra"] = row[at:at + n_extra * n].reshape((n_extra, n)).copy()
        at += n_extra * n
    return {**parts, "steps_done": int(header["steps_done"]), "n_samples": int(header["n_samples"]),
            "wall_time_s": header["wall_time_s"], "kernel_time_s": header["kernel_time_s"],
            "sequence": int(header["sequence"])}


def _record_dataset(group, length: int):
    """/state/record: (2, length), one HDF5 chunk per row, fletcher32."""
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk((1, length))
    dcpl.set_fletcher32()
    space = h5py.h5s.create_simple((2, length))
    return h5py.h5d.create(group.id, b"record", h5py.h5t.py_create(np.dtype("<f8")), space, dcpl=dcpl)


def _write_record_row(dataset_id, slot: int, row: np.ndarray) -> None:
    file_space = dataset_id.get_space()
    file_space.select_hyperslab((slot, 0), (1, row.size))
    dataset_id.write(h5py.h5s.create_simple((1, row.size)), file_space, np.ascontiguousarray(row[None, :]))


class RunWriter:
    """Appends the chunks of one run to its file and keeps /state current.

    ``create`` starts a new file, ``resume`` reopens one and returns the saved state.
    Before a chunk, ``fit_steps`` reserves its disk space. After each ``append`` call
    ``save_state``: the data are flushed first and the state second, so a state on disk
    never refers to data that did not reach it. ``finish`` writes the final root
    attributes and closes the file. If HDF5 fails while writing (``WriteFailed``), the
    writer is abandoned: the file stays as a killed writer would leave it.
    """

    def __init__(self, path: Path, file: h5py.File, datasets: dict, guard: _FileGuard | None = None,
                 sequence: int = 1):
        self.path = path
        self._file = file
        # Handles kept: h5py's name lookups cost more than a chunk's writes.
        self._datasets = datasets
        self._t, self._y = datasets["t"], datasets["y"]
        self._invariants = datasets["invariants"]    # in the column order of Chunk.invariants
        self._iterations = datasets["iterations"]
        self._substeps = datasets.get("substeps")    # absent in files written before the step engine
        self._multipliers = datasets.get("multipliers")
        self._state = datasets["state"]
        self._record = datasets.get("record")
        self._sequence = sequence
        self._guard = guard
        self.failed_step_iterations = None
        self.abandoned = False
        self.no_room = None          # why fit_steps found no room (safety.NoRoom)
        self.opened_as = path        # the name HDF5 knows the file by (a new file's temporary name)
        self.saved = {"steps_done": 0, "n_samples": 0, "t": math.nan,
                      "event_counts": np.zeros(len(_event_names(file)), np.int64)}

    @classmethod
    def _from_file(cls, path: Path, f: h5py.File, guard, sequence: int) -> "RunWriter":
        steps = f["steps"]
        multipliers = next((steps[name] for name in multiplier_datasets(steps)), None)
        order = [str(name) for name in _plain(f["invariants"].attrs["order"])]
        state = {name: dataset.id for name, dataset in f["state"].items() if name != "record"}
        return cls(path, f, {
            "t": _Growing(f["t"].id), "y": _Growing(f["y"].id),
            "invariants": [_Growing(f["invariants"][name].id) for name in order],
            "iterations": _Growing(steps["iterations"].id),
            "substeps": _Growing(steps["substeps"].id) if "substeps" in steps else None,
            "multipliers": _Growing(multipliers.id) if multipliers is not None else None,
            "state": state, "record": f["state"]["record"].id if "record" in f["state"] else None,
            **({"step_t": _Growing(steps["t"].id), "step_h": _Growing(steps["h"].id)} if "h" in steps else {}),
            **({"events": [(_Growing(f["events"][name]["t"].id), _Growing(f["events"][name]["y"].id))
                           for name in _event_names(f)]} if "events" in f else {})},
            guard=guard, sequence=sequence)

    # --- opening ---
    @classmethod
    def create(cls, path, integration, *, config_text: str, t_end: float | None = None,
               attributes: dict | None = None, overwrite: bool = True) -> "RunWriter":
        """Create ``path`` with the layout, the run's metadata and its sample at t0.

        The file is built under a temporary name and renamed to ``path`` once complete; an
        existing ``path`` is replaced (``overwrite``) unless another process is writing it.
        """
        path = Path(path)
        run, problem, method = integration, integration.problem, integration.method
        create_parent_directories(path)
        ensure_not_busy(path)
        free = _free_bytes(path.parent)
        if free is not None and free < SPACE_BASE:
            raise DiskFullError(f"{path}: the disk is full ({_size(free)} free); free some space, or write "
                                "the run elsewhere")
        temporary = _temporary_path(path)
        try:
            f = h5py.File(temporary, "w", libver=LIBVER)
        except OSError as err:
            with contextlib.suppress(OSError):
                temporary.unlink()
            room = no_room(err)
            if room is not None:
                raise DiskFullError(f"{path}: {room.sentence}; {room.fix}, or write the run elsewhere") from None
            raise OutputError(f"{path}: cannot create: {_described(err, temporary, path)}") from None
        guard = None
        try:
            guard = _FileGuard(temporary)
            guard.lock()
            mult = multiplier_name(run)
            n_datasets = 5 + len(problem.invariant_names) + (mult is not None)
            guard.reserve(SPACE_BASE + n_datasets * SPACE_MARGIN)
            _set_attributes(f, {**version_attributes(), "format": FORMAT, "format_version": FORMAT_VERSION,
                                "created": _now()})
            adaptive = getattr(run, "adaptive_kernel", False)
            datasets = create_run_group(f, problem=problem, method=method, conserve=run.conserve,
                                        n_multipliers=run.multipliers.size, multiplier=mult,
                                        adaptive_steps=adaptive, events=run.events.definitions() if adaptive else {},
                                        scales=problem.invariant_scales(run.y),
                                        values_at_t0=problem.invariant_values(run.y), attributes={
                # with_initial: a run started from a y0 of its own (Integration(y0=...)) says so too
                "config": config_text, **run_attributes(problem.with_initial(run.y), method, h=run.h, t0=run.t0,
                                                        n_steps=run.n_steps,
                                                        t_end=t_end, output_every=run.store_every,
                                                        conserve=run.conserve),
                "steps_done": 0, "status": STATUS_RUNNING, "wall_time_s": 0.0, "kernel_time_s": 0.0,
                **problem_file_attributes(problem), **(run.file_attributes() if adaptive else {}),
                **(attributes or {})})
            state = f.create_group("state")
            initial = dict(run.state(), n_samples=np.int64(1), wall_time_s=0.0, kernel_time_s=0.0)
            datasets["state"] = {key: _state_dataset(state, key, value) for key, value in initial.items()}
            n, s = run.y.size, run.coef.shape[0]
            record = _record_dataset(state, _record_length(n, s, run.multipliers.size,
                                                           sum(v.size for v in _record_tail(run.state()))))
            _state_dimensions(f, state, record)
            for sequence in (0, 1):
                _write_record_row(record, sequence, _pack_record(run.state(), sequence, 1, 0.0, 0.0))
            datasets["record"] = record
            _mark_writer(state)

            writer = cls(path, f, datasets, guard=guard, sequence=1)
            writer.opened_as = temporary
            writer.append(integration.initial_chunk())
            writer.saved = _saved_record(initial, 1)
            f.swmr_mode = True   # flushes: from here on the file on disk is always consistent
            _publish(temporary, path, overwrite)
            return writer
        except OutputError:                      # busy, or appeared meanwhile: HDF5 itself is fine
            _close_quietly(f, guard, temporary)
            raise
        except (OSError, RuntimeError) as err:   # HDF5 failed a write (or no room): never close it again
            _abandon(f, guard)
            with contextlib.suppress(OSError):
                temporary.unlink()
            room = no_room(err)
            if room is not None:
                raise DiskFullError(f"{path}: {room.sentence}; {room.fix}, or write the run elsewhere") from None
            raise OutputError(f"{path}: cannot create: {_described(err, temporary, path)}") from None
        except BaseException:
            _close_quietly(f, guard, temporary)
            raise

    @classmethod
    def resume(cls, path, *, restore=None, stop=None, config_text: str | None = None,
               extension: dict | None = None, problem_file: dict | None = None,
               set_overrides=None) -> tuple["RunWriter", dict]:
        """Reopen a run for writing; return (writer, saved) with saved = the state and the root attributes.

        Nothing is changed until everything the run will build on has been read back and
        found sound (``RunFile.verify``: metadata checksums, fletcher32 of every chunk up
        to the saved state, the state record) and ``restore(saved)`` has accepted the
        state (it raises ValueError or KeyError if the state does not fit the run). A file
        left by a killed writer (SWMR flags still set) is then repaired; if reopening it
        still fails, the flags are put back as they were. ``config_text``: the resolved
        config the run continues with (other solver settings or a later end): it replaces the
        stored config; ``solver_history`` records a change of solver. ``extension``: the new
        {"t_end", "n_steps", "output_times"} of a run continued to a later end
        (streaming.run_extension), recorded in ``extension_history``. ``problem_file``: an
        edited python: file's {problem_file_sha256}, recorded in ``problem_file_history``.
        ``set_overrides``: the --set values the run goes on with (layout.SET_OVERRIDES), or None to keep
        what is stored.
        """
        path = Path(path)
        if not path.exists():
            raise OutputError(f"{path}: no such file to resume")
        _regular_file(path, "run file")
        if not h5py.is_hdf5(path):
            raise NotAnElimfastFile(f"{path}: not an HDF5 file, so not an elimfast run to resume")
        ensure_not_busy(path)
        # a write cut off part-way (a file-size limit) leaves the file shorter than HDF5 recorded:
        # extended back (its saved part verified here), or left as it was if not sound
        with extended_to_recorded_end(path), RunFile(path) as existing:
            saved = existing.saved_state()
            existing.verify(stop=stop)
            # A failed fixed-step run ends with a sample of its last good state, off the grid
            # (Integration.advance): the continuation samples the grid again. Adaptive runs
            # (/steps/h; not step_control: all files have it) add none.
            if "h" not in existing._root["steps"]:
                saved["n_samples"] = min(saved["n_samples"], samples_on_grid(
                    saved["steps_done"], int(existing.attrs.get("output_every", 1))))
            n_datasets = 4 + len(existing.invariant_names) + (existing.multiplier_name is not None)
            # A format 1 file (no checksums, no record) is continued in its own format.
            if restore is not None:
                try:
                    restore(saved)
                except (KeyError, ValueError) as err:
                    raise OutputError(f"{path}: the stored state does not fit this run ({err})") from None
        flags = consistency_flags(path)
        guard = _FileGuard(path)
        try:
            if not guard.lock():
                raise FileBusyError(f"{path}: is being written by another process; stop it first")
            guard.reserve(SPACE_BASE + n_datasets * SPACE_MARGIN)
        except DiskFullError as err:
            guard.close()
            raise DiskFullError(f"{err}; {no_room(err).fix}, then resume again") from None
        except BaseException:
            guard.close()
            raise
        if flags:
            clear_consistency_flags(path)
        try:
            f = h5py.File(path, "r+", libver=LIBVER)
        except OSError as err:
            guard.close()
            if flags:
                with contextlib.suppress(OSError, OutputError):
                    set_consistency_flags(path, flags)
            raise OutputError(f"{path}: cannot open for resuming: {_one_line(err)}") from None
        try:
            attrs = {key: _plain(value) for key, value in f.attrs.items()}
            # Drop rows of the chunk that was being written when the run stopped.
            _cut_back(f, saved["n_samples"], saved["steps_done"], saved.get("event_counts", ()))
            f.attrs["status"] = STATUS_RUNNING
            if config_text is not None:
                replaced = {"config": config_text}
                before = _solver_line(str(attrs.get("config", "")))
                if _solver_line(config_text) != before:
                    history = list(_plain(f.attrs.get("solver_history", [])) or [])
                    history.append(f"from step {saved['steps_done']}: {_solver_line(config_text)} (before: {before})")
                    replaced["solver_history"] = history
                if extension is not None:
                    history = list(_plain(f.attrs.get("extension_history", [])) or [])
                    history.append(f"from step {saved['steps_done']}: t_end {extension['t_end']!r} "
                                   f"(before: {attrs.get('t_end')!r})")
                    replaced["extension_history"] = history
                    replaced["t_end"] = float(extension["t_end"])
                    if extension.get("n_steps") is not None:
                        replaced["n_steps"] = int(extension["n_steps"])
                    if extension.get("output_times") is not None:
                        replaced["output_times"] = int(extension["output_times"])
                _replace_attributes(f, replaced)
            if problem_file:
                digest = problem_file[PROBLEM_FILE_DIGEST]
                history = list(_plain(f.attrs.get("problem_file_history", [])) or [])
                history.append(f"from step {saved['steps_done']}: sha256 {digest[:16]} (before: "
                               f"{str(attrs.get(PROBLEM_FILE_DIGEST))[:16]})")
                _replace_attributes(f, {PROBLEM_FILE_DIGEST: digest, "problem_file_history": history})
            stored_sets = set_overrides_attribute(set_overrides)
            if stored_sets and stored_sets[SET_OVERRIDES] != attrs.get(SET_OVERRIDES):
                _replace_attributes(f, stored_sets)
            # stats_*: those of the end before; gone while the run goes on, so that a file killed
            # now claims none (finish writes new ones, as steps_done)
            for key in ["failed_step_iterations", *(key for key in f.attrs if key.startswith(STATS_PREFIX))]:
                if key in f.attrs:
                    del f.attrs[key]
            _mark_writer(f["state"])
            f.flush()
            f.swmr_mode = True
        except (OSError, RuntimeError) as err:
            _abandon(f, guard)
            room = no_room(err)
            if room is not None:
                raise DiskFullError(f"{path}: {room.sentence}; {room.fix}, then resume again") from None
            raise OutputError(f"{path}: cannot be resumed: {_one_line(err)}") from None
        except BaseException:
            _close_quietly(f, guard, None)
            raise
        writer = cls._from_file(path, f, guard, saved.get("sequence", 1))
        writer.saved = _saved_record(saved, saved["n_samples"])
        saved["attrs"] = attrs
        return writer, saved

    # --- disk space ---
    @property
    def n_datasets(self) -> int:
        return 3 + len(self._invariants) + (self._substeps is not None) + (self._multipliers is not None)

    def fit_steps(self, steps: int, step_bytes: float) -> int:
        """How many of ``steps`` steps (at ``step_bytes`` each) the disk can take; their
        space is reserved. 0: not even one step fits (the disk is full, or the file-size limit is
        reached: ``no_room`` says which)."""
        if self._guard is None:
            return steps
        margin = SPACE_BASE + self.n_datasets * SPACE_MARGIN
        try:
            self._guard.reserve(margin + SPACE_FACTOR * steps * step_bytes)
            return steps
        except DiskFullError:
            pass
        fitting = int((self._guard.room() - margin) // max(SPACE_FACTOR * step_bytes, 1.0))
        try:
            if fitting < 1:   # what reserve says about it: a full disk or the file-size limit
                self._guard.reserve(margin + SPACE_FACTOR * step_bytes)
            self._guard.reserve(margin + SPACE_FACTOR * fitting * step_bytes)
        except DiskFullError as err:
            self.no_room = no_room(err)
            return 0
        return min(steps, fitting)

    # --- writing ---
    def append(self, chunk) -> None:
        """Extend every dataset by the chunk's samples and steps (not yet flushed)."""
        steps_done = len(chunk.multipliers)
        iterations = chunk.iterations
        if len(iterations) > steps_done:   # a failed step's count: kept apart, rows stay per done step
            self.failed_step_iterations = int(iterations[steps_done])
            iterations = iterations[:steps_done]
        append_rows(self._datasets, t=chunk.t, y=chunk.y, invariants=chunk.invariants, iterations=iterations,
                    substeps=chunk.substeps, multipliers=chunk.multipliers, step_t=getattr(chunk, "step_t", None),
                    step_h=getattr(chunk, "step_h", None), event_index=getattr(chunk, "event_index", None),
                    event_t=getattr(chunk, "event_t", None), event_y=getattr(chunk, "event_y", None))

    def save_state(self, state: dict, *, wall_time_s: float, kernel_time_s: float) -> None:
        """Flush the appended data, then write and flush the state (two flushes: see class doc)."""
        self._file.flush()
        n_samples = self._t.rows
        if self._record is not None:
            self._sequence += 1
            if "coef_extra" not in self._state:   # a file written before it was kept: its record has no room
                state = {key: value for key, value in state.items() if key != "coef_extra"}
            _write_record_row(self._record, self._sequence % 2,
                              _pack_record(state, self._sequence, n_samples, wall_time_s, kernel_time_s))
        values = dict(state, n_samples=n_samples, wall_time_s=wall_time_s, kernel_time_s=kernel_time_s)
        for key, value in values.items():
            dataset = self._state.get(key)
            if dataset is None:     # last_h, newton_base: a file written before the step engine (no record);
                continue            # coef_extra: one written before the predictor kept it
            dataset.write(h5py.h5s.ALL, h5py.h5s.ALL, np.ascontiguousarray(value, dtype=dataset.dtype))
        self._file.flush()
        self.saved = _saved_record(state, n_samples)

    def finish(self, status: str, *, steps_done: int, wall_time_s: float, kernel_time_s: float,
               stats: dict | None = None, events_not_finite: dict | None = None) -> None:
        """Close the SWMR session, then write the final root attributes in a normal session.

        Rows and events appended after the last saved state (a chunk cut short) are dropped
        first: the datasets end where the saved state says. ``stats``: Result.stats of the saved state
        (``saved["counters"]``), written as stats_<name> (layout.stats_attributes). events_not_finite: see
        layout.NOT_FINITE_FROM.
        """
        if self.abandoned:
            return
        if self._guard is not None:
            self._guard.reserve(SPACE_BASE)
        saved_samples, saved_steps = self.saved["n_samples"], self.saved["steps_done"]
        self._file.close()
        try:
            with reopen_for_writing(self.path, LIBVER) as f:
                _cut_back(f, saved_samples, saved_steps, self.saved["event_counts"])
                f.attrs["status"] = status
                f.attrs["steps_done"] = min(steps_done, saved_steps)
                f.attrs["wall_time_s"] = wall_time_s
                f.attrs["kernel_time_s"] = kernel_time_s
                if self.failed_step_iterations is not None:
                    f.attrs["failed_step_iterations"] = self.failed_step_iterations
                if stats:
                    _replace_attributes(f, stats_attributes(stats))
                for name, first in (events_not_finite or {}).items():
                    if "events" in f and name in f["events"]:
                        group = f["events"][name]
                        group.attrs[NOT_FINITE_FROM] = min(float(first), float(group.attrs.get(NOT_FINITE_FROM, first)))
        finally:
            if self._guard is not None:
                self._guard.close()

    def close(self) -> None:
        """Close without final attributes (the file stays valid, status 'running')."""
        if self.abandoned:
            return
        try:
            if self._file.id.valid:
                self._file.close()
        finally:
            if self._guard is not None:
                self._guard.close()

    def describe(self, err: BaseException) -> str:
        """An HDF5 error on one line, naming the user's file where HDF5 names the temporary one."""
        return _described(err, self.opened_as, self.path)

    def abandon(self) -> None:
        """After HDF5 failed a write: never touch the file again (see _ABANDONED)."""
        if not self.abandoned:
            self.abandoned = True
            _abandon(self._file, self._guard, keep=self)


def _described(err: BaseException, opened_as: Path, path: Path) -> str:
    """HDF5's error text on one line, with ``path`` where HDF5 names the file it opened (a new
    file's hidden temporary name, which the user never gave)."""
    return _one_line(err).replace(str(opened_as), str(path))


def _mark_writer(state_group) -> None:
    state_group.attrs["writer_pid"] = os.getpid()
    state_group.attrs["writer_host"] = socket.gethostname()


def _event_names(f) -> list[str]:
    """The names of a run's events, in the order of its events group (none: no group)."""
    if "events" not in f:
        return []
    return [str(name) for name in _plain(f["events"].attrs.get("order", []))]


def _step_datasets(f):
    """Every dataset with one row per step: the per-step records and the multipliers."""
    steps = f["steps"]
    for name in PER_STEP_RECORDS + tuple(multiplier_datasets(steps)):
        if name in steps:
            yield steps[name]


def _sample_datasets(f):
    yield f["t"]
    yield f["y"]
    yield from f["invariants"].values()


def _solver_line(config_text: str) -> str:
    """The solver section of a resolved config, on one line."""
    import yaml
    try:
        solver = (yaml.safe_load(config_text) or {}).get("solver") or {}
    except (yaml.YAMLError, AttributeError):
        return "?"
    return ", ".join(f"{key} {value}" for key, value in solver.items()) if isinstance(solver, dict) else "?"


_STATE_MEMBERS = ("y", "y_comp", "clock", "coef", "multipliers", "steps_done", "n_samples", "wall_time_s",
                  "kernel_time_s")
_LAYOUT = ("t", "y", "invariants", "steps", "steps/iterations", "method", "state",
           *(f"state/{name}" for name in _STATE_MEMBERS))

def _killed_sweep(path: Path, writing: bool = False) -> str | None:
    """What a sweep file whose writer was killed holds (sweepfile.describe_sweep_file), or None
    for any other file HDF5 cannot open. A grid sweep writes outside SWMR mode, so HDF5 refuses
    its file after a kill although every run flushed before is whole (--resume keeps them).
    ``writing``: the same for a sweep that is writing the file now (a snapshot of its listing,
    which the sweep flushes as each run is stored)."""
    from .sweepfile import describe_sweep_file
    if not consistency_flags(path) & 1:
        return None
    try:
        with open_unflagged(path) as f:
            if _plain(f.attrs.get("format", "")) != SWEEP_FORMAT:
                return None
            return describe_sweep_file(path, f, killed=not writing, writing=writing)
    except Exception:   # noqa: BLE001 -- unreadable even so: the damage it was reported as
        return None


def _require_ours(path, f) -> None:
    """The format attribute, a version this reader knows, and every member of the layout."""
    try:
        names = set(f.attrs)    # listing them reads the whole attribute index: damage shows here
        fmt = _plain(f.attrs["format"]) if "format" in names else None
        version = int(f.attrs["format_version"]) if "format_version" in names else 0
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as err:
        raise _damaged(path, "its root attributes", err) from None
    if fmt == SWEEP_FORMAT:
        from .sweepfile import describe_sweep_file
        try:
            message = describe_sweep_file(path, f)
        except (OSError, RuntimeError, KeyError, ValueError, TypeError) as err:
            raise _damaged(path, "/runs", err) from None
        raise NotAnElimfastFile(message)
    if fmt != FORMAT:
        what = f"its format is {fmt!r}" if fmt else f"no '{FORMAT}' format attribute"
        raise NotAnElimfastFile(f"{path}: not an elimfast run file ({what}); give a file written by 'elimfast run'")
    if version > FORMAT_VERSION:
        raise OutputError(f"{path}: written in elimfast run format {version}; this elimfast reads up to "
                          f"{FORMAT_VERSION}: upgrade elimfast")
    for name in _LAYOUT:
        try:
            present = name in f
        except (OSError, RuntimeError, KeyError, ValueError) as err:
            raise _damaged(path, f"/{name}", err) from None
        if not present:
            raise DamagedFileError(f"{path} is damaged or incomplete: it has the elimfast run format but no /{name}; "
                                   f"{_DAMAGE_ADVICE}")


class RunFile:
    """A run file opened for reading (read-only; a killed run's file is opened in SWMR mode).

    ``attrs``: root attributes as plain Python values; ``steps_done`` and
    ``n_samples``: the rows that are consistent (from the saved state); ``status``: the
    recorded status, or 'killed' / 'running' for a file whose writer did not finish
    (decided by whether the writer process is alive). Every read that fails (a checksum,
    a missing member) raises DamagedFileError naming the file and the place.
    """

    def __init__(self, path, run: str | None = None):
        path, run = split_run_path(path, run)
        self.path = Path(path)
        self.run = run
        try:
            self._file = _open(self.path)
        except DamagedFileError:
            message = _killed_sweep(self.path)
            if message is None:
                raise
            raise OutputError(message) from None
        except FileBusyError:   # a sweep writing its file says how far it got
            message = _killed_sweep(self.path, writing=True)
            if message is None:
                raise
            raise FileBusyError(message) from None
        try:
            refuse_netcdf_copy(self.path, self._file.attrs)
            if run is None:
                _require_ours(self.path, self._file)
                self._root = self._file
            else:
                self._root = _sweep_run_group(self.path, self._file, run)
            with self._reading("the layout"):
                self._load()
        except BaseException:
            self.close()
            raise

    @property
    def name(self) -> str:
        """The file, or file:/runs/<label> for a run of a sweep file (its label, as the user
        writes it, not its group name, where '/' is '|': sweepfile.sweep_group_name)."""
        if self.run is None:
            return str(self.path)
        label = _plain(self._root.attrs.get("label", "")) or self._root.name.rsplit("/", 1)[-1].replace("|", "/")
        return f"{self.path}:/{RUNS_GROUP}/{label}"

    def _load(self) -> None:
        f = self._root
        with self._reading("the root attributes"):
            self.attrs = {key: _plain(value) for key, value in f.attrs.items()}
            if self.run is not None:   # the sweep file's versions and date, under the run's own attributes
                self.attrs = {**{key: _plain(value) for key, value in self._file.attrs.items()
                                 if key not in ("format", "sweep")}, **self.attrs}
        self.state_damage = None   # what a damaged saved state costs (_read_state), for inspect
        self._saved = self._read_state() if self.run is None else self._sweep_run_counts()
        self.steps_done = self._saved["steps_done"]
        with self._reading("/t"):
            self.n_samples = min(self._saved["n_samples"], f["t"].shape[0])
        self.status = str(self.attrs.get("status", "?"))
        # A finished run's times are the root's (RunWriter.finish, what `run` printed); the saved state's
        # are those of its last chunk, which is all a running or killed run has.
        times = self.attrs if self.status != STATUS_RUNNING and "wall_time_s" in self.attrs else self._saved
        self.wall_time_s = float(times["wall_time_s"])
        self.kernel_time_s = float(times.get("kernel_time_s", self._saved["kernel_time_s"]))
        if self.status == STATUS_RUNNING:
            if int(self.attrs.get("format_version", 1)) >= 2:   # its writer holds the lock while it lives
                alive = _writer_lock_held(self.path)
            else:
                state = f["state"]
                pid = int(state.attrs.get("writer_pid", 0))
                host = str(_plain(state.attrs.get("writer_host", "")))
                alive = host == socket.gethostname() and pid and _process_alive(pid) and pid != os.getpid()
            self.status = STATUS_RUNNING if alive else "killed"
        with self._reading("/y"):
            self.coordinate_names = component_names(f)
        with self._reading("/invariants"):
            self.invariant_names = [str(n) for n in _plain(f["invariants"].attrs["order"])]
            self.imposed = {name: read_flag(f["invariants"][name].attrs, "imposed")
                            for name in self.invariant_names}
        with self._reading("/steps"):
            self.multiplier_name = next(iter(multiplier_datasets(f["steps"])), None)

    @contextlib.contextmanager
    def _reading(self, where: str):
        """Turn any failure of HDF5 inside the block into DamagedFileError naming ``where``."""
        try:
            yield
        except ElimfastError:
            raise
        except (KeyError, OSError, RuntimeError, ValueError, TypeError, IndexError) as err:
            raise _damaged(self.path, where, err) from None

    def _read_state(self) -> dict:
        """The saved state: the valid row of /state/record with the higher sequence number
        (format 2), or the named /state datasets (format 1)."""
        state = self._root["state"]
        with self._reading("/state"):
            named = {key: np.array(state[key][()]) for key in _STATE_MEMBERS}
            if "coef_extra" in state:   # absent in files written before the predictor kept it
                named["coef_extra"] = np.array(state["coef_extra"][()])
        if "record" not in state:
            return {**named, "steps_done": int(named["steps_done"]), "n_samples": int(named["n_samples"]),
                    "wall_time_s": float(named["wall_time_s"]), "kernel_time_s": float(named["kernel_time_s"])}
        n, (s, _), n_mult = named["y"].size, named["coef"].shape, named["multipliers"].size
        adaptive = None
        if "control_state" in state:
            with self._reading("/state"):
                adaptive = (state["control_state"].shape[0], state["counters"].shape[0],
                            state["event_counts"].shape[0])
        best, problems = None, []
        for slot in (0, 1):
            try:
                row = self._root["state/record"][slot]
            except (KeyError, OSError, RuntimeError, ValueError) as err:
                problems.append(f"row {slot}: {_hdf5_reason(err)}")
                continue
            values = _unpack_record(np.asarray(row, dtype=np.float64), n, s, n_mult, adaptive,
                                    named["coef_extra"].shape[0] if "coef_extra" in named else None)
            if values is None:
                problems.append(f"row {slot} fails its CRC")
            elif best is None or values["sequence"] > best["sequence"]:
                best = values
        if best is None:
            raise DamagedFileError(f"{self.path} is damaged at /state/record: neither copy of the saved state is "
                                   f"sound ({'; '.join(problems)}); {_DAMAGE_ADVICE}")
        # the named datasets follow the record: a later count there means the lost copy was the newer
        if problems and int(named["steps_done"]) > best["steps_done"]:
            self.state_damage = (f"the newest copy of the saved state is damaged ({'; '.join(problems)}); resume "
                                 f"continues from the other copy, at step {best['steps_done']}")
        elif (int(named["steps_done"]), int(named["n_samples"])) == (best["steps_done"], best["n_samples"]):
            # the same save in both: a named copy (no checksum) unlike the record was altered since
            altered = [f"/state/{key}" for key in named if key in best and not np.array_equal(
                np.ravel(named[key]), np.ravel(best[key]), equal_nan=True)]
            if altered:
                self.state_damage = (f"{', '.join(altered)} not as in the checksummed copy of the same save "
                                     "(/state/record), which resume reads: altered since; do not read the state there")
        return best

    def _sweep_run_counts(self) -> dict:
        """A sweep run has no /state: its datasets end where the run ended."""
        f = self._root
        with self._reading("/t"):
            n_samples = f["t"].shape[0]
        with self._reading("/steps/iterations"):
            steps_done = min(int(self.attrs.get("steps_done", 0)), f["steps/iterations"].shape[0])
        return {"steps_done": steps_done, "n_samples": n_samples,
                "wall_time_s": float(self.attrs.get("wall_time_s", 0.0)), "kernel_time_s": 0.0}

    def saved_state(self) -> dict:
        """What resume continues from: y, y_comp, clock, coef, multipliers, steps_done,
        n_samples, wall_time_s, kernel_time_s (and the record's sequence number)."""
        return {key: (value.copy() if isinstance(value, np.ndarray) else value) for key, value in self._saved.items()}

    def verify(self, stop=None) -> dict:
        """Read every stored row the saved state counts (and the method tables) block by
        block, so that HDF5 checks every metadata checksum and every chunk's fletcher32;
        DamagedFileError for the first dataset that fails, naming the rows of its damaged
        chunks (every block of that dataset is read, so all of them), also if a dataset is
        shorter than the state says. ``stop``: an object whose ``requested`` ends the check
        early (KeyboardInterrupt). Returns {"chunks": HDF5 chunks read, "checksummed":
        whether they carry fletcher32}."""
        f = self._root
        targets = [("/t", "t", self._saved["n_samples"]), ("/y", "y", self._saved["n_samples"])]
        targets += [(f"/invariants/{name}", f"invariants/{name}", self._saved["n_samples"])
                    for name in self.invariant_names]
        with self._reading("/steps"):
            targets += [(f"/steps/{name}", f"steps/{name}", self._saved["steps_done"]) for name in f["steps"]
                        if name in PER_STEP_RECORDS or name in multiplier_datasets(f["steps"])]
        chunks, checksummed = 0, True
        for where, name, count in targets:
            with self._reading(where):
                dataset = f[name]
                if dataset.shape[0] < count:
                    raise DamagedFileError(f"{self.path} is damaged or incomplete at {where}: it has "
                                           f"{dataset.shape[0]} rows, the saved state counts {count}; "
                                           f"{_DAMAGE_ADVICE}")
                checksummed = checksummed and bool(dataset.fletcher32)
                chunk_rows = dataset.chunks[0] if dataset.chunks else max(count, 1)
                row_bytes = dataset.dtype.itemsize * int(np.prod(dataset.shape[1:], dtype=np.int64))
                block = max(1, VERIFY_BLOCK_BYTES // max(row_bytes, 1) // chunk_rows) * chunk_rows
            damaged, first_error = [], None
            for start in range(0, count, block):
                if stop is not None and stop.requested:
                    raise KeyboardInterrupt
                end = min(count, start + block)
                try:
                    dataset[start:end]
                except READ_ERRORS as err:
                    first_error = first_error or err
                    damaged += damaged_row_ranges(dataset, start, end) or [(start, end - 1)]
            if first_error is not None:
                raise _damaged(self.path, f"{where} {rows_text(_merged(damaged))}", first_error)
            chunks += -(-count // chunk_rows)
        with self._reading("/method"):
            for name in f["method"]:
                f["method"][name][()]
        return {"chunks": chunks, "checksummed": checksummed}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if getattr(self, "_file", None) is not None and self._file.id.valid:
            self._file.close()

    @property
    def swmr(self) -> bool:
        return bool(self._file.swmr_mode)

    # --- data ---
    def _rows(self, name: str, count: int, stride: int) -> np.ndarray:
        return self._read_rows(name, 0, count, stride)

    def _read_rows(self, name: str, start: int, stop: int, stride: int = 1) -> np.ndarray:
        """Rows start:stop:stride of a dataset; DamagedFileError naming the rows of the chunks
        that cannot be read (safety.damaged_row_ranges) when HDF5 fails to read them."""
        where = f"/{name}"
        with self._reading(where):
            dataset = self._root[name]
        try:
            return dataset[start:stop:stride]
        except READ_ERRORS as err:
            ranges = damaged_row_ranges(dataset, start, stop) or [(start, stop - 1)]
            raise _damaged(self.path, f"{where} {rows_text(ranges)}", err) from None

    def t(self, stride: int = 1) -> np.ndarray:
        return self._rows("t", self.n_samples, stride)

    def y(self, stride: int = 1) -> np.ndarray:
        return self._rows("y", self.n_samples, stride)

    def invariant(self, name: str, stride: int = 1) -> np.ndarray:
        return self._rows(f"invariants/{name}", self.n_samples, stride)

    def iterations(self, stride: int = 1) -> np.ndarray:
        return self._rows("steps/iterations", self.steps_done, stride)

    def substeps(self, stride: int = 1) -> np.ndarray:
        """Substeps of each step; ones for a file written before the step engine (none stored)."""
        with self._reading("/steps"):
            present = "substeps" in self._root["steps"]
        if not present:
            return np.ones(len(range(0, self.steps_done, stride)), dtype=np.int32)
        return self._rows("steps/substeps", self.steps_done, stride)

    @property
    def adaptive(self) -> bool:
        """Steps chosen by a controller (docs/adaptive.md): /steps/h holds their sizes."""
        return str(self.attrs.get("step_control", "fixed")) != "fixed"

    def step_sizes(self, stride: int = 1) -> np.ndarray | None:
        """/steps/h of a run through the adaptive kernel, else None (every step is h)."""
        if "h" not in self._root["steps"]:
            return None
        return self._rows("steps/h", self.steps_done, stride)

    def step_times(self, stride: int = 1) -> np.ndarray | None:
        if "t" not in self._root["steps"]:
            return None
        return self._rows("steps/t", self.steps_done, stride)

    def event_names(self) -> list[str]:
        return _event_names(self._root)

    def events_not_finite(self) -> dict[str, float]:
        """{event: first time it was NaN or infinite} (RunWriter.finish)."""
        events = self._root["events"] if "events" in self._root else {}
        return {name: float(events[name].attrs[NOT_FINITE_FROM]) for name in self.event_names()
                if NOT_FINITE_FROM in events[name].attrs}

    def event(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(t, y) of the occurrences of an event saved so far."""
        counts = dict(zip(self.event_names(), self._saved.get("event_counts", ())))
        count = int(counts.get(name, self._root["events"][name]["t"].shape[0]))
        with self._reading(f"/events/{name}"):
            return (np.array(self._root["events"][name]["t"][:count]),
                    np.array(self._root["events"][name]["y"][:count]))

    def stored_stats(self) -> dict:
        """Result.stats of an adaptive run as stored in its attributes stats_<name> (a sweep run;
        a run file's root since they were written there, when the run ended: none while it runs)."""
        return {key[len(STATS_PREFIX):]: int(value) for key, value in self.attrs.items()
                if key.startswith(STATS_PREFIX)}

    def multipliers(self, stride: int = 1) -> np.ndarray | None:
        if self.multiplier_name is None:
            return None
        return self._rows(f"steps/{self.multiplier_name}", self.steps_done, stride)

    def multiplier_labels(self) -> list[str]:
        if self.multiplier_name is None:
            return []
        with self._reading(f"/steps/{self.multiplier_name}"):
            names = _plain(self._root["steps"][self.multiplier_name].attrs.get("invariants", []))
        return [f"{self.multiplier_name}[{name}]" for name in names]

    def method_table(self, name: str) -> np.ndarray | None:
        with self._reading(f"/method/{name}"):
            group = self._root["method"]
            return group[name][()] if name in group else None

    def final_state(self) -> dict:
        return self.saved_state()

    # --- reductions, block by block (memory bounded for any length) ---
    def _block_rows(self, name: str) -> int:
        """Rows of the dataset name read at a time: about VERIFY_BLOCK_BYTES."""
        dataset = self._root[name]
        row_bytes = dataset.dtype.itemsize * int(np.prod(dataset.shape[1:], dtype=np.int64))
        return max(1, VERIFY_BLOCK_BYTES // max(row_bytes, 1))

    def _blocks(self, name: str, stop: int, block: int | None = None):
        """The rows [0, stop) of the dataset name in blocks of ``block`` rows (default _block_rows):
        datasets read side by side (zipped) must be given the same block."""
        block = block or self._block_rows(name)
        for start in range(0, stop, block):
            yield self._read_rows(name, start, min(stop, start + block))

    def invariant_drift(self) -> dict[str, float]:
        """max over the stored samples of |I(t) - I(t0)| for H and every invariant; NaN (no
        figure) before the first step is done (the rule: integrate.invariant_drift)."""
        from ..integrate import invariant_drift

        initial = self.initial_invariants()
        return {name: invariant_drift(self._blocks(f"invariants/{name}", self.n_samples), initial[name],
                                      self.steps_done)
                for name in self.invariant_names}

    def iteration_stats(self) -> dict:
        count, total, low, high = 0, 0, None, None
        histogram = np.zeros(0, dtype=np.int64)
        for block in self._blocks("steps/iterations", self.steps_done):
            if block.size == 0:
                continue
            count += block.size
            total += int(block.sum(dtype=np.int64))
            low = int(block.min()) if low is None else min(low, int(block.min()))
            high = int(block.max()) if high is None else max(high, int(block.max()))
            counts = np.bincount(np.maximum(block, 0).astype(np.int64))
            if counts.size > histogram.size:
                counts[:histogram.size] += histogram
                histogram = counts
            else:
                histogram[:counts.size] += counts
        if count == 0:
            return {"count": 0}
        cumulative = np.cumsum(histogram)
        median = int(np.searchsorted(cumulative, (count + 1) // 2))
        p99 = int(np.searchsorted(cumulative, math.ceil(0.99 * count)))
        return {"count": count, "total": total, "mean": total / count, "min": low, "median": median,
                "p99": p99, "max": high}

    @property
    def stores_values_at_t0(self) -> bool:
        """Whether every invariant has its value at t0 stored (attribute value_at_t0); files
        written before it was stored have not."""
        with self._reading("/invariants"):
            group = self._root["invariants"]
            return all(VALUE_AT_T0 in group[name].attrs for name in self.invariant_names)

    def initial_invariants(self) -> dict[str, float]:
        """H and every invariant at t0, of the initial state (attribute value_at_t0): the
        reference I(t0) of the invariant errors. A file written before it was stored gives
        its first sample's values (at t0 unless output times start later: ``reference_time``
        says when), NaN without samples."""
        if self.stores_values_at_t0:
            with self._reading("/invariants"):
                group = self._root["invariants"]
                return {name: float(group[name].attrs[VALUE_AT_T0]) for name in self.invariant_names}
        values = {}
        for name in self.invariant_names:
            first = math.nan
            for block in self._blocks(f"invariants/{name}", min(self.n_samples, 1)):
                first = float(block[0])
            values[name] = first
        return values

    def reference_time(self) -> float:
        """The time of the state the invariant errors are measured against: t0, or for a file
        written before the values at t0 were stored, its first sample's time (NaN without one)."""
        if self.stores_values_at_t0:
            return float(self.attrs.get("t0", 0.0))
        return float(self._read_rows("t", 0, 1)[0]) if self.n_samples else math.nan

    def invariant_scales(self) -> dict[str, float]:
        """The size of the terms of H and of every invariant at t0 (attribute ``scale``,
        Problem.invariant_scales); 0.0 for files written before it was stored."""
        with self._reading("/invariants"):
            group = self._root["invariants"]
            return {name: float(group[name].attrs.get("scale", 0.0)) for name in self.invariant_names}

    def substep_stats(self) -> dict:
        """{"split": steps split into substeps (docs/solver.md), "max": the most substeps of
        one step, "unimposed": steps with a substep taken without imposing the invariants (their
        multipliers are NaN, docs/solver.md#a-substep-without-imposing), "total": the (sub)steps
        taken in all}; zeros (and total = steps done) for a file written before the step engine
        (no /steps/substeps)."""
        with self._reading("/steps"):
            present = "substeps" in self._root["steps"]
        split, largest, unimposed, total = 0, 1 if self.steps_done else 0, 0, 0 if present else self.steps_done
        if present:
            for block in self._blocks("steps/substeps", self.steps_done):
                if block.size:
                    split += int(np.count_nonzero(block > 1))
                    largest = max(largest, int(block.max()))
                    total += int(block.sum())
        if self.multiplier_name is not None:
            for block in self._blocks(f"steps/{self.multiplier_name}", self.steps_done):
                unimposed += int(np.count_nonzero(np.isnan(block).any(axis=1)))
        return {"split": split, "max": largest, "unimposed": unimposed, "total": total}

    def alpha_spikes(self) -> int:
        """integrate.count_alpha_spikes over /steps/alpha, read in blocks (0 without alpha)."""
        from ..integrate import count_alpha_spikes
        if self.multiplier_name != "alpha":
            return 0
        # alpha's rows are wider than h's: read both in blocks of the same rows, or the pairs part
        # after the first block (a run of 2^20+ steps failed)
        adaptive = "h" in self._root["steps"]
        block = min(self._block_rows("steps/alpha"), self._block_rows("steps/h") if adaptive else np.inf)
        sizes = (self._blocks("steps/h", self.steps_done, block) if adaptive
                 else itertools.repeat(float(self.attrs["h"])))
        return count_alpha_spikes(zip(self._blocks("steps/alpha", self.steps_done, block), sizes))

    def max_abs_multipliers(self) -> list[float]:
        if self.multiplier_name is None:
            return []
        name = f"steps/{self.multiplier_name}"
        with self._reading(f"/{name}"):
            width = self._root[name].shape[1]
        result = np.full(width, np.nan)   # NaN where no step imposed
        for block in self._blocks(name, self.steps_done):
            if block.size:
                result = np.fmax(result, np.fmax.reduce(np.abs(block), axis=0))
        return result.tolist()
