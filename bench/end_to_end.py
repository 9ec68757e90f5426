"""End-to-end start-up benchmark of ``elimfast run`` (issues 4 and 12).

Fresh processes, side by side: each repeat runs every command below once, in turn, so
that load on the shared machine hits them alike; medians with min and max. Each
process is timed on the wall clock and by its CPU time (user + system, from
getrusage): on a shared 2-core machine the CPU time is the steadier of the two.

1. warm: ``elimfast run`` of configs/kepler.yaml cut to 100 steps (``--set
   integration.t_end=10``), with the caches warm. Targets (issue 12): < 0.5 s, and
   <= 1.3x the bare imports ``python -c "import numba, h5py"``.
2. the same for the whole 10,000-step configs/kepler.yaml (what ``make run`` runs).
3. ``elimfast --help``, ``--version``, ``problems``, ``methods`` (they import no Numba).
4. cold start (``--cold N`` rounds, 1-3 min each), with NUMBA_CACHE_DIR and
   ELIMFAST_CACHE_DIR pointing at fresh folders:
   - after installation: ``elimfast cache warm`` (what ``make`` runs after installing;
     timed apart), then the first ``elimfast run configs/kepler.yaml``. Target: < 10 s.
   - first compile: ``elimfast run configs/kepler.yaml`` on the empty caches, no warm-up.
5. in one process, the streaming driver's own time (chunks, HDF5) against its kernel
   time, for configs/kepler.yaml. Target: < 10 %.

    .venv/bin/python bench/end_to_end.py                  # 9 warm repeats, 1 cold round
    .venv/bin/python bench/end_to_end.py --warm 15 --cold 2 --out bench/results/end_to_end.md
"""
from __future__ import annotations

import argparse
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "kepler.yaml"
ELIMFAST = Path(sys.executable).with_name("elimfast")
TARGETS = {"warm": 0.5, "ratio": 1.3, "after_install": 10.0, "overhead": 0.10}
SHORT = ["--set", "integration.t_end=10"]     # 100 steps of h = 0.1


