"""One step of HBVM / ELIM / LIM by fixed-point iteration, and the time loop.

Numba only: plain floats and C-contiguous float64 arrays in, status codes out. The
problem's functions arrive as ``types.FunctionType`` arguments (see signatures.py),
so this module is compiled once and cached for every problem.

Notation follows spec sections 1-4 (``../shared/spec/methods.md``): m degrees of
freedom, n = 2m, k quadrature nodes for H, r nodes for the invariants, s Legendre
coefficients, nu imposed invariants.

The unknowns iterated on are the *effective* coefficients ``coef[j] = eta_j gamma_j``
(ELIM; eta_j = 1 for HBVM) or ``coef[0] = gamma_0 - phi_0 lambda, coef[j>0] = gamma_j``
(LIM), so that the stages are always ``u(c h) = y0 + h sum_j (int_0^c P_j) coef[j]``
and the new state is ``y1 = y0 + h coef[0]``.
"""
import warnings

import numpy as np
from numba import njit, types
from numba.core.errors import NumbaExperimentalFeatureWarning

from .linalg import cholesky_solve, lu_solve
from .signatures import (GRAD_H_TYPE, GRAD_INVARIANTS_TYPE, H_TYPE, INT_VECTOR,
                         INVARIANTS_TYPE, MATRIX, VECTOR)

# First-class function types are the documented way to pass functions to cached
# kernels; Numba still labels them experimental on every compile.
warnings.filterwarnings("ignore", category=NumbaExperimentalFeatureWarning, module=__name__)
warnings.filterwarnings("ignore", message="First-class function type feature is experimental")

# Status codes returned by the kernels (elimfast.integrate turns them into exceptions).
STATUS_OK = 0
STATUS_NOT_CONVERGED = 1
STATUS_SINGULAR = 2
STATUS_NONFINITE = 3

# Kernel families: ELIM covers GAUSS and HBVM (nu = 0); LIM covers GHBVM.
FAMILY_ELIM = 0
FAMILY_LIM = 1


# Non-improving iterations (below the stagnation threshold) that end an iteration.
# One is not enough: the convergence is often a staircase whose increments rise
# briefly (e.g. 3.5e-13 then 5.0e-13 then 1e-15 on Kepler, HBVM(7,4)), and stopping
# there leaves the iterate 1e-13 from the fixed point.
STALLS_TO_STOP = 2


@njit(cache=True, inline="always", error_model="numpy")
def _stopping_rule(delta, best, stalls, tol_abs, small_abs):
    """Spec 3 "practical points" and spec 7: returns (stop, best, stalls).

    Stop when the increment delta is at round-off (<= tol_abs), or when it has failed
    STALLS_TO_STOP times in a row to improve on the best increment so far, that best
    being below small_abs (rounding noise dominates: further iterations cannot help).
    """
    if delta <= tol_abs:
        return True, delta, 0
    if delta < best:
        return False, delta, 0
    if best <= small_abs:
        return stalls + 1 >= STALLS_TO_STOP, best, stalls + 1
    return False, best, 0


@njit(cache=True, inline="always", error_model="numpy")
def _stages(y, h, integrals, coef, n_coef, out):
    """out[l] = y + h sum_{j<n_coef} integrals[l, j] coef[j]   (spec 2: u_l = u(c_l h))."""
    n = y.shape[0]
    for l in range(out.shape[0]):
        for i in range(n):
            acc = 0.0
            for j in range(n_coef):
                acc += integrals[l, j] * coef[j, i]
            out[l, i] = y[i] + h * acc


@njit(cache=True, inline="always", error_model="numpy")
def _project(projection, values, n_degrees, out):
    """out[j] = sum_l projection[j, l] values[l] = sum_l b_l P_j(c_l) values[l], j < n_degrees.

    The discrete Legendre coefficients of spec 2 (gamma_j) and 3 (phi_j) of the rows of
    values (n_nodes, n); projection (>= n_degrees, n_nodes) holds b_l P_j(c_l).
    Scalar accumulators, four components at a time: accumulating into out[j, i]
    chains every update through memory (3x slower), and four independent sums let
    LLVM use one vector FMA for them.
    """
    n = values.shape[1]
    n_nodes = values.shape[0]
    n4 = n - n % 4
    for j in range(n_degrees):
        for i in range(0, n4, 4):
            acc0 = 0.0
            acc1 = 0.0
            acc2 = 0.0
            acc3 = 0.0
            for l in range(n_nodes):
                w = projection[j, l]
                acc0 += w * values[l, i]
                acc1 += w * values[l, i + 1]
                acc2 += w * values[l, i + 2]
                acc3 += w * values[l, i + 3]
            out[j, i] = acc0
            out[j, i + 1] = acc1
            out[j, i + 2] = acc2
            out[j, i + 3] = acc3
        for i in range(n4, n):
            acc = 0.0
            for l in range(n_nodes):
                acc += projection[j, l] * values[l, i]
            out[j, i] = acc


