"""The HDF5 run file: writer (streaming, crash-safe, resumable) and reader. The only module importing h5py.

Layout (format ``elimfast-run``, version 2; every growing dataset chunked, compressed
with the shuffle filter and gzip, checksummed with HDF5's fletcher32 filter, and
extended as the run goes):

    /t                      (samples,)           time of each stored sample
    /y                      (samples, 2m)        state; attribute ``coordinates`` (q names, then p names)
    /invariants/H           (samples,)           the Hamiltonian at each sample
    /invariants/<name>      (samples,)           every invariant of the problem; attribute ``imposed``
    /steps/iterations       (steps_done,) int32  solver iterations of each step (every try and substep)
    /steps/substeps         (steps_done,) int32  1, or the substeps of a step that was split (docs/solver.md)
    /steps/alpha            (steps_done, nu)     ELIM/EHBVM with nu >= 1 imposed invariants
    /steps/lambda           (steps_done, nu+1)   LIM/GHBVM (H first, then the imposed invariants)
    /method/A, b, c         the Runge-Kutta form (all but LIM/GHBVM; for ELIM/EHBVM the
                            underlying HBVM(k,s) tableau, i.e. eta = 1: attribute ``tableau``)
    /method/quadrature_nodes, quadrature_weights                      k-point Gauss-Legendre on [0, 1]
    /method/invariant_quadrature_nodes, invariant_quadrature_weights  the r points (ELIM/LIM)
    /state/...              what resume needs, rewritten after every flushed chunk:
                            y, y_comp (Kahan compensation), clock = [t, its compensation],
                            coef (s, 2m) last step's coefficients, multipliers, steps_done,
                            n_samples, wall_time_s, kernel_time_s
    /state/record           (2, L) float64: the same state as one row, written alternately
                            into row 0 and row 1 (see "Saved state" below)

Root attributes: elimfast_version, numba_version, numpy_version, h5py_version,
hdf5_version, created (UTC, ISO 8601), config (the resolved YAML), problem, method,
family, r, k, s, h, t0, t_end, n_steps, output_every, conserve, steps_done, status
(running | complete | interrupted | stopped: <reason> | failed: <reason>), wall_time_s,
kernel_time_s, format = 'elimfast-run', format_version. 'stopped' (the disk filled up,
a problem function raised) can be resumed; 'failed' (the numerics failed) cannot.

Crash safety. The file is written in HDF5's single-writer/multiple-reader (SWMR) mode,
whose ordered metadata writes keep the file consistent at every instant: a run killed
with SIGKILL leaves a file whose flushed chunks are all readable. (Without SWMR, 8 of
25 files killed during a stress test of appends had unreadable or wrong flushed data.)
Root attributes cannot change in SWMR mode, so they are final only once the run ends
(the writer then reopens the file normally); while a run is going, or after a kill,
``status`` still says ``running`` and /state holds the truth. After a kill the
superblock keeps its "open for writing" flags: ``elimfast inspect`` reads such a file in
SWMR mode, and ``elimfast run ... --resume`` clears the flags (as ``h5clear -s``) and
continues. Data rows beyond the saved state may exist after a kill; they belong to the
chunk being written and are dropped by resume.

Saved state. The named /state datasets are written one by one, so a kill between two
of those writes would leave them mixed (y of one chunk, steps_done of the one before).
The record is written in one piece, alternately into its two rows, each row with a
sequence number and a CRC-32 of its values (and HDF5's fletcher32 on each row): the
valid row with the higher sequence number is the state, and if a kill or a damaged
sector spoils one row, the other still holds the state of the chunk before.

Damage. Metadata carry HDF5's checksums (lookup3) and data chunks fletcher32, so
corruption is detected on reading; every read error names the file and the place
(``DamagedFileError``). A resume first reads everything it will build on and refuses a
damaged file, leaving it as it was. SWMR readers retry a metadata read whose checksum
fails (a writer may be in the middle of rewriting it); HDF5's default of 100 attempts
with exponential backoff turns one damaged block into hours of retrying, so readers here
allow ``METADATA_READ_ATTEMPTS``.

Writers. A new file is built under a temporary name beside the output and renamed over
it only when its layout is complete, so an existing file is never truncated in place.
While a run writes a file it holds an exclusive lock on it (a Linux open-file-description
lock, which HDF5's own locking does not see: HDF5 drops its lock in SWMR mode), and
``--overwrite`` and ``--resume`` refuse a file that another live process holds. Before
each chunk the writer reserves its disk space (``fallocate``): when the file system is
full the run stops at the chunk boundary with a clean, resumable file, instead of HDF5
failing part-way through a write (after which HDF5 2.0 crashes on closing the file).
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import datetime
import errno
import fcntl
import math
import os
import socket
import stat
import struct
import zlib
from pathlib import Path

import h5py
import numpy as np

from ..errors import DiskFullError, ElimfastError

FORMAT = "elimfast-run"
FORMAT_VERSION = 2            # 2: fletcher32 on every chunk, /state/record
# SWMR needs the 1.10 file format; bounding it at 1.10 keeps the files readable by any
# HDF5 >= 1.10 (tools linked against older 1.x libraries are common).
LIBVER = ("v110", "v110")
# gzip (readable by every HDF5 tool, unlike lzf) at level 1 after the shuffle filter:
# levels above 1 cost more time than they save bytes on these data.
GZIP_LEVEL = 1
# Small HDF5 chunks: every flush recompresses the last, partial chunk of each dataset,
# so this bounds the cost of a flush (256 KiB chunks made flushes 3x slower).
CHUNK_BYTES = 1 << 14      # target bytes per HDF5 chunk
MIN_CHUNK_ROWS = 64
# SWMR metadata read attempts. HDF5 backs off exponentially between attempts: on a damaged
# block, 20 attempts took 7 ms, 30 took 1.1 s and 50 more than 100 s (HDF5 2.0, measured).
METADATA_READ_ATTEMPTS = 20
# Disk space reserved ahead of the writes of a chunk: the chunk's raw bytes (compression
# only shrinks them) times this factor, plus SPACE_MARGIN per dataset (each flush rewrites
# the last partial HDF5 chunk of each dataset at a new address) and SPACE_BASE for
# metadata and for closing the file. A 10^4-step Kepler run grew by 0.55 bytes per raw byte.
SPACE_FACTOR = 1.25
SPACE_MARGIN = 2 * CHUNK_BYTES
SPACE_BASE = 64 << 10
VERIFY_BLOCK_BYTES = 16 << 20   # bytes per read when verifying or reducing long datasets
STATUS_RUNNING = "running"
STATUS_COMPLETE = "complete"
STATUS_INTERRUPTED = "interrupted"
FAILED_PREFIX = "failed: "
STOPPED_PREFIX = "stopped: "


class OutputError(ElimfastError):
    """The output file cannot be created, overwritten, resumed or read as asked."""


class NotAnElimfastFile(OutputError):
    """The file is HDF5 (or not even that) but was not written by elimfast."""


class DamagedFileError(OutputError):
    """A run file whose metadata or data fail their checksums, or that lacks part of the layout."""


class FileBusyError(OutputError):
    """Another live process is writing the file."""


# --- plain files ---------------------------------------------------------------------------
def _regular_file(path: Path, what: str = "file") -> os.stat_result:
    """stat of an existing regular file; an OutputError for anything else (a device, a FIFO)."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise OutputError(f"{path}: no such file") from None
    except OSError as err:
        raise OutputError(f"{path}: cannot be read ({err.strerror})") from None
    if stat.S_ISDIR(info.st_mode):
        raise OutputError(f"{path}: is a directory; give an HDF5 {what}")
    if not stat.S_ISREG(info.st_mode):
        raise OutputError(f"{path}: not a regular file (a device, FIFO or socket); give an HDF5 {what}")
    return info


def _one_line(err) -> str:
    return " ".join(str(err).split())


def _is_disk_full(err: BaseException) -> bool:
    """Whether an OSError (or an HDF5 error, whose text carries the errno) means no space."""
    if getattr(err, "errno", None) in (errno.ENOSPC, errno.EDQUOT):
        return True
    text = str(err)
    return f"errno = {errno.ENOSPC}," in text or f"errno = {errno.EDQUOT}," in text \
        or "No space left on device" in text or "Disk quota exceeded" in text


def _free_bytes(directory: Path) -> int | None:
    try:
        info = os.statvfs(directory)
    except OSError:
        return None
    return info.f_bavail * info.f_frsize


