"""The step protocol and the time loop: predict, solve, fall back, commit.

Numba only: plain floats and C-contiguous float64 arrays in, status codes out. The
problem's functions arrive as ``types.FunctionType`` arguments (see signatures.py),
so this module is compiled once and cached for every problem.

One step of any family goes through ``try_step`` (docs/methods.md#round-off-over-long-times and docs/solver.md):
  1. predict: the previous step's polynomial carried over, E(theta) [c_prev; gamma_s..], with
     the extra Legendre terms gamma_s.. of the previous step (coef_extra);
  2. solve (solver.py) with the family's map (maps.py);
  3. fall back: once more from the unextrapolated c_prev, then split the step into two
     half-steps, recursively up to max_halvings levels, so that the output grid is
     unchanged and every imposed invariant is still kept;
  4. commit: y += h coef_0 and t += h with compensated (Kahan) summation.
``time_loop`` (a run, with samples) and the ensemble kernel (many runs) both call it,
so an ensemble member is bit for bit the run ``elimfast.integrate`` makes.
"""
import warnings

import numpy as np
from numba import njit, types
from numba.extending import overload
from numba.core.errors import NumbaExperimentalFeatureWarning

from .codes import (internal, FAMILY_ELIM, FAMILY_LIM, SOLVER_FIXED_POINT, SOLVER_NEWTON, STATUS_NONFINITE,  # noqa: F401
                    STATUS_NOT_CONVERGED, STATUS_OK, STATUS_SINGULAR, STATUS_SPLIT, PREDICTOR_EXTRA_ROWS, DIAG_TIME,
                    DIAG_STEP, DIAG_INCREMENT, DIAG_CONDITION, DIAG_DEPTH, DIAG_ITERATIONS, N_DIAGNOSTICS)
from .linalg import cholesky_factor, cholesky_solve_factored
from .maps import EPS, RHS_STABLE, apply_J, elim_map, gradient_sizes, project
from .quadrature import legendre_table, two_prod, two_sum
from .signatures import (COMPLEX_MATRIX, COMPLEX_VECTOR, GRAD_H_TYPE, GRAD_INVARIANTS_TYPE, H_TYPE, HESS_H_TYPE, INT_VECTOR,
                         INVARIANTS_TYPE, MATRIX, VECTOR)
from .solver import (BAND_CAP, NEARLY_SINGULAR_GAMMA, SPLIT_CONDITION, SPLIT_ROUNDING, accelerates, alpha_rounding,
                     newton_factor, solve)
from .workspace import (Settings, Tables, borrow_tables, borrow_workspace, borrowed, by_ref, keep_alive,
                        make_workspace)

# First-class function types are the documented way to pass functions to cached
# kernels; Numba still labels them experimental on every compile.
warnings.filterwarnings("ignore", category=NumbaExperimentalFeatureWarning, module=__name__)
warnings.filterwarnings("ignore", message="First-class function type feature is experimental")

# The Newton matrix of an earlier step is reused while the solves need at most this many
# iterations (_newton_matrix).
REUSE_ITERATIONS = 6
REUSE_ITERATIONS_FULL = 3


@njit(cache=True)
def predictor_extra_rows(k, s):
    """How many extra Legendre terms a run of a method with k nodes and degree s keeps for its
    predictor (the rows of its coef_extra state): min(k - s, PREDICTOR_EXTRA_ROWS), as
    elimfast.integrate.predictor_extra_state sizes a run's state."""
    return min(k - s, PREDICTOR_EXTRA_ROWS)


@njit(cache=True, inline="always", error_model="numpy")
def kahan_add(value, compensation, increment):
    """Compensated summation (docs/methods.md#round-off-over-long-times): returns the new (value, compensation)."""
    corrected = increment + compensation
    new_value = value + corrected
    return new_value, (value - new_value) + corrected


@njit(cache=True, inline="always", error_model="numpy")
def add_product(value, compensation, h, x):
    """(value + compensation) + h x as a double-double: returns the new (value, compensation).

    The state's update y1 = y0 + h coef_0 (docs/methods.md#round-off-over-long-times), with the
    product h coef_0 taken exactly (quadrature.two_prod) and one rounding at the end: Kahan's
    sum of the rounded product kept its rounding, which for h = 0.1 (mantissa 8/5) has a mean
    that is not zero, 2e-20 of H per step on the harmonic oscillator, the same in every run."""
    product, error = two_prod(h, x)
    head, tail = two_sum(value, product)
    tail += error + compensation
    new_value = head + tail
    return new_value, tail - (new_value - head)


