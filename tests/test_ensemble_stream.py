"""Ensemble sweeps streamed to their file (issue 13, item 3): block by block as blocks end, with
a done record, bit for bit the one-call result; a stopped or killed sweep keeps its stored
blocks and `--resume` completes the file as an uninterrupted run writes it. (The same on a
Dask cluster: tests/test_dask.py.)"""
import re
import signal
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

import elimfast
from elimfast import ensemble as ensembles
from elimfast import sweep as sweeps
from elimfast.io.ensemblefile import EnsembleFile
from elimfast.io.safety import OutputError
from elimfast.io.sweepfile import SweepWriter
from elimfast_cli.main import cli
from runfiles import assert_same_files, stopped_after_blocks

N_TRAJECTORIES = 40
BASE = {"problem": {"builtin": "henon_heiles"}, "method": {"name": "hbvm", "k": 6, "s": 3},
        "integration": {"h": 0.1, "t_end": 10}}
ARRAYS = ("y0",) + ensembles.ROW_ARRAYS


def ensemble_sweep(tmp_path, base=BASE, name="ensemble.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump({"base": base, "ensemble": {"n": N_TRAJECTORIES, "seed": 7, "spread": 0.01}}))
    return path


@pytest.fixture
def small_blocks(monkeypatch):
    """Local blocks of a few trajectories (the first of 4 on 2 threads, then ~1 ms of kernel each)."""
    monkeypatch.setattr(ensembles, "TARGET_BLOCK_SECONDS", 1e-3)
    monkeypatch.setattr(ensembles, "FIRST_BLOCK_ROWS_PER_THREAD", 2)


def assert_same_ensembles(a, b):
    for name in ARRAYS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)   # bit for bit
    assert list(a.invariant_errors) == list(b.invariant_errors)
    for name, values in a.invariant_errors.items():
        np.testing.assert_array_equal(values, b.invariant_errors[name], err_msg=name)
    assert (a.h, a.n_steps, a.conserve, a.max_iter, a.solver) == (b.h, b.n_steps, b.conserve, b.max_iter, b.solver)


def test_a_streamed_local_ensemble_equals_the_one_call_result_bit_for_bit(tmp_path, small_blocks):
    path = ensemble_sweep(tmp_path)
    _, states, in_memory = sweeps.run_ensemble_sweep(sweeps.load_sweep(path), threads=2)   # one kernel call
    messages = []
    outcome = sweeps.run_to_file(path, tmp_path / "out.h5", workers=2, on_message=messages.append)
    blocks = [m for m in messages if m.startswith("[")]
    assert len(blocks) >= 3 and blocks[-1].startswith(f"[{N_TRAJECTORIES}/{N_TRAJECTORIES}] trajectories")
    assert_same_ensembles(in_memory, outcome.ensemble)              # read from the file as used
    # A user trial's n = 10^8 filled 17.7 GB without a word, and its progress showed no end in sight:
    # the size is said before the file is created, and every block but the last says the time left.
    from elimfast.io.ensemblefile import bytes_on_disk
    run = sweeps.ensemble_run(sweeps.load_sweep(path), *sweeps.ensemble_states(sweeps.load_sweep(path)), 2)
    size = sweeps._size(bytes_on_disk(run, states))
    assert messages[0] == (f"{tmp_path / 'out.h5'}: {N_TRAJECTORIES} trajectories take {size} on disk, allocated as "
                           "the file is created"), messages
    assert all(re.fullmatch(r"\[\d+/40\] trajectories \d+-\d+: 0 failed, ETA 0:00:\d\d", line) for line in blocks[:-1])
    assert blocks[-1].endswith(": 0 failed")
    assert_same_ensembles(in_memory, elimfast.load(tmp_path / "out.h5"))
    assert outcome.table() == sweeps.SweepOutcome(spec=outcome.spec, path=None, ensemble=in_memory).table()
    with h5py.File(tmp_path / "out.h5", "r") as f:
        group = f["ensemble"]
        assert group.attrs["status"] == "complete" and group.attrs["failed"] == 0
        assert group["stored"][()].all() and group["y_final"].shape == (N_TRAJECTORIES, 4)
        # No attribute grows with the trajectories (a per-trajectory 'reasons' list was read whole by
        # every opening of the group)
        assert all(np.size(value) < N_TRAJECTORIES for value in group.attrs.values())
        np.testing.assert_array_equal(group["y0"][()], states)


