"""Adaptive against fixed steps at equal final error, over 1000 periods of Kepler e = 0.9 (issue 11).

    .venv/bin/python bench/adaptive_vs_fixed.py [--periods 1000] [--starts 5] [--markdown bench/results/adaptive_vs_fixed.md]
    .venv/bin/python bench/adaptive_vs_fixed.py --project-energy --markdown bench/results/adaptive_vs_fixed_projected.md

The issue's question: how many fewer grad H evaluations does adaptive EHBVM(8,4) need than
fixed-step EHBVM(12,4), both imposing angular_momentum and lrl_y, at equal final error? The
exact state after a whole number of periods is y0, up to the rounding of y0 itself
(exact_state). Fixed steps: h = 2 pi / N for N steps
per period on a grid; adaptive: the error controller at several rtol and the time-reversible
controller at several epsilon. For each adaptive setting, the cheapest fixed N whose error is
at or below it; the ratio of their grad H counts (adaptive: stats['grad_H_evaluations'];
fixed: k x the iterations of every step). Work counts are exact; the wall times are medians
of one run per start, on a shared machine.

Over this long a time both errors are mostly rounding: the state error of one run is a
random walk's end point (the random walk of H drives the phase), not monotone in N, and
neighbouring settings differ by 10x or more. Comparing single runs then compares luck. So
every setting is run from several starts on the same orbit, at mean anomalies 0, 1e-3,
2e-3, ... after the pericentre (the same sensitivity to a phase error, independent
rounding), and compared by the median of the final errors; the largest is shown too.

``--project-energy``: every run with ``solver.project_energy`` (docs/methods.md#energy-projection),
which removes H's round-off walk: the errors are then the truncation's, growing linearly.
"""
import argparse
import math
import statistics
import time
from pathlib import Path

import numpy as np

import elimfast
from elimfast.methods import ehbvm
from elimfast.problems import kepler

CONSERVE = ("angular_momentum", "lrl_y")
ECCENTRICITY = 0.9
RTOLS = (1e-11, 1e-12, 1e-13, 1e-14)
EPSILONS = (0.15, 0.12, 0.1, 0.08)
STEPS_PER_PERIOD = (400, 480, 560, 640, 720, 800, 960, 1120, 1280, 1440, 1600, 1800, 2000, 2400)
START_SPACING = 1e-3


def start_state(mean_anomaly: float, e: float = ECCENTRICITY) -> np.ndarray:
    """The orbit of kepler(e) (a = 1, period 2 pi) at a mean anomaly: Kepler's equation by Newton."""
    anomaly = mean_anomaly
    for _ in range(50):
        anomaly -= (anomaly - e * math.sin(anomaly) - mean_anomaly) / (1.0 - e * math.cos(anomaly))
    c, s, b = math.cos(anomaly), math.sin(anomaly), math.sqrt(1.0 - e * e)
    r = 1.0 - e * c
    return np.array([c - e, b * s, -s / r, b * c / r])


def exact_state(y0: np.ndarray, t_end: float) -> np.ndarray:
    """The exact state at t_end of the Kepler orbit (mu = 1) through the doubles y0, for a t_end of
    a whole number of nominal periods 2 pi. That is y0 only if y0's energy is exactly -1/2, and
    the doubles of a state are not: their energy is off by up to ~1e-14 (the starts' computed
    by Kepler's equation), so the orbit's own period differs from 2 pi, and after 1000 periods
    the state is dt f(y0) away from y0, dt = t_end - 1000 P. Measured for the five starts:
    7e-10, 7.3e-9, 3.3e-9, 2.5e-8, 4.2e-9; taking y0 as the reference (as this bench and
    bench/controllers.py did until the energy projection showed it) put a floor of that size
    under the errors. H and dt in 40 digits (mpmath, sympy's dependency); dt is so small
    (< 1e-9) that the first order is exact to far below the errors measured."""
    import mpmath
    with mpmath.workdps(40):
        q1, q2, p1, p2 = (mpmath.mpf(float(value)) for value in y0)
        r = mpmath.sqrt(q1 * q1 + q2 * q2)
        energy = (p1 * p1 + p2 * p2) / 2 - 1 / r
        period = 2 * mpmath.pi / (-2 * energy) ** mpmath.mpf(1.5)
        periods = mpmath.nint(mpmath.mpf(t_end) / (2 * mpmath.pi))
        dt = mpmath.mpf(t_end) - periods * period
        velocity = [p1, p2, -q1 / r ** 3, -q2 / r ** 3]
        return np.array([float(mpmath.mpf(value) + dt * rate) for value, rate in zip(y0, velocity)])


def problems(starts: int, eccentricity: float = ECCENTRICITY):
    """kepler(e) from `starts` points of its orbit: the pericentre (its own y0), then mean anomalies
    START_SPACING, 2 START_SPACING, ... (bench/controllers.py takes them too)."""
    base = kepler(eccentricity)
    return [base if j == 0 else base.with_initial(start_state(j * START_SPACING, eccentricity))
            for j in range(starts)]


