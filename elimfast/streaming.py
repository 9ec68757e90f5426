"""The chunked run driver: Integration -> kernel chunks -> HDF5, with progress, signals and resume.

A run proceeds in chunks: one kernel call (``Integration.advance``) per chunk, then
the chunk is appended to the file and flushed, then /state is written and flushed.
Chunks are sized from the measured speed to take about ``TARGET_CHUNK_SECONDS`` and
never to need more than ``MAX_CHUNK_BYTES`` of output arrays, so memory stays bounded
whatever the run's length. (The first chunk is two kernel calls: a probe of
``FIRST_CHUNK_STEPS`` steps that measures the speed, then the rest of the chunk.)
Chunk boundaries do not change the numbers: the kernel continues a run exactly across
calls, so a run resumed from /state ends bit for bit where an uninterrupted one ends.

SIGINT and SIGTERM set a flag and the run stops at the next chunk boundary with status
'interrupted'. Python runs signal handlers between bytecodes, so a signal that arrives
during a kernel call is seen when the call returns: a chunk is never cut.
"""
from __future__ import annotations

import math
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from .io import hdf5
from .io.hdf5 import FAILED_PREFIX, STATUS_COMPLETE, STATUS_INTERRUPTED, OutputError

# Tunables of the driver (all in one place).
TARGET_CHUNK_SECONDS = 0.5     # kernel time per chunk: progress and Ctrl-C latency vs flush overhead
MAX_CHUNK_BYTES = 32 << 20     # output arrays of one chunk
FIRST_CHUNK_STEPS = 64         # the first chunk measures the speed
MAX_GROWTH = 256               # chunk size grows at most this factor per chunk
ABSORB_FRACTION = 0.5          # a remainder up to this fraction of a chunk joins it (no tiny last chunk)
PLAIN_PROGRESS_SECONDS = 5.0   # interval of the progress lines when stderr is not a terminal

EXIT_OK, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 130


@dataclass
class Outcome:
    """How a run ended: status as stored in the file, counts and times."""

    status: str
    path: Path
    steps_done: int
    n_steps: int
    wall_time_s: float            # this session plus earlier ones (resume)
    kernel_time_s: float          # idem
    session_wall_s: float = 0.0   # this session only
    session_kernel_s: float = 0.0
    session_write_s: float = 0.0   # appends, flushes and the final close
    session_open_s: float = 0.0    # creating (or reopening) the file
    session_steps: int = 0
    chunks: int = 0
    t: float = math.nan
    signal_name: str | None = None
    note: str = ""

    @property
    def exit_code(self) -> int:
        if self.status == STATUS_COMPLETE:
            return EXIT_OK
        if self.status == STATUS_INTERRUPTED:
            return EXIT_INTERRUPTED
        return EXIT_FAILED


