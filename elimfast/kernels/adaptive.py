"""Adaptive steps, output at requested times and events (docs/adaptive.md).

Numba only, like stepper.py, whose ``try_step`` takes every step here: the controllers
only choose h. HBVM, ELIM and LIM keep H and the imposed invariants at every step
whatever its size, so h may change at every step without losing conservation.

Controllers (``options[OPT_CONTROL]``):
  CONTROL_ERROR (default): the local error estimate of docs/adaptive.md,
      E = C_s h || (h J(u(h/2)))^s gamma_s ||,  C_s = sqrt(2s+1) s! / (2s+1)!,
    in the norm max_i |v_i| / (atol + rtol max(|y0_i|, |y1_i|)); accept when E <= 1;
    h_new = h min(2, max(0.2, min(F, F (h / h_prev) (E_prev / E)^(1/(2s+1))))),
    F = 0.9 E^(-1/(2s+1)) (Gustafsson's factor: without it, 662 rejections at e = 0.99).
    With ``verify``, E comes from step doubling instead (two extra half steps).
    A step whose solve fails is retried with half the step.
  CONTROL_TIME_SCALE: Hairer & Soderlind's time-reversible steps for a problem with a
    time scale sigma(y): rho_1/2 = 1/sigma(y0) + eps G(y0)/2, h_n = eps / rho_n+1/2,
    rho_n+3/2 = rho_n+1/2 + eps G(y_n+1), G = -grad sigma . f / sigma. No estimate,
    no rejection; a step whose solve fails is split (try_step).
  CONTROL_FIXED: h constant (used when a fixed-step run asks for output times or events).
The last step is clipped so that t_end is reached exactly.

Output at requested times and events use side steps: from the start of the step that
contains the time, a step of the method itself to that time, started from the step's
own polynomial; the side state then has the integrator's accuracy and keeps every
invariant (the stage polynomial between steps keeps neither). Events g(y) = 0 are
bracketed by the sign of g at the step points, located on the stage polynomial, then
refined by Newton iterations whose every value of g is taken at a side step.
"""
import math
import warnings

import numpy as np
from numba import njit, types
from numba.core.errors import NumbaExperimentalFeatureWarning

# The layout of the arrays this kernel shares with elimfast.adaptive (controls, options, control_state,
# counters, progress, diagnostics) is codes.py's, which the Python layer reads without loading this kernel.
from .codes import (internal, STATUS_NONFINITE, STATUS_NOT_CONVERGED, STATUS_OK, STATUS_TIME_SCALE,  # noqa: F401
                    CONTROL_ERROR, CONTROL_FIXED, CONTROL_TIME_SCALE, CTL_RTOL, CTL_ATOL, CTL_EPSILON, CTL_T_END,
                    CTL_H_MAX, CTL_H_TARGET, OPT_CONTROL, OPT_VERIFY, OPT_STORE_EVERY, OPT_N_TOTAL,
                    CS_H_NEXT, CS_H_PREV, CS_ERR_PREV, CS_RHO, CS_REJECTED, CNT_STEPS,
                    CNT_REJECTED, CNT_FAILED, CNT_SPLIT, CNT_ITERATIONS, CNT_SIDE_STEPS, CNT_SIDE_ITERATIONS,
                    CNT_NEXT_EVAL, CNT_EVENTS, CNT_FACTORISATIONS, CNT_ESTIMATE_HESSIANS, CNT_SIDE_FALLBACKS,
                    CNT_ENERGY_PROJECTIONS, N_PROGRESS, COLLAPSED_STEP, DIAG_DEPTH, DIAG_INCREMENT,
                    DIAG_ITERATIONS, DIAG_STEP, DIAG_TIME, N_DIAGNOSTICS)
from .quadrature import legendre_table
from .signatures import (COMPLEX_MATRIX, COMPLEX_VECTOR, GRAD_H_TYPE, GRAD_INVARIANTS_TYPE, H_TYPE, HESS_H_TYPE,
                         INT_VECTOR, INVARIANTS_TYPE, MATRIX, VECTOR)
from .stepper import (_copy, _sample, energy_projection_arrays, extrapolate, kahan_add, newton_eigenvalues,  # noqa: F401
                      project_energy, record_multipliers, restore_newton_matrix, try_step)
from .workspace import (Settings, Tables, borrow_tables, borrow_workspace, borrowed, by_ref, keep_alive,
                        make_workspace)

warnings.filterwarnings("ignore", category=NumbaExperimentalFeatureWarning, module=__name__)
warnings.filterwarnings("ignore", message="First-class function type feature is experimental")

