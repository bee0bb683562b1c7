"""Estimation core: batched Kalman filter, smoothing, motion models and fusion under known motion.

Nothing in this subpackage knows about images.
"""

from .fusion import FusionResult, fuse_closed_form, fuse_recursive
from .kalman import (
    InnovationStatistics,
    KalmanFilter,
    UpdateResult,
    innovation_statistics,
    kalman_predict,
    kalman_update,
)
from .models import LinearGaussianModel, constant_velocity_2d, initial_state
from .smoothing import FilterRun, SmoothedRun, smooth

__all__ = [
    "FilterRun",
    "FusionResult",
    "InnovationStatistics",
    "KalmanFilter",
    "LinearGaussianModel",
    "SmoothedRun",
    "UpdateResult",
    "constant_velocity_2d",
    "fuse_closed_form",
    "fuse_recursive",
    "initial_state",
    "innovation_statistics",
    "kalman_predict",
    "kalman_update",
    "smooth",
]
