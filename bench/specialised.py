"""elimfast's fixed point beside a hand-specialised kernel of the same method (issue 12, item 1).

The run (the issue's): EHBVM(12,3) imposing angular_momentum and lrl_y (docs/methods.md#elim,
with the stable right-hand side of #stable-right-hand-side), Kepler e = 0.6 (mu = 1), h = 0.1,
t in [0, 1000] (10^4 steps), the fixed point warm-started from the previous step's
coefficients (no predictor), accepted by elimfast's own stopping rule (kernels/solver.py
``solve``: d <= 2^-52, or two non-improving iterations inside the rounding band).

The specialised kernel (``run_specialised``) does the same arithmetic in the same order
with elimfast's tables (``ehbvm(12, 3)``), so its trajectory and its per-step iteration
counts are elimfast's, bit for bit (checked, and printed). What it does differently:
- the Kepler gradient and the gradients of L and A_y are written inline, fused with the
  stage sums, one node at a time in registers (no stage array, no lrl_x, no row copy);
- the sizes (k = 12, s = 3, n = 4, nu = 2) are compile-time constants;
- the solve and the map inlined into the time loop (only the rounding band, needed when an
  iterate stops improving, is a call);
- phi_0 is not formed (neither Gamma nor the stable right-hand side uses it);
- h Is is scaled once per run (h is fixed), where elimfast's maps check at each call that
  their scaled tables hold this h (maps.scale_tables).
It keeps elimfast's arithmetic of the state (docs/methods.md#round-off-over-long-times): the
stages from h Is as a double-double (Is + Is_low, exact integrals; scaled with
maps.scale_tables's operations) and from y's Kahan compensation, in maps.stages's order; y
updated by the exact product h coef_0 (stepper.add_product); Kahan's sum of t. And the
finiteness test, and the per-step spurious-solution test (cond(Gamma) <= 1e13,
|h^(2(s-1-j)) alpha_j| <= 1/2).

Variants of it each take over one of elimfast's generalities (see VARIANTS), to show where
elimfast's extra cost per iteration comes from; plus elimfast's own ``solve`` driven by a
bare loop, and Kepler from expressions (configs/kepler_expressions.yaml). Each of a few fresh
processes, one after the other, runs every entry once per round, for several rounds (medians);
the report gives the median over the processes and the spread between them.

    .venv/bin/python bench/specialised.py [--processes 3] [--rounds 11] [--markdown bench/results/specialised.md]

About a minute with Numba's cache warm (bench/__pycache__). The first run compiles every
variant, about 10 minutes on the shared 2-core machine (Numba's inlining of the solve into each
variant is slow), and so does the first run after an edit of this file (Numba's cache is keyed
by the file's modification time).
"""
import argparse
import importlib
import json
import math
import os
import platform
import random
import statistics
import subprocess
import sys
import time
import warnings
from collections import namedtuple
from pathlib import Path

import numpy as np
import numba
from numba import njit, types
from numba.core.errors import NumbaExperimentalFeatureWarning
from numba.extending import overload

ROOT = Path(__file__).resolve().parents[1]

import elimfast  # noqa: E402
from elimfast.config import load_run  # noqa: E402
from elimfast.integrate import SolverSettings  # noqa: E402
from elimfast.kernels.codes import (FAMILY_ELIM, SOLVER_FIXED_POINT, STATUS_NONFINITE,  # noqa: E402
                                    STATUS_NOT_CONVERGED, STATUS_OK, STATUS_SINGULAR, internal)
from elimfast.kernels.linalg import lu_factor, lu_solve_factored  # noqa: E402
from elimfast.kernels.maps import EPS  # noqa: E402
from elimfast.kernels.quadrature import quick_two_sum, two_prod  # noqa: E402
from elimfast.kernels.signatures import (GRAD_H_TYPE, GRAD_INVARIANTS_TYPE, INT_VECTOR, MATRIX,  # noqa: E402
                                         VECTOR)
from elimfast.kernels.solver import (BAND_CAP, BAND_FACTOR, IN_BAND_STALLS, MAX_CONDITION,  # noqa: E402
                                     MAX_ETA_CORRECTION, MAX_WITHOUT_PROGRESS, solve)
from elimfast.kernels.stepper import add_product, kahan_add  # noqa: E402
from elimfast.kernels.workspace import (Settings, Tables, borrow_tables, borrow_workspace, borrowed,  # noqa: E402
                                        make_workspace)
from elimfast.methods import ehbvm  # noqa: E402
from elimfast.problems import kepler  # noqa: E402

warnings.filterwarnings("ignore", category=NumbaExperimentalFeatureWarning)
warnings.filterwarnings("ignore", message="First-class function type feature is experimental")

kepler_module = importlib.import_module("elimfast.problems.kepler")

ECCENTRICITY, H_STEP, T_END = 0.6, 0.1, 1000.0
N_STEPS = int(round(T_END / H_STEP))
CONSERVE = ("angular_momentum", "lrl_y")
CONFIG = ROOT / "configs" / "kepler_expressions.yaml"
STORE_EVERY = 1000   # elimfast's samples: 11 per run, as in bench/kernel.py
TOL = 2.0 ** -52     # elimfast's default acceptance (integrate.DEFAULT_TOL)
MAX_ITER = 100       # elimfast's default for the fixed point (integrate.DEFAULT_MAX_ITER)

# The specialised kernel's sizes, compile-time constants: k nodes, s coefficients, n = 2m, nu imposed.
K, S, N, NU = 12, 3, 4, 2
N_INVARIANTS = 3     # Kepler's invariants: angular_momentum, lrl_x, lrl_y

# ---------------------------------------------------------------------------------------------
# Markers: namedtuple types that choose, at compile time, how the shared code below is put
# together (each variant is one choice changed; see VARIANTS).

Hand = namedtuple("Hand", ["unused"])    # Kepler's gradients inline, fused with the stages
Interface = namedtuple("Interface", ["params", "conserve_idx", "inv_grads"])   # elimfast's
#   problem interface (stages in an array, grad_H and grad_invariants of one node into arrays,
#   all three invariants' gradients, imposed rows copied by conserve_idx), functions inlined
Functions = namedtuple("Functions", ["grad_H", "grad_invariants", "params", "conserve_idx", "inv_grads"])
#   the same interface through types.FunctionType arguments, as elimfast calls them
Batched = namedtuple("Batched", ["grad_H", "grad_invariants", "params", "conserve_idx", "inv_grads"])
#   FunctionType arguments evaluating all k nodes per call
Fixed = namedtuple("Fixed", ["unused"])        # sizes: compile-time constants
Runtime = namedtuple("Runtime", ["unused"])    # sizes: read from the arrays' shapes
RuntimeMethod = namedtuple("RuntimeMethod", ["unused"])   # only the method's k, s, nu from the arrays
RuntimeState = namedtuple("RuntimeState", ["unused"])     # only the problem's n from the arrays
Inlined = namedtuple("Inlined", ["unused"])    # solve inlined into the time loop
Outlined = namedtuple("Outlined", ["unused"])  # step -> attempt -> solve as non-inlined functions passed
#   elimfast's Tables and Workspace namedtuples, like stepper.try_step -> _attempt -> solver.solve
OutlinedOnce = namedtuple("OutlinedOnce", ["unused"])   # the same with one non-inlined call (solve) per step

