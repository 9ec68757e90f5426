"""Slow, plain NumPy reference implementation of HBVM, ELIM and LIM (test oracle).

Written from the numerical specification (docs/methods.md) only,
independently of the fast implementation.  Clarity over speed: loops are fine.

Conventions: y = (q, p) is a 1-D array of length 2m; grad_H(y) returns a 1-D
array of length 2m; grad_L(y) returns a 2m x nu matrix (columns = gradients).
"""
import math

import numpy as np
from numpy.polynomial.legendre import Legendre, leggauss


# ---------------------------------------------------------------------------
# Basis, quadrature, tables
# ---------------------------------------------------------------------------

def gauss_legendre(n):
    """n-point Gauss-Legendre nodes (increasing) and weights on [0, 1]."""
    x, w = leggauss(n)              # on [-1, 1], increasing
    c = (x + 1.0) / 2.0
    b = w / 2.0
    return c, b


def legendre_P(j, x):
    """P_j(x) = sqrt(2j+1) * Legendre_j(2x - 1): orthonormal on [0, 1]."""
    x = np.asarray(x, dtype=float)
    return math.sqrt(2 * j + 1) * Legendre.basis(j)(2.0 * x - 1.0)


def legendre_P_integral(j, x):
    """int_0^x P_j(t) dt, by integrating the numpy Legendre polynomial.

    With z = 2t - 1:  int_0^x P_j(t) dt = sqrt(2j+1)/2 * int_{-1}^{2x-1} Legendre_j(z) dz.
    """
    x = np.asarray(x, dtype=float)
    antiderivative = Legendre.basis(j).integ(lbnd=-1)   # vanishes at z = -1
    return math.sqrt(2 * j + 1) * 0.5 * antiderivative(2.0 * x - 1.0)


def J_times(g):
    """J @ g with J = [[0, I], [-I, 0]]: returns (g_p, -g_q)."""
    g = np.asarray(g, dtype=float)
    m = g.shape[0] // 2
    return np.concatenate([g[m:], -g[:m]])


def _tables(n_nodes, n_funcs):
    """Nodes c, weights b, P[i, j] = P_j(c_i), I[i, j] = int_0^{c_i} P_j (n_nodes x n_funcs)."""
    c, b = gauss_legendre(n_nodes)
    P = np.zeros((n_nodes, n_funcs))
    I = np.zeros((n_nodes, n_funcs))
    for j in range(n_funcs):
        P[:, j] = legendre_P(j, c)
        I[:, j] = legendre_P_integral(j, c)
    return c, b, P, I


def butcher_hbvm(k, s, eta=None):
    """(A, b, c) with A = Is diag(eta) Ps^T Omega (eta defaults to ones; eta[0] must be 1)."""
    if eta is None:
        eta = np.ones(s)
    eta = np.asarray(eta, dtype=float)
    if eta.shape != (s,):
        raise ValueError("eta must have length s")
    if eta[0] != 1.0:
        raise ValueError("eta[0] must be 1")
    c, b, Ps, Is = _tables(k, s)
    A = Is @ np.diag(eta) @ Ps.T @ np.diag(b)
    return A, b, c


# ---------------------------------------------------------------------------
# Stopping rule shared by all methods
# ---------------------------------------------------------------------------

_STAGNATION = 1e-12


class _Stopper:
    """Stop when the stage change is <= tol*scale, or when it failed three times in a
    row to improve on the best change so far, that being below STAGNATION*scale.  Raise after max_iter iterations.

    Stricter than the kernel's rule on purpose: the oracle must sit at the fixed point
    (the convergence is often a staircase of nearly equal pairs of increments)."""

    def __init__(self, y0, tol, max_iter):
        self.scale = max(1.0, float(np.max(np.abs(y0))))
        self.tol = tol
        self.max_iter = max_iter
        self.best = math.inf
        self.stalls = 0

    def done(self, change, n_iter):
        if change <= self.tol * self.scale:
            return True
        if change < self.best:
            self.best, self.stalls = change, 0
        elif self.best < _STAGNATION * self.scale:
            self.stalls += 1
            if self.stalls >= 3:   # three non-improving iterations in a row: noise floor
                return True
        if n_iter >= self.max_iter:
            raise RuntimeError("fixed-point iteration did not converge in %d iterations "
                               "(last change %.3e)" % (self.max_iter, change))
        return False


# ---------------------------------------------------------------------------
# HBVM(k, s)
# ---------------------------------------------------------------------------

