"""elimfast beside other integrators on Kepler e = 0.6 (issue 5, item 4).

Usage: .venv/bin/python bench/peers.py [--repeats 5] [--long-repeats 3] [--out-dir bench/results]

Needs the ``bench`` extra (``pip install -e '.[bench]'``: scipy, rebound, heyoka); a
peer that cannot be imported is skipped with a message.

1. Work-precision over 10 periods (t = 20 pi; the exact y(20 pi) is y0): max-norm
   error of y against wall time, for GAUSS(s) s = 2, 3, 4, HBVM(12,s) and EHBVM(12,s)
   imposing angular momentum and lrl_y (s = 3, 4) at h = pi/N, scipy's DOP853 at
   several rtol (= atol), REBOUND's IAS15 at several epsilon and heyoka's Taylor
   integrator at several tolerances.
2. Long-time behaviour on [0, 1000]: elimfast at h = 0.1, the adaptive peers at their
   default and at tight tolerances. Max error in H, angular momentum L and the LRL
   vector A over the run, whether it drifts, the error of y at t = 1000 against the
   exact solution (Kepler's equation), and the wall time.

Fairness: every integrator is timed in this one process, the configurations
interleaved round by round, and the median kept (the machine is shared). Timed runs
keep only the final state (elimfast: store_every = n_steps; IAS15 and heyoka: one
propagate call); the invariants come from separate, untimed runs that record every
step. One-time costs are excluded and reported: heyoka compiles each integrator with
LLVM when it is built; elimfast's kernel is compiled once and cached on disk. scipy
calls a Python right-hand side (written with floats and ``math``), which dominates its
cost: that is how solve_ivp is used, but it is not a statement about DOP853 itself.
REBOUND integrates a test particle (m = 0) around a unit mass with G = 1, the planar
Kepler problem in Cartesian coordinates; y = (x, y, vx, vy) of the particle relative
to the central body. heyoka integrates the hand-written Kepler ODE
q' = p, p' = -q / |q|^3.
"""
import argparse
import importlib
import math
import os
import platform
import statistics
import sys
import time
import warnings
from decimal import Decimal, getcontext
from pathlib import Path

import numpy as np

import elimfast
from elimfast.methods import ehbvm, gauss, ghbvm, hbvm
from elimfast.problems import kepler

ROOT = Path(__file__).resolve().parents[1]
ECCENTRICITY = 0.6
T_SHORT = 20.0 * math.pi          # 10 periods
T_LONG = 1000.0
H_LONG = 0.1
STEP_DIVISORS = (15, 30, 60, 120, 240, 480)   # h = pi / N
CONSERVE = ("angular_momentum", "lrl_y")
DOP853_RTOLS = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12, 1e-13)
IAS15_EPSILONS = (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-9)   # 1e-9 is REBOUND's default
HEYOKA_TOLS = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12, 1e-14, None)  # None: heyoka's default, machine epsilon
ROUND_OFF = 1e-13                 # an invariant error below this over the run is round-off
TWO_PI = "6.2831853071795864769252867665590057683943387987502"

PROBLEM = kepler(ECCENTRICITY)
Y0 = PROBLEM.y0.copy()


def optional_import(name):
    try:
        return importlib.import_module(name)
    except ImportError as error:
        print(f"skipping {name}: it cannot be imported ({error}); install the bench extra: "
              f"pip install -e '.[bench]'", file=sys.stderr)
        return None


scipy_integrate = optional_import("scipy.integrate")
rebound = optional_import("rebound")
heyoka = optional_import("heyoka")


# --- the exact solution and the invariants (one NumPy formula for every integrator) -----
def exact_state(t):
    """Kepler e = 0.6, a = 1, perihelion at t = 0: solve E - e sin E = t (mod 2 pi) by Newton."""
    getcontext().prec = 50
    two_pi = Decimal(TWO_PI)
    turns = int(Decimal(repr(t)) / two_pi)
    mean_anomaly = float(Decimal(repr(t)) - turns * two_pi)
    e = ECCENTRICITY
    E = mean_anomaly if e < 0.8 else math.pi
    for _ in range(50):
        step = (E - e * math.sin(E) - mean_anomaly) / (1.0 - e * math.cos(E))
        E -= step
        if abs(step) < 1e-17:
            break
    root = math.sqrt(1.0 - e * e)
    speed = 1.0 / (1.0 - e * math.cos(E))
    return np.array([math.cos(E) - e, root * math.sin(E), -math.sin(E) * speed, root * math.cos(E) * speed])