# --- signals ------------------------------------------------------------------------------
class StopOnSignals:
    """Context manager: SIGINT/SIGTERM set ``.signal`` instead of raising (main thread only)."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self, enabled: bool = True):
        self.enabled = enabled and threading.current_thread() is threading.main_thread()
        self.signal: int | None = None
        self._previous = {}

    def _handler(self, signum, frame):
        self.signal = signum

    def __enter__(self):
        if self.enabled:
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    @property
    def requested(self) -> bool:
        return self.signal is not None

    @property
    def name(self) -> str | None:
        return signal.Signals(self.signal).name if self.signal is not None else None


# --- progress -----------------------------------------------------------------------------
class NoProgress:
    def start(self, steps_done: int, n_steps: int, label: str) -> None:
        pass

    def update(self, steps_done: int, t: float) -> None:
        pass

    def close(self) -> None:
        pass


class LineProgress(NoProgress):
    """A plain line every few seconds (stderr is a file or a pipe)."""

    def __init__(self, stream=None, interval: float = PLAIN_PROGRESS_SECONDS):
        self.stream = stream if stream is not None else sys.stderr
        self.interval = interval

    def start(self, steps_done, n_steps, label):
        self.n_steps, self.label = n_steps, label
        self.start_steps, self.start_time = steps_done, time.perf_counter()
        self.last = self.start_time

    def update(self, steps_done, t):
        now = time.perf_counter()
        if now - self.last < self.interval or steps_done >= self.n_steps:
            return
        self.last = now
        rate = (steps_done - self.start_steps) / max(now - self.start_time, 1e-9)
        eta = (self.n_steps - steps_done) / rate if rate > 0 else math.inf
        print(f"elimfast: {self.label}: step {steps_done}/{self.n_steps} ({100.0 * steps_done / self.n_steps:.1f}%), "
              f"t = {t:.6g}, {rate:,.0f} steps/s, ETA {_duration(eta)}", file=self.stream, flush=True)


class BarProgress(NoProgress):
    """A tqdm bar with steps/s and ETA (stderr is a terminal)."""

    def __init__(self, stream=None):
        self.stream = stream if stream is not None else sys.stderr
        self.bar = None

    def start(self, steps_done, n_steps, label):
        from tqdm import tqdm
        self.bar = tqdm(total=n_steps, initial=steps_done, unit="step", unit_scale=True, desc=label,
                        file=self.stream, dynamic_ncols=True, smoothing=0.3, leave=True)
        self.done = steps_done

    def update(self, steps_done, t):
        self.bar.set_postfix_str(f"t={t:.6g}", refresh=False)
        self.bar.update(steps_done - self.done)
        self.done = steps_done

    def close(self):
        if self.bar is not None:
            self.bar.close()


def progress_for(quiet: bool, stream=None) -> NoProgress:
    """Nothing when quiet, a bar on a terminal, plain lines otherwise."""
    stream = stream if stream is not None else sys.stderr
    if quiet:
        return NoProgress()
    isatty = getattr(stream, "isatty", None)
    return BarProgress(stream) if isatty is not None and isatty() else LineProgress(stream)


def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}"


# --- the loop -----------------------------------------------------------------------------
def bytes_per_step(integration) -> float:
    """Output bytes one step needs in a chunk: per-step data plus its share of a sample."""
    n_inv = len(integration.problem.invariant_names)
    sample = 8 * (1 + integration.y.size + 1 + n_inv)
    return 8 + 8 * integration.multipliers.size + sample / integration.store_every


def next_chunk_steps(previous_steps: int, previous_seconds: float, step_bytes: float,
                     target_seconds: float = TARGET_CHUNK_SECONDS, max_bytes: int = MAX_CHUNK_BYTES,
                     remaining: int | None = None) -> int:
    """Steps for the next chunk: about target_seconds of kernel time, bounded growth and memory."""
    cap = max(1, int(max_bytes // max(step_bytes, 1.0)))
    if previous_seconds > 0:
        ideal = previous_steps * target_seconds / previous_seconds
    else:
        ideal = previous_steps * MAX_GROWTH
    steps = int(min(max(ideal, 1), previous_steps * MAX_GROWTH))
    steps = max(1, min(steps, cap))
    if remaining is not None and remaining <= steps * (1.0 + ABSORB_FRACTION):
        steps = min(max(steps, remaining), cap)
    return steps


def drive(integration, writer: hdf5.RunWriter, *, progress: NoProgress | None = None,
          stop: StopOnSignals | None = None, wall_offset: float = 0.0, kernel_offset: float = 0.0,
          target_seconds: float = TARGET_CHUNK_SECONDS, max_chunk_bytes: int = MAX_CHUNK_BYTES,
          first_chunk_steps: int = FIRST_CHUNK_STEPS, label: str = "") -> Outcome:
    """Advance ``integration`` chunk by chunk into ``writer`` until done, failed or stopped.

    The writer is finished (status written, file closed) on every way out but an
    exception, where it is closed with status 'running' (resumable).
    """
    progress = progress or NoProgress()
    started = time.perf_counter()
    kernel_s = write_s = 0.0
    chunks = 0
    start_steps = integration.steps_done
    step_bytes = bytes_per_step(integration)
    steps = max(1, min(first_chunk_steps, int(max_chunk_bytes // step_bytes) or 1))
    probing = True   # the first kernel call only measures the speed: its data join the first chunk's flush
    progress.start(integration.steps_done, integration.n_steps, label)
    try:
        while not integration.finished and not (stop is not None and stop.requested):
            tick = time.perf_counter()
            chunk = integration.advance(steps)
            tock = time.perf_counter()
            kernel_s += tock - tick
            writer.append(chunk)
            steps = next_chunk_steps(len(chunk.iterations) or steps, tock - tick, step_bytes,
                                     target_seconds, max_chunk_bytes,
                                     remaining=integration.n_steps - integration.steps_done)
            if probing and not integration.finished:
                probing = False
                write_s += time.perf_counter() - tock
                continue
            probing = False
            writer.save_state(integration.state(), wall_time_s=wall_offset + time.perf_counter() - started,
                              kernel_time_s=kernel_offset + kernel_s)
            write_s += time.perf_counter() - tock
            chunks += 1
            progress.update(integration.steps_done, integration.t)
        if not probing and chunks == 0 and integration.steps_done > start_steps:
            # stopped right after the probe: its data need their flush and state too
            tock = time.perf_counter()
            writer.save_state(integration.state(), wall_time_s=wall_offset + tock - started,
                              kernel_time_s=kernel_offset + kernel_s)
            write_s += time.perf_counter() - tock
            chunks = 1
    except BaseException:
        progress.close()
        writer.close()
        raise
    progress.close()
    if integration.status != 0:
        status = FAILED_PREFIX + integration.failure_message()
    elif integration.steps_done >= integration.n_steps:
        status = STATUS_COMPLETE
    else:
        status = STATUS_INTERRUPTED
    tock = time.perf_counter()
    wall = wall_offset + tock - started
    writer.finish(status, steps_done=integration.steps_done, wall_time_s=wall, kernel_time_s=kernel_offset + kernel_s)
    write_s += time.perf_counter() - tock
    return Outcome(status=status, path=writer.path, steps_done=integration.steps_done, n_steps=integration.n_steps,
                   wall_time_s=wall, kernel_time_s=kernel_offset + kernel_s,
                   session_wall_s=time.perf_counter() - started, session_kernel_s=kernel_s,
                   session_write_s=write_s, session_steps=integration.steps_done - start_steps, chunks=chunks,
                   t=integration.t, signal_name=stop.name if stop is not None else None)


def config_difference(stored: str, current: str) -> str | None:
    """The first key where two resolved YAML configs differ (output.path ignored), or None."""
    import yaml
    try:
        old, new = yaml.safe_load(stored) or {}, yaml.safe_load(current) or {}
    except yaml.YAMLError:
        return "config (the stored one is not readable YAML)"
    for tree in (old, new):
        if isinstance(tree, dict) and isinstance(tree.get("output"), dict):
            tree["output"].pop("path", None)

    def first_difference(a, b, prefix=""):
        if isinstance(a, dict) and isinstance(b, dict):
            for key in sorted(set(a) | set(b), key=str):
                found = first_difference(a.get(key), b.get(key), f"{prefix}{key}.")
                if found:
                    return found
            return None
        return None if a == b else prefix.rstrip(".") or "config"

    return first_difference(old, new)


def run_to_file(integration, path, *, config_text: str, t_end: float | None = None, overwrite: bool = False,
                resume: bool = False, progress: NoProgress | None = None, handle_signals: bool = True,
                label: str = "", **drive_options) -> Outcome:
    """Run ``integration`` into the HDF5 file ``path`` (new, overwritten, or resumed).

    resume: continue the run stored in ``path`` (which must come from the same resolved
    config, output path aside); a missing file starts a new run. A complete run is left
    as it is; a failed one is refused (it would fail again). Raises OutputError for
    file problems, before any step is computed.
    """
    path = Path(path)
    if overwrite and resume:
        raise OutputError("--overwrite and --resume contradict each other: give one")
    hdf5.check_output_path(path, overwrite=overwrite, resume=resume)
    wall_offset = kernel_offset = 0.0
    note = ""
    with StopOnSignals(handle_signals) as stop:
        if resume and path.exists():
            with hdf5.RunFile(path) as existing:
                status, attrs = existing.status, existing.attrs
                steps_done = existing.steps_done
            difference = config_difference(str(attrs.get("config", "")), config_text)
            if difference is not None:
                raise OutputError(f"{path}: was written from a different config (first difference at "
                                  f"'{difference}'); resume with the same config and --set values, or use "
                                  f"--overwrite to start again")
            if status == STATUS_COMPLETE:
                return Outcome(status=STATUS_COMPLETE, path=path, steps_done=steps_done,
                               n_steps=int(attrs["n_steps"]), wall_time_s=float(attrs.get("wall_time_s", 0.0)),
                               kernel_time_s=float(attrs.get("kernel_time_s", 0.0)),
                               note="already complete; nothing to resume")
            if status.startswith(FAILED_PREFIX):
                raise OutputError(f"{path}: the run {status}; resuming would fail the same way: change the "
                                  f"config and start again with --overwrite")
            opening = time.perf_counter()
            writer, saved = hdf5.RunWriter.resume(path)
            try:
                integration.restore(saved)
            except (KeyError, ValueError) as err:
                writer.close()
                raise OutputError(f"{path}: the stored state does not fit this run ({err})") from None
            wall_offset, kernel_offset = float(saved["wall_time_s"]), float(saved["kernel_time_s"])
            note = f"resumed at step {integration.steps_done}"
            started_with = attrs.get("elimfast_version")
            if started_with != hdf5.version_attributes()["elimfast_version"]:
                note += (f"; the run was started by elimfast {started_with}: a continuation by another version "
                         "is not guaranteed to be bit for bit")
        else:
            opening = time.perf_counter()
            writer = hdf5.RunWriter.create(path, integration, config_text=config_text, t_end=t_end)
            if resume:
                note = "no file to resume: started a new run"
        open_s = time.perf_counter() - opening
        outcome = drive(integration, writer, progress=progress, stop=stop, wall_offset=wall_offset,
                        kernel_offset=kernel_offset, label=label, **drive_options)
    outcome.note = note
    outcome.session_open_s = open_s
    return outcome


__all__ = ["Outcome", "StopOnSignals", "drive", "run_to_file", "progress_for", "next_chunk_steps",
           "config_difference", "OutputError"]
