"""Run and sweep files open in xarray (h5netcdf engine), and elimfast.load / Result.to_xarray
give back what integrate returned (issue 10, items 4, 5 and 8's units)."""
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

import elimfast
from elimfast import methods, problems, streaming
from elimfast.integrate import Integration
from elimfast.sweep import run_to_file

xr = pytest.importorskip("xarray")
pytest.importorskip("h5netcdf")

ROOT = Path(__file__).resolve().parents[1]
KEPLER = ROOT / "configs" / "kepler.yaml"
CONSERVE = ("angular_momentum", "lrl_y")


def run_file(path, config=KEPLER, overrides=()):
    """A run file written the way `elimfast run` writes one (the stored config rebuilds the run)."""
    from elimfast.config import load_run
    spec = load_run(str(config), overrides=list(overrides))
    text = yaml.safe_dump(spec.resolved, sort_keys=False)
    outcome = streaming.run_to_file(Integration.from_spec(spec), path, config_text=text, t_end=spec.t_end,
                                    handle_signals=False)
    return spec, outcome


@pytest.fixture(scope="module")
def kepler_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("xarray") / "kepler.h5"
    spec, outcome = run_file(path, overrides=["integration.t_end=20"])
    assert outcome.status == "complete"
    return spec, path


@pytest.fixture(scope="module")
def sweep_file(tmp_path_factory):
    directory = tmp_path_factory.mktemp("sweep")
    sweep = directory / "sweep.yaml"
    sweep.write_text(yaml.safe_dump({
        "base": str(KEPLER), "set": {"integration": {"t_end": "2*pi"}, "output": {"every": 5}},
        "grid": [{"name": "method", "values": [
                      {"label": "GAUSS3", "set": {"method": {"name": "gauss", "s": 3}, "conserve": []}},
                      {"label": "GHBVM", "set": {"method": {"name": "ghbvm", "k": 6, "s": 3},
                                                 "conserve": ["angular_momentum"]}}]},
                 {"name": "h", "key": "integration.h", "values": ["2*pi/40", "2*pi/80"]}],
        "error": {"exact": "initial"}, "order_axis": "h"}))
    out = directory / "sweep.h5"
    outcome = run_to_file(sweep, out, workers=1, keep_results=True)
    assert not outcome.failures()
    return out, outcome


def test_a_run_file_opens_in_xarray_with_t_and_component_coordinates(kepler_file):
    spec, path = kepler_file
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert ds["y"].dims == ("t", "component")
        assert list(ds["component"].values) == ["q1", "q2", "p1", "p2"]
        assert ds["t"].dims == ("t",) and ds.sizes["t"] == 21 and ds["t"].values[-1] == pytest.approx(20.0)
        assert ds["t"].attrs["long_name"] == "time" and "long_name" in ds["y"].attrs
        assert ds.attrs["status"] == "complete" and ds.attrs["format"] == "elimfast-run"
        assert "coordinates" not in ds["y"].attrs     # CF reserves the name (issue 10, item 4)
    with xr.open_dataset(path, engine="h5netcdf", group="invariants") as inv:
        assert set(inv.data_vars) == {"H", "angular_momentum", "lrl_x", "lrl_y"}
        assert all(inv[name].dims == ("t",) for name in inv.data_vars)
        assert inv["H"].attrs["long_name"].startswith("Hamiltonian")


def test_a_run_file_opens_as_a_datatree_with_every_group_on_named_dimensions(kepler_file):
    _, path = kepler_file
    with xr.open_datatree(path, engine="h5netcdf") as tree:
        assert set(tree.children) == {"invariants", "steps", "method", "state"}
        invariants = tree["invariants"].to_dataset()
        assert invariants["H"].dims == ("t",) and invariants.sizes["t"] == 21
        np.testing.assert_array_equal(tree["invariants"]["t"].values, tree["t"].values)   # inherited coordinate
        steps = tree["steps"].to_dataset()
        assert steps["iterations"].dims == ("step",) and steps.sizes["step"] == 200
        assert steps["alpha"].dims == ("step", "invariant")
        assert list(steps["invariant"].values) == list(CONSERVE)
        assert tree["method"]["A"].dims == ("stage", "node")
        assert tree["state"]["coef"].dims == ("coefficient", "component")


def test_a_sweep_file_opens_as_a_datatree_with_one_node_per_run(sweep_file):
    path, outcome = sweep_file
    with xr.open_datatree(path, engine="h5netcdf") as tree:
        runs = tree["runs"]
        labels = {runs[name].attrs["label"] for name in runs.children}
        assert labels == {o.label for o in outcome.outcomes} and len(labels) == 4
        for name, node in runs.children.items():
            assert node["y"].dims == ("t", "component") and node.attrs["status"] == "complete"
            assert list(node["component"].values) == ["q1", "q2", "p1", "p2"]
            assert node["invariants"]["H"].dims == ("t",)
            assert node["steps"]["iterations"].dims == ("step",)
            assert node.attrs["n_steps"] == node["steps"].to_dataset().sizes["step"]
        ghbvm = runs["GHBVM|2*pi|40"]
        assert ghbvm["steps"]["lambda"].dims == ("step", "invariant")
        assert list(ghbvm["steps"]["invariant"].values) == ["H", "angular_momentum"]


def test_load_gives_back_the_result_integrate_returns(kepler_file, kepler):
    spec, path = kepler_file
    loaded = elimfast.load(path)
    direct = elimfast.integrate(kepler, methods.ehbvm(12, 3), h=0.1, t_end=20.0, conserve=CONSERVE, store_every=10)
    assert isinstance(loaded, elimfast.Result) and loaded.method.name == direct.method.name
    assert loaded.problem.name == "kepler" and loaded.conserve == direct.conserve
    for name in ("t", "y", "iterations", "substeps", "alpha", "y_final"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(direct, name), err_msg=name)
        assert getattr(loaded, name).dtype == getattr(direct, name).dtype, name   # iterations came back int32
    assert loaded.lam is None and loaded.t_final == direct.t_final and loaded.status == "complete"
    for name, values in direct.invariants.items():
        np.testing.assert_array_equal(loaded.invariants[name], values)
    assert (loaded.steps_done, loaded.n_steps, loaded.h) == (200, 200, 0.1)
    assert len(repr(loaded)) < 300       # a short summary, not every array


