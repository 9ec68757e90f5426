"""An elimfast file as an xarray DataTree, in time linear in its groups: ``open_datatree``.

Why not only ``xr.open_datatree(path, engine="h5netcdf")``: h5netcdf names the dimensions
of a variable by dereferencing the dimension scale of each axis (the DIMENSION_LIST
attribute) and asking HDF5 for the path of that scale (``Variable._lookup_dimensions``,
h5py's ``.name``). An object reached through a reference has no path of its own, so HDF5
(H5Iget_name -> H5G_get_name_by_addr) finds one by visiting the file's links from the root,
in their native order, until it meets the object: each lookup costs the objects visited
before it. A sweep file holds one run group per run, each with its own scales (t, step,
...: their lengths differ), so opening it costs O(runs^2): 2.0 s for 30 Kepler runs, 13 s
for 100, 118 s for 300, of which about 97 s in those lookups (18 per run at 18 ms each;
bench/results/sweep_xarray.md).
No layout with a dimension scale per run avoids it (HDF5 searches every lookup from the
root), and scales shared between runs would pad each run to the longest.

Here every dimension scale is known by its object identity (file number and address:
h5py's ObjectID equality) as the walk meets it, in the variable's group or an ancestor,
as netCDF-C matches them: a variable's dimension names are a dereference and a dictionary
lookup per axis, and the walk never asks HDF5 for the path of a dereferenced object.

The tree is the one h5netcdf gives: the same nodes, variables, dimensions, coordinates and
attributes (without netCDF's own: CLASS, NAME, REFERENCE_LIST, DIMENSION_LIST, ...),
decoded by xarray (the decode_* options of ``xr.open_datatree``, which also takes ``chunks``
and ``cache``). Numeric data are read when used (``.load()`` reads them into memory);
string variables (the component names) are read at once. A run file still being written (or
left by a killed run) is read as ``elimfast.load`` reads it, in SWMR mode, as a snapshot of the
rows its saved state counts (``_snapshot``): every group then has the same length however far
the run has gone on since. Encodings: only the HDF5 chunks, as
``preferred_chunks`` (what ``chunks={}`` uses); compression is not filled in. Files of elimfast's format 1 and 2 have no dimension
scales: ``elimfast.load`` reads them.
"""
from __future__ import annotations

import os
import re
import uuid
from pathlib import Path

import h5py
import numpy as np

from . import ensemblefile
from .layout import DIMENSION_ONLY, FORMAT, STATUS_RUNNING, SWEEP_FORMAT, _plain, split_run_path
from .safety import READ_ERRORS, NotAnElimfastFile, OutputError, _damaged

try:
    import xarray as xr
    from xarray.backends import BackendArray, BackendEntrypoint, CachingFileManager
    from xarray.core import indexing   # BackendArray's indexing helpers (xarray's guide to writing a backend)
except ImportError:
    raise ImportError("elimfast.open_datatree needs xarray: pip install xarray") from None

# Attributes that the HDF5 dimension-scale API and netCDF-4 keep for themselves (h5netcdf hides the same).
HIDDEN_ATTRIBUTES = frozenset({"REFERENCE_LIST", "CLASS", "DIMENSION_LIST", "NAME", "_Netcdf4Dimid",
                               "_Netcdf4Coordinates", "_nc3_strict", "_NCProperties"})
# The NAME of a scale that is a netCDF dimension and no variable (netCDF-C's text; layout.DIMENSION_ONLY).
DIMENSION_ONLY_PREFIX = DIMENSION_ONLY.split("%")[0].rstrip(".").encode()
DECODERS = ("mask_and_scale", "decode_times", "concat_characters", "decode_coords", "use_cftime",
            "decode_timedelta")


