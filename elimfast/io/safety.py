"""File safety for elimfast's HDF5 files: locks, disk space, atomic creation, SWMR crash recovery, bounded opening.

Nothing here knows the layout of a run or a sweep (``layout.py``, ``runfile.py``,
``sweepfile.py``); every writer and reader goes through these helpers.

Writers. A new file is built under a temporary name beside the output and renamed over
it only when its layout is complete, so an existing file is never truncated in place.
While a run writes a file it holds an exclusive lock on it (a Linux open-file-description
lock, which HDF5's own locking does not see: HDF5 drops its lock in SWMR mode), and
``--overwrite`` and ``--resume`` refuse a file that another live process holds. Before
each chunk the writer reserves its disk space (``fallocate``): when the file system is
full, or the file would pass the file-size limit (``ulimit -f``), the run stops at the chunk
boundary with a clean, resumable file, instead of HDF5 failing part-way through a write
(after which HDF5 2.0 crashes on closing the file).

Crash recovery. Run files are written in HDF5's single-writer/multiple-reader (SWMR)
mode, whose ordered metadata writes keep the file consistent at every instant. After a
kill the superblock keeps its "open for writing" flags, so plain HDF5 readers (h5py
without ``swmr=True``, xarray, netCDF tools) refuse the file: ``repair`` clears them
(as ``h5clear -s``) once no writer holds the file; elimfast's own readers open such a
file in SWMR mode, and ``--resume`` clears the flags itself.

Damage. Metadata carry HDF5's checksums (lookup3) and data chunks fletcher32, so
corruption is detected on reading. SWMR readers retry a metadata read whose checksum
fails (a writer may be in the middle of rewriting it); HDF5's default of 100 attempts
with exponential backoff turns one damaged block into hours of retrying, so readers here
allow ``METADATA_READ_ATTEMPTS``.
"""
from __future__ import annotations

import atexit
import contextlib
import ctypes
import ctypes.util
import errno
import fcntl
import hashlib
import io
import os
import resource
import socket
import stat
import struct
import typing
import weakref
from pathlib import Path

import h5py
import numpy as np

from ..errors import DiskFullError, ElimfastError

# SWMR metadata read attempts. HDF5 backs off exponentially between attempts: on a damaged
# block, 20 attempts took 7 ms, 30 took 1.1 s and 50 more than 100 s (HDF5 2.0, measured).
METADATA_READ_ATTEMPTS = 20
REPAIR_HINT = "elimfast repair {path}"   # what makes a killed run's file readable by other HDF5 tools


class OutputError(ElimfastError):
    """The output file cannot be created, overwritten, resumed or read as asked."""


class NotAnElimfastFile(OutputError):
    """The file is HDF5 (or not even that) but was not written by elimfast."""


class DamagedFileError(OutputError):
    """A run file whose metadata or data fail their checksums, or that lacks part of the layout."""


class FileBusyError(OutputError):
    """Another live process is writing the file."""


class FileSizeLimitError(DiskFullError):
    """The output file would grow past the largest file this process may write (RLIMIT_FSIZE:
    the shell's ``ulimit -f``): the run stops as on a full disk, its file closed and resumable."""


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


def _is_file_too_large(err: BaseException) -> bool:
    """Whether an OSError (or an HDF5 error, whose text carries the errno) means EFBIG: the
    file-size limit (ulimit -f), a per-file quota, or the file system's largest file."""
    if isinstance(err, FileSizeLimitError) or getattr(err, "errno", None) == errno.EFBIG:
        return True
    text = str(err)
    return f"errno = {errno.EFBIG}," in text or "File too large" in text


def _file_size_limit() -> int | None:
    """The largest file this process may write, in bytes (the soft RLIMIT_FSIZE, which the shell's
    ``ulimit -f`` sets); None when unlimited. Python ignores SIGXFSZ, so a write past it fails
    with EFBIG, part-way through an HDF5 flush: the writers check it before, as they check free space."""
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    except (OSError, ValueError):
        return None
    return None if soft == resource.RLIM_INFINITY or soft < 0 else int(soft)