@njit(cache=True, inline="always", error_model="numpy")
def project_energy(H, grad_H, grad_invariants, params, conserve_idx, y, y_comp, H_target, projection):
    """The energy projection of docs/methods.md#energy-projection (solver.project_energy): one
    Newton step of the projection of the state (y + y_comp, its compensated sum) onto
    H = H_target, along the shortest move that leaves the imposed invariants unchanged to
    first order: delta = G^T w, (G G^T) w = (H_target - H, 0, ..., 0), G the rows grad H and
    the imposed invariants' gradients. Without it each step rounds H by about eps |H|, a
    random walk whose phase error grows like t^(3/2) (Brouwer's law), the floor of long
    runs (docs/adaptive.md). Nothing moves when H_target is NaN (off), when H is off by no
    more than its own evaluation can tell, eps (|H| + sum |y_i dH/dy_i|), or when G G^T is
    singular or its solution not finite. projection: the loop's work arrays, from
    energy_projection_arrays: rows (1 + r, n), inv_gradients (n_inv, n), gram (1 + r, 1 + r),
    weights (1 + r,). Returns the evaluations of grad H it made: 1, or 0 when off (the adaptive
    loop's CNT_ENERGY_PROJECTIONS)."""
    if H_target != H_target:
        return 0
    rows, inv_gradients, gram, weights = projection
    n = y.shape[0]
    grad_H(y, params, rows[0])
    tilt = 0.0
    scale = 0.0
    for i in range(n):
        tilt += rows[0, i] * y_comp[i]   # H(y + y_comp) - H(y), to first order
        scale += abs(rows[0, i] * y[i])
    value = H(y, params)
    deviation = (value - H_target) + tilt
    if not abs(deviation) > EPS * (abs(value) + scale):
        return 1
    imposed = conserve_idx.shape[0]
    if imposed > 0:
        grad_invariants(y, params, inv_gradients)
        for a in range(imposed):
            for i in range(n):
                rows[1 + a, i] = inv_gradients[conserve_idx[a], i]
    for a in range(imposed + 1):
        for b in range(a + 1):
            acc = 0.0
            for i in range(n):
                acc += rows[a, i] * rows[b, i]
            gram[a, b] = acc
            gram[b, a] = acc
        weights[a] = 0.0
    weights[0] = -deviation
    if cholesky_factor(gram) != 0:   # also where a gradient is not finite (its diagonal entry)
        return 1
    cholesky_solve_factored(gram, weights)
    for a in range(imposed + 1):
        if not abs(weights[a]) < np.inf:
            return 1
    for i in range(n):
        move = 0.0
        for a in range(imposed + 1):
            move += weights[a] * rows[a, i]
        y[i], y_comp[i] = kahan_add(y[i], y_comp[i], move)
    return 1


@njit(cache=True, inline="always")
def energy_projection_arrays(n, n_inv, n_imposed):
    """The arrays project_energy works in: (rows, inv_gradients, gram, weights)."""
    return (np.empty((1 + n_imposed, n)), np.empty((max(n_inv, 1), n)), np.empty((1 + n_imposed, 1 + n_imposed)),
            np.empty(1 + n_imposed))


@njit(cache=True, inline="always", error_model="numpy")
def extrapolate(tables, work, offset, theta, base, extra, n_extra, out):
    """The predictor of docs/solver.md: out_i = sum_j E_ij base_j + sum_j E_i,s+j extra_j,
    E_ij = int_0^1 P_i(tau) P_j(offset + theta tau) dtau by (s+1)-point Gauss (exact:
    degree <= 2s-2 + n_extra, n_extra <= 3).

    base are a step's coefficients (its polynomial u' = sum_j base_j P_j on [0, 1] in
    units of that step), extra[:n_extra] its next Legendre coefficients gamma_s, ...
    (n_extra = 0: extra is not read, and out is bit for bit the degree s-1 predictor).
    offset = 1, theta = h_new / h_prev: the previous step carried over to the next one;
    offset = 0, theta = h_side / h: the same step restricted to its first h_side (the
    side steps of dense output, docs/adaptive.md).
    """
    s = base.shape[0]
    n = base.shape[1]
    n_terms = s + n_extra
    points, values, E = work.predictor_points, work.predictor_values, work.extrapolation
    for q in range(points.shape[0]):
        points[q] = offset + theta * tables.predictor_nodes[q]
    legendre_table(points, n_terms, values)
    for i in range(s):
        for j in range(n_terms):
            acc = 0.0
            for q in range(points.shape[0]):
                acc += tables.predictor_basis[q, i] * values[q, j]
            E[i, j] = acc
    for i in range(s):
        for p in range(n):
            acc = 0.0
            for j in range(s):
                acc += E[i, j] * base[j, p]
            for j in range(n_extra):
                acc += E[i, s + j] * extra[j, p]
            out[i, p] = acc


@njit(cache=True, inline="always", error_model="numpy")
def extra_terms(tables, work, s, coef_extra):
    """coef_extra[j] = gamma_{s+j} = J sum_l b_l P_{s+j}(c_l) grad H(u_l), j < coef_extra.shape[0]:
    the Legendre coefficients beyond the method's s of the solve just accepted, projected as
    the maps project gamma_j (maps.project, apply_J; work.proj is the maps' scratch, free
    between solves) from the gradients of its last map evaluation (work.grads: no new
    evaluation of grad H; they were taken one increment, at round-off, before the accepted
    iterate)."""
    rows = coef_extra.shape[0]
    project(tables.projection[s:s + rows], work.grads, rows, work.proj)
    apply_J(work.proj, rows, coef_extra)


