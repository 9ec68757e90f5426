"""Kernel speed: the step engine's solvers side by side, and against the NumPy reference.

The README's run (issue 8): EHBVM(12,3) imposing angular momentum and lrl_y on Kepler
e = 0.6, h = 0.1, t in [0, 1000] (10^4 steps), whole runs of elimfast.integrate:

- simplified Newton with the predictor and its secant acceleration (the default, docs/solver.md);
- the same without the acceleration (solver.accelerate: false);
- the fixed point with the predictor;
- the fixed point without it (elimfast's iteration before the step engine).

The runs alternate (A B C A B C ...) in one process so that the machine's drift hits
them alike; medians, the ratio of the medians and the median of the per-round ratios
are printed. The NumPy reference (tests/reference.py, fixed point) and the kernel with
Numba's JIT disabled run a prefix of the same run; they are compared per step.

Usage: .venv/bin/python bench/kernel.py [--repeats 9] [--markdown bench/results/kernel.md]
"""
import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import numba  # noqa: E402

import elimfast  # noqa: E402
from elimfast.integrate import SolverSettings  # noqa: E402
from elimfast.methods import ehbvm  # noqa: E402
from elimfast.problems import kepler  # noqa: E402

CONSERVE = ("angular_momentum", "lrl_y")
H, T_END = 0.1, 1000.0
VARIANTS = {
    "newton (default)": {"solver": "newton"},
    "newton, no secant acceleration": {"solver": SolverSettings(accelerate=False)},
    "fixed point + predictor": {"solver": "fixed_point"},
    "fixed point, no predictor": {"solver": "fixed_point", "predictor": False},
}


def cpu_model() -> str:
    """The processor's name (/proc/cpuinfo on Linux): the ratios of this bench move with it
    (the fixed point took 1.61x Newton's time on one machine, 1.47x on an AMD EPYC)."""
    try:
        with open("/proc/cpuinfo") as info:
            for line in info:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def one_run(options):
    problem, method = kepler(0.6), ehbvm(12, 3)
    start = time.perf_counter()
    result = elimfast.integrate(problem, method, H, t_end=T_END, conserve=CONSERVE, store_every=1000, **options)
    return time.perf_counter() - start, result


def interleaved(repeats):
    times = {name: [] for name in VARIANTS}
    results = {}
    for options in VARIANTS.values():
        one_run(options)   # load the cache / warm up
    for _ in range(repeats):
        for name, options in VARIANTS.items():
            seconds, results[name] = one_run(options)
            times[name].append(seconds)
    return times, results


def reference_run(n_steps):
    import reference
    grad_L = lambda y: reference.kepler_grad_L(y)[:, [0, 2]]  # noqa: E731
    y = reference.kepler_y0(0.6)
    total = 0
    start = time.perf_counter()
    for _ in range(n_steps):
        y, _, iterations = reference.elim_step(reference.kepler_grad_H, grad_L, y, H, 12, 12, 3)
        total += iterations
    return {"seconds": time.perf_counter() - start, "steps": n_steps, "iterations": total}


def no_jit_run(n_steps):
    """The same kernel code run by the Python interpreter (NUMBA_DISABLE_JIT=1), in a subprocess."""
    code = f"""
import json, time, elimfast
from elimfast.methods import ehbvm
from elimfast.problems import kepler
p, m = kepler(0.6), ehbvm(12, 3)
start = time.perf_counter()
r = elimfast.integrate(p, m, {H}, n_steps={n_steps}, conserve={CONSERVE!r})
print(json.dumps({{"seconds": time.perf_counter() - start, "steps": r.n_steps,
                   "iterations": int(r.iterations.sum())}}))
"""
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--reference-steps", type=int, default=100)
    parser.add_argument("--nojit-steps", type=int, default=10)
    parser.add_argument("--markdown", type=Path, help="also write the tables to this markdown file")
    args = parser.parse_args()

    times, results = interleaved(args.repeats)
    base = "newton (default)"
    lines = [f"EHBVM(12,3), Kepler e = 0.6, imposing {', '.join(CONSERVE)}, h = {H}, t in [0, {T_END:g}] "
             f"({results[base].n_steps} steps); {args.repeats} interleaved rounds; machine: {os.cpu_count()} cores, "
             f"{platform.machine()} ({cpu_model()}), Numba {numba.__version__}", "",
             "| solver | whole run, median (min-max) | iterations/step (max) | ns/iteration | split steps | "
             "time / newton: ratio of medians | median of per-round ratios |",
             "|---|---|---|---|---|---|---|"]
    newton_median = statistics.median(times[base])
    for name in VARIANTS:
        result = results[name]
        median = statistics.median(times[name])
        per_round = statistics.median(t / n for t, n in zip(times[name], times[base]))
        iterations = result.iterations
        lines.append(f"| {name} | {median:.4f} s ({min(times[name]):.4f}-{max(times[name]):.4f}) | "
                     f"{iterations.mean():.2f} ({iterations.max()}) | {median / iterations.sum() * 1e9:.0f} | "
                     f"{result.split_steps} | {median / newton_median:.2f} | {per_round:.2f} |")
    errors = results[base].invariant_errors()
    lines += ["", "Invariant errors of the default run: " + ", ".join(f"{k} {v:.1e}" for k, v in errors.items()), ""]

    fast = results["fixed point, no predictor"]
    fast_per_iteration = statistics.median(times["fixed point, no predictor"]) / fast.iterations.sum()
    lines += ["| implementation (fixed point, no predictor) | us/step | ns/iteration | iterations/step | "
              "slower than the kernel |", "|---|---|---|---|---|"]
    for name, entry in (("NumPy reference (tests/reference.py)", reference_run(args.reference_steps)),
                        ("elimfast kernel, JIT disabled", no_jit_run(args.nojit_steps))):
        per_iteration = entry["seconds"] / entry["iterations"]
        lines.append(f"| {name} | {entry['seconds'] / entry['steps'] * 1e6:.0f} | {per_iteration * 1e9:.0f} | "
                     f"{entry['iterations'] / entry['steps']:.2f} | {per_iteration / fast_per_iteration:.0f}x |")
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        args.markdown.write_text("# Kernel speed\n\nGenerated by `bench/kernel.py`.\n\n" + text + "\n")


if __name__ == "__main__":
    main()
