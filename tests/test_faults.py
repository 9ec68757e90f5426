"""Reliability under faults (issue 9): nothing a user computed is lost, no input can hang or
exhaust the machine.

Real processes where the fault needs one: a second writer, a full tmpfs, SIGINT/SIGTERM
during a kernel call that never returns, corrupted files read with a clock running.
Each subprocess is measured (wall time, and peak memory through wait4). The tmpfs tests
mount a 1 MiB tmpfs and skip where mounting is not allowed.
"""
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from elimfast.errors import exact_time
from elimfast.integrate import Integration
from elimfast.config import ConfigError, load_run, load_run_from_dict
from elimfast.io import hdf5
from elimfast.sweep import SweepError, load_sweep
from elimfast_cli.main import cli
from runfiles import steps_on_disk

ROOT = Path(__file__).resolve().parents[1]
KEPLER = str(ROOT / "configs" / "kepler.yaml")
ELIMFAST = str(Path(sys.executable).with_name("elimfast"))
# ~3 s of EHBVM(12,3) steps (as in test_resume): long enough to act after a few chunks.
LONG = ["--set", "integration.t_end=15000", "--set", "output.every=50"]
STEPS_BEFORE_SIGNAL = 1000
QUICK_SECONDS = 20          # a refused input: start-up (~1 s) and the refusal, with a wide margin
SMALL_MEMORY_MB = 400       # a refused input: the interpreter, numba and h5py (~170 MB) and nothing more


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    """One elimfast cache for the subprocesses of this module (python: problems compile once)."""
    return tmp_path_factory.mktemp("elimfast-cache")


@pytest.fixture(autouse=True)
def private_cache(cache_dir, monkeypatch):
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(cache_dir))


# --- processes ------------------------------------------------------------------------------
class Finished:
    def __init__(self, code, stdout, stderr, seconds, max_rss_mb):
        self.code, self.stdout, self.stderr = code, stdout, stderr
        self.seconds, self.max_rss_mb = seconds, max_rss_mb

    @property
    def last_line(self) -> str:
        lines = self.stderr.strip().splitlines()
        return lines[-1] if lines else ""

    def __repr__(self):
        return f"exit {self.code} after {self.seconds:.1f} s, {self.max_rss_mb:.0f} MB: {self.stderr.strip()}"


# The peak memory of a child counts what it inherited before exec: a child forked from this
# (large) test process would show the test process's size. So the elimfast process is
# started by a small Python process that reports its child's ru_maxrss (as a last line).
_MEASURED = ("import os, sys\n"
             "pid = os.posix_spawn(sys.argv[1], sys.argv[1:], os.environ)\n"
             "_, status, usage = os.wait4(pid, 0)\n"
             "sys.stderr.write(f'\\nmaxrss-kb {usage.ru_maxrss}\\n')\n"
             "sys.exit(os.waitstatus_to_exitcode(status) % 256)\n")


class Process:
    """An ``elimfast`` subprocess; with ``measured``, started through a small process that
    reports its peak memory (then signals reach that process, not elimfast)."""

    def __init__(self, *args, cwd=None, measured: bool = False):
        self._out = tempfile.TemporaryFile()
        self._err = tempfile.TemporaryFile()
        self.started = time.monotonic()
        command = [ELIMFAST, *map(str, args)]
        if measured:
            command = [sys.executable, "-S", "-c", _MEASURED, *command]
        self.popen = subprocess.Popen(command, stdout=self._out, stderr=self._err, cwd=cwd, stdin=subprocess.DEVNULL)
        self.pid = self.popen.pid

    def running(self) -> bool:
        return self.popen.poll() is None if self.popen.returncode is None else False

    def send(self, sig) -> float:
        self.popen.send_signal(sig)
        return time.monotonic()

    def finish(self, timeout: float = 300) -> Finished:
        deadline = time.monotonic() + timeout
        while True:
            pid, status, usage = os.wait4(self.pid, os.WNOHANG)
            if pid:
                break
            if time.monotonic() > deadline:
                self.popen.kill()
                pid, status, usage = os.wait4(self.pid, 0)
                break
            time.sleep(0.01)
        seconds = time.monotonic() - self.started
        code = os.waitstatus_to_exitcode(status)
        self.popen.returncode = code
        self._out.seek(0)
        self._err.seek(0)
        stderr, max_rss_kb = self._err.read().decode(), usage.ru_maxrss
        reported = re.search(r"\nmaxrss-kb (\d+)\n$", stderr)
        if reported:
            stderr, max_rss_kb = stderr[:reported.start()], int(reported.group(1))
        return Finished(code, self._out.read().decode(), stderr, seconds, max_rss_kb / 1024)


def elimfast(*args, timeout: float = 300, cwd=None) -> Finished:
    return Process(*args, cwd=cwd).finish(timeout)


def measured(*args, timeout: float = 60) -> Finished:
    """elimfast with its own peak memory (see _MEASURED)."""
    return Process(*args, measured=True).finish(timeout)


def assert_one_line(finished: Finished, code: int, fragment: str):
    assert finished.code == code, finished
    assert "Traceback" not in finished.stderr, finished.stderr
    lines = finished.stderr.strip().splitlines()
    assert len(lines) == 1 and fragment in lines[0], finished.stderr


def wait_for_steps(process: Process, path: Path, steps: int, timeout: float = 120):
    deadline = time.monotonic() + timeout
    while steps_on_disk(path) < steps:
        assert process.running(), process.finish()
        assert time.monotonic() < deadline, "the run did not get going in time"
        time.sleep(0.02)


