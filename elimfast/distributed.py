"""Sweeps and ensembles on a Dask cluster (``dask.distributed``); docs/dask.md.

    from dask.distributed import Client
    import elimfast.sweep
    with Client("tcp://scheduler:8786") as client:
        elimfast.sweep.run("configs/paper/table1.yaml", "out/table1.h5", client=client)

A grid sweep's runs are Dask tasks (``sweep._execute``, the function the local process
pool runs, so the numbers are the same bit for bit); an ensemble is split into blocks of
trajectories, each run in the parallel Numba kernel on a worker (``ensemble.EnsembleRun.rows``:
each trajectory is bit for bit the same whatever the block or thread count). Workers
only compute and return arrays; this process is the only writer of the HDF5 file and
stores each run or block as it arrives (``distributed.as_completed``, results released
once stored, so memory stays bounded; an ensemble's blocks are submitted a window at a
time, ``ensemble_blocks_on``).

Faults: a task whose worker dies is run again elsewhere by the scheduler (up to its
``distributed.scheduler.allowed-failures``, then the run is reported failed with
KilledWorker); a task that raises an unexpected exception is retried ``RETRIES``
times. A run that fails numerically is not an exception (``_execute`` returns its
status), so it is reported as in a local sweep and never retried.

Compilation: a worker builds a problem from its config as a local run does, so
generated code and Numba's cache are found by content hash in the worker's cache
directory (``ELIMFAST_CACHE_DIR``; shared or not). Before the runs, ``_warm`` runs on
every worker (``Client.run``): it loads the kernels and each distinct problem of the
sweep, so that no two tasks of one worker compile the same thing. A ``python:`` problem
file is shipped with the tasks; a worker that cannot see the file at its path writes
the shipped copy into its cache directory (``shipped/<hash>/``) and loads that.

dask is imported only here, and this module only when a client or scheduler is given.
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import math
import os
import re
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from .sweep import REFERENCE_LABEL, RunOutcome, SweepError, SweepSpec, _execute, default_workers, sweep_jobs

INSTALL_HINT = "pip install 'elimfast[dask]'"
CONNECT_TIMEOUT_S = 10            # a scheduler that does not answer within this is reported unreachable
WORKER_WAIT_S = 60                # how long to wait for a cluster's first worker
RETRIES = 2                       # retries of a task that raised an unexpected exception (not a numerical failure)
BLOCKS_PER_THREAD = 4             # ensemble blocks per worker thread: load balance against per-task overhead
MIN_BLOCK = 100                   # trajectories per block, at least (a block's overhead is ~10 ms; an orbit ~1 ms+)
MAX_BLOCK = 50_000                # and at most (a block's arrays in flight stay a few MB)
BLOCKS_IN_FLIGHT_PER_WORKER = 2   # ensemble blocks submitted and not yet stored, per worker process
MAX_WARM_PROBLEMS = 8             # distinct problems warmed on each worker before the runs
_ADDRESS = re.compile(r"^(tcp|tls|ucx|inproc|ws|wss)://[^\s/]+(:\d+)?/?$|^[A-Za-z0-9_.\-\[\]:]+:\d+$")
_KERNEL_LOCK = threading.Lock()   # one parallel kernel at a time per worker process (Numba's workqueue
                                  # threading layer aborts on concurrent launches from two threads)


def _distributed():
    try:
        import distributed
    except ImportError:
        raise SweepError(f"--scheduler needs dask.distributed, which is not installed: {INSTALL_HINT}") from None
    return distributed


def check_scheduler(scheduler: str, workers: int | None = None) -> None:
    """SweepError unless ``scheduler`` is 'local' or an address (tcp://host:port) and dask is installed."""
    if not isinstance(scheduler, str) or not (scheduler == "local" or _ADDRESS.match(scheduler)):
        raise SweepError(f"--scheduler {scheduler!r}: give the address of a Dask scheduler (tcp://host:8786) or "
                         "'local' for a cluster on this machine")
    if workers is not None and scheduler != "local":
        raise SweepError(f"--workers applies to the local pool and --scheduler local; the cluster at {scheduler} "
                         "has the workers it was started with (dask worker --nworkers N)")
    _distributed()


@contextlib.contextmanager
def connect(scheduler: str, workers: int | None = None, on_message: Callable[[str], None] | None = None):
    """A Client of the cluster at ``scheduler``, or of a new LocalCluster ('local': ``workers``
    processes, default one per core, one thread each); closed (and the cluster stopped) after.

    Not the process's default client (set_as_default=False): elimfast submits to it by name,
    and a default client sets dask's global scheduler option, which a client that failed to
    connect restored only when garbage-collected, possibly after another client's close: the
    process was left asking for a distributed scheduler with none active, and xarray's
    to_netcdf then raised "Requested dask.distributed scheduler but no Client active"."""
    check_scheduler(scheduler, workers)
    distributed = _distributed()
    say = on_message or (lambda line: None)
    with contextlib.ExitStack() as stack:
        if scheduler == "local":
            n = default_workers() if workers is None else int(workers)
            cluster = stack.enter_context(distributed.LocalCluster(
                n_workers=n, threads_per_worker=1, processes=True, dashboard_address=":0"))
            client = stack.enter_context(distributed.Client(cluster, set_as_default=False))
            say(f"dask: a local cluster of {n} worker process(es) at {cluster.scheduler_address}")
        else:
            try:
                client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
            except (OSError, TimeoutError, ValueError, TypeError, ImportError) as error:
                # TypeError: a tls:// address without dask's TLS settings (no ssl_context), a ucx://
                # one without ucx-py; both were 'internal error' with exit 1
                text = " ".join(str(error).split())[:160] or type(error).__name__
                raise SweepError(f"--scheduler {scheduler}: cannot connect ({text}); start one with `dask scheduler` "
                                 "and `dask worker ADDRESS`, or check the address") from None
            stack.enter_context(client)
            say(f"dask: connected to {scheduler}, {len(client.scheduler_info().get('workers', {}))} worker(s)")
        yield client


def _wait_for_workers(client) -> dict:
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
    except (TimeoutError, OSError):
        raise SweepError(f"the Dask cluster at {client.scheduler.address} has no workers after {WORKER_WAIT_S} s; "
                         "start some (dask worker ADDRESS)") from None
    return client.scheduler_info().get("workers", {})


# --- shipping python: problem files, warming the workers -------------------------------------
def _python_files(configs: list[dict], source: str) -> dict[str, str]:
    """{path as the config writes it: text} of the python: problem files the configs name, read
    here (relative paths are relative to the sweep file's folder, as sweep._execute reads them)."""
    shipped = {}
    for config in configs:
        problem = config.get("problem") if isinstance(config, dict) else None
        name = problem.get("python") if isinstance(problem, dict) else None
        if isinstance(name, str) and name not in shipped:
            path = Path(source).parent / name
            with contextlib.suppress(OSError, UnicodeDecodeError):
                shipped[name] = path.read_text(encoding="utf-8")   # unreadable: the worker reports it as locally
    return shipped


def _client_allows_python() -> bool:
    """config.python_allowed() here, on the client: its worker functions take it as an argument
    (a worker's environment does not carry the client's --allow-python)."""
    from .config import python_allowed
    return python_allowed()


def _localise(config: dict, source: str, shipped: dict[str, str]) -> dict:
    """On a worker: a config whose python: file is not visible here (or differs) points at the
    shipped copy, written into this machine's cache under its content hash."""
    problem = config.get("problem") if isinstance(config, dict) else None
    name = problem.get("python") if isinstance(problem, dict) else None
    if not isinstance(name, str) or name not in shipped:
        return config
    text = shipped[name]
    with contextlib.suppress(OSError, UnicodeDecodeError):
        if (Path(source).parent / name).read_text(encoding="utf-8") == text:
            return config
    from . import cache
    digest = hashlib.sha256(text.encode("utf-8")).hexdigest()
    copy_path = cache.cache_dir() / "shipped" / digest / Path(name).name
    if not copy_path.is_file():
        cache.write_atomic(copy_path, text)
    config = copy.deepcopy(config)
    config["problem"]["python"] = str(copy_path)
    return config


def _task(label: str, coordinates: dict, config: dict, source: str, store_arrays: bool,
          shipped: dict[str, str], allow_python: bool = False) -> RunOutcome:
    """A sweep run on a worker: sweep._execute, after making a shipped python: file visible. The
    Result comes back without its problem (the client puts its own back, ``_client_problem``):
    the problem's Numba functions, unpickled in the client, were compiled there afresh, once per
    worker and function, in every sweep (1.3 s of Table 1's 2.7 s with 2 workers, and a
    'compiling Numba kernels (once ...)' line each time). ``allow_python``: the client's
    config.python_allowed(), which a worker's environment does not carry."""
    from .config import allowing_python
    with allowing_python(allow_python):
        outcome = _execute(label, coordinates, _localise(config, source, shipped), source, store_arrays)
    if outcome.result is not None:
        outcome.result.problem = None
    return outcome


def _client_problem(config: dict, source: str, problems: dict):
    """The problem of a run's config, built here (from the caches: nothing compiles) once per
    distinct problem section."""
    key = repr(config.get("problem"))
    if key not in problems:
        from .config import load_run_from_dict
        problems[key] = load_run_from_dict(copy.deepcopy(config), source=source,
                                           base_dir=Path(source).parent).problem
    return problems[key]


def _warm(configs: list[dict], source: str, shipped: dict[str, str], allow_python: bool = False) -> dict:
    """On every worker, before the runs: load the kernels and build each problem once (generated
    code and Numba's cache by content hash), and take one step of each; report what was found."""
    import elimfast

    from .config import allowing_python, load_run_from_dict

    start = time.perf_counter()
    for config in configs:
        config = copy.deepcopy(config)
        integration = config.get("integration")
        if isinstance(integration, dict) and "h" in integration:   # fixed steps: two of them (an adaptive
            integration.pop("t_end", None)                          # run is only loaded: its length is unknown)
            integration["n_steps"] = 2
            _task("warm", {}, config, source, True, shipped, allow_python)   # a failure is the run's to report
        else:
            with contextlib.suppress(Exception), allowing_python(allow_python):
                load_run_from_dict(_localise(config, source, shipped), source=source, base_dir=Path(source).parent)
    return {"version": elimfast.__version__, "seconds": time.perf_counter() - start, "pid": os.getpid()}


def warm_workers(client, configs: list[dict], source: str, shipped: dict[str, str],
                 on_message: Callable[[str], None] | None = None) -> None:
    """Run ``_warm`` on every worker (concurrently); SweepError if a worker cannot import elimfast
    or runs another version of it."""
    import elimfast
    workers = _wait_for_workers(client)
    distinct, seen = [], set()
    for config in configs:
        key = repr(config.get("problem")) + repr(config.get("method")) if isinstance(config, dict) else ""
        if key not in seen and len(distinct) < MAX_WARM_PROBLEMS:
            seen.add(key)
            distinct.append(config)
    try:
        reports = client.run(_warm, distinct, source, shipped, _client_allows_python())
    except ImportError as error:   # the workers' environment lacks elimfast (or a dependency)
        raise SweepError(f"the Dask workers cannot import elimfast ({error}); install elimfast in the "
                         "workers' environment") from None
    other = {address: report["version"] for address, report in reports.items()
             if report["version"] != elimfast.__version__}
    if other:
        address, version = next(iter(other.items()))
        raise SweepError(f"the Dask worker {address} runs elimfast {version}, this process {elimfast.__version__}; "
                         "install the same version on every worker")
    if on_message is not None and reports:
        slowest = max(report["seconds"] for report in reports.values())
        on_message(f"dask: {len(workers)} worker(s) ready (kernels and problems loaded in {slowest:.1f} s at most)")


# --- a grid sweep ------------------------------------------------------------------------------
def run_sweep_on(client, spec: SweepSpec, store_arrays: bool = True,
                 on_done: Callable[[RunOutcome, int, int], None] | None = None, skip=frozenset(),
                 on_message: Callable[[str], None] | None = None) -> tuple[list[RunOutcome], RunOutcome | None]:
    """sweep.run_sweep on the Dask cluster of ``client``: the same outcomes, in grid order, and
    the reference outcome; ``on_done(outcome, done, total)`` here as each run arrives."""
    distributed = _distributed()
    jobs = sweep_jobs(spec, skip)
    total = len(jobs)
    results: dict[str, RunOutcome] = {}
    if total:
        shipped = _python_files([config for _, _, config in jobs], spec.source)
        warm_workers(client, [config for _, _, config in jobs], spec.source, shipped, on_message)
        futures, problems, allow = {}, {}, _client_allows_python()
        for index, (label, coordinates, config) in enumerate(jobs):
            future = client.submit(_task, label, coordinates, config, spec.source, store_arrays, shipped, allow,
                                   key=f"elimfast-run-{index}-{os.getpid()}-{time.monotonic_ns()}", pure=False,
                                   retries=RETRIES)
            futures[future] = (label, coordinates, config)
        try:
            for done, future in enumerate(distributed.as_completed(futures, loop=client.loop), start=1):
                label, coordinates, config = futures[future]
                try:
                    outcome = future.result()
                except Exception as error:   # noqa: BLE001 -- the task's failure, not this process's
                    outcome = RunOutcome(label=label, coordinates=coordinates, status=_task_failure(error))
                if outcome.result is not None and outcome.result.problem is None:
                    outcome.result.problem = _client_problem(config, spec.source, problems)
                future.release()             # stored next: the worker may drop it
                results[label] = outcome
                if on_done:
                    on_done(outcome, done, total)
        except BaseException:
            client.cancel(list(futures))   # Ctrl-C, SIGTERM, a write that failed: drop the rest
            raise
    reference = results.pop(REFERENCE_LABEL, None) if spec.reference is not None else None
    return [results[run.label] for run in spec.runs if run.label in results], reference


def _task_failure(error: BaseException) -> str:
    """A run's status when its task did not return: its worker died too often, or it raised
    (after RETRIES retries) something sweep._execute does not turn into a status."""
    text = " ".join(str(error).split())[:200]
    if type(error).__name__ == "KilledWorker":
        return ("failed: the Dask workers running it died repeatedly (KilledWorker; out of memory, or killed); "
                "run it alone with elimfast run to see why")
    return f"failed: on a Dask worker: {type(error).__name__}: {text}"


# --- an ensemble -------------------------------------------------------------------------------
def block_bounds(n_trajectories: int, threads: int, ranges=None) -> list[tuple[int, int]]:
    """[start, stop) of each block: about BLOCKS_PER_THREAD blocks per worker thread (so that a
    slow block or a lost worker costs little), each of MIN_BLOCK..MAX_BLOCK trajectories.
    ``ranges``: the [start, stop) ranges to cover (default: all; a resumed file's missing
    trajectories), each cut into blocks of that size."""
    ranges = [(0, n_trajectories)] if ranges is None else ranges
    todo = sum(stop - start for start, stop in ranges)
    blocks = max(1, BLOCKS_PER_THREAD * max(1, threads))
    size = min(MAX_BLOCK, max(MIN_BLOCK, math.ceil(todo / blocks)))
    return [(first, min(first + size, stop)) for start, stop in ranges for first in range(start, stop, size)]


def _ensemble_block(config: dict, source: str, states: np.ndarray, shipped: dict[str, str],
                    allow_python: bool = False) -> dict:
    """On a worker: one block of an ensemble in the parallel kernel, on the worker's threads (one
    block at a time per process): (its rows, as ensemble.EnsembleRun.rows gives them, threads used)."""
    import numba

    from .config import load_run_from_dict
    from .ensemble import EnsembleRun, check_states

    spec = load_run_from_dict(_localise(copy.deepcopy(config), source, shipped), source=source,
                              base_dir=Path(source).parent, allow_python=allow_python)
    threads = 1
    with contextlib.suppress(Exception):
        from distributed import get_worker
        threads = get_worker().state.nthreads
    threads = max(1, min(threads, numba.config.NUMBA_NUM_THREADS))
    states = check_states(spec.problem, states)
    with _KERNEL_LOCK:
        rows = EnsembleRun.from_spec(spec, states[0], n_threads=threads).rows(states)
    return rows, threads


def ensemble_blocks_on(client, spec: SweepSpec, states: np.ndarray, ranges,
                       on_message: Callable[[str], None] | None = None) -> Iterator[tuple[int, int, dict, int]]:
    """The rows of ``states`` in ``ranges`` ([start, stop) pairs), run in blocks on the Dask
    cluster of ``client``: yields (start, stop, rows, threads) as blocks arrive (rows as
    ensemble.EnsembleRun.rows gives them; threads: the kernel threads of the worker).

    At most ``ensemble_window`` blocks are submitted and not yet taken back from here: the
    next block is submitted only when the caller asks for the next one, after storing the
    last, so the states shipped, the results waiting on the workers and the block in hand
    stay bounded whatever the ensemble's size. Close the iterator (contextlib.closing) to
    cancel the blocks still out."""
    distributed = _distributed()
    if not any(stop > start for start, stop in ranges):
        return
    shipped, allow = _python_files([spec.base], spec.source), _client_allows_python()
    warm_workers(client, [spec.base], spec.source, shipped, on_message)
    workers = client.scheduler_info().get("workers", {})
    bounds = block_bounds(states.shape[0], sum(worker.get("nthreads", 1) for worker in workers.values()), ranges)
    window = ensemble_window(len(workers))
    if on_message is not None:
        on_message(f"dask: {sum(stop - start for start, stop in bounds):,} trajectories in {len(bounds)} block(s) "
                   f"of up to {max(stop - start for start, stop in bounds):,}, at most {window} at a time")
    waiting = iter(bounds)
    futures = {}

    def submit_next():
        bound = next(waiting, None)
        if bound is None:
            return None
        start, stop = bound
        future = client.submit(_ensemble_block, spec.base, spec.source, states[start:stop], shipped, allow,
                               key=f"elimfast-block-{start}-{os.getpid()}-{time.monotonic_ns()}", pure=False,
                               retries=RETRIES)
        futures[future] = bound
        return future

    arriving = distributed.as_completed([future for future in (submit_next() for _ in range(window))
                                         if future is not None], loop=client.loop)
    try:
        for future in arriving:
            start, stop = futures.pop(future)
            try:
                rows, threads = future.result()
            except Exception as error:   # noqa: BLE001
                raise SweepError(f"{spec.source}: ensemble: trajectories {start}-{stop - 1} could not be run on "
                                 f"the cluster ({_task_failure(error)[len('failed: '):]})") from None
            future.release()
            yield start, stop, rows, threads
            following = submit_next()   # only now: the block yielded is stored (or dropped)
            if following is not None:
                arriving.add(following)
    finally:   # done, or Ctrl-C, SIGTERM, a write that failed, the caller closing: drop the rest
        if futures:
            client.cancel(list(futures))


def ensemble_window(workers: int) -> int:
    """Blocks of an ensemble submitted and not yet stored, at most: BLOCKS_IN_FLIGHT_PER_WORKER
    per worker process (each runs one block at a time: one running, the next queued)."""
    return max(2, BLOCKS_IN_FLIGHT_PER_WORKER * max(1, workers))


def run_ensemble_on(client, spec: SweepSpec, on_start: Callable[[int], None] | None = None,
                    on_message: Callable[[str], None] | None = None):
    """sweep.run_ensemble_sweep on the Dask cluster of ``client``: (RunSpec, Y0, EnsembleResult),
    the result equal, array for array, to the local kernel's, assembled in memory (to store
    an ensemble block by block instead, give sweep.run_to_file a path)."""
    from .ensemble import EnsembleRows
    from .sweep import block_line, ensemble_run, ensemble_states

    run, states = ensemble_states(spec)
    ensemble = ensemble_run(spec, run, states)   # validated here, before any task
    n = states.shape[0]
    if on_start is not None:
        on_start(n)
    assembly, threads, done = EnsembleRows(n), 1, 0
    with contextlib.closing(ensemble_blocks_on(client, spec, states, [(0, n)], on_message)) as blocks:
        for start, stop, rows, block_threads in blocks:
            assembly.put(start, stop, rows)
            threads, done = max(threads, block_threads), done + stop - start
            if on_message is not None:
                on_message(block_line(rows, start, stop, done, n))
    return run, states, ensemble.result(states, assembly.rows, n_threads=threads)


__all__ = ["block_bounds", "check_scheduler", "connect", "ensemble_blocks_on", "ensemble_window", "run_ensemble_on",
           "run_sweep_on", "warm_workers"]
