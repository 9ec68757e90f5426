"""The HDF5 writer and reader, and the chunked driver (elimfast.io.hdf5, elimfast.streaming).

Everything in-process on small runs; the subprocess kill/resume tests are in test_resume.py.
"""
import struct
import tracemalloc

import h5py
import numpy as np
import pytest

from elimfast import integrate, methods, problems, streaming
from elimfast.integrate import Integration
from elimfast.io import hdf5

CONSERVE = ("angular_momentum", "lrl_y")


def kepler_run(kepler, n_steps=300, every=7, method=None, conserve=CONSERVE, **kw):
    method = method or methods.ehbvm(6, 3)
    return Integration(kepler, method, 0.1, n_steps, conserve=conserve, store_every=every, **kw)


def write(integration, path, **kw):
    kw.setdefault("config_text", "problem: {builtin: kepler}\n")
    return streaming.run_to_file(integration, path, handle_signals=False, **kw)


class StopAfter:
    """A stand-in for StopOnSignals that asks to stop after n chunks."""

    def __init__(self, chunks):
        self.chunks, self.calls, self.name = chunks, 0, "SIGINT"

    @property
    def requested(self):
        self.calls += 1
        return self.calls > self.chunks


# --- layout ---------------------------------------------------------------------------------
def test_layout_of_an_ehbvm_run(tmp_path, kepler):
    path = tmp_path / "run.h5"
    run = kepler_run(kepler, n_steps=300, every=7)
    outcome = write(run, path)
    assert outcome.status == "complete" and outcome.exit_code == 0
    ref = integrate(kepler, methods.ehbvm(6, 3), h=0.1, n_steps=300, conserve=CONSERVE, store_every=7)
    with h5py.File(path, "r") as f:
        a = f.attrs
        for key in ("elimfast_version", "numba_version", "numpy_version", "h5py_version", "created", "config",
                    "problem", "method", "r", "k", "s", "h", "t0", "t_end", "n_steps", "steps_done", "status",
                    "wall_time_s"):
            assert key in a, key
        assert (a["problem"], a["method"], a["status"]) == ("kepler", "EHBVM(6,3)", "complete")
        assert (a["r"], a["k"], a["s"], a["n_steps"], a["steps_done"]) == (6, 6, 3, 300, 300)
        assert a["h"] == 0.1 and a["t_end"] == pytest.approx(30.0) and a["wall_time_s"] > 0
        # samples: every 7th step and the last one (300 is no multiple of 7), plus t0
        n_samples = 1 + 300 // 7 + 1
        assert f["t"].shape == (n_samples,) and f["y"].shape == (n_samples, 4)
        assert [n.decode() for n in f["component"][()]] == ["q1", "q2", "p1", "p2"]   # CF reserves "coordinates"
        assert "coordinates" not in f["y"].attrs
        assert set(f["invariants"]) == {"H", "angular_momentum", "lrl_x", "lrl_y"}
        assert f["invariants/lrl_y"].attrs["imposed"] and not f["invariants/lrl_x"].attrs["imposed"]
        assert f["steps/iterations"].shape == (300,) and f["steps/iterations"].dtype.kind == "i"
        assert f["steps/alpha"].shape == (300, 2) and "lambda" not in f["steps"]
        for name in ("t", "y", "invariants/H", "steps/iterations", "steps/alpha"):
            d = f[name]
            assert d.chunks is not None and d.compression == "gzip" and d.maxshape[0] is None, name
        # the data are those of integrate(), bit for bit
        np.testing.assert_array_equal(f["t"][:], ref.t)
        np.testing.assert_array_equal(f["y"][:], ref.y)
        np.testing.assert_array_equal(f["invariants/lrl_x"][:], ref.invariants["lrl_x"])
        np.testing.assert_array_equal(f["steps/alpha"][:], ref.alpha)
        np.testing.assert_array_equal(f["steps/iterations"][:], ref.iterations)
        # method tables: ELIM stores the underlying HBVM tableau and says so
        A, b, c = run.method.butcher()
        np.testing.assert_array_equal(f["method/A"][:], A)
        np.testing.assert_array_equal(f["method/b"][:], b)
        np.testing.assert_array_equal(f["method/c"][:], c)
        assert "eta = 1" in f["method"].attrs["tableau"]
        np.testing.assert_array_equal(f["method/quadrature_nodes"][:], run.method.c)
        np.testing.assert_array_equal(f["method/invariant_quadrature_weights"][:], run.method.bhat)
        # state: the final state of the run
        np.testing.assert_array_equal(f["state/y"][:], ref.y_final)
        assert f["state/steps_done"][()] == 300 and f["state/n_samples"][()] == n_samples


