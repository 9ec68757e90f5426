"""elimfast's HDF5 files, one name for what the modules of ``elimfast.io`` provide.

The concerns live apart: ``safety`` (locks, disk space, atomic creation, SWMR crash
recovery, bounded opening), ``layout`` (the run group that a run file and each run of a
sweep file share, with its dimension scales), ``runfile`` (the streaming, resumable run
file and its reader) and ``sweepfile`` (the sweep file). Import from here or from them.
"""
from __future__ import annotations

from .layout import (FAILED_PREFIX, FORMAT, FORMAT_VERSION, STATUS_COMPLETE, STATUS_INTERRUPTED,
                     STATUS_KILLED, STATUS_RUNNING, STOPPED_PREFIX, multiplier_name, version_attributes)
from .layout import SWEEP_FORMAT, split_run_path
from .repair import repair
from .runfile import RunFile, RunWriter
from .safety import (DamagedFileError, FileBusyError, NotAnElimfastFile, OutputError, _is_disk_full,
                     check_creatable, check_output_path, clear_consistency_flags, consistency_flags,
                     create_parent_directories, ensure_not_busy, lookup3, set_consistency_flags)
from .sweepfile import SweepWriter, sweep_group_name

__all__ = ["FAILED_PREFIX", "FORMAT", "FORMAT_VERSION", "STATUS_COMPLETE", "STATUS_INTERRUPTED", "STATUS_KILLED",
           "STATUS_RUNNING", "STOPPED_PREFIX", "multiplier_name", "version_attributes", "SWEEP_FORMAT", "RunFile",
           "RunWriter", "repair", "split_run_path", "DamagedFileError", "FileBusyError", "NotAnElimfastFile",
           "OutputError", "_is_disk_full", "check_creatable", "check_output_path", "clear_consistency_flags",
           "consistency_flags", "create_parent_directories", "ensure_not_busy", "lookup3", "set_consistency_flags",
           "SweepWriter", "sweep_group_name"]
