"""Named bundles the step kernels pass around: method tables, solver settings, workspace.

Numba compiles ``collections.namedtuple`` instances to plain structs, so naming the
slots costs nothing at run time; it replaces positional 13-tuples whose slots changed
meaning between families. Everything here is built once per kernel call (or per
trajectory), never inside the step loop.

Borrowed arrays. Numba reference-counts every array variable and view; in the
iteration, with opaque calls to the problem's functions between them, it cannot prune
those updates, and they were measured at 21% of the run time of a Kepler step (atomic
increments in NRT_incref/NRT_decref). ``borrow_tables`` and ``borrow_workspace`` hand
the step kernels views that own no reference (a NULL meminfo, on which Numba's
reference counting returns at once). They are valid while their owners are alive: the
kernel that allocates the owners keeps them in a local until it returns.
"""
from collections import namedtuple

import numpy as np
from numba import njit, types
from numba.core import cgutils
from numba.core.imputils import impl_ret_borrowed, lower_getattr_generic
from numba.core.typing.templates import AttributeTemplate, infer_getattr
from numba.extending import intrinsic, models, overload, register_model

from .codes import FAMILY_LIM

# The tables of a method (docs/methods.md and docs/solver.md), built once by elimfast.methods:
#   projection (k, k): b_l P_j(c_l) indexed [j, l];  Is (k, s): int_0^{c_l} P_j;
#   projection_hat (r, r), Ihat (r, s): the same at the r nodes of the invariants;
#   X (s, s): Ps^T Omega Is, the tridiagonal matrix of the simplified Newton iteration;
#   abs_projection_hat (max(r, k),): S_j = sum_i |bhat_i P_j(chat_i)| or, larger, over the k nodes
#     (the rounding estimate; methods/base.py);
#   predictor_nodes (s+1,), predictor_basis (s+1, s): Gauss nodes x_q on [0, 1] and
#     w_q P_i(x_q), the quadrature of the predictor's projection E(theta).
#   newton_values (n_b,) complex, newton_vectors (s, n_b) complex, newton_inverse (n_b, s)
#     complex, newton_weights (n_b,): X = V Lambda V^-1 restricted to one eigenvalue per
#     conjugate pair (weight 2; a real eigenvalue has weight 1); empty when the method
#     factorises the full Newton matrix instead (large s, ill-conditioned V).
#   Is_low (k, s), Ihat_low (r, s): the low parts of Is and Ihat (double-doubles of the exact
#     integrals; maps.scale_tables, docs/methods.md#round-off-over-long-times).
Tables = namedtuple("Tables", ["projection", "Is", "projection_hat", "Ihat", "X", "abs_projection_hat",
                               "predictor_nodes", "predictor_basis", "newton_values", "newton_vectors",
                               "newton_inverse", "newton_weights", "Is_low", "Ihat_low"])

# The solver's settings (docs/solver.md): family and solver codes (codes.py), whether the
# ELIM right-hand side is the stable tail (docs/methods.md#stable-right-hand-side), whether each step starts from the
# previous one (warm_start) extrapolated by the predictor, the round-off acceptance
# tol, and the caps max_iter (per solve) and max_halvings (depth of step splitting).
Settings = namedtuple("Settings", ["family", "solver", "stable_rhs", "warm_start", "predictor", "tol",
                                   "max_iter", "max_halvings"])

