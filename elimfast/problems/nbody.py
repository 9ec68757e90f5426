"""Gravitational N-body problem in 3D, with total linear and angular momentum.

q = (x_0, y_0, z_0, x_1, ...) positions (3N), p = (px_0, py_0, pz_0, px_1, ...) momenta (3N),
params = [G, m_0, ..., m_{N-1}] (N is read from y.shape: 6N = len(y)). Coordinate names:
``<body>_x``, ``<body>_y``, ``<body>_z`` and ``<body>_px``, ``<body>_py``, ``<body>_pz``, with the
bodies named sun, jupiter, saturn, uranus, neptune, pluto for the default data and body0,
body1, ... otherwise (valid identifiers: usable in a config's ``initial:``).

H = sum_i |p_i|^2/(2 m_i) - G sum_{i<j} m_i m_j / |q_i - q_j|,
grad_{q_i} H = G sum_{j != i} m_i m_j (q_i - q_j)/|q_i - q_j|^3,  grad_{p_i} H = p_i/m_i.
Hessian: d^2 H/dp_i^2 = I/m_i; each pair adds B_ij = G m_i m_j (I/d^3 - 3 d d^T/d^5),
d = q_i - q_j, to the (q_i, q_i) and (q_j, q_j) blocks and -B_ij to (q_i, q_j) and (q_j, q_i).
Invariants (the potential depends on differences only and is rotation invariant):
  linear_momentum_{x,y,z} = sum_i p_i  (linear: every Runge-Kutta method keeps them, and
  ELIM/EHBVM cannot impose them: their phi_j, j >= 1, vanish and Gamma is singular, docs/methods.md#elim),
  angular_momentum_{x,y,z} = sum_i q_i x p_i  (quadratic; HBVM(k,s), k > s, does not keep
  them exactly). For nearly coplanar orbits (the default data) the three rows of Gamma
  are nearly parallel (all along the orbits' normal) and EHBVM imposing all three fails
  as singular at the first step: impose the component along the normal (here
  angular_momentum_z), or use LIM/GHBVM, whose Gram matrix is well conditioned.

Reference and default data: the outer solar system of Hairer, Lubich & Wanner, Geometric
Numerical Integration, 2nd ed., I.2.4: the Sun (mass including the inner planets),
Jupiter, Saturn, Uranus, Neptune, Pluto; units: astronomical units, days, solar masses
(``Problem.units``), G = 2.95912208286e-4. HLW give heliocentric positions and velocities
(the Sun at rest at the origin); that frame moves: its total momentum is that of the
planets, and the centre of mass drifts by |P| t / M (480 AU over 7e7 days). The data are
kept as HLW print them, and ``frame="barycentric"`` (the default) moves any given data to
the barycentre, as astronomers expect:
  M = sum_i m_i,  q_cm = sum_i m_i q_i / M,  v_cm = sum_i m_i v_i / M,
  q_i <- q_i - q_cm,  p_i = m_i (v_i - v_cm),
so sum_i p_i = 0 and sum_i m_i q_i = 0 up to round-off (~eps sum_i |p_i|, eps sum_i m_i |q_i|).
The relative motion, hence every orbit, is unchanged; the angular momentum is now the one
about the barycentre. ``frame="given"`` keeps the data as given (p_i = m_i v_i).
"""
import math

import numpy as np
from numba import njit

from ..kernels.signatures import (jit_gradient, jit_hamiltonian, jit_hessian, jit_invariant_gradients,
                                  jit_invariants)
from ..errors import ParameterError
from .base import Problem, real_parameter

# Hairer, Lubich & Wanner, GNI, I.2.4.
SOLAR_SYSTEM_G = 2.95912208286e-4
SOLAR_SYSTEM_UNITS = {"length": "AU", "time": "day", "mass": "solar mass"}   # those of SOLAR_SYSTEM_G
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


