"""Where Numba caches elimfast's compiled code: a folder keyed by the kernels' sources.

Numba's cache checks only the source file of the function it compiled. time_loop lives
in stepper.py but inlines or calls code from solver.py, maps.py, linalg.py and more; a
change there left the cached machine code of time_loop in place (last round, a changed
``error_model`` in signatures.py kept raising ZeroDivisionError from stale built-in
problem functions). So every function elimfast compiles (the kernels, the built-in
problems, and the generated or copied problem modules in elimfast's cache) is cached
under ``<cache>/kernels/<key>/``, where key is a hash of the elimfast version, the Numba
version and the text of every module of ``elimfast.kernels``: a changed kernel source
or version can never load old code; it compiles into a new folder.

With NUMBA_CACHE_DIR set, the keyed folder goes there instead of elimfast's cache.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

from numba.core import caching

KERNELS_DIR = Path(__file__).resolve().parent
PACKAGE_DIR = KERNELS_DIR.parent


def cache_key() -> str:
    """16 hex digits of sha256(elimfast version, numba version, the kernels' sources)."""
    import numba

    from .. import __version__
    digest = hashlib.sha256(f"{__version__}\0{numba.__version__}\0".encode())
    for path in sorted(KERNELS_DIR.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def kernels_root() -> Path:
    """The folder holding one subfolder per key (``elimfast cache clear --kernels`` empties it)."""
    override = os.environ.get("NUMBA_CACHE_DIR")
    if override:
        return Path(override).expanduser() / "elimfast-kernels"
    from ..cache import cache_dir
    return cache_dir() / "kernels"


_KEY = cache_key()
_ROOT = kernels_root() / _KEY


def kernel_cache_dir() -> Path:
    """This process's keyed folder."""
    return _ROOT


def _ours(py_file: str) -> bool:
    path = Path(py_file).resolve()
    if PACKAGE_DIR in path.parents:
        return True
    from ..cache import cache_dir
    return Path(cache_dir()).resolve() in path.parents


class KeyedCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """Numba cache locator for elimfast's own files: <root>/<key>/<Numba's subpath of the file>."""

    def __init__(self, py_func, py_file):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = str(_ROOT / self.get_suitable_cache_subpath(py_file))

    def get_cache_path(self):
        return self._cache_path

    @classmethod
    def from_function(cls, py_func, py_file):
        if not _ours(py_file):
            return None
        return super().from_function(py_func, py_file)   # None when the folder cannot be created


def install() -> None:
    """Put the keyed locator first in Numba's list (once per process)."""
    locators = caching.CacheImpl._locator_classes
    if KeyedCacheLocator not in locators:
        locators.insert(0, KeyedCacheLocator)
