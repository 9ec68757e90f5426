"""The addresses of the problem's functions, resolved once per function instead of at every kernel call.

The kernels take the problem's functions as first-class ``FunctionType`` arguments
(kernels/signatures.py), so one compiled kernel serves every problem. Numba turns each
such argument into two machine addresses (the function's C wrapper and its compiled
body) at *every* call, through ``numba.experimental.function_type._get_wrapper_address``
and ``_get_jit_address``: each looks the dispatcher's compile result up by signature,
hashing every argument type on the way. With 7 function arguments that was about half of
a kernel call's fixed cost: measured, ``integrate`` of one adaptive step 0.40 -> 0.21 ms,
of one fixed step 0.22 -> 0.10 ms, and Kepler e = 0.9 over 10 periods (HBVM(12,6),
rtol = 1e-14, 292 steps) 2.6 -> 2.3 ms.

``install`` wraps the two lookups with a memo per dispatcher and signature. The
generated code calls them by module attribute on each call, so the wrapped versions are
the ones used. The memo serves only the calls of elimfast's own kernels, made inside
``remembered_addresses()``: the Numba code of the user's program keeps Numba's lookups.
Importing this module installs it (the modules that call the kernels import it).

The signature object a call site passes is the same object every time (Numba unpickles it
once per call site). A miss only costs the original lookup, and each dispatcher's memo is
bounded. The memo holds the dispatcher weakly. Numba never frees compiled code, so a
remembered address always points to valid code; only a ``Dispatcher.recompile()`` of a
problem's function (elimfast never does that) would leave the memo pointing at the code
from before the recompilation. Anything but a Dispatcher (cfuncs, objects with
``__wrapper_address__``) goes to Numba's lookup as before. If Numba no longer has these
functions, ``install`` does nothing.
"""
from __future__ import annotations

import threading
import weakref

MAX_SIGNATURES = 64   # per dispatcher: more means the call sites' signature objects are not reused

_calls = threading.local()   # .depth > 0 inside remembered_addresses() in this thread


class remembered_addresses:
    """``with remembered_addresses(): kernel(...)``: the memo serves this thread's kernel calls in the block."""

    __slots__ = ()

    def __enter__(self):
        _calls.depth = getattr(_calls, "depth", 0) + 1

    def __exit__(self, *exc):
        _calls.depth -= 1
        return False


def _memoised(resolve, dispatcher_type):
    memo: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()

    def lookup(func, sig):
        if not getattr(_calls, "depth", 0) or not isinstance(func, dispatcher_type):
            return resolve(func, sig)
        per_signature = memo.get(func)
        if per_signature is not None:
            entry = per_signature.get(id(sig))
            if entry is not None and entry[0] is sig:
                return entry[1]
        address = resolve(func, sig)
        if per_signature is None:
            per_signature = memo.setdefault(func, {})
        if len(per_signature) >= MAX_SIGNATURES:
            per_signature.clear()
        per_signature[id(sig)] = (sig, address)   # sig kept alive: its id cannot be reused
        return address

    lookup.__wrapped__ = resolve
    lookup.elimfast_memo = memo
    return lookup


def install() -> bool:
    """Wrap Numba's two address lookups (once per process); True if they are wrapped."""
    try:
        from numba.core.dispatcher import Dispatcher
        from numba.experimental import function_type
    except ImportError:   # pragma: no cover - a Numba without first-class functions
        return False
    installed = True
    for name in ("_get_wrapper_address", "_get_jit_address"):
        current = getattr(function_type, name, None)
        if current is None:
            installed = False
            continue
        if getattr(current, "elimfast_memo", None) is None:
            setattr(function_type, name, _memoised(current, Dispatcher))
    return installed


install()

__all__ = ["install", "remembered_addresses", "MAX_SIGNATURES"]
