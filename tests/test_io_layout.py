"""The I/O split by concern and the defects of issue 10 around files: one run-group writer for
run and sweep files, sweep orchestration in the library, relative errors, the sweep tables,
the last good state of a failed run, ``elimfast repair`` and FILE:/runs/<label>."""
import csv
import io
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

import elimfast
from elimfast import methods, problems, streaming
from elimfast.integrate import Integration, relative_error
from elimfast.io import hdf5, layout, runfile, safety, sweepfile
from elimfast.sweep import format_table, run_to_file, table_rows
from elimfast_cli.main import cli

ROOT = Path(__file__).resolve().parents[1]
KEPLER = ROOT / "configs" / "kepler.yaml"
CONSERVE = ("angular_momentum", "lrl_y")
E = 0.9
APOCENTRE = [-(1 + E), 0.0, 0.0, -math.sqrt((1 - E) / (1 + E))]   # Kepler e = 0.9, far from the pericentre
# Fixed point with 25 iterations and no splitting: fails at step 11 as the orbit nears its pericentre.
FAILING = dict(h=0.3, n_steps=400, solver="fixed_point", max_iter=25, max_halvings=0, y0=APOCENTRE)


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def write_sweep(directory: Path, data: dict) -> Path:
    path = directory / "sweep.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


H_SWEEP = {"base": str(KEPLER), "set": {"integration": {"t_end": "2*pi"}, "output": {"every": 10}},
           "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30", "pi/60"]}],
           "error": {"exact": "initial"}, "order_axis": "h"}


@pytest.fixture(scope="module")
def h_sweep(tmp_path_factory):
    directory = tmp_path_factory.mktemp("h-sweep")
    out = directory / "sweep.h5"
    outcome = run_to_file(write_sweep(directory, H_SWEEP), out, workers=1)
    return out, outcome


# --- item 3: one owner per concern -----------------------------------------------------------------
def test_each_io_concern_is_its_own_module_and_only_io_imports_h5py():
    for module in (safety, layout, runfile, sweepfile):
        assert module.__doc__ and Path(module.__file__).stat().st_size < 64_000   # runfile.py: 62.6 kB
    assert hdf5.RunFile is runfile.RunFile and hdf5.SweepWriter is sweepfile.SweepWriter
    assert hdf5.check_output_path is safety.check_output_path
    importers = [p for p in (ROOT / "elimfast").rglob("*.py")
                 if "import h5py" in p.read_text() and p.parent.name != "io"]
    assert importers == []
    # the sweep loop lives in the library; the CLI keeps only the exit codes
    cli_text = (ROOT / "cli" / "main.py").read_text()
    assert "SweepWriter" not in cli_text and "run_sweep(" not in cli_text and "sweeps.run_to_file(" in cli_text


def test_run_file_and_sweep_runs_share_one_run_group_writer(tmp_path, h_sweep, kepler):
    """Both write the group through layout.create_run_group: the same members, dimensions and attributes."""
    path = tmp_path / "run.h5"
    run = Integration(kepler, methods.ehbvm(12, 3), math.pi / 30, 60, conserve=CONSERVE, store_every=10)
    streaming.run_to_file(run, path, config_text="a: 1\n", handle_signals=False)
    sweep_path, _ = h_sweep

    def shape_of(group):
        members = {}
        group.visititems(lambda name, obj: members.setdefault(
            name, (type(obj).__name__, tuple(d.label for d in obj.dims) if isinstance(obj, h5py.Dataset) else ())))
        return members

    with h5py.File(path, "r") as f, h5py.File(sweep_path, "r") as s:
        run_members = {k: v for k, v in shape_of(f).items() if not k.startswith("state")}
        sweep_members = shape_of(s["runs/pi|30"])
        assert run_members == sweep_members
        for key in ("problem", "method", "family", "h", "t0", "t_end", "n_steps", "output_every", "conserve"):
            assert key in s["runs/pi|30"].attrs, key
        assert s["runs/pi|30"].attrs["output_every"] == 10 and s["runs/pi|30/t"].shape == (7,)
        assert s["runs/pi|30/y"].fletcher32 and s["runs/pi|30/steps/substeps"].shape == (60,)


