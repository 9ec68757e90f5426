"""The built-in problem library (issue 3, item 5).

For every built-in: its gradients against central differences, its declared invariants
against the invariant identity grad L^T J grad H = 0 (docs/methods.md#notation), and a short run in
which EHBVM imposing the invariants keeps them to round-off (docs/methods.md#elim) while HBVM
of the same (k, s) does not, where that is true. Linear invariants (total momenta,
tr L of Toda) are kept by every Runge-Kutta method and cannot be imposed by ELIM/EHBVM
(their phi_j, j >= 1, vanish, so Gamma is singular): they are checked as kept, and imposed
with GHBVM instead. Problems without invariants test H conservation by HBVM.
"""
import importlib
import math

import numpy as np
import pytest

import elimfast
from elimfast import ConvergenceError, problems
from elimfast.methods import ehbvm, gauss, ghbvm, hbvm
from elimfast.problems import PROBLEMS, Problem

# The package exports each constructor under its module's name, so reach modules through importlib.
kepler_module = importlib.import_module("elimfast.problems.kepler")

EPS = np.finfo(float).eps
N_RANDOM_POINTS = 4
GRADIENT_RTOL = 1e-6           # central differences with steps ~ 1e-5: truncation ~ 1e-10
INVARIANT_IDENTITY_TOL = 1e-12  # |grad L^T J grad H| / (|grad L| |grad H|), round-off is ~1e-16
ROUND_OFF = 1e-13              # relative drift of an invariant over the short runs below
NOT_KEPT = 1e-10               # relative drift that is clearly truncation error, not round-off

NEW_BUILTINS = ("perturbed_kepler", "henon_heiles", "fpu_beta", "toda", "nbody", "pendulum")

# Each built-in in the variants that have different functions or invariants.
CASES = {
    "perturbed_kepler": lambda: problems.perturbed_kepler(),
    "henon_heiles": lambda: problems.henon_heiles(),
    "fpu_beta_periodic": lambda: problems.fpu_beta(),
    "fpu_beta_fixed": lambda: problems.fpu_beta(boundary="fixed"),
    "toda_4": lambda: problems.toda(4),
    "toda_5": lambda: problems.toda(5),
    "nbody_solar_system": lambda: problems.nbody(),
    "nbody_three_body": lambda: three_body(),
    "pendulum": lambda: problems.pendulum(omega=1.3),
}


def three_body() -> Problem:
    """Three bodies with G = 1 on inclined, eccentric orbits: the angular momentum
    vector is far from any coordinate axis, so all three components can be imposed."""
    return problems.nbody(masses=[1.0, 0.3, 0.1],
                          positions=[[0.0, 0.0, 0.0], [1.0, 0.2, 0.3], [-0.5, 1.6, -0.4]],
                          velocities=[[0.0, -0.1, 0.05], [0.1, 0.9, 0.3], [-0.6, -0.2, 0.35]], G=1.0)


@pytest.fixture(scope="module", params=list(CASES))
def case(request):
    return CASES[request.param]()


# --- helpers ---------------------------------------------------------------------------

def block_scales(y: np.ndarray) -> np.ndarray:
    """Per component: the rms of its block (q or p), or of y if that block is zero."""
    m = y.size // 2
    overall = math.sqrt(np.mean(y * y)) or 1.0
    scales = np.empty_like(y)
    for block in (slice(0, m), slice(m, 2 * m)):
        scales[block] = math.sqrt(np.mean(y[block] ** 2)) or overall
    return scales


def points_near_y0(problem: Problem, seed: int) -> list[np.ndarray]:
    """y0 and a few seeded random points within about 5% of it (per component)."""
    rng = np.random.default_rng(seed)
    y0 = problem.y0
    sigma = 0.05 * np.maximum(np.abs(y0), block_scales(y0))
    return [y0.copy()] + [y0 + sigma * rng.standard_normal(y0.size) for _ in range(N_RANDOM_POINTS)]


