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
during a kernel call is seen when the call returns: a chunk is never cut. A kernel call
that does not return within ``HARD_STOP_GRACE_SECONDS`` of the signal ends the process
as ``kill -9`` would, after the last flushed chunk (``StopOnSignals``).

A run can also stop short with status 'stopped: <reason>' (exit code 1; the file is
closed at the last saved chunk and can be resumed): when the disk has no room for the
next chunk (its space is reserved before the kernel call), and when a problem function
raises inside the kernel. If HDF5 itself fails a write, the file is left as a killed
writer leaves it (consistent up to the last saved chunk, resumable), never closed.
"""
from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import DiskFullError, exact_time
from .integrate import steps_before_raise
from .io import hdf5
from .io.hdf5 import FAILED_PREFIX, STATUS_COMPLETE, STATUS_INTERRUPTED, STOPPED_PREFIX, OutputError
from .io.layout import PROBLEM_FILE_DIGEST, problem_file_attributes, set_overrides_attribute
from .io.safety import no_room

# Tunables of the driver (all in one place).
TARGET_CHUNK_SECONDS = 0.5     # kernel time per chunk: progress and Ctrl-C latency vs flush overhead
MAX_CHUNK_BYTES = 32 << 20     # output arrays of one chunk
FIRST_CHUNK_STEPS = 64         # the first chunk measures the speed
MAX_GROWTH = 256               # chunk size grows at most this factor per chunk
ABSORB_FRACTION = 0.5          # a remainder up to this fraction of a chunk joins it (no tiny last chunk)
PLAIN_PROGRESS_SECONDS = 5.0   # interval of the progress lines when stderr is not a terminal
HARD_STOP_GRACE_SECONDS = 1.5  # after Ctrl-C, how long a kernel call may take to return before the exit

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
    message: str = ""             # the one-line report of a run that stopped short ("stopped: ...")

    @property
    def exit_code(self) -> int:
        if self.status == STATUS_COMPLETE:
            return EXIT_OK
        if self.status == STATUS_INTERRUPTED:
            return EXIT_INTERRUPTED
        return EXIT_FAILED


# --- signals ------------------------------------------------------------------------------
class StopOnSignals:
    """Context manager: SIGINT/SIGTERM/SIGHUP set ``.signal`` instead of raising (main thread only).
    SIGHUP is a closed terminal: without it a run ended as after kill -9 (a user trial).

    The driver checks ``requested`` between chunks. A kernel call runs in compiled code
    that Python cannot interrupt, and Python runs signal handlers only between bytecodes,
    so a call that does not return (a step that never converges, a problem function
    that loops) would make the signal wait for ever. Hence a watchdog: the C-level
    signal handler writes the signal number to a pipe (``signal.set_wakeup_fd``), a
    thread reading the pipe sees it while the main thread is inside a kernel call
    (``kernel_call``; the time-loop kernel releases the GIL), waits ``grace`` seconds for
    the call to return, and otherwise prints ``hard_stop(signal_name)`` and ends the
    process with exit code 130 (``os._exit``). Between kernel calls every chunk is
    already flushed, so the file on disk is then exactly as after ``kill -9``: consistent
    and resumable.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(self, enabled: bool = True, grace: float | None = None, hard_stop=None, raising: bool = False):
        self.enabled = enabled and threading.current_thread() is threading.main_thread()
        self.raising = raising         # raise KeyboardInterrupt (sweeps) instead of only recording the signal
        self.signal: int | None = None
        self.grace = HARD_STOP_GRACE_SECONDS if grace is None else float(grace)
        self.hard_stop = hard_stop     # callable(signal_name) -> the one line printed before exiting
        self._previous = {}
        self._previous_wakeup = None
        self._pipe = None
        self._watchdog = None
        self._calls = 0
        self._in_call = 0              # the number of the kernel call running, 0 between calls

    def _handler(self, signum, frame):
        self.signal = signum
        if self.raising:
            raise KeyboardInterrupt

    def __enter__(self):
        global _CURRENT
        if self.enabled:
            for sig in self.SIGNALS:
                self._previous[sig] = signal.signal(sig, self._handler)
            try:
                read_end, write_end = os.pipe()
                os.set_blocking(write_end, False)
                self._previous_wakeup = signal.set_wakeup_fd(write_end, warn_on_full_buffer=False)
            except (OSError, ValueError):
                return self
            self._pipe = (read_end, write_end)
            self._watchdog = threading.Thread(target=self._watch, args=(read_end,), name="elimfast-watchdog",
                                              daemon=True)
            self._watchdog.start()
            self._outer, _CURRENT = _CURRENT, self
        return self

    def __exit__(self, *exc):
        global _CURRENT
        if _CURRENT is self:
            _CURRENT = getattr(self, "_outer", None)
        if self._pipe is not None:
            signal.set_wakeup_fd(self._previous_wakeup if self._previous_wakeup is not None else -1)
            read_end, write_end = self._pipe
            os.close(write_end)        # the watchdog reads end-of-file and returns
            self._watchdog.join(timeout=1.0)
            if not self._watchdog.is_alive():
                os.close(read_end)
            self._pipe = None
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous.clear()

    @contextlib.contextmanager
    def kernel_call(self):
        """Mark a kernel call: a signal that arrives during it is watched (see the class doc)."""
        self._calls += 1
        self._in_call = self._calls
        try:
            yield
        finally:
            self._in_call = 0

    def _watch(self, read_end: int) -> None:
        while True:
            try:
                data = os.read(read_end, 64)
            except OSError:
                return
            if not data:
                return
            for signum in data:
                if signum not in self.SIGNALS:
                    continue
                self.signal = self.signal or signum
                call = self._in_call
                if not call:
                    continue              # between calls: the driver sees the flag at the next boundary
                deadline = time.monotonic() + self.grace
                while self._in_call == call and time.monotonic() < deadline:
                    time.sleep(0.02)
                if self._in_call == call:
                    self._exit_now(signum)

    def _exit_now(self, signum: int) -> None:
        name = signal.Signals(signum).name
        try:
            message = self.hard_stop(name) if self.hard_stop is not None else f"interrupted by {name}"
        except Exception:   # noqa: BLE001 -- the exit must happen whatever the message does
            message = f"interrupted by {name}"
        try:
            sys.stdout.flush()
        except Exception:   # noqa: BLE001
            pass
        try:
            os.write(2, (message + "\n").encode("utf-8", "replace"))
        finally:
            os._exit(EXIT_INTERRUPTED)

    @property
    def requested(self) -> bool:
        return self.signal is not None

    @property
    def name(self) -> str | None:
        return signal.Signals(self.signal).name if self.signal is not None else None


