"""Solving one step's nonlinear system: simplified Newton or the fixed point, with the
stopping rule of spec section 8.

Numba only. ``solve`` drives a family's residual map (maps.py) from an initial guess of
the coefficients to a converged iterate or a failure status; it knows nothing of the
time loop, predictors or step splitting (stepper.py).

Simplified Newton (spec 8, the default): with X_s = Ps^T Omega Is (tridiagonal) and
J0 = J Hess(H)(y0), M = I_{s n} - h X_s (x) J0 is factorised once per step, and each
iteration applies  coef <- coef + M^-1 vec(G(coef) - coef).  The fixed point applies
coef <- G(coef) (the paper's iteration, whose counts Table 2 reports).
"""
import math

import numpy as np
from numba import njit

from .codes import (FAMILY_LIM, SOLVER_NEWTON, STATUS_NONFINITE, STATUS_NOT_CONVERGED, STATUS_OK,
                    STATUS_SINGULAR)
from .linalg import lu_factor, lu_solve_factored
from .maps import EPS, condition_number, elim_map, elim_rounding, lim_map, lim_rounding

# The stopping rule's constants (spec 8; measured there, not tunables).
BAND_FACTOR = 4.0          # the rounding band is B = 4 omega ...
BAND_CAP = 1e-12           # ... and never wider than this (relative increment)
IN_BAND_STALLS = 2         # accept after this many in-band iterations that fail to improve the best in-band d
MAX_WITHOUT_PROGRESS = 6   # outside the band, fail after this many iterations without a new best d
MAX_CONDITION = 1e13       # an accepted alpha with cond(Gamma) above this is spurious
MAX_ETA_CORRECTION = 0.5   # ... and so is one with |h^(2(s-1-j)) alpha_j| above this


@njit(cache=True, error_model="numpy")
def newton_factor(hess_H, params, y, h, X, work):
    """Factorise M = I - h X (x) J0, J0 = J Hess(H)(y), into work.newton_matrix (spec 8).

    Index (j, p) of M is j n + p: row block j belongs to coefficient j. Returns
    STATUS_OK, STATUS_NONFINITE (Hessian not finite) or STATUS_SINGULAR.
    """
    n = y.shape[0]
    m = n // 2
    s = X.shape[0]
    hessian, jacobian, M = work.hessian, work.jacobian, work.newton_matrix
    hess_H(y, params, hessian)
    for q in range(n):
        for p in range(m):
            jacobian[p, q] = hessian[m + p, q]
            jacobian[m + p, q] = -hessian[p, q]
        for p in range(n):
            if not (abs(jacobian[p, q]) <= 1e308):
                return STATUS_NONFINITE
    for j in range(s):
        for i in range(s):
            factor = -h * X[j, i]
            for p in range(n):
                for q in range(n):
                    M[j * n + p, i * n + q] = factor * jacobian[p, q]
        for p in range(n):
            M[j * n + p, j * n + p] += 1.0
    if lu_factor(M, work.newton_pivots) != 0:
        return STATUS_SINGULAR
    return STATUS_OK


@njit(cache=True, error_model="numpy")
def _rounding_level(h, mult, solved, settings, tables, nu, s, work):
    """omega of spec 8: the relative size of the increments round-off alone produces.

    omega = 4 eps max_i (h max_l |f_{l,i}|)/sc_i  +  the multipliers' share:
      ELIM  max_{c,i} h w_c dalpha_c |gamma_{j_c,i}| / sc_i
      LIM   max_i h sum_a dlambda_a |phi_0^a_i| / sc_i
    solved: the last map solved its small system (else only the first term).
    Returns (omega, condition number of the small system or 0).
    """
    grads, scale, sizes, phi, gamma, h_powers = work.grads, work.scale, work.small_rounding, work.phi, work.gamma, work.h_powers
    n = scale.shape[0]
    m = n // 2
    omega = 0.0
    for i in range(n):
        partner = i + m if i < m else i - m   # |(J g)_i| = |g_partner|
        f_max = 0.0
        for l in range(grads.shape[0]):
            f_max = max(f_max, abs(grads[l, partner]))
        omega = max(omega, 4.0 * EPS * h * f_max / scale[i])
    cond = 0.0
    if not solved:
        return omega, cond
    if settings.family == FAMILY_LIM:
        n_tilde = nu + 1
        cond = lim_rounding(tables, n_tilde, s, work)
        for i in range(n):
            acc = 0.0
            for a in range(n_tilde):
                acc += sizes[0, a] * abs(phi[a, 0, i])
            omega = max(omega, h * acc / scale[i])
    elif nu > 0:
        cond = elim_rounding(h, mult, settings.stable_rhs != 0, tables, nu, s, work)
        for c in range(nu):
            j = s - nu + c
            for i in range(n):
                omega = max(omega, h * h_powers[c] * sizes[0, c] * abs(gamma[j, i]) / scale[i])
    return omega, cond


