"""Defects found by trying elimfast as a new user would (issue 10, item 10): each test
fails on the code before its fix."""
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import matplotlib
import pytest
from click.testing import CliRunner

from elimfast import methods, problems, streaming
from elimfast.integrate import Integration
from elimfast.io.hdf5 import RunFile
from elimfast_cli import plots
from elimfast_cli.main import cli, paper_configs

matplotlib.use("Agg")
ROOT = Path(__file__).resolve().parents[1]
ELIMFAST = str(Path(sys.executable).with_name("elimfast"))


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def kepler_file(path, every, n_steps=400, h=0.1, **kw):
    run = Integration(problems.kepler(0.6), methods.ehbvm(6, 3), h, n_steps, conserve=("angular_momentum",),
                      store_every=every, **kw)
    outcome = streaming.run_to_file(run, path, handle_signals=False, config_text="problem: {builtin: kepler}\n")
    return path, outcome


@pytest.fixture(scope="module")
def failed_file(tmp_path_factory):
    """Kepler e = 0.9 from aphelion: the fixed point fails near perihelion (tests/test_hdf5.py)."""
    e = 0.9
    aphelion = [-(1 + e), 0.0, 0.0, -((1 - e) / (1 + e)) ** 0.5]
    run = Integration(problems.kepler(e), methods.gauss(2), 0.1, 200, max_iter=10, y0=aphelion,
                      solver="fixed_point", max_halvings=0)
    path = tmp_path_factory.mktemp("failed") / "f.h5"
    outcome = streaming.run_to_file(run, path, handle_signals=False, config_text="problem: {builtin: kepler}\n")
    assert outcome.status.startswith("failed: ") and len(outcome.status) > 200
    return path


def test_a_failed_runs_plot_title_is_short_and_inside_the_figure(failed_file):
    import matplotlib.pyplot as plt
    with RunFile(failed_file) as run_file:
        figure = plots.draw(run_file, "invariants")
        status = run_file.status
    try:
        title = figure.axes[0].title
        text = title.get_text()
        first, second = text.split("\n")
        assert first.startswith("kepler, GAUSS(2), h = 0.1")
        step = re.search(r"at step \d+", status).group(0)
        assert second.startswith("[failed: ") and step in second and len(second) <= plots.TITLE_STATUS_CHARS + 2
        assert "GAUSS(2)" not in second          # the method is on the first line already
        figure.canvas.draw()
        box, canvas = title.get_window_extent(), figure.bbox
        assert box.x0 >= canvas.x0 and box.x1 <= canvas.x1 and box.y1 <= canvas.y1   # not cut at either edge
    finally:
        plt.close(figure)


@pytest.mark.parametrize("status,expected", [
    ("complete", "complete"),
    ("interrupted", "interrupted"),
    ("failed: EHBVM(12,3): the simplified Newton did not converge (max_iter = 30) at step 7 (t = 0.6 -> 0.7); "
     "last relative increment 1e-3; reduce h", "failed: the simplified Newton did not converge at step 7"),
    ("stopped: disk full at step 12", "stopped: disk full at step 12"),
])
def test_status_text_keeps_the_start_and_cuts_at_a_word(status, expected):
    assert plots.status_text(status) == expected
    long = "failed: " + "a very long reason " * 10
    short = plots.status_text(long)
    assert len(short) <= plots.TITLE_STATUS_CHARS and short.endswith("...")
    kept = short[:-3]
    assert long.startswith(kept) and long[len(kept)] == " "     # cut between words, the start kept


def test_orbit_of_sparse_samples_draws_markers_not_chords(tmp_path):
    import matplotlib.pyplot as plt
    sparse_path, _ = kepler_file(tmp_path / "sparse.h5", every=10)            # 6 samples per period
    dense_path, _ = kepler_file(tmp_path / "dense.h5", every=1, h=0.02, n_steps=400)   # 314 per period
    for path, expect_sparse in ((sparse_path, True), (dense_path, False)):
        with RunFile(path) as run_file:
            figure = plots.draw(run_file, "orbit")
        try:
            axes = figure.axes[0]
            (line,) = axes.get_lines()
            notes = [t.get_text() for t in axes.texts]
            if expect_sparse:
                assert line.get_linestyle() == "None" and line.get_marker() == "."
                assert any("markers only" in note for note in notes)
            else:
                assert line.get_linestyle() == "-" and not notes
        finally:
            plt.close(figure)