# The specialised kernel's own work arrays (shapes for sizes k, s, n, nu).
Work = namedtuple("Work", [
    "u",           # (k, n) stages (not used by Hand: its stages stay in registers)
    "grads",       # (k, n) grad H at the stages
    "grads_hat",   # (>= nu, k, n) gradients of the imposed invariants at the stages
    "gamma",       # (k, n) gamma_j = J sum_l b_l P_j(c_l) grad H(u_l)
    "phi",         # (nu, k, n) phi_j per imposed invariant (phi_0 unused)
    "big_gamma",   # (nu, nu) Gamma, unfactored
    "lu",          # (nu, nu) Gamma, LU-factored
    "pivots",      # (nu,) int64
    "bvec",        # (nu,) right-hand side, then scratch
    "inverse",     # (nu, nu) Gamma^-1 (condition number, rounding band)
    "dalpha",      # (nu,) rounding of alpha
    "sizes",       # (1 + nu, n) F_p, then A_{a,p} (rounding band)
    "level",       # (n,) omega_p
    "new_coef",    # (s, n) G(coef)
    "delta",       # (s n,) G(coef) - coef
    "scale",       # (n,) sc_p of the stopping rule
    "h_powers",    # (nu,) h^(2(nu-1-c))
    "scaled",      # (k, s) h Is as a double-double, high part (maps.scale_tables; once per run, h is fixed)
    "scaled_low",  # (k, s) its low part
    "comp",        # (n,) the Kahan compensation of y: the state's y_comp itself, which the stages add
])


@njit(inline="always")
def _make_work(k, s, n, nu):
    return Work(np.zeros((k, n)), np.zeros((k, n)), np.zeros((nu, k, n)), np.zeros((k, n)), np.zeros((nu, k, n)),
                np.zeros((nu, nu)), np.zeros((nu, nu)), np.zeros(nu, dtype=np.int64), np.zeros(nu),
                np.zeros((nu, nu)), np.zeros(nu), np.zeros((1 + nu, n)), np.zeros(n), np.zeros((s, n)),
                np.zeros(s * n), np.zeros(n), np.zeros(nu), np.zeros((k, s)), np.zeros((k, s)), np.zeros(n))


@njit(inline="always")
def _borrow_work(w):
    """Views that own no reference (workspace.borrowed): no reference counting in the loop, as in elimfast."""
    return Work(borrowed(w.u), borrowed(w.grads), borrowed(w.grads_hat), borrowed(w.gamma), borrowed(w.phi),
                borrowed(w.big_gamma), borrowed(w.lu), borrowed(w.pivots), borrowed(w.bvec), borrowed(w.inverse),
                borrowed(w.dalpha), borrowed(w.sizes), borrowed(w.level), borrowed(w.new_coef), borrowed(w.delta),
                borrowed(w.scale), borrowed(w.h_powers), borrowed(w.scaled), borrowed(w.scaled_low),
                borrowed(w.comp))


@njit(inline="always")
def _work_from_workspace(ws):
    """The same Work, as views into elimfast's Workspace (the Outlined variants)."""
    return Work(ws.u, ws.grads, ws.grads_hat, ws.gamma, ws.phi, ws.small_copy, ws.small_matrix, ws.small_pivots,
                ws.small_vector, ws.small_inverse, ws.small_rounding[0], ws.sizes, ws.rounding_level, ws.new_coef,
                ws.delta, ws.scale, ws.h_powers, ws.scaled_Is, ws.scaled_Is_low, ws.stage_comp)


@njit(cache=True)
def _keep_alive(owner):
    """workspace.keep_alive for this file's types. Not elimfast's: its cache index would then hold
    this script's namedtuple types, which another process cannot unpickle (ModuleNotFoundError
    when elimfast next compiles a caller of keep_alive)."""
    return owner is not None


def _is(marker_type, cls):
    return isinstance(marker_type, types.BaseNamedTuple) and marker_type.instance_class is cls


def sizes_of(mode, Is, y, nu):
    """(k, s, n, nu): the constants (Fixed), the arrays' shapes (Runtime), or a mix (RuntimeMethod, RuntimeState)."""
    raise NotImplementedError("compiled only")


@overload(sizes_of, jit_options={"cache": True}, inline="always")
def _sizes_of(mode, Is, y, nu):
    if _is(mode, Fixed):
        return lambda mode, Is, y, nu: (K, S, N, NU)
    if _is(mode, Runtime):
        return lambda mode, Is, y, nu: (Is.shape[0], Is.shape[1], y.shape[0], nu)
    if _is(mode, RuntimeMethod):
        return lambda mode, Is, y, nu: (Is.shape[0], Is.shape[1], N, nu)
    if _is(mode, RuntimeState):
        return lambda mode, Is, y, nu: (K, S, y.shape[0], NU)


# ---------------------------------------------------------------------------------------------
# Kepler: grad H = (q/|q|^3, p); grad L = (p2, -p1, -q2, q1); grad A_y as in problems/kepler.py,
# the same expressions in the same order (so the same bits).

_grad_H_inline = njit(inline="always", error_model="numpy")(kepler_module.grad_H.py_func)
_grad_invariants_inline = njit(inline="always", error_model="numpy")(kepler_module.grad_invariants.py_func)

NODES_VECTOR_FIELD = types.void(MATRIX, VECTOR, MATRIX)                         # (k, n) -> (k, n)
NODES_GRADIENTS = types.void(MATRIX, VECTOR, types.float64[:, :, ::1])         # (k, n) -> (n_inv, k, n)


@njit(NODES_VECTOR_FIELD, cache=True, error_model="numpy")
def kepler_grad_H_nodes(u, params, out):
    """grad H at every row of u: one call for all k nodes."""
    for l in range(u.shape[0]):
        _grad_H_inline(u[l], params, out[l])


@njit(NODES_GRADIENTS, cache=True, error_model="numpy")
def kepler_grad_invariants_nodes(u, params, out):
    """out[i, l] = grad L_i(u_l): one call for all k nodes."""
    for l in range(u.shape[0]):
        q1, q2, p1, p2 = u[l, 0], u[l, 1], u[l, 2], u[l, 3]
        r2 = q1 * q1 + q2 * q2
        inv_r = 1.0 / math.sqrt(r2)
        inv_r3 = inv_r / r2
        L = q1 * p2 - q2 * p1
        out[0, l, 0] = p2
        out[0, l, 1] = -p1
        out[0, l, 2] = -q2
        out[0, l, 3] = q1
        out[1, l, 0] = p2 * p2 - inv_r + q1 * q1 * inv_r3
        out[1, l, 1] = -p2 * p1 + q1 * q2 * inv_r3
        out[1, l, 2] = -p2 * q2
        out[1, l, 3] = L + p2 * q1
        out[2, l, 0] = -p1 * p2 + q1 * q2 * inv_r3
        out[2, l, 1] = p1 * p1 - inv_r + q2 * q2 * inv_r3
        out[2, l, 2] = -L + p1 * q2
        out[2, l, 3] = -p1 * q1


@njit(inline="always", error_model="numpy")
def _scale_tables(h, Is, Is_low, k, s, scaled, scaled_low):
    """scaled + scaled_low = h (Is + Is_low) as a double-double: maps.scale_tables's operations
    (an exact product, quadrature.two_prod, then quick_two_sum), once per run (h is fixed here;
    elimfast's maps check per call whether they hold this h)."""
    for l in range(k):
        for j in range(s):
            product, error = two_prod(h, Is[l, j])
            scaled[l, j], scaled_low[l, j] = quick_two_sum(product, error + h * Is_low[l, j])


@njit(inline="always", error_model="numpy")
def _stages(y, comp, scaled, scaled_low, coef, k, s, n, u):
    """u[l] = (y + comp) + h sum_j Is[l, j] coef[j] from h Is = scaled + scaled_low, in maps.stages's
    order: small = comp + scaled_low[l, 0] coef[0] + sum_{j>=1} scaled[l, j] coef[j], then
    u[l] = y + (scaled[l, 0] coef[0] + small)."""
    for l in range(k):
        for i in range(n):
            small = comp[i] + scaled_low[l, 0] * coef[0, i]
            for j in range(1, s):
                small += scaled[l, j] * coef[j, i]
            u[l, i] = y[i] + (scaled[l, 0] * coef[0, i] + small)