def _copy(source, target):
    """target[...] = source for the kernels' 1-D and 2-D C arrays, element by element (the
    interpreter's version, for NUMBA_DISABLE_JIT=1). Compiled, an explicit loop per rank:
    np.ndindex built an index tuple per element (~3 us per step in six copies), and
    reshape(-1) calls Numba's runtime helper numba_attempt_nocopy_reshape (3% of a
    GAUSS(4) run at small h)."""
    target[...] = source


@overload(_copy, jit_options={"cache": True, "error_model": "numpy"}, inline="always")
def _copy_overload(source, target):
    if isinstance(source, types.Array) and source.ndim == 1:
        def copy_1d(source, target):
            for i in range(source.shape[0]):
                target[i] = source[i]
        return copy_1d
    if isinstance(source, types.Array) and source.ndim == 2:
        def copy_2d(source, target):
            for i in range(source.shape[0]):
                for j in range(source.shape[1]):
                    target[i, j] = source[i, j]
        return copy_2d


@njit(cache=True, inline="always", error_model="numpy")
def _copy_rows(source, target, rows):
    """target[:rows] = source[:rows] (work.extra_start has room for more rows than a run keeps)."""
    for i in range(rows):
        for j in range(source.shape[1]):
            target[i, j] = source[i, j]


@internal
def _attempt(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
             y, h, h_prev, have_prev, coef, coef_extra, mult, newton_base, may_split):
    """Solve one (sub)step from y with step h: predicted guess, then the unextrapolated one.
    may_split: the caller can still halve this (sub)step, and a solve that converged with
    cond(Gamma) above SPLIT_CONDITION, whose alpha carries more than SPLIT_ROUNDING of rounding into
    the step (solver.alpha_rounding), counts as failed (STATUS_SPLIT) so that it is.

    coef/mult hold the previous (sub)step's coefficients and multipliers on entry (when
    have_prev) and the solution on success; on failure they are left as on entry.
    coef_extra likewise: the predictor's extra terms (extra_terms) of the previous
    (sub)step on entry, of this one on success.
    newton_base (n + 3,) = [valid, h, iterations of the last solve, y...]: where the Newton
    matrix in work was factorised (see _newton_matrix). Returns (status, iterations).
    """
    newton = settings.solver != SOLVER_FIXED_POINT
    fresh = False
    # cold is a variable, not a literal True/False at the calls: one compiled solve serves both.
    cold = not (have_prev and settings.warm_start != 0)
    if not cold:
        _copy(coef, work.coef_base)
        _copy(mult, work.mult_base)
    _initial_guess(tables, settings, work, h, h_prev, cold, coef, coef_extra, mult)
    if newton:
        _newton_point(tables, work, y, h, coef, cold or settings.predictor == 0)
        status, fresh = _newton_matrix(grad_H, hess_H, params, tables, work, work.newton_point, h, newton_base,
                                       False)
        if status != STATUS_OK:
            work.info[0], work.info[1], work.info[2], work.info[3] = np.inf, 0.0, 0.0, 0.0
            if not cold:
                _copy(work.coef_base, coef)
                _copy(work.mult_base, mult)
            return status, 0
    iterations = 0
    status = STATUS_NOT_CONVERGED
    for attempt in range(2):   # a second time with a fresh Newton matrix if a reused one failed
        if attempt > 0:
            _initial_guess(tables, settings, work, h, h_prev, cold, coef, coef_extra, mult)
        status, used = solve(grad_H, grad_invariants, params, settings, tables, conserve_idx, work,
                             y, h, coef, mult, cold)
        iterations += used
        if status != STATUS_OK and not cold and settings.predictor != 0:
            # Retry once from the unextrapolated coefficients (docs/solver.md#when-a-step-fails-retry-then-split).
            _copy(work.coef_base, coef)
            _copy(work.mult_base, mult)
            status, used = solve(grad_H, grad_invariants, params, settings, tables, conserve_idx, work,
                                 y, h, coef, mult, cold)
            iterations += used
        if status == STATUS_OK or not newton or fresh:
            break
        status, fresh = _newton_matrix(grad_H, hess_H, params, tables, work, work.newton_point, h, newton_base,
                                       True)
        if status != STATUS_OK:
            break
    if newton:
        newton_base[2] = work.info[2]
    if (status == STATUS_OK and may_split and work.info[1] > SPLIT_CONDITION
            and alpha_rounding(h, mult, settings, tables, conserve_idx.shape[0], coef.shape[0], work) > SPLIT_ROUNDING):
        status = STATUS_SPLIT
    if status == STATUS_OK:
        if settings.predictor != 0:
            # Without the predictor coef_extra stays zero, and every start (side steps' too)
            # is bit for bit what it was before the extra terms.
            extra_terms(tables, work, coef.shape[0], coef_extra)
    elif not cold:
        _copy(work.coef_base, coef)
        _copy(work.mult_base, mult)
    return status, iterations