def check_gradient(f, grad, y, what):
    """Central differences of the scalar f against grad (both at y), component by component.

    Step 1e-5 times the component's scale: truncation error ~ 1e-10 relative; the rounding
    error of the difference quotient, ~ eps |f| / step, is allowed for with a margin.
    """
    steps = 1e-5 * np.maximum(np.abs(y), block_scales(y))
    fd = np.empty_like(y)
    magnitude = abs(f(y))
    for i in range(y.size):
        plus, minus = y.copy(), y.copy()
        plus[i] += steps[i]
        minus[i] -= steps[i]
        f_plus, f_minus = f(plus), f(minus)
        fd[i] = (f_plus - f_minus) / (plus[i] - minus[i])
        magnitude = max(magnitude, abs(f_plus), abs(f_minus))
    tolerance = GRADIENT_RTOL * np.abs(grad) + 1e3 * EPS * magnitude / steps
    bad = np.flatnonzero(np.abs(fd - grad) > tolerance)
    assert bad.size == 0, (f"{what}: gradient differs from central differences at components {bad.tolist()}: "
                           f"analytic {grad[bad]}, differences {fd[bad]}")


def invariant_identity_residuals(problem: Problem, y: np.ndarray) -> np.ndarray:
    """|grad L_i^T J grad H| / (|grad L_i| |grad H|) for every declared invariant (docs/methods.md#notation)."""
    m = problem.degrees_of_freedom
    g = problem.gradient(y)
    J_grad_H = np.concatenate((g[m:], -g[:m]))
    grads = problem.invariant_gradients(y)
    norms = np.linalg.norm(grads, axis=1) * np.linalg.norm(g)
    return np.abs(grads @ J_grad_H) / np.where(norms > 0.0, norms, 1.0)


def drift(result, name) -> float:
    """max |I(t) - I(0)| / |I(0)| over the stored samples."""
    values = result.invariants[name]
    return float(np.max(np.abs(values - values[0])) / abs(values[0]))


def drifts(result, names) -> dict[str, float]:
    return {name: drift(result, name) for name in names}


# --- the library as a whole ----------------------------------------------------------------

def test_registry_holds_every_builtin_under_its_own_name():
    for name in ("kepler", "harmonic_oscillator", "quartic_oscillator", "central_quartic") + NEW_BUILTINS:
        problem = PROBLEMS[name]()
        assert isinstance(problem, Problem) and problem.name == name and problem.description
        assert getattr(problems, name) is PROBLEMS[name]
        assert name in problems.__all__


@pytest.mark.parametrize("name", NEW_BUILTINS)
def test_each_builtin_module_documents_formulas_and_a_reference(name):
    module = importlib.import_module(f"elimfast.problems.{name}")
    doc = module.__doc__
    assert "H = " in doc and ("Reference" in doc or "References" in doc), name


def test_gradients_match_central_differences(case):
    for y in points_near_y0(case, seed=1):
        check_gradient(case.hamiltonian, case.gradient(y), y, f"{case.name}: grad H")
        grads = case.invariant_gradients(y)
        for i, name in enumerate(case.invariant_names):
            check_gradient(lambda z: case.invariant_values(z)[name], grads[i], y, f"{case.name}: grad {name}")


def test_declared_invariants_satisfy_the_invariant_identity(case):
    for y in points_near_y0(case, seed=2):
        residuals = invariant_identity_residuals(case, y)
        assert np.all(residuals <= INVARIANT_IDENTITY_TOL), dict(zip(case.invariant_names, residuals))


def test_the_identity_check_rejects_a_non_invariant():
    """The LRL vector of Kepler is not conserved once delta != 0: the helper must see it."""
    perturbed = problems.perturbed_kepler(0.6, delta=0.01)
    y = perturbed.y0 + 0.01
    g = perturbed.gradient(y)
    lrl_grads = np.empty((3, 4))
    kepler_module.grad_invariants(y, np.zeros(0), lrl_grads)
    J_grad_H = np.concatenate((g[2:], -g[:2]))
    residual = abs(lrl_grads[2] @ J_grad_H) / (np.linalg.norm(lrl_grads[2]) * np.linalg.norm(g))
    assert residual > 1e-4
    assert invariant_identity_residuals(perturbed, y)[0] <= INVARIANT_IDENTITY_TOL


