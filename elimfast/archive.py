"""Reading a run back: ``load(path)`` and ``load(path, run=label)`` return the Result that
``integrate`` returned (or would have returned) for the run stored there; ``load`` of an
ensemble sweep's file returns the EnsembleResult of its ensemble (``load_ensemble``).

The problem and the method are built again from the resolved config stored with the run
(a ``python:`` problem needs its file where the config says), the arrays are read from
the file (``elimfast.io.runfile.RunFile``). Like REBOUND's SimulationArchive, this reader
knows the file only through the RunFile that reads it, and the run only through its config.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import ElimfastError
from .kernels.codes import FAMILY_LIM


# Where load or load_ensemble refuses a python: problem file: the data needs no problem.
_WITHOUT_RUNNING_IT = "; or read the data without its problem: elimfast.open_datatree(path)"


def _rebuilt_spec(config_text: str, where: str, what: str, base_dir, allow_python):
    """The RunSpec of the config stored at ``where`` (a run file, a sweep's run, an ensemble's
    group), for load and load_ensemble; its error names ``where`` and the ``what`` it rebuilds."""
    from .config import PythonNotAllowed, load_run_from_dict, parse_yaml
    source = f"{where} (its stored config)"
    try:
        return load_run_from_dict(parse_yaml(config_text, source), source=source, base_dir=base_dir,
                                  allow_python=allow_python)
    except ElimfastError as err:
        hint = _WITHOUT_RUNNING_IT if isinstance(err, PythonNotAllowed) else ""
        raise type(err)(f"{where}: cannot rebuild the {what} from its stored config: {err}{hint}") from None


def load(path, run: str | None = None, *, allow_python: bool | None = None):
    """The Result stored in the run file ``path``, or in the run labelled ``run`` of a sweep
    file (``path`` may also be given as ``"sweep.h5:/runs/<label>"``).

    The problem is built again from the stored config: a python: problem file it names (if
    that path exists here) is code, run only with ``allow_python=True`` (default:
    config.python_allowed()), so that opening a file someone sent runs nothing beside it.

    y_final and t_final are the saved state of a run file (what --resume continues from),
    and a sweep run's state after its last completed step (its attributes; the last sample in
    files written before they were kept, which is that state unless output.times end early).
    The file of an ensemble sweep gives its EnsembleResult (``load_ensemble``).
    Raises OutputError (an ElimfastError) for a file or run that cannot be read.
    """
    import warnings

    from .integrate import Result
    from .io.ensemblefile import is_ensemble_file
    from .io.layout import PROBLEM_FILE_DIGEST, problem_file_changed, split_run_path
    from .io.runfile import RunFile

    file_path, run = split_run_path(path, run)
    if run is None and is_ensemble_file(file_path):
        return load_ensemble(file_path, allow_python=allow_python)
    with RunFile(file_path, run=run) as stored:
        spec = _rebuilt_spec(str(stored.attrs.get("config", "")), stored.name, "run", Path(file_path).parent,
                             allow_python)
        changed = problem_file_changed(stored.attrs.get(PROBLEM_FILE_DIGEST), spec.problem)
        if changed:   # a user trial: the permission was given for the file that made the run
            warnings.warn(f"{stored.name}: {changed}: the Result's problem is that file as it is now, not the "
                          "run's", stacklevel=2)
        t, y = stored.t(), stored.y()
        invariants = {name: stored.invariant(name) for name in stored.invariant_names}
        multipliers = stored.multipliers()
        iterations = stored.iterations().astype(np.int64)   # stored as i4; integrate's are int64
        if "failed_step_iterations" in stored.attrs:
            iterations = np.append(iterations, int(stored.attrs["failed_step_iterations"]))
        substeps = stored.substeps().astype(np.int64)
        if run is None:
            saved = stored.saved_state()
            y_final, t_final = saved["y"].copy(), float(saved["clock"][0])
        elif "y_final" in stored.attrs:
            y_final, t_final = np.array(stored.attrs["y_final"], dtype=np.float64), float(stored.attrs["t_final"])
        else:
            y_final, t_final = y[-1].copy(), float(t[-1])
        name = stored.multiplier_name
        elim_family = spec.method.imposes_invariants and spec.method.kernel_family != FAMILY_LIM
        if name == "alpha":
            alpha = multipliers
        else:   # as integrate: ELIM imposing nothing has alpha with no columns
            alpha = np.zeros((stored.steps_done, 0)) if elim_family else None
        n_steps = int(stored.attrs.get("n_steps", spec.n_steps))
        if n_steps == 0 and stored.adaptive:
            # an adaptive run's file has no step count set in advance (0); its Result, as integrate's,
            # counts the steps taken
            n_steps = stored.steps_done
        return Result(problem=spec.problem, method=spec.method, h=float(stored.attrs.get("h", spec.h)),
                      conserve=tuple(spec.conserve), t=t, y=y, invariants=invariants, alpha=alpha,
                      lam=multipliers if name == "lambda" else None, iterations=iterations, substeps=substeps,
                      y_final=y_final, t_final=t_final, n_steps=n_steps,
                      steps_done=stored.steps_done, status=stored.status, solver=spec.solver,
                      y0=spec.problem.y0.copy(), t0=float(stored.attrs.get("t0", spec.t0)),
                      **_adaptive_parts(stored, spec))


def _adaptive_parts(stored, spec) -> dict:
    """A run through the adaptive kernel (docs/adaptive.md): its steps, events and stats."""
    if stored.step_sizes() is None:
        return {}
    from .adaptive import AdaptiveIntegration, EventRecord

    given = {name: {key: event[key] for key in ("expression", "direction", "terminal")}
             for name, event in (spec.events or {}).items()}   # the stored config's events section
    parts = {"step_t": stored.step_times(), "step_h": stored.step_sizes(), "step_control": spec.step_control,
             "events": {name: EventRecord(*stored.event(name), **given.get(name, {})) for name in stored.event_names()},
             "events_not_finite": stored.events_not_finite()}
    counters = stored.saved_state().get("counters")
    if counters is not None:
        run = AdaptiveIntegration.from_spec(spec)
        parts["stats"] = run.stats(counters)   # a file's counters may be fewer (counted_stats)
    elif stored.stored_stats():   # a sweep run (no /state; files written before they were stored: none)
        parts["stats"] = stored.stored_stats()
    return parts


def load_ensemble(path, lazy: bool = False, *, allow_python: bool | None = None):
    """The EnsembleResult of the ensemble sweep stored in ``path``, as the sweep returned it.

    The problem, the method and the settings are built again from the stored config (as
    ``elimfast.ensemble.EnsembleRun`` builds them for a run; a python: problem file only with
    ``allow_python``, as ``load``); the arrays are read from the
    file, all at once, or with ``lazy`` each when first used (so that a summary of a large
    ensemble holds a column or two, never every array). OutputError for a file whose
    ensemble is not complete (it says how to complete it) or that cannot be read.
    """
    from .ensemble import ROW_ARRAYS, EnsembleRun, LazyEnsembleResult
    from .io.ensemblefile import STATUS_COMPLETE, EnsembleFile
    from .io.safety import OutputError

    path = Path(path)
    with EnsembleFile(path) as stored:
        if stored.status != STATUS_COMPLETE:
            source = stored.root_attrs.get("source", "SWEEP.yaml")
            raise OutputError(f"{path}: its ensemble is {stored.status}: {stored.stored:,} of "
                              f"{stored.n_trajectories:,} trajectories stored; complete it with elimfast sweep "
                              f"{source} -o {path} --resume (/ensemble/stored marks the rows written)")
        if not stored.has("diagnostics"):
            raise OutputError(f"{path}: its ensemble was written by an earlier elimfast (no /ensemble/diagnostics); "
                              "read it with h5py or xarray, or run the sweep again")
        spec = _rebuilt_spec(str(stored.attrs.get("config", "")), f"{path}:/ensemble", "ensemble", path.parent,
                             allow_python)
        run = EnsembleRun.from_spec(spec, stored.column("y0", 0, 1)[0], n_threads=1)
        settings = {"problem": spec.problem, "method": spec.method, "h": float(stored.attrs.get("h", run.h)),
                    "conserve": run.conserve, "n_steps": int(stored.attrs.get("n_steps", run.n_steps)),
                    "max_iter": run.max_iter, "n_threads": int(stored.attrs.get("threads", 0)), "solver": run.solver}
        columns = {} if lazy else {name: _column(stored, name) for name in ("y0",) + ROW_ARRAYS + ("invariant_errors",)}
        n_trajectories = stored.n_trajectories

    def read(name):
        with EnsembleFile(path) as again:
            return _column(again, name)
    return LazyEnsembleResult(read, n_trajectories, **settings, **columns)


def _column(stored, name: str):
    """One per-trajectory array of an EnsembleFile (invariant_errors: a mapping of them)."""
    if name == "invariant_errors":
        return {invariant: stored.column(f"invariant_errors/{invariant}") for invariant in stored.invariant_names}
    return stored.column(name)