def gradients(problem, y, coef, k, s, n, nu, work):
    """work.grads[l] = grad H(u_l), work.grads_hat[a, l] = grad L_a(u_l) for the imposed L_a, the stages
    u_l from y, work.comp and the scaled tables work.scaled, work.scaled_low (_stages)."""
    raise NotImplementedError("compiled only")


@overload(gradients, jit_options={"cache": True, "error_model": "numpy"}, inline="always")
def _gradients(problem, y, coef, k, s, n, nu, work):
    if _is(problem, Hand):
        def hand(problem, y, coef, k, s, n, nu, work):
            grads, grads_hat = work.grads, work.grads_hat
            scaled, scaled_low, comp = work.scaled, work.scaled_low, work.comp
            for l in range(k):
                # _stages, one node at a time in registers, each component's sums in the same order
                w = scaled_low[l, 0]
                small0 = comp[0] + w * coef[0, 0]
                small1 = comp[1] + w * coef[0, 1]
                small2 = comp[2] + w * coef[0, 2]
                small3 = comp[3] + w * coef[0, 3]
                for j in range(1, s):
                    w = scaled[l, j]
                    small0 += w * coef[j, 0]
                    small1 += w * coef[j, 1]
                    small2 += w * coef[j, 2]
                    small3 += w * coef[j, 3]
                w = scaled[l, 0]
                q1 = y[0] + (w * coef[0, 0] + small0)
                q2 = y[1] + (w * coef[0, 1] + small1)
                p1 = y[2] + (w * coef[0, 2] + small2)
                p2 = y[3] + (w * coef[0, 3] + small3)
                r2 = q1 * q1 + q2 * q2
                root = math.sqrt(r2)
                inv_r3_H = 1.0 / (r2 * root)
                grads[l, 0] = q1 * inv_r3_H
                grads[l, 1] = q2 * inv_r3_H
                grads[l, 2] = p1
                grads[l, 3] = p2
                inv_r = 1.0 / root
                inv_r3 = inv_r / r2
                L = q1 * p2 - q2 * p1
                grads_hat[0, l, 0] = p2            # angular momentum
                grads_hat[0, l, 1] = -p1
                grads_hat[0, l, 2] = -q2
                grads_hat[0, l, 3] = q1
                grads_hat[1, l, 0] = -p1 * p2 + q1 * q2 * inv_r3    # A_y
                grads_hat[1, l, 1] = p1 * p1 - inv_r + q2 * q2 * inv_r3
                grads_hat[1, l, 2] = -L + p1 * q2
                grads_hat[1, l, 3] = -p1 * q1
        return hand
    if _is(problem, Interface):
        def interface(problem, y, coef, k, s, n, nu, work):
            u, grads, grads_hat = work.u, work.grads, work.grads_hat
            params, conserve_idx, inv_grads = problem.params, problem.conserve_idx, problem.inv_grads
            _stages(y, work.comp, work.scaled, work.scaled_low, coef, k, s, n, u)
            for l in range(k):
                _grad_H_inline(u[l], params, grads[l])
            for l in range(k):
                _grad_invariants_inline(u[l], params, inv_grads)
                for a in range(nu):
                    for p in range(n):
                        grads_hat[a, l, p] = inv_grads[conserve_idx[a], p]
        return interface
    if _is(problem, Functions):
        def functions(problem, y, coef, k, s, n, nu, work):
            u, grads, grads_hat = work.u, work.grads, work.grads_hat
            grad_H, grad_invariants = problem.grad_H, problem.grad_invariants
            params, conserve_idx, inv_grads = problem.params, problem.conserve_idx, problem.inv_grads
            _stages(y, work.comp, work.scaled, work.scaled_low, coef, k, s, n, u)
            for l in range(k):
                grad_H(u[l], params, grads[l])
            for l in range(k):
                grad_invariants(u[l], params, inv_grads)
                for a in range(nu):
                    for p in range(n):
                        grads_hat[a, l, p] = inv_grads[conserve_idx[a], p]
        return functions
    if _is(problem, Batched):
        def batched(problem, y, coef, k, s, n, nu, work):
            u, grads, grads_hat = work.u, work.grads, work.grads_hat
            params, conserve_idx, inv_grads = problem.params, problem.conserve_idx, problem.inv_grads
            _stages(y, work.comp, work.scaled, work.scaled_low, coef, k, s, n, u)
            problem.grad_H(u, params, grads)
            problem.grad_invariants(u, params, inv_grads)
            for a in range(nu):
                for l in range(k):
                    for p in range(n):
                        grads_hat[a, l, p] = inv_grads[conserve_idx[a], l, p]
        return batched


# ---------------------------------------------------------------------------------------------
# The map and the solve: maps.elim_map and solver.solve for ELIM with r = k, the stable
# right-hand side and the fixed point, operation for operation.

@njit(inline="always", error_model="numpy")
def _map_rest(h, projection, alpha, plain_sweep, k, s, n, nu, work):
    """From the gradients at the stages to G(coef) in work.new_coef (docs/methods.md#elim, #stable-right-hand-side):
    gamma_j (j < k), phi_j (0 < j < k), Gamma alpha = -sum_{j=s}^{k-1} phi_j^T gamma_j, G_j = eta_j gamma_j.
    Returns 1 when Gamma is singular (alpha keeps its value), else 0."""
    grads, grads_hat, gamma, phi, big_gamma = work.grads, work.grads_hat, work.gamma, work.phi, work.big_gamma
    bvec, lu, pivots, new_coef, h_powers = work.bvec, work.lu, work.pivots, work.new_coef, work.h_powers
    m = n // 2
    for j in range(k):
        for i in range(m):
            acc_q = 0.0
            acc_p = 0.0
            for l in range(k):
                w = projection[j, l]
                acc_q += w * grads[l, m + i]
                acc_p += w * grads[l, i]
            gamma[j, i] = acc_q
            gamma[j, m + i] = -acc_p
    for a in range(nu):
        for j in range(1, k):
            for p in range(n):
                acc = 0.0
                for l in range(k):
                    acc += projection[j, l] * grads_hat[a, l, p]
                phi[a, j, p] = acc
    for col in range(nu):
        j = s - nu + col
        for a in range(nu):
            acc = 0.0
            for p in range(n):
                acc += phi[a, j, p] * gamma[j, p]
            big_gamma[a, col] = h_powers[col] * acc
    for a in range(nu):
        acc = 0.0
        for j in range(s, k):
            for p in range(n):
                acc += phi[a, j, p] * gamma[j, p]
        bvec[a] = -1.0 * acc
    singular = 0
    if plain_sweep:
        for a in range(nu):
            alpha[a] = 0.0
    else:
        for a in range(nu):
            for c in range(nu):
                lu[a, c] = big_gamma[a, c]
        if lu_factor(lu, pivots) == 0:
            lu_solve_factored(lu, pivots, bvec)
            for a in range(nu):
                alpha[a] = bvec[a]
        else:
            singular = 1
    for j in range(s):
        eta = 1.0
        if j >= s - nu:
            eta = 1.0 - h_powers[j - (s - nu)] * alpha[j - (s - nu)]
        for p in range(n):
            new_coef[j, p] = eta * gamma[j, p]
    return singular


@njit(inline="always", error_model="numpy")
def _condition_number(nu, work):
    """||Gamma||_inf ||Gamma^-1||_inf, Gamma^-1 into work.inverse (maps.condition_number)."""
    unit, lu, pivots, matrix, inverse = work.bvec, work.lu, work.pivots, work.big_gamma, work.inverse
    for c in range(nu):
        for a in range(nu):
            unit[a] = 1.0 if a == c else 0.0
        lu_solve_factored(lu, pivots, unit)
        for a in range(nu):
            inverse[a, c] = unit[a]
    norm = 0.0
    inverse_norm = 0.0
    for a in range(nu):
        row = 0.0
        inverse_row = 0.0
        for c in range(nu):
            row += abs(matrix[a, c])
            inverse_row += abs(inverse[a, c])
        norm = max(norm, row)
        inverse_norm = max(inverse_norm, inverse_row)
    return norm * inverse_norm