def _size(n_bytes: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if n_bytes < 1024 or unit == "TiB":
            return f"{n_bytes:.0f} {unit}" if unit == "bytes" else f"{n_bytes:.1f} {unit}"
        n_bytes /= 1024
    return f"{n_bytes:.1f} TiB"


# --- locks and disk space -------------------------------------------------------------------
_LOCK_OFFSET = 1 << 62     # the byte locked: far beyond any data, so no other lock range meets it
_F_OFD_SETLK = getattr(fcntl, "F_OFD_SETLK", None)
_F_OFD_GETLK = getattr(fcntl, "F_OFD_GETLK", None)
_FALLOC_FL_KEEP_SIZE = 1


def _flock_struct(kind: int) -> bytes:
    # struct flock {short l_type, l_whence; off_t l_start, l_len; pid_t l_pid;} (Linux, 64-bit off_t)
    return struct.pack("hhqqi4x", kind, os.SEEK_SET, _LOCK_OFFSET, 1, 0)


def _lock_held_elsewhere(fd: int) -> bool:
    """Whether another open file (any process) holds our writer lock on this file."""
    if _F_OFD_GETLK is not None:
        try:
            answer = fcntl.fcntl(fd, _F_OFD_GETLK, _flock_struct(fcntl.F_WRLCK))
        except OSError:
            return False
        return struct.unpack("hhqqi4x", answer)[0] != fcntl.F_UNLCK
    return False


def _take_lock(fd: int) -> bool:
    """An exclusive lock on _LOCK_OFFSET: an open-file-description lock on Linux (kept until
    this descriptor closes, whatever else the process opens and closes), else a POSIX one."""
    try:
        if _F_OFD_SETLK is not None:
            fcntl.fcntl(fd, _F_OFD_SETLK, _flock_struct(fcntl.F_WRLCK))
        else:
            fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB, 1, _LOCK_OFFSET)
        return True
    except OSError as err:
        if err.errno in (errno.EAGAIN, errno.EACCES):
            return False
        return True   # a file system without locks: nothing to exclude with


_LIBC = None


def _fallocate(fd: int, offset: int, length: int) -> bool:
    """Reserve [offset, offset + length) without changing the file size (Linux fallocate
    with FALLOC_FL_KEEP_SIZE). True if reserved, False where the call is not available;
    DiskFullError when there is no room."""
    global _LIBC
    if _LIBC is None:
        try:
            _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
            _LIBC.fallocate.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_int64, ctypes.c_int64]
        except (OSError, AttributeError):
            _LIBC = False
    if not _LIBC:
        return False
    if _LIBC.fallocate(fd, _FALLOC_FL_KEEP_SIZE, offset, length) == 0:
        return True
    code = ctypes.get_errno()
    if code in (errno.ENOSPC, errno.EDQUOT):
        raise DiskFullError(os.strerror(code))
    return False   # EOPNOTSUPP, ENOSYS, EINVAL: the file system cannot reserve; check free space instead


class _FileGuard:
    """The writer's own descriptor of its file: holds the writer lock, reserves disk space."""

    def __init__(self, path: Path):
        self.path = path
        self.fd = os.open(path, os.O_RDWR | getattr(os, "O_CLOEXEC", 0))

    def lock(self) -> bool:
        return _take_lock(self.fd)

    def reserve(self, n_bytes: int) -> None:
        """Make sure the next n_bytes of the file have room on disk; DiskFullError if not."""
        n_bytes = int(max(n_bytes, 1))
        size = os.fstat(self.fd).st_size
        try:
            if _fallocate(self.fd, size, n_bytes):
                return
        except DiskFullError:
            raise DiskFullError(f"{self.path}: the disk is full ({_size(_free_bytes(self.path.parent) or 0)} "
                                f"free, {_size(n_bytes)} needed)") from None
        free = _free_bytes(self.path.parent)
        if free is not None and free < n_bytes:
            raise DiskFullError(f"{self.path}: the disk is full ({_size(free)} free, {_size(n_bytes)} needed)")

    def available(self) -> int | None:
        return _free_bytes(self.path.parent)

    def reserved(self) -> int:
        """Bytes allocated beyond the end of the file (reserved earlier, not yet written)."""
        info = os.fstat(self.fd)
        return max(0, getattr(info, "st_blocks", 0) * 512 - info.st_size)

    def close(self) -> None:
        """Give back the space reserved beyond the end of the file (a truncation to the
        same size frees it on tmpfs, ext4 and xfs), drop the lock, close."""
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                os.ftruncate(self.fd, os.fstat(self.fd).st_size)
            os.close(self.fd)
            self.fd = -1


def _writer_lock_held(path: Path) -> bool:
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return False
    try:
        return _lock_held_elsewhere(fd)
    finally:
        os.close(fd)


def _writer_pid(path: Path) -> tuple[int, str, int]:
    """(writer pid, host, format version) stored in a file, (0, '', 0) when unreadable."""
    try:
        with _open_swmr(path) as f:
            state = f["state"]
            return (int(state.attrs.get("writer_pid", 0)), str(_plain(state.attrs.get("writer_host", ""))),
                    int(f.attrs.get("format_version", 0)))
    except Exception:   # damaged or foreign: nobody we know is writing it
        return 0, "", 0


def ensure_not_busy(path) -> None:
    """FileBusyError if another live process writes (or holds open) ``path``. Touches nothing.

    Three checks: the writer lock of this version; HDF5's own lock (held by a writer
    outside SWMR mode, and by readers that opened it normally); and, for files of format
    1 whose writers held no lock, the writer's pid recorded in /state, alive on this host.
    """
    path = Path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        return
    except OSError:
        return
    if not stat.S_ISREG(info.st_mode):
        return
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return
    try:
        if _lock_held_elsewhere(fd):
            pid, host, _ = _writer_pid(path)
            who = f"process {pid}" if pid and host == socket.gethostname() else "another process"
            stop = f" (Ctrl-C or kill {pid})" if who != "another process" else ""
            raise FileBusyError(f"{path}: is being written by {who}; stop it first{stop} or choose another "
                                "output file")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.flock(fd, fcntl.LOCK_UN)
        except OSError as err:
            if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise FileBusyError(f"{path}: is open in another process (an HDF5 program or elimfast); close it "
                                    "there first, or choose another output file") from None
    finally:
        os.close(fd)
    if consistency_flags(path):
        pid, host, version = _writer_pid(path)
        if version < 2 and pid and host == socket.gethostname() and pid != os.getpid() and _process_alive(pid):
            raise FileBusyError(f"{path}: is still being written by process {pid}; stop it first "
                                f"(Ctrl-C or kill {pid}), or choose another output file")


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# --- paths -------------------------------------------------------------------------------
def check_output_path(path, *, overwrite: bool = False, resume: bool = False) -> Path:
    """Fail early (before any computation) if a run could not write ``path``.

    Missing parent directories are fine when they can be created (the writer creates
    them); an existing file needs ``overwrite`` or ``resume``, must be a regular file and
    must not be in use by another process. Writability is tested by doing (opening the
    file for update, or creating and removing a probe file), since permission bits say
    nothing for root or on read-only file systems.
    """
    path = Path(path)
    if path.is_dir():
        raise OutputError(f"{path}: is a directory; give a file name such as {path / 'run.h5'}")
    if path.exists():
        if not (overwrite or resume):
            raise OutputError(f"{path}: already exists; pass --overwrite to replace it or --resume to continue it")
        if not path.is_file():
            raise OutputError(f"{path}: not a regular file (a device, FIFO or socket); choose another output path")
        try:
            with open(path, "r+b"):
                pass
        except OSError as err:
            raise OutputError(f"{path}: not writable ({err.strerror}); choose another output path") from None
        ensure_not_busy(path)
        return path
    ancestor = path.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise OutputError(f"{path}: {ancestor} is a file, not a directory; choose another output path")
    try:
        handle, probe = _mkstemp(ancestor)
        os.close(handle)
        os.unlink(probe)
    except OSError as err:
        raise OutputError(f"{path}: cannot create files in {ancestor} ({err.strerror}); "
                          "choose another output path") from None
    return path


def _mkstemp(directory: Path):
    import tempfile
    return tempfile.mkstemp(prefix=".elimfast-probe-", dir=directory)


def _temporary_path(path: Path) -> Path:
    """Where a new file is built before it is renamed to ``path``; stale ones of dead writers go."""
    prefix = f".{path.name}."
    with contextlib.suppress(OSError):
        for name in os.listdir(path.parent):
            pid = name[len(prefix):-len(".tmp")]
            if name.startswith(prefix) and name.endswith(".tmp") and pid.isdigit() and not _process_alive(int(pid)):
                with contextlib.suppress(OSError):
                    (path.parent / name).unlink()
    return path.with_name(f"{prefix}{os.getpid()}.tmp")


def _publish(temporary: Path, path: Path, overwrite: bool) -> None:
    """Rename the finished new file onto ``path`` (refusing a file that appeared meanwhile
    unless overwriting, and a file another process is writing in any case)."""
    ensure_not_busy(path)
    if overwrite:
        os.replace(temporary, path)
        return
    try:
        os.link(temporary, path)   # fails if path exists, unlike a rename
    except FileExistsError:
        raise OutputError(f"{path}: appeared while the run was being set up; pass --overwrite to replace it "
                          "or --resume to continue it") from None
    except OSError:
        if path.exists():
            raise OutputError(f"{path}: already exists; pass --overwrite to replace it or --resume to continue "
                              "it") from None
        os.replace(temporary, path)
        return
    os.unlink(temporary)


