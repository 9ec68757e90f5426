"""The Henon-Heiles model: a cubic Hamiltonian in the plane.

H = (p1^2 + p2^2)/2 + (q1^2 + q2^2)/2 + q1^2 q2 - q2^3/3,
grad_q H = (q1 + 2 q1 q2, q2 + q1^2 - q2^2),  grad_p H = p,
Hessian: q block [[1 + 2 q2, 2 q1], [2 q1, 1 - 2 q2]], p block the identity.
No invariant besides H; H is a cubic polynomial, so HBVM(k,s) with 3 <= 2k/s keeps it to
round-off. Motion is bounded for H < 1/6 (the saddle points of the potential).
Default initial state: on the section q1 = 0 used by Henon & Heiles, q = (0, 0.1),
p2 = 0 and p1 = sqrt(2 (E - V(0, 0.1))) > 0, so that H = E; the default E = 1/8 is the
energy at which Henon & Heiles found a mostly chaotic section.
References: M. Henon and C. Heiles, Astron. J. 69 (1964) 73-79; Hairer, Lubich & Wanner,
Geometric Numerical Integration, 2nd ed., I.3.
"""
import math

import numpy as np

from ..kernels.signatures import jit_gradient, jit_hamiltonian, jit_hessian, no_invariant_gradients, no_invariants
from ..errors import ParameterError
from .base import Problem, real_parameter

ESCAPE_ENERGY = 1.0 / 6.0
Q2_START = 0.1


@jit_hamiltonian
def H(y, params):
    q1, q2, p1, p2 = y[0], y[1], y[2], y[3]
    return 0.5 * (p1 * p1 + p2 * p2) + 0.5 * (q1 * q1 + q2 * q2) + q1 * q1 * q2 - q2 * q2 * q2 / 3.0


@jit_gradient
def grad_H(y, params, out):
    q1, q2 = y[0], y[1]
    out[0] = q1 + 2.0 * q1 * q2
    out[1] = q2 + q1 * q1 - q2 * q2
    out[2] = y[2]
    out[3] = y[3]


@jit_hessian
def hess_H(y, params, out):
    q1, q2 = y[0], y[1]
    out[:] = 0.0
    out[0, 0] = 1.0 + 2.0 * q2
    out[1, 1] = 1.0 - 2.0 * q2
    out[0, 1] = out[1, 0] = 2.0 * q1
    out[2, 2] = 1.0
    out[3, 3] = 1.0


def henon_heiles(energy: float = 0.125) -> Problem:
    """Henon-Heiles from q = (0, 0.1), p = (p1, 0) with p1 > 0 fixed by H = energy < 1/6."""
    energy = real_parameter("energy", energy)
    potential = 0.5 * Q2_START ** 2 - Q2_START ** 3 / 3.0
    if not (potential < energy < ESCAPE_ENERGY):
        raise ParameterError("energy", f"must lie in ({potential:.6g}, 1/6) (above the potential at the start "
                         f"q = (0, {Q2_START}), below the escape energy), got {energy}")
    y0 = np.array([0.0, Q2_START, math.sqrt(2.0 * (energy - potential)), 0.0])
    return Problem(
        name="henon_heiles", q_names=("q1", "q2"), p_names=("p1", "p2"),
        H=H, grad_H=grad_H, hess_H=hess_H, hessian_source="analytic",
        invariants=no_invariants, grad_invariants=no_invariant_gradients,
        invariant_names=(), y0=y0, params=np.zeros(0), parameters={"energy": energy},
        description="Henon-Heiles, H = |p|^2/2 + |q|^2/2 + q1^2 q2 - q2^3/3", hamiltonian_degree=3,
    )
