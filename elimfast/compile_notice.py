"""One line when Numba starts compiling (a cache miss), for the command line and Python alike.

A cold cache makes the first run wait 1-2 minutes for elimfast's kernels, about 90 s for a
per-problem kernel, a few seconds for a problem's own functions; without a word a user takes
that for a hang. The line is said at most once per process and kind: elimfast's kernels
(after an install, a change of elimfast or Numba, `elimfast cache clear --kernels`), a
per-problem kernel, or the functions of a problem, an event or a time scale from expressions
or a Python file, which `elimfast cache warm` cannot compile ahead. Warm runs say nothing.

The command line writes the line with click on stderr (``announce(write=...)``). Elsewhere it
goes to the ``elimfast`` logger at level WARNING: with logging left unconfigured Python prints
it on stderr, and ``logging.getLogger("elimfast").setLevel(logging.ERROR)`` silences it.
``elimfast.kernels`` registers it before any kernel is compiled or loaded.
"""
from __future__ import annotations

import logging

KERNELS = ("compiling Numba kernels (once: later runs load them from the cache; "
           "`elimfast cache warm` does it ahead) ...")
PER_PROBLEM = ("compiling the kernel for this problem (solver.kernel: per_problem; about 90 s, "
               "once: later runs of this problem load it from the cache) ...")
USER = "compiling the problem's own functions (once: later runs load them from the cache) ..."

_LISTENER = []   # the one registered listener of this process


def _log(line: str) -> None:
    logging.getLogger("elimfast").warning(line)


def announce(write=None) -> None:
    """Register the listener once per process; ``write`` (a callable taking the line), when
    given, replaces where the lines go from now on (the command line's click.echo). Imports
    Numba."""
    if _LISTENER:
        if write is not None:
            _LISTENER[0].write = write
        return
    from numba.core import event

    class Announce(event.Listener):
        def __init__(self):
            self.said = set()
            self.write = write or _log

        def on_start(self, ev):
            data = ev.data if isinstance(ev.data, dict) else {}
            module = getattr(getattr(data.get("dispatcher"), "py_func", None), "__module__", "") or ""
            from elimfast.per_problem import MODULE_PREFIX as PER_PROBLEM_PREFIX
            if module == "numba" or module.startswith("numba."):
                # Numba's own jitted helpers (np.linalg's, for one), compiled for whatever is compiling:
                # that one is announced (they were taken for the problem's functions, on a config naming none)
                return
            kind = ("kernels" if module == "elimfast" or module.startswith("elimfast.")
                    else "per_problem" if module.startswith(PER_PROBLEM_PREFIX) else "user")
            if kind in self.said:
                return
            self.said.add(kind)
            if kind == "per_problem":
                # it compiles elimfast's kernel code again for the problem, and the problem's functions
                # once more for their calls there: one line says it all
                self.said.update(("kernels", "user"))
            self.write({"kernels": KERNELS, "per_problem": PER_PROBLEM, "user": USER}[kind])

        def on_end(self, ev):
            pass

    _LISTENER.append(Announce())
    event.register("numba:compile", _LISTENER[0])
