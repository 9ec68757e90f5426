"""The Numba kernels against the plain NumPy reference (tests/reference.py), step by step."""
import math

import numpy as np
import pytest

import elimfast
from elimfast.methods import ehbvm, elim, gauss, ghbvm, hbvm, lim

import reference

N_STEPS = 50
KEPLER_COLUMNS = {"angular_momentum": 0, "lrl_x": 1, "lrl_y": 2}

CASES = [
    (gauss(3), (), "stable"),
    (hbvm(12, 3), (), "stable"),
    (hbvm(7, 4), (), "stable"),
    (ehbvm(12, 3), ("angular_momentum",), "stable"),
    (ehbvm(12, 3), ("angular_momentum", "lrl_y"), "stable"),
    (ehbvm(12, 3), ("angular_momentum", "lrl_y"), "literal"),
    (ehbvm(12, 4), ("angular_momentum",), "stable"),
    (elim(8, 12, 3), ("angular_momentum",), "stable"),
    (elim(16, 12, 3), ("lrl_y",), "stable"),
    (elim(3, 12, 3), ("angular_momentum",), "stable"),
    (elim(4, 12, 4), ("angular_momentum", "lrl_y"), "stable"),
    (elim(8, 12, 3), ("lrl_x", "lrl_y"), "literal"),
    (ghbvm(12, 3), ("angular_momentum",), "stable"),
    (ghbvm(12, 3), ("angular_momentum", "lrl_y"), "stable"),
    (lim(8, 12, 3), ("lrl_y",), "stable"),
    (ghbvm(6, 2), (), "stable"),
]


def reference_step(method, conserve, rhs):
    columns = [KEPLER_COLUMNS[name] for name in conserve]
    grad_L = lambda y: reference.kepler_grad_L(y)[:, columns]  # noqa: E731
    if method.family in ("gauss", "hbvm"):
        return lambda y: (reference.hbvm_step(reference.kepler_grad_H, y, method_h, method.k, method.s)[0], None)
    if method.family in ("elim", "ehbvm"):
        return lambda y: reference.elim_step(reference.kepler_grad_H, grad_L, y, method_h, method.r, method.k,
                                             method.s, rhs=rhs)[:2]
    return lambda y: reference.lim_step(reference.kepler_grad_H, grad_L, y, method_h, method.r, method.k,
                                        method.s)[:2]


method_h = math.pi / 30


@pytest.mark.parametrize("method,conserve,rhs", CASES,
                         ids=[f"{m.name}-{'+'.join(c) or 'none'}-{r}" for m, c, r in CASES])
def test_kernel_matches_reference_at_every_step(kepler, method, conserve, rhs):
    result = elimfast.integrate(kepler, method, method_h, n_steps=N_STEPS, conserve=conserve, rhs=rhs)
    step = reference_step(method, conserve, rhs)
    y = reference.kepler_y0(0.6)
    np.testing.assert_allclose(result.y[0], y, rtol=0, atol=1e-15)
    multipliers = result.alpha if result.alpha is not None else result.lam
    for n in range(N_STEPS):
        y, multiplier = step(y)
        assert np.max(np.abs(result.y[n + 1] - y)) < 1e-13, (method.name, n + 1)
        if multiplier is not None and len(multiplier):
            # The literal alpha is bvec / Gamma with Gamma = O(h^(2s-2)) (docs/methods.md#stable-right-hand-side): two
            # iterates 1e-12 apart (both "converged") move it by about 1e-12 h^-(2s-2).
            # Two such iterates give literal alphas that agree to about 3 digits only:
            # that noise is what docs/methods.md#stable-right-hand-side is about.
            if rhs == "literal" or method.r > method.k:   # r > k: the paper's sum whatever rhs says
                np.testing.assert_allclose(multipliers[n], multiplier, rtol=1e-3,
                                           atol=1e-12 * method_h ** -(2 * method.s - 2))
            else:
                np.testing.assert_allclose(multipliers[n], multiplier, rtol=1e-6, atol=1e-12)


def test_reference_quartic_energy_agrees(quartic):
    result = elimfast.integrate(quartic, hbvm(6, 3), 0.1, n_steps=N_STEPS)
    y = np.array(quartic.y0)
    for n in range(N_STEPS):
        y = reference.hbvm_step(reference.quartic_grad_H, y, 0.1, 6, 3)[0]
        assert np.max(np.abs(result.y[n + 1] - y)) < 1e-13


def test_problem_functions_match_reference_formulas(kepler):
    rng = np.random.default_rng(7)
    for _ in range(20):
        y = rng.normal(size=4)
        assert kepler.hamiltonian(y) == pytest.approx(reference.kepler_H(y), rel=1e-14)
        np.testing.assert_allclose(kepler.gradient(y), reference.kepler_grad_H(y), rtol=1e-13, atol=1e-14)
        values = kepler.invariant_values(y)
        np.testing.assert_allclose([values[n] for n in KEPLER_COLUMNS], reference.kepler_L(y), rtol=1e-13)
        np.testing.assert_allclose(kepler.invariant_gradients(y).T, reference.kepler_grad_L(y), rtol=1e-12,
                                   atol=1e-13)
