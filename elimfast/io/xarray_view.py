"""A Result as an xarray.Dataset, with the dimensions and names of a run file (layout.py)."""
from __future__ import annotations

import numpy as np

from .layout import LONG_NAMES, unit_attributes


def result_dataset(result):
    """y on (t, component); H and every invariant on t; iterations, substeps and alpha or
    lambda on step (alpha/lambda also on ``invariant``, the invariant of each column).
    Attributes: problem, method, h, conserve, n_steps, steps_done, status and the units."""
    try:
        import xarray as xr
    except ImportError:
        raise ImportError("Result.to_xarray needs xarray: pip install xarray") from None
    units = dict(getattr(result.problem, "units", {}) or {})
    time_attrs = {"long_name": LONG_NAMES["t"], **({"units": units["time"]} if "time" in units else {})}
    coords = {"t": ("t", np.asarray(result.t), time_attrs),
              "component": ("component", np.array(result.problem.coordinate_names, dtype=object),
                            {"long_name": LONG_NAMES["component"]})}
    data = {"y": (("t", "component"), np.asarray(result.y), {"long_name": LONG_NAMES["y"]})}
    for name, values in result.invariants.items():
        data[name] = ("t", np.asarray(values), {"long_name": LONG_NAMES["H"] if name == "H" else f"invariant {name}",
                                                "imposed": int(name in result.conserve)})
    done = result.steps_done
    data["iterations"] = ("step", np.asarray(result.iterations[:done]), {"long_name": LONG_NAMES["iterations"]})
    data["substeps"] = ("step", np.asarray(result.substeps[:done]), {"long_name": LONG_NAMES["substeps"]})
    for name, values, columns in (("alpha", result.alpha, tuple(result.conserve)),
                                  ("lambda", result.lam, ("H",) + tuple(result.conserve))):
        if values is not None and values.shape[1]:
            coords["invariant"] = ("invariant", np.array(columns, dtype=object), {"long_name": LONG_NAMES["invariant"]})
            data[name] = (("step", "invariant"), np.asarray(values[:done]), {"long_name": LONG_NAMES[name]})
    attrs = {"problem": result.problem.name, "method": result.method.name, "h": float(result.h),
             "conserve": list(result.conserve), "n_steps": int(result.n_steps), "steps_done": int(done),
             "status": result.status, **unit_attributes(result.problem)}
    return xr.Dataset(data, coords=coords, attrs=attrs)
