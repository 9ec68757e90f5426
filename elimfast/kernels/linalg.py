"""Dense solves of the kernels: the nu x nu systems of docs/methods.md#elim and #lim, and the
simplified-Newton matrix of docs/solver.md.

nu is 1 to a few and the Newton matrix is (s 2m) x (s 2m), or about s/2 blocks of 2m x 2m,
so plain loops beat any BLAS call. Every function works in place and returns a status (0
ok, 1 singular or badly conditioned) instead of raising.
"""
import math

import numpy as np
from numba import njit

from .simd import addsub4, load4_row, load_pair_row, mul4, splat4, store4_row, store_pair_row, sub4, swap_pairs4

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
    return _lu_factor(a, pivots, False)


@njit(cache=True, inline="always")
def lu_factor_columns(a, pivots):
    """lu_factor judging each pivot against its own column's largest entry instead of the
    matrix's: the floor of the LU of a D for a diagonal D > 0 that gives every column the same
    size. Scaling columns changes neither partial pivoting's choice of rows nor the multipliers,
    so where lu_factor succeeds this gives its factors bit for bit; it succeeds also where the
    columns differ in size by more than 1/RELATIVE_PIVOT_FLOOR (ELIM's Gamma, whose columns carry
    w_c = h^(2(nu-1-c)) in absolute time: maps.elim_map). The factors are those of a itself.
    """
    return _lu_factor(a, pivots, True)


@njit(cache=True, inline="always")
def _lu_factor(a, pivots, per_column):
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
        floor = scale
        if per_column:
            # the column as it stands, U's entries above the pivot included: scaling a column
            # scales all of it, so this floor, like the pivot, is blind to that scaling
            floor = 0.0
            for i in range(n):
                floor = max(floor, abs(a[i, col]))
        if pivot_abs <= RELATIVE_PIVOT_FLOOR * floor:
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

    The kernels call its vectorised forms, invert_real, invert_complex and invert_pair (the
    same bits); this scalar elimination is what they are tested against, byte for byte
    (tests/test_newton_vectorised.py). The first pass and the pivoting are theirs too.
    """
    scale = _invert_start(a, inverse)
    if not (scale > 0.0):
        return 1
    n = a.shape[0]
    for col in range(n):
        if not _pivot(a, inverse, col, scale):
            return 1
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


@njit(cache=True, inline="always")
def _invert_start(a, inverse):
    """invert's first pass: the largest |Re| + |Im| of a (-1 when an entry is not finite), and
    inverse <- I."""
    n = a.shape[0]
    scale = 0.0
    for i in range(n):
        for j in range(n):
            v = abs(a[i, j].real) + abs(a[i, j].imag)
            if not (v <= 1e308):
                return -1.0
            if v > scale:
                scale = v
            inverse[i, j] = 0.0
        inverse[i, i] = 1.0
    return scale


@njit(cache=True, inline="always")
def _pivot(a, inverse, col, scale):
    """invert's partial pivoting at column col: the row swap; False when the pivot is too small."""
    n = a.shape[0]
    pivot_row = col
    pivot_abs = abs(a[col, col].real) + abs(a[col, col].imag)
    for i in range(col + 1, n):
        v = abs(a[i, col].real) + abs(a[i, col].imag)
        if v > pivot_abs:
            pivot_abs = v
            pivot_row = i
    if pivot_abs <= RELATIVE_PIVOT_FLOOR * scale:
        return False
    if pivot_row != col:
        for j in range(n):
            tmp = a[col, j]
            a[col, j] = a[pivot_row, j]
            a[pivot_row, j] = tmp
            tmp = inverse[col, j]
            inverse[col, j] = inverse[pivot_row, j]
            inverse[pivot_row, j] = tmp
    return True


@njit(cache=True, inline="always")
def _real_column(a, inverse, col, scale):
    """invert's elimination of column col, real a: False when its pivot is too small."""
    n = a.shape[0]
    n4 = n - n % 4
    if not _pivot(a, inverse, col, scale):
        return False
    inverse_pivot = 1.0 / a[col, col]
    start = (col + 1) - (col + 1) % 4
    ip = splat4(inverse_pivot)
    for j in range(start, n4, 4):
        store4_row(a, col, j, mul4(load4_row(a, col, j), ip))
    for j in range(max(start, n4), n):
        a[col, j] *= inverse_pivot
    for j in range(0, n4, 4):
        store4_row(inverse, col, j, mul4(load4_row(inverse, col, j), ip))
    for j in range(n4, n):
        inverse[col, j] *= inverse_pivot
    for i in range(n):
        if i != col:
            factor = a[i, col]
            if factor != 0.0:
                f = splat4(factor)
                for j in range(start, n4, 4):
                    store4_row(a, i, j, sub4(load4_row(a, i, j), mul4(f, load4_row(a, col, j))))
                for j in range(max(start, n4), n):
                    a[i, j] -= factor * a[col, j]
                for j in range(0, n4, 4):
                    store4_row(inverse, i, j, sub4(load4_row(inverse, i, j), mul4(f, load4_row(inverse, col, j))))
                for j in range(n4, n):
                    inverse[i, j] -= factor * inverse[col, j]
    return True


