"""Planar Kepler problem with angular momentum and the Laplace-Runge-Lenz vector.

H = |p|^2/2 - 1/|q| (docs/methods.md#typos-in-the-paper: the paper prints +1/|q| by mistake),
grad_q H = q/|q|^3, grad_p H = p; Hessian: d^2 H/dq_i dq_j = delta_ij/|q|^3 - 3 q_i q_j/|q|^5,
d^2 H/dp_i dp_j = delta_ij, no q-p coupling.
L1 = q1 p2 - q2 p1 (angular momentum), A = (p2 L1 - q1/|q|, -p1 L1 - q2/|q|) (LRL vector;
the paper's L2 is A_y, with the sign the paper drops restored).
Initial state for eccentricity e: q0 = (1-e, 0), p0 = (0, sqrt((1+e)/(1-e))): period 2 pi,
H0 = -1/2, L1 = sqrt(1-e^2), A = (e, 0).
Reference: Brugnano & Sun, Numer. Algorithms 65 (2014) 611-632, section 3;
Hairer, Lubich & Wanner, Geometric Numerical Integration, I.2.3.
"""
import math

import numpy as np

from ..kernels.signatures import (jit_gradient, jit_hamiltonian, jit_hessian, jit_invariant_gradients,
                                  jit_invariants)
from ..errors import ParameterError
from .base import Problem, real_parameter


@jit_hamiltonian
def H(y, params):
    return 0.5 * (y[2] * y[2] + y[3] * y[3]) - 1.0 / math.sqrt(y[0] * y[0] + y[1] * y[1])


@jit_gradient
def grad_H(y, params, out):
    r2 = y[0] * y[0] + y[1] * y[1]
    inv_r3 = 1.0 / (r2 * math.sqrt(r2))
    out[0] = y[0] * inv_r3
    out[1] = y[1] * inv_r3
    out[2] = y[2]
    out[3] = y[3]


@jit_hessian
def hess_H(y, params, out):
    r2 = y[0] * y[0] + y[1] * y[1]
    inv_r3 = 1.0 / (r2 * math.sqrt(r2))
    inv_r5 = inv_r3 / r2
    out[:] = 0.0
    out[0, 0] = inv_r3 - 3.0 * y[0] * y[0] * inv_r5
    out[1, 1] = inv_r3 - 3.0 * y[1] * y[1] * inv_r5
    out[0, 1] = out[1, 0] = -3.0 * y[0] * y[1] * inv_r5
    out[2, 2] = 1.0
    out[3, 3] = 1.0


@jit_invariants
def invariants(y, params, out):
    q1, q2, p1, p2 = y[0], y[1], y[2], y[3]
    inv_r = 1.0 / math.sqrt(q1 * q1 + q2 * q2)
    L = q1 * p2 - q2 * p1
    out[0] = L
    out[1] = p2 * L - q1 * inv_r
    out[2] = -p1 * L - q2 * inv_r


@jit_invariant_gradients
def grad_invariants(y, params, out):
    q1, q2, p1, p2 = y[0], y[1], y[2], y[3]
    r2 = q1 * q1 + q2 * q2
    inv_r = 1.0 / math.sqrt(r2)
    inv_r3 = inv_r / r2
    L = q1 * p2 - q2 * p1
    # grad L = (p2, -p1, -q2, q1)
    out[0, 0] = p2
    out[0, 1] = -p1
    out[0, 2] = -q2
    out[0, 3] = q1
    # A_x = p2 L - q1/r
    out[1, 0] = p2 * p2 - inv_r + q1 * q1 * inv_r3
    out[1, 1] = -p2 * p1 + q1 * q2 * inv_r3
    out[1, 2] = -p2 * q2
    out[1, 3] = L + p2 * q1
    # A_y = -p1 L - q2/r
    out[2, 0] = -p1 * p2 + q1 * q2 * inv_r3
    out[2, 1] = p1 * p1 - inv_r + q2 * q2 * inv_r3
    out[2, 2] = -L + p1 * q2
    out[2, 3] = -p1 * q1


@jit_invariants
def time_scale(y, params, out):
    """sigma = |q|^(3/2) (the local period's scale at distance |q|) and its gradient
    (docs/adaptive.md, the time-reversible controller)."""
    r = math.sqrt(y[0] * y[0] + y[1] * y[1])
    sigma = r * math.sqrt(r)
    out[0] = sigma
    factor = 1.5 * sigma / (r * r)
    out[1] = factor * y[0]
    out[2] = factor * y[1]
    out[3] = 0.0
    out[4] = 0.0


def kepler(eccentricity: float = 0.6) -> Problem:
    """The planar Kepler problem of the paper, e in [0, 1)."""
    e = real_parameter("eccentricity", eccentricity)
    if not 0.0 <= e < 1.0:
        raise ParameterError("eccentricity", f"must be in [0, 1) for a periodic orbit, got {e}")
    y0 = np.array([1.0 - e, 0.0, 0.0, math.sqrt((1.0 + e) / (1.0 - e))])
    return Problem(
        name="kepler", q_names=("q1", "q2"), p_names=("p1", "p2"),
        H=H, grad_H=grad_H, hess_H=hess_H, hessian_source="analytic",
        invariants=invariants, grad_invariants=grad_invariants,
        invariant_names=("angular_momentum", "lrl_x", "lrl_y"),
        y0=y0, params=np.zeros(0), parameters={"eccentricity": e},
        description="planar Kepler problem, H = |p|^2/2 - 1/|q|, period 2 pi",
        time_scale=time_scale,
    )
