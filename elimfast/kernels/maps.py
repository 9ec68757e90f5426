"""The residual maps of the methods: coefficients in, the map G(coefficients) out.

Numba only. Each family supplies one map and the solver (solver.py) drives it, the
way scipy's Radau separates ``solve_collocation_system`` from the method:

    elim_map  ELIM(r,k,s) of docs/methods.md#elim with the stable right-hand side (and HBVM,
              GAUSS when no invariant is imposed, docs/methods.md#hbvm)
    lim_map   LIM(r,k,s) of docs/methods.md#lim

The unknowns are the *effective* coefficients ``coef[j]``: eta_j gamma_j (ELIM; eta_j = 1
for HBVM) or coef[0] = gamma_0 - phi_0 lambda, coef[j>0] = gamma_j (LIM), so that every
family's stages are ``u(c h) = y0 + h sum_j (int_0^c P_j) coef[j]`` and its new state is
``y1 = y0 + h coef[0]``. A map evaluates the stages of ``coef``, the problem's gradients
there, the Legendre coefficients gamma_j and phi_j, the small system (Gamma or the
Gram matrix) and its multipliers, and writes G(coef) into ``work.new_coef``.

Each map also has its rounding estimate (``*_rounding``): how far round-off alone moves
G through the multipliers, the second term of the rounding level omega of docs/solver.md.
"""
import numpy as np
from numba import njit

from .linalg import cholesky_factor, cholesky_solve_factored, lu_factor, lu_factor_columns, lu_solve_factored
from .quadrature import quick_two_sum, two_prod
from .simd import add4, load4, load4_row, mul4, splat4, store4_row

EPS = 2.0 ** -52


@njit(cache=True, inline="always", error_model="numpy")
def stages(y, comp, scaled, scaled_low, coef, n_coef, out):
    """out[l] = (y + comp) + h sum_{j<n_coef} Is[l, j] coef[j]   (docs/methods.md#hbvm: u_l = u(c_l h)),
    with h Is = scaled + scaled_low (scale_tables) and comp the Kahan compensation of y.

    Rounded once, at the size of the stage increment (docs/methods.md#round-off-over-long-times):
    the leading term scaled[l, 0] coef[0] alone, then the small ones (comp, the leading term's low
    part, the other coefficients' terms) summed apart and added to it, then y. (The other low
    parts, scaled_low[l, j >= 1] coef[j], are below the rounding of the small sum and left out:
    with them the run took 4% more time and drifted no less.) Rounding the sum first and
    multiplying it by h after (the paper's form, y + h sum) rounds twice, and h = 0.1 (mantissa
    8/5) rounds products with a mean error of -0.057 eps on the doubles near 0.6: with the
    rounded table Is that made GAUSS(2) gain 3.6e-19 of H per step on the harmonic oscillator,
    the same for every start, a linear drift instead of a random walk.

    Four components at a time in one vector (simd.Double4: each lane the scalar operations, the
    same bits), the nodes in the inner loop (y, comp and coef[0] loaded once per four components).
    """
    n = y.shape[0]
    n4 = n - n % 4
    for i in range(0, n4, 4):
        y4 = load4(y, i)
        comp4 = load4(comp, i)
        coef4 = load4_row(coef, 0, i)
        for l in range(out.shape[0]):
            small = add4(comp4, mul4(splat4(scaled_low[l, 0]), coef4))
            for j in range(1, n_coef):
                small = add4(small, mul4(splat4(scaled[l, j]), load4_row(coef, j, i)))
            store4_row(out, l, i, add4(y4, add4(mul4(splat4(scaled[l, 0]), coef4), small)))
    for l in range(out.shape[0]):
        for i in range(n4, n):
            small = comp[i] + scaled_low[l, 0] * coef[0, i]
            for j in range(1, n_coef):
                small += scaled[l, j] * coef[j, i]
            out[l, i] = y[i] + (scaled[l, 0] * coef[0, i] + small)


