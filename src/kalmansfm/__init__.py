"""kalmansfm: Kalman feature tracking, shape from motion by factorization, and structure fusion.

The public API is what ``__all__`` lists; everything else is internal.
"""

from importlib.metadata import PackageNotFoundError, version

from . import models
from .errors import (
    InvalidInputError,
    KalmanSfmError,
    KalmanSfmWarning,
    NotEnoughDataError,
    SingularCovarianceError,
)
from .estimation import FusionResult, KalmanFilter, fuse_closed_form, fuse_recursive
from .tracking import Tracker, Tracks, track

try:
    __version__ = version("kalmansfm")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

__all__ = [
    "FusionResult",
    "InvalidInputError",
    "KalmanFilter",
    "KalmanSfmError",
    "KalmanSfmWarning",
    "NotEnoughDataError",
    "SingularCovarianceError",
    "Tracker",
    "Tracks",
    "__version__",
    "fuse_closed_form",
    "fuse_recursive",
    "models",
    "track",
]