def invariants(Y):
    """H, L, A_x, A_y of states Y (n, 4) (docs/methods.md#typos-in-the-paper)."""
    q1, q2, p1, p2 = Y[:, 0], Y[:, 1], Y[:, 2], Y[:, 3]
    r = np.sqrt(q1 * q1 + q2 * q2)
    L = q1 * p2 - q2 * p1
    H = 0.5 * (p1 * p1 + p2 * p2) - 1.0 / r
    return H, L, p2 * L - q1 / r, -p1 * L - q2 / r


def kepler_rhs(t, y):
    q1, q2, p1, p2 = y
    r2 = q1 * q1 + q2 * q2
    inv_r3 = 1.0 / (r2 * math.sqrt(r2))
    return [p1, p2, -q1 * inv_r3, -q2 * inv_r3]


# --- the integrators: final(T) is timed; trajectory(T) records every step ---------------
class ElimfastRun:
    family = "elimfast"

    def __init__(self, method, h, conserve=()):
        self.method, self.h, self.conserve = method, h, tuple(conserve)
        imposed = f" + {', '.join('L' if c == 'angular_momentum' else c for c in conserve)}" if conserve else ""
        self.label = f"{method.name}{imposed}"

    def setting(self):
        return f"h = {self.h:.4g}"

    def n_steps(self, T):
        return int(round(T / self.h))

    def final(self, T):
        n = self.n_steps(T)
        return elimfast.integrate(PROBLEM, self.method, self.h, n_steps=n, conserve=self.conserve,
                                  store_every=n).y_final

    def trajectory(self, T):
        r = elimfast.integrate(PROBLEM, self.method, self.h, n_steps=self.n_steps(T), conserve=self.conserve)
        return r.t, r.y, f"{r.n_steps} steps, {int(r.iterations.sum())} iterations"


class Dop853Run:
    family = "scipy DOP853"

    def __init__(self, rtol, atol=None, note=""):
        self.rtol, self.atol = rtol, rtol if atol is None else atol
        self.label = "scipy DOP853" + note

    def setting(self):
        return f"rtol = {self.rtol:.0e}, atol = {self.atol:.0e}"

    def _solve(self, T):
        return scipy_integrate.solve_ivp(kepler_rhs, (0.0, T), Y0, method="DOP853", rtol=self.rtol, atol=self.atol)

    def final(self, T):
        return self._solve(T).y[:, -1]

    def trajectory(self, T):
        solution = self._solve(T)
        return solution.t, solution.y.T, f"{solution.t.size - 1} steps, {solution.nfev} f-evaluations"


class Ias15Run:
    family = "REBOUND IAS15"

    def __init__(self, epsilon, note=""):
        self.epsilon = epsilon
        self.label = "REBOUND IAS15" + note

    def setting(self):
        return f"epsilon = {self.epsilon:.0e}"

    def _simulation(self):
        sim = rebound.Simulation()
        sim.G = 1.0
        sim.add(m=1.0)
        sim.add(m=0.0, x=Y0[0], y=Y0[1], vx=Y0[2], vy=Y0[3])
        sim.integrator = "ias15"
        sim.integrator.epsilon = self.epsilon
        return sim

    @staticmethod
    def _state(sim):
        star, planet = sim.particles[0], sim.particles[1]
        return np.array([planet.x - star.x, planet.y - star.y, planet.vx - star.vx, planet.vy - star.vy])

    def final(self, T):
        sim = self._simulation()
        sim.integrate(T, exact_finish_time=1)
        return self._state(sim)

    def trajectory(self, T):
        # exact_finish_time=0: each call stops at the first step end past the sample time,
        # so sampling does not change the step sequence.
        sim = self._simulation()
        times, states = [0.0], [Y0.copy()]
        for sample in np.arange(1, int(round(T / H_LONG)) + 1) * H_LONG:
            if sim.t < sample:
                sim.integrate(sample, exact_finish_time=0)
                times.append(sim.t)
                states.append(self._state(sim))
        return np.array(times), np.array(states), f"{sim.steps_done} steps"


