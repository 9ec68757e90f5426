"""``elimfast``: click commands that parse, call the library and print; no numerics here.

Exit codes: 0 done; 1 the integration failed (or an internal error); 2 usage, config or
file error; 130 interrupted. Every error is one line on stderr; set ELIMFAST_DEBUG=1 to
get the traceback of an unexpected one. Heavy modules (numba kernels, h5py, matplotlib)
are imported inside the commands that need them, so ``--help`` stays instant.
"""
from __future__ import annotations

import contextlib
import functools
import gc
import math
import os
import sys
from pathlib import Path

import click

DEBUG_ENV = "ELIMFAST_DEBUG"
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
CONTEXT = {"help_option_names": ["-h", "--help"], "max_content_width": 100}


# --- the error boundary -------------------------------------------------------------------
def one_line(text) -> str:
    return " ".join(str(text).split())


def error_line(exc: BaseException) -> tuple[str, int]:
    """(message, exit code) for an exception that reached the command line."""
    from elimfast.errors import ConvergenceError, ElimfastError

    if isinstance(exc, ConvergenceError):
        return f"run failed: {one_line(exc)}", EXIT_FAILED
    if isinstance(exc, ElimfastError):
        return one_line(exc), getattr(exc, "exit_code", EXIT_USAGE)
    if isinstance(exc, OSError):
        name = getattr(exc, "filename", None)
        reason = exc.strerror or one_line(exc)
        return (f"{name}: {reason}" if name else reason), EXIT_USAGE
    yaml = sys.modules.get("yaml")
    if yaml is not None and isinstance(exc, yaml.YAMLError):
        return f"invalid YAML: {one_line(exc)}", EXIT_USAGE
    if isinstance(exc, UnicodeDecodeError):
        return f"not a UTF-8 text file ({one_line(exc)})", EXIT_USAGE
    if isinstance(exc, MemoryError):
        return "out of memory; lower output.every's sample count or the problem size", EXIT_FAILED
    if isinstance(exc, ValueError) and str(exc).startswith("Number of threads specified must be > 0"):
        # Numba's own check of its thread count, raised when a parallel kernel first starts (a user
        # trial's NUMBA_NUM_THREADS=0 ensemble was an internal error)
        return (f"NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', '?')} in the environment: Numba needs at "
                "least 1 thread; unset it, or set it to the number of cores"), EXIT_USAGE
    where = ""
    tb = exc.__traceback__
    while tb is not None:
        where = f" at {Path(tb.tb_frame.f_code.co_filename).name}:{tb.tb_lineno}"
        tb = tb.tb_next
    return (f"internal error: {type(exc).__name__}: {one_line(exc)}{where} "
            f"(please report it; rerun with {DEBUG_ENV}=1 for the traceback)"), EXIT_FAILED


class _Exit(Exception):
    """Carries an exit code out of the error handlers to the one place that exits."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def fail(message: str, code: int):
    click.echo(f"error: {message}", err=True)
    raise _Exit(code)


def _leave(code: int, fast: bool):
    """Exit with code. ``fast``: skip the interpreter's teardown (about 0.25 s of unloading
    numba and llvmlite) once every file is closed and the streams are flushed; only for
    a real command line (args from sys.argv), never inside a caller's process."""
    if fast:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        except (BrokenPipeError, ValueError):
            pass
        os._exit(code)
    sys.exit(code)


_COMMAND_LINE = False   # set by ElimfastGroup.main in a real `elimfast` process (not inside a caller's)
# What an interruption outside a run's chunks (imports, compiling, loading the config) leaves:
# `run` says that its output file is as it was (a user trial saw only "interrupted").
_INTERRUPTED = ["interrupted"]


class _Interrupted(BaseException):
    """A signal outside a run's own handling: not a KeyboardInterrupt, which click answers with a
    blank line on stderr before ours."""


# The signals _interrupt was called for. Raised inside a ctypes callback of Numba's compiler, the
# _Interrupted is swallowed ("Exception ignored on calling ctypes callback function") and the compile
# fails later with an error of its own ("RuntimeError: no compiled object yet"), reported as an internal
# error, exit 1 (a user trial, 1 Ctrl-C in 7 while a problem compiled): after a signal, any error is
# the interruption's.
_SIGNALLED: list[int] = []


def _interrupt(signum, frame):
    """Ctrl-C, SIGTERM or SIGHUP before a run's own handling (streaming.StopOnSignals) takes over:
    one line and exit 130 (a user trial, signalling `run --resume` at start-up: SIGTERM ended it
    silently with 143, Ctrl-C printed a blank line and 'interrupted')."""
    _SIGNALLED.append(signum)
    raise _Interrupted


def _unraisable(hook):
    """sys.unraisablehook that drops an _Interrupted raised where Python cannot propagate it (a
    ctypes callback): its interruption is reported once, at exit (_SIGNALLED)."""
    def quiet(unraisable):
        if unraisable.exc_type is _Interrupted:
            return
        hook(unraisable)
    return quiet


@contextlib.contextmanager
def start_up():
    """Imports and kernel loading with Python's cyclic garbage collector paused.

    Importing Numba and loading kernels from its cache creates a few hundred thousand
    long-lived objects, and the collector rescans them all on every full collection it
    runs meanwhile: about 0.1 s of a 0.7 s `elimfast run` (measured: CPU time 0.74 s ->
    0.63 s with the collector off). In an `elimfast` process the objects loaded so far
    are then frozen (gc.freeze: they live until exit; later collections skip them)."""
    paused = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if paused:
            if _COMMAND_LINE:
                gc.freeze()
            gc.enable()


class ElimfastGroup(click.Group):
    """A click group whose every error is one line on stderr, with the documented exit codes."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        debug = bool(os.environ.get(DEBUG_ENV))
        fast = args is None and standalone_mode and not debug
        global _COMMAND_LINE
        _COMMAND_LINE = args is None and standalone_mode
        if _COMMAND_LINE:
            import signal
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
                signal.signal(sig, _interrupt)
            sys.unraisablehook = _unraisable(sys.unraisablehook)
        try:
            try:
                code = super().main(args, prog_name or "elimfast", complete_var, standalone_mode=False, **extra)
            except click.UsageError as err:
                command = err.ctx.command_path if err.ctx is not None else "elimfast"
                fail(f"{one_line(err.format_message()).rstrip('.')} (see '{command} --help')", EXIT_USAGE)
            except click.ClickException as err:
                fail(one_line(err.format_message()), EXIT_USAGE)
            except (click.Abort, KeyboardInterrupt, _Interrupted) as err:
                cause = err.__cause__ if isinstance(err, click.Abort) else None
                if isinstance(cause, EOFError) and not _SIGNALLED:
                    # click turns an EOFError into Abort, as for Ctrl-D at a prompt; elimfast reads no
                    # input, so it is an error of ours, not an interruption (a user trial: an empty cache
                    # file's EOFError was 'interrupted while starting', exit 130, on every run)
                    if debug:
                        raise cause from None
                    fail(*error_line(cause))
                fail(_INTERRUPTED[-1], EXIT_INTERRUPTED)
            except BrokenPipeError:
                # The reader went away (elimfast inspect ... | head): not an error of ours.
                sys.stderr.close()
                os._exit(EXIT_OK)
            except SystemExit as err:
                # click answers a broken pipe itself: it wraps the streams and exits with 1, the code of a
                # failed integration (a user trial: `elimfast check ... | head -1` exited 1)
                if err.code == 1 and type(sys.stdout).__name__.endswith("PacifyFlushWrapper"):
                    os._exit(EXIT_OK)
                raise
            except _Exit:
                raise   # fail() inside a command: its message is printed, the code stands
            except Exception as err:
                if debug:
                    raise
                if _SIGNALLED:
                    fail(_INTERRUPTED[-1], EXIT_INTERRUPTED)
                fail(*error_line(err))
        except _Exit as done:
            code = done.code
        code = code if isinstance(code, int) else EXIT_OK
        if standalone_mode:
            _leave(code, fast)
        return code


def _versions() -> str:
    from importlib.metadata import PackageNotFoundError, version

    def v(name):
        try:
            return version(name)
        except PackageNotFoundError:
            return "?"
    return (f"elimfast {v('elimfast')} (numba {v('numba')}, numpy {v('numpy')}, h5py {v('h5py')}, "
            f"python {sys.version.split()[0]})")


def _print_version(ctx, param, value):
    if value and not ctx.resilient_parsing:
        click.echo(_versions())
        ctx.exit(EXIT_OK)


def announce_compilation():
    """Say on stderr, in one line, when Numba starts compiling (elimfast/compile_notice.py owns
    the lines and when they are said). Imports Numba."""
    from elimfast import compile_notice
    compile_notice.announce(write=lambda line: click.echo(line, err=True))


@click.group(name="elimfast", cls=ElimfastGroup, context_settings=CONTEXT, invoke_without_command=True)
@click.option("--version", is_flag=True, expose_value=False, is_eager=True, callback=_print_version,
              help="Show the versions of elimfast, numba, numpy, h5py and exit.")
@click.pass_context
def cli(ctx):
    """Invariant-conserving integrators for Hamiltonian problems (GAUSS, HBVM, ELIM/EHBVM, LIM/GHBVM).

    \b
    Examples:
      elimfast run configs/kepler.yaml -o out/kepler.h5
      elimfast inspect out/kepler.h5
      elimfast plot out/kepler.h5 --kind invariants -o errors.png
      elimfast repair out/kepler.h5   (after kill -9: for h5py, xarray and other HDF5 programs)

    Exit codes: 0 done, 1 the integration failed, 2 usage/config/file error, 130 interrupted.
    Set ELIMFAST_DEBUG=1 for the traceback of an unexpected error.
    """
    if ctx.invoked_subcommand is None:
        click.echo(ctx.get_help())


def _file_name(ctx, param, value):
    """An output option's value: a file name, refused when empty (as a path, '' would be '.')."""
    if value is not None and not value.strip():
        raise click.BadParameter(f"the output path is empty; give a file name ({param.metavar})")
    return value


