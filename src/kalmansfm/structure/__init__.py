"""Structure: factorization (shape and motion), alignment, triangulation, structure fusion with known cameras,
and calibrated reconstruction with unknown motion (bundle adjustment).

Nothing here knows about images or tracks files; it works on arrays of positions.
"""

from .geometry.alignment import Alignment, align_affine, align_similarity
from .affine.factorization import Reconstruction, factorize, metric_upgrade
from .fusion.landmark import LandmarkEstimates, estimate_landmarks
from .affine.lowrank import TruncatedSVD, subspace_angle, truncated_svd
from .perspective.reconstruct import PerspectiveReconstruction, PerspectiveSettings, reconstruct_perspective
from .geometry.pinhole import CameraSet, decompose_projection, project_points, triangulate_points
from .fusion.point_fusion import FusedStructure, FusionHistory, FusionSettings, fuse, pair_triangulations
from .points import PointStatus, rms_std
from .geometry.triangulation import TriangulationResult, triangulate_midpoint
from .affine.uncertainty import PointUncertainty, point_uncertainty

__all__ = [
    "Alignment",
    "CameraSet",
    "FusedStructure",
    "FusionHistory",
    "FusionSettings",
    "LandmarkEstimates",
    "PerspectiveReconstruction",
    "PerspectiveSettings",
    "PointStatus",
    "PointUncertainty",
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
    "point_uncertainty",
    "project_points",
    "reconstruct_perspective",
    "rms_std",
    "subspace_angle",
    "triangulate_midpoint",
    "triangulate_points",
    "truncated_svd",
]