def test_sweep_run_to_file_is_the_library_entry_and_reports_failures_without_exiting(tmp_path):
    path = write_sweep(tmp_path, {**H_SWEEP, "grid": [{"name": "h", "key": "integration.h", "values": ["pi/30", "4*pi"]}],
                                  "set": {"integration": {"t_end": "8*pi"}, "output": {"every": 1},
                                          "solver": {"method": "fixed_point", "max_iter": 30, "max_halvings": 0}}})
    outcome = run_to_file(path, tmp_path / "s.h5", workers=1)
    assert outcome.outcomes[0].ok and not outcome.outcomes[1].ok
    assert outcome.failures() == ["1 of 2 runs failed (see the status column)"]
    with pytest.raises(safety.OutputError, match="already exists"):
        run_to_file(path, tmp_path / "s.h5", workers=1)


# --- item 6: relative errors -------------------------------------------------------------------------
def test_relative_error_is_relative_unless_the_initial_value_is_zero():
    assert relative_error(1e-20, -3.2e-8) == pytest.approx(1e-20 / 3.2e-8)
    assert relative_error(1e-16, 0.0) == 1e-16
    # a value that is a cancellation to round-off is measured against the size of its terms
    assert relative_error(1e-20, -3.2e-8, 1e-7) == pytest.approx(1e-20 / 3.2e-8)
    assert relative_error(1e-19, 8e-22, 2e-5) == pytest.approx(1e-19 / 2e-5)
    assert relative_error(1e-16, 0.0, 0.5) == pytest.approx(2e-16)
    assert relative_error(1e-16, 0.0, float("nan")) == 1e-16


def test_invariant_scales_are_the_size_of_the_terms():
    from elimfast.problems import kepler as kepler_problem, nbody
    p = kepler_problem(0.6)
    y = p.y0
    scales = p.invariant_scales(y)
    q1, q2, p1, p2 = y
    r = math.hypot(q1, q2)
    assert scales["H"] == pytest.approx(p1 ** 2 + p2 ** 2 + 1.0 / r, rel=1e-14)   # 2T + |V|
    assert scales["angular_momentum"] == pytest.approx(2 * (abs(q1 * p2) + abs(q2 * p1)), rel=1e-14)
    solar = nbody()
    sizes = solar.invariant_scales(solar.y0)
    values = solar.invariant_values(solar.y0)
    momenta = solar.y0.reshape(2, -1, 3)[1]
    assert sizes["linear_momentum_x"] == pytest.approx(momenta.shape[0] * np.max(np.abs(momenta)), rel=1e-14)
    assert p.invariant_scales(y)["lrl_y"] > 0.5     # A_y(y0) = 0 with every y_j dA_y/dy_j = 0
    assert abs(values["linear_momentum_x"]) < 1e-12 * sizes["linear_momentum_x"]   # a cancellation


def inspected_invariant_lines(run, path) -> dict[str, str]:
    """Run into path, inspect it, and return inspect's invariant rows by invariant name."""
    streaming.run_to_file(run, path, config_text="a: 1\n", handle_signals=False)
    result = invoke("inspect", path)
    assert result.exit_code == 0, result.output
    return {line.split()[0]: line for line in result.output.splitlines() if line.startswith("  ")}


def test_inspect_measures_a_cancelled_invariant_against_its_terms(tmp_path):
    """The solar system's linear momenta sum to ~1e-21 from terms of ~1e-5: their round-off
    errors read as relative errors of 1e1..1e3 against I(t0), of ~1e-14 against the terms."""
    from elimfast.problems import nbody
    solar = nbody()
    conserve = ("linear_momentum_x", "angular_momentum_z")
    path = tmp_path / "solar.h5"
    lines = inspected_invariant_lines(Integration(solar, methods.ghbvm(12, 3), 50.0, 200, conserve=conserve,
                                                  store_every=20), path)
    with h5py.File(path, "r") as f:
        values = f["invariants/linear_momentum_x"][()]
        scale = f["invariants/linear_momentum_x"].attrs["scale"]
    absolute = float(np.max(np.abs(values - values[0])))
    assert scale == pytest.approx(solar.invariant_scales(solar.y0)["linear_momentum_x"], rel=1e-15)
    assert f"relative {absolute / scale:.3e} to the size of its terms" in lines["linear_momentum_x"]
    assert absolute / scale < 1e-12
    assert "size of its terms" not in lines["angular_momentum_z"]