@njit(cache=True, error_model="numpy")
def solve(grad_H, grad_invariants, params, settings, tables, conserve_idx, work, y, h, coef, mult, cold):
    """Iterate a family's map from the guess coef to a converged iterate (spec 8).

    settings.solver: SOLVER_NEWTON (needs work.newton_matrix factorised for this y and h
    by newton_factor) or the fixed point. coef (s, n) and mult (alpha or lambda) in/out.
    cold: the stages start at y (coef = 0): ELIM keeps alpha = 0 for two sweeps.

    Stopping rule (spec 8), on d = max_{j,i} |h Delta_{j,i}| / sc_i, sc_i = max(|y_i|, |h G_0,i|):
      accept when d <= settings.tol (round-off);
      inside the rounding band d <= B = min(4 omega, 1e-12), accept after 2 iterations in a
      row that fail to improve the best in-band d;
      fail after 6 iterations without a new best d, at max_iter, or on NaN.
    An accepted ELIM iterate is rejected as spurious when cond(Gamma) > 1e13 or some
    |w_c alpha_c| > 0.5, and as singular when its Gamma could not be solved.

    Returns (status, iterations); work.info = [last d, cond(Gamma) or 0, iterations, last B].
    """
    n = y.shape[0]
    s = coef.shape[0]
    nu = conserve_idx.shape[0]
    is_lim = settings.family == FAMILY_LIM
    newton = settings.solver == SOLVER_NEWTON
    # Bound once: an attribute read inside the loop costs a reference count update per read.
    delta, scale, new_coef, info, h_powers = work.delta, work.scale, work.new_coef, work.info, work.h_powers
    newton_matrix, newton_pivots = work.newton_matrix, work.newton_pivots
    max_iter, tol = settings.max_iter, settings.tol
    for c in range(nu):
        h_powers[c] = h ** (2 * (nu - 1 - c))

    best = np.inf
    without_progress = 0
    best_in_band = np.inf
    stalls = 0
    band = 0.0
    d = np.inf
    accepted = False
    singular = 0
    iteration = 0
    for iteration in range(1, max_iter + 1):
        plain_sweep = cold and iteration <= 2
        if is_lim:
            singular = lim_map(grad_H, grad_invariants, params, y, h, coef, mult, tables, conserve_idx, work)
            if singular != 0:
                info[0], info[1], info[2], info[3] = d, np.inf, iteration, band
                return STATUS_SINGULAR, iteration
        else:
            singular = elim_map(grad_H, grad_invariants, params, y, h, coef, mult, plain_sweep,
                                settings.stable_rhs != 0, tables, conserve_idx, work)

        largest = 0.0
        for i in range(n):
            scale[i] = max(abs(y[i]), abs(h * new_coef[0, i]))
            largest = max(largest, scale[i])
        for i in range(n):
            if not (scale[i] > 0.0):
                # A component and its increment both exactly zero: measure it against the
                # state as a whole (NaN falls through to the finiteness test below).
                scale[i] = largest if largest > 0.0 else 1.0
        for j in range(s):
            for p in range(n):
                delta[j * n + p] = new_coef[j, p] - coef[j, p]
        if newton:
            lu_solve_factored(newton_matrix, newton_pivots, delta)
        d = 0.0
        for j in range(s):
            for p in range(n):
                value = abs(h * delta[j * n + p]) / scale[p]
                if not (value <= d):   # also catches NaN
                    d = value
                coef[j, p] += delta[j * n + p]
        if not (d <= 1e308):
            info[0], info[1], info[2], info[3] = d, 0.0, iteration, band
            return STATUS_NONFINITE, iteration
        if cold and not is_lim and nu > 0 and iteration == 3:
            # alpha has just switched on: the map changed, progress counts afresh
            best = np.inf
            without_progress = 0
            band = 0.0
        if d <= tol:
            accepted = True
            break
        if d <= BAND_CAP:
            if band == 0.0:
                # Estimated once per solve, at the first small increment: the iterates then
                # differ by less than 1e-12 relative, and so do their rounding levels.
                omega, _ = _rounding_level(h, mult, singular == 0 and not plain_sweep, settings, tables, nu, s,
                                           work)
                band = min(BAND_FACTOR * omega, BAND_CAP)
            if d <= band:
                if d < best_in_band:
                    best_in_band = d
                    stalls = 0
                else:
                    stalls += 1
                    if stalls >= IN_BAND_STALLS:
                        accepted = True
                        break
        if d < best:
            best = d
            without_progress = 0
        else:
            without_progress += 1
            if without_progress >= MAX_WITHOUT_PROGRESS:
                break

    info[0], info[1], info[2], info[3] = d, 0.0, iteration, band
    if not accepted:
        return STATUS_NOT_CONVERGED, iteration
    if is_lim or nu == 0 or (cold and iteration <= 2):
        return STATUS_OK, iteration
    if singular != 0:
        info[1] = np.inf
        return STATUS_SINGULAR, iteration
    # Spurious solutions (spec 8): a nearly singular Gamma, or a correction as large as the term.
    cond = condition_number(work, nu, False)
    info[1] = cond
    if not (cond <= MAX_CONDITION):
        return STATUS_SINGULAR, iteration
    for c in range(nu):
        if not (abs(h_powers[c] * mult[c]) <= MAX_ETA_CORRECTION):
            return STATUS_SINGULAR, iteration
    return STATUS_OK, iteration