@njit(inline="always", error_model="numpy")
def _dot_rounding(S_hat, phi, gamma, j, sizes, a, n):
    """maps._dot_rounding: the rounding of phi_j^a . gamma_j."""
    acc = 0.0
    for p in range(n):
        acc += (S_hat[j] * (sizes[1 + a, p] * abs(gamma[j, p]) + sizes[0, p] * abs(phi[a, j, p]))
                + abs(phi[a, j, p]) * abs(gamma[j, p]))
    return EPS * acc


@internal
def _band(h, alpha, solved, abs_projection, k, s, n, nu, work):
    """The rounding band B = min(4 max(omega, eps), 1e-12) (solver._band for the fixed point on ELIM;
    solved: with the multipliers' share). Not inlined: it runs only when an iterate stops improving
    below 1e-12, and inlining it doubled the compile time."""
    grads, grads_hat, gamma, phi, scale = work.grads, work.grads_hat, work.gamma, work.phi, work.scale
    level, sizes, h_powers, dalpha, d_rhs, inverse = (work.level, work.sizes, work.h_powers, work.dalpha, work.bvec,
                                                     work.inverse)
    m = n // 2
    for p in range(n):
        partner = p + m if p < m else p - m
        F = 0.0
        for l in range(k):
            F = max(F, abs(grads[l, partner]))
        sizes[0, p] = F
    if solved:
        for a in range(nu):
            for p in range(n):
                A = 0.0
                for i in range(k):
                    A = max(A, abs(grads_hat[a, i, p]))
                sizes[1 + a, p] = A
    for p in range(n):
        level[p] = 4.0 * EPS * h * sizes[0, p] / scale[p]
    if solved and nu > 0:
        _condition_number(nu, work)
        for a in range(nu):
            acc = 0.0
            for j in range(s, k):
                acc += _dot_rounding(abs_projection, phi, gamma, j, sizes, a, n)
            for c in range(nu):
                acc += h_powers[c] * _dot_rounding(abs_projection, phi, gamma, s - nu + c, sizes, a, n) * abs(alpha[c])
            d_rhs[a] = acc
        for a in range(nu):
            acc = 0.0
            for b in range(nu):
                acc += abs(inverse[a, b]) * d_rhs[b]
            dalpha[a] = acc
        for p in range(n):
            share = 0.0
            for c in range(nu):
                share = max(share, h_powers[c] * dalpha[c] * abs(gamma[s - nu + c, p]))
            level[p] += h * share / scale[p]
    omega = 0.0
    for p in range(n):
        omega = max(omega, level[p])
    return min(BAND_FACTOR * max(omega, EPS), BAND_CAP)


@njit(inline="always", error_model="numpy")
def _solve(problem, y, h, projection, abs_projection, coef, alpha, cold, tol, max_iter, k, s, n, nu, work):
    """solver.solve for the fixed point on ELIM (stable right-hand side): iterate coef <- G(coef) from
    the guess in coef (cold: coef = 0, alpha = 0 for two sweeps). Returns (status, iterations)."""
    new_coef, delta, scale, h_powers = work.new_coef, work.delta, work.scale, work.h_powers
    for c in range(nu):
        h_powers[c] = h ** (2 * (nu - 1 - c))
    best = np.inf
    without_progress = 0
    best_in_band = np.inf
    stalls = 0
    band = 0.0
    band_complete = False
    d = np.inf
    accepted = False
    singular = 0
    plain_sweep = False
    iteration = 0
    for iteration in range(1, max_iter + 1):
        plain_sweep = cold and iteration <= 2
        gradients(problem, y, coef, k, s, n, nu, work)
        singular = _map_rest(h, projection, alpha, plain_sweep, k, s, n, nu, work)
        largest = 0.0
        for i in range(n):
            scale[i] = max(abs(y[i]), abs(h * new_coef[0, i]))
            largest = max(largest, scale[i])
        for i in range(n):
            if not (scale[i] > 0.0):
                scale[i] = largest if largest > 0.0 else 1.0
        for j in range(s):
            for p in range(n):
                delta[j * n + p] = new_coef[j, p] - coef[j, p]
        d = 0.0
        for p in range(n):
            largest_p = 0.0
            for j in range(s):
                value = abs(h * delta[j * n + p]) / scale[p]
                if not (value <= largest_p):
                    largest_p = value
                coef[j, p] += delta[j * n + p]
            if not (largest_p <= d):
                d = largest_p
        if not (d <= 1e308):
            return STATUS_NONFINITE, iteration
        if cold and nu > 0 and iteration == 3:
            best = np.inf
            without_progress = 0
            best_in_band = np.inf
            band = 0.0
            band_complete = False
        if d <= tol:
            accepted = True
            break
        if d <= BAND_CAP:
            if d < best_in_band:
                best_in_band = d
                stalls = 0
            else:
                if band == 0.0:
                    band = _band(h, alpha, False, abs_projection, k, s, n, nu, work)
                if (d > band or best_in_band > band) and not band_complete:
                    band = _band(h, alpha, singular == 0 and not plain_sweep, abs_projection, k, s, n, nu, work)
                    band_complete = True
                if d <= band and best_in_band <= band:
                    stalls += 1
                    if stalls >= IN_BAND_STALLS:
                        accepted = True
                        break
        if d < best:
            best = d
            without_progress = 0
        else:
            without_progress += 1
            if without_progress >= MAX_WITHOUT_PROGRESS:
                break
    if not accepted:
        return STATUS_NOT_CONVERGED, iteration
    if nu == 0 or (cold and iteration <= 2):
        return STATUS_OK, iteration
    if singular != 0:
        return STATUS_SINGULAR, iteration
    if not (_condition_number(nu, work) <= MAX_CONDITION):
        return STATUS_SINGULAR, iteration
    for c in range(nu):
        if not (abs(h_powers[c] * alpha[c]) <= MAX_ETA_CORRECTION):
            return STATUS_SINGULAR, iteration
    return STATUS_OK, iteration


# The Outlined variants: three nested non-inlined calls per step (like stepper.try_step ->
# stepper._attempt -> solver.solve), each passed elimfast's Tables and Workspace namedtuples,
# compiled as elimfast's internal functions are (codes.internal: no reference counting).

@internal
def _solve_outlined(problem, sizes_mode, y, h, tables, workspace, coef, alpha, cold, tol, max_iter):
    k, s, n, nu = sizes_of(sizes_mode, tables.Is, y, alpha.shape[0])
    return _solve(problem, y, h, tables.projection, tables.abs_projection_hat, coef, alpha, cold, tol, max_iter,
                  k, s, n, nu, _work_from_workspace(workspace))


@internal
def _attempt_outlined(problem, sizes_mode, y, h, tables, workspace, coef, alpha, cold, tol, max_iter):
    return _solve_outlined(problem, sizes_mode, y, h, tables, workspace, coef, alpha, cold, tol, max_iter)


@internal
def _step_outlined(problem, sizes_mode, y, h, tables, workspace, coef, alpha, cold, tol, max_iter):
    return _attempt_outlined(problem, sizes_mode, y, h, tables, workspace, coef, alpha, cold, tol, max_iter)


def solve_step(call_mode, problem, sizes_mode, y, h, tables, work, coef, alpha, cold, tol, max_iter):
    raise NotImplementedError("compiled only")