def timed_process(argv, env=None, cwd=None, expect_stderr=None) -> tuple[float, float, str]:
    """(wall s, CPU s of the child, its stderr)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    done = subprocess.run(argv, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        sys.exit(f"{' '.join(map(str, argv))} failed ({done.returncode}): {done.stderr.strip()}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, done.stderr


def run_config(extra=(), env=None) -> tuple[float, float, str]:
    """``elimfast run configs/kepler.yaml`` in a fresh directory (its output path is relative)."""
    with tempfile.TemporaryDirectory(prefix="elimfast-bench-") as work:
        (Path(work) / "configs").mkdir()
        (Path(work) / "configs" / "kepler.yaml").write_text(CONFIG.read_text())
        return timed_process([str(ELIMFAST), "run", "configs/kepler.yaml", *extra], env=env, cwd=work)


COMMANDS = {
    "bare imports: python -c 'import numba, h5py'": lambda: timed_process([sys.executable, "-c", "import numba, h5py"]),
    "elimfast run, 100 steps": lambda: run_config(SHORT),
    "elimfast run configs/kepler.yaml (10,000 steps)": lambda: run_config(),
    "python -c 'import elimfast'": lambda: timed_process([sys.executable, "-c", "import elimfast"]),
    "elimfast --help": lambda: timed_process([str(ELIMFAST), "--help"]),
    "elimfast --version": lambda: timed_process([str(ELIMFAST), "--version"]),
    "elimfast problems": lambda: timed_process([str(ELIMFAST), "problems"]),
    "elimfast methods": lambda: timed_process([str(ELIMFAST), "methods"]),
}


def compile_bytecode() -> None:
    """Compile the package's bytecode, as make does after installing: with PYTHONDONTWRITEBYTECODE
    set (as on this machine), a module edited since the install is otherwise compiled again in
    every process, which measured 40 ms of a 0.55 s run after a few edits."""
    import compileall
    for folder in ("elimfast", "cli"):
        compileall.compile_dir(ROOT / folder, quiet=1)


def cold_round() -> dict:
    """One round of the two cold starts, each on fresh caches."""
    out = {}
    with tempfile.TemporaryDirectory(prefix="elimfast-cold-") as caches:
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(caches) / "numba"),
                   ELIMFAST_CACHE_DIR=str(Path(caches) / "elimfast"))
        out["warm-up"] = timed_process([str(ELIMFAST), "cache", "warm", "--quiet"], env=env)
        out["after installation"] = run_config(env=env)
    with tempfile.TemporaryDirectory(prefix="elimfast-cold-") as caches:
        env = dict(os.environ, NUMBA_CACHE_DIR=str(Path(caches) / "numba"),
                   ELIMFAST_CACHE_DIR=str(Path(caches) / "elimfast"))
        out["first compile"] = run_config(env=env)
    return out


def overhead(repeats: int) -> dict:
    """Driver (chunks + HDF5) vs its kernel calls, same process, same config."""
    from elimfast import streaming
    from elimfast.config import load_run
    from elimfast.integrate import Integration

    spec = load_run(CONFIG)
    Integration.from_spec(spec).advance(10)          # load the kernel outside the timings
    own, kernel = [], []
    with tempfile.TemporaryDirectory(prefix="elimfast-overhead-") as work:
        for i in range(repeats):
            run = Integration.from_spec(spec)
            start = time.perf_counter()
            outcome = streaming.run_to_file(run, Path(work) / f"k{i}.h5", config_text="bench\n", t_end=spec.t_end,
                                            handle_signals=False)
            total = time.perf_counter() - start
            own.append(total - outcome.session_kernel_s)
            kernel.append(outcome.session_kernel_s)
    return {"own": own, "kernel": kernel, "ratio": [o / k for o, k in zip(own, kernel)]}


def stats(values) -> tuple[float, float, float]:
    return statistics.median(values), min(values), max(values)


def fmt(values, unit="s", scale=1.0, digits=3) -> str:
    med, low, high = (v * scale for v in stats(values))
    return f"{med:.{digits}f} {unit} ({low:.{digits}f}-{high:.{digits}f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--warm", type=int, default=9, help="repeats of the warm commands, interleaved")
    parser.add_argument("--cold", type=int, default=1, help="rounds of the two cold starts (1-3 min each)")
    parser.add_argument("--overhead", type=int, default=9, help="in-process driver repetitions")
    parser.add_argument("--out", type=Path, help="also write the results as markdown to this file")
    args = parser.parse_args()

    load_before = os.getloadavg()[0]
    compile_bytecode()
    run_config(SHORT)   # make sure the caches are warm
    warm = {name: {"wall": [], "cpu": []} for name in COMMANDS}
    for _ in range(args.warm):
        for name, command in COMMANDS.items():
            wall, cpu, _stderr = command()
            warm[name]["wall"].append(wall)
            warm[name]["cpu"].append(cpu)
    bare = warm["bare imports: python -c 'import numba, h5py'"]
    short = warm["elimfast run, 100 steps"]
    ratio_wall = [s / b for s, b in zip(short["wall"], bare["wall"])]
    ratio_cpu = [s / b for s, b in zip(short["cpu"], bare["cpu"])]

    cold = {key: {"wall": [], "cpu": [], "announced": []} for key in ("warm-up", "after installation", "first compile")}
    for _ in range(args.cold):
        for key, (wall, cpu, stderr) in cold_round().items():
            cold[key]["wall"].append(wall)
            cold[key]["cpu"].append(cpu)
            cold[key]["announced"].append("compiling Numba kernels" in stderr)
    o = overhead(args.overhead) if args.overhead else None
    load_after = os.getloadavg()[0]

    lines = ["# End-to-end start-up: `elimfast run` in a fresh process", "",
             f"Generated by `bench/end_to_end.py --warm {args.warm} --cold {args.cold}`. "
             f"{os.cpu_count()} cores shared with other work ({platform.machine()}, Python "
             f"{platform.python_version()}); load average {load_before:.2f} before, {load_after:.2f} after. "
             "Each repeat runs every command once, in turn; medians (min-max). CPU: user + system time "
             "of the process, steadier than the wall clock on a shared machine.", "",
             f"## Warm caches ({args.warm} interleaved repeats)", "",
             "| command | wall | CPU |", "|---|---|---|"]
    for name, times in warm.items():
        lines.append(f"| {name} | {fmt(times['wall'])} | {fmt(times['cpu'])} |")
    med_short, med_ratio = statistics.median(short["wall"]), statistics.median(ratio_wall)
    lines += ["", "| target (issue 12, item 2) | measured | met |", "|---|---|---|",
              f"| warm `elimfast run` of 100 steps < {TARGETS['warm']} s wall | {med_short:.3f} s | "
              f"{'yes' if med_short < TARGETS['warm'] else 'no'} |",
              f"| same, <= {TARGETS['ratio']}x the bare imports (median of per-repeat ratios) | wall {med_ratio:.2f}x "
              f"({min(ratio_wall):.2f}-{max(ratio_wall):.2f}), CPU {statistics.median(ratio_cpu):.2f}x "
              f"({min(ratio_cpu):.2f}-{max(ratio_cpu):.2f}) | {'yes' if med_ratio <= TARGETS['ratio'] else 'no'} |"]
    if args.cold:
        lines += ["", f"## Empty caches ({args.cold} round(s); fresh NUMBA_CACHE_DIR and ELIMFAST_CACHE_DIR)", "",
                  "| step | wall | CPU | printed 'compiling Numba kernels' |", "|---|---|---|---|"]
        names = {"warm-up": "`elimfast cache warm` (the install step of `make`)",
                 "after installation": "then the first `elimfast run configs/kepler.yaml`",
                 "first compile": "`elimfast run configs/kepler.yaml` without the warm-up (true first compile)"}
        for key, times in cold.items():
            said = "n/a" if key == "warm-up" else ", ".join("yes" if a else "no" for a in times["announced"])
            lines.append(f"| {names[key]} | {fmt(times['wall'], digits=1)} | {fmt(times['cpu'], digits=1)} | {said} |")
        after = statistics.median(cold["after installation"]["wall"])
        lines += ["", f"Target (item 3): the first run after installation < {TARGETS['after_install']:g} s: "
                      f"{after:.2f} s, {'met' if after < TARGETS['after_install'] else 'missed'}."]
    if o is not None:
        lines += ["", f"## Driver overhead ({args.overhead} runs in one process, configs/kepler.yaml)", "",
                  f"- kernel calls: {fmt(o['kernel'])}; the driver's own time (file, appends, flushes, close): "
                  f"{fmt(o['own'], unit='ms', scale=1000.0, digits=1)}",
                  f"- own time / kernel time: {fmt(o['ratio'], unit='%', scale=100.0, digits=1)} "
                  f"(target < {TARGETS['overhead'] * 100:g} %)"]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