def test_lim_stores_lambda_and_no_tableau(tmp_path, kepler):
    path = tmp_path / "lim.h5"
    write(kepler_run(kepler, n_steps=40, every=1, method=methods.ghbvm(4, 2), conserve=("angular_momentum",)), path)
    with h5py.File(path, "r") as f:
        assert f["steps/lambda"].shape == (40, 2)
        assert list(f["steps/lambda"].attrs["invariants"]) == ["H", "angular_momentum"]
        assert "A" not in f["method"] and "quadrature_nodes" in f["method"]


def test_gauss_stores_no_multipliers(tmp_path, kepler):
    path = tmp_path / "gauss.h5"
    write(kepler_run(kepler, n_steps=20, every=1, method=methods.gauss(2), conserve=()), path)
    with h5py.File(path, "r") as f:
        assert set(f["steps"]) == {"iterations", "substeps", "step"}   # step: the dimension (no data)
        assert (f["steps/substeps"][:] == 1).all()
        assert f["method/A"].shape == (2, 2)
    with hdf5.RunFile(path) as run_file:
        assert run_file.multiplier_name is None and run_file.max_abs_multipliers() == []


# --- streaming --------------------------------------------------------------------------------
def test_chunk_boundaries_do_not_change_the_numbers(tmp_path, kepler):
    ref = kepler_run(kepler, n_steps=500, every=3)
    ref.advance(10 ** 9)
    for target, first in ((1e-9, 1), (1e-4, 5), (10.0, 64)):   # ~1-step chunks, small ones, one big chunk
        run = kepler_run(kepler, n_steps=500, every=3)
        outcome = write(run, tmp_path / f"c{first}.h5", target_seconds=target, first_chunk_steps=first, overwrite=True)
        assert outcome.status == "complete"
        np.testing.assert_array_equal(run.y, ref.y)
        np.testing.assert_array_equal(run.clock, ref.clock)
    assert outcome.chunks <= 2


def test_chunk_sizing_is_bounded():
    # ~target seconds, at most MAX_GROWTH times the last chunk, at most the memory cap
    assert streaming.next_chunk_steps(100, 0.01, 100.0, target_seconds=0.5) == 5000
    assert streaming.next_chunk_steps(100, 0.0, 100.0) == 100 * streaming.MAX_GROWTH
    assert streaming.next_chunk_steps(10 ** 6, 0.001, 1000.0, max_bytes=1 << 20) == (1 << 20) // 1000
    assert streaming.next_chunk_steps(100, 1.0, 100.0, target_seconds=0.5) == 50
    # a small remainder joins the chunk instead of making a tiny last one
    assert streaming.next_chunk_steps(100, 0.01, 100.0, target_seconds=0.5, remaining=6000) == 6000
    assert streaming.next_chunk_steps(100, 0.01, 100.0, target_seconds=0.5, remaining=9000) == 5000


