"""Many trajectories of one problem and one method at once: ``prange`` over trajectories.

Numba only, like stepper.py: the problem's functions arrive as ``types.FunctionType``
arguments (signatures.py), so this one cached kernel serves every problem.

Each trajectory is exactly the run ``stepper.time_loop`` makes from its initial state
(same step functions, warm start, compensated summation of y and t, stopping rule,
failure handling), so an ensemble member equals, bit for bit, the same orbit run alone
by ``elimfast.integrate``. Trajectories are independent and each writes only its own
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

from .signatures import (GRAD_H_TYPE, GRAD_INVARIANTS_TYPE, H_TYPE, INT_VECTOR,
                         INVARIANTS_TYPE, MATRIX, VECTOR)
from .stepper import FAMILY_LIM, STATUS_NONFINITE, STATUS_OK, _kahan_add, elim_step, lim_step

warnings.filterwarnings("ignore", category=NumbaExperimentalFeatureWarning, module=__name__)
warnings.filterwarnings("ignore", message="First-class function type feature is experimental")


# Status of a trajectory whose problem function raised (e.g. ZeroDivisionError at the
# singularity of Kepler's H): the kernel catches it so the other trajectories go on.
# Beyond stepper's codes, which elimfast.integrate would instead raise as the exception.
STATUS_EXCEPTION = 4


@njit(cache=True)
def _run_trajectory(H, grad_H, invariants, grad_invariants, params,
                    family, n_inv, stable_rhs, warm_start,
                    h, tables, conserve_idx, tol, small, max_iter,
                    y0, t0, n_steps, n_mult, y, errors, counts, reals):
    """One trajectory from y0 (n,): ``stepper.time_loop`` with store_every = 1, reduced on the fly.

    Writes, current after every step (so that they hold the last completed step if a
    problem function raises): y (n,) the state; errors (1 + n_inv,) max |I(y_n) - I(y0)|
    for H, then every invariant; counts (2,) = [steps done, iterations so far];
    reals (2,) = [t, max |multiplier|]. Returns the status; as in time_loop, a failed
    step is not applied (its iterations are counted), except a step whose result is not
    finite (STATUS_NONFINITE: y then holds it and t its end time, steps done does not
    count it). The workspace is allocated here, once per trajectory, never inside the
    step loop.
    """
    projection, Is, projection_hat, Ihat = tables
    n = y0.shape[0]
    k = Is.shape[0]
    r = Ihat.shape[0]
    s = Is.shape[1]
    nu = conserve_idx.shape[0]
    n_tilde = nu + 1 if family == FAMILY_LIM else nu
    n_big = max(k, r, s)

    # The same workspace and step logic as time_loop (see there); nothing is allocated in
    # the loop. Deliberately a copy: sharing both loops' workspace and step through inlined
    # helpers was measured 1.5-1.8x slower per iteration (Numba 0.68), and the tests hold
    # the two bit for bit equal (tests/test_ensemble.py).
    u = np.zeros((k, n))
    grads = np.zeros((k, n))
    proj = np.zeros((n_big, n))
    gamma = np.zeros((n_big, n))
    gamma_hat = np.zeros((n_big, n))
    uhat = np.zeros((r, n))
    grads_hat = np.zeros((n_tilde + 1, r, n))
    inv_grads = np.zeros((n_inv, n))
    inv_values = np.zeros(n_inv)
    inv_initial = np.zeros(n_inv)
    phi = np.zeros((max(n_tilde, 1), n_big, n))
    small_matrix = np.zeros((max(n_tilde, 1), max(n_tilde, 1)))
    small_vector = np.zeros(max(n_tilde, 1))
    new_coef = np.zeros((s, n))
    coef = np.zeros((s, n))
    saved_coef = np.zeros((s, n))
    multipliers = np.zeros(n_mult)
    saved_mult = np.zeros(n_mult)
    y_comp = np.zeros(n)
    h_powers = np.zeros(max(nu, 1))
    for col in range(nu):
        h_powers[col] = h ** (2 * (nu - 1 - col))
    work = (u, grads, proj, gamma, uhat, grads_hat, inv_grads, phi, gamma_hat,
            small_matrix, small_vector, new_coef, h_powers)

    for p in range(n):
        y[p] = y0[p]
    for a in range(1 + n_inv):
        errors[a] = 0.0
    t = t0
    t_comp = 0.0
    reals[0] = t
    reals[1] = 0.0
    counts[0] = 0
    counts[1] = 0
    H_initial = H(y, params)
    invariants(y, params, inv_initial)

    for step in range(n_steps):
        cold = not (warm_start != 0 and step > 0)
        for j in range(s):
            for p in range(n):
                saved_coef[j, p] = coef[j, p]
                if cold:
                    coef[j, p] = 0.0
        for a in range(n_mult):
            saved_mult[a] = multipliers[a]
            if cold:
                multipliers[a] = 0.0
        if family == FAMILY_LIM:
            status, step_iterations = lim_step(
                grad_H, grad_invariants, params, y, h, tables, conserve_idx,
                coef, multipliers, tol, small, max_iter, work)
        else:
            status, step_iterations = elim_step(
                grad_H, grad_invariants, params, y, h, tables, conserve_idx,
                stable_rhs != 0, coef, multipliers, cold, tol, small, max_iter, work)
        counts[1] += step_iterations
        if status != STATUS_OK:
            for j in range(s):
                for p in range(n):
                    coef[j, p] = saved_coef[j, p]
            for a in range(n_mult):
                multipliers[a] = saved_mult[a]
            return status
        for a in range(n_mult):
            if not (abs(multipliers[a]) <= reals[1]):
                reals[1] = abs(multipliers[a])
        for p in range(n):
            y[p], y_comp[p] = _kahan_add(y[p], y_comp[p], h * coef[0, p])
        t, t_comp = _kahan_add(t, t_comp, h)
        reals[0] = t
        for p in range(n):
            if not (abs(y[p]) <= 1e308):
                return STATUS_NONFINITE
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
    return STATUS_OK


@njit(cache=True)
def _guarded_trajectory(H, grad_H, invariants, grad_invariants, params,
                        family, n_inv, stable_rhs, warm_start,
                        h, tables, conserve_idx, tol, small, max_iter,
                        y0, t0, n_steps, n_mult, index,
                        y_final, t_final, inv_error, iterations, max_multiplier, steps_done):
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
    counts = np.zeros(2, dtype=np.int64)
    reals = np.zeros(2)
    try:
        status = _run_trajectory(H, grad_H, invariants, grad_invariants, params,
                                 family, n_inv, stable_rhs, warm_start,
                                 h, tables, conserve_idx, tol, small, max_iter,
                                 y0, t0, n_steps, n_mult, y, errors, counts, reals)
    except Exception:  # noqa: BLE001 - Numba cannot bind or filter the exception object
        status = STATUS_EXCEPTION
    for p in range(y.shape[0]):
        y_final[index, p] = y[p]
    for a in range(errors.shape[0]):
        inv_error[index, a] = errors[a]
    steps_done[index] = counts[0]
    iterations[index] = counts[1]
    t_final[index] = reals[0]
    max_multiplier[index] = reals[1]
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
    H_TYPE, GRAD_H_TYPE, INVARIANTS_TYPE, GRAD_INVARIANTS_TYPE, VECTOR,   # problem
    types.int64, types.int64, types.int64, types.int64,                   # family, n_inv, stable_rhs, warm_start
    types.float64, MATRIX, MATRIX, MATRIX, MATRIX,                        # h, projection, Is, projection_hat, Ihat
    INT_VECTOR, types.float64, types.float64, types.int64,                # conserve_idx, tol, small, max_iter
    MATRIX, types.float64, types.int64, types.int64, types.int64,         # Y0, t0, n_steps, n_mult, n_workers
    MATRIX, VECTOR, MATRIX, INT_VECTOR, VECTOR, INT_VECTOR, INT_VECTOR,   # outputs
)


@njit(ENSEMBLE_SIGNATURE, parallel=True, cache=True)
def ensemble_loop(H, grad_H, invariants, grad_invariants, params,
                  family, n_inv, stable_rhs, warm_start,
                  h, projection, Is, projection_hat, Ihat,
                  conserve_idx, tol, small, max_iter,
                  Y0, t0, n_steps, n_mult, n_workers,
                  y_final, t_final, inv_error, iterations, max_multiplier, status, steps_done):
    """Run n_steps steps of one method from each row of Y0, trajectories in parallel.

    Spec sections 2-4 (the steps) and 7 (compensated summation), exactly as
    ``stepper.time_loop`` from step 0 with store_every = 1: every trajectory starts
    with coef = 0 and multipliers = 0 (cold first step), then warm-starts each step
    from the previous step's coefficients when warm_start is set.

    Inputs: Y0 (n_traj, n) initial states, all at time t0; n_mult = nu (ELIM) or
    nu + 1 (LIM), the length of the multiplier vector alpha or lambda; n_workers: the
    number of Numba threads set for the call (an argument: numba.get_num_threads()
    inside the kernel would defeat the cache); the other arguments as for time_loop.
    Outputs, one row per trajectory (written by that trajectory only):
      y_final (n_traj, n): the state after the last completed step (as time_loop:
        on STATUS_NONFINITE, the non-finite state);
      t_final (n_traj,): its time (compensated sum of t0 + h + h + ...);
      inv_error (n_traj, 1 + n_inv): max over steps of |I(y_n) - I(y_0)| for H, then
        every invariant of the problem (imposed or not);
      iterations (n_traj,): fixed-point iterations, summed over the steps, the failed
        step's included; max_multiplier (n_traj,): max over completed steps of
        |alpha|_inf (ELIM) or |lambda|_inf (LIM), 0 when there is none;
      status (n_traj,): STATUS_OK, the failing step's status, or STATUS_EXCEPTION when
        a problem function raised (the outputs then hold the last completed step); a
        failure ends that trajectory only; steps_done (n_traj,): steps completed.
    """
    tables = (projection, Is, projection_hat, Ihat)
    n_traj = Y0.shape[0]
    next_trajectory = np.zeros(1, dtype=np.int64)
    for worker in prange(min(n_workers, n_traj)):
        while True:
            i = _fetch_add(next_trajectory, np.int64(1))
            if i >= n_traj:
                break
            status[i] = _guarded_trajectory(
                H, grad_H, invariants, grad_invariants, params,
                family, n_inv, stable_rhs, warm_start,
                h, tables, conserve_idx, tol, small, max_iter,
                Y0[i], t0, n_steps, n_mult, i,
                y_final, t_final, inv_error, iterations, max_multiplier, steps_done)