Workspace = namedtuple("Workspace", [
    "u",                 # (k, n) stages at the k nodes
    "grads",             # (k, n) grad H at the stages
    "proj",              # (n_big, n) Legendre coefficients of grads
    "gamma",             # (n_big, n) gamma_j = J proj_j
    "uhat",              # (r, n) stages at the r nodes (r != k)
    "grads_hat",         # (n_tilde, r, n) imposed invariants' gradients at the r nodes (LIM: H first)
    "inv_grads",         # (n_inv, n) one call of grad_invariants
    "phi",               # (max(n_tilde, 1), n_big, n) phi_j per imposed invariant (j >= s: at the k nodes
    #                      when r < k, maps.TAIL_K_NODES)
    "small_matrix",      # (n_t, n_t) Gamma (ELIM) or the Gram matrix (LIM), factored in place
    "small_copy",        # (n_t, n_t) the same matrix unfactored
    "small_inverse",     # (n_t, n_t) its inverse (rounding level and condition number)
    "small_vector",      # (n_t,) right-hand side, then the multipliers
    "small_pivots",      # (n_t,) int64
    "small_rounding",    # (1, n_t) rounding of the multipliers
    "sizes",             # (1 + n_t, n) F_p = max_l |f_{l,p}|, then A_{a,p} = max_i |grad L_a(uhat_i)_p|
    "rounding_level",    # (n,) omega_p, the relative rounding level of each component
    "component_increment",   # (n,) max_j |h Delta_{j,p}| / sc_p of the last iteration
    "carried",           # (n,) rounding carried into each component by the Jacobian (solver._carried_level)
    "h_powers",          # (max(nu, 1),) w_c = h^(2(nu-1-c)) of the step being solved
    "new_coef",          # (s, n) the map G(coef)
    "delta",             # (3 s n,) the increment (Newton: M^-1 (G - coef)), then Newton's previous
    #                      iterate and its increment, the secant acceleration's history
    #                      (solver._secant_update)
    "scale",             # (n,) sc_i of the stopping rule
    "newton_matrix",     # (s n, s n) M~ = I - h X (x) J0~, factored (full form; else 0 x 0)
    "newton_pivots",     # (s n,) int64
    "newton_blocks",     # (n_b, n, n) complex: I - h lambda_b J0~, LU-factored, or its inverse (block
    #                      forms; else 0 x n x n)
    "newton_block_pivots",   # (n_b, n) int64 (LU blocks)
    "newton_block_rhs",  # (n_b, n) complex
    "newton_block_scratch",  # (n, n) complex: I - h lambda_b J0~ before inversion (inverse form; else 0 x 0)
    "newton_real_inverse",   # (n, n): the inverse of the block of X's real eigenvalue, in real arithmetic
    #                          (inverse form with an odd s; else 0 x 0)
    "newton_inverse_split",  # (2 n_b n, n): the inverted blocks transposed, real and imaginary parts apart:
    #                          row (2 b) n + q holds Re(B_b^-1[:, q]), row (2 b + 1) n + q Im(B_b^-1[:, q])
    #                          (the real eigenvalue's block: its real inverse); written by newton_factor
    #                          for newton_solve's vectorised products (inverse form; else 0 x 0)
    "newton_rhs_split",  # (2 n_b, n): newton_solve's w_b, real parts in row 2 b, imaginary in 2 b + 1
    #                      (inverse form; else 0 x 0)
    "newton_scale",      # (n,) d_p, the equilibration of the Newton matrix
    "newton_point",      # (n,) where its Jacobian is taken (stepper._newton_point)
    "half_row",          # (s,) row 0 of E(offset 0, theta 1/2), the mean of u' over the step's first half
    #                      (stepper._newton_point; zero until its first use)
    "hessian",           # (n, n) Hess(H)(y0)
    "jacobian",          # (n, n) J0 = J Hess(H)(y0)
    "y_start",           # (n,) the state at the start of the step (restored on failure)
    "y_comp_start",      # (n,)
    "coef_start",        # (s, n) the coefficients before the step (restored on failure)
    "mult_start",        # (n_mult,)
    "coef_base",         # (s, n) the previous (sub)step's coefficients, base of the predictor
    "mult_base",         # (n_mult,)
    "predictor_points",  # (s + 1,) 1 + theta x_q
    "predictor_values",  # (s + 1, s + e_max) P_j(1 + theta x_q), e_max = min(k - s, 3) extra terms
    #                      (stepper.extrapolate: the (s+1)-point rule is exact up to 3 of them)
    "extrapolation",     # (s, s + e_max) E(theta)
    "info",              # (6,) of the last solve: last increment, cond(Gamma), iterations, rounding band;
    #                      then the count of Newton factorisations (Hessian evaluations) of the call, and
    #                      the substeps of the last step taken without imposing (stepper.try_step)
    "extra_start",       # (e_max, n) the predictor's extra terms before the step (restored on failure)
    "metric",            # (n,) LIM's diagonal metric W of the correction (ones: the spec's Euclidean one;
    #                      the scaled metric: the mean square of each component over the stages)
    "scaled_Is",         # (k, s), with scaled_Is_low: h Is + h Is_low as a double-double, for the h in
    "scaled_Is_low",     #   scaled_h (maps.scale_tables: the stages' tables)
    "scaled_Ihat",       # (r, s), and scaled_Ihat_low: the same for Ihat
    "scaled_Ihat_low",
    "scaled_h",          # (1,) the h of the scaled tables (NaN until the first)
    "stage_comp",        # (n,) the Kahan compensation of the (sub)step's start, added into its stages
])