class NoRoom(typing.NamedTuple):
    """Why a write has no room, in a message's words: ``short`` for a status ('disk full at step
    12'), ``sentence`` after a file's name, ``fix`` what the user does before continuing."""
    short: str
    sentence: str
    fix: str


def no_room(err: BaseException | None) -> NoRoom | None:
    """The one wording of every 'no room' message (a full disk or quota; a file-size limit), or
    None when ``err`` is another failure."""
    if err is None:
        return None
    if _is_file_too_large(err):
        limit = _file_size_limit()
        if limit is None:   # a per-file quota, or the file system's largest file
            return NoRoom("file too large", "the file has reached the largest size allowed here (File too large)",
                          "write it where larger files are allowed, or raise that limit")
        return NoRoom("file-size limit reached", f"the file-size limit (ulimit -f: {_size(limit)}) is reached",
                      "raise the limit (ulimit -f unlimited)")
    if isinstance(err, DiskFullError) or _is_disk_full(err):
        return NoRoom("disk full", "the disk is full", "free some space")
    return None


def _free_bytes(directory: Path) -> int | None:
    try:
        info = os.statvfs(directory)
    except OSError:
        return None
    return info.f_bavail * info.f_frsize


def _size(n_bytes: float) -> str:
    """A size for a message: '18.4 GB' (decimal units, 3 digits). The one formatter of the
    disk and memory messages (io, sweeps)."""
    for unit in ("bytes", "KB", "MB", "GB", "TB"):
        if n_bytes < 1000 or unit == "TB":
            return f"{n_bytes:.0f} {unit}" if unit == "bytes" else f"{n_bytes:.3g} {unit}"
        n_bytes /= 1000
    return f"{n_bytes:.3g} TB"


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
        limit = _file_size_limit()
        if limit is not None and size + n_bytes > limit:
            raise FileSizeLimitError(f"{self.path}: the file-size limit (ulimit -f: {_size(limit)}) is reached "
                                     f"({_size(size)} written, {_size(n_bytes)} more needed)")
        try:
            if _fallocate(self.fd, size, n_bytes):
                return
        except DiskFullError:
            raise DiskFullError(f"{self.path}: the disk is full ({_size(_free_bytes(self.path.parent) or 0)} "
                                f"free, {_size(n_bytes)} needed)") from None
        free = _free_bytes(self.path.parent)
        if free is not None and free < n_bytes:
            raise DiskFullError(f"{self.path}: the disk is full ({_size(free)} free, {_size(n_bytes)} needed)")

    def room(self) -> int:
        """Bytes the file can still grow by: the free space plus what it reserved earlier beyond
        its end, and no more than the file-size limit allows."""
        info = os.fstat(self.fd)
        reserved = max(0, getattr(info, "st_blocks", 0) * 512 - info.st_size)
        room = (_free_bytes(self.path.parent) or 0) + reserved
        limit = _file_size_limit()
        return room if limit is None else min(room, limit - info.st_size)

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


def reopen_for_writing(path, libver) -> h5py.File:
    """h5py.File(path, "r+") for a writer that holds elimfast's writer lock (so no other writer
    exists) and has just closed its SWMR session to write what SWMR mode cannot (the final
    attributes). A reader watching the run (h5py with swmr=True, open_datatree, as the README
    invites) holds HDF5's shared lock, which refused this open: the run failed at its end, its
    status left 'running' (a user trial). The reader then keeps its snapshot; the file is written
    past HDF5's lock, as it is consistent on disk once this session closes."""
    try:
        return h5py.File(path, "r+", libver=libver)
    except BlockingIOError:
        return h5py.File(path, "r+", libver=libver, locking=False)


