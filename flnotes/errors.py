"""The package's own exception: a documented solver outcome, as opposed to a programming error.

:func:`flnotes.simulate` applies its fallback input *only* when a controller
raises :class:`SolverFailure`; any other exception (``ValueError``,
``TypeError``, ``ImportError``, ...) is a mistake in the call or in the code and
stops the run with its message.
"""
from __future__ import annotations

__all__ = ["SolverFailure"]


class SolverFailure(RuntimeError):
    """A controller could not produce an input at this state: the program is infeasible,
    the solver hit its time limit without an admissible incumbent, or the solver itself failed.

    Parameters
    ----------
    message
        What happened, for the log.
    status
        The solver outcome: ``"infeasible"``, ``"time_limit"`` or ``"error"``.

    Notes
    -----
    It derives from ``RuntimeError`` so that code catching ``RuntimeError``
    keeps working. A controller raises it from ``step`` when it has no input
    to apply; :func:`flnotes.simulate` then applies its documented fallback,
    flags the step (``log.fallback``) and records the message in
    ``log.status`` and ``log.steps[k].info``.
    """

    def __init__(self, message: str, status: str = "error"):
        super().__init__(message)
        self.status = str(status)