SOLVER = {}   # the solver settings of every run (--project-energy)
SOLVER_ARGS = {}   # integrate's keyword for them, when there are any


def one_run(problem, periods: int, setting: dict) -> dict:
    start = time.perf_counter()
    t_end = periods * 2 * math.pi
    if "per_period" in setting:
        method = ehbvm(12, 4)
        result = elimfast.integrate(problem, method, 2 * math.pi / setting["per_period"],
                                    n_steps=periods * setting["per_period"], conserve=CONSERVE, store_every=10 ** 9,
                                    **SOLVER_ARGS)
        grad_H = method.k * int(np.sum(result.iterations)) + (result.steps_done if SOLVER else 0)
    else:
        options = {key: value for key, value in setting.items() if key != "label"}
        result = elimfast.integrate(problem, ehbvm(8, 4), t_end=t_end, conserve=CONSERVE, store_every=10 ** 9,
                                    **SOLVER_ARGS, **options)
        grad_H = result.stats["grad_H_evaluations"]
    return {"status": result.status, "seconds": time.perf_counter() - start, "steps": result.steps_done,
            "grad_H": grad_H, "error": float(np.max(np.abs(result.y_final - exact_state(problem.y0, t_end))))}


def run_setting(starts, periods: int, setting: dict) -> dict:
    runs = [one_run(problem, periods, setting) for problem in starts]
    row = {"setting": setting["label"], "runs": runs,
           "status": "complete" if all(r["status"] == "complete" for r in runs) else
           ", ".join(sorted({r["status"] for r in runs})),
           "steps": statistics.mean(r["steps"] for r in runs),
           "grad_H": statistics.mean(r["grad_H"] for r in runs),
           "error": statistics.median(r["error"] for r in runs),
           "worst": max(r["error"] for r in runs),
           "seconds": statistics.median(r["seconds"] for r in runs)}
    print({key: value for key, value in row.items() if key != "runs"}, flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--periods", type=int, default=1000)
    parser.add_argument("--starts", type=int, default=5, help="runs per setting, from mean anomalies 0, 1e-3, ...")
    parser.add_argument("--markdown", type=Path)
    parser.add_argument("--project-energy", action="store_true", help="every run with solver.project_energy")
    args = parser.parse_args()
    if args.project_energy:
        SOLVER["project_energy"] = True
        SOLVER_ARGS["solver"] = SOLVER
    starts = problems(args.starts)
    adaptive = {"error controller": [run_setting(starts, args.periods, {"label": f"rtol = {rtol:g}", "rtol": rtol})
                                     for rtol in RTOLS],
                "time-reversible": [run_setting(starts, args.periods,
                                                {"label": f"epsilon = {eps:g}", "step_control": "time_scale",
                                                 "epsilon": eps}) for eps in EPSILONS]}
    fixed = [run_setting(starts, args.periods, {"label": f"h = 2 pi / {n}", "per_period": n})
             for n in STEPS_PER_PERIOD]
    lines = [f"# Adaptive against fixed steps: Kepler e = {ECCENTRICITY}, {args.periods} periods", "",
             f"Generated by `bench/adaptive_vs_fixed.py --periods {args.periods} --starts {args.starts}`. Every run "
             f"imposes {', '.join(CONSERVE)}{' with solver.project_energy' if SOLVER else ''}; error: max-norm of y(t_end) - "
             "the exact state (y0 moved by the orbit's own period, exact_state), "
             f"median over {args.starts} starts at mean anomalies 0, {START_SPACING:g}, ... (worst: the largest); "
             "grad H and steps: their mean. Wall time: median, shared 2-core machine.", "",
             "| method | setting | steps per period | grad H | median error | worst error | wall time | status |",
             "|---|---|---|---|---|---|---|---|"]
    rows = [(f"EHBVM(8,4), {name}", row) for name, group in adaptive.items() for row in group]
    rows += [("EHBVM(12,4) fixed step", row) for row in fixed]
    for name, row in rows:
        lines.append(f"| {name} | {row['setting']} | {row['steps'] / args.periods:.1f} | {row['grad_H']:,.0f} | "
                     f"{row['error']:.2e} | {row['worst']:.2e} | {row['seconds']:.2f} s | {row['status']} |")
    lines += ["", "At equal final error: for each adaptive setting, the cheapest fixed step whose median error is at "
              "or below its median error.", "",
              "| adaptive | its median error | cheapest fixed step at or below | its median error | "
              "grad H, fixed / adaptive |", "|---|---|---|---|---|"]
    for name, group in adaptive.items():
        for row in group:
            reaching = [f for f in fixed if f["status"] == "complete" and f["error"] <= row["error"]]
            if not reaching:
                lines.append(f"| {name}, {row['setting']} | {row['error']:.2e} | none on the grid | - | - |")
                continue
            best = min(reaching, key=lambda f: f["grad_H"])
            lines.append(f"| {name}, {row['setting']} | {row['error']:.2e} | {best['setting']} | {best['error']:.2e} | "
                         f"{best['grad_H'] / row['grad_H']:.1f}x |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.markdown:
        args.markdown.write_text(text)


if __name__ == "__main__":
    main()