@njit(cache=True, inline="always", error_model="numpy")
def _apply_J(projected, n_degrees, out):
    """out[j] = J projected[j], J = [[0, I], [-I, 0]] (spec 1)."""
    m = projected.shape[1] // 2
    for j in range(n_degrees):
        for i in range(m):
            out[j, i] = projected[j, m + i]
            out[j, m + i] = -projected[j, i]


@njit(cache=True, inline="always", error_model="numpy")
def _update_coef(coef, new_coef, n_coef, h, y):
    """Copy new_coef into coef; return the largest relative stage increment.

    Component i of every coefficient is measured against
    max(|y_i|, |h new_coef[0, i]|): relative to the state where it is not near zero,
    to the step's own increment where it is. One common scale fails on problems whose
    components differ in size by orders (the solar system: positions ~30, momenta
    ~1e-5 stopped iterating with the momenta far from converged).
    """
    delta = 0.0
    for i in range(coef.shape[1]):
        scale = max(abs(y[i]), abs(h * new_coef[0, i]))
        for j in range(n_coef):
            d = abs(h * (new_coef[j, i] - coef[j, i]))
            if d != 0.0:
                d = d / scale if scale > 0.0 else np.inf
            if not (d <= delta):  # also catches NaN
                delta = d
            coef[j, i] = new_coef[j, i]
    return delta


