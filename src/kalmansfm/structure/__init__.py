"""Structure: factorization (shape and motion) and triangulation with known motion."""

from .consistency import ConsistencyResult, run_consistency, task2_consistency, task7_consistency
from .landmark import LandmarkEstimates, estimate_landmarks
from .task7 import Task7Result, simulate_task7
from .triangulation import TriangulationResult, triangulate_midpoint

__all__ = [
    "ConsistencyResult",
    "LandmarkEstimates",
    "Task7Result",
    "TriangulationResult",
    "estimate_landmarks",
    "run_consistency",
    "simulate_task7",
    "task2_consistency",
    "task7_consistency",
    "triangulate_midpoint",
]
