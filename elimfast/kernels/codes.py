"""The integer codes kernels and the Python layer share: statuses, families, solvers.

One owner for each code: kernels return these, ``elimfast.integrate`` turns them into
exceptions and messages.
"""

# Status of a step or a kernel call.
STATUS_OK = 0
STATUS_NOT_CONVERGED = 1   # the iteration did not reach its stopping rule (docs/solver.md)
STATUS_SINGULAR = 2        # Gamma (ELIM) or the Gram matrix (LIM) singular, or a spurious alpha
STATUS_NONFINITE = 3       # NaN or infinity in the iteration or the state
STATUS_EXCEPTION = 4       # a problem function raised (ensembles only: a single run raises it)

# Kernel families: ELIM covers GAUSS and HBVM (nu = 0); LIM covers GHBVM.
FAMILY_ELIM = 0
FAMILY_LIM = 1

# Solvers of one step's nonlinear system (spec 8).
SOLVER_FIXED_POINT = 0
SOLVER_NEWTON = 1
