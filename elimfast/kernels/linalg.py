"""Dense solves of the kernels: the nu x nu systems of docs/methods.md#elim and #lim, and the
simplified-Newton matrix of docs/solver.md.

nu is 1 to a few and the Newton matrix is (s 2m) x (s 2m), or about s/2 blocks of 2m x 2m,
so plain loops beat any BLAS call. Every function works in place and returns a status (0
ok, 1 singular or badly conditioned) instead of raising.
"""
import math

import numpy as np
from numba import njit

# A pivot smaller than this times the largest entry of the matrix is treated as zero:
# the solution would carry no correct digit. Relative, because Gamma is O(h^(2s-2)).
RELATIVE_PIVOT_FLOOR = 1e-13


@njit(cache=True, inline="always")
def lu_factor(a, pivots):
    """LU factorisation with partial pivoting, in place: P a = L U.

    a: (n, n), overwritten by L (unit lower, below the diagonal) and U; pivots: (n,)
    int64, the row swapped with row i at step i. Returns 0, or 1 if a pivot falls below
    RELATIVE_PIVOT_FLOOR * max|a| (singular or badly conditioned) or a is not finite.
    """
    n = a.shape[0]
    scale = 0.0
    for i in range(n):
        for j in range(n):
            v = abs(a[i, j])
            if not (v <= 1e308):
                return 1
            if v > scale:
                scale = v
    if scale == 0.0:
        return 1
    for col in range(n):
        pivot_row = col
        pivot_abs = abs(a[col, col])
        for i in range(col + 1, n):
            if abs(a[i, col]) > pivot_abs:
                pivot_abs = abs(a[i, col])
                pivot_row = i
        pivots[col] = pivot_row
        if pivot_abs <= RELATIVE_PIVOT_FLOOR * scale:
            return 1
        if pivot_row != col:
            for j in range(n):
                tmp = a[col, j]
                a[col, j] = a[pivot_row, j]
                a[pivot_row, j] = tmp
        inverse_pivot = 1.0 / a[col, col]
        for i in range(col + 1, n):
            factor = a[i, col] * inverse_pivot
            a[i, col] = factor
            if factor != 0.0:
                for j in range(col + 1, n):
                    a[i, j] -= factor * a[col, j]
    return 0


@njit(cache=True, inline="always")
def lu_solve_factored(lu, pivots, x):
    """Solve a z = x with the factors of lu_factor; z overwrites x (n,)."""
    n = x.shape[0]
    for col in range(n):
        p = pivots[col]
        if p != col:
            tmp = x[col]
            x[col] = x[p]
            x[p] = tmp
    for i in range(n):
        acc = x[i]
        for j in range(i):
            acc -= lu[i, j] * x[j]
        x[i] = acc
    for i in range(n - 1, -1, -1):
        acc = x[i]
        for j in range(i + 1, n):
            acc -= lu[i, j] * x[j]
        x[i] = acc / lu[i, i]


@njit(cache=True, inline="always")
def invert(a, inverse):
    """inverse <- a^-1 by Gauss-Jordan elimination with partial pivoting; a (n, n), real or
    complex, is destroyed.

    For the small blocks I - h lambda J0 of the simplified Newton matrix (docs/solver.md,
    "Block form"): applied by a matrix-vector product, the inverse costs one n^2 pass per
    iteration whose rows are independent, where an LU solve is two chains of dependent
    substitutions and, for complex blocks, n complex divisions. Measured on Kepler (n = 4),
    one factorisation and 5 solves of GHBVM/EHBVM(12,3)'s blocks: 0.76 us against 1.26 us
    (LU blocks) and 1.62 us (the real 12 x 12 LU). For n >= 12 the LU's n^3/3 beats the
    inverse's n^3 (stepper keeps the LU there). Pivots are compared by |Re| + |Im| (no
    square root). Returns 0, or 1 as lu_factor: a pivot below RELATIVE_PIVOT_FLOOR times
    the largest entry, or an entry that is not finite.
    """
    n = a.shape[0]
    scale = 0.0
    for i in range(n):
        for j in range(n):
            v = abs(a[i, j].real) + abs(a[i, j].imag)
            if not (v <= 1e308):
                return 1
            if v > scale:
                scale = v
            inverse[i, j] = 0.0
        inverse[i, i] = 1.0
    if scale == 0.0:
        return 1
    for col in range(n):
        pivot_row = col
        pivot_abs = abs(a[col, col].real) + abs(a[col, col].imag)
        for i in range(col + 1, n):
            v = abs(a[i, col].real) + abs(a[i, col].imag)
            if v > pivot_abs:
                pivot_abs = v
                pivot_row = i
        if pivot_abs <= RELATIVE_PIVOT_FLOOR * scale:
            return 1
        if pivot_row != col:
            for j in range(n):
                tmp = a[col, j]
                a[col, j] = a[pivot_row, j]
                a[pivot_row, j] = tmp
                tmp = inverse[col, j]
                inverse[col, j] = inverse[pivot_row, j]
                inverse[pivot_row, j] = tmp
        inverse_pivot = 1.0 / a[col, col]
        for j in range(col + 1, n):
            a[col, j] *= inverse_pivot
        for j in range(n):
            inverse[col, j] *= inverse_pivot
        for i in range(n):
            if i != col:
                factor = a[i, col]
                if factor != 0.0:
                    for j in range(col + 1, n):
                        a[i, j] -= factor * a[col, j]
                    for j in range(n):
                        inverse[i, j] -= factor * inverse[col, j]
    return 0


