"""Regenerate hard_steps.npz: states from which one step of EHBVM(12,3) is hard (docs/solver.md).

The README's run 100x longer (Kepler e = 0.6, EHBVM(12,3) imposing angular_momentum and
lrl_y, h = 0.1) aborted at step 836104, the step from t = 83610.3, whose midpoint is
2.2e-7 time units from a pericentre: Gamma is nearly singular there. This script runs
the same orbit to that time and stores the state there and at the two steps before it.

With --exact it also stores each state's step solved in 40-digit arithmetic (mpmath, the
fixed point to 1e-36), whole (exact_whole) and as two half steps (exact_halves): near that
pericentre the solution of the step is so sensitive to rounding (cond(Gamma) ~ 1e7) that the
NumPy reference in doubles (tests/reference.py) is itself 1.1e-13 from it, more than the
kernel (tests/test_step_engine.py).

    .venv/bin/python tests/data/make_hard_steps.py [--exact]   (--exact alone: keeps the states)

With --pericentre it writes pericentre_steps.npz instead: steps of EHBVM(8,4) through the pericentre
of Kepler e = 0.99, where cond(Gamma) reaches 1e6-1e9 from Gamma's scaling alone, and their 40-digit
solutions (tests/test_step_engine.py: they are taken whole, and exactly).
"""
import functools
import math
import sys
from pathlib import Path

import mpmath as mp
import numpy as np

import elimfast
from elimfast.methods import ehbvm
from elimfast.problems import kepler

STEP = 836103   # the state before step 836104 (1-based), t = 83610.3
OUT = Path(__file__).with_name("hard_steps.npz")
PERICENTRE_OUT = Path(__file__).with_name("pericentre_steps.npz")

mp.mp.dps = 40
nu = 2


@functools.lru_cache(maxsize=None)
def tables(k, s):
    """HBVM(k, s)'s tables in 40 digits: the Gauss-Legendre nodes c and weights b, P_j(c_l) and
    int_0^c_l P_j (j < s)."""
    roots = sorted(mp.polyroots(mp.taylor(lambda x: mp.legendre(k, x), 0, k)[::-1], maxsteps=500, extraprec=800))
    c = [(1 + x) / 2 for x in roots]
    b = [1 / ((1 - x ** 2) * mp.diff(lambda t: mp.legendre(k, t), x) ** 2) for x in roots]
    Pk = [[P(j, c[l]) for j in range(k)] for l in range(k)]
    Ik = [[mp.quad(lambda t, j=j: P(j, t), [0, c[l]]) for j in range(s)] for l in range(k)]
    return c, b, Pk, Ik


def P(j, x):
    return mp.sqrt(2 * j + 1) * mp.legendre(j, 2 * x - 1)


def grad_H(y):
    q1, q2, p1, p2 = y
    r2 = q1 * q1 + q2 * q2
    r3 = r2 * mp.sqrt(r2)
    return [q1 / r3, q2 / r3, p1, p2]


def grad_L(y):
    """The gradients of angular_momentum and lrl_y (elimfast.problems.kepler)."""
    q1, q2, p1, p2 = y
    rr = mp.sqrt(q1 * q1 + q2 * q2)
    r3 = rr ** 3
    L = q1 * p2 - q2 * p1
    return [[p2, -p1, -q2, q1], [-p1 * p2 + q1 * q2 / r3, p1 * p1 - 1 / rr + q2 * q2 / r3, -L + p1 * q2, -p1 * q1]]


def J(v):
    return [v[2], v[3], -v[0], -v[1]]


