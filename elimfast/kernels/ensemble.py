"""Many trajectories of one problem and one method at once: ``prange`` over trajectories.

Numba only, like stepper.py: the problem's functions arrive as ``types.FunctionType``
arguments (signatures.py), so this one cached kernel serves every problem.

Each trajectory is a loop of ``stepper.try_step``, the step protocol ``time_loop``
runs (predictor, solver, fallback, compensated summation), so an ensemble member
equals, bit for bit, the same orbit run alone by ``elimfast.integrate``. Trajectories are independent and each writes only its own
row of the outputs, so the results do not depend on the number of threads or on how
the trajectories are scheduled.

Scheduling is dynamic: one prange iteration per thread, and each thread takes the next
trajectory from a shared atomic counter until none is left. Numba's own prange split
is static (contiguous blocks, even with set_parallel_chunksize under the OpenMP and
workqueue layers), which leaves a thread idle when costs are uneven: ensembles sorted
by energy, chaotic next to regular orbits, trajectories that fail early, or a core
shared with another process.
"""
import warnings

import numpy as np
from numba import njit, prange, types
from numba.core.errors import NumbaExperimentalFeatureWarning
from numba.extending import intrinsic

from .codes import N_DIAGNOSTICS, STATUS_EXCEPTION, STATUS_OK, internal_allocating
from .signatures import INT_VECTOR, MATRIX, VECTOR
from .stepper import RUN_ARGUMENT_TYPES, newton_eigenvalues, predictor_extra_rows, try_step
from .workspace import (Settings, Tables, borrow_tables, borrow_workspace, borrowed, by_ref, keep_alive,
                        make_workspace)

warnings.filterwarnings("ignore", category=NumbaExperimentalFeatureWarning, module=__name__)
warnings.filterwarnings("ignore", message="First-class function type feature is experimental")


@internal_allocating
def _run_trajectory(H, grad_H, hess_H, invariants, grad_invariants, params, settings, tables, conserve_idx,
                    h, y0, t0, n_steps, n_mult, y, errors, counts, reals, diagnostics):
    """One trajectory from y0 (n,): ``stepper.time_loop`` with store_every = 1, reduced on the fly.

    The steps are ``stepper.try_step``, exactly as time_loop takes them (same settings,
    same workspace layout, the first step cold), so the trajectory is bit for bit the run
    integrate makes. Writes, current after every step (so that they hold the last
    completed step if a problem function raises): y (n,) the state; errors (1 + n_inv,)
    max |I(y_n) - I(y0)| for H, then every invariant; counts (4,) = [steps done,
    iterations so far, split steps, steps taken unimposed]; reals (2,) = [t, max |multiplier|
    over the steps that imposed the invariants, as a run file's alpha history]; diagnostics
    (N_DIAGNOSTICS,) of a failed step (stepper.try_step). Returns the status; a failed
    step is not applied (its iterations are counted).
    """
    n = y0.shape[0]
    n_inv = errors.shape[0] - 1
    owners = make_workspace(n, tables.Is.shape[0], tables.Ihat.shape[0], tables.Is.shape[1],
                            conserve_idx.shape[0], settings.family, n_inv, n_mult,
                            newton_eigenvalues(settings, tables.newton_values))
    work = by_ref(borrow_workspace(owners))
    tables = by_ref(tables)   # passed on by address (workspace.ByRef), as time_loop's
    inv_values = np.zeros(n_inv)
    inv_initial = np.zeros(n_inv)
    coef = np.zeros((tables.Is.shape[1], n))
    coef_extra = np.zeros((predictor_extra_rows(tables.Is.shape[0], tables.Is.shape[1]), n))
    multipliers = np.zeros(n_mult)
    y_comp = np.zeros(n)
    clock = np.array([t0, 0.0])
    last_h = np.array([h])
    newton_base = np.zeros(n + 3)

    for p in range(n):
        y[p] = y0[p]
    for a in range(1 + n_inv):
        errors[a] = 0.0
    reals[0] = t0
    reals[1] = 0.0
    counts[0] = 0
    counts[1] = 0
    counts[2] = 0
    counts[3] = 0
    H_initial = H(y, params)
    invariants(y, params, inv_initial)

    # Borrowed views (workspace.py): shared arrays such as params would otherwise have
    # their reference count updated by every thread at every call, one contended cache line.
    params_view, conserve_view, y_view = borrowed(params), borrowed(conserve_idx), borrowed(y)
    y_comp_view, clock_view, coef_view = borrowed(y_comp), borrowed(clock), borrowed(coef)
    mult_view, last_h_view, diagnostics_view = borrowed(multipliers), borrowed(last_h), borrowed(diagnostics)
    base_view, extra_view = borrowed(newton_base), borrowed(coef_extra)
    status = STATUS_OK
    for step in range(n_steps):
        status, iterations, substeps = try_step(
            grad_H, hess_H, grad_invariants, params_view, settings, tables, conserve_view, work,
            y_view, y_comp_view, clock_view, coef_view, extra_view, mult_view, h, last_h_view, base_view, step > 0,
            diagnostics_view, settings.max_halvings > 0, settings.max_halvings > 0)
        counts[1] += iterations
        if status != STATUS_OK:
            break
        if substeps > 1:
            counts[2] += 1
        if work.info[5] > 0.0:
            # (a substep of) it taken without imposing the invariants: no multiplier exists
            # (stepper.record_multipliers, NaN in a run's history)
            counts[3] += 1
        else:
            for a in range(n_mult):
                if not (abs(multipliers[a]) <= reals[1]):
                    reals[1] = abs(multipliers[a])
        reals[0] = clock[0]
        counts[0] = step + 1
        # The invariants after every step: time_loop's samples with store_every = 1.
        error = abs(H(y, params) - H_initial)
        if error > errors[0]:
            errors[0] = error
        invariants(y, params, inv_values)
        for a in range(n_inv):
            error = abs(inv_values[a] - inv_initial[a])
            if error > errors[1 + a]:
                errors[1 + a] = error
    keep_alive((owners, y_comp, clock, coef, coef_extra, multipliers, last_h, newton_base))
    return status


