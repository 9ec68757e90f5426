"""The memo of the problem's function addresses (elimfast/function_addresses.py): a kernel
call resolves each first-class function once per function and signature, and the runs are
bit for bit the ones Numba's own lookups give."""
import math

import numpy as np
from numba import njit, types
from numba.experimental import function_type

import elimfast
from elimfast import function_addresses
from elimfast.methods import ehbvm, hbvm
from elimfast.problems import henon_heiles, kepler


def _counting(monkeypatch):
    """Count the calls that reach Numba's own lookups (behind the memo)."""
    calls = []
    for name in ("_get_wrapper_address", "_get_jit_address"):
        memoised = getattr(function_type, name)
        original = memoised.__wrapped__

        def counted(func, sig, original=original):
            calls.append(func)
            return original(func, sig)

        monkeypatch.setattr(function_type, name, function_addresses._memoised(counted, type(kepler(0.6).grad_H)))
    return calls


def test_loading_the_integrator_installs_the_memo():
    assert callable(elimfast.integrate)     # elimfast loads it on first use
    for name in ("_get_wrapper_address", "_get_jit_address"):
        assert getattr(function_type, name).elimfast_memo is not None
    assert function_addresses.install()     # again: a no-op, not a second wrapper
    assert not hasattr(function_type._get_wrapper_address.__wrapped__, "elimfast_memo")


def test_each_function_is_resolved_once_and_the_runs_do_not_change(monkeypatch):
    p = kepler(0.6)
    plain = [elimfast.integrate(p, ehbvm(12, 3), 0.1, n_steps=50, conserve=["angular_momentum", "lrl_y"])
             for _ in range(2)]
    calls = _counting(monkeypatch)
    first = elimfast.integrate(p, ehbvm(12, 3), 0.1, n_steps=50, conserve=["angular_momentum", "lrl_y"])
    resolved = len(calls)
    assert resolved > 0
    again = [elimfast.integrate(p, ehbvm(12, 3), 0.1, n_steps=50, conserve=["angular_momentum", "lrl_y"])
             for _ in range(3)]
    assert len(calls) == resolved          # later calls: every address from the memo
    for result in [first] + again:
        np.testing.assert_array_equal(result.y, plain[0].y)
        np.testing.assert_array_equal(result.iterations, plain[0].iterations)
    # another problem's functions are other dispatchers: resolved afresh, and its run is right
    other = elimfast.integrate(henon_heiles(), hbvm(6, 3), 0.05, n_steps=40)
    assert len(calls) > resolved
    errors = other.invariant_errors()
    assert errors["H"] < 1e-14


def test_an_adaptive_run_with_events_is_unchanged_by_the_memo(monkeypatch):
    p = kepler(0.9)
    options = dict(t_end=4 * math.pi, rtol=1e-12, conserve=["angular_momentum", "lrl_y"],
                   events={"pericentre": {"expression": "q1*p1 + q2*p2", "direction": 1}})
    with monkeypatch.context() as patch:
        for name in ("_get_wrapper_address", "_get_jit_address"):
            patch.setattr(function_type, name, getattr(function_type, name).__wrapped__)   # Numba's own
        plain = elimfast.integrate(p, ehbvm(8, 4), **options)
    memo_run = elimfast.integrate(p, ehbvm(8, 4), **options)
    np.testing.assert_array_equal(memo_run.y, plain.y)
    np.testing.assert_array_equal(memo_run.step_h, plain.step_h)
    np.testing.assert_array_equal(memo_run.events["pericentre"].t, plain.events["pericentre"].t)


def test_the_memo_is_bounded_when_signature_objects_are_not_reused():
    seen = []
    lookup = function_addresses._memoised(lambda func, sig: seen.append(sig) or 1234, object)

    class Sig:
        pass

    func = type("F", (), {})()
    with function_addresses.remembered_addresses():
        for _ in range(3 * function_addresses.MAX_SIGNATURES):
            assert lookup(func, Sig()) == 1234
        assert len(lookup.elimfast_memo[func]) <= function_addresses.MAX_SIGNATURES
        same = Sig()
        lookup(func, same)
        lookup(func, same)
    assert seen.count(same) == 1


def test_the_memo_serves_only_elimfasts_kernel_calls(monkeypatch):
    """Numba code of the user's own that takes first-class functions keeps Numba's lookups,
    call after call (a recompiled function of theirs is then never served stale code)."""
    calls = _counting(monkeypatch)
    signature = types.float64(types.float64)

    @njit(signature)
    def square(x):
        return x * x

    @njit(types.float64(types.FunctionType(signature), types.float64))
    def apply(f, x):
        return f(x)

    assert apply(square, 3.0) == 9.0
    first = len(calls)
    assert first > 0
    assert apply(square, 4.0) == 16.0
    assert len(calls) == 2 * first          # resolved again: no memo outside remembered_addresses()
    with function_addresses.remembered_addresses():
        apply(square, 5.0)
        inside = len(calls)
        apply(square, 6.0)
        assert len(calls) == inside         # inside: from the memo
