"""Structure: factorization (shape and motion), alignment, and triangulation and landmark fusion with known motion.

Nothing here knows about images or tracks files; it works on arrays of positions.
"""

from .alignment import Alignment, align_affine, align_similarity
from .factorization import Reconstruction, factorize, metric_upgrade
from .landmark import LandmarkEstimates, estimate_landmarks
from .lowrank import TruncatedSVD, subspace_angle, truncated_svd
from .triangulation import TriangulationResult, triangulate_midpoint

__all__ = [
    "Alignment",
    "LandmarkEstimates",
    "Reconstruction",
    "TriangulationResult",
    "TruncatedSVD",
    "align_affine",
    "align_similarity",
    "estimate_landmarks",
    "factorize",
    "metric_upgrade",
    "subspace_angle",
    "triangulate_midpoint",
    "truncated_svd",
]