def test_the_time_left_reads_as_a_runs_eta():
    rows = {"status": np.zeros(10, dtype=np.int64)}
    assert sweeps.block_line(rows, 0, 10, 10, 1000, rate=2.0) == "[10/1,000] trajectories 0-9: 0 failed, ETA 0:08:15"
    assert sweeps.block_line(rows, 990, 1000, 1000, 1000, rate=2.0) == "[1,000/1,000] trajectories 990-999: 0 failed"
    assert sweeps.block_line(rows, 0, 10, 10, 1000) == "[10/1,000] trajectories 0-9: 0 failed"    # no rate (Dask)
    assert sweeps.block_line(rows, 0, 10, 10, 10 ** 8, rate=2.0) == (
        "[10/100,000,000] trajectories 0-9: 0 failed, ETA 13888:53:15")


def test_failed_trajectories_are_stored_and_reported_as_in_memory(tmp_path, small_blocks):
    # Kepler near e = 0.6 with two fixed-point iterations a step and no halving: most fail.
    path = ensemble_sweep(tmp_path, base={"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}},
                                          "method": {"name": "gauss", "s": 3},
                                          "solver": {"method": "fixed_point", "max_iter": 2, "max_halvings": 0},
                                          "integration": {"h": 0.1, "t_end": 5}})
    in_memory = sweeps.run_to_file(path, workers=2)
    streamed = sweeps.run_to_file(path, tmp_path / "out.h5", workers=2)
    assert in_memory.ensemble.n_failed > 0
    assert streamed.failures() == in_memory.failures() and streamed.table() == in_memory.table()
    with h5py.File(tmp_path / "out.h5", "r") as f:
        assert f["ensemble"].attrs["failed"] == in_memory.ensemble.n_failed
        status = f["ensemble/status"]
        words = dict(zip(status.attrs["flag_values"].tolist(), status.attrs["flag_meanings"].split()))
        assert [words[code] for code in status[()].tolist()] == [r.replace(" ", "_") for r in in_memory.ensemble.reasons]
        assert "reasons" not in f["ensemble"].attrs
    inspected = CliRunner().invoke(cli, ["inspect", str(tmp_path / "out.h5")])
    assert f"failed       {in_memory.ensemble.n_failed} of the {N_TRAJECTORIES} stored (" in inspected.output


def test_a_streamed_ensemble_file_opens_in_xarray_on_named_dimensions(tmp_path):
    xr = pytest.importorskip("xarray")
    out = tmp_path / "out.h5"
    sweeps.run_to_file(ensemble_sweep(tmp_path), out, workers=1)
    with xr.open_datatree(out, engine="h5netcdf") as tree:
        ensemble = tree["ensemble"].ds
        assert dict(ensemble.sizes) == {"trajectory": N_TRAJECTORIES, "component": 4, "diagnostic": 6}
        assert ensemble["y_final"].dims == ("trajectory", "component")
        assert int(ensemble["stored"].sum()) == N_TRAJECTORIES and ensemble.attrs["status"] == "complete"
        assert list(ensemble["component"].values) == ["q1", "q2", "p1", "p2"]
        # the diagnostics are labelled, in the kernel's order (it was a bare dimension)
        assert list(ensemble["diagnostic"].values) == ["t", "h", "increment", "condition", "depth", "iterations"]
        assert ensemble["diagnostics"].dims == ("trajectory", "diagnostic")
        with elimfast.open_datatree(out) as ours:   # the same tree, built without h5netcdf's path searches
            xr.testing.assert_identical(ours, tree)