@intrinsic
def _borrowed_view(typingctx, array):
    if not isinstance(array, types.Array):
        return None

    def codegen(context, builder, signature, args):
        source = context.make_array(array)(context, builder, args[0])
        view = context.make_array(array)(context, builder)
        context.populate_array(view, data=source.data, shape=source.shape, strides=source.strides,
                               itemsize=source.itemsize, meminfo=cgutils.get_null_value(source.meminfo.type))
        return view._getvalue()
    return array(array), codegen


def borrowed(array):
    """A view of ``array`` that owns no reference (meminfo and parent NULL) in compiled code;
    the array itself in the interpreter (NUMBA_DISABLE_JIT=1)."""
    return array


@overload(borrowed, jit_options={"cache": True})
def _borrowed_overload(array):
    if isinstance(array, types.Array):
        return lambda array: _borrowed_view(array)


class ByRef(types.Type):
    """The address of a Tables or Workspace struct in the frame of the kernel that made it
    (by_ref). Internal functions take it in place of the struct, and read its members
    through it as they read the struct's (``work.delta``), one load each.

    Why: Numba passes a struct argument member by member, and a Workspace is ~50 arrays of
    5-9 words each: every call that took it copied ~530 words onto the stack (the call of
    solve from _attempt was 531 push instructions), about 1 us per step in the calls of
    try_step, _attempt, solve and newton_factor, for every solver (measured with perf on the
    README's run)."""

    def __init__(self, value_type):
        self.value_type = value_type
        super().__init__(name=f"ByRef({value_type})")


register_model(ByRef)(models.OpaqueModel)


@intrinsic
def _by_ref(typingctx, value):
    if not isinstance(value, types.BaseNamedTuple):
        return None

    def codegen(context, builder, signature, args):
        slot = cgutils.alloca_once_value(builder, args[0])   # the kernel's entry block: lives as long as it
        return builder.bitcast(slot, cgutils.voidptr_t)
    return ByRef(value)(value), codegen


def by_ref(value):
    """``value`` (a Tables or Workspace) passed by its address in compiled code (ByRef); the
    value itself in the interpreter (NUMBA_DISABLE_JIT=1). Valid while the calling kernel
    runs: make it there, never return it."""
    return value


# inline="always": inlined in Numba's IR, so that the slot is the calling kernel's (a compiled
# overload is a function of its own, whose frame would end with the call)
@overload(by_ref, inline="always", jit_options={"cache": True})
def _by_ref_overload(value):
    if isinstance(value, types.BaseNamedTuple):
        return lambda value: _by_ref(value)


@infer_getattr
class _ByRefAttributes(AttributeTemplate):
    key = ByRef

    def generic_resolve(self, ref, attr):
        fields = ref.value_type.fields
        if attr in fields:
            return ref.value_type.types[fields.index(attr)]
        return None


@lower_getattr_generic(ByRef)
def _by_ref_getattr(context, builder, typ, value, attr):
    index = typ.value_type.fields.index(attr)
    struct = builder.bitcast(value, context.get_value_type(typ.value_type).as_pointer())
    member = builder.load(cgutils.gep_inbounds(builder, struct, 0, index))
    return impl_ret_borrowed(context, builder, typ.value_type.types[index], member)