def test_memory_stays_bounded_for_long_runs(tmp_path):
    """2e6 steps, a sample every 1000: the per-step data alone (iterations) would be 16 MB."""
    oscillator = problems.harmonic_oscillator()
    run = Integration(oscillator, methods.gauss(1), 0.01, 2_000_000, store_every=1000)
    tracemalloc.start()
    try:
        outcome = write(run, tmp_path / "long.h5", max_chunk_bytes=1 << 20)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert outcome.status == "complete" and outcome.chunks >= 16
    assert peak < 6 << 20, f"peak {peak / 2**20:.1f} MiB"
    with hdf5.RunFile(tmp_path / "long.h5") as f:
        assert f.n_samples == 2001 and f.steps_done == 2_000_000
        assert f.iteration_stats()["count"] == 2_000_000


def test_interrupt_then_resume_in_process_is_exact(tmp_path, kepler):
    path = tmp_path / "resume.h5"
    ref = kepler_run(kepler, n_steps=400, every=6)
    ref_chunks = [ref.initial_chunk(), ref.advance(10 ** 9)]
    run = kepler_run(kepler, n_steps=400, every=6)
    writer = hdf5.RunWriter.create(path, run, config_text="a: 1\n")
    outcome = streaming.drive(run, writer, stop=StopAfter(3), first_chunk_steps=7, target_seconds=1e-9)
    assert outcome.status == "interrupted" and outcome.exit_code == 130 and 0 < outcome.steps_done < 400
    with hdf5.RunFile(path) as f:
        assert f.status == "interrupted" and f.steps_done == outcome.steps_done

    fresh = kepler_run(kepler, n_steps=400, every=6)
    outcome = write(fresh, path, config_text="a: 1\n", resume=True)
    assert outcome.status == "complete" and outcome.note.startswith("resumed at step")
    np.testing.assert_array_equal(fresh.y, ref.y)
    np.testing.assert_array_equal(fresh.y_comp, ref.y_comp)
    with h5py.File(path, "r") as f:
        np.testing.assert_array_equal(f["y"][:], np.concatenate([c.y for c in ref_chunks]))
        np.testing.assert_array_equal(f["steps/alpha"][:], ref_chunks[1].multipliers)
        assert f.attrs["steps_done"] == 400 and f.attrs["status"] == "complete"


def test_resume_refuses_other_configs_and_failed_runs(tmp_path, kepler):
    path = tmp_path / "r.h5"
    run = kepler_run(kepler, n_steps=50)
    writer = hdf5.RunWriter.create(path, run, config_text="method: {s: 3}\noutput: {path: a.h5}\n")
    streaming.drive(run, writer, stop=StopAfter(1), first_chunk_steps=5)
    with pytest.raises(hdf5.OutputError, match="different config.*method.s"):
        write(kepler_run(kepler, n_steps=50), path, config_text="method: {s: 4}\n", resume=True)
    # the output path may differ (the file was moved)
    outcome = write(kepler_run(kepler, n_steps=50), path, config_text="method: {s: 3}\noutput: {path: b.h5}\n",
                    resume=True)
    assert outcome.status == "complete"

    failing = tmp_path / "fail.h5"
    outcome = write(kepler_run(kepler, n_steps=50, max_iter=3), failing)
    assert outcome.status.startswith("failed: ") and outcome.exit_code == 1
    with pytest.raises(hdf5.OutputError, match="would fail the same way"):
        write(kepler_run(kepler, n_steps=50, max_iter=3), failing, resume=True)


def test_a_failed_run_keeps_its_data(tmp_path):
    # Kepler, e = 0.9, from aphelion: the fixed point cannot converge in 10 iterations
    # near perihelion with h = 0.1 (step 24), after 23 good steps, and no step is split.
    e = 0.9
    aphelion = [-(1 + e), 0.0, 0.0, -((1 - e) / (1 + e)) ** 0.5]
    run = Integration(problems.kepler(e), methods.gauss(2), 0.1, 200, max_iter=10, y0=aphelion,
                      solver="fixed_point", max_halvings=0)
    outcome = write(run, tmp_path / "f.h5")
    assert outcome.status.startswith("failed: GAUSS(2): the fixed-point iteration did not converge")
    assert 10 < outcome.steps_done < 40 and outcome.exit_code == 1
    done = outcome.steps_done
    assert f"at step {done + 1} " in outcome.status
    with hdf5.RunFile(tmp_path / "f.h5") as f:
        assert f.status == outcome.status and f.steps_done == done
        assert len(f.iterations()) == done and f.n_samples == done + 1
        # two tries of max_iter = 10: from the predicted guess, then the unextrapolated one (docs/solver.md)
        assert f.attrs["failed_step_iterations"] == 2 * 10


