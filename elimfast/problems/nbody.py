"""Gravitational N-body problem in 3D, with total linear and angular momentum.

q = (x0, y0, z0, x1, ...) positions (3N), p = (px0, py0, pz0, px1, ...) momenta (3N),
params = [G, m_0, ..., m_{N-1}] (N is read from y.shape: 6N = len(y)).

H = sum_i |p_i|^2/(2 m_i) - G sum_{i<j} m_i m_j / |q_i - q_j|,
grad_{q_i} H = G sum_{j != i} m_i m_j (q_i - q_j)/|q_i - q_j|^3,  grad_{p_i} H = p_i/m_i.
Invariants (the potential depends on differences only and is rotation invariant):
  linear_momentum_{x,y,z} = sum_i p_i  (linear: every Runge-Kutta method keeps them, and
  ELIM/EHBVM cannot impose them: their phi_j, j >= 1, vanish and Gamma is singular, spec 3),
  angular_momentum_{x,y,z} = sum_i q_i x p_i  (quadratic; HBVM(k,s), k > s, does not keep
  them exactly). For nearly coplanar orbits (the default data) the three rows of Gamma
  are nearly parallel (all along the orbits' normal) and EHBVM imposing all three fails
  as singular at the first step: impose the component along the normal (here
  angular_momentum_z), or use LIM/GHBVM, whose Gram matrix is well conditioned.

Reference and default data: the outer solar system of Hairer, Lubich & Wanner, Geometric
Numerical Integration, 2nd ed., I.2.4: the Sun (mass including the inner planets),
Jupiter, Saturn, Uranus, Neptune, Pluto; units: solar masses, astronomical units, days,
G = 2.95912208286e-4; heliocentric positions and velocities (Sun at rest at the origin),
p_i = m_i v_i.
"""
import math

import numpy as np

from ..kernels.signatures import jit_gradient, jit_hamiltonian, jit_invariant_gradients, jit_invariants
from .base import Problem

# Hairer, Lubich & Wanner, GNI, I.2.4.
SOLAR_SYSTEM_G = 2.95912208286e-4
SOLAR_SYSTEM_BODIES = ("sun", "jupiter", "saturn", "uranus", "neptune", "pluto")
SOLAR_SYSTEM_MASSES = (1.00000597682, 0.000954786104043, 0.000285583733151,
                       0.0000437273164546, 0.0000517759138449, 1.0 / 1.3e8)
SOLAR_SYSTEM_POSITIONS = (
    (0.0, 0.0, 0.0),
    (-3.5023653, -3.8169847, -1.5507963),
    (9.0755314, -3.0458353, -1.6483708),
    (8.3101420, -16.2901086, -7.2521278),
    (11.4707666, -25.7294829, -10.8169456),
    (-15.5387357, -25.2225594, -3.1902382),
)
SOLAR_SYSTEM_VELOCITIES = (
    (0.0, 0.0, 0.0),
    (0.00565429, -0.00412490, -0.00190589),
    (0.00168318, 0.00483525, 0.00192462),
    (0.00354178, 0.00137102, 0.00055029),
    (0.00288930, 0.00114527, 0.00039677),
    (0.00276725, -0.00170702, -0.00136504),
)


@jit_hamiltonian
def H(y, params):
    G = params[0]
    n_bodies = y.shape[0] // 6
    offset = 3 * n_bodies
    kinetic = 0.0
    for i in range(n_bodies):
        p2 = 0.0
        for c in range(3):
            p2 += y[offset + 3 * i + c] ** 2
        kinetic += 0.5 * p2 / params[1 + i]
    potential = 0.0
    for i in range(n_bodies):
        for j in range(i + 1, n_bodies):
            d2 = 0.0
            for c in range(3):
                d2 += (y[3 * i + c] - y[3 * j + c]) ** 2
            potential += params[1 + i] * params[1 + j] / math.sqrt(d2)
    return kinetic - G * potential


@jit_gradient
def grad_H(y, params, out):
    G = params[0]
    n_bodies = y.shape[0] // 6
    offset = 3 * n_bodies
    for i in range(n_bodies):
        inv_m = 1.0 / params[1 + i]
        for c in range(3):
            out[3 * i + c] = 0.0
            out[offset + 3 * i + c] = y[offset + 3 * i + c] * inv_m
    for i in range(n_bodies):
        for j in range(i + 1, n_bodies):
            dx = y[3 * i] - y[3 * j]
            dy = y[3 * i + 1] - y[3 * j + 1]
            dz = y[3 * i + 2] - y[3 * j + 2]
            d2 = dx * dx + dy * dy + dz * dz
            w = G * params[1 + i] * params[1 + j] / (d2 * math.sqrt(d2))
            out[3 * i] += w * dx
            out[3 * i + 1] += w * dy
            out[3 * i + 2] += w * dz
            out[3 * j] -= w * dx
            out[3 * j + 1] -= w * dy
            out[3 * j + 2] -= w * dz