@internal
def _attempt_unimposed(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
                       y, h, h_prev, have_prev, coef, coef_extra, mult, newton_base):
    """The last resort of an ELIM substep that failed at the deepest halving
    (docs/solver.md#a-substep-without-imposing): the same substep with alpha = 0 (the HBVM map),
    accepted only if it changes every imposed invariant by less than rounding the state to
    doubles does, |h b_a| <= eps sum_p A_{a,p} max(|y_p|, |y1_p|).

    b_a is the right-hand side of Gamma alpha = b at the accepted coefficients: with alpha = 0,
    h b_a is L_a(y1) - L_a(y) up to the quadrature of the r nodes (docs/methods.md#elim: the
    full sum over j of phi_j^T gamma_j vanishes, grad L . J grad H = 0), and A_{a,p} =
    max_i |grad L_a(uhat_i)_p| (maps.gradient_sizes). Where Gamma is nearly singular and b at
    round-off, alpha = b / Gamma is rounding over rounding and the imposed solve cannot settle
    (a Lennard-Jones trimer imposing its angular momentum, h = 0.01: at every depth one half
    stalled at increments 2e-12 to 3e-11, while the unimposed step changed L by 3e-17).
    Returns (status, iterations); the multipliers are 0 on success. On failure work.info's last
    increment and cond(Gamma) are the imposed solve's again: the failure's diagnostics."""
    increment, condition = work.info[0], work.info[1]
    status, iterations = _attempt(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx[:0], work,
                                  y, h, h_prev, have_prev, coef, coef_extra, mult, newton_base, False)
    if status != STATUS_OK:
        work.info[0], work.info[1] = increment, condition
        return status, iterations
    # One map evaluation at the accepted coefficients, alpha = 0: b and the gradients of the invariants.
    elim_map(grad_H, grad_invariants, params, y, h, coef, mult, True, (settings.stable_rhs & RHS_STABLE) != 0, tables,
             conserve_idx, work)
    nu = conserve_idx.shape[0]
    gradient_sizes(work, nu, tables.Ihat.shape[0])
    sizes, change = work.sizes, work.small_vector
    for a in range(nu):
        allowed = 0.0
        for p in range(y.shape[0]):
            allowed += sizes[1 + a, p] * max(abs(y[p]), abs(y[p] + h * coef[0, p]))
        if not (abs(h * change[a]) <= EPS * allowed):
            work.info[0], work.info[1] = increment, condition
            return STATUS_NOT_CONVERGED, iterations
    return STATUS_OK, iterations


@njit(cache=True, inline="always", error_model="numpy")
def _initial_guess(tables, settings, work, h, h_prev, cold, coef, coef_extra, mult):
    """The solve's starting coefficients and multipliers: zero (cold), the previous ones
    (work.coef_base, mult_base) carried over by the predictor with the previous step's
    extra terms coef_extra (zero rows: a state saved before they were kept), or unchanged."""
    if cold:
        coef[:, :] = 0.0
        mult[:] = 0.0
    elif settings.predictor != 0:
        extrapolate(tables, work, 1.0, h / h_prev, work.coef_base, coef_extra, coef_extra.shape[0], coef)
    else:
        _copy(work.coef_base, coef)
        _copy(work.mult_base, mult)


@njit(cache=True, inline="always", error_model="numpy")
def _newton_point(tables, work, y, h, coef, at_start):
    """Where the Newton matrix takes its Jacobian J0 (docs/solver.md): the middle of the
    predicted step, u(h/2) = y + h int_0^(1/2) sum_j coef_j P_j, into work.newton_point; y
    itself when there is no prediction (at_start).

    The Jacobian at the middle of the step is a second-order approximation of the map's
    over the step (the one at y is first-order). Measured, iterations per step: Kepler
    e = 0.9 over 10 periods, adaptive at rtol = 1e-14, HBVM(12,6) 6.22 -> 5.43 and
    HBVM(8,4) 4.50 -> 4.02; e = 0.6, h = 0.1, HBVM(12,3) 4.80 -> 4.65, GHBVM(12,3) 4.97 ->
    4.73, EHBVM(12,3) 5.36 -> 5.26. ELIM barely gains (EHBVM(8,4) adaptive: 5.86 -> 5.89):
    what slows its iteration is alpha's dependence on the stages, which M ignores.
    """
    point = work.newton_point
    _copy(y, point)
    if at_start:
        return
    # The step restricted to its first half, as dense output's side steps take it: its
    # coefficient 0 is the mean of u' over [0, h/2], so u(h/2) = y + h/2 half_0, half_0 =
    # sum_j E_0j coef_j with E = E(offset 0, theta 1/2). That row is the method's own: taken
    # once per kernel call from extrapolate (work.half_row, 0 until then; E_00 = 1).
    row = work.half_row
    if row[0] == 0.0:
        half = work.new_coef      # free until the solve's first map writes it
        extrapolate(tables, work, 0.0, 0.5, coef, coef, 0, half)
        for j in range(row.shape[0]):
            row[j] = work.extrapolation[0, j]
    for p in range(point.shape[0]):
        acc = 0.0
        for j in range(row.shape[0]):
            acc += row[j] * coef[j, p]
        point[p] += 0.5 * h * acc


@njit(cache=True, inline="always")
def newton_eigenvalues(settings, newton_values):
    """make_workspace's n_eigenvalues: the blocks of the Newton matrix, or -1 for the fixed
    point (no Newton matrix, no n x n arrays)."""
    return -1 if settings.solver == SOLVER_FIXED_POINT else newton_values.shape[0]


