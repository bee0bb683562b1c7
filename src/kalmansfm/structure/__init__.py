"""Structure: 3-D points and cameras from image positions, every method returning one
:class:`Reconstruction`.

Four wings, each one problem: ``geometry/`` (pinhole cameras, rotations, alignment, the rows of
orthographic cameras, two-view triangulation), ``affine/`` (Tomasi–Kanade factorization),
``fusion/`` (3-D points fused view by view with known cameras) and ``perspective/`` (calibrated
reconstruction with unknown motion: registration and bundle adjustment).  The shared point
status and the record itself sit on top of the wings (``points.py``, ``reconstruction.py``).

Nothing here knows about images or tracks files; it works on arrays of positions.
"""

from .affine.lowrank import TruncatedSVD, subspace_angle, truncated_svd
from .affine.reconstruct import factorize
from .affine.factorization import metric_upgrade
from .fusion import FusionHistory, FusionSettings, fuse, pair_triangulations
from .fusion.landmark import LandmarkEstimates, estimate_landmarks
from .geometry.alignment import Alignment, align_affine, align_similarity
from .geometry.pinhole import CameraSet, decompose_projection, project_points, triangulate_points
from .geometry.triangulation import TriangulationResult, triangulate_midpoint
from .perspective import PerspectiveSettings, reconstruct_perspective
from .points import PointStatus, rms_std
from .reconstruction import FrameStatus, NoiseEstimate, Observations, Reconstruction

__all__ = [
    "Alignment",
    "CameraSet",
    "FrameStatus",
    "FusionHistory",
    "FusionSettings",
    "LandmarkEstimates",
    "NoiseEstimate",
    "Observations",
    "PerspectiveSettings",
    "PointStatus",
    "Reconstruction",
    "TriangulationResult",
    "TruncatedSVD",
    "align_affine",
    "align_similarity",
    "estimate_landmarks",
    "decompose_projection",
    "factorize",
    "fuse",
    "metric_upgrade",
    "pair_triangulations",
    "project_points",
    "reconstruct_perspective",
    "rms_std",
    "subspace_angle",
    "triangulate_midpoint",
    "triangulate_points",
    "truncated_svd",
]
