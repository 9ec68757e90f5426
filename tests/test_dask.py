"""Sweeps and ensembles on Dask (elimfast.distributed, issue 13): the same files, bit for bit,
as the local process pool; a worker killed mid-sweep; --resume; a cluster started by hand."""
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

distributed = pytest.importorskip("distributed")

from elimfast import distributed as on_dask  # noqa: E402
from elimfast import sweep as sweeps  # noqa: E402
from elimfast.sweep import SweepError  # noqa: E402
from elimfast_cli.main import cli  # noqa: E402
from runfiles import assert_same_files, contents, stopped_after_blocks  # noqa: E402

ELIMFAST = Path(sys.executable).with_name("elimfast")
DASK = Path(sys.executable).with_name("dask")
BASE = {
    "problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}},
    "method": {"name": "ehbvm", "k": 12, "s": 3},
    "conserve": ["angular_momentum"],
    "integration": {"h": "pi/30", "t_end": "2*pi"},
}


def write_sweep(tmp_path, data, name="sweep.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def grid_sweep(tmp_path, steps=("2*pi/40", "2*pi/80", "2*pi/160"), t_end="2*pi", name="sweep.yaml"):
    return write_sweep(tmp_path, {
        "base": {**BASE, "integration": {"h": "pi/30", "t_end": t_end}},
        "grid": [{"name": "method", "values": [
                     {"label": "GAUSS3", "set": {"method": {"name": "gauss", "s": 3}, "conserve": []}},
                     {"label": "EHBVM", "set": {}}]},
                 {"name": "h", "key": "integration.h", "values": list(steps)}],
        "error": {"exact": "initial"}, "order_axis": "h"}, name)


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as cluster, distributed.Client(cluster) as client:
        yield client


def test_a_sweep_on_a_local_cluster_writes_the_file_the_local_pool_writes(tmp_path, client):
    path = grid_sweep(tmp_path)
    pool = sweeps.run_to_file(path, tmp_path / "pool.h5", workers=2)
    dask = sweeps.run(path, tmp_path / "dask.h5", client=client)
    assert_same_files(tmp_path / "pool.h5", tmp_path / "dask.h5")
    assert pool.table() == dask.table()
    assert [o.status for o in dask.outcomes] == ["complete"] * 6


def ensemble_sweep(tmp_path):
    return write_sweep(tmp_path, {"base": {"problem": {"builtin": "henon_heiles"},
                                           "method": {"name": "hbvm", "k": 6, "s": 3},
                                           "integration": {"h": 0.1, "t_end": 20}},
                                  "ensemble": {"n": 200, "seed": 3, "spread": 0.01}})


def test_an_ensemble_in_blocks_on_a_local_cluster_equals_the_local_kernel(tmp_path, client, monkeypatch):
    monkeypatch.setattr(on_dask, "MIN_BLOCK", 16)   # 8 blocks of 25 (2 worker threads): blocks meet
    path = ensemble_sweep(tmp_path)
    assert len(on_dask.block_bounds(200, 2)) == 8
    local = sweeps.run_to_file(path, tmp_path / "pool.h5", workers=2)
    dask = sweeps.run_to_file(path, tmp_path / "dask.h5", client=client)
    assert_same_files(tmp_path / "pool.h5", tmp_path / "dask.h5")
    for name in ("y_final", "t_final", "iterations", "max_multiplier", "status", "steps_done", "split_steps"):
        np.testing.assert_array_equal(getattr(local.ensemble, name), getattr(dask.ensemble, name))
    assert local.table() == dask.table()


def test_an_ensemble_streamed_from_a_local_cluster_equals_the_in_memory_results(tmp_path, client, monkeypatch):
    monkeypatch.setattr(on_dask, "MIN_BLOCK", 16)
    path = ensemble_sweep(tmp_path)
    one_call = sweeps.run_to_file(path, workers=2).ensemble                # no file: one kernel call here
    gathered = sweeps.run_to_file(path, client=client).ensemble            # no file: the blocks in memory
    streamed = sweeps.run_to_file(path, tmp_path / "dask.h5", client=client).ensemble   # read from the file
    for name in ("y0", "y_final", "t_final", "iterations", "max_multiplier", "status", "steps_done", "split_steps",
                 "diagnostics"):
        np.testing.assert_array_equal(getattr(one_call, name), getattr(gathered, name), err_msg=name)
        np.testing.assert_array_equal(getattr(one_call, name), getattr(streamed, name), err_msg=name)
    for name, values in one_call.invariant_errors.items():
        np.testing.assert_array_equal(values, streamed.invariant_errors[name], err_msg=name)


def test_an_ensembles_blocks_in_flight_never_exceed_the_window(tmp_path, client, monkeypatch):
    """Blocks submitted and not yet stored (the states shipped, results waiting on the workers,
    the block in hand) stay within ensemble_window, whatever the number of blocks."""
    from elimfast.io.sweepfile import SweepWriter

    monkeypatch.setattr(on_dask, "MIN_BLOCK", 16)   # 8 blocks of 25 (2 worker threads)
    window = on_dask.ensemble_window(2)
    assert window < 8
    submitted, stored, most = [0], [0], [0]
    submit, store = client.submit, SweepWriter.add_ensemble_rows

    def counted_submit(function, *args, **options):
        if function is on_dask._ensemble_block:
            submitted[0] += 1
            most[0] = max(most[0], submitted[0] - stored[0])
        return submit(function, *args, **options)

    def counted_store(writer, *block):
        store(writer, *block)
        stored[0] += 1

    monkeypatch.setattr(client, "submit", counted_submit)
    monkeypatch.setattr(SweepWriter, "add_ensemble_rows", counted_store)
    sweeps.run_to_file(ensemble_sweep(tmp_path), tmp_path / "dask.h5", client=client)
    assert submitted[0] == stored[0] == 8
    assert most[0] == window


def test_resume_on_a_local_cluster_completes_a_stopped_ensemble_file(tmp_path, client, monkeypatch):
    monkeypatch.setattr(on_dask, "MIN_BLOCK", 16)   # 8 blocks of 25
    path = ensemble_sweep(tmp_path)
    sweeps.run_to_file(path, tmp_path / "full.h5", workers=2)
    half = stopped_after_blocks(path, tmp_path / "half.h5", 3, monkeypatch, client=client)
    messages = []
    sweeps.run_to_file(path, half, resume=True, client=client, on_message=messages.append)
    assert f"resume: 75 of 200 trajectories are stored in {half}; running the other 125" in messages
    assert any(m.startswith("dask: 125 trajectories in ") for m in messages), messages
    assert_same_files(tmp_path / "full.h5", half)


def test_block_sizes_keep_the_overhead_small_and_cover_every_trajectory():
    for n, threads in ((1, 1), (99, 2), (10**5, 2), (10**7, 64), (12345, 7)):
        bounds = on_dask.block_bounds(n, threads)
        assert bounds[0][0] == 0 and bounds[-1][1] == n
        assert all(a[1] == b[0] for a, b in zip(bounds, bounds[1:]))
        sizes = [stop - start for start, stop in bounds]
        assert max(sizes) <= on_dask.MAX_BLOCK
        assert len(bounds) == 1 or min(sizes[:-1]) >= on_dask.MIN_BLOCK
    # A resumed file's missing ranges: covered exactly, no block across a gap.
    ranges = [(0, 50), (300, 1000), (4000, 4001)]
    bounds = on_dask.block_bounds(5000, 2, ranges)
    assert sorted({i for start, stop in bounds for i in range(start, stop)}) == \
        [i for start, stop in ranges for i in range(start, stop)]
    assert all(any(a <= start < stop <= b for a, b in ranges) for start, stop in bounds)


def test_a_worker_killed_mid_sweep_does_not_lose_the_sweep(tmp_path, client):
    # Eight runs of ~0.3-0.6 s each on two workers: when the first arrives, both workers are busy.
    path = grid_sweep(tmp_path, steps=[f"2*pi/{n}" for n in (200, 240, 280, 320)], t_end="80*pi")
    pids = client.run(os.getpid)
    killed = []

    def kill_one(outcome, done, total):
        if not killed:
            busy = {address: keys for address, keys in client.processing().items() if keys}
            address = next(iter(busy))         # a worker that is running a run now
            os.kill(pids[address], signal.SIGKILL)
            killed.append((pids[address], busy[address]))

    outcome = sweeps.run_to_file(path, tmp_path / "dask.h5", client=client, on_done=kill_one)
    assert killed and killed[0][1]
    assert killed[0][0] not in client.run(os.getpid).values()
    assert [o.status for o in outcome.outcomes] == ["complete"] * 8
    with h5py.File(tmp_path / "dask.h5", "r") as f:
        assert len(f["runs"]) == 8
        assert all(f["runs"][name].attrs["status"] == "complete" for name in f["runs"])
    client.wait_for_workers(2, timeout=60)   # the nanny restarted it, for the tests after this one


def half_written(tmp_path, sweep_path, runs_kept: int) -> Path:
    """A sweep file as a sweep killed (kill -9) after ``runs_kept`` runs leaves it."""
    out = tmp_path / "half.h5"
    process = subprocess.Popen([str(ELIMFAST), "sweep", str(sweep_path), "-o", str(out), "--workers", "1"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    for line in process.stderr:
        if line.startswith(f"[{runs_kept}/"):
            process.send_signal(signal.SIGKILL)
            break
    process.wait(timeout=60)
    assert process.returncode == -signal.SIGKILL
    return out


@pytest.mark.parametrize("where", ["pool", "dask"])
def test_resume_completes_a_half_written_sweep_file(tmp_path, client, where):
    path = grid_sweep(tmp_path, steps=[f"2*pi/{n}" for n in (100, 140, 180)], t_end="10*pi")
    full = sweeps.run_to_file(path, tmp_path / "full.h5", workers=1)
    out = half_written(tmp_path, path, runs_kept=2)
    messages = []
    resumed = sweeps.run_to_file(path, out, resume=True, client=client if where == "dask" else None,
                                 workers=None if where == "dask" else 2, on_message=messages.append)
    assert any(m.startswith("resume: ") and " of 6 runs are complete" in m for m in messages), messages
    done_before = int(next(m for m in messages if m.startswith("resume: ")).split()[1])
    assert 2 <= done_before < 6
    assert resumed.table() == full.table()
    assert_same_files(tmp_path / "full.h5", out)


def test_resume_reruns_a_run_whose_data_were_not_all_stored(tmp_path):
    path = grid_sweep(tmp_path, steps=["2*pi/40"])
    out = tmp_path / "out.h5"
    sweeps.run_to_file(path, out, workers=1)
    with h5py.File(out, "a") as f:
        del f["runs"]["GAUSS3|2*pi|40"].attrs["stored"]   # as a kill between its data and the marker
    messages = []
    sweeps.run_to_file(path, out, resume=True, workers=1, on_message=messages.append)
    assert messages == [f"resume: 1 of 2 runs are complete in {out}; running the other 1"]
    with h5py.File(out, "r") as f:
        assert all(f["runs"][name].attrs["stored"] for name in f["runs"])


def test_resume_refuses_a_file_of_another_sweep(tmp_path):
    """Another sweep's file holds runs the sweep does not have: --resume would keep them (an
    edited sweep is continued only where it keeps every stored run, sweep.solver_only_edit)."""
    out = tmp_path / "out.h5"
    sweeps.run_to_file(grid_sweep(tmp_path, steps=["2*pi/40"]), out, workers=1)
    before = contents(out)
    other = grid_sweep(tmp_path, steps=["2*pi/80"], name="other.yaml")
    result = CliRunner().invoke(cli, ["sweep", str(other), "-o", str(out), "--resume"])
    assert result.exit_code == 2
    assert result.output.strip() == (f"error: {out}: was written by the sweep {tmp_path.resolve() / 'sweep.yaml'}, and "
                                      f"this is {other.resolve()}, and the run 'EHBVM/2*pi/40', stored "
                                      "complete, is no longer in it: --resume keeps every stored run; pass --overwrite "
                                      "to start again, or give this sweep another output file")
    after = contents(out)
    assert sorted(after) == sorted(before) and all(np.array_equal(np.asarray(after[key]), np.asarray(value))
                                                   for key, value in before.items())


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_the_client_compiles_nothing_to_store_the_runs_of_a_cluster(tmp_path, client):
    """Each run came back with its problem's Numba functions, which the client rebuilt and
    compiled afresh, once per worker and function, in every `elimfast sweep --scheduler`
    (1.3 s of Table 1's 2.7 s, and a false 'compiling Numba kernels (once ...)' line each
    time). The client must put its own problem (from the caches) into the Results instead."""
    from numba.core import event

    path = write_sweep(tmp_path, {
        "base": {"problem": {"builtin": "pendulum"}, "method": {"name": "hbvm", "k": 4, "s": 2},
                 "integration": {"h": 0.1, "t_end": 1}},
        "grid": [{"name": "h", "key": "integration.h", "values": [0.1, 0.05, 0.025, 0.0125]}]})
    pool = sweeps.run_to_file(path, tmp_path / "pool.h5", workers=1)   # the problem built (or loaded) here first

    class Compiles(event.Listener):
        names = []

        def on_start(self, ev):
            dispatcher = ev.data.get("dispatcher") if isinstance(ev.data, dict) else None
            self.names.append(getattr(getattr(dispatcher, "py_func", None), "__qualname__", "?"))

        def on_end(self, ev):
            pass

    listener = Compiles()
    event.register("numba:compile", listener)
    try:
        dask = sweeps.run(path, tmp_path / "dask.h5", client=client, keep_results=True)
    finally:
        event.unregister("numba:compile", listener)
    assert listener.names == []
    assert_same_files(tmp_path / "pool.h5", tmp_path / "dask.h5")
    assert pool.table() == dask.table()
    assert all(o.result.problem.name == "pendulum" for o in dask.outcomes)


@pytest.mark.parametrize("arguments,message", [
    (["--scheduler", "tcp://127.0.0.1:PORT"], "--scheduler tcp://127.0.0.1:PORT: cannot connect ("),
    (["--scheduler", "not an address"], "--scheduler 'not an address': give the address of a Dask scheduler"),
    (["--scheduler", "tls://127.0.0.1:PORT"], "--scheduler tls://127.0.0.1:PORT: cannot connect (TLS expects"),
    (["--scheduler", "tcp://127.0.0.1:PORT", "--workers", "2"], "--workers applies to the local pool"),
    (["--resume"], "--resume continues the sweep file given with -o OUT.h5"),
    (["--resume", "--overwrite", "-o", "x.h5"], "--resume and --overwrite exclude each other"),
])
def test_bad_scheduler_options_give_one_line_errors(tmp_path, arguments, message, monkeypatch):
    monkeypatch.setattr(on_dask, "CONNECT_TIMEOUT_S", 2)
    port = str(free_port())   # nothing listens there
    arguments = [a.replace("PORT", port) for a in arguments]
    import distributed  # noqa: F401 -- imported before the clock starts: the bound is on the connect timeout,
    # not on importing Dask (which took over 6 s on a loaded machine and failed the bound in one run)
    start = time.perf_counter()
    result = CliRunner().invoke(cli, ["sweep", str(grid_sweep(tmp_path)), *arguments])
    assert result.exit_code == 2, result.output
    assert result.output.startswith("error: " + message.replace("PORT", port)), result.output
    assert result.output.count("\n") == 1 and "Traceback" not in result.output
    assert time.perf_counter() - start < 5 * on_dask.CONNECT_TIMEOUT_S   # dask's own default is 30 s


def test_elimfast_leaves_dask_s_global_scheduler_option_alone(tmp_path, monkeypatch):
    """elimfast submits to its client by name; a client it makes is not the process's default,
    which would set dask's global 'scheduler' option. A default client that failed to connect
    restored that option only when garbage-collected, which in this suite happened after the
    module's own client had closed: the process was left asking for a distributed scheduler
    with none active, and xarray's to_netcdf failed in a later test."""
    dask = pytest.importorskip("dask")
    import gc
    monkeypatch.setattr(on_dask, "CONNECT_TIMEOUT_S", 1)
    before = dask.config.get("scheduler", None)
    with pytest.raises(SweepError, match="cannot connect"):
        sweeps.run(grid_sweep(tmp_path), scheduler=f"tcp://127.0.0.1:{free_port()}")
    with on_dask.connect("local", workers=1) as client:
        assert dask.config.get("scheduler", None) == before
        assert client.status == "running"
    gc.collect()
    assert dask.config.get("scheduler", None) == before


def test_without_dask_the_error_says_how_to_install_it(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)   # import distributed raises ImportError
    result = CliRunner().invoke(cli, ["sweep", str(grid_sweep(tmp_path)), "--scheduler", "local"])
    assert result.exit_code == 2
    assert result.output == ("error: --scheduler needs dask.distributed, which is not installed: "
                             "pip install 'elimfast[dask]'\n")
    with pytest.raises(SweepError, match="elimfast\\[dask\\]"):
        sweeps.run(grid_sweep(tmp_path), scheduler="tcp://127.0.0.1:8786")


def test_the_local_pool_does_not_import_dask(tmp_path):
    code = ("import sys, elimfast.sweep as s; s.run_to_file(sys.argv[1], workers=1); "
            "print('distributed' in sys.modules or 'dask' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code, str(grid_sweep(tmp_path, steps=["2*pi/40"]))],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "False"


def test_a_cluster_started_by_hand_runs_a_sweep(tmp_path):
    """dask scheduler and two dask worker processes on 127.0.0.1, as a user starts them."""
    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    environment = {**os.environ, "DASK_DISTRIBUTED__WORKER__DAEMON": "False"}
    processes = [subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                   "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                  env=environment, start_new_session=True)]
    try:
        for _ in range(2):
            processes.append(subprocess.Popen([str(DASK), "worker", address, "--nthreads", "1", "--no-dashboard",
                                               "--host", "127.0.0.1"], stdout=subprocess.DEVNULL,
                                              stderr=subprocess.DEVNULL, env=environment, start_new_session=True,
                                              cwd=tmp_path))
        path = grid_sweep(tmp_path)
        out = tmp_path / "out.h5"
        done = subprocess.run([str(ELIMFAST), "sweep", str(path), "-o", str(out), "--scheduler", address],
                              capture_output=True, text=True, timeout=180)
        assert done.returncode == 0, done.stderr
        assert f"dask: connected to {address}" in done.stderr
        assert "[6/6]" in done.stderr
        sweeps.run_to_file(path, tmp_path / "pool.h5", workers=1)
        assert_same_files(tmp_path / "pool.h5", out)
    finally:
        for process in reversed(processes):
            os.killpg(process.pid, signal.SIGTERM)
        for process in processes:
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


def test_inspect_of_a_sweep_file_being_written_says_how_far_the_sweep_got(tmp_path):
    """HDF5 lets no other program open a grid sweep's file while the sweep writes it (outside SWMR
    mode: each run adds groups); inspect and load said only 'open for writing in another
    process'. They now list the runs stored so far (a snapshot of the last flush)."""
    # the longest run starts first (on one worker) and outlasts the test; the short ones end on the other
    path = write_sweep(tmp_path, {"base": {**BASE, "integration": {"h": "pi/30", "t_end": "2*pi"}},
                                  "grid": [{"name": "h", "key": "integration.h",
                                            "values": ["2*pi/40", "2*pi/80", "2*pi/40000000"]}]})
    out = tmp_path / "live.h5"
    process = subprocess.Popen([str(ELIMFAST), "sweep", str(path), "-o", str(out), "--workers", "2"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        for line in process.stderr:
            if line.startswith("[2/"):   # both short runs stored
                break
        result = CliRunner().invoke(cli, ["inspect", str(out)])
        assert process.poll() is None, "the sweep ended before it was inspected"
        assert result.exit_code == 2
        assert result.output.startswith(f"error: {out}: a sweep is writing it: 2 of 3 runs stored (2*pi/40, 2*pi/80) "
                                        "so far; HDF5 lets other programs read it when the sweep ends"), result.output
    finally:
        process.kill()
        process.wait(timeout=60)