# --- run, check -------------------------------------------------------------------------
SET_HELP = "Override a config key, e.g. --set method.s=4 --set integration.t_end=100 (repeatable)."


def _allow_python_option(command, names: str = "the config names"):
    """--allow-python: the python: problem files named by the config (or --set) may run, for this
    command only (config.allowing_python until click closes its context: a CLI called in-process,
    from a notebook, leaves no permission behind); a sweep's worker processes and Dask tasks are
    given it by the sweep."""
    def allow(ctx, param, value):
        if value:
            from elimfast.config import allowing_python
            ctx.with_resource(allowing_python(True))
        return value
    return click.option("--allow-python", is_flag=True, expose_value=False, callback=allow,
                        help=f"Run the python: problem files {names}: they are code, which a config alone never "
                             "runs (also: ELIMFAST_ALLOW_PYTHON=1).")(command)


def _load(config: str, overrides):
    from elimfast.config import load_run
    return load_run(config, overrides=list(overrides))


def _resolved_yaml(spec, output_path=None) -> str:
    import copy

    import yaml
    resolved = copy.deepcopy(spec.resolved)
    if output_path is not None:
        resolved.setdefault("output", {})["path"] = str(output_path)
    return yaml.safe_dump(resolved, sort_keys=False, default_flow_style=None, width=100)


@cli.command(context_settings=CONTEXT)
@click.argument("config", metavar="CONFIG")
@_allow_python_option
@click.option("-o", "--output", metavar="OUT.h5", callback=_file_name,
              help="The HDF5 file to write (overrides output.path).")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help=SET_HELP)
@click.option("--overwrite", is_flag=True, help="Replace OUT.h5 if it exists.")
@click.option("--resume", is_flag=True, help="Continue the interrupted or killed run stored in OUT.h5.")
@click.option("-q", "--quiet", is_flag=True, help="No progress and no summary line (errors only, and the "
              "one line saying that Numba compiles, on a cold cache).")
def run(config, output, overrides, overwrite, resume, quiet):
    """Run the integration described by CONFIG into an HDF5 file.

    The run proceeds in chunks, each appended to OUT.h5 and flushed, with a progress bar
    on a terminal (a line every few seconds otherwise). Ctrl-C, SIGTERM or SIGHUP stops at the
    next chunk boundary (exit 130); --resume continues exactly where it stopped, even
    after kill -9, and ends bit for bit where an uninterrupted run ends. --resume reads
    CONFIG again, with the --set values of the runs before (stored in OUT.h5) and then the
    new ones, and takes its differences from the config stored in OUT.h5 as changes (an
    edit of CONFIG counts as the --set of that key): solver.* only, e.g. to continue a failed run with more step
    halvings, and integration.t_end (with output.times, keeping the times written), to
    continue a run, complete or not, to a later end; others are refused. A relative output
    path is taken from the current directory.

    \b
    Examples:
      elimfast run configs/kepler.yaml -o out/kepler.h5
      elimfast run configs/kepler.yaml -o out/k.h5 --set method.s=4 --set integration.t_end=100
      elimfast run configs/kepler.yaml -o out/kepler.h5 --resume
      elimfast run configs/kepler.yaml -o out/kepler.h5 --resume --set solver.max_halvings=8
      elimfast run configs/kepler.yaml -o out/kepler.h5 --resume --set integration.t_end=2000
    """
    if overwrite and resume:
        raise click.UsageError("--overwrite and --resume contradict each other; give one of them")
    target = output if output is not None else "the output file"
    _INTERRUPTED.append(f"interrupted while starting, before any step: {target} is as it was; run the same "
                        "command again" + (" to resume it" if resume else ""))
    with start_up():
        from elimfast.io.hdf5 import check_output_path
        from elimfast.io.safety import output_path

        if output is not None:   # before loading the config: compiling a problem can take a while
            output = str(output_path(output))
            _refuse_writing_over(output, config, "config file")
            check_output_path(output, overwrite=overwrite, resume=resume)
        announce_compilation()
        from elimfast.integrate import Integration

        from_config, origins, set_overrides = [], {}, list(overrides)
        if resume and output is not None and Path(output).is_file():
            _refuse_resuming_a_sweep(output)
            spec, from_config, origins, set_overrides = _stored_spec(output, overrides, config)
        else:
            spec = _load(config, overrides)
        path = output if output is not None else spec.output_path
        if path is None:
            raise click.UsageError(f"no output file: give -o OUT.h5 or set output.path in {config}")
        path = Path(path).expanduser()
        _refuse_writing_over(path, config, "config file")   # output.path may name it too
        if spec.problem.source_file:   # (a user trial: -o PROBLEM.py --overwrite replaced the problem file)
            _refuse_writing_over(path, spec.problem.source_file, "problem file")
        check_output_path(path, overwrite=overwrite, resume=resume)
        if resume and output is None and path.is_file():
            _refuse_resuming_a_sweep(path)
            spec, from_config, origins, set_overrides = _stored_spec(path, overrides, config)
        if resume and not path.exists():
            # Resume-or-start serves job scripts that rerun one command; said first, and under --quiet
            # too, so that a mistyped path does not restart a long run unnoticed.
            click.echo(f"note: no file {path} to resume: starting a new run", err=True)
        integration = Integration.from_spec(spec)
        from elimfast import streaming
    label = f"{spec.method.name} {spec.problem.name}"
    resume_command = _resume_command(config, path, spec)
    outcome = streaming.run_to_file(
        integration, path, config_text=_resolved_yaml(spec, path), t_end=spec.t_end, overwrite=overwrite,
        resume=resume, progress=streaming.progress_for(quiet), label=label,
        resume_command=resume_command, origins=origins, set_overrides=set_overrides,
        notice=lambda line: click.echo(f"note: {line}", err=True))
    _INTERRUPTED.pop()   # the run has handled its own signals; what follows is the report
    if from_config:
        outcome.note = "; ".join(filter(None, [outcome.note, f"with {config}'s changes: {', '.join(from_config)}"]))
    return _report_run(outcome, config, path, quiet, resume_command, problem=spec.problem)