@njit(cache=True, inline="always", error_model="numpy")
def _newton_matrix(grad_H, hess_H, params, tables, work, y, h, newton_base, force):
    """Keep or refactorise the simplified Newton matrix for a solve from y with step h.

    Simplified Newton needs only an approximation of the Jacobian (docs/solver.md): like
    Hairer & Wanner's RADAU5, for large systems (LU-factorised blocks) the matrix of an earlier
    step is kept while the step size is the same and the last solve needed at most
    REUSE_ITERATIONS iterations; otherwise (or when force) it is factorised at (y, h), and
    newton_base records where. Returns (status, fresh): fresh when factorised now.
    Measured: the solar system (n = 36, GHBVM(12,3)) took 126 us per step refactorising
    every step, 101 us keeping the matrix (6.6 iterations per step either way); Kepler
    (n = 4) is better off refactorising at h = 0.1 (5.36 iterations instead of 6.30, 10%
    faster), but not at small steps, where its solves take at most 3 iterations: GAUSS(4),
    h = pi/120, 2400 steps, 16.0 -> 12.8 ms; EHBVM(12,4), h = pi/480, 78 -> 71 ms (h = 0.1:
    unchanged, no solve there is that easy).
    """
    n = y.shape[0]
    # The LU blocks' factorisation is kept while solves stay easy; for small systems (inverted
    # blocks, or the full form) only while they take at most REUSE_ITERATIONS_FULL iterations: small steps,
    # where refactorising every step cost more than the iterations it saved.
    lu_blocks = work.newton_blocks.shape[0] > 0 and work.newton_block_scratch.shape[0] == 0
    limit = REUSE_ITERATIONS if lu_blocks else REUSE_ITERATIONS_FULL
    if not force and newton_base[0] != 0.0 and newton_base[1] == h and newton_base[2] <= limit:
        return STATUS_OK, False
    status = newton_factor(grad_H, hess_H, params, y, h, tables, work)
    newton_base[0] = 1.0 if status == STATUS_OK else 0.0
    newton_base[1] = h
    newton_base[2] = 0.0
    for p in range(n):
        newton_base[3 + p] = y[p]
    return status, True


