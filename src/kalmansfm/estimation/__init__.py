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
from .noise_model import (
    NOISE_MODELS,
    GroupScales,
    NoiseFit,
    SerialCorrelation,
    fit_noise_model,
    fit_serial_correlation,
    serial_covariance,
)
from .smoothing import FilterRun, SmoothedRun, smooth
from .split_nees import (
    PredictedNees,
    SplitCovariances,
    nees_weights,
    predict_nees,
    split_covariances,
)

__all__ = [
    "NOISE_MODELS",
    "FilterRun",
    "FusionResult",
    "GroupScales",
    "InnovationStatistics",
    "KalmanFilter",
    "LinearGaussianModel",
    "NoiseFit",
    "PredictedNees",
    "SerialCorrelation",
    "SmoothedRun",
    "SplitCovariances",
    "UpdateResult",
    "constant_velocity_2d",
    "fit_noise_model",
    "fit_serial_correlation",
    "fuse_closed_form",
    "fuse_recursive",
    "initial_state",
    "innovation_statistics",
    "kalman_predict",
    "kalman_update",
    "nees_weights",
    "predict_nees",
    "serial_covariance",
    "smooth",
    "split_covariances",
]