@njit(cache=True, inline="always", error_model="numpy")
def scale_tables(h, tables, work):
    """work.scaled_Is (+ scaled_Is_low) = h (Is + Is_low) as a double-double, and the same for
    Ihat where r != k (where r = k the maps take the stages at the k nodes for both), unless they
    already hold this h (work.scaled_h): the stages' tables (stages). Exact products
    (quadrature.two_prod) of the double h with the double-double tables."""
    if work.scaled_h[0] == h:
        return
    for pair in range(1 if tables.Ihat.shape[0] == tables.Is.shape[0] else 2):
        high, low = (tables.Is, tables.Is_low) if pair == 0 else (tables.Ihat, tables.Ihat_low)
        out, out_low = (work.scaled_Is, work.scaled_Is_low) if pair == 0 else (work.scaled_Ihat, work.scaled_Ihat_low)
        for l in range(high.shape[0]):
            for j in range(high.shape[1]):
                product, error = two_prod(h, high[l, j])
                out[l, j], out_low[l, j] = quick_two_sum(product, error + h * low[l, j])
    work.scaled_h[0] = h


@njit(cache=True, inline="always", error_model="numpy")
def project(projection, values, n_degrees, out):
    """out[j] = sum_l projection[j, l] values[l] = sum_l b_l P_j(c_l) values[l], j < n_degrees.

    The discrete Legendre coefficients of docs/methods.md#hbvm (gamma_j) and #elim (phi_j) of the rows of
    values (n_nodes, n); projection (>= n_degrees, n_nodes) holds b_l P_j(c_l).
    Each sum runs over l in order from 0.0, in registers: four components at a time in one
    vector (simd.Double4; accumulating into out[j, i] chains every update through memory,
    3x slower), for two degrees j at a time (two independent chains of additions, which
    share the loads of values). The vector lanes do the scalar operations: the same bits
    as one scalar sum per (j, i). Measured (the three projections of EHBVM(12,3) on
    Kepler, n = 4): 456 ns with four scalar sums, 210 ns.
    """
    n = values.shape[1]
    n_nodes = values.shape[0]
    n4 = n - n % 4
    n2 = n_degrees - n_degrees % 2
    for j in range(0, n2, 2):
        for i in range(0, n4, 4):
            acc = splat4(0.0)
            acc_next = splat4(0.0)
            for l in range(n_nodes):
                x = load4_row(values, l, i)
                acc = add4(acc, mul4(splat4(projection[j, l]), x))
                acc_next = add4(acc_next, mul4(splat4(projection[j + 1, l]), x))
            store4_row(out, j, i, acc)
            store4_row(out, j + 1, i, acc_next)
        for i in range(n4, n):
            acc1 = 0.0
            acc1_next = 0.0
            for l in range(n_nodes):
                acc1 += projection[j, l] * values[l, i]
                acc1_next += projection[j + 1, l] * values[l, i]
            out[j, i] = acc1
            out[j + 1, i] = acc1_next
    for j in range(n2, n_degrees):
        for i in range(0, n4, 4):
            acc = splat4(0.0)
            for l in range(n_nodes):
                acc = add4(acc, mul4(splat4(projection[j, l]), load4_row(values, l, i)))
            store4_row(out, j, i, acc)
        for i in range(n4, n):
            acc1 = 0.0
            for l in range(n_nodes):
                acc1 += projection[j, l] * values[l, i]
            out[j, i] = acc1


@njit(cache=True, inline="always", error_model="numpy")
def apply_J(projected, n_degrees, out):
    """out[j] = J projected[j], J = [[0, I], [-I, 0]] (docs/methods.md#notation)."""
    m = projected.shape[1] // 2
    for j in range(n_degrees):
        for i in range(m):
            out[j, i] = projected[j, m + i]
            out[j, m + i] = -projected[j, i]


# Where the stable tail's phi_j (j >= s) come from (elim_rhs_terms, lim_rhs_terms).
TAIL_SAME = 0      # the literal sum, or r = k: phi_j as the map computes them
TAIL_K_NODES = 1   # r < k: phi_j (j >= s) from the k nodes (grad L evaluated there), into phi's rows j >= s


