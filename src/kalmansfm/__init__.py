"""kalmansfm: Kalman feature tracking, shape from motion by factorization, and structure fusion.

The public API is what ``__all__`` lists; everything else is internal.
Data flows one way: frames → :func:`track` → a :class:`Reconstruction` → report
(:func:`run_demo` does all of it).  Every way of reconstructing returns the same
:class:`Reconstruction`: :func:`factorize` (affine cameras), :func:`fuse` (each tracked point fused
over views of known cameras, :class:`CameraSet`) and :func:`reconstruct_perspective` (calibrated
cameras with unknown motion); :func:`fuse_recursive` and :func:`estimate_landmarks` fuse 3D
structure under known motion; :func:`reconstruct_images` turns calibrated images (any order)
into cameras and points.
The layers and what each may import: docs/architecture.md.

Importing the package is light: the names of ``__all__`` other than the error classes are
loaded when first used (from :mod:`kalmansfm._api`, and ``__version__`` from the package
metadata), so that the command line can install its signal handling before NumPy and
OpenCV load.
"""

from .errors import InvalidInputError, KalmanSfmError, KalmanSfmWarning, NotEnoughDataError, SingularCovarianceError

TYPE_CHECKING = False  # not typing.TYPE_CHECKING: importing typing alone takes longer than this whole file
if TYPE_CHECKING:  # what type checkers see; at run time __getattr__ loads these on first use
    from ._api import *  # noqa: F403
    from ._version import __version__

__all__ = [
    "Affine",
    "CameraSet",
    "DemoRequest",
    "DemoRun",
    "FrameStatus",
    "FuseRequest",
    "FuseRun",
    "FeatureSettings",
    "FusionSettings",
    "FilterRun",
    "FusionResult",
    "ImageReconstruction",
    "InvalidInputError",
    "KalmanFilter",
    "KalmanSfmError",
    "KalmanSfmWarning",
    "LandmarkEstimates",
    "LinearGaussianModel",
    "MappingSettings",
    "NoiseEstimate",
    "NotEnoughDataError",
    "Observations",
    "Perspective",
    "PerspectiveSettings",
    "PointStatus",
    "ReconstructRequest",
    "Reconstruction",
    "SingularCovarianceError",
    "SmoothedRun",
    "TrackStatus",
    "Tracker",
    "TrackerSettings",
    "Tracks",
    "TriangulationResult",
    "ViewStatus",
    "__version__",
    "align_similarity",
    "constant_velocity_2d",
    "estimate_landmarks",
    "factorize",
    "fuse",
    "fuse_closed_form",
    "fuse_recursive",
    "reconstruct_images",
    "reconstruct_perspective",
    "run_demo",
    "run_fuse",
    "run_reconstruct",
    "smooth",
    "track",
    "triangulate_midpoint",
]


def __getattr__(name: str) -> object:
    """Load a public name on first use (PEP 562)."""
    if name in __all__:
        if name == "__version__":  # the package metadata lookup takes tens of milliseconds
            from . import _version as _api
        else:
            from . import _api

        value = getattr(_api, name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
