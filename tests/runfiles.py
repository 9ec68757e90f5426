"""Helpers shared by the tests that watch a real `elimfast run` process write its file, and by
those that compare two files written by different routes (pool and Dask, resumed and not)."""
from pathlib import Path

import h5py
import numpy as np


def steps_on_disk(path: Path) -> int:
    """/state/steps_done as a reader sees it while the run is writing (0 before the file exists)."""
    try:
        with h5py.File(path, "r", swmr=True) as f:
            return int(f["state/steps_done"][()])
    except (OSError, KeyError):
        return 0


# Attributes that say when and how long, not what: they differ between any two runs.
TIMING_ATTRIBUTES = {"created", "wall_time_s", "kernel_time_s", "threads"}


def contents(path) -> dict:
    """Every dataset (as an array) and attribute of an HDF5 file, by path; timing attributes left out."""
    found = {}

    def visit(name, obj):
        for key, value in obj.attrs.items():
            if key not in TIMING_ATTRIBUTES and not key.startswith(("DIMENSION_LIST", "REFERENCE_LIST")):
                found[f"{name}@{key}"] = value
        if isinstance(obj, h5py.Dataset) and obj.dtype.kind != "O" and not obj.dtype.names:
            found[name] = obj[()]
    with h5py.File(path, "r") as f:
        visit("/", f)
        f.visititems(visit)
    return found


def assert_same_files(a, b):
    first, second = contents(a), contents(b)
    assert any(key.endswith("/y") or key.endswith("/y_final") for key in first)   # the arrays are compared
    assert sorted(first) == sorted(second)
    for key, value in first.items():
        other = second[key]
        if isinstance(value, np.ndarray) and value.dtype.kind == "f":
            np.testing.assert_array_equal(value, other, err_msg=key)   # bit for bit (nan == nan)
        else:
            assert np.array_equal(np.asarray(value), np.asarray(other)), key


def stopped_after_blocks(path, out, after_blocks: int, monkeypatch, **options):
    """The file an ensemble sweep leaves when stopped (Ctrl-C) after storing ``after_blocks`` blocks."""
    import pytest

    from elimfast import sweep as sweeps
    from elimfast.io.sweepfile import SweepWriter

    store = SweepWriter.add_ensemble_rows

    def store_then_stop(writer, start, stop, rows):
        if writer.stored_blocks == after_blocks:
            raise KeyboardInterrupt
        store(writer, start, stop, rows)
        writer.stored_blocks += 1

    with monkeypatch.context() as patch:
        patch.setattr(SweepWriter, "stored_blocks", 0, raising=False)
        patch.setattr(SweepWriter, "add_ensemble_rows", store_then_stop)
        with pytest.raises(KeyboardInterrupt):
            sweeps.run_to_file(path, out, **options)
    return out
