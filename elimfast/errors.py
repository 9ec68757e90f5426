"""The exceptions elimfast raises on its own account.

Each class carries the command line's exit code for it (``exit_code``): 2 for what the
user gave (a config, a file, a size that cannot fit), 1 for a run that failed.
"""


class ElimfastError(Exception):
    """Base class of elimfast's own errors (exit code 2: a usage, config or file error)."""

    exit_code = 2


class ParameterError(ElimfastError, ValueError):
    """A parameter of the library's API out of its range or of the wrong kind.

    ``parameter`` names it as the API does (``"tol"``, ``"k"``, ``"t_end"``,
    ``"conserve"``), ``index`` the entry of a list parameter at fault (``conserve[1]``),
    and ``detail`` says what is wrong and what to do. ``str(err)`` is
    ``"parameter[index] detail"``, so details read on from the name ("must be ...",
    "is ..."). The validators that raise it are the only statement of each rule; the
    config layer puts the YAML key and line in front of ``detail`` instead of the name.
    ``related`` names the other parameters the rule depends on (t_end's step count on h and
    t0), so that a value given by --set to one of them is named too.
    """

    def __init__(self, parameter: str, message: str, *, index: int | None = None, related: tuple = ()):
        where = parameter if index is None else f"{parameter}[{index}]"
        super().__init__(f"{where} {message}")
        self.parameter = parameter
        self.index = index
        self.detail = message
        self.related = tuple(related)


def real_number(parameter: str, value) -> float:
    """``value`` as a float, or a ParameterError naming ``parameter``: the one check of a real
    number the API is given (t0, h, t_end, rtol, atol, epsilon, h_max, tol). A bool is not a number,
    nor is a string: the API takes numbers, and a config's expressions ('pi/30') are the config's
    to read (a user trial: h='0.1' was taken and h='pi/30' refused)."""
    if isinstance(value, str):
        raise ParameterError(parameter, f"must be a number, got the string {value!r}: pass the number itself "
                                        "(math.pi / 30, say); expressions such as 'pi/30' are read in configs")
    if isinstance(value, bool):
        raise ParameterError(parameter, f"must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ParameterError(parameter, f"must be a number, got {value!r}") from None


class ConvergenceError(ElimfastError, RuntimeError):
    """The run stopped: the fixed-point iteration did not converge, the small system was
    singular, or the solution stopped being finite.

    step: the 1-based number of the failed step; time: the time it started from;
    reason: 'not converged', 'singular' or 'non-finite'; result: the partial Result
    (every completed step, with its samples and per-step data).
    """

    exit_code = 1

    def __init__(self, message, *, step, time, result, reason):
        super().__init__(message)
        self.step = step
        self.time = time
        self.result = result
        self.reason = reason


class ResourceError(ElimfastError):
    """An input that asks for more memory, disk or steps than the run may take; the
    message says how much it would need and what to change (exit code 2)."""


class DiskFullError(ElimfastError, OSError):
    """The output's file system has no room for the next chunk (exit code 1: the run
    stopped; its file holds every step before it and can be resumed once there is space)."""

    exit_code = 1


class ProblemFunctionError(ElimfastError, RuntimeError):
    """A problem function (H, grad_H, invariants, ...) raised during a run (exit code 1)."""

    exit_code = 1


def closest(word, options, cutoff: float = 0.6) -> str | None:
    """The option a mistyped word most likely meant, or None: one that differs only in case or in
    '_' first (P2 -> p2, timescale -> time_scale; difflib's ratio preferred q2 and nothing), else
    difflib's closest above cutoff. The one rule of every 'did you mean' (integrate.suggest,
    expressions.did_you_mean, a sweep's unknown keys)."""
    import difflib
    options = [str(option) for option in options]
    folded = str(word).lower().replace("_", "")
    for option in options:
        if option.lower().replace("_", "") == folded:
            return option
    close = difflib.get_close_matches(str(word), options, n=1, cutoff=cutoff)
    return close[0] if close else None


def exact_time(t) -> str:
    """A time as messages write it: the shortest text that reads back as the same float, without
    a trailing '.0' (t = 0 -> 0.1, t = 0.30000000000000004, t = 50), where 17 digits gave
    0.20000000000000001."""
    text = repr(float(t))
    return text[:-2] if text.endswith(".0") else text
