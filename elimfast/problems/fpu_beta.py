"""The Fermi-Pasta-Ulam beta chain: n unit masses joined by anharmonic nearest-neighbour springs.

H = sum_i p_i^2/2 + sum_springs V(r),  V(r) = r^2/2 + beta r^4/4,  params = [beta],
with r the stretch q_{i+1} - q_i of each spring (indices 1..n below, 0-based in the code).

- boundary="periodic" (default): n springs, q_{n+1} = q_1 (a ring). The potential depends
  on differences only, so the total momentum P = sum p_i is an invariant ("momentum",
  linear, grad P = (0, 1)). Every Runge-Kutta method keeps a linear invariant exactly
  (up to round-off), so there is nothing for ELIM/EHBVM to impose: imposing it makes
  Gamma singular (its phi_j, j >= 1, vanish; docs/methods.md#elim).
- boundary="fixed": n + 1 springs, q_0 = q_{n+1} = 0 (both ends clamped). No invariant
  besides H.
grad_q H_i = V'(r_{i-1}) - V'(r_i), V'(r) = r + beta r^3 (r_i: the spring right of mass i).
Hessian: each spring between masses a and b adds its stiffness V''(r) = 1 + 3 beta r^2 to
the (a, a) and (b, b) entries and subtracts it from (a, b) and (b, a) (a clamped end has no
entry); the p block is the identity.
H is a quartic polynomial: HBVM(k,s) keeps it to round-off when 4 <= 2k/s.

Default initial states, with amplitude 1 in the lowest mode:
- periodic: q_j = sin(2 pi j/n), p_j = 0.1 + omega_1 cos(2 pi j/n), omega_1 = 2 sin(pi/n)
  (j = 1..n): a travelling long wave on a drift, total momentum 0.1 n;
- fixed: q_j = sin(pi j/(n+1)), p_j = 0, the initial state of Fermi, Pasta and Ulam.
References: E. Fermi, J. Pasta, S. Ulam, Studies of nonlinear problems, Los Alamos report
LA-1940 (1955); G. Gallavotti (ed.), The Fermi-Pasta-Ulam Problem, Lecture Notes in
Physics 728 (2008), chapter 1.
"""
import math

import numpy as np
from numba import njit

from ..kernels.signatures import (jit_gradient, jit_hamiltonian, jit_hessian, jit_invariant_gradients,
                                  jit_invariants, no_invariant_gradients, no_invariants)
from ..errors import ParameterError
from .base import Problem, real_parameter

BOUNDARIES = ("periodic", "fixed")


@jit_hamiltonian
def _periodic_H(y, params):
    beta = params[0]
    n = y.shape[0] // 2
    energy = 0.0
    for i in range(n):
        r = y[(i + 1) % n] - y[i]
        r2 = r * r
        energy += 0.5 * y[n + i] * y[n + i] + 0.5 * r2 + 0.25 * beta * r2 * r2
    return energy


@jit_gradient
def _periodic_grad_H(y, params, out):
    beta = params[0]
    n = y.shape[0] // 2
    for i in range(n):
        out[i] = 0.0
        out[n + i] = y[n + i]
    for i in range(n):
        right = (i + 1) % n
        r = y[right] - y[i]
        force = r + beta * r * r * r   # V'(r) of the spring between i and i+1
        out[i] -= force
        out[right] += force


@njit(cache=True, inline="always")
def _clear_with_unit_momentum_block(out, n):
    """out = [[0, 0], [0, I_n]]: the kinetic part of every chain's Hessian."""
    out[:] = 0.0
    for i in range(n):
        out[n + i, n + i] = 1.0


@jit_hessian
def _periodic_hess_H(y, params, out):
    beta = params[0]
    n = y.shape[0] // 2
    _clear_with_unit_momentum_block(out, n)
    for i in range(n):
        right = (i + 1) % n
        r = y[right] - y[i]
        stiffness = 1.0 + 3.0 * beta * r * r   # V''(r); n = 2: both springs join the same pair, and add up
        out[i, i] += stiffness
        out[right, right] += stiffness
        out[i, right] -= stiffness
        out[right, i] -= stiffness