def run_reference(overrides):
    """An uninterrupted run in this process (the same compiled kernel as the subprocesses)."""
    spec = load_run(KEPLER, overrides=overrides)
    run = Integration.from_spec(spec)
    chunks = [run.initial_chunk(), run.advance(spec.n_steps)]
    return {"y_final": run.y.copy(), "n_steps": spec.n_steps, "y": np.concatenate([c.y for c in chunks]),
            "alpha": chunks[1].multipliers, "iterations": chunks[1].iterations}


def assert_equal_to_reference(path: Path, reference):
    with h5py.File(path, "r") as f:
        assert f.attrs["status"] == "complete" and f.attrs["steps_done"] == reference["n_steps"]
        np.testing.assert_array_equal(f["state/y"][:], reference["y_final"])
        np.testing.assert_array_equal(f["y"][:], reference["y"])
        np.testing.assert_array_equal(f["steps/alpha"][:], reference["alpha"])
        np.testing.assert_array_equal(f["steps/iterations"][:], reference["iterations"])


@pytest.fixture(scope="module")
def long_reference():
    return run_reference(LONG[1::2])


@pytest.fixture(scope="module")
def killed_run(tmp_path_factory):
    """A run of the LONG config killed with SIGKILL after a few flushed chunks (copy it to use it)."""
    path = tmp_path_factory.mktemp("killed") / "killed.h5"
    process = Process("run", KEPLER, "-o", path, *LONG, "--quiet")
    wait_for_steps(process, path, STEPS_BEFORE_SIGNAL)
    process.send(signal.SIGKILL)
    assert process.finish().code == -signal.SIGKILL
    assert hdf5.consistency_flags(path) != 0
    return path


def copy_of(source: Path, directory: Path, name: str = "run.h5") -> Path:
    target = directory / name
    shutil.copyfile(source, target)
    return target


# --- 1. a second writer -----------------------------------------------------------------------
@pytest.mark.slow
def test_overwrite_and_resume_refuse_a_file_another_process_is_writing(tmp_path, long_reference):
    path = tmp_path / "busy.h5"
    first = Process("run", KEPLER, "-o", path, *LONG, "--quiet")
    wait_for_steps(first, path, STEPS_BEFORE_SIGNAL)
    for flag in ("--overwrite", "--resume"):
        second = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), *LONG, flag])
        assert second.exit_code == 2, second.output
        assert re.fullmatch(rf"error: {re.escape(str(path))}: is being written by process {first.pid}; .*\n",
                            second.stderr), second.stderr
    also = CliRunner().invoke(cli, ["sweep", str(tmp_path / "any.yaml"), "-o", str(path), "--overwrite"])
    assert also.exit_code == 2 and "is being written by process" in also.stderr
    finished = first.finish()
    assert finished.code == 0, finished
    assert_equal_to_reference(path, long_reference)     # untouched by the refused runs
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".busy.h5.")]   # no temporary left


def test_overwrite_replaces_a_file_only_once_the_new_one_is_complete(tmp_path):
    """The new file is built beside the old one and renamed over it: a run whose setup fails
    (here: its output is busy at the last moment) leaves the old file as it was."""
    path = tmp_path / "old.h5"
    runner = CliRunner()
    assert runner.invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5", "-q"]).exit_code == 0
    before = path.read_bytes()
    holder = h5py.File(path, "r")        # a reader that holds HDF5's lock: the file is in use
    try:
        result = runner.invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=6", "--overwrite"])
    finally:
        holder.close()
    assert result.exit_code == 2 and "is open in another process" in result.stderr
    assert path.read_bytes() == before
    result = runner.invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=6", "--overwrite", "-q"])
    assert result.exit_code == 0
    with hdf5.RunFile(path) as f:
        assert f.steps_done == 60 and f.status == "complete"


def test_non_regular_outputs_are_refused(tmp_path):
    fifo = tmp_path / "pipe.h5"
    os.mkfifo(fifo)
    for output in (fifo, Path("/dev/null")):
        result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(output), "--overwrite"])
        assert result.exit_code == 2 and "not a regular file" in result.stderr, result.stderr
    assert Path("/dev/null").is_char_device()


