"""A Result as an xarray.Dataset, with the dimensions and names of a run file (layout.py)."""
from __future__ import annotations

import numpy as np

from .layout import LONG_NAMES, NOT_FINITE_FROM, STEP_CONTROL_FIXED, VALUE_AT_T0, stats_attributes, unit_attributes


def result_dataset(result):
    """y on (t, component); H and every invariant on t; iterations, substeps and alpha or
    lambda on step (alpha/lambda also on ``invariant``, the invariant of each column).
    Adaptive runs add step_t and step_h on step (a run file's /steps/t and /steps/h), and
    every event its times ``<name>_t`` on ``<name>_occurrence`` (attributes: the event's
    expression, direction, terminal 0/1 and, where it was NaN or infinite at a sample, the first
    such time not_finite_from) and states ``<name>_y`` on (``<name>_occurrence``, component)
    (a run file's /events/<name>). H and each invariant
    carry ``value_at_t0``, I of the initial state, and ``scale``, the size of its terms there
    (for relative errors), as in a run file; ``imposed`` is 0 or 1.
    Attributes: problem, method, h (adaptive: the first step, also as h_first), conserve,
    n_steps, steps_done, status and the units; adaptive runs add the step control's
    settings (step_control, rtol, atol or epsilon, verify) and the counts of Result.stats, named
    stats_<name> as in a run file (layout.stats_attributes)."""
    try:
        import xarray as xr
    except ImportError:
        raise ImportError("Result.to_xarray needs xarray: pip install xarray") from None
    units = dict(getattr(result.problem, "units", {}) or {})
    time_unit = {"units": units["time"]} if "time" in units else {}   # as a run file: t, step_t, step_h, events
    time_attrs = {"long_name": LONG_NAMES["t"], **time_unit}
    coords = {"t": ("t", np.asarray(result.t), time_attrs),
              "component": ("component", np.array(result.problem.coordinate_names, dtype=object),
                            {"long_name": LONG_NAMES["component"]})}
    data = {"y": (("t", "component"), np.asarray(result.y), {"long_name": LONG_NAMES["y"]})}
    at_t0, scales = result.initial_invariants(), result.invariant_scales()
    for name, values in result.invariants.items():
        # imposed as 0/1, as a run file has it (layout.flag_attribute): netCDF has no boolean attributes
        data[name] = ("t", np.asarray(values), {"long_name": LONG_NAMES["H"] if name == "H" else f"invariant {name}",
                                                "imposed": int(name in result.conserve),
                                                **({"scale": float(scales[name])} if name in scales else {}),
                                                VALUE_AT_T0: at_t0.get(name, float("nan"))})
    done = result.steps_done
    data["iterations"] = ("step", np.asarray(result.iterations[:done]), {"long_name": LONG_NAMES["iterations"]})
    data["substeps"] = ("step", np.asarray(result.substeps[:done]), {"long_name": LONG_NAMES["substeps"]})
    for name, values, columns in (("alpha", result.alpha, tuple(result.conserve)),
                                  ("lambda", result.lam, ("H",) + tuple(result.conserve))):
        if values is not None and values.shape[1]:
            coords["invariant"] = ("invariant", np.array(columns, dtype=object), {"long_name": LONG_NAMES["invariant"]})
            data[name] = (("step", "invariant"), np.asarray(values[:done]), {"long_name": LONG_NAMES[name]})
    if result.step_t is not None:
        data["step_t"] = ("step", np.asarray(result.step_t[:done]), {"long_name": LONG_NAMES["step_t"], **time_unit})
        data["step_h"] = ("step", np.asarray(result.step_h[:done]), {"long_name": LONG_NAMES["step_h"], **time_unit})
    for name, record in result.events.items():
        occurrence = f"{name}_occurrence"
        # the event as given and where it stopped being finite, as a run file's /events/<name> has them
        # (terminal as 0/1: netCDF has no boolean attributes)
        given = {"expression": record.expression, "direction": int(record.direction),
                 "terminal": int(bool(record.terminal))}
        if name in result.events_not_finite:
            given[NOT_FINITE_FROM] = float(result.events_not_finite[name])
        data[f"{name}_t"] = (occurrence, np.asarray(record.t), {"long_name": f"time of event {name}", **given,
                                                               **time_unit})
        data[f"{name}_y"] = ((occurrence, "component"), np.asarray(record.y), {"long_name": f"state at event {name}"})
    attrs = {"problem": result.problem.name, "method": result.method.name, "h": float(result.h),
             "conserve": list(result.conserve), "n_steps": int(result.n_steps), "steps_done": int(done),
             "status": result.status, **unit_attributes(result.problem)}
    control = result.step_control
    attrs["step_control"] = STEP_CONTROL_FIXED   # as a run file says it (layout.run_attributes)
    if control is not None:
        # n_steps as the run file has it: 0, not known in advance (the README; a user trial saw 8373
        # here beside the file's 0; steps_done counts the steps)
        attrs["n_steps"] = 0
        attrs["h_first"] = float(result.h)
        settings = control.as_dict()
        attrs["step_control"] = settings.pop("controller")     # the run file's name for it
        # verify as 0/1, as imposed: netCDF has no boolean attributes (to_netcdf refused every adaptive run)
        attrs.update({key: int(value) if isinstance(value, (bool, np.bool_)) else value
                      for key, value in settings.items() if value is not None})
        # stats_<name>, as a run file's root has them (a user trial: a bare 'iterations' attribute beside
        # the variable iterations)
        attrs.update(stats_attributes(result.stats))
    return xr.Dataset(data, coords=coords, attrs=attrs)


