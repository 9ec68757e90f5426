"""Solving one step's nonlinear system: simplified Newton or the fixed point, with the
stopping rule of docs/solver.md.

Numba only. ``solve`` drives a family's residual map (maps.py) from an initial guess of
the coefficients to a converged iterate or a failure status; it knows nothing of the
time loop, predictors or step splitting (stepper.py).

Simplified Newton (docs/solver.md, the default): with X_s = Ps^T Omega Is (tridiagonal) and
J0 = J Hess(H) at the predicted midpoint (stepper._newton_point), M = I_{s n} - h X_s (x) J0
is factorised once per step, and each iteration applies
coef <- coef + M^-1 vec(G(coef) - coef).  The fixed point applies coef <- G(coef) (the
paper's iteration, whose counts Table 2 reports).
"""
import numpy as np
from numba import njit

from .codes import (internal, FAMILY_LIM, SOLVER_FIXED_POINT, SOLVER_NEWTON_ACCELERATED, STATUS_NONFINITE,
                    STATUS_NOT_CONVERGED, STATUS_OK, STATUS_SINGULAR)
from .linalg import invert_complex, invert_pair, invert_real, lu_factor, lu_solve_factored
from .simd import (abs4, add4, addsub4, div4, load4, load4_dup_row, load4_row, mul4, pair4, raise4, splat4, store4,
                   store4_row, store_pair_row, sub4)
from .maps import (EPS, RHS_STABLE, column_scaled_condition, condition_number, elim_map, elim_rhs_terms, elim_rounding,
                   gradient_sizes, lim_map, lim_rounding)

# The stopping rule's constants (docs/solver.md; measured there, not tunables).
BAND_FACTOR = 4.0          # the rounding band is B = 4 omega ...
BAND_CAP = 1e-12           # ... and never wider than this (relative increment)
IN_BAND_STALLS = 2         # accept after this many in-band iterations that fail to improve the best in-band d
MAX_WITHOUT_PROGRESS = 6   # outside the band, fail after this many iterations without a new best d
RESCUE_BAND_CAP = 1e-9     # a stalled iterate is accepted where every component is within 4 omega_p, up to this
MAX_CONDITION = 1e13       # an accepted alpha with cond(Gamma) above this is spurious
MAX_ETA_CORRECTION = 0.5   # ... and so is one with |h^(2(s-1-j)) alpha_j| above this
# A solve that stalls with cond(Gamma) above this is one where Assumption 1 fails for the imposed
# invariants (their gradients nearly dependent), which smaller steps do not cure: its failure is
# blamed on Gamma (integrate.failure_message) and never taken without imposing (stepper.try_step).
# Measured: well-posed steps have cond(Gamma) 8-30, up to 4e3 next to a pericentre; Kepler's L with
# A_x (gradients dependent at the apsides) stalled at 6e8.
NEARLY_SINGULAR_GAMMA = 1e6
# An imposed solve that converged with cond(Gamma) above this is split when the step may still be
# halved (stepper._attempt): its alpha, and so y1, carries rounding amplified by cond(Gamma), and the
# halves of such a step, nearly symmetric about a pericentre, are well conditioned. Measured: the step
# from t = 83610.3 of the README's run x100 (cond ~ 1e7) converged whole to 1.6e-14 of its 40-digit
# solution, where the NumPy reference in doubles misses it by 1.1e-13; split, 2e-16.
SPLIT_CONDITION = 1e6
# ... unless the rounding its alpha carries into the step (alpha_rounding: spec 8's share of omega, the
# componentwise |Gamma^-1| (db + dGamma |alpha|) in units of the state) is at most this. cond(Gamma) alone
# also grows with a poor scaling of Gamma's rows and columns, which pivoting does not mind: at e = 0.99
# (pericentre distance 0.01) every step near the pericentre has cond(Gamma) 1e6 to 1e9, growing like 1/h,
# with alpha's share at most 2.4e-16 (1.1 eps); splitting cascaded to the deepest level, 16 substeps
# each, for a fifth of the time-scale controller's steps. The hard step above: cond 6.3e6, share 4.2e-11.
SPLIT_ROUNDING = 4.0 * EPS
# The secant acceleration of simplified Newton (docs/solver.md#secant-acceleration; measured there,
# not tunables): used only while the increment is above ACCEL_FLOOR (below it the increments carry
# rounding that an extrapolation would amplify; at 1e-14 the slowest solve of the README's run took 16
# iterations instead of 13), while the iteration contracts by less than 1 / ACCEL_SLOW a step, when
# the change of the increment is nearly parallel to it (cos^2 above ACCEL_ALIGNMENT: one slow mode
# dominates), and with a weight below ACCEL_MAX_WEIGHT (a contraction of at most 0.999).
ACCEL_FLOOR = 1e-13
ACCEL_ALIGNMENT = 0.9
ACCEL_MAX_WEIGHT = 1e3
ACCEL_SLOW = 1e-3
# newton_factor's second try, when the Newton matrix equilibrated by the state is singular: no
# component scaled below this fraction of the largest (2^-26, the square root of eps). (Its third:
# one scale per block, positions and momenta.)
NEWTON_SCALE_FLOOR = 2.0 ** -26


