"""The HDF5 run file: writer (streaming, crash-safe, resumable) and reader. The only module importing h5py.

Layout (format ``elimfast-run``, version 1; every dataset chunked, gzip-compressed with
the shuffle filter, and extended as the run goes):

    /t                      (samples,)           time of each stored sample
    /y                      (samples, 2m)        state; attribute ``coordinates`` (q names, then p names)
    /invariants/H           (samples,)           the Hamiltonian at each sample
    /invariants/<name>      (samples,)           every invariant of the problem; attribute ``imposed``
    /steps/iterations       (steps_done,) int32  fixed-point iterations of each step
    /steps/alpha            (steps_done, nu)     ELIM/EHBVM with nu >= 1 imposed invariants
    /steps/lambda           (steps_done, nu+1)   LIM/GHBVM (H first, then the imposed invariants)
    /method/A, b, c         the Runge-Kutta form (all but LIM/GHBVM; for ELIM/EHBVM the
                            underlying HBVM(k,s) tableau, i.e. eta = 1: attribute ``tableau``)
    /method/quadrature_nodes, quadrature_weights                      k-point Gauss-Legendre on [0, 1]
    /method/invariant_quadrature_nodes, invariant_quadrature_weights  the r points (ELIM/LIM)
    /state/...              what resume needs, rewritten after every flushed chunk:
                            y, y_comp (Kahan compensation), clock = [t, its compensation],
                            coef (s, 2m) last step's coefficients, multipliers, steps_done,
                            n_samples, wall_time_s, kernel_time_s

Root attributes: elimfast_version, numba_version, numpy_version, h5py_version,
hdf5_version, created (UTC, ISO 8601), config (the resolved YAML), problem, method,
family, r, k, s, h, t0, t_end, n_steps, output_every, conserve, steps_done, status
(running | complete | interrupted | failed: <reason>), wall_time_s, kernel_time_s,
format = 'elimfast-run', format_version.

Crash safety. The file is written in HDF5's single-writer/multiple-reader (SWMR) mode,
whose ordered metadata writes keep the file consistent at every instant: a run killed
with SIGKILL leaves a file whose flushed chunks are all readable. (Without SWMR, 8 of
25 files killed during a stress test of appends had unreadable or wrong flushed data.)
Root attributes cannot change in SWMR mode, so they are final only once the run ends
(the writer then reopens the file normally); while a run is going, or after a kill,
``status`` still says ``running`` and /state holds the truth. After a kill the
superblock keeps its "open for writing" flags: open such a file with
``h5py.File(path, "r", swmr=True)`` (``elimfast inspect`` does this itself), or clear
the flags with ``h5clear -s``; ``elimfast run ... --resume`` clears them and continues.
Data rows beyond /state/n_samples and /state/steps_done may exist after a kill; they
belong to the chunk being written and are dropped by resume.
"""
from __future__ import annotations

import datetime
import math
import os
import socket
import struct
import tempfile
from pathlib import Path

import h5py
import numpy as np

from ..errors import ElimfastError

FORMAT = "elimfast-run"
FORMAT_VERSION = 1
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
STATUS_RUNNING = "running"
STATUS_COMPLETE = "complete"
STATUS_INTERRUPTED = "interrupted"
FAILED_PREFIX = "failed: "


class OutputError(ElimfastError):
    """The output file cannot be created, overwritten, resumed or read as asked."""


class NotAnElimfastFile(OutputError):
    """The file is HDF5 (or not even that) but was not written by elimfast."""


