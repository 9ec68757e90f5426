"""Findings of two user trials (a GNI researcher's and a tester's of faults), each with the
behaviour it asked for. Each test fails on the code before its fix."""
import math
import os
import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

import elimfast
from elimfast.errors import ConvergenceError, ParameterError
from elimfast.methods import ehbvm, hbvm
from elimfast.problems import henon_heiles, kepler
from elimfast_cli.main import cli


def test_a_step_too_short_for_elim_s_gamma_is_named_as_such_not_blamed_on_the_invariants():
    """Kepler e = 0.9 imposing L and A_y at h = 1e-5 fails after 4 halvings (Gamma's entries, of size
    ~h^j, below their own rounding): the message said 'Assumption 1 fails for these invariants;
    impose fewer or other invariants, or change h', where the gradients are independent and
    GHBVM, or a larger h, completes."""
    problem = kepler(eccentricity=0.9)
    with pytest.raises(ConvergenceError) as info:
        elimfast.integrate(problem, ehbvm(8, 4), h=1e-5, n_steps=50_000, conserve=["angular_momentum", "lrl_y"])
    message = str(info.value)
    assert "too short for ELIM's Gamma here" in message and "take a larger h" in message, message
    assert "fewer halvings (solver.max_halvings)" in message and "take GHBVM" in message
    assert "gradients independent here" in message and "Assumption 1" not in message
    # what it advises completes
    elimfast.integrate(problem, ehbvm(8, 4), h=1e-4, n_steps=5000, conserve=["angular_momentum", "lrl_y"])


def test_h_max_and_epsilon_are_bounded_as_a_fixed_h_is():
    """h_max = 1e-9 over t = 100 (10^11 steps at least) started at once and wrote 217 MB in 20 s on
    its way to 2 TB; a fixed h that small is refused. epsilon = 1e-9 ran 400 steps and failed."""
    problem = henon_heiles()
    with pytest.raises(ParameterError, match=r"^h_max gives \(t_end - t0\)/h_max = 1e\+11 steps at least, more "
                                             r"than 1e10: .* raise h_max or shorten the run"):
        elimfast.integrate(problem, hbvm(8, 4), t_end=100.0, rtol=1e-10, h_max=1e-9)
    with pytest.raises(ParameterError, match=r"^epsilon must be at least 1e-06: .* got 1e-09"):
        elimfast.integrate(kepler(0.9), hbvm(8, 4), t_end=1.0, step_control="time_scale", epsilon=1e-9)
    elimfast.integrate(problem, hbvm(8, 4), t_end=1.0, rtol=1e-10, h_max=0.1)   # a sensible cap runs


@pytest.mark.parametrize("chunk_steps, match", [(0, r"must be >= 1, got 0"), (-5, r"must be >= 1, got -5"),
                                                (2.5, r"must be a whole number")])
def test_chunk_steps_is_validated(chunk_steps, match):
    """chunk_steps = 0 appended empty chunks until 24 GB were gone; -5 gave NumPy's message."""
    with pytest.raises(ParameterError, match=rf"^chunk_steps {match}"):
        elimfast.integrate(kepler(), ehbvm(12, 3), h=0.1, t_end=100.0, chunk_steps=chunk_steps)


def test_an_eof_error_is_an_error_not_an_interruption(tmp_path, monkeypatch):
    """click turns EOFError into Abort, as for Ctrl-D at a prompt, and the command line reported it
    as 'interrupted while starting', exit 130 (an empty cache file's EOFError, on every run)."""
    import elimfast_cli.main as main

    def empty(*args, **kwargs):
        raise EOFError("Ran out of input")
    monkeypatch.setattr(main, "_load", empty)
    config = tmp_path / "run.yaml"
    config.write_text("problem: kepler\nmethod: {name: gauss, s: 2}\nintegration: {h: 0.1, n_steps: 10}\n")
    result = CliRunner().invoke(cli, ["run", str(config), "-o", str(tmp_path / "o.h5")])
    assert result.exit_code == 1 and "interrupted" not in result.output, result.output
    assert "EOFError: Ran out of input" in result.output


HELPER_PROBLEM = '''\
import numba
Q_NAMES = ("q",)
P_NAMES = ("p",)
Y0 = [0.5, 1.0]

@numba.njit
def force(q):
    return q ** 3

def H(y, params):
    return 0.5 * y[1] ** 2 + 0.25 * y[0] ** 4

def grad_H(y, params, out):
    out[0] = force(y[0])
    out[1] = y[1]
'''


@pytest.mark.slow
def test_a_problem_file_s_njit_helpers_are_cached_with_its_functions(tmp_path):
    """A Lennard-Jones file whose helpers were plain @numba.njit compiled them, and every function
    calling them, in every process, each saying 'compiling the problem's own functions (once: later
    runs load them from the cache)'."""
    (tmp_path / "problem.py").write_text(HELPER_PROBLEM)
    script = tmp_path / "probe.py"
    script.write_text(textwrap.dedent(f"""\
        import numpy as np
        from elimfast.problems import problem_from_file
        p = problem_from_file({str(tmp_path / 'problem.py')!r})
        out = np.empty(2)
        p.grad_H(np.array([0.5, 1.0]), p.params, out)
        print(out.tolist())
        """))
    env = {**os.environ, "ELIMFAST_CACHE_DIR": str(tmp_path / "ef")}

    def run():
        done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
        return done.stdout.strip(), done.stderr

    first, said = run()
    assert first == "[0.125, 1.0]" and "compiling the problem's own functions" in said
    again, said = run()
    assert again == first and "compiling" not in said, said