class HeyokaRun:
    family = "heyoka Taylor"
    _cache = {}

    def __init__(self, tol, note=""):
        self.tol = tol
        self.label = "heyoka Taylor" + note
        self.build_seconds = None

    def setting(self):
        return "tol = eps (default)" if self.tol is None else f"tol = {self.tol:.0e}"

    def integrator(self):
        if self.tol not in HeyokaRun._cache:
            x, y, vx, vy = heyoka.make_vars("x", "y", "vx", "vy")
            r3 = heyoka.sqrt(x * x + y * y) ** 3
            system = [(x, vx), (y, vy), (vx, -x / r3), (vy, -y / r3)]
            options = {} if self.tol is None else {"tol": self.tol}
            start = time.perf_counter()
            HeyokaRun._cache[self.tol] = (heyoka.taylor_adaptive(system, Y0.copy(), **options),
                                          time.perf_counter() - start)
        ta, self.build_seconds = HeyokaRun._cache[self.tol]
        ta.time = 0.0
        ta.state[:] = Y0
        return ta

    def final(self, T):
        ta = self.integrator()
        ta.propagate_until(T)
        return ta.state.copy()

    def trajectory(self, T):
        ta = self.integrator()
        times, states = [0.0], [Y0.copy()]
        while ta.time < T:
            ta.step(T - ta.time)     # never past T
            times.append(ta.time)
            states.append(ta.state.copy())
        return np.array(times), np.array(states), f"{len(times) - 1} steps, order {ta.order}"


# --- timing ---------------------------------------------------------------------------
def median_times(runs, T, repeats):
    """Median wall time of run.final(T) per run; the runs interleaved round by round."""
    times = {id(run): [] for run in runs}
    finals = {}
    for run in runs:                       # warm-up: caches, JIT builds, first-call costs
        finals[id(run)] = run.final(T)
    for _ in range(repeats):
        for run in runs:
            start = time.perf_counter()
            run.final(T)
            times[id(run)].append(time.perf_counter() - start)
    return {key: statistics.median(values) for key, values in times.items()}, finals


def peers_short():
    runs = []
    if scipy_integrate is not None:
        runs += [Dop853Run(rtol) for rtol in DOP853_RTOLS]
    if rebound is not None:
        runs += [Ias15Run(epsilon) for epsilon in IAS15_EPSILONS]
    if heyoka is not None:
        runs += [HeyokaRun(tol) for tol in HEYOKA_TOLS]
    return runs


def elimfast_short():
    methods = [(gauss(2), ()), (gauss(3), ()), (gauss(4), ()), (hbvm(12, 3), ()), (hbvm(12, 4), ()),
               (ehbvm(12, 3), CONSERVE), (ehbvm(12, 4), CONSERVE)]
    runs = []
    for method, conserve in methods:
        for divisor in STEP_DIVISORS:
            run = ElimfastRun(method, math.pi / divisor, conserve)
            try:
                run.final(T_SHORT)
            except elimfast.ConvergenceError as error:
                print(f"work-precision: {run.label} at h = pi/{divisor} fails ({error.reason}): left out",
                      file=sys.stderr)
                continue
            runs.append(run)
    return runs


def work_precision(repeats):
    runs = elimfast_short() + peers_short()
    seconds, finals = median_times(runs, T_SHORT, repeats)
    rows = []
    for run in runs:
        error = float(np.max(np.abs(finals[id(run)] - Y0)))
        rows.append({"run": run, "family": run.family, "label": run.label, "setting": run.setting(),
                     "error": error, "seconds": seconds[id(run)]})
    return rows


# --- long-time behaviour ----------------------------------------------------------------
def growth(t, error, T):
    """Max error in each tenth of [0, T]; the exponent p of a fit max ~ t^p over the tenths."""
    edges = np.linspace(0.0, T, 11)
    maxima, centres = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        inside = (t > a) & (t <= b)
        if inside.any():
            maxima.append(float(np.max(error[inside])))
            centres.append(0.5 * (a + b))
    maxima, centres = np.array(maxima), np.array(centres)
    positive = maxima > 0
    if positive.sum() < 3:
        return maxima, 0.0
    p = float(np.polyfit(np.log(centres[positive]), np.log(maxima[positive]), 1)[0])
    return maxima, p