@internal
def newton_factor(grad_H, hess_H, params, y, h, tables, work):
    """Factorise the simplified Newton matrix M = I - h X (x) J0, J0 = J Hess(H)(y) (docs/solver.md).

    Equilibrated: the unknowns are measured in units of the state, D = diag(d_p) with
    d_p = max(|y_p|, |h f_p(y)|) (the scale of the stopping rule; the largest of them where
    both vanish), so that M~ = D^-1 M D has entries of size h/(time scale) whatever the
    units (the solar system's momenta are 1e-11 to 1e-5 of its positions: unscaled,
    cond(M) was 1.7e19). The |h f_p| term matters where a coordinate passes through
    zero (Kepler's q2 and p1 at apocentre, ~1e-16): |y_p| alone made M~ singular there.

    Three forms (the workspace's arrays say which, workspace.make_workspace): with
    X = V Lambda V^-1 (tables newton_values, newton_vectors, newton_inverse), M~ is block
    diagonal in the eigenbasis, one complex n x n matrix I - h lambda J0~ per eigenvalue
    (one per conjugate pair), as in Hairer & Wanner's RADAU5; each block is inverted
    (small n, linalg.invert; the real eigenvalue of an odd s in real arithmetic, into
    work.newton_real_inverse; linalg.invert_real and invert_complex, invert's
    elimination in vector registers) or LU-factorised (large n). Without an eigenbasis (large s,
    where V is ill-conditioned), one real (s n) x (s n) LU of M~.
    Returns STATUS_OK, STATUS_NONFINITE (Hessian not finite) or STATUS_SINGULAR.
    """
    n = y.shape[0]
    m = n // 2
    hessian, unit, gradient = work.hessian, work.newton_scale, work.scale
    hess_H(y, params, hessian)
    grad_H(y, params, gradient)
    work.info[4] += 1.0
    largest = 0.0
    for p in range(m):   # |f| = |J grad H|: f_q = grad_p H, f_p = -grad_q H
        unit[p] = max(abs(y[p]), abs(h * gradient[m + p]))
        unit[m + p] = max(abs(y[m + p]), abs(h * gradient[p]))
    for p in range(n):
        largest = max(largest, unit[p])
    for p in range(n):
        if not (unit[p] > 0.0):
            unit[p] = largest if largest > 0.0 else 1.0
    status = _newton_factor_scaled(y, h, tables, work)
    if status != STATUS_SINGULAR:
        return status
    # Components far below the state's size are zeros by symmetry that rounding made nonzero, or the
    # small perturbations they seed (an FPU mode with every other particle at rest from
    # q = 0.5 cos(pi i / 2): q ~ 3e-17, growing along an unstable mode), coupled through the Hessian to
    # components of size 1: scaled by themselves they make M~ singular (entries 1e16). M~ is only the
    # approximate Jacobian of simplified Newton, so a second try scales every component as at least
    # NEWTON_SCALE_FLOOR of the state as a whole; the first try keeps a genuinely tiny component's own
    # scale (a light body's momentum, 1e-11 of the solar system's positions), which it needs.
    changed = False
    for p in range(n):
        if unit[p] < NEWTON_SCALE_FLOOR * largest:
            unit[p] = NEWTON_SCALE_FLOOR * largest
            changed = True
    if changed:
        hess_H(y, params, hessian)   # the first try overwrote it (the real block's scratch)
        work.info[4] += 1.0
        status = _newton_factor_scaled(y, h, tables, work)
        if status != STATUS_SINGULAR:
            return status
    # A third try with one scale for every position and one for every momentum (the largest of each
    # block). A zero by symmetry whose |h f| is small but far above rounding (a close pair along z
    # beside a third body in the x-y plane: out-of-plane momenta scaled at 4e-10 of the state) put
    # ratios of 1e9 between scales into J0~, and both tries above found M~ singular at every halving
    # (the ratios scale with h), where M itself had cond 3e8 (a user trial). The scaling changes only
    # how M is factorised, not the iteration (D^-1 M^-1 D is M^-1 in other units).
    q_scale, p_scale = 0.0, 0.0
    for p in range(m):
        q_scale = max(q_scale, unit[p])
        p_scale = max(p_scale, unit[m + p])
    for p in range(m):
        unit[p] = q_scale if q_scale > 0.0 else largest
        unit[m + p] = p_scale if p_scale > 0.0 else largest
    hess_H(y, params, hessian)
    work.info[4] += 1.0
    return _newton_factor_scaled(y, h, tables, work)


@njit(cache=True, inline="always", error_model="numpy")
def _split_real(real_inverse, split, b):
    """The real eigenvalue's inverted block, transposed, into rows (2 b) n + q of split (solve_inverted)."""
    n = real_inverse.shape[0]
    for p in range(n):
        for q in range(n):
            split[2 * b * n + q, p] = real_inverse[p, q]