def test_an_ensemble_file_says_in_xarray_what_each_variable_is_its_status_codes_and_units(tmp_path):
    """Every dataset of /ensemble but `stored` came without long_name, units or the meaning of
    the integer status codes: in xarray a user saw `status (trajectory) int64` and nothing
    to decode it with. Run files label theirs; an ensemble file must too (CF flags for status)."""
    xr = pytest.importorskip("xarray")
    out = tmp_path / "out.h5"
    path = ensemble_sweep(tmp_path, base={"problem": {"builtin": "nbody"}, "method": {"name": "gauss", "s": 2},
                                          "integration": {"h": 10, "t_end": 20}})
    sweeps.run_to_file(path, out, workers=1)
    with xr.open_datatree(out, engine="h5netcdf") as tree:
        ensemble = tree["ensemble"].ds
        unlabelled = [name for name in ensemble.variables if not ensemble[name].attrs.get("long_name")
                      and name != "trajectory"]
        assert not unlabelled
        assert all(tree["ensemble/invariant_errors"].ds[name].attrs["long_name"].startswith(f"max |{name}(t)")
                   for name in tree["ensemble/invariant_errors"].ds.data_vars)
        status = ensemble["status"].attrs
        meanings = dict(zip(status["flag_values"].tolist(), status["flag_meanings"].split()))
        assert meanings[0] == "ok" and meanings[1] == "not_converged"
        assert {word.replace("_", " ") for word in meanings.values()} >= set(ensembles.STATUS_NAMES.values())
        assert "time_scale" not in meanings.values()   # adaptive steps' failure: an ensemble takes fixed steps
        assert ensemble["t_final"].attrs["units"] == "day" and ensemble.attrs["time_unit"] == "day"


def test_an_ensemble_result_as_xarray_holds_what_its_file_holds(tmp_path):
    """EnsembleResult.to_xarray (in memory, and of the result elimfast.load reads from the file)
    gives the file's /ensemble variables on the same named dimensions, with the same labels and
    CF status flags, and the invariant errors as one variable on (trajectory, invariant)."""
    xr = pytest.importorskip("xarray")
    out = tmp_path / "out.h5"
    path = ensemble_sweep(tmp_path, base={"problem": {"builtin": "kepler", "parameters": {"eccentricity": 0.6}},
                                          "method": {"name": "gauss", "s": 3},
                                          "solver": {"method": "fixed_point", "max_iter": 2, "max_halvings": 0},
                                          "integration": {"h": 0.1, "t_end": 5}})
    sweeps.run_to_file(path, out, workers=1)
    in_memory = sweeps.run_to_file(path, workers=1).ensemble
    assert in_memory.n_failed > 0 and not isinstance(in_memory, ensembles.LazyEnsembleResult)
    with xr.open_datatree(out, engine="h5netcdf") as tree:
        stored, errors = tree["ensemble"].ds, tree["ensemble/invariant_errors"].ds
        for result in (in_memory, elimfast.load(out)):
            ds = result.to_xarray()
            for name in ARRAYS:
                assert ds[name].dims == stored[name].dims, name
                np.testing.assert_array_equal(ds[name].values, stored[name].values, err_msg=name)
                assert ds[name].attrs["long_name"] == stored[name].attrs["long_name"], name
            assert ds["status"].attrs["flag_meanings"] == stored["status"].attrs["flag_meanings"]
            np.testing.assert_array_equal(ds["status"].attrs["flag_values"], stored["status"].attrs["flag_values"])
            assert list(ds["invariant"].values) == ["H", "angular_momentum", "lrl_x", "lrl_y"]
            for name in ds["invariant"].values:
                np.testing.assert_array_equal(ds["invariant_error"].sel(invariant=name).values, errors[name].values)
            assert ds.attrs["failed"] == in_memory.n_failed and ds.attrs["method"] == "GAUSS(3)"
            failed = int(np.flatnonzero(ds["status"].values != 0)[0])
            assert ds["diagnostics"].sel(trajectory=failed, diagnostic="iterations") == 2
        # imposing nothing: an empty list, as a grid run's file has (it was [''], a name no invariant has)
        assert list(stored.attrs["conserve"]) == [] and list(elimfast.load(out).conserve) == []


def test_the_diagnostic_labels_follow_the_kernel_indices():
    from elimfast.io.ensemblefile import DIAGNOSTIC_NAMES
    from elimfast.kernels import stepper
    indices = [stepper.DIAG_TIME, stepper.DIAG_STEP, stepper.DIAG_INCREMENT, stepper.DIAG_CONDITION,
               stepper.DIAG_DEPTH, stepper.DIAG_ITERATIONS]
    assert len(DIAGNOSTIC_NAMES) == stepper.N_DIAGNOSTICS
    assert [DIAGNOSTIC_NAMES[i] for i in indices] == ["t", "h", "increment", "condition", "depth", "iterations"]


