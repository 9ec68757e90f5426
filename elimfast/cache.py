"""The on-disk cache of generated problem code and its Numba compilations.

Location: ``$ELIMFAST_CACHE_DIR`` if set, else ``platformdirs.user_cache_dir("elimfast")``, or,
where that cannot be written (a read-only home), ``$TMPDIR/elimfast-cache-<uid>`` (cache_dir).
Layout (everything elimfast writes lives in these two folders; nothing else is touched):

    <cache>/problems/p_<sha256>.py        code generated from expressions (symbolic.py)
    <cache>/problems/f_<sha256>.py        events and time scales from expressions (symbolic.py)
    <cache>/problems/u_<sha256>.py        copies of ``python:`` problem files (user_file.py)
    <cache>/problems/k_<digest>.py        per-problem kernels (solver.kernel: per_problem; per_problem.py)
    <cache>/keys/<sha256>                 input key -> generated file name (skips sympy when warm)
    <cache>/configs/<sha256>              a config file's validated sections (skips pydantic when
                                          the same config runs again; config.load_run)
    <cache>/kernels/<key>/...             Numba's cache of the modules above, one folder per key
                                          of the kernels' sources (kernels/_cache.py; the
                                          kernels and built-in problems are cached in the
                                          package's __pycache__/kernels/<key>/; everything
                                          under $NUMBA_CACHE_DIR/elimfast-kernels if that is set)

Files are named by content hashes that include the elimfast version and are written
atomically (temporary file + ``os.replace``), so concurrent processes can share the
cache and a stale or half-written file is never imported.

Every change of elimfast, Numba or a kernel's source makes a new key folder; the old ones
are pruned. A process that uses a key folder sets its mtime (once, kernel_folder_used), and
the first process to use a new key folder (one without the marker file ``.pruned``)
removes the key folders of the same root not used for STALE_AFTER_DAYS days.
``elimfast cache clear --stale`` removes every key folder but the current one.
"""
from __future__ import annotations

import errno
import functools
import hashlib
import os
import stat
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from .errors import ElimfastError

ENV_VAR = "ELIMFAST_CACHE_DIR"
PROBLEMS_SUBDIR = "problems"
KEYS_SUBDIR = "keys"
VALIDATED_SUBDIR = "configs"


class CacheError(ElimfastError, OSError):
    """The cache directory cannot be created or written."""


def _unwritable(path: Path, err: OSError) -> CacheError:
    return CacheError(f"cannot write the elimfast cache at {path} ({type(err).__name__}: {err.strerror or err}); "
                      f"set {ENV_VAR} to a writable directory")


def cache_dir() -> Path:
    """The cache root (not created here): $ELIMFAST_CACHE_DIR if set (a folder the user chose:
    if it cannot be written, writing says so, CacheError); else the user cache folder, or,
    where that cannot be created or written, a private temporary one (_default_cache_dir)."""
    override = os.environ.get(ENV_VAR)
    if override:
        return Path(override).expanduser()
    import platformdirs
    return _default_cache_dir(platformdirs.user_cache_dir("elimfast"))


@functools.lru_cache(maxsize=None)
def _default_cache_dir(default: str) -> Path:
    """``default``, or where it cannot be written, temporary_cache_dir() with a one-line note
    on stderr. A cluster job whose home is read-only must still run (a user trial: 'internal
    error: ... no locator available'); it compiles once per machine, not once per job, as the
    temporary folder is kept. The folder becomes $ELIMFAST_CACHE_DIR of this process, so that
    its workers (a sweep's processes, a local Dask cluster) use it without a note of their own."""
    path = Path(default)
    reason = _why_not_writable(path)
    if reason is None:
        return path
    fallback = temporary_cache_dir()
    os.environ[ENV_VAR] = str(fallback)
    print(f"note: cannot write the elimfast cache at {path} ({reason}); using {fallback} (set {ENV_VAR} to a "
          "writable directory to choose where)", file=sys.stderr)
    return fallback


def _why_not_writable(path: Path) -> str | None:
    """None if ``path`` is a folder this process can write or create (nothing is created
    here); else why not."""
    existing = path
    while not os.path.lexists(existing) and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{existing} is not writable"
    return None