def test_inspect_shows_relative_errors_beside_absolute_ones(tmp_path, kepler):
    path = tmp_path / "run.h5"
    lines = inspected_invariant_lines(Integration(kepler, methods.ehbvm(12, 3), 0.1, 100, conserve=CONSERVE,
                                                  store_every=10), path)
    with h5py.File(path, "r") as f:
        H = f["invariants/H"][()]
        lrl_y = f["invariants/lrl_y"][()]
        lrl_y_scale = f["invariants/lrl_y"].attrs["scale"]
    absolute = float(np.max(np.abs(H - H[0])))
    assert f"{absolute:.3e}" in lines["H"] and f"relative {absolute / abs(H[0]):.3e}" in lines["H"]
    assert lrl_y[0] == 0.0 and lrl_y_scale > 0.1   # lrl_y(0) = 0: measured against its terms
    assert (f"relative {np.max(np.abs(lrl_y)) / lrl_y_scale:.3e} to the size of its terms (I(t0) = 0)"
            in lines["lrl_y"])
    assert "relative" in lines["lrl_x"]


def test_the_invariants_plot_has_a_relative_panel(tmp_path, kepler, monkeypatch):
    from elimfast_cli import plots
    drawn = {}
    original = plots._invariants

    def spy(run_file, axes, relative_axes=None):
        original(run_file, axes, relative_axes)
        drawn["absolute"] = [line.get_ydata() for line in axes.get_lines()]
        drawn["relative"] = [line.get_ydata() for line in relative_axes.get_lines()]
        drawn["labels"] = [line.get_label() for line in relative_axes.get_lines()]

    monkeypatch.setattr(plots, "_invariants", spy)
    path = tmp_path / "run.h5"
    run = Integration(kepler, methods.hbvm(6, 3), 0.1, 100, store_every=5)
    streaming.run_to_file(run, path, config_text="a: 1\n", handle_signals=False)
    result = invoke("plot", path, "--kind", "invariants", "-o", tmp_path / "inv.png")
    assert result.exit_code == 0, result.output
    with h5py.File(path, "r") as f:
        first = {name: f[f"invariants/{name}"][0] for name in f["invariants"].attrs["order"]}
        scales = {name: f[f"invariants/{name}"].attrs["scale"] for name in first}
    for name, absolute, relative, label in zip(first, drawn["absolute"], drawn["relative"], drawn["labels"]):
        scale = abs(first[name]) if first[name] != 0 else scales[name]
        np.testing.assert_allclose(relative, absolute / scale, rtol=1e-15, equal_nan=True)
        assert label.endswith("(to the size of its terms: I(t0) ~ 0)") == (first[name] == 0)


def test_sweep_tables_carry_relative_errors_full_precision_csv_and_escaped_pipes(h_sweep):
    _, outcome = h_sweep
    spec = outcome.spec
    header, rows = table_rows(spec, outcome.outcomes, None, "csv")
    table = list(csv.reader(io.StringIO(format_table(header, rows, "csv"))))
    assert table[0][:2] == ["h", "h_expression"] and "max rel err H" in table[0]
    first = dict(zip(table[0], table[1]))
    assert float(first["h"]) == math.pi / 30 and first["h_expression"] == "pi/30"   # a number, read back exactly
    run = outcome.outcomes[0]
    assert float(first["max err H"]) == run.invariant_errors["H"]                   # full precision
    assert float(first["error"]) == float(np.max(np.abs(run.y_final - run.y_initial)))
    assert float(first["max rel err H"]) == relative_error(run.invariant_errors["H"], run.initial_invariants["H"])
    markdown = format_table(*table_rows(spec, outcome.outcomes, None))
    header_line = markdown.splitlines()[0]
    assert "max \\|alpha\\|/\\|lambda\\|" in header_line
    # every line has as many unescaped cell separators as the header
    separators = [line.replace("\\|", "").count("|") for line in markdown.splitlines()]
    assert len(set(separators)) == 1


