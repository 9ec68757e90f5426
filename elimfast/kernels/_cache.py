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

Every index and data file there carries a sha256 of its content (ChecksummedCacheFile): a
damaged, truncated or empty one is a cache miss, compiled again, never machine code loaded
as it is.

Loading them from there skips what only a compilation needs (start-up, issue 12): Numba's
registries of typing and lowering rules (_load_overload) and, for the two run kernels, the
parse of their linking bitcode (_LazyLinkingLibrary).
"""
from __future__ import annotations

import functools
import hashlib
import os
import pickle
from pathlib import Path

from numba.core import caching
from numba.core import codegen as numba_codegen
from numba.core import compiler as numba_compiler

from ..cache import ENV_VAR, CacheError

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
    installed package may not be writable) elimfast's cache (cache.cache_dir: a private
    temporary folder where the default one cannot be written). Once per file and cache
    settings (``settings``: the two environment variables that move the cache), not once
    per function: a kernel module defines up to 20 cached functions, and resolving the
    file's place and test-writing its folder took ~0.4 ms a function, 57 functions in a
    warm `elimfast run`.

    An elimfast file with no writable root raises CacheError naming the folder and the
    setting to change: returning None there let Numba's own locators take the file, which
    wrote unkeyed cache files into the package (stale after a kernel edit) or failed with
    'RuntimeError: no locator available' (a user trial, both)."""
    place = _place(py_file)
    if place is None or not os.path.exists(py_file):
        return None
    for in_package in (True, False) if place == "package" else (False,):
        root = kernel_cache_dir(in_package)
        probe = KeyedCacheLocator.__new__(KeyedCacheLocator)
        probe._cache_path = str(root / KeyedCacheLocator.get_suitable_cache_subpath(py_file))
        try:
            probe.ensure_cache_path()   # Numba's check: the folder exists and takes a file
        except OSError as err:
            failure = err
            continue
        return root
    # the last root tried is the one a setting moves: $NUMBA_CACHE_DIR's, else elimfast's cache
    fix = ("set NUMBA_CACHE_DIR to a writable directory, or unset it" if os.environ.get("NUMBA_CACHE_DIR") else
           f"set {ENV_VAR} to a writable directory")
    raise CacheError(f"cannot write the compiled-code cache at {root} ({failure.strerror or failure}); {fix}")


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
    every compile), and a cache miss here falls through to it unchanged. The run kernels
    (LAZY_LINKING) load through _load_linking_lazily.
    """
    if not isinstance(getattr(self._impl, "locator", None), KeyedCacheLocator):
        return _NUMBA_LOAD_OVERLOAD(self, sig, target_context)
    from numba.core.runtime import rtsys
    rtsys.initialize(target_context)
    with self._guard_against_spurious_io_errors():
        py_func = self._py_func
        if _LAZY_LINKING_WORKS and (py_func.__module__, py_func.__qualname__) in LAZY_LINKING:
            return _load_linking_lazily(self, sig, target_context)
        return self._load_overload(sig, target_context)


# The run kernels, loaded with their linking bitcode left unparsed (_LazyLinkingLibrary): each
# is compiled with both of Numba's wrappers (an explicit signature, called from Python), is
# large (time_loop's bitcode is 0.9 MB), and no compiled code calls it.
LAZY_LINKING = {("elimfast.kernels.stepper", "time_loop"), ("elimfast.kernels.adaptive", "adaptive_loop")}


class _LazyLinkingLibrary(numba_codegen.JITCodeLibrary):
    """A library loaded from Numba's cache that parses its linking bitcode on first need.

    The cache holds a function's machine code and, to link it into code compiled later, its
    LLVM bitcode. Numba parses that bitcode on every load (time_loop: 45-55 ms of CPU, a
    tenth of a warm `elimfast run`), though the machine code runs without it: only to list
    the library's symbols. Here the loader registers the three symbols it looks up (the
    function and its two wrappers); the bitcode is parsed, and all its symbols registered,
    when code links the library (``_shared_module``) or asks for another symbol."""

    _linking_bitcode = None
    _linking_module = None

    @property
    def _shared_module(self):
        if self._linking_bitcode is not None:
            import llvmlite.binding as llvm
            self._linking_module = llvm.parse_bitcode(self._linking_bitcode)
            self._linking_bitcode = None
            self._codegen._engine._load_defined_symbols(self._linking_module)
        return self._linking_module

    @_shared_module.setter
    def _shared_module(self, module):
        self._linking_module = module

    def get_pointer_to_function(self, name):
        if self._linking_bitcode is not None and not self._codegen._engine.is_symbol_defined(name):
            self._shared_module   # noqa: B018 -- parses the bitcode, which registers every symbol
        return super().get_pointer_to_function(name)


_COMPILE_RESULT_FIELDS = {"typing_context", "target_context", "entry_point", "typing_error", "type_annotation",
                          "signature", "objectmode", "lifted", "fndesc", "library", "call_helper", "environment",
                          "metadata", "reload_init", "referenced_envs"}
# The Numba internals _load_linking_lazily uses; with another layout, Numba's own loader runs.
_LAZY_LINKING_WORKS = (set(getattr(numba_compiler, "CR_FIELDS", ())) == _COMPILE_RESULT_FIELDS
                       and all(hasattr(numba_codegen.JITCodeLibrary, name) for name in (
                           "_finalize_final_module", "enable_object_caching", "_set_compiled_object"))
                       and hasattr(numba_codegen.JitEngine, "_load_defined_symbols")
                       and all(hasattr(caching.Cache, name) for name in ("_index_key", "_load_overload")))


def _load_linking_lazily(cache, sig, target_context):
    """Numba's ``Cache._load_overload`` and ``CompileResult._rebuild`` for a LAZY_LINKING
    kernel, building a _LazyLinkingLibrary; None when the cache has no entry. Data of
    another form (no machine code, object mode, parallel code's reload hooks) are loaded
    by Numba's own code."""
    if not cache._enabled:
        return None
    data = cache._cache_file.load(cache._index_key(sig, target_context.codegen()))
    if data is None:
        return None
    try:
        libdata, fndesc, env, signature, objectmode, lifted, typeann, reload_init, referenced_envs = data
        name, kind, (object_code, linking_bitcode) = libdata
    except (TypeError, ValueError):
        kind = None
    if kind != "object" or objectmode or reload_init:
        return cache._impl.rebuild(target_context, data)
    library = target_context.codegen().create_library(name)
    if type(library) is not numba_codegen.JITCodeLibrary:
        return cache._impl.rebuild(target_context, data)
    library.__class__ = _LazyLinkingLibrary
    library.enable_object_caching()
    library._set_compiled_object(object_code)
    library._linking_bitcode = linking_bitcode
    library._finalize_final_module()
    library._codegen._engine._defined_symbols.update(
        (fndesc.llvm_func_name, fndesc.llvm_cpython_wrapper_name, fndesc.llvm_cfunc_wrapper_name))
    result = numba_compiler.CompileResult(
        typing_context=target_context.typing_context, target_context=target_context,
        entry_point=target_context.get_executable(library, fndesc, env), typing_error=None, type_annotation=typeann,
        signature=signature, objectmode=objectmode, lifted=lifted, fndesc=fndesc, library=library, call_helper=None,
        environment=env, metadata=None, reload_init=reload_init, referenced_envs=referenced_envs)
    for referenced in referenced_envs:
        library.codegen.set_env(referenced.env_name, referenced)
    return result


# --- checksummed cache files -----------------------------------------------------------------

_SEAL = b"elimfast-sha256:"   # then the 32 bytes of the sha256 of what precedes it


def _sealed(data: bytes) -> bytes:
    """data with its checksum appended (pickle.loads ignores bytes after the pickle: Numba's
    own reader still reads such a file)."""
    return data + _SEAL + hashlib.sha256(data).digest()


def _unsealed(data: bytes) -> bytes | None:
    """The data of a _sealed file, None when the seal is missing or does not match."""
    size = len(_SEAL) + 32
    if len(data) < size or data[-size:-32] != _SEAL:
        return None
    body = data[:-size]
    return body if hashlib.sha256(body).digest() == data[-32:] else None


class ChecksummedCacheFile(caching.IndexDataCacheFile):
    """Numba's index and data files of elimfast's keyed folders, each written with a sha256 of
    its content and read only when it matches; a damaged, truncated or empty file is a cache
    miss (the function compiles again and its files are rewritten).

    Numba loads its cache files as they are: a user trial flipped one bit of the cached
    grad_H of Kepler (a multiply became an add) and the run completed with H off by 2.6,
    exit 0; one byte changed in the time loop's machine code gave a run 7e-15 off the
    clean one, unnoticed; an empty data file raised EOFError, which the command line took
    for Ctrl-C, and a truncated one UnpicklingError, an internal error, on every run."""

    def _dump(self, obj):
        return _sealed(super()._dump(obj))   # the index's (stamp, overloads) and every data file

    def _load_index(self):
        try:
            with open(self._index_path, "rb") as f:
                version = pickle.load(f)
                data = f.read()
        except FileNotFoundError:
            return {}
        except (OSError, EOFError, pickle.UnpicklingError, ValueError, TypeError, AttributeError, IndexError):
            return {}   # damaged beyond its first pickle: a miss
        if version != self._version:
            return {}
        body = _unsealed(data)
        try:
            stamp, overloads = pickle.loads(body) if body is not None else (None, {})
        except Exception:   # noqa: BLE001 -- a sealed file that still does not unpickle: a miss
            return {}
        return overloads if stamp == self._source_stamp and isinstance(overloads, dict) else {}

    def _load_data(self, name):
        path = self._data_path(name)
        with open(path, "rb") as f:
            data = f.read()
        body = _unsealed(data)
        if body is None:   # Numba's load() takes an OSError for a missing file: a miss
            raise OSError(f"{path}: damaged or truncated compiled-code cache file (its checksum does not match)")
        return pickle.loads(body)


_NUMBA_CACHE_INIT = caching.Cache.__init__


def _cache_init(self, py_func):
    """Numba's ``Cache.__init__``, with the ChecksummedCacheFile for functions under the keyed
    locator (any other function's files are Numba's own)."""
    _NUMBA_CACHE_INIT(self, py_func)
    cache_file = getattr(self, "_cache_file", None)
    if isinstance(getattr(self._impl, "locator", None), KeyedCacheLocator) \
            and type(cache_file) is caching.IndexDataCacheFile:
        cache_file.__class__ = ChecksummedCacheFile


# The Numba internals the checksums replace; with another layout, Numba's own files are used.
_CHECKSUMS_WORK = all(hasattr(caching.IndexDataCacheFile, name) for name in (
    "_dump", "_load_index", "_load_data", "_data_path", "_save_data", "_save_index"))


def install() -> None:
    """Put the keyed locator first in Numba's list, load elimfast's functions from the cache
    with _load_overload, and checksum their cache files (ChecksummedCacheFile); once per process."""
    locators = caching.CacheImpl._locator_classes
    if KeyedCacheLocator not in locators:
        locators.insert(0, KeyedCacheLocator)
    if hasattr(caching.Cache, "_load_overload") and hasattr(caching.Cache, "_guard_against_spurious_io_errors"):
        caching.Cache.load_overload = _load_overload
    if _CHECKSUMS_WORK and caching.Cache.__init__ is _NUMBA_CACHE_INIT:
        caching.Cache.__init__ = _cache_init