def _refuse_resuming_a_sweep(path) -> None:
    """run --resume on a sweep's file: say how the sweep is continued (the reader's message told
    how to name one run for inspect, which run cannot write to)."""
    from elimfast.io.sweepfile import sweep_file_source
    source = sweep_file_source(path)
    if source is not None:
        import shlex
        fail(f"{path}: a sweep's file, which elimfast run does not continue: continue the sweep with "
             f"{shlex.join(['elimfast', 'sweep', source, '-o', str(path), '--resume'])}", EXIT_USAGE)


def _refuse_writing_over(output, source, what: str) -> None:
    """A usage error when the output file is the input file itself (``run CONFIG -o CONFIG
    --overwrite`` replaced the YAML by HDF5, and the next run could not read its config)."""
    if output is not None and Path(source).exists() and Path(output).expanduser().resolve() == Path(source).resolve():
        raise click.UsageError(f"the output file {output} is the {what} itself, which writing would replace; give "
                               "another output file, e.g. -o out/run.h5")


def _earlier_end(stored: dict, overrides) -> tuple[float, float] | None:
    """(the t_end a --set asks for, the stored run's) when the first is the earlier, else None."""
    from elimfast.problems.expressions import evaluate_number
    ends = [item.split("=", 1)[1] for item in overrides if _set_key(item) == "integration.t_end"]
    old = (stored.get("integration") or {}).get("t_end") if isinstance(stored, dict) else None
    try:
        new, old = float(evaluate_number(ends[-1])), float(evaluate_number(old))
    except Exception:   # noqa: BLE001 -- no t_end given, or not a number: the resume's own rule decides
        return None
    return (new, old) if new < old else None


def _stored_spec(path, overrides, config):
    """The spec with which --resume continues the run stored in ``path``: its stored config with
    the differences of CONFIG and --set from it on top, each as the --set of that key, so that
    the resume's one rule decides on all of them (solver.* and a later end are taken; other
    changes refused, by streaming.resume_refusal). CONFIG is read as a new run reads it (its
    errors are a new run's), with the --set values the file stores from the runs before applied
    first, as they were then (they need not be given again); the resolved configs are compared,
    so comments, formatting and defaults written out are no change. Returns (spec, the changes
    that come from CONFIG, not --set, as KEY=VALUE, {changed key: where its change comes from}
    for the refusal to say (resume_refusal's origins), the --set values to store: the stored
    ones merged with the given).

    A refusal names a key the user changed: a --set key first, then one CONFIG writes out, then
    one that follows from them (a user trial's --set integration.rtol was refused as
    'integration.atol (in CONFIG)': atol defaults to rtol, and comes first in key order)."""
    from elimfast.config import ConfigError, _clip, load_run_from_dict, parse_yaml, python_file_named, read_text_file
    from elimfast.io.hdf5 import RunFile
    from elimfast.io.layout import stored_set_overrides
    from elimfast.streaming import (ABSENT, EXTENSION_KEYS, LOAD_ONLY_KEYS, SOLVER_SECTIONS, STEP_SOLVER_KEYS,
                                    config_differences, keys_overlap, resume_refusal)

    with RunFile(path) as run_file:
        text = str(run_file.attrs.get("config", ""))
        stored_sets = stored_set_overrides(run_file.attrs) or []   # none in files written before they were
    set_overrides = _merge_sets(stored_sets, overrides)
    source = f"{path} (its stored config)"
    data = parse_yaml(text, source)
    written = parse_yaml(read_text_file(Path(config), str(config), what="config file"), str(config))
    # Only CONFIG and the --set given here may name the Python file to run: the file's stored --set
    # values and stored config are the file's, and a run file someone sent must not choose code (a
    # user trial: a stored 'problem=evil.py' ran evil.py under the --allow-python given for CONFIG's file).
    config_dir = Path(config).resolve().parent
    users_file = python_file_named(written, overrides, config_dir)
    with_stored = python_file_named(written, set_overrides, config_dir)
    if with_stored is not None and with_stored != users_file:
        item = next((item for item in reversed(stored_sets) if _set_key(item).split(".")[0] == "problem"), "")
        raise ConfigError(f"{path}: the --set {_clip(item)} stored by its earlier run names the Python file "
                          f"{with_stored}, which {config} does not; a run file cannot choose code to run: if you trust "
                          f"that file, give the --set again yourself (with --allow-python)", key="problem.python")
    try:
        loaded = _load(config, set_overrides)
    except ConfigError as err:
        earlier = _earlier_end(data, set_overrides)
        if earlier is not None and str(err.key or "").startswith("output.times"):
            # The stored output times past the earlier end were refused as a new run's ("must lie within
            # the run"), before the resume's own rule could say why (a user trial)
            from elimfast.streaming import earlier_end_refusal
            raise earlier_end_refusal(path, *earlier) from None
        stored_only = [item for item in stored_sets if item not in overrides and f"--set {item}" in str(err)]
        if stored_only:
            # A --set the file stored, applied to another CONFIG than its run's, was blamed as the user's
            # (a user trial resumed a file written from another Kepler config: 'not a whole number of steps
            # ... (value from --set integration.t_end=16000*pi)', a --set never typed there)
            raise ConfigError(f"{path}: the --set {_clip(stored_only[-1])} that its earlier run stored (and "
                              f"--resume applies again) does not fit {config}: {err}; was the run made from "
                              f"another config? resume it with that one (the file stores it: elimfast inspect "
                              f"{path})", key=err.key) from None
        raise
    given = parse_yaml(_resolved_yaml(loaded), str(config))
    set_keys = _given_keys(overrides)
    changes, from_config, rank, where = [], [], {}, {}
    for key, value in config_differences(data, given):
        if key == "output.path":
            continue
        by_set = any(keys_overlap(key, k) for k in set_keys)
        if by_set:
            items = [item for item in overrides if keys_overlap(key, _set_key(item))]
            rank[key], where[key] = 0, f"value from --set {_clip(items[-1])}" if items else None
        else:
            rank[key], where[key] = (1 if _writes_out(written, key) else 2), f"in {config}"
        if value is ABSENT:   # a key CONFIG leaves out, as --set KEY=null leaves it out
            if key in STEP_SOLVER_KEYS:
                # left out for its default (SolverSettings.as_dict writes project_energy only when on):
                # the default, which the rule on them then compares (a user trial: switched off at
                # --resume, project_energy was silently kept on)
                value = STEP_SOLVER_KEYS[key]
            elif key.split(".")[0] in SOLVER_SECTIONS or key in LOAD_ONLY_KEYS:
                continue
            else:
                value = None
        if key == "integration.n_steps" and "integration.t_end" in {_set_key(item) for item in changes}:
            continue   # follows from t_end
        item = f"{key}={_yaml_value(value)}"
        changes.append(item)
        if not by_set:
            from_config.append(item)
    if any(r == 0 for r in rank.values()):   # what follows from a --set is not CONFIG's doing
        where.update({key: None for key, r in rank.items() if r == 2})
        # ... nor is it said as CONFIG's change (a user trial: --set solver.method=fixed_point was
        # reported "with kepler.yaml's changes: solver.max_iter=100", a default that follows from it)
        from_config = [item for item in from_config if rank.get(_set_key(item)) != 2]
    origins = {key: where[key] for key in sorted(rank, key=rank.get)}
    stored_file = python_file_named(data, (), Path(path).resolve().parent)
    if stored_file is not None and stored_file != users_file:
        # the stored config's own Python file is loaded below only where CONFIG names it too
        raise resume_refusal(path, "problem.python", configs=(data, given), origins=origins)
    # The stored config resolves both t_end and n_steps: a run continued to a later end
    # gets the other from the one given.
    keys = {_set_key(item) for item in changes}
    stored_integration = data.get("integration") if isinstance(data, dict) else None
    if isinstance(stored_integration, dict):
        if "integration.t_end" in keys and "integration.n_steps" not in keys:
            stored_integration.pop("n_steps", None)
        elif "integration.n_steps" in keys and "integration.t_end" not in keys:
            stored_integration.pop("t_end", None)
    try:
        return load_run_from_dict(data, source=source, overrides=changes), from_config, origins, set_overrides
    except ConfigError:
        # CONFIG with --set loaded as a whole, so a change that does not load on the stored config
        # contradicts what it keeps (integration.h the stored n_steps, say): the resume's rule names
        # the first change that fails alone, one that may not change before one that may.
        kept = [item for item in changes if _set_key(item).split(".")[0] in SOLVER_SECTIONS]
        if len(kept) == len(changes):
            raise
        load_run_from_dict(data, source=source, overrides=kept)
        others = sorted((item for item in changes if item not in kept),
                        key=lambda item: (any(_set_key(item).startswith(k) for k in EXTENSION_KEYS),
                                          rank.get(_set_key(item), 2)))

        def fails(item) -> bool:
            try:
                load_run_from_dict(data, source=source, overrides=[*kept, item])
            except ConfigError:
                return True
            return False
        failing = next((item for item in others if fails(item)), others[0])
        raise resume_refusal(path, _set_key(failing), configs=(data, given), origins=origins) from None