def test_load_of_a_sweep_run_by_label_and_by_path(sweep_file):
    path, outcome = sweep_file
    stored = next(o for o in outcome.outcomes if o.label == "GHBVM/2*pi/80")
    for loaded in (elimfast.load(path, run="GHBVM/2*pi/80"), elimfast.load(f"{path}:/runs/GHBVM/2*pi/80")):
        np.testing.assert_array_equal(loaded.y, stored.result.y)
        np.testing.assert_array_equal(loaded.lam, stored.result.lam)
        np.testing.assert_array_equal(loaded.y_final, stored.y_final)
        assert loaded.method.name == "GHBVM(6,3)" and loaded.alpha is None
        assert loaded.h == pytest.approx(2 * math.pi / 80) and loaded.status == "complete"
    with pytest.raises(elimfast.ElimfastError, match="has no run 'nope'; its runs: GAUSS3/2"):
        elimfast.load(path, run="nope")


def test_result_to_xarray_matches_the_file_layout(kepler):
    result = elimfast.integrate(kepler, methods.ehbvm(6, 3), h=0.1, n_steps=50, conserve=CONSERVE, store_every=5)
    ds = result.to_xarray()
    assert ds["y"].dims == ("t", "component") and ds.sizes == {"t": 11, "component": 4, "step": 50, "invariant": 2}
    np.testing.assert_array_equal(ds["y"].values, result.y)
    np.testing.assert_array_equal(ds["lrl_y"].values, result.invariants["lrl_y"])
    np.testing.assert_array_equal(ds["alpha"].values, result.alpha)
    assert list(ds["invariant"].values) == list(CONSERVE) and ds.attrs["status"] == "complete"


def test_result_to_xarray_labels_the_invariants_as_the_file_does_and_writes_to_netcdf(kepler_file, tmp_path):
    """Each invariant carries the file's attributes: scale (the size of its terms at t0, which
    relative errors divide by; it was missing), value_at_t0 and imposed, as 0/1 so that the
    Dataset can be written with to_netcdf (netCDF has no boolean attributes)."""
    _, path = kepler_file
    ds = elimfast.load(path).to_xarray()
    with xr.open_datatree(path, engine="h5netcdf") as tree:
        stored = tree["invariants"].ds
        for name in ("H", "angular_momentum", "lrl_x", "lrl_y"):
            assert ds[name].attrs["scale"] == stored[name].attrs["scale"] > 0, name
            assert ds[name].attrs["value_at_t0"] == stored[name].attrs["value_at_t0"], name
            assert ds[name].attrs["imposed"] == int(bool(stored[name].attrs["imposed"])), name
    assert ds["angular_momentum"].attrs["imposed"] == 1 and ds["lrl_x"].attrs["imposed"] == 0
    ds.to_netcdf(tmp_path / "copy.nc", engine="h5netcdf")
    with xr.open_dataset(tmp_path / "copy.nc", engine="h5netcdf") as copy:
        assert copy["H"].attrs["scale"] == ds["H"].attrs["scale"]


def test_the_solar_system_states_its_units_in_the_file_and_in_xarray(tmp_path):
    problem = problems.nbody()
    run = Integration(problem, methods.gauss(2), 10.0, 4)
    path = tmp_path / "solar.h5"
    assert streaming.run_to_file(run, path, config_text="a: 1\n", handle_signals=False).status == "complete"
    with h5py.File(path, "r") as f:
        assert (f.attrs["length_unit"], f.attrs["time_unit"], f.attrs["mass_unit"]) == ("AU", "day", "solar mass")
        assert f["t"].attrs["units"] == "day"
    with xr.open_dataset(path, engine="h5netcdf", decode_timedelta=False) as ds:
        assert ds["t"].attrs["units"] == "day" and ds["t"].dtype == np.float64
    result = elimfast.integrate(problem, methods.gauss(2), h=10.0, n_steps=2)
    assert result.to_xarray().attrs["length_unit"] == "AU"


def test_files_of_format_2_are_still_read(tmp_path, kepler):
    """Format 2 kept the component names in an attribute of /y named 'coordinates'."""
    path = tmp_path / "old.h5"
    run = Integration(kepler, methods.ehbvm(6, 3), 0.1, 20, conserve=CONSERVE)
    streaming.run_to_file(run, path, config_text="a: 1\n", handle_signals=False)
    with h5py.File(path, "r+") as f:
        names = [n.decode() for n in f["component"][()]]
        f["y"].dims[1].detach_scale(f["component"])
        del f["component"]
        f["y"].attrs["coordinates"] = names
        f.attrs["format_version"] = 2
    from elimfast.io.hdf5 import RunFile
    with RunFile(path) as stored:
        assert stored.coordinate_names == ["q1", "q2", "p1", "p2"]