@pytest.mark.parametrize("constructor, kwargs", [
    (problems.perturbed_kepler, {"eccentricity": 1.0}),
    (problems.perturbed_kepler, {"delta": math.inf}),
    (problems.henon_heiles, {"energy": 0.2}),
    (problems.fpu_beta, {"n": 1}),
    (problems.fpu_beta, {"n": 2.5}),
    (problems.fpu_beta, {"beta": -1.0}),
    (problems.fpu_beta, {"boundary": "open"}),
    (problems.toda, {"n": 2}),
    (problems.nbody, {"masses": [1.0, -1.0], "positions": [[0, 0, 0], [1, 0, 0]],
                      "velocities": [[0, 0, 0], [0, 1, 0]]}),
    (problems.nbody, {"masses": [1.0, 1.0]}),
    (problems.nbody, {"positions": [[0, 0, 0]] * 6}),
    (problems.nbody, {"G": 0.0}),
    (problems.pendulum, {"omega": 0.0}),
])
def test_constructors_reject_bad_arguments_with_a_value_error(constructor, kwargs):
    with pytest.raises(ValueError):
        constructor(**kwargs)


# --- perturbed Kepler ----------------------------------------------------------------------

def test_perturbed_kepler_initial_values_and_reduction_to_kepler():
    e, delta = 0.6, 0.01
    problem = problems.perturbed_kepler(e, delta)
    values = problem.invariant_values(problem.y0)
    assert values["angular_momentum"] == pytest.approx(math.sqrt(1 - e * e), rel=1e-15)
    assert values["H"] == pytest.approx(-0.5 - delta / (2 * (1 - e) ** 3), rel=1e-15)
    unperturbed, kepler = problems.perturbed_kepler(e, delta=0.0), problems.kepler(e)
    y = kepler.y0 + 0.03
    assert np.array_equal(unperturbed.y0, kepler.y0)
    assert unperturbed.hamiltonian(y) == pytest.approx(kepler.hamiltonian(y), rel=1e-15)
    np.testing.assert_allclose(unperturbed.gradient(y), kepler.gradient(y), rtol=1e-15)


def test_perturbed_kepler_ehbvm_keeps_angular_momentum_and_hbvm_does_not():
    problem = problems.perturbed_kepler()
    imposed = elimfast.integrate(problem, ehbvm(12, 3), 0.2, n_steps=200, conserve=["angular_momentum"])
    free = elimfast.integrate(problem, hbvm(12, 3), 0.2, n_steps=200)
    assert drift(imposed, "angular_momentum") < ROUND_OFF
    assert drift(free, "angular_momentum") > NOT_KEPT
    # H is not a polynomial, but with k = 12 its O(h^25) error per step is below round-off.
    assert drift(imposed, "H") < ROUND_OFF and drift(free, "H") < ROUND_OFF


# --- Henon-Heiles ---------------------------------------------------------------------------

def test_henon_heiles_default_energy():
    for energy in (0.125, 0.1, 1 / 12):
        problem = problems.henon_heiles(energy)
        assert problem.hamiltonian(problem.y0) == pytest.approx(energy, rel=1e-15)
        assert problem.y0[0] == 0.0 and problem.y0[2] > 0.0   # on the section q1 = 0, crossing it upwards


def test_henon_heiles_cubic_energy_kept_by_hbvm_with_2k_over_s_at_least_3():
    problem = problems.henon_heiles()
    kept = elimfast.integrate(problem, hbvm(6, 4), 0.5, n_steps=200)     # 2k/s = 3
    symplectic = elimfast.integrate(problem, gauss(4), 0.5, n_steps=200)  # 2k/s = 2
    assert drift(kept, "H") < ROUND_OFF
    assert drift(symplectic, "H") > NOT_KEPT


# --- FPU beta -------------------------------------------------------------------------------

@pytest.mark.parametrize("boundary", ["periodic", "fixed"])
def test_fpu_quartic_energy_kept_by_hbvm_with_2k_over_s_at_least_4(boundary):
    problem = problems.fpu_beta(boundary=boundary)
    # Amplitude 2: the quartic term matters, and GAUSS's energy error is far above round-off.
    problem = problem.with_initial(2.0 * problem.y0)
    kept = elimfast.integrate(problem, hbvm(8, 4), 0.4, n_steps=200)     # 2k/s = 4
    symplectic = elimfast.integrate(problem, gauss(4), 0.4, n_steps=200)
    assert drift(kept, "H") < ROUND_OFF
    assert drift(symplectic, "H") > NOT_KEPT
    if boundary == "periodic":
        # Linear: kept by every Runge-Kutta method.
        assert drift(kept, "momentum") < ROUND_OFF and drift(symplectic, "momentum") < ROUND_OFF