@internal
def _newton_factor_scaled(y, h, tables, work):
    """newton_factor's J0~ and factorisation, with the equilibration in work.newton_scale and
    the Hessian at y in work.hessian."""
    n = y.shape[0]
    m = n // 2
    X = tables.X
    s = X.shape[0]
    hessian, jacobian, unit = work.hessian, work.jacobian, work.newton_scale
    # J0~[p, q] = (J Hess)[p, q] d_q / d_p, with (J Hess)[p] = Hess[m + p] and [m + p] = -Hess[p].
    # Four entries of a row at a time in one vector (simd.Double4, the same operations; the sign
    # change as -0.0 - x, exact like the scalar negation). Scalar tail for n % 4.
    n4 = n - n % 4
    for p in range(m):
        inverse_q, inverse_p = 1.0 / unit[p], 1.0 / unit[m + p]
        to_q, to_p = splat4(inverse_q), splat4(inverse_p)
        for q in range(0, n4, 4):
            d = load4(unit, q)
            store4_row(jacobian, p, q, mul4(mul4(load4_row(hessian, m + p, q), d), to_q))
            store4_row(jacobian, m + p, q, mul4(mul4(sub4(splat4(-0.0), load4_row(hessian, p, q)), d), to_p))
        for q in range(n4, n):
            jacobian[p, q] = hessian[m + p, q] * unit[q] * inverse_q
            jacobian[m + p, q] = -hessian[p, q] * unit[q] * inverse_p
    for p in range(n):
        for q in range(n):
            if not (abs(jacobian[p, q]) <= 1e308):
                return STATUS_NONFINITE
    values = tables.newton_values
    if work.newton_blocks.shape[0] > 0:
        blocks, pivots, scratch = work.newton_blocks, work.newton_block_pivots, work.newton_block_scratch
        inverted = scratch.shape[0] > 0
        real_inverse, split = work.newton_real_inverse, work.newton_inverse_split
        # X's real eigenvalue (odd s): its block in real arithmetic, a quarter of the work; the
        # Hessian's array is free once J0~ is built. Built first and inverted together with the
        # first complex block (linalg.invert_pair: the two eliminations' chains of dependent
        # operations overlap), alone when there is none (s = 1).
        real_pending = -1
        if inverted and real_inverse.shape[0] > 0:
            for b in range(values.shape[0]):
                if values[b].imag == 0.0:
                    real_pending = b
            real_factor = -h * values[real_pending].real
            real_block = hessian
            real_factor4 = splat4(real_factor)
            for p in range(n):
                for q in range(0, n4, 4):
                    store4_row(real_block, p, q, mul4(real_factor4, load4_row(jacobian, p, q)))
                for q in range(n4, n):
                    real_block[p, q] = real_factor * jacobian[p, q]
                real_block[p, p] += 1.0
            if values.shape[0] == 1:
                if invert_real(real_block, real_inverse) != 0:
                    return STATUS_SINGULAR
                _split_real(real_inverse, split, real_pending)
        for b in range(values.shape[0]):
            if inverted and values[b].imag == 0.0 and real_inverse.shape[0] > 0:
                continue
            factor = -h * values[b]
            block = scratch if inverted else blocks[b]
            if inverted:
                # factor * J (complex * float: Numba makes J complex, (f_re J - f_im 0) + i(f_re 0 + f_im J)),
                # two entries at a time as (re, im, re, im); the imaginary part's terms in the
                # other order (exact)
                factors = pair4(factor.real, factor.imag)
                zeros = mul4(pair4(factor.imag, factor.real), splat4(0.0))
                for p in range(n):
                    for q in range(0, n - n % 2, 2):
                        store_pair_row(block, p, q, addsub4(mul4(factors, load4_dup_row(jacobian, p, q)), zeros))
                    for q in range(n - n % 2, n):
                        block[p, q] = factor * jacobian[p, q]
                    block[p, p] += 1.0
            else:
                for p in range(n):
                    for q in range(n):
                        block[p, q] = factor * jacobian[p, q]
                    block[p, p] += 1.0
            if inverted:
                if real_pending >= 0:
                    if invert_pair(hessian, real_inverse, block, blocks[b]) != 0:
                        return STATUS_SINGULAR
                    _split_real(real_inverse, split, real_pending)
                    real_pending = -1
                elif invert_complex(block, blocks[b]) != 0:
                    return STATUS_SINGULAR
                inverse = blocks[b]
                for p in range(n):   # transposed, real and imaginary parts apart, for solve_inverted
                    for q in range(n):
                        split[2 * b * n + q, p] = inverse[p, q].real
                        split[(2 * b + 1) * n + q, p] = inverse[p, q].imag
            elif lu_factor(block, pivots[b]) != 0:
                return STATUS_SINGULAR
        return STATUS_OK
    M = work.newton_matrix
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


@njit(cache=True, inline="always", error_model="numpy")
def _eigen_rhs(V_inverse, delta, unit, b, p, n, s):
    """Component p of w_b = sum_j Vinv[b, j] r_j / d_p (newton_solve), as (real, imaginary): the
    parts apart, since a complex / float division is Numba's general complex division (Smith's
    algorithm, branches), and two real divisions give the same bits."""
    acc_re = 0.0
    acc_im = 0.0
    for j in range(s):
        x = delta[j * n + p]
        acc_re += V_inverse[b, j].real * x
        acc_im += V_inverse[b, j].imag * x
    return acc_re / unit[p], acc_im / unit[p]


