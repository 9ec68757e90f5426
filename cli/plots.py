"""``elimfast plot``: matplotlib figures of a RunFile (Agg backend, no display needed)."""
from __future__ import annotations

import numpy as np

from elimfast.errors import ElimfastError

MAX_POINTS = 200_000    # points per curve; longer data are strided (every n-th row)
# Samples may be far apart (output.every): dots with a faint line, not chords alone.
ORBIT_STYLE = {"marker": ".", "ms": 1.5, "lw": 0.2}


class PlotError(ElimfastError):
    """The requested plot does not exist for this run."""


def _stride(n: int) -> int:
    return max(1, -(-n // MAX_POINTS))


def _bodies(names):
    """(x, y) coordinate index pairs when the q names look like per-body x, y[, z] triples/pairs."""
    for width in (3, 2):
        if len(names) % width or len(names) < width:
            continue
        groups = [names[i:i + width] for i in range(0, len(names), width)]
        if all(g[0].lower().startswith("x") and g[1].lower().startswith("y") for g in groups):
            return [(i, i + 1) for i in range(0, len(names), width)], [g[0][1:] or str(j) for j, g in enumerate(groups)]
    return None, None


def plot_run(run_file, kind: str, path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    attrs = run_file.attrs
    title = f"{attrs.get('problem')}, {attrs.get('method')}, h = {attrs.get('h'):.6g}"
    if kind == "invariants":   # absolute errors, and beside them the relative ones
        figure, (axes, relative_axes) = plt.subplots(1, 2, figsize=(13, 5), dpi=100)
    else:
        figure, axes = plt.subplots(figsize=(8, 5), dpi=100)
    try:
        if kind == "orbit":
            _orbit(run_file, axes)
        elif kind == "invariants":
            _invariants(run_file, axes, relative_axes)
        elif kind == "alpha":
            _multipliers(run_file, axes)
        elif kind == "iterations":
            _iterations(run_file, axes)
        else:
            raise PlotError(f"unknown plot kind {kind!r}; use orbit, invariants, alpha or iterations")
        axes.set_title(title + ("" if run_file.status == "complete" else f" [{run_file.status}]"))
        figure.tight_layout()
        figure.savefig(path)
    finally:
        plt.close(figure)


def _orbit(run_file, axes) -> None:
    n = run_file.n_samples
    if n < 2:
        raise PlotError(f"{run_file.name}: only {n} sample(s) stored; nothing to draw")
    y = run_file.y(_stride(n))
    names = run_file.coordinate_names
    m = len(names) // 2
    pairs, labels = _bodies(names[:m])
    if m == 1:
        axes.plot(y[:, 0], y[:, 1], **ORBIT_STYLE)
        axes.set_xlabel(names[0])
        axes.set_ylabel(names[1])
        axes.set_aspect("equal", adjustable="datalim")
    elif pairs is not None:
        for (i, j), label in zip(pairs, labels):
            axes.plot(y[:, i], y[:, j], label=label, **ORBIT_STYLE)
        axes.set_xlabel("x")
        axes.set_ylabel("y")
        axes.set_aspect("equal", adjustable="datalim")
        axes.legend(fontsize="small")
    elif m == 2:
        axes.plot(y[:, 0], y[:, 1], **ORBIT_STYLE)
        axes.set_xlabel(names[0])
        axes.set_ylabel(names[1])
        axes.set_aspect("equal", adjustable="datalim")
    else:   # a chain: each q against t
        t = run_file.t(_stride(n))
        for i in range(min(m, 12)):
            axes.plot(t, y[:, i], lw=0.6, label=names[i])
        axes.set_xlabel("t")
        axes.legend(fontsize="small", ncol=2)


def _invariants(run_file, axes, relative_axes=None) -> None:
    """|I(t) - I(t0)| on ``axes``; on ``relative_axes`` |I(t) - I(t0)| / |I(t0)|, absolute
    where I(t0) = 0 (say for the solar system's H0 = -3.2e-8 an absolute 1e-20 means little)."""
    from elimfast.integrate import relative_error

    n = run_file.n_samples
    if n < 2:
        raise PlotError(f"{run_file.name}: only {n} sample(s) stored; nothing to draw")
    stride = _stride(n)
    t = run_file.t(stride)
    conserve = set(run_file.attrs.get("conserve") or [])
    for name in run_file.invariant_names:
        values = run_file.invariant(name, stride)
        error = np.abs(values - values[0])
        error[error == 0.0] = np.nan   # exact agreement has no place on a log scale
        label = name + (" (imposed)" if name in conserve else "")
        axes.semilogy(t, error, lw=0.8, label=label)
        if relative_axes is not None:
            scale = relative_error(1.0, float(values[0]))    # 1/|I0|, or 1 where I0 = 0
            relative_label = label + ("" if values[0] != 0.0 else " (absolute: I(t0) = 0)")
            relative_axes.semilogy(t, error * scale, lw=0.8, label=relative_label)
    axes.set_xlabel("t")
    axes.set_ylabel("|I(t) - I(t0)|")
    axes.legend(fontsize="small")
    axes.grid(True, which="major", alpha=0.3)
    if relative_axes is not None:
        relative_axes.set_xlabel("t")
        relative_axes.set_ylabel("|I(t) - I(t0)| / |I(t0)|")
        relative_axes.set_title("relative errors")
        relative_axes.legend(fontsize="small")
        relative_axes.grid(True, which="major", alpha=0.3)


def _step_times(run_file, count: int, stride: int) -> np.ndarray:
    attrs = run_file.attrs
    return float(attrs["t0"]) + float(attrs["h"]) * (np.arange(0, count, stride) + 1)


def _multipliers(run_file, axes) -> None:
    if run_file.multiplier_name is None:
        raise PlotError(f"{run_file.name}: {run_file.attrs.get('method')} imposes no invariant, so there is no "
                        "alpha to plot; try --kind invariants")
    n = run_file.steps_done
    if n < 1:
        raise PlotError(f"{run_file.name}: no steps stored yet; nothing to draw")
    stride = _stride(n)
    values = run_file.multipliers(stride)
    t = _step_times(run_file, n, stride)
    for column, label in enumerate(run_file.multiplier_labels()):
        axes.plot(t, values[:, column], lw=0.6, label=label)
    axes.set_xlabel("t")
    axes.set_ylabel(run_file.multiplier_name + " (per step)")
    axes.legend(fontsize="small")


def _iterations(run_file, axes) -> None:
    n = run_file.steps_done
    if n < 1:
        raise PlotError(f"{run_file.name}: no steps stored yet; nothing to draw")
    stride = _stride(n)
    iterations = run_file.iterations(stride)
    t = _step_times(run_file, n, stride)
    axes.plot(t, iterations, ".", ms=1.5)
    axes.set_xlabel("t")
    axes.set_ylabel("fixed-point iterations per step")
    axes.set_ylim(bottom=0)
