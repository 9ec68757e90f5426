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
from dataclasses import dataclass
from typing import Iterable

import numba
import numpy as np

from .integrate import DEFAULT_MAX_HALVINGS, DEFAULT_SOLVER, Integration, failure_message
from .integrate import STATUS_NAMES as _RUN_STATUS_NAMES
from .integrate import SolverSettings, resolve_steps
from .kernels import stepper
from .kernels.codes import STATUS_EXCEPTION
from .kernels.ensemble import ensemble_loop
from .methods import Method
from .problems import Problem

# integrate's status names, and the one only an ensemble reports.
STATUS_NAMES = {**_RUN_STATUS_NAMES, STATUS_EXCEPTION: "exception"}


@dataclass
class EnsembleResult:
    """Per-trajectory outcome of ``integrate_ensemble``; every array has n_traj rows.

    y0 (n_traj, 2m) the initial states; y_final (n_traj, 2m) the state after the last
    completed step (for a 'non-finite' failure, the non-finite state, as integrate);
    t_final (n_traj,); invariant_errors: name -> (n_traj,), max over the steps of
    |I(y_n) - I(y_0)| for 'H' and every invariant of the problem, imposed or not;
    iterations (n_traj,) fixed-point iterations summed over the steps (a failed step's
    included); max_multiplier (n_traj,) max |alpha| (ELIM) or |lambda| (LIM) over the
    completed steps, 0 for GAUSS/HBVM; status (n_traj,) stepper.STATUS_* codes or
    kernels.ensemble.STATUS_EXCEPTION (names: ``reasons``); steps_done (n_traj,).
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
    solver: SolverSettings
    diagnostics: np.ndarray

    @property
    def n_trajectories(self) -> int:
        return self.y0.shape[0]

    @property
    def ok(self) -> np.ndarray:
        """(n_traj,) bool: the trajectory ran all n_steps."""
        return self.status == stepper.STATUS_OK

    @property
    def n_failed(self) -> int:
        return int(np.count_nonzero(~self.ok))

    @property
    def reasons(self) -> list[str]:
        """'ok', 'not converged', 'singular', 'non-finite' or 'exception' for each trajectory."""
        return [STATUS_NAMES[int(code)] for code in self.status]

    def failure_message(self, index: int) -> str | None:
        """The message integrate would raise for trajectory ``index`` (None if it completed)."""
        code = int(self.status[index])
        if code == stepper.STATUS_OK:
            return None
        step = int(self.steps_done[index]) + 1
        t_start = float(self.t_final[index])  # as integrate says it (after a non-finite step: its end)
        if code == STATUS_EXCEPTION:
            return (f"{self.method.name}: trajectory {index}: a problem function raised an exception (e.g. a "
                    f"division by zero at a singularity) after step {step - 1} (t = {t_start:.17g}); run "
                    f"elimfast.integrate from this trajectory's y0 to see it")
        message = failure_message(self.method, self.solver, code, step, t_start, self.h, self.diagnostics[index])
        name = f"{self.method.name}: "
        return name + f"trajectory {index}: " + message[len(name):]


def _thread_count(n_threads) -> int:
    available = numba.config.NUMBA_NUM_THREADS
    if n_threads is None:
        return available
    if isinstance(n_threads, bool) or not float(n_threads).is_integer() or not 1 <= n_threads <= available:
        raise ValueError(f"n_threads must be an integer from 1 to {available} (NUMBA_NUM_THREADS), "
                         f"got {n_threads!r}")
    return int(n_threads)


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
    h, n_steps = resolve_steps(h, t_end=t_end, n_steps=n_steps, t0=t0)
    if not isinstance(problem, Problem):
        raise TypeError(f"problem must be an elimfast Problem, got {type(problem).__name__}")
    n = 2 * problem.degrees_of_freedom
    try:
        states = np.array(Y0, dtype=np.float64, order="C")
    except (TypeError, ValueError):
        raise TypeError(f"Y0 must be an array of initial states, shape (n_traj, {n})") from None
    if states.ndim != 2 or states.shape[0] < 1 or states.shape[1] != n:
        raise ValueError(f"Y0 must have shape (n_traj, {n}) with n_traj >= 1 "
                         f"(rows: {', '.join(problem.coordinate_names)}), got shape {states.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(states), axis=1))
    if bad.size:
        raise ValueError(f"Y0 has non-finite entries in row(s) {bad[:10].tolist()}"
                         + (" ..." if bad.size > 10 else ""))
    # The validation integrate does (problem, method, conserve, tol, max_iter, rhs), by the same code.
    run = Integration(problem, method, h, n_steps, conserve=conserve, tol=tol, max_iter=max_iter, rhs=rhs,
                      warm_start=warm_start, t0=t0, y0=states[0], solver=solver, predictor=predictor,
                      max_halvings=max_halvings)
    threads = _thread_count(n_threads)

    n_traj = states.shape[0]
    n_inv = len(problem.invariant_names)
    y_final = np.empty((n_traj, n))
    t_final = np.empty(n_traj)
    inv_error = np.empty((n_traj, 1 + n_inv))
    iterations = np.empty(n_traj, dtype=np.int64)
    max_multiplier = np.empty(n_traj)
    status = np.empty(n_traj, dtype=np.int64)
    steps_done = np.empty(n_traj, dtype=np.int64)
    split_steps = np.empty(n_traj, dtype=np.int64)
    diagnostics = np.zeros((n_traj, stepper.N_DIAGNOSTICS))
    previous_threads = numba.get_num_threads()
    numba.set_num_threads(threads)
    from .streaming import current_watchdog
    watchdog = current_watchdog()
    try:
        with watchdog.kernel_call() if watchdog is not None else contextlib.nullcontext():
            ensemble_loop(
                *run.kernel_settings(),
                states, float(t0), run.n_steps, run.multipliers.size, threads,
                y_final, t_final, inv_error, iterations, max_multiplier, status, steps_done, split_steps,
                diagnostics)
    finally:
        numba.set_num_threads(previous_threads)
    errors = {"H": inv_error[:, 0].copy()}
    for i, name in enumerate(problem.invariant_names):
        errors[name] = inv_error[:, 1 + i].copy()
    return EnsembleResult(
        problem=problem, method=method, h=run.h, conserve=run.conserve, n_steps=run.n_steps,
        max_iter=run.max_iter, n_threads=threads, y0=states, y_final=y_final, t_final=t_final,
        invariant_errors=errors, iterations=iterations, max_multiplier=max_multiplier,
        status=status, steps_done=steps_done, split_steps=split_steps, solver=run.solver, diagnostics=diagnostics)


__all__ = ["EnsembleResult", "STATUS_NAMES", "integrate_ensemble"]
