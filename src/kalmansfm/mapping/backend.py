"""The one place that reads the back end's record: what guided matching needs from a reconstruction.

Everything else in :mod:`kalmansfm.mapping` works on :class:`CameraSolution`, the few arrays of a
:class:`~kalmansfm.structure.Reconstruction` it needs; :func:`read_solution` is the only code that
reads the record.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..structure.reconstruction import FrameStatus, Reconstruction

__all__ = ["CameraSolution", "read_solution"]


@dataclass(frozen=True)
class CameraSolution:
    """Cameras and points of a reconstruction, as the front end uses them (x_cam = R X + t).

    Attributes
    ----------
    registered : (F,) bool.
    rotations, translations : (F, 3, 3), (F, 3) — NaN where not registered.
    camera_covariances : (F, 6, 6) — of (δω, δC); NaN where not registered.
    points : (P, 3) — NaN where not reconstructed.
    point_covariances : (P, 3, 3) — NaN where not reconstructed.
    inliers : (F, P) bool — the observations the reconstruction kept.
    pixel_std : σ of the image noise (pixels).
    pose_failed : (F,) bool — views the back end tried to pose and could not (the others without a camera
        shared too few points with the reconstruction).
    warnings : the back end's warnings.
    """

    registered: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    camera_covariances: np.ndarray
    points: np.ndarray
    point_covariances: np.ndarray
    inliers: np.ndarray
    pixel_std: float
    pose_failed: np.ndarray
    warnings: tuple[str, ...] = ()

    @property
    def reconstructed(self) -> np.ndarray:
        """(P,) bool — tracks with a 3-D point."""
        return np.isfinite(self.points).all(axis=1)

    @property
    def centres(self) -> np.ndarray:
        """(F, 3) camera centres -Rᵀ t."""
        return -np.einsum("fji,fj->fi", self.rotations, self.translations)


def read_solution(reconstruction: Reconstruction) -> CameraSolution:
    """The front end's view of a back-end reconstruction (the only coupling to its record).

    Examples
    --------
    >>> from kalmansfm.scenes.perspective import perspective_scene
    >>> from kalmansfm.structure.perspective import reconstruct_perspective
    >>> scene = perspective_scene(frames=5, points=120, pixel_std=0.5, seed=1)
    >>> solution = read_solution(reconstruct_perspective(scene.observations, scene.intrinsics))
    >>> bool(solution.registered.all()), solution.points.shape, bool(solution.reconstructed.sum() > 100)
    (True, (120, 3), True)
    """
    return CameraSolution(
        registered=reconstruction.registered.copy(),
        rotations=reconstruction.rotations,
        translations=reconstruction.translations,
        camera_covariances=reconstruction.pose_covariances,
        points=np.where(reconstruction.reconstructed[:, None], reconstruction.points, np.nan),
        point_covariances=reconstruction.point_covariances,
        inliers=reconstruction.observations.used_mask(),
        pixel_std=float(reconstruction.noise.std),
        pose_failed=reconstruction.frame_status == FrameStatus.POSE_FAILED,
        warnings=tuple(reconstruction.warnings),
    )
