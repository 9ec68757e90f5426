"""Planar Kepler problem as a ``python:`` problem file (see elimfast/problems/user_file.py).

H = |p|^2/2 - mu/|q|, angular momentum L = q1 p2 - q2 p1 and the Laplace-Runge-Lenz
vector A = (p2 L - mu q1/|q|, -p1 L - mu q2/|q|) (docs/methods.md#typos-in-the-paper, sign restored).
With mu = 1 and the default Y0 this is the built-in ``kepler`` with eccentricity 0.6.
"""
import math

NAME = "kepler_python"
Q_NAMES = ("q1", "q2")
P_NAMES = ("p1", "p2")
PARAMETERS = {"mu": 1.0}                      # read as params[0]
Y0 = [0.4, 0.0, 0.0, 2.0]                     # q = (1 - e, 0), p = (0, sqrt((1 + e)/(1 - e))), e = 0.6
INVARIANT_NAMES = ("angular_momentum", "lrl_x", "lrl_y")


def H(y, params):
    mu = params[0]
    return 0.5 * (y[2] * y[2] + y[3] * y[3]) - mu / math.sqrt(y[0] * y[0] + y[1] * y[1])


def grad_H(y, params, out):
    mu = params[0]
    r2 = y[0] * y[0] + y[1] * y[1]
    mu_r3 = mu / (r2 * math.sqrt(r2))
    out[0] = y[0] * mu_r3
    out[1] = y[1] * mu_r3
    out[2] = y[2]
    out[3] = y[3]


def invariants(y, params, out):
    q1, q2, p1, p2 = y[0], y[1], y[2], y[3]
    mu_r = params[0] / math.sqrt(q1 * q1 + q2 * q2)
    L = q1 * p2 - q2 * p1
    out[0] = L
    out[1] = p2 * L - q1 * mu_r
    out[2] = -p1 * L - q2 * mu_r


def grad_invariants(y, params, out):
    q1, q2, p1, p2 = y[0], y[1], y[2], y[3]
    mu = params[0]
    r2 = q1 * q1 + q2 * q2
    mu_r = mu / math.sqrt(r2)
    mu_r3 = mu_r / r2
    L = q1 * p2 - q2 * p1
    out[0, 0] = p2                      # grad L = (p2, -p1, -q2, q1)
    out[0, 1] = -p1
    out[0, 2] = -q2
    out[0, 3] = q1
    out[1, 0] = p2 * p2 - mu_r + q1 * q1 * mu_r3   # A_x = p2 L - mu q1/r
    out[1, 1] = -p2 * p1 + q1 * q2 * mu_r3
    out[1, 2] = -p2 * q2
    out[1, 3] = L + p2 * q1
    out[2, 0] = -p1 * p2 + q1 * q2 * mu_r3         # A_y = -p1 L - mu q2/r
    out[2, 1] = p1 * p1 - mu_r + q2 * q2 * mu_r3
    out[2, 2] = -L + p1 * q2
    out[2, 3] = -p1 * q1