def hbvm_step(grad_H, y0, h, k, s, tol=1e-16, max_iter=500):
    """One step of HBVM(k, s) by fixed-point iteration on gamma_0..gamma_{s-1}.

    Returns (y1, n_iter)."""
    y0 = np.asarray(y0, dtype=float)
    if k < s:
        raise ValueError("HBVM(k,s) needs k >= s")
    c, b, Ps, Is = _tables(k, s)
    dim = y0.shape[0]
    gamma = np.zeros((s, dim))               # gamma[j] = gamma_j
    stages = np.array([y0.copy() for _ in range(k)])
    stop = _Stopper(y0, tol, max_iter)
    n_iter = 0
    while True:
        n_iter += 1
        # new coefficients from the current stages
        f = np.array([J_times(grad_H(stages[l])) for l in range(k)])
        new_gamma = np.zeros((s, dim))
        for j in range(s):
            for l in range(k):
                new_gamma[j] += b[l] * Ps[l, j] * f[l]
        gamma = new_gamma
        # new stages from the new coefficients
        new_stages = np.zeros((k, dim))
        for l in range(k):
            new_stages[l] = y0.copy()
            for j in range(s):
                new_stages[l] += h * Is[l, j] * gamma[j]
        change = float(np.max(np.abs(new_stages - stages)))
        stages = new_stages
        if stop.done(change, n_iter):
            break
    y1 = y0 + h * gamma[0]
    return y1, n_iter


# ---------------------------------------------------------------------------
# ELIM(r, k, s)  (EHBVM(k, s) = ELIM(k, k, s))
# ---------------------------------------------------------------------------

# Number of initial plain HBVM sweeps (alpha = 0) in ELIM.  Iteration 1: all stages
# equal y0, so gamma_j = 0 for j >= 1 and Gamma = 0 (docs/methods.md#elim).  Iteration 2:
# the stages are still linear in c (u(ch) = y0 + c h J grad H(y0)); for a quadratic
# invariant (e.g. Kepler angular momentum) grad L is then linear in c, so phi_j = 0
# for j >= 2 and both Gamma's row and bvec vanish up to round-off whenever
# s - nu >= 2: alpha would be 0/0 noise (or Gamma exactly singular, e.g. s=4, nu=1).
# Iteration 3 gives usable (O(true alpha)) values; measured on Kepler e=0.6, s=3..5,
# first-solve |alpha| after 2 sweeps reached 1e4 for EHBVM(12,4) imposing L1.
# The converged fixed point does not depend on this choice.
_ELIM_PLAIN_SWEEPS = 3


def _elim_eta(h, s, nu, alpha):
    """eta_j = 1 for j < s-nu, eta_j = 1 - h^{2(s-1-j)} alpha_j for j = s-nu..s-1."""
    eta = np.ones(s)
    for i in range(nu):
        j = s - nu + i
        eta[j] = 1.0 - h ** (2 * (s - 1 - j)) * alpha[i]
    return eta