# --- 2. a full disk ------------------------------------------------------------------------------
@pytest.fixture
def small_disk(tmp_path):
    """A 1 MiB tmpfs (root only; skipped where mounting is not allowed)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip() or done.returncode}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def grow(mount: Path, size: str):
    subprocess.run(["mount", "-o", f"remount,size={size}", "tmpfs", str(mount)], check=True, capture_output=True)


FULL = ["--set", "integration.t_end=3000", "--set", "output.every=1"]   # 30,000 steps, ~2.6 MB of rows


@pytest.mark.slow
def test_a_full_disk_stops_the_run_cleanly_and_resume_continues_bit_for_bit(small_disk):
    path = small_disk / "run.h5"
    args = ["run", KEPLER, "-o", path, *FULL]
    full = elimfast(*args)
    assert_one_line(full, 1, "disk full at step ")
    step = int(re.search(r"disk full at step (\d+); the (\d+) steps before it are in ", full.stderr).group(1))
    assert f"the {step - 1} steps before it are in {path}; free some space, then continue with: " in full.stderr
    assert 1000 < step < 30_000
    assert hdf5.consistency_flags(path) == 0          # closed cleanly: plain h5py opens it
    with h5py.File(path, "r") as f:
        assert f.attrs["status"] == f"stopped: disk full at step {step}"
        assert f["steps/alpha"].shape[0] == step - 1 == f["state/steps_done"][()]
    with hdf5.RunFile(path) as f:
        assert f.verify()["checksummed"]

    before = path.read_bytes()
    still_full = elimfast(*args, "--resume")          # no room yet: refused, the file untouched
    assert_one_line(still_full, 1, "the disk is full")
    assert path.read_bytes() == before

    grow(small_disk, "16m")
    resumed = elimfast(*args, "--resume", "--quiet")
    assert resumed.code == 0, resumed
    assert_equal_to_reference(path, run_reference(FULL[1::2]))
    assert not [p for p in small_disk.iterdir() if p.name != "run.h5"]


@pytest.mark.slow
def test_a_new_run_on_a_full_disk_is_one_line_and_leaves_nothing(small_disk):
    ballast = small_disk / "ballast"
    with open(ballast, "wb") as handle:
        try:
            handle.write(b"\0" * (2 << 20))
        except OSError:
            pass
    done = elimfast("run", KEPLER, "-o", small_disk / "new.h5", "--set", "integration.t_end=5")
    assert_one_line(done, 1, "the disk is full")
    assert sorted(p.name for p in small_disk.iterdir()) == ["ballast"]


# --- 3. damaged files -----------------------------------------------------------------------------
def corrupt(path: Path, offset: int, count: int = 16, seed: int = 0):
    data = bytearray(path.read_bytes())
    noise = np.random.default_rng(seed).integers(0, 256, count, dtype=np.uint8).tobytes()
    data[offset:offset + count] = bytes(a ^ b | 1 for a, b in zip(data[offset:offset + count], noise))
    path.write_bytes(bytes(data))


def metadata_offset(path: Path, signature: bytes, which: int) -> int:
    """Inside the which-th block of a kind of HDF5 metadata, found by its 4-byte signature
    (OHDR object headers, EAHD/EAIB the chunk indexes of growing datasets, FAHD/FADB the
    index of /state/record, BTLF the link B-trees of groups)."""
    data = path.read_bytes()
    found = [m.start() for m in re.finditer(re.escape(signature), data)]
    assert found, signature
    return found[which] + 6


def chunk_offset(path: Path, dataset: str, index: int = 0) -> int:
    with h5py.File(path, "r", swmr=True) as f:
        return f[dataset].id.get_chunk_info(index).byte_offset + 4


DAMAGE = [
    ("a dataset's object header", b"OHDR", 8),
    ("a chunk index header", b"EAHD", 2),
    ("a chunk index block", b"EAIB", 1),
    ("the state record's index", b"FAHD", 0),
    ("a group's link tree", b"BTLF", 0),
]


@pytest.mark.slow
@pytest.mark.parametrize("label,signature,which", DAMAGE, ids=[d[0] for d in DAMAGE])
def test_damaged_metadata_is_reported_quickly_and_never_resumed(tmp_path, killed_run, label, signature, which):
    """A killed run's file (read in SWMR mode) with 16 bytes of metadata corrupted: HDF5's
    default 100 read attempts with backoff made inspect and resume hang for hours."""
    path = copy_of(killed_run, tmp_path)
    corrupt(path, metadata_offset(path, signature, which))
    before, flags = path.read_bytes(), hdf5.consistency_flags(path)
    inspected = elimfast("inspect", path, timeout=120)
    assert inspected.seconds < QUICK_SECONDS, inspected
    assert inspected.code in (0, 2), inspected
    resumed = elimfast("run", KEPLER, "-o", path, *LONG, "--resume", timeout=120)
    assert resumed.seconds < QUICK_SECONDS, resumed
    assert_one_line(resumed, 2, f"{path} is damaged")
    assert path.read_bytes() == before and hdf5.consistency_flags(path) == flags
    if inspected.code == 2:
        assert_one_line(inspected, 2, f"{path} is damaged at ")


@pytest.mark.slow
def test_every_kind_of_damaged_metadata_is_found_by_inspect(tmp_path, killed_run):
    found = []
    for label, signature, which in DAMAGE:
        path = copy_of(killed_run, tmp_path, f"{signature.decode()}.h5")
        corrupt(path, metadata_offset(path, signature, which))
        with pytest.raises(hdf5.DamagedFileError, match=f"{re.escape(str(path))} is damaged") as caught:
            with hdf5.RunFile(path) as f:
                f.verify()
                f.invariant_drift()
        found.append(str(caught.value))
    assert len(found) == len(DAMAGE)


def test_a_damaged_chunk_is_found_and_a_resume_refuses_it(tmp_path, killed_run):
    """The data chunks carry fletcher32: a corrupted chunk of /y fails on reading, and resume
    (which reads everything it builds on first) refuses the file instead of marking it
    complete around the damage."""
    path = copy_of(killed_run, tmp_path)
    corrupt(path, chunk_offset(path, "y", 0))
    before, flags = path.read_bytes(), hdf5.consistency_flags(path)
    inspected = CliRunner().invoke(cli, ["inspect", str(path)])
    assert inspected.exit_code == 2 and inspected.stdout == ""
    assert re.fullmatch(rf"error: {re.escape(str(path))} is damaged at /y rows 0-\d+ \(a data chunk fails its "
                        r"fletcher32 checksum\); restore it from a copy, or start the run again with --overwrite\n",
                        inspected.stderr), inspected.stderr
    resumed = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), *LONG, "--resume"])
    assert resumed.exit_code == 2 and f"{path} is damaged at /y rows" in resumed.stderr
    assert path.read_bytes() == before and hdf5.consistency_flags(path) == flags
    plotted = CliRunner().invoke(cli, ["plot", str(path), "--kind", "orbit", "-o", str(tmp_path / "o.png")])
    assert plotted.exit_code == 2 and "is damaged at /y" in plotted.stderr


def test_a_damaged_copy_of_the_saved_state_falls_back_to_the_other(tmp_path, killed_run, long_reference):
    """/state/record keeps the state twice (alternate rows): with the newer row damaged, resume
    continues from the older one, and still ends bit for bit where an uninterrupted run ends."""
    path = copy_of(killed_run, tmp_path)
    with hdf5.RunFile(path) as f:
        newest = f.saved_state()
        slot = newest["sequence"] % 2
    corrupt(path, chunk_offset(path, "state/record", slot), count=8)
    with hdf5.RunFile(path) as f:
        older = f.saved_state()
    assert older["sequence"] == newest["sequence"] - 1 and older["steps_done"] < newest["steps_done"]
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), *LONG, "--resume"])
    assert result.exit_code == 0, result.output
    assert f"resumed at step {older['steps_done']}" in result.stderr
    assert_equal_to_reference(path, long_reference)


def test_an_altered_named_state_dataset_is_reported_and_resume_keeps_the_record(tmp_path, killed_run, long_reference):
    """The named /state datasets are a readable copy of /state/record without checksums of their
    own: a byte changed in /state/y (contiguous storage: nothing fails on reading it) is reported
    by inspect, which said nothing before, and resume still continues from the record and ends bit
    for bit where an uninterrupted run ends. The killed run itself, whose copies are of the same
    save, reports nothing."""
    untouched = CliRunner().invoke(cli, ["inspect", str(killed_run)])
    assert untouched.exit_code == 0 and "saved state" not in untouched.stdout, untouched.output
    path = copy_of(killed_run, tmp_path)
    with h5py.File(path, "r", swmr=True) as f:
        offset = f["state/y"].id.get_offset()
        before = f["state/y"][()]
    corrupt(path, offset + 2, count=1)
    with h5py.File(path, "r", swmr=True) as f:
        assert not np.array_equal(f["state/y"][()], before)
    inspected = CliRunner().invoke(cli, ["inspect", str(path)])
    assert inspected.exit_code == 0, inspected.output
    assert re.search(r"saved state +/state/y not as in the checksummed copy of the same save \(/state/record\), "
                     r"which resume reads: altered since", inspected.stdout), inspected.stdout
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), *LONG, "--resume"])
    assert result.exit_code == 0, result.output
    assert_equal_to_reference(path, long_reference)


def test_an_elimfast_file_without_state_is_damaged_not_an_internal_error(tmp_path):
    path = tmp_path / "nostate.h5"
    with h5py.File(path, "w") as f:
        f.attrs["format"] = "elimfast-run"
        f.attrs["format_version"] = 2
        for name in ("t", "y", "steps/iterations"):
            f[name] = [0.0]
        f.create_group("invariants")
        f.create_group("method")
    for args in (["inspect", str(path)], ["run", KEPLER, "-o", str(path), "--resume"]):
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 2, result.output
        assert result.stderr == (f"error: {path} is damaged or incomplete: it has the elimfast run format but no "
                                 "/state; restore it from a copy, or start the run again with --overwrite\n")


# --- 4, 5. inputs that are only data ---------------------------------------------------------------
def test_devices_fifos_and_oversized_files_are_refused_at_once(tmp_path):
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    big = tmp_path / "big.yaml"
    big.write_text("# " + "x" * (2 << 20) + "\n")
    (tmp_path / "zero_sweep.yaml").write_text("base: /dev/zero\n")
    (tmp_path / "fifo_sweep.yaml").write_text("base: fifo.yaml\n")
    (tmp_path / "py_zero.yaml").write_text("problem: {python: /dev/zero}\nmethod: {name: gauss, s: 1}\n"
                                           "integration: {h: 0.1, n_steps: 3}\n")
    cases = [
        (["run", "/dev/zero", "-o", tmp_path / "o.h5"], "/dev/zero: not a regular file"),
        (["run", fifo, "-o", tmp_path / "o.h5"], "fifo.yaml: not a regular file"),
        (["run", big, "-o", tmp_path / "o.h5"], "more than a config file can be"),
        (["check", "/dev/zero"], "/dev/zero: not a regular file"),
        (["sweep", tmp_path / "zero_sweep.yaml"], "/dev/zero: not a regular file"),
        (["sweep", tmp_path / "fifo_sweep.yaml"], "fifo.yaml: not a regular file"),
        (["sweep", "/dev/zero"], "/dev/zero: not a regular file"),
        (["run", tmp_path / "py_zero.yaml", "-o", tmp_path / "o.h5"], "problem.python: /dev/zero: not a regular"),
        (["inspect", "/dev/zero"], "/dev/zero: not a regular file"),
        (["inspect", fifo], "fifo.yaml: not a regular file"),
    ]
    for args, fragment in cases:
        done = measured(*args)
        assert_one_line(done, 2, fragment)
        assert done.seconds < QUICK_SECONDS and done.max_rss_mb < SMALL_MEMORY_MB, (args, done)
    assert not (tmp_path / "o.h5").exists()


def write_yaml(path: Path, data) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path


def test_huge_grids_and_ensembles_are_refused_before_anything_is_allocated(tmp_path):
    base = {"problem": {"builtin": "henon_heiles"}, "method": {"name": "hbvm", "k": 6, "s": 3},
            "integration": {"h": 0.1, "n_steps": 100}}
    # ten axes of ten variants each (ten plain axes on one key are refused for that: one axis per key)
    grid = write_yaml(tmp_path / "grid.yaml", {"base": base, "grid": [
        {"name": f"a{i}", "values": [{"label": f"v{j}", "set": {}} for j in range(10)]} for i in range(10)]})
    ensemble = write_yaml(tmp_path / "ensemble.yaml", {"base": base, "ensemble": {"n": "1e8"}})
    wide = write_yaml(tmp_path / "wide.yaml", {"base": base, "ensemble": {"n": 10 ** 12}})
    out = ["-o", tmp_path / "out.h5"]
    cases = [
        (grid, out, "grid: 10,000,000,000 runs (10 x 10 x 10 x 10 x 10 x 10 x 10 x 10 x 10 x 10), more than a sweep"),
        # In memory, 184 bytes a trajectory: states 4 x 4 x 8, H's error 2 x 8, five numbers 5 x 8; streamed to
        # a file, 112: states 2 x 4 x 8, H's error 8, five numbers 5 x 8 (sweep.ensemble_bytes)
        (ensemble, [], "ensemble.n: ensemble.n = 100,000,000 trajectories of 4 coordinates would need 18.4 GB of memory"),
        (wide, out, "ensemble.n = 1,000,000,000,000 trajectories of 4 coordinates would need 112 TB of memory"),
        (wide, [], "ensemble.n = 1,000,000,000,000 trajectories of 4 coordinates would need 184 TB of memory"),
    ]
    for path, options, fragment in cases:
        done = measured("sweep", path, *options)
        if "1e8" in path.read_text() and "would need" not in done.stderr:
            pytest.skip("this machine has more than 37 GB available: 10^8 trajectories would fit")
        assert_one_line(done, 2, fragment)
        assert done.seconds < QUICK_SECONDS and done.max_rss_mb < SMALL_MEMORY_MB, (path, done)
    assert not (tmp_path / "out.h5").exists()


def test_sweep_labels_must_be_printable_and_odd_ones_still_store(tmp_path):
    base = {"problem": {"builtin": "harmonic_oscillator"}, "method": {"name": "gauss", "s": 1},
            "integration": {"h": 0.1, "n_steps": 5}}
    nul = write_yaml(tmp_path / "nul.yaml", {"base": base, "grid": [
        {"name": "m", "values": [{"label": "a\0b", "set": {}}, {"label": "c", "set": {}}]}]})
    with pytest.raises(SweepError, match=r"grid\[0\]\.values\[0\]\.label: the label 'a\\x00b' contains the control "
                                         r"character '\\x00'"):
        load_sweep(nul)
    result = CliRunner().invoke(cli, ["sweep", str(nul)])
    assert result.exit_code == 2 and result.stderr.count("\n") == 1 and "control character" in result.stderr
    odd = write_yaml(tmp_path / "odd.yaml", {"base": base, "grid": [
        {"name": "h", "key": "integration.h", "values": [0.1, 0.05], "labels": [".", "a/b"]}]})
    out = tmp_path / "odd.h5"
    result = CliRunner().invoke(cli, ["sweep", str(odd), "-o", str(out), "--workers", "1", "-q"])
    assert result.exit_code == 0, result.output
    with h5py.File(out, "r") as f:
        assert sorted(f["runs"]) == ["_.", "a|b"]
        assert f["runs/_."].attrs["label"] == "."


# --- 7. numbers out of range ---------------------------------------------------------------------------
def test_numbers_out_of_range_are_config_errors_and_leave_no_file(tmp_path):
    cases = [
        (["integration.t_end=null", "integration.n_steps=1e30"], "integration.n_steps: must be <= 1e10, got 1e30"),
        (["output.every=1e30"], "output.every: must be <= 1e10"),
        (["integration.t_end=1", "integration.h=1e-300"], "integration.t_end: (t_end - t0)/h = 1e+300 steps"),
        (["solver.max_iter=1e30"], "solver.max_iter: must be <= 10000, got 1e30"),
        (["solver.tol=1e10"], "solver.tol: must be <= 1e-08"),
    ]
    for overrides, fragment in cases:
        args = ["run", KEPLER, "-o", str(tmp_path / "o.h5")] + [a for o in overrides for a in ("--set", o)]
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 2, (overrides, result.output)
        assert result.stderr.count("\n") == 1 and fragment in result.stderr, result.stderr
    assert not (tmp_path / "o.h5").exists()
    # output.every may exceed the steps: only the first and the last state are kept
    spec = load_run(KEPLER, overrides=["integration.t_end=1", "output.every=1000"])
    assert spec.output_every == 1000 and spec.n_steps == 10
    with pytest.raises(ConfigError, match="problem.parameters.n: must be at most 100000"):
        load_run_from_dict({"problem": {"builtin": "fpu_beta", "parameters": {"n": "1e9"}},
                            "method": {"name": "gauss", "s": 1}, "integration": {"h": 0.1, "n_steps": 1}})


# --- 8. interrupts during a kernel call that never returns -----------------------------------------------
DRIFT = '''
"""A free particle drifting towards a wall at q = WALL, where grad_H misbehaves (a test problem)."""
PARAMETERS = {"wall": 50.0}
Y0 = [0.0, 1.0]


def H(y, params):
    return 0.5 * y[1] * y[1]


def grad_H(y, params, out):
    out[0] = 0.0
    out[1] = y[1]
    if y[0] > params[0]:
        MISBEHAVE
'''
LOOP = "while y[0] > params[0]:      # for ever (the store keeps the loop from being optimised away)\n" \
       "            out[1] = out[1] + 1.0"
RAISE = 'raise ValueError("q is beyond the wall")'
FIXED = "out[1] = y[1]"
DRIFT_CONFIG = ("problem: {python: drift.py}\nmethod: {name: gauss, s: 1}\n"
                "integration: {h: 0.001, n_steps: 100000}\noutput: {every: 1000}\n")


def steps_when_stuck(process: Process, path: Path, quiet_seconds: float = 2.0) -> int:
    """The saved steps once the run is stuck (nothing new saved for quiet_seconds, still running)."""
    wait_for_steps(process, path, 1)
    deadline = time.monotonic() + 120
    steps, since = steps_on_disk(path), time.monotonic()
    while time.monotonic() - since < quiet_seconds:
        assert process.running(), process.finish()
        assert time.monotonic() < deadline
        time.sleep(0.05)
        now = steps_on_disk(path)
        if now != steps:
            steps, since = now, time.monotonic()
    return steps


def drift_problem(directory: Path, misbehaviour: str) -> Path:
    (directory / "drift.py").write_text(textwrap.dedent(DRIFT).replace("MISBEHAVE", misbehaviour))
    config = directory / "drift.yaml"
    config.write_text(DRIFT_CONFIG)
    return config


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
@pytest.mark.usefixtures("allow_python")
def test_a_signal_stops_a_kernel_call_that_never_returns(tmp_path, sig):
    config = drift_problem(tmp_path, LOOP)
    path = tmp_path / "loop.h5"
    process = Process("run", config, "-o", path)
    saved = steps_when_stuck(process, path)   # now inside the kernel call that loops at step 50,001
    assert 0 < saved < 50_000
    sent = process.send(sig)
    finished = process.finish(timeout=60)
    stopped_after = time.monotonic() - sent
    assert finished.code == 130, finished
    assert stopped_after < 4.0, f"took {stopped_after:.1f} s to stop"
    name = signal.Signals(sig).name
    with hdf5.RunFile(path) as f:            # as after kill -9: consistent, resumable
        assert f.status == "killed" and f.steps_done == saved
        assert f.verify()["checksummed"]
        t = float(f.saved_state()["clock"][0])
    assert finished.last_line == (f"interrupted by {name} at step {saved}/100000 (t = {exact_time(t)}); {path} is complete "
                                  f"up to there; continue with: elimfast run {config} -o {path} --resume --allow-python")
    if sig == signal.SIGINT:                 # fix the problem, resume, compare with a run of the fixed one
        drift_problem(tmp_path, FIXED)
        resumed = elimfast("run", config, "-o", path, "--resume")
        assert resumed.code == 0 and f"resumed at step {saved}" in resumed.stderr, resumed
        fresh = elimfast("run", config, "-o", tmp_path / "fresh.h5", "--quiet")
        assert fresh.code == 0, fresh
        with h5py.File(path, "r") as a, h5py.File(tmp_path / "fresh.h5", "r") as b:
            np.testing.assert_array_equal(a["y"][:], b["y"][:])
            np.testing.assert_array_equal(a["steps/iterations"][:], b["steps/iterations"][:])


# --- 9. a problem function that raises ------------------------------------------------------------------
@pytest.mark.usefixtures("allow_python")
def test_a_problem_function_that_raises_is_one_line_naming_the_users_file(tmp_path):
    config = drift_problem(tmp_path, RAISE)
    path = tmp_path / "raise.h5"
    result = CliRunner().invoke(cli, ["run", str(config), "-o", str(path)])
    assert result.exit_code == 1, result.output
    with h5py.File(path, "r") as f:          # closed cleanly at the last saved chunk
        assert f.attrs["status"] == "stopped: the problem raised ValueError: q is beyond the wall at step 50001 (t = 50)"
        saved = int(f["state/steps_done"][()])
        # every step before the one that raised is kept (the kernel call that raised had done them:
        # they are taken again and saved), not only those of the chunks written before it
        assert saved == 50_000 and f["steps/iterations"].shape[0] == saved and f["y"].shape[0] == 51
    # the user's new file is compiled: the one line announcing it comes first, once per process
    errors = "".join(line for line in result.stderr.splitlines(keepends=True)
                     if not line.startswith("compiling "))
    assert errors == (f"error: {tmp_path / 'drift.py'}: a problem function raised ValueError: q is beyond the "
                      f"wall at step 50001 (t = 50); {path} holds the {saved} steps saved before it; fix the "
                      f"problem, then continue with: elimfast run {config} -o {path} --resume --allow-python\n")
    assert "u_" not in result.stderr
    drift_problem(tmp_path, FIXED)
    resumed = CliRunner().invoke(cli, ["run", str(config), "-o", str(path), "--resume"])
    assert resumed.exit_code == 0 and f"resumed at step {saved}" in resumed.stderr, resumed.output
    fresh = CliRunner().invoke(cli, ["run", str(config), "-o", str(tmp_path / "fresh.h5"), "--quiet"])
    assert fresh.exit_code == 0, fresh.output
    with h5py.File(path, "r") as a, h5py.File(tmp_path / "fresh.h5", "r") as b:   # the steps kept are exact
        np.testing.assert_array_equal(a["y"][:], b["y"][:])
        np.testing.assert_array_equal(a["steps/iterations"][:], b["steps/iterations"][:])


@pytest.mark.usefixtures("allow_python")
def test_a_sweep_run_whose_problem_raises_fails_alone(tmp_path):
    drift_problem(tmp_path, RAISE)
    sweep = write_yaml(tmp_path / "sweep.yaml", {
        "base": "drift.yaml", "set": {"integration": {"n_steps": 60000}},
        "grid": [{"name": "wall", "key": "problem.parameters.wall", "values": [50.0, 100.0]}]})
    out = tmp_path / "sweep.h5"
    result = CliRunner().invoke(cli, ["sweep", str(sweep), "-o", str(out), "--workers", "1", "-q"])
    assert result.exit_code == 1, result.output
    assert "1 of 2 runs failed" in result.stderr and "Traceback" not in result.output
    with h5py.File(out, "r") as f:
        failed = str(f["runs/50.0"].attrs["status"])
        assert failed.startswith(f"failed: {tmp_path / 'drift.py'}: a problem function raised ValueError")
        assert "at step 50001" in failed
        assert f["runs/100.0"].attrs["status"] == "complete"


@pytest.mark.slow
def test_a_sweep_that_fills_the_disk_keeps_the_runs_stored_before(small_disk, tmp_path):
    sweep = write_yaml(tmp_path / "sweep.yaml", {
        "base": KEPLER, "set": {"integration": {"t_end": 400}, "output": {"every": 1}},
        "grid": [{"name": "h", "key": "integration.h", "values": [0.1, 0.05, 0.025, 0.0125]}]})
    out = small_disk / "sweep.h5"
    done = elimfast("sweep", sweep, "-o", out, "--workers", "1", "-q")
    assert_one_line(done, 1, f"{out}: the disk is full; the runs stored before this one are in the file")
    with h5py.File(out, "r") as f:           # closed normally: every stored run readable
        stored = list(f["runs"])
        assert stored and all(f["runs"][name].attrs["status"] == "complete" for name in stored)
        assert f["runs/0.1/y"].shape == (4001, 4)


def test_sweep_workers_are_bounded(tmp_path):
    sweep = write_yaml(tmp_path / "sweep.yaml", {"base": KEPLER, "grid": [
        {"name": "h", "key": "integration.h", "values": [0.1, 0.05]}]})
    result = CliRunner().invoke(cli, ["sweep", str(sweep), "--workers", "100000"])
    assert result.exit_code == 2 and "--workers 100000: at most" in result.stderr


def test_a_format_1_file_without_the_state_record_still_resumes_exactly(tmp_path, killed_run, long_reference):
    path = copy_of(killed_run, tmp_path)
    hdf5.clear_consistency_flags(path)
    with h5py.File(path, "r+") as f:         # what elimfast 0.1 wrote: no /state/record, format 1
        del f["state/record"]
        f.attrs["format_version"] = 1
    with hdf5.RunFile(path) as f:
        assert "sequence" not in f.saved_state() and f.steps_done >= STEPS_BEFORE_SIGNAL
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), *LONG, "--resume"])
    assert result.exit_code == 0 and "resumed at step" in result.stderr, result.output
    assert_equal_to_reference(path, long_reference)
    with h5py.File(path, "r") as f:
        assert f.attrs["format_version"] == 1 and "record" not in f["state"]


def as_written_before_coef_extra(path: Path) -> None:
    """Turn a run file into what elimfast wrote before the predictor kept its extra term: no
    /state/coef_extra, and a state record without it (both rows repacked, their CRCs anew)."""
    from elimfast.io import runfile
    with h5py.File(path, "r+") as f:
        state = f["state"]
        n, s, n_mult = state["y"].shape[0], state["coef"].shape[0], state["multipliers"].shape[0]
        n_extra = state["coef_extra"].shape[0]
        rows = [runfile._unpack_record(np.asarray(row, dtype=np.float64), n, s, n_mult, None, n_extra)
                for row in state["record"][()]]
        for name in ("record", "coef_extra", "extra_coefficient", "record_slot", "record_field"):
            del state[name]
        old_rows = [runfile._pack_record({key: value for key, value in row.items() if key != "coef_extra"},
                                         row["sequence"], row["n_samples"], row["wall_time_s"],
                                         row["kernel_time_s"]) for row in rows]
        record = runfile._record_dataset(state, old_rows[0].size)
        for row in old_rows:
            runfile._write_record_row(record, int(row[0]) % 2, row)   # the slot of its sequence number
        runfile.attach(record, runfile.dimension(state, "record_slot", 2),
                       runfile.dimension(state, "record_field", old_rows[0].size))


def test_a_file_written_before_the_predictor_kept_gamma_s_resumes_without_it(tmp_path, killed_run,
                                                                              long_reference):
    """A file of the previous version has no /state/coef_extra: it resumes (and stays in its
    format), its first step predicted from the coefficients alone, so the continued run equals
    an uninterrupted one only to round-off, not bit for bit (docs/solver.md#the-predictor)."""
    path = copy_of(killed_run, tmp_path)
    hdf5.clear_consistency_flags(path)
    as_written_before_coef_extra(path)
    with hdf5.RunFile(path) as f:
        saved = f.saved_state()
        assert "coef_extra" not in saved and f.steps_done >= STEPS_BEFORE_SIGNAL
    result = CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), *LONG, "--resume"])
    assert result.exit_code == 0 and f"resumed at step {saved['steps_done']}" in result.stderr, result.output
    with h5py.File(path, "r") as f:
        assert f.attrs["status"] == "complete" and "coef_extra" not in f["state"]
        done = saved["steps_done"]
        np.testing.assert_array_equal(f["steps/iterations"][:done], long_reference["iterations"][:done])
        assert np.max(np.abs(f["state/y"][:] - long_reference["y_final"])) < 1e-9
    with hdf5.RunFile(path) as f:
        assert f.steps_done == long_reference["n_steps"] and "coef_extra" not in f.saved_state()


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
@pytest.mark.usefixtures("allow_python")
def test_a_signal_stops_a_sweep_whose_run_never_returns(tmp_path, workers):
    """In process (one worker) the watchdog ends the kernel call; with worker processes the
    parent stops at once and kills its workers (which cannot run a signal handler)."""
    drift_problem(tmp_path, LOOP)
    sweep = write_yaml(tmp_path / "sweep.yaml", {
        "base": "drift.yaml", "grid": [{"name": "wall", "key": "problem.parameters.wall", "values": [0.5, 0.6]}]})
    process = Process("sweep", sweep, "-o", tmp_path / "sweep.h5", "--workers", workers, "-q")
    time.sleep(6.0)                          # start-up, compiling the problem, then both runs loop
    assert process.running()
    sent = process.send(signal.SIGINT)
    finished = process.finish(timeout=60)
    assert finished.code == 130 and time.monotonic() - sent < 4.0, finished
    assert "Traceback" not in finished.stderr and finished.last_line.startswith("error: interrupted"), finished
    if workers == 2:
        time.sleep(0.5)
        left = subprocess.run(["pgrep", "-f", str(sweep)], capture_output=True, text=True).stdout.split()
        assert not left, f"workers left running: {left}"