@njit(cache=True, inline="always")
def _pair(y, params, G, i, j):
    """(d_x, d_y, d_z, |d|^2, G m_i m_j / |d|^3) for d = q_i - q_j."""
    dx = y[3 * i] - y[3 * j]
    dy = y[3 * i + 1] - y[3 * j + 1]
    dz = y[3 * i + 2] - y[3 * j + 2]
    d2 = dx * dx + dy * dy + dz * dz
    return dx, dy, dz, d2, G * params[1 + i] * params[1 + j] / (d2 * math.sqrt(d2))


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
            dx, dy, dz, d2, w = _pair(y, params, G, i, j)
            out[3 * i] += w * dx
            out[3 * i + 1] += w * dy
            out[3 * i + 2] += w * dz
            out[3 * j] -= w * dx
            out[3 * j + 1] -= w * dy
            out[3 * j + 2] -= w * dz


@jit_hessian
def hess_H(y, params, out):
    G = params[0]
    n_bodies = y.shape[0] // 6
    offset = 3 * n_bodies
    out[:] = 0.0
    for i in range(n_bodies):
        inv_m = 1.0 / params[1 + i]
        for c in range(3):
            out[offset + 3 * i + c, offset + 3 * i + c] = inv_m
    for i in range(n_bodies):
        for j in range(i + 1, n_bodies):
            _, _, _, d2, w = _pair(y, params, G, i, j)   # w = G m_i m_j / d^3
            w3 = 3.0 * w / d2
            for a in range(3):
                da = y[3 * i + a] - y[3 * j + a]
                for b in range(3):
                    # B_ij[a, b], with d_a d_b formed first: B_ij[b, a] is then the same double
                    block = -w3 * (da * (y[3 * i + b] - y[3 * j + b]))
                    if a == b:
                        block += w
                    out[3 * i + a, 3 * i + b] += block
                    out[3 * j + a, 3 * j + b] += block
                    out[3 * i + a, 3 * j + b] -= block
                    out[3 * j + a, 3 * i + b] -= block


@jit_invariants
def time_scale(y, params, out):
    """sigma = min over pairs of |q_i - q_j|^(3/2) / sqrt(G (m_i + m_j)), the shortest local
    orbital time scale, and its gradient (that of the pair attaining the minimum;
    docs/adaptive.md, the time-reversible controller)."""
    G = params[0]
    n_bodies = y.shape[0] // 6
    best = np.inf
    best_i, best_j = 0, 1
    for i in range(n_bodies):
        for j in range(i + 1, n_bodies):
            dx, dy, dz = y[3 * i] - y[3 * j], y[3 * i + 1] - y[3 * j + 1], y[3 * i + 2] - y[3 * j + 2]
            d = math.sqrt(dx * dx + dy * dy + dz * dz)
            sigma = d * math.sqrt(d / (G * (params[1 + i] + params[1 + j])))
            if sigma < best:
                best, best_i, best_j = sigma, i, j
    for p in range(y.shape[0] + 1):
        out[p] = 0.0
    out[0] = best
    d2 = 0.0
    for c in range(3):
        diff = y[3 * best_i + c] - y[3 * best_j + c]
        d2 += diff * diff
    factor = 1.5 * best / d2
    for c in range(3):
        diff = y[3 * best_i + c] - y[3 * best_j + c]
        out[1 + 3 * best_i + c] = factor * diff
        out[1 + 3 * best_j + c] = -factor * diff


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
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        # a ragged list ([[1, 3, 0], [1, -1]]) or a non-number: NumPy's own text reached the user (a user trial)
        rows = value if isinstance(value, (list, tuple)) else [value]
        bad = next((i for i, row in enumerate(rows) if not (isinstance(row, (list, tuple)) and len(row) == 3)), None)
        which = f" (body {bad}: {rows[bad]!r})" if bad is not None else ""
        raise ParameterError(name, f"must be a list of [x, y, z] triples of numbers, one per body{which}") from None
    if array.ndim != 2 or array.shape[1] != 3:
        raise ParameterError(name, f"must be a list of [x, y, z] triples, one per body, got shape {array.shape}")
    if n_bodies is not None and array.shape[0] != n_bodies:
        raise ParameterError(name, f"has {array.shape[0]} bodies but masses has {n_bodies}")
    if not np.all(np.isfinite(array)):
        raise ParameterError(name, "must be finite numbers")
    return array


FRAMES = ("barycentric", "given")