@njit(cache=True)
def keep_alive(owner):
    """A use of ``owner`` that the compiler cannot drop: called after the last use of the
    borrowed views into it, it keeps Numba from releasing owner earlier."""
    return owner is not None


@njit(cache=True, inline="always")
def borrow_tables(t):
    """The same Tables, as borrowed views (see the module docstring)."""
    return Tables(borrowed(t.projection), borrowed(t.Is), borrowed(t.projection_hat), borrowed(t.Ihat),
                  borrowed(t.X), borrowed(t.abs_projection_hat), borrowed(t.predictor_nodes),
                  borrowed(t.predictor_basis), borrowed(t.newton_values), borrowed(t.newton_vectors),
                  borrowed(t.newton_inverse), borrowed(t.newton_weights), borrowed(t.Is_low), borrowed(t.Ihat_low))


@njit(cache=True, inline="always")
def borrow_workspace(w):
    """The same Workspace, as borrowed views (see the module docstring)."""
    return Workspace(
        borrowed(w.u), borrowed(w.grads), borrowed(w.proj), borrowed(w.gamma), borrowed(w.uhat),
        borrowed(w.grads_hat), borrowed(w.inv_grads), borrowed(w.phi),
        borrowed(w.small_matrix), borrowed(w.small_copy), borrowed(w.small_inverse), borrowed(w.small_vector),
        borrowed(w.small_pivots), borrowed(w.small_rounding), borrowed(w.sizes), borrowed(w.rounding_level),
        borrowed(w.component_increment), borrowed(w.carried), borrowed(w.h_powers), borrowed(w.new_coef),
        borrowed(w.delta), borrowed(w.scale), borrowed(w.newton_matrix), borrowed(w.newton_pivots),
        borrowed(w.newton_blocks), borrowed(w.newton_block_pivots), borrowed(w.newton_block_rhs),
        borrowed(w.newton_block_scratch), borrowed(w.newton_real_inverse),
        borrowed(w.newton_inverse_split), borrowed(w.newton_rhs_split), borrowed(w.newton_scale),
        borrowed(w.newton_point), borrowed(w.half_row),
        borrowed(w.hessian), borrowed(w.jacobian), borrowed(w.y_start), borrowed(w.y_comp_start),
        borrowed(w.coef_start), borrowed(w.mult_start), borrowed(w.coef_base), borrowed(w.mult_base),
        borrowed(w.predictor_points), borrowed(w.predictor_values), borrowed(w.extrapolation), borrowed(w.info),
        borrowed(w.extra_start), borrowed(w.metric), borrowed(w.scaled_Is), borrowed(w.scaled_Is_low),
        borrowed(w.scaled_Ihat), borrowed(w.scaled_Ihat_low), borrowed(w.scaled_h), borrowed(w.stage_comp))


# The Newton matrix is factorised in blocks whenever the method has an eigenbasis of X
# (tables.newton_values, methods/base.py): measured on Kepler (n = 4), one factorisation and
# 5 solves cost 0.76 us as inverted blocks against 1.62 us for the real 12 x 12 LU of
# EHBVM(12,3), and 1.5 us against 5.6 us at s = 6. Up to this n the blocks are inverted
# (linalg.invert, a matrix-vector product per solve); above it, LU-factorised (n^3/3
# instead of n^3: the solar system's n = 36).
INVERSE_MAX_N = 8


@njit(cache=True, inline="always")
def dense_sizes(n, s, n_eigenvalues):
    """(n_jacobian, n_blocks, n_full, n_scratch, n_real): the sizes of a workspace's dense arrays
    (hessian and jacobian n_jacobian^2; newton_blocks n_blocks n^2 complex, or newton_matrix
    n_full^2; newton_block_scratch n_scratch^2 complex; newton_real_inverse n_real^2; newton_inverse_split
    2 n_blocks n_scratch^2), for
    make_workspace and for the memory they take (workspace_dense_bytes). n_eigenvalues < 0: the
    fixed point, which has no Newton matrix and leaves them all empty (fpu_beta with 10^5
    masses: 640 GB of them)."""
    newton = n_eigenvalues >= 0
    n_blocks = max(n_eigenvalues, 0)
    n_full = s * n if newton and n_blocks == 0 else 0
    n_scratch = n if n_blocks > 0 and n <= INVERSE_MAX_N else 0
    n_real = n_scratch if s % 2 == 1 else 0     # an odd s has one real eigenvalue of X
    n_jacobian = n if newton else 0
    return n_jacobian, n_blocks, n_full, n_scratch, n_real