def open_datatree(path, run: str | None = None, **options):
    """The file ``path`` as an xarray DataTree: every group a node, as
    ``xr.open_datatree(path, engine="h5netcdf")`` gives it, but in time linear in the groups
    (a sweep file of 300 runs: 3.9 s instead of 118 s; the module doc says why).

    ``run``: the label of one run of a sweep file (or ``path`` given as
    ``"sweep.h5:/runs/<label>"``): the tree of that run's group alone, as a run file's.
    ``options``: those of ``xr.open_datatree`` (``group``, ``chunks``, ``cache``, ``decode_times``, ...).
    One difference from h5netcdf's tree: a group's own variable named as a coordinate its
    ancestors pass down is renamed ``<group>_<name>``: the step times /steps/t of adaptive
    runs are ``tree["steps"]["step_t"]``, an event's times ``tree["events/<name>"]["<name>_t"]``
    (Result.to_xarray's names; the step sizes /steps/h are ``step_h`` likewise). The inherited ``t``
    hid them: ``tree["steps"]["t"]`` gave the root's sample times, silently (with h5netcdf it still does).
    The data are read when used; ``tree.close()`` closes the file. A run still being written
    gives the rows its last saved state counts, in every group (the root attributes status and
    steps_done say how far, as ``elimfast inspect`` does); open it again for more. Raises
    OutputError (an ElimfastError) for a file or run that cannot be read.
    """
    if "engine" in options:
        raise TypeError("elimfast.open_datatree reads with its own backend: leave out engine, or call "
                        "xr.open_datatree(path, engine=...) for another one")
    file_path, run = split_run_path(path, run)
    group = options.pop("group", None)   # a group of the file, as xr.open_datatree takes it
    if run is not None and group is not None:
        raise TypeError("give run (a run of a sweep file) or group (any group of the file), not both")
    if run is not None:
        from .runfile import _sweep_run_group
        with _open_file(file_path) as f:
            group = _sweep_run_group(file_path, f, run).name
    # The backend's datasets carry their indexes already. xarray's default pass that creates them
    # (map_over_datasets over each node's dataset with the inherited coordinates) replaced a
    # group's own variable named as an inherited coordinate by that coordinate: /steps/t and
    # /events/<name>/t of adaptive runs came back as the root's sample times, silently.
    options.setdefault("create_default_indexes", False)
    return xr.open_datatree(os.fspath(file_path), engine=ElimfastBackend, group=group, **options)


def _open_file(path) -> h5py.File:
    """The file opened for reading as RunFile opens it (a killed run's file in SWMR mode), or
    OutputError in one line (no file, not HDF5, a sweep whose writer was killed)."""
    from .runfile import _killed_sweep
    from .safety import DamagedFileError, _open
    try:
        return _open(path)
    except DamagedFileError:
        message = _killed_sweep(Path(path))
        if message is None:
            raise
        raise OutputError(message) from None


def _snapshot(path, f) -> tuple[dict, dict]:
    """({dataset path: rows}, {root attribute: value}) that make a run file still being written
    (status 'running': also a killed run's) one consistent snapshot, as RunFile reads it: the
    rows its saved state counts (samples, steps, each event's occurrences), no more than the
    shortest dataset of each as this handle sees it, with the state's steps_done and status
    ('running' or 'killed'). ({}, {}) for any other file: its datasets end where its run did.
    A user trial: a live run's tree failed at random ("groups ... not aligned": /invariants
    read longer than /t), where load, inspect and plot read it."""
    if _plain(f.attrs.get("format")) != FORMAT or _plain(f.attrs.get("status")) != STATUS_RUNNING:
        return {}, {}
    from .runfile import RunFile, _event_names, _sample_datasets, _step_datasets
    with RunFile(path) as stored:   # reads the saved state (CRC-checked) in its own handle
        saved, status = stored.saved_state(), stored.status
    try:
        dimensions = [(list(_sample_datasets(f)), saved["n_samples"]), (list(_step_datasets(f)), saved["steps_done"])]
        counts = saved.get("event_counts")
        for name, count in zip(_event_names(f), () if counts is None else counts):
            dimensions.append(([f["events"][name]["t"], f["events"][name]["y"]], count))
        rows = {}
        for datasets, count in dimensions:
            if f.swmr_mode:   # a handle of this process opened earlier shares HDF5's cached extents: update them
                for dataset in datasets:
                    dataset.refresh()
            # rows below the saved count were flushed before the state that counts them: final
            n = min([int(count)] + [dataset.shape[0] for dataset in datasets])
            rows.update({dataset.name: n for dataset in datasets})
    except READ_ERRORS as err:
        raise _damaged(path, "the groups of the saved state", err) from None
    return rows, {"status": status, "steps_done": rows.get("/steps/iterations", int(saved["steps_done"]))}