def test_an_adaptive_result_in_xarray_has_its_steps_events_and_step_control():
    """Result.to_xarray of an adaptive run carries what its run file holds in /steps and
    /events: every step's end time and size, and each event's times and states."""
    p = problems.kepler(0.9)
    r = elimfast.integrate(p, methods.ehbvm(8, 4), t_end=4 * math.pi, rtol=1e-12, conserve=CONSERVE,
                           events={"pericentre": {"expression": "q1*p1 + q2*p2", "direction": 1}})
    ds = r.to_xarray()
    assert ds.sizes["step"] == r.steps_done
    np.testing.assert_array_equal(ds["step_t"].values, r.step_t)
    np.testing.assert_array_equal(ds["step_h"].values, r.step_h)
    assert ds["step_t"].values[-1] == r.t_final
    np.testing.assert_array_equal(ds["pericentre_t"].values, r.events["pericentre"].t)
    np.testing.assert_array_equal(ds["pericentre_y"].values, r.events["pericentre"].y)
    assert ds["pericentre_y"].dims == ("pericentre_occurrence", "component")
    assert ds.sizes["pericentre_occurrence"] == 2
    assert ds.attrs["step_control"] == "error" and ds.attrs["rtol"] == 1e-12
    assert ds.attrs["stats_rejected_steps"] == r.stats["rejected_steps"] and ds.attrs["stats_steps"] == r.steps_done
    assert "iterations" not in ds.attrs   # named as in a run file, apart from the variable iterations
    # a fixed-step result has none of these, and says step_control = fixed, as its run file does
    fixed = elimfast.integrate(p, methods.ehbvm(8, 4), 0.01, n_steps=10, conserve=CONSERVE).to_xarray()
    assert "step_h" not in fixed and "rtol" not in fixed.attrs and fixed.attrs["step_control"] == "fixed"


def test_events_in_xarray_carry_their_definition_and_where_they_stopped_being_finite(tmp_path):
    """A user trial: Result.to_xarray() dropped each event's expression, direction, terminal
    and not_finite_from, which the run file's /events/<name> has. Now <name>_t carries them,
    from integrate's Result and from load(FILE)'s alike."""
    events = {"pericentre": {"expression": "q1*p1 + q2*p2", "direction": 1},
              "right": {"expression": "sqrt(q1) - 0.2", "direction": -1, "terminal": False}}
    r = elimfast.integrate(problems.kepler(0.9), methods.ehbvm(8, 4), t_end=4 * math.pi, rtol=1e-10,
                           conserve=CONSERVE, events=events)
    assert "right" in r.events_not_finite   # q1 < 0 on the far side of the orbit
    config = tmp_path / "events.yaml"
    config.write_text("problem: {builtin: kepler, parameters: {eccentricity: 0.9}}\n"
                      "method: {name: ehbvm, k: 8, s: 4}\nconserve: [angular_momentum, lrl_y]\n"
                      "integration: {rtol: 1e-10, t_end: 4*pi}\n"
                      "events: {pericentre: {expression: 'q1*p1 + q2*p2', direction: 1},\n"
                      "         right: {expression: 'sqrt(q1) - 0.2', direction: -1}}\n")
    path = tmp_path / "events.h5"
    assert run_file(path, config=config)[1].status == "complete"
    for ds in (r.to_xarray(), elimfast.load(path).to_xarray()):
        pericentre, right = ds["pericentre_t"].attrs, ds["right_t"].attrs
        assert (pericentre["expression"], pericentre["direction"], pericentre["terminal"]) == ("q1*p1 + q2*p2", 1, 0)
        assert "not_finite_from" not in pericentre
        assert (right["expression"], right["direction"], right["terminal"]) == ("sqrt(q1) - 0.2", -1, 0)
        assert right["not_finite_from"] == r.events_not_finite["right"] > 0
    with h5py.File(path, "r") as f:
        assert f["events/right"].attrs["not_finite_from"] == r.events_not_finite["right"]


def test_an_adaptive_run_file_loads_with_the_attributes_of_the_result_it_stores(tmp_path):
    """elimfast.load(FILE).to_xarray() of an adaptive run has the attributes integrate's Result
    gives: n_steps is the steps taken (the file's root says 0: no count was set in advance)."""
    path = tmp_path / "adaptive.h5"
    spec, outcome = run_file(path, ROOT / "configs" / "kepler_adaptive.yaml", ["integration.t_end=4*pi"])
    assert outcome.status == "complete"
    stored = elimfast.load(path)
    direct = elimfast.integrate(spec.problem, spec.method, t_end=spec.t_end, rtol=spec.step_control.rtol,
                                atol=spec.step_control.atol, conserve=spec.conserve, store_every=spec.output_every,
                                events={"pericentre": {"expression": "q1*p1 + q2*p2", "direction": 1}})
    assert stored.n_steps == stored.steps_done == direct.n_steps == direct.steps_done
    mine, theirs = stored.to_xarray().attrs, direct.to_xarray().attrs
    assert {key: str(mine[key]) for key in theirs} == {key: str(value) for key, value in theirs.items()}



def test_an_event_group_says_what_it_found(tmp_path):
    """/events/<name> carries its definition: expression, direction, terminal (before, only the
    root's config text had it)."""
    config = tmp_path / "solar.yaml"
    config.write_text("problem: {builtin: nbody}\nmethod: {name: hbvm, s: 3}\n"
                      "integration: {rtol: 1e-8, atol: 1e-12, t_end: 5000}\n"
                      "events: {jupiter: {expression: 'jupiter_y - sun_y', direction: 0}}\n")
    path = tmp_path / "solar.h5"
    assert run_file(path, config=config)[1].status == "complete"
    with h5py.File(path, "r") as f:
        definition = dict(f["events/jupiter"].attrs)
        assert (definition["expression"], int(definition["direction"]), bool(definition["terminal"])) == \
            ("jupiter_y - sun_y", 0, False)
        assert f["events/jupiter/t"].shape[0] >= 1
    with xr.open_dataset(path, engine="h5netcdf", group="events/jupiter") as ds:
        assert ds.attrs["expression"] == "jupiter_y - sun_y"


