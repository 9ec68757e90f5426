"""The periodic Toda lattice, with traces of powers of its Lax matrix as invariants.

H = sum_i p_i^2/2 + sum_i exp(q_i - q_{i+1}),  q_{n+1} = q_1,  n >= 3 particles.
Hessian: each term w = exp(q_i - q_{i+1}) adds w to the (i, i) and (i+1, i+1) entries and
-w to (i, i+1) and (i+1, i); the p block is the identity.
Flaschka variables a_i = exp((q_i - q_{i+1})/2)/2, b_i = -p_i/2 give the symmetric
periodic tridiagonal Lax matrix L (L_ii = b_i, L_{i,i+1} = L_{i+1,i} = a_i, corners
L_{n,1} = L_{1,n} = a_n), and L' = [B, L] makes every tr(L^k) an invariant.
Declared invariants: trace_L1, trace_L3, trace_L4, ..., trace_LK with K = min(n, 5):
- tr(L) = -sum p_i/2 is (minus half) the total momentum: linear, kept by every Runge-Kutta
  method, and not imposable by ELIM/EHBVM (its phi_j, j >= 1, vanish: Gamma singular);
- tr(L^2) = sum b_i^2 + 2 sum a_i^2 = H/2 exactly, so it is left out (imposing it next to
  H, which HBVM/ELIM keep anyway, makes Gamma singular);
- tr(L^k) for k > n is a polynomial in tr(L^1..n) (Newton's identities), hence K <= n;
  K <= 5 bounds the cost. trace_L3..trace_LK are independent: with n >= 5, nu = 3 of
  them can be imposed at once (n = 4 allows two).
Gradients (derived by hand): d tr(L^k) = k tr(L^(k-1) dL), so with M = L^(k-1)
  d tr(L^k)/d p_i = -(k/2) M_ii,   d tr(L^k)/d q_i = k (a_i M_{i,i+1} - a_{i-1} M_{i-1,i}).
Nothing is allocated. The gradients (called k times per iteration by the kernels) get
M_ii and M_{i,i+1} from v <- L v applied K-1 times to each unit vector e_i, O(K n^2),
with grad tr(L)'s row of ``out`` as workspace (it is constant and written last). The
values (called once per step) have no workspace: tr(L^k) sums the weighted closed walks
of length k on the ring (each step: stay at x, weight b_x; move to x+1, weight a_x; move
to x-1, weight a_{x-1}), enumerating 3^(k-1) step sequences from each site. The two
evaluations are independent, and the tests compare them (by central differences) and
both with dense matrix powers.
Default initial state (j = 1..n): q_j = 0.3 sin(2 pi j/n + 0.7),
p_j = cos(2 pi j/n + 0.4) + sin(4 pi j/n + 1.1)/2 + 1/4. The phases avoid symmetric
states: from q = 0, p = (1/4, -3/4, 1/4, 5/4) (p_j = p_(n-j)), EHBVM(12,3) imposing
trace_L3 and trace_L4 fails at the first step (Gamma singular) and HBVM keeps both traces
to round-off anyway. Even from generic states Gamma is nearly singular at isolated
steps (its determinant changes sign along the flow): alpha then spikes far above its
O(h^2) size, and with larger h the iteration can fail to converge.
References: H. Flaschka, Phys. Rev. B 9 (1974) 1924-1925; M. Toda, Theory of Nonlinear
Lattices, Springer (1981), ch. 4; Hairer, Lubich & Wanner, Geometric Numerical
Integration, 2nd ed., chapter X (the Toda lattice example of section X.1).
"""
import math

import numpy as np
from numba import njit

from ..kernels.signatures import (jit_gradient, jit_hamiltonian, jit_hessian, jit_invariant_gradients,
                                  jit_invariants)
from ..errors import ParameterError
from .base import Problem, real_parameter

MAX_POWER = 5


@jit_hamiltonian
def H(y, params):
    n = y.shape[0] // 2
    energy = 0.0
    for i in range(n):
        energy += 0.5 * y[n + i] * y[n + i] + math.exp(y[i] - y[(i + 1) % n])
    return energy