SAFETY = 0.9
MIN_FACTOR = 0.2
MAX_FACTOR = 2.0
MAX_CONSECUTIVE_FAILURES = 40      # halvings of one step before the run fails
# The solver's convergence limits the step too (docs/adaptive.md#controller): an accepted step
# whose solve took more than this fraction of max_iter iterations makes the next one smaller
# (SLOW_SOLVE_FACTOR), more than NO_GROWTH_FRACTION keeps it from growing. At loose
# tolerances the error estimate allows steps at which simplified Newton on ELIM converges
# linearly at rate ~0.5 (it does not see alpha's dependence on the stages): half the solves
# failed at max_iter = 30 and were halved (Kepler e = 0.99, EHBVM(8,4) imposing L and A_y,
# rtol 1e-6: 69 failed solves and 5169 iterations over 3 periods; with this, 19 and 3430).
# Lower fractions cut more (1/3 and 1/4: 9 and 2920) but also held back steps at tight
# tolerances, where up to 14 iterations occur at pericentres: the 1000-period e = 0.9 run
# then ended 1.5e-8 from its start instead of 5e-9.
SLOW_SOLVE_FRACTION = 0.5
NO_GROWTH_FRACTION = 1.0 / 3.0
SLOW_SOLVE_FACTOR = 0.8
EVENT_NEWTON_STEPS = 6             # side steps to refine one event
POLYNOMIAL_ROOT_ITERATIONS = 60


@njit(cache=True)
def error_constant(s):
    """C_s = sqrt(2s+1) s! / (2s+1)! of the error estimate."""
    value = math.sqrt(2.0 * s + 1.0)
    for i in range(s + 1, 2 * s + 2):
        value /= i
    return value


@internal
def _apply_jacobian(hessian, v, out):
    """out = J Hess v with J = [[0, I], [-I, 0]] (y = (q, p))."""
    n = v.shape[0]
    m = n // 2
    for i in range(n):
        acc = 0.0
        row = i + m if i < m else i - m
        for j in range(n):
            acc += hessian[row, j] * v[j]
        out[i] = acc if i < m else -acc


@internal
def stage_at(tau, y, h, coef, integrals, out):
    """u(tau h) = y + h sum_j coef_j int_0^tau P_j: the stage polynomial of a step (docs/methods.md).

    int_0^tau P_0 = tau; for j >= 1, (P_{j+1}(tau)/sqrt(2j+3) - P_{j-1}(tau)/sqrt(2j-1)) /
    (2 sqrt(2j+1)) (quadrature.legendre_integral_table's closed form, without its allocation:
    the kernels' internal functions run without reference counting, codes.internal).
    integrals (3, s + 1) scratch: row 0 the integrals, row 1 holds tau, row 2 P_0..P_s(tau).
    """
    s = coef.shape[0]
    n = y.shape[0]
    point = integrals[1, :1]
    point[0] = tau
    values = integrals[2:3]
    legendre_table(point, s + 1, values)
    table = integrals[0]
    table[0] = tau
    for j in range(1, s):
        table[j] = (values[0, j + 1] / math.sqrt(2.0 * j + 3.0) - values[0, j - 1] / math.sqrt(2.0 * j - 1.0)) \
            / (2.0 * math.sqrt(2.0 * j + 1.0))
    for p in range(n):
        acc = 0.0
        for j in range(s):
            acc += table[j] * coef[j, p]
        out[p] = y[p] + h * acc


@internal
def error_estimate(hess_H, params, tables, work, y0, y1, h, coef, rtol, atol, scratch, hessian, integrals):
    """E = C_s h || (h J(u(h/2)))^s gamma_s || (docs/adaptive.md), the last step's
    local error estimate in the weighted max norm. gamma_s = J sum_l b_l P_s(c_l) grad H(u_l)
    from the gradients of the last iteration (work.grads, no new evaluation); needs k > s.
    scratch (3, n); hessian (n, n); integrals (3, s + 1) (stage_at)."""
    n = y0.shape[0]
    s = coef.shape[0]
    m = n // 2
    projection, grads = tables.projection, work.grads
    k = grads.shape[0]
    v, w, mid = scratch[0], scratch[1], scratch[2]
    for p in range(n):
        acc = 0.0
        for l in range(k):
            acc += projection[s, l] * grads[l, p]
        w[p] = acc
    for p in range(m):   # gamma_s = J w
        v[p] = w[p + m]
        v[p + m] = -w[p]
    stage_at(0.5, y0, h, coef, integrals, mid)
    hess_H(mid, params, hessian)
    for _ in range(s):
        _apply_jacobian(hessian, v, w)
        for p in range(n):
            v[p] = h * w[p]
    largest = 0.0
    for p in range(n):
        weight = atol + rtol * max(abs(y0[p]), abs(y1[p]))
        largest = max(largest, abs(v[p]) / weight)
    return error_constant(s) * abs(h) * largest


@internal
def _time_scale_rate(grad_H, time_scale, params, y, scratch):
    """(sigma(y), G(y)) with G = -grad sigma . f / sigma, f = J grad H (docs/adaptive.md).
    scratch (2, n + 1): time_scale writes [sigma, grad sigma] into row 0."""
    n = y.shape[0]
    m = n // 2
    out, grad = scratch[0], scratch[1]
    time_scale(y, params, out)
    grad_H(y, params, grad[:n])
    acc = 0.0
    for p in range(m):   # f_q = dH/dp, f_p = -dH/dq
        acc += out[1 + p] * grad[m + p] - out[1 + m + p] * grad[p]
    return out[0], -acc / out[0]