@internal
def solve_inverted(V, V_inverse, weights, values, real_block, unit, split, rhs, delta, s):
    """newton_solve's inverse form: delta (s n,) <- D Re(sum_b weight_b V[:, b] B_b^-1 w_b),
    w_b = sum_j Vinv[b, j] r_j / d, with the inverted blocks as newton_factor leaves them in split
    (rows (2 b) n + q: Re B_b^-1[:, q], (2 b + 1) n + q: Im; the real eigenvalue's block, when
    real_block, in real arithmetic from its rows (2 b) n + q), w_b into rhs (rows 2 b, 2 b + 1).

    Four components p at a time in one vector (simd.Double4), each lane the operations of the
    scalar loops in their order, so the bits of them: the sums over j and q from 0.0 as written,
    Numba's complex product (ac - bd) + i(ad + bc) with each product rounded, and z *= weight d_p
    as Numba's complex * float, (z_re c - z_im 0) + i(z_re 0 + z_im c). Scalar tail for n % 4.
    """
    n = unit.shape[0]
    n4 = n - n % 4
    n_b = values.shape[0]
    for b in range(n_b):
        for p in range(0, n4, 4):
            acc_re = splat4(0.0)
            acc_im = splat4(0.0)
            for j in range(s):
                x = load4(delta, j * n + p)
                acc_re = add4(acc_re, mul4(splat4(V_inverse[b, j].real), x))
                acc_im = add4(acc_im, mul4(splat4(V_inverse[b, j].imag), x))
            d = load4(unit, p)
            store4_row(rhs, 2 * b, p, div4(acc_re, d))
            store4_row(rhs, 2 * b + 1, p, div4(acc_im, d))
        for p in range(n4, n):
            rhs[2 * b, p], rhs[2 * b + 1, p] = _eigen_rhs(V_inverse, delta, unit, b, p, n, s)
    for i in range(s * n):
        delta[i] = 0.0
    zero = splat4(0.0)
    for b in range(n_b):
        row_re = 2 * b * n
        row_im = row_re + n
        weight = weights[b]
        if values[b].imag == 0.0 and real_block:
            # the real eigenvalue's block (newton_factor): w_b, V[:, b] and the inverse are real
            for p in range(0, n4, 4):
                z = splat4(0.0)
                for q in range(n):
                    z = add4(z, mul4(load4_row(split, row_re + q, p), splat4(rhs[2 * b, q])))
                z = mul4(z, mul4(splat4(weight), load4(unit, p)))
                for j in range(s):
                    i = j * n + p
                    store4(delta, i, add4(load4(delta, i), mul4(splat4(V[j, b].real), z)))
            for p in range(n4, n):
                z_re = 0.0
                for q in range(n):
                    z_re += split[row_re + q, p] * rhs[2 * b, q]
                z_re *= weight * unit[p]
                for j in range(s):
                    delta[j * n + p] += V[j, b].real * z_re
            continue
        for p in range(0, n4, 4):
            z_re = splat4(0.0)
            z_im = splat4(0.0)
            for q in range(n):
                a = load4_row(split, row_re + q, p)
                a_im = load4_row(split, row_im + q, p)
                c = splat4(rhs[2 * b, q])
                c_im = splat4(rhs[2 * b + 1, q])
                z_re = add4(z_re, sub4(mul4(a, c), mul4(a_im, c_im)))
                z_im = add4(z_im, add4(mul4(a, c_im), mul4(a_im, c)))
            factor = mul4(splat4(weight), load4(unit, p))
            scaled_re = sub4(mul4(z_re, factor), mul4(z_im, zero))
            scaled_im = add4(mul4(z_re, zero), mul4(z_im, factor))
            for j in range(s):
                i = j * n + p
                product = sub4(mul4(splat4(V[j, b].real), scaled_re), mul4(splat4(V[j, b].imag), scaled_im))
                store4(delta, i, add4(load4(delta, i), product))
        for p in range(n4, n):
            z = 0.0 + 0.0j
            for q in range(n):
                z += complex(split[row_re + q, p], split[row_im + q, p]) * complex(rhs[2 * b, q], rhs[2 * b + 1, q])
            z *= weight * unit[p]
            for j in range(s):
                delta[j * n + p] += (V[j, b] * z).real