@pytest.mark.parametrize("events", [False, True], ids=["fixed steps", "fixed steps with an event"])
def test_a_failure_where_the_orbit_escapes_names_the_step_and_the_growth(tmp_path, events):
    """A user trial: a Henon-Heiles variant whose potential is unbounded below (x^2 y - y^3/3 with
    2 for 1, no quartic term) escapes to infinity and fails at step 130; with an event (the
    adaptive kernel's fixed steps) the line read "t = 6.45 -> 6.453125" (the substep's h for the
    step's), and either way it advised reducing h, which cannot help. It names the step [6.45,
    6.5] and the state's growth."""
    config = {"problem": {"name": "escape", "coordinates": {"q": ["x", "y"], "p": ["px", "py"]},
                          "hamiltonian": "(px**2 + py**2)/2 + (x**2 + y**2)/2 + 2*(x**2*y - y**3/3)",
                          "initial": {"x": 0.1, "y": 0.2, "px": 0.3, "py": 0.0}},
              "method": {"name": "hbvm", "k": 6, "s": 3}, "integration": {"h": 0.05, "t_end": 50}}
    if events:
        config["events"] = {"section": {"expression": "x", "direction": 1}}
    path = tmp_path / "escape.yaml"
    path.write_text(yaml.safe_dump(config))
    result = CliRunner().invoke(cli, ["run", str(path), "-o", str(tmp_path / "escape.h5")])
    assert result.exit_code == 1, result.output
    line = result.stderr.strip().splitlines()[-1]
    match = re.search(r"at step (\d+) \(t = ([0-9.]+) -> ([0-9.]+)\)", line)
    assert match and abs(float(match.group(3)) - float(match.group(2)) - 0.05) < 1e-12, line
    assert "if the orbit is escaping to infinity, or its momenta blowing up in a fall into a singularity of H, " \
        "no step size gets through" in line, line