@internal
def side_step(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
              y_from, comp_from, t_from, position, h_step, coef_step, extra_step, mult_step, h_side, newton_base,
              y_side, side_comp, side_clock, side_coef, side_extra, side_mult, side_last_h, diagnostics):
    """A step of the method itself of size h_side from a point of a step of size h_step:
    its start (position 0, h_side > 0) or its end (position 1, h_side < 0, backwards),
    started from the step's own polynomial (docs/adaptive.md) with its extra Legendre
    terms extra_step (stepper.extra_terms, the predictor's; zero without the predictor).
    Those saved 5-14% of the side steps' iterations, measured (NUMBA_DISABLE_JIT) with 80
    output times over a period of Kepler e = 0.9: adaptive EHBVM(8,4) imposing L, A_y at
    rtol 1e-14, 3.81 -> 3.26 per side step; HBVM(8,4) at 1e-12, 3.76 -> 3.56; and at 137
    times in 100 fixed steps h = 0.1 of EHBVM(12,3), e = 0.6: 3.58 -> 3.37. work and
    newton_base are the side steps' own (adaptive_loop): nothing of the main run changes.
    Returns (status, iterations); the state is y_side (side_extra: scratch, the side
    step's own extra terms, which side steps do not compute)."""
    _copy(y_from, y_side)
    _copy(comp_from, side_comp)
    side_clock[0] = t_from
    side_clock[1] = 0.0
    extrapolate(tables, work, position, h_side / h_step, coef_step, extra_step, extra_step.shape[0], side_coef)
    _copy(mult_step, side_mult)
    side_last_h[0] = h_side
    status, iterations, _ = try_step(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
                                     y_side, side_comp, side_clock, side_coef, side_extra, side_mult, h_side,
                                     side_last_h, newton_base, np.bool_(True), diagnostics, np.bool_(False),
                                     settings.max_halvings > 0)
    return status, iterations


@internal
def dense_state(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
                y_start, comp_start, t_start, y_end, comp_end, t_end, h, coef, coef_extra, mult, offset, newton_base,
                y_side, side_comp, side_clock, side_coef, side_extra, side_mult, side_last_h, diagnostics, integrals,
                counters):
    """The state at offset (0 < offset < h) into the step [t_start, t_start + h]: a side step
    from the nearer end, else from the other one (a side step of a tiny fraction of the
    step can fail: its Gamma is then nearly singular), else the stage polynomial
    (accurate to O(h^(s+1)) but keeping no invariant; counted in CNT_SIDE_FALLBACKS)."""
    for attempt in range(2):
        from_start = (offset <= 0.5 * h) == (attempt == 0)
        if from_start:
            status, used = side_step(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
                                     y_start, comp_start, t_start, 0.0, h, coef, coef_extra, mult, offset,
                                     newton_base, y_side, side_comp, side_clock, side_coef, side_extra, side_mult,
                                     side_last_h, diagnostics)
        else:
            status, used = side_step(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
                                     y_end, comp_end, t_end, 1.0, h, coef, coef_extra, mult, offset - h,
                                     newton_base, y_side, side_comp, side_clock, side_coef, side_extra, side_mult,
                                     side_last_h, diagnostics)
        counters[CNT_SIDE_STEPS] += 1
        counters[CNT_SIDE_ITERATIONS] += used
        if status == STATUS_OK:
            return
    counters[CNT_SIDE_FALLBACKS] += 1
    stage_at(offset / h, y_start, h, coef, integrals, y_side)


@njit(cache=True, inline="always", error_model="numpy")
def _whole_step_failure(diagnostics, t, h, increment, iterations):
    """diagnostics of a failure of the controller itself, at a whole step (depth 0) from t of size h:
    increment is what the status reports there (integrate.failure_message)."""
    diagnostics[DIAG_TIME] = t
    diagnostics[DIAG_STEP] = h
    diagnostics[DIAG_INCREMENT] = increment
    diagnostics[DIAG_DEPTH] = 0
    diagnostics[DIAG_ITERATIONS] = iterations


@internal
def _crossed(direction, g_old, g_new):
    """g went from g_old to g_new through 0 in the event's direction (+1 up, -1 down, 0 both)."""
    up = g_old < 0.0 and g_new >= 0.0
    down = g_old > 0.0 and g_new <= 0.0
    if direction > 0:
        return up
    if direction < 0:
        return down
    return up or down


