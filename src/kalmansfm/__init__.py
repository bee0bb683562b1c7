"""kalmansfm: Kalman feature tracking, shape from motion by factorization, and structure fusion.

The public API is what ``__all__`` lists; everything else is internal.
Data flows one way: frames → :func:`track` → :func:`factorize` → report
(:func:`run_demo` does all of it); :func:`fuse` fuses each tracked point over views of
known cameras (:class:`CameraSet`) into a 3D point with a covariance; :func:`fuse_recursive`
and :func:`estimate_landmarks` fuse 3D structure under known motion.
The layers and what each may import: docs/architecture.md.
"""

from ._version import __version__
from .errors import InvalidInputError, KalmanSfmError, KalmanSfmWarning, NotEnoughDataError, SingularCovarianceError
from .estimation import (
    FilterRun,
    FusionResult,
    KalmanFilter,
    LinearGaussianModel,
    SmoothedRun,
    constant_velocity_2d,
    fuse_closed_form,
    fuse_recursive,
    smooth,
)
from .pipeline import DemoRun, FuseRun, run_demo, run_fuse
from .structure import (
    CameraSet,
    FusedStructure,
    FusionSettings,
    LandmarkEstimates,
    PerspectiveReconstruction,
    PerspectiveSettings,
    Reconstruction,
    TriangulationResult,
    align_similarity,
    estimate_landmarks,
    factorize,
    fuse,
    reconstruct_perspective,
    triangulate_midpoint,
)
from .tracking import Tracker, TrackerSettings, Tracks, TrackStatus, track

__all__ = [
    "CameraSet",
    "DemoRun",
    "FuseRun",
    "FusedStructure",
    "FusionSettings",
    "FilterRun",
    "FusionResult",
    "InvalidInputError",
    "KalmanFilter",
    "KalmanSfmError",
    "KalmanSfmWarning",
    "LandmarkEstimates",
    "LinearGaussianModel",
    "NotEnoughDataError",
    "PerspectiveReconstruction",
    "PerspectiveSettings",
    "Reconstruction",
    "SingularCovarianceError",
    "SmoothedRun",
    "TrackStatus",
    "Tracker",
    "TrackerSettings",
    "Tracks",
    "TriangulationResult",
    "__version__",
    "align_similarity",
    "constant_velocity_2d",
    "estimate_landmarks",
    "factorize",
    "fuse",
    "fuse_closed_form",
    "fuse_recursive",
    "reconstruct_perspective",
    "run_demo",
    "run_fuse",
    "smooth",
    "track",
    "triangulate_midpoint",
]