@njit(cache=True, inline="always")
def elim_rhs_terms(stable_rhs, k, r, s):
    """The Legendre indices j in [first, last) whose phi_j^T gamma_j make up bvec (first = 0: the
    paper's sum_{j<s}; first = s: the stable tail, with the opposite sign), and where the tail's phi_j
    come from (TAIL_*; docs/methods.md#elim, #stable-right-hand-side).

    The tail -sum_{j=s}^{k-1} phi_j^T gamma_j equals sum_{j<s} phi_j^T gamma_j when both are taken
    at the k nodes (the identity of docs/methods.md#stable-right-hand-side). r < k: grad L at the k
    nodes too, so that bvec is the paper's exactly whenever the r nodes integrate phi_j (j < s)
    exactly (L of degree <= 2r/s, the paper's condition for keeping L: quadratic invariants for any
    r >= s). Taken at the r nodes instead (as the spec's 3b says) it missed the k-node part of
    gamma_j, and r = s left the tail empty (alpha = 0: HBVM's conservation, a user trial's
    ELIM(3,12,3)). r > k: no tail is exact in general (at the r nodes it needs H of degree <= 2k/s,
    at the k nodes L of degree <= 2k/s; a user trial's ELIM(6,3,2) lost L at 3e-7), so the paper's sum."""
    if not stable_rhs or r > k:
        return 0, s, TAIL_SAME
    if r == k:
        return s, k, TAIL_SAME
    return s, k, TAIL_K_NODES


@njit(cache=True, inline="always", error_model="numpy")
def tail_phi_at_k_nodes(grad_invariants, params, u, conserve_idx, projection, first_row, s, k, inv_grads, phi):
    """phi[first_row + a, j] = sum_l b_l P_j(c_l) grad L_a(u_l) for j in [s, k), the imposed
    invariants' tail at the k nodes (TAIL_K_NODES; docs/methods.md#stable-right-hand-side).
    Rows j < s (at the r nodes, which define the method) are left as they are."""
    n = u.shape[1]
    nu = conserve_idx.shape[0]
    if nu == 0:
        return
    for a in range(nu):
        for j in range(s, k):
            for p in range(n):
                phi[first_row + a, j, p] = 0.0
    for l in range(k):
        grad_invariants(u[l], params, inv_grads)
        for a in range(nu):
            row = conserve_idx[a]
            for j in range(s, k):
                weight = projection[j, l]
                for p in range(n):
                    phi[first_row + a, j, p] += weight * inv_grads[row, p]


