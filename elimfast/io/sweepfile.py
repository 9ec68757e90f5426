"""The sweep file: every run of a sweep under /runs/<label>/, in the layout of a run group.

Format ``elimfast-sweep``: root attributes as a run file's versions and date, plus
``sweep`` (the sweep file's text), ``source``, ``axes`` and ``runs_planned`` (the number
of runs of the grid; absent in files of earlier elimfast versions), and for a sweep with a
reference run its summary, ``reference_key`` (its config), ``reference_status``,
``reference_t_final``, ``reference_t_end`` and ``reference_y_final`` (--resume reads it back
instead of running it again). Each run's group is written
by ``layout.create_run_group``, the function that writes a run file's root, so it holds
t, component, y, invariants/<name>, steps/..., method/... on the same dimension scales,
and a run file's attributes (config, problem, method, h, n_steps, steps_done, status,
wall_time_s, ...) plus ``label`` and ``axis_<name>`` for its coordinates. An ensemble
sweep stores /ensemble instead, block by block (``ensemblefile.py``: its layout, its done
record and its reader). ``elimfast.open_datatree(path)`` reads the file into an xarray
DataTree, one node per run (``xarray.open_datatree(path, engine="h5netcdf")`` gives the
same tree, in time that grows with the square of the runs: io/xarray_tree.py);
``RunFile("file.h5:/runs/<label>")`` and ``elimfast.load(path, run=label)`` read one run.
"""
from __future__ import annotations

import contextlib
import shlex
from pathlib import Path

import h5py
import numpy as np

from ..errors import DiskFullError, ElimfastError
from . import ensemblefile
from .layout import (FORMAT_VERSION, LIBVER, PROBLEM_FILE_DIGEST, SPACE_BASE, SPACE_FACTOR, _replace_attributes,
                     _set_attributes, append_rows, RUNS_GROUP, SWEEP_FORMAT, create_run_group, run_attributes,
                     flag_attribute, read_flag, stats_attributes, version_attributes)
from .runfile import _now
from .safety import (OutputError, _abandon, _close_quietly, _FileGuard, no_room, _one_line, _plain,
                     _publish, _temporary_path, clear_consistency_flags, consistency_flags, create_parent_directories,
                     ensure_not_busy, reopen_for_writing)


def sweep_group_name(label: str) -> str:
    """The group of a sweep run: its label with '/' (an HDF5 path separator) written as '|',
    and a label of only dots ('.', '..': not names HDF5 accepts) prefixed with '_'."""
    name = label.replace("/", "|")
    return "_" + name if not name.strip(".") else name


RUNS_PLANNED = "runs_planned"   # root attribute: how many runs the sweep has (files of elimfast before: absent)
RUN_INDEX = "run_index"         # a run's attribute: its place in the grid (files of elimfast before: absent)
SHOWN_LABELS = 4                # run labels a message lists
INTERRUPTED = "interrupted"     # in grid_sweep_runs' attributes (not stored): the writer was killed


def _listed_runs(f) -> list[tuple[str, bool, str, int]]:
    """(label, stored, status, run_index or -1) of every run group of an open sweep file, in the
    grid's order where the file records it (HDF5 lists groups by name: 'pi/240' before 'pi/30'),
    the others after them in HDF5's order."""
    runs = f[RUNS_GROUP] if RUNS_GROUP in f else {}
    listed = [(str(_plain(runs[name].attrs.get("label", name))), read_flag(runs[name].attrs, "stored"),
               str(_plain(runs[name].attrs.get("status", "?"))), int(runs[name].attrs.get(RUN_INDEX, -1)))
              for name in runs]
    listed.sort(key=lambda run: (run[3] < 0, run[3]))   # stable: HDF5's order among runs without an index
    return listed


