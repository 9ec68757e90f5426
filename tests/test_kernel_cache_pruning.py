"""The kernel cache keeps one folder per key (elimfast, Numba and kernel versions): `elimfast
cache clear --stale` removes all but the current one, and the first process to use a new key
removes the folders no process used for 30 days. Nothing outside a key folder is touched.

Every test works in temporary roots: NUMBA_CACHE_DIR puts both of elimfast's kernel roots
in one folder, $NUMBA_CACHE_DIR/elimfast-kernels (kernels/_cache.py)."""
import os
import threading
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

from elimfast import cache
from elimfast.kernels._cache import kernel_cache_dir
from elimfast_cli.main import cli

DAY = 86400.0


@pytest.fixture()
def root(tmp_path, monkeypatch):
    """The kernel root of this test, with no key folder marked as used by this process yet."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba"))
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setattr(cache, "_USED", set())
    path = tmp_path / "numba" / "elimfast-kernels"
    path.mkdir(parents=True)
    assert cache.kernel_roots() == [path] and kernel_cache_dir() == path / cache.current_key()
    return path


def key_folder(root: Path, name: str, sizes=(100, 250), age_days: float = 0.0) -> Path:
    """A key folder as Numba fills it (a subfolder per source file, .nbi/.nbc files of the
    given sizes), last used age_days ago. Returns it."""
    folder = root / name
    sub = folder / "stepper-a1b2c3"
    sub.mkdir(parents=True, exist_ok=True)
    for index, size in enumerate(sizes):
        (sub / f"stepper.f-{index}.py311.{'nbi' if index % 2 == 0 else 'nbc'}").write_bytes(b"x" * size)
    set_age(folder, age_days)
    return folder


def set_age(folder: Path, age_days: float) -> None:
    stamp = time.time() - age_days * DAY
    os.utime(folder, (stamp, stamp))


def other_key(index: int) -> str:
    """A key that is not the current one (same length, hex)."""
    name = f"{index:x}".rjust(len(cache.current_key()), "0")
    assert name != cache.current_key()
    return name


def tree(path: Path) -> set:
    return {str(p.relative_to(path)) for p in path.rglob("*")}


# --- elimfast cache clear --stale ------------------------------------------------------------

def test_clear_stale_removes_every_other_key_folder_reports_the_bytes_and_touches_nothing_else(root, tmp_path):
    current = key_folder(root, cache.current_key(), sizes=(40, 60), age_days=400)   # old, but in use: kept
    key_folder(root, other_key(1), sizes=(1000, 2000), age_days=1)
    second = key_folder(root, other_key(2), sizes=(500,), age_days=90)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "precious.txt").write_text("keep me")
    (second / "stepper-a1b2c3" / "link").symlink_to(outside)       # a link inside: removed, not its target
    (root / other_key(3)).symlink_to(outside, target_is_directory=True)   # named like a key, but a link: kept
    (root / "notes").mkdir()                                        # not named like a key: kept
    (root / "notes" / "a.nbi").write_bytes(b"y" * 7)
    (root / other_key(0xabc).upper()).mkdir()                           # not a key (upper case): kept
    (root / (other_key(5) + "0")).mkdir()                           # not a key (longer): kept
    problem_file = tmp_path / "cache" / "problems" / "p_0.py"       # the problem cache: not --stale's
    problem_file.parent.mkdir(parents=True)
    problem_file.write_text("x = 1\n")
    kept_current = tree(current)

    info = CliRunner().invoke(cli, ["cache", "info"])
    assert info.exit_code == 0 and "stale kernels:  2 key folders of other versions (3.5 KB" in info.output, \
        info.output
    result = CliRunner().invoke(cli, ["cache", "clear", "--stale"])
    assert result.exit_code == 0, result.output
    assert result.output == (f"removed 2 stale kernel folders from {root}, freed 3.5 KB (3,500 bytes); kept the "
                             f"current one ({cache.current_key()})\n")
    assert sorted(p.name for p in root.iterdir()) == sorted(
        [cache.current_key(), other_key(3), "notes", other_key(0xabc).upper(), other_key(5) + "0"])
    assert tree(current) == kept_current and (outside / "precious.txt").read_text() == "keep me"
    assert (root / other_key(3) / "precious.txt").exists() and (root / "notes" / "a.nbi").exists()
    assert problem_file.exists()
    assert "stale kernels" not in CliRunner().invoke(cli, ["cache", "info"]).output

    again = CliRunner().invoke(cli, ["cache", "clear", "--stale"])
    assert again.exit_code == 0 and again.output.startswith("removed 0 stale kernel folders from ")
    assert "freed 0 bytes; kept the current one" in again.output


def test_clear_stale_with_kernels_is_a_usage_error(root):
    key_folder(root, other_key(1))
    result = CliRunner().invoke(cli, ["cache", "clear", "--stale", "--kernels"])
    assert result.exit_code == 2 and "not both" in result.output and "Traceback" not in result.output
    assert (root / other_key(1)).is_dir()


def test_clear_stale_reports_a_folder_it_cannot_remove_in_one_line(root, monkeypatch):
    blocked = key_folder(root, other_key(1), sizes=(10,))
    real_rmdir = os.rmdir

    def rmdir(path, *args, **kwargs):
        if Path(path) == blocked:
            raise PermissionError(13, "Permission denied")
        return real_rmdir(path, *args, **kwargs)

    monkeypatch.setattr(os, "rmdir", rmdir)
    result = CliRunner().invoke(cli, ["cache", "clear", "--stale"])
    assert result.exit_code == 2
    assert result.stderr == f"error: cannot remove {blocked}: Permission denied; check its permissions\n"
    assert result.stdout.startswith(f"removed 0 stale kernel folders from {root}, freed 10 bytes;")
    assert blocked.is_dir() and not any(blocked.rglob("*.nbi"))


def test_prune_covers_every_root_and_only_key_folders(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    package_root, cache_root = tmp_path / "package", tmp_path / "cache"
    for where in (package_root, cache_root):
        key_folder(where, cache.current_key(), sizes=(5,))
        key_folder(where, other_key(7), sizes=(11, 13))
        (where / "other").mkdir()
    pruned = cache.prune_kernel_folders(roots=[package_root, cache_root, package_root])
    assert sorted(pruned.folders) == sorted([package_root / other_key(7), cache_root / other_key(7)])
    assert pruned.bytes == 2 * (11 + 13) and pruned.failed == []
    for where in (package_root, cache_root):
        assert sorted(p.name for p in where.iterdir()) == sorted([cache.current_key(), "other"])
    assert cache.prune_kernel_folders(roots=[tmp_path / "missing"]).folders == []


# --- automatic: a new key prunes the folders unused for 30 days --------------------------------

def test_the_first_use_of_a_new_key_folder_removes_folders_unused_for_30_days(root):
    current = key_folder(root, cache.current_key(), age_days=0.5)   # just compiled into, not yet marked
    key_folder(root, other_key(1), age_days=cache.STALE_AFTER_DAYS + 1)
    recent = key_folder(root, other_key(2), age_days=cache.STALE_AFTER_DAYS - 1)
    cache.kernel_folder_used(in_package=True)
    assert sorted(p.name for p in root.iterdir()) == sorted([cache.current_key(), other_key(2)])
    assert (current / cache.PRUNED_MARKER).exists() and time.time() - current.stat().st_mtime < 60
    assert recent.is_dir()


def test_a_known_key_folder_is_touched_once_per_process_and_prunes_nothing(root, monkeypatch):
    current = key_folder(root, cache.current_key(), age_days=10)
    (current / cache.PRUNED_MARKER).write_bytes(b"")    # an earlier process marked it (and pruned)
    set_age(current, 10)
    old = key_folder(root, other_key(1), age_days=cache.STALE_AFTER_DAYS + 10)

    cache.kernel_folder_used(in_package=True)
    assert time.time() - current.stat().st_mtime < 60    # used now
    assert old.is_dir()                                  # not a new key: nothing pruned
    set_age(current, 10)
    calls = []
    with monkeypatch.context() as patched:
        patched.setattr(os, "utime", lambda *args, **kwargs: calls.append(args))
        for _ in range(3):
            cache.kernel_folder_used(in_package=True)
    assert calls == [] and current.stat().st_mtime < time.time() - 9 * DAY   # once per process

    monkeypatch.setattr(cache, "_USED", set())           # another process
    cache.kernel_folder_used(in_package=True)
    assert time.time() - current.stat().st_mtime < 60 and old.is_dir()


def test_no_key_folder_yet_means_nothing_is_created_or_pruned(root):
    old = key_folder(root, other_key(1), age_days=365)
    cache.kernel_folder_used(in_package=True)
    cache.kernel_folder_used(in_package=False)
    assert sorted(p.name for p in root.iterdir()) == [other_key(1)] and old.is_dir()


def test_concurrent_pruning_removes_each_file_once_and_never_fails(root):
    expected = 0
    for index in range(1, 13):
        sizes = [index * 10 + k for k in range(40)]
        key_folder(root, other_key(index), sizes=sizes, age_days=60)
        expected += sum(sizes)
    key_folder(root, cache.current_key())
    results, errors = [], []
    barrier = threading.Barrier(4)

    def prune():
        try:
            barrier.wait()
            results.append(cache.prune_kernel_folders(cache.STALE_AFTER_DAYS))
        except BaseException as err:   # noqa: BLE001 -- reported below
            errors.append(err)

    threads = [threading.Thread(target=prune) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == [] and all(r.failed == [] for r in results)
    assert sum(r.bytes for r in results) == expected          # every file counted by the one that removed it
    assert [p.name for p in root.iterdir()] == [cache.current_key()]


def test_a_folder_removed_by_another_process_meanwhile_is_skipped(root, monkeypatch):
    gone = root / other_key(1)
    key_folder(root, other_key(2), sizes=(30,))
    listed = cache.stale_kernel_folders
    monkeypatch.setattr(cache, "stale_kernel_folders", lambda r, days=None: [gone, *listed(r, days)])
    pruned = cache.prune_kernel_folders()
    assert pruned.failed == [] and pruned.bytes == 30 and not (root / other_key(2)).exists()


def test_integrate_marks_the_kernels_key_folder_as_used():
    import elimfast.integrate  # noqa: F401 -- the hook runs at its import

    folder = kernel_cache_dir(in_package=True)
    if not folder.is_dir():      # the package is not writable: its kernels are in elimfast's cache
        folder = kernel_cache_dir(in_package=False)
    assert folder in cache._USED and (folder / cache.PRUNED_MARKER).is_file()


def test_a_generated_problem_compiling_into_a_new_cache_key_folder_prunes_old_ones(tmp_path, monkeypatch):
    from elimfast.problems.symbolic import problem_from_expressions

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("ELIMFAST_CACHE_DIR", str(tmp_path / "cache"))
    kernels = tmp_path / "cache" / "kernels"
    old = key_folder(kernels, other_key(1), age_days=cache.STALE_AFTER_DAYS + 5)
    recent = key_folder(kernels, other_key(2), age_days=2)
    problem = problem_from_expressions(coordinates={"q": ["x"], "p": ["v"]}, hamiltonian="v**2/2 + x**4/4 + x**2/2",
                                       initial={"x": 0.5, "v": 0.25}, name="prune_probe")
    assert problem.hamiltonian(problem.y0) == pytest.approx(0.25 ** 2 / 2 + 0.5 ** 4 / 4 + 0.5 ** 2 / 2)
    current = kernels / cache.current_key()
    assert (current / cache.PRUNED_MARKER).is_file() and any(current.rglob("*.nbi"))
    assert not old.exists() and recent.is_dir()