# --- item 10: the last good state of a failed run ------------------------------------------------------
def test_a_run_that_fails_between_samples_keeps_a_sample_of_its_last_good_state(tmp_path):
    kepler = problems.kepler(E)
    with pytest.raises(elimfast.ConvergenceError) as caught:
        elimfast.integrate(kepler, methods.gauss(3), store_every=1000, **FAILING)
    result = caught.value.result
    assert result.steps_done == 10 and result.steps_done % 1000 != 0
    assert result.t[-1] == result.t_final and np.array_equal(result.y[-1], result.y_final)
    assert result.invariants["H"][-1] == kepler.hamiltonian(result.y_final)
    # the run file holds it too, and a resume with other solver settings drops it again
    path = tmp_path / "failed.h5"
    settings = {k: v for k, v in FAILING.items() if k not in ("h", "n_steps", "y0")}
    run = Integration(kepler, methods.gauss(3), FAILING["h"], 40, store_every=7, y0=APOCENTRE, **settings)
    outcome = streaming.run_to_file(run, path, config_text="a: 1\n", handle_signals=False)
    assert outcome.status.startswith("failed: ")
    with hdf5.RunFile(path) as f:
        assert f.n_samples == 1 + 10 // 7 + 1 and f.t()[-1] == pytest.approx(3.0)
        np.testing.assert_array_equal(f.y()[-1], f.saved_state()["y"])
    resumed = Integration(kepler, methods.gauss(3), FAILING["h"], 40, store_every=7, y0=APOCENTRE,
                          solver="newton", max_halvings=4)
    writer, saved = hdf5.RunWriter.resume(path, restore=resumed.restore)
    writer.close()
    assert saved["n_samples"] == 1 + 10 // 7


def test_every_run_file_says_its_step_control_and_files_written_without_it_are_still_read(tmp_path, h_sweep):
    """The README lists the root attribute step_control (fixed, error, time_scale), but a plain
    fixed-step run file had none (only runs with output times or events wrote 'fixed'): a user
    trial's script reading attrs["step_control"] raised KeyError, and so did Result.to_xarray's
    attrs. Now every run file, sweep run and xarray view has it. A file written before, without
    it, is read as fixed: load, inspect, and --resume of a failed run, which must still drop the
    sample of its last good state (it told the two kinds of run apart by this attribute)."""
    path = tmp_path / "plain.h5"
    result = invoke("run", KEPLER, "-o", path, "-q", "--set", "integration.t_end=2")
    assert result.exit_code == 0, result.output
    with h5py.File(path, "r") as f:
        assert f.attrs["step_control"] == "fixed"
    assert elimfast.load(path).to_xarray().attrs["step_control"] == "fixed"
    fixed = elimfast.integrate(problems.kepler(0.6), methods.gauss(3), h=0.1, n_steps=10)
    assert fixed.to_xarray().attrs["step_control"] == "fixed"
    # n_steps: an adaptive run's file says 0 (not known in advance); so does its xarray view (a user trial)
    adaptive = tmp_path / "adaptive.h5"
    assert invoke("run", KEPLER, "-o", adaptive, "-q", "--set", "integration.h=null", "--set",
                  "integration.rtol=1e-8", "--set", "integration.t_end=2").exit_code == 0
    with h5py.File(adaptive, "r") as f:
        assert f.attrs["n_steps"] == 0 and f.attrs["step_control"] == "error"
    view = elimfast.load(adaptive).to_xarray().attrs
    assert view["n_steps"] == 0 and view["steps_done"] > 0
    sweep, _ = h_sweep
    with h5py.File(sweep, "r") as f:
        assert {f["runs"][label].attrs["step_control"] for label in f["runs"]} == {"fixed"}
    # a file written before: no attribute
    with h5py.File(path, "r+") as f:
        del f.attrs["step_control"]
    with hdf5.RunFile(path) as stored:
        assert not stored.adaptive and stored.step_sizes() is None
    assert elimfast.load(path).steps_done == 20
    assert invoke("inspect", path).exit_code == 0
    # a failed fixed-step run written before: --resume drops its off-grid sample as it did
    failed = tmp_path / "failed.h5"
    settings = {k: v for k, v in FAILING.items() if k not in ("h", "n_steps", "y0")}
    kepler = problems.kepler(E)
    run = Integration(kepler, methods.gauss(3), FAILING["h"], 40, store_every=7, y0=APOCENTRE, **settings)
    assert streaming.run_to_file(run, failed, config_text="a: 1\n", handle_signals=False).status.startswith("failed")
    with h5py.File(failed, "r+") as f:
        assert f.attrs["step_control"] == "fixed"
        del f.attrs["step_control"]
    resumed = Integration(kepler, methods.gauss(3), FAILING["h"], 40, store_every=7, y0=APOCENTRE,
                          solver="newton", max_halvings=4)
    writer, saved = hdf5.RunWriter.resume(failed, restore=resumed.restore)
    writer.close()
    assert saved["n_samples"] == 1 + 10 // 7


