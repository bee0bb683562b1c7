"""kalmansfm: Kalman feature tracking, shape from motion by factorization, and structure fusion.

The public API is what ``__all__`` lists; everything else is internal.
Data flows one way: frames → :func:`track` → :func:`factorize` → report
(:func:`run_pipeline` does all of it); :func:`fuse_recursive` and
:func:`estimate_landmarks` fuse 3D structure under known motion.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("kalmansfm")
except PackageNotFoundError:  # running from a source tree without installation
    __version__ = "0.0.0+unknown"

from . import models  # noqa: E402
from .errors import (  # noqa: E402
    InvalidInputError,
    KalmanSfmError,
    KalmanSfmWarning,
    NotEnoughDataError,
    SingularCovarianceError,
)
from .estimation import (  # noqa: E402
    FilterRun,
    FusionResult,
    KalmanFilter,
    SmoothedRun,
    fuse_closed_form,
    fuse_recursive,
    smooth,
)
from .pipeline import PipelineResult, run_pipeline  # noqa: E402
from .structure import (  # noqa: E402
    LandmarkEstimates,
    Reconstruction,
    TriangulationResult,
    align_similarity,
    estimate_landmarks,
    factorize,
    triangulate_midpoint,
)
from .tracking import Tracker, Tracks, track  # noqa: E402

__all__ = [
    "FilterRun",
    "FusionResult",
    "InvalidInputError",
    "KalmanFilter",
    "KalmanSfmError",
    "KalmanSfmWarning",
    "LandmarkEstimates",
    "NotEnoughDataError",
    "PipelineResult",
    "Reconstruction",
    "SingularCovarianceError",
    "SmoothedRun",
    "Tracker",
    "Tracks",
    "TriangulationResult",
    "__version__",
    "align_similarity",
    "estimate_landmarks",
    "factorize",
    "fuse_closed_form",
    "fuse_recursive",
    "models",
    "run_pipeline",
    "smooth",
    "track",
    "triangulate_midpoint",
]
