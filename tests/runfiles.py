"""Helpers shared by the tests that watch a real `elimfast run` process write its file."""
from pathlib import Path

import h5py


def steps_on_disk(path: Path) -> int:
    """/state/steps_done as a reader sees it while the run is writing (0 before the file exists)."""
    try:
        with h5py.File(path, "r", swmr=True) as f:
            return int(f["state/steps_done"][()])
    except (OSError, KeyError):
        return 0