def _writes_out(data, key: str) -> bool:
    """Whether a parsed config (as its file has it) gives the dotted ``key``: the key itself, a
    key under it, or a short form above it (method: EHBVM(12,3) gives method.k)."""
    node = data
    for part in key.split("."):
        if not isinstance(node, dict):
            return node is not None
        if part not in node:
            return False
        node = node[part]
    return True


def _yaml_value(value) -> str:
    """A value as the text of a --set that reads back as the same value."""
    import yaml
    return yaml.safe_dump(value, default_flow_style=True, width=float("inf")).strip().removesuffix("\n...")


def _set_key(item: str) -> str:
    return str(item).partition("=")[0].strip()


def _resume_command(config, path, spec) -> str:
    """The command that continues a run: its --set values are stored in the file
    (io.layout.SET_OVERRIDES) and applied again, so they are not part of it. With --allow-python
    when the run of ``spec`` runs a python: problem file by the user's leave (this command's)."""
    import shlex

    from elimfast.config import python_allowed
    problem = spec.resolved.get("problem")
    allow = ["--allow-python"] if isinstance(problem, dict) and "python" in problem and python_allowed() else []
    return shlex.join(["elimfast", "run", str(config), "-o", str(path), "--resume", *allow])


def _merge_sets(stored, given) -> list[str]:
    """The --set values a run goes on with: the stored ones, less those a given one replaces (the
    same key or a key under it; t_end and n_steps decide each other), then the given. A stored
    value above a given key stays, and the given one changes a part of it: a stored
    ``output.times={start: 0, stop: 20, step: 0.5}`` with a given ``output.times.stop=40`` (what
    the refusal of an earlier output end advises) lost start and step."""
    keys = _given_keys(given)
    return [item for item in stored
            if not any(_set_key(item) == k or _set_key(item).startswith(k + ".") for k in keys)] + list(given)


def _given_keys(overrides) -> set[str]:
    """The keys of --set values; t_end and n_steps decide each other, so either one gives both."""
    keys = {_set_key(item) for item in overrides}
    if keys & {"integration.t_end", "integration.n_steps"}:
        keys |= {"integration.t_end", "integration.n_steps"}
    return keys


def _report_run(outcome, config, path, quiet, resume_command: str, problem=None) -> int:
    from elimfast.io.hdf5 import STATUS_COMPLETE, STATUS_INTERRUPTED, STOPPED_PREFIX
    from elimfast.streaming import interrupted_line

    note = f" ({outcome.note})" if outcome.note else ""
    if outcome.status == STATUS_COMPLETE:
        if not quiet:
            from .report import _rate
            # the rate of the figures printed beside it (and by inspect): the run's steps over its wall
            # time; this session's steps over this session's elapsed time printed another number
            rate_text = (f", {_rate(outcome.steps_done, outcome.wall_time_s)}"
                         if outcome.steps_done and outcome.wall_time_s > 0 else "")
            click.echo(f"{path}: complete, {outcome.steps_done:,} steps, wall time {outcome.wall_time_s:.3g} s"
                       f"{rate_text}{note}", err=True)
            from elimfast.io.hdf5 import RunFile

            from .report import run_notes
            with RunFile(path) as run_file:
                for line in run_notes(run_file, problem):
                    click.echo(f"note: {line}", err=True)
        return EXIT_OK
    if outcome.status == STATUS_INTERRUPTED:
        click.echo(interrupted_line(outcome.signal_name, outcome.steps_done, outcome.n_steps, outcome.t, path,
                                    resume_command), err=True)
        return EXIT_INTERRUPTED
    if outcome.status.startswith(STOPPED_PREFIX) and outcome.message:
        click.echo(f"error: {one_line(outcome.message)}", err=True)
        return EXIT_FAILED
    click.echo(f"error: run {outcome.status} (the {outcome.steps_done} steps before it are in {path})", err=True)
    return EXIT_FAILED


@cli.command(context_settings=CONTEXT)
@click.argument("config", metavar="CONFIG")
@_allow_python_option
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE", help=SET_HELP)
def check(config, overrides):
    """Validate CONFIG, check its derivatives and invariants, print the resolved config.

    The derivative check compares grad_H, the invariants' gradients and hess_H with
    central differences of H, the invariants and grad_H; the invariant check evaluates
    |grad L^T J grad H| / (|grad L| |grad H|). Both look at the initial state and at seeded
    random points near it (also when the config says problem.check: false). The output is
    YAML: comments with the checks, then the resolved config that 'run' would use and
    store in the HDF5 file.

    \b
    Examples:
      elimfast check configs/kepler.yaml
      elimfast check configs/kepler.yaml --set method.s=4
    """
    from elimfast.problems.check import DEFAULT_TOLERANCE, check_derivatives, check_invariants, require_problem
    from elimfast.problems.expressions import ProblemDefinitionError

    from .report import adaptive_text, unused_h_note

    spec = _load(config, overrides)
    problem, method = spec.problem, spec.method
    if spec.step_control is not None:
        settings = spec.resolved["integration"]   # the step control's settings, as a run file stores them
        first = f", first step h = {spec.h!r}" if spec.h is not None else ""
        if spec.step_control.controller == "time_scale":   # every step is the controller's: h is not used
            h_first = spec.step_control.first_step(problem, method, problem.y0, spec.t_end - spec.t0)
            first = f", first step h = {h_first!r}" + (f"; {unused_h_note(spec.h)}" if spec.h is not None else "")
        steps = f"{adaptive_text(settings)} from t = {spec.t0!r} to {spec.t_end!r}{first}"
    else:
        steps = f"{spec.n_steps} steps of h = {spec.h!r} from t = {spec.t0!r} to {spec.t_end!r}"
    lines = [f"# {config}: the config is valid (the checks of the problem follow)",
             f"# problem {problem.name}, {method.name}"
             + (f" imposing {', '.join(spec.conserve)}" if spec.conserve else "") + f", {steps}"]
    try:
        reports = check_derivatives(problem)
        residuals = check_invariants(problem)
    except ProblemDefinitionError as err:   # at y0 (problem.check: false let the config load)
        raise _check_error(config, spec, err) from None
    lines.append("# derivative check (error / what central differences allow; fails above 1):")
    width = max(len(report.name) for report in reports)
    lines += [f"#   {report.name:<{width}}  {report.ratio:.1e}  {'ok' if report.ok else 'DOES NOT MATCH'}"
              for report in reports]
    lines.append(f"# hess_H: {problem.hessian_description}")
    lines.append(f"# H: {_quadrature_of_H(problem, method)}")
    if residuals:
        lines.append(f"# invariant check (relative residual, tolerance {DEFAULT_TOLERANCE:.0e}):")
        width = max(len(name) for name in residuals)
        for name, value in residuals.items():
            verdict = "ok" if value <= DEFAULT_TOLERANCE else "NOT CONSERVED"
            lines.append(f"#   {name:<{width}}  {value:.3e}  {verdict}")
    else:
        lines.append(f"# invariant check: problem {problem.name} declares no invariants besides H")
    if spec.output_path:
        from elimfast.io.hdf5 import OutputError, check_output_path
        try:
            check_output_path(spec.output_path)
            lines.append(f"# output {spec.output_path}: writable")
        except OutputError as err:
            lines.append(f"# output: {one_line(err)}")
    click.echo("\n".join(lines))
    click.echo(_resolved_yaml(spec), nl=False)
    try:
        require_problem(problem)   # exit 2 with the mismatch or the residual when a check fails
    except ProblemDefinitionError as err:
        raise _check_error(config, spec, err) from None
    return EXIT_OK


