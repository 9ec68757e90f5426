"""The mathematical pendulum, one degree of freedom.

H = p^2/2 - omega^2 cos q,   q' = p,  p' = -omega^2 sin q,
Hessian diag(omega^2 cos q, 1).
No invariant besides H (HBVM keeps H only to O(h^(2k+1)) per step: H is not a polynomial).
Default initial state: q0 = 1 (radian), p0 = 0, a libration of amplitude 1 for every omega
(the separatrix is H = omega^2).
Reference: Hairer, Lubich & Wanner, Geometric Numerical Integration, 2nd ed., I.1.2.
"""
import math

import numpy as np

from ..kernels.signatures import jit_gradient, jit_hamiltonian, jit_hessian, no_invariant_gradients, no_invariants
from ..errors import ParameterError
from .base import Problem, real_parameter


@jit_hamiltonian
def H(y, params):
    omega = params[0]
    return 0.5 * y[1] * y[1] - omega * omega * math.cos(y[0])


@jit_gradient
def grad_H(y, params, out):
    omega = params[0]
    out[0] = omega * omega * math.sin(y[0])
    out[1] = y[1]


@jit_hessian
def hess_H(y, params, out):
    omega = params[0]
    out[0, 0] = omega * omega * math.cos(y[0])
    out[0, 1] = out[1, 0] = 0.0
    out[1, 1] = 1.0


def pendulum(omega: float = 1.0) -> Problem:
    """The pendulum H = p^2/2 - omega^2 cos q (small-oscillation frequency omega > 0)."""
    omega = real_parameter("omega", omega)
    if not (math.isfinite(omega) and omega > 0.0):
        raise ParameterError("omega", f"must be a positive finite frequency, got {omega}")
    return Problem(
        name="pendulum", q_names=("q",), p_names=("p",),
        H=H, grad_H=grad_H, hess_H=hess_H, hessian_source="analytic",
        invariants=no_invariants, grad_invariants=no_invariant_gradients,
        invariant_names=(), y0=np.array([1.0, 0.0]), params=np.array([omega]),
        parameters={"omega": omega},
        description="mathematical pendulum, H = p^2/2 - omega^2 cos q",
    )
