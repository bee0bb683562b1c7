"""Structure: factorization (shape and motion), alignment, triangulation and landmark fusion with known motion,
and calibrated reconstruction with unknown motion (bundle adjustment).

Nothing here knows about images or tracks files; it works on arrays of positions.
"""

from .alignment import Alignment, align_affine, align_similarity
from .factorization import Reconstruction, factorize, metric_upgrade
from .landmark import LandmarkEstimates, estimate_landmarks
from .lowrank import TruncatedSVD, subspace_angle, truncated_svd
from .perspective import PerspectiveReconstruction, PerspectiveSettings, reconstruct_perspective
from .triangulation import TriangulationResult, triangulate_midpoint

__all__ = [
    "Alignment",
    "LandmarkEstimates",
    "PerspectiveReconstruction",
    "PerspectiveSettings",
    "Reconstruction",
    "TriangulationResult",
    "TruncatedSVD",
    "align_affine",
    "align_similarity",
    "estimate_landmarks",
    "factorize",
    "metric_upgrade",
    "reconstruct_perspective",
    "subspace_angle",
    "triangulate_midpoint",
    "truncated_svd",
]