def workspace_dense_bytes(n: int, s: int, n_eigenvalues: int) -> int:
    """The bytes of one workspace's dense arrays (dense_sizes, evaluated in Python)."""
    # py_func: the plain function (also what dense_sizes is under NUMBA_DISABLE_JIT=1)
    n_jacobian, n_blocks, n_full, n_scratch, n_real = getattr(dense_sizes, "py_func", dense_sizes)(n, s, n_eigenvalues)
    return (16 * n_jacobian ** 2 + 16 * n_blocks * n * n + 8 * n_full ** 2 + 16 * n_scratch ** 2 + 8 * n_real ** 2
            + 16 * n_blocks * n_scratch ** 2)


@njit(cache=True)
def make_workspace(n, k, r, s, nu, family, n_inv, n_mult, n_eigenvalues):
    """Allocate every array a step needs (sizes as in the Workspace comments). The Newton
    matrix is factorised in n_eigenvalues complex blocks (tables.newton_values.shape[0]),
    inverted when n <= INVERSE_MAX_N, when there are some, else whole (the workspace's array
    shapes say which). n_eigenvalues < 0: the fixed point, whose dense arrays are left empty
    (dense_sizes)."""
    n_tilde = nu + 1 if family == FAMILY_LIM else nu
    n_jacobian, n_blocks, n_full, n_scratch, n_real = dense_sizes(n, s, n_eigenvalues)
    n_big = max(k, r, s)
    n_t = max(n_tilde, 1)
    e_max = min(k - s, 3)   # room for the predictor's extra terms (stepper.predictor_extra_rows)
    n_rhs_split = 2 * n_blocks if n_scratch > 0 else 0
    return Workspace(
        np.zeros((k, n)), np.zeros((k, n)), np.zeros((n_big, n)), np.zeros((n_big, n)), np.zeros((r, n)),
        np.zeros((max(n_tilde, 1), r, n)), np.zeros((n_inv, n)), np.zeros((n_t, n_big, n)),
        np.zeros((n_t, n_t)), np.zeros((n_t, n_t)), np.zeros((n_t, n_t)), np.zeros(n_t),
        np.zeros(n_t, dtype=np.int64), np.zeros((1, n_t)), np.zeros((1 + n_t, n)), np.zeros(n), np.zeros(n),
        np.zeros(n), np.zeros(max(nu, 1)),
        np.zeros((s, n)), np.zeros(3 * s * n), np.zeros(n),
        np.zeros((n_full, n_full)), np.zeros(n_full, dtype=np.int64),
        np.zeros((n_blocks, n, n), dtype=np.complex128), np.zeros((n_blocks, n), dtype=np.int64),
        np.zeros((n_blocks, n), dtype=np.complex128), np.zeros((n_scratch, n_scratch), dtype=np.complex128),
        np.zeros((n_real, n_real)),
        np.zeros((2 * n_blocks * n_scratch, n_scratch)), np.zeros((n_rhs_split, n_scratch)),
        np.zeros(n), np.zeros(n), np.zeros(s), np.zeros((n_jacobian, n_jacobian)), np.zeros((n_jacobian, n_jacobian)),
        np.zeros(n), np.zeros(n), np.zeros((s, n)), np.zeros(n_mult), np.zeros((s, n)), np.zeros(n_mult),
        np.zeros(s + 1), np.zeros((s + 1, s + e_max)), np.zeros((s, s + e_max)), np.zeros(6),
        np.zeros((e_max, n)), np.ones(n), np.zeros((k, s)), np.zeros((k, s)), np.zeros((r, s)), np.zeros((r, s)),
        np.full(1, np.nan), np.zeros(n))