TEMPORARY_PREFIX = "elimfast-cache-"


def temporary_cache_dir() -> Path:
    """A folder of this user alone in the temporary directory ($TMPDIR, else /tmp):
    elimfast-cache-<uid>, created mode 0700 and kept between runs; a new one for this process
    if that name is anything else (another user's, or writable by others: Numba's cache files
    are pickles, and loading one that others could write would run their code)."""
    path = Path(tempfile.gettempdir()) / f"{TEMPORARY_PREFIX}{os.getuid()}"
    try:
        path.mkdir(mode=0o700, exist_ok=True)
        info = os.lstat(path)
        if stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid() and not info.st_mode & 0o022:
            return path
    except OSError:
        pass
    try:
        return Path(tempfile.mkdtemp(prefix=TEMPORARY_PREFIX))
    except OSError as err:
        raise _unwritable(path, err) from None


def _subdirectory(name: str) -> Path:
    path = cache_dir() / name
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise _unwritable(path, err) from None
    return path


def problems_dir() -> Path:
    """Where generated and copied problem modules go (created if needed)."""
    return _subdirectory(PROBLEMS_SUBDIR)


def keys_dir() -> Path:
    """Where the keys mapping parsed inputs to generated files go (created if needed)."""
    return _subdirectory(KEYS_SUBDIR)


def content_hash(*parts: str) -> str:
    """sha256 hex digest of the parts (NUL-separated), including the elimfast version."""
    from . import __version__
    digest = hashlib.sha256()
    for part in (__version__, *parts):
        digest.update(part.encode("utf-8"))
        digest.update(b"\0")
    return digest.hexdigest()


def write_if_changed(path: Path, text: str) -> None:
    """Write a generated or copied module into the cache unless it already holds this text
    (its Numba cache is keyed by the file's time stamp: rewriting the same text would recompile)."""
    try:
        current = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        current = None
    if current != text:
        write_atomic(path, text)


def import_file(path: Path, module_name: str, prepare=None):
    """Import the module file ``path`` as ``module_name``: in sys.modules while its code runs
    (Numba's cache finds its functions by module) and after; removed again if the code raises,
    which the caller then reports. ``prepare(module)`` runs first (a user's file sees its own
    location as __file__)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(module_name, path)
    module = importlib.util.module_from_spec(spec)
    if prepare is not None:
        prepare(module)
    sys.modules[module_name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(module_name, None)
        raise
    return module


def write_atomic(path: Path, text: str | bytes, *, sync: bool = True) -> None:
    """Write text (or bytes) to path so that readers see either nothing or the whole file;
    ``sync``: on disk before it is renamed into place (also after a crash of the machine)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=path.suffix, dir=path.parent)
    except OSError as err:
        raise _unwritable(path.parent, err) from None
    try:
        with (os.fdopen(fd, "wb") if isinstance(text, bytes) else os.fdopen(fd, "w", encoding="utf-8")) as handle:
            handle.write(text)
            handle.flush()
            if sync:
                os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if isinstance(err, OSError):
            raise _unwritable(path.parent, err) from None
        raise


def _our_files():
    root = cache_dir()
    for sub in (PROBLEMS_SUBDIR, KEYS_SUBDIR, VALIDATED_SUBDIR):
        folder = root / sub
        if not folder.is_dir():
            continue
        for dirpath, _dirnames, filenames in os.walk(folder):
            for name in filenames:
                yield Path(dirpath) / name


def cache_info() -> dict:
    """{'path': cache root, 'entries': generated problem modules, 'kernels': per-problem kernel
    modules, 'bytes': total size of our files}."""
    root = cache_dir()
    entries = kernels = 0
    size = 0
    problems = root / PROBLEMS_SUBDIR
    for path in _our_files():
        try:
            size += path.stat().st_size
        except OSError:
            continue
        if path.parent == problems and path.suffix == ".py":
            entries += path.name[:2] in ("p_", "u_", "f_")
            kernels += path.name[:2] == "k_"
    return {"path": str(root), "entries": entries, "kernels": kernels, "bytes": size}