def barycentric(masses: np.ndarray, positions: np.ndarray, velocities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities relative to the centre of mass and its velocity (module docstring)."""
    total = masses.sum()
    centre = (masses[:, None] * positions).sum(axis=0) / total
    drift = (masses[:, None] * velocities).sum(axis=0) / total
    return positions - centre, velocities - drift


def nbody(masses=None, positions=None, velocities=None, G: float = SOLAR_SYSTEM_G,
          frame: str = "barycentric") -> Problem:
    """Gravitational N-body problem; defaults: the outer solar system of HLW I.2.4.

    masses (N,), positions (N, 3) and velocities (N, 3) default to the HLW data (each
    separately, so e.g. only the masses can be changed); frame "barycentric" moves them
    to the centre of mass (momenta m_i (v_i - v_cm)), "given" keeps them (momenta m_i v_i).
    The bodies are named after the planets while the positions are HLW's. Units are
    stated (AU, day, solar mass) when G is HLW's, whose value fixes them.
    """
    default_data = masses is None and positions is None and velocities is None
    G = real_parameter("G", G)
    if not (math.isfinite(G) and G > 0.0):
        raise ParameterError("G", f"must be a positive finite number, got {G}")
    if frame not in FRAMES:
        raise ParameterError("frame", f"must be 'barycentric' or 'given', got {frame!r}")
    try:
        masses = np.array(SOLAR_SYSTEM_MASSES if masses is None else masses, dtype=np.float64)
    except (TypeError, ValueError):
        raise ParameterError("masses", f"must be a list of at least 2 numbers, got {masses!r}") from None
    if masses.ndim != 1 or masses.size < 2:
        raise ParameterError("masses", f"must be a list of at least 2 numbers, got {masses.tolist()!r}")
    if not np.all(np.isfinite(masses) & (masses > 0.0)):
        raise ParameterError("masses", f"must be positive finite numbers, got {masses.tolist()!r}")
    n_bodies = masses.size
    for name, given, default in (("positions", positions, SOLAR_SYSTEM_POSITIONS),
                                 ("velocities", velocities, SOLAR_SYSTEM_VELOCITIES)):
        if given is None and n_bodies != len(default):
            # (it was blamed on positions, which the user had not given: "positions: has 6 bodies but masses has 2")
            raise ParameterError("masses", f"has {n_bodies} bodies, but {name} is not given and its default (the "
                                           f"outer solar system) has {len(default)}; give positions and velocities "
                                           f"of {n_bodies} bodies too")
    q = _bodies_array(SOLAR_SYSTEM_POSITIONS if positions is None else positions, "positions", n_bodies)
    # By value, not by "positions is None": a resolved config passes HLW's positions explicitly.
    hlw_positions = q.shape == (6, 3) and np.array_equal(q, SOLAR_SYSTEM_POSITIONS)
    bodies = SOLAR_SYSTEM_BODIES if hlw_positions else tuple(f"body{i}" for i in range(n_bodies))
    v = _bodies_array(SOLAR_SYSTEM_VELOCITIES if velocities is None else velocities, "velocities", n_bodies)
    for i in range(n_bodies):
        for j in range(i + 1, n_bodies):
            if np.array_equal(q[i], q[j]):
                raise ParameterError("positions", f"of bodies {i} and {j} are the same, {q[i].tolist()}: "
                                 "the potential is singular there")
    q_start, v_start = barycentric(masses, q, v) if frame == "barycentric" else (q, v)
    p = masses[:, None] * v_start
    q_names = tuple(f"{body}_{c}" for body in bodies for c in "xyz")
    p_names = tuple(f"{body}_p{c}" for body in bodies for c in "xyz")
    return Problem(
        name="nbody", q_names=q_names, p_names=p_names,
        H=H, grad_H=grad_H, hess_H=hess_H, hessian_source="analytic",
        invariants=invariants, grad_invariants=grad_invariants, invariant_names=INVARIANT_NAMES,
        y0=np.concatenate((q_start.ravel(), p.ravel())), params=np.concatenate(([G], masses)),
        parameters={"G": G, "masses": masses.tolist(), "positions": q.tolist(), "velocities": v.tolist(),
                    "frame": frame},
        units=dict(SOLAR_SYSTEM_UNITS) if G == SOLAR_SYSTEM_G else {},
        description=f"gravitational {n_bodies}-body problem in 3D, {frame} frame"
                    + (" (outer solar system, HLW I.2.4)" if default_data else ""),
        time_scale=time_scale,
    )