@jit_invariants
def _periodic_invariants(y, params, out):
    n = y.shape[0] // 2
    total = 0.0
    for i in range(n):
        total += y[n + i]
    out[0] = total


@jit_invariant_gradients
def _periodic_grad_invariants(y, params, out):
    n = y.shape[0] // 2
    for i in range(n):
        out[0, i] = 0.0
        out[0, n + i] = 1.0


@jit_hamiltonian
def _fixed_H(y, params):
    beta = params[0]
    n = y.shape[0] // 2
    energy = 0.0
    left = 0.0   # q_0 = 0
    for i in range(n + 1):
        right = y[i] if i < n else 0.0   # q_{n+1} = 0
        r = right - left
        r2 = r * r
        energy += 0.5 * r2 + 0.25 * beta * r2 * r2
        left = right
    for i in range(n):
        energy += 0.5 * y[n + i] * y[n + i]
    return energy


@jit_gradient
def _fixed_grad_H(y, params, out):
    beta = params[0]
    n = y.shape[0] // 2
    left = 0.0
    for i in range(n):
        out[i] = 0.0
        out[n + i] = y[n + i]
    for i in range(n + 1):
        right = y[i] if i < n else 0.0
        r = right - left
        force = r + beta * r * r * r   # V'(r) of the spring between masses i-1 and i (0-based)
        if i > 0:
            out[i - 1] -= force
        if i < n:
            out[i] += force
        left = right


@jit_hessian
def _fixed_hess_H(y, params, out):
    beta = params[0]
    n = y.shape[0] // 2
    _clear_with_unit_momentum_block(out, n)
    left = 0.0
    for i in range(n + 1):
        right = y[i] if i < n else 0.0
        r = right - left
        stiffness = 1.0 + 3.0 * beta * r * r   # V''(r) of the spring between masses i-1 and i (0-based)
        if i > 0:
            out[i - 1, i - 1] += stiffness
        if i < n:
            out[i, i] += stiffness
        if 0 < i < n:
            out[i - 1, i] -= stiffness
            out[i, i - 1] -= stiffness
        left = right


def fpu_beta(n: int = 8, beta: float = 1.0, boundary: str = "periodic") -> Problem:
    """FPU-beta chain of n >= 2 unit masses, beta >= 0, boundary 'periodic' or 'fixed'."""
    if isinstance(n, bool) or not real_parameter("n", n).is_integer() or n < 2:
        raise ParameterError("n", f"must be an integer >= 2 (the number of masses), got {n!r}")
    n = int(n)
    beta = real_parameter("beta", beta)
    if not (math.isfinite(beta) and beta >= 0.0):
        raise ParameterError("beta", f"must be finite and >= 0 (beta < 0 makes the potential unbounded below), "
                                     f"got {beta}")
    if boundary not in BOUNDARIES:
        raise ParameterError("boundary", f"must be 'periodic' or 'fixed', got {boundary!r}")
    j = np.arange(1, n + 1)
    if boundary == "periodic":
        omega_1 = 2.0 * math.sin(math.pi / n)
        y0 = np.concatenate((np.sin(2.0 * math.pi * j / n), 0.1 + omega_1 * np.cos(2.0 * math.pi * j / n)))
        functions = dict(H=_periodic_H, grad_H=_periodic_grad_H, hess_H=_periodic_hess_H,
                         invariants=_periodic_invariants, grad_invariants=_periodic_grad_invariants)
        invariant_names = ("momentum",)
    else:
        y0 = np.concatenate((np.sin(math.pi * j / (n + 1)), np.zeros(n)))
        functions = dict(H=_fixed_H, grad_H=_fixed_grad_H, hess_H=_fixed_hess_H, invariants=no_invariants,
                         grad_invariants=no_invariant_gradients)
        invariant_names = ()
    return Problem(
        name="fpu_beta", q_names=tuple(f"q{i}" for i in j), p_names=tuple(f"p{i}" for i in j),
        invariant_names=invariant_names, y0=y0, params=np.array([beta]), hessian_source="analytic",
        parameters={"n": n, "beta": beta, "boundary": boundary},
        description=f"FPU-beta chain, {n} masses, {boundary} ends, V(r) = r^2/2 + beta r^4/4",
        hamiltonian_degree=4 if beta != 0.0 else 2,
        **functions,
    )