@njit(cache=True, inline="always")
def _complex_column(a, inverse, col, scale):
    """invert's elimination of column col, complex a: False when its pivot is too small."""
    n = a.shape[0]
    n2 = n - n % 2
    if not _pivot(a, inverse, col, scale):
        return False
    inverse_pivot = 1.0 / a[col, col]
    start = (col + 1) - (col + 1) % 2
    p_re = splat4(inverse_pivot.real)
    p_im = splat4(inverse_pivot.imag)
    for j in range(start, n2, 2):
        x = load_pair_row(a, col, j)
        store_pair_row(a, col, j, addsub4(mul4(x, p_re), mul4(swap_pairs4(x), p_im)))
    for j in range(max(start, n2), n):
        a[col, j] *= inverse_pivot
    for j in range(0, n2, 2):
        x = load_pair_row(inverse, col, j)
        store_pair_row(inverse, col, j, addsub4(mul4(x, p_re), mul4(swap_pairs4(x), p_im)))
    for j in range(n2, n):
        inverse[col, j] *= inverse_pivot
    for i in range(n):
        if i != col:
            factor = a[i, col]
            if factor != 0.0:
                f_re = splat4(factor.real)
                f_im = splat4(factor.imag)
                for j in range(start, n2, 2):
                    x = load_pair_row(a, col, j)
                    product = addsub4(mul4(f_re, x), mul4(f_im, swap_pairs4(x)))
                    store_pair_row(a, i, j, sub4(load_pair_row(a, i, j), product))
                for j in range(max(start, n2), n):
                    a[i, j] -= factor * a[col, j]
                for j in range(0, n2, 2):
                    x = load_pair_row(inverse, col, j)
                    product = addsub4(mul4(f_re, x), mul4(f_im, swap_pairs4(x)))
                    store_pair_row(inverse, i, j, sub4(load_pair_row(inverse, i, j), product))
                for j in range(n2, n):
                    inverse[i, j] -= factor * inverse[col, j]
    return True


@njit(cache=True, inline="always")
def invert_real(a, inverse):
    """invert for a real a (n, n), C-contiguous: the same elimination, the same bits (every entry
    of the inverse is the scalar code's), with the row operations four entries at a time in one
    vector (simd.Double4: each lane the scalar multiply and subtract).

    The row operations of a start at the multiple of 4 at or below col + 1, not at col + 1: the
    columns up to col are never read again once column col is eliminated, so what the extra lanes
    write there does not matter (a is destroyed). Scalar tails for n % 4."""
    scale = _invert_start(a, inverse)
    if not (scale > 0.0):
        return 1
    for col in range(a.shape[0]):
        if not _real_column(a, inverse, col, scale):
            return 1
    return 0


@njit(cache=True, inline="always")
def invert_complex(a, inverse):
    """invert for a complex a (n, n), C-contiguous: the same elimination, the same bits, with the
    row operations two complex entries at a time in one vector (simd.Double4 as re, im, re, im).
    Numba's complex product (ac - bd) + i(ad + bc), each product rounded, lane by lane: x * p as
    (x_re p_re, x_im p_re) -+ (x_im p_im, x_re p_im) (simd.addsub4; the imaginary part's two terms
    in the other order, an exact commutation) and f * x as (f_re x_re, f_re x_im) -+ (f_im x_im,
    f_im x_re). As invert_real, the rows of a from the even column at or below col + 1. Scalar
    tails for an odd n."""
    scale = _invert_start(a, inverse)
    if not (scale > 0.0):
        return 1
    for col in range(a.shape[0]):
        if not _complex_column(a, inverse, col, scale):
            return 1
    return 0


@njit(cache=True, inline="always")
def invert_pair(real_a, real_inverse, complex_a, complex_inverse):
    """invert_real(real_a, real_inverse) and invert_complex(complex_a, complex_inverse) (the same
    n), column by column in one loop: each elimination is a chain of dependent operations (pivot,
    division, row updates) that leaves the processor idle, and the two chains are independent, so
    that it runs them side by side. Every entry the same bits as the two calls; returns 1 if
    either matrix is singular (the inverses are then unfinished), else 0."""
    real_scale = _invert_start(real_a, real_inverse)
    complex_scale = _invert_start(complex_a, complex_inverse)
    if not (real_scale > 0.0) or not (complex_scale > 0.0):
        return 1
    for col in range(real_a.shape[0]):
        if not _real_column(real_a, real_inverse, col, real_scale):
            return 1
        if not _complex_column(complex_a, complex_inverse, col, complex_scale):
            return 1
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