def test_an_ensemble_shows_itself_in_one_line_without_reading_its_file(tmp_path):
    """A user trial's finding: ``elimfast.load(ENSEMBLE.h5)`` in a notebook printed the dataclass's
    repr, every array of every trajectory (25 kB for 100 trajectories), reading all of the file."""
    out = tmp_path / "out.h5"
    lazy = sweeps.run_to_file(ensemble_sweep(tmp_path), out, workers=1).ensemble
    read_before = set(vars(lazy))
    assert repr(lazy) == (f"<LazyEnsembleResult HBVM(6,3) on henon_heiles, {N_TRAJECTORIES} "
                          "trajectories of 100 steps, h = 0.1, 0 failed>")
    assert set(vars(lazy)) - read_before <= {"status"}   # no other column read for it
    loaded = elimfast.load(out)
    assert repr(loaded).startswith("<LazyEnsembleResult HBVM(6,3) on henon_heiles, ") and "\n" not in repr(loaded)
    _, _, in_memory = sweeps.run_ensemble_sweep(sweeps.load_sweep(ensemble_sweep(tmp_path)), threads=1)
    assert repr(in_memory) == repr(loaded).replace("LazyEnsembleResult", "EnsembleResult")


def test_a_local_ensemble_holds_one_block_at_a_time(tmp_path, small_blocks, monkeypatch):
    """The next block is computed only once the last is stored: never two blocks' rows at once."""
    events = []
    rows, store = ensembles.EnsembleRun.rows, SweepWriter.add_ensemble_rows
    monkeypatch.setattr(ensembles.EnsembleRun, "rows", lambda self, states: events.append("run") or rows(self, states))
    monkeypatch.setattr(SweepWriter, "add_ensemble_rows",
                        lambda writer, *block: events.append("store") or store(writer, *block))
    sweeps.run_to_file(ensemble_sweep(tmp_path), tmp_path / "out.h5", workers=2)
    assert events.count("run") >= 3
    assert events == ["run", "store"] * events.count("run")


def test_resume_completes_a_stopped_ensemble_file_bit_for_bit(tmp_path, small_blocks, monkeypatch):
    path = ensemble_sweep(tmp_path)
    sweeps.run_to_file(path, tmp_path / "full.h5", workers=2)
    half = stopped_after_blocks(path, tmp_path / "half.h5", 2, monkeypatch, workers=2)
    with EnsembleFile(half) as stored:
        assert stored.status == "incomplete" and 0 < stored.stored < N_TRAJECTORIES
        kept = stored.stored
        assert stored.stored_mask()[:kept].all() and not stored.stored_mask()[kept:].any()
    ran, rows = [], ensembles.EnsembleRun.rows
    monkeypatch.setattr(ensembles.EnsembleRun, "rows", lambda self, states: ran.append(len(states)) or rows(self, states))
    messages = []
    resumed = sweeps.run_to_file(path, half, resume=True, workers=1, on_message=messages.append)
    assert messages[0] == (f"resume: {kept} of {N_TRAJECTORIES} trajectories are stored in {half}; running the "
                           f"other {N_TRAJECTORIES - kept}")
    assert sum(ran) == N_TRAJECTORIES - kept                      # the stored blocks are not run again
    assert_same_files(tmp_path / "full.h5", half)
    assert resumed.failures() == []
    # A complete file resumes to itself, running nothing.
    ran.clear()
    sweeps.run_to_file(path, half, resume=True, workers=1)
    assert ran == []
    assert_same_files(tmp_path / "full.h5", half)


