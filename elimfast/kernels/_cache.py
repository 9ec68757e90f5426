"""Where Numba caches elimfast's compiled code: a folder keyed by the kernels' sources.

Numba's cache checks only the source file of the function it compiled. time_loop lives
in stepper.py but inlines or calls code from solver.py, maps.py, linalg.py and more; a
change there left the cached machine code of time_loop in place (last round, a changed
``error_model`` in signatures.py kept raising ZeroDivisionError from stale built-in
problem functions). So every function elimfast compiles (the kernels, the built-in
problems, and the generated or copied problem modules in elimfast's cache) is cached
in a folder named by a key, a hash of the elimfast version, the Numba version and the
text of every module of ``elimfast.kernels``: a changed kernel source or version can
never load old code; it compiles into a new folder. The package's own functions go to
``elimfast/__pycache__/kernels/<key>/`` (elimfast's cache if the package is not
writable), the generated problem modules to ``<cache>/kernels/<key>/``; with
NUMBA_CACHE_DIR set, both go to ``$NUMBA_CACHE_DIR/elimfast-kernels/<key>/``.
"""
from __future__ import annotations

import functools
import hashlib
import os
from pathlib import Path

from numba.core import caching

from ..cache import ENV_VAR

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


def kernels_root(in_package: bool = False) -> Path:
    """The folder holding one subfolder per key (``elimfast cache clear --kernels`` empties it):
    $NUMBA_CACHE_DIR/elimfast-kernels if set; else, for the package's own files
    (``in_package``), the package's __pycache__ (where Numba itself would put them, so
    that a changed ELIMFAST_CACHE_DIR does not recompile the kernels); for the generated
    problem modules, elimfast's cache."""
    override = os.environ.get("NUMBA_CACHE_DIR")
    if override:
        return Path(override).expanduser() / "elimfast-kernels"
    if in_package:
        return PACKAGE_DIR / "__pycache__" / "kernels"
    from ..cache import cache_dir
    return cache_dir() / "kernels"


_KEY = cache_key()


def kernel_cache_dir(in_package: bool = False) -> Path:
    """This process's keyed folder (under the root as it is set now)."""
    return kernels_root(in_package) / _KEY


def _place(py_file: str) -> str | None:
    """'package' for elimfast's own modules, 'cache' for the modules in elimfast's cache, else None."""
    path = Path(py_file).resolve()
    if PACKAGE_DIR in path.parents:
        return "package"
    from ..cache import cache_dir
    return "cache" if Path(cache_dir()).resolve() in path.parents else None


class KeyedCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """Numba cache locator for elimfast's own files: <root>/<key>/<Numba's subpath of the file>."""

    def __init__(self, py_func, py_file, root: Path):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = str(root / self.get_suitable_cache_subpath(py_file))

    def get_cache_path(self):
        return self._cache_path

    @classmethod
    def from_function(cls, py_func, py_file):
        root = _writable_root(py_file, os.environ.get("NUMBA_CACHE_DIR"), os.environ.get(ENV_VAR))
        return None if root is None else cls(py_func, py_file, root)


@functools.lru_cache(maxsize=None)
def _writable_root(py_file: str, *settings) -> Path | None:
    """The keyed root under which the functions of py_file are cached, or None for a file
    that is not elimfast's: for the package's own modules the package's folder, else (an
    installed package may not be writable) elimfast's cache. Once per file and cache
    settings (``settings``: the two environment variables that move the cache), not once
    per function: a kernel module defines up to 20 cached functions, and resolving the
    file's place and test-writing its folder took ~0.4 ms a function, 57 functions in a
    warm `elimfast run`."""
    place = _place(py_file)
    if place is None or not os.path.exists(py_file):
        return None
    for in_package in (True, False) if place == "package" else (False,):
        root = kernel_cache_dir(in_package)
        probe = KeyedCacheLocator.__new__(KeyedCacheLocator)
        probe._cache_path = str(root / KeyedCacheLocator.get_suitable_cache_subpath(py_file))
        try:
            probe.ensure_cache_path()   # Numba's check: the folder exists and takes a file
        except OSError:
            continue
        return root
    return None


_NUMBA_LOAD_OVERLOAD = caching.Cache.load_overload


def _load_overload(self, sig, target_context):
    """Numba's ``Cache.load_overload`` without its ``target_context.refresh()`` for elimfast's
    own functions (those under the keyed locator; any other function loads as Numba does).

    The refresh imports and installs every typing and lowering registry of Numba (about
    70 modules: numba.np.*, numba.cpython.*, typed containers, jitclass, random), which
    only a compilation uses; running machine code loaded from the cache needs only the
    NRT (``rtsys.initialize``, the refresh's first step). Measured: 0.10-0.13 s of CPU of
    a warm `elimfast run`, a third of its cost above the bare `import numba, h5py`. A
    compilation in the same process still refreshes first (Numba's compiler does so on
    every compile), and a cache miss here falls through to it unchanged.
    """
    if not isinstance(getattr(self._impl, "locator", None), KeyedCacheLocator):
        return _NUMBA_LOAD_OVERLOAD(self, sig, target_context)
    from numba.core.runtime import rtsys
    rtsys.initialize(target_context)
    with self._guard_against_spurious_io_errors():
        return self._load_overload(sig, target_context)


def install() -> None:
    """Put the keyed locator first in Numba's list and load elimfast's functions from the
    cache without the registries refresh (_load_overload); once per process."""
    locators = caching.CacheImpl._locator_classes
    if KeyedCacheLocator not in locators:
        locators.insert(0, KeyedCacheLocator)
    if hasattr(caching.Cache, "_load_overload") and hasattr(caching.Cache, "_guard_against_spurious_io_errors"):
        caching.Cache.load_overload = _load_overload