@njit(cache=True, inline="always", error_model="numpy")
def elim_map(grad_H, grad_invariants, params, y, h, coef, alpha, plain_sweep, stable_rhs, tables,
             conserve_idx, work):
    """G(coef) of ELIM(r,k,s), docs/methods.md#elim (HBVM when nu = 0, docs/methods.md#hbvm), into work.new_coef.

        u_l     = y + h sum_j Is[l,j] coef_j,     gamma_j = sum_l b_l P_j(c_l) J grad H(u_l)
        phi_j   = sum_i bhat_i P_j(chat_i) grad L(uhat_i)          (nu imposed invariants)
        Gamma alpha = bvec,  Gamma[:, c] = w_c phi_{s-nu+c}^T gamma_{s-nu+c},  w_c = h^(2(nu-1-c))
        G_j     = eta_j gamma_j,   eta_j = 1 - w_{j-s+nu} alpha_{j-s+nu} for the last nu j
    bvec is the stable tail -sum_{j=s}^{k-1} phi_j^T gamma_j, phi_j (j >= s) taken at the k nodes
    (docs/methods.md#stable-right-hand-side, elim_rhs_terms) when stable_rhs and r <= k, the paper's
    sum_{j<s} phi_j^T gamma_j otherwise. plain_sweep: alpha = 0 (the first sweeps
    of a cold start, when Gamma is singular or noise: docs/methods.md#practical-points).

    Shapes: y (n,), coef (s, n), alpha (nu,) in/out, conserve_idx (nu,); work.h_powers holds
    w_c for this h. Leaves Gamma unfactored in work.small_copy and factored in
    work.small_matrix/small_pivots (the solver's rounding estimate and checks use them).
    Returns 0, or 1 when Gamma is singular (alpha then keeps its previous value): a pivot below
    the floor against Gamma's largest entry and then either against its own column's
    (lu_factor_columns) or with the rows and columns scaled (equilibrated_condition above
    EQUILIBRATED_LIMIT). The second try is for the w_c in the columns, which in absolute time
    differ by 1e-14 where the time scale is 1e-7 (Kepler e = 0.99999 at pericentre).
    """
    # Every array is bound once here: an attribute read inside a loop costs a reference
    # count update per read (Numba does not hoist it out of loops with opaque calls).
    projection, Is, projection_hat, Ihat = tables.projection, tables.Is, tables.projection_hat, tables.Ihat
    u, grads, proj, gamma, uhat = work.u, work.grads, work.proj, work.gamma, work.uhat
    grads_hat, phi, inv_grads, h_powers = work.grads_hat, work.phi, work.inv_grads, work.h_powers
    big_gamma, bvec, small_matrix, small_pivots = work.small_copy, work.small_vector, work.small_matrix, work.small_pivots
    new_coef = work.new_coef
    n = y.shape[0]
    k = Is.shape[0]
    r = Ihat.shape[0]
    s = coef.shape[0]
    nu = conserve_idx.shape[0]
    first_rhs, last_rhs, tail_nodes = elim_rhs_terms(stable_rhs, k, r, s)
    # Legendre coefficients needed: the stable tail runs up to k - 1 (elim_rhs_terms).
    n_gamma = last_rhs if nu > 0 else s
    n_phi = last_rhs if (nu > 0 and tail_nodes != TAIL_K_NODES) else s

    scale_tables(h, tables, work)
    stages(y, work.stage_comp, work.scaled_Is, work.scaled_Is_low, coef, s, u)
    for l in range(k):
        grad_H(u[l], params, grads[l])
    project(projection, grads, n_gamma, proj)
    apply_J(proj, n_gamma, gamma)

    singular = 0
    if nu > 0:
        if r == k:
            stage_hat = u
        else:
            stages(y, work.stage_comp, work.scaled_Ihat, work.scaled_Ihat_low, coef, s, uhat)
            stage_hat = uhat
        for i in range(r):
            grad_invariants(stage_hat[i], params, inv_grads)
            for a in range(nu):
                for p in range(n):
                    grads_hat[a, i, p] = inv_grads[conserve_idx[a], p]
        for a in range(nu):
            project(projection_hat, grads_hat[a], n_phi, phi[a])
        for col in range(nu):
            j = s - nu + col
            for a in range(nu):
                acc = 0.0
                for p in range(n):
                    acc += phi[a, j, p] * gamma[j, p]
                big_gamma[a, col] = h_powers[col] * acc
        if tail_nodes == TAIL_K_NODES:
            # r < k: the tail with grad L taken at the k nodes too.
            tail_phi_at_k_nodes(grad_invariants, params, u, conserve_idx, projection, 0, s, k, inv_grads, phi)
        sign = -1.0 if first_rhs > 0 else 1.0   # the tail, or the paper's sum
        for a in range(nu):
            acc = 0.0
            for j in range(first_rhs, last_rhs):
                for p in range(n):
                    acc += phi[a, j, p] * gamma[j, p]
            bvec[a] = sign * acc
        if plain_sweep:
            for a in range(nu):
                alpha[a] = 0.0
        else:
            _copy_square(big_gamma, small_matrix, nu)
            factored = lu_factor(small_matrix, small_pivots) == 0
            if not factored:
                _copy_square(big_gamma, small_matrix, nu)   # the first LU overwrote it
                factored = (lu_factor_columns(small_matrix, small_pivots) == 0
                            and not (equilibrated_condition(work, nu) > EQUILIBRATED_LIMIT))
            if factored:
                lu_solve_factored(small_matrix, small_pivots, bvec)
                for a in range(nu):
                    alpha[a] = bvec[a]
            else:
                singular = 1

    for j in range(s):
        eta = 1.0
        if j >= s - nu:
            eta = 1.0 - h_powers[j - (s - nu)] * alpha[j - (s - nu)]
        for p in range(n):
            new_coef[j, p] = eta * gamma[j, p]
    return singular


# Bits of settings.stable_rhs (the kernels' int for the solver's rhs and, for LIM, its metric).
RHS_STABLE = 1
LIM_SCALED_METRIC = 2
# The scaled metric's floor, relative to its largest entry: a component that is zero over the
# whole step (a planar problem's z) keeps a positive weight, so that the Gram matrix of an
# invariant living there (linear_momentum_z) stays positive definite.
METRIC_FLOOR = 1e-30