def _check_error(config, spec, err):
    """A check's failure as the config error a run reports (FILE: problem.KEY: ...), also when the
    config says problem.check: false, which only 'run' obeys: its advice to set it is then left out."""
    from elimfast.config import ConfigError

    problem = spec.resolved.get("problem", {})
    mode = "python" if "python" in problem else "builtin" if "builtin" in problem else "expressions"
    key = err.key or ""
    if not ((mode == "expressions" and key) or key.split(".")[0] in ("parameters", "initial")):
        key = {"python": "python", "builtin": "builtin"}.get(mode, "hamiltonian")
    text = str(err)
    if problem.get("check") is False:
        text = text.replace(", or set problem.check: false to skip this check",
                            " (problem.check: false skips this check in run, not in check)")
    return ConfigError(f"{config}: problem.{key}: {text}", key=f"problem.{key}")


# --- inspect, plot ------------------------------------------------------------------------
@cli.command(context_settings=CONTEXT)
@click.argument("file", metavar="OUT.h5")
def inspect(file):
    """Summarise a run file: problem, method, progress, timing, invariant errors, iterations.

    Reads files of finished, interrupted, failed, killed and still running runs (the last
    two through HDF5's SWMR mode); memory stays bounded for any length. Every stored row
    is read back, so HDF5 checks every checksum: a damaged file is reported (exit 2)
    with the place of the damage. One run of a sweep file: SWEEP.h5:/runs/<label>. The
    file of an ensemble sweep: how many trajectories it stores (complete, or how to
    complete it with --resume), failures and invariant errors over those stored. A
    sweep file: its runs, one row each (status, steps, iterations, invariant error).

    \b
    Examples:
      elimfast inspect out/kepler.h5
      elimfast inspect out/table1.h5
      elimfast inspect out/table1.h5:/runs/GAUSS3/pi/30
      elimfast inspect out/ensemble.h5
    """
    from elimfast.io.ensemblefile import EnsembleFile, is_ensemble_file
    from elimfast.io.hdf5 import RunFile

    from elimfast.io.sweepfile import grid_sweep_runs

    from .report import ensemble_summary, summary, sweep_summary

    if is_ensemble_file(file):
        with EnsembleFile(file) as ensemble_file:
            click.echo(ensemble_summary(ensemble_file))
        return EXIT_OK
    sweep = grid_sweep_runs(file)
    if sweep is not None:
        click.echo(sweep_summary(file, *sweep))
        return EXIT_OK
    with RunFile(file) as run_file:
        integrity = run_file.verify()
        click.echo(summary(run_file, integrity))
    return EXIT_OK


@cli.command(context_settings=CONTEXT)
@click.argument("file", metavar="OUT.h5")
@click.option("--kind", type=click.Choice(["orbit", "invariants", "alpha", "iterations", "section"]),
              default="invariants",
              show_default=True, help="orbit: the trajectory; invariants: |I(t) - I(t0)| on a log scale; "
                                      "alpha: the multipliers per step (lambda for LIM); iterations: per step; "
                                      "section: the states at an event (a surface of section; --event), q_j against p_j "
                                      "for the last degree of freedom the event leaves free.")
@click.option("--event", metavar="NAME", help="The event of --kind section (default: the run's first).")
@click.option("-o", "--output", metavar="FIG.png", callback=_file_name,
              help="Image file (default: OUT_<kind>.png beside OUT.h5); the suffix picks the format (png, pdf, svg).")
@click.option("--overwrite", is_flag=True, help="Replace FIG if it exists.")
def plot(file, kind, output, overwrite, event):
    """Plot a run file (or one run of a sweep file, SWEEP.h5:/runs/<label>) with matplotlib (headless).

    \b
    Examples:
      elimfast plot out/kepler.h5
      elimfast plot out/table1.h5:/runs/GAUSS3/pi/30 --kind invariants -o gauss3.png
      elimfast plot out/kepler.h5 --kind orbit -o orbit.png
      elimfast plot out/kepler.h5 --kind alpha -o alpha.pdf

    Missing directories of FIG are created, as `elimfast run` creates those of OUT.h5.
    """
    from elimfast.io.hdf5 import OutputError, RunFile, check_creatable
    from elimfast.io.layout import split_run_path

    from .plots import check_image_path, plot_run

    run_path, run = split_run_path(file)
    default_name = f"{run_path.stem}_{run.replace('/', '_')}_{kind}.png" if run else f"{run_path.stem}_{kind}.png"
    path = Path(output).expanduser() if output else run_path.with_name(default_name)
    check_image_path(path)   # before reading the run: a usage error, exit 2
    if path.exists() and not overwrite:
        raise OutputError(f"{path}: already exists; pass --overwrite to replace it or -o another name")
    if not path.exists():
        check_creatable(path)   # missing directories are made as `run` makes them, once the figure is drawn
    with RunFile(file) as run_file:
        plot_run(run_file, kind, path, event)
    click.echo(str(path))
    return EXIT_OK


@cli.command(context_settings=CONTEXT)
@click.argument("file", metavar="FILE.h5")
def repair(file):
    """Make the file of a killed run readable by every HDF5 program (h5py, xarray, h5dump).

    A run killed with kill -9 (or a crash) leaves its file consistent but marked "open for
    writing", so programs other than elimfast refuse it ("file is already open for write
    ... h5clear"). repair clears that mark, as h5clear -s does, once no process writes the
    file any more, and cuts the file back to the last saved chunk. The run can still be
    continued with --resume afterwards.

    \b
    Example:
      elimfast repair out/kepler.h5
    """
    from elimfast.io.repair import repair as repair_file

    click.echo(repair_file(file))
    return EXIT_OK


# --- problems, methods, tableau ---------------------------------------------------------------
def _abbreviate(names, limit: int = 10) -> str:
    names = list(names)
    if len(names) <= limit:
        return ", ".join(names) or "none"
    return ", ".join(names[:4]) + f", ... ({len(names) - 6} more) ..., " + ", ".join(names[-2:])


@cli.command(context_settings=CONTEXT)
def problems():
    """List the built-in problems with their parameters, coordinates and invariants.

    \b
    Example:
      elimfast problems
      then in a config:  problem: {builtin: kepler, parameters: {eccentricity: 0.6}}
    """
    from elimfast.problems.catalogue import LISTING   # the listing as data: no problem is compiled

    blocks = []
    for name, entry in LISTING.items():
        params = ", ".join(f"{k} = {v!r}" for k, v in entry.parameters) or "none"
        invariants = ", ".join(["H"] + ([_abbreviate(entry.invariants)] if entry.invariants else []))
        blocks.append(f"{name}: {entry.description}\n"
                      f"    parameters:  {params}\n"
                      f"    coordinates: {_abbreviate(entry.coordinates)}\n"
                      f"    invariants:  {invariants}")
    click.echo("\n".join(blocks))
    return EXIT_OK


@cli.command(context_settings=CONTEXT)
def methods():
    """List the method families, their parameters and what they conserve.

    \b
    Example:
      elimfast methods
      then in a config:  method: {name: ehbvm, k: 12, s: 3}
    """
    from elimfast.methods import FAMILIES

    rows = [(family.signature(), family.description) for family in FAMILIES.values()]
    width = max(len(r[0]) for r in rows)
    click.echo("\n".join(f"{sig:<{width}}  {note}" for sig, note in rows))
    click.echo("\nk, r: quadrature nodes (k >= s, r >= s, at most 64); s: the order is 2s (s at most 63). "
               "Tableau: elimfast tableau NAME --k K --s S [--r R] [--eta ...]. "
               "The methods and their math: docs/methods.md")
    return EXIT_OK