def test_fpu_fixed_and_periodic_potentials():
    """Direct sums over the springs (a naive reference for the compiled loops)."""
    beta, n = 0.7, 5
    rng = np.random.default_rng(5)
    y = rng.standard_normal(2 * n)
    q, p = y[:n], y[n:]
    V = lambda r: np.sum(r ** 2 / 2 + beta * r ** 4 / 4)
    periodic = problems.fpu_beta(n, beta, "periodic")
    fixed = problems.fpu_beta(n, beta, "fixed")
    assert periodic.hamiltonian(y) == pytest.approx(p @ p / 2 + V(np.roll(q, -1) - q), rel=1e-14)
    assert fixed.hamiltonian(y) == pytest.approx(p @ p / 2 + V(np.diff(np.concatenate(([0.0], q, [0.0])))),
                                                 rel=1e-14)
    assert periodic.invariant_values(periodic.y0)["momentum"] == pytest.approx(0.1 * n, rel=1e-13)


def test_fpu_momentum_is_imposed_by_ghbvm_and_cannot_be_by_ehbvm():
    problem = problems.fpu_beta()
    imposed = elimfast.integrate(problem, ghbvm(8, 4), 0.2, n_steps=200, conserve=["momentum"])
    assert drift(imposed, "momentum") < ROUND_OFF and drift(imposed, "H") < ROUND_OFF
    # A linear invariant has phi_j = 0 for j >= 1: Gamma is zero up to round-off.
    with pytest.raises((ConvergenceError, ValueError)):
        elimfast.integrate(problem, ehbvm(8, 2), 0.2, n_steps=5, conserve=["momentum"])


# --- Toda -----------------------------------------------------------------------------------

def lax_matrix(y: np.ndarray) -> np.ndarray:
    """The periodic Flaschka-Lax matrix, built densely (naive reference)."""
    n = y.size // 2
    q, p = y[:n], y[n:]
    a = 0.5 * np.exp(0.5 * (q - np.roll(q, -1)))
    L = np.diag(-0.5 * p)
    for i in range(n):
        L[i, (i + 1) % n] += a[i]
        L[(i + 1) % n, i] += a[i]
    return L


@pytest.mark.parametrize("n", [3, 4, 5, 7])
def test_toda_traces_match_dense_matrix_powers(n):
    problem = problems.toda(n)
    powers = [1] + list(range(3, min(n, 5) + 1))
    assert problem.invariant_names == tuple(f"trace_L{k}" for k in powers)
    for y in points_near_y0(problem, seed=n):
        L = lax_matrix(y)
        values = problem.invariant_values(y)
        for k in powers:
            expected = np.trace(np.linalg.matrix_power(L, k))
            assert values[f"trace_L{k}"] == pytest.approx(expected, rel=1e-13, abs=1e-13)
        # The documented reasons for leaving tr(L^2) out and for tr(L) being linear.
        assert np.trace(L @ L) == pytest.approx(values["H"] / 2, rel=1e-13)
        assert values["trace_L1"] == pytest.approx(-0.5 * np.sum(y[n:]), rel=1e-14, abs=1e-15)


def test_toda_ehbvm_keeps_two_traces_and_hbvm_does_not():
    problem = problems.toda(4)
    imposed_names = ("trace_L3", "trace_L4")
    imposed = elimfast.integrate(problem, ehbvm(12, 3), 0.1, n_steps=200, conserve=imposed_names)
    free = elimfast.integrate(problem, hbvm(12, 3), 0.1, n_steps=200)
    for name in problem.invariant_names:   # trace_L1 is linear: kept by both
        assert drift(imposed, name) < ROUND_OFF, (name, drifts(imposed, problem.invariant_names))
    assert min(drift(free, name) for name in imposed_names) > NOT_KEPT


def test_toda_ehbvm_keeps_three_traces():
    """nu = 3 needs n >= 5 (tr L^k, k > n, depends on the lower traces) and s >= 4.

    No comparison with HBVM(12,4) here: it is of order 8, and at the step sizes where
    Gamma (3 x 3) stays well conditioned along the whole run (h <= 0.08 for this state;
    at h = 0.1 alpha spikes to O(1) and at larger h the iteration fails) its drift is
    itself only ~20 times round-off.
    """
    problem = problems.toda(5)
    imposed_names = ("trace_L3", "trace_L4", "trace_L5")
    imposed = elimfast.integrate(problem, ehbvm(12, 4), 0.05, n_steps=200, conserve=imposed_names)
    for name in problem.invariant_names:
        assert drift(imposed, name) < ROUND_OFF, (name, drifts(imposed, problem.invariant_names))
    assert np.max(np.abs(imposed.alpha)) < 0.1   # alpha = O(h^2): Gamma well conditioned


