"""Lennard-Jones trimer in the plane (epsilon = sigma = 1, unit masses)."""
import math

NAME = "lj_trimer"
Q_NAMES = ("x1", "y1", "x2", "y2", "x3", "y3")
P_NAMES = ("px1", "py1", "px2", "py2", "px3", "py3")
PARAMETERS = {"eps": 1.0}
_a = 2.0 ** (1.0 / 6.0)
Y0 = [0.0, 0.0, _a * 1.02, 0.0, 0.5 * _a, 0.866 * _a,
      0.1, -0.05, -0.02, 0.08, -0.08, -0.03]
INVARIANT_NAMES = ("angular_momentum", "momentum_x", "momentum_y")


def H(y, params):
    e = params[0]
    T = 0.0
    for i in range(6, 12):
        T += 0.5 * y[i] * y[i]
    V = 0.0
    for i in range(3):
        for j in range(i + 1, 3):
            dx = y[2 * i] - y[2 * j]
            dy = y[2 * i + 1] - y[2 * j + 1]
            r2 = dx * dx + dy * dy
            s6 = 1.0 / (r2 * r2 * r2)
            V += 4.0 * e * (s6 * s6 - s6)
    return T + V


def grad_H(y, params, out):
    e = params[0]
    for i in range(6):
        out[i] = 0.0
    for i in range(6, 12):
        out[i] = y[i]
    for i in range(3):
        for j in range(i + 1, 3):
            dx = y[2 * i] - y[2 * j]
            dy = y[2 * i + 1] - y[2 * j + 1]
            r2 = dx * dx + dy * dy
            s6 = 1.0 / (r2 * r2 * r2)
            # dV/dr / r = 4 e (-12 s12 + 6 s6) / r2
            f = 4.0 * e * (-12.0 * s6 * s6 + 6.0 * s6) / r2
            out[2 * i] += f * dx
            out[2 * i + 1] += f * dy
            out[2 * j] -= f * dx
            out[2 * j + 1] -= f * dy


def invariants(y, params, out):
    L = 0.0
    px = 0.0
    py = 0.0
    for i in range(3):
        L += y[2 * i] * y[6 + 2 * i + 1] - y[2 * i + 1] * y[6 + 2 * i]
        px += y[6 + 2 * i]
        py += y[6 + 2 * i + 1]
    out[0] = L
    out[1] = px
    out[2] = py


def grad_invariants(y, params, out):
    for k in range(3):
        for i in range(12):
            out[k, i] = 0.0
    for i in range(3):
        out[0, 2 * i] = y[6 + 2 * i + 1]
        out[0, 2 * i + 1] = -y[6 + 2 * i]
        out[0, 6 + 2 * i] = -y[2 * i + 1]
        out[0, 6 + 2 * i + 1] = y[2 * i]
        out[1, 6 + 2 * i] = 1.0
        out[2, 6 + 2 * i + 1] = 1.0


def hess_H(y, params, out):
    e = params[0]
    for i in range(12):
        for j in range(12):
            out[i, j] = 0.0
    for i in range(6, 12):
        out[i, i] = 1.0
    for i in range(3):
        for j in range(i + 1, 3):
            d0 = y[2 * i] - y[2 * j]
            d1 = y[2 * i + 1] - y[2 * j + 1]
            r2 = d0 * d0 + d1 * d1
            s6 = 1.0 / (r2 * r2 * r2)
            f = 4.0 * e * (-12.0 * s6 * s6 + 6.0 * s6) / r2
            g = 4.0 * e * (168.0 * s6 * s6 - 48.0 * s6) / (r2 * r2)
            d = (d0, d1)
            for a in range(2):
                for b in range(2):
                    v = g * d[a] * d[b] + (f if a == b else 0.0)
                    out[2 * i + a, 2 * i + b] += v
                    out[2 * j + a, 2 * j + b] += v
                    out[2 * i + a, 2 * j + b] -= v
                    out[2 * j + a, 2 * i + b] -= v
