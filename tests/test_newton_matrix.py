"""The simplified Newton matrix M = I - h X (x) J Hess(H)(y0) of docs/solver.md in its three
forms (kernels/solver.py): inverted eigen-blocks (small n), LU-factorised eigen-blocks (large
n), the whole real matrix (no eigenbasis, large s). Each applies M^-1 as numpy.linalg.solve
does on the matrix built here from the problem's Hessian, whatever the equilibration."""
import numpy as np
import pytest
from numba import njit

from elimfast.kernels import codes
from elimfast.kernels.solver import newton_factor, newton_solve
from elimfast.kernels.workspace import INVERSE_MAX_N, Tables, make_workspace
import elimfast
from elimfast.methods import ehbvm, gauss, hbvm
from elimfast.problems import fpu_beta, kepler, nbody


@njit(cache=False)
def _apply_inverse(grad_H, hess_H, params, y, h, tables, k, s, n_eigenvalues, rhs):
    """rhs <- M^-1 rhs as the solver does it: in the workspace's own delta, whose first s n entries
    are the increment and the rest (the secant history) must be left alone; returns (status,
    form, the rest untouched)."""
    work = make_workspace(y.shape[0], k, k, s, 0, codes.FAMILY_ELIM, 1, 0, n_eigenvalues)
    status = newton_factor(grad_H, hess_H, params, y, h, tables, work)
    size = rhs.shape[0]
    work.delta[:size] = rhs
    work.delta[size:] = 12345.0
    newton_solve(tables, work, work.delta)
    rhs[:] = work.delta[:size]
    rest_untouched = work.delta.shape[0] > size and np.all(work.delta[size:] == 12345.0)
    form = 0 if work.newton_blocks.shape[0] == 0 else (1 if work.newton_block_scratch.shape[0] > 0 else 2)
    return status, form, rest_untouched


def _tables(m):
    return Tables(m.projection, m.Is, m.projection_hat, m.Is_hat, m.X, m.abs_projection_hat, m.predictor_nodes,
                  m.predictor_basis, m.newton_values, m.newton_vectors, m.newton_inverse, m.newton_weights,
                  m.Is_low, m.Is_hat_low)


FULL, INVERTED, LU_BLOCKS = 0, 1, 2


@pytest.mark.parametrize("problem, method, h, blocks, form", [
    # Kepler from its pericentre, |J0| ~ 1/r^3 = 1e3: h |J0| from 0.1 to 30
    (kepler(0.9), ehbvm(12, 3), 0.01, True, INVERTED),      # one real and one complex block
    (kepler(0.9), hbvm(12, 6), 0.03, True, INVERTED),       # three complex blocks
    (kepler(0.9), hbvm(12, 3), 0.01, False, FULL),          # the whole matrix when asked
    (kepler(0.9), hbvm(24, 12), 0.0001, True, FULL),        # s = 12: no eigenbasis (cond(V) ~ 1e6)
    (fpu_beta(), hbvm(8, 4), 0.2, True, LU_BLOCKS),         # n = 16 > INVERSE_MAX_N
    (nbody(), hbvm(12, 3), 50.0, True, LU_BLOCKS),          # the solar system: scales 1e-11 to 30
])
def test_each_form_applies_the_inverse_of_the_newton_matrix(problem, method, h, blocks, form):
    y = problem.y0.copy()   # writable, as the kernels get it
    n, s = y.size, method.s
    assert (n > INVERSE_MAX_N) == (form == LU_BLOCKS)
    m = n // 2
    J = np.block([[np.zeros((m, m)), np.eye(m)], [-np.eye(m), np.zeros((m, m))]])
    M = np.eye(s * n) - h * np.kron(method.X, J @ problem.hessian(y))
    rng = np.random.default_rng(s * n)
    # the solver's right-hand sides are coefficient increments, in units of the state
    rhs = (rng.normal(size=(s, n)) * np.maximum(np.abs(y), 1e-3 * np.abs(y).max())).ravel()
    expected = np.linalg.solve(M, rhs)
    out = rhs.copy()
    status, used, rest_untouched = _apply_inverse(problem.grad_H, problem.hess_H, problem.params, y, h,
                                                  _tables(method), method.k, s,
                                                  method.newton_values.shape[0] if blocks else 0, out)
    assert status == codes.STATUS_OK and used == form and rest_untouched
    # Both are backward stable: in units of the state, where M is well conditioned (the solar
    # system's M is not, unscaled: cond 1e19), they differ by about eps cond, times cond(V)
    # for the block forms (methods/base.py: MAX_EIGENBASIS_CONDITION).
    f = np.abs(J @ problem.gradient(y))
    units = np.tile(np.maximum(np.abs(y), h * f), s)
    scaled = M / units[:, None] * units[None, :]
    bound = 100 * np.finfo(float).eps * np.linalg.cond(scaled)
    if form != FULL:
        bound *= np.linalg.cond(np.linalg.eig(method.X)[1])
    assert bound < 1e-9
    assert np.max(np.abs(out - expected) / units) <= bound * np.max(np.abs(expected) / units)


@pytest.mark.parametrize("method", [gauss(11), hbvm(24, 12)], ids=lambda m: m.name)
def test_methods_without_an_eigenbasis_run_with_newton_and_agree_with_the_fixed_point(method):
    """From s = 11 on X has no well-conditioned eigenbasis and simplified Newton factorises the
    whole (s n)^2 matrix. Its solve ran over the whole 3 s n of the workspace's delta, past the
    pivots, and every such method crashed the interpreter (a user trial: GAUSS(11) to GAUSS(40),
    HBVM(24,12), in integrate and in elimfast run). Fixed and adaptive steps now run, and take
    the fixed point's steps to round-off."""
    assert method.newton_values.shape[0] == 0
    p = kepler(0.6)
    newton = elimfast.integrate(p, method, 0.1, n_steps=50)
    fixed = elimfast.integrate(p, method, 0.1, n_steps=50, solver="fixed_point")
    assert newton.status == fixed.status == "complete"
    assert np.max(np.abs(newton.y_final - fixed.y_final)) < 1e-13
    assert max(newton.invariant_errors().values()) < 1e-12 or method.k == method.s   # GAUSS keeps only L
    assert newton.iterations.mean() < fixed.iterations.mean()
    adaptive = elimfast.integrate(p, method, t_end=2.0, rtol=1e-12)
    assert adaptive.status == "complete" and abs(adaptive.t_final - 2.0) < 1e-15
