"""Sweeps on Dask against the local pool (issue 13); kept from the sweep bench it grew in.

Usage: .venv/bin/python bench/sweep_dask.py --dask [--repeats 3]   (the 1-vs-2-worker pool bench is bench/sweep.py)

Two measurements, alternating 1 and 2 workers so that load on the shared machine hits
both alike; medians reported:
- the grid itself: elimfast.sweep.run_sweep in this process (kernels already loaded);
- the whole command: a fresh `elimfast sweep` process, start-up included (warm cache).

With --dask (issue 13; needs `pip install 'elimfast[dask]'`), instead: the local pool of 2
processes against a 2-worker dask.distributed LocalCluster (one thread each), alternating,
medians side by side, written to bench/results/dask.md:
- a 100-run sweep (Kepler, 10 eccentricities x 10 step sizes, EHBVM(12,3) imposing L),
  stored in an HDF5 file as `elimfast sweep -o` does; the cluster's time with the cluster
  already running (a long-lived cluster) and with its start included (--scheduler local);
- a Henon-Heiles ensemble of --orbits orbits (1e5), the local kernel on 2 threads against
  blocks on the cluster.
"""
import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

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


KEPLER_GRID = {
    "description": "100 Kepler runs: 10 eccentricities x 10 step sizes (bench/sweep_dask.py --dask)",
    "base": {"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}},
             "method": {"name": "ehbvm", "k": 12, "s": 3}, "conserve": ["angular_momentum"],
             "integration": {"h": "pi/30", "t_end": "40*pi"}, "output": {"every": 10}},
    "grid": [{"name": "e", "key": "problem.parameters.eccentricity",
              "values": [round(0.1 + 0.06 * i, 2) for i in range(10)]},
             {"name": "h", "key": "integration.h", "values": [f"2*pi/{100 + 10 * i}" for i in range(10)]}],
    "error": {"exact": "initial"}, "order_axis": "h",
}


def henon_heiles_ensemble(orbits: int, t_end: float) -> dict:
    return {"description": f"{orbits} Henon-Heiles orbits (bench/sweep_dask.py --dask)",
            "base": {"problem": {"builtin": "henon_heiles"}, "method": {"name": "hbvm", "k": 6, "s": 3},
                     "integration": {"h": 0.1, "t_end": t_end}},
            "ensemble": {"n": orbits, "seed": 1, "spread": 0.01}}


def dask_comparison(args):
    import distributed

    from elimfast.sweep import run_to_file
    folder = Path(tempfile.mkdtemp(prefix="elimfast-bench-dask-"))
    grid_file = folder / "grid.yaml"
    grid_file.write_text(yaml.safe_dump(KEPLER_GRID, sort_keys=False))
    ensemble_file = folder / "ensemble.yaml"
    ensemble_file.write_text(yaml.safe_dump(henon_heiles_ensemble(args.orbits, args.t_end), sort_keys=False))
    out = folder / "out.h5"

    def timed(function):
        start = time.perf_counter()
        result = function()
        return time.perf_counter() - start, result

    rows = []
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) \
            as cluster, distributed.Client(cluster) as client:
        for name, sweep_file, repeats, is_grid in (
                ("100-run sweep", grid_file, args.repeats, True),
                (f"{args.orbits:,}-orbit ensemble", ensemble_file, args.ensemble_repeats, False)):
            # (a flag, not the name: "100,000-orbit ensemble" starts with "100" too)
            local = "local pool, 2 processes" if is_grid else "local kernel, 2 threads"
            modes = {local: lambda f=sweep_file: run_to_file(f, out, workers=2, overwrite=True),
                     "LocalCluster, 2 workers (running)":
                         lambda f=sweep_file: run_to_file(f, out, client=client, overwrite=True)}
            if is_grid:
                modes["--scheduler local (start included)"] = \
                    lambda f=sweep_file: run_to_file(f, out, scheduler="local", workers=2, overwrite=True)
            for function in modes.values():
                function()   # warm: kernels, problems, the workers
            times = {mode: [] for mode in modes}
            tables = {}
            for _ in range(repeats):
                for mode, function in modes.items():
                    seconds, outcome = timed(function)
                    times[mode].append(seconds)
                    tables[mode] = outcome.table()
                    print(f"{name}: {mode}: {seconds:.2f} s", file=sys.stderr)
            same = all(table == tables[local] for table in tables.values())
            pool = statistics.median(times[local])
            for mode, values in times.items():
                median = statistics.median(values)
                rows.append(f"| {name} | {mode} | {median:.2f} s | {min(values):.2f}-{max(values):.2f} s | "
                            f"{median / pool:.2f} | {'yes' if same else 'NO'} |")
    lines = [
        "# Sweeps and ensembles: local pool vs a 2-worker Dask LocalCluster",
        "",
        f"Generated by `bench/sweep_dask.py --dask` (`{' '.join(sys.argv[1:])}`), dask.distributed "
        f"{distributed.__version__}; machine: {os.cpu_count()} cores shared with other work, "
        f"{platform.machine()}; load average {os.getloadavg()[0]:.2f} at the end.",
        "",
        f"- 100-run sweep: {KEPLER_GRID['description']}, t in [0, 40 pi], every run stored in an HDF5 file "
        "(the client streams them in as they arrive).",
        f"- Ensemble: HBVM(6,3), h = 0.1, t in [0, {args.t_end:g}], {args.orbits:,} orbits near E = 1/8; the local "
        "kernel on 2 threads, the cluster in blocks (elimfast.distributed.block_bounds) of 1 thread each.",
        "- Modes alternate within each repeat; medians (and ranges). Ratio: median / the local pool's median.",
        "",
        "| workload | mode | median | range | ratio to local | same table |",
        "|---|---|---|---|---|---|",
        *rows,
        "",
        "Target (issue 13): the cluster within 1.2x of the local pool's time.",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    target = ROOT / "bench" / "results" / "dask.md"
    target.write_text(text)
    print(f"wrote {target.relative_to(ROOT)}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--dask", action="store_true", help="compare the local pool with a Dask LocalCluster")
    parser.add_argument("--orbits", type=int, default=100_000, help="--dask: orbits of the ensemble")
    parser.add_argument("--t-end", type=float, default=20.0, help="--dask: the ensemble's t_end")
    parser.add_argument("--ensemble-repeats", type=int, default=3, help="--dask: repeats of the ensemble")
    args = parser.parse_args()
    if args.dask:
        dask_comparison(args)
        return
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
