"""The paper's published numbers (docs/methods.md#the-papers-numbers) and the stable right-hand
side (docs/methods.md#stable-right-hand-side)."""
import math

import numpy as np
import pytest

import elimfast
from elimfast.methods import ehbvm, gauss, ghbvm, hbvm

L1, L2 = "angular_momentum", "lrl_y"
COLUMNS = {
    "GAUSS3": (lambda: gauss(3), ()),
    "HBVM(12,3)": (lambda: hbvm(12, 3), ()),
    "EHBVM(12,3) L1": (lambda: ehbvm(12, 3), (L1,)),
    "GHBVM(12,3) L1": (lambda: ghbvm(12, 3), (L1,)),
    "EHBVM(12,3) L1,L2": (lambda: ehbvm(12, 3), (L1, L2)),
    "GHBVM(12,3) L1,L2": (lambda: ghbvm(12, 3), (L1, L2)),
}
TABLE_1 = {  # docs/methods.md#the-papers-numbers: max-norm error of y_N - y0 at T = 20 pi
    30: (1.942e-03, 4.587e-05, 1.017e-05, 4.049e-05, 1.928e-05, 4.367e-05),
    60: (2.817e-05, 7.375e-07, 1.644e-07, 6.505e-07, 3.052e-07, 6.868e-07),
    120: (4.346e-07, 1.161e-08, 2.591e-09, 1.023e-08, 4.785e-09, 1.075e-08),
}
TABLE_3 = {30: (4.530e-3, 1.246e-2), 60: (1.155e-3, 3.195e-3), 120: (2.902e-4, 8.040e-4)}
TABLE_2_PI_30 = (6705, 6775, 7256, 6779, 7474, 6781)


def run_column(kepler, column, divisions, **solver):
    make, conserve = COLUMNS[column]
    h = math.pi / divisions
    return elimfast.integrate(kepler, make(), h, t_end=20 * math.pi, conserve=conserve, **solver)


@pytest.mark.parametrize("divisions", sorted(TABLE_1))
def test_table_1_errors_and_table_3_alpha(kepler, divisions):
    for column, expected in zip(COLUMNS, TABLE_1[divisions]):
        result = run_column(kepler, column, divisions)
        error = float(np.max(np.abs(result.y_final - kepler.y0)))
        assert abs(error / expected - 1.0) < 2e-3, (column, divisions, error, expected)
        if column.startswith("EHBVM"):
            alpha = float(np.max(np.abs(result.alpha)))
            expected_alpha = TABLE_3[divisions][0 if column.endswith("L1") else 1]
            assert abs(alpha / expected_alpha - 1.0) < 2e-3, (column, divisions, alpha, expected_alpha)


def test_table_2_iteration_totals(kepler, capsys):
    """Table 2 counts the paper's fixed-point iterations (each step warm-started from the
    previous one, no predictor); elimfast's default, simplified Newton, needs about half."""
    rows = []
    for column, paper in zip(COLUMNS, TABLE_2_PI_30):
        total = int(run_column(kepler, column, 30, solver="fixed_point", predictor=False).iterations.sum())
        rows.append((column, total, paper))
        newton = int(run_column(kepler, column, 30).iterations.sum())
        assert newton < 0.7 * total, (column, newton, total)
    with capsys.disabled():
        print("\nTable 2 at h = pi/30 (fixed point, stable right-hand side, warm start):")
        for column, total, paper in rows:
            print(f"  {column:20s} elimfast {total:6d}   paper {paper:6d}   ratio {total / paper:.3f}")
    for column, total, paper in rows:
        assert abs(total / paper - 1.0) < 0.15, (column, total, paper)
    # With the stable form EHBVM needs about as many iterations as HBVM (docs/methods.md#stable-right-hand-side).
    totals = dict((c, t) for c, t, _ in rows)
    assert totals["EHBVM(12,3) L1,L2"] < 1.05 * totals["HBVM(12,3)"]


def test_stable_rhs_keeps_ehbvm_12_4_converging_and_literal_breaks_down(kepler):
    """Spec 3b: EHBVM(12,4) imposing L1, e = 0.6, h = pi/60, 1200 steps."""
    stable = elimfast.integrate(kepler, ehbvm(12, 4), math.pi / 60, n_steps=1200, conserve=[L1])
    assert stable.iterations.max() <= 20
    assert abs(np.max(np.abs(stable.alpha)) / 1.45e-3 - 1.0) < 0.05
    assert stable.invariant_errors()[L1] < 1e-13
    try:
        literal = elimfast.integrate(kepler, ehbvm(12, 4), math.pi / 60, n_steps=1200, conserve=[L1],
                                     rhs="literal")
        # NaN: a substep taken without imposing L (docs/solver.md#a-substep-without-imposing)
        literal_alpha = float(np.nanmax(np.abs(literal.alpha)))
    except elimfast.ConvergenceError as error:  # hitting the iteration cap is the breakdown too
        literal_alpha = float(np.nanmax(np.abs(error.result.alpha)))
    # alpha is rounding noise: two orders of magnitude above its O(h^2) value
    assert literal_alpha > 30 * 1.45e-3


@pytest.mark.slow
def test_long_run_gauss_energy_bounded_and_ehbvm_keeps_everything(kepler):
    """Spec 6, long run: h = 0.1 on [0, 1000]."""
    gauss_run = elimfast.integrate(kepler, gauss(3), 0.1, t_end=1000.0, store_every=10)
    H_error = np.abs(gauss_run.invariants["H"] - gauss_run.invariants["H"][0])
    assert H_error.max() > 1e-8
    # bounded: the second half of the run is no worse than the first half, to within 10%
    half = H_error.size // 2
    assert H_error[half:].max() < 1.1 * H_error[:half].max()
    ehbvm_run = elimfast.integrate(kepler, ehbvm(12, 3), 0.1, t_end=1000.0, conserve=[L1, L2])
    errors = ehbvm_run.invariant_errors()
    assert errors["H"] < 1e-11 and errors[L1] < 1e-11 and errors[L2] < 1e-11, errors
