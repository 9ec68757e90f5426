"""Ensembles: many initial states of one problem and one method, in one parallel kernel call.

    from elimfast.ensemble import integrate_ensemble
    result = integrate_ensemble(problem, method, h, Y0, t_end=100.0)   # Y0: (n_traj, 2m)

The arguments are validated by the same code as ``elimfast.integrate`` (an
``Integration`` is built for the first state and supplies the checked conserve indices,
steps, tol and max_iter); the kernel (``kernels.ensemble.ensemble_loop``) runs the
trajectories with ``prange``. Each trajectory equals, bit for bit, the same orbit run
alone with ``elimfast.integrate(..., y0=Y0[i])``, whatever the number of threads.
A failed trajectory does not stop the others: its status says why and where. That
includes a problem function raising (e.g. ZeroDivisionError at Kepler's singularity),
which integrate would raise and the ensemble reports as status 'exception'.
"""
from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from typing import Iterable, Iterator

import numba
import numpy as np

from .errors import ParameterError, exact_time
from .integrate import (DEFAULT_MAX_HALVINGS, DEFAULT_SOLVER, Integration, failure_message, gradients_independence,
                        undefined_at)
from .integrate import STATUS_NAMES as _RUN_STATUS_NAMES
from .integrate import SolverSettings, resolve_steps
from .kernels import codes
from .kernels.codes import STATUS_EXCEPTION, STATUS_TIME_SCALE
from .function_addresses import remembered_addresses
from .methods import Method, as_method
from .problems import Problem
from .problems.base import real_state, require_problem_object

# Blocks of a local ensemble written to a file (elimfast sweep -o): sized from the measured
# speed, as a run's chunks are (streaming.next_chunk_steps), to take about this long. Each
# block ends with threads idle while the last trajectories finish (at most one trajectory's
# time: a 2,000-step Henon-Heiles orbit took 4 ms on one thread in bench/ensemble.py, 15 ms
# on a loaded machine) and costs one kernel call (2 ms measured, threads woken included): at
# 5 s a block, under 0.5%; a kill loses at most one block. (configs/sweeps/henon_heiles_ensemble.yaml on 2 threads, to a file in 3 blocks and
# in memory in one call: 11.1 and 11.7 s vs 11.8 and 11.2 s, on a machine loaded by others.)
TARGET_BLOCK_SECONDS = 5.0
FIRST_BLOCK_ROWS_PER_THREAD = 8   # the first block measures the speed

# integrate's status names, and the one only an ensemble reports; not the time-scale failure
# of adaptive steps (an ensemble takes fixed steps), which the files' flag_meanings listed.
STATUS_NAMES = {**{code: name for code, name in _RUN_STATUS_NAMES.items() if code != STATUS_TIME_SCALE},
                STATUS_EXCEPTION: "exception"}


