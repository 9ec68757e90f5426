"""Time and memory bounds for fuzz examples: an input that is only data must neither take
long nor use much memory (issue 9).

``bounded_example`` wraps a hypothesis test's body (put it under ``@given``) so that each
example is held to ``EXAMPLE_CPU_SECONDS`` of CPU time and ``EXAMPLE_MEGABYTES`` of Python
allocations (tracemalloc peak, numpy arrays included). CPU time, not wall time: a loaded
2-core machine stretches wall time, not the CPU an example needs, so the bound does not
turn flaky. A hang in Python code is cut by SIGALRM after ``WALL_GUARD_SECONDS``.
Measured on this machine over the 1,800 examples of the config and expression fuzzers: at
most 0.18 s of CPU and 1.9 MB, so the bounds leave a margin of about 25x and 50x.
"""
from __future__ import annotations

import contextlib
import functools
import signal
import threading
import time
import tracemalloc

EXAMPLE_CPU_SECONDS = 5.0
EXAMPLE_MEGABYTES = 100
WALL_GUARD_SECONDS = 60


class ExampleTooSlow(AssertionError):
    pass


@contextlib.contextmanager
def bounded(cpu_seconds: float = EXAMPLE_CPU_SECONDS, megabytes: float = EXAMPLE_MEGABYTES):
    """Assert that the block uses at most cpu_seconds of CPU and megabytes of Python memory."""
    tracing = tracemalloc.is_tracing()
    if not tracing:
        tracemalloc.start()
    tracemalloc.reset_peak()
    base, _ = tracemalloc.get_traced_memory()
    guard = threading.current_thread() is threading.main_thread()
    if guard:
        def timeout(signum, frame):
            raise ExampleTooSlow(f"an example ran for more than {WALL_GUARD_SECONDS} s")
        previous = signal.signal(signal.SIGALRM, timeout)
        signal.alarm(WALL_GUARD_SECONDS)
    started = time.process_time()
    try:
        yield
    finally:
        cpu = time.process_time() - started
        if guard:
            signal.alarm(0)
            signal.signal(signal.SIGALRM, previous)
        _, peak = tracemalloc.get_traced_memory()
        if not tracing:
            tracemalloc.stop()
    used = (peak - base) / 2 ** 20
    assert cpu <= cpu_seconds, f"an example took {cpu:.2f} s of CPU (bound {cpu_seconds} s)"
    assert used <= megabytes, f"an example allocated {used:.0f} MB (bound {megabytes} MB)"


def bounded_example(test):
    """Decorator: each call of ``test`` (each hypothesis example) runs under ``bounded()``."""
    @functools.wraps(test)
    def wrapper(*args, **kwargs):
        with bounded():
            return test(*args, **kwargs)
    return wrapper
