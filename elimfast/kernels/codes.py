"""The integer codes kernels and the Python layer share (statuses, families, solvers), and
the compile options of the kernels' internal functions.

One owner for each code: kernels return these, ``elimfast.integrate`` turns them into
exceptions and messages.
"""
from numba import njit

# Functions only kernels call: no wrappers for calls from Python or C (each costs
# compile time, several seconds for a function that takes the Workspace's 40 arrays), and
# no reference counting (_nrt=False): they allocate nothing, and their caller keeps every
# array alive. With it, each call increfed and decrefed every array of the Tables and
# Workspace structs it was passed: ~200 ns per call, measured, and a step makes about six
# such calls (GAUSS(4) on Kepler at h = pi/120 spent more time in calls than in its map).
# A function that must allocate uses internal_allocating.
# Flags passed to them are runtime values (np.bool_(True), a comparison), never a literal True or
# False: Numba compiles a function once per literal argument value, and try_step called with
# literal flags from four places was compiled four times (+15 s to the fixed-step kernel's cache
# warm, +30 s to the adaptive one's).
internal = njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True, _nrt=False)
internal_allocating = njit(cache=True, error_model="numpy", no_cpython_wrapper=True, no_cfunc_wrapper=True)

# Status of a step or a kernel call.
STATUS_OK = 0
STATUS_NOT_CONVERGED = 1   # the iteration did not reach its stopping rule (docs/solver.md)
STATUS_SINGULAR = 2        # Gamma (ELIM) or the Gram matrix (LIM) singular, or a spurious alpha
STATUS_NONFINITE = 3       # NaN or infinity in the iteration or the state
STATUS_EXCEPTION = 4       # a problem function raised (ensembles only: a single run raises it)
STATUS_SPLIT = 6           # internal to stepper.try_step: an ELIM solve that converged, but whose alpha carries
#                            rounding into the step (stepper._attempt): split it, never take it unimposed
STATUS_TIME_SCALE = 5      # time-reversible steps: sigma(y) not positive and finite, or h = epsilon sigma too
#                            small to advance t (adaptive kernel, docs/adaptive.md#time-reversible-steps-step_controltime_scale)

# Kernel families: ELIM covers GAUSS and HBVM (nu = 0); LIM covers GHBVM.
FAMILY_ELIM = 0
FAMILY_LIM = 1

# Solvers of one step's nonlinear system (docs/solver.md).
SOLVER_FIXED_POINT = 0
SOLVER_NEWTON = 1
# Simplified Newton with the secant acceleration of docs/solver.md#secant-acceleration (the default);
# SOLVER_NEWTON is the plain iteration (solver.accelerate: false).
SOLVER_NEWTON_ACCELERATED = 2

# The predictor (docs/solver.md#the-predictor) carries the previous step's polynomial over with
# this many Legendre coefficients gamma_s, gamma_s+1, ... beyond its s effective ones, when the
# method computes them (k > s; GAUSS has none: P_s vanishes at its nodes). One makes the
# predictor one order more accurate: its error max |h (c_pred - c)| / sc on Kepler e = 0.6,
# h = 0.1 (median over 300 steps, 0..3 extra terms) is 7.3e-5, 5.6e-6, 1.2e-6, 1.2e-6, and it
# drops like h^(s+1) with h instead of h^s (tests/test_step_engine.py). Iterations per step
# with 0, 1, 2, 3 extra terms, measured:
#   Kepler e = 0.6, h = 0.1, t <= 1000: EHBVM(12,3) imposing L, A_y 5.26, 5.02, 5.00, 5.00
#     (fixed point 9.18, 8.37, 8.18, 8.13); HBVM(12,3) 4.65, 4.41, 4.40, 4.41; GHBVM(12,3) 4.73,
#     4.49, 4.49, 4.49; HBVM(12,6) (t <= 300) 3.79, 3.62, 3.63, 3.62;
#   small steps: EHBVM(12,4) imposing L, h = pi/480: 3.01, 2.50, 2.51, 2.98; h = pi/960: 2.65,
#     2.09, 2.13, 2.46; HBVM(12,6), h = pi/120: 3.11, 3.01, 3.03, 3.06;
#   adaptive, Kepler e = 0.9, 10 periods at rtol 1e-14: EHBVM(8,4) imposing L, A_y 5.89, 5.63,
#     5.50, 5.29; HBVM(12,6) 5.44, 5.33, 5.32, 5.33; HBVM(8,4) 4.02 in every case;
#   the outer solar system, h = 50: GHBVM(12,3) 5.84, 5.55, 5.53, 5.52.
# A second and third term gain a little more with large steps and lose at small ones: there
# gamma_j is mostly rounding noise, which the extrapolation to [1, 2] amplifies like P_j(2)
# (3.7^j). Beyond 3 the (s+1)-point rule of E(theta) is no longer exact (degree 2s - 2 + e).
PREDICTOR_EXTRA_ROWS = 1