@internal
def try_step(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
             y, y_comp, clock, coef, coef_extra, mult, h, last_h, newton_base, have_prev, diagnostics,
             last_resort, skip_imposing):
    """One step of size h from (y, clock): predict, solve, fall back, commit (docs/solver.md;
    compensated sums: docs/methods.md#round-off-over-long-times).

    In/out: y (n,) and y_comp (n,) the state and its Kahan compensation; clock (2,) =
    [t, its compensation]; coef (s, n), mult: the last (sub)step's coefficients and
    multipliers; coef_extra (e, n), e = predictor_extra_rows(k, s): its Legendre terms
    gamma_s.. for the predictor; last_h (1,): that (sub)step's size; newton_base (n + 3,):
    where the Newton matrix in work was factorised (_newton_matrix). have_prev: coef holds a previous
    step (else the first step starts cold). A step that fails is retried from the
    unextrapolated guess, then split into halves, recursively to settings.max_halvings
    levels (a failed half is split again; the other half is tried whole). A substep of ELIM
    that fails at the deepest level is, when last_resort (the caller's say: the run's
    max_halvings > 0, which 0 turns off with the splitting, and the caller will not retry the
    step itself) and cond(Gamma) <= NEARLY_SINGULAR_GAMMA (above it the imposed
    invariants themselves are degenerate there, and the run stops with that message), taken
    without imposing the invariants if that keeps them to rounding (_attempt_unimposed).
    skip_imposing (the run's max_halvings > 0): so is a whole ELIM step whose solve converged
    to an alpha that is rounding over rounding (STATUS_SINGULAR), before it is split: a step
    too short for Gamma (docs/solver.md#a-substep-without-imposing). work.info[5] counts the
    step's substeps taken unimposed. A whole step split for alpha's rounding (STATUS_SPLIT) whose
    split fails at the deepest level is, when last_resort, taken whole without imposing the
    invariants if that keeps them to rounding, as a step too short for Gamma is. The clock
    advances by h in one compensated addition whether or not the step was split.

    Returns (status, iterations, substeps). On failure nothing is applied: y, y_comp,
    clock, coef, coef_extra, mult and last_h are as on entry, and diagnostics (N_DIAGNOSTICS,)
    holds the failing substep's start time, size, last increment, cond(Gamma), depth
    and iterations.
    """
    _copy(y, work.y_start)
    _copy(y_comp, work.y_comp_start)
    _copy(y_comp, work.stage_comp)   # the maps' stages start from y + y_comp (maps.stages)
    _copy(coef, work.coef_start)
    _copy_rows(coef_extra, work.extra_start, coef_extra.shape[0])
    _copy(mult, work.mult_start)
    h_start = last_h[0]
    n = y.shape[0]
    depth = 0
    units_left = 1          # substeps of size h / 2^depth still to take
    iterations = 0
    substeps = 0
    previous = have_prev
    h_prev = last_h[0]
    work.info[5] = 0.0
    may_leave_unimposed = last_resort and settings.family == FAMILY_ELIM and conserve_idx.shape[0] > 0
    may_skip_imposing = skip_imposing and settings.family == FAMILY_ELIM and conserve_idx.shape[0] > 0
    # Only where the solve took secant steps: elsewhere a plain retry would repeat the same solve.
    retry_plain = accelerates(settings, conserve_idx.shape[0])
    plain = Settings(settings.family, np.int64(SOLVER_NEWTON), settings.stable_rhs, settings.warm_start,
                     settings.predictor, settings.tol, settings.max_iter, settings.max_halvings)
    split_for_rounding = False   # the whole step converged, but was split for alpha's rounding
    while units_left > 0:
        h_sub = h * 0.5 ** depth
        may_split = depth < settings.max_halvings
        status, used = _attempt(grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
                                y, h_sub, h_prev, previous, coef, coef_extra, mult, newton_base, may_split)
        iterations += used
        if status == STATUS_SPLIT and depth == 0:
            split_for_rounding = True
        if status != STATUS_OK and status != STATUS_SPLIT and retry_plain:
            # The secant steps can carry a hard solve to a spurious alpha, which is rejected
            # (docs/solver.md#secant-acceleration): plain Newton tries the substep before it is split.
            status, used = _attempt(grad_H, hess_H, grad_invariants, params, plain, tables, conserve_idx, work,
                                    y, h_sub, h_prev, previous, coef, coef_extra, mult, newton_base, may_split)
            iterations += used
        if status != STATUS_OK and (
                (status == STATUS_SINGULAR and depth == 0 and may_skip_imposing and work.info[0] <= BAND_CAP)
                or (depth >= settings.max_halvings and may_leave_unimposed and work.info[1] <= NEARLY_SINGULAR_GAMMA)):
            # Without imposing, if that keeps the invariants to rounding (docs/solver.md#a-substep-without-
            # imposing): (1) a whole step whose solve converged but whose alpha is rounding over rounding, a
            # step so short that the Legendre coefficients gamma_j, phi_j (j >= s - nu) in Gamma are below
            # the rounding of the sums that form them (~h^j), which halving only makes worse (Kepler
            # imposing L and A_y could not take h = 1e-8; adaptive runs at e = 0.9999 halved their first
            # step 40 times); (2) the deepest substep, failing otherwise. The failure's diagnostics stay
            # those of the imposed solve (_attempt_unimposed keeps them).
            unimposed_status, unimposed_used = _attempt_unimposed(
                grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
                y, h_sub, h_prev, previous, coef, coef_extra, mult, newton_base)
            iterations += unimposed_used
            if unimposed_status == STATUS_OK:
                status = STATUS_OK
                work.info[5] += 1.0
            elif depth == 0:   # what a split starts from: the step's start
                _copy(work.coef_start, coef)
                _copy_rows(work.extra_start, coef_extra, coef_extra.shape[0])
                _copy(work.mult_start, mult)
        if status == STATUS_OK:
            finite = True
            for p in range(n):
                if not (abs(y[p] + h_sub * coef[0, p]) <= 1e308):
                    finite = False
            if finite:
                for p in range(n):
                    y[p], y_comp[p] = add_product(y[p], y_comp[p], h_sub, coef[0, p])
                    work.stage_comp[p] = y_comp[p]
                substeps += 1
                units_left -= 1
                h_prev = h_sub
                previous = True
                # Back to the coarser level once its first half is done (the recursion's order).
                while depth > 0 and units_left > 0 and units_left % 2 == 0:
                    depth -= 1
                    units_left //= 2
                continue
            status = STATUS_NONFINITE
        if depth >= settings.max_halvings and split_for_rounding and last_resort:
            # The split of a whole step split for alpha's rounding failed (substeps too short for Gamma:
            # configs/toda.yaml 100x longer, whose drifting positions put alpha's rounding above
            # SPLIT_ROUNDING, failed at t = 7711 with cond(Gamma) 1.7e9 in a 16th of the step): the whole
            # step is taken without imposing, if that keeps the invariants to rounding, as a step too short
            # for Gamma is (there it agrees with the whole imposed solve to 5e-15: tests/test_step_engine.py).
            split_for_rounding = False
            _back_to_start(work, y, y_comp, coef, coef_extra, mult)
            whole_status, whole_used = _attempt_unimposed(
                grad_H, hess_H, grad_invariants, params, settings, tables, conserve_idx, work,
                y, h, h_start, have_prev, coef, coef_extra, mult, newton_base)
            iterations += whole_used
            if whole_status == STATUS_OK:
                for p in range(n):
                    y[p], y_comp[p] = add_product(y[p], y_comp[p], h, coef[0, p])
                    work.stage_comp[p] = y_comp[p]
                work.info[5] = 1.0   # one (whole) step unimposed; the substeps before are undone
                substeps = 1
                h_prev = h
                break
        if depth >= settings.max_halvings:
            done_fraction = 1.0 - units_left * 0.5 ** depth
            diagnostics[DIAG_TIME] = clock[0] + done_fraction * h
            diagnostics[DIAG_STEP] = h_sub
            diagnostics[DIAG_INCREMENT] = work.info[0]
            diagnostics[DIAG_CONDITION] = work.info[1]
            diagnostics[DIAG_DEPTH] = depth
            diagnostics[DIAG_ITERATIONS] = used
            _back_to_start(work, y, y_comp, coef, coef_extra, mult)
            last_h[0] = h_start
            return status, iterations, substeps
        depth += 1
        units_left *= 2
    last_h[0] = h_prev
    clock[0], clock[1] = kahan_add(clock[0], clock[1], h)
    return STATUS_OK, iterations, substeps