def verdict(error_max, maxima, p):
    if error_max < ROUND_OFF:
        return "round-off"
    ratio = maxima[-1] / maxima[0] if maxima[0] > 0 else math.inf
    if p < 0.3 and ratio < 3.0:
        return "bounded"
    if p < 0.75:
        return f"grows ~t^{p:.1f}"
    return f"drifts ~t^{p:.1f}"


def long_runs():
    runs = [ElimfastRun(gauss(3), H_LONG), ElimfastRun(hbvm(12, 3), H_LONG),
            ElimfastRun(ehbvm(12, 3), H_LONG, ("angular_momentum",)),
            ElimfastRun(ehbvm(12, 3), H_LONG, CONSERVE), ElimfastRun(ghbvm(12, 3), H_LONG, CONSERVE),
            ElimfastRun(ehbvm(12, 4), H_LONG, CONSERVE)]
    if scipy_integrate is not None:
        runs += [Dop853Run(1e-3, 1e-6, " (default tol)"), Dop853Run(1e-12, 1e-12, " (tight)")]
    if rebound is not None:
        runs += [Ias15Run(1e-9, " (default)")]
    if heyoka is not None:
        runs += [HeyokaRun(1e-10, ""), HeyokaRun(None, " (default)")]
    return runs


def long_time(repeats):
    runs = long_runs()
    seconds, finals = median_times(runs, T_LONG, repeats)
    exact = exact_state(T_LONG)
    H0, L0, Ax0, Ay0 = (v[0] for v in invariants(Y0[None, :]))
    rows = []
    for run in runs:
        t, Y, work = run.trajectory(T_LONG)
        H, L, Ax, Ay = invariants(Y)
        errors = {"H": np.abs(H - H0), "L": np.abs(L - L0),
                  "A": np.maximum(np.abs(Ax - Ax0), np.abs(Ay - Ay0))}
        row = {"run": run, "label": run.label, "setting": run.setting(), "work": work,
               "seconds": seconds[id(run)], "y_error": float(np.max(np.abs(finals[id(run)] - exact)))}
        for name, error in errors.items():
            maxima, p = growth(t, error, T_LONG)
            row[name] = (float(error.max()), p, verdict(float(error.max()), maxima, p))
        rows.append(row)
    return rows


# --- output ---------------------------------------------------------------------------
MARKERS = {"GAUSS": "o", "HBVM": "s", "EHBVM": "D", "scipy DOP853": "v", "REBOUND IAS15": "^",
           "heyoka Taylor": "P"}