@pytest.mark.usefixtures("allow_python")
def test_the_H_note_of_a_run_resumed_with_an_edited_problem_file_names_the_edit(tmp_path):
    """A user trial killed a run, edited its python: file's potential and resumed: the note spoke of
    quadrature and k, and not of the two H the run had solved."""
    from elimfast.io.hdf5 import RunFile

    from elimfast_cli.report import energy_note
    problem_file = tmp_path / "problem.py"
    problem_file.write_text(HELPER_PROBLEM)
    config = tmp_path / "run.yaml"
    config.write_text("problem: {python: problem.py}\nmethod: {name: gauss, s: 2}\nintegration: {h: 0.2, n_steps: 50}\n")
    out = tmp_path / "o.h5"
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(out)]).exit_code == 0
    with RunFile(out) as run_file:
        plain = energy_note(run_file)
    assert plain is not None and "edited" not in plain   # GAUSS(2) loses a quartic H: the quadrature note
    with h5py.File(out, "a") as f:
        f.attrs["problem_file_history"] = ["from step 30: sha256 0123456789abcdef (before: fedcba9876543210)"]
    with RunFile(out) as run_file:
        edited = energy_note(run_file)
    assert edited.startswith("the python: problem file was edited during the run (from step 30; --resume with the "
                             "new one), so its steps solve more than one H") and edited.endswith(plain), edited


def test_a_bit_flipped_in_the_method_tables_is_found_by_inspect(tmp_path):
    """The tables under /method were contiguous, without a checksum: a flipped bit made b[4] read
    1.868 instead of 0.1167 and inspect said every checksum held."""
    from elimfast.io.hdf5 import RunFile
    config = tmp_path / "run.yaml"
    config.write_text("problem: kepler\nmethod: {name: ehbvm, k: 8, s: 4}\nintegration: {h: 0.1, n_steps: 20}\n")
    out = tmp_path / "o.h5"
    assert CliRunner().invoke(cli, ["run", str(config), "-o", str(out)]).exit_code == 0
    with h5py.File(out, "r") as f:
        assert f["method/b"].fletcher32 and f["method/A"].fletcher32
        offset = f["method/b"].id.get_chunk_info(0).byte_offset
    with open(out, "r+b") as raw:
        raw.seek(offset + 38)
        byte = raw.read(1)[0]
        raw.seek(offset + 38)
        raw.write(bytes([byte ^ 0x40]))
    result = CliRunner().invoke(cli, ["inspect", str(out)])
    assert result.exit_code != 0 and "/method" in result.output, result.output
    with RunFile(out) as run_file, pytest.raises(elimfast.errors.ElimfastError, match="/method"):
        run_file.verify()


@pytest.mark.parametrize("config", ["kepler.yaml", "kepler_adaptive.yaml"])
def test_a_t_end_before_a_t0_given_by_set_names_the_set(config):
    """`check calogero.yaml --set integration.t0=6` was told 'integration.t_end: must be after t0 =
    6.0' without the --set that made it so, as other rules that depend on t0 name it."""
    from pathlib import Path

    from elimfast.config import ConfigError, load_run
    path = Path(__file__).resolve().parents[1] / "configs" / config
    with pytest.raises(ConfigError, match=r"integration.t_end: must be .*after t0 = 2000.*\(with --set "
                                          r"integration.t0=2000\)$"):
        load_run(path, ["integration.t0=2000"])


def test_paper_out_naming_a_file_is_refused_before_any_run(tmp_path):
    """`elimfast paper --out existing_file.yaml` was told only '<it>: File exists', with no fix."""
    target = tmp_path / "k.yaml"
    target.write_text("x: 1\n")
    result = CliRunner().invoke(cli, ["paper", "--out", str(target)])
    assert result.exit_code == 2 and "is a file, not a folder" in result.output and "--out" in result.output, \
        result.output
    assert target.read_text() == "x: 1\n"


def test_numba_s_thread_count_of_zero_is_named_not_an_internal_error():
    """NUMBA_NUM_THREADS=0 made an ensemble sweep fail with 'internal error: ValueError: Number of
    threads specified must be > 0. at parallel.py:42 (please report it...)', exit 1."""
    from elimfast_cli.main import EXIT_USAGE, error_line
    message, code = error_line(ValueError("Number of threads specified must be > 0."))
    assert code == EXIT_USAGE and message.startswith("NUMBA_NUM_THREADS=") and "unset it" in message
    assert error_line(ValueError("something else"))[0].startswith("internal error: ValueError")
