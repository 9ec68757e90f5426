"""Small dense solves for the nu x nu systems of spec sections 3 and 4.

nu is 1 to a few, so plain loops beat any BLAS call. Both solve in place and return a
status (0 ok, 1 singular or badly conditioned) instead of raising.
"""
import math

from numba import njit

# A pivot smaller than this times the largest entry of the matrix is treated as zero:
# the solution would carry no correct digit. Relative, because Gamma is O(h^(2s-2)).
RELATIVE_PIVOT_FLOOR = 1e-13


@njit(cache=True)
def lu_solve(a, x):
    """Solve a z = x by Gaussian elimination with partial pivoting; z overwrites x.

    Spec section 3, "Gamma alpha = bvec" (Assumption 1 of the paper: Gamma nonsingular).
    a: (n, n), destroyed; x: (n,). Returns 0, or 1 if a pivot falls below
    RELATIVE_PIVOT_FLOOR * max|a| (singular or badly conditioned), or if a is not finite.
    """
    n = x.shape[0]
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
        if pivot_abs <= RELATIVE_PIVOT_FLOOR * scale:
            return 1
        if pivot_row != col:
            for j in range(n):
                tmp = a[col, j]
                a[col, j] = a[pivot_row, j]
                a[pivot_row, j] = tmp
            tmp = x[col]
            x[col] = x[pivot_row]
            x[pivot_row] = tmp
        for i in range(col + 1, n):
            factor = a[i, col] / a[col, col]
            for j in range(col + 1, n):
                a[i, j] -= factor * a[col, j]
            x[i] -= factor * x[col]
    for i in range(n - 1, -1, -1):
        acc = x[i]
        for j in range(i + 1, n):
            acc -= a[i, j] * x[j]
        x[i] = acc / a[i, i]
    return 0


@njit(cache=True)
def cholesky_solve(a, x):
    """Solve a z = x for symmetric positive definite a by Cholesky; z overwrites x.

    Spec section 4, "(phi_0^T phi_0) lambda = ..." (the LIM Gram matrix).
    a: (n, n), overwritten by its Cholesky factor; x: (n,). Returns 0, or 1 if a is not
    (numerically) positive definite.
    """
    n = x.shape[0]
    scale = 0.0
    for i in range(n):
        if a[i, i] > scale:
            scale = a[i, i]
    if not (scale > 0.0 and scale <= 1e308):
        return 1
    for j in range(n):
        d = a[j, j]
        for p in range(j):
            d -= a[j, p] * a[j, p]
        if d <= RELATIVE_PIVOT_FLOOR * scale:
            return 1
        d = math.sqrt(d)
        a[j, j] = d
        for i in range(j + 1, n):
            v = a[i, j]
            for p in range(j):
                v -= a[i, p] * a[j, p]
            a[i, j] = v / d
    for i in range(n):
        acc = x[i]
        for p in range(i):
            acc -= a[i, p] * x[p]
        x[i] = acc / a[i, i]
    for i in range(n - 1, -1, -1):
        acc = x[i]
        for p in range(i + 1, n):
            acc -= a[p, i] * x[p]
        x[i] = acc / a[i, i]
    return 0