# Diagnostics of a failed step (the kernels' ``diagnostics`` output, in this order).
DIAG_TIME, DIAG_STEP, DIAG_INCREMENT, DIAG_CONDITION, DIAG_DEPTH, DIAG_ITERATIONS = range(6)
N_DIAGNOSTICS = 6

# The adaptive kernel's arrays (kernels/adaptive.py adaptive_loop; elimfast.adaptive fills and reads them).
CONTROL_ERROR = 0
CONTROL_TIME_SCALE = 1
CONTROL_FIXED = 2

# controls (float64): the run's real parameters.
CTL_RTOL, CTL_ATOL, CTL_EPSILON, CTL_T_END, CTL_H_MAX, CTL_H_TARGET = range(6)
N_CONTROLS = 6
# options (int64): the run's integer parameters.
OPT_CONTROL, OPT_VERIFY, OPT_STORE_EVERY, OPT_N_TOTAL = range(4)
N_OPTIONS = 4
# control_state (float64), saved with the run so that a resumed run continues exactly:
# the next step to try, the last accepted step and its error estimate (0: none yet),
# rho of the time-reversible controller (0: not started), and 1 when the last attempt was
# rejected or failed (the next accepted step then may not grow: Hairer & Wanner's rule;
# without it Kepler e = 0.99 at rtol 1e-9 failed 189 solves in 10 periods).
CS_H_NEXT, CS_H_PREV, CS_ERR_PREV, CS_RHO, CS_REJECTED = range(5)
N_CONTROL_STATE = 5
# counters (int64), saved with the run: steps accepted, steps rejected by the estimate,
# failed solves (h halved), split steps, iterations of accepted and rejected steps,
# side steps and their iterations, the next requested time, events found,
# Newton factorisations (Hessian evaluations), Hessians of the error estimate,
# states taken from the stage polynomial because both side steps failed, and states
# checked by the energy projection (one grad H each; solver.project_energy).
(CNT_STEPS, CNT_REJECTED, CNT_FAILED, CNT_SPLIT, CNT_ITERATIONS, CNT_SIDE_STEPS, CNT_SIDE_ITERATIONS,
 CNT_NEXT_EVAL, CNT_EVENTS, CNT_FACTORISATIONS, CNT_ESTIMATE_HESSIANS, CNT_SIDE_FALLBACKS,
 CNT_ENERGY_PROJECTIONS) = range(13)
N_COUNTERS = 13
# progress (int64) of one call: steps, samples, events written; 1 when the run is finished
# (t_end reached or a terminal event).
N_PROGRESS = 4
# A step below this times |t| (or |t_end|) no longer advances the clock: time-reversible steps'
# sigma has collapsed (STATUS_TIME_SCALE), or the error controller's steps have (a failure of
# STATUS_NOT_CONVERGED with no iterations: collapsed_steps).
COLLAPSED_STEP = 4.0 * 2.0 ** -52