def ensure_not_busy(path, other_output: bool = True) -> None:
    """FileBusyError if another live process writes (or holds open) ``path``. Touches nothing.
    ``other_output``: the messages offer another output file (not to ``repair``, which writes none).

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
            raise FileBusyError(f"{path}: is being written by {who}; stop it first{stop}"
                                + (" or choose another output file" if other_output else ""))
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.flock(fd, fcntl.LOCK_UN)
        except OSError as err:
            if err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise FileBusyError(f"{path}: is open in another process (an HDF5 program or elimfast); close it "
                                    "there first" + (", or choose another output file" if other_output else "")) from None
    finally:
        os.close(fd)
    if consistency_flags(path):
        pid, host, version = _writer_pid(path)
        if version < 2 and pid and host == socket.gethostname() and pid != os.getpid() and _process_alive(pid):
            raise FileBusyError(f"{path}: is still being written by process {pid}; stop it first "
                                f"(Ctrl-C or kill {pid})" + (", or choose another output file" if other_output else ""))


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
    text = str(path)
    if ":/" in text and Path(text.split(":/", 1)[0]).is_file():
        # FILE.h5:/runs/<label> names a run inside a sweep file for inspect, plot and load; as an
        # output path it made a folder 'FILE.h5:' and a new run in it (a user trial)
        container = text.split(":/", 1)[0]
        raise OutputError(f"{path}: names a group inside the file {container}, as inspect, plot and load name a run "
                          "of a sweep file; a run is written to a file of its own: give -o OUT.h5 (a sweep's runs "
                          "are continued with elimfast sweep SWEEP.yaml -o SWEEP.h5 --resume)")
    path = Path(path)
    if path.is_dir() or text.endswith(("/", os.sep)):   # a trailing '/': see output_path
        raise OutputError(f"{path}: is a directory; give a file name such as {path / 'run.h5'}")
    if path.exists():
        if not path.is_file():
            raise OutputError(f"{path}: not a regular file (a device, FIFO or socket); choose another output path")
        if not (overwrite or resume):
            raise OutputError(f"{path}: already exists; pass --overwrite to replace it or --resume to continue it")
        try:
            with open(path, "r+b"):
                pass
        except OSError as err:
            raise OutputError(f"{path}: not writable ({err.strerror}); choose another output path") from None
        ensure_not_busy(path)
        return path
    return check_creatable(path)


def output_path(text) -> Path:
    """The Path of an output option's text ('~' expanded), OutputError for one that ends in '/':
    it names a directory (Path drops the '/', and 'newdir/' became a file named newdir)."""
    if str(text).endswith(("/", os.sep)):
        raise OutputError(f"{text}: is a directory; give a file name such as {Path(text).expanduser() / 'run.h5'}")
    return Path(text).expanduser()


def check_creatable(path) -> Path:
    """OutputError unless a new file ``path`` can be created, its missing directories included
    (which ``create_parent_directories`` makes when the file is written): the nearest existing
    ancestor must be a directory in which files can be created (tested by creating one)."""
    path = Path(path)
    ancestor = _nearest_existing_ancestor(path)
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


def create_parent_directories(path) -> None:
    """Create the missing directories above a new output file (a run file, a sweep file, a
    figure): the one rule of every writer, so that ``elimfast run``, ``sweep`` and ``plot``
    treat ``-o some/missing/dir/NAME`` alike. OutputError naming the file and the
    directory that could not be made."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        ancestor = _nearest_existing_ancestor(path)
        if not ancestor.is_dir():
            raise OutputError(f"{path}: {ancestor} is a file, not a directory; choose another output path") from None
        directory = err.filename or path.parent
        raise OutputError(f"{path}: cannot create the directory {directory} ({err.strerror or _one_line(err)}); "
                          "choose another output path") from None


def _nearest_existing_ancestor(path: Path) -> Path:
    ancestor = path.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    return ancestor


