"""Numba's cache files of elimfast's functions carry a checksum (kernels/_cache.py,
ChecksummedCacheFile): a damaged, truncated or empty one is a cache miss, never machine
code loaded as it is. A user trial flipped one bit of the cached grad_H of Kepler (a
multiply became an add) and the run completed with H off by 2.6, exit 0; an empty data
file was reported as Ctrl-C, a truncated one as an internal error, on every run."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
from numba.core import caching

from elimfast.kernels import _cache

PROBE = """\
import numpy as np
from elimfast.problems.symbolic import problem_from_expressions
p = problem_from_expressions({"q": ["q"], "p": ["p"]}, "p**2/2 + q**4/4 + q**2*p", initial={"q": 0.5, "p": 1.0},
                             name="probe")
out = np.empty(2)
p.grad_H(np.array([0.5, 1.0]), p.params, out)
print(repr(out.tolist()))
"""


def _cache_file(tmp_path) -> _cache.ChecksummedCacheFile:
    return _cache.ChecksummedCacheFile(cache_path=str(tmp_path), filename_base="probe.f-1.py311", source_stamp=("s", 1))


def test_a_damaged_truncated_empty_or_unsealed_cache_file_is_a_miss(tmp_path):
    cache_file = _cache_file(tmp_path)
    cache_file.save("key", ("machine code", 42))
    assert cache_file.load("key") == ("machine code", 42)
    data = next(tmp_path.glob("*.nbc"))
    original = data.read_bytes()
    for damaged in (original[:10] + bytes([original[10] ^ 0x04]) + original[11:],   # one bit flipped
                    original[: len(original) // 2], b"",                             # truncated, empty
                    original[: -len(_cache._SEAL) - 32]):                            # Numba's own, unsealed
        data.write_bytes(damaged)
        assert cache_file.load("key") is None
    data.write_bytes(original)
    index = next(tmp_path.glob("*.nbi"))
    whole = index.read_bytes()
    for damaged in (whole[: len(whole) // 2], whole[:3], b"", whole[:-1] + bytes([whole[-1] ^ 1])):
        index.write_bytes(damaged)
        assert cache_file.load("key") is None   # (a miss: the next save writes a new index)
    cache_file.save("key", ("machine code", 43))
    assert cache_file.load("key") == ("machine code", 43)


def test_elimfast_s_functions_use_the_checksummed_files_and_others_numba_s():
    from elimfast import problems
    grad_H = problems.kepler().grad_H
    assert type(grad_H._cache._cache_file) is _cache.ChecksummedCacheFile

    from numba import njit

    @njit(cache=True)
    def not_elimfast_s(x):   # a test module: Numba's own locator and files
        return x + 1
    assert type(not_elimfast_s._cache._cache_file) is caching.IndexDataCacheFile


@pytest.mark.slow
def test_a_bit_flipped_in_cached_machine_code_is_compiled_again_not_run(tmp_path):
    """The trial's case end to end, in fresh processes: a problem's functions are compiled into
    an empty cache, a bit of its grad_H's cache file is flipped, and the next process compiles
    it again (the notice says so) and computes the same numbers."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba"), "ELIMFAST_CACHE_DIR": str(tmp_path / "ef")}
    script = tmp_path / "probe.py"
    script.write_text(PROBE)

    def run():
        done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip(), done.stderr

    clean, _ = run()
    assert clean == "[1.125, 1.25]"
    assert "compiling" not in run()[1]   # loaded from the cache
    (data,) = Path(tmp_path / "numba").rglob("p_*.grad_H-*.nbc")
    damaged = bytearray(data.read_bytes())
    damaged[len(damaged) // 2] ^= 0x04
    data.write_bytes(bytes(damaged))
    again, said = run()
    assert again == clean and "compiling the problem's own functions" in said, said
    assert _cache._unsealed(data.read_bytes()) is not None   # rewritten whole
    assert "compiling" not in run()[1]