ADAPTIVE_LOOP_SIGNATURE = types.int64(
    H_TYPE, GRAD_H_TYPE, HESS_H_TYPE, INVARIANTS_TYPE, GRAD_INVARIANTS_TYPE, VECTOR,   # problem
    INVARIANTS_TYPE, INVARIANTS_TYPE,                                                  # time_scale, events
    types.int64, types.int64, types.int64, types.int64, types.int64,                   # family, solver, stable_rhs,
    types.float64, types.int64, types.int64,                                           # warm_start, predictor, tol,
    #                                                                                    max_iter, max_halvings
    types.float64, MATRIX, MATRIX, MATRIX, MATRIX, MATRIX, VECTOR, VECTOR, MATRIX,    # h0 and the method's tables
    COMPLEX_VECTOR, COMPLEX_MATRIX, COMPLEX_MATRIX, VECTOR, MATRIX, MATRIX,
    INT_VECTOR,                                                                        # conserve_idx
    VECTOR, INT_VECTOR, VECTOR, INT_VECTOR, INT_VECTOR,                                # controls, options, t_eval,
    #                                                                                    event direction, terminal
    VECTOR, VECTOR, VECTOR, MATRIX, MATRIX, VECTOR, VECTOR, VECTOR, VECTOR, INT_VECTOR,  # y, y_comp, clock,
    #                                                                                    coef, coef_extra,
    #                                                                                    multipliers, last_h,
    #                                                                                    newton_base, control_state,
    #                                                                                    counters
    types.int64,                                                                       # max_steps
    VECTOR, VECTOR, MATRIX, INT_VECTOR, INT_VECTOR,                                    # per step: t, h, mult,
    #                                                                                    iterations, substeps
    VECTOR, MATRIX, MATRIX,                                                            # samples: t, y, invariants
    INT_VECTOR, VECTOR, MATRIX,                                                        # events: which, t, y
    INT_VECTOR, VECTOR,                                                                # progress, diagnostics
)


