"""Structure: factorization (shape and motion) and triangulation with known motion."""

from .alignment import Alignment, align_affine, align_similarity
from .consistency import ConsistencyResult, run_consistency, task2_consistency, task7_consistency
from .factorization import Reconstruction, factorize, metric_upgrade
from .landmark import LandmarkEstimates, estimate_landmarks
from .lowrank import TruncatedSVD, subspace_angle, truncated_svd
from .task7 import Task7Result, simulate_task7
from .triangulation import TriangulationResult, triangulate_midpoint

__all__ = [
    "Alignment",
    "ConsistencyResult",
    "LandmarkEstimates",
    "Reconstruction",
    "Task7Result",
    "TriangulationResult",
    "TruncatedSVD",
    "align_affine",
    "align_similarity",
    "estimate_landmarks",
    "factorize",
    "metric_upgrade",
    "run_consistency",
    "simulate_task7",
    "subspace_angle",
    "task2_consistency",
    "task7_consistency",
    "triangulate_midpoint",
    "truncated_svd",
]