@njit(cache=True, inline="always")
def lim_rhs_terms(stable_rhs, k, r, s):
    """The Legendre indices j in [first, last) whose phi_j^T gamma_j make up LIM's right-hand side,
    and where the tail's phi_j come from (TAIL_*): sum_{j<s} (the spec's, literal), or the stable
    tail -sum_{j=s}^{k-1} at the k nodes (elim_rhs_terms), docs/methods.md#stable-right-hand-side
    carried over to LIM: sum_{j<k} phi_j^T gamma_j = sum_l b_l grad Ltilde(u_l)^T J grad H(u_l) = 0
    exactly at the k nodes (H's row too: phi^H_j = J^T gamma_j). r > k: the spec's sum, as for ELIM
    (a user trial's LIM(6,3,2): the tail at the r nodes lost H at 2e-6 and L at 3e-7).
    stable_rhs: the settings' bits (RHS_STABLE, LIM_SCALED_METRIC)."""
    return elim_rhs_terms((stable_rhs & RHS_STABLE) != 0, k, r, s)


@njit(cache=True, inline="always", error_model="numpy")
def lim_map(grad_H, grad_invariants, params, y, h, coef, lam, tables, conserve_idx, work, stable_rhs):
    """G(coef) of LIM(r,k,s), docs/methods.md#lim, into work.new_coef.

    Ltilde = (H, L_conserve...) has nu + 1 components:
        gamma_j = sum_l b_l Ps[l,j] J grad H(u_l)                 (k nodes)
        phi_j   = sum_i bhat_i P_j(chat_i) grad Ltilde(uhat_i)    (r nodes)
        (phi_0^T W phi_0) lambda = sum_{j<s} phi_j^T gamma_j      (SPD solve)
        G_0 = gamma_0 - W phi_0 lambda,  G_j = gamma_j
    W = I (the spec's) unless stable_rhs has LIM_SCALED_METRIC: then W = diag(w),
    w_p = sum_l b_l u_{l,p}^2 (the mean square of component p over the step), which makes the
    correction invariant under a rescaling of the components (the solar system's momenta are
    1e-11..1e-5 of its positions). Every invariant stays kept (L(y1) - L(y0) = h (sum_j phi_j^T
    gamma_j - phi_0^T W phi_0 lambda) = 0 for any W) and lambda = O(h^(2s)). With RHS_STABLE the
    right-hand side is the tail of lim_rhs_terms.
    lam (nu+1,) in/out. Leaves the Gram matrix in work.small_copy and its Cholesky factor
    in work.small_matrix, W in work.metric. Returns 0, or 1 when the Gram matrix is not positive definite.
    """
    projection, Is, projection_hat, Ihat = tables.projection, tables.Is, tables.projection_hat, tables.Ihat
    u, grads, proj, gamma, uhat = work.u, work.grads, work.proj, work.gamma, work.uhat
    grads_hat, phi, gram, rhs = work.grads_hat, work.phi, work.small_copy, work.small_vector
    inv_grads, factor, new_coef, metric = work.inv_grads, work.small_matrix, work.new_coef, work.metric
    n = y.shape[0]
    k = Is.shape[0]
    r = Ihat.shape[0]
    s = coef.shape[0]
    n_tilde = conserve_idx.shape[0] + 1
    first_rhs, last_rhs, tail_nodes = lim_rhs_terms(stable_rhs, k, r, s)
    n_gamma = last_rhs
    n_phi = last_rhs if tail_nodes != TAIL_K_NODES else s

    scale_tables(h, tables, work)
    stages(y, work.stage_comp, work.scaled_Is, work.scaled_Is_low, coef, s, u)
    for l in range(k):
        grad_H(u[l], params, grads[l])
    project(projection, grads, n_gamma, proj)
    apply_J(proj, n_gamma, gamma)

    if r == k:
        stage_hat = u
        for i in range(r):
            for p in range(n):
                grads_hat[0, i, p] = grads[i, p]
    else:
        stages(y, work.stage_comp, work.scaled_Ihat, work.scaled_Ihat_low, coef, s, uhat)
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
        project(projection_hat, grads_hat[a], n_phi, phi[a])
    if tail_nodes == TAIL_K_NODES:
        # grad Ltilde at the k nodes: H's row is the projection of grad H there (proj, rows < k).
        for j in range(s, k):
            for p in range(n):
                phi[0, j, p] = proj[j, p]
        tail_phi_at_k_nodes(grad_invariants, params, u, conserve_idx, projection, 1, s, k, inv_grads, phi)
    if (stable_rhs & LIM_SCALED_METRIC) != 0:
        largest = 0.0
        for p in range(n):
            acc = 0.0
            for l in range(k):
                acc += projection[0, l] * u[l, p] * u[l, p]     # projection[0, l] = b_l P_0 = b_l
            metric[p] = acc
            largest = max(largest, acc)
        floor = METRIC_FLOOR * largest if largest > 0.0 else 1.0
        for p in range(n):
            metric[p] = max(metric[p], floor)
    sign = -1.0 if first_rhs > 0 else 1.0   # the tail, or the spec's sum
    for a in range(n_tilde):
        for c in range(n_tilde):
            acc = 0.0
            for p in range(n):
                acc += phi[a, 0, p] * metric[p] * phi[c, 0, p]
            gram[a, c] = acc
            factor[a, c] = acc
        acc = 0.0
        for j in range(first_rhs, last_rhs):
            for p in range(n):
                acc += phi[a, j, p] * gamma[j, p]
        rhs[a] = sign * acc
    if cholesky_factor(factor) != 0:
        return 1
    cholesky_solve_factored(factor, rhs)
    for a in range(n_tilde):
        lam[a] = rhs[a]

    for j in range(s):
        for p in range(n):
            new_coef[j, p] = gamma[j, p]
    for a in range(n_tilde):
        for p in range(n):
            new_coef[0, p] -= lam[a] * metric[p] * phi[a, 0, p]
    return 0