_CURRENT: StopOnSignals | None = None   # the innermost watching StopOnSignals of this process


def current_watchdog() -> StopOnSignals | None:
    """The StopOnSignals watching kernel calls in this process (None: none installed)."""
    return _CURRENT


def kernel_call(stop):
    """``stop.kernel_call()`` when the stop object watches kernel calls, else nothing."""
    watch = getattr(stop, "kernel_call", None)
    return watch() if watch is not None else contextlib.nullcontext()


def interrupted_line(signal_name: str | None, steps_done: int, n_steps: int, t: float, path,
                     resume_command: str | None = None) -> str:
    """The one line that reports an interrupted run and how to continue it."""
    why = f" by {signal_name}" if signal_name else ""
    how = resume_command or "elimfast run CONFIG -o FILE --resume"
    of = f"/{n_steps}" if n_steps is not None else ""   # adaptive steps: no total known
    return (f"interrupted{why} at step {steps_done}{of} (t = {exact_time(t)}); {path} is complete up to there; "
            f"continue with: {how}")


# --- progress -----------------------------------------------------------------------------
class NoProgress:
    """Progress reports: by steps when their number is known, else (adaptive steps) by the
    fraction of [t0, t_end] covered (t_span). silent: the lines said during the run (write) are
    dropped too (`--quiet`: errors only; a user trial saw its mid-run note)."""

    silent = False

    def __init__(self, silent: bool = False):
        self.silent = silent

    def start(self, steps_done: int, n_steps: int | None, label: str, t_span=None) -> None:
        pass

    def update(self, steps_done: int, t: float) -> None:
        pass

    def close(self) -> None:
        pass

    def write(self, line: str, notice) -> None:
        """Say ``line`` through ``notice`` (the caller's: the CLI's 'note: ...' on stderr) in the middle of
        the run; a bar is cleared around it."""
        if not self.silent:
            notice(line)


class LineProgress(NoProgress):
    """A plain line every few seconds (stderr is a file or a pipe)."""

    def __init__(self, stream=None, interval: float = PLAIN_PROGRESS_SECONDS):
        self.stream = stream if stream is not None else sys.stderr
        self.interval = interval

    def start(self, steps_done, n_steps, label, t_span=None):
        self.n_steps, self.label, self.t_span = n_steps, label, t_span
        self.start_steps, self.start_time = steps_done, time.perf_counter()
        self.last = self.start_time
        self.start_t = t_span[0] if t_span else 0.0

    def update(self, steps_done, t):
        now = time.perf_counter()
        if now - self.last < self.interval or (self.n_steps is not None and steps_done >= self.n_steps):
            return
        self.last = now
        if self.n_steps is None:
            t0, t_end = self.t_span if self.t_span else (0.0, math.nan)
            fraction = (t - t0) / (t_end - t0) if t_end != t0 else 1.0
            rate = (steps_done - self.start_steps) / max(now - self.start_time, 1e-9)
            print(f"elimfast: {self.label}: step {steps_done}, t = {t:.6g} of {t_end:.6g} ({100.0 * fraction:.1f}%), "
                  f"{rate:,.0f} steps/s", file=self.stream, flush=True)
            return
        rate = (steps_done - self.start_steps) / max(now - self.start_time, 1e-9)
        eta = (self.n_steps - steps_done) / rate if rate > 0 else math.inf
        print(f"elimfast: {self.label}: step {steps_done}/{self.n_steps} ({100.0 * steps_done / self.n_steps:.1f}%), "
              f"t = {t:.6g}, {rate:,.0f} steps/s, ETA {_duration(eta)}", file=self.stream, flush=True)


class BarProgress(NoProgress):
    """A tqdm bar with steps/s and ETA (stderr is a terminal)."""

    def __init__(self, stream=None):
        self.stream = stream if stream is not None else sys.stderr
        self.bar = None

    def start(self, steps_done, n_steps, label, t_span=None):
        from tqdm import tqdm
        self.by_time = n_steps is None and t_span is not None
        if self.by_time:   # adaptive steps: the bar counts time, not steps
            self.t0, self.t_end = t_span
            self.bar = tqdm(total=float(self.t_end - self.t0), initial=0.0, unit="t", unit_scale=True, desc=label,
                            file=self.stream, dynamic_ncols=True, smoothing=0.3, leave=True)
            self.done = 0.0
        else:
            self.bar = tqdm(total=n_steps, initial=steps_done, unit="step", unit_scale=True, desc=label,
                            file=self.stream, dynamic_ncols=True, smoothing=0.3, leave=True)
            self.done = steps_done

    def update(self, steps_done, t):
        if self.by_time:
            self.bar.set_postfix_str(f"step {steps_done}", refresh=False)
            self.bar.update((t - self.t0) - self.done)
            self.done = t - self.t0
            return
        self.bar.set_postfix_str(f"t={t:.6g}", refresh=False)
        self.bar.update(steps_done - self.done)
        self.done = steps_done

    def close(self):
        if self.bar is not None:
            self.bar.close()

    def write(self, line, notice):
        if self.bar is None:
            notice(line)
            return
        with self.bar.external_write_mode():
            notice(line)