def test_step_and_event_times_in_xarray_have_the_time_unit_of_the_run_file():
    """Result.to_xarray gives step_t, step_h and the event times the unit a run file gives
    /steps/t, /steps/h and /events/<name>/t (they had none; only t had 'day')."""
    r = elimfast.integrate(problems.nbody(), methods.hbvm(6, 3), t_end=5000.0, rtol=1e-8, atol=1e-12,
                           events={"jupiter": {"expression": "jupiter_y - sun_y"}})
    ds = r.to_xarray()
    assert ds["jupiter_t"].size >= 1
    assert {ds[name].attrs.get("units") for name in ("t", "step_t", "step_h", "jupiter_t")} == {"day"}


def test_an_event_whose_xarray_names_are_taken_is_refused():
    """Result.to_xarray names an event's times <name>_t: an event 'step' silently replaced the
    steps' end times step_t with its own (on step_occurrence)."""
    from elimfast.errors import ParameterError
    with pytest.raises(ParameterError, match=r"^events\.step .*step_t, the name of other data of the run"):
        elimfast.integrate(problems.kepler(0.9), methods.ehbvm(8, 4), t_end=1.0, rtol=1e-10,
                           events={"step": {"expression": "q2"}})
    r = elimfast.integrate(problems.kepler(0.9), methods.ehbvm(8, 4), t_end=1.0, rtol=1e-10,
                           events={"steps": {"expression": "q2"}})
    assert r.to_xarray()["step_t"].dims == ("step",)
    # an invariant x_occurrence became a stray coordinate on t beside the event x's dimension (a user trial)
    from elimfast.problems import problem_from_expressions
    oscillator = problem_from_expressions({"q": ["q"], "p": ["p"]}, "p**2/2 + q**2/2", initial={"q": 1, "p": 0},
                                          invariants={"x_occurrence": "p**2 + q**2"})
    with pytest.raises(ParameterError, match=r"^events\.x .*x_occurrence, the name of other data of the run"):
        elimfast.integrate(oscillator, methods.hbvm(4, 2), t_end=1.0, rtol=1e-10, events={"x": "q"})


def test_an_event_named_as_a_coordinate_every_group_inherits_is_refused(tmp_path, kepler_file):
    """/events/<name> is a group below the run's root, whose coordinates t and component xarray's
    DataTree passes down: an event named t or component ran, and then every DataTree reader
    (h5netcdf, netCDF4, elimfast.open_datatree) failed on the file with 'parent events already
    contains a variable named t'. Refused as an event 'step' is, in Python and in configs."""
    from elimfast.config import load_run
    from elimfast.errors import ElimfastError, ParameterError
    from elimfast.io.layout import INHERITED_COORDINATES
    with xr.open_datatree(kepler_file[1], engine="h5netcdf") as tree:   # the names the rule keeps free
        assert set(INHERITED_COORDINATES) == set(tree.coords)
    for name in INHERITED_COORDINATES:
        with pytest.raises(ParameterError, match=rf"^events\.{name} .*give the event another name"):
            elimfast.integrate(problems.kepler(0.9), methods.ehbvm(8, 4), t_end=1.0, rtol=1e-10,
                               events={name: {"expression": "q2"}})
        config = tmp_path / f"{name}.yaml"
        config.write_text("problem: {builtin: kepler}\nmethod: {name: ehbvm, k: 8, s: 4}\n"
                          f"integration: {{rtol: 1e-10, t_end: 1}}\nevents: {{{name}: q2}}\n")
        with pytest.raises(ElimfastError, match=rf"{name}.yaml:4: events\.{name}: .*give the event another name"):
            load_run(str(config))


GHBVM_80 = "GHBVM/2*pi/80"        # a run of the sweep_file fixture, and its group (sweepfile.sweep_group_name)
GHBVM_80_GROUP = "runs/GHBVM|2*pi|80"


def test_elimfast_open_datatree_gives_the_tree_h5netcdf_gives(kepler_file, sweep_file):
    """elimfast.open_datatree reads a file into the nodes, variables, dimensions, coordinates and
    attributes that xr.open_datatree(path, engine="h5netcdf") gives: a run file, a sweep file,
    one run of it (by label or FILE:/runs/<label>), and one group through xr.open_dataset."""
    from elimfast.io.xarray_tree import ElimfastBackend
    for path in (kepler_file[1], sweep_file[0]):
        with xr.open_datatree(path, engine="h5netcdf") as theirs, elimfast.open_datatree(path) as ours:
            xr.testing.assert_identical(ours, theirs)
    path = sweep_file[0]
    with xr.open_datatree(path, engine="h5netcdf", group=GHBVM_80_GROUP) as theirs:
        for ours in (elimfast.open_datatree(path, run=GHBVM_80), elimfast.open_datatree(f"{path}:/runs/{GHBVM_80}")):
            with ours:
                xr.testing.assert_identical(ours, theirs)
    group = f"{GHBVM_80_GROUP}/steps"
    with xr.open_dataset(path, engine="h5netcdf", group=group) as theirs, \
            xr.open_dataset(path, engine=ElimfastBackend, group=group) as ours:
        xr.testing.assert_identical(ours, theirs)
        assert ours["lambda"].dims == ("step", "invariant")


