"""End-to-end benchmark of ``elimfast run configs/kepler.yaml`` (issue 4).

Measures, as medians over repeated runs, side by side with their targets:

1. warm cache: wall time of ``elimfast run configs/kepler.yaml`` in a fresh process
   (the exact command, run in a fresh temporary directory, so it writes
   out/kepler.h5 there). Target: < 1.5 s.
2. empty cache: the same with empty Numba and elimfast caches (NUMBA_CACHE_DIR and
   ELIMFAST_CACHE_DIR pointing at fresh temporary directories, so every kernel is
   compiled). Target: < 20 s.
3. overhead of chunking and writing: in one process, the streaming driver writing the
   HDF5 file (elimfast.streaming.run_to_file) against one bare kernel call for the
   whole run (Integration.advance(n_steps)), same config. Target: the driver's own
   time (creating the file, appends, flushes, closing: everything but its kernel calls)
   < 10 % of its kernel time. Also shown: the comparison with the bare call on the wall
   and CPU clocks (noisier: two separate runs on a shared machine), and the startup
   floor (``python -c "import elimfast"``).

    .venv/bin/python bench/end_to_end.py                 # 7 warm runs, 3 cold runs
    .venv/bin/python bench/end_to_end.py --cold 1 --warm 5

The machine is shared: medians, and min/max beside them to show the spread.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "kepler.yaml"
ELIMFAST = Path(sys.executable).with_name("elimfast")
TARGETS = {"warm": 1.5, "cold": 20.0, "overhead": 0.10}


def timed_process(argv, env=None, cwd=None) -> float:
    start = time.perf_counter()
    done = subprocess.run(argv, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        sys.exit(f"{' '.join(map(str, argv))} failed ({done.returncode}): {done.stderr.strip()}")
    return elapsed


def run_config(env=None) -> float:
    """``elimfast run configs/kepler.yaml`` in a fresh directory (its output path is relative)."""
    with tempfile.TemporaryDirectory(prefix="elimfast-bench-") as work:
        (Path(work) / "configs").mkdir()
        (Path(work) / "configs" / "kepler.yaml").write_text(CONFIG.read_text())
        return timed_process([str(ELIMFAST), "run", "configs/kepler.yaml"], env=env, cwd=work)


def cold_run() -> float:
    with tempfile.TemporaryDirectory(prefix="elimfast-cold-") as caches:
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(caches) / "numba"),
                   ELIMFAST_CACHE_DIR=str(Path(caches) / "elimfast"))
        return run_config(env)


def overhead(repeats: int) -> dict:
    """Driver (chunks + HDF5) vs one bare kernel call, same process, same config.

    Timed with the process's CPU clock as well as the wall clock: on a shared machine
    the CPU time is the steadier measure of the work done.
    """
    from elimfast import streaming
    from elimfast.config import load_run
    from elimfast.integrate import Integration

    spec = load_run(CONFIG)
    Integration.from_spec(spec).advance(10)          # compile / load the kernel outside the timings
    out = {key: [] for key in ("bare", "driver", "bare_cpu", "driver_cpu", "kernel", "write", "open")}
    with tempfile.TemporaryDirectory(prefix="elimfast-overhead-") as work:
        for i in range(repeats):
            run = Integration.from_spec(spec)
            wall, cpu = time.perf_counter(), time.process_time()
            run.advance(spec.n_steps)
            out["bare"].append(time.perf_counter() - wall)
            out["bare_cpu"].append(time.process_time() - cpu)

            run = Integration.from_spec(spec)
            wall, cpu = time.perf_counter(), time.process_time()
            outcome = streaming.run_to_file(run, Path(work) / f"k{i}.h5", config_text="bench\n", t_end=spec.t_end,
                                            handle_signals=False)
            out["driver"].append(time.perf_counter() - wall)
            out["driver_cpu"].append(time.process_time() - cpu)
            out["kernel"].append(outcome.session_kernel_s)
            out["write"].append(outcome.session_write_s)
            out["open"].append(outcome.session_open_s)
    out["chunks"], out["n_steps"] = outcome.chunks, spec.n_steps
    return out


def row(name, values, target=None, unit="s", scale=1.0):
    if not values:
        return
    med = statistics.median(values) * scale
    low, high = min(values) * scale, max(values) * scale
    verdict = "" if target is None else ("ok" if med < target * scale else "MISSED")
    target_text = "" if target is None else f"< {target * scale:g} {unit}"
    print(f"{name:<50} {med:>9.3f} {unit:<2} {low:>9.3f} {high:>9.3f}   {target_text:<10} {verdict}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--warm", type=int, default=7, help="fresh-process runs with a warm cache")
    parser.add_argument("--cold", type=int, default=3, help="fresh-process runs with empty caches (~10-20 s each)")
    parser.add_argument("--overhead", type=int, default=15, help="in-process driver vs bare kernel repetitions")
    args = parser.parse_args()

    run_config()   # make sure the caches are warm
    startup = [timed_process([sys.executable, "-c", "import elimfast"]) for _ in range(args.warm)]
    warm = [run_config() for _ in range(args.warm)]
    cold = [cold_run() for _ in range(args.cold)]
    o = overhead(args.overhead)

    print(f"elimfast run configs/kepler.yaml: EHBVM(12,3), {o['n_steps']} steps, a sample every 10; "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")
    print(f"{'':<50} {'median':>12} {'min':>9} {'max':>9}   target")
    row(f"fresh process, warm cache ({args.warm} runs)", warm, TARGETS["warm"])
    row(f"fresh process, empty caches ({args.cold} runs)", cold, TARGETS["cold"])
    row("  floor: python -c 'import elimfast'", startup)
    own = [d - k for d, k in zip(o["driver"], o["kernel"])]
    row(f"in process, bare kernel, one call ({args.overhead} runs)", o["bare"])
    row("in process, the driver's kernel calls", o["kernel"])
    row(f"in process, driver + HDF5 ({o['chunks']} chunk(s)), total", o["driver"])
    row("  its own time: everything but the kernel calls", own, unit="ms", scale=1000.0)
    row("    creating the file", o["open"], unit="ms", scale=1000.0)
    row("    appends, flushes, final close", o["write"], unit="ms", scale=1000.0)
    # Per run: the driver's own time over its kernel time (both from the same run, so a
    # busy machine slows them alike); then the noisier comparison of two separate runs.
    row("overhead: own time / kernel time, same run", [x / k for x, k in zip(own, o["kernel"])],
        TARGETS["overhead"], unit="%", scale=100.0)
    row("overhead: driver total / bare kernel - 1, wall", [d / b - 1 for d, b in zip(o["driver"], o["bare"])],
        unit="%", scale=100.0)
    row("overhead: driver total / bare kernel - 1, CPU",
        [d / b - 1 for d, b in zip(o["driver_cpu"], o["bare_cpu"])], unit="%", scale=100.0)

if __name__ == "__main__":
    main()