def describe_sweep_file(path, f, *, killed: bool = False, writing: bool = False) -> str:
    """One line for a reader given a sweep file where it wants one run (``inspect``,
    ``load``, ``plot``). Says what the file holds, how to name one run, and, for a sweep that
    did not end, how many runs are stored and that --resume completes it; a sweep whose writer
    was killed (``killed``, or found so by ``interrupted``: HDF5 refuses such a file, which
    safety._open reads through its unflagged view) is called interrupted.
    ``writing``: a sweep is writing the file now (read like a killed writer's: a snapshot of
    what its last flush wrote); HDF5 lets no other program open it until the sweep ends."""
    if ensemblefile.GROUP in f:
        return (f"{path}: the file of an ensemble sweep (no single runs); read it with elimfast inspect {path} or "
                f"elimfast.load('{path}')")
    stored = [label for label, done, _, _ in _listed_runs(f) if done]
    planned = int(f.attrs.get(RUNS_PLANNED, 0))
    count = f"{len(stored)} of {planned}" if planned else f"{len(stored)}"
    shown = ", ".join(stored[:SHOWN_LABELS]) + (", ..." if len(stored) > SHOWN_LABELS else "")
    listing = f"{count} runs stored" + (f" ({shown})" if shown else "")
    source = str(_plain(f.attrs.get("source", ""))) or "SWEEP.yaml"
    resume = f"complete it with elimfast sweep {source} -o {path} --resume"
    # quoted as a shell needs it: labels have spaces, parentheses and '*' (Table 1's 'EHBVM(12,3) L1,L2/pi/120')
    example = shlex.quote(f"{path}:/runs/{stored[0]}" if stored else f"{path}:/runs/<label>")
    if writing:
        return (f"{path}: a sweep is writing it: {listing} so far; HDF5 lets other programs read it when the "
                "sweep ends (elimfast sweep prints a line as each run is stored)")
    if killed or interrupted(path):
        return f"{path}: an interrupted sweep (its writer was killed): {listing}; {resume}; read one run as {example}"
    if planned and len(stored) < planned:
        return f"{path}: an incomplete sweep file, not a single run: {listing}; {resume}; read one run as {example}"
    label = stored[0] if stored else "<label>"
    return (f"{path}: a sweep file, not a single run: give one of its runs as {example} (in Python: "
            f"elimfast.load('{path}', run='{label}')); {listing}")


def interrupted(path) -> bool:
    """Whether a grid sweep's file was left by a writer that was killed: HDF5's open-for-writing
    flag is still set (readers get here only for a writer that is gone: one alive holds HDF5's
    lock, and safety._open says it is busy). It is read as it is (safety._open_interrupted_sweep)."""
    return bool(consistency_flags(path) & 1)


def sweep_file_source(path) -> str | None:
    """The sweep file (its stored ``source``, or 'SWEEP.yaml') that wrote ``path``, when ``path``
    is a sweep's file (grid or ensemble); None for anything else, or a file that cannot be read."""
    from .safety import _open
    try:
        with _open(Path(path)) as f:
            if str(_plain(f.attrs.get("format", ""))) != SWEEP_FORMAT:
                return None
            return str(_plain(f.attrs.get("source", ""))) or "SWEEP.yaml"
    except Exception:   # noqa: BLE001 -- not readable as a sweep file: the caller's own reader says what it is
        return None


def grid_sweep_runs(path) -> tuple[dict, list[tuple[str, bool, str]]] | None:
    """(root attributes, [(label, stored, status)] in the grid's order) of a grid sweep's file, or None
    for anything else (a run file, an ensemble sweep's file, a file that cannot be opened:
    the caller's own reader says what). ``inspect`` summarises a sweep file from this. The
    attributes hold INTERRUPTED too: its writer was killed (``interrupted``)."""
    from .safety import _open
    try:
        with _open(Path(path)) as f:
            if str(_plain(f.attrs.get("format", ""))) != SWEEP_FORMAT or ensemblefile.GROUP in f:
                return None
            attrs = {key: _plain(value) for key, value in f.attrs.items() if key != "sweep"}
            listed = _listed_runs(f)
        attrs[INTERRUPTED] = interrupted(path)
        return attrs, [run[:3] for run in listed]
    except Exception:   # noqa: BLE001 -- damaged, busy, not HDF5: RunFile reports it
        return None