def _parse_floats(values) -> list[float] | None:
    if not values:
        return None
    out = []
    for value in values:
        for item in str(value).replace(",", " ").split():
            try:
                number = float(item)
            except ValueError:
                raise click.BadParameter(f"{item!r} is not a number", param_hint="--eta") from None
            if not math.isfinite(number):   # a user trial: nan printed a tableau of NaN, exit 0
                raise click.BadParameter(f"{item!r} is not a finite number", param_hint="--eta")
            out.append(number)
    return out


def _quadrature_of_H(problem, method) -> str:
    """What ``check`` says of how the method keeps H (docs/solver.md#quadrature-of-h-when-k-is-too-small):
    exactly where H is a polynomial of degree <= 2k/s (Problem.hamiltonian_degree), else up to
    the quadrature error of the k nodes."""
    from elimfast.methods import integrates_exactly
    label, k = method.kind.nodes_keeping_H(method.r, method.k)   # LIM(r,k,s): its r nodes
    s, degree = method.s, problem.hamiltonian_degree
    if integrates_exactly(degree, k, s):
        return (f"a polynomial of degree {degree}, which the {label} = {k} nodes of {method.name} integrate exactly "
                f"(degree <= 2{label}/s = {2 * k / s:.3g}): kept to round-off")
    what = (f"a polynomial of degree {degree} > 2{label}/s = {2 * k / s:.3g}" if degree is not None
            else {"analytic": "not a polynomial", "symbolic": "not a polynomial as written"}.get(
                problem.hessian_source, "not known to be a polynomial (a python: problem)"))
    from elimfast.problems.expressions import kink_note
    kinks = f"; {kink_note(problem.hamiltonian_kinks)}" if problem.hamiltonian_kinks else ""
    return (f"{what}: {method.name} keeps it up to the quadrature error of its {label} = {k} nodes, O(h^{2 * k + 1}) "
            f"per step (inspect and the end-of-run line flag a loss above 1e-12){kinks}")


@cli.command(context_settings=CONTEXT)
@click.argument("name", metavar="NAME", nargs=-1, required=True)   # the rest: values after one --eta, refused below
@click.option("--k", "k", type=int, help="Quadrature nodes for H (hbvm, elim, ehbvm, lim, ghbvm).")
@click.option("--s", "s", type=int, help="Number of Legendre coefficients; order 2s (every method).")
@click.option("--r", "r", type=int, help="Quadrature nodes for the invariants (elim, lim).")
@click.option("--eta", multiple=True, metavar="ETA",
              help="ELIM scaling factors eta_1..eta_(s-1) (or eta_0..eta_(s-1), eta_0 = 1): "
                   "repeat the option or separate by commas. Default: all 1 (the HBVM tableau).")
def tableau(name, k, s, r, eta):
    """Print the Butcher tableau (A, b, c) of a method, as elimfast computes it.

    Every number is printed with Python's repr, so reading it back gives the same
    double: the one the kernels use (a product of the method's matrices, which can be a
    few units in the last place from the exact value, e.g. GAUSS(2)'s 1/4). Rows: c_i |
    a_i1 ... a_ik, then a rule and the weights b_j. LIM and GHBVM have no fixed
    Runge-Kutta form.

    \b
    Examples:
      elimfast tableau gauss --s 2
      elimfast tableau hbvm --k 4 --s 2
      elimfast tableau 'HBVM(4,2)'
      elimfast tableau elim --r 3 --k 3 --s 2 --eta 0.999
    """
    from elimfast import methods
    from elimfast.errors import ParameterError

    name, *extra = name
    if extra:
        # `--eta 1 1 0.99` got click's "unexpected extra arguments (1 0.99)"
        hint = (f"--eta takes one value: repeat it (--eta {' --eta '.join(eta + tuple(extra))}) or separate the values "
                f"by commas (--eta {','.join(eta + tuple(extra))})" if eta else "give one method name")
        raise click.UsageError(f"unexpected values {' '.join(extra)} after {name}; {hint}")
    given = {key: value for key, value in (("r", r), ("k", k), ("s", s)) if value is not None}
    try:
        written = methods.from_notation(name)   # 'HBVM(4,2)' as the paper writes it
        if written is not None and given:
            raise ParameterError(sorted(given)[0], f"does not apply: {name} gives the parameters already; remove it")
        method = methods.get(**written) if written is not None else methods.get(name, **given)
    except ParameterError as err:   # the library's rule and fix, with the option's name
        option = "NAME" if err.parameter == "name" else f"--{err.parameter}"
        raise click.UsageError(f"{option} {err.detail}") from None
    try:
        eta_values = _parse_floats(eta)
        if eta_values is not None and not method.kind.scales_tableau:
            scaled = ", ".join(n for n, f in methods.FAMILIES.items() if f.scales_tableau)
            raise ValueError(f"--eta applies to {scaled} only; {method.name} has eta = 1")
        A, b, c = method.butcher(eta_values)
    except (TypeError, ValueError) as err:
        raise click.UsageError(one_line(err)) from None
    click.echo(_format_tableau(method, A, b, c, eta_values))
    return EXIT_OK


def _format_tableau(method, A, b, c, eta) -> str:
    cells = [[repr(float(x)) for x in row] for row in A]
    c_text = [repr(float(x)) for x in c]
    b_text = [repr(float(x)) for x in b]
    width = max(len(t) for t in [*c_text, *b_text, *(x for row in cells for x in row)])
    c_width = max(len(t) for t in c_text)
    eta_text = "1 (the HBVM tableau)" if eta is None else ", ".join(repr(float(e)) for e in eta)
    # The method's order is 2s with eta = 1 - h^(2(s-1-j)) alpha_j of each step (docs/methods.md#elim);
    # a tableau of fixed eta other than 1 has a lower one (a user trial: eta 1, 1, 0.99 matched exp(z)
    # through z^4 only, and was labelled order 6)
    fixed = eta is not None and any(float(e) != 1.0 for e in eta)
    order = (f"order {method.order} only as the method, whose eta change with each step (these fixed eta give "
             "a lower one)" if fixed else f"order {method.order}")
    lines = [f"# {method.name}: Butcher tableau, {len(c)} stage{'s' if len(c) != 1 else ''}, {order}; eta = {eta_text}",
             "# c_i | a_i1 ... a_ik, then | b_1 ... b_k; each number is repr(float): it reads back exactly"]
    for ci, row in zip(c_text, cells):
        lines.append(f"{ci:>{c_width}} | " + " ".join(f"{x:>{width}}" for x in row))
    lines.append("-" * c_width + "-+-" + "-" * ((width + 1) * len(b_text) - 1))
    lines.append(" " * c_width + " | " + " ".join(f"{x:>{width}}" for x in b_text))
    return "\n".join(lines)


# --- cache ---------------------------------------------------------------------------------
# --- sweep, paper -------------------------------------------------------------------------
@cli.command(context_settings=CONTEXT)
@click.argument("sweep_file", metavar="SWEEP.yaml")
@functools.partial(_allow_python_option, names="the sweep's configs name")
@click.option("-o", "--output", metavar="OUT.h5", callback=_file_name,
              help="Store every run under /runs/<label>/ of this file.")
@click.option("--workers", type=click.IntRange(min=1), default=None, metavar="N",
              help="Worker processes (default: all cores).")
@click.option("--format", "table_format", type=click.Choice(["markdown", "csv"]), default="markdown",
              show_default=True, help="Format of the printed table.")
@click.option("--overwrite", is_flag=True, help="Replace OUT.h5 if it exists.")
@click.option("--resume", is_flag=True, help="OUT.h5 holds part of this sweep: run only the runs (or an ensemble's "
                                              "trajectories) not complete in it. The sweep file may have been edited "
                                              "where the edit keeps the stored runs' configs outside solver.* (more "
                                              "halvings for a failed run, say, or added runs).")
@click.option("--scheduler", metavar="ADDRESS", default=None,
              help="Run on a Dask cluster: its scheduler (tcp://host:8786), or 'local' for a LocalCluster of "
                   "--workers processes (docs/dask.md; pip install 'elimfast[dask]').")
