"""Structure: factorization (shape and motion) and triangulation with known motion."""

from .alignment import Alignment, align_affine, align_similarity
from .factorization import Reconstruction, factorize, metric_upgrade
from .lowrank import TruncatedSVD, subspace_angle, truncated_svd

__all__ = [
    "Alignment",
    "Reconstruction",
    "TruncatedSVD",
    "align_affine",
    "align_similarity",
    "factorize",
    "metric_upgrade",
    "subspace_angle",
    "truncated_svd",
]
