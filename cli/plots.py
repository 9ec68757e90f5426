"""``elimfast plot``: matplotlib figures of a RunFile (Agg backend, no display needed)."""
from __future__ import annotations

import numpy as np

from elimfast.errors import ElimfastError

MAX_POINTS = 200_000    # points per curve; longer data are strided (every n-th row), or their peaks taken
PEAK_BLOCK_WINDOWS = 4096   # windows of rows read at a time by _window_peaks
# Dense samples: a line with dots on it. Sparse ones (output.every large against the
# orbit): markers alone, since lines between them are chords across the orbit.
ORBIT_STYLE = {"marker": ".", "ms": 1.5, "lw": 0.2}
SPARSE_ORBIT_STYLE = {"marker": ".", "ms": 3.0, "ls": "none"}
# Samples are sparse when the median distance between consecutive ones exceeds this
# fraction of the orbit's extent (the diagonal of its bounding box): 0.05 is about 60
# samples per turn of a circle, below which the polygon visibly cuts corners.
SPARSE_STEP_FRACTION = 0.05
TITLE_STATUS_CHARS = 80   # the status part of a title; a failure's full message is in `inspect`


def image_formats() -> dict[str, str]:
    """The suffixes matplotlib can write (without the dot) and their descriptions."""
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.backend_bases import FigureCanvasBase
    return FigureCanvasBase.get_supported_filetypes()


def check_image_path(path) -> None:
    """PlotError (exit 2) unless path's suffix names a format matplotlib writes."""
    from pathlib import Path
    suffix = Path(path).suffix.lower().lstrip(".")
    formats = image_formats()
    if suffix not in formats:
        what = f"unknown image format '.{suffix}'" if suffix else "no suffix to pick the image format"
        raise PlotError(f"{path}: {what}; use a file name ending in one of {', '.join('.' + f for f in formats)} "
                        f"(e.g. fig.png)")


def status_text(status: str, limit: int = TITLE_STATUS_CHARS) -> str:
    """A run's status short enough for a title: 'complete', or its first clause cut at a word.

    A failure reads 'failed: EHBVM(12,3): the simplified Newton did not converge ... at step
    N (...); last increment ...; advice': the method is in the title already, and the
    advice belongs to `inspect`, so the title keeps 'failed: <what> at step N', without
    the parenthesised details (max_iter, the times).
    """
    import re

    status = " ".join(str(status).split())
    head, _, reason = status.partition(": ")
    if reason:
        reason = reason.split("; ")[0]
        method_prefix, sep, rest = reason.partition(": ")
        if sep and "(" in method_prefix and " " not in method_prefix:
            reason = rest
        reason = re.sub(r"\s*\([^()]*\)", "", reason)
        status = f"{head}: {reason}"
    if len(status) > limit:
        cut = status[:limit - 3].rsplit(" ", 1)[0].rstrip(",;:")
        status = cut + "..."
    return status


def plot_title(run_file) -> str:
    """Problem, method and h; a second line with the status unless the run is complete."""
    attrs = run_file.attrs
    if run_file.adaptive:   # docs/adaptive.md
        control = attrs.get("step_control")
        steps = (f"adaptive steps, rtol = {attrs.get('rtol'):.3g}" if control == "error"
                 else f"time-reversible steps, epsilon = {attrs.get('epsilon'):.3g}")
    else:
        steps = f"h = {attrs.get('h'):.6g}"
    title = f"{attrs.get('problem')}, {attrs.get('method')}, {steps}"
    if run_file.status != "complete":
        title += f"\n[{status_text(run_file.status)}]"
    return title


class PlotError(ElimfastError):
    """The requested plot does not exist for this run."""