@jit_gradient
def grad_H(y, params, out):
    n = y.shape[0] // 2
    for i in range(n):
        out[i] = 0.0
        out[n + i] = y[n + i]
    for i in range(n):
        right = (i + 1) % n
        force = math.exp(y[i] - y[right])
        out[i] += force
        out[right] -= force


@jit_hessian
def hess_H(y, params, out):
    n = y.shape[0] // 2
    out[:] = 0.0
    for i in range(n):
        out[n + i, n + i] = 1.0
    for i in range(n):
        right = (i + 1) % n
        w = math.exp(y[i] - y[right])
        out[i, i] += w
        out[right, right] += w
        out[i, right] -= w
        out[right, i] -= w


@njit(cache=True)
def _closed_walks(y, start, length):
    """(L^length)[start, start], length >= 2: the weighted closed walks from ``start``.

    Enumerates the 3^(length-1) sequences of the first length-1 steps; the last step is
    forced (back to start, if start is within one site). The a-weights of a walk are
    multiplied as one exp of their summed exponents (q_x - q_{x+1})/2, times 2^-moves.
    """
    n = y.shape[0] // 2
    before = start - 1 if start > 0 else n - 1
    after = start + 1 if start + 1 < n else 0
    total = 0.0
    for code in range(3 ** (length - 1)):
        x = start
        rest = code
        b_product = 1.0
        exponent = 0.0
        moves = 0
        for _ in range(length - 1):
            step = rest % 3
            rest //= 3
            if step == 0:
                b_product *= -0.5 * y[n + x]
            elif step == 1:
                right = x + 1 if x + 1 < n else 0
                exponent += 0.5 * (y[x] - y[right])
                moves += 1
                x = right
            else:
                left = x - 1 if x > 0 else n - 1
                exponent += 0.5 * (y[left] - y[x])
                moves += 1
                x = left
        if x == start:
            b_product *= -0.5 * y[n + start]
        elif x == before:      # a_{start-1}: the step before -> start
            exponent += 0.5 * (y[before] - y[start])
            moves += 1
        elif x == after:       # a_start: the step after -> start
            exponent += 0.5 * (y[start] - y[after])
            moves += 1
        else:
            continue
        total += b_product * math.exp(exponent) * 0.5 ** moves
    return total


@njit(cache=True, inline="always")
def _row_power(row):
    """Row 0 holds tr(L), row r >= 1 holds tr(L^(r+2))."""
    return 1 if row == 0 else row + 2


@jit_invariants
def invariants(y, params, out):
    n = y.shape[0] // 2
    for row in range(out.shape[0]):
        power = _row_power(row)
        if power == 1:
            total = 0.0
            for i in range(n):
                total -= 0.5 * y[n + i]
        else:
            total = 0.0
            for i in range(n):
                total += _closed_walks(y, i, power)
        out[row] = total


@njit(cache=True, inline="always")
def _apply_lax_in_place(y, a, v):
    """v <- L v for the periodic tridiagonal L (n >= 3), with two scalars of carry."""
    n = v.shape[0]
    first = v[0]            # old v_0, needed by the last row (wrap-around)
    previous = v[n - 1]     # old v_{x-1}
    for x in range(n):
        left = x - 1 if x > 0 else n - 1
        following = v[x + 1] if x + 1 < n else first
        current = v[x]
        v[x] = -0.5 * y[n + x] * current + a[x] * following + a[left] * previous
        previous = current