@dataclass
class EnsembleResult:
    """Per-trajectory outcome of ``integrate_ensemble``; every array has n_traj rows.

    y0 (n_traj, 2m) the initial states; y_final (n_traj, 2m) the state after the last
    completed step (for a 'non-finite' failure, the non-finite state, as integrate);
    t_final (n_traj,); invariant_errors: name -> (n_traj,), max over the steps of
    |I(y_n) - I(y_0)| for 'H' and every invariant of the problem, imposed or not (NaN
    for a trajectory that failed before completing a step);
    iterations (n_traj,) fixed-point iterations summed over the steps (a failed step's
    included); max_multiplier (n_traj,) max |alpha| (ELIM) or |lambda| (LIM) over the
    completed steps that imposed the invariants, 0 for GAUSS/HBVM; status (n_traj,) codes.STATUS_* codes
    or kernels.ensemble.STATUS_EXCEPTION (names: ``reasons``); steps_done (n_traj,); split_steps
    (n_traj,) steps split into substeps; unimposed_steps (n_traj,) steps taken, or with a substep
    taken, without imposing the invariants (docs/solver.md#a-substep-without-imposing; -1: not
    recorded, an ensemble file written before elimfast counted them).
    """

    problem: Problem
    method: Method
    h: float
    conserve: tuple[str, ...]
    n_steps: int
    max_iter: int
    n_threads: int
    y0: np.ndarray
    y_final: np.ndarray
    t_final: np.ndarray
    invariant_errors: dict[str, np.ndarray]
    iterations: np.ndarray
    max_multiplier: np.ndarray
    status: np.ndarray
    steps_done: np.ndarray
    split_steps: np.ndarray
    unimposed_steps: np.ndarray
    solver: SolverSettings
    diagnostics: np.ndarray

    @property
    def n_trajectories(self) -> int:
        return self.y0.shape[0]

    def __repr__(self) -> str:
        # One line, as Result's: the dataclass's repr printed every array (25 kB for 100 LJ
        # trimers) and made a LazyEnsembleResult read all of its file's columns.
        imposing = f" imposing {', '.join(self.conserve)}" if self.conserve else ""
        return (f"<{type(self).__name__} {self.method.name} on {self.problem.name}{imposing}, "
                f"{self.n_trajectories} {'trajectory' if self.n_trajectories == 1 else 'trajectories'} of "
                f"{self.n_steps} steps, h = {self.h:g}, "
                f"{self.n_failed} failed>")

    @property
    def ok(self) -> np.ndarray:
        """(n_traj,) bool: the trajectory ran all n_steps."""
        return self.status == codes.STATUS_OK

    @property
    def n_failed(self) -> int:
        return int(np.count_nonzero(~self.ok))

    @property
    def reasons(self) -> list[str]:
        """'ok', 'not converged', 'singular', 'non-finite' or 'exception' for each trajectory."""
        return [STATUS_NAMES[int(code)] for code in self.status]

    def to_xarray(self):
        """An xarray.Dataset on (trajectory, component, ...), named as an ensemble file's
        /ensemble (``elimfast.io.xarray_view.ensemble_dataset``; needs xarray)."""
        from .io.xarray_view import ensemble_dataset
        return ensemble_dataset(self, STATUS_NAMES)

    def failure_message(self, index: int) -> str | None:
        """The message integrate would raise for trajectory ``index`` (None if it completed)."""
        code = int(self.status[index])
        if code == codes.STATUS_OK:
            return None
        step = int(self.steps_done[index]) + 1
        t_start = float(self.t_final[index])  # as integrate says it (after a non-finite step: its end)
        if code == STATUS_EXCEPTION:
            return (f"{self.method.name}: trajectory {index}: a problem function raised an exception (e.g. a "
                    f"division by zero at a singularity) after step {step - 1} (t = {exact_time(t_start)}); run "
                    f"elimfast.integrate from this trajectory's y0 to see it")
        name = f"{self.method.name}: "
        if code == codes.STATUS_NONFINITE and step == 1:
            # (only for trajectories failed at their first step: a call per row from Python would cost
            # seconds per million rows)
            undefined = undefined_at(self.problem, self.y0[index])
            if undefined is not None:
                # as integrate refuses such a y0 (resolve_initial_state); the kernel only sees the NaN
                # of its first step, which it blamed on h after 4 halvings (a user trial)
                return (f"{name}trajectory {index}: {undefined} at its initial state {self.y0[index].tolist()}: it "
                        "is not defined there; choose initial states away from the problem's singularities")
        # y, y0: a state grown far beyond its start is named (an escaping Henon-Heiles orbit, |p| ~ 8e6, was
        # told to allow more step halvings, a user trial)
        indices = [self.problem.invariant_names.index(name) for name in self.conserve]
        message = failure_message(self.method, self.solver, code, step, t_start, self.h, self.diagnostics[index],
                                  imposed=len(self.conserve), y=self.y_final[index], y0=self.y0[index],
                                  independence=gradients_independence(self.problem, indices, self.y_final[index]))
        return name + f"trajectory {index}: " + message[len(name):]


def _thread_count(n_threads) -> int:
    available = numba.config.NUMBA_NUM_THREADS
    if n_threads is None:
        return available
    if isinstance(n_threads, bool) or not float(n_threads).is_integer() or not 1 <= n_threads <= available:
        raise ValueError(f"n_threads must be an integer from 1 to {available} (NUMBA_NUM_THREADS), "
                         f"got {n_threads!r}")
    return int(n_threads)