@njit(cache=True, inline="always", error_model="numpy")
def elim_step(grad_H, grad_invariants, params, y, h, tables, conserve_idx, stable_rhs,
              coef, alpha, cold, tol, small, max_iter, work):
    """One ELIM(r,k,s) step by fixed-point iteration (spec section 3; HBVM when nu = 0, spec 2).

    Iterates  coef_j = eta_j gamma_j(u),  gamma_j = sum_l b_l Ps[l,j] J grad H(u_l),
    eta_j = 1 - h^{2(s-1-j)} alpha_j for the last nu coefficients, where alpha solves
    Gamma alpha = bvec (spec 3). bvec is the stable tail -sum_{j=s}^{k-1} phi_j^T gamma_j
    of spec 3b when stable_rhs is true, the paper's sum_{j<s} phi_j^T gamma_j otherwise.

    Shapes: y (n,); tables = (projection (k, k): b_l P_j(c_l) indexed [j, l],
    Is (k, s), projection_hat (r, r): bhat_i P_j(chat_i) indexed [j, i], Ihat (r, s));
    conserve_idx (nu,);
    coef (s, n) in/out (initial guess, then the converged coefficients); alpha (nu,)
    in/out. work: the caller-allocated workspace tuple built by time_loop.
    (Tables and workspace travel as tuples so the call stays under CPython's 30
    arguments, above which it cannot be inlined.)
    cold: the stages start at y0, so Gamma is singular on the first iteration
    (spec 3, "practical points"): alpha = 0 there.

    Stopping rule (spec 3 and 7, see _stopping_rule and _update_coef): stop when the
    relative stage increment max_i |h d coef_i| / max(|y_i|, |h coef_0,i|) is at
    round-off (<= tol), or when it has stopped improving after having fallen below
    small; fail after max_iter.

    Returns (status, iterations). y1 = y + h coef[0].
    """
    projection, Is, projection_hat, Ihat = tables
    (u, grads, proj, gamma, uhat, grads_hat, inv_grads, phi, gamma_hat,
     big_gamma, bvec, new_coef, h_powers) = work
    n = y.shape[0]
    k = Is.shape[0]
    r = Ihat.shape[0]
    s = coef.shape[0]
    nu = conserve_idx.shape[0]
    shared_nodes = r == k
    # Legendre coefficients needed: the stable tail runs up to k-1 (r-1 at the r nodes).
    n_gamma = k if (nu > 0 and stable_rhs and shared_nodes) else s
    n_phi = r if (nu > 0 and stable_rhs) else s

    best = np.inf
    stalls = 0
    gamma_singular = False
    for iteration in range(1, max_iter + 1):
        _stages(y, h, Is, coef, s, u)
        for l in range(k):
            grad_H(u[l], params, grads[l])
        _project(projection, grads, n_gamma, proj)
        _apply_J(proj, n_gamma, gamma)

        if nu > 0:
            if shared_nodes:
                stage_hat = u
            else:
                _stages(y, h, Ihat, coef, s, uhat)
                stage_hat = uhat
            for i in range(r):
                grad_invariants(stage_hat[i], params, inv_grads)
                for a in range(nu):
                    for p in range(n):
                        grads_hat[a, i, p] = inv_grads[conserve_idx[a], p]
            for a in range(nu):
                _project(projection_hat, grads_hat[a], n_phi, phi[a])
            for col in range(nu):
                j = s - nu + col
                for a in range(nu):
                    acc = 0.0
                    for p in range(n):
                        acc += phi[a, j, p] * gamma[j, p]
                    big_gamma[a, col] = h_powers[col] * acc
            if stable_rhs:
                if shared_nodes:
                    tail = gamma
                    n_tail = k
                else:
                    # Spec 3b for r != k: the tail with J grad H taken at the r nodes too.
                    for i in range(r):
                        grad_H(uhat[i], params, grads_hat[nu, i])
                    _project(projection_hat, grads_hat[nu], r, proj)
                    _apply_J(proj, r, gamma_hat)
                    tail = gamma_hat
                    n_tail = r
                for a in range(nu):
                    acc = 0.0
                    for j in range(s, n_tail):
                        for p in range(n):
                            acc += phi[a, j, p] * tail[j, p]
                    bvec[a] = -acc
            else:
                for a in range(nu):
                    acc = 0.0
                    for j in range(s):
                        for p in range(n):
                            acc += phi[a, j, p] * gamma[j, p]
                    bvec[a] = acc
            if cold and iteration <= 2:
                # A cold start's stages are constant in c on iteration 1 and linear on
                # iteration 2 (coef_j, j >= 1, are still rounding noise), so phi_j and
                # gamma_j for j >= 2 vanish and Gamma is singular or pure noise (spec 3,
                # "practical points", generalised): plain HBVM sweeps until the stages
                # have full degree.
                for a in range(nu):
                    alpha[a] = 0.0
            else:
                # Keep the previous alpha if Gamma cannot be solved on the way; only a
                # Gamma still singular at the converged iterate is an error.
                gamma_singular = lu_solve(big_gamma, bvec) != 0
                if not gamma_singular:
                    for a in range(nu):
                        alpha[a] = bvec[a]

        for j in range(s):
            eta = 1.0
            if j >= s - nu:
                eta = 1.0 - h_powers[j - (s - nu)] * alpha[j - (s - nu)]
            for p in range(n):
                new_coef[j, p] = eta * gamma[j, p]
        delta = _update_coef(coef, new_coef, s, h, y)
        if not (delta <= 1e308):
            return STATUS_NONFINITE, iteration
        stop, best, stalls = _stopping_rule(delta, best, stalls, tol, small)
        if stop:
            if gamma_singular:
                return STATUS_SINGULAR, iteration
            return STATUS_OK, iteration
    return STATUS_NOT_CONVERGED, max_iter