def test_a_run_watched_by_a_reader_to_its_end_completes(tmp_path):
    """A user trial: a run whose file an h5py reader (swmr=True, as the README invites) held open
    when it ended failed with exit 1, 'cannot write ... at step 300001 ... check the disk', and
    left its status 'running' (inspect: killed): the final attributes' session was refused by
    HDF5's lock, which the reader held. It now completes, and the reader keeps its snapshot."""
    path = tmp_path / "watched.h5"
    run = subprocess.Popen([ELIMFAST, "run", str(ROOT / "configs" / "kepler.yaml"), "-o", str(path), "--quiet", "--set",
                            "integration.t_end=100000"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 600   # a cold Numba cache compiles the kernels first
    while steps_on_disk(path) < 1000:
        assert run.poll() is None, run.communicate()
        assert time.monotonic() < deadline
        time.sleep(0.01)
    with h5py.File(path, "r", swmr=True) as reader:
        seen = reader["y"].shape[0]
        assert run.poll() is None, "the run ended before the reader held its file: make it longer"
        _, stderr = run.communicate(timeout=600)
        assert reader["y"].shape[0] == seen
    assert run.returncode == 0 and stderr == "", stderr
    with h5py.File(path, "r") as f:
        assert f.attrs["status"] == "complete" and int(f.attrs["steps_done"]) == 1_000_000
