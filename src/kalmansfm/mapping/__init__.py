"""From calibrated images to cameras and points: the feature front end (:mod:`kalmansfm.features`), the
calibrated back end (:func:`kalmansfm.structure.reconstruct_perspective`) and guided matching between them.

Arrays in (images and intrinsics), a frozen :class:`ImageReconstruction` out; reading image files is
``kalmansfm.io``'s job.
"""

from .active_search import GuidedMatchingSummary, active_search
from .backend import CameraSolution, read_solution
from .guided import GuidedMatches, Prediction, guided_search, pose_from_correspondences, predict_points
from .reconstruct import ImageReconstruction, reconstruct_images
from .settings import MappingSettings, ViewStatus

__all__ = [
    "CameraSolution",
    "GuidedMatches",
    "GuidedMatchingSummary",
    "ImageReconstruction",
    "MappingSettings",
    "Prediction",
    "ViewStatus",
    "active_search",
    "guided_search",
    "pose_from_correspondences",
    "predict_points",
    "read_solution",
    "reconstruct_images",
]
