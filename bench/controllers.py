"""The two step controllers side by side on eccentric Kepler orbits (docs/adaptive.md).

    .venv/bin/python bench/controllers.py [--periods 10] [--markdown bench/results/controllers.md]

EHBVM(8,4) imposing angular_momentum and lrl_y, e = 0.6, 0.9, 0.99: the error controller
(rtol) against the time-reversible one (step_control="time_scale", epsilon). Per run: steps
and grad H evaluations per period, and the final error against the exact state (the state
after a whole number of periods is y0). Work counts are exact; no timings (see
bench/peers.py for those).
"""
import argparse
import math
from pathlib import Path

import numpy as np

import elimfast
from elimfast.methods import ehbvm
from elimfast.problems import kepler

CONSERVE = ("angular_momentum", "lrl_y")
SETTINGS = [("rtol", value) for value in (1e-11, 1e-12, 1e-13, 1e-14)] + \
           [("epsilon", value) for value in (0.2, 0.1, 0.05, 0.025)]


def run(eccentricity: float, periods: int, kind: str, value: float) -> dict:
    problem = kepler(eccentricity)
    control = {"rtol": value} if kind == "rtol" else {"step_control": "time_scale", "epsilon": value}
    result = elimfast.integrate(problem, ehbvm(8, 4), t_end=periods * 2 * math.pi, conserve=CONSERVE,
                                store_every=10 ** 9, **control)
    return {"status": result.status, "steps": result.steps_done / periods,
            "grad_H": result.stats["grad_H_evaluations"] / periods,
            "error": float(np.max(np.abs(result.y_final - problem.y0)))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--periods", type=int, default=10)
    parser.add_argument("--markdown", type=Path)
    args = parser.parse_args()
    lines = [f"EHBVM(8,4) imposing {', '.join(CONSERVE)}, Kepler, {args.periods} periods", "",
             "| e | controller | steps/period | grad H/period | final error | status |", "|---|---|---|---|---|---|"]
    for eccentricity in (0.6, 0.9, 0.99):
        for kind, value in SETTINGS:
            row = run(eccentricity, args.periods, kind, value)
            lines.append(f"| {eccentricity} | {kind} {value:g} | {row['steps']:.0f} | {row['grad_H']:.0f} | "
                         f"{row['error']:.1e} | {row['status']} |")
            print(lines[-1], flush=True)
    if args.markdown:
        args.markdown.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
