"""The text of ``elimfast inspect``: a RunFile's summary, formatted (the numbers come from RunFile)."""
from __future__ import annotations

import functools
import math
import shlex

import numpy as np

import yaml


def no_samples_text(run_file) -> str | None:
    """What a run with steps done and no sample says of its invariants: it ended (a terminal event)
    before its first output time, so nothing was sampled to measure them on. None otherwise. (A
    user trial: such a run was told that H and every invariant were NaN in some samples, "not
    defined on the whole orbit".)"""
    if run_file.n_samples or run_file.steps_done <= 0:
        return None
    clock = run_file.saved_state().get("clock")   # a run of a sweep file keeps no state
    ended = f" at t = {float(clock[0]):.10g}" if clock is not None else ""
    return (f"no sample stored: the run ended{ended} before its first output time (output.times), so its invariants "
            "are not measured; the last state is y_final (and a terminal event's state is under /events)")


def _samples_end(run_file) -> str:
    """' (t <= 3; the run ended at t = 30.14)' when the samples stop before the run's last
    state (output times before a terminal event or before t_end): the figures do not cover
    the end. Empty otherwise."""
    if not run_file.n_samples:
        return ""
    clock = run_file.saved_state().get("clock")   # a run of a sweep file keeps no state
    if clock is None:
        return ""
    times = run_file.t()
    first, last, end = float(times[0]), float(times[-1]), float(clock[0])
    if not abs(end - first) > abs(last - first) + 1e-12 * max(abs(end), 1.0):   # also backward in time
        return ""
    # (a file still being written: its last saved state, not an end; a user trial read "ended")
    where = "is at" if str(run_file.attrs.get("status", "")) == "running" else "ended at"
    return f" (t <= {last:.10g}; the run {where} t = {end:.10g}, after the last sample)"