def _mkstemp(directory: Path):
    import tempfile
    return tempfile.mkstemp(prefix=".elimfast-probe-", dir=directory)


NAME_MAX = 255            # bytes of a file name (Linux, most file systems): a temporary name must fit too
_TEMPORARY_PID = 20       # room kept for '.' + a pid + '.tmp'


def _published_path(path: Path) -> Path:
    """Where the file ``path`` names is written: a symlink's target (an existing link, a dangling
    one too), so that --overwrite replaces the target and keeps the link, as --resume writes it."""
    return Path(os.path.realpath(path)) if os.path.islink(path) else path


def _temporary_path(path: Path) -> Path:
    """Where a new file is built before it is renamed to ``path`` (beside its symlink's target:
    a rename does not cross file systems); stale ones of dead writers go. A name too long for
    '.<name>.<pid>.tmp' (249 to 255 bytes) is shortened, with a hash of it to keep it apart."""
    path = _published_path(path)
    stem = path.name
    if len(os.fsencode(stem)) + 1 + _TEMPORARY_PID > NAME_MAX:
        digest = hashlib.sha1(os.fsencode(stem)).hexdigest()[:12]
        stem = os.fsencode(stem)[:NAME_MAX - _TEMPORARY_PID - 1 - 13].decode(errors="ignore") + "~" + digest
    prefix = f".{stem}."
    with contextlib.suppress(OSError):
        for name in os.listdir(path.parent):
            pid = name[len(prefix):-len(".tmp")]
            if name.startswith(prefix) and name.endswith(".tmp") and pid.isdigit() and not _process_alive(int(pid)):
                with contextlib.suppress(OSError):
                    (path.parent / name).unlink()
    return path.with_name(f"{prefix}{os.getpid()}.tmp")


def _publish(temporary: Path, path: Path, overwrite: bool) -> None:
    """Rename the finished new file onto ``path`` (a symlink: onto its target), refusing a file
    that appeared meanwhile unless overwriting, and a file another process is writing in any case."""
    path = _published_path(path)
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


def recorded_end(path) -> int | None:
    """The end of the file that its superblock records (base address + end-of-file address),
    or None where the superblock cannot say (not HDF5, version 0/1, a damaged superblock)."""
    try:
        raw, end = _superblock(path)
    except (OutputError, OSError):
        return None
    if lookup3(bytes(raw[:end])) != struct.unpack("<I", raw[end:end + 4])[0]:
        return None
    size = raw[9]
    base = int.from_bytes(raw[12:12 + size], "little")
    return base + int.from_bytes(raw[12 + 2 * size:12 + 3 * size], "little")


def cut_short(path) -> str:
    """'' for a file at least as long as the end its superblock records, else what is missing, in
    words (a write cut off by a file-size limit or a full disk, or an incomplete copy)."""
    path = Path(path)
    size, end = path.stat().st_size, recorded_end(path)
    if end is None or end <= size:
        return ""
    return (f"it is cut short, {size:,} of the {end:,} bytes HDF5 recorded (a write cut off by a file-size limit "
            "or a full disk, or an incomplete copy)")


