"""The on-disk cache of generated problem code and its Numba compilations.

Location: ``$ELIMFAST_CACHE_DIR`` if set, else ``platformdirs.user_cache_dir("elimfast")``.
Layout (everything elimfast writes lives in these two folders; nothing else is touched):

    <cache>/problems/p_<sha256>.py        code generated from expressions (symbolic.py)
    <cache>/problems/f_<sha256>.py        events and time scales from expressions (symbolic.py)
    <cache>/problems/u_<sha256>.py        copies of ``python:`` problem files (user_file.py)
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
"""
from __future__ import annotations

import hashlib
import os
import tempfile
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
    """The cache root (not created here)."""
    override = os.environ.get(ENV_VAR)
    if override:
        return Path(override).expanduser()
    import platformdirs
    return Path(platformdirs.user_cache_dir("elimfast"))


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
    """{'path': cache root, 'entries': generated problem modules, 'bytes': total size of our files}."""
    root = cache_dir()
    entries = 0
    size = 0
    problems = root / PROBLEMS_SUBDIR
    for path in _our_files():
        try:
            size += path.stat().st_size
        except OSError:
            continue
        if path.parent == problems and path.suffix == ".py" and path.name[:2] in ("p_", "u_", "f_"):
            entries += 1
    return {"path": str(root), "entries": entries, "bytes": size}


def kernel_cache_files(only_problems: bool = False) -> tuple[Path, list[Path]]:
    """(the kernel cache root, the Numba index and data files under it). only_problems:
    just those of the generated and copied problem modules (every key's folder for them)."""
    from numba.core.caching import _CacheLocator

    from .kernels._cache import kernels_root
    root = kernels_root()
    roots = [root] if only_problems else [kernels_root(in_package=True), root]
    folders = [r for r in dict.fromkeys(roots) if r.is_dir()]
    if only_problems:
        name = _CacheLocator.get_suitable_cache_subpath(str(cache_dir() / PROBLEMS_SUBDIR / "x.py"))
        folders = [key / name for folder in folders for key in folder.iterdir() if (key / name).is_dir()]
    files = [Path(dirpath) / name for folder in folders for dirpath, _dirs, names in os.walk(folder)
             for name in names if name.endswith((".nbi", ".nbc"))]
    return root, files


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
    from .kernels._cache import kernels_root
    root, files = kernel_cache_files()
    removed = _remove(files)
    for folder in (root, kernels_root(in_package=True)):
        _remove_empty_folders(folder)
    return removed


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
