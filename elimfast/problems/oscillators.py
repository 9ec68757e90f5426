"""Polynomial Hamiltonians, for the exact-conservation tests of docs/methods.md#hbvm and #elim.

- ``harmonic_oscillator(omega)``: H = p^2/2 + omega^2 q^2/2 (degree 2), one degree of freedom;
  Hessian diag(omega^2, 1).
- ``quartic_oscillator()``: H = p^2/2 + q^4/4 (degree 4), one degree of freedom;
  Hessian diag(3 q^2, 1).
- ``central_quartic()``: H = |p|^2/2 + |q|^4/4 in the plane (degree 4) with the
  quadratic invariant L = q1 p2 - q2 p1 (angular momentum); grad_q H = |q|^2 q,
  Hessian: q block |q|^2 delta_ij + 2 q_i q_j, p block the identity.
HBVM(k,s) keeps a polynomial H of degree <= 2k/s to round-off (Brugnano, Iavernaro,
Trigiante, JNAIAM 5 (2010)); ELIM keeps a polynomial L of degree <= 2r/s.
"""
import numpy as np

from ..kernels.signatures import (jit_gradient, jit_hamiltonian, jit_hessian, jit_invariant_gradients,
                                  jit_invariants, no_invariant_gradients, no_invariants)
from .base import Problem, real_parameter


@jit_hamiltonian
def _harmonic_H(y, params):
    return 0.5 * y[1] * y[1] + 0.5 * params[0] * params[0] * y[0] * y[0]


@jit_gradient
def _harmonic_grad_H(y, params, out):
    out[0] = params[0] * params[0] * y[0]
    out[1] = y[1]


@jit_hessian
def _harmonic_hess_H(y, params, out):
    out[0, 0] = params[0] * params[0]
    out[0, 1] = out[1, 0] = 0.0
    out[1, 1] = 1.0


def harmonic_oscillator(omega: float = 1.0) -> Problem:
    omega = real_parameter("omega", omega)
    return Problem(
        name="harmonic_oscillator", q_names=("q",), p_names=("p",),
        H=_harmonic_H, grad_H=_harmonic_grad_H, hess_H=_harmonic_hess_H, hessian_source="analytic",
        invariants=no_invariants, grad_invariants=no_invariant_gradients,
        invariant_names=(), y0=np.array([1.0, 0.0]), params=np.array([omega]),
        parameters={"omega": omega}, description="H = p^2/2 + omega^2 q^2/2", hamiltonian_degree=2,
    )


@jit_hamiltonian
def _quartic_H(y, params):
    return 0.5 * y[1] * y[1] + 0.25 * y[0] ** 4


@jit_gradient
def _quartic_grad_H(y, params, out):
    out[0] = y[0] ** 3
    out[1] = y[1]


@jit_hessian
def _quartic_hess_H(y, params, out):
    out[0, 0] = 3.0 * y[0] * y[0]
    out[0, 1] = out[1, 0] = 0.0
    out[1, 1] = 1.0


def quartic_oscillator() -> Problem:
    return Problem(
        name="quartic_oscillator", q_names=("q",), p_names=("p",),
        H=_quartic_H, grad_H=_quartic_grad_H, hess_H=_quartic_hess_H, hessian_source="analytic",
        invariants=no_invariants, grad_invariants=no_invariant_gradients,
        invariant_names=(), y0=np.array([1.0, 0.5]), description="H = p^2/2 + q^4/4", hamiltonian_degree=4,
    )


@jit_hamiltonian
def _central_H(y, params):
    r2 = y[0] * y[0] + y[1] * y[1]
    return 0.5 * (y[2] * y[2] + y[3] * y[3]) + 0.25 * r2 * r2


@jit_gradient
def _central_grad_H(y, params, out):
    r2 = y[0] * y[0] + y[1] * y[1]
    out[0] = r2 * y[0]
    out[1] = r2 * y[1]
    out[2] = y[2]
    out[3] = y[3]


@jit_hessian
def _central_hess_H(y, params, out):
    r2 = y[0] * y[0] + y[1] * y[1]
    out[:] = 0.0
    out[0, 0] = r2 + 2.0 * y[0] * y[0]
    out[1, 1] = r2 + 2.0 * y[1] * y[1]
    out[0, 1] = out[1, 0] = 2.0 * y[0] * y[1]
    out[2, 2] = 1.0
    out[3, 3] = 1.0


@jit_invariants
def _central_invariants(y, params, out):
    out[0] = y[0] * y[3] - y[1] * y[2]


@jit_invariant_gradients
def _central_grad_invariants(y, params, out):
    out[0, 0] = y[3]
    out[0, 1] = -y[2]
    out[0, 2] = -y[1]
    out[0, 3] = y[0]


def central_quartic() -> Problem:
    return Problem(
        name="central_quartic", q_names=("q1", "q2"), p_names=("p1", "p2"),
        H=_central_H, grad_H=_central_grad_H, hess_H=_central_hess_H, hessian_source="analytic",
        invariants=_central_invariants, grad_invariants=_central_grad_invariants, invariant_names=("angular_momentum",),
        y0=np.array([1.0, 0.0, 0.2, 0.8]), description="H = |p|^2/2 + |q|^4/4 in the plane", hamiltonian_degree=4,
    )
