"""Kernel speed: EHBVM(12,3) imposing angular momentum and lrl_y on Kepler e = 0.6,
h = 0.1, t in [0, 1000] (issue 2), for both right-hand-side forms, side by side with
the plain NumPy reference (tests/reference.py) and with Numba's JIT disabled.

Usage: .venv/bin/python bench/kernel.py [--repeats 7]

All timings are medians of repeated runs in one process (the machine is shared).
The reference and the JIT-disabled kernel are far too slow for 10^4 steps: they run
a prefix of the same run and are compared per step and per fixed-point iteration.
"""
import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import elimfast  # noqa: E402
from elimfast.methods import ehbvm  # noqa: E402
from elimfast.problems import kepler  # noqa: E402

CONSERVE = ("angular_momentum", "lrl_y")
H, T_END = 0.1, 1000.0


def median_time(function, repeats):
    times = []
    result = None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def kernel_run(rhs, repeats):
    problem, method = kepler(0.6), ehbvm(12, 3)
    run = lambda: elimfast.integrate(problem, method, H, t_end=T_END, conserve=CONSERVE, rhs=rhs,  # noqa: E731
                                     store_every=100)
    run()  # compile / load from cache
    seconds, result = median_time(run, repeats)
    return {"seconds": seconds, "steps": result.n_steps, "iterations": int(result.iterations.sum())}


def reference_run(rhs, n_steps, repeats):
    import reference
    grad_L = lambda y: reference.kepler_grad_L(y)[:, [0, 2]]  # noqa: E731

    def run():
        y = reference.kepler_y0(0.6)
        total = 0
        for _ in range(n_steps):
            y, _, iterations = reference.elim_step(reference.kepler_grad_H, grad_L, y, H, 12, 12, 3, rhs=rhs)
            total += iterations
        return total
    seconds, iterations = median_time(run, repeats)
    return {"seconds": seconds, "steps": n_steps, "iterations": iterations}


def no_jit_run(rhs, n_steps):
    """The same kernel code run by the Python interpreter (NUMBA_DISABLE_JIT=1), in a subprocess."""
    code = f"""
import json, time, elimfast
from elimfast.methods import ehbvm
from elimfast.problems import kepler
p, m = kepler(0.6), ehbvm(12, 3)
start = time.perf_counter()
r = elimfast.integrate(p, m, {H}, n_steps={n_steps}, conserve={CONSERVE!r}, rhs={rhs!r})
print(json.dumps({{"seconds": time.perf_counter() - start, "steps": r.n_steps,
                   "iterations": int(r.iterations.sum())}}))
"""
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def per(entry):
    return entry["seconds"] / entry["steps"] * 1e6, entry["seconds"] / entry["iterations"] * 1e9


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--reference-steps", type=int, default=100)
    parser.add_argument("--nojit-steps", type=int, default=20)
    args = parser.parse_args()
    print(f"EHBVM(12,3), Kepler e = 0.6, conserve {', '.join(CONSERVE)}, h = {H}, t in [0, {T_END:g}]")
    print(f"{'rhs':8s} {'implementation':24s} {'whole run':>11s} {'us/step':>9s} {'ns/iter':>9s} {'iter/step':>9s} {'slower':>8s}")
    for rhs in ("literal", "stable"):
        fast = kernel_run(rhs, args.repeats)
        rows = [("elimfast (Numba)", fast),
                ("NumPy reference", reference_run(rhs, args.reference_steps, max(1, args.repeats // 3))),
                ("elimfast, JIT disabled", no_jit_run(rhs, args.nojit_steps))]
        fast_per_iter = per(fast)[1]
        for name, entry in rows:
            us_step, ns_iter = per(entry)
            whole = entry["seconds"] if entry is fast else us_step * fast["steps"] * 1e-6
            note = "" if entry is fast else " (extrapolated)"
            print(f"{rhs:8s} {name:24s} {whole:10.3f}s {us_step:9.2f} {ns_iter:9.0f} "
                  f"{entry['iterations'] / entry['steps']:9.2f} {ns_iter / fast_per_iter:7.0f}x{note}")


if __name__ == "__main__":
    main()
