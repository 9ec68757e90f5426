"""Output paths as users give them (a user trial): a trailing '/', symlinks (dangling too), the
longest legal file names, a device; and the advice for a file another HDF5 program left open."""
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import pytest
from click.testing import CliRunner

from elimfast.io import hdf5
from elimfast_cli.main import cli

ROOT = Path(__file__).resolve().parents[1]
KEPLER = str(ROOT / "configs" / "kepler.yaml")
SHORT = ["--set", "integration.t_end=1", "-q"]


def run(*args):
    return CliRunner().invoke(cli, ["run", KEPLER, *SHORT, *map(str, args)])


def steps_done(path) -> int:
    with h5py.File(path, "r") as f:
        return int(f.attrs["steps_done"])


def test_an_output_ending_in_a_slash_names_a_directory_and_is_refused(tmp_path):
    target = f"{tmp_path / 'newdir'}/"
    result = run("-o", target)
    assert result.exit_code == 2 and "is a directory" in result.stderr and "give a file name" in result.stderr, \
        result.output
    assert not (tmp_path / "newdir").exists()


def test_overwrite_through_a_symlink_writes_its_target(tmp_path):
    target = tmp_path / "data" / "run.h5"
    target.parent.mkdir()
    assert run("-o", target).exit_code == 0
    link = tmp_path / "link.h5"
    link.symlink_to(target)
    result = run("-o", link, "--overwrite", "--set", "integration.t_end=2")
    assert result.exit_code == 0, result.output
    assert link.is_symlink() and steps_done(target) == 20
    assert [p.name for p in target.parent.iterdir()] == ["run.h5"]


def test_a_dangling_symlink_as_output_creates_its_target(tmp_path):
    link = tmp_path / "link.h5"
    link.symlink_to(tmp_path / "target.h5")
    result = run("-o", link)
    assert result.exit_code == 0 and "appeared while" not in result.output, result.output
    assert link.is_symlink() and steps_done(tmp_path / "target.h5") == 10


@pytest.mark.parametrize("length", [249, 255])
def test_the_longest_legal_file_names_are_written(tmp_path, length):
    path = tmp_path / ("r" * (length - 3) + ".h5")
    result = run("-o", path)
    assert result.exit_code == 0, result.output
    assert steps_done(path) == 10 and [p.name for p in tmp_path.iterdir()] == [path.name]
    again = run("-o", path, "--overwrite")                     # a stale temporary name is found again
    assert again.exit_code == 0, again.output


def test_a_device_as_output_is_not_a_regular_file_at_once():
    result = run("-o", "/dev/null")
    assert result.exit_code == 2 and "not a regular file" in result.stderr, result.output
    assert "--overwrite" not in result.stderr


def test_a_file_another_hdf5_program_left_open_is_sent_to_repair(tmp_path):
    """SIGKILLed while h5py had it open for writing (not SWMR): HDF5 refuses it, repair fixes it."""
    path = tmp_path / "left.h5"
    writer = subprocess.Popen([sys.executable, "-c",
                               "import h5py, sys, time\n"
                               f"f = h5py.File({str(path)!r}, 'w', libver='latest')\n"
                               "f['x'] = [1.0, 2.0]\nf.flush()\nprint('open', flush=True)\ntime.sleep(60)\n"],
                              stdout=subprocess.PIPE, text=True)
    assert writer.stdout.readline().strip() == "open"
    writer.send_signal(signal.SIGKILL)
    writer.wait()
    assert hdf5.consistency_flags(path)
    result = CliRunner().invoke(cli, ["inspect", str(path)])
    assert result.exit_code == 2 and f"elimfast repair {path}" in result.stderr, result.output
    repaired = CliRunner().invoke(cli, ["repair", str(path)])
    assert repaired.exit_code == 0, repaired.output
    with h5py.File(path, "r") as f:
        assert list(f["x"][:]) == [1.0, 2.0]


def test_a_sweep_output_ending_in_a_slash_is_refused(tmp_path):
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text(f"base: {KEPLER}\ngrid:\n  - {{name: h, key: integration.h, values: [0.1]}}\n")
    result = CliRunner().invoke(cli, ["sweep", str(sweep), "-o", f"{tmp_path / 'newdir'}/", "-q"])
    assert result.exit_code == 2 and "is a directory; give a file name" in result.stderr, result.output
    assert not (tmp_path / "newdir").exists()


def test_inspect_says_when_the_newest_saved_state_is_damaged(tmp_path):
    """/state/record keeps the state twice; with the newer copy spoiled, resume falls back to the
    older one (test_faults), and inspect says so instead of showing the older count silently."""
    path = tmp_path / "run.h5"
    assert CliRunner().invoke(cli, ["run", KEPLER, "-o", str(path), "--set", "integration.t_end=5", "-q",
                                    "--set", "output.every=1"]).exit_code == 0
    with h5py.File(path, "r+") as f:
        record = f["state/record"]
        newer = int(record[0, 0] < record[1, 0])
        row = record[newer]
        row[10] += 1.0                       # its CRC no longer matches
        record[newer] = row
    with hdf5.RunFile(path) as run_file:
        older = run_file.saved_state()["steps_done"]
    result = CliRunner().invoke(cli, ["inspect", str(path)])
    assert "the newest copy of the saved state is damaged" in result.output, result.output
    assert f"resume continues from the other copy, at step {older}" in result.output