REFERENCE_FIELDS = ("key", "status", "t_final", "t_end", "y_final")   # SweepWriter.add_reference
REFERENCE_KEY = "reference_key"


class SweepWriter:
    """One HDF5 file for a whole sweep: /runs/<label>/ per run, in the layout of a run file.

    Each run's group holds t, y, invariants/<name>, steps/iterations, steps/alpha or
    steps/lambda, method/..., and the run attributes of a run file (config, problem,
    method, h, n_steps, steps_done, status, wall_time_s, ...) plus ``label`` and the
    run's coordinates on the sweep's axes. There is no /state: a sweep run is not
    resumable on its own; rerun the sweep. Runs are written and flushed as they finish,
    so a killed sweep keeps every finished run. The file is built under a temporary
    name and renamed into place (an existing file another process uses is refused).

    An ensemble sweep (``ensemble=(run, states, config_text)``: an
    elimfast.ensemble.EnsembleRun, its initial states and its resolved config) gets
    /ensemble with every dataset at its final shape before the file is published; the
    file is then written in SWMR mode, block by block (``add_ensemble_rows``), and
    completed by ``finish_ensemble``. ``ensemble_todo``: the [start, stop) ranges of
    trajectories not stored yet (all of them, or what a resumed file lacks).
    """

    def __init__(self, path, *, sweep_text: str, attributes: dict | None = None, overwrite: bool = True,
                 resume: bool = False, ensemble: tuple | None = None, accept_edit=None):
        self.path = Path(path)
        self.complete: dict[str, str] = {}   # label -> group name of the runs a resumed file already holds
        self.ensemble_todo: list[tuple[int, int]] | None = None
        self.edited = False                  # a resumed grid sweep whose sweep file was edited (accept_edit)
        self.written_by = None               # resumed: the sweep file that wrote it (its source attribute)
        self.stored_reference: dict | None = None   # resumed: the reference run's summary (add_reference)
        self._ensemble = None
        self._kept = "the runs stored before this one are in the file" if ensemble is None else \
            "the trajectories marked stored before it are in the file (--resume runs the rest)"
        if resume and self.path.exists():
            self._reopen(sweep_text, ensemble, accept_edit, attributes or {})
            return
        create_parent_directories(self.path)
        ensure_not_busy(self.path)
        temporary = _temporary_path(self.path)
        try:
            self._file = h5py.File(temporary, "w", libver=LIBVER)
        except OSError as err:
            with contextlib.suppress(OSError):
                temporary.unlink()
            raise OutputError(f"{self.path}: cannot create: {_one_line(err)}") from None
        self._guard = None
        try:
            self._guard = _FileGuard(temporary)
            self._guard.reserve(SPACE_BASE + len(sweep_text)
                                + (0 if ensemble is None else ensemblefile.bytes_on_disk(ensemble[0], ensemble[1])))
            _set_attributes(self._file, {
                **version_attributes(), "format": SWEEP_FORMAT, "format_version": FORMAT_VERSION,
                "created": _now(),
                "sweep": sweep_text, **(attributes or {})})
            self._runs = self._file.create_group(RUNS_GROUP)
            if ensemble is not None:
                self._ensemble = ensemblefile.create(self._file, *ensemble)
                self.ensemble_todo = [(0, ensemble[1].shape[0])]
            self._file.flush()
            _publish(temporary, self.path, overwrite)
            if ensemble is not None:
                self._file.swmr_mode = True   # flushes; from here on the file on disk is always consistent
        except DiskFullError as err:
            _close_quietly(self._file, self._guard, temporary)
            room = no_room(err)
            raise DiskFullError(f"{self.path}: {room.sentence}; {room.fix}, or write the sweep elsewhere") from None
        except BaseException:
            _close_quietly(self._file, self._guard, temporary)
            raise

    def _reopen(self, sweep_text: str, ensemble: tuple | None, accept_edit, attributes: dict) -> None:
        """Open an existing sweep file to add the runs it lacks (``--resume``): the file must
        hold the same sweep (its stored text), and every run that is not marked stored and
        complete (failed, or cut off by a kill) is removed so that it runs again. An
        ensemble's file must hold the same ensemble (``ensemblefile.check_resumable``); its
        trajectories not marked stored are the ones to run.

        A grid sweep's file written by another text is continued when ``accept_edit``, given
        {label: stored config text} of its complete runs, returns {label: place in the edited grid}
        (it raises OutputError for an edit that would change those runs: the rule is the sweep's,
        elimfast.sweep.solver_only_edit); the file then takes the new text, ``attributes`` (the
        grid's size, its axes) and the kept runs' new places, and ``edited`` is set. An ensemble's
        ``accept_edit`` (elimfast.sweep.same_trajectories) is given the stored sweep text and the
        stored ensemble's config (None: no /ensemble yet) and raises OutputError for an edit that
        changes the trajectories; an edit it takes (comments, description) is stored likewise."""
        ensure_not_busy(self.path)
        if consistency_flags(self.path):   # a writer killed before closing it (HDF5 refuses such a file)
            try:
                clear_consistency_flags(self.path)
            except (OSError, ElimfastError) as err:
                raise OutputError(f"{self.path}: cannot resume ({_one_line(err)}); start again with "
                                  "--overwrite") from None
        try:
            self._file = h5py.File(self.path, "a", libver=LIBVER)
        except OSError as err:
            raise OutputError(f"{self.path}: cannot resume: HDF5 cannot open it ({_one_line(err)[:160]}); start "
                              "again with --overwrite") from None
        self._guard = None
        try:
            self._guard = _FileGuard(self.path)
            if not self._guard.lock():
                raise OutputError(f"{self.path}: is being written by another process; stop it first or choose "
                                  "another output file")
            if str(_plain(self._file.attrs.get("format", ""))) != SWEEP_FORMAT or RUNS_GROUP not in self._file:
                raise OutputError(f"{self.path}: not an elimfast sweep file, so --resume cannot continue it; "
                                  "choose another output file or pass --overwrite")
            holds_ensemble = ensemblefile.GROUP in self._file
            if holds_ensemble != (ensemble is not None):
                # a grid sweep's runs written into an ensemble's file (or the reverse) mixed the two: the
                # file had no complete grid runs, so a grid sweep took it for an edit of itself
                raise OutputError(f"{self.path}: holds {'an ensemble sweep' if holds_ensemble else 'a grid sweep'}, "
                                  f"and this is {'an ensemble' if ensemble is not None else 'a grid'} sweep: "
                                  "--resume continues the sweep that wrote the file; choose another output file, "
                                  "or pass --overwrite to replace it")
            stored_text = str(_plain(self._file.attrs.get("sweep", "")))
            edited = stored_text != sweep_text
            self.written_by = str(_plain(self._file.attrs.get("source", ""))) or None
            if ensemble is not None and accept_edit is not None:
                # even an unedited text: its base config is a file of its own, which may have changed
                stored = self._file[ensemblefile.GROUP].attrs.get("config") if holds_ensemble else None
                accept_edit(stored_text, None if stored is None else str(_plain(stored)))
            elif edited and accept_edit is None:
                raise OutputError(f"{self.path}: was written by a different sweep file (the stored sweep text "
                                  "differs); pass --overwrite to start again, or choose another output file")
            self._runs = self._file[RUNS_GROUP]
            complete, digests = {}, {}
            for name in self._runs:
                run = self._runs[name].attrs
                label = str(_plain(run.get("label", "")))
                if label and read_flag(run, "stored") and str(_plain(run.get("status"))) == "complete":
                    complete[label] = (name, str(_plain(run.get("config", ""))))
                    if PROBLEM_FILE_DIGEST in run:
                        digests[label] = str(_plain(run[PROBLEM_FILE_DIGEST]))
            if edited and ensemble is not None:   # an edit accepted above: the file takes the new text
                _replace_attributes(self._file, {"sweep": sweep_text, **attributes})
                self.edited = True
            elif ensemble is None and (edited or accept_edit is not None):
                # Before anything is removed: a refused edit leaves the file as it was. An unedited
                # text too: a config it names is a file of its own, which may have changed, and the
                # kept runs and the new ones would then come from different configs unsaid.
                run_index = accept_edit({label: config for label, (_, config) in complete.items()},
                                        written_by=self.written_by, digests=digests)
                if edited:
                    _replace_attributes(self._file, {"sweep": sweep_text, **attributes})
                    for label, (name, _) in complete.items():   # the kept runs' places in the edited grid
                        _replace_attributes(self._runs[name], {RUN_INDEX: int(run_index[label])})
                    self.edited = True
            for name in list(self._runs):
                if name not in {group for group, _ in complete.values()}:
                    del self._runs[name]
            self.complete = {label: name for label, (name, _) in complete.items()}
            if REFERENCE_KEY in self._file.attrs:
                attrs = self._file.attrs
                self.stored_reference = {name: _plain(attrs[f"reference_{name}"]) for name in REFERENCE_FIELDS
                                         if f"reference_{name}" in attrs}
            if ensemble is not None:
                self._resume_ensemble(ensemble)
            self._file.flush()
            if ensemble is not None:
                self._file.swmr_mode = True
        except (OutputError, DiskFullError):
            _close_quietly(self._file, self._guard, None)
            raise
        except (OSError, RuntimeError, KeyError) as err:
            _close_quietly(self._file, self._guard, None)
            raise OutputError(f"{self.path}: cannot resume: the file is damaged ({_one_line(err)[:160]}); start "
                              "again with --overwrite") from None

    def _resume_ensemble(self, ensemble: tuple) -> None:
        run, states, config_text = ensemble
        if ensemblefile.GROUP not in self._file:   # an earlier elimfast's, killed before it wrote the ensemble
            self._guard.reserve(SPACE_BASE + ensemblefile.bytes_on_disk(run, states))
            self._ensemble = ensemblefile.create(self._file, run, states, config_text)
        else:
            self._ensemble = self._file[ensemblefile.GROUP]
            ensemblefile.check_resumable(self.path, self._ensemble, run, states, config_text)
        self.ensemble_todo = ensemblefile.unstored_ranges(self._ensemble)

    @property
    def ensemble_complete(self) -> bool:
        """/ensemble is marked complete (every trajectory stored and the totals written)."""
        return str(_plain(self._ensemble.attrs.get("status", ""))) == ensemblefile.STATUS_COMPLETE

    def add_ensemble_rows(self, start: int, stop: int, rows: dict) -> None:
        """Store the trajectories [start, stop) of the ensemble (``rows``: ensemble.ROW_ARRAYS
        and invariant_errors): their data, flushed, then their done record, flushed."""
        with self._writing():
            ensemblefile.write_rows(self._ensemble, start, stop, rows)
            self._file.flush()
            ensemblefile.mark_stored(self._ensemble, start, stop)
            self._file.flush()

    def finish_ensemble(self, *, threads: int, ok_status: int) -> None:
        """Mark the ensemble complete, once every trajectory is stored (``ensemblefile.finish``)."""
        with self._writing():
            self._file.close()   # attributes change only outside SWMR mode: reopen the file normally
            self._file = reopen_for_writing(self.path, LIBVER)   # past a watching reader's lock
            self._ensemble = self._file[ensemblefile.GROUP]
            ensemblefile.finish(self._ensemble, threads=threads, ok_status=ok_status)
            self._file.flush()

    def forget(self, label: str) -> None:
        """Remove a stored run of a resumed file, so that it runs (and is stored) again."""
        name = self.complete.pop(label, None)
        if name is not None:
            with self._writing():
                del self._runs[name]
                self._file.flush()

    def _writing(self):
        """HDF5 failing a write (a full disk): abandon the file (see _ABANDONED) and say so."""
        return _SweepWriting(self)

    def _reserve(self, arrays) -> None:
        """Room for a run's arrays before HDF5 writes any of them: DiskFullError leaves the
        file as the last flush left it (closed normally, every stored run in it)."""
        n_bytes = sum(getattr(value, "nbytes", 0) for value in arrays)
        try:
            self._guard.reserve(SPACE_BASE + SPACE_FACTOR * n_bytes)
        except DiskFullError as err:
            raise DiskFullError(f"{self.path}: {no_room(err).sentence}; the runs stored before this one are in the "
                                "file") from None

    def add_reference(self, *, key: str, status: str, y_final, t_final: float, t_end: float | None) -> None:
        """Store the summary of a grid sweep's reference run (its errors' y_final) as root attributes
        reference_<field>, so that --resume need not run it again (a user trial's resume ran its
        reference again, 23 s): ``key`` says which reference it is (elimfast.sweep.reference_key);
        stored_reference gives them back on resume."""
        values = {"key": key, "status": status, "t_final": float(t_final),
                  "t_end": float("nan") if t_end is None else float(t_end),
                  "y_final": np.asarray([] if y_final is None else y_final, dtype=np.float64)}
        with self._writing():
            # the key last: a kill between the writes leaves no key, and the reference runs again
            _replace_attributes(self._file, {f"reference_{name}": values[name] for name in REFERENCE_FIELDS
                                             if name != "key"})
            self._file.flush()
            _replace_attributes(self._file, {REFERENCE_KEY: key})
            self._file.flush()

    def add_run(self, label: str, result=None, *, status: str, config_text: str, coordinates: dict,
                wall_time_s: float = 0.0, group_name: str | None = None, t_end: float | None = None,
                file_attributes: dict | None = None, run_index: int | None = None) -> None:
        """Store one finished (or failed) sweep run: ``result`` is the Result of the run (the one
        ``integrate`` returns; its arrays go into the group through ``layout.create_run_group``,
        as a run file's do), or None for a run that never started (a bad config). ``t_end``: the
        config's end, and ``file_attributes``: an adaptive-kernel run's step control settings
        (AdaptiveIntegration.file_attributes), as a run file stores them; without ``t_end``, a
        fixed-step run's t0 + n_steps h. ``run_index``: the run's place in the sweep's grid (readers
        list the runs in that order; HDF5 lists them by name)."""
        arrays = () if result is None else (result.t, result.y, result.iterations, *result.invariants.values())
        self._reserve(arrays)
        extra = dict(file_attributes or {})
        if run_index is not None:
            extra[RUN_INDEX] = int(run_index)
        with self._writing():
            self._add_run(label, result, status, config_text, coordinates, wall_time_s, group_name, t_end, extra)

    def _add_run(self, label, result, status, config_text, coordinates, wall_time_s, group_name, t_end,
                 file_attributes) -> None:
        import yaml

        group = self._runs.create_group(group_name or sweep_group_name(label))
        attributes = {"label": label, "status": status, "wall_time_s": float(wall_time_s), "config": config_text,
                      **{f"axis_{axis}": value for axis, value in coordinates.items()}}
        if result is None:
            _set_attributes(group, {**attributes, **file_attributes, "steps_done": 0, "stored": True})
            self._file.flush()
            return
        try:
            resolved = yaml.safe_load(config_text) or {}
        except yaml.YAMLError:
            resolved = {}
        integration = resolved.get("integration") or {}
        output = resolved.get("output") or {}
        t0 = (float(result.t0) if getattr(result, "t0", None) is not None   # the first sample may be later
              else float(integration.get("t0", result.t[0] if result.t.size else 0.0)))
        # as a run file: an adaptive run's n_steps is 0, not known in advance (its steps_done says how many)
        n_steps = 0 if file_attributes.get("step_control", "fixed") != "fixed" else result.n_steps
        multipliers = result.alpha if result.alpha is not None else result.lam
        name = "lambda" if result.lam is not None else "alpha" if result.alpha is not None and \
            result.alpha.shape[1] else None
        datasets = create_run_group(group, problem=result.problem, method=result.method, conserve=result.conserve,
                                    n_multipliers=0 if multipliers is None else multipliers.shape[1],
                                    multiplier=name, adaptive_steps=result.step_h is not None,
                                    events={event: (resolved.get("events") or {}).get(event) or {}
                                            for event in result.events}, scales=result.invariant_scales(),
                                    values_at_t0=result.initial_invariants(), attributes={
            **attributes, **run_attributes(result.problem, result.method, h=result.h, t0=t0, n_steps=n_steps,
                                           t_end=t_end, output_every=int(output.get("every", 1)),
                                           conserve=result.conserve),
            **file_attributes, **stats_attributes(result.stats),
            "steps_done": result.steps_done})
        names = ("H",) + tuple(result.problem.invariant_names)
        done = result.steps_done
        append_rows(datasets, t=result.t, y=result.y,
                    invariants=np.column_stack([result.invariants[n] for n in names]),
                    iterations=result.iterations[:done], substeps=result.substeps[:done],
                    multipliers=None if multipliers is None else multipliers[:done],
                    step_t=result.step_t, step_h=result.step_h, **_event_rows(result))
        if result.iterations.size > done:
            group.attrs["failed_step_iterations"] = int(result.iterations[done])
        # The state after the last completed step: the last sample is not it when output.times end
        # before t_end (a user trial: a resumed sweep's errors, taken from the last sample, were 2.5
        # where the run's were 1e-9). archive.load reads them back.
        group.attrs["t_final"] = float(result.t_final)
        group.attrs["y_final"] = np.asarray(result.y_final, dtype=np.float64)
        self._file.flush()
        # Written only once the run's data are on disk: --resume keeps the runs marked so.
        group.attrs["stored"] = flag_attribute(True)
        self._file.flush()

    def close(self) -> None:
        try:
            if not getattr(self, "abandoned", False) and self._file.id.valid:
                self._file.close()
        finally:
            if self._guard is not None:
                self._guard.close()


class _SweepWriting:
    def __init__(self, writer: SweepWriter):
        self.writer = writer

    def __enter__(self):
        if getattr(self.writer, "abandoned", False):
            raise OutputError(f"{self.writer.path}: an earlier write failed; {self.writer._kept}")
        return self

    def __exit__(self, kind, err, traceback):
        if kind is not None and issubclass(kind, (OSError, RuntimeError)) and not issubclass(kind, ElimfastError):
            self.writer.abandoned = True
            _abandon(self.writer._file, None, keep=self.writer)
            room = no_room(err)
            if room is not None:
                raise DiskFullError(f"{self.writer.path}: {room.sentence}; {self.writer._kept}") from None
            raise OutputError(f"{self.writer.path}: cannot write ({_one_line(err)[:200]}); {self.writer._kept}") \
                from None
        return False


def _event_rows(result) -> dict:
    """A Result's events as append_rows takes them (one table, an index per row)."""
    if not result.events:
        return {}
    index = np.concatenate([np.full(record.t.size, i, dtype=np.int64)
                            for i, record in enumerate(result.events.values())])
    return {"event_index": index, "event_t": np.concatenate([r.t for r in result.events.values()]),
            "event_y": np.concatenate([r.y for r in result.events.values()])}