def test_a_killed_ensemble_sweep_leaves_a_readable_file_that_resume_completes(tmp_path):
    path = ensemble_sweep(tmp_path)
    full, out = tmp_path / "full.h5", tmp_path / "out.h5"
    sweeps.run_to_file(path, full, workers=1)
    # `elimfast sweep` whose second block never ends (as a long kernel call): killed there, with
    # the first block (8 trajectories on 1 thread) stored.
    code = textwrap.dedent(f"""
        import sys, time
        import elimfast.ensemble as ensembles
        from elimfast_cli.main import cli
        rows, calls = ensembles.EnsembleRun.rows, []
        def second_never_ends(self, states):
            calls.append(len(states))
            if len(calls) == 2:
                time.sleep(600)
            return rows(self, states)
        ensembles.EnsembleRun.rows = second_never_ends
        cli(["sweep", {str(path)!r}, "-o", {str(out)!r}, "--workers", "1"])
    """)
    process = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True)
    first = ensembles.FIRST_BLOCK_ROWS_PER_THREAD
    lines = []
    for line in process.stderr:
        lines.append(line)
        if line.startswith(f"[{first}/{N_TRAJECTORIES}] trajectories 0-{first - 1}: 0 failed"):
            process.send_signal(signal.SIGKILL)
            break
    process.wait(timeout=60)
    assert process.returncode == -signal.SIGKILL, lines

    with EnsembleFile(out) as stored, h5py.File(full, "r") as reference:
        assert stored.swmr and stored.status == "incomplete" and stored.stored == first
        np.testing.assert_array_equal(stored.column("y_final", 0, first), reference["ensemble/y_final"][:first])
        assert np.isnan(stored.column("y_final", first)).all()      # not written yet
    # A user trial: open_datatree showed the unwritten rows as status 0 ('ok') and the ensemble 'running'
    tree = elimfast.open_datatree(out)
    try:
        ensemble = tree["ensemble"]
        assert ensemble.attrs["status"] == "incomplete"
        status = ensemble["status"].values
        assert (status[:first] == 0).all() and (status[first:] == -1).all()
        meanings = dict(zip(ensemble["status"].attrs["flag_values"].tolist(),
                            ensemble["status"].attrs["flag_meanings"].split()))
        assert meanings[-1] == "not_stored" and meanings[0] == "ok"
    finally:
        tree.close()
    inspected = CliRunner().invoke(cli, ["inspect", str(out)])
    assert inspected.exit_code == 0, inspected.output
    assert f"trajectories {first} of {N_TRAJECTORIES} stored" in inspected.output
    assert f"incomplete (the sweep stopped or was killed before every block was stored; complete it with " \
           f"elimfast sweep {path} -o {out} --resume)" in inspected.output
    with pytest.raises(OutputError, match=f"{first} of {N_TRAJECTORIES} trajectories stored; complete it with "
                                          "elimfast sweep .* --resume"):
        elimfast.load(out)

    resumed = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(out), "--resume", "--workers", "2"])
    assert resumed.exit_code == 0, resumed.output
    assert f"resume: {first} of {N_TRAJECTORIES} trajectories are stored in {out}" in resumed.stderr
    assert "trajectories on 2 threads" in resumed.stderr   # the count, not 'all thread(s)'
    assert_same_files(full, out)
    assert "status       complete" in CliRunner().invoke(cli, ["inspect", str(out)]).output


def test_resume_refuses_an_ensemble_file_of_another_config_or_without_the_done_record(tmp_path, small_blocks,
                                                                                       monkeypatch):
    # The sweep file stays the same; the base config it names changes between the runs.
    path, base = tmp_path / "ensemble.yaml", tmp_path / "base.yaml"
    path.write_text(yaml.safe_dump({"base": "base.yaml", "ensemble": {"n": N_TRAJECTORIES, "seed": 7}}))
    base.write_text(yaml.safe_dump(BASE))
    out = stopped_after_blocks(path, tmp_path / "half.h5", 1, monkeypatch, workers=1)
    base.write_text(yaml.safe_dump({**BASE, "integration": {"h": 0.05, "t_end": 10}}))
    result = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(out), "--resume", "-q"])
    assert result.exit_code == 2
    assert result.output == (f"error: {out}: integration.h changed since its stored trajectories were run (the sweep "
                             "file or its base config was edited), and --resume keeps them as they are; undo the "
                             "edit, pass --overwrite to start again, or write the edited sweep to another file\n")

    base.write_text(yaml.safe_dump(BASE))
    with h5py.File(out, "a") as f:
        del f["ensemble/stored"]                      # as the files written whole, before the done record
    result = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(out), "--resume", "-q"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert result.output == (f"error: {out}: its ensemble was written by an elimfast without the record of stored "
                             "trajectories, so --resume cannot tell what is done; pass --overwrite to run it again\n")


