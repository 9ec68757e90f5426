"""Gauss-Legendre quadrature on [0, 1] and the Legendre tables of docs/methods.md#notation.

Only floats and arrays here; the Method objects call these once, outside the time loop.

The nodes must be accurate to a few ulp (relative) for every n up to 64, including
the smallest ones (c_1 ~ 3.5e-4 at n = 64). Plain double-precision Newton on the
three-term recurrence loses up to ~50 ulp on nodes and ~800 ulp on weights there,
because the rounding of the recurrence is amplified near x = -1. So each root is
polished by Newton in double-double arithmetic (error-free transformations, Dekker
1971), working directly in c in [0, 1/2] and mirroring c -> 1 - c for the other half.
"""
import math

import numpy as np
from numba import njit

# --- double-double helpers (value = hi + lo, |lo| <= ulp(hi)/2) -------------------

_SPLITTER = 134217729.0  # 2**27 + 1, Dekker's splitting constant for float64


@njit(cache=True, inline="always")
def two_sum(a, b):
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


@njit(cache=True, inline="always")
def quick_two_sum(a, b):
    s = a + b
    return s, b - (s - a)


@njit(cache=True, inline="always")
def _split(a):
    t = _SPLITTER * a
    hi = t - (t - a)
    return hi, a - hi


@njit(cache=True, inline="always")
def two_prod(a, b):
    p = a * b
    ah, al = _split(a)
    bh, bl = _split(b)
    return p, ((ah * bh - p) + ah * bl + al * bh) + al * bl


@njit(cache=True, inline="always")
def _dd_add(ah, al, bh, bl):
    s, e = two_sum(ah, bh)
    e += al + bl
    return quick_two_sum(s, e)


@njit(cache=True, inline="always")
def _dd_mul(ah, al, bh, bl):
    p, e = two_prod(ah, bh)
    e += ah * bl + al * bh
    return quick_two_sum(p, e)


@njit(cache=True, inline="always")
def _dd_mul_d(ah, al, b):
    p, e = two_prod(ah, b)
    e += al * b
    return quick_two_sum(p, e)


@njit(cache=True, inline="always")
def _dd_div_d(ah, al, b):
    q1 = ah / b
    p, e = two_prod(q1, b)
    rh, rl = _dd_add(ah, al, -p, -e)
    q2 = rh / b
    return quick_two_sum(q1, q2)


@njit(cache=True)
def _legendre_dd(n, ch, cl):
    """(P_n(x), P_{n-1}(x)) in double-double at x = 2c - 1, c = ch + cl."""
    xh, xl = _dd_add(2.0 * ch, 2.0 * cl, -1.0, 0.0)
    p0h, p0l = 1.0, 0.0
    p1h, p1l = xh, xl
    for j in range(1, n):
        th, tl = _dd_mul(xh, xl, p1h, p1l)
        th, tl = _dd_mul_d(th, tl, 2.0 * j + 1.0)
        uh, ul = _dd_mul_d(p0h, p0l, -float(j))
        th, tl = _dd_add(th, tl, uh, ul)
        th, tl = _dd_div_d(th, tl, j + 1.0)
        p0h, p0l = p1h, p1l
        p1h, p1l = th, tl
    return p1h, p1l, p0h, p0l


@njit(cache=True)
def polished_node(c, n):
    """The root of the shifted Legendre polynomial P_n near the double c, as a double-double
    (ch, cl): three Newton steps in double-double (the correction only needs double precision;
    ch is c up to an ulp). gauss_legendre's last polish, and legendre_integral_table_dd's nodes."""
    ch, cl = c, 0.0
    for _ in range(3):
        ph, pl, qh, ql = _legendre_dd(n, ch, cl)
        x = 2.0 * ch - 1.0
        dp_dc = 2.0 * n * (x * ph - qh) / (x * x - 1.0)
        ch, cl = _dd_add(ch, cl, -(ph + pl) / dp_dc, 0.0)
    return ch, cl


@njit(cache=True)
def gauss_legendre(n, nodes, weights):
    """n-point Gauss-Legendre nodes and weights on [0, 1] (docs/methods.md#notation).

    Writes the nodes in increasing order into ``nodes`` (n,) and the weights into
    ``weights`` (n,). Returns 0 on success, 1 if n < 1.

    Method: asymptotic initial guess theta_i = pi (i + 3/4) / (n + 1/2), Newton in
    double precision, then two Newton steps with P_n evaluated in double-double.
    Weight: w_i = 4 c (1 - c) / (n P_{n-1}(2c - 1))^2 on [0, 1]
    (Abramowitz & Stegun 25.4.29 mapped to [0, 1]), also in double-double.
    """
    if n < 1:
        return 1
    half = n // 2
    for i in range(half + (n % 2)):
        if n % 2 == 1 and i == half:
            ch, cl = 0.5, 0.0
        else:
            theta = math.pi * (i + 0.75) / (n + 0.5)
            c = math.sin(0.5 * theta) ** 2
            # Newton in double precision to get within a few ulp of the root.
            for _ in range(100):
                ph, pl, qh, ql = _legendre_dd(n, c, 0.0)
                x = 2.0 * c - 1.0
                dp_dc = 2.0 * n * (x * ph - qh) / (x * x - 1.0)
                step = ph / dp_dc
                c -= step
                if abs(step) <= 1e-15 * c:
                    break
            ch, cl = polished_node(c, n)
        ph, pl, qh, ql = _legendre_dd(n, ch, cl)
        # 4 c (1 - c) in double-double
        oh, ol = _dd_add(1.0, 0.0, -ch, -cl)
        ah, al = _dd_mul(ch, cl, oh, ol)
        ah, al = _dd_mul_d(ah, al, 4.0)
        dh, dl = _dd_mul_d(qh, ql, float(n))
        dh, dl = _dd_mul(dh, dl, dh, dl)
        # division of double-doubles, to double precision
        w = (ah + al) / (dh + dl)
        q1 = ah / dh
        ph2, pe2 = two_prod(q1, dh)
        rh, rl = _dd_add(ah, al, -ph2, -pe2)
        rh, rl = _dd_add(rh, rl, -q1 * dl, 0.0)
        w = q1 + rh / dh
        nodes[i] = ch
        weights[i] = w
        if not (n % 2 == 1 and i == half):
            nodes[n - 1 - i] = oh + ol  # 1 - c, rounded once
            weights[n - 1 - i] = w
    return 0