def test_plot_to_an_unknown_format_is_a_usage_error_naming_the_suffixes(tmp_path):
    path, _ = kepler_file(tmp_path / "k.h5", every=10, n_steps=20)
    for name, fragment in (("fig.xyz", "unknown image format '.xyz'"), ("fig", "no suffix")):
        result = invoke("plot", path, "-o", tmp_path / name)
        assert result.exit_code == 2, result.output
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and fragment in lines[0] and ".png" in lines[0] and ".pdf" in lines[0]
        assert "internal error" not in result.stderr and not (tmp_path / name).exists()


def test_paper_outside_the_repository_is_a_usage_error_or_finds_the_configs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert paper_configs() == ROOT / "configs" / "paper"        # an editable install finds the repository's
    process = subprocess.run([ELIMFAST, "paper", "--configs", str(tmp_path / "none"), "--out", "X"],
                             capture_output=True, text=True, timeout=120)
    assert process.returncode == 2, process.stderr
    assert process.stderr.count("\n") == 1 and "no such sweep file" in process.stderr
    assert "internal error" not in process.stderr


def test_paper_does_not_replace_an_earlier_runs_tables_unasked(tmp_path):
    out = tmp_path / "paper-out"
    out.mkdir()
    (out / "table1.md").write_text("my annotated table\n")
    process = subprocess.run([ELIMFAST, "paper", "--out", str(out)], capture_output=True, text=True, timeout=120,
                             cwd=ROOT)
    assert process.returncode == 2, process.stderr
    assert process.stderr.count("\n") == 1 and "--overwrite" in process.stderr and "table1.md" in process.stderr
    assert (out / "table1.md").read_text() == "my annotated table\n"


def _command_lines(text: str, heading: str) -> list[str]:
    block = text.split(heading, 1)[1]
    return [line.split("#")[0].strip() for line in block.splitlines() if line.startswith("    elimfast ")]


def test_readmes_first_cli_command_works_after_make_run(tmp_path, monkeypatch):
    """`make run` writes out/kepler.h5; the README's first command must not then fail on it."""
    make_run = next(line for line in (ROOT / "Makefile").read_text().splitlines() if "elimfast run" in line)
    make_arguments = shlex.split(make_run.split("elimfast", 1)[1])
    first = _command_lines((ROOT / "README.md").read_text(), "## Command line")[0]
    readme_arguments = shlex.split(first.split("elimfast", 1)[1])
    assert readme_arguments[0] == "run"
    shutil.copytree(ROOT / "configs", tmp_path / "configs")
    monkeypatch.chdir(tmp_path)
    quick = ["--set", "integration.t_end=5"]
    made = invoke(*make_arguments, *quick)
    assert made.exit_code == 0 and Path("out/kepler.h5").is_file(), made.output
    again = invoke(*readme_arguments, "--quiet", *quick)
    assert again.exit_code == 0, again.stderr
    assert os.path.getsize("out/kepler.h5") > 0


def test_every_dotted_elimfast_name_in_the_docs_exists():
    """Each `elimfast.a.b` that README.md and docs/*.md name resolves as a user's code would
    reach it: `import elimfast.a` then attribute access. docs/solver.md said
    `solver=elimfast.integrate.SolverSettings(...)`, but elimfast.integrate is the function."""
    import importlib
    import types
    texts = [(ROOT / "README.md").read_text()] + [path.read_text() for path in sorted((ROOT / "docs").glob("*.md"))]
    names = sorted({m.group(0) for text in texts for m in re.finditer(r"\belimfast(\.[A-Za-z_]\w*)+", text)})
    assert "elimfast.sweep.run" in names
    missing = []
    for name in names:
        parts = name.split(".")
        value = importlib.import_module(parts[0])
        for depth, part in enumerate(parts[1:], start=1):
            if not hasattr(value, part) and isinstance(value, types.ModuleType):
                try:
                    importlib.import_module(".".join(parts[:depth + 1]))   # import elimfast.sweep
                except ImportError:
                    pass
            if not hasattr(value, part):
                missing.append(name)
                break
            value = getattr(value, part)
    assert not missing, missing