def _stride(n: int) -> int:
    return max(1, -(-n // MAX_POINTS))


def _magnitude(values: np.ndarray) -> np.ndarray:
    """|values|, NaN (an unimposed step's alpha) smallest: a window's peak is a number where it has one."""
    return np.nan_to_num(np.abs(values), nan=-1.0)


def _step_time_dataset(run_file) -> str | None:
    """'steps/t' where the steps' end times are stored (the adaptive kernel's runs), else None."""
    return "steps/t" if run_file.step_times(max(1, run_file.steps_done)) is not None else None


def _window_peaks(run_file, name: str, count: int, stride: int, size=_magnitude,
                  times: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(times, values), each (windows, columns), of dataset ``name``'s first count rows: in each
    window of ``stride`` rows, column by column, the row where size(value) is largest, and its time
    from the dataset ``times`` (None: the fixed steps' t0 + h (row + 1)). A long run's curves keep
    at most MAX_POINTS points, and every stride-th row alone dropped the extremes (a user trial: an
    alpha spike of 0.32 at step 293,615 of 4e5 drew as 0.058, and the iterations plot showed its
    spike of 3514 only by luck). Reads PEAK_BLOCK_WINDOWS windows at a time."""
    found_times, found_values = [], []
    for start in range(0, count, stride * PEAK_BLOCK_WINDOWS):
        stop = min(start + stride * PEAK_BLOCK_WINDOWS, count)
        block = run_file._read_rows(name, start, stop)
        block = block.reshape(block.shape[0], -1)
        block_times = run_file._read_rows(times, start, stop) if times is not None else None
        whole = block.shape[0] // stride * stride
        for first, last, width in ((0, whole, stride), (whole, block.shape[0], block.shape[0] - whole)):
            if last <= first:
                continue
            windows = block[first:last].reshape(-1, width, block.shape[1])
            at = np.argmax(size(windows), axis=1)   # (windows, columns)
            rows = first + np.arange(windows.shape[0])[:, None] * width + at
            found_values.append(np.take_along_axis(windows, at[:, None, :], axis=1)[:, 0, :])
            if block_times is not None:
                found_times.append(block_times[rows])
            else:
                attrs = run_file.attrs
                found_times.append(float(attrs["t0"]) + float(attrs["h"]) * (start + rows + 1))
    return np.concatenate(found_times), np.concatenate(found_values)


def _windowed(label: str, stride: int, rows: str) -> str:
    """An axis label that says when its curve is of window peaks (_window_peaks): each point is the
    largest of ``stride`` rows, so dips between peaks are not drawn (the last note: nothing said so)."""
    return label if stride <= 1 else f"{label}\n(largest of each {stride:,} {rows})"


def _bodies(names):
    """(x, y) coordinate index pairs when the q names look like per-body x, y[, z] triples/pairs:
    x1, y1, z1, ... or, as the built-in nbody names them, sun_x, sun_y, sun_z, ..."""
    for width in (3, 2):
        if len(names) % width or len(names) < width:
            continue
        groups = [[name.lower() for name in names[i:i + width]] for i in range(0, len(names), width)]
        if all(g[0].startswith("x") and g[1].startswith("y") for g in groups):
            return [(i, i + 1) for i in range(0, len(names), width)], [g[0][1:] or str(j) for j, g in enumerate(groups)]
        if all(g[0].endswith("_x") and g[1] == g[0][:-1] + "y" for g in groups):
            return [(i, i + 1) for i in range(0, len(names), width)], [names[i][:-2] for i in range(0, len(names),
                                                                                                   width)]
    return None, None


def plot_run(run_file, kind: str, path, event: str | None = None) -> None:
    """Draw one plot kind of a run into the image file ``path``, creating its missing
    directories (as a run file's writer does); event: the section's event (kind section)."""
    import matplotlib.pyplot as plt

    from elimfast.io.safety import create_parent_directories

    check_image_path(path)
    figure = draw(run_file, kind, event)
    try:
        create_parent_directories(path)
        figure.savefig(path)
    finally:
        plt.close(figure)


def draw(run_file, kind: str, event: str | None = None):
    """The matplotlib figure of one plot kind (the caller saves and closes it); event: the
    section's event (kind section; default: the run's first)."""
    if event is not None and kind != "section":
        raise PlotError(f"--event chooses the event of --kind section, not of --kind {kind}")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    relative_axes = None
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
        elif kind == "section":
            _section(run_file, axes, event)
        else:
            raise PlotError(f"unknown plot kind {kind!r}; use orbit, invariants, alpha, iterations or section")
        axes.set_title(plot_title(run_file), fontsize="medium")
        figure.tight_layout()
    except BaseException:
        plt.close(figure)
        raise
    return figure


def sparse(points: np.ndarray) -> bool:
    """True when consecutive samples of an orbit (rows of (x, y)) are far apart against its size."""
    finite = points[np.all(np.isfinite(points), axis=1)]
    if len(finite) < 3:
        return True
    extent = float(np.hypot(*(finite.max(axis=0) - finite.min(axis=0))))
    if extent == 0.0:
        return False
    steps = np.hypot(*np.diff(finite, axis=0).T)
    return float(np.median(steps)) > SPARSE_STEP_FRACTION * extent


CHAIN_CURVES = 12   # coordinates drawn against t when the q are not per-body x, y pairs


def _orbit(run_file, axes) -> None:
    n = run_file.n_samples
    if n < 2:
        raise PlotError(f"{run_file.name}: only {n} sample(s) stored; nothing to draw")
    y = run_file.y(_stride(n))
    names = run_file.coordinate_names
    m = len(names) // 2
    pairs, labels = _bodies(names[:m])
    if m == 1 or (m == 2 and pairs is None) or pairs is not None:
        if m == 1 or pairs is None:
            pairs, labels = [(0, 1)], [None]        # q against p (m = 1), or q1 against q2
            axes.set_xlabel(names[0])
            axes.set_ylabel(names[1])
        else:
            axes.set_xlabel("x")
            axes.set_ylabel("y")
        curves = [y[:, [i, j]] for i, j in pairs]
        style = SPARSE_ORBIT_STYLE if any(sparse(points) for points in curves) else ORBIT_STYLE
        for points, label in zip(curves, labels):
            axes.plot(points[:, 0], points[:, 1], label=label, **style)
        axes.set_aspect("equal", adjustable="datalim")
        if labels[0] is not None:
            axes.legend(fontsize="small")
        if style is SPARSE_ORBIT_STYLE:
            axes.annotate(f"{n} samples, far apart: markers only (lower output.every for a curve)", (0.01, 0.01),
                          xycoords="axes fraction", fontsize="small", color="0.4")
    else:   # a chain: each q against t
        t = run_file.t(_stride(n))
        for i in range(min(m, CHAIN_CURVES)):
            axes.plot(t, y[:, i], lw=0.6, label=names[i])
        axes.set_xlabel("t")
        axes.legend(fontsize="small", ncol=2)
        if m > CHAIN_CURVES:
            axes.annotate(f"the first {CHAIN_CURVES} of {m} coordinates q", (0.01, 0.01), xycoords="axes fraction",
                          fontsize="small", color="0.4")


# Fewer finite points than this are drawn with markers (_invariants).
FEW_POINTS = 20


def _invariants(run_file, axes, relative_axes=None) -> None:
    """|I(t) - I(t0)| on ``axes``; on ``relative_axes`` |I(t) - I(t0)| / |I(t0)| (say for the solar
    system's H0 = -3.2e-8 an absolute 1e-20 means little), relative to the size of I's terms
    where I(t0) vanishes against them (integrate.relative_reference)."""
    from elimfast.integrate import relative_reference

    from .report import reference_label

    n = run_file.n_samples
    if run_file.steps_done < 1:   # its samples are all of the initial state (integrate.invariant_drift)
        raise PlotError(f"{run_file.name}: no step done ({status_text(run_file.status)}); no invariant error to "
                        "draw")
    if n < 2:
        raise PlotError(f"{run_file.name}: only {n} sample(s) stored; nothing to draw")
    stride = _stride(n)
    conserve = set(run_file.attrs.get("conserve") or [])
    scales = run_file.invariant_scales()
    initial = run_file.initial_invariants()   # I(t0) of the initial state (older files: the first sample)
    for name in run_file.invariant_names:
        if stride > 1:   # the largest error of each window of samples, at its time
            t, values = _window_peaks(run_file, f"invariants/{name}", n, stride,
                                      size=lambda v, i0=initial[name]: _magnitude(v - i0), times="t")
            t, values = t[:, 0], values[:, 0]
        else:
            t, values = run_file.t(1), run_file.invariant(name, 1)
        error = np.abs(values - initial[name])
        error[error == 0.0] = np.nan   # exact agreement has no place on a log scale
        label = name + (" (imposed)" if name in conserve else "")
        finite = int(np.count_nonzero(np.isfinite(error)))
        if finite == 0:
            label += " (= I(t0) at every sample)"
        # a line needs two points: with few samples (a sweep run keeps t0 and t_end) mark each one
        style = {"marker": "o", "ms": 3} if finite < FEW_POINTS else {}
        axes.semilogy(t, error, lw=0.8, label=label, **style)
        if relative_axes is not None:
            reference, kind = relative_reference(initial[name], scales.get(name, 0.0))
            scale = 1.0 / reference
            relative_label = label + {"I(t0)": "", "terms": " (to the size of its terms: I(t0) ~ 0)",
                                      "absolute": " (absolute: I(t0) = 0)"}[kind]
            relative_axes.semilogy(t, error * scale, lw=0.8, label=relative_label, **style)
    axes.set_xlabel("t")
    axes.set_ylabel(_windowed(f"|I(t) - I({reference_label(run_file)})|", stride, "samples"))
    axes.legend(fontsize="small")
    axes.grid(True, which="major", alpha=0.3)
    if relative_axes is not None:
        relative_axes.set_xlabel("t")
        at = reference_label(run_file)
        relative_axes.set_ylabel(_windowed(f"|I(t) - I({at})| / |I({at})|", stride, "samples"))
        relative_axes.set_title("relative errors")
        relative_axes.legend(fontsize="small")
        relative_axes.grid(True, which="major", alpha=0.3)


def _step_times(run_file, count: int, stride: int) -> np.ndarray:
    stored = run_file.step_times(stride)   # adaptive steps: their end times are stored
    if stored is not None:
        return stored[:len(range(0, count, stride))]
    attrs = run_file.attrs
    return float(attrs["t0"]) + float(attrs["h"]) * (np.arange(0, count, stride) + 1)


# A coordinate whose values over a section's crossings spread by less than this fraction of the state's
# size is the one the event pins (q1 = 0: its crossings' q1 are rounding, ~1e-14).
SECTION_PINNED = 1e-9


def _section(run_file, axes, event: str | None = None) -> None:
    """A surface of section: the states at the occurrences of an event (the run's first unless
    event names one), q_j against p_j for the last degree of freedom j whose q_j and p_j both vary
    over the crossings (Henon-Heiles with the event q1 = 0: the (q2, p2) plane; with q2 = 0, the
    (q1, p1) plane, where a user trial got q2 against p2, the section's own coordinate at 0)."""
    names = run_file.event_names()
    if not names:
        raise PlotError(f"{run_file.name}: the run has no events; a section plot needs one, e.g. events: "
                        "{section: {expression: q1, direction: 1}} (docs/adaptive.md)")
    if event is not None and event not in names:
        raise PlotError(f"{run_file.name}: the run has no event {event!r}; its events: {', '.join(names)}")
    name = names[0] if event is None else event
    times, states = run_file.event(name)
    if times.size == 0:
        others = ", ".join(repr(n) for n in names if n != name)
        hint = f"; choose another with --event ({others})" if others else ""
        raise PlotError(f"{run_file.name}: event {name!r} never occurred; nothing to draw{hint}")
    coordinates = run_file.coordinate_names
    m = len(coordinates) // 2
    spread = np.ptp(states, axis=0) if times.size > 1 else np.ones(2 * m)
    pinned = spread <= SECTION_PINNED * max(float(np.max(np.abs(states))), 1e-300)
    free = [j for j in range(m) if not (pinned[j] or pinned[m + j])]
    j = free[-1] if free else m - 1
    axes.plot(states[:, j], states[:, m + j], ".", ms=2.0, color="k")
    axes.set_xlabel(coordinates[j])
    axes.set_ylabel(coordinates[m + j])
    axes.annotate(f"{times.size} crossings of {name}", (0.01, 0.01), xycoords="axes fraction",
                  fontsize="small", color="0.4")


def _multipliers(run_file, axes) -> None:
    if run_file.multiplier_name is None:
        raise PlotError(f"{run_file.name}: {run_file.attrs.get('method')} imposes no invariant, so there is no "
                        "alpha to plot; try --kind invariants")
    n = run_file.steps_done
    if n < 1:
        raise PlotError(f"{run_file.name}: no steps stored yet; nothing to draw")
    stride = _stride(n)
    labels = run_file.multiplier_labels()
    if stride > 1:   # each window's largest |alpha|, at its step
        t, values = _window_peaks(run_file, f"steps/{run_file.multiplier_name}", n, stride,
                                  times=_step_time_dataset(run_file))
        for column, label in enumerate(labels):
            axes.plot(t[:, column], values[:, column], lw=0.6, label=label)
    else:
        values = run_file.multipliers(1)
        t = _step_times(run_file, n, 1)
        for column, label in enumerate(labels):
            axes.plot(t, values[:, column], lw=0.6, label=label)
    axes.set_xlabel("t")
    axes.set_ylabel(_windowed(run_file.multiplier_name + " (per step)", stride, "steps, by magnitude"))
    axes.legend(fontsize="small")


def _solver_name(run_file) -> str:
    """What iterated: the stored config's solver, or 'solver' when a resume changed it (the
    label said 'fixed-point' of Newton's iterations too)."""
    from .report import config_of

    method = (config_of(run_file).get("solver") or {}).get("method", "fixed_point")
    if any("method" in str(entry) for entry in run_file.attrs.get("solver_history", [])):
        return "solver"
    return {"newton": "simplified Newton", "fixed_point": "fixed-point"}.get(method, "solver")


def _iterations(run_file, axes) -> None:
    n = run_file.steps_done
    if n < 1:
        raise PlotError(f"{run_file.name}: no steps stored yet; nothing to draw")
    stride = _stride(n)
    if stride > 1:   # each window's largest count, at its step
        t, iterations = _window_peaks(run_file, "steps/iterations", n, stride,
                                      times=_step_time_dataset(run_file))
        t, iterations = t[:, 0], iterations[:, 0]
    else:
        iterations, t = run_file.iterations(1), _step_times(run_file, n, 1)
    axes.plot(t, iterations, ".", ms=1.5)
    axes.set_xlabel("t")
    axes.set_ylabel(_windowed(f"{_solver_name(run_file)} iterations per step", stride, "steps"))
    axes.set_ylim(bottom=0)
