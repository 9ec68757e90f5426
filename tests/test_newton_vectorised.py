"""solver.solve_inverted, the inverse form of newton_solve, computes four components at a time in
vector registers (kernels/simd.py): each lane must do the scalar code's operations in their order,
Numba's complex products included, so that every increment is the scalar loops' bit for bit (the
runs' trajectories and resume depend on it), for every size n (a multiple of 4, the scalar tail,
both) and s, compiled and in the interpreter. Also newton_factor's split copy of its inverses."""
import os
import subprocess
import sys

import numba
import numpy as np
import pytest
from numba import njit

from elimfast.kernels.linalg import invert
from elimfast.kernels.solver import _newton_factor_scaled, _secant_update, solve_inverted


@njit(cache=False, error_model="numpy")
def scalar_solve(V, V_inverse, weights, values, blocks, real_inverse, unit, delta, s):
    """newton_solve's inverse form as it was before solve_inverted (complex blocks, scalar loops)."""
    n = unit.shape[0]
    rhs = np.zeros((values.shape[0], n), dtype=np.complex128)
    for b in range(values.shape[0]):
        for p in range(n):
            acc_re = 0.0
            acc_im = 0.0
            for j in range(s):
                x = delta[j * n + p]
                acc_re += V_inverse[b, j].real * x
                acc_im += V_inverse[b, j].imag * x
            rhs[b, p] = complex(acc_re / unit[p], acc_im / unit[p])
    for i in range(s * n):
        delta[i] = 0.0
    for b in range(values.shape[0]):
        if values[b].imag == 0.0 and real_inverse.shape[0] > 0:
            for p in range(n):
                z_re = 0.0
                for q in range(n):
                    z_re += real_inverse[p, q] * rhs[b, q].real
                z_re *= weights[b] * unit[p]
                for j in range(s):
                    delta[j * n + p] += V[j, b].real * z_re
            continue
        inverse = blocks[b]
        for p in range(n):
            z = 0.0 + 0.0j
            for q in range(n):
                z += inverse[p, q] * rhs[b, q]
            z *= weights[b] * unit[p]
            for j in range(s):
                delta[j * n + p] += (V[j, b] * z).real


@njit(cache=False, error_model="numpy")
def compiled_solve_inverted(V, V_inverse, weights, values, real_block, unit, split, rhs, delta, s):
    solve_inverted(V, V_inverse, weights, values, real_block, unit, split, rhs, delta, s)


def split_inverses(values, blocks, real_inverse, n):
    """The transposed real/imaginary copy newton_factor writes into work.newton_inverse_split."""
    split = np.zeros((2 * values.shape[0] * n, n))
    for b in range(values.shape[0]):
        if values[b].imag == 0.0 and real_inverse.shape[0] > 0:
            split[2 * b * n:2 * b * n + n] = real_inverse.T
        else:
            split[2 * b * n:2 * b * n + n] = blocks[b].real.T
            split[(2 * b + 1) * n:(2 * b + 2) * n] = blocks[b].imag.T
    return split


def _values(rng, shape):
    # widely spread magnitudes and signs, so that every rounding shows
    return rng.normal(size=shape) * 10.0 ** rng.integers(-12, 4, size=shape)


def _complex(rng, shape):
    return _values(rng, shape) + 1j * _values(rng, shape)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7, 8, 9, 12])
