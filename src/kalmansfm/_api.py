"""The public API of kalmansfm, loaded on first use of a name by ``kalmansfm/__init__.py``.

``import kalmansfm`` stays light (the version and the error classes) so that the command
line can set up its signal handling before NumPy, OpenCV and the rest load; the names
listed in ``kalmansfm.__all__`` come from the imports below when first asked for.
"""

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
from .features import FeatureSettings
from .mapping import ImageReconstruction, MappingSettings, ViewStatus, reconstruct_images
from .pipeline import (
    Affine,
    DemoRequest,
    DemoRun,
    FuseRequest,
    FuseRun,
    Perspective,
    ReconstructRequest,
    run_demo,
    run_fuse,
    run_reconstruct,
)
from .structure import (
    CameraSet,
    FrameStatus,
    FusionSettings,
    LandmarkEstimates,
    NoiseEstimate,
    Observations,
    PerspectiveSettings,
    PointStatus,
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
