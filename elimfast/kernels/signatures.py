"""The fixed Numba signatures of a problem's compiled functions.

Kernels receive a problem's functions as ``types.FunctionType`` arguments with these
signatures. That keeps the kernels cacheable across processes (a plain dispatcher
argument makes the caller "use dynamic globals" and defeats ``cache=True``, numba
issues 6972 and 6264) and means one compiled kernel serves every problem: only a
problem's own small functions are compiled per problem. Measured (see
``bench/kernel.py``): no slower than calling the problem's functions as globals.

All arrays are C-contiguous float64; ``params`` is the problem's parameter vector.

- ``H(y, params) -> float``
- ``grad_H(y, params, out)``: out (2m,) = dH/dy
- ``invariants(y, params, out)``: out (n_inv,) = L_i(y)
- ``grad_invariants(y, params, out)``: out (n_inv, 2m), row i = grad L_i(y)
- ``hess_H(y, params, out)``: out (2m, 2m) = the symmetric matrix d^2 H / dy^2, rows and
  columns in the order q then p (so out[i, j] = d^2 H / dy_i dy_j); every entry is written.
  The simplified Newton solver of docs/solver.md factorises I - h X_s (x) J Hess(H)(y0)
  once per step with it. Built-ins compute it analytically, expression problems by sympy,
  ``python:`` files with their own ``hess_H`` or by central differences of ``grad_H``
  (``Problem.hessian_source`` says which).
"""
from numba import njit, types

VECTOR = types.float64[::1]
MATRIX = types.float64[:, ::1]
INT_VECTOR = types.int64[::1]
COMPLEX_VECTOR = types.complex128[::1]
COMPLEX_MATRIX = types.complex128[:, ::1]

H_SIGNATURE = types.float64(VECTOR, VECTOR)
GRAD_H_SIGNATURE = types.void(VECTOR, VECTOR, VECTOR)
INVARIANTS_SIGNATURE = types.void(VECTOR, VECTOR, VECTOR)
GRAD_INVARIANTS_SIGNATURE = types.void(VECTOR, VECTOR, MATRIX)
HESS_H_SIGNATURE = types.void(VECTOR, VECTOR, MATRIX)

H_TYPE = types.FunctionType(H_SIGNATURE)
GRAD_H_TYPE = types.FunctionType(GRAD_H_SIGNATURE)
INVARIANTS_TYPE = types.FunctionType(INVARIANTS_SIGNATURE)
GRAD_INVARIANTS_TYPE = types.FunctionType(GRAD_INVARIANTS_SIGNATURE)
HESS_H_TYPE = types.FunctionType(HESS_H_SIGNATURE)

# Decorators for problem modules: compile eagerly with the signature the kernels expect.
# error_model="numpy": a division by zero gives inf/NaN, which the kernel reports as a
# non-finite solution (STATUS_NONFINITE), instead of a ZeroDivisionError escaping it.
jit_hamiltonian = njit(H_SIGNATURE, cache=True, error_model="numpy")
jit_gradient = njit(GRAD_H_SIGNATURE, cache=True, error_model="numpy")
jit_invariants = njit(INVARIANTS_SIGNATURE, cache=True, error_model="numpy")
jit_invariant_gradients = njit(GRAD_INVARIANTS_SIGNATURE, cache=True, error_model="numpy")
jit_hessian = njit(HESS_H_SIGNATURE, cache=True, error_model="numpy")


@jit_invariants
def no_invariants(y, params, out):
    """For problems with no invariant besides H: writes nothing (out has length 0)."""
    return


@jit_invariant_gradients
def no_invariant_gradients(y, params, out):
    """For problems with no invariant besides H: writes nothing (out is 0 x 2m)."""
    return