def _attribute(value):
    """An attribute as h5netcdf and xarray give it: strings as str, arrays of strings as
    lists, a one-element array as its element."""
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, np.ndarray) and value.ndim:
        if value.dtype.kind in "OS":
            value = [item.decode("utf-8", "replace") if isinstance(item, bytes) else item for item in value.flat]
        if len(value) == 1:
            return value[0]
    return value


def _is_scale(attrs, names) -> bool:
    """Whether the dataset of ``attrs`` (its attribute names: ``names``) is a dimension scale."""
    return "CLASS" in names and bytes(attrs["CLASS"]) == b"DIMENSION_SCALE"


class _Walk:
    """Reads the groups of one open file into {path relative to the first group: xr.Dataset}.
    Every object is reached by its path, which the walk carries (it never asks HDF5 for one)."""

    def __init__(self, f, manager, path, decoders: dict, drop_variables):
        self.f, self.manager, self.path = f, manager, path
        self.decoders = decoders
        self.rows, self.root_attributes = _snapshot(path, f)
        if isinstance(drop_variables, str):
            drop_variables = [drop_variables]
        self.drop = set(drop_variables or ())

    def scales_above(self, location: str) -> dict:
        """{ObjectID: dimension name} of the dimension scales in the ancestors of the group at
        ``location`` (an absolute path): the dimensions its variables may use."""
        scales: dict = {}
        names = [name for name in location.split("/") if name]
        for depth in range(len(names)):
            self._members(self.f["/" + "/".join(names[:depth])], scales)
        return scales

    @staticmethod
    def _members(group, scales: dict) -> tuple[dict, list]:
        """The datasets {name: Dataset} and the subgroups [name] of ``group``; its dimension
        scales are added to ``scales``, keyed by object identity (file number and address)."""
        datasets, groups = {}, []
        for name in group:
            member = group.get(name)
            if isinstance(member, h5py.Dataset):
                datasets[name] = member
                attrs = member.attrs
                if _is_scale(attrs, attrs):
                    scales[member.id] = name
            elif isinstance(member, h5py.Group):
                groups.append(name)
        return datasets, groups

    def groups(self, location: str, relative: str, scales: dict, recursive: bool, out: dict,
               inherited: frozenset = frozenset()) -> dict:
        """``inherited``: the coordinates the tree's ancestors of this group pass down to it."""
        scales = dict(scales)
        try:
            datasets, groups = self._members(self.f[location], scales)
            raw = self.dataset(location, datasets, scales)
        except READ_ERRORS as err:   # HDF5 failing to read the group's metadata (a checksum, a bad reference)
            raise _damaged(self.path, location, err) from None
        raw = _rename_shadowed(raw, inherited, location.rstrip("/").rsplit("/", 1)[-1])
        dataset = xr.decode_cf(raw, **self.decoders)
        dataset.set_close(self.manager.close)
        out[relative or "/"] = dataset
        if recursive:
            inherited = inherited | {name for name, variable in raw.variables.items() if variable.dims == (name,)}
            for name in groups:
                self.groups(f"{location.rstrip('/')}/{name}", f"{relative}/{name}", scales, True, out, inherited)
        return out

    def dataset(self, location: str, datasets: dict, scales: dict):
        variables = {}
        for name, member in datasets.items():
            attrs = member.attrs
            keys = list(attrs)
            scale = _is_scale(attrs, keys)
            if scale and bytes(attrs.get("NAME", b"")).startswith(DIMENSION_ONLY_PREFIX):
                continue   # a netCDF dimension that is no variable
            if name in self.drop:
                continue
            path = f"{location.rstrip('/')}/{name}"
            dims = self.dimensions(path, member, attrs, keys, scale, scales)
            # chunks={} takes a backend's preferred chunks (as h5netcdf's): the HDF5 chunks, which a
            # dask chunk reads whole; without them each variable was one dask chunk
            encoding = {"preferred_chunks": dict(zip(dims, member.chunks))} if member.chunks else {}
            variables[name] = xr.Variable(dims, self.data(member, path, self.rows.get(path)),
                                          {key: _attribute(attrs[key]) for key in keys
                                           if key not in HIDDEN_ATTRIBUTES}, encoding)
        group = self.f[location]
        attributes = {key: _attribute(value) for key, value in group.attrs.items() if key not in HIDDEN_ATTRIBUTES}
        if location == "/":
            attributes.update(self.root_attributes)
        elif location == f"/{ensemblefile.GROUP}" and "status" in attributes:
            # a killed sweep's ensemble still says 'running' (a user trial), as EnsembleFile reads it
            attributes["status"] = ensemblefile.read_status(self.path, attributes["status"])
        return xr.Dataset(variables, attrs=attributes)

    def dimensions(self, path: str, member, attrs, keys, scale: bool, scales: dict) -> tuple:
        """The dimension names of the dataset at ``path``: a 1-d scale is its own dimension; any
        other dataset's come from the scales its DIMENSION_LIST refers to, known by identity."""
        if scale:
            if member.ndim != 1:
                raise OutputError(f"{self.path}:{path}: a {member.ndim}-d dimension scale, which "
                                  "elimfast.open_datatree does not read; use xr.open_datatree(path, engine='h5netcdf')")
            return (path.rsplit("/", 1)[-1],)
        if member.ndim == 0:
            return ()
        if "DIMENSION_LIST" not in keys:
            raise OutputError(f"{self.path}:{path}: has no dimension scales (files of elimfast format 1 and 2 have "
                              "none); read the run with elimfast.load")
        dims = []
        for axis in attrs["DIMENSION_LIST"]:
            if len(axis) == 0:
                raise OutputError(f"{self.path}:{path}: an axis without a dimension scale; read the run with "
                                  "elimfast.load")
            target = self.f[axis[-1]]   # netCDF-C and h5netcdf take the last scale attached to an axis
            dimension = scales.get(target.id)
            if dimension is None:   # a scale outside the group and its ancestors: named as h5netcdf names it
                dimension = target.name.rsplit("/", 1)[-1]
            dims.append(dimension)
        return tuple(dims)

    def data(self, member, path: str, rows: int | None = None):
        """``rows``: read only the first rows (_snapshot), else all."""
        if h5py.check_string_dtype(member.dtype) is not None:
            return np.asarray(member.asstr()[()], dtype=object)
        shape = member.shape if rows is None else (rows,) + member.shape[1:]
        return indexing.LazilyIndexedArray(_LazyDataset(self.manager, path, shape, member.dtype))