@contextlib.contextmanager
def extended_to_recorded_end(path):
    """A file shorter than its recorded end, extended to it with zeros for the block; yields
    the bytes added (0: the file was whole). HDF5 refuses such a file ('truncated file'): a
    write that failed part-way (EFBIG, a file-size limit) after HDF5 had allocated the space
    leaves one, whose saved part is whole; the callers verify what they read. The file keeps
    the extension when the block ends normally, and gets its old size back when it raises."""
    path = Path(path)
    size, end = os.stat(path).st_size, recorded_end(path)
    if end is None or end <= size:
        yield 0
        return
    try:
        os.truncate(path, end)
    except OSError as err:
        raise OutputError(f"{path}: is shorter than HDF5 recorded ({size} of {end} bytes) and cannot be "
                          f"extended to that ({err.strerror}); {no_room(err).fix if no_room(err) else 'check the disk'}"
                          ", then try again") from None
    try:
        yield end - size
    except BaseException:
        with contextlib.suppress(OSError):
            os.truncate(path, size)
        raise


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
    interrupted = _open_interrupted_sweep(path)
    if interrupted is not None:
        return interrupted
    if consistency_flags(path):
        # a writer killed before it closed the file: what repair undoes
        raise _damaged(path, "its start (HDF5 cannot open it)", first,
                       f"its writer did not close it: run {REPAIR_HINT.format(path=path)}, or {_DAMAGE_ADVICE}") \
            from None
    short = cut_short(path)
    if short:
        # Closed, but shorter than HDF5 recorded: a write cut off by a file-size limit (repair
        # extends it, and its saved part reads back) or a copy cut short, whose missing end may
        # hold metadata that nothing can rebuild (repair then says so). Not "did not close it":
        # a user trial's truncated copy of a completed run was told that.
        raise _damaged(path, "its start (HDF5 cannot open it)", first,
                       f"{short}: run {REPAIR_HINT.format(path=path)}, which keeps what was written if the "
                       f"missing end held no HDF5 metadata, or {_DAMAGE_ADVICE}") from None
    raise _damaged(path, "its start (HDF5 cannot open it)", first) from None


def _open_interrupted_sweep(path: Path) -> h5py.File | None:
    """A grid sweep's file whose writer was killed, read through _UnflaggedView (the file is not
    touched), or None for any other file. A grid sweep writes outside SWMR mode (it creates a
    group per run, which SWMR forbids), so HDF5 refuses its file after a kill; yet each run was
    flushed before it was marked stored, and metadata checksums and fletcher32 make a torn write
    visible, so its stored runs are read as a killed run's file is (a user trial: inspect, load
    and open_datatree refused such a file). Readers say it was interrupted (sweepfile)."""
    from .layout import SWEEP_FORMAT
    if consistency_flags(path) & 0b101 != 1:   # open for writing, not SWMR writing (a run's, an ensemble's)
        return None
    try:
        view = _UnflaggedView(path)
    except (OSError, OutputError):
        return None
    try:
        f = h5py.File(view, "r")
    except OSError:
        view.close()
        return None
    try:
        ours = _plain(f.attrs.get("format", "")) == SWEEP_FORMAT
    except (OSError, RuntimeError):
        ours = False
    if not ours:
        f.close()
        view.close()
        return None
    _VIEW_FILES.add(f)
    return f   # the view is closed with the last reference to it (h5py's file-object driver holds it)


# The files open through an _UnflaggedView, closed at exit before the interpreter tears down: HDF5's
# own close at exit calls back into the view (h5py's file-object driver), and where the view, or the
# Python machinery it needs, went first, the process crashed (a user trial: load(run=...) and
# open_datatree of one killed sweep file, exit code 139 after the script's last line).
_VIEW_FILES: weakref.WeakSet = weakref.WeakSet()


@atexit.register   # registered after h5py's import, so run before h5py's own handler (last in, first out)
def _close_view_files() -> None:
    for f in list(_VIEW_FILES):
        with contextlib.suppress(Exception):
            f.close()


class _UnflaggedView(io.FileIO):
    """A file read as if its superblock's consistency flags were clear (what ``repair`` would
    write), without changing the file: for h5py's file-object driver, so that the file of a
    writer killed outside SWMR mode (a sweep's) can be read to say what it holds."""

    def __init__(self, path):
        raw, end = _superblock(path)
        raw[11] = 0
        raw[end:end + 4] = struct.pack("<I", lookup3(bytes(raw[:end])))
        self._head = bytes(raw[:end + 4])
        super().__init__(path, "r")

    def readinto(self, buffer):
        start = self.tell()
        n = super().readinto(buffer)
        if n and start < len(self._head):
            stop = min(len(self._head), start + n)
            memoryview(buffer).cast("B")[:stop - start] = self._head[start:stop]
        return n