# --- N bodies -------------------------------------------------------------------------------

ANGULAR = ("angular_momentum_x", "angular_momentum_y", "angular_momentum_z")
LINEAR = ("linear_momentum_x", "linear_momentum_y", "linear_momentum_z")


HLW_MASSES = np.array([1.00000597682, 0.000954786104043, 0.000285583733151,
                       0.0000437273164546, 0.0000517759138449, 1 / 1.3e8])
HLW_POSITIONS = np.array([[0.0, 0.0, 0.0], [-3.5023653, -3.8169847, -1.5507963], [9.0755314, -3.0458353, -1.6483708],
                          [8.3101420, -16.2901086, -7.2521278], [11.4707666, -25.7294829, -10.8169456],
                          [-15.5387357, -25.2225594, -3.1902382]])
HLW_VELOCITIES = np.array([[0.0, 0.0, 0.0], [0.00565429, -0.00412490, -0.00190589],
                           [0.00168318, 0.00483525, 0.00192462], [0.00354178, 0.00137102, 0.00055029],
                           [0.00288930, 0.00114527, 0.00039677], [0.00276725, -0.00170702, -0.00136504]])
HLW_G = 2.95912208286e-4


def test_nbody_default_is_the_hlw_outer_solar_system_moved_to_the_barycentre():
    """HLW I.2.4's heliocentric data (copied here from the book), moved to the barycentre."""
    problem = problems.nbody()
    masses = HLW_MASSES
    np.testing.assert_array_equal(problem.params, np.concatenate(([HLW_G], masses)))
    assert problem.parameters["positions"] == HLW_POSITIONS.tolist()      # the source data, as printed
    assert problem.parameters["frame"] == "barycentric"
    assert problem.units == {"length": "AU", "time": "day", "mass": "solar mass"}
    q = problem.y0[:18].reshape(6, 3)
    v = problem.y0[18:].reshape(6, 3) / masses[:, None]
    M = masses.sum()
    centre, drift_velocity = masses @ HLW_POSITIONS / M, masses @ HLW_VELOCITIES / M
    np.testing.assert_allclose(q, HLW_POSITIONS - centre, rtol=1e-15, atol=1e-17)
    np.testing.assert_allclose(v, HLW_VELOCITIES - drift_velocity, rtol=1e-13, atol=1e-19)
    # The relative motion, hence every orbit, is the book's.
    np.testing.assert_allclose(q[5] - q[0], HLW_POSITIONS[5], rtol=1e-15)
    np.testing.assert_allclose(v[1] - v[0], HLW_VELOCITIES[1], rtol=1e-13)
    assert problem.q_names == tuple(f"{body}_{c}" for body in ("sun", "jupiter", "saturn", "uranus", "neptune",
                                                                "pluto") for c in "xyz")
    assert problem.p_names[:4] == ("sun_px", "sun_py", "sun_pz", "jupiter_px")
    # H against a direct NumPy evaluation.
    kinetic = 0.5 * np.sum(masses[:, None] * v * v)
    potential = sum(HLW_G * masses[i] * masses[j] / np.linalg.norm(q[i] - q[j]) for i in range(6) for j in range(i))
    assert problem.hamiltonian(problem.y0) == pytest.approx(kinetic - potential, rel=1e-13)


def test_nbody_ragged_lists_are_refused_naming_the_body():
    """A user trial: positions [[1, 3, 0], [-2, -1, 0], [1, -1]] showed NumPy's 'setting an array element
    with a sequence. The requested array has an inhomogeneous shape ...'."""
    from elimfast.errors import ParameterError
    with pytest.raises(ParameterError, match=r"^positions must be a list of \[x, y, z\] triples of numbers, one per "
                                             r"body \(body 2: \[1, -1\]\)$"):
        elimfast.problems.nbody(masses=[1, 1, 1], positions=[[1, 3, 0], [-2, -1, 0], [1, -1]],
                                velocities=[[0, 0, 0]] * 3)
    with pytest.raises(ParameterError, match=r"^masses must be a list of at least 2 numbers, got \[1, \[2\]\]$"):
        elimfast.problems.nbody(masses=[1, [2]])