# --- paths -------------------------------------------------------------------------------
def check_output_path(path, *, overwrite: bool = False, resume: bool = False) -> Path:
    """Fail early (before any computation) if a run could not write ``path``.

    Missing parent directories are fine when they can be created (the writer creates
    them); an existing file needs ``overwrite`` or ``resume``. Writability is tested by
    doing (opening the file for update, or creating and removing a probe file), since
    permission bits say nothing for root or on read-only file systems.
    """
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a directory; give a file name such as {path / 'run.h5'}")
    if path.exists():
        if not (overwrite or resume):
            raise OutputError(f"{path}: already exists; pass --overwrite to replace it or --resume to continue it")
        try:
            with open(path, "r+b"):
                pass
        except OSError as err:
            raise OutputError(f"{path}: not writable ({err.strerror}); choose another output path") from None
        return path
    ancestor = path.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputError(f"{path}: {ancestor} is a file, not a directory; choose another output path")
    try:
        handle, probe = tempfile.mkstemp(prefix=".elimfast-probe-", dir=ancestor)
        os.close(handle)
        os.unlink(probe)
    except OSError as err:
        raise OutputError(f"{path}: cannot create files in {ancestor} ({err.strerror}); "
                          "choose another output path") from None
    return path


# --- SWMR consistency flags --------------------------------------------------------------
_MASK = 0xFFFFFFFF
_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _rot(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _MASK


def lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 ``hashlittle``: HDF5's metadata checksum (H5checksum.c)."""
    length = len(data)
    a = b = c = (0xDEADBEEF + length + initval) & _MASK
    i = 0
    while length > 12:
        a = (a + int.from_bytes(data[i:i + 4], "little")) & _MASK
        b = (b + int.from_bytes(data[i + 4:i + 8], "little")) & _MASK
        c = (c + int.from_bytes(data[i + 8:i + 12], "little")) & _MASK
        a = (a - c) & _MASK; a ^= _rot(c, 4); c = (c + b) & _MASK      # noqa: E702 (lookup3 "mix")
        b = (b - a) & _MASK; b ^= _rot(a, 6); a = (a + c) & _MASK      # noqa: E702
        c = (c - b) & _MASK; c ^= _rot(b, 8); b = (b + a) & _MASK      # noqa: E702
        a = (a - c) & _MASK; a ^= _rot(c, 16); c = (c + b) & _MASK     # noqa: E702
        b = (b - a) & _MASK; b ^= _rot(a, 19); a = (a + c) & _MASK     # noqa: E702
        c = (c - b) & _MASK; c ^= _rot(b, 4); b = (b + a) & _MASK      # noqa: E702
        length -= 12
        i += 12
    if length == 0:
        return c
    tail = data[i:i + length] + bytes(12 - length)
    a = (a + int.from_bytes(tail[0:4], "little")) & _MASK
    b = (b + int.from_bytes(tail[4:8], "little")) & _MASK
    c = (c + int.from_bytes(tail[8:12], "little")) & _MASK
    c ^= b; c = (c - _rot(b, 14)) & _MASK      # noqa: E702 (lookup3 "final")
    a ^= c; a = (a - _rot(c, 11)) & _MASK      # noqa: E702
    b ^= a; b = (b - _rot(a, 25)) & _MASK      # noqa: E702
    c ^= b; c = (c - _rot(b, 16)) & _MASK      # noqa: E702
    a ^= c; a = (a - _rot(c, 4)) & _MASK       # noqa: E702
    b ^= a; b = (b - _rot(a, 14)) & _MASK      # noqa: E702
    c ^= b; c = (c - _rot(b, 24)) & _MASK      # noqa: E702
    return c


def _superblock(path) -> tuple[bytearray, int]:
    """The version 2/3 superblock at offset 0 and the offset of its checksum."""
    with open(path, "rb") as handle:
        raw = bytearray(handle.read(64))
    if raw[:8] != _SIGNATURE:
        raise NotAnElimfastFile(f"{path}: not an HDF5 file (no HDF5 signature at offset 0)")
    version, size_of_offsets = raw[8], raw[9]
    if version not in (2, 3) or size_of_offsets not in (2, 4, 8):
        raise OutputError(f"{path}: HDF5 superblock version {version} has no consistency flags to clear")
    return raw, 12 + 4 * size_of_offsets


def consistency_flags(path) -> int:
    """The superblock's file-consistency flags (1: open for writing, 4: SWMR writing)."""
    try:
        raw, _ = _superblock(path)
    except OutputError:
        return 0
    return raw[11]


def clear_consistency_flags(path) -> None:
    """What ``h5clear -s`` does: zero the flags a killed writer left, fix the checksum.

    Spec: HDF5 File Format Specification, superblock versions 2 and 3 (byte 11 holds the
    flags; a lookup3 checksum of the preceding bytes follows the four addresses).
    """
    raw, end = _superblock(path)
    stored = struct.unpack("<I", raw[end:end + 4])[0]
    if lookup3(bytes(raw[:end])) != stored:
        raise OutputError(f"{path}: the HDF5 superblock checksum does not match; not touching the file")
    raw[11] = 0
    raw[end:end + 4] = struct.pack("<I", lookup3(bytes(raw[:end])))
    with open(path, "r+b") as handle:
        handle.write(raw[:end + 4])
        handle.flush()
        os.fsync(handle.fileno())


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _open(path, mode: str) -> h5py.File:
    """Open an existing file; read access falls back to SWMR reading for a killed run."""
    path = Path(path)
    if not path.exists():
        raise OutputError(f"{path}: no such file")
    if not h5py.is_hdf5(path):
        raise NotAnElimfastFile(f"{path}: not an HDF5 file, so not an elimfast run file")
    try:
        return h5py.File(path, mode, libver=LIBVER) if mode != "r" else h5py.File(path, "r")
    except OSError as err:
        if mode == "r" and consistency_flags(path):
            return h5py.File(path, "r", swmr=True)
        raise OutputError(f"{path}: cannot open: {_one_line(err)}") from None


def _one_line(err) -> str:
    return " ".join(str(err).split())


# --- the writer --------------------------------------------------------------------------
def _chunk_rows(row_bytes: int) -> int:
    return max(MIN_CHUNK_ROWS, CHUNK_BYTES // max(row_bytes, 1))


def _growing(group, name: str, width: int | None, dtype) -> "_Growing":
    """An empty dataset, chunked and compressed, resizable along its first axis.

    Created through h5py's low-level API: the high-level one re-derives the filter
    pipeline for every dataset and costs more than writing a whole short run.
    """
    dtype = np.dtype(dtype)
    tail = () if width is None else (int(width),)
    rows = _chunk_rows(dtype.itemsize * (width or 1))
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk((rows,) + tail)
    dcpl.set_shuffle()
    dcpl.set_deflate(GZIP_LEVEL)
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


def multiplier_name(integration) -> str | None:
    """'alpha' (ELIM/EHBVM imposing invariants), 'lambda' (LIM/GHBVM) or None."""
    from ..kernels.stepper import FAMILY_LIM
    if integration.method.kernel_family == FAMILY_LIM:
        return "lambda"
    return "alpha" if integration.multipliers.size else None


def version_attributes() -> dict:
    import numba

    from .. import __version__
    return {"elimfast_version": __version__, "numba_version": numba.__version__,
            "numpy_version": np.__version__, "h5py_version": h5py.__version__,
            "hdf5_version": h5py.version.hdf5_version}


class RunWriter:
    """Appends the chunks of one run to its file and keeps /state current.

    ``create`` starts a new file, ``resume`` reopens one and returns the saved state.
    After each ``append`` call ``save_state``: the data are flushed first and the state
    second, so a state on disk never refers to data that did not reach it. ``finish``
    writes the final root attributes and closes the file.
    """

    def __init__(self, path: Path, file: h5py.File, datasets: dict):
        self.path = path
        self._file = file
        # Handles kept: h5py's name lookups cost more than the writes of a chunk.
        self._t, self._y = datasets["t"], datasets["y"]
        self._invariants = datasets["invariants"]    # in the column order of Chunk.invariants
        self._iterations = datasets["iterations"]
        self._multipliers = datasets.get("multipliers")
        self._state = datasets["state"]
        self.failed_step_iterations = None

    @classmethod
    def _from_file(cls, path: Path, f: h5py.File) -> "RunWriter":
        steps = f["steps"]
        multipliers = next((steps[name] for name in ("alpha", "lambda") if name in steps), None)
        order = [str(name) for name in _plain(f["invariants"].attrs["order"])]
        return cls(path, f, {
            "t": _Growing(f["t"].id), "y": _Growing(f["y"].id),
            "invariants": [_Growing(f["invariants"][name].id) for name in order],
            "iterations": _Growing(steps["iterations"].id),
            "multipliers": _Growing(multipliers.id) if multipliers is not None else None,
            "state": {name: dataset.id for name, dataset in f["state"].items()}})

    # --- opening ---
    @classmethod
    def create(cls, path, integration, *, config_text: str, t_end: float | None = None,
               attributes: dict | None = None) -> "RunWriter":
        """Create (or truncate) ``path`` with the layout, the run's metadata and its sample at t0."""
        path = Path(path)
        run, problem, method = integration, integration.problem, integration.method
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            f = h5py.File(path, "w", libver=LIBVER)
        except OSError as err:
            raise OutputError(f"{path}: cannot create: {_one_line(err)}") from None
        try:
            mult = multiplier_name(run)
            names = ("H",) + tuple(problem.invariant_names)
            _set_attributes(f, {
                **version_attributes(), "format": FORMAT, "format_version": FORMAT_VERSION,
                "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "config": config_text, "problem": problem.name, "method": method.name, "family": method.family,
                "r": method.r, "k": method.k, "s": method.s, "h": run.h, "t0": run.t0,
                "t_end": float(t_end) if t_end is not None else run.t0 + run.n_steps * run.h,
                "n_steps": run.n_steps, "output_every": run.store_every, "conserve": list(run.conserve),
                "steps_done": 0, "status": STATUS_RUNNING, "wall_time_s": 0.0, "kernel_time_s": 0.0,
                **(attributes or {})})
            datasets = {"t": _growing(f, "t", None, "f8"), "y": _growing(f, "y", run.y.size, "f8")}
            _set_attributes(datasets["y"], {"coordinates": list(problem.coordinate_names)})
            inv = f.create_group("invariants")
            _set_attributes(inv, {"order": list(names)})
            datasets["invariants"] = [_growing(inv, name, None, "f8") for name in names]
            for name, dataset in zip(names, datasets["invariants"]):
                _set_attributes(dataset, {"imposed": name in run.conserve})
            steps = f.create_group("steps")
            datasets["iterations"] = _growing(steps, "iterations", None, "i4")
            if mult is not None:
                datasets["multipliers"] = _growing(steps, mult, run.multipliers.size, "f8")
                imposed = ("H",) + run.conserve if mult == "lambda" else run.conserve
                _set_attributes(datasets["multipliers"], {"invariants": list(imposed)})
            _write_method(f.create_group("method"), method)

            state = f.create_group("state")
            initial = dict(run.state(), n_samples=np.int64(1), wall_time_s=0.0, kernel_time_s=0.0)
            datasets["state"] = {key: _small_dataset(state, key, value) for key, value in initial.items()}
            _mark_writer(state)

            writer = cls(path, f, datasets)
            writer.append(integration.initial_chunk())
            f.swmr_mode = True   # flushes: from here on the file on disk is always consistent
            return writer
        except BaseException:
            f.close()
            raise

    @classmethod
    def resume(cls, path) -> tuple["RunWriter", dict]:
        """Reopen a run for writing; return (writer, saved) with saved = /state and the root attributes.

        A file left by a killed writer (SWMR flags still set) is repaired first,
        unless that writer's process is still alive on this machine.
        """
        path = Path(path)
        if not path.exists():
            raise OutputError(f"{path}: no such file to resume")
        if not h5py.is_hdf5(path):
            raise NotAnElimfastFile(f"{path}: not an HDF5 file, so not an elimfast run to resume")
        if consistency_flags(path):
            with h5py.File(path, "r", swmr=True) as f:
                _require_ours(path, f)
                pid = int(f["state"].attrs.get("writer_pid", 0))
                host = str(f["state"].attrs.get("writer_host", ""))
            if pid and host == socket.gethostname() and pid != os.getpid() and _process_alive(pid):
                raise OutputError(f"{path}: still being written by process {pid}; stop it first "
                                  f"(Ctrl-C or kill {pid}), then resume")
            clear_consistency_flags(path)
        try:
            f = h5py.File(path, "r+", libver=LIBVER)
        except OSError as err:
            raise OutputError(f"{path}: cannot open for resuming: {_one_line(err)}") from None
        try:
            _require_ours(path, f)
            saved = {key: np.array(value[()]) for key, value in f["state"].items()}
            saved["steps_done"] = int(saved["steps_done"])
            saved["n_samples"] = int(saved["n_samples"])
            saved["attrs"] = {key: _plain(value) for key, value in f.attrs.items()}
            # Drop rows of the chunk that was being written when the run stopped.
            for d in _sample_datasets(f):
                d.resize(saved["n_samples"], axis=0)
            for d in f["steps"].values():
                d.resize(saved["steps_done"], axis=0)
            f.attrs["status"] = STATUS_RUNNING
            for key in ("failed_step_iterations",):
                if key in f.attrs:
                    del f.attrs[key]
            _mark_writer(f["state"])
            f.flush()
            f.swmr_mode = True
            return cls._from_file(path, f), saved
        except BaseException:
            f.close()
            raise

    # --- writing ---
    def append(self, chunk) -> None:
        """Extend every dataset by the chunk's samples and steps (not yet flushed)."""
        self._t.append(chunk.t)
        self._y.append(chunk.y)
        for column, dataset in enumerate(self._invariants):
            dataset.append(chunk.invariants[:, column])
        steps_done = len(chunk.multipliers)
        iterations = chunk.iterations
        if len(iterations) > steps_done:   # a failed step's count: kept apart, rows stay per done step
            self.failed_step_iterations = int(iterations[steps_done])
            iterations = iterations[:steps_done]
        self._iterations.append(iterations)
        if self._multipliers is not None:
            self._multipliers.append(chunk.multipliers)

    def save_state(self, state: dict, *, wall_time_s: float, kernel_time_s: float) -> None:
        """Flush the appended data, then write and flush /state (two flushes: see class doc)."""
        self._file.flush()
        values = dict(state, n_samples=self._t.rows, wall_time_s=wall_time_s, kernel_time_s=kernel_time_s)
        for key, value in values.items():
            dataset = self._state[key]
            dataset.write(h5py.h5s.ALL, h5py.h5s.ALL, np.ascontiguousarray(value, dtype=dataset.dtype))
        self._file.flush()

    def finish(self, status: str, *, steps_done: int, wall_time_s: float, kernel_time_s: float) -> None:
        """Close the SWMR session, then write the final root attributes in a normal session."""
        self._file.close()
        with h5py.File(self.path, "r+", libver=LIBVER) as f:
            f.attrs["status"] = status
            f.attrs["steps_done"] = steps_done
            f.attrs["wall_time_s"] = wall_time_s
            f.attrs["kernel_time_s"] = kernel_time_s
            if self.failed_step_iterations is not None:
                f.attrs["failed_step_iterations"] = self.failed_step_iterations

    def close(self) -> None:
        """Close without final attributes (the file stays valid, status 'running')."""
        if self._file.id.valid:
            self._file.close()


SWEEP_FORMAT = "elimfast-sweep"


def sweep_group_name(label: str) -> str:
    """The group of a sweep run: its label with '/' (an HDF5 path separator) written as '|'."""
    return label.replace("/", "|")


class SweepWriter:
    """One HDF5 file for a whole sweep: /runs/<label>/ per run, in the layout of a run file.

    Each run's group holds t, y, invariants/<name>, steps/iterations, steps/alpha or
    steps/lambda, method/..., and the run attributes of a run file (config, problem,
    method, h, n_steps, steps_done, status, wall_time_s, ...) plus ``label`` and the
    run's coordinates on the sweep's axes. There is no /state: a sweep run is not
    resumable on its own; rerun the sweep. Runs are written and flushed as they finish,
    so a killed sweep keeps every finished run.
    """

    def __init__(self, path, *, sweep_text: str, attributes: dict | None = None):
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = h5py.File(self.path, "w", libver=LIBVER)
        except OSError as err:
            raise OutputError(f"{self.path}: cannot create: {_one_line(err)}") from None
        _set_attributes(self._file, {
            **version_attributes(), "format": SWEEP_FORMAT, "format_version": FORMAT_VERSION,
            "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "sweep": sweep_text, **(attributes or {})})
        self._runs = self._file.create_group("runs")
        self._file.flush()

    def add_run(self, outcome, method, *, group_name: str | None = None) -> None:
        """Store one finished (or failed) sweep run; outcome is an elimfast.sweep.RunOutcome."""
        import yaml

        group = self._runs.create_group(group_name or sweep_group_name(outcome.label))
        resolved = outcome.resolved or {}
        attributes = {"label": outcome.label, "status": outcome.status, "steps_done": outcome.steps_done,
                      "n_steps": outcome.n_steps, "wall_time_s": outcome.wall_time,
                      "config": yaml.safe_dump(resolved, sort_keys=False, default_flow_style=None, width=100)}
        attributes.update({f"axis_{axis}": value for axis, value in outcome.coordinates.items()})
        if method is not None:
            integration = resolved.get("integration", {})
            attributes.update({"method": method.name, "family": method.family, "r": method.r, "k": method.k,
                               "s": method.s, "h": outcome.h, "t0": float(integration.get("t0", 0.0)),
                               "conserve": list(resolved.get("conserve", []))})
            problem = resolved.get("problem", {})
            attributes["problem"] = str(problem.get("builtin") or problem.get("name") or "user-defined")
            _write_method(group.create_group("method"), method)
        _set_attributes(group, attributes)
        arrays = outcome.arrays
        if arrays:
            _small_dataset(group, "t", arrays["t"])
            y = _small_dataset(group, "y", arrays["y"])
            _set_attributes(h5py.Dataset(y), {"coordinates": list(arrays["coordinate_names"])})
            invariants = group.create_group("invariants")
            names = list(arrays["invariant_names"])
            _set_attributes(invariants, {"order": names})
            imposed = set(resolved.get("conserve", []))
            for column, name in enumerate(names):
                dataset = _small_dataset(invariants, name, arrays["invariants"][:, column])
                _set_attributes(h5py.Dataset(dataset), {"imposed": name in imposed})
            steps = group.create_group("steps")
            done = outcome.steps_done
            _small_dataset(steps, "iterations", arrays["iterations"][:done].astype("i4"))
            if arrays["multipliers"].shape[1] or arrays["multiplier_name"] == "lambda":
                _small_dataset(steps, arrays["multiplier_name"], arrays["multipliers"][:done])
        self._file.flush()

    def add_ensemble(self, result, states, resolved: dict) -> None:
        """Store an ensemble sweep under /ensemble: per trajectory y0, y_final, t_final,
        iterations (totals), max_multiplier, status (0 ok), steps_done, and
        invariant_errors/<name> (max |I(t) - I(0)|); the failure reasons as an attribute."""
        import yaml

        group = self._file.create_group("ensemble")
        _set_attributes(group, {
            "problem": result.problem.name, "method": result.method.name, "h": result.h,
            "n_steps": result.n_steps, "conserve": list(result.conserve) or [""], "threads": result.n_threads,
            "config": yaml.safe_dump(resolved, sort_keys=False, default_flow_style=None, width=100),
            "failed": result.n_failed, "reasons": list(result.reasons) or [""]})
        y0 = _small_dataset(group, "y0", states)
        _set_attributes(h5py.Dataset(y0), {"coordinates": list(result.problem.coordinate_names)})
        for name in ("y_final", "t_final", "iterations", "max_multiplier", "status", "steps_done"):
            _small_dataset(group, name, getattr(result, name))
        errors = group.create_group("invariant_errors")
        for name, values in result.invariant_errors.items():
            _small_dataset(errors, name, values)
        _write_method(group.create_group("method"), result.method)
        self._file.flush()

    def close(self) -> None:
        if self._file.id.valid:
            self._file.close()


def _mark_writer(state_group) -> None:
    state_group.attrs["writer_pid"] = os.getpid()
    state_group.attrs["writer_host"] = socket.gethostname()


def _sample_datasets(f):
    yield f["t"]
    yield f["y"]
    yield from f["invariants"].values()


def _write_method(group, method) -> None:
    if method.has_runge_kutta_form:
        A, b, c = method.butcher()
        for name, table in (("A", A), ("b", b), ("c", c)):
            _small_dataset(group, name, table)
        if method.family in ("elim", "ehbvm"):
            tableau = (f"the underlying HBVM({method.k},{method.s}) tableau (eta = 1); each ELIM step scales it "
                       "with eta_j = 1 - h^(2(s-1-j)) alpha_j (spec 3)")
        else:
            tableau = f"{method.name}: A, b, c of its Runge-Kutta form"
    else:
        tableau = f"{method.name} has no fixed Runge-Kutta form (its correction acts through phi_0, spec 4)"
    _set_attributes(group, {"order": method.order, "tableau": tableau,
                            "quadrature": f"{method.k}-point Gauss-Legendre on [0, 1] for H"
                                          + (f", {method.r}-point for the invariants" if method.imposes_invariants
                                             else "")})
    _small_dataset(group, "quadrature_nodes", method.c)
    _small_dataset(group, "quadrature_weights", method.b)
    if method.imposes_invariants:
        _small_dataset(group, "invariant_quadrature_nodes", method.chat)
        _small_dataset(group, "invariant_quadrature_weights", method.bhat)


def _set_attributes(obj, values: dict) -> None:
    """Create attributes through h5py's low-level API (numbers, strings, lists of strings, arrays)."""
    for name, value in values.items():
        if isinstance(value, str) or (isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)):
            data = np.array(value, dtype=h5py.string_dtype())
        else:
            data = np.asarray(value)
        space = h5py.h5s.create(h5py.h5s.SCALAR) if data.ndim == 0 else h5py.h5s.create_simple(data.shape)
        attribute = h5py.h5a.create(obj.id, name.encode(), h5py.h5t.py_create(data.dtype, logical=True), space)
        attribute.write(data, mtype=h5py.h5t.py_create(data.dtype))


def _small_dataset(group, name: str, value):
    """A small contiguous dataset (tables, /state) written at once; returns its low-level id."""
    data = np.array(value, order="C")   # (ascontiguousarray would make a scalar 1-d)
    space = h5py.h5s.create(h5py.h5s.SCALAR) if data.ndim == 0 else h5py.h5s.create_simple(data.shape)
    dataset_id = h5py.h5d.create(group.id, name.encode(), h5py.h5t.py_create(data.dtype), space)
    dataset_id.write(h5py.h5s.ALL, h5py.h5s.ALL, data)
    return dataset_id


# --- reading -----------------------------------------------------------------------------
def _plain(value):
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()] if value.dtype.kind in "OSU" else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _require_ours(path, f) -> None:
    if f.attrs.get("format") != FORMAT or "state" not in f or "t" not in f:
        raise NotAnElimfastFile(f"{path}: not an elimfast run file (no '{FORMAT}' format attribute); "
                                "give a file written by 'elimfast run'")
    version = int(f.attrs.get("format_version", 0))
    if version > FORMAT_VERSION:
        raise OutputError(f"{path}: written in elimfast run format {version}; this elimfast reads up to "
                          f"{FORMAT_VERSION}: upgrade elimfast")


class RunFile:
    """A run file opened for reading (read-only; a killed run's file is opened in SWMR mode).

    ``attrs``: root attributes as plain Python values; ``steps_done`` and
    ``n_samples``: the rows that are consistent (from /state while status is
    'running'); ``status``: the recorded status, or 'killed' / 'running' for a file whose
    writer did not finish (decided by whether the writer process is alive).
    """

    READ_BLOCK = 1 << 20   # rows per read when reducing long datasets

    def __init__(self, path):
        self.path = Path(path)
        self._file = _open(self.path, "r")
        try:
            _require_ours(self.path, self._file)
        except BaseException:
            self._file.close()
            raise
        f = self._file
        self.attrs = {key: _plain(value) for key, value in f.attrs.items()}
        state = f["state"]
        self.steps_done = int(state["steps_done"][()])
        self.n_samples = min(int(state["n_samples"][()]), f["t"].shape[0])
        self.wall_time_s = float(state["wall_time_s"][()])
        self.kernel_time_s = float(state["kernel_time_s"][()])
        self.status = str(self.attrs.get("status", "?"))
        if self.status == STATUS_RUNNING:
            pid = int(state.attrs.get("writer_pid", 0))
            host = str(_plain(state.attrs.get("writer_host", "")))
            alive = host == socket.gethostname() and pid and _process_alive(pid) and pid != os.getpid()
            self.status = STATUS_RUNNING if alive else "killed"
        self.coordinate_names = [str(n) for n in _plain(f["y"].attrs.get("coordinates", []))]
        self.invariant_names = [str(n) for n in _plain(f["invariants"].attrs["order"])]
        self.imposed = {name: bool(f["invariants"][name].attrs.get("imposed", False))
                        for name in self.invariant_names}
        self.multiplier_name = ("lambda" if "lambda" in f["steps"]
                                else "alpha" if "alpha" in f["steps"] else None)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if self._file.id.valid:
            self._file.close()

    @property
    def swmr(self) -> bool:
        return bool(self._file.swmr_mode)

    # --- data ---
    def t(self, stride: int = 1) -> np.ndarray:
        return self._file["t"][:self.n_samples:stride]

    def y(self, stride: int = 1) -> np.ndarray:
        return self._file["y"][:self.n_samples:stride]

    def invariant(self, name: str, stride: int = 1) -> np.ndarray:
        return self._file["invariants"][name][:self.n_samples:stride]

    def iterations(self, stride: int = 1) -> np.ndarray:
        return self._file["steps/iterations"][:self.steps_done:stride]

    def multipliers(self, stride: int = 1) -> np.ndarray | None:
        if self.multiplier_name is None:
            return None
        return self._file["steps"][self.multiplier_name][:self.steps_done:stride]

    def multiplier_labels(self) -> list[str]:
        if self.multiplier_name is None:
            return []
        names = _plain(self._file["steps"][self.multiplier_name].attrs.get("invariants", []))
        return [f"{self.multiplier_name}[{name}]" for name in names]

    def method_table(self, name: str) -> np.ndarray | None:
        group = self._file["method"]
        return group[name][()] if name in group else None

    def final_state(self) -> dict:
        return {key: np.array(value[()]) for key, value in self._file["state"].items()}

    # --- reductions, block by block (memory bounded for any length) ---
    def _blocks(self, dataset, stop):
        for start in range(0, stop, self.READ_BLOCK):
            yield dataset[start:min(stop, start + self.READ_BLOCK)]

    def invariant_drift(self) -> dict[str, float]:
        """max over the stored samples of |I(t) - I(t0)| for H and every invariant."""
        drift = {}
        for name in self.invariant_names:
            d = self._file["invariants"][name]
            if self.n_samples == 0:
                drift[name] = math.nan
                continue
            first = float(d[0])
            drift[name] = max((float(np.max(np.abs(block - first))) for block in self._blocks(d, self.n_samples)),
                              default=0.0)
        return drift

    def iteration_stats(self) -> dict:
        d = self._file["steps/iterations"]
        count, total, low, high = 0, 0, None, None
        histogram = np.zeros(0, dtype=np.int64)
        for block in self._blocks(d, self.steps_done):
            if block.size == 0:
                continue
            count += block.size
            total += int(block.sum(dtype=np.int64))
            low = int(block.min()) if low is None else min(low, int(block.min()))
            high = int(block.max()) if high is None else max(high, int(block.max()))
            counts = np.bincount(block.astype(np.int64))
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

    def max_abs_multipliers(self) -> list[float]:
        if self.multiplier_name is None:
            return []
        d = self._file["steps"][self.multiplier_name]
        result = np.zeros(d.shape[1])
        for block in self._blocks(d, self.steps_done):
            if block.size:
                result = np.maximum(result, np.max(np.abs(block), axis=0))
        return result.tolist()