def kernel_cache_files(only_problems: bool = False) -> tuple[list[Path], list[Path]]:
    """(the kernel cache roots, the Numba index and data files under them): the package's folder
    (elimfast's own kernels) and elimfast's cache's (the problems' modules), one folder with
    NUMBA_CACHE_DIR (kernel_roots). only_problems: just the files of the generated and copied
    problem modules (every key's folder for them), under elimfast's cache's root."""
    from numba.core.caching import _CacheLocator

    from .kernels._cache import kernels_root
    roots = [kernels_root()] if only_problems else kernel_roots()
    folders = [r for r in roots if r.is_dir()]
    if only_problems:
        name = _CacheLocator.get_suitable_cache_subpath(str(cache_dir() / PROBLEMS_SUBDIR / "x.py"))
        folders = [key / name for folder in folders for key in folder.iterdir() if (key / name).is_dir()]
    files = [Path(dirpath) / name for folder in folders for dirpath, _dirs, names in os.walk(folder)
             for name in names if name.endswith((".nbi", ".nbc"))]
    return roots, files


def _remove(paths) -> int:
    removed = 0
    for path in paths:
        try:
            path.unlink()
            removed += 1
        except FileNotFoundError:
            pass
    return removed


def _remove_empty_folders(folder: Path) -> None:
    for dirpath, _dirnames, _filenames in sorted(os.walk(folder), reverse=True) if folder.is_dir() else ():
        try:
            os.rmdir(dirpath)
        except OSError:
            pass


def clear_kernels() -> int:
    """Remove every compiled kernel (all keys); the next run compiles again. Returns the count."""
    roots, files = kernel_cache_files()
    removed = _remove(files)
    for folder in roots:
        _remove(key / PRUNED_MARKER for key in _key_folders(folder))
        _remove_empty_folders(folder)
    return removed


# --- pruning the key folders of old kernels ------------------------------------------------

STALE_AFTER_DAYS = 30     # a key folder no process used for this long is removed when a new key comes
PRUNED_MARKER = ".pruned"  # in a key folder: the first process to use it pruned its root
_USED: set = set()        # the key folders this process has marked as used


def kernel_roots() -> list[Path]:
    """The folders holding one subfolder per key (kernels/_cache.py): the package's (its own
    kernels) and elimfast's cache's (generated problems; every kernel if the package is not
    writable); one folder if NUMBA_CACHE_DIR is set."""
    from .kernels._cache import kernels_root
    return list(dict.fromkeys((kernels_root(in_package=True), kernels_root())))


def current_key() -> str:
    """The key of this process's kernels (the name of its folder in each root)."""
    from .kernels._cache import kernel_cache_dir
    return kernel_cache_dir().name


def _key_folders(root: Path):
    """The key folders directly in root: real directories (not symlinks) named like a key
    (lowercase hex digits, as long as the current key). Nothing else in root is ever touched."""
    key = current_key()
    try:
        with os.scandir(root) as listing:
            entries = list(listing)
    except OSError:   # no root yet, or unreadable: nothing to prune
        return
    for entry in entries:
        name = entry.name
        if len(name) != len(key) or name.strip("0123456789abcdef"):
            continue
        try:
            if entry.is_dir(follow_symlinks=False):
                yield Path(entry.path)
        except OSError:
            continue


def stale_kernel_folders(root: Path, unused_for_days: float | None = None) -> list[Path]:
    """The key folders of root but the current one; with unused_for_days, only those whose
    mtime (the last use, kernel_folder_used) is older than that."""
    key = current_key()
    cutoff = None if unused_for_days is None else time.time() - unused_for_days * 86400.0
    stale = []
    for folder in _key_folders(root):
        if folder.name == key:
            continue
        if cutoff is not None:
            try:
                if os.stat(folder, follow_symlinks=False).st_mtime >= cutoff:
                    continue
            except FileNotFoundError:   # removed meanwhile by another process
                continue
        stale.append(folder)
    return stale