@pytest.mark.parametrize("s", [1, 2, 3, 4, 5, 6])
def test_solve_inverted_is_the_scalar_solve_bit_for_bit(n, s):
    rng = np.random.default_rng(100 * n + s)
    n_b = (s + 1) // 2
    values = _complex(rng, n_b)
    weights = np.full(n_b, 2.0)
    if s % 2 == 1:
        values[n_b // 2] = values[n_b // 2].real   # the real eigenvalue, anywhere among the pairs
        weights[n_b // 2] = 1.0
    real_inverse = _values(rng, (n, n)) if s % 2 == 1 else np.zeros((0, 0))
    V = _complex(rng, (s, n_b))
    V_inverse = _complex(rng, (n_b, s))
    blocks = _complex(rng, (n_b, n, n))
    unit = np.abs(_values(rng, n)) + 1e-300
    delta = np.full(3 * s * n, np.nan)
    delta[:s * n] = _values(rng, s * n)
    delta[s * n + 1:s * n + 3] = 0.0   # with zeros among the history, which stays untouched
    expected = delta.copy()
    scalar_solve(V, V_inverse, weights, values, blocks, real_inverse, unit, expected, s)
    split = split_inverses(values, blocks, real_inverse, n)
    for function in (compiled_solve_inverted, getattr(solve_inverted, "py_func", solve_inverted)):
        out = delta.copy()
        rhs = np.full((2 * n_b, n), np.nan)
        function(V, V_inverse, weights, values, real_inverse.shape[0] > 0, unit, split, rhs, out, s)
        assert out.tobytes() == expected.tobytes(), function


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7, 8, 9, 12])
@pytest.mark.parametrize("kind", ["real", "complex"])
def test_vectorised_inverses_are_invert_bit_for_bit(n, kind):
    """linalg.invert_real and invert_complex (newton_factor's blocks) against linalg.invert: the same
    inverse bit for bit, the same status, on well and badly conditioned matrices, with row swaps
    (random entries), zero multipliers (a triangular matrix) and a singular one."""
    from elimfast.kernels.linalg import invert_complex, invert_real
    vectorised = invert_real if kind == "real" else invert_complex
    rng = np.random.default_rng(10 * n + (kind == "complex"))
    matrices = []
    for trial in range(4):
        a = _values(rng, (n, n)) if kind == "real" else _complex(rng, (n, n))
        if trial == 1:
            a = np.eye(n) + 0.1 * a / np.abs(a).max()   # the Newton blocks' shape: I - h lambda J0~
        if trial == 2:
            a = np.triu(a) + np.eye(n) * (1 + np.abs(a).max())   # zero multipliers below the diagonal
        matrices.append(np.ascontiguousarray(a))
    singular = matrices[0].copy()
    singular[-1] = singular[0]
    matrices.append(singular)
    for a in matrices:
        # compiled against compiled (interpreted against interpreted: test_interpreted, under
        # NUMBA_DISABLE_JIT=1; a py_func here would call the compiled column helpers, and 1 / a_kk
        # is Numba's complex division in one and NumPy's in the other)
        for reference, function in ((invert, vectorised),):
            expected = np.full((n, n), np.nan, dtype=a.dtype)
            status = reference(a.copy(), expected)
            out = np.full((n, n), np.nan, dtype=a.dtype)
            assert function(a.copy(), out) == status, function
            if status == 0:
                assert out.tobytes() == expected.tobytes(), function


@njit(cache=False, error_model="numpy")
def scalar_secant(h, scale, delta, coef, component, have_history, d_before, s, n):
    """solver._secant_update as it was before its loops over p were vectorised."""
    sn = s * n
    d = 0.0
    for p in range(n):
        largest_p = 0.0
        for j in range(s):
            value = abs(h * delta[j * n + p]) / scale[p]
            if not (value <= largest_p):
                largest_p = value
        component[p] = largest_p
        if not (largest_p <= d):
            d = largest_p
    weight = 0.0
    if have_history and d > 1e-13 and d > 1e-3 * d_before and d <= 1e308:
        along = 0.0
        squared = 0.0
        size = 0.0
        for p in range(n):
            unit = (h / scale[p]) ** 2
            for j in range(s):
                i = j * n + p
                difference = delta[i] - delta[2 * sn + i]
                along += unit * difference * delta[i]
                squared += unit * difference * difference
                size += unit * delta[i] * delta[i]
        if squared > 0.0 and along * along > 0.9 * squared * size:
            weight = along / squared
            if not (abs(weight) < 1e3):
                weight = 0.0
    for j in range(s):
        for p in range(n):
            i = j * n + p
            step = delta[i]
            if weight != 0.0:
                step -= weight * ((coef[j, p] - delta[sn + i]) + (delta[i] - delta[2 * sn + i]))
            delta[sn + i] = coef[j, p]
            delta[2 * sn + i] = delta[i]
            coef[j, p] += step
    return d


