"""Calibrated reconstruction from point tracks when the camera motion is unknown.

Given each frame's intrinsics K and the tracks' pixel positions, recover the
camera poses and the 3-D points, each point with a covariance in the
free-network gauge (:mod:`.bundle`).

Pipeline (``method="batch"``, the default)
------------------------------------------
1. **Initial pair.**  Frame pairs sharing many tracks are tried: an essential
   matrix by RANSAC (OpenCV ``findEssentialMat`` on normalised coordinates) and
   a homography on the same matches.  A pair whose matches a homography
   explains (almost) as well is degenerate — a planar scene or a camera that
   only rotated — and is skipped.  The pose comes from ``recoverPose``
   (cheirality), the points from linear triangulation (:mod:`.pinhole`); the
   pair that maximises (inliers × median triangulation angle², the angle capped
   at 20°) starts the reconstruction, in the first camera's frame with unit
   baseline.
2. **Growth.**  The unregistered frame that sees the most reconstructed points
   is registered by PnP with RANSAC (``solvePnPRansac``, then ``solvePnPRefineLM``
   on the inliers); the tracks it completes are triangulated with the
   known-camera fusion engine (:func:`~kalmansfm.structure.fusion.fuse`, per-point maximum
   likelihood with leave-one-out outlier rejection); a bundle adjustment with a
   Huber loss follows whenever the registered set has grown by a quarter, and
   observations beyond twice the outlier threshold are dropped.
3. **Refinement.**  Every track is re-estimated from all its registered
   observations (so an early wrong rejection is undone), then bundle
   adjustment with the robust loss, then rounds of [re-estimate the points
   with leave-one-out outlier tests → bundle adjustment by plain least squares
   on the inliers] until a round changes neither the inliers nor the reconstructed
   tracks; a round fuses again only the tracks whose result could change (those
   with observations to readmit, or that fail the fusion's tests at their
   bundle-adjusted point).  An observation is an
   outlier when its leave-one-out residual (where the other views put it) is
   beyond both ``outlier_threshold_px`` and the χ²(2) bound of
   ``outlier_probability`` under the estimated σ.
4. **Uncertainty.**  σ is estimated from the inlier residuals with the degrees
   of freedom counted (2 per observation − 6 per camera − 3 per point + 7 for
   the gauge), and the covariances are those of :func:`.bundle.free_network_covariances`.

``method="recursive"`` is the report's view instead (:mod:`.recursive`).

Frames that cannot be registered (too few tracks shared with the
reconstruction, or no consistent pose) keep NaN poses and a frame status;
tracks that cannot be triangulated keep NaN points and a point status.  A scene
without parallax is refused with a message saying so.
"""

from __future__ import annotations

from ...errors import InvalidInputError
from .bundle import single_threaded_blas
from .settings import (
    COVARIANCE_GAUGE,
    DEFAULT_OUTLIER_THRESHOLD_PX,
    PERSPECTIVE_METHODS,
    FrameStatus,
    PerspectiveSettings,
    validate_tracks_and_intrinsics,
)
from .incremental import reconstruct_incremental
from .recursive import reconstruct_recursive
from ..reconstruction import PerspectiveDetails, Reconstruction

__all__ = [
    "COVARIANCE_GAUGE",
    "DEFAULT_OUTLIER_THRESHOLD_PX",
    "PERSPECTIVE_METHODS",
    "FrameStatus",
    "PerspectiveSettings",
    "reconstruct_perspective",
]


@single_threaded_blas
def reconstruct_perspective(observations: object, intrinsics: object, method: str | None = None, *,
                            outlier_threshold_px: float | None = None,
                            settings: PerspectiveSettings | None = None,
                            start: Reconstruction | None = None) -> Reconstruction:
    """Camera poses and 3-D points from calibrated point tracks, with covariances in the free-network gauge.

    Parameters
    ----------
    observations : (F, P, 2) float
        Pixel positions (x = column, y = row) of P tracks in F frames; NaN where a
        track is not observed.
    intrinsics : (3, 3) or (F, 3, 3)
        K = [[fx, s, cx], [0, fy, cy], [0, 0, 1]] of every frame (or one for all).
    method : {"batch", "recursive"}, default "batch"
        ``"batch"``: incremental reconstruction and bundle adjustment (the
        module docstring); ``"recursive"``: the report's relative orientation of
        consecutive frames and recursive structure fusion (:mod:`.recursive`).
    outlier_threshold_px : float, default :data:`DEFAULT_OUTLIER_THRESHOLD_PX`
        An observation farther than this (pixels) from where the other views put
        its point is an outlier (unless the estimated noise σ makes the χ² bound wider).
    settings : PerspectiveSettings, optional
        All options at once; then ``method`` and ``outlier_threshold_px`` must not be
        given as well (they belong inside ``settings``).
    start : Reconstruction, optional
        A batch reconstruction of the same F frames (e.g. of some of these tracks): its registered
        poses replace the initial pair, and the result is in its frame (batch method only).

    Returns
    -------
    Reconstruction
        ``kind="perspective"``, ``camera_model="pinhole"``: the poses of the registered frames
        (``frame_status``), the points, their covariances and the pose covariances in the
        free-network gauge, the observations used, σ estimated from the inlier residuals
        (``noise``) and the initial pair (``details``).

    Raises
    ------
    InvalidInputError
        Bad shapes, non-finite positions, a missing or malformed K; ``settings`` given
        together with ``method`` or ``outlier_threshold_px``.
    NotEnoughDataError
        No frame pair to start from: too few shared tracks, or no parallax (all
        points on a plane, a camera that only rotated).

    Examples
    --------
    >>> from kalmansfm.scenes.perspective import perspective_scene
    >>> scene = perspective_scene(frames=6, points=150, pixel_std=0.5, seed=3)
    >>> rec = reconstruct_perspective(scene.observations, scene.intrinsics)
    >>> int(rec.registered.sum()), int(rec.reconstructed.sum()) >= 145, round(rec.noise.std, 1)
    (6, True, 0.5)
    """
    if settings is None:
        defaults = PerspectiveSettings()
        settings = PerspectiveSettings(
            method=defaults.method if method is None else method,
            outlier_threshold_px=defaults.outlier_threshold_px if outlier_threshold_px is None else outlier_threshold_px)
    elif method is not None or outlier_threshold_px is not None:
        raise InvalidInputError("reconstruct_perspective: give method and outlier_threshold_px inside settings, "
                                "not beside it (settings would silently win)")
    obs, K = validate_tracks_and_intrinsics(observations, intrinsics)
    if start is not None:
        _check_start(start, settings, len(obs))
    if settings.method == "recursive":
        return reconstruct_recursive(obs, K, settings)
    return reconstruct_incremental(obs, K, settings, start)


def _check_start(start: object, settings: PerspectiveSettings, frames: int) -> None:
    if settings.method != "batch":
        raise InvalidInputError(f"reconstruct_perspective: start poses are for the batch method, not {settings.method!r}")
    if not isinstance(start, Reconstruction) or start.kind != "perspective" or start.rotations.shape[0] != frames \
            or not isinstance(start.details, PerspectiveDetails):
        what = type(start).__name__ if not isinstance(start, Reconstruction) else \
            f"a {start.kind} reconstruction of {start.rotations.shape[0]} frames"
        raise InvalidInputError(f"reconstruct_perspective: start must be a batch perspective reconstruction of the "
                                f"same {frames} frames; got {what}")