def test_open_datatree_keeps_each_group_s_own_step_and_event_times(tmp_path):
    """An adaptive run's /steps/t and /events/<name>/t are variables of their groups named as the
    root's coordinate t. Through xarray's default index pass they came back as the root's sample
    times, silently (a user trial: the pericentre times were lost); then, with that pass off,
    tree["steps"]["t"] still gave the inherited t (the next user trial), and with chunks xarray
    replaced them. The tree names them as Result.to_xarray does (step_t, <event>_t), and every
    group's own variables are compared here, read as users read them, with and without chunks."""
    config = tmp_path / "adaptive.yaml"
    config.write_text("problem: {builtin: kepler, parameters: {eccentricity: 0.9}}\n"
                      "conserve: [angular_momentum]\nmethod: {name: ehbvm, s: 4}\n"
                      "integration: {rtol: 1e-10, t_end: 4*pi}\noutput: {every: 10}\n"
                      "events: {pericentre: {expression: 'q1*p1 + q2*p2', direction: 1}}\n")
    path = tmp_path / "adaptive.h5"
    assert run_file(path, config=config)[1].status == "complete"
    with h5py.File(path, "r") as f:
        stored = {name: f[name][()] for name in ("steps/t", "events/pericentre/t")}
    own = {"steps": "step_t", "events/pericentre": "pericentre_t"}   # Result.to_xarray's names
    for options in ({}, {"chunks": {}}):
        with elimfast.open_datatree(path, **options) as ours, xr.open_datatree(path, engine="h5netcdf") as theirs:
            for node, name in own.items():
                mine = ours[node].to_dataset(inherit=False)
                renamed = {"t": own[node], "h": "step_h"} if node == "steps" else {"t": own[node]}
                expected = {renamed.get(v, v) for v in theirs[node].to_dataset(inherit=False).variables}
                assert set(mine.variables) == expected, node
                # as users index the tree (README), where the inherited t hid the group's own (a user trial)
                np.testing.assert_array_equal(ours[node][name].values, stored[f"{node}/t"])
                assert ours[node][name].attrs["stored_as"] == "t"
                np.testing.assert_array_equal(ours[node]["t"].values, ours["t"].values)   # the inherited t
        assert len(stored["events/pericentre/t"]) == 2
        # the step sizes under Result.to_xarray's name too (they were 'h' here, 'step_h' there)
        with elimfast.open_datatree(path, **options) as ours, h5py.File(path, "r") as f:
            np.testing.assert_array_equal(ours["steps"]["step_h"].values, f["steps/h"][()])
            assert "h" not in ours["steps"].to_dataset(inherit=False).variables


def test_open_datatree_never_asks_hdf5_for_the_path_of_a_dimension_scale(sweep_file, monkeypatch):
    """What keeps elimfast.open_datatree linear in the runs of a sweep file: h5netcdf names the
    dimension of each axis by the HDF5 path of the scale its DIMENSION_LIST refers to (h5py
    .name, H5Iget_name), and HDF5 finds the path of an object reached by reference by visiting
    the file's links from the root until it meets the object, past the runs stored before it:
    O(runs) per lookup, O(runs^2) per file (bench/sweep_xarray.py). open_datatree knows every
    scale by object identity as it walks the groups, and asks HDF5 for no path at all."""
    path, _ = sweep_file
    asked = []
    get_name = h5py.h5i.get_name

    def counting(obj, *args):
        asked.append(obj)
        return get_name(obj, *args)

    monkeypatch.setattr(h5py.h5i, "get_name", counting)
    with elimfast.open_datatree(path) as tree:
        assert len(tree["runs"].children) == 4 and tree[f"{GHBVM_80_GROUP}/steps"]["lambda"].dims == \
            ("step", "invariant")
    assert asked == []
    with xr.open_datatree(path, engine="h5netcdf"):   # the search this avoids: one per axis of each variable
        pass
    assert len(asked) >= 4 * 6      # each run: y (2 axes), H and 3 invariants, iterations, substeps, lambda (2)


def test_a_sweep_run_in_xarray_holds_the_data_elimfast_load_gives(sweep_file):
    """A run of a sweep file, opened with xr.open_datatree (h5netcdf) or elimfast.open_datatree,
    holds the arrays elimfast.load(path, run=label) returns, on its named dimensions."""
    path, _ = sweep_file
    loaded = elimfast.load(path, run=GHBVM_80)
    with xr.open_datatree(path, engine="h5netcdf") as theirs, elimfast.open_datatree(path) as ours:
        for tree in (theirs, ours):
            run = tree[GHBVM_80_GROUP]
            assert run.attrs["label"] == GHBVM_80 and run["y"].dims == ("t", "component")
            np.testing.assert_array_equal(run["t"].values, loaded.t)
            np.testing.assert_array_equal(run["y"].values, loaded.y)
            assert list(run["component"].values) == list(loaded.problem.coordinate_names)
            for name, values in loaded.invariants.items():
                np.testing.assert_array_equal(run["invariants"][name].values, values, err_msg=name)
            np.testing.assert_array_equal(run["steps"]["iterations"].values, loaded.iterations)
            np.testing.assert_array_equal(run["steps"]["substeps"].values, loaded.substeps)
            np.testing.assert_array_equal(run["steps"]["lambda"].values, loaded.lam)


def test_open_datatree_takes_group_refuses_engine_and_runs_may_be_numbers(tmp_path, sweep_file):
    """xr.open_datatree's group option raised 'got multiple values for keyword argument', and an
    engine likewise; a run named by a number (a sweep over h: run=0.1) raised AttributeError
    ('float' object has no attribute 'replace') in open_datatree and elimfast.load alike."""
    path, _ = sweep_file
    with elimfast.open_datatree(path, group=GHBVM_80_GROUP) as by_group, \
            elimfast.open_datatree(path, run=GHBVM_80) as by_run:
        xr.testing.assert_identical(by_group, by_run)
    with pytest.raises(TypeError, match="its own backend"):
        elimfast.open_datatree(path, engine="h5netcdf")
    with pytest.raises(TypeError, match="not both"):
        elimfast.open_datatree(path, run=GHBVM_80, group=GHBVM_80_GROUP)
    sweep = tmp_path / "h.yaml"
    sweep.write_text(yaml.safe_dump({"base": str(KEPLER), "set": {"integration": {"t_end": 1}},
                                     "grid": [{"name": "h", "key": "integration.h", "values": [0.1, 0.05]}]}))
    out = tmp_path / "h.h5"
    run_to_file(sweep, out, workers=1)
    assert elimfast.load(out, run=0.1).h == 0.1
    with elimfast.open_datatree(out, run=0.05) as tree:
        assert tree.attrs["label"] == "0.05"