def progress_for(quiet: bool, stream=None) -> NoProgress:
    """Nothing when quiet, a bar on a terminal, plain lines otherwise."""
    stream = stream if stream is not None else sys.stderr
    if quiet:
        return NoProgress(silent=True)
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
LARGE_OUTPUT_BYTES = 1e9   # a run whose file will grow by more is told so before its first step


def output_growth_note(writer, remaining_steps: int | None, step_bytes: float) -> str | None:
    """What a run whose output may grow by more than LARGE_OUTPUT_BYTES says before it starts (a
    user trial's 10^9 steps with output.every 1, about 43 GB, began without a word): the size
    before compression (what each chunk reserves; Kepler's rows compress to about half), what
    makes it, and whether its disk has the room (where it has not, the run stops when the disk
    is full, resumable). None for smaller runs and adaptive ones (steps not known)."""
    if remaining_steps is None or remaining_steps * step_bytes <= LARGE_OUTPUT_BYTES:
        return None
    from .io.safety import _free_bytes, _size
    growth = remaining_steps * step_bytes
    free = _free_bytes(Path(writer.path).parent)
    room = ("" if free is None or free >= growth else
            f"; its disk has {_size(free)} free: if it fills, the run stops there (resume it once there is room)")
    return (f"{writer.path} may grow by up to {_size(growth)}: {remaining_steps:,} steps of up to "
            f"{step_bytes:.0f} bytes each before compression (every step's iterations and multipliers, and the "
            f"samples; raise output.every or shorten the run for less){room}")


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


UNIMPOSED_NOTICE_STEPS = 200


def unimposed_notice(chunk, seen: list, say) -> None:
    """Count a chunk's steps taken without imposing the invariants (their multipliers NaN,
    docs/solver.md#a-substep-without-imposing) into ``seen`` = [unimposed, steps, said]; once
    UNIMPOSED_NOTICE_STEPS steps are seen and most went so, ``say`` it, once. A user trial's
    EHBVM(12,4) imposing the three angular momenta of the solar system took all 40,000 steps so,
    at a fifth of GHBVM's speed, and heard it only at the end (a 100x longer run: after an hour)."""
    multipliers = getattr(chunk, "multipliers", None)
    if multipliers is None or multipliers.ndim != 2 or not multipliers.shape[1]:
        return
    seen[0] += int(np.count_nonzero(np.isnan(multipliers).any(axis=1)))
    seen[1] += multipliers.shape[0]
    if seen[1] >= UNIMPOSED_NOTICE_STEPS and 2 * seen[0] > seen[1]:
        seen[2] = True
        say(f"{seen[0]:,} of the {seen[1]:,} steps taken so far went without imposing the invariants (imposing "
            "failed there; they are kept to round-off, at several times the cost of a step): the run goes on; "
            "imposing fewer or none, or GHBVM/LIM, is faster (docs/solver.md#a-substep-without-imposing)")


