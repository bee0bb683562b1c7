"""Estimation core: batched Kalman filter, motion models and fusion under known motion.

Nothing in this subpackage knows about images.
"""

from .fusion import FusionResult, fuse_closed_form, fuse_recursive
from .kalman import KalmanFilter, UpdateResult, kalman_predict, kalman_update
from .models import LinearGaussianModel, constant_velocity_2d, initial_state

__all__ = [
    "FusionResult",
    "KalmanFilter",
    "LinearGaussianModel",
    "UpdateResult",
    "constant_velocity_2d",
    "fuse_closed_form",
    "fuse_recursive",
    "initial_state",
    "kalman_predict",
    "kalman_update",
]