@njit(cache=True, inline="always", error_model="numpy")
def gradient_sizes(work, n_rows, n_nodes):
    """Component-wise sizes for the rounding estimate of docs/solver.md, into work.sizes:
    row 0: F_p = max_l |f_{l,p}| over the k nodes (f = J grad H: |f_p| is |grad H| at p's
    partner), rows 1 + a: A_{a,p} = max_i |grad L_a(uhat_i)_p| at the r nodes."""
    grads, grads_hat, sizes = work.grads, work.grads_hat, work.sizes
    n = grads.shape[1]
    m = n // 2
    for p in range(n):
        partner = p + m if p < m else p - m
        F = 0.0
        for l in range(grads.shape[0]):
            F = max(F, abs(grads[l, partner]))
        sizes[0, p] = F
    for a in range(n_rows):
        for p in range(n):
            A = 0.0
            for i in range(n_nodes):
                A = max(A, abs(grads_hat[a, i, p]))
            sizes[1 + a, p] = A


@njit(cache=True, inline="always", error_model="numpy")
def _dot_rounding(S, phi_a, gamma, j, sizes, a):
    """Rounding of phi_j^a . gamma_j (docs/solver.md's db term, taken component by component):
    eps sum_p [S_j (A_{a,p} |gamma_{j,p}| + F_p |phi^a_{j,p}|) + |phi^a_{j,p}| |gamma_{j,p}|].
    docs/solver.md's form uses max_p A_{a,p} and max_p F_p; summing per component is a tighter
    bound of the same rounding, and it matters where components differ in size by orders
    (the solar system's momenta are 1e-11 to 1e-5 of its positions)."""
    acc = 0.0
    for p in range(gamma.shape[1]):
        acc += (S[j] * (sizes[1 + a, p] * abs(gamma[j, p]) + sizes[0, p] * abs(phi_a[j, p]))
                + abs(phi_a[j, p]) * abs(gamma[j, p]))
    return EPS * acc


@njit(cache=True, inline="always", error_model="numpy")
def condition_number(work, n_t, symmetric_positive):
    """work.small_inverse = the inverse of the small matrix from its factors; returns
    ||M||_inf ||M^-1||_inf, the condition number in the infinity norm."""
    unit, factor, pivots, matrix, inverse = (work.small_vector, work.small_matrix, work.small_pivots,
                                             work.small_copy, work.small_inverse)
    norm = 0.0
    inverse_norm = 0.0
    for c in range(n_t):
        for a in range(n_t):
            unit[a] = 1.0 if a == c else 0.0
        if symmetric_positive:
            cholesky_solve_factored(factor, unit)
        else:
            lu_solve_factored(factor, pivots, unit)
        for a in range(n_t):
            inverse[a, c] = unit[a]
    for a in range(n_t):
        row = 0.0
        inverse_row = 0.0
        for c in range(n_t):
            row += abs(matrix[a, c])
            inverse_row += abs(inverse[a, c])
        norm = max(norm, row)
        inverse_norm = max(inverse_norm, inverse_row)
    return norm * inverse_norm