def test_open_datatree_of_groups_of_different_lengths_says_why(tmp_path, kepler_file):
    """Groups of different lengths: xarray's 'group /invariants is not aligned with its parents'
    came through raw (a user trial, on a run still being written, which is now read as a
    snapshot). A finished run's file like that was changed or damaged: one more value of every
    invariant than samples."""
    import shutil
    path = tmp_path / "growing.h5"
    shutil.copy(kepler_file[1], path)
    with h5py.File(path, "a") as f:
        for dataset in f["invariants"].values():
            dataset.resize((dataset.shape[0] + 1,))
    with pytest.raises(elimfast.ElimfastError, match="its groups have different lengths .*elimfast.load"):
        elimfast.open_datatree(path)


def test_open_datatree_of_a_run_still_being_written_gives_its_saved_rows_as_load_does(tmp_path):
    """A user trial: elimfast.open_datatree on a run in progress in another process raised
    'its groups have different lengths' (at random: a group read while the writer extended it),
    where elimfast.load, inspect and plot read it. Now it reads as they do, in SWMR mode, the
    rows the saved state counts in every group, whatever was appended since: simulated with a
    writer that appended a chunk it has not saved yet and an /invariants extended ahead of /t
    (as a reader between two of the writer's appends sees it), and with the file a kill -9 left."""
    from elimfast.config import load_run
    from elimfast.io import hdf5
    path = tmp_path / "live.h5"
    spec = load_run(str(KEPLER), overrides=["integration.t_end=10", "output.every=1"])
    run = Integration.from_spec(spec)
    writer = hdf5.RunWriter.create(path, run, config_text=yaml.safe_dump(spec.resolved, sort_keys=False))
    try:
        writer.append(run.advance(30))
        writer.save_state(run.state(), wall_time_s=1.0, kernel_time_s=0.5)
        writer.append(run.advance(5))   # flushed, not saved
        for dataset in writer._file["invariants"].values():
            dataset.resize((dataset.shape[0] + 3,))
        writer._file.flush()
        killed = tmp_path / "killed.h5"
        killed.write_bytes(path.read_bytes())
        for name in (path, killed):
            loaded = elimfast.load(name)
            with elimfast.open_datatree(name) as tree:
                assert tree.sizes["t"] == loaded.t.size == 31 and tree["steps"].sizes["step"] == 30
                assert tree["invariants"].sizes["t"] == 31
                np.testing.assert_array_equal(tree["y"].values, loaded.y)
                np.testing.assert_array_equal(tree["invariants"]["H"].values, loaded.invariants["H"])
                np.testing.assert_array_equal(tree["steps"]["iterations"].values, loaded.iterations)
                assert tree.attrs["steps_done"] == 30 and tree.attrs["status"] in ("running", "killed")
        writer.append(run.advance(5))   # the tree is a snapshot: opened again, it has the newly saved rows
        writer.save_state(run.state(), wall_time_s=2.0, kernel_time_s=1.0)
        with elimfast.open_datatree(path) as tree:
            assert tree["steps"].sizes["step"] == 40 and tree.attrs["steps_done"] == 40
    finally:
        writer.close()