def elim_step(grad_H, grad_L, y0, h, r, k, s, rhs="stable", tol=1e-16, max_iter=500):
    """One step of ELIM(r, k, s).  Returns (y1, alpha (nu,), n_iter)."""
    y0 = np.asarray(y0, dtype=float)
    if rhs not in ("stable", "literal"):
        raise ValueError("rhs must be 'stable' or 'literal'")
    if k < s or r < s:
        raise ValueError("ELIM(r,k,s) needs r, k >= s")
    nu = np.asarray(grad_L(y0), dtype=float).reshape(y0.shape[0], -1).shape[1]
    if s <= nu:
        raise ValueError("ELIM needs s > nu (s=%d, nu=%d)" % (s, nu))
    dim = y0.shape[0]

    # tables: k nodes with up to k functions, r nodes with up to r functions
    c, b, Pk, Ik = _tables(k, k)
    chat, bhat, Pr, Ir = _tables(r, r)

    def u_at(Itab, n_nodes, gamma, eta):
        # u(c h) = y0 + h sum_{j<s} (int_0^c P_j) eta_j gamma_j
        U = np.zeros((n_nodes, dim))
        for l in range(n_nodes):
            U[l] = y0.copy()
            for j in range(s):
                U[l] += h * Itab[l, j] * eta[j] * gamma[j]
        return U

    gamma = np.zeros((s, dim))
    alpha = np.zeros(nu)
    eta = np.ones(s)
    stages = u_at(Ik, k, gamma, eta)          # all equal y0
    stop = _Stopper(y0, tol, max_iter)
    n_iter = 0
    while True:
        n_iter += 1
        uhat = u_at(Ir, r, gamma, eta)        # current stages at the r nodes
        # gamma_j from J grad H at the k nodes (j = 0..k-1; only j<s enter u)
        f = np.array([J_times(grad_H(stages[l])) for l in range(k)])
        gam_all = np.zeros((k, dim))
        for j in range(k):
            for l in range(k):
                gam_all[j] += b[l] * Pk[l, j] * f[l]
        if nu > 0:
            # phi_j from grad L at the r nodes (j = 0..r-1)
            gL = [np.asarray(grad_L(uhat[i]), dtype=float).reshape(dim, nu) for i in range(r)]
            phi = np.zeros((r, dim, nu))
            for j in range(r):
                for i in range(r):
                    phi[j] += bhat[i] * Pr[i, j] * gL[i]
            if n_iter <= _ELIM_PLAIN_SWEEPS:
                new_alpha = np.zeros(nu)      # Gamma singular (or 0/0) on these sweeps
            else:
                Gamma = np.zeros((nu, nu))
                for col in range(nu):
                    j = s - nu + col
                    Gamma[:, col] = h ** (2 * (s - 1 - j)) * (phi[j].T @ gam_all[j])
                bvec = np.zeros(nu)
                if rhs == "literal" or r > k:
                    # r > k: no tail is exact in general (docs/methods.md#stable-right-hand-side)
                    for j in range(s):
                        bvec += phi[j].T @ gam_all[j]
                elif r == k:
                    for j in range(s, k):
                        bvec -= phi[j].T @ gam_all[j]
                elif r < k:
                    # tail with both sums at the k nodes: grad L evaluated at the k stages
                    gLk = [np.asarray(grad_L(stages[l]), dtype=float).reshape(dim, nu) for l in range(k)]
                    for j in range(s, k):
                        phi_k_j = np.zeros((dim, nu))
                        for l in range(k):
                            phi_k_j += b[l] * Pk[l, j] * gLk[l]
                        bvec -= phi_k_j.T @ gam_all[j]
                if not np.all(np.isfinite(Gamma)) or np.linalg.cond(Gamma) > 1e15:
                    raise np.linalg.LinAlgError(
                        "ELIM: Gamma singular or badly conditioned (cond=%.3e)"
                        % np.linalg.cond(Gamma))
                new_alpha = np.linalg.solve(Gamma, bvec)
        else:
            new_alpha = np.zeros(0)
        gamma = gam_all[:s].copy()
        alpha = new_alpha
        eta = _elim_eta(h, s, nu, alpha)
        new_stages = u_at(Ik, k, gamma, eta)
        change = float(np.max(np.abs(new_stages - stages)))
        stages = new_stages
        if stop.done(change, n_iter):
            break
    y1 = y0 + h * gamma[0]                    # eta_0 = 1
    return y1, alpha, n_iter


# ---------------------------------------------------------------------------
# LIM(r, k, s)  (GHBVM(k, s) = LIM(k, k, s))
# ---------------------------------------------------------------------------

def lim_step(grad_H, grad_L, y0, h, r, k, s, tol=1e-16, max_iter=500):
    """One step of LIM(r, k, s) imposing Ltilde = (H, L_1..L_nu).

    Returns (y1, lam (nu+1,), n_iter)."""
    y0 = np.asarray(y0, dtype=float)
    if k < s or r < s:
        raise ValueError("LIM(r,k,s) needs r, k >= s")
    dim = y0.shape[0]

    def grad_Lt(y):
        gh = np.asarray(grad_H(y), dtype=float).reshape(dim, 1)
        gl = np.asarray(grad_L(y), dtype=float).reshape(dim, -1)
        return np.hstack([gh, gl])

    nt = grad_Lt(y0).shape[1]                 # nu + 1
    c, b, Pk, Ik = _tables(k, s)
    chat, bhat, Pr, Ir = _tables(r, s)

    def u_at(cnodes, Itab, n_nodes, gamma, phi0, lam):
        # u(c h) = y0 + h sum_{j<s} (int_0^c P_j) gamma_j - c h phi_0 lambda
        U = np.zeros((n_nodes, dim))
        for l in range(n_nodes):
            U[l] = y0.copy()
            for j in range(s):
                U[l] += h * Itab[l, j] * gamma[j]
            U[l] -= cnodes[l] * h * (phi0 @ lam)
        return U

    gamma = np.zeros((s, dim))
    phi0 = np.zeros((dim, nt))
    lam = np.zeros(nt)
    stages = u_at(c, Ik, k, gamma, phi0, lam)
    stop = _Stopper(y0, tol, max_iter)
    n_iter = 0
    while True:
        n_iter += 1
        uhat = u_at(chat, Ir, r, gamma, phi0, lam)
        f = np.array([J_times(grad_H(stages[l])) for l in range(k)])
        new_gamma = np.zeros((s, dim))
        for j in range(s):
            for l in range(k):
                new_gamma[j] += b[l] * Pk[l, j] * f[l]
        gL = [grad_Lt(uhat[i]) for i in range(r)]
        phi = np.zeros((s, dim, nt))
        for j in range(s):
            for i in range(r):
                phi[j] += bhat[i] * Pr[i, j] * gL[i]
        rhs_vec = np.zeros(nt)
        for j in range(s):
            rhs_vec += phi[j].T @ new_gamma[j]
        gram = phi[0].T @ phi[0]
        new_lam = np.linalg.solve(gram, rhs_vec)
        gamma, phi0, lam = new_gamma, phi[0], new_lam
        new_stages = u_at(c, Ik, k, gamma, phi0, lam)
        change = float(np.max(np.abs(new_stages - stages)))
        stages = new_stages
        if stop.done(change, n_iter):
            break
    y1 = y0 + h * (gamma[0] - phi0 @ lam)
    return y1, lam, n_iter