@njit(cache=True, inline="always", error_model="numpy")
def newton_solve(tables, work, delta):
    """delta (s n,) <- M^-1 delta with the factors of newton_factor (same two forms).

    Block forms: w = V^-1 D^-1 r (per eigenvalue b, w_b = sum_j Vinv[b, j] r_j / d), z_b =
    (I - h lambda_b J0~)^-1 w_b (a product with the inverted block, or the LU solve),
    Delta = D Re(sum_b weight_b V[:, b] z_b), weight 2 for the representative of a
    conjugate pair (its partner contributes the conjugate), 1 for a real eigenvalue.
    """
    n = work.newton_scale.shape[0]
    unit = work.newton_scale
    values = tables.newton_values
    s = tables.X.shape[0]
    if work.newton_blocks.shape[0] > 0:
        V, V_inverse, weights = tables.newton_vectors, tables.newton_inverse, tables.newton_weights
        blocks, pivots, rhs = work.newton_blocks, work.newton_block_pivots, work.newton_block_rhs
        if work.newton_block_scratch.shape[0] > 0:
            solve_inverted(V, V_inverse, weights, values, work.newton_real_inverse.shape[0] > 0, unit,
                           work.newton_inverse_split, work.newton_rhs_split, delta, s)
            return
        for b in range(values.shape[0]):
            for p in range(n):
                re, im = _eigen_rhs(V_inverse, delta, unit, b, p, n, s)
                rhs[b, p] = complex(re, im)
        for b in range(values.shape[0]):
            lu_solve_factored(blocks[b], pivots[b], rhs[b])
        for j in range(s):
            for p in range(n):
                acc = 0.0
                for b in range(values.shape[0]):
                    acc += weights[b] * (V[j, b] * rhs[b, p]).real
                delta[j * n + p] = acc * unit[p]
        return
    for j in range(s):
        for p in range(n):
            delta[j * n + p] /= unit[p]
    # delta holds 3 s n numbers (the secant history behind the first s n): solve on the first
    # s n only (lu_solve_factored takes its size from x; the whole array ran past the pivots
    # and crashed every method without an eigenbasis of X, s >= 11)
    lu_solve_factored(work.newton_matrix, work.newton_pivots, delta[:s * n])
    for j in range(s):
        for p in range(n):
            delta[j * n + p] *= unit[p]


@njit(cache=True, inline="always", error_model="numpy")
def accelerates(settings, nu):
    """Does a solve with these settings, imposing nu invariants, take secant steps
    (docs/solver.md#secant-acceleration)? Only simplified Newton with the acceleration on, and only on
    ELIM imposing invariants: elsewhere Newton has no slow mode for it to remove (HBVM(12,3),
    GHBVM(12,3) on Kepler e = 0.6: 4.41 and 4.49 iterations per step either way), and it costs ~5%."""
    return settings.solver == SOLVER_NEWTON_ACCELERATED and settings.family != FAMILY_LIM and nu > 0


@internal
def _secant_update(h, scale, delta, coef, component, have_history, d_before, s, n):
    """One update of simplified Newton with the secant acceleration (docs/solver.md#secant-acceleration);
    returns d, the stopping rule's size of the plain increment f = delta[:s n], and sets component.

    Anderson's acceleration with one difference: with df = f - f_prev and the previous iterate
    c_prev (delta[s n:2 s n] and delta[2 s n:], kept here), coef <- coef + f - g ((coef - c_prev) + df),
    g = <df, f> / <df, df> in the stopping rule's units (h / sc_p). g = 0 (a plain step) without
    history (have_history), at or below ACCEL_FLOOR, where the iteration already contracts by more
    than 1 / ACCEL_SLOW, unless df and f are nearly parallel (<df, f>^2 > ACCEL_ALIGNMENT <df, df>
    <f, f>: one slow mode), and for |g| >= ACCEL_MAX_WEIGHT. Outside solve's loop so that the plain
    iteration compiles as before (inlined, it made the README's run 15% slower with Newton and 27% with
    the fixed point, which never takes this branch)."""
    sn = s * n
    n4 = n - n % 4
    d = 0.0
    # component[p] four at a time in one vector (simd.Double4: each lane the scalar division and the
    # same NaN-catching maximum, simd.raise4); scalar tail for n % 4
    h4 = splat4(h)
    for p in range(0, n4, 4):
        largest4 = splat4(0.0)
        sc = load4(scale, p)
        for j in range(s):
            largest4 = raise4(largest4, div4(abs4(mul4(h4, load4(delta, j * n + p))), sc))
        store4(component, p, largest4)
    for p in range(n4, n):
        largest_p = 0.0
        for j in range(s):
            value = abs(h * delta[j * n + p]) / scale[p]
            if not (value <= largest_p):   # also catches NaN
                largest_p = value
        component[p] = largest_p
    for p in range(n):
        largest_p = component[p]
        if not (largest_p <= d):
            d = largest_p
    weight = 0.0
    if have_history and d > ACCEL_FLOOR and d > ACCEL_SLOW * d_before and d <= 1e308:
        along = 0.0
        squared = 0.0
        size = 0.0
        for p in range(n):
            unit = (h / scale[p]) ** 2
            for j in range(s):
                i = j * n + p
                difference = delta[i] - delta[2 * sn + i]
                along += unit * difference * delta[i]
                squared += unit * difference * difference
                size += unit * delta[i] * delta[i]
        if squared > 0.0 and along * along > ACCEL_ALIGNMENT * squared * size:
            weight = along / squared
            if not (abs(weight) < ACCEL_MAX_WEIGHT):
                weight = 0.0
    weight4 = splat4(weight)
    for j in range(s):
        for p in range(0, n4, 4):
            i = j * n + p
            now, c = load4(delta, i), load4_row(coef, j, p)
            step = now
            if weight != 0.0:
                step = sub4(now, mul4(weight4, add4(sub4(c, load4(delta, sn + i)), sub4(now, load4(delta, 2 * sn + i)))))
            store4(delta, sn + i, c)
            store4(delta, 2 * sn + i, now)
            store4_row(coef, j, p, add4(c, step))
        for p in range(n4, n):
            i = j * n + p
            step = delta[i]
            if weight != 0.0:
                step -= weight * ((coef[j, p] - delta[sn + i]) + (delta[i] - delta[2 * sn + i]))
            delta[sn + i] = coef[j, p]
            delta[2 * sn + i] = delta[i]
            coef[j, p] += step
    return d