def test_open_datatree_says_in_one_line_what_it_cannot_open(tmp_path, sweep_file, kepler):
    path, _ = sweep_file
    with pytest.raises(elimfast.ElimfastError, match=r"has no run 'nope'; its runs: GAUSS3/2"):
        elimfast.open_datatree(path, run="nope")
    with pytest.raises(elimfast.ElimfastError, match=r"missing\.h5: no such file$"):
        elimfast.open_datatree(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("not HDF5\n")
    with pytest.raises(elimfast.ElimfastError, match=r"text\.h5: not an HDF5 file"):
        elimfast.open_datatree(tmp_path / "text.h5")
    old = tmp_path / "old.h5"    # format 2: no /component scale (test_files_of_format_2_are_still_read)
    streaming.run_to_file(Integration(kepler, methods.ehbvm(6, 3), 0.1, 20, conserve=CONSERVE), old,
                          config_text="a: 1\n", handle_signals=False)
    with h5py.File(old, "r+") as f:
        f["y"].dims[1].detach_scale(f["component"])
        del f["component"]
        f.attrs["format_version"] = 2
    with pytest.raises(elimfast.ElimfastError, match=r"old\.h5:/y: an axis without a dimension scale; read the "
                                                     r"run with elimfast\.load$"):
        elimfast.open_datatree(old)


# --- netCDF compatibility of the attributes (a user trial) -------------------------------------------
ADAPTIVE_WITH_EVENT = ("problem: {builtin: kepler, parameters: {eccentricity: 0.9}}\n"
                       "conserve: [angular_momentum]\nmethod: {name: ehbvm, s: 4}\n"
                       "integration: {rtol: 1e-10, t_end: 4*pi, verify: true}\noutput: {every: 10}\n"
                       "events: {pericentre: {expression: 'q1*p1 + q2*p2', direction: 1, terminal: false}}\n")
# The yes/no attributes of a run file, by the object that carries them (FLAG: the flag's name).
FLAGS = {"invariants/angular_momentum": "imposed", "invariants/lrl_x": "imposed", "/": "verify",
         "events/pericentre": "terminal"}


def invoke_cli(*args):
    from click.testing import CliRunner
    from elimfast_cli.main import cli
    result = CliRunner().invoke(cli, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


@pytest.fixture(scope="module")
def cli_files(tmp_path_factory):
    """A fixed-step run and an adaptive run (step doubling) with an event, written by `elimfast run`."""
    directory = tmp_path_factory.mktemp("cli_files")
    config = directory / "adaptive.yaml"
    config.write_text(ADAPTIVE_WITH_EVENT)
    fixed, adaptive = directory / "fixed.h5", directory / "adaptive.h5"
    invoke_cli("run", KEPLER, "-o", fixed, "--set", "integration.t_end=2")
    invoke_cli("run", config, "-o", adaptive)
    return fixed, adaptive


def netcdf_engines() -> list[str]:
    try:
        import netCDF4  # noqa: F401
    except ImportError:
        return ["h5netcdf"]
    return ["h5netcdf", "netcdf4"]


def test_run_files_go_through_xarray_to_netcdf_and_back(cli_files, tmp_path):
    """netCDF has no boolean type: the HDF5 booleans imposed, verify and terminal made to_netcdf
    of every run file fail ('boolean dtypes are not a supported NetCDF feature'; netCDF4: 'illegal
    data type for attribute'), and netCDF-C dropped them. They are int8 0/1 now, and a tree
    written back reads back with them."""
    fixed, adaptive = cli_files
    for path in (fixed, adaptive):
        with h5py.File(path, "r") as f:
            flags = {where: f[where].attrs[name] for where, name in FLAGS.items()
                     if where in f and name in f[where].attrs}
        for engine in netcdf_engines():
            copy = tmp_path / f"{path.stem}_{engine}.nc"
            with xr.open_datatree(path, engine="h5netcdf") as tree:
                tree.to_netcdf(copy, engine=engine)
            with xr.open_datatree(copy, engine=engine) as back:   # netCDF-C dropped the booleans
                assert back["invariants"]["angular_momentum"].attrs["imposed"] == 1
                assert back["invariants"]["lrl_x"].attrs["imposed"] == 0
                if path == adaptive:
                    assert back.attrs["verify"] == 1 and back["events/pericentre"].attrs["terminal"] == 0
            with xr.open_dataset(path, engine="h5netcdf") as ds:
                ds.to_netcdf(tmp_path / f"{path.stem}_{engine}_root.nc", engine=engine)
            with elimfast.open_datatree(path) as ours:
                ours.to_netcdf(tmp_path / f"{path.stem}_{engine}_ours.nc", engine=engine)
        assert all(np.asarray(value).dtype == np.int8 for value in flags.values()), flags
    assert set(flags) == set(FLAGS)   # the adaptive file has every one of them


def test_readers_take_the_boolean_flags_of_files_written_before(cli_files, sweep_file, tmp_path):
    """Files written before the flags were int8 hold HDF5 booleans: elimfast's readers (load,
    inspect, open_datatree, a sweep's list of stored runs) read them as they read the new ones."""
    import shutil

    from elimfast.io.runfile import RunFile
    from elimfast.io.sweepfile import grid_sweep_runs
    _, adaptive = cli_files
    old = tmp_path / "old.h5"
    shutil.copy(adaptive, old)
    with h5py.File(old, "r+") as f:
        for where, name in FLAGS.items():
            f[where].attrs[name] = bool(f[where].attrs[name])
        assert f.attrs["verify"].dtype == np.bool_
    with RunFile(old) as before, RunFile(adaptive) as now:
        assert before.imposed == now.imposed == {"H": False, "angular_momentum": True, "lrl_x": False,
                                                  "lrl_y": False}
    assert elimfast.load(old).conserve == ("angular_momentum",)
    assert "step doubling" in invoke_cli("inspect", adaptive)
    assert invoke_cli("inspect", old).replace(str(old), "FILE") == invoke_cli("inspect", adaptive).replace(
        str(adaptive), "FILE")
    with elimfast.open_datatree(old) as tree:
        assert bool(tree["invariants"]["angular_momentum"].attrs["imposed"])
    old_sweep = tmp_path / "old_sweep.h5"
    shutil.copy(sweep_file[0], old_sweep)
    with h5py.File(old_sweep, "r+") as f:
        for run in f["runs"].values():
            run.attrs["stored"] = bool(run.attrs["stored"])
    listed = grid_sweep_runs(old_sweep)[1]
    assert listed == grid_sweep_runs(sweep_file[0])[1] and all(stored for _, stored, _ in listed)


def test_open_datatree_of_a_file_with_an_event_named_t_says_why_in_one_line(cli_files, tmp_path):
    """A file written before such names were refused: a raw KeyError traceback before."""
    import shutil

    from elimfast.io.safety import OutputError
    path = tmp_path / "event_t.h5"
    shutil.copy(cli_files[1], path)
    with h5py.File(path, "r+") as f:
        f.move("events/pericentre", "events/t")
        f["events"].attrs["order"] = ["t"]
    with pytest.raises(OutputError, match=r"event_t.h5: its group events/t .*an event named 't'.*; read the run with elimfast.load$"):
        elimfast.open_datatree(path)
    np.testing.assert_array_equal(elimfast.load(path).events["t"].t, elimfast.load(cli_files[1]).events["pericentre"].t)


def test_open_datatree_with_chunks_gives_the_hdf5_chunks(tmp_path):
    """chunks={} asks a backend for its preferred chunks, as xarray's own backends give them: the
    HDF5 chunks (h5netcdf does). elimfast.open_datatree gave one dask chunk per variable."""
    pytest.importorskip("dask")
    path = tmp_path / "long.h5"
    run_file(path, overrides=["integration.t_end=120", "output.every=1"])   # 1201 samples, 1200 steps
    with h5py.File(path, "r") as f:
        on_disk = {}
        f.visititems(lambda name, item: on_disk.update({name: (item.shape, item.chunks)})
                     if isinstance(item, h5py.Dataset) and item.chunks and item.size else None)
    assert on_disk["y"][0][0] > on_disk["y"][1][0]   # more rows than one chunk holds
    compared = 0
    with elimfast.open_datatree(path, chunks={}) as tree:
        for name, (shape, chunks) in on_disk.items():
            node, _, variable = name.rpartition("/")
            dataset = tree[node or "/"].to_dataset(inherit=False)
            if variable not in dataset.variables or variable in dataset.indexes:
                continue   # a dimension without values, or an index (xarray loads those)
            expected = tuple(tuple([size] * (length // size) + ([length % size] if length % size else []))
                             for length, size in zip(shape, chunks))
            assert dataset[variable].chunks == expected, name
            compared += 1
    assert compared >= 5   # y, H and the invariants, iterations, substeps, alpha


def test_an_adaptive_run_file_has_the_stats_of_its_result_as_root_attributes(tmp_path):
    """A run file had only /state/counters, an unlabelled vector, where a sweep run has stats_*
    attributes and Result.to_xarray the counts: a plain h5py or xarray reader found no rejected
    steps, side steps or grad H evaluations. The root carries stats_<name> = Result.stats now."""
    from elimfast.adaptive import counted_stats
    from elimfast.io.layout import STATS_PREFIX
    path = tmp_path / "adaptive.h5"
    config = tmp_path / "adaptive.yaml"
    config.write_text(ADAPTIVE_WITH_EVENT)
    spec, outcome = run_file(path, config=config)
    assert outcome.status == "complete"
    direct = elimfast.integrate(spec.problem, spec.method, t_end=spec.t_end, rtol=spec.step_control.rtol,
                                verify=True, conserve=spec.conserve, store_every=spec.output_every,
                                events={"pericentre": {"expression": "q1*p1 + q2*p2", "direction": 1}})
    with h5py.File(path, "r") as f:
        stored = {key[len(STATS_PREFIX):]: int(value) for key, value in f.attrs.items()
                  if key.startswith(STATS_PREFIX)}
        counted = counted_stats(f["state/counters"][()])
    assert stored == direct.stats and stored["grad_H_evaluations"] > 0
    assert {key: stored[key] for key in counted} == counted
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        assert ds.attrs["stats_rejected_steps"] == direct.stats["rejected_steps"]
    # a resumed run drops them until it ends: a file killed meanwhile claims no stats of an earlier end
    from elimfast.io.runfile import RunWriter
    writer, _ = RunWriter.resume(path)
    writer.close()   # as a killed writer leaves it: status running
    with h5py.File(path, "r", swmr=True) as f:
        assert f.attrs["status"] == "running" and not any(key.startswith(STATS_PREFIX) for key in f.attrs)


def test_open_datatree_on_another_hdf5_file_says_it_is_not_elimfast_s(tmp_path):
    """A user trial: a plain HDF5 file got 'has no dimension scales (files of elimfast format 1 and 2
    have none); read the run with elimfast.load', which then refused it too."""
    from elimfast.io.safety import NotAnElimfastFile
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["x"] = np.arange(3.0)
    with pytest.raises(NotAnElimfastFile) as info:
        elimfast.open_datatree(path)
    assert str(info.value) == (f"{path}: not an elimfast run or sweep file (no 'elimfast-run' format attribute); "
                               "open another HDF5 file with xr.open_datatree(path, engine='h5netcdf')")


def test_a_netcdf_copy_of_a_run_or_sweep_file_is_named_as_such_not_damaged(kepler_file, sweep_file, tmp_path):
    """A user trial: open_datatree(...).to_netcdf(copy), then inspect or load of the copy, said it was
    'damaged at its root attributes' and to start the run again with --overwrite. xarray writes each
    scalar attribute as an array of one; open_datatree still reads the copy."""
    from click.testing import CliRunner
    from elimfast_cli.main import cli
    run_copy, sweep_copy = tmp_path / "run.nc", tmp_path / "sweep.nc"
    for source, copy in ((kepler_file[1], run_copy), (sweep_file[0], sweep_copy)):
        with elimfast.open_datatree(source) as tree:
            tree.to_netcdf(copy)
    said = ("a copy written by xarray (to_netcdf) or another netCDF writer, whose attributes are arrays, not an "
            "elimfast file: read it with elimfast.open_datatree or xarray, or give elimfast the original")
    for copy, run in ((run_copy, None), (sweep_copy, "GHBVM/2*pi/80")):
        with pytest.raises(elimfast.ElimfastError) as refused:
            elimfast.load(copy, run=run)
        assert str(refused.value) == f"{copy}: {said}"
        result = CliRunner().invoke(cli, ["inspect", str(copy)])
        assert result.exit_code == 2 and result.output == f"error: {copy}: {said}\n"
    with elimfast.open_datatree(run_copy) as tree:
        assert tree["steps"]["iterations"].size > 0


def test_a_tree_left_open_does_not_freeze_later_trees_of_a_live_run(tmp_path):
    """A user trial: with one open_datatree of a run still being written left open (as the README's
    `tree = elimfast.open_datatree(...)`), every later open_datatree of the file in that process gave
    the same snapshot (steps_done 179,934 three times over 2 s while the run reached 600,000); load
    saw the new rows. A later tree now sees them too; the first keeps its own snapshot."""
    import subprocess
    import sys
    import time

    from runfiles import steps_on_disk
    path = tmp_path / "live.h5"
    run = subprocess.Popen([str(Path(sys.executable).with_name("elimfast")), "run", str(ROOT / "configs" / "kepler.yaml"),
                            "-o", str(path), "--quiet", "--set", "integration.t_end=200000"],
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 600   # a cold Numba cache compiles the kernels first
        while steps_on_disk(path) < 1000:
            assert run.poll() is None and time.monotonic() < deadline
            time.sleep(0.01)
        first = elimfast.open_datatree(path)
        seen = int(first.attrs["steps_done"])
        while steps_on_disk(path) < seen + 20000:
            assert run.poll() is None, "the run ended first: make it longer"
            time.sleep(0.01)
        later = elimfast.open_datatree(path)
        assert int(later.attrs["steps_done"]) >= seen + 20000 and later["steps"].sizes["step"] >= seen + 20000
        assert int(first.attrs["steps_done"]) == seen == first["steps"].sizes["step"]
        later.close()
        first.close()
    finally:
        run.kill()
        run.wait()