@jit_invariants
def invariants(y, params, out):
    n_bodies = y.shape[0] // 6
    offset = 3 * n_bodies
    for a in range(6):
        out[a] = 0.0
    for i in range(n_bodies):
        x, yy, z = y[3 * i], y[3 * i + 1], y[3 * i + 2]
        px, py, pz = y[offset + 3 * i], y[offset + 3 * i + 1], y[offset + 3 * i + 2]
        out[0] += px
        out[1] += py
        out[2] += pz
        out[3] += yy * pz - z * py
        out[4] += z * px - x * pz
        out[5] += x * py - yy * px


@jit_invariant_gradients
def grad_invariants(y, params, out):
    n_bodies = y.shape[0] // 6
    offset = 3 * n_bodies
    for a in range(6):
        for i in range(y.shape[0]):
            out[a, i] = 0.0
    for i in range(n_bodies):
        qi = 3 * i            # x_i, y_i, z_i at qi, qi+1, qi+2
        pj = offset + 3 * i   # px_i, py_i, pz_i at pj, pj+1, pj+2
        x, yy, z = y[qi], y[qi + 1], y[qi + 2]
        px, py, pz = y[pj], y[pj + 1], y[pj + 2]
        for c in range(3):
            out[c, pj + c] = 1.0   # linear momentum
        # L_x = y pz - z py
        out[3, qi + 1] = pz
        out[3, qi + 2] = -py
        out[3, pj + 1] = -z
        out[3, pj + 2] = yy
        # L_y = z px - x pz
        out[4, qi + 2] = px
        out[4, qi] = -pz
        out[4, pj + 2] = -x
        out[4, pj] = z
        # L_z = x py - y px
        out[5, qi] = py
        out[5, qi + 1] = -px
        out[5, pj] = -yy
        out[5, pj + 1] = x


INVARIANT_NAMES = ("linear_momentum_x", "linear_momentum_y", "linear_momentum_z",
                   "angular_momentum_x", "angular_momentum_y", "angular_momentum_z")


def _bodies_array(value, name, n_bodies=None):
    array = np.array(value, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{name} must be a list of [x, y, z] triples, one per body, got shape {array.shape}")
    if n_bodies is not None and array.shape[0] != n_bodies:
        raise ValueError(f"{name} has {array.shape[0]} bodies but masses has {n_bodies}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name} must be finite numbers")
    return array


def nbody(masses=None, positions=None, velocities=None, G: float = SOLAR_SYSTEM_G) -> Problem:
    """Gravitational N-body problem; defaults: the outer solar system of HLW I.2.4.

    masses (N,), positions (N, 3) and velocities (N, 3) default to the HLW data (each
    separately, so e.g. only the masses can be changed); momenta are m_i v_i.
    """
    default_data = masses is None and positions is None and velocities is None
    G = float(G)
    if not (math.isfinite(G) and G > 0.0):
        raise ValueError(f"G must be a positive finite number, got {G}")
    masses = np.array(SOLAR_SYSTEM_MASSES if masses is None else masses, dtype=np.float64)
    if masses.ndim != 1 or masses.size < 2:
        raise ValueError(f"masses must be a list of at least 2 numbers, got {masses.tolist()!r}")
    if not np.all(np.isfinite(masses) & (masses > 0.0)):
        raise ValueError(f"masses must be positive finite numbers, got {masses.tolist()!r}")
    n_bodies = masses.size
    q = _bodies_array(SOLAR_SYSTEM_POSITIONS if positions is None else positions, "positions", n_bodies)
    v = _bodies_array(SOLAR_SYSTEM_VELOCITIES if velocities is None else velocities, "velocities", n_bodies)
    for i in range(n_bodies):
        for j in range(i + 1, n_bodies):
            if np.array_equal(q[i], q[j]):
                raise ValueError(f"bodies {i} and {j} start at the same position {q[i].tolist()}: "
                                 "the potential is singular there")
    p = masses[:, None] * v
    q_names = tuple(f"{c}{i}" for i in range(n_bodies) for c in "xyz")
    p_names = tuple(f"p{c}{i}" for i in range(n_bodies) for c in "xyz")
    return Problem(
        name="nbody", q_names=q_names, p_names=p_names,
        H=H, grad_H=grad_H, invariants=invariants, grad_invariants=grad_invariants,
        invariant_names=INVARIANT_NAMES,
        y0=np.concatenate((q.ravel(), p.ravel())), params=np.concatenate(([G], masses)),
        parameters={"G": G, "masses": masses.tolist(), "positions": q.tolist(), "velocities": v.tolist()},
        description=f"gravitational {n_bodies}-body problem in 3D"
                    + (" (outer solar system, HLW I.2.4)" if default_data else ""),
    )