@njit(cache=True, no_cpython_wrapper=True, no_cfunc_wrapper=True)
def _guarded_trajectory(H, grad_H, hess_H, invariants, grad_invariants, params, settings, tables, conserve_idx,
                        h, y0, t0, n_steps, n_mult, index,
                        y_final, t_final, inv_error, iterations, max_multiplier, steps_done, split_steps,
                        unimposed_steps, diagnostics):
    """Trajectory ``index``: _run_trajectory, then its results copied to row ``index`` of the outputs.

    An exception from a problem function becomes STATUS_EXCEPTION: escaping a prange
    body it would abort every trajectory (and reach Python as a SystemError). Neither
    function is inlined: Numba checks an inlined callee's exceptions only when the try
    block ends (measured with Numba 0.68), so the trajectory would run on with garbage;
    a real call returns at the first exception, and the private arrays then hold the
    last completed step.
    The trajectory works in private arrays and writes the shared outputs once, at the
    end: updated every step, they would make neighbouring trajectories running on
    different threads write to the same cache lines (false sharing).
    """
    y = np.empty(y0.shape[0])
    errors = np.zeros(inv_error.shape[1])
    counts = np.zeros(4, dtype=np.int64)
    reals = np.zeros(2)
    failure = np.zeros(N_DIAGNOSTICS)
    try:
        status = _run_trajectory(H, grad_H, hess_H, invariants, grad_invariants, params, settings, tables,
                                 conserve_idx, h, y0, t0, n_steps, n_mult, y, errors, counts, reals, failure)
    except Exception:  # noqa: BLE001 - Numba cannot bind or filter the exception object
        status = STATUS_EXCEPTION
    for p in range(y.shape[0]):
        y_final[index, p] = y[p]
    for a in range(errors.shape[0]):
        inv_error[index, a] = errors[a]
    steps_done[index] = counts[0]
    iterations[index] = counts[1]
    split_steps[index] = counts[2]
    unimposed_steps[index] = counts[3]
    t_final[index] = reals[0]
    max_multiplier[index] = reals[1]
    for a in range(N_DIAGNOSTICS):
        diagnostics[index, a] = failure[a]
    return status


