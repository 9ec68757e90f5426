"""The perturbed planar Kepler problem: Kepler plus a 1/|q|^3 term (orbits precess).

H = |p|^2/2 - 1/|q| - delta/(2 |q|^3),   params = [delta],
grad_q H = q f(r),  f(r) = 1/r^3 + (3 delta/2)/r^5  (r = |q|),  grad_p H = p,
Hessian: d^2 H/dq_i dq_j = f(r) delta_ij + (f'(r)/r) q_i q_j with
f'(r)/r = -3/r^5 - (15 delta/2)/r^7;  d^2 H/dp_i dp_j = delta_ij; no q-p coupling.
The potential is still central, so the angular momentum L = q1 p2 - q2 p1 is an
invariant; the Laplace-Runge-Lenz vector is not (its direction turns with the perihelion).
Initial state as for ``kepler``: q0 = (1-e, 0), p0 = (0, sqrt((1+e)/(1-e))), so
L(y0) = sqrt(1-e^2) and H(y0) = -1/2 - delta/(2 (1-e)^3).
Reference: Hairer, Lubich & Wanner, Geometric Numerical Integration, 2nd ed., I.2.3 (the
perturbed Kepler problem, same initial values).
"""
import math

import numpy as np

from ..kernels.signatures import (jit_gradient, jit_hamiltonian, jit_hessian, jit_invariant_gradients,
                                  jit_invariants)
from ..errors import ParameterError
from .base import Problem, real_parameter
from .kepler import time_scale as kepler_time_scale


@jit_hamiltonian
def H(y, params):
    delta = params[0]
    r2 = y[0] * y[0] + y[1] * y[1]
    r = math.sqrt(r2)
    return 0.5 * (y[2] * y[2] + y[3] * y[3]) - 1.0 / r - 0.5 * delta / (r2 * r)


@jit_gradient
def grad_H(y, params, out):
    delta = params[0]
    r2 = y[0] * y[0] + y[1] * y[1]
    inv_r3 = 1.0 / (r2 * math.sqrt(r2))
    radial = inv_r3 + 1.5 * delta * inv_r3 / r2   # 1/r^3 + (3 delta/2)/r^5
    out[0] = y[0] * radial
    out[1] = y[1] * radial
    out[2] = y[2]
    out[3] = y[3]


@jit_hessian
def hess_H(y, params, out):
    delta = params[0]
    r2 = y[0] * y[0] + y[1] * y[1]
    inv_r2 = 1.0 / r2
    inv_r3 = inv_r2 / math.sqrt(r2)
    inv_r5 = inv_r3 * inv_r2
    radial = inv_r3 + 1.5 * delta * inv_r5                  # f(r)
    slope = -3.0 * inv_r5 - 7.5 * delta * inv_r5 * inv_r2   # f'(r)/r
    out[:] = 0.0
    out[0, 0] = radial + slope * y[0] * y[0]
    out[1, 1] = radial + slope * y[1] * y[1]
    out[0, 1] = out[1, 0] = slope * y[0] * y[1]
    out[2, 2] = 1.0
    out[3, 3] = 1.0


@jit_invariants
def invariants(y, params, out):
    out[0] = y[0] * y[3] - y[1] * y[2]


@jit_invariant_gradients
def grad_invariants(y, params, out):
    # grad (q1 p2 - q2 p1) = (p2, -p1, -q2, q1)
    out[0, 0] = y[3]
    out[0, 1] = -y[2]
    out[0, 2] = -y[1]
    out[0, 3] = y[0]


def perturbed_kepler(eccentricity: float = 0.6, delta: float = 0.01) -> Problem:
    """Perturbed Kepler, H = |p|^2/2 - 1/|q| - delta/(2|q|^3), from the Kepler initial state."""
    e = real_parameter("eccentricity", eccentricity)
    if not 0.0 <= e < 1.0:
        raise ParameterError("eccentricity", f"must be in [0, 1), got {e}")
    delta = real_parameter("delta", delta)
    if not math.isfinite(delta):
        raise ParameterError("delta", f"must be a finite number, got {delta}")
    y0 = np.array([1.0 - e, 0.0, 0.0, math.sqrt((1.0 + e) / (1.0 - e))])
    return Problem(
        name="perturbed_kepler", q_names=("q1", "q2"), p_names=("p1", "p2"),
        H=H, grad_H=grad_H, hess_H=hess_H, hessian_source="analytic",
        invariants=invariants, grad_invariants=grad_invariants,
        invariant_names=("angular_momentum",),
        y0=y0, params=np.array([delta]), parameters={"eccentricity": e, "delta": delta},
        description="perturbed Kepler problem, H = |p|^2/2 - 1/|q| - delta/(2|q|^3)",
        time_scale=kepler_time_scale,   # |q|^(3/2), as for Kepler
    )