def test_nbody_barycentric_start_has_zero_momentum_and_centre_of_mass_at_the_origin():
    problem = problems.nbody()
    p = problem.y0[18:].reshape(6, 3)
    q = problem.y0[:18].reshape(6, 3)
    assert np.max(np.abs(p.sum(axis=0))) < 1e-18                  # |p_i| ~ 5e-6: round-off is ~1e-21
    assert np.max(np.abs(HLW_MASSES @ q)) < 1e-15                 # sum m_i |q_i| ~ 0.03
    values = problem.invariant_values(problem.y0)
    assert max(abs(values[name]) for name in LINEAR) < 1e-18
    # The heliocentric frame of the book, kept by frame="given", carries the planets' momentum.
    given = problems.nbody(frame="given")
    np.testing.assert_array_equal(given.y0[:18].reshape(6, 3), HLW_POSITIONS)
    assert np.max(np.abs(given.y0[18:].reshape(6, 3).sum(axis=0))) > 1e-6


def test_nbody_centre_of_mass_stays_at_the_origin_while_the_heliocentric_one_drifts():
    """Issue 10, point 8: the centre of mass drifted 480 AU over 7e7 days, |P| t / M."""
    t_end = 2e5
    drifts_by_frame = {}
    for frame in ("barycentric", "given"):
        problem = problems.nbody(frame=frame)
        result = elimfast.integrate(problem, gauss(2), 100.0, t_end=t_end)
        assert result.status == "complete"
        start, end = (HLW_MASSES @ y[:18].reshape(6, 3) / HLW_MASSES.sum() for y in (problem.y0, result.y_final))
        drifts_by_frame[frame] = (float(np.linalg.norm(start)), float(np.linalg.norm(end - start)))
    velocity = np.linalg.norm(HLW_MASSES @ HLW_VELOCITIES) / HLW_MASSES.sum()
    assert drifts_by_frame["given"][1] == pytest.approx(velocity * t_end, rel=1e-9)   # 1.35 AU
    assert max(drifts_by_frame["barycentric"]) < 1e-14


def test_nbody_coordinate_names_work_as_config_initial_keys(tmp_path):
    from elimfast.config import load_run
    from elimfast.problems.expressions import check_name
    for name in problems.nbody().coordinate_names + three_body().coordinate_names:
        check_name(name, "coordinate name")
    config = tmp_path / "nbody.yaml"
    config.write_text("problem: {builtin: nbody, initial: {jupiter_x: -3.6, pluto_pz: 0.0}}\n"
                      "method: {name: gauss, s: 2}\nintegration: {h: 50, n_steps: 2}\n")
    problem = load_run(config).problem
    assert problem.y0[problem.coordinate_names.index("jupiter_x")] == -3.6
    assert problem.y0[problem.coordinate_names.index("pluto_pz")] == 0.0
    assert three_body().q_names[:4] == ("body0_x", "body0_y", "body0_z", "body1_x")


def test_nbody_invariants_against_numpy():
    problem = three_body()
    y = points_near_y0(problem, seed=7)[1]
    q, p = y[:9].reshape(3, 3), y[9:].reshape(3, 3)
    values = problem.invariant_values(y)
    np.testing.assert_allclose([values[name] for name in LINEAR], p.sum(axis=0), rtol=1e-14)
    np.testing.assert_allclose([values[name] for name in ANGULAR], np.cross(q, p).sum(axis=0), rtol=1e-13)


def test_nbody_ehbvm_keeps_three_angular_momenta_and_hbvm_does_not():
    problem = three_body()
    imposed = elimfast.integrate(problem, ehbvm(12, 4), 0.08, n_steps=200, conserve=ANGULAR)
    free = elimfast.integrate(problem, hbvm(12, 4), 0.08, n_steps=200)
    scale = np.linalg.norm([imposed.invariants[name][0] for name in ANGULAR])
    for name in ANGULAR:
        assert np.max(np.abs(imposed.invariants[name] - imposed.invariants[name][0])) < ROUND_OFF * scale
    assert max(np.max(np.abs(free.invariants[name] - free.invariants[name][0])) for name in ANGULAR) \
        > NOT_KEPT * scale
    for name in LINEAR:   # linear: kept by both
        for result in (imposed, free):
            assert np.max(np.abs(result.invariants[name] - result.invariants[name][0])) < ROUND_OFF * scale