@intrinsic
def _fetch_add(typingctx, counter, increment):
    """Atomically counter[0] += increment; returns the old value (LLVM atomicrmw add)."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and counter.ndim == 1
            and increment == types.int64):
        return None

    def codegen(context, builder, signature, args):
        array = context.make_array(signature.args[0])(context, builder, args[0])
        return builder.atomic_rmw("add", array.data, args[1], "monotonic")
    return types.int64(counter, increment), codegen


ENSEMBLE_SIGNATURE = types.void(
    *RUN_ARGUMENT_TYPES,                                                               # as time_loop's
    MATRIX, types.float64, types.int64, types.int64, types.int64,                      # Y0, t0, n_steps, n_mult,
    #                                                                                    n_workers
    MATRIX, VECTOR, MATRIX, INT_VECTOR, VECTOR, INT_VECTOR, INT_VECTOR, INT_VECTOR,    # outputs
    INT_VECTOR, MATRIX,
)


@njit(ENSEMBLE_SIGNATURE, parallel=True, cache=True, nogil=True)
def ensemble_loop(H, grad_H, hess_H, invariants, grad_invariants, params,
                  family, solver, stable_rhs, warm_start, predictor, tol, max_iter, max_halvings,
                  h, projection, Is, projection_hat, Ihat, X, abs_projection_hat, predictor_nodes, predictor_basis,
                  newton_values, newton_vectors, newton_inverse, newton_weights, Is_low, Ihat_low,
                  conserve_idx,
                  Y0, t0, n_steps, n_mult, n_workers,
                  y_final, t_final, inv_error, iterations, max_multiplier, status, steps_done, split_steps,
                  unimposed_steps, diagnostics):
    """Run n_steps steps of one method from each row of Y0, trajectories in parallel.

    Each trajectory is the run ``stepper.time_loop`` makes from step 0 with
    store_every = 1 (same step protocol, ``stepper.try_step``): the first step cold, the
    later ones predicted from the previous step (docs/solver.md), compensated summation
    (docs/methods.md#round-off-over-long-times).

    Inputs: the settings and tables as for time_loop; Y0 (n_traj, n) initial states, all
    at time t0; n_mult = nu (ELIM) or nu + 1 (LIM); n_workers: the number of Numba
    threads set for the call (an argument: numba.get_num_threads() inside the kernel
    would defeat the cache).
    Outputs, one row per trajectory (written by that trajectory only):
      y_final (n_traj, n): the state after the last completed step;
      t_final (n_traj,): its time (compensated sum of t0 + h + h + ...);
      inv_error (n_traj, 1 + n_inv): max over steps of |I(y_n) - I(y_0)| for H, then
        every invariant of the problem (imposed or not);
      iterations (n_traj,): iterations summed over the steps, the failed step's included;
      max_multiplier (n_traj,): max over completed steps of |alpha|_inf (ELIM) or
        |lambda|_inf (LIM), 0 when there is none (steps taken without imposing the invariants
        have none: stepper.try_step);
      status (n_traj,): STATUS_OK, the failing step's status, or STATUS_EXCEPTION when
        a problem function raised (the outputs then hold the last completed step); a
        failure ends that trajectory only; steps_done (n_traj,): steps completed;
      split_steps (n_traj,): steps that were split into substeps;
      unimposed_steps (n_traj,): steps taken, or with a substep taken, without imposing the
        invariants (docs/solver.md#a-substep-without-imposing);
      diagnostics (n_traj, N_DIAGNOSTICS): of a failed trajectory's failed step.
    """
    settings = Settings(family, solver, stable_rhs, warm_start, predictor, tol, max_iter, max_halvings)
    tables = borrow_tables(Tables(projection, Is, projection_hat, Ihat, X, abs_projection_hat, predictor_nodes,
                                  predictor_basis, newton_values, newton_vectors, newton_inverse,
                                  newton_weights, Is_low, Ihat_low))
    n_traj = Y0.shape[0]
    next_trajectory = np.zeros(1, dtype=np.int64)
    for worker in prange(min(n_workers, n_traj)):
        while True:
            i = _fetch_add(next_trajectory, np.int64(1))
            if i >= n_traj:
                break
            status[i] = _guarded_trajectory(
                H, grad_H, hess_H, invariants, grad_invariants, params, settings, tables, conserve_idx,
                h, Y0[i], t0, n_steps, n_mult, i,
                y_final, t_final, inv_error, iterations, max_multiplier, steps_done, split_steps, unimposed_steps,
                diagnostics)