# ---------------------------------------------------------------------------
# Time loop
# ---------------------------------------------------------------------------

def integrate(step, y0, h, n_steps):
    """y_{n+1} = step(y_n); returns the (n_steps+1, 2m) array of all states.

    `h` is not used here (it is baked into `step`); kept for a uniform interface."""
    y = np.asarray(y0, dtype=float).copy()
    out = np.zeros((n_steps + 1, y.shape[0]))
    out[0] = y
    for n in range(n_steps):
        y = np.asarray(step(y), dtype=float)
        out[n + 1] = y
    return out


# ---------------------------------------------------------------------------
# Test problems
# ---------------------------------------------------------------------------

def kepler_H(y):
    """H = |p|^2/2 - 1/|q|."""
    q1, q2, p1, p2 = y
    return 0.5 * (p1 * p1 + p2 * p2) - 1.0 / math.sqrt(q1 * q1 + q2 * q2)


def kepler_grad_H(y):
    q1, q2, p1, p2 = y
    rr = math.sqrt(q1 * q1 + q2 * q2)
    r3 = rr ** 3
    return np.array([q1 / r3, q2 / r3, p1, p2])


def kepler_L(y):
    """[L1, A_x, A_y]: angular momentum and Laplace-Runge-Lenz vector."""
    q1, q2, p1, p2 = y
    rr = math.sqrt(q1 * q1 + q2 * q2)
    L1 = q1 * p2 - q2 * p1
    Ax = p2 * L1 - q1 / rr
    Ay = -p1 * L1 - q2 / rr
    return np.array([L1, Ax, Ay])


def kepler_grad_L(y):
    """4 x 3 matrix: columns grad L1, grad A_x, grad A_y; rows d/dq1, d/dq2, d/dp1, d/dp2."""
    q1, q2, p1, p2 = y
    rr = math.sqrt(q1 * q1 + q2 * q2)
    r3 = rr ** 3
    L1 = q1 * p2 - q2 * p1
    gL1 = np.array([p2, -p1, -q2, q1])
    # A_x = p2 L1 - q1/|q|
    gAx = np.array([
        p2 * p2 - 1.0 / rr + q1 * q1 / r3,     # d/dq1
        -p2 * p1 + q1 * q2 / r3,               # d/dq2
        -p2 * q2,                              # d/dp1
        L1 + p2 * q1,                          # d/dp2
    ])
    # A_y = -p1 L1 - q2/|q|
    gAy = np.array([
        -p1 * p2 + q1 * q2 / r3,               # d/dq1
        p1 * p1 - 1.0 / rr + q2 * q2 / r3,     # d/dq2
        -L1 + p1 * q2,                         # d/dp1
        -p1 * q1,                              # d/dp2
    ])
    return np.column_stack([gL1, gAx, gAy])


def kepler_y0(e):
    """q0 = (1-e, 0), p0 = (0, sqrt((1+e)/(1-e)))."""
    return np.array([1.0 - e, 0.0, 0.0, math.sqrt((1.0 + e) / (1.0 - e))])


def harmonic_H(y):
    """Harmonic oscillator, 1 degree of freedom: H = (q^2 + p^2)/2."""
    q, p = y
    return 0.5 * (q * q + p * p)


def harmonic_grad_H(y):
    q, p = y
    return np.array([q, p])


def quartic_H(y):
    """Quartic oscillator, 1 degree of freedom: H = p^2/2 + q^4/4."""
    q, p = y
    return 0.5 * p * p + 0.25 * q ** 4


def quartic_grad_H(y):
    q, p = y
    return np.array([q ** 3, p])