def test_solar_system_ehbvm_keeps_the_normal_angular_momentum():
    """The orbits are nearly coplanar: the three rows of Gamma for L_x, L_y, L_z are nearly
    parallel (Gamma singular at step 1), so EHBVM imposes L_z, the component along the normal."""
    problem = problems.nbody()
    imposed = elimfast.integrate(problem, ehbvm(12, 2), 100.0, n_steps=200, conserve=["angular_momentum_z"])
    free = elimfast.integrate(problem, hbvm(12, 2), 100.0, n_steps=200)
    assert drift(imposed, "angular_momentum_z") < ROUND_OFF
    assert drift(free, "angular_momentum_z") > NOT_KEPT


def test_solar_system_ghbvm_imposes_all_six_momenta():
    problem = problems.nbody()
    imposed = elimfast.integrate(problem, ghbvm(12, 2), 100.0, n_steps=200, conserve=problem.invariant_names)
    for name in ("H",) + ANGULAR:
        assert drift(imposed, name) < ROUND_OFF, (name, drifts(imposed, ("H",) + problem.invariant_names))
    # The barycentric linear momenta start at ~1e-22: their drift is measured against the
    # momenta that cancel in them, sum_i |p_i|.
    scale = np.abs(problem.y0[18:].reshape(6, 3)).sum(axis=0)
    for axis, name in enumerate(LINEAR):
        values = imposed.invariants[name]
        assert np.max(np.abs(values - values[0])) < ROUND_OFF * scale[axis], name


# --- pendulum -------------------------------------------------------------------------------

def test_pendulum_energy_kept_by_hbvm_and_not_by_gauss():
    problem = problems.pendulum(omega=1.3)
    assert problem.hamiltonian(problem.y0) == pytest.approx(-1.3 ** 2 * math.cos(1.0), rel=1e-15)
    kept = elimfast.integrate(problem, hbvm(12, 2), 0.5, n_steps=200)  # O(h^25) per step: round-off
    symplectic = elimfast.integrate(problem, gauss(2), 0.5, n_steps=200)
    assert drift(kept, "H") < ROUND_OFF
    assert drift(symplectic, "H") > NOT_KEPT


def _toda_trace_gradients(y, powers):
    """NumPy: d tr(L^k)/dy of the periodic Toda Lax matrix (lax_matrix: L_xx = -p_x/2,
    L_x,x+1 = L_x+1,x = a_x = exp((q_x - q_x+1)/2)/2), from d tr(L^k) = k tr(L^(k-1) dL)."""
    n = y.size // 2
    a = 0.5 * np.exp(0.5 * (y[:n] - np.roll(y[:n], -1)))
    L = lax_matrix(y)
    rows = []
    for k in powers:
        M = np.linalg.matrix_power(L, k - 1)
        grad = np.empty(2 * n)
        grad[n:] = -0.5 * k * np.diag(M)
        upper = np.array([M[x, (x + 1) % n] for x in range(n)])
        grad[:n] = k * (a * upper - np.roll(a * upper, 1))
        rows.append(grad)
    return np.array(rows)


@pytest.mark.parametrize("n", [7, 40])
def test_toda_invariant_gradients_agree_with_a_dense_numpy_reference(n):
    """The Toda lattice's grad tr(L^k), against the dense matrices. From n = 11 on the kernel
    computes L^m e_i only on the window i - m .. i + m where it lives (a user trial: toda with
    10^5 particles spent minutes in each call, O(n^2)); the window gives the same numbers bit
    for bit as the whole ring did, and a call at n = 10^5 takes milliseconds."""
    chain = problems.toda(n)
    rng = np.random.default_rng(n)
    y = chain.y0 + 0.3 * rng.standard_normal(chain.y0.size)
    powers = [int(name[len("trace_L"):]) for name in chain.invariant_names]
    expected = _toda_trace_gradients(y, powers)
    np.testing.assert_allclose(chain.invariant_gradients(y), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    huge = problems.toda(100_000)
    gradients = huge.invariant_gradients(huge.y0)
    assert gradients.shape == (4, 200_000) and np.all(np.isfinite(gradients))