@njit(cache=True, inline="always", error_model="numpy")
def lim_step(grad_H, grad_invariants, params, y, h, tables, conserve_idx,
             coef, lam, tol, small, max_iter, work):
    """One LIM(r,k,s) step by fixed-point iteration (spec section 4).

    Ltilde = (H, L_conserve...) has nu + 1 components. Iterates
        gamma_j = sum_l b_l Ps[l,j] J grad H(u_l)                 (k nodes)
        phi_j   = sum_i bhat_i P_j(chat_i) grad Ltilde(uhat_i)    (r nodes)
        (phi_0^T phi_0) lambda = sum_{j<s} phi_j^T gamma_j        (SPD solve)
        coef_0 = gamma_0 - phi_0 lambda,  coef_j = gamma_j
    with the same stopping rule as elim_step. lam (nu+1,) in/out; tables and work
    as for elim_step (grads_hat (nu+2, r, n), phi (nu+1, >= s, n), and the small
    matrix and vector serve as the Gram matrix and right-hand side).
    Returns (status, iterations). y1 = y + h coef[0].
    """
    projection, Is, projection_hat, Ihat = tables
    (u, grads, proj, gamma, uhat, grads_hat, inv_grads, phi, gamma_hat,
     gram, rhs, new_coef, h_powers) = work
    n = y.shape[0]
    k = Is.shape[0]
    r = Ihat.shape[0]
    s = coef.shape[0]
    n_tilde = conserve_idx.shape[0] + 1
    shared_nodes = r == k

    best = np.inf
    stalls = 0
    for iteration in range(1, max_iter + 1):
        _stages(y, h, Is, coef, s, u)
        for l in range(k):
            grad_H(u[l], params, grads[l])
        _project(projection, grads, s, proj)
        _apply_J(proj, s, gamma)

        if shared_nodes:
            stage_hat = u
            for i in range(r):
                for p in range(n):
                    grads_hat[0, i, p] = grads[i, p]
        else:
            _stages(y, h, Ihat, coef, s, uhat)
            stage_hat = uhat
            for i in range(r):
                grad_H(uhat[i], params, grads_hat[0, i])
        if n_tilde > 1:
            for i in range(r):
                grad_invariants(stage_hat[i], params, inv_grads)
                for a in range(1, n_tilde):
                    for p in range(n):
                        grads_hat[a, i, p] = inv_grads[conserve_idx[a - 1], p]
        for a in range(n_tilde):
            _project(projection_hat, grads_hat[a], s, phi[a])
        for a in range(n_tilde):
            for c in range(n_tilde):
                acc = 0.0
                for p in range(n):
                    acc += phi[a, 0, p] * phi[c, 0, p]
                gram[a, c] = acc
            acc = 0.0
            for j in range(s):
                for p in range(n):
                    acc += phi[a, j, p] * gamma[j, p]
            rhs[a] = acc
        if cholesky_solve(gram, rhs) != 0:
            return STATUS_SINGULAR, iteration
        for a in range(n_tilde):
            lam[a] = rhs[a]

        for j in range(s):
            for p in range(n):
                new_coef[j, p] = gamma[j, p]
        for a in range(n_tilde):
            for p in range(n):
                new_coef[0, p] -= lam[a] * phi[a, 0, p]
        delta = _update_coef(coef, new_coef, s, h, y)
        if not (delta <= 1e308):
            return STATUS_NONFINITE, iteration
        stop, best, stalls = _stopping_rule(delta, best, stalls, tol, small)
        if stop:
            return STATUS_OK, iteration
    return STATUS_NOT_CONVERGED, max_iter


@njit(cache=True, inline="always", error_model="numpy")
def _kahan_add(value, compensation, increment):
    """Compensated summation (spec 7): returns the new (value, compensation)."""
    corrected = increment + compensation
    new_value = value + corrected
    return new_value, (value - new_value) + corrected


@njit(cache=True, inline="always", error_model="numpy")
def _sample(H, invariants, params, y, t, index, t_out, y_out, inv_out, inv_values):
    t_out[index] = t
    for p in range(y.shape[0]):
        y_out[index, p] = y[p]
    inv_out[index, 0] = H(y, params)
    invariants(y, params, inv_values)
    for a in range(inv_values.shape[0]):
        inv_out[index, 1 + a] = inv_values[a]


TIME_LOOP_SIGNATURE = types.int64(
    H_TYPE, GRAD_H_TYPE, INVARIANTS_TYPE, GRAD_INVARIANTS_TYPE, VECTOR,   # problem
    types.int64, types.int64, types.int64, types.int64,                   # family, n_inv, stable_rhs, warm_start
    types.float64, MATRIX, MATRIX, MATRIX, MATRIX,                        # h, projection, Is, projection_hat, Ihat
    INT_VECTOR, types.float64, types.float64, types.int64,                # conserve_idx, tol, small, max_iter
    VECTOR, VECTOR, VECTOR, MATRIX, VECTOR,                               # y, y_comp, clock, coef, multipliers
    types.int64, types.int64, types.int64, types.int64,                   # step_start, n_steps, n_total, store_every
    VECTOR, MATRIX, MATRIX, MATRIX, INT_VECTOR, INT_VECTOR,               # outputs, progress
)


