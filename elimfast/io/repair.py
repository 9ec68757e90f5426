"""Repair: make the file of a killed (or cut-off) writer readable by every HDF5 program.

As ``h5clear -s``, once no process writes the file; a run file is also cut back to its saved
state; a file shorter than the end HDF5 recorded is extended to it first
(``safety.extended_to_recorded_end``). The result is read back before repair says it succeeded.
"""
from __future__ import annotations

import contextlib
from pathlib import Path

import h5py

from ..errors import ElimfastError
from .layout import FORMAT, LIBVER, STATUS_KILLED, _plain
from .runfile import RunFile, _cut_back
from .safety import (_DAMAGE_ADVICE, DamagedFileError, FileBusyError, NotAnElimfastFile, OutputError, _damaged,
                     _FileGuard, _regular_file, clear_consistency_flags, consistency_flags, ensure_not_busy,
                     cut_short, extended_to_recorded_end, set_consistency_flags)


def repair(path) -> str:
    """Make the file of a killed writer readable by every HDF5 program (as ``h5clear -s``),
    once no process writes it; return what was done.

    A run file is also cut back to its saved state (the rows of the chunk that was being
    written go) and gets ``status = killed`` and the saved ``steps_done`` as root
    attributes, so that readers that know nothing of /state (xarray) see the truth.
    ``--resume`` continues a repaired file as it would the killed one. A file shorter than
    the end HDF5 recorded (a write cut off by a file-size limit) is extended to that end
    first. The repaired file is read back (every object; a run file's rows up to its saved
    state): DamagedFileError, and the flags put back, where that fails.
    """
    path = Path(path)
    _regular_file(path, "file")
    if not h5py.is_hdf5(path):
        raise NotAnElimfastFile(f"{path}: not an HDF5 file; nothing to repair")
    ensure_not_busy(path, other_output=False)
    flags = consistency_flags(path)
    short = cut_short(path)
    if not flags and not short:
        return f"{path}: nothing to repair (no writer left it open)"
    guard = _FileGuard(path)
    try:
        if not guard.lock():
            raise FileBusyError(f"{path}: is being written by another process; stop it first")
        try:
            with extended_to_recorded_end(path) as added:
                with RunFile(path) if _format_of(path) == FORMAT else contextlib.nullcontext() as run_file:
                    saved = run_file.saved_state() if run_file is not None else None
                if flags:
                    clear_consistency_flags(path)
                try:
                    with h5py.File(path, "r+", libver=LIBVER) as f:
                        if saved is not None:
                            _cut_back(f, saved["n_samples"], saved["steps_done"], saved.get("event_counts", ()))
                            f.attrs["status"] = STATUS_KILLED
                            f.attrs["steps_done"] = saved["steps_done"]
                            f.attrs["wall_time_s"] = float(saved["wall_time_s"])
                            f.attrs["kernel_time_s"] = float(saved["kernel_time_s"])
                    _read_back(path, saved is not None)
                except (OSError, RuntimeError, ValueError, KeyError, ElimfastError) as err:
                    with contextlib.suppress(OSError, OutputError):
                        set_consistency_flags(path, flags)
                    if isinstance(err, DamagedFileError) and flags:
                        raise DamagedFileError(f"{err} (repair cleared the flags its writer left, but could not "
                                               "make it readable)") from None
                    if isinstance(err, DamagedFileError):
                        raise
                    raise _damaged(path, "its start (HDF5 cannot open it for the repair)", err) from None
        except DamagedFileError as err:
            if short:
                # The missing end held metadata (a copy cut short, not a write cut off by a limit):
                # say why nothing could be kept, instead of only where the damage showed.
                found = str(err).removesuffix(f"; {_DAMAGE_ADVICE}")
                raise DamagedFileError(f"{path} cannot be repaired: {short}, and its missing end held HDF5 metadata "
                                       f"that nothing can rebuild ({found}); {_DAMAGE_ADVICE}") from None
            raise
    finally:
        guard.close()
    extended = (f"extended it by the {added} bytes a cut-off write had not written (to the end HDF5 recorded), "
                if added else "")
    if saved is None:
        return f"{path}: repaired: {extended}cleared the flags its writer left; every HDF5 program opens it now"
    return (f"{path}: repaired: {extended}cleared the flags its killed writer left and kept the "
            f"{saved['steps_done']} steps it had saved; every HDF5 program opens it now (continue the run with "
            "elimfast run ... --resume)")


def _read_back(path: Path, run_file: bool) -> None:
    """Read a repaired file as plain HDF5 programs do: every object and its attributes, and for
    a run file its rows up to the saved state (RunFile.verify); raises where that fails."""
    def read(name, item) -> None:   # None: visititems goes on to the next object
        dict(item.attrs)

    with h5py.File(path, "r") as f:
        f.visititems(read)
    if run_file:
        with RunFile(path) as written:
            written.verify()


def _format_of(path) -> str:
    from .safety import _open_swmr
    try:
        with _open_swmr(path) as f:
            return str(_plain(f.attrs.get("format", "")))
    except (OSError, RuntimeError, KeyError):
        return ""
