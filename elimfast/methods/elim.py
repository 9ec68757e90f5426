"""ELIM(r,k,s) and EHBVM(k,s) = ELIM(k,k,s): docs/methods.md#elim (the paper's new methods)."""
from .base import IMPOSES_FEWER_THAN_S, Family, Method, build, register


def elim(r: int, k: int, s: int) -> Method:
    """ELIM(r,k,s): HBVM(k,s) whose last nu coefficients are scaled to conserve nu < s invariants."""
    return build("elim", r, k, s)


def ehbvm(k: int, s: int) -> Method:
    """EHBVM(k,s) = ELIM(k,k,s)."""
    return build("ehbvm", k, k, s)


_ELIM = dict(
    kernel_map="elim", imposes=IMPOSES_FEWER_THAN_S, multiplier="alpha", multiplier_counts_H=False,
    imposes_linear=False, scales_tableau=True, has_runge_kutta_form=True, docs="docs/methods.md#elim",
    linear_refusal=("every Runge-Kutta method keeps linear invariants exactly, {method} included, and ELIM cannot "
                    "impose one (its column of Gamma vanishes, docs/methods.md#linear-invariants); leave it out of "
                    "conserve (or impose it with lim/ghbvm)"),
    notes="Imposes nu < s invariants by scaling gamma_(s-nu)..gamma_(s-1) with eta_j = 1 - h^(2(s-1-j)) alpha_j; "
          "alpha = O(h^2). Cannot impose linear invariants (it keeps them anyway).")

register(Family(
    name="elim", parameters=("r", "k", "s"), constructor=elim, **_ELIM,
    description="HBVM(k,s) with its last nu coefficients scaled to conserve nu < s invariants (r nodes for them)"))
register(Family(
    name="ehbvm", parameters=("k", "s"), constructor=ehbvm, **_ELIM,
    description="ELIM(k,k,s): conserves H and up to s-1 invariants"))
