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
