"""What every fusion entry point checks first: observations against cameras, and the scene's orientation."""

from __future__ import annotations

import numpy as np

from ...errors import InvalidInputError, NotEnoughDataError
from ..._validation import as_float_array
from ..geometry.pinhole import CameraSet, triangulate_points

__all__ = ["scene_orientation_of", "validate_inputs"]

# Points used to decide the scene orientation (the sign of the depths most points agree on).
_ORIENTATION_SAMPLE = 2_000


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


def scene_orientation_of(cams: CameraSet, obs: np.ndarray) -> int:
    """The sign of the depths most (linearly triangulated) points agree on."""
    counts = np.isfinite(obs[..., 0]).sum(axis=0)
    sample = np.flatnonzero(counts >= 2)[:_ORIENTATION_SAMPLE]
    if sample.size == 0:
        return 1
    return triangulate_points(cams, obs[:, sample]).orientation