@click.option("-q", "--quiet", is_flag=True, help="No progress lines (the table is still printed, and the one line "
              "saying that Numba compiles, on a cold cache).")
def sweep(sweep_file, output, workers, table_format, overwrite, resume, scheduler, quiet):
    """Run a grid of configs in parallel and print the error, order, iteration and invariant table.

    SWEEP.yaml names a base config and the axes of the grid (see elimfast/sweep.py or the
    README): each point is one run, labelled by its coordinates. Errors are taken against
    the exact solution (error: {exact: initial}, a periodic orbit over whole periods) or a
    reference run named in the sweep file; orders between successive values of order_axis
    (a plain axis of numbers: h, or epsilon, rtol, ... for the order in those).
    A failed run does not stop the others: it is marked with its reason (its figures read
    'failed': they would cover only the steps before the failure) and the exit code is 1;
    a run whose config is refused (a grid value of h that is no whole number of steps)
    makes it 2, a usage error.

    An ensemble sweep (an ensemble: section, one config from many initial states) runs
    in the parallel Numba kernel on N threads instead, and stores /ensemble in OUT.h5 block
    by block as the blocks end; --resume runs only the trajectories not stored yet.

    \b
    Examples:
      elimfast sweep configs/paper/table1.yaml
      elimfast sweep configs/sweeps/henon_heiles_ensemble.yaml -o out/ensemble.h5
      elimfast sweep configs/paper/table1.yaml -o out/table1.h5 --workers 2 --format csv
      elimfast sweep configs/paper/table1.yaml -o out/table1.h5 --resume   # after a kill, or an edit: the rest
      elimfast sweep configs/paper/table1.yaml -o out/table1.h5 --scheduler tcp://node1:8786
    """
    with start_up():   # what every sweep loads (the config machinery, the kernels), with the GC paused
        from elimfast import sweep as sweeps
        from elimfast import config_schema, integrate  # noqa: F401 (a sweep's runs are validated by pydantic)
        from elimfast.streaming import StopOnSignals
    announce_compilation()   # a sweep after an upgrade compiles its kernels first (40 s for an ensemble)

    if output is not None:
        from elimfast.io.safety import OutputError, output_path
        try:
            output = output_path(output)
        except OutputError as err:
            fail(str(err), EXIT_USAGE)
        _refuse_writing_over(output, sweep_file, "sweep file")
    if resume and output is None:
        fail("--resume continues the sweep file given with -o OUT.h5; add it", EXIT_USAGE)
    if overwrite and output is None:
        fail("--overwrite replaces the file given with -o OUT.h5, and there is none: add -o OUT.h5, or leave "
             "out --overwrite", EXIT_USAGE)
    if resume and overwrite:
        fail("--resume and --overwrite exclude each other: --resume keeps the runs in OUT.h5, --overwrite "
             "replaces them", EXIT_USAGE)

    started_ensemble = []   # not empty once an ensemble sweep's trajectories start (on_start)

    def hard_stop(signal_name):
        """The line of an interrupted sweep (also after a kernel call that did not return)."""
        import shlex
        why = f" by {signal_name}" if signal_name else ""
        if output is None:
            return f"error: interrupted{why} (no -o OUT.h5: nothing was stored)"
        command = shlex.join(["elimfast", "sweep", str(sweep_file), "-o", str(output), "--resume"])
        kept = "the ensemble's stored blocks" if started_ensemble else "the finished runs"
        return f"error: interrupted{why}; {kept} are in {output}; run the rest with: {command}"

    def on_start(n_trajectories):
        started_ensemble.append(n_trajectories)
        if not quiet:
            if scheduler:
                where = f"the Dask cluster ({scheduler})"
            else:
                import numba   # loaded by now: the ensemble's kernel runs next
                threads = workers or numba.config.NUMBA_NUM_THREADS
                where = f"{threads} thread{'s' if threads != 1 else ''}"
            click.echo(f"ensemble: running {n_trajectories:,} trajectories on {where}", err=True)

    finished = {}   # label -> outcome: an interrupted sweep without -o prints these rows

    def on_done(outcome, done, total):
        finished[outcome.label] = outcome
        if not quiet:
            name = "reference run" if outcome.label == sweeps.REFERENCE_LABEL else outcome.label
            click.echo(f"[{done}/{total}] {name}: {outcome.status} ({outcome.wall_time:.2f} s)", err=True)

    def finished_table() -> bool:
        """Print the table of the runs finished before an interrupt (no -o: nothing else keeps them);
        True if there were any."""
        reference = finished.pop(sweeps.REFERENCE_LABEL, None)
        if output is not None or not finished:
            return False
        spec = sweeps.load_sweep(sweep_file)
        outcomes = [finished[run.label] for run in spec.runs if run.label in finished]
        header, rows = sweeps.table_rows(spec, outcomes, reference, table_format)
        click.echo(sweeps.format_table(header, rows, table_format), nl=False)
        return True

    # Ctrl-C and SIGTERM end the sweep (KeyboardInterrupt), also inside a kernel call that does not return.
    with StopOnSignals(raising=True, hard_stop=hard_stop) as stop:
        try:
            outcome = sweeps.run_to_file(sweep_file, output, workers=workers, overwrite=overwrite,
                                         on_start=on_start, on_done=on_done, resume=resume, scheduler=scheduler,
                                         on_message=None if quiet else (lambda line: click.echo(line, err=True)))
        except KeyboardInterrupt:
            import signal
            name = signal.Signals(stop.signal).name if stop.signal else None
            if finished_table():
                click.echo(f"error: interrupted{f' by {name}' if name else ''}: the {len(finished)} runs finished "
                           "are the rows above (no -o OUT.h5: nothing was stored; with it, --resume runs the rest)",
                           err=True)
            else:
                click.echo(hard_stop(name), err=True)
            raise _Exit(EXIT_INTERRUPTED) from None
    shared = outcome.config_error()
    if shared is not None:
        # every run failed to load: a 200-row table of the same failure, exit 1, hid a bad input
        fail(f"every run of the sweep failed to load its config, the first with: {shared}", EXIT_USAGE)
    if outcome.ensemble is not None:
        result = outcome.ensemble
        # the title on stderr for csv, whose stdout a CSV reader takes whole (a user trial: pandas read
        # the title as the header)
        click.echo(f"{result.method.name} on {result.problem.name}, {result.n_trajectories} trajectories "
                   f"of {result.n_steps} steps, h = {result.h:g}", err=table_format == "csv")
    header, rows = outcome.table(table_format)
    click.echo(sweeps.format_table(header, rows, table_format), nl=False)
    for line in outcome.failures():
        click.echo(f"error: {line}", err=True)
    if any(o.config_error or o.refused for o in outcome.outcomes):
        # a run whose config is refused (a grid value h = -0.05), or that would not fit in memory, is a
        # usage error, not a failed integration (a user trial's sweep exited 1); the other runs are in the table
        return EXIT_USAGE
    return EXIT_FAILED if outcome.failures() else EXIT_OK


def paper_configs() -> Path:
    """configs/paper of the current directory if it has one, else the repository's beside the
    package (an editable install), so that `elimfast paper` works from any folder."""
    here = Path("configs/paper")
    if (here / "table1.yaml").is_file():
        return here
    import elimfast
    beside = Path(elimfast.__file__).resolve().parents[1] / "configs" / "paper"
    return beside if (beside / "table1.yaml").is_file() else here


@cli.command(context_settings=CONTEXT)
@click.option("--configs", "config_dir", default=None, metavar="DIR",
              help="The folder holding table1.yaml and long_run.yaml (default: configs/paper here, else the "
                   "repository's beside the installed package).")
@click.option("--out", "out_dir", default="paper-out", show_default=True, metavar="DIR",
              help="Where to write the tables (markdown) and figures (PNG).")
@click.option("--workers", type=click.IntRange(min=1), default=None, metavar="N",
              help="Worker processes (default: all cores).")