def test_output_path_checks(tmp_path):
    existing = tmp_path / "x.h5"
    existing.write_bytes(b"")
    with pytest.raises(hdf5.OutputError, match="already exists; pass --overwrite"):
        hdf5.check_output_path(existing)
    hdf5.check_output_path(existing, overwrite=True)
    with pytest.raises(hdf5.OutputError, match="is a directory"):
        hdf5.check_output_path(tmp_path)
    with pytest.raises(hdf5.OutputError, match="is a file, not a directory"):
        hdf5.check_output_path(existing / "sub" / "y.h5")
    hdf5.check_output_path(tmp_path / "new" / "dirs" / "y.h5")   # creatable
    assert not (tmp_path / "new").exists()                      # ... but not created by the check


def test_missing_directories_of_an_output_are_created_or_named_in_one_line(tmp_path):
    """The one rule of the writers (run and sweep files, figures): make the missing directories;
    where that fails, say which file and which directory."""
    path = tmp_path / "a" / "b" / "fig.png"
    hdf5.create_parent_directories(path)
    assert path.parent.is_dir() and not path.exists()
    with pytest.raises(hdf5.OutputError) as caught:
        hdf5.create_parent_directories("/proc/elimfast-test/sub/fig.png")   # /proc takes no new directories
    message = str(caught.value)
    assert message.startswith("/proc/elimfast-test/sub/fig.png: cannot create the directory /proc/elimfast-test (")
    assert message.endswith("); choose another output path") and "\n" not in message
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    with pytest.raises(hdf5.OutputError, match=f"^{a_file / 'd' / 'x.h5'}: {a_file} is a file, not a directory;"):
        hdf5.create_parent_directories(a_file / "d" / "x.h5")


def test_reader_rejects_foreign_files(tmp_path):
    text = tmp_path / "notes.h5"
    text.write_text("hello")
    with pytest.raises(hdf5.NotAnElimfastFile, match="not an HDF5 file"):
        hdf5.RunFile(text)
    foreign = tmp_path / "foreign.h5"
    with h5py.File(foreign, "w") as f:
        f["t"] = np.arange(3.0)
    with pytest.raises(hdf5.NotAnElimfastFile, match="not an elimfast run file"):
        hdf5.RunFile(foreign)
    with pytest.raises(hdf5.OutputError, match="no such file"):
        hdf5.RunFile(tmp_path / "missing.h5")


def test_reader_summaries(tmp_path, kepler):
    path = tmp_path / "s.h5"
    run = kepler_run(kepler, n_steps=200, every=1)
    write(run, path)
    ref = integrate(kepler, methods.ehbvm(6, 3), h=0.1, n_steps=200, conserve=CONSERVE)
    with hdf5.RunFile(path) as f:
        drift = f.invariant_drift()
        for name, value in ref.invariant_errors().items():
            assert drift[name] == value
        stats = f.iteration_stats()
        assert stats["count"] == 200 and stats["max"] == ref.iterations.max() and stats["min"] == ref.iterations.min()
        assert stats["mean"] == pytest.approx(ref.iterations.mean())
        assert stats["median"] == int(np.median(ref.iterations))
        np.testing.assert_array_equal(f.max_abs_multipliers(), np.abs(ref.alpha).max(axis=0))
        assert f.multiplier_labels() == ["alpha[angular_momentum]", "alpha[lrl_y]"]


