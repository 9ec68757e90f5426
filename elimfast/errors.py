"""The exceptions elimfast raises on its own account."""


class ElimfastError(Exception):
    """Base class of elimfast's own errors."""


class ConvergenceError(ElimfastError, RuntimeError):
    """The run stopped: the fixed-point iteration did not converge, the small system was
    singular, or the solution stopped being finite.

    step: the 1-based number of the failed step; time: the time it started from;
    reason: 'not converged', 'singular' or 'non-finite'; result: the partial Result
    (every completed step, with its samples and per-step data).
    """

    def __init__(self, message, *, step, time, result, reason):
        super().__init__(message)
        self.step = step
        self.time = time
        self.result = result
        self.reason = reason