# --- item 10: FILE:/runs/<label> --------------------------------------------------------------------
def test_inspect_and_plot_open_a_run_of_a_sweep_file(h_sweep, tmp_path):
    path, _ = h_sweep
    result = invoke("inspect", f"{path}:/runs/pi/30")
    assert result.exit_code == 0, result.output
    assert f"{path}:/runs/pi/30" in result.output and "complete" in result.output
    assert "max |alpha|" in result.output and "relative" in result.output
    figure = tmp_path / "sweep_run.png"
    result = invoke("plot", f"{path}:/runs/pi|30", "--kind", "orbit", "-o", figure)
    assert result.exit_code == 0, result.output
    assert figure.stat().st_size > 1000
    missing = invoke("inspect", f"{path}:/runs/pi/7")
    assert missing.exit_code == 2 and "has no run 'pi/7'; its runs: pi/30, pi/60" in missing.output
    assert "Traceback" not in missing.output


# --- item 10: elimfast repair -------------------------------------------------------------------------
def killed_copy(tmp_path, kepler) -> Path:
    """A run file as kill -9 leaves it: copied while its writer holds it open in SWMR mode,
    with rows of a chunk appended after the last saved state."""
    path = tmp_path / "open.h5"
    run = Integration(kepler, methods.ehbvm(6, 3), 0.1, 100, conserve=CONSERVE)
    writer = hdf5.RunWriter.create(path, run, config_text="a: 1\n")
    writer.append(run.advance(30))
    writer.save_state(run.state(), wall_time_s=1.0, kernel_time_s=0.5)
    writer.append(run.advance(5))     # flushed below, but never saved in /state
    writer._file.flush()
    left = tmp_path / "killed.h5"
    left.write_bytes(path.read_bytes())
    writer.close()
    return left


def test_repair_makes_a_killed_file_readable_by_plain_h5py_and_xarray(tmp_path, kepler):
    xr = pytest.importorskip("xarray")
    left = killed_copy(tmp_path, kepler)
    with pytest.raises(OSError):
        h5py.File(left, "r")
    inspected = invoke("inspect", left)
    assert inspected.exit_code == 0 and f"elimfast repair {left}" in inspected.output
    result = invoke("repair", left)
    assert result.exit_code == 0, result.output
    assert "repaired" in result.output and "30 steps" in result.output
    assert hdf5.consistency_flags(left) == 0
    with h5py.File(left, "r") as f:
        assert f.attrs["status"] == "killed" and f.attrs["steps_done"] == 30
        assert f["t"].shape == (31,) and f["steps/iterations"].shape == (30,)   # the unsaved rows are gone
    with xr.open_dataset(left, engine="h5netcdf") as ds:
        assert ds.sizes["t"] == 31
    with hdf5.RunFile(left) as f:
        assert f.status == "killed" and f.steps_done == 30
    again = invoke("repair", left)
    assert again.exit_code == 0 and "nothing to repair" in again.output


def test_repair_refuses_a_file_that_is_still_being_written(tmp_path, kepler):
    path = tmp_path / "live.h5"
    run = Integration(kepler, methods.ehbvm(6, 3), 0.1, 100, conserve=CONSERVE)
    writer = hdf5.RunWriter.create(path, run, config_text="a: 1\n")
    try:
        flags = hdf5.consistency_flags(path)
        assert flags != 0
        result = invoke("repair", path)
        assert result.exit_code == 2 and "is being written by" in result.output
        assert "output file" not in result.output   # repair writes none (a user trial was offered another)
        assert hdf5.consistency_flags(path) == flags      # the live writer's file is left alone
    finally:
        writer.close()


def test_a_repaired_file_resumes_bit_for_bit(tmp_path, kepler):
    left = killed_copy(tmp_path, kepler)
    hdf5.repair(left)
    run = Integration(kepler, methods.ehbvm(6, 3), 0.1, 100, conserve=CONSERVE)
    outcome = streaming.run_to_file(run, left, config_text="a: 1\n", resume=True, handle_signals=False)
    assert outcome.status == "complete"
    whole = elimfast.integrate(kepler, methods.ehbvm(6, 3), h=0.1, n_steps=100, conserve=CONSERVE)
    with hdf5.RunFile(left) as f:
        np.testing.assert_array_equal(f.y(), whole.y)
        np.testing.assert_array_equal(f.saved_state()["y"], whole.y_final)


def test_repair_of_things_that_are_not_run_files_is_one_line(tmp_path):
    text = tmp_path / "notes.txt"
    text.write_text("hello")
    result = invoke("repair", text)
    assert result.exit_code == 2 and "not an HDF5 file" in result.output
    result = invoke("repair", tmp_path / "missing.h5")
    assert result.exit_code == 2 and "no such file" in result.output
