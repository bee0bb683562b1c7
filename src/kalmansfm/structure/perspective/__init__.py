"""Calibrated (pinhole) reconstruction with unknown motion: cameras and points from tracks
and intrinsics, by incremental registration and bundle adjustment or by the report's
recursive relative orientation, with covariances in the free-network gauge."""

from .reconstruct import reconstruct_perspective
from .settings import (
    COVARIANCE_GAUGE,
    DEFAULT_OUTLIER_THRESHOLD_PX,
    PERSPECTIVE_METHODS,
    FrameStatus,
    PerspectiveSettings,
)

__all__ = [
    "COVARIANCE_GAUGE",
    "DEFAULT_OUTLIER_THRESHOLD_PX",
    "PERSPECTIVE_METHODS",
    "FrameStatus",
    "PerspectiveSettings",
    "reconstruct_perspective",
]