@jit_invariant_gradients
def grad_invariants(y, params, out):
    # Row 0 (grad tr L, a constant) is written last: until then it is the workspace,
    # a_x in its first n entries and the vector v of the recursion v <- L v in the rest.
    # No allocation: this runs k (or r) times per iteration in the kernels.
    n = y.shape[0] // 2
    n_rows = out.shape[0]
    a = out[0, :n]
    v = out[0, n:]
    for x in range(n):
        right = x + 1 if x + 1 < n else 0
        a[x] = 0.5 * math.exp(0.5 * (y[x] - y[right]))
    # Pass 1: v = L^m e_i for m = 1..K-1; row r (power k = r + 2, m = k - 1) keeps
    # M_ii in its p part and M_{i,i+1} in its q part, M = L^m.
    reach = n_rows               # L^m e_i lives on i - m .. i + m, m <= n_rows
    if n >= 2 * reach + 3:
        # Only that window of v is computed (the same sums, term for term, as on the whole
        # ring: the rest of v is zero): O(n K^2) instead of O(n^2 K); toda with 10^5
        # particles spent minutes in each call. The window w = v[i - reach .. i + reach] is
        # kept in v's first 2 reach + 1 entries, free in this branch.
        width = 2 * reach + 1
        for i in range(n):
            for d in range(width):
                v[d] = 0.0
            v[reach] = 1.0
            for m in range(1, n_rows + 1):
                previous = 0.0          # old w[d - 1]; zero left of the window
                for d in range(width):
                    x = i + d - reach
                    x = x + n if x < 0 else (x - n if x >= n else x)
                    left = x - 1 if x > 0 else n - 1
                    following = v[d + 1] if d + 1 < width else 0.0
                    current = v[d]
                    v[d] = -0.5 * y[n + x] * current + a[x] * following + a[left] * previous
                    previous = current
                if m >= 2:
                    row = m - 1
                    out[row, n + i] = v[reach]
                    out[row, i] = v[reach + 1]
    else:
        for i in range(n):
            for x in range(n):
                v[x] = 0.0
            v[i] = 1.0
            for m in range(1, n_rows + 1):
                _apply_lax_in_place(y, a, v)
                if m >= 2:
                    row = m - 1
                    out[row, n + i] = v[i]
                    out[row, i] = v[i + 1 if i + 1 < n else 0]
    # Pass 2: d tr(L^k)/d p_i = -(k/2) M_ii,  d tr(L^k)/d q_j = k (a_j M_{j,j+1} - a_{j-1} M_{j-1,j}).
    for row in range(1, n_rows):
        power = _row_power(row)
        for i in range(n):
            out[row, n + i] *= -0.5 * power
        previous = a[n - 1] * out[row, n - 1]
        for j in range(n):
            current = a[j] * out[row, j]
            out[row, j] = power * (current - previous)
            previous = current
    for i in range(n):
        out[0, i] = 0.0
        out[0, n + i] = -0.5


def invariant_names_for(n: int) -> tuple[str, ...]:
    """trace_L1, trace_L3, ..., trace_LK, K = min(n, MAX_POWER)."""
    return ("trace_L1",) + tuple(f"trace_L{k}" for k in range(3, min(n, MAX_POWER) + 1))


def toda(n: int = 4) -> Problem:
    """Periodic Toda lattice of n >= 3 particles (invariants: see the module docstring)."""
    if isinstance(n, bool) or not real_parameter("n", n).is_integer() or n < 3:
        raise ParameterError("n", f"must be an integer >= 3 (the number of particles on the ring), got {n!r}")
    n = int(n)
    j = np.arange(1, n + 1)
    q0 = 0.3 * np.sin(2.0 * math.pi * j / n + 0.7)
    p0 = np.cos(2.0 * math.pi * j / n + 0.4) + 0.5 * np.sin(4.0 * math.pi * j / n + 1.1) + 0.25
    return Problem(
        name="toda", q_names=tuple(f"q{i}" for i in j), p_names=tuple(f"p{i}" for i in j),
        H=H, grad_H=grad_H, hess_H=hess_H, hessian_source="analytic",
        invariants=invariants, grad_invariants=grad_invariants, invariant_names=invariant_names_for(n),
        y0=np.concatenate((q0, p0)), params=np.zeros(0), parameters={"n": n},
        description=f"periodic Toda lattice, {n} particles, H = |p|^2/2 + sum exp(q_i - q_(i+1))",
    )
