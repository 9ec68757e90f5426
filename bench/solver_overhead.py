"""Where a small problem's time goes in one step's solve (issue 12, item 1; README "Kernel").

    .venv/bin/python bench/solver_overhead.py

GAUSS(4) on Kepler at h = pi/120, the fixed point from a cold start: the ELIM map called
alone from a small loop, against whole solves (kernels/solver.py) at two tolerances.
Measured (this machine, shared), before and after the kernels' internal functions lost
their reference counting (kernels/codes.py): the map alone 61-68 ns per call; a solve of
6 iterations (tol 1e-8) 2.7 -> 1.7 us, of 11 iterations (tol eps) 4.0 -> 2.4 us. What is
left is about 140 ns per iteration and 0.8 us per solve beyond the map: the stopping
rule's bookkeeping and the call itself (the Tables and Workspace structs, ~60 arrays,
passed by value). The next thing to cut for small problems at small steps.
"""
import math
import time

import numpy as np
from numba import njit

from elimfast.kernels import codes
from elimfast.kernels.maps import elim_map
from elimfast.kernels.solver import solve
from elimfast.kernels.workspace import Settings, Tables, borrow_tables, borrow_workspace, keep_alive, make_workspace
from elimfast.methods import gauss
from elimfast.problems import kepler

PROBLEM, METHOD = kepler(0.6), gauss(4)
K, R, S = METHOD.k, METHOD.r, METHOD.s
H = math.pi / 120


@njit
def maps_alone(grad_H, grad_invariants, params, y, h, tables0, n):
    owners = make_workspace(4, K, R, S, 0, codes.FAMILY_ELIM, 3, 0, tables0.newton_values.shape[0])
    work, tables = borrow_workspace(owners), borrow_tables(tables0)
    coef, alpha, conserve = np.zeros((S, 4)), np.zeros(0), np.zeros(0, dtype=np.int64)
    acc = 0.0
    for i in range(n):
        elim_map(grad_H, grad_invariants, params, y, h, coef, alpha, i < 0, n > 0, tables, conserve, work)
        for j in range(S):
            for q in range(4):
                coef[j, q] = work.new_coef[j, q]
        acc += coef[0, 0]
    keep_alive(owners)
    return acc


@njit
def solves(grad_H, grad_invariants, params, y, h, tables0, settings, n):
    owners = make_workspace(4, K, R, S, 0, codes.FAMILY_ELIM, 3, 0, tables0.newton_values.shape[0])
    work, tables = borrow_workspace(owners), borrow_tables(tables0)
    coef, alpha, conserve = np.zeros((S, 4)), np.zeros(0), np.zeros(0, dtype=np.int64)
    total = 0
    for _ in range(n):
        coef[:, :] = 0.0
        _, used = solve(grad_H, grad_invariants, params, settings, tables, conserve, work, y, h, coef, alpha, True)
        total += used
    keep_alive(owners)
    return total


def main():
    m, p = METHOD, PROBLEM
    tables = Tables(m.projection, m.Is, m.projection_hat, m.Is_hat, m.X, m.abs_projection_hat, m.predictor_nodes,
                    m.predictor_basis, m.newton_values, m.newton_vectors, m.newton_inverse, m.newton_weights,
                    m.Is_low, m.Is_hat_low)
    y = p.y0.copy()
    n = 200_000
    maps_alone(p.grad_H, p.grad_invariants, p.params, y, H, tables, 10)
    times = []
    for _ in range(5):
        start = time.perf_counter()
        maps_alone(p.grad_H, p.grad_invariants, p.params, y, H, tables, n)
        times.append(time.perf_counter() - start)
    print(f"map alone: {np.median(times) / n * 1e9:.0f} ns per call (median of 5)")
    for tol in (1e-8, 2.0 ** -52):
        settings = Settings(codes.FAMILY_ELIM, codes.SOLVER_FIXED_POINT, 1, 1, 0, tol, 100, 4)
        solves(p.grad_H, p.grad_invariants, p.params, y, H, tables, settings, 10)
        times, iterations = [], 0
        for _ in range(5):
            start = time.perf_counter()
            iterations = solves(p.grad_H, p.grad_invariants, p.params, y, H, tables, settings, n // 10)
            times.append(time.perf_counter() - start)
        per_solve = np.median(times) / (n // 10)
        print(f"solve, tol {tol:.3g}: {per_solve * 1e9:.0f} ns per solve, {iterations / (n // 10):.1f} iterations, "
              f"{per_solve / (iterations / (n // 10)) * 1e9:.0f} ns per iteration")


if __name__ == "__main__":
    main()
