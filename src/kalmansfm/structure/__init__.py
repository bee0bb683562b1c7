"""Structure: factorization (shape and motion), alignment, triangulation, structure fusion with known cameras,
and calibrated reconstruction with unknown motion (bundle adjustment).

Nothing here knows about images or tracks files; it works on arrays of positions.
"""

from .alignment import Alignment, align_affine, align_similarity
from .factorization import Reconstruction, factorize, metric_upgrade
from .landmark import LandmarkEstimates, estimate_landmarks
from .lowrank import TruncatedSVD, subspace_angle, truncated_svd
from .perspective import PerspectiveReconstruction, PerspectiveSettings, reconstruct_perspective
from .pinhole import CameraSet, PointStatus, decompose_projection, project_points, triangulate_points
from .point_fusion import FusedStructure, FusionHistory, FusionSettings, fuse, pair_triangulations
from .triangulation import TriangulationResult, triangulate_midpoint

__all__ = [
    "Alignment",
    "CameraSet",
    "FusedStructure",
    "FusionHistory",
    "FusionSettings",
    "PointStatus",
    "LandmarkEstimates",
    "PerspectiveReconstruction",
    "PerspectiveSettings",
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
    "subspace_angle",
    "triangulate_midpoint",
    "triangulate_points",
    "truncated_svd",
]