@njit(cache=True, inline="always", error_model="numpy")
def _back_to_start(work, y, y_comp, coef, coef_extra, mult):
    """try_step's state as it was at the step's start (work.y_start, ..., saved on entry)."""
    _copy(work.y_start, y)
    _copy(work.y_comp_start, y_comp)
    _copy(work.y_comp_start, work.stage_comp)
    _copy(work.coef_start, coef)
    _copy_rows(work.extra_start, coef_extra, coef_extra.shape[0])
    _copy(work.mult_start, mult)


@njit(cache=True, inline="always", error_model="numpy")
def record_multipliers(unimposed, multipliers, out):
    """A step's multipliers for the run's output (alpha or lambda history): those of its last
    substep, or NaN when unimposed (work.info[5] after try_step) says that a substep of it was
    taken without imposing the invariants: no multiplier then exists
    (docs/solver.md#a-substep-without-imposing)."""
    for a in range(multipliers.shape[0]):
        out[a] = np.nan if unimposed > 0.0 else multipliers[a]


@internal
def restore_newton_matrix(grad_H, hess_H, params, settings, tables, work, newton_base):
    """Factorise the Newton matrix where newton_base says it was (a new kernel call's work is
    empty); a base that no longer factorises is dropped (the next step makes a new one)."""
    if settings.solver == SOLVER_FIXED_POINT or newton_base[0] == 0.0:
        return
    n = work.newton_scale.shape[0]
    if newton_factor(grad_H, hess_H, params, newton_base[3:3 + n], newton_base[1], tables, work) != STATUS_OK:
        newton_base[0] = 0.0


@njit(cache=True, inline="always", error_model="numpy")
def _sample(H, invariants, params, y, t, index, t_out, y_out, inv_out, inv_values):
    t_out[index] = t
    for p in range(y.shape[0]):
        y_out[index, p] = y[p]
    inv_out[index, 0] = H(y, params)
    invariants(y, params, inv_values)
    for a in range(inv_values.shape[0]):
        inv_out[index, 1 + a] = inv_values[a]


# The arguments every run kernel starts with (time_loop here, ensemble_loop): the problem's
# functions and parameters, the solver settings, h and the method's tables, conserve_idx.
RUN_ARGUMENT_TYPES = (
    H_TYPE, GRAD_H_TYPE, HESS_H_TYPE, INVARIANTS_TYPE, GRAD_INVARIANTS_TYPE, VECTOR,   # problem
    types.int64, types.int64, types.int64, types.int64, types.int64,                   # family, solver, stable_rhs,
    types.float64, types.int64, types.int64,                                           # warm_start, predictor, tol,
    #                                                                                    max_iter, max_halvings
    types.float64, MATRIX, MATRIX, MATRIX, MATRIX, MATRIX, VECTOR, VECTOR, MATRIX,    # h and the method's tables
    COMPLEX_VECTOR, COMPLEX_MATRIX, COMPLEX_MATRIX, VECTOR, MATRIX, MATRIX,            # (workspace.Tables)
    INT_VECTOR,                                                                        # conserve_idx
)

TIME_LOOP_SIGNATURE = types.int64(
    *RUN_ARGUMENT_TYPES,
    VECTOR, VECTOR, VECTOR, MATRIX, MATRIX, VECTOR, VECTOR, VECTOR,                    # y, y_comp, clock, coef,
    #                                                                                    coef_extra, multipliers,
    #                                                                                    last_h, newton_base
    types.float64,                                                                     # H_target
    types.int64, types.int64, types.int64, types.int64,                                # step_start, n_steps,
    #                                                                                    n_total, store_every
    VECTOR, MATRIX, MATRIX, MATRIX, INT_VECTOR, INT_VECTOR, INT_VECTOR, VECTOR,        # outputs, progress, diagnostics
)


