"""Kepler, whose gradient raises once q1 < -1 (the apocentre side of the e = 0.6 orbit, x = -1.6)."""
import math

NAME = "raise_late"
Q_NAMES = ("q1", "q2")
P_NAMES = ("p1", "p2")
PARAMETERS = {"mu": 1.0}
Y0 = [0.4, 0.0, 0.0, 2.0]


def H(y, params):
    return 0.5 * (y[2] * y[2] + y[3] * y[3]) - params[0] / math.sqrt(y[0] * y[0] + y[1] * y[1])


def grad_H(y, params, out):
    if y[0] < -1.0:
        raise ValueError("negative q1")
    r2 = y[0] * y[0] + y[1] * y[1]
    mu_r3 = params[0] / (r2 * math.sqrt(r2))
    out[0] = y[0] * mu_r3
    out[1] = y[1] * mu_r3
    out[2] = y[2]
    out[3] = y[3]
