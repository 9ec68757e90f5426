"""Method objects: a family, (r, k, s), and the tables of docs/methods.md#notation built once.

A ``Family`` says what a family of methods does: its parameters, its multipliers (their
name and count), how many invariants it may impose and whether linear ones, whether it
has a Runge-Kutta form, and how to describe it. Each family module (hbvm.py, elim.py,
lim.py) declares its families; nothing outside ``elimfast.methods`` spells these out.
"""
from __future__ import annotations

import operator
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..errors import ParameterError

# elimfast.kernels (Numba) is imported only where a table is computed or a kernel code is
# asked for: the registry, the listings and `elimfast methods` import no Numba.

MAX_NODES = 64  # the quadrature is verified to a few ulp up to here


def quadrature(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n-point Gauss-Legendre nodes and weights on [0, 1] (docs/methods.md#notation)."""
    n = _positive_int("n", n)
    if n > MAX_NODES:
        raise ParameterError("n", f"must be <= {MAX_NODES} (the Gauss-Legendre nodes are verified up to there), got {n}")
    from ..kernels.quadrature import gauss_legendre

    nodes = np.empty(n)
    weights = np.empty(n)
    gauss_legendre(n, nodes, weights)
    return nodes, weights


def legendre_values(nodes: np.ndarray, n_values: int) -> np.ndarray:
    """Ps of docs/methods.md#notation: Ps[i, j] = P_j(c_i), j < n_values."""
    from ..kernels.quadrature import legendre_table

    nodes = np.ascontiguousarray(nodes, dtype=np.float64)
    values = np.empty((nodes.size, n_values))
    legendre_table(nodes, n_values, values)
    return values


def legendre_tables(nodes: np.ndarray, n_values: int, n_integrals: int) -> tuple[np.ndarray, np.ndarray]:
    """(Ps, Is) of docs/methods.md#notation at any nodes, in double precision: Ps[i, j] = P_j(c_i),
    j < n_values; Is[i, j] = int_0^{c_i} P_j, j < n_integrals. (A method's own Is, at its Gauss
    nodes, is integral_tables'.)"""
    from ..kernels.quadrature import legendre_integral_table

    nodes = np.ascontiguousarray(nodes, dtype=np.float64)
    integrals = np.empty((nodes.size, n_integrals))
    legendre_integral_table(nodes, n_integrals, integrals)
    return legendre_values(nodes, n_values), integrals


def integral_tables(nodes: np.ndarray, n_integrals: int) -> tuple[np.ndarray, np.ndarray]:
    """Is = int_0^{c_i} P_j at the exact Gauss nodes whose doubles are ``nodes`` (the len(nodes)-point
    rule), j < n_integrals, as a double-double (Is, Is_low): the kernels' stages take both
    (docs/methods.md#round-off-over-long-times)."""
    from ..kernels.quadrature import legendre_integral_table_dd

    nodes = np.ascontiguousarray(nodes, dtype=np.float64)
    high = np.empty((nodes.size, n_integrals))
    low = np.empty((nodes.size, n_integrals))
    legendre_integral_table_dd(nodes, nodes.size, n_integrals, high, low)
    return high, low


def integrates_exactly(degree, k, s) -> bool:
    """Whether the k-node quadrature of HBVM(k,s) and its relatives integrates a Hamiltonian that
    is a polynomial of this total degree exactly, so that the method keeps H to round-off:
    degree <= 2k/s (docs/methods.md). None or a negative degree (not a polynomial, or not known),
    or k or s unknown: False."""
    if degree is None or k is None or s is None or int(degree) < 0:
        return False
    return int(degree) * int(s) <= 2 * int(k)


def _positive_int(name: str, value) -> int:
    if isinstance(value, bool):
        raise ParameterError(name, f"must be a whole number (an integer), not {value!r}")
    try:
        as_int = operator.index(value)
    except TypeError:
        if isinstance(value, float) and value.is_integer():
            as_int = int(value)
        else:
            raise ParameterError(name, f"must be a whole number (an integer), got {value!r}") from None
    if as_int < 1:
        raise ParameterError(name, f"must be >= 1, got {as_int}")
    return as_int


# How many invariants (besides H) a family may impose: none, fewer than s, or any number.
IMPOSES_NONE, IMPOSES_FEWER_THAN_S, IMPOSES_ANY = "none", "fewer than s", "any"


@dataclass(frozen=True)
class Family:
    """What a family of methods does, declared once by its module.

    name: the registry name ('ehbvm'); parameters: the constructor's, in order (('k', 's'));
    constructor: the function that builds one (``ehbvm(k, s)``);
    kernel_map: the name of its map in the kernels, "elim" or "lim" (``kernel_family`` is
    its code, kernels.codes.FAMILY_ELIM or FAMILY_LIM); imposes:
    IMPOSES_NONE, IMPOSES_FEWER_THAN_S or IMPOSES_ANY; multiplier: the name of the
    per-step multipliers ('alpha', 'lambda') or None; multiplier_counts_H: the
    multipliers include one for H (LIM's lambda: nu + 1 of them, H first);
    imposes_linear: whether a linear invariant may be imposed; linear_refusal: why not,
    when it may not; scales_tableau: a step's Runge-Kutta form is the base tableau with
    eta_j = 1 - h^(2(s-1-j)) alpha_j (ELIM), else fixed; has_runge_kutta_form: LIM has
    none; description: one line for listings; notes: what a user should know; docs:
    where docs/methods.md explains it.
    """

    name: str
    parameters: tuple[str, ...]
    constructor: Callable[..., "Method"]
    kernel_map: str
    imposes: str
    multiplier: str | None
    multiplier_counts_H: bool
    imposes_linear: bool
    linear_refusal: str
    scales_tableau: bool
    has_runge_kutta_form: bool
    description: str
    notes: str
    docs: str

    @property
    def kernel_family(self) -> int:
        """The kernels' code of its map: codes.FAMILY_ELIM or FAMILY_LIM (imports the kernels)."""
        from ..kernels import codes
        return getattr(codes, f"FAMILY_{self.kernel_map.upper()}")

    def nodes_keeping_H(self, r, k) -> tuple[str, int]:
        """The quadrature H is kept to, named and counted: LIM imposes H with its invariants
        (multiplier_counts_H), and its loss of H follows r (a user trial: LIM(6,12,3)
        lost H to 4e-9 where HBVM(12,3) keeps 9e-13, and LIM(24,6,3) kept what HBVM(6,3) loses); the
        others keep H through the k nodes."""
        return ("r", r) if self.multiplier_counts_H and "r" in self.parameters else ("k", k)

    def signature(self) -> str:
        """'ehbvm(k, s)'."""
        return f"{self.name}({', '.join(self.parameters)})"


FAMILIES: dict[str, Family] = {}


def register(family: Family) -> Family:
    """Declare a family (its module does this at import); the registry keeps declaration order."""
    if family.name in FAMILIES:
        raise ValueError(f"method family {family.name!r} is declared twice")
    FAMILIES[family.name] = family
    return family


@dataclass(frozen=True, eq=False)
class Method:
    """A method of docs/methods.md (HBVM, ELIM, LIM) with its tables, built once.

    family: a registered family's name (``FAMILIES``; ``kind`` is its record). k nodes for H, r nodes
    for the invariants (r = k where the family has no separate r), s coefficients.
    Tables: c, b (k nodes and weights), Ps (k x k: P_j(c_l), j < k, enough for the
    stable right-hand side, docs/methods.md#stable-right-hand-side), Is (k x s) and Is_low, its
    low part (Is + Is_low is int_0^{c_l} P_j at the exact node to ~1e-32, double-double; the stages
    take both, docs/methods.md#round-off-over-long-times); chat, bhat, Ps_hat (r x r), Is_hat and
    Is_hat_low (r x s) at the r nodes; projection[j, l] = b_l P_j(c_l) and
    projection_hat[j, i] = bhat_i P_j(chat_i), the kernels' form of Ps^T Omega.
    Solver tables (docs/solver.md): X (s x s) = Ps^T Omega Is, tridiagonal (X[0,0] = 1/2,
    X[j,j-1] = -X[j-1,j] = 1/(2 sqrt(4j^2 - 1))), the simplified Newton matrix's;
    abs_projection_hat (max(r, k),) = S_j, the larger of sum_i |bhat_i P_j(chat_i)| and sum_l |b_l P_j(c_l)|
      where defined (the rounding estimate's S_j; phi_j comes from either node set);
    predictor_nodes (s+1,) and predictor_basis (s+1, s) = w_q P_i(x_q): the (s+1)-point
    Gauss rule of the predictor's projection E(theta). newton_values, newton_vectors,
    newton_inverse, newton_weights: X = V Lambda V^-1, one eigenvalue per conjugate pair
    (weight 2, a real one weight 1), for the block form of the Newton solve; empty when V
    is too ill-conditioned (large s) and the kernel factorises the full matrix instead.
    """

    family: str
    r: int
    k: int
    s: int
    c: np.ndarray = field(repr=False)
    b: np.ndarray = field(repr=False)
    Ps: np.ndarray = field(repr=False)
    Is: np.ndarray = field(repr=False)
    chat: np.ndarray = field(repr=False)
    bhat: np.ndarray = field(repr=False)
    Ps_hat: np.ndarray = field(repr=False)
    Is_hat: np.ndarray = field(repr=False)
    projection: np.ndarray = field(repr=False)
    projection_hat: np.ndarray = field(repr=False)
    X: np.ndarray = field(repr=False)
    abs_projection_hat: np.ndarray = field(repr=False)
    predictor_nodes: np.ndarray = field(repr=False)
    predictor_basis: np.ndarray = field(repr=False)
    newton_values: np.ndarray = field(repr=False)
    newton_vectors: np.ndarray = field(repr=False)
    newton_inverse: np.ndarray = field(repr=False)
    newton_weights: np.ndarray = field(repr=False)
    Is_low: np.ndarray = field(repr=False)
    Is_hat_low: np.ndarray = field(repr=False)

    @property
    def order(self) -> int:
        """Classical order 2s (docs/methods.md)."""
        return 2 * self.s

    @property
    def kind(self) -> Family:
        """The family's record: what this method does (multipliers, invariants, description)."""
        return FAMILIES[self.family]

    @property
    def kernel_family(self) -> int:
        return self.kind.kernel_family

    @property
    def imposes_invariants(self) -> bool:
        """True for ELIM/EHBVM/LIM/GHBVM: they accept invariants to conserve."""
        return self.kind.imposes != IMPOSES_NONE

    @property
    def has_runge_kutta_form(self) -> bool:
        """ELIM has one for given eta; LIM's correction acts through phi_0, so it has none."""
        return self.kind.has_runge_kutta_form

    @property
    def name(self) -> str:
        """'GAUSS(3)', 'EHBVM(12,3)', 'ELIM(8,12,3)': the family and its parameters."""
        return f"{self.family.upper()}({','.join(str(getattr(self, p)) for p in self.kind.parameters)})"

    @property
    def parameters(self) -> dict[str, int]:
        """The constructor's parameters and their values, e.g. {'k': 12, 's': 3}."""
        return {p: getattr(self, p) for p in self.kind.parameters}

    def __repr__(self) -> str:
        return f"<Method {self.name}, order {self.order}>"

    # Equal when built from the same family and parameters (the tables follow from them): a user
    # trial found ehbvm(12, 3) != ehbvm(12, 3). EHBVM(12,3) and ELIM(12,12,3), the same method under
    # two names, stay apart, as their names do.
    def __eq__(self, other) -> bool:
        if not isinstance(other, Method):
            return NotImplemented
        return (self.family, self.r, self.k, self.s) == (other.family, other.r, other.k, other.s)

    def __hash__(self) -> int:
        return hash((self.family, self.r, self.k, self.s))

    def max_conserved(self) -> int | None:
        """How many invariants (besides H) the method can impose; None: no limit."""
        imposes = self.kind.imposes
        if imposes == IMPOSES_FEWER_THAN_S:
            return self.s - 1
        if imposes == IMPOSES_ANY:
            return None
        return 0

    def multiplier_name(self, n_imposed: int) -> str | None:
        """'alpha', 'lambda' or None: the per-step multipliers of a run imposing n_imposed invariants."""
        return self.kind.multiplier if self.multiplier_count(n_imposed) else None

    def multiplier_count(self, n_imposed: int) -> int:
        """How many multipliers each step has: alpha: nu, lambda: nu + 1 (H too), none: 0."""
        if self.kind.multiplier is None:
            return 0
        return n_imposed + (1 if self.kind.multiplier_counts_H else 0)

    def multiplier_components(self, conserve) -> tuple[str, ...]:
        """The invariant behind each multiplier, in order: ('H', *conserve) for lambda, conserve for alpha."""
        if self.kind.multiplier is None:
            return ()
        return (("H",) if self.kind.multiplier_counts_H else ()) + tuple(conserve)

    def evaluations_per_iteration(self, n_imposed: int, stable_rhs: bool) -> tuple[int, int]:
        """(grad H, grad L) evaluations of one iteration of the family's map (kernels/maps.py),
        for a run imposing n_imposed invariants, with the stable right-hand side or not."""
        grad_H, grad_L = self.k, (self.r if n_imposed > 0 else 0)
        if self.kind.kernel_map == "lim":
            grad_H += self.r if self.r != self.k else 0     # H is one of LIM's invariants, at the r nodes
        if n_imposed > 0 and stable_rhs and self.r < self.k:
            grad_L += self.k            # the stable tail's grad L at the k nodes (maps.TAIL_K_NODES)
        return grad_H, grad_L

    def require_imposable(self, n_imposed: int) -> None:
        """ParameterError unless this method can impose n_imposed invariants besides H."""
        if n_imposed and not self.imposes_invariants:
            able = "/".join(name for name, kind in FAMILIES.items() if kind.imposes != IMPOSES_NONE)
            # (a user trial: GAUSS "cannot impose invariants besides H" read as if it kept any H)
            keeps = ("it imposes no invariant (it keeps quadratic ones by itself, H only when H is quadratic)"
                     if self.k == self.s else "it imposes no invariant besides H")
            raise ParameterError("conserve", f"must be empty for {self.name}: {keeps}; use "
                                             f"one of {able}, or remove conserve (docs/methods.md#methods)")
        limit = self.max_conserved()
        if limit is not None and n_imposed > limit:
            raise ParameterError("s", f"must be >= {n_imposed + 1} to impose {n_imposed} invariant(s): {self.name} "
                                      f"imposes at most s - 1 = {limit}, one for each of the coefficients "
                                      "gamma_1..gamma_(s-1) (gamma_0 fixes y1; docs/methods.md#elim); raise s to "
                                      f"{n_imposed + 1} or conserve fewer")

    def butcher(self, eta=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, b, c) of the Runge-Kutta form: A = Is diag(1, eta_1..eta_{s-1}) Ps^T Omega.

        Spec sections 2 and 3 (paper section 2.3). eta defaults to ones (HBVM(k,s));
        for ELIM pass the step's eta (length s or s-1; eta_0 is always 1).
        """
        if not self.has_runge_kutta_form:
            raise ValueError(
                f"{self.name} has no fixed Runge-Kutta form: its correction -c h phi_0 lambda "
                "depends on the invariants' gradients (docs/methods.md#lim); use the HBVM of the same k, s for its "
                "base tableau")
        s = self.s
        if eta is None:
            eta_full = np.ones(s)
        else:
            eta = np.asarray(eta, dtype=float).ravel()
            if eta.size == s - 1:
                eta_full = np.concatenate(([1.0], eta))
            elif eta.size == s:
                if eta[0] != 1.0:
                    raise ValueError(f"eta_0 must be 1 (docs/methods.md#elim), got {eta[0]}")
                eta_full = eta
            else:
                raise ValueError(f"eta must have {s - 1} or {s} entries for {self.name}, got {eta.size}")
        A = self.Is @ np.diag(eta_full) @ self.Ps[:, :s].T @ np.diag(self.b)
        return A, self.b.copy(), self.c.copy()


def build(family: str, r: int, k: int, s: int) -> Method:
    """Validate (k >= s >= 1, r >= s, k, r <= 64) and build the tables once.

    Errors are ParameterErrors naming the family's own parameter (GAUSS(s) has only s:
    a bad value is reported as s, not as the k = s it implies) and what to change.
    """
    kind = FAMILIES[family]
    values = {"r": r, "k": k, "s": s}
    for name in kind.parameters:
        values[name] = _positive_int(name, values[name])
    r, k, s = (_positive_int(name, values[name]) for name in ("r", "k", "s"))

    def own(name: str) -> str:   # the parameter the user gave that sets this one
        return name if name in kind.parameters else ("k" if "k" in kind.parameters else "s")

    if k < s:
        raise ParameterError(own("k"), f"must be >= s = {s} (the quadrature needs at least s nodes), got {k}; "
                                       "raise k or lower s")
    if r < s:
        raise ParameterError(own("r"), f"must be >= s = {s} (the invariants' quadrature needs at least s nodes), "
                                       f"got {r}; raise r or lower s")
    if s >= MAX_NODES:   # the predictor takes s + 1 nodes (a user trial: GAUSS(64) was told "--n must be <= 64")
        raise ParameterError(own("s"), f"must be <= {MAX_NODES - 1} (the predictor's s + 1 Gauss-Legendre nodes are "
                                       f"verified up to {MAX_NODES}), got {s}")
    for name, value in (("k", k), ("r", r)):
        if value > MAX_NODES:
            raise ParameterError(own(name), f"must be <= {MAX_NODES} (the Gauss-Legendre nodes are verified up to "
                                            f"there), got {value}")
    c, b = quadrature(k)
    Ps = legendre_values(c, k)
    Is, Is_low = integral_tables(c, s)
    chat, bhat = (c, b) if r == k else quadrature(r)
    Ps_hat = Ps if r == k else legendre_values(chat, r)
    Is_hat, Is_hat_low = (Is, Is_low) if r == k else integral_tables(chat, s)
    # Left writable: Numba types read-only arrays differently from the kernels' signatures.
    projection = (b[:, None] * Ps).T
    projection_hat = (bhat[:, None] * Ps_hat).T
    X = projection[:s] @ Is                        # exact: the integrand has degree <= 2s - 1 <= 2k - 1
    # S_j bounds the rounding of phi_j from either node set: the stable tail takes phi_j (j >= s) at the
    # k nodes when r < k (kernels/maps.py, elim_rhs_terms), so S has max(r, k) entries.
    abs_projection_hat = np.zeros(max(r, k))
    abs_projection_hat[:r] = np.abs(projection_hat).sum(axis=1)
    abs_projection_hat[:k] = np.maximum(abs_projection_hat[:k], np.abs(projection).sum(axis=1))
    predictor_nodes, predictor_weights = quadrature(s + 1)
    predictor_basis = predictor_weights[:, None] * legendre_values(predictor_nodes, s)
    arrays = [np.ascontiguousarray(a) for a in (c, b, Ps, Is, chat, bhat, Ps_hat, Is_hat, projection, projection_hat,
                                                 X, abs_projection_hat, predictor_nodes, predictor_basis,
                                                 *newton_eigenbasis(X), Is_low, Is_hat_low)]
    return Method(kind.name, r, k, s, *arrays)


# Above this condition number of X's eigenvectors the block form of the Newton solve
# loses digits that simplified Newton would pay for in iterations; the full matrix is
# then factorised. Measured cond(V): 13 at s = 3, 44 at s = 4, 5.6e2 at s = 6, 7.4e3
# at s = 8, 9.9e4 at s = 10, 1.3e6 at s = 12 (V Lambda V^-1 then misses X by 1.6e-7).
MAX_EIGENBASIS_CONDITION = 1e5


def newton_eigenbasis(X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(values, vectors, inverse, weights) of X = V Lambda V^-1 for the block Newton solve (docs/solver.md).

    One eigenvalue per conjugate pair (Im > 0, weight 2) and each real one (weight 1); V's
    columns of a pair are exact conjugates, so that V^-1 r of a real r has conjugate
    entries for the pair and sum_b weight_b Re(V[:, b] z_b) is V z. Empty arrays when
    cond(V) exceeds MAX_EIGENBASIS_CONDITION.
    """
    s = X.shape[0]
    values, vectors = np.linalg.eig(X)
    order = np.argsort(-values.imag)
    values, vectors = values[order], vectors[:, order]
    representatives, columns, weights = [], [], []
    used = np.zeros(s, dtype=bool)
    for i in range(s):
        if used[i]:
            continue
        used[i] = True
        if abs(values[i].imag) <= 1e-12 * max(1.0, abs(values[i])):
            representatives.append(values[i].real + 0j)
            columns.append(vectors[:, i].real.astype(complex))
            weights.append(1.0)
            continue
        partner = min((j for j in range(s) if not used[j]), key=lambda j: abs(values[j] - values[i].conjugate()))
        used[partner] = True
        representatives.append(values[i])
        columns.append(vectors[:, i])
        weights.append(2.0)
    full = []
    for value, column, weight in zip(representatives, columns, weights):
        full.append(column)
        if weight == 2.0:
            full.append(column.conjugate())
    V_full = np.column_stack(full)
    empty = (np.zeros(0, complex), np.zeros((s, 0), complex), np.zeros((0, s), complex), np.zeros(0))
    if not np.all(np.isfinite(V_full)) or np.linalg.cond(V_full) > MAX_EIGENBASIS_CONDITION:
        return empty
    inverse_full = np.linalg.inv(V_full)
    rows = []
    index = 0
    for weight in weights:
        # A real eigenvalue's row of V^-1 is real: its rounding's imaginary part (~1e-17) dropped,
        # so that the kernels can take that block in real arithmetic (solver.newton_factor).
        rows.append(inverse_full[index] if weight == 2.0 else inverse_full[index].real.astype(complex))
        index += 2 if weight == 2.0 else 1
    return (np.array(representatives, dtype=complex), np.column_stack(columns).astype(complex),
            np.array(rows, dtype=complex), np.array(weights))