@njit(TIME_LOOP_SIGNATURE, cache=True, nogil=True, error_model="numpy")
def time_loop(H, grad_H, hess_H, invariants, grad_invariants, params,
              family, solver, stable_rhs, warm_start, predictor, tol, max_iter, max_halvings,
              h, projection, Is, projection_hat, Ihat, X, abs_projection_hat, predictor_nodes, predictor_basis,
              newton_values, newton_vectors, newton_inverse, newton_weights, Is_low, Ihat_low,
              conserve_idx,
              y, y_comp, clock, coef, coef_extra, multipliers, last_h, newton_base, H_target,
              step_start, n_steps, n_total, store_every,
              t_out, y_out, inv_out, mult_out, iter_out, substeps_out, progress, diagnostics):
    """Run n_steps steps of one method in one call (docs/methods.md and docs/solver.md).

    Settings (see workspace.Settings): family, solver (codes.py), stable_rhs, warm_start,
    predictor, tol, max_iter, max_halvings. Tables (see workspace.Tables): the method's.
    State, updated in place so that consecutive calls continue one run exactly:
      y (n,), y_comp (n,): the state and its Kahan compensation;
      clock (2,): [t, its compensation]; coef (s, n): the last step's coefficients;
      coef_extra (predictor_extra_rows(k, s), n): its Legendre terms gamma_s.. (the predictor's);
      multipliers: alpha (nu,) for ELIM, lambda (nu+1,) for LIM; last_h (1,): the size
      of the last (sub)step (the predictor's theta); newton_base (n + 3,): where the
      Newton matrix was last factorised ([valid, h, last iterations, y...]; the call
      factorises it there again first, so that a run continued in a later call, or
      resumed, solves with the same matrix as an uninterrupted one).
    H_target: H(y0) of the run for the energy projection after every step (project_energy),
    NaN for none.
    Steps are numbered globally from step_start (0 for a new run) to step_start +
    n_steps; n_total is the run's total. The first step of a run (and every step without
    warm_start) starts cold, from coef = 0.

    Outputs, written from index 0 on:
      iter_out (n_steps,) iterations per step (every try, every substep);
      substeps_out (n_steps,) 1, or the number of substeps of a split step;
      mult_out (n_steps, len(multipliers)) the multipliers of the step's last substep;
      a sample after every global step that is a multiple of store_every, and after
      the last step of the run: t_out (n_samples,), y_out (n_samples, n),
      inv_out (n_samples, 1 + n_inv) holding H then the problem's invariants.
    progress (2,): [steps done in this call, samples written in this call].
    diagnostics (N_DIAGNOSTICS,): of a failed step (see try_step).

    Returns a status code: STATUS_OK, or the failing step's status; y, clock and coef
    then hold the last good step (the failed step is not applied), and progress says how
    far it got.
    """
    n = y.shape[0]
    k = Is.shape[0]
    r = Ihat.shape[0]
    s = coef.shape[0]
    n_inv = inv_out.shape[1] - 1
    settings = Settings(family, solver, stable_rhs, warm_start, predictor, tol, max_iter, max_halvings)
    # Tables and workspace are passed on by address (workspace.ByRef): by value, each call of
    # try_step, _attempt, solve and newton_factor copied their ~530 words (README run: Newton
    # 73.7 -> 60.8 ms, the fixed point 102.7 -> 88.7 ms, bit for bit the same steps).
    tables = by_ref(borrow_tables(Tables(projection, Is, projection_hat, Ihat, X, abs_projection_hat,
                                         predictor_nodes, predictor_basis, newton_values, newton_vectors,
                                         newton_inverse, newton_weights, Is_low, Ihat_low)))
    owners = make_workspace(n, k, r, s, conserve_idx.shape[0], family, n_inv, multipliers.shape[0],
                            newton_eigenvalues(settings, newton_values))
    work = by_ref(borrow_workspace(owners))   # owners stays alive in this frame until the loop is done
    inv_values = np.zeros(n_inv)
    projection_arrays = energy_projection_arrays(n, n_inv, conserve_idx.shape[0])

    n_samples = 0
    progress[0] = 0
    progress[1] = 0
    # The caller's arrays, borrowed for the call (no reference counting in the loop).
    params_view, conserve_view, y_view = borrowed(params), borrowed(conserve_idx), borrowed(y)
    y_comp_view, clock_view, coef_view = borrowed(y_comp), borrowed(clock), borrowed(coef)
    mult_view, last_h_view, diagnostics_view = borrowed(multipliers), borrowed(last_h), borrowed(diagnostics)
    base_view, extra_view = borrowed(newton_base), borrowed(coef_extra)
    restore_newton_matrix(grad_H, hess_H, params_view, settings, tables, work, base_view)
    status = STATUS_OK
    for step in range(n_steps):
        global_step = step_start + step
        status, iterations, substeps = try_step(
            grad_H, hess_H, grad_invariants, params_view, settings, tables, conserve_view, work,
            y_view, y_comp_view, clock_view, coef_view, extra_view, mult_view, h, last_h_view, base_view,
            global_step > 0, diagnostics_view, max_halvings > 0, max_halvings > 0)
        iter_out[step] = iterations
        if status != STATUS_OK:
            break
        substeps_out[step] = substeps
        project_energy(H, grad_H, grad_invariants, params_view, conserve_view, y_view, y_comp_view, H_target,
                       projection_arrays)
        record_multipliers(work.info[5], multipliers, mult_out[step])
        progress[0] = step + 1
        done = global_step + 1
        if done % store_every == 0 or done == n_total:
            _sample(H, invariants, params, y, clock[0], n_samples, t_out, y_out, inv_out, inv_values)
            n_samples += 1
            progress[1] = n_samples
    keep_alive(owners)   # the borrowed views in work point into owners' memory
    return status
