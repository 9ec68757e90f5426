"""A 7-atom Lennard-Jones cluster in the plane (a hexagon and its centre; epsilon = sigma = 1, unit
masses), from a user trial: imposing L_z with EHBVM, its 1 x 1 Gamma passes through zero every few
time units (docs/solver.md#when-gamma-passes-through-zero)."""
import math
import numpy as np

N = 7
NAME = "lj7_2d"
Q_NAMES = tuple(f"{c}{i}" for i in range(N) for c in ("x", "y"))
P_NAMES = tuple(f"p{c}{i}" for i in range(N) for c in ("x", "y"))
PARAMETERS = {"eps": 1.0, "sigma": 1.0}
INVARIANT_NAMES = ("Px", "Py", "Lz")
_a = 2.0 ** (1.0 / 6.0)
_q = [0.0, 0.0]
for k in range(6):
    _q += [_a * math.cos(k * math.pi / 3), _a * math.sin(k * math.pi / 3)]
# small random-ish momenta with zero total momentum, nonzero angular momentum
_p = []
for i in range(N):
    _p += [0.05 * math.sin(1.3 * i + 0.2), 0.05 * math.cos(2.1 * i + 0.5)]
_mx = sum(_p[0::2]) / N
_my = sum(_p[1::2]) / N
for i in range(N):
    _p[2 * i] -= _mx
    _p[2 * i + 1] -= _my
Y0 = _q + _p


def H(y, params):
    eps = params[0]
    sig = params[1]
    n = 7
    kin = 0.0
    for i in range(2 * n, 4 * n):
        kin += 0.5 * y[i] * y[i]
    pot = 0.0
    for i in range(n):
        for j in range(i + 1, n):
            dx = y[2 * i] - y[2 * j]
            dy = y[2 * i + 1] - y[2 * j + 1]
            s2 = sig * sig / (dx * dx + dy * dy)
            s6 = s2 * s2 * s2
            pot += 4.0 * eps * (s6 * s6 - s6)
    return kin + pot


def grad_H(y, params, out):
    eps = params[0]
    sig = params[1]
    n = 7
    for i in range(2 * n):
        out[i] = 0.0
    for i in range(2 * n, 4 * n):
        out[i] = y[i]
    for i in range(n):
        for j in range(i + 1, n):
            dx = y[2 * i] - y[2 * j]
            dy = y[2 * i + 1] - y[2 * j + 1]
            r2 = dx * dx + dy * dy
            s2 = sig * sig / r2
            s6 = s2 * s2 * s2
            # dV/dr * 1/r = 4 eps (-12 s12 + 6 s6)/r^2
            f = 4.0 * eps * (-12.0 * s6 * s6 + 6.0 * s6) / r2
            out[2 * i] += f * dx
            out[2 * i + 1] += f * dy
            out[2 * j] -= f * dx
            out[2 * j + 1] -= f * dy


def invariants(y, params, out):
    n = 7
    px = 0.0
    py = 0.0
    lz = 0.0
    for i in range(n):
        px += y[2 * n + 2 * i]
        py += y[2 * n + 2 * i + 1]
        lz += y[2 * i] * y[2 * n + 2 * i + 1] - y[2 * i + 1] * y[2 * n + 2 * i]
    out[0] = px
    out[1] = py
    out[2] = lz


def grad_invariants(y, params, out):
    n = 7
    for r in range(3):
        for c in range(4 * n):
            out[r, c] = 0.0
    for i in range(n):
        out[0, 2 * n + 2 * i] = 1.0
        out[1, 2 * n + 2 * i + 1] = 1.0
        out[2, 2 * i] = y[2 * n + 2 * i + 1]
        out[2, 2 * i + 1] = -y[2 * n + 2 * i]
        out[2, 2 * n + 2 * i] = -y[2 * i + 1]
        out[2, 2 * n + 2 * i + 1] = y[2 * i]
