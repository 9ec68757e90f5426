"""The paper's Table 1 sweep (30 runs) with 1 worker and with 2 workers (issue 5: at most 0.6x).

Usage: .venv/bin/python bench/sweep.py [--repeats 5]

Two measurements, alternating 1 and 2 workers so that load on the shared machine hits
both alike; medians reported:
- the grid itself: elimfast.sweep.run_sweep in this process (kernels already loaded);
- the whole command: a fresh `elimfast sweep` process, start-up included (warm cache).
"""
import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ELIMFAST = Path(sys.executable).with_name("elimfast")
SWEEP = ROOT / "configs/paper/table1.yaml"


def command(workers: int) -> float:
    start = time.perf_counter()
    subprocess.run([str(ELIMFAST), "sweep", str(SWEEP), "--workers", str(workers), "-q"], check=True,
                   capture_output=True)
    return time.perf_counter() - start


def grid(workers: int) -> float:
    from elimfast.sweep import load_sweep, run_sweep
    spec = load_sweep(SWEEP)
    start = time.perf_counter()
    run_sweep(spec, workers=workers)
    return time.perf_counter() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    grid(1)
    command(1)  # warm the caches
    for name, measure in (("grid (in process)", grid), ("whole command", command)):
        times = {1: [], 2: []}
        for _ in range(args.repeats):
            for workers in (1, 2):
                times[workers].append(measure(workers))
        one, two = statistics.median(times[1]), statistics.median(times[2])
        print(f"Table 1 sweep, {name:18s}: 1 worker {one:.2f} s, 2 workers {two:.2f} s, ratio {two / one:.2f} "
              f"(target <= 0.6); medians of {args.repeats}")


if __name__ == "__main__":
    main()