def _damage_chunk_at_row(path, dataset: str, row: int) -> None:
    """Flip 16 bytes inside the stored chunk of ``dataset`` that holds ``row`` (its fletcher32 then fails)."""
    with h5py.File(path, "r") as f:
        chunks = f[dataset].id
        info = next(chunks.get_chunk_info(i) for i in range(chunks.get_num_chunks())
                    if chunks.get_chunk_info(i).chunk_offset[0] <= row < chunks.get_chunk_info(i).chunk_offset[0]
                    + f[dataset].chunks[0])
    data = bytearray(path.read_bytes())
    middle = info.byte_offset + info.size // 2
    data[middle:middle + 16] = bytes(b ^ 0x5A for b in data[middle:middle + 16])
    path.write_bytes(bytes(data))


@pytest.fixture(scope="module")
def long_file(tmp_path_factory, kepler):
    """5000 steps, a sample each: /y has 5001 rows in chunks of 512, /invariants/H in chunks of 2048."""
    path = tmp_path_factory.mktemp("damage") / "long.h5"
    write(kepler_run(kepler, n_steps=5000, every=1), path)
    with h5py.File(path, "r") as f:
        assert f["y"].shape == (5001, 4) and f["y"].chunks == (512, 4) and f["invariants/H"].chunks == (2048,)
    return path


@pytest.mark.parametrize("rows,expected", [
    ((2600,), "rows 2560-3071"),
    ((2600, 4100), "rows 2560-3071 and 4096-4607"),
    ((2600, 3100), "rows 2560-3583"),                     # adjacent chunks: one range
    ((10, 600, 1100, 2600, 4100), "rows 0-1535, 2560-3071 and 4096-4607"),
    ((10, 1100, 2600, 4100), "rows 0-511, 1024-1535, 2560-3071 and 1 more damaged range"),
], ids=["one chunk", "two chunks", "adjacent chunks", "merged ranges", "more than three ranges"])
def test_damage_names_the_rows_of_the_damaged_chunks(long_file, tmp_path, rows, expected):
    """A damaged chunk of /y holding rows 2560-3071 was reported as '/y rows 0-5000' (the
    whole block read at once): the message names the damaged chunks' rows, on one line."""
    path = tmp_path / "damaged.h5"
    path.write_bytes(long_file.read_bytes())
    for row in rows:
        _damage_chunk_at_row(path, "y", row)
    message = (f"{path} is damaged at /y {expected} (a data chunk fails its fletcher32 checksum); restore it "
               "from a copy, or start the run again with --overwrite")
    with hdf5.RunFile(path) as f:
        with pytest.raises(hdf5.DamagedFileError) as verified:
            f.verify()
        assert str(verified.value) == message
        with pytest.raises(hdf5.DamagedFileError) as read:   # what plot and load read
            f.y()
        assert str(read.value) == message
        np.testing.assert_array_equal(f.t()[:3], [0.0, 0.1, 0.2])   # the other datasets still read


def test_damage_found_by_a_reduction_names_the_chunk(long_file, tmp_path):
    path = tmp_path / "damaged.h5"
    path.write_bytes(long_file.read_bytes())
    _damage_chunk_at_row(path, "invariants/H", 2100)
    with hdf5.RunFile(path) as f, pytest.raises(hdf5.DamagedFileError, match=r" is damaged at /invariants/H rows "
                                                                          r"2048-4095 \(a data chunk fails"):
        f.invariant_drift()


# --- SWMR and the consistency flags ---------------------------------------------------------
def test_lookup3_matches_jenkins_and_hdf5():
    # Test vectors from lookup3.c (driver5).
    assert hdf5.lookup3(b"") == 0xDEADBEEF
    assert hdf5.lookup3(b"", 0xDEADBEEF) == 0xBD5B7DDE
    assert hdf5.lookup3(b"Four score and seven years ago") == 0x17770551
    assert hdf5.lookup3(b"Four score and seven years ago", 1) == 0xCD628161