def ensemble_dataset(result, status_names: dict):
    """An EnsembleResult as an xarray.Dataset, with the names of an ensemble file's /ensemble
    (ensemblefile.py): y0 and y_final on (trajectory, component); t_final, iterations,
    max_multiplier, status (CF flag_values and flag_meanings), steps_done, split_steps and
    unimposed_steps on trajectory; diagnostics on (trajectory, diagnostic); the file's invariant_errors/<name> as
    one variable invariant_error on (trajectory, invariant), H first. Attributes: problem,
    method, h, n_steps, conserve, failed and the units. status_names: code -> word (the
    caller's: io does not import the ensemble module). A result read from a file reads
    every column."""
    try:
        import xarray as xr
    except ImportError:
        raise ImportError("EnsembleResult.to_xarray needs xarray: pip install xarray") from None
    from .ensemblefile import DIAGNOSTIC_NAMES, ROW_LONG_NAMES, status_flags
    units = dict(getattr(result.problem, "units", {}) or {})
    time_unit = {"units": units["time"]} if "time" in units else {}
    n = result.n_trajectories
    coords = {"trajectory": ("trajectory", np.arange(n), {"long_name": "trajectory (row of the initial states)"}),
              "component": ("component", np.array(result.problem.coordinate_names, dtype=object),
                            {"long_name": LONG_NAMES["component"]})}
    data = {"y0": (("trajectory", "component"), np.asarray(result.y0), {"long_name": ROW_LONG_NAMES["y0"]}),
            "y_final": (("trajectory", "component"), np.asarray(result.y_final),
                        {"long_name": ROW_LONG_NAMES["y_final"]})}
    for name in ("t_final", "iterations", "max_multiplier", "status", "steps_done", "split_steps", "unimposed_steps"):
        data[name] = ("trajectory", np.asarray(getattr(result, name)),
                      {"long_name": ROW_LONG_NAMES[name], **(time_unit if name == "t_final" else {})})
    data["status"][2].update(status_flags(status_names, np.asarray(result.status).dtype))
    diagnostics = np.asarray(result.diagnostics)
    coords["diagnostic"] = ("diagnostic", np.array(DIAGNOSTIC_NAMES[:diagnostics.shape[1]], dtype=object),
                            {"long_name": "diagnostic of the failed step (kernels/stepper.py try_step)"})
    data["diagnostics"] = (("trajectory", "diagnostic"), diagnostics, {"long_name": ROW_LONG_NAMES["diagnostics"]})
    invariants = list(result.invariant_errors)
    coords["invariant"] = ("invariant", np.array(invariants, dtype=object), {"long_name": "invariant (H first)"})
    data["invariant_error"] = (("trajectory", "invariant"),
                               np.stack([np.asarray(result.invariant_errors[name]) for name in invariants], axis=1)
                               if invariants else np.zeros((n, 0)),
                               {"long_name": "max |I(t) - I(t0)| over the steps, for each invariant"})
    attrs = {"problem": result.problem.name, "method": result.method.name, "h": float(result.h),
             "n_steps": int(result.n_steps), "conserve": list(result.conserve), "failed": int(result.n_failed),
             **unit_attributes(result.problem)}
    return xr.Dataset(data, coords=coords, attrs=attrs)
