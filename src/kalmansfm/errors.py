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
    "Interrupted",
    "KalmanSfmWarning",
]


class KalmanSfmError(Exception):
    """Base class of every error kalmansfm raises on purpose.

    Parameters
    ----------
    message : one line: what is wrong, what was expected and what came.
    fields : the names of the arguments or request fields the message mentions, so that a
        front end (the command line) can put its own names (``--focal``) in their place.

    Examples
    --------
    >>> err = InvalidInputError("give intrinsics or focal, exactly one", fields=("intrinsics", "focal"))
    >>> str(err), err.fields
    ('give intrinsics or focal, exactly one', ('intrinsics', 'focal'))
    """

    def __init__(self, *args: object, fields: tuple[str, ...] = ()) -> None:
        super().__init__(*args)
        self.fields = tuple(fields)


class InvalidInputError(KalmanSfmError, ValueError):
    """An argument, file or option has the wrong shape, type or value."""


class NotEnoughDataError(InvalidInputError):
    """Too few frames, points or measurements for the requested estimate."""


class SingularCovarianceError(KalmanSfmError, ArithmeticError):
    """A covariance that must be positive definite is not (e.g. the innovation covariance)."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C (SIGINT) or SIGTERM stopped a command; the message, when there is one, says what is on disk.

    The command line raises it from its SIGTERM handler, so that a job killer cleans up
    exactly as Ctrl-C does, and ``batch`` raises it to say which sequences finished.

    Attributes
    ----------
    signal_number : the signal that stopped the command (2 = SIGINT, 15 = SIGTERM).
    """

    def __init__(self, message: str = "", signal_number: int = 2) -> None:
        super().__init__(message)
        self.signal_number = signal_number


class KalmanSfmWarning(UserWarning):
    """A result was computed but deserves the user's attention (degenerate data, fallbacks)."""