@njit(TIME_LOOP_SIGNATURE, cache=True, nogil=True, error_model="numpy")
def time_loop(H, grad_H, invariants, grad_invariants, params,
              family, n_inv, stable_rhs, warm_start,
              h, projection, Is, projection_hat, Ihat,
              conserve_idx, tol, small, max_iter,
              y, y_comp, clock, coef, multipliers,
              step_start, n_steps, n_total, store_every,
              t_out, y_out, inv_out, mult_out, iter_out, progress):
    """Run n_steps steps of one method in one call (spec sections 2-4 and 7).

    State, updated in place so that consecutive calls continue one run exactly:
      y (n,), y_comp (n,): the state and its Kahan compensation;
      clock (2,): [t, its compensation]; coef (s, n): the last step's coefficients;
      multipliers: alpha (nu,) for ELIM, lambda (nu+1,) for LIM.
    Steps are numbered globally from step_start (0 for a new run) to step_start +
    n_steps; n_total is the run's total. Each step starts from the previous step's
    coefficients when warm_start is set (and step > 0), else from coef = 0, i.e. every
    stage at y_n.

    Outputs, written from index 0 on:
      iter_out (n_steps,) iterations per step; mult_out (n_steps, len(multipliers));
      a sample after every global step that is a multiple of store_every, and after
      the last step of the run: t_out (n_samples,), y_out (n_samples, n),
      inv_out (n_samples, 1 + n_inv) holding H then the problem's invariants.
    progress (2,): [steps done in this call, samples written in this call].

    Returns a status code: STATUS_OK, or the failing step's STATUS_NOT_CONVERGED,
    STATUS_SINGULAR or STATUS_NONFINITE; y, clock and coef then hold the last good
    step (the failed step is not applied), and progress says how far it got.
    """
    n = y.shape[0]
    k = Is.shape[0]
    r = Ihat.shape[0]
    s = coef.shape[0]
    nu = conserve_idx.shape[0]
    n_tilde = nu + 1 if family == FAMILY_LIM else nu
    n_big = max(k, r, s)

    # Workspace, allocated once per call: nothing is allocated inside the loop.
    u = np.zeros((k, n))
    grads = np.zeros((k, n))
    proj = np.zeros((n_big, n))
    gamma = np.zeros((n_big, n))
    gamma_hat = np.zeros((n_big, n))
    uhat = np.zeros((r, n))
    grads_hat = np.zeros((n_tilde + 1, r, n))
    inv_grads = np.zeros((n_inv, n))
    inv_values = np.zeros(n_inv)
    phi = np.zeros((max(n_tilde, 1), n_big, n))
    small_matrix = np.zeros((max(n_tilde, 1), max(n_tilde, 1)))
    small_vector = np.zeros(max(n_tilde, 1))
    new_coef = np.zeros((s, n))
    saved_coef = np.zeros((s, n))
    saved_mult = np.zeros(multipliers.shape[0])
    h_powers = np.zeros(max(nu, 1))
    for col in range(nu):
        h_powers[col] = h ** (2 * (nu - 1 - col))
    tables = (projection, Is, projection_hat, Ihat)
    work = (u, grads, proj, gamma, uhat, grads_hat, inv_grads, phi, gamma_hat,
            small_matrix, small_vector, new_coef, h_powers)

    n_samples = 0
    progress[0] = 0
    progress[1] = 0
    for step in range(n_steps):
        global_step = step_start + step
        cold = not (warm_start and global_step > 0)
        for j in range(s):
            for p in range(n):
                saved_coef[j, p] = coef[j, p]
                if cold:
                    coef[j, p] = 0.0
        for a in range(multipliers.shape[0]):
            saved_mult[a] = multipliers[a]
            if cold:
                multipliers[a] = 0.0
        if family == FAMILY_LIM:
            status, iterations = lim_step(
                grad_H, grad_invariants, params, y, h, tables, conserve_idx,
                coef, multipliers, tol, small, max_iter, work)
        else:
            status, iterations = elim_step(
                grad_H, grad_invariants, params, y, h, tables, conserve_idx,
                stable_rhs != 0, coef, multipliers, cold, tol, small, max_iter, work)
        iter_out[step] = iterations
        if status != STATUS_OK:
            # Leave the state at the last good step so the caller can report or resume.
            for j in range(s):
                for p in range(n):
                    coef[j, p] = saved_coef[j, p]
            for a in range(multipliers.shape[0]):
                multipliers[a] = saved_mult[a]
            return status
        for a in range(multipliers.shape[0]):
            mult_out[step, a] = multipliers[a]
        for p in range(n):
            y[p], y_comp[p] = _kahan_add(y[p], y_comp[p], h * coef[0, p])
        clock[0], clock[1] = _kahan_add(clock[0], clock[1], h)
        for p in range(n):
            if not (abs(y[p]) <= 1e308):
                return STATUS_NONFINITE
        progress[0] = step + 1
        done = global_step + 1
        if done % store_every == 0 or done == n_total:
            _sample(H, invariants, params, y, clock[0], n_samples,
                    t_out, y_out, inv_out, inv_values)
            n_samples += 1
            progress[1] = n_samples
    return STATUS_OK