def _fmt_time(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    if seconds < 120:
        return f"{seconds:.3g} s"
    hours, rest = divmod(int(round(seconds)), 3600)
    minutes, secs = divmod(rest, 60)
    return f"{seconds:.0f} s ({hours}:{minutes:02d}:{secs:02d})"


PROBLEM_TEXT_CHARS = 80   # the listed parameters, and the listed initial state, each cut to about this


def _listed(values: dict) -> str:
    listed = ", ".join(f"{k} = {v}" for k, v in values.items())
    return listed if len(listed) <= PROBLEM_TEXT_CHARS else listed[:PROBLEM_TEXT_CHARS - 3] + "..."


def _problem_text(run_file) -> str:
    """The problem row: its name and parameters; when the state was given in place of the
    problem's default (attribute initial_state, layout.run_attributes), that it comes from
    problem.initial and what it is, so that parameters which only chose the default state
    (kepler's eccentricity) are not read as describing the orbit."""
    from elimfast.io.layout import INITIAL_GIVEN

    attrs = run_file.attrs
    problem = config_of(run_file).get("problem")
    parameters = problem.get("parameters") if isinstance(problem, dict) else None
    text = f"{attrs.get('problem')} ({_listed(parameters)})" if parameters else str(attrs.get("problem"))
    if attrs.get("initial_state") == INITIAL_GIVEN:
        initial = problem.get("initial") if isinstance(problem, dict) else None
        state = f": {_listed(initial)}" if isinstance(initial, dict) and initial else ""
        not_default = ", not the default of these parameters" if parameters else ""
        text += f"; initial state from problem.initial{not_default}{state}"
    return text


def start_time(run_file) -> float:
    """t0 of a run: its config's (a sweep file of earlier versions stored its first sample's
    time as the attribute t0), else the attribute."""
    integration = config_of(run_file).get("integration")
    if isinstance(integration, dict) and isinstance(integration.get("t0"), (int, float)):
        return float(integration["t0"])
    return float(run_file.attrs.get("t0", 0.0))


def reference_label(run_file) -> str:
    """What the invariant errors are measured against, as the axes say it: 't0' (the initial
    state), or for a file written before I(t0) was stored whose first sample is later, that
    sample's time ('t = 5')."""
    when = run_file.reference_time()
    return "t0" if math.isnan(when) or when == start_time(run_file) else f"t = {when:.6g}"


def config_of(run_file) -> dict:
    """The run's resolved config as stored in the file ({} when unreadable). Read-only: the
    parsed mapping is shared by the calls for one file (an end-of-run line asked for it 4 times)."""
    text = run_file.attrs.get("config", "")
    return _parsed_config(text) if isinstance(text, (str, bytes)) else {}


@functools.lru_cache(maxsize=8)
def _parsed_config(text) -> dict:
    # libyaml's safe loader where PyYAML has it (the same tags as yaml.safe_load, 10x faster)
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        config = yaml.load(text, Loader=loader) or {}
    except (yaml.YAMLError, TypeError):
        return {}
    return config if isinstance(config, dict) else {}


def relative_drift(run_file, names=None, drift=None) -> dict[str, float]:
    """{name: max |I(t) - I(t0)| relative (integrate.relative_error)} over a run file's samples,
    for ``names`` (default: H and every invariant); names without a finite figure (no step
    done yet) are left out. ``drift``: run_file.invariant_drift() when the caller has read it
    (it reads every sample)."""
    from elimfast.integrate import relative_error

    drift = run_file.invariant_drift() if drift is None else drift
    initial, scales = run_file.initial_invariants(), run_file.invariant_scales()
    relative = {}
    for name in (drift if names is None else names):
        error, first = drift.get(name, math.nan), initial.get(name, math.nan)
        if math.isfinite(error) and math.isfinite(first):
            relative[name] = relative_error(error, first, scales.get(name, 0.0))
    return relative


def _rate(steps, seconds) -> str:
    """Steps per second, or seconds per step when that is under one (a slow run read '0 steps/s')."""
    rate = steps / seconds
    return f"{rate:,.0f} steps/s" if rate >= 1 else f"{seconds / steps:.3g} s/step"


def energy_note(run_file, drift=None, problem=None) -> str | None:
    """Spec 8, "Quadrature of H": the note (elimfast.integrate.energy_note) when H or an imposed
    invariant lost more than round-off (relative 1e-12) in a run file (``drift``: as relative_drift's).
    ``problem``: the run's, where the caller has it (the run command), to see how far H's terms
    grew over the samples (integrate.terms_peak); inspect reads the file alone."""
    from elimfast.integrate import energy_note as note
    from elimfast.integrate import roundoff_allowance

    attrs = run_file.attrs
    relative = relative_drift(run_file, ("H", *list(attrs.get("conserve") or [])), drift)
    steps = run_file.substep_stats()["total"]
    initial, scales = run_file.initial_invariants(), run_file.invariant_scales()
    roundoff = {name: roundoff_allowance(steps, initial.get(name, math.nan), scales.get(name, 0.0))
                for name in relative}
    tol = (config_of(run_file).get("solver") or {}).get("tol")
    edits = [str(entry).split(":")[0] for entry in np.atleast_1d(attrs.get("problem_file_history") or [])]
    text = note(attrs.get("method"), attrs.get("k"), attrs.get("r"), attrs.get("h"), relative, run_file.adaptive,
                s=attrs.get("s"), degree=attrs.get("hamiltonian_degree"), roundoff=roundoff, steps=steps,
                tol=tol if isinstance(tol, (int, float)) else None,
                hand_written="python" in (config_of(run_file).get("problem") or {}),
                unchecked=(config_of(run_file).get("problem") or {}).get("check") is False,
                kinks=_kinks(config_of(run_file).get("problem") or {}), family=attrs.get("family"),
                peak=None if problem is None else lambda: _terms_peak(run_file, problem, scales.get("H", 0.0)))
    if text and edits:
        # H and the invariants are measured against t0's, of the first version of the file (a user trial
        # edited its pair potential and resumed: the note spoke of quadrature and k only)
        text = (f"the python: problem file was edited during the run ({', '.join(edits)}; --resume with the new one), "
                f"so its steps solve more than one H, which alone moves H and the invariants; if that is not it: {text}")
    return text


def _terms_peak(run_file, problem, reference: float):
    """integrate.terms_peak of a run file's samples, read with the stride it would take."""
    from elimfast.integrate import peak_stride, terms_peak
    stride = peak_stride(run_file.n_samples)
    return terms_peak(problem, run_file.y(stride), run_file.t(stride), reference)


def _kinks(problem_section) -> tuple:
    """The kinked functions of a stored config's H from expressions (Problem.hamiltonian_kinks)."""
    hamiltonian = problem_section.get("hamiltonian") if isinstance(problem_section, dict) else None
    if not isinstance(hamiltonian, str):
        return ()
    import ast

    from elimfast.problems.expressions import kinked_functions
    try:   # the run validated it; its calls are read, nothing is evaluated
        return kinked_functions(ast.parse(hamiltonian, mode="eval"))
    except (SyntaxError, ValueError, RecursionError):
        return ()


def run_notes(run_file, problem=None) -> list[str]:
    """What the end-of-run line adds: split steps, an H error above round-off, an unused h
    (``problem``: the run's, for energy_note)."""
    notes = []
    substeps = run_file.substep_stats()
    drift = run_file.invariant_drift()
    if substeps["split"]:
        # ("kept" only where the invariants are defined: a trial's H was NaN in a third of the samples, and
        # this note, beside the one saying so, said every invariant was kept)
        kept = ("; every invariant is kept there too" if not any(math.isnan(value) for value in drift.values())
                else "")
        notes.append(f"{substeps['split']:,} step(s) were split into substeps (at most {substeps['max']}): the solver "
                     "could not converge them whole, or could only with alpha carrying rounding into the step "
                     f"(docs/solver.md#when-a-step-fails-retry-then-split){kept}")
    if substeps.get("unimposed"):
        notes.append(unimposed_text(substeps["unimposed"], run_file.steps_done, run_file.adaptive,
                                    _literal_sum(run_file)))
    spikes = run_file.alpha_spikes()
    if spikes:
        from elimfast.integrate import alpha_spike_note
        notes.append(alpha_spike_note(spikes, run_file.steps_done))
    warning = energy_note(run_file, drift, problem)
    if warning:
        notes.append(warning)
    no_samples = no_samples_text(run_file)   # reads the saved state: once
    if no_samples:
        notes.append(no_samples)
    elif run_file.steps_done > 0:
        undefined = [name for name, value in drift.items() if math.isnan(value)]
        if undefined:
            # a user trial: H NaN in a third of the samples (log(x) with x < 0 on the orbit, the check off)
            # completed without a word
            notes.append(f"{', '.join(undefined)} {'is' if len(undefined) == 1 else 'are'} NaN or infinite in some "
                         "samples: the problem's function gave it there, where the state is finite, so it is not "
                         "defined on the whole orbit (elimfast check CONFIG tests the problem's functions)")
    h = (config_of(run_file).get("integration") or {}).get("h")
    if run_file.attrs.get("step_control") == "time_scale" and h is not None:
        notes.append(unused_h_note(h, run_file.attrs.get("h_first")))
    return notes


def unused_h_note(h, first=None) -> str:
    """An h given beside step_control: time_scale (say left from a fixed-step config under --set
    integration.step_control=time_scale): that controller takes every step, the first too."""
    taken = f" ({first!r} here)" if first is not None else ""
    return (f"integration.h = {h!r} is not used: time-scale steps are all the controller's, the first "
            f"too{taken}, epsilon / rho at y0: integration.epsilon sets their size (docs/adaptive.md)")


# Above this fraction of a run's steps, substeps taken without imposing are no transient zero of
# Gamma: the imposed invariant is degenerate along the orbit (L on a circular Kepler orbit: 234 of 240).
UNIMPOSED_DEGENERATE_FRACTION = 0.01
# What such degenerate invariants look like (a user trial: the solar system imposing its three angular
# momenta, every step unimposed, was told of circular orbits and close approaches it did not have).
DEGENERATE_EXAMPLES = ("e.g. L on a circular orbit, where it is a function of H, or the components of the angular "
                       "momentum of a nearly planar system, whose rows of Gamma are nearly proportional")


def _literal_sum(run_file) -> str | None:
    """integrate.literal_sum_note of a run file's method and right-hand side."""
    from elimfast.integrate import literal_sum_note
    attrs = run_file.attrs
    rhs = (config_of(run_file).get("solver") or {}).get("rhs", "stable")
    return literal_sum_note(str(attrs.get("family")), attrs.get("r"), attrs.get("k"), attrs.get("s"), str(rhs))


def unimposed_text(count: int, steps_done: int, adaptive: bool = False, literal_sum: str | None = None) -> str:
    """What a run's steps with a substep taken without imposing the invariants mean (docs/solver.md).
    ``literal_sum``: integrate.literal_sum_note of the run's method, the likelier cause when given."""
    text = (f"{count:,} step(s) were taken, or had a substep taken, without imposing the invariants, because "
            "imposing failed there (alpha was rounding over rounding, or the solver could not converge even after "
            "the last halving) and the step kept them to round-off anyway (their alpha is NaN; "
            "docs/solver.md#a-substep-without-imposing)")
    if count > UNIMPOSED_DEGENERATE_FRACTION * steps_done and literal_sum:
        text += f"; that many: {literal_sum}"
    elif count > UNIMPOSED_DEGENERATE_FRACTION * steps_done and adaptive:
        # a user trial: Kepler e = 0.99 under the time-scale controller, epsilon 0.05, whose pericentre
        # steps of 5e-5 are too short for Gamma, was told that L and A_y were degenerate on its orbit
        text += ("; that many means that its shortest steps (at close approaches) are too short for Gamma, "
                 f"or that the imposed invariants are degenerate along this orbit ({DEGENERATE_EXAMPLES}): a "
                 "larger epsilon or rtol takes longer steps there; imposing fewer or none, or GHBVM (LIM), is "
                 "faster")
    elif count > UNIMPOSED_DEGENERATE_FRACTION * steps_done:
        text += (f"; that many means the imposed invariants are degenerate along this orbit ({DEGENERATE_EXAMPLES}),"
                 " where ELIM's Gamma is (nearly) singular: impose fewer or none, which is faster, or take GHBVM "
                 "(LIM), whose Gram matrix does not degenerate with Gamma (docs/methods.md#lim)")
    return text


def adaptive_text(settings) -> str:
    """How an adaptive run chooses its steps, from its step control's settings (a run
    file's attributes, or StepControl.as_dict() with the key step_control for controller)."""
    control = str(settings.get("step_control"))
    how = (f"rtol {settings.get('rtol')!r}, atol {settings.get('atol')!r}"
           + (", step doubling" if settings.get("verify") else "")
           if control == "error" else f"epsilon {settings.get('epsilon')!r}")
    if settings.get("h_max") is not None:   # it decides the steps as much as rtol or epsilon does
        how += f", h_max {settings.get('h_max')!r}"
    return f"adaptive ({control}: {how}; docs/adaptive.md)"


def _changed_settings(entry: str) -> str:
    """A solver_history entry, 'from step N: key value, ... (before: key value, ...)', cut to the
    settings that changed ('from step N: max_iter 30 (before: 3)'); other entries as they are."""
    import re
    match = re.fullmatch(r"(from step \d+: )(.*) \(before: (.*)\)", entry)
    if not match:
        return entry
    head, after, before = match.groups()
    pairs = [item.partition(" ") for item in after.split(", ")]
    old = dict((key, value) for key, _, value in (item.partition(" ") for item in before.split(", ")))
    changed = [(key, value) for key, _, value in pairs if old.get(key) != value]
    if not changed or any(key not in old for key, _ in changed):
        return entry
    return head + ", ".join(f"{key} {value} (before: {old[key]})" for key, value in changed)


def _swmr_note(path, status: str) -> str:
    """The file row's note on a file HDF5 sees open for writing: its writer is still at work
    (repair refuses such a file), or stopped without closing it (kill -9: repair it)."""
    if status == "running":
        return "  (opened in SWMR mode: its writer is still running)"
    return (f"  (opened in SWMR mode: its writer did not close it; other HDF5 programs open it after "
            f"'elimfast repair {path}')")


def summary(run_file, integrity: dict | None = None) -> str:
    """The inspect summary of an open RunFile (``integrity``: what RunFile.verify returned)."""
    a = run_file.attrs
    rows = []

    def row(key, value):
        rows.append(f"{key:<13}{value}")

    conserve = list(a.get("conserve") or [])
    row("file", f"{run_file.name}" + (_swmr_note(run_file.path, run_file.status) if run_file.swmr else ""))
    row("problem", _problem_text(run_file))
    method = f"{a.get('method')}, order {2 * int(a.get('s', 0))}"
    row("method", method + (f", imposing {', '.join(conserve)}" if conserve else ""))
    done = run_file.steps_done
    terminal_t = _terminal_event_time(run_file)   # reads the saved state: once
    samples = (f"samples at {a.get('output_times')} requested times" if "output_times" in a
               else "a sample every step" if str(a.get("output_every")) == "1"
               else f"a sample every {a.get('output_every')} steps")
    if run_file.adaptive:
        h_max = (config_of(run_file).get("integration") or {}).get("h_max")   # in the stored config only
        row("steps", f"{adaptive_text({**a, 'h_max': h_max})}, t0 = {a.get('t0')!r}, t_end = {a.get('t_end')!r}, "
                     f"{samples}")
        sizes = run_file.step_sizes()
        if sizes is not None and sizes.size:
            last = ""
            if sizes.size > 1 and str(run_file.status) == "complete" and sizes[-1] < sizes[:-1].min():
                # the last step is cut to land on t_end: as 'h min' it read 5.2e-3 for a controller whose
                # steps were all 0.085-0.092 (a user trial); it is no measure of the controller's work;
                # or on the terminal event that ended the run (a user trial read 't_end' there)
                where = "the terminal event" if terminal_t is not None else "t_end"
                last = f"; the last, cut to land on {where}, {sizes[-1]:.3e}"
                sizes = sizes[:-1]
            row("h", f"min {sizes.min():.3e}, median {np.median(sizes):.3e}, max {sizes.max():.3e}{last}")
        row("steps done", f"{done:,}")
        from elimfast.adaptive import counted_stats

        # a run file's saved counters, or the Result.stats stored with a run of a sweep file
        counters = run_file.saved_state().get("counters")
        stats = counted_stats(counters) if counters is not None else run_file.stored_stats()
        if stats:
            row("stats", f"{stats.get('rejected_steps', 0):,} rejected, {stats.get('failed_solves', 0):,} halved "
                         f"after a failed solve, {stats.get('side_steps', 0):,} side steps, "
                         f"{stats.get('hessian_evaluations', 0):,} Hessians")
    else:
        row("h", f"{a.get('h')!r}  (t0 = {a.get('t0')!r}, t_end = {a.get('t_end')!r}, {samples})")
        n_steps = int(a.get("n_steps", 0))
        row("steps done", f"{done} / {n_steps}" + (f"  ({100.0 * done / n_steps:.1f}%)" if done < n_steps else ""))
    not_finite = run_file.events_not_finite()
    for name in run_file.event_names():
        times, _ = run_file.event(name)
        shown = ", ".join(f"{t:.10g}" for t in times[:3]) + (", ..." if times.size > 3 else "")
        row("events" if name == run_file.event_names()[0] else "",
            f"{name}: {times.size} found" + (f", t = {shown}" if times.size else "")
            # "from t on" read as "everywhere after" beside crossings found later (a user trial: log(q1) + 2)
            + (f"; NaN or infinite at samples, first at t = {not_finite[name]:.6g}: no crossing can be found "
               "where it is (check the expression)" if name in not_finite else ""))
    status = run_file.status
    if status == "killed":
        status = ("killed (the writer stopped without closing the file; continue with elimfast run ... --resume"
                  + (f"; make it readable by other HDF5 programs with elimfast repair {run_file.path})"
                     if run_file.swmr else ")"))
    elif status == "running":
        status = "running (another process is writing it)"
    elif status == "complete" and terminal_t is not None:
        status += f" (ended by a terminal event at t = {terminal_t:.10g})"
    row("status", status)
    # how the run was continued (--resume with other solver settings, to a later end, or an edited
    # python: problem file)
    for key, what in (("solver_history", "solver"), ("extension_history", "continued"),
                      ("problem_file_history", "problem file changed")):
        for entry in np.atleast_1d(a.get(key) if a.get(key) is not None else []):
            row("resumed", f"{what} {_changed_settings(str(entry))}")
    wall, kernel = run_file.wall_time_s, run_file.kernel_time_s
    rate = f", {_rate(done, wall)}" if wall > 0 and done else ""
    kernel_text = f"; kernel {_fmt_time(kernel)}, {_rate(done, kernel)}" if kernel > 0 and done else ""
    row("wall time", f"{_fmt_time(wall)}{rate}{kernel_text}")
    row("created", f"{a.get('created')} with elimfast {a.get('elimfast_version')}, numba {a.get('numba_version')}, "
                   f"numpy {a.get('numpy_version')}, h5py {a.get('h5py_version')}")

    from elimfast.integrate import relative_reference

    drift = run_file.invariant_drift()
    samples_drift = drift
    initial = run_file.initial_invariants()
    scales = run_file.invariant_scales()
    if not any(math.isfinite(value) for value in drift.values()):
        # integrate.invariant_drift: no step done, no figure (0 would read as a perfect result)
        no_samples = no_samples_text(run_file)   # reads the saved state: once
        if no_samples:
            rows.append(f"invariants   no figures: {no_samples}")
        elif run_file.steps_done > 0:
            # a user trial: an H that was NaN in every sample read "no step done yet" after 100 steps
            rows.append(f"invariants   no figures: after {run_file.steps_done:,} steps, the invariants are NaN or "
                        "infinite in some or all of the samples (the problem's functions gave them there; the state "
                        "itself stayed finite)")
        else:
            why = "the run failed at its first step" if str(run_file.status).startswith("failed") else "no step done yet"
            rows.append(f"invariants   no figures: {why}, so no state after t0 to compare with I(t0)")
        drift = {}
    else:
        span = " before the failure" if str(run_file.status).startswith("failed") else ""
        span += _samples_end(run_file)
        when = reference_label(run_file)
        if when == "t0":
            rows.append(f"invariants   max |I(t) - I(t0)| over {run_file.n_samples} samples{span}, and relative to "
                        "|I(t0)|")
        else:   # a file written before I(t0) was stored, whose samples start after t0
            rows.append(f"invariants   max |I(t) - I({when})| over {run_file.n_samples} samples{span}, and relative "
                        f"to it: the first sample, not t0 = {start_time(run_file)!r} (the file predates storing "
                        "I(t0))")
    width = max(len(n) for n in drift) if drift else 0
    # GAUSS(s) = HBVM(s,s) keeps H only where its s nodes integrate it (a quadratic H): say so
    # rather than claim it kept an H it lost to 3e-6
    kept_H = ("  (H: GAUSS keeps only a quadratic H; HBVM(k,s) with k > s keeps others)"
              if str(run_file.attrs.get("family", "")) == "gauss"
              else "  (H: kept by HBVM/ELIM/LIM up to the quadrature error of their nodes)")
    # Imposed, but not at every step: say how often (a user trial read '(imposed)' beside a run none of
    # whose 12,770 steps could impose it, its alpha history all NaN)
    substeps = run_file.substep_stats()
    unimposed = substeps.get("unimposed", 0) if conserve and run_file.steps_done else 0
    imposed_tag = ("  (imposed, but no step could: see the note below)" if unimposed >= run_file.steps_done > 0
                   else f"  (imposed; {unimposed:,} of {run_file.steps_done:,} steps could not: see below)" if unimposed
                   else "  (imposed)")
    for name, value in drift.items():
        tag = imposed_tag if name in conserve else (kept_H if name == "H" else "")
        first = initial.get(name, math.nan)
        relative = ""
        if math.isfinite(first):
            reference, kind = relative_reference(first, scales.get(name, 0.0))
            relative = {"I(t0)": f"relative {value / reference:.3e}",
                        "terms": f"relative {value / reference:.3e} to the size of its terms ("
                                 + ("I(t0) = 0)" if first == 0.0 else f"I(t0) = {first:.1e}, a cancellation)"),
                        "absolute": "(absolute: I(t0) = 0)"}[kind]
        rows.append(f"  {name:<{width}}  {value:.3e}  {relative}{tag}".rstrip())

    solver = (config_of(run_file).get("solver") or {})
    stats = run_file.iteration_stats()
    if stats.get("count"):
        every = a.get("stats_iterations")
        # An adaptive run's total counts every solve (rejected steps', side steps'), as its grad H count and
        # the sweep table do; the per-step figures are the accepted steps' (a user trial read two totals)
        whole = (f"; all solves, rejected and side steps too: {int(every):,}"
                 if every is not None and int(every) != stats["total"] else "")
        row("iterations", f"{'of the accepted steps: ' if whole else ''}mean {stats['mean']:.2f}, median "
                          f"{stats['median']}, 99% <= {stats['p99']}, min {stats['min']}, max {stats['max']}, "
                          f"total {stats['total']:,}{whole}")
        max_iter = solver.get("max_iter")
        if isinstance(max_iter, int) and stats["max"] > max_iter:
            # max_iter bounds one solve; a step's count is every solve it took
            row("", "a step counts every solve it took (max_iter bounds one): a solve that fails is tried again "
                    "from another start or with a fresh Newton matrix before the step is split")
    else:
        row("iterations", "no steps yet")
    if "failed_step_iterations" in a:
        row("", f"the failed step used {a['failed_step_iterations']} iterations")
    if solver:
        # A file written before a setting existed ran without it (no predictor, no acceleration).
        row("solver", f"{solver.get('method', 'fixed_point')}, max_iter {solver.get('max_iter')}, "
                      f"max_halvings {solver.get('max_halvings', 0)}, predictor {solver.get('predictor', False)}, "
                      f"accelerate {solver.get('accelerate', False)}"
                      + (" (simplified Newton's only)" if solver.get("method") == "fixed_point"
                         and solver.get("accelerate") else "")
                      + (f", lim_metric {solver['lim_metric']}" if solver.get("lim_metric", "euclidean") != "euclidean"
                         else "")
                      + (", kernel per_problem" if solver.get("kernel") == "per_problem" else "")
                      + (", project_energy true" if solver.get("project_energy") else ""))
    row("split steps", f"{substeps['split']:,}" + (f" (at most {substeps['max']} substeps in one step; a step the "
                                                   "solver could not converge is split in halves)"
                                                   if substeps["split"] else ""))
    if substeps.get("unimposed"):
        row("", unimposed_text(substeps["unimposed"], run_file.steps_done, run_file.adaptive, _literal_sum(run_file)))
    warning = energy_note(run_file, samples_drift)
    if warning:
        row("note", warning)
    labels = run_file.multiplier_labels()
    maxima = run_file.max_abs_multipliers()
    if run_file.multiplier_name is None:
        row("max |alpha|", f"none: {a.get('method')} imposes no invariant")
    else:
        symbol = run_file.multiplier_name
        text = ", ".join((f"{v:.3e}" if v == v else "none (no step imposed it)")   # NaN: every step unimposed
                         + f" ({label.split('[', 1)[1].rstrip(']')})" for v, label in zip(maxima, labels))
        row(f"max |{symbol}|", text if done else "no steps yet")
        spikes = run_file.alpha_spikes()
        if spikes:
            from elimfast.integrate import alpha_spike_note
            row("", alpha_spike_note(spikes, run_file.steps_done))
    if integrity is not None:
        checked = (f"{integrity['chunks']} data chunks read back, fletcher32 checksums verified"
                   if integrity["checksummed"] else
                   f"{integrity['chunks']} data chunks read back (a format 1 file: its data carry no checksums)")
        row("integrity", checked)
    if run_file.state_damage:
        row("saved state", run_file.state_damage)
    return "\n".join(rows)


def _terminal_event_time(run_file) -> float | None:
    """The time a terminal event ended a complete run with events before its t_end (docs/adaptive.md),
    else None."""
    if str(run_file.status) != "complete" or not run_file.event_names():
        return None
    clock = run_file.saved_state().get("clock")
    t_end = run_file.attrs.get("t_end")
    t_final = float(np.asarray(clock).ravel()[0]) if clock is not None else None
    if t_final is not None and t_end is not None and t_final < float(t_end):
        return t_final
    return None


def ensemble_summary(ensemble_file) -> str:
    """The inspect summary of an open EnsembleFile (io/ensemblefile.py): what it holds, how
    far it got and, over the stored trajectories, failures, invariant errors and iterations.
    Columns are read a block of rows at a time, so memory stays bounded for any size."""
    from elimfast.ensemble import STATUS_NAMES
    from elimfast.kernels.codes import STATUS_OK

    a, root = ensemble_file.attrs, ensemble_file.root_attrs
    path, n = ensemble_file.path, ensemble_file.n_trajectories
    rows = []

    def row(key, value):
        rows.append(f"{key:<13}{value}")

    row("file", f"{path}" + (_swmr_note(path, ensemble_file.status) if ensemble_file.swmr else ""))
    row("sweep", f"{root.get('source', '?')} (an ensemble)")
    row("problem", _problem_text(ensemble_file))
    conserve = [name for name in (a.get("conserve") or []) if name]
    row("method", f"{a.get('method')}" + (f", imposing {', '.join(conserve)}" if conserve else ""))
    row("h", f"{a.get('h')!r}  ({a.get('n_steps')} steps a trajectory)")
    stored = ensemble_file.stored
    row("trajectories", f"{stored:,} of {n:,} stored" + (f"  ({100.0 * stored / n:.1f}%)" if stored < n else ""))
    status = ensemble_file.status
    resume = f"elimfast sweep {root.get('source', 'SWEEP.yaml')} -o {path} --resume"
    if status == "incomplete":
        status = (f"incomplete (the sweep stopped or was killed before every block was stored; complete it with "
                  f"{resume})")
    elif status == "running":
        status = "running (another process is writing it)"
    row("status", status)
    counts = np.zeros(max(STATUS_NAMES) + 1, dtype=np.int64)
    drift = {name: 0.0 for name in ensemble_file.invariant_names}
    iterations, completed = 0, 0
    split = {"split_steps": [0, 0], "unimposed_steps": [0, 0]}   # trajectories with some, steps in all
    for start, stop in ensemble_file.blocks():
        kept = ensemble_file.stored_mask(start, stop)
        codes = ensemble_file.column("status", start, stop)[kept]
        counts += np.bincount(np.clip(codes, 0, counts.size - 1), minlength=counts.size)
        ok = np.zeros(stop - start, dtype=bool)
        ok[kept] = codes == STATUS_OK
        completed += int(ok.sum())
        iterations += int(ensemble_file.column("iterations", start, stop)[ok].sum())
        for name, (having, total) in split.items():
            if ensemble_file.has(name):
                values = ensemble_file.column(name, start, stop)[ok]
                split[name] = [having + int((values > 0).sum()), total + int(values[values > 0].sum())]
        for name in drift:
            values = ensemble_file.column(f"invariant_errors/{name}", start, stop)[ok]
            if values.size:
                drift[name] = max(drift[name], float(values.max()))
    failed = stored - int(counts[STATUS_OK])
    reasons = ", ".join(f"{int(count):,} {STATUS_NAMES[code]}" for code, count in enumerate(counts)
                        if count and code != STATUS_OK and code in STATUS_NAMES)
    row("failed", f"{failed:,} of the {stored:,} stored" + (f" ({reasons})" if reasons else ""))
    if completed:
        rows.append(f"invariants   max |I(t) - I(0)| over the {completed:,} stored trajectories that completed")
        width = max(len(name) for name in drift)
        for name, value in drift.items():
            tag = "  (imposed)" if name in conserve else ""
            rows.append(f"  {name:<{width}}  {value:.3e}{tag}")
        row("iterations", f"mean {iterations / completed:,.1f} a completed trajectory, total {iterations:,}")
        having, total = split["split_steps"]
        if having:
            row("split steps", f"{total:,} in {having:,} of the {completed:,} trajectories (steps the solver could not "
                               "converge whole were split into substeps; every invariant is kept there too)")
        having, total = split["unimposed_steps"]
        if having:
            row("unimposed", f"{total:,} steps in {having:,} of the {completed:,} trajectories were taken without "
                             "imposing the invariants (imposing failed; each such step kept them to round-off, at "
                             "several times a step's cost; docs/solver.md#a-substep-without-imposing)")
    if "threads" in a:
        row("threads", str(a["threads"]))
    row("created", f"{root.get('created')} with elimfast {root.get('elimfast_version')}, numba "
                   f"{root.get('numba_version')}, numpy {root.get('numpy_version')}, h5py {root.get('h5py_version')}")
    return "\n".join(rows)


def sweep_summary(path, attrs: dict, runs: list[tuple[str, bool, str]]) -> str:
    """The inspect summary of a grid sweep's file (io/sweepfile.grid_sweep_runs gives attrs and
    runs): what it holds, whether it is complete (else how to complete it), and a row per
    stored run: status, steps, iterations per step, the largest relative invariant error (H's
    and every invariant's, as inspect of one run computes them) and the wall time."""
    from elimfast.errors import ElimfastError
    from elimfast.io.hdf5 import RunFile
    from elimfast.sweep import format_table

    lines = []

    def row(key, value):
        lines.append(f"{key:<12} {value}")

    planned = int(attrs.get("runs_planned", 0) or 0)
    stored = [(label, status) for label, done, status in runs if done]
    source = str(attrs.get("source", "")) or "SWEEP.yaml"
    axes = [axis for axis in (attrs.get("axes") or []) if axis]
    row("file", str(path))
    row("sweep", source + (f", axes {', '.join(axes)}" if axes else ""))
    table, failed, wall = [], 0, 0.0
    for label, stored_status in stored:
        try:
            run_file = RunFile(f"{path}:/runs/{label}")
        except ElimfastError:   # a run that failed before it stored any data (a bad config value, say)
            failed += 1
            table.append([label, _clipped(stored_status), "-", "-", "-", "-"])
            continue
        with run_file:
            a = run_file.attrs
            status = str(a.get("status", "?"))
            worst, worst_name = -1.0, ""
            for name, value in relative_drift(run_file).items():
                if math.isfinite(value) and value > worst:
                    worst, worst_name = value, name
            stats = run_file.iteration_stats()
            steps = int(a.get("steps_done", 0))
            mean = f"{stats['total'] / stats['count']:.2f}" if stats.get("count") else "-"
            seconds = float(a.get("wall_time_s", 0.0) or 0.0)
        failed += not status.startswith("complete")
        wall += seconds
        table.append([label, _clipped(status), f"{steps:,}", mean,
                      f"{worst:.2e} ({worst_name})" if worst >= 0 else "-", _fmt_time(seconds)])
    count = f"{len(stored)} of {planned}" if planned else f"{len(stored)}"
    row("runs", f"{count} stored" + (f", {failed} failed" if failed else ", none failed" if stored else ""))
    if attrs.get("interrupted") or (planned and len(stored) < planned):
        state = "interrupted (its writer was killed)" if attrs.get("interrupted") else "incomplete"
        # other HDF5 tools (h5py, h5netcdf) refuse a killed writer's file until it is repaired (a user trial)
        repair = (f"; other HDF5 tools open it after elimfast repair {shlex.quote(str(path))}"
                  if attrs.get("interrupted") else "")
        row("status", f"{state}: complete it with elimfast sweep {shlex.quote(source)} -o "
                      f"{shlex.quote(str(path))} --resume{repair}")
    row("wall time", f"{_fmt_time(wall)} in all (the runs' own, summed)")
    lines.append("")
    header = ["run", "status", "steps", "iterations/step", "max relative invariant error", "wall time"]
    lines.append(format_table(header, table, "markdown").rstrip("\n"))
    complete = [label for label, status in stored if status.startswith("complete")] or [label for label, _ in stored]
    example = shlex.quote(f"{path}:/runs/{complete[0] if complete else '<label>'}")
    lines.append("")
    lines.append(f"One run in full: elimfast inspect {example}; the sweep's table (errors, orders), from the "
                 f"stored runs: elimfast sweep {shlex.quote(source)} -o {shlex.quote(str(path))} --resume; "
                 f"in xarray: elimfast.open_datatree({str(path)!r})")
    return "\n".join(lines)


def _clipped(status: str, width: int = 40) -> str:
    return status if len(status) <= width else status[:width - 3] + "..."