@click.option("--overwrite", is_flag=True, help="Replace the tables and figures of an earlier run in DIR.")
@click.option("-q", "--quiet", is_flag=True, help="No progress lines.")
def paper(config_dir, out_dir, workers, overwrite, quiet):
    """Reproduce Brugnano & Sun (2014): Tables 1-3 and Figures 1-4, beside the paper's values.

    \b
    Example:
      elimfast paper --out paper-out
    """
    from elimfast import paper as reproduction

    def on_done(outcome, done, total):
        if not quiet:
            click.echo(f"[{done}/{total}] {outcome.label}: {outcome.status} ({outcome.wall_time:.2f} s)", err=True)

    if config_dir is None:
        config_dir = paper_configs()
    for name in ("table1.yaml", "long_run.yaml"):
        if not (Path(config_dir) / name).is_file():
            fail(f"{Path(config_dir) / name}: no such sweep file; give --configs the folder of the paper's sweeps "
                 "(configs/paper in the repository)", EXIT_USAGE)
    if Path(out_dir).exists() and not Path(out_dir).is_dir():
        # (a user trial's --out naming a file was told only "<it>: File exists", after the runs)
        fail(f"--out {out_dir}: is a file, not a folder; give a folder for the tables and figures (it is created "
             "if missing), e.g. --out paper-out", EXIT_USAGE)
    earlier = [name for name in reproduction.TABLES + reproduction.FIGURES if (Path(out_dir) / name).exists()]
    if earlier and not overwrite:
        fail(f"{out_dir} holds the tables of an earlier run ({', '.join(earlier[:2])}"
             f"{', ...' if len(earlier) > 2 else ''}); add --overwrite to replace them, or give another --out",
             EXIT_USAGE)
    try:
        result = reproduction.reproduce(config_dir, out_dir, workers=workers, on_done=on_done)
    except RuntimeError as err:
        fail(f"a paper run failed: {one_line(err)}", EXIT_FAILED)
    worst = max(abs(row[4]) for row in result["table1"] if row[0] not in reproduction.ROUND_OFF_ROWS)
    worst_alpha = max(abs(row[4]) for row in result["table3"] if row[0] not in reproduction.ROUND_OFF_ROWS)
    click.echo(f"wrote {out_dir}/table1.md, table2.md, table3.md, long_run.md and {len(result['figures'])} figures")
    click.echo(f"Table 1 at pi/30..pi/120: largest relative difference to the paper {worst:.1e}; "
               f"Table 3: {worst_alpha:.1e} (tolerance {reproduction.TOLERANCE:g})")
    return EXIT_OK if max(worst, worst_alpha) < reproduction.TOLERANCE else EXIT_FAILED


@cli.group(context_settings=CONTEXT)
def cache():
    """Inspect or clear the cache of generated problem code and compiled kernels.

    \b
    Examples:
      elimfast cache info
      elimfast cache clear
      elimfast cache clear --stale   (the kernels of other versions only)
    """


def _size(n_bytes: int) -> str:
    from elimfast.io.safety import _size as size   # the one size formatter of the messages
    return size(n_bytes)


@cache.command("info", context_settings=CONTEXT)
def cache_info():
    """Where the caches are and how much they hold.

    \b
    Example:
      elimfast cache info
    """
    from elimfast.cache import ENV_VAR, cache_info as info, kernel_cache_files, kernel_roots, stale_kernel_folders

    data = info()
    roots, files = kernel_cache_files()
    kernels = f", {data['kernels']} per-problem kernels" if data.get("kernels") else ""
    click.echo(f"problem cache:  {data['path']}  ({data['entries']} generated problems{kernels}, "
               f"{_size(data['bytes'])}; set {ENV_VAR} to move it)")
    # Each root with its own files (a user trial: one folder was named, which did not exist, while
    # the files counted beside it were in the package's own __pycache__).
    what = ["elimfast's own kernels", "the problems' compiled modules"] if len(roots) > 1 else ["every kernel"]
    for index, (root, holds) in enumerate(zip(roots, what)):
        mine = [f for f in files if root in f.parents]
        size = sum(f.stat().st_size for f in mine if f.exists())
        label = "kernel cache:" if index == 0 else ""
        click.echo(f"{label:<16}{root}  ({len(mine)} Numba files, {_size(size)}: {holds})")
    click.echo(f"{'':<16}(set NUMBA_CACHE_DIR to move {'both' if len(roots) > 1 else 'it'})")
    stale = [folder for root in kernel_roots() for folder in stale_kernel_folders(root)]
    if stale:
        stale_size = sum(f.stat().st_size for f in files if f.exists() and any(s in f.parents for s in stale))
        click.echo(f"stale kernels:  {len(stale)} key folders of other versions ({_size(stale_size)} of the above; "
                   "`elimfast cache clear --stale` removes them)")
    return EXIT_OK


@cache.command("warm", context_settings=CONTEXT)
@click.option("-q", "--quiet", is_flag=True, help="Print nothing (errors only).")
def cache_warm(quiet):
    """Compile every kernel once into the cache, so that the next runs start at once.

    `make` runs this after installing. With a warm cache it only loads the kernels (about a
    second); after a change of elimfast, Numba or a kernel it compiles them again (minutes).

    \b
    Example:
      elimfast cache warm
    """
    from elimfast import compile_notice
    compile_notice.announce(write=lambda line: None)   # the lines below say it, step by step
    from elimfast.warm import warm

    if not quiet:
        click.echo("compiling elimfast's kernels into the cache (a few minutes the first time) ...", err=True)

    def on_step(what, seconds):
        if not quiet:
            click.echo(f"  {what}: {seconds:.1f} s", err=True)

    total = warm(on_step)
    if not quiet:
        from elimfast.cache import kernel_cache_files
        roots, files = kernel_cache_files()
        click.echo(f"kernels ready in {total:.1f} s ({len(files)} Numba files in {' and '.join(map(str, roots))})",
                   err=True)
    return EXIT_OK


@cache.command("clear", context_settings=CONTEXT)
@click.option("--kernels", is_flag=True, help="Also delete Numba's compiled kernels (the next run recompiles what it needs, ~1-2 min; "
                   "`elimfast cache warm` all of them, 2-3 min).")
@click.option("--stale", is_flag=True,
              help="Only delete the compiled kernels of other elimfast, Numba or kernel versions (every key folder "
                   "but the current one); nothing this elimfast uses.")
def cache_clear(kernels, stale):
    """Delete the generated problem code (and with --kernels the compiled kernels).

    Each version of elimfast, Numba or the kernels compiles into its own key folder; a new
    one removes those unused for 30 days, and --stale removes all the others now.

    \b
    Examples:
      elimfast cache clear
      elimfast cache clear --kernels
      elimfast cache clear --stale
    """
    from elimfast.cache import cache_dir, clear_cache, clear_kernels, kernel_cache_files

    if stale:
        if kernels:
            raise click.UsageError("give --stale (the kernels of other versions) or --kernels (all kernels), not both")
        return _clear_stale()
    removed = clear_cache()
    click.echo(f"removed {removed} files from {cache_dir()}")
    if kernels:
        roots = kernel_cache_files()[0]
        click.echo(f"removed {clear_kernels()} Numba files from {' and '.join(map(str, roots))}")
    return EXIT_OK


def _clear_stale() -> int:
    from elimfast.cache import current_key, kernel_roots, prune_kernel_folders

    roots = kernel_roots()
    pruned = prune_kernel_folders()
    where = " and ".join(str(root) for root in roots)
    folders = "folder" if len(pruned.folders) == 1 else "folders"
    exact = f" ({pruned.bytes:,} bytes)" if pruned.bytes >= 1000 else ""
    click.echo(f"removed {len(pruned.folders)} stale kernel {folders} from {where}, freed {_size(pruned.bytes)}"
               f"{exact}; kept the current one ({current_key()})")
    if pruned.failed:
        folder, err = pruned.failed[0]
        others = f" (and {len(pruned.failed) - 1} more)" if len(pruned.failed) > 1 else ""
        click.echo(f"error: cannot remove {folder}{others}: {err.strerror or err}; check its permissions", err=True)
        return EXIT_USAGE
    return EXIT_OK


if __name__ == "__main__":
    cli()
