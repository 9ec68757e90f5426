"""Where compiled code goes when the cache folder elimfast would use cannot be written (a user
trial: a user whose home is not writable got 'internal error: RuntimeError: cannot cache
function 'lu_factor': no locator available', and an unwritable NUMBA_CACHE_DIR sent Numba's
cache files into the package's own __pycache__, where the keyed cache of kernels/_cache.py
cannot keep them apart from stale ones).

The rule (elimfast/cache.py, kernels/_cache.py): a folder the user chose (ELIMFAST_CACHE_DIR,
NUMBA_CACHE_DIR) that cannot be written is a one-line error naming it; the default folder
that cannot be written (a cluster job whose home is read-only) gives way to a private folder
in the temporary directory, with a one-line note."""
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

import elimfast

PACKAGE = Path(elimfast.__file__).resolve().parent
# A kernel with cache=True and nothing else to compile: its import asks Numba for a cache locator.
COMPILE_ONE_KERNEL = ("import numpy as np\n"
                      "from elimfast.kernels.linalg import lu_factor\n"
                      "print(lu_factor(np.eye(2), np.zeros(2, dtype=np.int64)))\n")


def numba_files_in_package() -> set[Path]:
    return {path for pattern in ("*.nbi", "*.nbc") for path in PACKAGE.rglob(pattern)
            if "__pycache__/kernels" not in path.as_posix()}   # the keyed folders are elimfast's own


def environment(**settings) -> dict:
    env = {key: value for key, value in os.environ.items() if key not in ("NUMBA_CACHE_DIR", "ELIMFAST_CACHE_DIR")}
    env.update(settings)
    return env


def test_an_unwritable_numba_cache_dir_is_a_one_line_error_and_nothing_is_written_into_the_package(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")   # a folder under a regular file cannot be created, also by root
    before = numba_files_in_package()
    try:
        result = subprocess.run([sys.executable, "-c", COMPILE_ONE_KERNEL], capture_output=True, text=True,
                                env=environment(NUMBA_CACHE_DIR=str(blocker / "numba")), timeout=300)
        written = numba_files_in_package() - before
    finally:
        for path in numba_files_in_package() - before:   # what the unkeyed fallback left, on a failing run
            path.unlink()
    assert written == set()
    assert result.returncode != 0, result.stdout
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith(f"elimfast.cache.CacheError: cannot write the compiled-code cache at {blocker}/numba/"
                           "elimfast-kernels"), result.stderr
    assert last.endswith("set NUMBA_CACHE_DIR to a writable directory, or unset it"), last


def test_the_cli_says_an_unwritable_numba_cache_dir_in_one_line(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    config = Path(__file__).resolve().parents[1] / "configs" / "kepler.yaml"
    result = subprocess.run([sys.executable, "-m", "elimfast_cli.main", "run", str(config), "-o",
                             str(tmp_path / "a.h5"), "--set", "integration.t_end=10"], capture_output=True, text=True,
                            env=environment(NUMBA_CACHE_DIR=str(blocker)), timeout=300)
    assert result.returncode == 2, result.stderr
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr
    assert result.stderr.startswith(f"error: cannot write the compiled-code cache at {blocker}/elimfast-kernels")
    assert not (tmp_path / "a.h5").exists()


def as_a_user_who_cannot_write_the_package() -> list[str] | None:
    """The command prefix that runs a process which cannot write the package (nobody, through
    setpriv, when this is root; nothing for a user who cannot write it anyway); None where
    neither works."""
    if os.geteuid() == 0:
        return ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"] if shutil.which("setpriv") else None
    return [] if not os.access(PACKAGE, os.W_OK) else None


def test_a_home_that_cannot_be_written_runs_with_a_private_temporary_cache_and_one_note():
    prefix = as_a_user_who_cannot_write_the_package()
    if prefix is None:
        pytest.skip("needs root (setpriv) or an elimfast package this user cannot write")
    # Folders the other user can reach (pytest's tmp_path is private to root).
    scratch = Path(tempfile.mkdtemp(prefix="elimfast-test-home-"))
    try:
        home, tmp = scratch / "home", scratch / "tmp"
        home.mkdir()
        tmp.mkdir()
        os.chmod(scratch, 0o755)
        os.chmod(home, 0o555)   # read-only home
        os.chmod(tmp, 0o1777)
        env = environment(HOME=str(home), TMPDIR=str(tmp), XDG_CACHE_HOME=str(home / ".cache"))
        runs = [subprocess.run(prefix + [sys.executable, "-c", COMPILE_ONE_KERNEL], capture_output=True, text=True,
                               env=env, timeout=300) for _ in range(2)]
        for index, result in enumerate(runs):
            assert result.returncode == 0, result.stderr
            assert result.stdout == "0\n"
            lines = result.stderr.strip().splitlines()
            # the first process compiles into the temporary cache and says so (compile_notice); the second loads
            compiling = [line for line in lines if line.startswith("compiling Numba kernels")]
            assert len(compiling) == (1 if index == 0 else 0), result.stderr
            notes = [line for line in lines if line not in compiling]
            assert len(notes) == 1 and notes[0].startswith(f"note: cannot write the elimfast cache at {home}/.cache"), \
                result.stderr
            uid = 65534 if os.geteuid() == 0 else os.getuid()
            assert f"using {tmp}/elimfast-cache-{uid}" in notes[0] and "ELIMFAST_CACHE_DIR" in notes[0]
        cached = tmp / f"elimfast-cache-{uid}"
        assert oct(cached.stat().st_mode & 0o777) == "0o700"
        assert list((cached / "kernels").rglob("*.nbi"))     # kept for the next run of this user here
    finally:
        subprocess.run(["chmod", "-R", "u+w", str(scratch)], check=False)
        shutil.rmtree(scratch, ignore_errors=True)
