"""LIM(r,k,s) and GHBVM(k,s) = LIM(k,k,s): docs/methods.md#lim (Brugnano & Iavernaro 2012)."""
from .base import IMPOSES_ANY, Family, Method, build, register


def lim(r: int, k: int, s: int) -> Method:
    """LIM(r,k,s): HBVM(k,s) with a correction -c h phi_0 lambda imposing H and the chosen invariants."""
    return build("lim", r, k, s)


def ghbvm(k: int, s: int) -> Method:
    """GHBVM(k,s) = LIM(k,k,s)."""
    return build("ghbvm", k, k, s)


# lambda has one entry for H and one per imposed invariant: LIM treats H as one more invariant.
_LIM = dict(
    kernel_map="lim", imposes=IMPOSES_ANY, multiplier="lambda", multiplier_counts_H=True,
    imposes_linear=True, linear_refusal="", scales_tableau=False, has_runge_kutta_form=False,
    docs="docs/methods.md#lim",
    notes="Imposes H and any number of invariants through one correction of gamma_0; lambda = O(h^(2s)). "
          "Has no fixed Runge-Kutta form.")

register(Family(
    name="lim", parameters=("r", "k", "s"), constructor=lim, **_LIM,
    description="HBVM(k,s) with the correction -c h phi_0 lambda: H and any number of invariants (no RK form)"))
register(Family(
    name="ghbvm", parameters=("k", "s"), constructor=ghbvm, **_LIM,
    description="LIM(k,k,s): conserves H and any number of invariants (no RK form)"))