@njit(cache=False, error_model="numpy")
def compiled_secant(h, scale, delta, coef, component, have_history, d_before, s, n):
    return _secant_update(h, scale, delta, coef, component, have_history, d_before, s, n)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 8, 9, 12])
@pytest.mark.parametrize("s", [1, 2, 3, 4, 5, 6])
def test_secant_update_is_the_scalar_one_bit_for_bit(n, s):
    rng = np.random.default_rng(1000 + 10 * n + s)
    scale = np.abs(_values(rng, n)) + 1e-300
    coef = _values(rng, (s, n))
    for case in range(4):
        delta = _values(rng, 3 * s * n)
        if case == 1:   # a slow mode: the increment nearly parallel to its change, a secant step taken
            delta[2 * s * n:] = 1.01 * delta[:s * n]
        if case == 2:
            delta[1] = np.nan
        if case == 3:
            delta[:s * n] = 0.0
        for have_history in (False, True):
            d_before = 1e-6 if case != 1 else 1.0
            expected_delta, expected_coef, expected_component = delta.copy(), coef.copy(), np.full(n, -1.0)
            expected = scalar_secant(0.1, scale, expected_delta, expected_coef, expected_component, have_history,
                                     d_before, s, n)
            for function in (compiled_secant, getattr(_secant_update, "py_func", _secant_update)):
                out_delta, out_coef, out_component = delta.copy(), coef.copy(), np.full(n, -1.0)
                d = function(0.1, scale, out_delta, out_coef, out_component, have_history, d_before, s, n)
                assert np.array(d).tobytes() == np.array(expected).tobytes(), function
                for got, want in ((out_delta, expected_delta), (out_coef, expected_coef),
                                  (out_component, expected_component)):
                    assert got.tobytes() == want.tobytes(), function


@njit(cache=False, error_model="numpy")
def scalar_factor(hessian, unit, h, values, n):
    """newton_factor's J0~ and inverted blocks as they were built before (scalar loops, linalg.invert)."""
    from_invert = np.zeros((values.shape[0], n, n), dtype=np.complex128)
    real_inverse = np.zeros((n, n))
    jacobian = np.zeros((n, n))
    m = n // 2
    for p in range(m):
        inverse_q, inverse_p = 1.0 / unit[p], 1.0 / unit[m + p]
        for q in range(n):
            jacobian[p, q] = hessian[m + p, q] * unit[q] * inverse_q
            jacobian[m + p, q] = -hessian[p, q] * unit[q] * inverse_p
    for b in range(values.shape[0]):
        if values[b].imag == 0.0:
            real_factor = -h * values[b].real
            real_block = np.zeros((n, n))
            for p in range(n):
                for q in range(n):
                    real_block[p, q] = real_factor * jacobian[p, q]
                real_block[p, p] += 1.0
            invert(real_block, real_inverse)
            continue
        factor = -h * values[b]
        block = np.zeros((n, n), dtype=np.complex128)
        for p in range(n):
            for q in range(n):
                block[p, q] = factor * jacobian[p, q]
            block[p, p] += 1.0
        invert(block, from_invert[b])
    return jacobian, from_invert, real_inverse


@njit(cache=False, error_model="numpy")
def compiled_factor(y, h, tables, work):
    return _newton_factor_scaled(y, h, tables, work)