# Gamma whose pivots fall below the floor only against the matrix's largest entry (lu_factor) is
# solved if, with its rows and columns scaled to unit size, its condition number is at most this.
# Measured: Kepler imposing L and A_y, 10-19 at every step of one orbit of e = 0.9 to 0.999999 (steps
# of rtol 1e-12, and a 16th of each); the solar system's three angular momenta at h = 50, whose rows
# are nearly proportional (Assumption 1 all but failing for a nearly planar system), 2.6e3-2.9e7 at
# 21 states over 2e5 days: they stay singular, as before (taken unimposed, where imposing them would
# split most steps).
EQUILIBRATED_LIMIT = 1e3


@njit(cache=True, inline="always", error_model="numpy")
def equilibrated_condition(work, n_t):
    """cond_inf(R Gamma C) for Gamma in work.small_copy, factored in work.small_matrix and
    work.small_pivots: C = diag(1 / size_c), size_c = max_a |Gamma[a, c]|, gives every column unit
    size, then R = diag(1 / row_a), row_a = max_c |Gamma[a, c]| / size_c, every row; inf for a zero
    row or column. Unlike cond(Gamma), all but blind to the units of the invariants (rows)
    and to the powers of h in the columns (w_c): within a factor nu^2 of the same whatever they are,
    so large only where the rows are nearly dependent, Assumption 1 failing. Uses
    work.small_inverse as scratch (its row a: row_a Gamma^-1 e_a), and _column_sizes' scratch."""
    matrix, inverse, factor, pivots = work.small_copy, work.small_inverse, work.small_matrix, work.small_pivots
    sizes = work.small_rounding[0]
    if not _column_sizes(matrix, n_t, sizes):
        return np.inf
    norm = 0.0
    for a in range(n_t):
        row = 0.0
        total = 0.0
        for c in range(n_t):
            entry = abs(matrix[a, c]) / sizes[c]
            row = max(row, entry)
            total += entry
        if not (row > 0.0):
            return np.inf
        norm = max(norm, total / row)
        for c in range(n_t):
            inverse[a, c] = 1.0 if a == c else 0.0
        lu_solve_factored(factor, pivots, inverse[a])
        for c in range(n_t):   # (R Gamma C)^-1 = C^-1 Gamma^-1 R^-1: entry (c, a) = size_c Gamma^-1[c, a] row_a
            inverse[a, c] *= row
    inverse_norm = 0.0
    for c in range(n_t):
        total = 0.0
        for a in range(n_t):
            total += abs(inverse[a, c])
        inverse_norm = max(inverse_norm, sizes[c] * total)
    return norm * inverse_norm


@njit(cache=True, inline="always")
def _copy_square(source, target, n):
    """target[:n, :n] = source[:n, :n]"""
    for a in range(n):
        for c in range(n):
            target[a, c] = source[a, c]


@njit(cache=True, inline="always")
def _column_sizes(matrix, n_t, sizes):
    """sizes[c] = max_a |matrix[a, c]| (the scaling of equilibrated_condition and
    column_scaled_condition, into the scratch work.small_rounding[0]: elim_rounding writes it afresh
    before anything reads it); False for a zero (or NaN) column."""
    for c in range(n_t):
        size = 0.0
        for a in range(n_t):
            size = max(size, abs(matrix[a, c]))
        sizes[c] = size
        if not (size > 0.0):
            return False
    return True


