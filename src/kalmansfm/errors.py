"""Exception and warning classes of kalmansfm.

Every error that a user's input can cause derives from :class:`KalmanSfmError`,
so the command line can tell a user mistake (exit code 2, one line) from a bug
(exit code 1).  The input errors also derive from :class:`ValueError`, so code
written against plain NumPy conventions keeps working.
"""

from __future__ import annotations

__all__ = [
    "KalmanSfmError",
    "InvalidInputError",
    "NotEnoughDataError",
    "SingularCovarianceError",
    "ReportInterrupted",
    "KalmanSfmWarning",
]


class KalmanSfmError(Exception):
    """Base class of every error kalmansfm raises on purpose."""


class InvalidInputError(KalmanSfmError, ValueError):
    """An argument, file or option has the wrong shape, type or value."""


class NotEnoughDataError(InvalidInputError):
    """Too few frames, points or measurements for the requested estimate."""


class SingularCovarianceError(KalmanSfmError, ArithmeticError):
    """A covariance that must be positive definite is not (e.g. the innovation covariance)."""


class ReportInterrupted(KeyboardInterrupt):
    """Ctrl-C while ``report.html`` was being built, after the run's results were written.

    The message says what is on disk: the new results, and no report.
    """


class KalmanSfmWarning(UserWarning):
    """A result was computed but deserves the user's attention (degenerate data, fallbacks)."""