@contextlib.contextmanager
def open_unflagged(path):
    """The h5py.File of a killed non-SWMR writer's file, read-only, its flags ignored (see
    _UnflaggedView); the file is not touched. Raises OSError or OutputError where HDF5 cannot
    read it even so. For diagnosis: data written after the writer's last flush may be torn."""
    view = _UnflaggedView(path)
    try:
        with h5py.File(view, "r") as f:
            yield f
    finally:
        view.close()


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




# Writers whose HDF5 calls failed part-way: HDF5 cannot close such a file without crashing
# (HDF5 2.0 segfaults), so its objects are kept here, never released; the file on disk is
# then as a killed writer leaves it, consistent and resumable.
_ABANDONED: list = []


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


def refuse_netcdf_copy(path, attrs) -> None:
    """OutputError for a copy of an elimfast file written by xarray (to_netcdf) or another netCDF
    writer, which stores every scalar attribute as an array of one: readers of elimfast's layout
    would call it damaged (a user trial). elimfast.open_datatree reads such a copy."""
    try:
        copy = "format" in attrs and np.ndim(attrs.get("format_version", 0)) == 1
    except READ_ERRORS:   # damaged attributes: the reader that follows names the damage
        return
    if copy:
        raise OutputError(f"{path}: a copy written by xarray (to_netcdf) or another netCDF writer, whose attributes "
                          "are arrays, not an elimfast file: read it with elimfast.open_datatree or xarray, or give "
                          "elimfast the original")


def _damaged(path, where: str, err: BaseException, advice: str = _DAMAGE_ADVICE) -> DamagedFileError:
    return DamagedFileError(f"{path} is damaged at {where} ({_hdf5_reason(err)}); {advice}")


# What HDF5 raises for a read it cannot do (a checksum, a chunk it cannot find or decode).
READ_ERRORS = (KeyError, OSError, RuntimeError, ValueError, TypeError, IndexError)
SHOWN_DAMAGED_RANGES = 3   # row ranges a damage message names; more are counted


def damaged_row_ranges(dataset, start: int, stop: int) -> list[tuple[int, int]]:
    """(first, last) rows of the HDF5 chunks of ``dataset`` between rows ``start`` and ``stop``
    that cannot be read, found by reading chunk by chunk (after a read of the whole range
    failed); adjacent damaged chunks make one range. [] for a dataset not chunked along its
    rows (nothing smaller to blame) or when every chunk reads (the damage is elsewhere)."""
    if not dataset.chunks or stop <= start:
        return []
    rows, length = dataset.chunks[0], dataset.shape[0]
    ranges: list[tuple[int, int]] = []
    for first in range(start - start % rows, stop, rows):
        try:
            dataset[max(first, start):min(first + rows, stop)]
        except READ_ERRORS:
            last = min(first + rows, length) - 1
            if ranges and ranges[-1][1] == first - 1:
                ranges[-1] = (ranges[-1][0], last)
            else:
                ranges.append((first, last))
    return ranges


def rows_text(ranges: list[tuple[int, int]]) -> str:
    """'rows 2560-3071', 'rows 2560-3071 and 8192-8703', or the first SHOWN_DAMAGED_RANGES
    ranges and how many more: where in a dataset a damage message points."""
    shown = [f"{first}-{last}" if last > first else f"{first}" for first, last in ranges[:SHOWN_DAMAGED_RANGES]]
    more = len(ranges) - len(shown)
    if more:
        return f"rows {', '.join(shown)} and {more} more damaged range{'s' if more > 1 else ''}"
    return "rows " + (" and ".join(shown) if len(shown) <= 2 else f"{', '.join(shown[:-1])} and {shown[-1]}")


def _plain(value):
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()] if value.dtype.kind in "OSU" else value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    return value