@pytest.mark.usefixtures("allow_python")
def test_resume_refuses_an_ensemble_whose_python_problem_file_changed(tmp_path, small_blocks, monkeypatch):
    """A user trial: an ensemble of a python: problem killed part-way, the file's H and grad_H changed,
    --resume: trajectories 0-55 came from the old file, 56 on from the new, exit 0."""
    problem = tmp_path / "osc.py"
    source = ("Y0 = [1.0, 0.0]\n\ndef H(y, params):\n    return 0.5 * y[1] ** 2 + 0.5 * W * y[0] ** 2\n\n"
              "def grad_H(y, params, out):\n    out[0] = W * y[0]\n    out[1] = y[1]\n")
    problem.write_text("W = 1.0\n" + source)
    path = ensemble_sweep(tmp_path, base={"problem": {"python": "osc.py"}, "method": {"name": "hbvm", "k": 6, "s": 3},
                                          "integration": {"h": 0.1, "t_end": 10}})
    out = stopped_after_blocks(path, tmp_path / "half.h5", 1, monkeypatch, workers=1)
    with h5py.File(out, "r") as f:
        assert len(str(f["ensemble"].attrs["problem_file_sha256"])) == 64
    problem.write_text("W = 2.0\n" + source)
    with pytest.raises(OutputError, match=r"half\.h5: the problem file .*osc\.py has changed since it was stored "
                                          r"\(sha256 \w{16} then, \w{16} now\): its stored trajectories and the "
                                          r"others would come from two versions of the problem"):
        sweeps.run_to_file(path, out, resume=True, workers=1)
    problem.write_text("W = 1.0\n" + source)                      # undone: resumes
    assert sweeps.run_to_file(path, out, resume=True, workers=1).failures() == []


def test_resume_of_an_ensemble_takes_an_edit_of_comments_or_description_and_names_the_key_of_a_real_one(
        tmp_path, small_blocks, monkeypatch):
    """A user trial: a comment added to the top of an ensemble's sweep file, or a changed
    description:, and --resume refused the file ('the stored sweep text differs'). What decides
    the trajectories is the base config (with set: applied) and the ensemble: section; an edit of
    those is refused naming the key, anything else is taken and the file ends as an uninterrupted
    run of the edited sweep writes it."""
    path = ensemble_sweep(tmp_path)
    half = stopped_after_blocks(path, tmp_path / "half.h5", 1, monkeypatch, workers=1)
    text = path.read_text()
    path.write_text("# a comment\n" + text + "description: the same orbits, described\n")
    sweeps.run_to_file(path, tmp_path / "full.h5", workers=1)
    resumed = sweeps.run_to_file(path, half, resume=True, workers=1)
    assert resumed.failures() == []
    assert_same_files(tmp_path / "full.h5", half)

    half = stopped_after_blocks(path, tmp_path / "half2.h5", 1, monkeypatch, workers=1)
    for edit, key in ((("seed: 7", "seed: 8"), "ensemble.seed"), (("h: 0.1", "h: 0.05"), "integration.h"),
                      (("description: the same", "set: {solver: {max_iter: 77}}\ndescription: the same"), "solver.max_iter")):
        path.write_text(path.read_text().replace(*edit))
        result = CliRunner().invoke(cli, ["sweep", str(path), "-o", str(half), "--resume", "-q"])
        assert result.exit_code == 2 and "Traceback" not in result.output, result.output
        assert result.output.startswith(f"error: {half}: {key} changed since its stored trajectories were run"), \
            result.output
        assert "--overwrite" in result.output and result.output.count("\n") == 1
        path.write_text(path.read_text().replace(edit[1], edit[0]))


def test_an_ensemble_file_written_before_unimposed_steps_were_counted_reads_and_resumes(tmp_path, small_blocks,
                                                                                           monkeypatch):
    """/ensemble/unimposed_steps is new: a file without it reads it as -1 (not recorded) in
    load_ensemble, inspect says nothing of it, and --resume completes the file without it."""
    from elimfast.archive import load_ensemble
    path = ensemble_sweep(tmp_path)
    half = stopped_after_blocks(path, tmp_path / "half.h5", 2, monkeypatch, workers=2)
    with h5py.File(half, "r+") as f:
        del f["ensemble/unimposed_steps"]
    sweeps.run_to_file(path, half, resume=True, workers=1)
    with h5py.File(half, "r") as f:
        assert "unimposed_steps" not in f["ensemble"] and f["ensemble"].attrs["status"] == "complete"
    loaded = load_ensemble(half)
    assert loaded.unimposed_steps.tolist() == [-1] * N_TRAJECTORIES and loaded.ok.all()
    report = CliRunner().invoke(cli, ["inspect", str(half)])
    assert report.exit_code == 0 and "unimposed" not in report.output, report.output