@njit(cache=True)
def lu_solve(a, x):
    """Solve a z = x by Gaussian elimination with partial pivoting; z overwrites x.

    Spec section 3, "Gamma alpha = bvec" (Assumption 1 of the paper: Gamma nonsingular).
    a: (n, n), destroyed; x: (n,). Returns 0, or 1 if a pivot falls below
    RELATIVE_PIVOT_FLOOR * max|a| (singular or badly conditioned), or if a is not finite.
    """
    pivots = np.empty(x.shape[0], dtype=np.int64)
    if lu_factor(a, pivots) != 0:
        return 1
    lu_solve_factored(a, pivots, x)
    return 0


@njit(cache=True, inline="always")
def cholesky_factor(a):
    """Cholesky factorisation a = L L^T in place (L in the lower triangle).

    Spec section 4, "(phi_0^T phi_0) lambda = ..." (the LIM Gram matrix). a: (n, n).
    Returns 0, or 1 if a is not (numerically) positive definite: a pivot below
    RELATIVE_PIVOT_FLOOR times its own diagonal entry (for a Gram matrix, the squared sine of
    the angle between a gradient and the span of the earlier ones). Relative to its own
    diagonal, not the largest one: Cholesky's rounding does not depend on the scaling of the
    rows and columns (van der Sluis), so neither may the test. Kepler e = 0.999 at
    pericentre, LIM imposing L and A_y: |grad H|^2 ~ 1e12, |grad L|^2 ~ 2e3, and L's pivot,
    8e-7 (sin^2 = 4e-10), fell below 1e-13 * 1e12 at every step size.
    """
    n = a.shape[0]
    for i in range(n):
        if not (a[i, i] > 0.0 and a[i, i] <= 1e308):
            return 1
    for j in range(n):
        diagonal = a[j, j]
        d = diagonal
        for p in range(j):
            d -= a[j, p] * a[j, p]
        if not (d > RELATIVE_PIVOT_FLOOR * diagonal):
            return 1
        d = math.sqrt(d)
        a[j, j] = d
        for i in range(j + 1, n):
            v = a[i, j]
            for p in range(j):
                v -= a[i, p] * a[j, p]
            a[i, j] = v / d
    return 0


@njit(cache=True, inline="always")
def cholesky_solve_factored(factor, x):
    """Solve (L L^T) z = x with the factor of cholesky_factor; z overwrites x."""
    n = x.shape[0]
    for i in range(n):
        acc = x[i]
        for p in range(i):
            acc -= factor[i, p] * x[p]
        x[i] = acc / factor[i, i]
    for i in range(n - 1, -1, -1):
        acc = x[i]
        for p in range(i + 1, n):
            acc -= factor[p, i] * x[p]
        x[i] = acc / factor[i, i]


@njit(cache=True)
def cholesky_solve(a, x):
    """Solve a z = x for symmetric positive definite a by Cholesky; z overwrites x.

    a: (n, n), overwritten by its Cholesky factor; x: (n,). Returns 0, or 1 if a is not
    (numerically) positive definite.
    """
    if cholesky_factor(a) != 0:
        return 1
    cholesky_solve_factored(a, x)
    return 0