@overload(solve_step, jit_options={"cache": True, "error_model": "numpy"}, inline="always")
def _solve_step(call_mode, problem, sizes_mode, y, h, tables, work, coef, alpha, cold, tol, max_iter):
    if _is(call_mode, Inlined):
        def inlined(call_mode, problem, sizes_mode, y, h, tables, work, coef, alpha, cold, tol, max_iter):
            k, s, n, nu = sizes_of(sizes_mode, tables.Is, y, alpha.shape[0])
            return _solve(problem, y, h, tables.projection, tables.abs_projection_hat, coef, alpha, cold, tol,
                          max_iter, k, s, n, nu, work)
        return inlined
    if _is(call_mode, Outlined):
        def outlined(call_mode, problem, sizes_mode, y, h, tables, work, coef, alpha, cold, tol, max_iter):
            return _step_outlined(problem, sizes_mode, y, h, tables, work, coef, alpha, cold, tol, max_iter)
        return outlined
    if _is(call_mode, OutlinedOnce):
        def outlined_once(call_mode, problem, sizes_mode, y, h, tables, work, coef, alpha, cold, tol, max_iter):
            return _solve_outlined(problem, sizes_mode, y, h, tables, work, coef, alpha, cold, tol, max_iter)
        return outlined_once


def make_work(call_mode, k, s, n, nu):
    raise NotImplementedError("compiled only")


@overload(make_work, jit_options={"cache": True}, inline="always")
def _make_work_overload(call_mode, k, s, n, nu):
    if _is(call_mode, Inlined):
        return lambda call_mode, k, s, n, nu: _make_work(k, s, n, nu)
    if _is(call_mode, Outlined) or _is(call_mode, OutlinedOnce):
        return lambda call_mode, k, s, n, nu: make_workspace(n, k, k, s, nu, FAMILY_ELIM, N_INVARIANTS, nu, 0)


def borrow(call_mode, work):
    raise NotImplementedError("compiled only")


@overload(borrow, jit_options={"cache": True}, inline="always")
def _borrow_overload(call_mode, work):
    if _is(call_mode, Inlined):
        return lambda call_mode, work: _borrow_work(work)
    if _is(call_mode, Outlined) or _is(call_mode, OutlinedOnce):
        return lambda call_mode, work: borrow_workspace(work)


def work_view(call_mode, work):
    raise NotImplementedError("compiled only")


@overload(work_view, jit_options={"cache": True}, inline="always")
def _work_view_overload(call_mode, work):
    """The Work of make_work's (borrowed) work: itself, or its views into elimfast's Workspace."""
    if _is(call_mode, Inlined):
        return lambda call_mode, work: work
    if _is(call_mode, Outlined) or _is(call_mode, OutlinedOnce):
        return lambda call_mode, work: _work_from_workspace(work)


@njit(cache=True, error_model="numpy")
def _time_loop(problem, sizes_mode, call_mode, y0, h, n_steps, tables0, tol, max_iter, y_final, iter_out, alpha_out):
    """n_steps fixed steps from y0 (stepper.time_loop for this run: warm start without the predictor,
    y kept with its compensation y_comp, which the stages add (maps.stages), and updated by the exact
    product h coef_0 (stepper.add_product); Kahan's sum of t). The stages' tables h Is (double-double)
    are computed once, before the loop. y_comp is the work's comp array itself (elimfast copies its
    y_comp into work.stage_comp at each step). Returns (status, steps done). Compiled once per
    combination of markers (one call per run: not inlined into the entry points, which saves a level
    of Numba's slow IR inlining)."""
    k, s, n, nu = sizes_of(sizes_mode, tables0.Is, y0, alpha_out.shape[1])
    owners = make_work(call_mode, k, s, n, nu)
    work = borrow(call_mode, owners)
    tables = borrow_tables(tables0)
    view = work_view(call_mode, work)
    _scale_tables(h, tables.Is, tables.Is_low, k, s, view.scaled, view.scaled_low)
    y = np.zeros(n)
    y_comp = view.comp
    for p in range(n):
        y[p] = y0[p]
        y_comp[p] = 0.0
    coef = np.zeros((s, n))
    alpha = np.zeros(nu)
    t = 0.0
    t_comp = 0.0
    status = STATUS_OK
    done = 0
    for step in range(n_steps):
        status, iterations = solve_step(call_mode, problem, sizes_mode, y, h, tables, work, coef, alpha, step == 0,
                                        tol, max_iter)
        iter_out[step] = iterations
        if status != STATUS_OK:
            break
        for p in range(n):
            if not (abs(y[p] + h * coef[0, p]) <= 1e308):
                status = STATUS_NONFINITE
        if status != STATUS_OK:
            break
        for p in range(n):
            y[p], y_comp[p] = add_product(y[p], y_comp[p], h, coef[0, p])
        t, t_comp = kahan_add(t, t_comp, h)
        for a in range(nu):
            alpha_out[step, a] = alpha[a]
        done = step + 1
    for p in range(n):
        y_final[p] = y[p]
    _keep_alive(owners)
    return status, done


# ---------------------------------------------------------------------------------------------
# Entry points, one per variant (the markers are built inside, so each compiles and caches alone).