# --- SWMR consistency flags --------------------------------------------------------------
_MASK = 0xFFFFFFFF
_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def _rot(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _MASK


def lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 ``hashlittle``: HDF5's metadata checksum (H5checksum.c)."""
    length = len(data)
    a = b = c = (0xDEADBEEF + length + initval) & _MASK
    i = 0
    while length > 12:
        a = (a + int.from_bytes(data[i:i + 4], "little")) & _MASK
        b = (b + int.from_bytes(data[i + 4:i + 8], "little")) & _MASK
        c = (c + int.from_bytes(data[i + 8:i + 12], "little")) & _MASK
        a = (a - c) & _MASK; a ^= _rot(c, 4); c = (c + b) & _MASK      # noqa: E702 (lookup3 "mix")
        b = (b - a) & _MASK; b ^= _rot(a, 6); a = (a + c) & _MASK      # noqa: E702
        c = (c - b) & _MASK; c ^= _rot(b, 8); b = (b + a) & _MASK      # noqa: E702
        a = (a - c) & _MASK; a ^= _rot(c, 16); c = (c + b) & _MASK     # noqa: E702
        b = (b - a) & _MASK; b ^= _rot(a, 19); a = (a + c) & _MASK     # noqa: E702
        c = (c - b) & _MASK; c ^= _rot(b, 4); b = (b + a) & _MASK      # noqa: E702
        length -= 12
        i += 12
    if length == 0:
        return c
    tail = data[i:i + length] + bytes(12 - length)
    a = (a + int.from_bytes(tail[0:4], "little")) & _MASK
    b = (b + int.from_bytes(tail[4:8], "little")) & _MASK
    c = (c + int.from_bytes(tail[8:12], "little")) & _MASK
    c ^= b; c = (c - _rot(b, 14)) & _MASK      # noqa: E702 (lookup3 "final")
    a ^= c; a = (a - _rot(c, 11)) & _MASK      # noqa: E702
    b ^= a; b = (b - _rot(a, 25)) & _MASK      # noqa: E702
    c ^= b; c = (c - _rot(b, 16)) & _MASK      # noqa: E702
    a ^= c; a = (a - _rot(c, 4)) & _MASK       # noqa: E702
    b ^= a; b = (b - _rot(a, 14)) & _MASK      # noqa: E702
    c ^= b; c = (c - _rot(b, 24)) & _MASK      # noqa: E702
    return c


def _superblock(path) -> tuple[bytearray, int]:
    """The version 2/3 superblock at offset 0 and the offset of its checksum."""
    with open(path, "rb") as handle:
        raw = bytearray(handle.read(64))
    if raw[:8] != _SIGNATURE:
        raise NotAnElimfastFile(f"{path}: not an HDF5 file (no HDF5 signature at offset 0)")
    version, size_of_offsets = raw[8], raw[9]
    if version not in (2, 3) or size_of_offsets not in (2, 4, 8):
        raise OutputError(f"{path}: HDF5 superblock version {version} has no consistency flags to clear")
    return raw, 12 + 4 * size_of_offsets


def consistency_flags(path) -> int:
    """The superblock's file-consistency flags (1: open for writing, 4: SWMR writing)."""
    try:
        raw, _ = _superblock(path)
    except (OutputError, OSError):
        return 0
    return raw[11]


def set_consistency_flags(path, flags: int = 0) -> None:
    """Write the superblock's flags and fix its checksum; ``flags=0`` is what ``h5clear -s`` does.

    Spec: HDF5 File Format Specification, superblock versions 2 and 3 (byte 11 holds the
    flags; a lookup3 checksum of the preceding bytes follows the four addresses).
    """
    raw, end = _superblock(path)
    stored = struct.unpack("<I", raw[end:end + 4])[0]
    if lookup3(bytes(raw[:end])) != stored:
        raise DamagedFileError(f"{path} is damaged at the HDF5 superblock (its checksum does not match); "
                               "not touching the file")
    raw[11] = flags
    raw[end:end + 4] = struct.pack("<I", lookup3(bytes(raw[:end])))
    with open(path, "r+b") as handle:
        handle.write(raw[:end + 4])
        handle.flush()
        os.fsync(handle.fileno())


def clear_consistency_flags(path) -> None:
    """Zero the flags a killed writer left (``h5clear -s``)."""
    set_consistency_flags(path, 0)


# --- opening, bounded ------------------------------------------------------------------------
_HDF5_LIBRARY = None


def _hdf5_library():
    """The HDF5 library h5py loaded, for the one setting h5py does not expose (or None)."""
    global _HDF5_LIBRARY
    if _HDF5_LIBRARY is None:
        _HDF5_LIBRARY = False
        try:
            with open("/proc/self/maps") as maps:
                paths = {line.split()[-1] for line in maps if "libhdf5" in line and "_hl" not in line}
            for candidate in sorted(paths):
                library = ctypes.CDLL(candidate)   # already loaded by h5py: the same handle
                function = library.H5Pset_metadata_read_attempts
                function.argtypes = [ctypes.c_int64, ctypes.c_uint]
                function.restype = ctypes.c_int
                _HDF5_LIBRARY = library
                break
        except (OSError, AttributeError):
            _HDF5_LIBRARY = False
    return _HDF5_LIBRARY or None


def _open_swmr(path) -> h5py.File:
    """Open for SWMR reading with at most METADATA_READ_ATTEMPTS attempts per metadata read."""
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    library = _hdf5_library()
    if library is not None:
        library.H5Pset_metadata_read_attempts(fapl.id, METADATA_READ_ATTEMPTS)
    fid = h5py.h5f.open(os.fsencode(str(path)), h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ, fapl=fapl)
    return h5py.File(fid)


def _open(path) -> h5py.File:
    """Open an existing file for reading; a killed or live run's file is read in SWMR mode."""
    path = Path(path)
    _regular_file(path, "run file")
    if not h5py.is_hdf5(path):
        raise NotAnElimfastFile(f"{path}: not an HDF5 file, so not an elimfast run file")
    try:
        return h5py.File(path, "r")
    except OSError as err:
        first = err
    if consistency_flags(path):
        try:
            return _open_swmr(path)
        except OSError as err:
            first = err
    if _held_exclusively(path):
        raise FileBusyError(f"{path}: is open for writing in another process (a run finishing, or another HDF5 "
                            "program); try again when it is done") from None
    raise _damaged(path, "its start (HDF5 cannot open it)", first) from None


def _held_exclusively(path: Path) -> bool:
    """Whether another process holds HDF5's exclusive lock (a writer outside SWMR mode)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        return False
    except OSError as err:
        return err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)
    finally:
        os.close(fd)


# --- the writer --------------------------------------------------------------------------
def _chunk_rows(row_bytes: int) -> int:
    return max(MIN_CHUNK_ROWS, CHUNK_BYTES // max(row_bytes, 1))


def _growing(group, name: str, width: int | None, dtype) -> "_Growing":
    """An empty dataset, chunked, compressed and checksummed, resizable along its first axis.

    Created through h5py's low-level API: the high-level one re-derives the filter
    pipeline for every dataset and costs more than writing a whole short run. fletcher32
    comes last in the pipeline, so it checksums the stored (compressed) bytes.
    """
    dtype = np.dtype(dtype)
    tail = () if width is None else (int(width),)
    rows = _chunk_rows(dtype.itemsize * (width or 1))
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk((rows,) + tail)
    dcpl.set_shuffle()
    dcpl.set_deflate(GZIP_LEVEL)
    dcpl.set_fletcher32()
    space = h5py.h5s.create_simple((0,) + tail, (h5py.h5s.UNLIMITED,) + tail)
    dataset_id = h5py.h5d.create(group.id, name.encode(), h5py.h5t.py_create(dtype), space, dcpl=dcpl)
    return _Growing(dataset_id)


class _Growing:
    """A dataset extended along its first axis by low-level writes (no h5py selection machinery)."""

    __slots__ = ("id", "rows", "tail", "dtype")

    def __init__(self, dataset_id):
        self.id = dataset_id
        shape = dataset_id.shape
        self.rows, self.tail = shape[0], tuple(shape[1:])
        self.dtype = dataset_id.dtype

    @property
    def attrs(self):
        return h5py.Dataset(self.id).attrs

    @property
    def row_bytes(self) -> int:
        return self.dtype.itemsize * int(np.prod(self.tail, dtype=np.int64))

    def append(self, data) -> None:
        count = len(data)
        if count == 0:
            return
        data = np.ascontiguousarray(data, dtype=self.dtype)
        start = self.rows
        self.id.set_extent((start + count,) + self.tail)
        file_space = self.id.get_space()
        file_space.select_hyperslab((start,) + (0,) * len(self.tail), (count,) + self.tail)
        self.id.write(h5py.h5s.create_simple((count,) + self.tail), file_space, data)
        self.rows = start + count

    def truncate(self, rows: int) -> None:
        self.id.set_extent((rows,) + self.tail)
        self.rows = rows


# The saved state as one row of /state/record: a header, the arrays, a CRC-32.
_RECORD_HEADER = ("sequence", "steps_done", "n_samples", "wall_time_s", "kernel_time_s")


def _record_length(n: int, s: int, n_mult: int) -> int:
    return len(_RECORD_HEADER) + 2 + 2 * n + s * n + n_mult + 1 + (n + 3) + 1


def _pack_record(state: dict, sequence: int, n_samples: int, wall_time_s: float, kernel_time_s: float) -> np.ndarray:
    body = np.concatenate([
        np.array([sequence, state["steps_done"], n_samples, wall_time_s, kernel_time_s], dtype=np.float64),
        np.asarray(state["clock"], dtype=np.float64).ravel(), np.asarray(state["y"], dtype=np.float64).ravel(),
        np.asarray(state["y_comp"], dtype=np.float64).ravel(), np.asarray(state["coef"], dtype=np.float64).ravel(),
        np.asarray(state["multipliers"], dtype=np.float64).ravel(), np.asarray(state["last_h"], dtype=np.float64).ravel(),
        np.asarray(state["newton_base"], dtype=np.float64).ravel()])
    return np.append(body, float(zlib.crc32(body.astype("<f8").tobytes())))


def _unpack_record(row: np.ndarray, n: int, s: int, n_mult: int) -> dict | None:
    """The state in a record row, or None if its CRC does not match (a torn or damaged row)."""
    if row.shape != (_record_length(n, s, n_mult),) or not np.all(np.isfinite(row[:5])):
        return None
    if float(zlib.crc32(row[:-1].astype("<f8").tobytes())) != row[-1]:
        return None
    header = dict(zip(_RECORD_HEADER, row[:5].tolist()))
    at = len(_RECORD_HEADER)
    parts = {}
    for key, size, shape in (("clock", 2, (2,)), ("y", n, (n,)), ("y_comp", n, (n,)), ("coef", s * n, (s, n)),
                             ("multipliers", n_mult, (n_mult,)), ("last_h", 1, (1,)), ("newton_base", n + 3, (n + 3,))):
        parts[key] = row[at:at + size].reshape(shape).copy()
        at += size
    return {**parts, "steps_done": int(header["steps_done"]), "n_samples": int(header["n_samples"]),
            "wall_time_s": header["wall_time_s"], "kernel_time_s": header["kernel_time_s"],
            "sequence": int(header["sequence"])}


def _record_dataset(group, length: int):
    """/state/record: (2, length), one HDF5 chunk per row, fletcher32."""
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk((1, length))
    dcpl.set_fletcher32()
    space = h5py.h5s.create_simple((2, length))
    return h5py.h5d.create(group.id, b"record", h5py.h5t.py_create(np.dtype("<f8")), space, dcpl=dcpl)


def _write_record_row(dataset_id, slot: int, row: np.ndarray) -> None:
    file_space = dataset_id.get_space()
    file_space.select_hyperslab((slot, 0), (1, row.size))
    dataset_id.write(h5py.h5s.create_simple((1, row.size)), file_space, np.ascontiguousarray(row[None, :]))


def multiplier_name(integration) -> str | None:
    """The name of the run's per-step multipliers ('alpha', 'lambda'), or None: the method's."""
    return integration.method.multiplier_name(len(integration.conserve))


def _multiplier_datasets(steps) -> list[str]:
    """The per-step multipliers stored in /steps: every dataset but the per-step counts. The
    file names them by the method's multiplier (alpha, lambda), so no reader lists families."""
    return [name for name in steps if name not in ("iterations", "substeps")]


def version_attributes() -> dict:
    import numba

    from .. import __version__
    return {"elimfast_version": __version__, "numba_version": numba.__version__,
            "numpy_version": np.__version__, "h5py_version": h5py.__version__,
            "hdf5_version": h5py.version.hdf5_version}


# Writers whose HDF5 calls failed part-way: HDF5 cannot close such a file without crashing
# (HDF5 2.0 segfaults), so its objects are kept here, never released; the file on disk is
# then as a killed writer leaves it, consistent and resumable.
_ABANDONED: list = []


class RunWriter:
    """Appends the chunks of one run to its file and keeps /state current.

    ``create`` starts a new file, ``resume`` reopens one and returns the saved state.
    Before a chunk, ``fit_steps`` reserves its disk space. After each ``append`` call
    ``save_state``: the data are flushed first and the state second, so a state on disk
    never refers to data that did not reach it. ``finish`` writes the final root
    attributes and closes the file. If HDF5 fails while writing (``WriteFailed``), the
    writer is abandoned: the file stays as a killed writer would leave it.
    """

    def __init__(self, path: Path, file: h5py.File, datasets: dict, guard: _FileGuard | None = None,
                 sequence: int = 1):
        self.path = path
        self._file = file
        # Handles kept: h5py's name lookups cost more than the writes of a chunk.
        self._t, self._y = datasets["t"], datasets["y"]
        self._invariants = datasets["invariants"]    # in the column order of Chunk.invariants
        self._iterations = datasets["iterations"]
        self._substeps = datasets.get("substeps")    # absent in files written before the step engine
        self._multipliers = datasets.get("multipliers")
        self._state = datasets["state"]
        self._record = datasets.get("record")
        self._sequence = sequence
        self._guard = guard
        self.failed_step_iterations = None
        self.abandoned = False
        self.saved = {"steps_done": 0, "n_samples": 0, "t": math.nan}

    @classmethod
    def _from_file(cls, path: Path, f: h5py.File, guard, sequence: int) -> "RunWriter":
        steps = f["steps"]
        multipliers = next((steps[name] for name in _multiplier_datasets(steps)), None)
        order = [str(name) for name in _plain(f["invariants"].attrs["order"])]
        state = {name: dataset.id for name, dataset in f["state"].items() if name != "record"}
        return cls(path, f, {
            "t": _Growing(f["t"].id), "y": _Growing(f["y"].id),
            "invariants": [_Growing(f["invariants"][name].id) for name in order],
            "iterations": _Growing(steps["iterations"].id),
            "substeps": _Growing(steps["substeps"].id) if "substeps" in steps else None,
            "multipliers": _Growing(multipliers.id) if multipliers is not None else None,
            "state": state, "record": f["state"]["record"].id if "record" in f["state"] else None},
            guard=guard, sequence=sequence)

    # --- opening ---
    @classmethod
    def create(cls, path, integration, *, config_text: str, t_end: float | None = None,
               attributes: dict | None = None, overwrite: bool = True) -> "RunWriter":
        """Create ``path`` with the layout, the run's metadata and its sample at t0.

        The file is built under a temporary name and renamed to ``path`` once complete; an
        existing ``path`` is replaced (``overwrite``) unless another process is writing it.
        """
        path = Path(path)
        run, problem, method = integration, integration.problem, integration.method
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(f"{path}: cannot create: {_one_line(err)}") from None
        ensure_not_busy(path)
        free = _free_bytes(path.parent)
        if free is not None and free < SPACE_BASE:
            raise DiskFullError(f"{path}: the disk is full ({_size(free)} free); free some space, or write "
                                "the run elsewhere")
        temporary = _temporary_path(path)
        try:
            f = h5py.File(temporary, "w", libver=LIBVER)
        except OSError as err:
            with contextlib.suppress(OSError):
                temporary.unlink()
            if _is_disk_full(err):
                raise DiskFullError(f"{path}: the disk is full; free some space, or write the run elsewhere") from None
            raise OutputError(f"{path}: cannot create: {_one_line(err)}") from None
        guard = None
        try:
            guard = _FileGuard(temporary)
            guard.lock()
            mult = multiplier_name(run)
            names = ("H",) + tuple(problem.invariant_names)
            n_datasets = 4 + len(names) + (mult is not None)
            guard.reserve(SPACE_BASE + n_datasets * SPACE_MARGIN)
            _set_attributes(f, {
                **version_attributes(), "format": FORMAT, "format_version": FORMAT_VERSION,
                "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "config": config_text, "problem": problem.name, "method": method.name, "family": method.family,
                "r": method.r, "k": method.k, "s": method.s, "h": run.h, "t0": run.t0,
                "t_end": float(t_end) if t_end is not None else run.t0 + run.n_steps * run.h,
                "n_steps": run.n_steps, "output_every": run.store_every, "conserve": list(run.conserve),
                "steps_done": 0, "status": STATUS_RUNNING, "wall_time_s": 0.0, "kernel_time_s": 0.0,
                **(attributes or {})})
            datasets = {"t": _growing(f, "t", None, "f8"), "y": _growing(f, "y", run.y.size, "f8")}
            _set_attributes(datasets["y"], {"coordinates": list(problem.coordinate_names)})
            inv = f.create_group("invariants")
            _set_attributes(inv, {"order": list(names)})
            datasets["invariants"] = [_growing(inv, name, None, "f8") for name in names]
            for name, dataset in zip(names, datasets["invariants"]):
                _set_attributes(dataset, {"imposed": name in run.conserve})
            steps = f.create_group("steps")
            datasets["iterations"] = _growing(steps, "iterations", None, "i4")
            datasets["substeps"] = _growing(steps, "substeps", None, "i4")
            if mult is not None:
                datasets["multipliers"] = _growing(steps, mult, run.multipliers.size, "f8")
                _set_attributes(datasets["multipliers"],
                                {"invariants": list(method.multiplier_components(run.conserve))})
            _write_method(f.create_group("method"), method)

            state = f.create_group("state")
            initial = dict(run.state(), n_samples=np.int64(1), wall_time_s=0.0, kernel_time_s=0.0)
            datasets["state"] = {key: _small_dataset(state, key, value) for key, value in initial.items()}
            n, s = run.y.size, run.coef.shape[0]
            record = _record_dataset(state, _record_length(n, s, run.multipliers.size))
            for sequence in (0, 1):
                _write_record_row(record, sequence, _pack_record(run.state(), sequence, 1, 0.0, 0.0))
            datasets["record"] = record
            _mark_writer(state)

            writer = cls(path, f, datasets, guard=guard, sequence=1)
            writer.append(integration.initial_chunk())
            writer.saved = {"steps_done": run.steps_done, "n_samples": 1, "t": run.t}
            f.swmr_mode = True   # flushes: from here on the file on disk is always consistent
            _publish(temporary, path, overwrite)
            return writer
        except OutputError:                      # busy, or appeared meanwhile: HDF5 itself is fine
            _close_quietly(f, guard, temporary)
            raise
        except (OSError, RuntimeError) as err:   # HDF5 failed a write (or no room): never close it again
            _abandon(f, guard)
            with contextlib.suppress(OSError):
                temporary.unlink()
            if isinstance(err, DiskFullError) or _is_disk_full(err):
                raise DiskFullError(f"{path}: the disk is full; free some space, or write the run "
                                    "elsewhere") from None
            raise OutputError(f"{path}: cannot create: {_one_line(err)}") from None
        except BaseException:
            _close_quietly(f, guard, temporary)
            raise

    @classmethod
    def resume(cls, path, *, restore=None, stop=None, config_text: str | None = None) -> tuple["RunWriter", dict]:
        """Reopen a run for writing; return (writer, saved) with saved = the state and the root attributes.

        Nothing is changed until everything the run will build on has been read back and
        found sound (``RunFile.verify``: metadata checksums, fletcher32 of every chunk up
        to the saved state, the state record) and ``restore(saved)`` has accepted the
        state (it raises ValueError or KeyError if the state does not fit the run). A file
        left by a killed writer (SWMR flags still set) is then repaired; if reopening it
        still fails, the flags are put back as they were. ``config_text``: the resolved
        config the run continues with, when its solver settings differ from the stored
        one's; it replaces the stored config, and ``solver_history`` records the change.
        """
        path = Path(path)
        if not path.exists():
            raise OutputError(f"{path}: no such file to resume")
        _regular_file(path, "run file")
        if not h5py.is_hdf5(path):
            raise NotAnElimfastFile(f"{path}: not an HDF5 file, so not an elimfast run to resume")
        ensure_not_busy(path)
        with RunFile(path) as existing:
            saved = existing.saved_state()
            existing.verify(stop=stop)
            n_datasets = 4 + len(existing.invariant_names) + (existing.multiplier_name is not None)
        # A format 1 file (no checksums, no record) is continued in its own format.
        if restore is not None:
            try:
                restore(saved)
            except (KeyError, ValueError) as err:
                raise OutputError(f"{path}: the stored state does not fit this run ({err})") from None
        flags = consistency_flags(path)
        guard = _FileGuard(path)
        try:
            if not guard.lock():
                raise FileBusyError(f"{path}: is being written by another process; stop it first")
            guard.reserve(SPACE_BASE + n_datasets * SPACE_MARGIN)
        except DiskFullError as err:
            guard.close()
            raise DiskFullError(f"{err}; free some space, then resume again") from None
        except BaseException:
            guard.close()
            raise
        if flags:
            clear_consistency_flags(path)
        try:
            f = h5py.File(path, "r+", libver=LIBVER)
        except OSError as err:
            guard.close()
            if flags:
                with contextlib.suppress(OSError, OutputError):
                    set_consistency_flags(path, flags)
            raise OutputError(f"{path}: cannot open for resuming: {_one_line(err)}") from None
        try:
            attrs = {key: _plain(value) for key, value in f.attrs.items()}
            # Drop rows of the chunk that was being written when the run stopped.
            for d in _sample_datasets(f):
                d.resize(saved["n_samples"], axis=0)
            for d in f["steps"].values():
                d.resize(saved["steps_done"], axis=0)
            f.attrs["status"] = STATUS_RUNNING
            if config_text is not None:
                history = list(_plain(f.attrs.get("solver_history", [])) or [])
                history.append(f"from step {saved['steps_done']}: {_solver_line(config_text)} "
                               f"(before: {_solver_line(str(attrs.get('config', '')))})")
                _replace_attributes(f, {"config": config_text, "solver_history": history})
            for key in ("failed_step_iterations",):
                if key in f.attrs:
                    del f.attrs[key]
            _mark_writer(f["state"])
            f.flush()
            f.swmr_mode = True
        except (OSError, RuntimeError) as err:
            _abandon(f, guard)
            if _is_disk_full(err):
                raise DiskFullError(f"{path}: the disk is full; free some space, then resume again") from None
            raise OutputError(f"{path}: cannot be resumed: {_one_line(err)}") from None
        except BaseException:
            _close_quietly(f, guard, None)
            raise
        writer = cls._from_file(path, f, guard, saved.get("sequence", 1))
        writer.saved = {"steps_done": saved["steps_done"], "n_samples": saved["n_samples"],
                        "t": float(saved["clock"][0])}
        saved["attrs"] = attrs
        return writer, saved

    # --- disk space ---
    @property
    def n_datasets(self) -> int:
        return 3 + len(self._invariants) + (self._substeps is not None) + (self._multipliers is not None)

    def fit_steps(self, steps: int, step_bytes: float) -> int:
        """How many of ``steps`` steps (at ``step_bytes`` each) the disk can take; their
        space is reserved. 0: not even one step fits (the disk is full)."""
        if self._guard is None:
            return steps
        margin = SPACE_BASE + self.n_datasets * SPACE_MARGIN
        try:
            self._guard.reserve(margin + SPACE_FACTOR * steps * step_bytes)
            return steps
        except DiskFullError:
            pass
        free = (self._guard.available() or 0) + self._guard.reserved()
        fitting = int((free - margin) // max(SPACE_FACTOR * step_bytes, 1.0))
        if fitting < 1:
            return 0
        try:
            self._guard.reserve(margin + SPACE_FACTOR * fitting * step_bytes)
        except DiskFullError:
            return 0
        return min(steps, fitting)

    # --- writing ---
    def append(self, chunk) -> None:
        """Extend every dataset by the chunk's samples and steps (not yet flushed)."""
        self._t.append(chunk.t)
        self._y.append(chunk.y)
        for column, dataset in enumerate(self._invariants):
            dataset.append(chunk.invariants[:, column])
        steps_done = len(chunk.multipliers)
        iterations = chunk.iterations
        if len(iterations) > steps_done:   # a failed step's count: kept apart, rows stay per done step
            self.failed_step_iterations = int(iterations[steps_done])
            iterations = iterations[:steps_done]
        self._iterations.append(iterations)
        if self._substeps is not None:
            self._substeps.append(chunk.substeps)
        if self._multipliers is not None:
            self._multipliers.append(chunk.multipliers)

    def save_state(self, state: dict, *, wall_time_s: float, kernel_time_s: float) -> None:
        """Flush the appended data, then write and flush the state (two flushes: see class doc)."""
        self._file.flush()
        n_samples = self._t.rows
        if self._record is not None:
            self._sequence += 1
            _write_record_row(self._record, self._sequence % 2,
                              _pack_record(state, self._sequence, n_samples, wall_time_s, kernel_time_s))
        values = dict(state, n_samples=n_samples, wall_time_s=wall_time_s, kernel_time_s=kernel_time_s)
        for key, value in values.items():
            dataset = self._state.get(key)
            if dataset is None:     # last_h, newton_base: a file written before the step engine (no record)
                continue
            dataset.write(h5py.h5s.ALL, h5py.h5s.ALL, np.ascontiguousarray(value, dtype=dataset.dtype))
        self._file.flush()
        self.saved = {"steps_done": int(state["steps_done"]), "n_samples": n_samples,
                      "t": float(np.asarray(state["clock"])[0])}

    def finish(self, status: str, *, steps_done: int, wall_time_s: float, kernel_time_s: float) -> None:
        """Close the SWMR session, then write the final root attributes in a normal session.

        Rows appended after the last saved state (a chunk cut short) are dropped first, so
        the datasets end where the saved state says.
        """
        if self.abandoned:
            return
        if self._guard is not None:
            self._guard.reserve(SPACE_BASE)
        saved_samples, saved_steps = self.saved["n_samples"], self.saved["steps_done"]
        cut_short = self._t.rows > saved_samples or self._iterations.rows > saved_steps
        self._file.close()
        try:
            with h5py.File(self.path, "r+", libver=LIBVER) as f:
                if cut_short:
                    for d in _sample_datasets(f):
                        if d.shape[0] > saved_samples:
                            d.resize(saved_samples, axis=0)
                    for d in f["steps"].values():
                        if d.shape[0] > saved_steps:
                            d.resize(saved_steps, axis=0)
                f.attrs["status"] = status
                f.attrs["steps_done"] = min(steps_done, saved_steps)
                f.attrs["wall_time_s"] = wall_time_s
                f.attrs["kernel_time_s"] = kernel_time_s
                if self.failed_step_iterations is not None:
                    f.attrs["failed_step_iterations"] = self.failed_step_iterations
        finally:
            if self._guard is not None:
                self._guard.close()

    def close(self) -> None:
        """Close without final attributes (the file stays valid, status 'running')."""
        if self.abandoned:
            return
        try:
            if self._file.id.valid:
                self._file.close()
        finally:
            if self._guard is not None:
                self._guard.close()

    def abandon(self) -> None:
        """After HDF5 failed a write: never touch the file again (see _ABANDONED)."""
        if not self.abandoned:
            self.abandoned = True
            _abandon(self._file, self._guard, keep=self)


def _abandon(f, guard, keep=None) -> None:
    _ABANDONED.append((f, keep))
    if guard is not None:
        guard.close()


def _close_quietly(f, guard, temporary) -> None:
    with contextlib.suppress(Exception):
        if f.id.valid:
            f.close()
    if guard is not None:
        guard.close()
    if temporary is not None:
        with contextlib.suppress(OSError):
            temporary.unlink()


SWEEP_FORMAT = "elimfast-sweep"


def sweep_group_name(label: str) -> str:
    """The group of a sweep run: its label with '/' (an HDF5 path separator) written as '|',
    and a label of only dots ('.', '..': not names HDF5 accepts) prefixed with '_'."""
    name = label.replace("/", "|")
    return "_" + name if not name.strip(".") else name


class SweepWriter:
    """One HDF5 file for a whole sweep: /runs/<label>/ per run, in the layout of a run file.

    Each run's group holds t, y, invariants/<name>, steps/iterations, steps/alpha or
    steps/lambda, method/..., and the run attributes of a run file (config, problem,
    method, h, n_steps, steps_done, status, wall_time_s, ...) plus ``label`` and the
    run's coordinates on the sweep's axes. There is no /state: a sweep run is not
    resumable on its own; rerun the sweep. Runs are written and flushed as they finish,
    so a killed sweep keeps every finished run. The file is built under a temporary
    name and renamed into place (an existing file another process uses is refused).
    """

    def __init__(self, path, *, sweep_text: str, attributes: dict | None = None, overwrite: bool = True):
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutputError(f"{self.path}: cannot create: {_one_line(err)}") from None
        ensure_not_busy(self.path)
        temporary = _temporary_path(self.path)
        try:
            self._file = h5py.File(temporary, "w", libver=LIBVER)
        except OSError as err:
            with contextlib.suppress(OSError):
                temporary.unlink()
            raise OutputError(f"{self.path}: cannot create: {_one_line(err)}") from None
        self._guard = None
        try:
            self._guard = _FileGuard(temporary)
            self._guard.reserve(SPACE_BASE + len(sweep_text))
            _set_attributes(self._file, {
                **version_attributes(), "format": SWEEP_FORMAT, "format_version": FORMAT_VERSION,
                "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "sweep": sweep_text, **(attributes or {})})
            self._runs = self._file.create_group("runs")
            self._file.flush()
            _publish(temporary, self.path, overwrite)
        except DiskFullError:
            _close_quietly(self._file, self._guard, temporary)
            raise DiskFullError(f"{self.path}: the disk is full; free some space, or write the sweep elsewhere") \
                from None
        except BaseException:
            _close_quietly(self._file, self._guard, temporary)
            raise

    def _writing(self):
        """HDF5 failing a write (a full disk): abandon the file (see _ABANDONED) and say so."""
        return _SweepWriting(self)

    def _reserve(self, arrays) -> None:
        """Room for a run's arrays before HDF5 writes any of them: DiskFullError leaves the
        file as the last flush left it (closed normally, every stored run in it)."""
        n_bytes = sum(getattr(value, "nbytes", 0) for value in arrays)
        try:
            self._guard.reserve(SPACE_BASE + SPACE_FACTOR * n_bytes)
        except DiskFullError:
            raise DiskFullError(f"{self.path}: the disk is full; the runs stored before this one are in the "
                                "file") from None

    def add_run(self, outcome, method, *, group_name: str | None = None) -> None:
        """Store one finished (or failed) sweep run; outcome is an elimfast.sweep.RunOutcome."""
        self._reserve((outcome.arrays or {}).values())
        with self._writing():
            self._add_run(outcome, method, group_name)

    def _add_run(self, outcome, method, group_name) -> None:
        import yaml

        group = self._runs.create_group(group_name or sweep_group_name(outcome.label))
        resolved = outcome.resolved or {}
        attributes = {"label": outcome.label, "status": outcome.status, "steps_done": outcome.steps_done,
                      "n_steps": outcome.n_steps, "wall_time_s": outcome.wall_time,
                      "config": yaml.safe_dump(resolved, sort_keys=False, default_flow_style=None, width=100)}
        attributes.update({f"axis_{axis}": value for axis, value in outcome.coordinates.items()})
        if method is not None:
            integration = resolved.get("integration", {})
            attributes.update({"method": method.name, "family": method.family, "r": method.r, "k": method.k,
                               "s": method.s, "h": outcome.h, "t0": float(integration.get("t0", 0.0)),
                               "conserve": list(resolved.get("conserve", []))})
            problem = resolved.get("problem", {})
            attributes["problem"] = str(problem.get("builtin") or problem.get("name") or "user-defined")
            _write_method(group.create_group("method"), method)
        _set_attributes(group, attributes)
        arrays = outcome.arrays
        if arrays:
            _small_dataset(group, "t", arrays["t"])
            y = _small_dataset(group, "y", arrays["y"])
            _set_attributes(h5py.Dataset(y), {"coordinates": list(arrays["coordinate_names"])})
            invariants = group.create_group("invariants")
            names = list(arrays["invariant_names"])
            _set_attributes(invariants, {"order": names})
            imposed = set(resolved.get("conserve", []))
            for column, name in enumerate(names):
                dataset = _small_dataset(invariants, name, arrays["invariants"][:, column])
                _set_attributes(h5py.Dataset(dataset), {"imposed": name in imposed})
            steps = group.create_group("steps")
            done = outcome.steps_done
            _small_dataset(steps, "iterations", arrays["iterations"][:done].astype("i4"))
            if arrays["multiplier_name"] is not None:
                _small_dataset(steps, arrays["multiplier_name"], arrays["multipliers"][:done])
        self._file.flush()

    def add_ensemble(self, result, states, resolved: dict) -> None:
        """Store an ensemble sweep under /ensemble: per trajectory y0, y_final, t_final,
        iterations (totals), max_multiplier, status (0 ok), steps_done, and
        invariant_errors/<name> (max |I(t) - I(0)|); the failure reasons as an attribute."""
        self._reserve([states, result.y_final, *result.invariant_errors.values()]
                      + [getattr(result, name) for name in ("t_final", "iterations", "max_multiplier", "status",
                                                            "steps_done")])
        with self._writing():
            self._add_ensemble(result, states, resolved)

    def _add_ensemble(self, result, states, resolved: dict) -> None:
        import yaml

        group = self._file.create_group("ensemble")
        _set_attributes(group, {
            "problem": result.problem.name, "method": result.method.name, "h": result.h,
            "n_steps": result.n_steps, "conserve": list(result.conserve) or [""], "threads": result.n_threads,
            "config": yaml.safe_dump(resolved, sort_keys=False, default_flow_style=None, width=100),
            "failed": result.n_failed, "reasons": list(result.reasons) or [""]})
        y0 = _small_dataset(group, "y0", states)
        _set_attributes(h5py.Dataset(y0), {"coordinates": list(result.problem.coordinate_names)})
        for name in ("y_final", "t_final", "iterations", "max_multiplier", "status", "steps_done"):
            _small_dataset(group, name, getattr(result, name))
        errors = group.create_group("invariant_errors")
        for name, values in result.invariant_errors.items():
            _small_dataset(errors, name, values)
        _write_method(group.create_group("method"), result.method)
        self._file.flush()

    def close(self) -> None:
        try:
            if not getattr(self, "abandoned", False) and self._file.id.valid:
                self._file.close()
        finally:
            if self._guard is not None:
                self._guard.close()


class _SweepWriting:
    def __init__(self, writer: SweepWriter):
        self.writer = writer

    def __enter__(self):
        if getattr(self.writer, "abandoned", False):
            raise OutputError(f"{self.writer.path}: an earlier write failed; the file holds the runs before it")
        return self

    def __exit__(self, kind, err, traceback):
        if kind is not None and issubclass(kind, (OSError, RuntimeError)) and not issubclass(kind, ElimfastError):
            self.writer.abandoned = True
            _abandon(self.writer._file, None, keep=self.writer)
            if _is_disk_full(err):
                raise DiskFullError(f"{self.writer.path}: the disk is full; the runs stored before this one are "
                                    "in the file") from None
            raise OutputError(f"{self.writer.path}: cannot write ({_one_line(err)[:200]}); the runs stored before "
                              "this one are in the file") from None
        return False


def _mark_writer(state_group) -> None:
    state_group.attrs["writer_pid"] = os.getpid()
    state_group.attrs["writer_host"] = socket.gethostname()


def _sample_datasets(f):
    yield f["t"]
    yield f["y"]
    yield from f["invariants"].values()


def _write_method(group, method) -> None:
    if method.has_runge_kutta_form:
        A, b, c = method.butcher()
        for name, table in (("A", A), ("b", b), ("c", c)):
            _small_dataset(group, name, table)
        if method.kind.scales_tableau:
            tableau = (f"the underlying HBVM({method.k},{method.s}) tableau (eta = 1); each ELIM step scales it "
                       "with eta_j = 1 - h^(2(s-1-j)) alpha_j (docs/methods.md#elim)")
        else:
            tableau = f"{method.name}: A, b, c of its Runge-Kutta form"
    else:
        tableau = f"{method.name} has no fixed Runge-Kutta form (its correction acts through phi_0, docs/methods.md#lim)"
    _set_attributes(group, {"order": method.order, "tableau": tableau,
                            "quadrature": f"{method.k}-point Gauss-Legendre on [0, 1] for H"
                                          + (f", {method.r}-point for the invariants" if method.imposes_invariants
                                             else "")})
    _small_dataset(group, "quadrature_nodes", method.c)
    _small_dataset(group, "quadrature_weights", method.b)
    if method.imposes_invariants:
        _small_dataset(group, "invariant_quadrature_nodes", method.chat)
        _small_dataset(group, "invariant_quadrature_weights", method.bhat)


def _solver_line(config_text: str) -> str:
    """The solver section of a resolved config, on one line."""
    import yaml
    try:
        solver = (yaml.safe_load(config_text) or {}).get("solver") or {}
    except (yaml.YAMLError, AttributeError):
        return "?"
    return ", ".join(f"{key} {value}" for key, value in solver.items()) if isinstance(solver, dict) else "?"


def _replace_attributes(obj, values: dict) -> None:
    for name in values:
        if name in obj.attrs:
            del obj.attrs[name]
    _set_attributes(obj, values)


def _set_attributes(obj, values: dict) -> None:
    """Create attributes through h5py's low-level API (numbers, strings, lists of strings, arrays)."""
    for name, value in values.items():
        if isinstance(value, str) or (isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value)):
            data = np.array(value, dtype=h5py.string_dtype())
        else:
            data = np.asarray(value)
        space = h5py.h5s.create(h5py.h5s.SCALAR) if data.ndim == 0 else h5py.h5s.create_simple(data.shape)
        attribute = h5py.h5a.create(obj.id, name.encode(), h5py.h5t.py_create(data.dtype, logical=True), space)
        attribute.write(data, mtype=h5py.h5t.py_create(data.dtype))


def _small_dataset(group, name: str, value):
    """A small contiguous dataset (tables, /state) written at once; returns its low-level id."""
    data = np.array(value, order="C")   # (ascontiguousarray would make a scalar 1-d)
    space = h5py.h5s.create(h5py.h5s.SCALAR) if data.ndim == 0 else h5py.h5s.create_simple(data.shape)
    dataset_id = h5py.h5d.create(group.id, name.encode(), h5py.h5t.py_create(data.dtype), space)
    dataset_id.write(h5py.h5s.ALL, h5py.h5s.ALL, data)
    return dataset_id


# --- reading -----------------------------------------------------------------------------
def _plain(value):
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()] if value.dtype.kind in "OSU" else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value


_STATE_MEMBERS = ("y", "y_comp", "clock", "coef", "multipliers", "steps_done", "n_samples", "wall_time_s",
                  "kernel_time_s")
_LAYOUT = ("t", "y", "invariants", "steps", "steps/iterations", "method", "state",
           *(f"state/{name}" for name in _STATE_MEMBERS))
_DAMAGE_ADVICE = "restore it from a copy, or start the run again with --overwrite"


def _hdf5_reason(err: BaseException) -> str:
    """What an HDF5 error means, in a few words (its full text is a stack of library calls)."""
    text = _one_line(err)
    if "checksum" in text and "metadata" in text:
        return "a metadata checksum does not match"
    if "filter returned failure" in text or "Fletcher32" in text or "fletcher32" in text:
        return "a data chunk fails its fletcher32 checksum"
    if isinstance(err, KeyError) and ("doesn't exist" in text or "not found" in text or "no such" in text.lower()):
        return f"missing {text}"
    return text if len(text) <= 160 else text[:157] + "..."


def _damaged(path, where: str, err: BaseException) -> DamagedFileError:
    return DamagedFileError(f"{path} is damaged at {where} ({_hdf5_reason(err)}); {_DAMAGE_ADVICE}")


def _require_ours(path, f) -> None:
    """The format attribute, a version this reader knows, and every member of the layout."""
    try:
        names = set(f.attrs)    # listing them reads the whole attribute index: damage shows here
        fmt = _plain(f.attrs["format"]) if "format" in names else None
        version = int(f.attrs["format_version"]) if "format_version" in names else 0
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as err:
        raise _damaged(path, "its root attributes", err) from None
    if fmt != FORMAT:
        what = f"its format is {fmt!r}" if fmt else f"no '{FORMAT}' format attribute"
        raise NotAnElimfastFile(f"{path}: not an elimfast run file ({what}); give a file written by 'elimfast run'")
    if version > FORMAT_VERSION:
        raise OutputError(f"{path}: written in elimfast run format {version}; this elimfast reads up to "
                          f"{FORMAT_VERSION}: upgrade elimfast")
    for name in _LAYOUT:
        try:
            present = name in f
        except (OSError, RuntimeError, KeyError, ValueError) as err:
            raise _damaged(path, f"/{name}", err) from None
        if not present:
            raise DamagedFileError(f"{path} is damaged or incomplete: it has the elimfast run format but no /{name}; "
                                   f"{_DAMAGE_ADVICE}")


class RunFile:
    """A run file opened for reading (read-only; a killed run's file is opened in SWMR mode).

    ``attrs``: root attributes as plain Python values; ``steps_done`` and
    ``n_samples``: the rows that are consistent (from the saved state); ``status``: the
    recorded status, or 'killed' / 'running' for a file whose writer did not finish
    (decided by whether the writer process is alive). Every read that fails (a checksum,
    a missing member) raises DamagedFileError naming the file and the place.
    """

    def __init__(self, path):
        self.path = Path(path)
        self._file = _open(self.path)
        try:
            _require_ours(self.path, self._file)
            with self._reading("the layout"):
                self._load()
        except BaseException:
            self.close()
            raise

    def _load(self) -> None:
        f = self._file
        with self._reading("the root attributes"):
            self.attrs = {key: _plain(value) for key, value in f.attrs.items()}
        self._saved = self._read_state()
        self.steps_done = self._saved["steps_done"]
        with self._reading("/t"):
            self.n_samples = min(self._saved["n_samples"], f["t"].shape[0])
        self.wall_time_s = self._saved["wall_time_s"]
        self.kernel_time_s = self._saved["kernel_time_s"]
        self.status = str(self.attrs.get("status", "?"))
        if self.status == STATUS_RUNNING:
            if int(self.attrs.get("format_version", 1)) >= 2:   # its writer holds the lock while it lives
                alive = _writer_lock_held(self.path)
            else:
                state = f["state"]
                pid = int(state.attrs.get("writer_pid", 0))
                host = str(_plain(state.attrs.get("writer_host", "")))
                alive = host == socket.gethostname() and pid and _process_alive(pid) and pid != os.getpid()
            self.status = STATUS_RUNNING if alive else "killed"
        with self._reading("/y"):
            self.coordinate_names = [str(n) for n in _plain(f["y"].attrs.get("coordinates", []))]
        with self._reading("/invariants"):
            self.invariant_names = [str(n) for n in _plain(f["invariants"].attrs["order"])]
            self.imposed = {name: bool(f["invariants"][name].attrs.get("imposed", False))
                            for name in self.invariant_names}
        with self._reading("/steps"):
            self.multiplier_name = next(iter(_multiplier_datasets(f["steps"])), None)

    @contextlib.contextmanager
    def _reading(self, where: str):
        """Turn any failure of HDF5 inside the block into DamagedFileError naming ``where``."""
        try:
            yield
        except ElimfastError:
            raise
        except (KeyError, OSError, RuntimeError, ValueError, TypeError, IndexError) as err:
            raise _damaged(self.path, where, err) from None

    def _read_state(self) -> dict:
        """The saved state: the valid row of /state/record with the higher sequence number
        (format 2), or the named /state datasets (format 1)."""
        state = self._file["state"]
        with self._reading("/state"):
            named = {key: np.array(state[key][()]) for key in _STATE_MEMBERS}
        if "record" not in state:
            return {**named, "steps_done": int(named["steps_done"]), "n_samples": int(named["n_samples"]),
                    "wall_time_s": float(named["wall_time_s"]), "kernel_time_s": float(named["kernel_time_s"])}
        n, (s, _), n_mult = named["y"].size, named["coef"].shape, named["multipliers"].size
        best, problems = None, []
        for slot in (0, 1):
            try:
                row = self._file["state/record"][slot]
            except (KeyError, OSError, RuntimeError, ValueError) as err:
                problems.append(f"row {slot}: {_hdf5_reason(err)}")
                continue
            values = _unpack_record(np.asarray(row, dtype=np.float64), n, s, n_mult)
            if values is None:
                problems.append(f"row {slot} fails its CRC")
            elif best is None or values["sequence"] > best["sequence"]:
                best = values
        if best is None:
            raise DamagedFileError(f"{self.path} is damaged at /state/record: neither copy of the saved state is "
                                   f"sound ({'; '.join(problems)}); {_DAMAGE_ADVICE}")
        return best

    def saved_state(self) -> dict:
        """What resume continues from: y, y_comp, clock, coef, multipliers, steps_done,
        n_samples, wall_time_s, kernel_time_s (and the record's sequence number)."""
        return {key: (value.copy() if isinstance(value, np.ndarray) else value) for key, value in self._saved.items()}

    def verify(self, stop=None) -> dict:
        """Read every stored row the saved state counts (and the method tables) block by
        block, so that HDF5 checks every metadata checksum and every chunk's fletcher32;
        DamagedFileError at the first failure, also if a dataset is shorter than the state
        says. ``stop``: an object whose ``requested`` ends the check early (KeyboardInterrupt).
        Returns {"chunks": HDF5 chunks read, "checksummed": whether they carry fletcher32}."""
        f = self._file
        targets = [("/t", "t", self._saved["n_samples"]), ("/y", "y", self._saved["n_samples"])]
        targets += [(f"/invariants/{name}", f"invariants/{name}", self._saved["n_samples"])
                    for name in self.invariant_names]
        with self._reading("/steps"):
            targets += [(f"/steps/{name}", f"steps/{name}", self._saved["steps_done"]) for name in f["steps"]]
        chunks, checksummed = 0, True
        for where, name, count in targets:
            with self._reading(where):
                dataset = f[name]
                if dataset.shape[0] < count:
                    raise DamagedFileError(f"{self.path} is damaged or incomplete at {where}: it has "
                                           f"{dataset.shape[0]} rows, the saved state counts {count}; "
                                           f"{_DAMAGE_ADVICE}")
                checksummed = checksummed and bool(dataset.fletcher32)
                chunk_rows = dataset.chunks[0] if dataset.chunks else max(count, 1)
                row_bytes = dataset.dtype.itemsize * int(np.prod(dataset.shape[1:], dtype=np.int64))
                block = max(1, VERIFY_BLOCK_BYTES // max(row_bytes, 1) // chunk_rows) * chunk_rows
            for start in range(0, count, block):
                if stop is not None and stop.requested:
                    raise KeyboardInterrupt
                end = min(count, start + block)
                with self._reading(f"{where} rows {start}-{end - 1}"):
                    dataset[start:end]
            chunks += -(-count // chunk_rows)
        with self._reading("/method"):
            for name in f["method"]:
                f["method"][name][()]
        return {"chunks": chunks, "checksummed": checksummed}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self) -> None:
        if getattr(self, "_file", None) is not None and self._file.id.valid:
            self._file.close()

    @property
    def swmr(self) -> bool:
        return bool(self._file.swmr_mode)

    # --- data ---
    def _rows(self, name: str, count: int, stride: int) -> np.ndarray:
        with self._reading(f"/{name}"):
            return self._file[name][:count:stride]

    def t(self, stride: int = 1) -> np.ndarray:
        return self._rows("t", self.n_samples, stride)

    def y(self, stride: int = 1) -> np.ndarray:
        return self._rows("y", self.n_samples, stride)

    def invariant(self, name: str, stride: int = 1) -> np.ndarray:
        return self._rows(f"invariants/{name}", self.n_samples, stride)

    def iterations(self, stride: int = 1) -> np.ndarray:
        return self._rows("steps/iterations", self.steps_done, stride)

    def multipliers(self, stride: int = 1) -> np.ndarray | None:
        if self.multiplier_name is None:
            return None
        return self._rows(f"steps/{self.multiplier_name}", self.steps_done, stride)

    def multiplier_labels(self) -> list[str]:
        if self.multiplier_name is None:
            return []
        with self._reading(f"/steps/{self.multiplier_name}"):
            names = _plain(self._file["steps"][self.multiplier_name].attrs.get("invariants", []))
        return [f"{self.multiplier_name}[{name}]" for name in names]

    def method_table(self, name: str) -> np.ndarray | None:
        with self._reading(f"/method/{name}"):
            group = self._file["method"]
            return group[name][()] if name in group else None

    def final_state(self) -> dict:
        return self.saved_state()

    # --- reductions, block by block (memory bounded for any length) ---
    def _blocks(self, name: str, stop: int):
        dataset = self._file[name]
        row_bytes = dataset.dtype.itemsize * int(np.prod(dataset.shape[1:], dtype=np.int64))
        block = max(1, VERIFY_BLOCK_BYTES // max(row_bytes, 1))
        for start in range(0, stop, block):
            end = min(stop, start + block)
            with self._reading(f"/{name} rows {start}-{end - 1}"):
                yield dataset[start:end]

    def invariant_drift(self) -> dict[str, float]:
        """max over the stored samples of |I(t) - I(t0)| for H and every invariant."""
        drift = {}
        for name in self.invariant_names:
            if self.n_samples == 0:
                drift[name] = math.nan
                continue
            first = None
            largest = 0.0
            for block in self._blocks(f"invariants/{name}", self.n_samples):
                if first is None:
                    first = float(block[0])
                largest = max(largest, float(np.max(np.abs(block - first))))
            drift[name] = largest
        return drift

    def iteration_stats(self) -> dict:
        count, total, low, high = 0, 0, None, None
        histogram = np.zeros(0, dtype=np.int64)
        for block in self._blocks("steps/iterations", self.steps_done):
            if block.size == 0:
                continue
            count += block.size
            total += int(block.sum(dtype=np.int64))
            low = int(block.min()) if low is None else min(low, int(block.min()))
            high = int(block.max()) if high is None else max(high, int(block.max()))
            counts = np.bincount(np.maximum(block, 0).astype(np.int64))
            if counts.size > histogram.size:
                counts[:histogram.size] += histogram
                histogram = counts
            else:
                histogram[:counts.size] += counts
        if count == 0:
            return {"count": 0}
        cumulative = np.cumsum(histogram)
        median = int(np.searchsorted(cumulative, (count + 1) // 2))
        p99 = int(np.searchsorted(cumulative, math.ceil(0.99 * count)))
        return {"count": count, "total": total, "mean": total / count, "min": low, "median": median,
                "p99": p99, "max": high}

    def initial_invariants(self) -> dict[str, float]:
        """H and every invariant at the first sample (t0), NaN when there is none."""
        values = {}
        for name in self.invariant_names:
            first = math.nan
            for block in self._blocks(f"invariants/{name}", min(self.n_samples, 1)):
                first = float(block[0])
            values[name] = first
        return values

    def substep_stats(self) -> dict:
        """{"split": steps split into substeps (docs/solver.md), "max": the most substeps of
        one step}; zeros for a file written before the step engine (no /steps/substeps)."""
        with self._reading("/steps"):
            present = "substeps" in self._file["steps"]
        split, largest = 0, 1 if self.steps_done else 0
        if present:
            for block in self._blocks("steps/substeps", self.steps_done):
                if block.size:
                    split += int(np.count_nonzero(block > 1))
                    largest = max(largest, int(block.max()))
        return {"split": split, "max": largest}

    def max_abs_multipliers(self) -> list[float]:
        if self.multiplier_name is None:
            return []
        name = f"steps/{self.multiplier_name}"
        with self._reading(f"/{name}"):
            width = self._file[name].shape[1]
        result = np.zeros(width)
        for block in self._blocks(name, self.steps_done):
            if block.size:
                result = np.maximum(result, np.max(np.abs(block), axis=0))
        return result.tolist()