@internal
def _rounding_level(h, mult, solved, settings, tables, nu, s, work):
    """omega of docs/solver.md, component by component, into work.rounding_level; returns max_p omega_p.

    omega_p = 4 eps h F_p / sc_p  +  the multipliers' share:
      ELIM  max_c h w_c dalpha_c |gamma_{j_c,p}| / sc_p
      LIM   h sum_a dlambda_a |phi_0^a_p| / sc_p
    with F_p = max_l |f_{l,p}| (docs/solver.md takes max_p F_p in the second term; per component is
    a tighter bound, see maps._dot_rounding). solved: the last map solved its small system
    (else only the first term).
    """
    scale, level, rounding, phi, sizes = work.scale, work.rounding_level, work.small_rounding, work.phi, work.sizes
    n = scale.shape[0]
    is_lim = settings.family == FAMILY_LIM
    n_rows = nu + 1 if is_lim else nu
    gradient_sizes(work, n_rows if solved else 0, tables.Ihat.shape[0])
    # |h|: a backward run's h is negative, and its band must be the forward run's
    for p in range(n):
        level[p] = 4.0 * EPS * abs(h) * sizes[0, p] / scale[p]
    if solved and is_lim:
        lim_rounding(tables, n_rows, s, settings.stable_rhs, work)
        metric = work.metric
        for p in range(n):
            acc = 0.0
            for a in range(n_rows):
                acc += rounding[0, a] * metric[p] * abs(phi[a, 0, p])
            level[p] += abs(h) * acc / scale[p]
    elif solved and nu > 0:
        elim_rounding(h, mult, (settings.stable_rhs & RHS_STABLE) != 0, tables, nu, s, work)
        for p in range(n):
            level[p] += _alpha_share(h, nu, s, work, p)
    omega = 0.0
    for p in range(n):
        omega = max(omega, level[p])
    return omega


@njit(cache=True, inline="always", error_model="numpy")
def _alpha_share(h, nu, s, work, p):
    """ELIM's share of omega_p (docs/solver.md): |h| max_c w_c dalpha_c |gamma_{j_c,p}| / sc_p, j_c = s - nu + c,
    with dalpha in work.small_rounding[0] (maps.elim_rounding)."""
    rounding, gamma, h_powers = work.small_rounding, work.gamma, work.h_powers
    share = 0.0
    for c in range(nu):
        share = max(share, h_powers[c] * rounding[0, c] * abs(gamma[s - nu + c, p]))
    return abs(h) * share / work.scale[p]


@internal
def alpha_rounding(h, mult, settings, tables, nu, s, work):
    """The rounding an accepted ELIM solve's alpha carries into its step: max_p of _alpha_share, the
    multipliers' part of docs/solver.md's omega, from the last map's gradients and Gamma (nu >= 1).
    stepper._attempt splits a solve with cond(Gamma) above SPLIT_CONDITION only when this exceeds
    SPLIT_ROUNDING."""
    gradient_sizes(work, nu, tables.Ihat.shape[0])
    elim_rounding(h, mult, (settings.stable_rhs & RHS_STABLE) != 0, tables, nu, s, work)
    largest = 0.0
    for p in range(work.scale.shape[0]):
        largest = max(largest, _alpha_share(h, nu, s, work, p))
    return largest


@internal
def _carried_level(h, work):
    """Add to each omega_p (at least eps) the rounding of the other components carried into p
    by one step of the dynamics, h/2 sum_q |J0~[p, q]| omega_q (J0~: the equilibrated
    Jacobian of newton_factor; |X| <= 1/2), in place; returns the new max_p omega_p.

    Near a pericentre of Kepler e = 0.9, |J0| ~ 1/r^3 ~ 10^3 turns the eps of the stage
    sums into increments of ~6 eps that no iteration removes; Pluto's position inherits
    the rounding of its momentum through 1/m. Simplified Newton only (it has J0~).
    """
    level, jacobian, unit, scale, carried = (work.rounding_level, work.jacobian, work.newton_scale, work.scale,
                                             work.carried)
    n = level.shape[0]
    for p in range(n):
        acc = 0.0
        for q in range(n):
            acc += abs(jacobian[p, q]) * max(level[q], EPS) * (scale[q] / unit[q])
        carried[p] = 0.5 * abs(h) * acc * (unit[p] / scale[p])
    largest = 0.0
    for p in range(n):
        level[p] = max(level[p], EPS) + carried[p]
        largest = max(largest, level[p])
    return largest


@internal
def _band(h, mult, solved, newton, settings, tables, nu, s, work):
    """The rounding band B = min(4 max(omega, eps), 1e-12) of docs/solver.md (omega from _rounding_level,
    and for Newton with the rounding the Jacobian carries, _carried_level)."""
    omega = _rounding_level(h, mult, solved, settings, tables, nu, s, work)
    if newton:
        omega = _carried_level(h, work)
    return min(BAND_FACTOR * max(omega, EPS), BAND_CAP)