def check_states(problem: Problem, Y0) -> np.ndarray:
    """Y0 as a C-contiguous float64 array (n_traj, 2m) of finite initial states; TypeError or
    ValueError naming what is wrong."""
    require_problem_object(problem)
    n = 2 * problem.degrees_of_freedom
    states = np.ascontiguousarray(real_state(Y0, "Y0"))
    if states.ndim != 2 or states.shape[0] < 1 or states.shape[1] != n:
        raise ValueError(f"Y0 must have shape (n_traj, {n}) with n_traj >= 1 "
                         f"(rows: {', '.join(problem.coordinate_names)}), got shape {states.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(states), axis=1))
    if bad.size:
        raise ValueError(f"Y0 has non-finite entries in row(s) {bad[:10].tolist()}"
                         + (" ..." if bad.size > 10 else ""))
    return states


# The per-trajectory arrays of an EnsembleResult that the kernel computes (y0 is its input;
# invariant_errors, a mapping of such arrays, comes beside them): one block of an ensemble is
# these arrays for some of its rows, plus invariant_errors.
ROW_ARRAYS = ("y_final", "t_final", "iterations", "max_multiplier", "status", "steps_done", "split_steps",
              "unimposed_steps", "diagnostics")


class LazyEnsembleResult(EnsembleResult):
    """An EnsembleResult whose per-trajectory arrays (y0, ROW_ARRAYS, invariant_errors) not
    given are got from ``read(name)`` when first used, then kept: a summary of a large
    ensemble read from its file (archive.load_ensemble) holds the columns it uses, not all.
    The dataclass's fields are set here, not by its __init__; ``__getattr__`` runs only for
    an attribute not set yet."""

    _ARRAYS = frozenset(("y0", "invariant_errors", *ROW_ARRAYS))

    def __init__(self, read, n_trajectories: int, **fields):
        self.__dict__.update(fields)
        self._read, self._n_trajectories = read, n_trajectories

    def __getattr__(self, name):
        if name not in self._ARRAYS:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        value = self._read(name)
        self.__dict__[name] = value
        return value

    @property
    def n_trajectories(self) -> int:
        return self._n_trajectories


class EnsembleRun:
    """A validated ensemble: the problem, the method and the settings of ``integrate_ensemble``,
    ready to run any rows of initial states in the kernel (``rows``).

    Trajectories are independent (kernels/ensemble.py), so the rows of one call over some
    states are, bit for bit, those of one call over all of them: an ensemble may be run in
    blocks of rows, in any order, in any process.
    """

    def __init__(self, problem: Problem, method: Method, h: float, y0, t_end: float | None = None,
                 n_steps: int | None = None, conserve: Iterable[str] = (), tol: float | None = None,
                 max_iter: int | None = None, rhs: str = "stable", n_threads: int | None = None, t0: float = 0.0,
                 warm_start: bool = True, solver: str | SolverSettings = DEFAULT_SOLVER, predictor: bool = True,
                 max_halvings: int = DEFAULT_MAX_HALVINGS):
        h, n_steps = resolve_steps(h, t_end=t_end, n_steps=n_steps, t0=t0)
        # The validation integrate does (problem, method, conserve, tol, max_iter, rhs), by the same
        # code, for one initial state (y0: the ensemble's first).
        self.integration = Integration(problem, method, h, n_steps, conserve=conserve, tol=tol, max_iter=max_iter,
                                       rhs=rhs, warm_start=warm_start, t0=t0, y0=y0, solver=solver,
                                       predictor=predictor, max_halvings=max_halvings, check_y0=False)
        from .per_problem import refuse
        refuse(self.integration.solver, "ensembles")
        if self.integration.solver.project_energy:
            raise ParameterError("project_energy", "is not available for ensembles (their kernel has no energy "
                                                   "projection, docs/methods.md#energy-projection): leave it out")
        self.problem, self.method, self.t0 = problem, method, float(t0)
        self.n_threads = _thread_count(n_threads)

    @classmethod
    def from_spec(cls, spec, y0, n_threads: int | None = None) -> "EnsembleRun":
        """The ensemble of a validated config (``elimfast.config.RunSpec``) from its initial states."""
        return cls(spec.problem, spec.method, spec.h, y0, n_steps=spec.n_steps, conserve=spec.conserve,
                   solver=spec.solver, n_threads=n_threads, t0=spec.t0)

    h = property(lambda self: self.integration.h)
    n_steps = property(lambda self: self.integration.n_steps)
    status_names = STATUS_NAMES   # the words of the status codes, for the ensemble file
    conserve = property(lambda self: self.integration.conserve)
    max_iter = property(lambda self: self.integration.max_iter)
    solver = property(lambda self: self.integration.solver)

    n_diagnostics = codes.N_DIAGNOSTICS   # columns of a trajectory's diagnostics

    @property
    def invariant_names(self) -> tuple[str, ...]:
        """The invariants whose errors each trajectory reports: H, then every invariant of the problem."""
        return ("H",) + tuple(self.problem.invariant_names)

    def row_layout(self) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
        """ROW_ARRAYS: the shape of one trajectory's entry and the dtype of each (what ``rows``
        returns, and what an ensemble file holds per trajectory beside y0 and invariant_errors)."""
        n, real, integer = 2 * self.problem.degrees_of_freedom, np.dtype(np.float64), np.dtype(np.int64)
        layout = {"y_final": ((n,), real), "t_final": ((), real), "iterations": ((), integer),
                  "max_multiplier": ((), real), "status": ((), integer), "steps_done": ((), integer),
                  "split_steps": ((), integer), "unimposed_steps": ((), integer),
                  "diagnostics": ((self.n_diagnostics,), real)}
        return {name: layout[name] for name in ROW_ARRAYS}

    def rows(self, states: np.ndarray) -> dict:
        """Run ``states`` (n_rows, 2m; checked by ``check_states``) in the kernel on n_threads
        threads (the previous Numba setting is restored afterwards): ROW_ARRAYS, each with
        n_rows rows, and invariant_errors {name: (n_rows,)}."""
        run, threads = self.integration, self.n_threads
        n_rows = states.shape[0]
        rows = {name: np.zeros((n_rows,) + shape, dtype) if name == "diagnostics" else np.empty((n_rows,) + shape, dtype)
                for name, (shape, dtype) in self.row_layout().items()}   # the kernel sets diagnostics on failure only
        inv_error = np.empty((n_rows, len(self.invariant_names)))
        previous_threads = numba.get_num_threads()
        numba.set_num_threads(threads)
        from .kernels.ensemble import ensemble_loop   # not at import: it loads (or compiles) the kernel
        from .streaming import current_watchdog
        watchdog = current_watchdog()
        try:
            with watchdog.kernel_call() if watchdog is not None else contextlib.nullcontext(), remembered_addresses():
                ensemble_loop(
                    *run.kernel_settings(),
                    states, self.t0, run.n_steps, run.multipliers.size, threads,
                    rows["y_final"], rows["t_final"], inv_error, rows["iterations"], rows["max_multiplier"],
                    rows["status"], rows["steps_done"], rows["split_steps"], rows["unimposed_steps"],
                    rows["diagnostics"])
        finally:
            numba.set_num_threads(previous_threads)
        # A trajectory that completed no step has no invariant error to report (NaN, as inspect
        # reports none for such a run): the kernel's 0 read as 'kept exactly' beside its failure.
        inv_error[rows["steps_done"] == 0] = np.nan
        rows["invariant_errors"] = {name: inv_error[:, i].copy() for i, name in enumerate(self.invariant_names)}
        return rows

    def result(self, states: np.ndarray, rows: dict, n_threads: int | None = None) -> EnsembleResult:
        """The EnsembleResult of ``states`` from their rows (``rows``, or assembled by EnsembleRows)."""
        return EnsembleResult(
            problem=self.problem, method=self.method, h=self.h, conserve=self.conserve, n_steps=self.n_steps,
            max_iter=self.max_iter, n_threads=self.n_threads if n_threads is None else n_threads, y0=states,
            solver=self.solver, invariant_errors=rows["invariant_errors"], **{name: rows[name] for name in ROW_ARRAYS})


class EnsembleRows:
    """The rows of a whole ensemble in memory, put in place block by block as blocks arrive."""

    def __init__(self, n_trajectories: int):
        self.n_trajectories = n_trajectories
        self.rows: dict | None = None

    def put(self, start: int, stop: int, block: dict) -> None:
        if self.rows is None:
            n = self.n_trajectories
            self.rows = {name: np.empty((n,) + block[name].shape[1:], dtype=block[name].dtype) for name in ROW_ARRAYS}
            self.rows["invariant_errors"] = {name: np.empty(n, dtype=values.dtype)
                                             for name, values in block["invariant_errors"].items()}
        for name in ROW_ARRAYS:
            self.rows[name][start:stop] = block[name]
        for name, values in block["invariant_errors"].items():
            self.rows["invariant_errors"][name][start:stop] = values


def run_in_blocks(run: EnsembleRun, states: np.ndarray, ranges, target_seconds: float | None = None,
                  first_rows: int | None = None) -> Iterator[tuple[int, int, dict, int]]:
    """Run the rows of ``states`` in ``ranges`` ([start, stop) pairs) in consecutive blocks, one
    kernel call each, on this process's threads: yields (start, stop, rows, threads) as each block ends,
    and runs the next only when asked for it (so one block's rows are held at a time). Blocks
    take about ``target_seconds`` (default TARGET_BLOCK_SECONDS) each, from the measured
    speed; the first has ``first_rows`` (default FIRST_BLOCK_ROWS_PER_THREAD per thread). The
    rows are those of one call over all the states, bit for bit."""
    from .streaming import next_chunk_steps

    target_seconds = TARGET_BLOCK_SECONDS if target_seconds is None else target_seconds

    row_bytes = 8.0 * (states.shape[1] + len(run.invariant_names)) + sum(
        dtype.itemsize * int(np.prod(shape)) for shape, dtype in run.row_layout().values())
    size = first_rows or FIRST_BLOCK_ROWS_PER_THREAD * run.n_threads
    seconds, measured = 0.0, False   # the last block's time, once one is measured
    for range_start, range_stop in ranges:
        start = range_start
        while start < range_stop:
            if measured:
                size = next_chunk_steps(size, seconds, row_bytes, target_seconds=target_seconds,
                                        remaining=range_stop - start)
            stop = min(start + size, range_stop)
            began = time.perf_counter()
            rows = run.rows(states[start:stop])
            seconds, size, measured = time.perf_counter() - began, stop - start, True
            yield start, stop, rows, run.n_threads
            start = stop


def integrate_ensemble(problem: Problem, method: Method, h: float, Y0, t_end: float | None = None,
                       n_steps: int | None = None, conserve: Iterable[str] = (), tol: float | None = None,
                       max_iter: int | None = None, rhs: str = "stable", n_threads: int | None = None,
                       t0: float = 0.0, warm_start: bool = True, solver: str | SolverSettings = DEFAULT_SOLVER,
                       predictor: bool = True, max_halvings: int = DEFAULT_MAX_HALVINGS) -> EnsembleResult:
    """Integrate ``problem`` with ``method`` and step ``h`` from every row of Y0 (n_traj, 2m).

    Arguments as for ``elimfast.integrate`` (give exactly one of t_end and n_steps);
    n_threads: Numba threads for this call (default: all, NUMBA_NUM_THREADS); the
    previous setting is restored afterwards. Failures do not raise: see
    ``EnsembleResult.status`` and ``failure_message``.
    """
    method = as_method(method)   # "EHBVM(12,3)" too, as integrate
    resolve_steps(h, t_end=t_end, n_steps=n_steps, t0=t0)   # its errors first, as integrate's
    states = check_states(problem, Y0)
    run = EnsembleRun(problem, method, h, states[0], t_end=t_end, n_steps=n_steps, conserve=conserve, tol=tol,
                      max_iter=max_iter, rhs=rhs, n_threads=n_threads, t0=t0, warm_start=warm_start, solver=solver,
                      predictor=predictor, max_halvings=max_halvings)
    return run.result(states, run.rows(states))


__all__ = ["EnsembleResult", "EnsembleRows", "EnsembleRun", "LazyEnsembleResult", "ROW_ARRAYS", "STATUS_NAMES", "check_states",
           "integrate_ensemble", "run_in_blocks"]