def test_clearing_the_flags_of_a_file_left_open(tmp_path, kepler):
    """A writer that never closes (as after kill -9) leaves flags that block plain opening."""
    path = tmp_path / "open.h5"
    run = kepler_run(kepler, n_steps=100, every=1)
    writer = hdf5.RunWriter.create(path, run, config_text="a: 1\n")
    writer.append(run.advance(30))
    writer.save_state(run.state(), wall_time_s=1.0, kernel_time_s=0.5)
    # Copy the file as it is on disk now, as a killed writer would leave it.
    left = tmp_path / "left.h5"
    left.write_bytes(path.read_bytes())
    writer.close()
    assert hdf5.consistency_flags(left) != 0
    with pytest.raises(OSError):
        h5py.File(left, "r")
    with hdf5.RunFile(left) as f:             # SWMR reading works without repair
        assert f.swmr and f.status == "killed" and f.steps_done == 30 and f.n_samples == 31
        assert np.all(np.isfinite(f.y()))
    raw = left.read_bytes()[:48]
    assert struct.unpack("<I", raw[44:48])[0] == hdf5.lookup3(raw[:44])   # we read HDF5's checksum right
    hdf5.clear_consistency_flags(left)
    assert hdf5.consistency_flags(left) == 0
    with h5py.File(left, "r") as f:
        assert f["state/steps_done"][()] == 30


def test_progress_reporters(capsys):
    import io

    assert type(streaming.progress_for(quiet=True)) is streaming.NoProgress

    class Terminal(io.StringIO):
        def isatty(self):
            return True
    assert isinstance(streaming.progress_for(False, Terminal()), streaming.BarProgress)
    stream = io.StringIO()
    progress = streaming.progress_for(False, stream)
    assert isinstance(progress, streaming.LineProgress)
    progress.interval = 0.0
    progress.start(0, 1000, "EHBVM(6,3) kepler")
    progress.update(500, 50.0)
    progress.close()
    line = stream.getvalue().strip()
    assert "step 500/1000 (50.0%)" in line and "steps/s" in line and "ETA" in line and "\n" not in line

    bar_stream = Terminal()
    bar = streaming.BarProgress(bar_stream)
    bar.start(0, 1000, "run")
    bar.update(1000, 100.0)
    bar.close()
    assert "1.00k/1.00k" in bar_stream.getvalue() and "step/s" in bar_stream.getvalue()


def test_a_stop_right_after_the_probe_still_saves_the_state(tmp_path, kepler):
    path = tmp_path / "probe.h5"
    run = kepler_run(kepler, n_steps=400, every=6)
    writer = hdf5.RunWriter.create(path, run, config_text="a: 1\n")
    outcome = streaming.drive(run, writer, stop=StopAfter(1), first_chunk_steps=10)
    assert outcome.status == "interrupted" and outcome.steps_done == 10 and outcome.chunks == 1
    with hdf5.RunFile(path) as f:
        assert f.steps_done == 10 and f.attrs["steps_done"] == 10 and f.n_samples == 2


def test_inspect_of_a_file_being_written_does_not_advise_repair(tmp_path, kepler):
    """inspect said of a running run's file 'its writer did not close it; other HDF5 programs
    open it after elimfast repair', which refuses a file being written; its status said running."""
    from click.testing import CliRunner
    from elimfast_cli.main import cli

    path = tmp_path / "live.h5"
    run = kepler_run(kepler, n_steps=100, every=1)
    writer = hdf5.RunWriter.create(path, run, config_text="a: 1\n")
    writer.append(run.advance(30))
    writer.save_state(run.state(), wall_time_s=1.0, kernel_time_s=0.5)
    try:
        with hdf5.RunFile(path) as f:
            assert f.swmr and f.status == "running"
        result = CliRunner().invoke(cli, ["inspect", str(path)])
        assert "repair" not in result.stdout and "its writer is still running" in result.stdout, result.output
        assert CliRunner().invoke(cli, ["repair", str(path)]).exit_code == 2   # what the note no longer advises
    finally:
        writer.close()