@internal
def _within_rounding(h, mult, solved, settings, tables, nu, s, work):
    """A stalled iterate's test: is every component's increment within its own rounding band,
    d_p <= max(tol, min(4 omega'_p, 1e-9)), omega' as in _carried_level?"""
    _rounding_level(h, mult, solved, settings, tables, nu, s, work)
    _carried_level(h, work)
    level, component = work.rounding_level, work.component_increment
    for p in range(level.shape[0]):
        if not (component[p] <= max(settings.tol, min(BAND_FACTOR * level[p], RESCUE_BAND_CAP))):
            return False
    return True


@internal
def solve(grad_H, grad_invariants, params, settings, tables, conserve_idx, work, y, h, coef, mult, cold):
    """Iterate a family's map from the guess coef to a converged iterate (docs/solver.md).

    settings.solver: SOLVER_NEWTON or SOLVER_NEWTON_ACCELERATED (both need work.newton_matrix
    factorised for this y and h by newton_factor; the second takes secant steps on ELIM imposing
    invariants, _secant_update) or the fixed point. coef (s, n) and mult (alpha or lambda) in/out.
    cold: the stages start at y (coef = 0): ELIM keeps alpha = 0 for two sweeps.

    Stopping rule (docs/solver.md), on d = max_{j,i} |h Delta_{j,i}| / sc_i, sc_i = max(|y_i|, |h G_0,i|):
      accept when d <= settings.tol (round-off);
      inside the rounding band d <= B = min(4 max(omega, eps), 1e-12), accept after 2
      iterations in a row that fail to improve the best d below 1e-12, when that best is
      in the band too (Newton: omega plus the rounding carried in by the Jacobian,
      _carried_level; B is estimated only once an iteration fails to improve);
      after 6 iterations without a new best d (stalled), Newton on LIM (or on ELIM with the
      literal right-hand side) accepts if every component is within its own band
      (_within_rounding), else fails; fail at max_iter or on NaN.
    The stalled LIM case is beyond docs/solver.md: with LIM imposing momenta of the solar system,
    the rounding of lambda (eps times the largest momenta) reaches every momentum, and
    Pluto's, 1e-6 of Jupiter's, cannot settle below ~1e-11 relative; the iteration then
    cycles at that level (measured: a period-2 cycle, d = 9.1e-12) and only halving h
    would get it under docs/solver.md's 1e-12 cap. That was the literal right-hand side's
    rounding: the stable tail (maps.lim_rhs_terms, the default) removes it there (GHBVM(12,3),
    h = 12.5: 3.1 iterations per step, was 4.1-4.6), but the rescue stays for rhs: literal.
    An accepted ELIM iterate is rejected as spurious when cond(Gamma) > 1e13 or some
    |w_c alpha_c| > 0.5, and as singular when its Gamma could not be solved.

    Returns (status, iterations); work.info = [last d, cond(Gamma) or 0, iterations, last B].
    """
    n = y.shape[0]
    s = coef.shape[0]
    nu = conserve_idx.shape[0]
    is_lim = settings.family == FAMILY_LIM
    # ELIM whose bvec is the paper's sum (rhs literal, or r > k: maps.elim_rhs_terms)
    paper_sum = elim_rhs_terms((settings.stable_rhs & RHS_STABLE) != 0, tables.Is.shape[0], tables.Ihat.shape[0],
                               coef.shape[0])[0] == 0
    newton = settings.solver != SOLVER_FIXED_POINT
    # Bound once: an attribute read inside the loop costs a reference count update per read.
    delta, scale, new_coef, info, h_powers = work.delta, work.scale, work.new_coef, work.info, work.h_powers
    component = work.component_increment
    max_iter, tol = settings.max_iter, settings.tol
    for c in range(nu):
        h_powers[c] = h ** (2 * (nu - 1 - c))

    accelerate = accelerates(settings, nu)
    have_history = False
    d_before = np.inf
    best = np.inf
    without_progress = 0
    best_in_band = np.inf
    stalls = 0
    band = 0.0
    band_complete = False
    d = np.inf
    accepted = False
    singular = 0
    iteration = 0
    for iteration in range(1, max_iter + 1):
        plain_sweep = cold and iteration <= 2
        if is_lim:
            singular = lim_map(grad_H, grad_invariants, params, y, h, coef, mult, tables, conserve_idx, work,
                               settings.stable_rhs)
            if singular != 0:
                info[0], info[1], info[2], info[3] = d, np.inf, iteration, band
                return STATUS_SINGULAR, iteration
        else:
            singular = elim_map(grad_H, grad_invariants, params, y, h, coef, mult, plain_sweep,
                                (settings.stable_rhs & RHS_STABLE) != 0, tables, conserve_idx, work)

        largest = 0.0
        for i in range(n):
            scale[i] = max(abs(y[i]), abs(h * new_coef[0, i]))
            largest = max(largest, scale[i])
        for i in range(n):
            if not (scale[i] > 0.0):
                # A component and its increment both exactly zero: measure it against the
                # state as a whole (NaN falls through to the finiteness test below).
                scale[i] = largest if largest > 0.0 else 1.0
            elif scale[i] < EPS * largest:
                # Below rounding of the state as a whole, a component's value and increment shrink
                # together, so measured against themselves they never converge (d stayed at 1):
                # Newton: one zero by symmetry (an FPU mode with particles at rest) that its solve
                # couples to the others; the fixed point: the far end of a chain started from rest,
                # which the iteration reaches one neighbour per sweep (a pulse at one end of 64
                # masses failed at step 1). Newton measures it against the Newton matrix's own
                # scale of it (newton_factor's d_p at the step's start: the state as a whole where
                # it was zero there), so that a small but genuine component (a light body's
                # momentum) keeps its own; the fixed point, which has none, against rounding of
                # the state, eps times its largest component.
                scale[i] = max(scale[i], work.newton_scale[i] if newton else EPS * largest)
        for j in range(s):
            for p in range(n):
                delta[j * n + p] = new_coef[j, p] - coef[j, p]
        if newton:
            newton_solve(tables, work, delta)
        if accelerate:
            if cold and iteration <= 3:
                have_history = False    # alpha switches on after two plain sweeps: another map
            d = _secant_update(h, scale, delta, coef, component, have_history, d_before, s, n)
            have_history = d > ACCEL_FLOOR
            d_before = d
        else:
            d = 0.0
            for p in range(n):
                largest_p = 0.0
                for j in range(s):
                    value = abs(h * delta[j * n + p]) / scale[p]
                    if not (value <= largest_p):   # also catches NaN
                        largest_p = value
                    coef[j, p] += delta[j * n + p]
                component[p] = largest_p
                if not (largest_p <= d):
                    d = largest_p
        if not (d <= 1e308):
            info[0], info[1], info[2], info[3] = d, 0.0, iteration, band
            return STATUS_NONFINITE, iteration
        if cold and not is_lim and nu > 0 and iteration == 3:
            # alpha has just switched on: the map changed, progress counts afresh
            best = np.inf
            without_progress = 0
            best_in_band = np.inf
            band = 0.0
            band_complete = False
        if d <= tol:
            accepted = True
            break
        if d <= BAND_CAP:
            if d < best_in_band:
                # Still improving below the cap: the band is not needed yet (most steps end
                # here at d <= tol, and estimating the band costs about a tenth of a step).
                best_in_band = d
                stalls = 0
            else:
                # Not improving: is it the rounding level? Estimated at most twice per solve,
                # first without the multipliers' share (a lower bound, docs/solver.md's first term
                # and, for Newton, what the Jacobian carries), then with it if that does not
                # explain d. Never narrower than 4 eps: the stage sums y + h sum_j Is c_j
                # round at eps relative to sc (>= |y|), so d does not settle below ~eps
                # whatever omega says (LIM(8,10,3) on Kepler stalled at d = 1.3 eps with
                # omega = 7e-17).
                if band == 0.0:
                    band = _band(h, mult, np.bool_(False), newton, settings, tables, nu, s, work)
                if (d > band or best_in_band > band) and not band_complete:
                    band = _band(h, mult, singular == 0 and not plain_sweep, newton, settings, tables, nu, s, work)
                    band_complete = True
                if d <= band and best_in_band <= band:
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
                # LIM, and ELIM with the paper's literal right-hand side: there the rounding of
                # the multipliers is what stalls an iterate (docs/methods.md#stable-right-hand-side). ELIM with the stable
                # form stalls near steps symmetric about a pericentre, where Gamma is nearly
                # singular and an in-band test would accept unconverged iterates (docs/solver.md):
                # those are split, and their halves are well-conditioned.
                if d <= RESCUE_BAND_CAP and newton and (is_lim or paper_sum):
                    accepted = _within_rounding(h, mult, singular == 0 and not plain_sweep, settings, tables,
                                                nu, s, work)
                break

    info[0], info[1], info[2], info[3] = d, 0.0, iteration, band
    if not accepted:
        if not is_lim and nu > 0 and singular == 0 and not plain_sweep:
            # For the failure's message: an iteration that stalls where Gamma is nearly singular
            # (Assumption 1 failing, e.g. Kepler's L with A_x at the apsides) is not cured by smaller steps.
            info[1] = condition_number(work, nu, False)
        return STATUS_NOT_CONVERGED, iteration
    if is_lim or nu == 0 or (cold and iteration <= 2):
        return STATUS_OK, iteration
    if singular != 0:
        info[1] = np.inf
        return STATUS_SINGULAR, iteration
    # Spurious solutions (docs/solver.md): a nearly singular Gamma, or a correction as large as the term.
    cond = condition_number(work, nu, False)
    info[1] = cond
    if not (cond <= MAX_CONDITION) and not (column_scaled_condition(work, nu) <= MAX_CONDITION):
        # Only a Gamma ill-conditioned after its columns are scaled is spurious: the w_c in its
        # columns make cond(Gamma) alone grow as the step shrinks (maps.column_scaled_condition).
        return STATUS_SINGULAR, iteration
    for c in range(nu):
        if not (abs(h_powers[c] * mult[c]) <= MAX_ETA_CORRECTION):
            return STATUS_SINGULAR, iteration
    return STATUS_OK, iteration