def _remove_tree(folder: Path, pruned: "Pruned") -> None:
    """Delete folder and everything under it without following symbolic links (a link is
    removed, never its target), adding the bytes of the regular files this call removed to
    pruned.bytes. Files another process removes first are skipped (concurrent pruning); a
    folder another process wrote into meanwhile stays, with that file. Other OS errors are
    raised."""
    if os.path.islink(folder):
        return
    for dirpath, dirnames, filenames in os.walk(folder, topdown=False, onerror=_ignore_missing):
        links = [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]
        for name in (*filenames, *links):
            path = os.path.join(dirpath, name)
            try:
                info = os.lstat(path)
                os.unlink(path)
            except FileNotFoundError:
                continue
            if stat.S_ISREG(info.st_mode):
                pruned.bytes += info.st_size
        try:
            os.rmdir(dirpath)
        except FileNotFoundError:
            pass
        except OSError as err:
            if err.errno != errno.ENOTEMPTY:
                raise


def _ignore_missing(err: OSError) -> None:
    if not isinstance(err, FileNotFoundError):
        raise err


@dataclass
class Pruned:
    """What prune_kernel_folders removed: the folders, the bytes of the files it removed
    (also from folders it could not remove entirely), and those folders with the error."""

    folders: list[Path] = field(default_factory=list)
    bytes: int = 0
    failed: list[tuple[Path, OSError]] = field(default_factory=list)


def prune_kernel_folders(unused_for_days: float | None = None, roots=None) -> Pruned:
    """Remove the key folders of the kernel roots (kernel_roots(), or roots) but the current
    key's; with unused_for_days, only those not used for that long. Safe to run in several
    processes at once: what another one removed first is skipped."""
    pruned = Pruned()
    for root in dict.fromkeys(roots if roots is not None else kernel_roots()):
        for folder in stale_kernel_folders(Path(root), unused_for_days):
            try:
                _remove_tree(folder, pruned)
            except OSError as err:
                pruned.failed.append((folder, err))
            else:
                pruned.folders.append(folder)
    return pruned


def kernel_folder_used(in_package: bool = True) -> None:
    """Mark this process's key folder as used now (its mtime), once per process and folder;
    the first process to use a key folder (it has no PRUNED_MARKER yet: the key is new, or
    its folder was just created) then removes the key folders of the same root that no
    process used for STALE_AFTER_DAYS. ``in_package``: the folder of elimfast's own kernels
    (integrate.py, when it loads them), else that of the generated problem modules (where
    they are imported). Best effort, never raises; a few system calls when nothing is new."""
    from .kernels._cache import kernel_cache_dir
    folder = kernel_cache_dir(in_package)
    if in_package and folder not in _USED and not folder.is_dir():
        folder = kernel_cache_dir(False)   # the package is not writable: its kernels are in elimfast's cache
    if folder in _USED:
        return
    _USED.add(folder)
    try:
        os.close(os.open(folder / PRUNED_MARKER, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644))
    except FileExistsError:   # not new: only mark the use
        try:
            os.utime(folder)
        except OSError:
            pass
        return
    except OSError:           # no folder (nothing compiled there yet) or not writable: nothing to do
        return
    # The marker is in place (which also set the folder's mtime): this process prunes.
    try:
        prune_kernel_folders(STALE_AFTER_DAYS, roots=[folder.parent])
    except OSError:
        pass


def clear_cache() -> int:
    """Remove every file elimfast put in the cache for problems (generated and copied modules,
    keys, and their compiled code); return how many were removed.

    Processes that already imported a generated module keep working; a later load
    regenerates and recompiles it.
    """
    removed = _remove(kernel_cache_files(only_problems=True)[1])
    for path in list(_our_files()):
        try:
            path.unlink()
            removed += 1
        except FileNotFoundError:
            pass
    root = cache_dir()
    for sub in (PROBLEMS_SUBDIR, KEYS_SUBDIR, VALIDATED_SUBDIR):
        folder = root / sub
        for dirpath, _dirnames, _filenames in sorted(os.walk(folder), reverse=True) if folder.is_dir() else ():
            try:
                os.rmdir(dirpath)
            except OSError:
                pass
    return removed