def _rename_shadowed(dataset, inherited: frozenset, group_name: str):
    """The group's own variables named as a coordinate its ancestors pass down, renamed
    <group>_<name> (``steps`` -> step_t, ``events/pericentre`` -> pericentre_t: the names of
    Result.to_xarray). In a DataTree the inherited coordinate hides such a variable:
    ``tree["steps"]["t"]`` gave the root's sample times, not the step times, and with
    ``chunks`` xarray replaced the variable itself. The attribute ``stored_as`` keeps the
    file's name."""
    shadowed = [name for name in dataset.variables if name in inherited and dataset[name].dims != (name,)]
    if group_name == "steps" and "h" in dataset.variables and dataset["h"].dims != ("h",):
        shadowed.append("h")   # no clash, but Result.to_xarray's step_h beside step_t (a user trial: 'h' here)
    if not shadowed:
        return dataset
    prefix = "step" if group_name == "steps" else group_name
    renamed = dataset.rename_vars({name: f"{prefix}_{name}" for name in shadowed})
    for name in shadowed:
        renamed[f"{prefix}_{name}"].attrs["stored_as"] = name
    return renamed


class _LazyDataset(BackendArray):
    """One HDF5 dataset, read when used through the file manager (which reopens a closed file)."""

    def __init__(self, manager, path: str, shape, dtype):
        self.manager, self.path, self.shape, self.dtype = manager, path, tuple(shape), np.dtype(dtype)

    def __getitem__(self, key):
        return indexing.explicit_indexing_adapter(key, self.shape, indexing.IndexingSupport.BASIC, self._read)

    def _read(self, key):
        # slices within this array's shape, which a snapshot (_snapshot) cuts below the dataset's
        key = tuple(slice(*part.indices(size)) if isinstance(part, slice) else part
                    for part, size in zip(key, self.shape))
        with self.manager.acquire_context() as f:
            try:
                return np.asarray(f[self.path][key])
            except READ_ERRORS as err:
                raise _damaged(f.filename, self.path, err) from None