@njit(cache=True, inline="always", error_model="numpy")
def column_scaled_condition(work, n_t):
    """cond_inf(Gamma D), D = diag(1 / max_a |Gamma[a, c]|): the condition number of the small
    matrix work.small_copy with its columns scaled to unit size, from the inverse that
    condition_number leaves in work.small_inverse (call it first); inf for a zero column.

    LU with partial pivoting is blind to the scaling of columns, and this number, not
    cond(Gamma), bounds the relative error of each alpha_c. Gamma's columns carry w_c =
    h^(2(nu-1-c)) (docs/methods.md#elim), an absolute h: at a pericentre of e = 0.9999 (steps
    of 1e-7, a tenth of the time scale there) they differ by 1e-14 and cond(Gamma) reached 7e14
    where the scaled matrix is well conditioned."""
    matrix, inverse = work.small_copy, work.small_inverse
    sizes = work.small_rounding[0]
    if not _column_sizes(matrix, n_t, sizes):
        return np.inf
    norm = 0.0
    inverse_norm = 0.0
    for c in range(n_t):
        inverse_row = 0.0
        for a in range(n_t):
            inverse_row += abs(inverse[c, a])
        inverse_norm = max(inverse_norm, sizes[c] * inverse_row)
    for a in range(n_t):
        row = 0.0
        for c in range(n_t):
            row += abs(matrix[a, c]) / sizes[c]
        norm = max(norm, row)
    return norm * inverse_norm


@njit(cache=True, inline="always", error_model="numpy")
def elim_rounding(h, alpha, stable_rhs, tables, nu, s, work):
    """Spec 8, the rounding of alpha, for ELIM with nu >= 1:
    dalpha = |Gamma^-1| (db + dGamma |alpha|), db_a the rounding of bvec_a and dGamma_ac =
    w_c (the rounding of phi_{j_c}^a . gamma_{j_c}), j_c = s - nu + c (see _dot_rounding).
    Writes dalpha into work.small_rounding[0] and returns cond(Gamma) (infinity norm).
    Needs work.sizes (gradient_sizes), Gamma factored (the last map solved it) and
    work.small_copy unfactored.
    """
    gamma, phi, h_powers, rounding, inverse, sizes = (work.gamma, work.phi, work.h_powers, work.small_rounding,
                                                      work.small_inverse, work.sizes)
    k = tables.Is.shape[0]
    r = tables.Ihat.shape[0]
    first_rhs, last_rhs, _ = elim_rhs_terms(stable_rhs, k, r, s)
    S = tables.abs_projection_hat
    cond = condition_number(work, nu, False)
    d_rhs = work.small_vector
    for a in range(nu):
        acc = 0.0
        for j in range(first_rhs, last_rhs):
            acc += _dot_rounding(S, phi[a], gamma, j, sizes, a)
        for c in range(nu):
            acc += h_powers[c] * _dot_rounding(S, phi[a], gamma, s - nu + c, sizes, a) * abs(alpha[c])
        d_rhs[a] = acc
    _abs_times(inverse, d_rhs, nu, rounding[0])
    return cond


@njit(cache=True, inline="always", error_model="numpy")
def _abs_times(matrix, vector, n, out):
    """out = |matrix| vector over the leading n x n block: how the rounding of a small
    system's right-hand side reaches its solution (spec 8's |Gamma^-1| db)."""
    for a in range(n):
        acc = 0.0
        for b in range(n):
            acc += abs(matrix[a, b]) * vector[b]
        out[a] = acc


@njit(cache=True, inline="always", error_model="numpy")
def lim_rounding(tables, n_tilde, s, stable_rhs, work):
    """Spec 8's rounding of the multipliers carried over to LIM: dlambda = |Gram^-1| db,
    db_a the rounding of LIM's right-hand side (the terms of lim_rhs_terms; a = 0 is H; see _dot_rounding).
    Writes dlambda into work.small_rounding[0]; returns cond(Gram). Needs work.sizes."""
    gamma, phi, rounding, inverse, sizes = work.gamma, work.phi, work.small_rounding, work.small_inverse, work.sizes
    S = tables.abs_projection_hat
    first_rhs, last_rhs, _ = lim_rhs_terms(stable_rhs, tables.Is.shape[0], tables.Ihat.shape[0], s)
    cond = condition_number(work, n_tilde, True)
    d_rhs = work.small_vector
    for a in range(n_tilde):
        acc = 0.0
        for j in range(first_rhs, last_rhs):
            acc += _dot_rounding(S, phi[a], gamma, j, sizes, a)
        d_rhs[a] = acc
    _abs_times(inverse, d_rhs, n_tilde, rounding[0])
    return cond