@njit(cache=True, error_model="numpy")
def run_specialised(y0, h, n_steps, tables, tol, max_iter, y_final, iter_out, alpha_out):
    """The hand-specialised kernel: Hand gradients, Fixed sizes, Inlined solve."""
    return _time_loop(Hand(0), Fixed(0), Inlined(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


@njit(cache=True, error_model="numpy")
def run_runtime_sizes(y0, h, n_steps, tables, tol, max_iter, y_final, iter_out, alpha_out):
    return _time_loop(Hand(0), Runtime(0), Inlined(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


@njit(cache=True, error_model="numpy")
def run_runtime_method(y0, h, n_steps, tables, tol, max_iter, y_final, iter_out, alpha_out):
    return _time_loop(Hand(0), RuntimeMethod(0), Inlined(0), y0, h, n_steps, tables, tol, max_iter, y_final,
                      iter_out, alpha_out)


@njit(cache=True, error_model="numpy")
def run_runtime_state(y0, h, n_steps, tables, tol, max_iter, y_final, iter_out, alpha_out):
    return _time_loop(Hand(0), RuntimeState(0), Inlined(0), y0, h, n_steps, tables, tol, max_iter, y_final,
                      iter_out, alpha_out)


@njit(cache=True, error_model="numpy")
def run_outlined_once(y0, h, n_steps, tables, tol, max_iter, y_final, iter_out, alpha_out):
    return _time_loop(Hand(0), Fixed(0), OutlinedOnce(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


@njit(cache=True, error_model="numpy")
def run_outlined(y0, h, n_steps, tables, tol, max_iter, y_final, iter_out, alpha_out):
    return _time_loop(Hand(0), Fixed(0), Outlined(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


@njit(cache=True, error_model="numpy")
def run_interface(params, conserve_idx, y0, h, n_steps, tables, tol, max_iter, y_final, iter_out, alpha_out):
    problem = Interface(params, conserve_idx, np.zeros((N_INVARIANTS, N)))
    return _time_loop(problem, Fixed(0), Inlined(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


@njit(cache=True, error_model="numpy")
def run_per_problem(params, conserve_idx, y0, h, n_steps, tables, tol, max_iter, y_final, iter_out, alpha_out):
    """What compiling elimfast's kernel for each problem would give: the problem's functions inlined
    (and its n constant), the method's sizes at runtime, the solve outlined with the structs."""
    problem = Interface(params, conserve_idx, np.zeros((N_INVARIANTS, N)))
    return _time_loop(problem, RuntimeMethod(0), Outlined(0), y0, h, n_steps, tables, tol, max_iter, y_final,
                      iter_out, alpha_out)


def _signature(function_types, tables):
    """(status, steps) of (functions..., params, conserve_idx, y0, h, n_steps, tables, tol, max_iter,
    y_final, iter_out, alpha_out): the FunctionType arguments need an explicit signature."""
    return types.UniTuple(types.int64, 2)(*function_types, VECTOR, INT_VECTOR, VECTOR, types.float64, types.int64,
                                          numba.typeof(tables), types.float64, types.int64, VECTOR, INT_VECTOR,
                                          MATRIX)


def _run_functions(grad_H, grad_invariants, params, conserve_idx, y0, h, n_steps, tables, tol, max_iter, y_final,
                   iter_out, alpha_out):
    problem = Functions(grad_H, grad_invariants, params, conserve_idx, np.zeros((N_INVARIANTS, N)))
    return _time_loop(problem, Fixed(0), Inlined(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


def _run_batched(grad_H, grad_invariants, params, conserve_idx, y0, h, n_steps, tables, tol, max_iter, y_final,
                 iter_out, alpha_out):
    problem = Batched(grad_H, grad_invariants, params, conserve_idx, np.zeros((N_INVARIANTS, K, N)))
    return _time_loop(problem, Fixed(0), Inlined(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


def _run_generic(grad_H, grad_invariants, params, conserve_idx, y0, h, n_steps, tables, tol, max_iter, y_final,
                 iter_out, alpha_out):
    problem = Functions(grad_H, grad_invariants, params, conserve_idx, np.zeros((N_INVARIANTS, y0.shape[0])))
    return _time_loop(problem, Runtime(0), Outlined(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


def _run_batched_generic(grad_H, grad_invariants, params, conserve_idx, y0, h, n_steps, tables, tol, max_iter,
                         y_final, iter_out, alpha_out):
    problem = Batched(grad_H, grad_invariants, params, conserve_idx,
                      np.zeros((N_INVARIANTS, tables.Is.shape[0], y0.shape[0])))
    return _time_loop(problem, Runtime(0), Outlined(0), y0, h, n_steps, tables, tol, max_iter, y_final, iter_out,
                      alpha_out)


def _run_elimfast_solve(grad_H, grad_invariants, params, conserve_idx, y0, h, n_steps, tables, tol, max_iter,
                        y_final, iter_out, alpha_out):
    """elimfast's own solver.solve (its map, stopping rule, Workspace, FunctionType calls) from a bare
    time loop: what stepper.try_step and time_loop add is the difference to elimfast's whole run.
    As try_step: work.stage_comp = y_comp before each solve (the map's stages add it; the map scales
    its tables itself, maps.scale_tables), and the update by stepper.add_product."""
    n = y0.shape[0]
    k, s = tables.Is.shape
    nu = conserve_idx.shape[0]
    settings = Settings(FAMILY_ELIM, SOLVER_FIXED_POINT, 1, 1, 0, tol, max_iter, 4)
    owners = make_workspace(n, k, k, s, nu, FAMILY_ELIM, N_INVARIANTS, nu, tables.newton_values.shape[0])
    work = borrow_workspace(owners)
    borrowed_tables = borrow_tables(tables)
    y = np.zeros(n)
    y_comp = np.zeros(n)
    for p in range(n):
        y[p] = y0[p]
    coef = np.zeros((s, n))
    alpha = np.zeros(nu)
    t = 0.0
    t_comp = 0.0
    status = STATUS_OK
    done = 0
    for step in range(n_steps):
        for p in range(n):
            work.stage_comp[p] = y_comp[p]
        status, iterations = solve(grad_H, grad_invariants, params, settings, borrowed_tables, conserve_idx, work,
                                   y, h, coef, alpha, step == 0)
        iter_out[step] = iterations
        if status != STATUS_OK:
            break
        for p in range(n):
            y[p], y_comp[p] = add_product(y[p], y_comp[p], h, coef[0, p])
        t, t_comp = kahan_add(t, t_comp, h)
        for a in range(nu):
            alpha_out[step, a] = alpha[a]
        done = step + 1
    for p in range(n):
        y_final[p] = y[p]
    _keep_alive(owners)
    return status, done


_compiled = {}


def function_kernel(python_function, function_types, tables):
    """python_function compiled (once per process, cached on disk) with FunctionType arguments."""
    if python_function not in _compiled:
        _compiled[python_function] = njit(_signature(function_types, tables), cache=True,
                                          error_model="numpy")(python_function)
    return _compiled[python_function]


# ---------------------------------------------------------------------------------------------
# The measurements.

PER_NODE = (GRAD_H_TYPE, GRAD_INVARIANTS_TYPE)
PER_K_NODES = (types.FunctionType(NODES_VECTOR_FIELD), types.FunctionType(NODES_GRADIENTS))

# label, what it changes (relative to the specialised kernel), how it is run
VARIANTS = [
    ("specialised", "the hand-specialised kernel (Kepler inline, sizes constant, solve inlined)", "specialised"),
    ("problem interface, inlined", "elimfast's problem interface: stages stored, grad_H and grad_invariants per node "
     "into arrays, all 3 invariant gradients, rows copied by conserve_idx; the functions still inlined", "interface"),
    ("FunctionType, 1 node per call", "that interface through FunctionType arguments (elimfast's calls)",
     "functions"),
    ("FunctionType, k nodes per call", "FunctionType arguments evaluating all 12 nodes per call (2 calls per "
     "iteration instead of 24)", "batched"),
    ("sizes at runtime", "k, s, n, nu read from the arrays instead of compile-time constants", "runtime"),
    ("method's sizes at runtime", "k, s, nu read from the arrays, n = 4 constant", "runtime_method"),
    ("problem's size at runtime", "n read from the state, k, s, nu constant", "runtime_state"),
    ("outlined, Tables/Workspace", "step -> attempt -> solve as 3 non-inlined calls per step passing elimfast's "
     "Tables and Workspace namedtuples (no reference counting, as codes.internal)", "outlined"),
    ("outlined once, Tables/Workspace", "the same with one non-inlined call (solve) per step", "outlined_once"),
    ("all three (FunctionType 1 node, runtime sizes, outlined)", "the three generalities together", "generic"),
    ("k nodes per call, otherwise all three", "FunctionType k nodes per call, sizes at runtime, outlined: what a "
     "k-node signature alone would give elimfast", "batched_generic"),
    ("per-problem kernel", "elimfast's interface with the functions inlined (n constant), the method's sizes at "
     "runtime, outlined: what compiling elimfast's kernel for each problem would give", "per_problem"),
    ("elimfast's solver.solve, bare loop", "elimfast's own solve and map (FunctionType, Workspace) from a loop "
     "without try_step", "elimfast_solve"),
]

# The same kernels with the problem from configs/kepler_expressions.yaml (its generated functions).
USER_VARIANTS = [
    ("FunctionType, 1 node per call, expression functions", "as 'FunctionType, 1 node per call', with the "
     "functions generated from expressions (two changes)", "functions"),
    ("elimfast's solver.solve, bare loop, expression functions", "elimfast's solve with the functions generated "
     "from expressions", "elimfast_solve"),
]


def setup():
    problem = kepler(ECCENTRICITY)
    method = ehbvm(12, 3)
    user = load_run(CONFIG).problem
    assert (user.y0 == problem.y0).all() and user.invariant_names == problem.invariant_names
    m = method
    tables = Tables(m.projection, m.Is, m.projection_hat, m.Is_hat, m.X, m.abs_projection_hat, m.predictor_nodes,
                    m.predictor_basis, m.newton_values, m.newton_vectors, m.newton_inverse, m.newton_weights,
                    m.Is_low, m.Is_hat_low)
    conserve_idx = np.array([problem.invariant_names.index(c) for c in CONSERVE], dtype=np.int64)
    return problem, user, method, tables, conserve_idx


def make_runner(kind, problem, tables, conserve_idx):
    """A function of no arguments running one whole run; returns (seconds, ((status, steps), iterations, y_final,
    alpha))."""
    y0 = problem.y0.copy()

    def outputs():
        return np.zeros(N), np.zeros(N_STEPS, dtype=np.int64), np.zeros((N_STEPS, len(CONSERVE)))

    simple = {"specialised": run_specialised, "runtime": run_runtime_sizes, "runtime_method": run_runtime_method,
              "runtime_state": run_runtime_state, "outlined": run_outlined, "outlined_once": run_outlined_once}
    if kind in simple:
        kernel = simple[kind]

        def call(y_final, iterations, alpha):
            return kernel(y0, H_STEP, N_STEPS, tables, TOL, MAX_ITER, y_final, iterations, alpha)
    elif kind in ("interface", "per_problem"):
        kernel = run_interface if kind == "interface" else run_per_problem

        def call(y_final, iterations, alpha):
            return kernel(problem.params, conserve_idx, y0, H_STEP, N_STEPS, tables, TOL, MAX_ITER, y_final,
                          iterations, alpha)
    else:
        python_function, function_types, functions = {
            "functions": (_run_functions, PER_NODE, (problem.grad_H, problem.grad_invariants)),
            "batched": (_run_batched, PER_K_NODES, (kepler_grad_H_nodes, kepler_grad_invariants_nodes)),
            "generic": (_run_generic, PER_NODE, (problem.grad_H, problem.grad_invariants)),
            "batched_generic": (_run_batched_generic, PER_K_NODES, (kepler_grad_H_nodes, kepler_grad_invariants_nodes)),
            "elimfast_solve": (_run_elimfast_solve, PER_NODE, (problem.grad_H, problem.grad_invariants)),
        }[kind]
        kernel = function_kernel(python_function, function_types, tables)

        def call(y_final, iterations, alpha):
            return kernel(*functions, problem.params, conserve_idx, y0, H_STEP, N_STEPS, tables, TOL, MAX_ITER,
                          y_final, iterations, alpha)

    def run():
        y_final, iterations, alpha = outputs()
        start = time.perf_counter()
        status, done = call(y_final, iterations, alpha)
        seconds = time.perf_counter() - start
        return seconds, ((status, done), iterations, y_final, alpha)
    return run


def elimfast_runner(problem, method, n_steps, kernel="shared"):
    """A whole elimfast.integrate call of n_steps steps (t_end = T_END for the whole run), on the
    shared kernel or the problem's own (solver.kernel, docs/solver.md#per-problem-kernel)."""
    span = {"t_end": T_END} if n_steps == N_STEPS else {"n_steps": n_steps}
    solver = SolverSettings(method="fixed_point", predictor=False, kernel=kernel)

    def run():
        start = time.perf_counter()
        result = elimfast.integrate(problem, method, H_STEP, conserve=CONSERVE, solver=solver,
                                    store_every=STORE_EVERY, **span)
        return time.perf_counter() - start, result
    return run


def invariant_errors(problem, y0, y):
    """|H(y) - H(y0)|, |L(y) - L(y0)|, |A_y(y) - A_y(y0)|."""
    y0, y = np.array(y0, dtype=np.float64), np.array(y, dtype=np.float64)   # writable: the signatures' arrays
    before, after = np.zeros(3), np.zeros(3)
    problem.invariants(y0, problem.params, before)
    problem.invariants(y, problem.params, after)
    return (abs(problem.H(y, problem.params) - problem.H(y0, problem.params)), abs(after[0] - before[0]),
            abs(after[2] - before[2]))


def load_average():
    return os.getloadavg()[0]


BUILTIN_RUN, USER_RUN = "elimfast, built-in Kepler", "elimfast, Kepler from expressions"
PER_PROBLEM_BUILTIN_RUN = "elimfast, per-problem kernel, built-in Kepler"
PER_PROBLEM_USER_RUN = "elimfast, per-problem kernel, Kepler from expressions"
ELIMFAST_RUNS = (BUILTIN_RUN, USER_RUN, PER_PROBLEM_BUILTIN_RUN, PER_PROBLEM_USER_RUN)
BASE = "specialised"


def measure(rounds):
    """One process's measurement: every entry compiled or loaded, then `rounds` interleaved rounds.

    Returns plain data: ns per iteration of every entry round by round (elimfast's kernel time:
    its call less the 1-step call of the same round, over the iterations less that step's), the
    whole-call times, the verification rows, the load average and how long it all took."""
    problem, user, method, tables, conserve_idx = setup()
    compile_start = time.perf_counter()
    entries = {   # label -> a whole run: () -> (seconds, Result or kernel outputs)
        BUILTIN_RUN: elimfast_runner(problem, method, N_STEPS),
        BUILTIN_RUN + ", 1 step": elimfast_runner(problem, method, 1),
        USER_RUN: elimfast_runner(user, method, N_STEPS),
        USER_RUN + ", 1 step": elimfast_runner(user, method, 1),
        PER_PROBLEM_BUILTIN_RUN: elimfast_runner(problem, method, N_STEPS, "per_problem"),
        PER_PROBLEM_BUILTIN_RUN + ", 1 step": elimfast_runner(problem, method, 1, "per_problem"),
        PER_PROBLEM_USER_RUN: elimfast_runner(user, method, N_STEPS, "per_problem"),
        PER_PROBLEM_USER_RUN + ", 1 step": elimfast_runner(user, method, 1, "per_problem"),
    }
    for label, _, kind in VARIANTS:
        entries[label] = make_runner(kind, problem, tables, conserve_idx)
    for label, _, kind in USER_VARIANTS:
        entries[label] = make_runner(kind, user, tables, conserve_idx)
    last = {}
    for label, run in entries.items():   # compile (the first time: up to a minute each) or load
        start = time.perf_counter()
        last[label] = run()
        print(f"  ready: {label} ({time.perf_counter() - start:.1f} s)", file=sys.stderr, flush=True)
    warm_up = time.perf_counter() - compile_start

    times = {label: [] for label in entries}
    loads = [load_average()]
    wall_start = time.perf_counter()
    order = list(entries)
    shuffle = random.Random(12).shuffle   # a new order every round: no entry always follows the same one
    for _ in range(rounds):
        shuffle(order)
        for label in order:
            seconds, payload = entries[label]()
            times[label].append(seconds)
            last[label] = (seconds, payload)
        loads.append(load_average())
    wall = time.perf_counter() - wall_start

    ns, iterations = {}, {}
    for label in ELIMFAST_RUNS:
        result = last[label][1]
        total, first = int(result.iterations.sum()), int(result.iterations[0])
        iterations[label] = total
        ns[label] = [(t - t1) / (total - first) * 1e9 for t, t1 in zip(times[label], times[label + ", 1 step"])]
        ns[label + " (whole call)"] = [t / total * 1e9 for t in times[label]]
    kernel_labels = [label for label, _, _ in VARIANTS + USER_VARIANTS]
    for label in kernel_labels:
        iterations[label] = int(last[label][1][1].sum())
        ns[label] = [t / iterations[label] * 1e9 for t in times[label]]

    reference, reference_user = last[BUILTIN_RUN][1], last[USER_RUN][1]
    user_labels = {label for label, _, _ in USER_VARIANTS}
    checks = []
    for label in kernel_labels:
        _, ((status, done), steps_iterations, y_final, alpha) = last[label]
        ref = reference_user if label in user_labels else reference
        checks.append([label, int(status), int(done), int(steps_iterations.sum()),
                       int(np.count_nonzero(steps_iterations != ref.iterations)),
                       float(np.max(np.abs(y_final - ref.y_final))), float(np.max(np.abs(alpha - ref.alpha))),
                       [float(e) for e in invariant_errors(problem, problem.y0, y_final)]])
    for label, result in ((BUILTIN_RUN, reference), (USER_RUN, reference_user)):
        checks.append([label, result.status, int(result.steps_done), int(result.iterations.sum()), None, None, None,
                       [float(e) for e in invariant_errors(problem, problem.y0, result.y_final)]])
    for label, ref in ((PER_PROBLEM_BUILTIN_RUN, reference), (PER_PROBLEM_USER_RUN, reference_user)):
        result = last[label][1]   # against the shared kernel's run of the same problem
        checks.append([label, result.status, int(result.steps_done), int(result.iterations.sum()),
                       int(np.count_nonzero(result.iterations != ref.iterations)),
                       float(np.max(np.abs(result.y_final - ref.y_final))), float(np.max(np.abs(result.alpha - ref.alpha))),
                       [float(e) for e in invariant_errors(problem, problem.y0, result.y_final)]])
    spec_iterations = last[BASE][1][1]
    return {
        "ns": ns, "iterations": iterations, "checks": checks,
        "whole_call_ms": {label: [t * 1e3 for t in times[label]] for label in (*ELIMFAST_RUNS, BASE)},
        "one_step_ms": {label: statistics.median(times[label + ", 1 step"]) * 1e3 for label in ELIMFAST_RUNS},
        "user_vs_builtin": [int(np.count_nonzero(reference_user.iterations != reference.iterations)),
                            float(np.max(np.abs(reference_user.y_final - reference.y_final)))],
        "iterations_per_step": [float(spec_iterations.mean()), int(spec_iterations.max())],
        "loads": loads, "wall": wall, "warm_up": warm_up, "rounds": rounds,
    }


def report(runs):
    """The markdown report of the measurements of several processes (measure's results)."""
    first = runs[0]

    def per_process(label):
        """Per process: (median ns/iteration, median over rounds of the ratio to the specialised kernel)."""
        values = []
        for run in runs:
            ns = run["ns"]
            values.append((statistics.median(ns[label]),
                           statistics.median(a / b for a, b in zip(ns[label], ns[BASE]))))
        return values

    def cells(label):
        values = per_process(label)
        ratios = [ratio for _, ratio in values]
        return (f"{statistics.median(median for median, _ in values):.0f} | {statistics.median(ratios):.2f} | "
                f"{min(ratios):.2f}-{max(ratios):.2f}")

    loads = [load for run in runs for load in run["loads"]]
    rounds = sum(run["rounds"] for run in runs)
    lines = [f"EHBVM(12,3) imposing {', '.join(CONSERVE)}, Kepler e = {ECCENTRICITY}, h = {H_STEP}, "
             f"t in [0, {T_END:g}] ({N_STEPS} steps), fixed point warm-started without the predictor, elimfast's "
             f"stopping rule. {len(runs)} processes one after the other, each {first['rounds']} interleaved rounds "
             f"(every entry once per round, in a shuffled order; {rounds} rounds in all). Machine: "
             f"{os.cpu_count()} cores ({platform.machine()}), shared with other work: load average (1 min) "
             f"{min(loads):.2f}-{max(loads):.2f} during the rounds ({sum(run['wall'] for run in runs):.0f} s). "
             f"Python {platform.python_version()}, Numba {numba.__version__}, NumPy {np.__version__}. Compile or "
             f"load and warm-up of the first process: {first['warm_up']:.0f} s.", "",
             "ns/iteration: the median over the processes of each process's median. Ratio: per iteration, to the "
             "specialised kernel, taken within each round; its median over each process's rounds, then the median "
             "and the range of those over the processes. The same compiled code measures a few percent apart "
             "from one process or session to the next (where code and data land in memory, the machine's other "
             "load), some rows up to 10%: treat differences below that as unresolved.", ""]

    lines += ["## elimfast against the specialised kernel", "",
              f"elimfast: `elimfast.integrate(problem, ehbvm(12, 3), {H_STEP}, t_end={T_END:g}, conserve={CONSERVE}, "
              f"solver=SolverSettings(method=\"fixed_point\", predictor=False, kernel=...), "
              f"store_every={STORE_EVERY})`, timed around the call; kernel 'shared' (the default) or 'per_problem' "
              "(docs/solver.md#per-problem-kernel). "
              "'kernel': less the same call for 1 step in the same round (the fixed cost of a call, "
              f"{first['one_step_ms'][BUILTIN_RUN]:.2f} ms built-in and {first['one_step_ms'][USER_RUN]:.2f} ms "
              "from expressions, medians of the first process) and that step's iterations.", "",
              "| run | whole call, median (min-max), first process | iterations | ns/iteration, whole call | "
              "ns/iteration, kernel | ratio | ratio over processes |", "|---|---|---|---|---|---|---|"]
    for label in (*ELIMFAST_RUNS, BASE):
        ms = first["whole_call_ms"][label]
        whole = statistics.median(statistics.median(run["ns"][label + " (whole call)" if label != BASE else label])
                                  for run in runs)
        name = "specialised kernel" if label == BASE else label
        lines.append(f"| {name} | {statistics.median(ms):.1f} ms ({min(ms):.1f}-{max(ms):.1f}) | "
                     f"{first['iterations'][label]} | {whole:.0f} | {cells(label)} |")

    lines += ["", "## Verification", "",
              "Each kernel against elimfast's run of the same problem (the expression rows against elimfast's run "
              "from expressions). 'steps differing': steps whose iteration count differs from elimfast's "
              "`Result.iterations`. The errors are |I(y(1000)) - I(y0)| of H, L and A_y.", "",
              "| kernel | status | steps | iterations | steps differing | max abs y(1000) - elimfast's | "
              "max abs alpha - elimfast's | H, L, A_y errors |", "|---|---|---|---|---|---|---|---|"]
    for label, status, done, total, differing, dy, dalpha, errors in first["checks"]:
        tail = f"{differing} | {dy:.1e} | {dalpha:.1e}" if differing is not None else "- | - | -"
        lines.append(f"| {label} | {status} | {done} | {total} | {tail} | " + ", ".join(f"{e:.1e}" for e in errors)
                     + " |")
    same = all(run["checks"] == first["checks"] for run in runs)
    differing, distance = first["user_vs_builtin"]
    mean, largest = first["iterations_per_step"]
    lines += ["", f"elimfast from expressions against built-in: {first['iterations'][USER_RUN]} against "
              f"{first['iterations'][BUILTIN_RUN]} iterations, {differing} steps with other counts, y(1000) apart "
              f"by {distance:.1e} (the generated functions round differently). Iterations per step: mean "
              f"{mean:.2f}, max {largest}. Every process: {'the same' if same else 'NOT the same'} table.", ""]

    lines += ["## Where the cost goes: variants of the specialised kernel", "",
              "The rows from 'problem interface, inlined' to 'outlined once' each change one thing in the "
              "specialised kernel; the rows below them combine several, or run elimfast's own code. Every kernel "
              "row takes the same iterations to the same trajectory, bit for bit (Verification).", "",
              "| variant | what changes | ns/iteration | ratio | ratio over processes |", "|---|---|---|---|---|"]
    for label, what, _ in VARIANTS + USER_VARIANTS:
        lines.append(f"| {label} | {what} | {cells(label)} |")
    for label in ELIMFAST_RUNS:
        lines.append(f"| {label} (kernel, from the first table) | time_loop, try_step, _attempt, solve | "
                     f"{cells(label)} |")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--processes", type=int, default=3, help="fresh processes, one after the other")
    parser.add_argument("--rounds", type=int, default=11, help="interleaved rounds per process (at least 9)")
    parser.add_argument("--markdown", type=Path, default=ROOT / "bench" / "results" / "specialised.md",
                        help="write the report here ('-': do not write)")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    rounds = max(9, args.rounds)
    if args.worker:
        print(json.dumps(measure(rounds)))
        return
    runs = []
    for index in range(max(1, args.processes)):
        print(f"process {index + 1} of {args.processes}", file=sys.stderr, flush=True)
        out = subprocess.run([sys.executable, __file__, "--worker", "--rounds", str(rounds)], check=True,
                             stdout=subprocess.PIPE, text=True)
        runs.append(json.loads(out.stdout))
    text = report(runs)
    print(text)
    if str(args.markdown) != "-":
        args.markdown.write_text("# elimfast against a hand-specialised kernel\n\nGenerated by "
                                 "`bench/specialised.py` (issue 12, item 1).\n\n" + text + "\n")


if __name__ == "__main__":
    main()