def exact_step(y0, h, k=12, s=3, iterations=5000):
    """One step of EHBVM(k,s) imposing L and A_y (stable right-hand side, docs/methods.md#elim) in
    40-digit arithmetic: the fixed point, alpha = 0 for two sweeps, to increments below 1e-36."""
    c, b, Pk, Ik = tables(k, s)
    y0 = [mp.mpf(float(v)) for v in y0]
    h = mp.mpf(float(h))
    coef = [[mp.mpf(0)] * 4 for _ in range(s)]
    alpha = [mp.mpf(0)] * nu
    for iteration in range(iterations):
        U = [[y0[i] + h * sum(Ik[l][j] * coef[j][i] for j in range(s)) for i in range(4)] for l in range(k)]
        f = [J(grad_H(u)) for u in U]
        gam = [[sum(b[l] * Pk[l][j] * f[l][i] for l in range(k)) for i in range(4)] for j in range(k)]
        gL = [grad_L(u) for u in U]
        phi = [[[sum(b[l] * Pk[l][j] * gL[l][a][i] for l in range(k)) for i in range(4)] for a in range(nu)]
               for j in range(k)]
        if iteration >= 2:
            G, rhs = mp.matrix(nu, nu), mp.matrix(nu, 1)
            for col in range(nu):
                j = s - nu + col
                for a in range(nu):
                    G[a, col] = h ** (2 * (nu - 1 - col)) * sum(phi[j][a][i] * gam[j][i] for i in range(4))
            for a in range(nu):
                rhs[a] = -sum(sum(phi[j][a][i] * gam[j][i] for i in range(4)) for j in range(s, k))
            solution = mp.lu_solve(G, rhs)
            alpha = [solution[a] for a in range(nu)]
        new = []
        for j in range(s):
            eta = 1 - h ** (2 * (nu - 1 - (j - s + nu))) * alpha[j - s + nu] if j >= s - nu else 1
            new.append([eta * gam[j][i] for i in range(4)])
        change = max(abs(new[j][i] - coef[j][i]) for j in range(s) for i in range(4))
        coef = new
        if iteration > 5 and change < mp.mpf(10) ** -36:
            return np.array([float(y0[i] + h * coef[0][i]) for i in range(4)])
    raise RuntimeError("the 40-digit fixed point did not converge")


def pericentre_steps():
    """Kepler e = 0.99, EHBVM(8,4) imposing L and A_y on time-reversible steps (epsilon = 0.1), one
    period: the states and steps of the first three and the last three steps, the passages of the
    pericentre, where cond(Gamma) is 1e6 to 1e9 (docs/solver.md), and each step solved in 40 digits."""
    run = elimfast.integrate(kepler(0.99), ehbvm(8, 4), t_end=2 * math.pi, conserve=["angular_momentum", "lrl_y"],
                             step_control="time_scale", epsilon=0.1, store_every=1)
    picks = [0, 1, 2, len(run.t) - 4, len(run.t) - 3, len(run.t) - 2]
    states, steps = run.y[picks], (run.t[1:] - run.t[:-1])[picks]
    return {"states": states, "steps": steps,
            "exact_whole": np.array([exact_step(y0, h, k=8, s=4) for y0, h in zip(states, steps)]),
            "source": f"elimfast {elimfast.__version__}, Kepler e = 0.99, time_scale epsilon 0.1, steps {picks}"}


def main():
    if "--pericentre" in sys.argv:
        np.savez(PERICENTRE_OUT, **pericentre_steps())
        print(f"stored {PERICENTRE_OUT}")
        return
    if "--exact" in sys.argv and OUT.exists():
        stored = dict(np.load(OUT))
    else:
        result = elimfast.integrate(kepler(0.6), ehbvm(12, 3), 0.1, n_steps=STEP,
                                    conserve=["angular_momentum", "lrl_y"], store_every=1)
        stored = {"states": result.y[STEP - 2:STEP + 1], "times": result.t[STEP - 2:STEP + 1],
                  "source": f"elimfast {elimfast.__version__}, steps {STEP - 2}..{STEP} of the README's run x100"}
    if "--exact" in sys.argv:
        stored["exact_whole"] = np.array([exact_step(y0, 0.1) for y0 in stored["states"]])
        stored["exact_halves"] = np.array([exact_step(exact_step(y0, 0.05), 0.05) for y0 in stored["states"]])
    np.savez(OUT, **stored)
    print(f"stored {len(stored['states'])} states at t = {stored['times']}")


if __name__ == "__main__":
    main()