class ElimfastBackend(BackendEntrypoint):
    """xarray's backend for elimfast files, asked for by class: ``xr.open_datatree(path,
    engine=ElimfastBackend)`` (what ``open_datatree`` calls), ``xr.open_dataset(path,
    engine=ElimfastBackend, group="runs/<name>")``, ``xr.open_groups``."""

    description = "elimfast run and sweep files, opened in time linear in their groups"
    open_dataset_parameters = ("filename_or_obj", "drop_variables", "group") + DECODERS

    def guess_can_open(self, filename_or_obj) -> bool:
        return False   # only when asked for: h5netcdf stays xarray's choice for .h5 files

    def _groups(self, filename_or_obj, group, drop_variables, decoders, recursive: bool) -> dict:
        path = os.fspath(filename_or_obj)
        # a handle of its own (xarray's cache keys a manager by its arguments alone): a tree left open
        # made every later open of the same live file in the process reuse its handle and snapshot
        # (a user trial: steps_done 179,934 three times over 2 s while the run reached 600,000)
        manager = CachingFileManager(_open_file, path, manager_id=uuid.uuid4())
        try:
            f = manager.acquire()
            fmt = _plain(f.attrs.get("format", ""))
            if fmt not in (FORMAT, SWEEP_FORMAT):
                # (a user trial: a plain HDF5 file got "has no dimension scales ... elimfast format 1 and 2")
                what = f"its format is {fmt!r}" if fmt else f"no '{FORMAT}' format attribute"
                raise NotAnElimfastFile(f"{path}: not an elimfast run or sweep file ({what}); open another HDF5 "
                                        "file with xr.open_datatree(path, engine='h5netcdf')")
            location = "/" + (group or "").strip("/")
            if location not in f or not isinstance(f[location], h5py.Group):
                raise OutputError(f"{path}: has no group {group!r}")
            walk = _Walk(f, manager, path, decoders, drop_variables)
            return walk.groups(location, "", walk.scales_above(location), recursive, {})
        except BaseException:
            manager.close()
            raise

    def open_dataset(self, filename_or_obj, *, drop_variables=None, group=None, mask_and_scale=True,
                     decode_times=True, concat_characters=True, decode_coords=True, use_cftime=None,
                     decode_timedelta=None):
        return self._groups(filename_or_obj, group, drop_variables, _decoders(locals()), recursive=False)["/"]

    def open_groups_as_dict(self, filename_or_obj, *, drop_variables=None, group=None, mask_and_scale=True,
                            decode_times=True, concat_characters=True, decode_coords=True, use_cftime=None,
                            decode_timedelta=None) -> dict:
        return self._groups(filename_or_obj, group, drop_variables, _decoders(locals()), recursive=True)

    def open_datatree(self, filename_or_obj, *, drop_variables=None, group=None, mask_and_scale=True,
                      decode_times=True, concat_characters=True, decode_coords=True, use_cftime=None,
                      decode_timedelta=None):
        groups = self._groups(filename_or_obj, group, drop_variables, _decoders(locals()), recursive=True)
        try:
            tree = xr.DataTree.from_dict(groups)
        except KeyError as err:
            groups["/"].close()
            clash = re.fullmatch(r"parent (.*) already contains a variable named (.*)", str(err.args[0]))
            if clash is None:
                raise
            parent, name = clash.groups()
            # written before events named as an inherited coordinate were refused (adaptive._check_event_name)
            raise OutputError(f"{filename_or_obj}: its group {parent}/{name} has the name of a coordinate of "
                              f"{parent}, which an xarray DataTree cannot hold (an event named {name!r}, which "
                              "elimfast now refuses); read the run with elimfast.load") from None
        except ValueError as err:
            groups["/"].close()
            if "not aligned" not in str(err):
                raise
            # Groups of different lengths (t of /invariants longer than the root's), which xarray
            # reports as "group ... is not aligned": a run file still being written is read as a
            # snapshot (_snapshot), so a file a writer changed outside elimfast's way, or damaged.
            raise OutputError(f"{filename_or_obj}: its groups have different lengths (written to while it was read, "
                              "or damaged); read the stored part consistently with elimfast.load, or check it with "
                              "elimfast inspect") from None
        tree.set_close(groups["/"].close)   # every group's close closes the one file
        return tree


def _decoders(arguments: dict) -> dict:
    return {name: arguments[name] for name in DECODERS}