@njit(cache=True)
def legendre_table(x, n_degrees, out):
    """Ps[i, j] = P_j(x_i) = sqrt(2j+1) Legendre_j(2 x_i - 1), j < n_degrees (docs/methods.md#notation).

    x: (n,), out: (n, n_degrees). Shifted and normalised so that the P_j are
    orthonormal on [0, 1].
    """
    for i in range(x.shape[0]):
        t = 2.0 * x[i] - 1.0
        p_prev = 1.0
        p_cur = t
        for j in range(n_degrees):
            if j == 0:
                value = 1.0
            elif j == 1:
                value = t
            else:
                p_next = ((2.0 * j - 1.0) * t * p_cur - (j - 1.0) * p_prev) / j
                p_prev = p_cur
                p_cur = p_next
                value = p_cur
            out[i, j] = math.sqrt(2.0 * j + 1.0) * value


@njit(cache=True)
def legendre_integral_table(x, n_degrees, out):
    """Is[i, j] = int_0^{x_i} P_j (docs/methods.md#notation, closed form).

    int_0^c P_0 = c; for j >= 1,
    int_0^c P_j = (P_{j+1}(c)/sqrt(2j+3) - P_{j-1}(c)/sqrt(2j-1)) / (2 sqrt(2j+1)).
    x: (n,), out: (n, n_degrees).
    """
    n = x.shape[0]
    table = np.empty((n, n_degrees + 1))
    legendre_table(x, n_degrees + 1, table)
    for i in range(n):
        out[i, 0] = x[i]
        for j in range(1, n_degrees):
            out[i, j] = (table[i, j + 1] / math.sqrt(2.0 * j + 3.0)
                         - table[i, j - 1] / math.sqrt(2.0 * j - 1.0)) / (2.0 * math.sqrt(2.0 * j + 1.0))


@njit(cache=True, inline="always")
def _dd_sqrt(a):
    """sqrt(a) of a double a, as a double-double (one Newton step on the rounded root)."""
    root = math.sqrt(a)
    p, e = two_prod(root, root)
    return quick_two_sum(root, ((a - p) - e) / (2.0 * root))


@njit(cache=True)
def legendre_integral_table_dd(x, n_nodes, n_degrees, high, low):
    """Is[i, j] = int_0^{c_i} P_j at the exact Gauss nodes c_i, as double-doubles high + low:
    c_i is the n_nodes-point Gauss-Legendre node whose double is x[i] (polished_node), and

        int_0^c P_j = (L_{j+1}(2c - 1) - L_{j-1}(2c - 1)) / (2 sqrt(2j + 1))   (j >= 1),  c (j = 0),

    with L the Legendre polynomials (P_j = sqrt(2j+1) L_j(2c - 1)), all in double-double.

    Why (docs/methods.md#round-off-over-long-times): the stages take h Is from the low parts too,
    so that the method the kernels compute is the exact collocation method, whose H is kept
    exactly on linear problems; with Is rounded to doubles, GAUSS(2) on the harmonic oscillator
    gained 2.8e-19 of H per step, the same for every start (H grew linearly, not as a random walk).
    """
    for i in range(x.shape[0]):
        ch, cl = polished_node(x[i], n_nodes)
        high[i, 0] = ch
        low[i, 0] = cl
        if n_degrees < 2:
            continue
        xh, xl = _dd_add(2.0 * ch, 2.0 * cl, -1.0, 0.0)
        # L_0, L_1, ... by the three-term recurrence in double-double
        prev_h, prev_l = 1.0, 0.0           # L_{j-1}
        cur_h, cur_l = xh, xl               # L_j
        for j in range(1, n_degrees):
            th, tl = _dd_mul(xh, xl, cur_h, cur_l)
            th, tl = _dd_mul_d(th, tl, 2.0 * j + 1.0)
            uh, ul = _dd_mul_d(prev_h, prev_l, -float(j))
            th, tl = _dd_add(th, tl, uh, ul)
            next_h, next_l = _dd_div_d(th, tl, j + 1.0)         # L_{j+1}
            dh, dl = _dd_add(next_h, next_l, -prev_h, -prev_l)   # L_{j+1} - L_{j-1}
            rh, rl = _dd_sqrt(2.0 * j + 1.0)
            dh, dl = _dd_mul(dh, dl, rh, rl)
            dh, dl = _dd_div_d(dh, dl, 2.0 * (2.0 * j + 1.0))   # times sqrt(2j+1) / (2 (2j+1))
            high[i, j] = dh
            low[i, j] = dl
            prev_h, prev_l = cur_h, cur_l
            cur_h, cur_l = next_h, next_l
