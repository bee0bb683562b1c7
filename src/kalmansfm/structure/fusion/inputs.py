"""What every fusion entry point checks first: observations against cameras, and the scene's orientation."""

from __future__ import annotations

import numpy as np

from ...errors import InvalidInputError, NotEnoughDataError
from ..._validation import as_float_array
from ..geometry.pinhole import CameraSet
from ..reconstruction import Observations

__all__ = ["are_poses", "validate_inputs", "validate_sparse_inputs"]

# |λ - 1| below this for every camera: the cameras are poses K [R | t] (from_pose, K, R, t files).
_POSE_SCALE_TOLERANCE = 1e-6


def validate_inputs(observations: object, cameras: object) -> tuple[CameraSet, np.ndarray]:
    cams = cameras if isinstance(cameras, CameraSet) else CameraSet.from_matrices(cameras)
    obs = as_float_array("observations", observations)
    V = len(cams)
    if obs.ndim != 3 or obs.shape[0] != V or obs.shape[2] != 2:
        raise InvalidInputError(
            f"observations must have shape ({V} views, N points, 2) as (x, y), NaN where unseen; got {obs.shape}")
    if np.isinf(obs).any():
        raise InvalidInputError("observations must not contain infinity (NaN marks an unseen point)")
    if V < 2:
        raise NotEnoughDataError(f"fusing structure needs >= 2 cameras; got {V}")
    # a point with one NaN coordinate is unseen in that view
    obs = np.where(np.isnan(obs).any(axis=2, keepdims=True), np.nan, obs)
    return cams, obs


def validate_sparse_inputs(observations: Observations, cameras: object) -> CameraSet:
    """The cameras of observations given per observation (frame = view index), after checking they agree."""
    cams = cameras if isinstance(cameras, CameraSet) else CameraSet.from_matrices(cameras)
    V = len(cams)
    if observations.shape[0] != V:
        raise InvalidInputError(f"observations must be over the {V} views of the cameras; they are over "
                                f"{observations.shape[0]} frames")
    if not np.isfinite(observations.xy).all():
        raise InvalidInputError("observations given per observation must be finite (leave out what is unseen)")
    if V < 2:
        raise NotEnoughDataError(f"fusing structure needs >= 2 cameras; got {V}")
    return cams


def are_poses(cams: CameraSet) -> bool:
    """Every camera is exactly K [R | t] with det R = +1 and K[2, 2] = 1 (scale λ = +1): a pose, not a bare P.

    Such cameras fix which side is in front (positive depth); a projection matrix of unknown
    scale and sign does not (a mirrored world frame looks like points behind every camera).
    """
    return bool(np.all(np.abs(cams.decompose().scales - 1.0) <= _POSE_SCALE_TOLERANCE))