def drive(integration, writer: hdf5.RunWriter, *, progress: NoProgress | None = None,
          stop: StopOnSignals | None = None, wall_offset: float = 0.0, kernel_offset: float = 0.0,
          target_seconds: float = TARGET_CHUNK_SECONDS, max_chunk_bytes: int = MAX_CHUNK_BYTES,
          first_chunk_steps: int = FIRST_CHUNK_STEPS, label: str = "", resume_command: str | None = None,
          problem_source: str | None = None, notice: Callable[[str], None] | None = None) -> Outcome:
    """Advance ``integration`` chunk by chunk into ``writer`` until done, failed or stopped.

    The writer is finished (status written, file closed) on every way out but an
    exception, where it is closed with status 'running' (resumable), and a failed HDF5
    write, where it is abandoned (see the module doc). ``problem_source``: the file that
    defines the problem, named when a problem function raises (default: the problem's
    ``source_file``, else its name). ``notice``: called, once, when most of the first
    UNIMPOSED_NOTICE_STEPS steps or more were taken without imposing the invariants
    (unimposed_notice): the run goes on, but its user hears it then, not at the end.
    """
    progress = progress or NoProgress()
    prepare = getattr(integration, "prepare_kernel", None)
    if prepare is not None:
        prepare()   # a per-problem kernel is compiled (or loaded) here, outside the run's wall time and ETA
    started = time.perf_counter()
    kernel_s = write_s = 0.0
    chunks = 0
    start_steps = integration.steps_done
    step_bytes = bytes_per_step(integration)
    steps = max(1, min(first_chunk_steps, int(max_chunk_bytes // step_bytes) or 1))
    if notice is not None:
        growth = output_growth_note(writer, integration.remaining_steps, step_bytes)
        if growth:
            progress.write(growth, notice)
    probing = True   # the first kernel call only measures the speed: its data join the first chunk's flush
    stopped = None   # (status reason, message) when the run stops short
    unimposed = [0, 0, notice is None]   # steps taken without imposing, steps seen, said
    progress.start(integration.steps_done, integration.n_steps, label,
                   t_span=(integration.t0, getattr(integration, "t_end", math.nan)))
    try:
        while not integration.finished and not (stop is not None and stop.requested):
            remaining = integration.remaining_steps
            fitting = writer.fit_steps(steps if remaining is None else min(steps, remaining), step_bytes)
            if fitting < 1:
                stopped = _disk_full(writer, resume_command)
                break
            before = integration.steps_done
            before_state = integration.state()   # copies: the steps before a raise are taken again from it
            tick = time.perf_counter()
            try:
                with kernel_call(stop):
                    chunk = integration.advance(fitting)
            except Exception as err:   # noqa: BLE001 -- a problem function raised inside the kernel
                raised_at, t_raised = steps_before_raise(integration), integration.t
                kernel_s += time.perf_counter() - tick
                if raised_at > 0:
                    _save_steps_before_raise(integration, before_state, raised_at, writer, stop,
                                             wall_offset + time.perf_counter() - started, kernel_offset + kernel_s)
                stopped = _problem_raised(integration, before + raised_at + 1, t_raised, err, writer,
                                          resume_command, problem_source)
                break
            tock = time.perf_counter()
            kernel_s += tock - tick
            if not unimposed[2]:
                unimposed_notice(chunk, unimposed, lambda line: progress.write(line, notice))
            try:
                writer.append(chunk)
                steps = next_chunk_steps(len(chunk.iterations) or fitting, tock - tick, step_bytes,
                                         target_seconds, max_chunk_bytes,
                                         remaining=integration.remaining_steps)
                if probing and not integration.finished:
                    probing = False
                    write_s += time.perf_counter() - tock
                    continue
                probing = False
                writer.save_state(integration.state(), wall_time_s=wall_offset + time.perf_counter() - started,
                                  kernel_time_s=kernel_offset + kernel_s)
            except (OSError, RuntimeError) as err:
                writer.abandon()
                stopped = _write_failed(writer, err, resume_command)
                break
            write_s += time.perf_counter() - tock
            chunks += 1
            progress.update(integration.steps_done, integration.t)
        if stopped is None and not probing and chunks == 0 and integration.steps_done > start_steps:
            # stopped right after the probe: its data need their flush and state too
            tock = time.perf_counter()
            try:
                writer.save_state(integration.state(), wall_time_s=wall_offset + tock - started,
                                  kernel_time_s=kernel_offset + kernel_s)
            except (OSError, RuntimeError) as err:
                writer.abandon()
                stopped = _write_failed(writer, err, resume_command)
            write_s += time.perf_counter() - tock
            chunks = 1
    except BaseException:
        progress.close()
        writer.close()
        raise
    progress.close()
    if stopped is not None:
        status = STOPPED_PREFIX + stopped[0]
    elif integration.status != 0:
        status = FAILED_PREFIX + integration.failure_message(run_file=True)
    elif integration.complete:
        status = STATUS_COMPLETE
    else:
        status = STATUS_INTERRUPTED
    tock = time.perf_counter()
    wall = wall_offset + tock - started
    steps_done = writer.saved["steps_done"] if stopped is not None else integration.steps_done
    if not writer.abandoned:
        try:
            writer.finish(status, steps_done=steps_done, wall_time_s=wall, kernel_time_s=kernel_offset + kernel_s,
                          stats=saved_stats(integration, writer),
                          events_not_finite=getattr(integration, "events_not_finite", None))
        except (OSError, RuntimeError) as err:   # DiskFullError included: leave it as a killed writer would
            writer.abandon()
            if stopped is None:
                stopped = _write_failed(writer, err, resume_command)
                status = STOPPED_PREFIX + stopped[0]
                steps_done = writer.saved["steps_done"]
    write_s += time.perf_counter() - tock
    return Outcome(status=status, path=writer.path, steps_done=steps_done, n_steps=integration.n_steps,
                   wall_time_s=wall, kernel_time_s=kernel_offset + kernel_s,
                   session_wall_s=time.perf_counter() - started, session_kernel_s=kernel_s,
                   session_write_s=write_s, session_steps=steps_done - start_steps, chunks=chunks,
                   t=writer.saved["t"] if stopped is not None else integration.t,
                   signal_name=stop.name if stop is not None else None,
                   message=stopped[1] if stopped is not None else "")


def _continue_with(resume_command: str | None) -> str:
    return resume_command or "elimfast run CONFIG -o FILE --resume"


def _disk_full(writer, resume_command, room=None) -> tuple[str, str]:
    """A run stopped for lack of room: ``room`` (safety.NoRoom) or what fit_steps found."""
    room = room or writer.no_room or no_room(DiskFullError())
    done = writer.saved["steps_done"]
    return (f"{room.short} at step {done + 1}",
            f"{room.short} at step {done + 1}; the {done} steps before it are in {writer.path}; {room.fix}, "
            f"then continue with: {_continue_with(resume_command)}")


def _write_failed(writer, err, resume_command) -> tuple[str, str]:
    room = no_room(err)
    if room is not None:
        return _disk_full(writer, resume_command, room)
    done = writer.saved["steps_done"]
    detail = writer.describe(err)
    if len(detail) > 200:
        detail = detail[:197] + "..."
    return (f"write failed at step {done + 1}",
            f"cannot write {writer.path} at step {done + 1} ({type(err).__name__}: {detail}); the {done} steps "
            f"before it are in the file; check the disk, then continue with: {_continue_with(resume_command)}")


def saved_stats(integration, writer) -> dict | None:
    """Result.stats of what the file holds (the writer's last saved state, which a run stopped
    short is cut back to), or None for a run without counters (the fixed-step kernel)."""
    counters = writer.saved.get("counters")
    if counters is None or not getattr(integration, "adaptive_kernel", False):
        return None
    return integration.stats(counters)


def _save_steps_before_raise(integration, before_state: dict, n: int, writer, stop, wall_s: float,
                             kernel_s: float) -> None:
    """Keep the n steps a raising kernel call completed: its output buffers died with the
    exception, and the state arrays hold the raising step's iterate, so the call is taken
    again from the state before it, for those n steps only (the same steps, bit for bit:
    a kernel call is deterministic, as resume relies on), then written and saved as a
    chunk is. Where that raises too (an invariant raising on the last sample), or the
    writing fails, the file keeps what it had and the state is put back."""
    integration.restore(before_state)
    try:
        with kernel_call(stop):
            chunk = integration.advance(n)
        if integration.steps_done != before_state["steps_done"] + n or integration.status != 0:
            raise RuntimeError("the steps before the raise came out otherwise")
        writer.append(chunk)
        writer.save_state(integration.state(), wall_time_s=wall_s, kernel_time_s=kernel_s)
    except Exception:   # noqa: BLE001 -- best effort: the run stops with the problem's own error either way
        integration.restore(before_state)


def _problem_raised(integration, step: int, t: float, err: BaseException, writer, resume_command,
                    problem_source=None) -> tuple[str, str]:
    """A problem function raised inside the kernel, in step ``step`` from time t: name the
    user's file, the step and the time."""
    problem = integration.problem
    source = getattr(problem, "source_file", None) or problem_source
    where = f"{source}" if source else f"problem {problem.name!r}"
    text = " ".join(str(err).split()) or "(no message)"
    if len(text) > 200:
        text = text[:197] + "..."
    what = f"{type(err).__name__}: {text}"
    done = writer.saved["steps_done"]
    return (f"the problem raised {what} at step {step} (t = {exact_time(t)})",
            f"{where}: a problem function raised {what} at step {step} (t = {exact_time(t)}); {writer.path} holds "
            f"the {done} steps saved before it; fix the problem, then continue with: "
            f"{_continue_with(resume_command)}")


# Config sections that only decide how a step is solved, not which steps are taken: a
# run may be resumed with other values there (a failed run with more halvings, say).
SOLVER_SECTIONS = ("solver",)
# Keys that may grow on --resume: a run continued to a later end (run_extension; README, "Ctrl-C").
EXTENSION_KEYS = ("integration.t_end", "integration.n_steps", "output.times")
# Keys that decide only what is checked when the problem loads (grad L . J grad H = 0), never a step.
LOAD_ONLY_KEYS = ("problem.check",)


# solver.* keys that change the steps themselves, not only how each step's system is solved
# (with their defaults, for configs stored before the key existed): --resume may not change them.
STEP_SOLVER_KEYS = {"solver.lim_metric": "euclidean", "solver.project_energy": False}
# what each of them changes, for the refusal
STEP_SOLVER_EFFECTS = {"solver.lim_metric": "LIM's correction, docs/methods.md#the-metric-of-the-correction",
                       "solver.project_energy": "every state is projected onto H(y0), "
                                                "docs/methods.md#energy-projection"}


def step_solver_change(stored: str, current: str) -> str | None:
    """The first STEP_SOLVER_KEYS key whose value differs between two resolved configs, or None."""
    old, new = _parsed(stored, current)
    for key, default in STEP_SOLVER_KEYS.items():
        section, _, name = key.partition(".")
        values = [tree.get(section, {}).get(name, default)
                  if isinstance(tree, dict) and isinstance(tree.get(section, {}), dict) else default
                  for tree in (old, new)]
        if values[0] != values[1]:
            return key
    return None


def step_solver_refusal(path, key: str) -> OutputError:
    return OutputError(f"{path}: {key} changes the steps themselves ({STEP_SOLVER_EFFECTS[key]}), not only how "
                       "each is solved, so --resume may not change it: start a new run (-o NEW.h5), or replace this "
                       "one with --overwrite")


def resume_refusal(path, key: str, prefix: str = "", configs=(), origins=None) -> OutputError:
    """The refusal of a --resume that would change ``key``, a key outside SOLVER_SECTIONS;
    ``configs``: the stored config and the new one, as far as known (parsed YAML), which tell
    a terminal event from one that is not (``change_effect``). ``origins``: {dotted key: where
    its change comes from, as the message says it ("value from --set integration.rtol=1e-12",
    "in run.yaml"), or None}, the keys the user changed first (run_to_file names the first
    that differs)."""
    origins = origins or {}
    origin = origins[key] if key in origins else next(
        (where for changed, where in origins.items() if where and keys_overlap(key, changed)), None)
    label = f"{key} ({origin})" if origin else key
    return OutputError(f"{path}: {prefix}only {'/'.join(s + '.*' for s in SOLVER_SECTIONS)} may change on --resume; "
                       f"{change_effect(key, configs, label)}: start a new run (-o NEW.h5), or replace this one with "
                       "--overwrite")


def keys_overlap(key: str, other: str) -> bool:
    """Whether two dotted config keys name the same setting, or one holds the other."""
    return key == other or key.startswith(other + ".") or other.startswith(key + ".")


def change_effect(key: str, configs=(), label: str | None = None) -> str:
    """What changing ``key`` of a stored run would do, in the words of resume_refusal. Only a
    terminal event ends the run: one that is not leaves every step as it is (events are
    located by side steps with their own workspace, docs/adaptive.md), but the events the
    file holds were found with the stored definitions. output.every changes the sampling.
    ``label``: the key as the message writes it (default: the key itself)."""
    label = label or key
    section, _, rest = key.partition(".")
    if section == "events":
        name, _, field = rest.partition(".")

        def terminal(config) -> bool:
            events = config.get("events") if isinstance(config, dict) else None
            entries = ([events.get(name)] if name else list(events.values())) if isinstance(events, dict) else []
            return any(isinstance(entry, dict) and bool(entry.get("terminal")) for entry in entries)

        if field == "terminal" or any(terminal(config) for config in configs):
            return f"{label} changes where the run ends (a terminal event stops it), and so the trajectory"
        return (f"{label} leaves the trajectory as it is (an event that is not terminal only records where it "
                "occurs), but the events stored for the steps already done were found with the stored definition, "
                "so the file would hold events of two definitions")
    if section == "output":
        return (f"{label} leaves the trajectory as it is, but changes which states are sampled, so the file's "
                "samples would change their spacing part-way")
    return f"{label} changes the trajectory"


def config_difference(stored: str, current: str, ignore: tuple[str, ...] = (),
                      ignore_keys: tuple[str, ...] = (), prefer: tuple[str, ...] = ()) -> str | None:
    """The first key where two resolved YAML configs differ (output.path, the sections in
    ``ignore`` and the dotted keys in ``ignore_keys`` left out), or None. ``prefer``: dotted
    keys, most wanted first, named before the others where they differ (a key the user changed
    before one that follows from it: atol, which defaults to rtol, comes first in key order)."""
    import yaml
    try:
        old, new = yaml.safe_load(stored) or {}, yaml.safe_load(current) or {}
    except yaml.YAMLError:
        return "config (the stored one is not readable YAML)"
    for tree in (old, new):
        if isinstance(tree, dict) and isinstance(tree.get("output"), dict):
            tree["output"].pop("path", None)
        if isinstance(tree, dict):
            for section in ignore:
                tree.pop(section, None)
            for key in ignore_keys:
                section, _, name = key.partition(".")
                if isinstance(tree.get(section), dict):
                    tree[section].pop(name, None)
    keys = [key for key, _ in config_differences(old, new)]
    wanted = (key for preferred in prefer for key in keys if keys_overlap(key, preferred))
    return next(wanted, keys[0] if keys else None)


ABSENT = object()   # config_differences' new value of a key that only the old config has


def config_differences(old, new, prefix: str = ""):
    """Every (dotted key, new value) where two parsed configs differ, recursing while both
    sides are mappings (t_end before n_steps, which follows from it; else in key order); the
    new value is ABSENT for a key the new config does not have."""
    if not (isinstance(old, dict) and isinstance(new, dict)):
        if old != new:
            yield prefix.rstrip(".") or "config", new
        return
    keys = sorted(set(old) | set(new), key=str)
    if not prefix:   # the sections as a config is read: the problem before its method (a user trial resumed
        from .config_schema import RunConfig   # a Kepler run with a pendulum config: "method.name changes")
        order = list(RunConfig.model_fields)
        keys.sort(key=lambda key: order.index(key) if key in order else len(order))
    if "t_end" in keys and "n_steps" in keys:   # n_steps follows from t_end: name the one users write
        keys.remove("t_end")
        keys.insert(0, "t_end")
    for key in keys:
        if key not in new:
            if old[key] is not None:
                yield f"{prefix}{key}", ABSENT
        else:
            yield from config_differences(old.get(key), new[key], f"{prefix}{key}.")


def _parsed(*texts: str) -> list:
    """YAML texts as data (an unreadable one as None)."""
    import yaml
    parsed = []
    for text in texts:
        try:
            parsed.append(yaml.safe_load(text))
        except yaml.YAMLError:
            parsed.append(None)
    return parsed


def terminal_event_end(integration, status: str, clock, t_end: float) -> float | None:
    """The time at which a terminal event ended the stored run (complete before its t_end),
    else None. ``clock``: the stored state's [t, compensation]."""
    t_final = float(np.asarray(clock).ravel()[0]) if clock is not None else t_end
    terminal = np.any(np.asarray(getattr(getattr(integration, "events", None), "terminal", ()), dtype=bool))
    # (a fixed-step clock may end an ulp short of t_end: only a terminal event ends a run early)
    if status == STATUS_COMPLETE and terminal and t_final < t_end - 1e-12 * abs(t_end):
        return t_final
    return None


def integration_t_eval(integration) -> np.ndarray:
    """The run's requested output times (empty without them)."""
    return np.asarray(getattr(integration, "t_eval", np.zeros(0)))


def earlier_end_refusal(path, new_end: float, old_end: float) -> OutputError:
    """The refusal of a --resume to a t_end before the stored run's end (run_extension's, and the
    CLI's where a new run's rule on output.times would otherwise speak first)."""
    return OutputError(f"{path}: integration.t_end = {new_end:.10g} is before the end of the stored run, "
                       f"{old_end:.10g}: --resume continues a run to a later t_end, never an earlier one; start "
                       "a new run (-o NEW.h5) for a shorter one")


def _extend_times_hint(attrs: dict, stored_t, new_end: float) -> str:
    """How to give output.times that keep the stored ones and reach new_end, in the form the stored
    config gave them: a later stop for {start, stop, step}, else the whole list with new_end added (a
    user trial: a list was told to set output.times.stop, which a list does not have)."""
    import yaml
    try:
        times = ((yaml.safe_load(str(attrs.get("config", ""))) or {}).get("output") or {}).get("times")
    except (yaml.YAMLError, AttributeError):
        times = None
    if isinstance(times, dict) or stored_t is None:
        return f"keep its start and step and give a later stop, e.g. --set output.times.stop={exact_time(new_end)}"
    shown = [exact_time(float(t)) for t in stored_t]
    listed = ", ".join(shown) if len(shown) <= 8 else ", ".join(shown[:3] + ["..."] + shown[-2:])
    return (f"give the whole list, the times written first, then later ones, e.g. --set 'output.times=[{listed}, "
            f"{exact_time(new_end)}]'" + (" (every one of the times written, where '...' stands)" if len(shown) > 8
                                          else ""))


def run_extension(path, attrs: dict, status: str, clock, stored_t, integration, t_end=None) -> dict | None:
    """A --resume that continues the run stored in ``path`` to a later end: None when the end
    is the stored one, else the root attributes the continued run has (RunWriter.resume's
    ``extension``). Raises OutputError for an end that is earlier, a run that a terminal event
    ended, or output times that do not begin with the ones already written (``stored_t``).

    A fixed-step run continued so is the uninterrupted run to the new end, bit for bit; an
    adaptive one is the run that stopped at the old end and went on (its last step was cut
    to land there; the controller's next step is the one it had proposed before that).
    ``t_end``: the config's end (else the integration's); with fixed steps the number of
    steps decides, so that t0 + n h rounding off the config's t_end is no change.
    """
    old_end = float(attrs.get("t_end", math.nan))
    new_end = t_end if t_end is not None else getattr(integration, "t_end", None)
    if new_end is None:
        new_end = integration.t0 + integration.n_steps * integration.h
    new_end = float(new_end)
    new_steps, old_steps = getattr(integration, "n_steps", None), int(attrs.get("n_steps", 0))
    if new_steps is not None and old_steps > 0:   # fixed steps
        change = (new_steps > old_steps) - (new_steps < old_steps)
    else:
        change = (new_end > old_end) - (new_end < old_end)
    new_times = integration_t_eval(integration)
    if (stored_t is None) != (new_times.size == 0):
        raise OutputError(f"{path}: output.times cannot be {'removed' if new_times.size == 0 else 'added'} on "
                          "--resume (the samples written follow the stored run's); start a new run (-o NEW.h5)")
    if change == 0:
        if stored_t is not None and (new_times.size != int(attrs.get("output_times", 0))
                                     or not np.array_equal(new_times[:stored_t.size], stored_t)):
            raise OutputError(f"{path}: output.times may change on --resume only to add times after a later "
                              "integration.t_end (the run's samples are written); start a new run (-o NEW.h5) for "
                              "other times")
        return None
    if change < 0:
        raise earlier_end_refusal(path, new_end, old_end)
    t_event = terminal_event_end(integration, status, clock, old_end)
    if t_event is not None:
        raise OutputError(f"{path}: the run was ended by a terminal event at t = {exact_time(t_event)}; a later "
                          "t_end does not continue it past the event: start a new run from there, without terminal")
    if stored_t is not None:
        count = stored_t.size
        if not (new_times.size >= count and np.array_equal(new_times[:count], stored_t)):
            raise OutputError(f"{path}: output.times must keep the {count} times already written and add later "
                              f"ones: {_extend_times_hint(attrs, stored_t, new_end)}")
        if status == STATUS_COMPLETE and new_times.size > count and new_times[count] <= old_end:
            raise OutputError(f"{path}: output.times adds times before the stored run's end, {old_end:.10g}: "
                              "only later times can be added")
        if new_times.size == count and new_times[-1] <= old_end:
            # Once the run has gone on, samples before its new end cannot be added: an extension without
            # them left half a run unsampled, and the advice to add them was refused (a user trial).
            raise OutputError(f"{path}: output.times stops at {exact_time(float(new_times[-1]))}, so the run "
                              f"continued to t_end = {exact_time(new_end)} would have no samples after "
                              f"{exact_time(old_end)}, and they cannot be added later: extend output.times with "
                              f"it: {_extend_times_hint(attrs, stored_t, new_end)}")
    return {"t_end": new_end, "n_steps": getattr(integration, "n_steps", None),
            "output_times": new_times.size if new_times.size else None}


def _python_file(config_text: str) -> str | None:
    """problem.python of a resolved config (the user's problem file), if it has one."""
    if "python" not in config_text:   # no such key: skips parsing the YAML (2-3 ms on every run)
        return None
    import yaml
    try:
        problem = (yaml.safe_load(config_text) or {}).get("problem")
    except (yaml.YAMLError, AttributeError):
        return None
    return str(problem["python"]) if isinstance(problem, dict) and problem.get("python") else None


def run_to_file(integration, path, *, config_text: str, t_end: float | None = None, overwrite: bool = False,
                resume: bool = False, progress: NoProgress | None = None, handle_signals: bool = True,
                label: str = "", resume_command: str | None = None, origins: dict | None = None,
                set_overrides=None, notice: Callable[[str], None] | None = None, **drive_options) -> Outcome:
    """Run ``integration`` into the HDF5 file ``path`` (new, overwritten, or resumed).

    resume: continue the run stored in ``path`` (which must come from the same resolved
    config, output path and solver settings aside, and read back without damage); a
    missing file starts a new run. A complete run is left as it is; a failed one
    continues from its last good step only with changed solver settings (with the same
    ones it would fail again). The caller says that a missing file starts a new run (the
    command line does so before the run). Raises OutputError for file problems and DiskFullError when the disk has no
    room, before any step is computed. ``resume_command``: the command line that
    continues this run, quoted in the messages of an interrupted or stopped run. ``origins``:
    resume_refusal's, where each change comes from, the keys the user changed first: a refusal
    names the first of them that may not change. ``set_overrides``:
    the command line's --set values the run is made with (all of them, a resume's merged with the
    stored ones), stored for the next --resume (io.layout.SET_OVERRIDES); None stores none.
    ``notice``: called with what the user must hear before the steps run, whatever the run's
    end (a python: problem file changed since the run began; without it that goes in the note),
    and during the run (drive's unimposed_notice).
    """
    path = Path(path)
    if overwrite and resume:
        raise OutputError("--overwrite and --resume contradict each other: give one")
    hdf5.check_output_path(path, overwrite=overwrite, resume=resume)
    wall_offset = kernel_offset = 0.0
    note = ""
    writer = None

    def hard_stop(signal_name):
        saved = writer.saved if writer is not None else {"steps_done": integration.steps_done, "t": integration.t}
        return interrupted_line(signal_name, saved["steps_done"], integration.n_steps, saved["t"], path,
                                resume_command)

    with StopOnSignals(handle_signals, hard_stop=hard_stop) as stop:
        if resume and path.exists():
            with hdf5.RunFile(path) as existing:
                status, attrs = existing.status, existing.attrs
                steps_done = existing.steps_done
                stored_t = existing.t() if attrs.get("output_times") else None
                clock = existing.saved_state().get("clock")
                # Events NaN or infinite before a kill are in no attribute (RunWriter.finish writes them):
                # the stored samples are checked again, as the run checked its own
                not_finite = None
                if getattr(integration, "events_not_finite", None) is not None and existing.event_names():
                    from .adaptive import EVENT_CHECK_SAMPLES
                    stride = max(1, existing.n_samples // EVENT_CHECK_SAMPLES)
                    not_finite = (existing.events_not_finite(), existing.t(stride), existing.y(stride))
            stored = str(attrs.get("config", ""))
            difference = config_difference(stored, config_text, ignore=SOLVER_SECTIONS,
                                           ignore_keys=EXTENSION_KEYS + LOAD_ONLY_KEYS, prefer=tuple(origins or ()))
            if difference is not None:
                raise resume_refusal(path, difference, prefix="was written from a different config; ",
                                     configs=_parsed(stored, config_text), origins=origins)
            step_key = step_solver_change(stored, config_text)
            if step_key is not None:
                raise step_solver_refusal(path, step_key)
            extension = run_extension(path, attrs, status, clock, stored_t, integration, t_end)
            solver_changed = config_difference(stored, config_text,
                                               ignore_keys=EXTENSION_KEYS + LOAD_ONLY_KEYS) is not None
            if status == STATUS_COMPLETE and extension is None:
                t_event = terminal_event_end(integration, status, clock, float(attrs.get("t_end", math.nan)))
                if t_event is not None:   # a later t_end would be refused (run_extension): no hint to give one
                    done = f"already complete: it ended at its terminal event at t = {exact_time(t_event)}"
                else:
                    done = ("already complete; nothing to resume; to continue it to a later end: --resume --set "
                            "integration.t_end=LATER")
                return Outcome(status=STATUS_COMPLETE, path=path, steps_done=steps_done,
                               n_steps=int(attrs["n_steps"]), wall_time_s=float(attrs.get("wall_time_s", 0.0)),
                               kernel_time_s=float(attrs.get("kernel_time_s", 0.0)),
                               note=done)
            if status.startswith(FAILED_PREFIX) and not solver_changed:
                from .adaptive import NO_SETTING_GETS_THROUGH
                if NO_SETTING_GETS_THROUGH in status:
                    raise OutputError(f"{path}: the run {status}; resuming it would fail the same way: start again "
                                      "with --overwrite, from another initial state or with other parameters")
                raise OutputError(f"{path}: the run {status}; resuming with the same solver settings would fail the "
                                  "same way: resume with other ones (e.g. --set solver.max_halvings=8), or start "
                                  "again with --overwrite")
            opening = time.perf_counter()
            restore = integration.restore
            if extension is not None:
                def restore(saved):   # the stored run reached its end; this one goes on
                    integration.restore({**saved, "finished": 0})
            # The config names a python: problem's file by its path only: an edit since the run began
            # (fixing a function that raised, as the failure message asks) is recorded and said.
            source_file = problem_file_attributes(integration.problem)
            if attrs.get(PROBLEM_FILE_DIGEST) in (None, source_file.get(PROBLEM_FILE_DIGEST)):
                source_file = None
            writer, saved = hdf5.RunWriter.resume(
                path, restore=restore, stop=stop, extension=extension, problem_file=source_file,
                config_text=config_text if (solver_changed or extension is not None) else None,
                set_overrides=set_overrides)
            wall_offset, kernel_offset = float(saved["wall_time_s"]), float(saved["kernel_time_s"])
            if not_finite is not None and not_finite[1].size:
                integration.check_events_finite(*not_finite[1:])
                for name, first in not_finite[0].items():
                    integration.events_not_finite[name] = min(first, integration.events_not_finite.get(name, first))
            note = f"resumed at step {integration.steps_done}" + (" with new solver settings" if solver_changed else "")
            if extension is not None:
                # (its t_end, which a run stopped before it never reached: a user trial's interrupted run "ended at" it)
                note += f", continued to t_end = {extension['t_end']:.10g} (its t_end was {float(attrs['t_end']):.10g})"
            if source_file is not None:
                changed = (f"the problem file {integration.problem.source_file} has changed since the run began: "
                           f"the {saved['steps_done']} steps before used the old one (problem_file_history)")
                if notice is not None:
                    # Before the steps, and under --quiet too: a user trial heard of it only in the
                    # summary line of a run that completed, which --quiet does not print.
                    notice(changed)
                else:
                    note += f"; {changed}"
            started_with = saved["attrs"].get("elimfast_version")
            if started_with != hdf5.version_attributes()["elimfast_version"]:
                note += (f"; the run was started by elimfast {started_with}: a continuation by another version "
                         "is not guaranteed to be bit for bit")
        else:
            opening = time.perf_counter()
            writer = hdf5.RunWriter.create(path, integration, config_text=config_text, t_end=t_end,
                                           overwrite=overwrite or resume,
                                           attributes=set_overrides_attribute(set_overrides))
        open_s = time.perf_counter() - opening
        drive_options.setdefault("problem_source", _python_file(config_text))
        outcome = drive(integration, writer, progress=progress, stop=stop, wall_offset=wall_offset,
                        kernel_offset=kernel_offset, label=label, resume_command=resume_command, notice=notice,
                        **drive_options)
    not_finite = getattr(integration, "events_not_finite", None)
    if not_finite:
        listed = ", ".join(f"{name!r} (first at t = {t:.6g})" for name, t in not_finite.items())
        note += (("; " if note else "") + f"event{'s' if len(not_finite) > 1 else ''} {listed} NaN or infinite at "
                 "samples of this run: no crossing is found where an event is not finite; check the expression")
    outcome.note = note
    outcome.session_open_s = open_s
    return outcome


__all__ = ["Outcome", "StopOnSignals", "drive", "run_to_file", "progress_for", "next_chunk_steps",
           "config_difference", "interrupted_line", "kernel_call", "current_watchdog", "OutputError"]