@njit(ADAPTIVE_LOOP_SIGNATURE, cache=True, nogil=True, error_model="numpy")
def adaptive_loop(H, grad_H, hess_H, invariants, grad_invariants, params, time_scale, events,
                  family, solver, stable_rhs, warm_start, predictor, tol, max_iter, max_halvings,
                  h0, projection, Is, projection_hat, Ihat, X, abs_projection_hat, predictor_nodes, predictor_basis,
                  newton_values, newton_vectors, newton_inverse, newton_weights, Is_low, Ihat_low,
                  conserve_idx,
                  controls, options, t_eval, event_direction, event_terminal,
                  y, y_comp, clock, coef, coef_extra, multipliers, last_h, newton_base, control_state, counters,
                  max_steps,
                  step_t, step_h, mult_out, iter_out, substeps_out,
                  t_out, y_out, inv_out,
                  event_out, event_t_out, event_y_out,
                  progress, diagnostics):
    """Up to max_steps accepted steps of a run with varying h (module docstring), from and
    into the run's state (as stepper.time_loop, plus control_state and counters, see
    the CS_* and CNT_* constants), so that consecutive calls continue one run exactly.

    controls: CTL_*; options: OPT_* (the controller, step doubling, store_every, and for
    CONTROL_FIXED the run's total number of steps). h0: the first step (CONTROL_ERROR,
    CONTROL_FIXED: the step). t_eval: requested output times, increasing, after t0 (empty:
    a sample every store_every steps and at t_end). events: g(y, params, out) for the
    len(event_direction) events; event_direction +1, -1, 0; event_terminal 1 stops the run.

    Per accepted step (index from 0 in this call): step_t the time at its end, step_h its
    size, mult_out, iter_out (every try, rejected ones included), substeps_out. Samples
    into t_out, y_out, inv_out; events into event_out (the event's index), event_t_out,
    event_y_out. The call returns when max_steps steps are done, when a sample or event
    buffer is full (their lengths), when the run is finished (progress[3] = 1), or on a
    failure (the status; the state is then the last good step's).
    """
    n = y.shape[0]
    k = Is.shape[0]
    r = Ihat.shape[0]
    s = coef.shape[0]
    n_inv = inv_out.shape[1] - 1
    n_events = event_direction.shape[0]
    control = options[OPT_CONTROL]
    verify = options[OPT_VERIFY] != 0
    store_every = options[OPT_STORE_EVERY]
    rtol, atol, epsilon, t_end, h_max = (controls[CTL_RTOL], controls[CTL_ATOL], controls[CTL_EPSILON],
                                         controls[CTL_T_END], controls[CTL_H_MAX])
    H_target = controls[CTL_H_TARGET]   # the energy projection's (NaN: none; stepper.project_energy)
    # Main steps: the error controller halves a failing step itself; the others split it.
    main_halvings = 0 if control == CONTROL_ERROR else max_halvings
    settings = Settings(family, solver, stable_rhs, warm_start, predictor, tol, max_iter, main_halvings)
    # Side steps start from their own step's polynomial (no predictor) and may split.
    side_settings = Settings(family, solver, stable_rhs, warm_start, 0, tol, max_iter, max_halvings)
    # Tables and workspaces are passed on by address (workspace.ByRef), as in stepper.time_loop.
    tables = by_ref(borrow_tables(Tables(projection, Is, projection_hat, Ihat, X, abs_projection_hat,
                                         predictor_nodes, predictor_basis, newton_values, newton_vectors,
                                         newton_inverse, newton_weights, Is_low, Ihat_low)))
    owners = make_workspace(n, k, r, s, conserve_idx.shape[0], family, n_inv, multipliers.shape[0],
                            newton_eigenvalues(settings, newton_values))
    work = by_ref(borrow_workspace(owners))
    # Side steps (output times, events) have a workspace and a Newton matrix of their own: in
    # the main one they replaced the matrix a later main step would have reused, so a run with
    # output times or events took other solves than the same run without (round-off apart).
    side_owners = make_workspace(n, k, r, s, conserve_idx.shape[0], family, n_inv, multipliers.shape[0],
                                 newton_eigenvalues(settings, newton_values))
    side_work = by_ref(borrow_workspace(side_owners))
    side_base = np.zeros(n + 3)
    n_mult = multipliers.shape[0]
    inv_values = np.zeros(n_inv)
    # The step's start (for rejection, side steps and events) and the side steps' state.
    y_back, comp_back, coef_back, mult_back = np.empty(n), np.empty(n), np.empty((s, n)), np.empty(n_mult)
    n_extra = coef_extra.shape[0]
    extra_back, side_extra, half_extra = np.empty((n_extra, n)), np.empty((n_extra, n)), np.empty((n_extra, n))
    clock_back, last_h_back = np.empty(2), np.empty(1)
    y_side, side_comp, side_clock = np.empty(n), np.empty(n), np.empty(2)
    side_coef, side_mult, side_last_h = np.empty((s, n)), np.empty(n_mult), np.empty(1)
    y_end_state, comp_end_state = np.empty(n), np.empty(n)
    y_half, half_comp, half_clock = np.empty(n), np.empty(n), np.empty(2)
    half_coef, half_mult, half_last_h = np.empty((s, n)), np.empty(n_mult), np.empty(1)
    scratch, hessian, integrals = np.empty((3, n)), np.empty((n, n)), np.empty((3, s + 1))
    scale_scratch = np.zeros((2, n + 1))
    g_old, g_new, g_side = np.empty(n_events), np.empty(n_events), np.empty(n_events)
    terminal_y, terminal_comp = np.empty(n), np.empty(n)   # the earliest terminal event of a step
    poly_state = np.empty(n)
    projection_arrays = energy_projection_arrays(n, n_inv, conserve_idx.shape[0])
    side_diagnostics = np.empty(N_DIAGNOSTICS)
    order_exponent = 1.0 / (2.0 * s + 1.0)

    params_view, conserve_view, y_view = borrowed(params), borrowed(conserve_idx), borrowed(y)
    y_comp_view, clock_view, coef_view = borrowed(y_comp), borrowed(clock), borrowed(coef)
    mult_view, last_h_view, diagnostics_view = borrowed(multipliers), borrowed(last_h), borrowed(diagnostics)
    base_view, extra_view = borrowed(newton_base), borrowed(coef_extra)
    restore_newton_matrix(grad_H, hess_H, params_view, settings, tables, work, base_view)
    work.info[4] = 0.0

    for i in range(N_PROGRESS):
        progress[i] = 0
    n_samples = 0
    n_found = 0
    if n_events > 0:
        events(y, params, g_old)
    if control == CONTROL_TIME_SCALE and control_state[CS_RHO] == 0.0:
        sigma, rate = _time_scale_rate(grad_H, time_scale, params, y, scale_scratch)
        control_state[CS_RHO] = 1.0 / sigma + 0.5 * epsilon * rate
    if control_state[CS_H_NEXT] == 0.0:
        control_state[CS_H_NEXT] = h0
    status = STATUS_OK
    step = 0
    consecutive_failures = 0
    finished = False
    while step < max_steps and not finished:
        if n_samples >= t_out.shape[0] or n_found + n_events > event_out.shape[0]:
            break   # the caller drains the buffers and calls again
        global_step = counters[CNT_STEPS]
        remaining = (t_end - clock[0]) - clock[1]
        if control == CONTROL_TIME_SCALE:
            h = epsilon / control_state[CS_RHO]
            if not (h > COLLAPSED_STEP * max(abs(clock[0]), abs(t_end))):   # also NaN and h <= 0
                # sigma reached zero (or left the positive numbers) along the orbit: the steps
                # collapse, and the solver would fail on a step of 1e-300 blaming Gamma or NaN.
                sigma, _ = _time_scale_rate(grad_H, time_scale, params, y, scale_scratch)
                status = STATUS_TIME_SCALE
                _whole_step_failure(diagnostics, clock[0], h, sigma, 0)   # for this status: sigma(y)
                break
        else:
            h = control_state[CS_H_NEXT]
            if control == CONTROL_ERROR and not (h > COLLAPSED_STEP * max(abs(clock[0]), abs(t_end))):
                # The error controller's steps have collapsed: ever smaller steps were accepted and
                # rejected until they no longer advance t (a user trial: perturbed Kepler falling
                # into its centre took 19,410 steps at one t, down to h = 4e-113, H drifting to 1e115,
                # before a solve failed). Such a step would need over 2^50 steps to reach t_end.
                status = STATUS_NOT_CONVERGED
                _whole_step_failure(diagnostics, clock[0], h, 0.0, 0)
                break
        # A time-scale step cut by h_max is not the controller's: it starts afresh after it (below).
        capped = control == CONTROL_TIME_SCALE and h > h_max
        h = min(h, h_max)
        last = False
        if control == CONTROL_FIXED:
            last = global_step + 1 == options[OPT_N_TOTAL]
        elif h >= remaining or remaining - h < 0.01 * h:
            h = remaining   # no sliver of a step at the end
            last = True
        # The step's start, for a rejection and for side steps.
        _copy(y, y_back)
        _copy(y_comp, comp_back)
        _copy(coef, coef_back)
        _copy(coef_extra, extra_back)
        _copy(multipliers, mult_back)
        _copy(clock, clock_back)
        last_h_back[0] = last_h[0]
        status, iterations, substeps = try_step(
            grad_H, hess_H, grad_invariants, params_view, settings, tables, conserve_view, work,
            y_view, y_comp_view, clock_view, coef_view, extra_view, mult_view, h, last_h_view, base_view,
            global_step > 0, diagnostics_view,
            # the error controller retries a failed step with half of it (its main steps are not split):
            # the unimposed substep is its last resort; max_halvings = 0 turns it off, as it does the splitting
            max_halvings > 0 and (control != CONTROL_ERROR or consecutive_failures + 1 >= MAX_CONSECUTIVE_FAILURES),
            max_halvings > 0)
        unimposed = work.info[5]
        counters[CNT_ITERATIONS] += iterations
        if status != STATUS_OK:
            if control != CONTROL_ERROR:
                break
            counters[CNT_FAILED] += 1
            control_state[CS_REJECTED] = 1.0
            consecutive_failures += 1
            if consecutive_failures >= MAX_CONSECUTIVE_FAILURES:
                break
            control_state[CS_H_NEXT] = 0.5 * h
            continue
        estimate = 0.0   # the error controller's, set below
        if control == CONTROL_ERROR:
            if verify:
                # Step doubling: two half steps from the same start (exact to 0.2%, docs/adaptive.md).
                _copy(y_back, y_half)
                _copy(comp_back, half_comp)
                _copy(clock_back, half_clock)
                _copy(coef_back, half_coef)
                _copy(extra_back, half_extra)
                _copy(mult_back, half_mult)
                half_last_h[0] = last_h_back[0]
                half_status = STATUS_OK
                for _ in range(2):
                    half_status, used, _ = try_step(
                        grad_H, hess_H, grad_invariants, params_view, settings, tables, conserve_view, work,
                        y_half, half_comp, half_clock, half_coef, half_extra, half_mult, 0.5 * h, half_last_h,
                        base_view, global_step > 0, side_diagnostics, np.bool_(False), max_halvings > 0)
                    counters[CNT_ITERATIONS] += used
                    if half_status != STATUS_OK:
                        break
                if half_status != STATUS_OK:
                    estimate = np.inf
                else:
                    largest = 0.0
                    for p in range(n):
                        weight = atol + rtol * max(abs(y_back[p]), abs(y[p]))
                        largest = max(largest, abs((y[p] - y_half[p]) + (y_comp[p] - half_comp[p])) / weight)
                    estimate = largest / (1.0 - 0.5 ** (2 * s))
            else:
                estimate = error_estimate(hess_H, params_view, tables, work, y_back, y, h, coef, rtol, atol,
                                          scratch, hessian, integrals)
                counters[CNT_ESTIMATE_HESSIANS] += 1
            if not (estimate <= 1.0):
                # Rejected: back to the step's start, with a smaller step.
                _copy(y_back, y)
                _copy(comp_back, y_comp)
                _copy(coef_back, coef)
                _copy(extra_back, coef_extra)
                _copy(mult_back, multipliers)
                _copy(clock_back, clock)
                last_h[0] = last_h_back[0]
                counters[CNT_REJECTED] += 1
                control_state[CS_REJECTED] = 1.0
                factor = MIN_FACTOR
                if estimate < np.inf:
                    factor = max(MIN_FACTOR, SAFETY * estimate ** (-order_exponent))
                control_state[CS_H_NEXT] = h * min(factor, 1.0)
                consecutive_failures += 1
                if consecutive_failures >= MAX_CONSECUTIVE_FAILURES:
                    status = STATUS_NOT_CONVERGED
                    _whole_step_failure(diagnostics, clock[0], h, estimate, iterations)
                    break
                continue
        # Accepted: its end state is projected onto H(y0) first (solver.project_energy), so that the
        # controllers below, and all that follows, see the state the run goes on from.
        counters[CNT_ENERGY_PROJECTIONS] += project_energy(H, grad_H, grad_invariants, params_view, conserve_view,
                                                           y_view, y_comp_view, H_target, projection_arrays)
        if control == CONTROL_ERROR:
            # Accepted: the next step (Gustafsson's controller).
            safe = max(estimate, 1e-300)
            factor = SAFETY * safe ** (-order_exponent)
            if control_state[CS_ERR_PREV] > 0.0 and control_state[CS_H_PREV] > 0.0:
                factor = min(factor, factor * (h / control_state[CS_H_PREV])
                             * (control_state[CS_ERR_PREV] / safe) ** order_exponent)
            if control_state[CS_REJECTED] != 0.0:
                factor = min(factor, 1.0)
                control_state[CS_REJECTED] = 0.0
            # A step taken unimposed counts the imposed solve that failed before it: not a slow solve,
            # and one that smaller steps do not cure (their Gamma is worse: stepper.try_step). Held
            # back, Kepler e = 0.9999 imposing L and A_y shrank its steps by 0.8 each, to 1e-10.
            if unimposed != 0.0:
                pass
            elif iterations > SLOW_SOLVE_FRACTION * settings.max_iter:
                factor = min(factor, SLOW_SOLVE_FACTOR)
            elif iterations > NO_GROWTH_FRACTION * settings.max_iter:
                factor = min(factor, 1.0)
            if not last:
                control_state[CS_H_PREV] = h
                control_state[CS_ERR_PREV] = safe
                control_state[CS_H_NEXT] = h * min(MAX_FACTOR, max(MIN_FACTOR, factor))
        elif control == CONTROL_TIME_SCALE:
            sigma, rate = _time_scale_rate(grad_H, time_scale, params, y, scale_scratch)
            if capped:
                # A step cut by h_max is not the controller's (its fictive time is h rho, not
                # epsilon), so the recurrence below does not hold across it: the controller starts
                # afresh from the new state, rho = 1/sigma + epsilon G / 2, as at t0. Adding
                # epsilon G after capped steps drove rho through zero (Kepler e = 0.6, h_max = 0.004:
                # "time scale collapsed" at step 62); integrating d rho/dt = rho G over them instead
                # drifted, the pericentre's steps growing 2% an orbit. Not time-reversible while
                # capped, as no cap can be.
                control_state[CS_RHO] = 1.0 / sigma + 0.5 * epsilon * rate
            else:
                control_state[CS_RHO] += epsilon * rate
        consecutive_failures = 0
        if last and control != CONTROL_FIXED:
            clock[0] = t_end   # exactly, whatever the rounding of the sum of the steps
            clock[1] = 0.0
        counters[CNT_STEPS] += 1
        if substeps > 1:
            counters[CNT_SPLIT] += 1
        step_t[step] = clock[0]
        step_h[step] = h
        iter_out[step] = iterations
        substeps_out[step] = substeps
        record_multipliers(unimposed, multipliers, mult_out[step])
        step += 1
        progress[0] = step
        if last:
            finished = True

        # Events: a sign change of g over the step, located on the stage polynomial, then
        # refined by Newton steps whose values of g are taken at side steps. A terminal
        # event ends the step, and the run, at the event: the earliest terminal one of the
        # step, whatever the order the events are listed in, and the events found after it
        # in the step are dropped (they happen after the run's end).
        h_end = h   # where this step ends for the samples below (a terminal event ends it early)
        _copy(y, y_end_state)   # the step's end, for side steps backwards from it
        _copy(y_comp, comp_end_state)
        t_end_state = clock[0]
        if n_events > 0:
            events(y, params, g_new)
            terminal_hit = False
            terminal_row = -1
            first_row = n_found
            for e in range(n_events):
                if not _crossed(event_direction[e], g_old[e], g_new[e]):
                    continue
                # Illinois on the stage polynomial, in units of the step.
                a, b, g_a, g_b = 0.0, 1.0, g_old[e], g_new[e]
                tau = 1.0
                for _ in range(POLYNOMIAL_ROOT_ITERATIONS):
                    if g_b == g_a:
                        break
                    tau = (a * g_b - b * g_a) / (g_b - g_a)
                    stage_at(tau, y_back, h, coef, integrals, poly_state)
                    events(poly_state, params, g_side)
                    g_tau = g_side[e]
                    if g_tau == 0.0 or (b - a) < 1e-15:
                        break
                    if (g_tau < 0.0) == (g_b < 0.0):
                        b, g_b = tau, g_tau
                        g_a *= 0.5
                    else:
                        a, g_a = tau, g_tau
                        g_b *= 0.5
                # The slope of g along the step, from the polynomial.
                upper, lower = min(1.0, tau + 1e-6), max(0.0, tau - 1e-6)
                stage_at(upper, y_back, h, coef, integrals, poly_state)
                events(poly_state, params, g_side)
                g_plus = g_side[e]
                stage_at(lower, y_back, h, coef, integrals, poly_state)
                events(poly_state, params, g_side)
                slope = (g_plus - g_side[e]) / (upper - lower)
                for _ in range(EVENT_NEWTON_STEPS):
                    if tau >= 1.0:
                        _copy(y_end_state, y_side)
                        _copy(comp_end_state, side_comp)
                    else:
                        dense_state(grad_H, hess_H, grad_invariants, params_view, side_settings, tables,
                                    conserve_view, side_work, y_back, comp_back, clock_back[0], y_end_state,
                                    comp_end_state, t_end_state, h,
                                    coef, coef_extra, multipliers, tau * h, side_base, y_side, side_comp, side_clock,
                                    side_coef, side_extra, side_mult, side_last_h, side_diagnostics, integrals,
                                    counters)
                        counters[CNT_ENERGY_PROJECTIONS] += project_energy(
                            H, grad_H, grad_invariants, params_view, conserve_view, y_side, side_comp, H_target,
                            projection_arrays)
                    events(y_side, params, g_side)
                    if slope == 0.0 or g_side[e] == 0.0:
                        break
                    new_tau = min(1.0, max(0.0, tau - g_side[e] / slope))
                    if abs(new_tau - tau) * abs(h) <= 2e-16 * (abs(clock_back[0]) + abs(h)):
                        break
                    tau = new_tau
                event_out[n_found] = e
                event_t_out[n_found] = clock_back[0] + (clock_back[1] + tau * h)
                for p in range(n):
                    event_y_out[n_found, p] = y_side[p]
                n_found += 1
                counters[CNT_EVENTS] += 1
                if event_terminal[e] != 0 and (not terminal_hit or event_t_out[n_found - 1] < clock[0]):
                    terminal_hit = True
                    terminal_row = n_found - 1
                    _copy(y_side, terminal_y)
                    _copy(side_comp, terminal_comp)
                    clock[0] = event_t_out[n_found - 1]
                    h_end = tau * h
            if terminal_hit:
                _copy(terminal_y, y)
                _copy(terminal_comp, y_comp)
                clock[1] = 0.0
                step_t[step - 1] = clock[0]
                step_h[step - 1] = h_end
                kept = first_row
                for row in range(first_row, n_found):
                    if row == terminal_row or event_t_out[row] <= clock[0]:
                        if kept != row:
                            event_out[kept] = event_out[row]
                            event_t_out[kept] = event_t_out[row]
                            for p in range(n):
                                event_y_out[kept, p] = event_y_out[row, p]
                        kept += 1
                counters[CNT_EVENTS] -= n_found - kept
                n_found = kept
            for e in range(n_events):
                g_old[e] = g_new[e]
            if terminal_hit:
                finished = True

        # Samples: at the requested times inside this step, by side steps from its start;
        # else every store_every steps and at the end of the run.
        if t_eval.shape[0] > 0:
            while counters[CNT_NEXT_EVAL] < t_eval.shape[0] and n_samples < t_out.shape[0]:
                t_wanted = t_eval[counters[CNT_NEXT_EVAL]]
                offset = (t_wanted - clock_back[0]) - clock_back[1]
                # Times within rounding of the step's end are the step's end (t_end itself,
                # and fixed-step times such as 10.0 after 100 steps of 0.1).
                slack = 4e-16 * (abs(clock_back[0]) + abs(h_end))
                if offset > h_end + slack:
                    break
                if offset >= h_end - slack:
                    _sample(H, invariants, params, y, t_wanted, n_samples, t_out, y_out, inv_out, inv_values)
                else:
                    dense_state(grad_H, hess_H, grad_invariants, params_view, side_settings, tables, conserve_view,
                                side_work, y_back, comp_back, clock_back[0], y_end_state, comp_end_state, t_end_state,
                                h, coef, coef_extra, multipliers, offset, side_base, y_side, side_comp, side_clock,
                                side_coef, side_extra, side_mult, side_last_h, side_diagnostics, integrals,
                                counters)
                    counters[CNT_ENERGY_PROJECTIONS] += project_energy(
                        H, grad_H, grad_invariants, params_view, conserve_view, y_side, side_comp, H_target,
                        projection_arrays)
                    _sample(H, invariants, params, y_side, t_wanted, n_samples, t_out, y_out, inv_out,
                            inv_values)
                n_samples += 1
                counters[CNT_NEXT_EVAL] += 1
        elif (global_step + 1) % store_every == 0 or finished:
            _sample(H, invariants, params, y, clock[0], n_samples, t_out, y_out, inv_out, inv_values)
            n_samples += 1
        progress[1] = n_samples
        progress[2] = n_found
    progress[0] = step
    progress[1] = n_samples
    progress[2] = n_found
    progress[3] = 1 if finished else 0
    counters[CNT_FACTORISATIONS] += np.int64(work.info[4]) + np.int64(side_work.info[4])
    keep_alive((owners, side_owners))
    return status