@pytest.mark.parametrize("n", [2, 4, 6, 8])
@pytest.mark.parametrize("s", [1, 2, 3, 4, 5, 6])
def test_newton_factor_blocks_are_the_scalar_ones_bit_for_bit(n, s):
    """J0~, the inverted blocks (vectorised construction, invert_real/invert_complex) and their split
    copy against the scalar construction and linalg.invert."""
    from elimfast.kernels import codes
    from elimfast.kernels.workspace import Tables, make_workspace
    from elimfast.methods import hbvm
    m = hbvm(12, s)
    tables = Tables(m.projection, m.Is, m.projection_hat, m.Is_hat, m.X, m.abs_projection_hat, m.predictor_nodes,
                    m.predictor_basis, m.newton_values, m.newton_vectors, m.newton_inverse, m.newton_weights,
                    m.Is_low, m.Is_hat_low)
    rng = np.random.default_rng(10 * n + s)
    work = make_workspace(n, m.k, m.k, s, 0, codes.FAMILY_ELIM, 1, 0, m.newton_values.shape[0])
    assert work.newton_block_scratch.shape[0] == n   # the inverse form
    hessian = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-3, 2, size=(n, n))
    hessian = hessian + hessian.T
    unit = 10.0 ** rng.uniform(-2, 2, size=n)
    work.hessian[:] = hessian
    work.newton_scale[:] = unit
    h = 0.1
    assert compiled_factor(np.zeros(n), h, tables, work) == codes.STATUS_OK
    jacobian, blocks, real_inverse = scalar_factor(hessian, unit, h, m.newton_values, n)
    assert work.jacobian.tobytes() == jacobian.tobytes()
    for b in range(m.newton_values.shape[0]):
        rows = work.newton_inverse_split[2 * b * n:2 * b * n + 2 * n]
        if m.newton_values[b].imag == 0.0:
            assert work.newton_real_inverse.tobytes() == real_inverse.tobytes()
            assert np.ascontiguousarray(rows[:n].T).tobytes() == real_inverse.tobytes()
        else:
            assert work.newton_blocks[b].tobytes() == blocks[b].tobytes()
            assert np.ascontiguousarray(rows[:n].T).tobytes() == blocks[b].real.copy().tobytes()
            assert np.ascontiguousarray(rows[n:].T).tobytes() == blocks[b].imag.copy().tobytes()


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 8, 9])
def test_invert_pair_is_the_two_inverses_bit_for_bit(n):
    """linalg.invert_pair, newton_factor's real and first complex block side by side, against
    invert_real and invert_complex one after the other (and so against linalg.invert)."""
    from elimfast.kernels.linalg import invert_complex, invert_pair, invert_real
    rng = np.random.default_rng(700 + n)
    for trial in range(4):
        real = np.eye(n) + 0.3 * rng.normal(size=(n, n))
        cplx = np.eye(n) + 0.3 * (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n)))
        if trial == 3:
            cplx[-1] = cplx[0]   # singular: the status says so
        for pair, one_real, one_complex in ((invert_pair, invert_real, invert_complex),):
            want_real, want_complex = np.full((n, n), np.nan), np.full((n, n), np.nan, dtype=complex)
            status = one_real(real.copy(), want_real) | one_complex(cplx.copy(), want_complex)
            got_real, got_complex = np.full((n, n), np.nan), np.full((n, n), np.nan, dtype=complex)
            assert pair(real.copy(), got_real, cplx.copy(), got_complex) == status
            if status == 0:
                assert got_real.tobytes() == want_real.tobytes()
                assert got_complex.tobytes() == want_complex.tobytes()


@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="this is the interpreted run")
def test_interpreted():
    """The tests above with Numba's JIT disabled (NUMBA_DISABLE_JIT=1): the plain Python of every
    routine (simd's NumPy lanes) against the plain scalar loops, bit for bit."""
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    done = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", __file__,
                           "-k", "not test_interpreted"],
                          env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