def plot(rows, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8.5, 6.0))
    series = {}
    for row in rows:
        series.setdefault(row["label"], []).append(row)
    for label, points in series.items():
        # In the order of the settings (h or tolerance decreasing), not of the noisy times.
        family = points[0]["family"]
        marker = MARKERS.get(family) or MARKERS[label.split("(")[0]]
        style = "-" if family == "elimfast" else "--"
        errors = [max(r["error"], 1e-17) for r in points]
        ax.loglog([r["seconds"] for r in points], errors, style, marker=marker, label=label, markersize=5)
    ax.set_xlabel("wall time (s), median")
    ax.set_ylabel("max-norm error of y at t = 20 pi (10 periods)")
    ax.set_title(f"Kepler e = {ECCENTRICITY}: work-precision (elimfast solid, peers dashed)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def fastest_to(rows, target):
    """Per family (elimfast counts as one), the fastest run with error <= target."""
    best = {}
    for row in rows:
        if row["error"] <= target:
            family = row["family"]
            if family not in best or row["seconds"] < best[family]["seconds"]:
                best[family] = row
    return best


def markdown(short_rows, long_rows, heyoka_builds, args, load):
    versions = [f"elimfast {elimfast.__version__}", f"numpy {np.__version__}"]
    for name, module in (("scipy", "scipy"), ("rebound", "rebound"), ("heyoka", "heyoka")):
        if sys.modules.get(module) is not None:
            versions.append(f"{name} {sys.modules[module].__version__}")
    missing = [name for name, module in (("scipy", scipy_integrate), ("REBOUND", rebound), ("heyoka", heyoka))
               if module is None]
    lines = [
        "# elimfast beside other integrators: Kepler e = 0.6",
        "",
        f"Generated by `bench/peers.py` (`{' '.join(sys.argv[1:]) or 'defaults'}`): {', '.join(versions)}; "
        f"{os.cpu_count()} cores shared with other work, {platform.machine()}, load average "
        f"{load[0]:.2f} at the start and {load[1]:.2f} at the end. Wall times are medians of "
        f"{args.repeats} (work-precision) and {args.long_repeats} (long runs) runs, every integrator timed "
        "in the same process with the configurations interleaved.",
        "",
    ]
    if missing:
        lines += [f"**Skipped (could not be imported): {', '.join(missing)}.**", ""]
    lines += [
        "![work-precision](peers_work_precision.png)",
        "",
        "## Work-precision over 10 periods",
        "",
        "Error: max-norm of y(20 pi) - y0 (the exact solution). elimfast at h = pi/N, "
        f"N = {', '.join(map(str, STEP_DIVISORS))}; EHBVM imposes L and lrl_y.",
        "",
        "| integrator | setting | error | wall time |",
        "|---|---|---|---|",
    ]
    for row in short_rows:
        lines.append(f"| {row['label']} | {row['setting']} | {row['error']:.2e} | {row['seconds'] * 1e3:.2f} ms |")
    if heyoka_builds:
        build = ", ".join(f"{b * 1e3:.0f} ms" for b in heyoka_builds)
        lines += ["", f"heyoka's one-time LLVM build per tolerance (not in the times above): {build}."]
    lines += ["", "Fastest run of each kind reaching a given error:", "",
              "| error <= | " + " | ".join(("elimfast", "scipy DOP853", "REBOUND IAS15", "heyoka Taylor")) + " |",
              "|---|---|---|---|---|"]
    for target in (1e-4, 1e-7, 1e-10, 1e-12):
        best = fastest_to(short_rows, target)
        cells = []
        for family in ("elimfast", "scipy DOP853", "REBOUND IAS15", "heyoka Taylor"):
            row = best.get(family)
            if row:
                cells.append(f"{row['seconds'] * 1e3:.2f} ms ({row['label']}, {row['setting']})")
            else:
                ran = any(r["family"] == family for r in short_rows)
                cells.append("not reached" if ran else "skipped")
        lines.append(f"| {target:.0e} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Long-time behaviour on [0, 1000]",
        "",
        f"Max over the run of abs(I(t) - I(0)) for H, L and the LRL vector A (max of its two components), "
        "taken at every step of each integrator; then whether it drifts: the exponent p of a fit "
        "max-in-each-tenth ~ t^p ('round-off': below "
        f"{ROUND_OFF:.0e} throughout; 'bounded': p < 0.3 and the last tenth within 3x of the first). "
        "'y error at 1000': max-norm error against the exact solution (Kepler's equation).",
        "",
        "| integrator | setting | work | wall time | H error | L error | A error | y error at 1000 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in long_rows:
        cells = [f"{row[name][0]:.1e} ({row[name][2]})" for name in ("H", "L", "A")]
        lines.append(f"| {row['label']} | {row['setting']} | {row['work']} | {row['seconds'] * 1e3:.1f} ms | "
                     + " | ".join(cells) + f" | {row['y_error']:.1e} |")
    lines += ["", "## Summary", "", summary(short_rows, long_rows), ""]
    return "\n".join(lines)


def summary(short_rows, long_rows):
    """The reading of the tables above, every number filled in from this run."""
    def best(target, family):
        return fastest_to(short_rows, target).get(family)

    def kept(row):
        return all(row[name][2] in ("round-off", "bounded") for name in ("H", "L", "A"))

    def described(row):
        return f"{row['label']} ({row['setting']}, {row['seconds'] * 1e3:.0f} ms)"

    parts = []
    target = 1e-10
    mine = best(target, "elimfast")
    if mine is not None:
        faster, slower = [], []
        for family in ("scipy DOP853", "REBOUND IAS15", "heyoka Taylor"):
            row = best(target, family)
            if row is None:
                if any(r["family"] == family for r in short_rows):
                    slower.append(f"{family} (which never gets there in this range)")
            elif row["seconds"] < mine["seconds"]:
                faster.append(f"{family} ({row['seconds'] * 1e3:.2f} ms, {mine['seconds'] / row['seconds']:.0f}x less)")
            else:
                slower.append(f"{family} ({row['seconds'] * 1e3:.1f} ms)")
        sentence = (f"Accuracy per unit of work: to reach an error of {target:.0e} over 10 periods elimfast's fastest "
                    f"run ({mine['label']}, {mine['setting']}) takes {mine['seconds'] * 1e3:.1f} ms")
        if faster:
            sentence += f"; {', '.join(faster)} do it for less, so there elimfast loses"
        if slower:
            sentence += f"; it does better than {', '.join(slower)}"
        if faster:
            sentence += (". The high-order adaptive peers (IAS15 is of order 15, heyoka's Taylor series of order "
                         "13 to 20 here) adapt their steps to the perihelion passages and take far fewer steps than "
                         "a fixed-step implicit method of order 4 to 8, whose every step costs several fixed-point "
                         "iterations of k gradient evaluations each (k = s for GAUSS, 12 for HBVM and EHBVM here)")
        if slower:
            sentence += "; scipy pays mostly for its Python right-hand side"
        parts.append(sentence + ".")
    elim_kept = [r for r in long_rows if r["run"].family == "elimfast" and kept(r)]
    peers_kept = [r for r in long_rows if r["run"].family != "elimfast" and kept(r)]
    peers_drift = [r for r in long_rows if r["run"].family != "elimfast" and not kept(r)]
    elim_drift = [r for r in long_rows if r["run"].family == "elimfast" and not kept(r)]
    if elim_kept:
        y_errors = [r["y_error"] for r in elim_kept]
        parts.append(
            "Long runs: at the coarse step h = 0.1 (about 63 steps per period), "
            f"{', '.join(described(r) for r in elim_kept)} keep H, the angular momentum and the LRL vector at "
            "round-off or bounded, with no drift, by construction, while their error in y at t = 1000 is "
            f"{min(y_errors):.0e} to {max(y_errors):.0e}"
            + (f"; the elimfast methods that do not impose the LRL vector "
               f"({', '.join(r['label'] for r in elim_drift)}) let it drift, as the paper says" if elim_drift else "")
            + ".")
    if peers_drift:
        parts.append(f"The adaptive peers short of machine precision drift in at least one invariant: "
                     f"{', '.join(described(r) for r in peers_drift)}.")
    if peers_kept:
        parts.append(
            f"But at their default, near-machine-precision tolerances {', '.join(described(r) for r in peers_kept)} "
            "also keep every invariant at round-off over this interval, with a far smaller error in y, and "
            + ("faster. " if max(r["seconds"] for r in peers_kept) < min(r["seconds"] for r in elim_kept) else "")
            + "On a smooth two-body problem, then, elimfast's advantage is the guarantee (the invariants hold "
            "whatever the step, and any invariant the user names can be imposed) and the parallel ensemble "
            "kernel, not speed: where plain accuracy is affordable, the compiled high-order adaptive peers "
            "are the better tool.")
    return " ".join(parts)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per configuration (work-precision)")
    parser.add_argument("--long-repeats", type=int, default=3, help="timed runs per configuration on [0, 1000]")
    parser.add_argument("--out-dir", type=Path, default=ROOT / "bench" / "results")
    args = parser.parse_args()
    warnings.filterwarnings("ignore", message=".*predictor corrector loops in IAS15.*")
    load_start = os.getloadavg()[0]
    short_rows = work_precision(args.repeats)
    for row in short_rows:
        print(f"{row['label']:32s} {row['setting']:28s} error {row['error']:.2e}  {row['seconds'] * 1e3:9.2f} ms")
    long_rows = long_time(args.long_repeats)
    for row in long_rows:
        print(f"{row['label']:32s} {row['setting']:28s} {row['seconds'] * 1e3:9.1f} ms  "
              + "  ".join(f"{n} {row[n][0]:.1e} {row[n][2]}" for n in ("H", "L", "A")) + f"  y {row['y_error']:.1e}")
    heyoka_builds = [build for _, build in HeyokaRun._cache.values()]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    plot(short_rows, args.out_dir / "peers_work_precision.png")
    text = markdown(short_rows, long_rows, heyoka_builds, args, (load_start, os.getloadavg()[0]))
    (args.out_dir / "peers.md").write_text(text)
    print(f"wrote {args.out_dir / 'peers.md'} and {args.out_dir / 'peers_work_precision.png'}")


if __name__ == "__main__":
    main()
