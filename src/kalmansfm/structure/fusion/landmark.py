"""Landmarks from a moving camera with known motion (the report's Task 7), on the known-camera fusion engine.

Task 7 of Thomas & Oliensis (``004_cd423c68da9c9743.txt``, section 7): a camera
moves with known motion and tracks landmarks; the goal is each landmark's
position in the current camera frame after every image, with an uncertainty
one can trust.  Known motion is known cameras: image k is the camera
P_k = diag(f, f, 1) [A_k | -c_k] with X_k = A_k X_0 - c_k, and every method is
:func:`~kalmansfm.structure.fusion.fuse` with its history (the estimate
after every image), moved into camera frame k.

``method="pairs"`` (the report's scheme)
    Each consecutive pair of a landmark's observations is triangulated
    (:func:`~kalmansfm.structure.geometry.triangulation.triangulate_midpoint`, eqs. 29-31),
    given its first-order covariance (eq. 34) and fused by the Kalman filter as a
    direct measurement — the same recursion as :func:`~kalmansfm.fuse_recursive`
    with the motion x_k = C_{k-1} x_{k-1} - b_{k-1} (eq. 23).  Consecutive pairs
    share an image and the first-order covariance is evaluated at the noisy image
    points: the fused covariance is too small (``docs/task7.md``).

``method="recursive"`` (the paper's Kalman fusion, consistent)
    The landmark's inverse depth in its first image, started from its first two
    images and updated by an iterated EKF on each further image's projection.

``method="batch"`` (Gauss-Newton maximum likelihood, the reference)
    After every image k, the landmark is re-estimated from *all* its observations
    0..k; covariance σ² (JᵀJ)⁻¹ at the solution.

Every observation is used (no outlier test: the simulation has none).  Poses:
``rotations[k]`` and ``translations[k]`` (C_k, b_k) take a point's coordinates
from camera frame k to camera frame k+1, X_{k+1} = C_k X_k - b_k.  Image
coordinates follow :mod:`kalmansfm.structure.geometry.triangulation`: (x, y) =
(f X / Z, f Y / Z) from the principal point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InvalidInputError, NotEnoughDataError
from ..._validation import as_float_array, check_choice, check_positive
from ..geometry.pinhole import CameraSet
from .fuse import fuse
from .pairs import pair_triangulations
from .settings import FUSION_METHODS
from ..geometry.triangulation import check_focal, check_motion

__all__ = [
    "DEFAULT_METHOD",
    "TASK7_DEFAULT_METHOD",
    "check_method",
    "LandmarkEstimates",
    "estimate_landmarks",
    "project",
]

#: The default of :func:`estimate_landmarks`: Gauss-Newton maximum likelihood, the reference estimator.
DEFAULT_METHOD = "batch"
#: The default of the Task 7 reproduction (``kalmansfm tables --task 7``, ``kalmansfm consistency
#: --task 7`` and the functions behind them): the report's own scheme, so that the table is the
#: report's table and the consistency check shows how over-confident that scheme is.
TASK7_DEFAULT_METHOD = "pairs"


@dataclass(frozen=True)
class LandmarkEstimates:
    """Estimates of L landmarks after each of K images, in the camera frame of that image.

    Attributes
    ----------
    method : "pairs", "batch" or "recursive".
    estimates : (K, L, 3) — the landmark in camera frame k after image k; NaN
        where the method has no estimate yet (always at k = 0: one image gives no depth).
    covariances : (K, L, 3, 3) — the method's covariance of ``estimates``.
    measurements : (K, L, 3) — the single-pair triangulation of the landmark's previous
        observation and image k (images (k-1, k) when it is seen in both), in frame k;
        NaN at k = 0 and where it failed.
    measurement_covariances : (K, L, 3, 3) — its first-order covariance (eq. 34).
    measurement_status : (K, L) int8 — the pair triangulation's :class:`~.points.PointStatus`
        (``OK``, ``DEGENERATE`` for parallel rays, ``BEHIND_CAMERA``, ``TOO_FEW_VIEWS`` where
        no pair ends at image k).
    converged : (K, L) bool — the method has a finite estimate after image k.
    inverse_depth, inverse_depth_covariances : (K, L, 3), (K, L, 3, 3) or None — for
        ``recursive``, the filter's state after image k: (x/z, y/z, 1/z) of the landmark in
        the camera frame of its first image (finite also where the depth is not determined
        yet and ``estimates`` is NaN).
    """

    method: str
    estimates: np.ndarray
    covariances: np.ndarray
    measurements: np.ndarray
    measurement_covariances: np.ndarray
    measurement_status: np.ndarray
    converged: np.ndarray
    inverse_depth: np.ndarray | None = None
    inverse_depth_covariances: np.ndarray | None = None

    @property
    def standard_deviations(self) -> np.ndarray:
        """(K, L, 3) per-axis standard deviations of ``estimates``."""
        return np.sqrt(np.diagonal(self.covariances, axis1=-2, axis2=-1))

    @property
    def measurement_standard_deviations(self) -> np.ndarray:
        """(K, L, 3) per-axis standard deviations of ``measurements``."""
        return np.sqrt(np.diagonal(self.measurement_covariances, axis1=-2, axis2=-1))


def project(points: np.ndarray, focal: float) -> np.ndarray:
    """Pinhole projection (..., 3) -> (..., 2): (x, y) = (f X / Z, f Y / Z).

    Examples
    --------
    >>> project(np.array([1.0, 2.0, 10.0]), 500.0)
    array([ 50., 100.])
    """
    points = np.asarray(points, dtype=float)
    return focal * points[..., :2] / points[..., 2:3]


def _cumulative_poses(C: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A_k, c_k with X_k = A_k X_0 - c_k for k = 0..K-1."""
    K = C.shape[0] + 1
    A = np.empty((K, 3, 3))
    c = np.empty((K, 3))
    A[0], c[0] = np.eye(3), 0.0
    for k in range(K - 1):
        # X_{k+1} = C_k (A_k X_0 - c_k) - b_k
        A[k + 1] = C[k] @ A[k]
        c[k + 1] = C[k] @ c[k] + b[k]
    return A, c


def _validate(observations: object, rotations: object, translations: object, focal: object, pixel_std: object
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    f = check_focal(focal)
    obs = as_float_array("observations", observations)
    if obs.ndim == 2 and obs.shape[-1] == 2:
        obs = obs[:, None, :]
    if obs.ndim != 3 or obs.shape[-1] != 2:
        raise InvalidInputError(
            f"observations must have shape (K images, L landmarks, 2) as (x, y), NaN where unseen; got {obs.shape}"
        )
    K = obs.shape[0]
    if K < 2:
        raise NotEnoughDataError(f"estimate_landmarks needs >= 2 images; got {K}")
    if np.isinf(obs).any():
        raise InvalidInputError("observations must not contain infinity (NaN marks an unseen landmark)")
    C = as_float_array("rotations", rotations)
    b = as_float_array("translations", translations)
    if C.shape != (K - 1, 3, 3):
        raise InvalidInputError(f"rotations must have shape ({K - 1}, 3, 3) for {K} images; got {C.shape}")
    if b.shape != (K - 1, 3):
        raise InvalidInputError(f"translations must have shape ({K - 1}, 3) for {K} images; got {b.shape}")
    for k in range(K - 1):
        check_motion(C[k], b[k], what=f"s[{k}]")
    sigma = check_positive("pixel_std", pixel_std, "pixels; the estimators weight observations by 1/σ²")
    return obs, C, b, f, sigma


def _to_frames(A: np.ndarray, c: np.ndarray, X: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and covariances (K, L, ...) in frame 0 moved into frame k: X_k = A_k X - c_k."""
    return (np.einsum("kij,klj->kli", A, X) - c[:, None, :],
            np.einsum("kij,kljm,knm->klin", A, P, A))


def check_method(method: str) -> str:
    """``method`` if it is one of :data:`~kalmansfm.structure.fusion.FUSION_METHODS`.

    Parameters
    ----------
    method : str
        The name of a landmark estimator.

    Returns
    -------
    str
        ``method`` unchanged.

    Raises
    ------
    InvalidInputError
        ``method`` is not one of the fusion methods.

    Examples
    --------
    >>> check_method("pairs")
    'pairs'
    """
    check_choice("method", method, FUSION_METHODS)
    return method


def estimate_landmarks(
    observations: object,
    rotations: object,
    translations: object,
    focal: float,
    pixel_std: object,
    method: str = DEFAULT_METHOD,
) -> LandmarkEstimates:
    """Estimate landmarks after every image from a camera with known motion.

    Parameters
    ----------
    observations : (K, L, 2) float, or (K, 2) for one landmark
        Image coordinates (x, y) of L landmarks in K images (from the principal
        point, pixels); NaN where a landmark is not seen.
    rotations : (K-1, 3, 3)
        C_k with X_{k+1} = C_k X_k - b_k (camera frame k to k+1).
    translations : (K-1, 3)
        b_k, non-zero (no triangulation without a baseline).
    focal : float
        Focal length f > 0 in pixels.
    pixel_std : float
        Standard deviation (> 0) of the image noise in x and y, pixels.
    method : {"batch", "recursive", "pairs"}
        ``"batch"``: Gauss-Newton maximum likelihood on all observations so far,
        re-solved after every image.  ``"recursive"``: the paper's Kalman fusion,
        inverse depth updated image by image (consistent from the first images).
        ``"pairs"``: the report's Kalman fusion of consecutive-pair triangulations
        (over-confident).

    Returns
    -------
    LandmarkEstimates
        Estimates in the camera frame of each image, the pair triangulations and
        status flags.  A landmark that cannot be estimated yet is NaN there, with
        ``converged`` False; nothing raises in the middle of a sequence.

    Examples
    --------
    A landmark seen from three positions along the optical axis, no noise:

    >>> import numpy as np
    >>> X0 = np.array([4.0, 2.0, 20.0]); b = np.array([0.0, 0.0, 1.0])
    >>> X = np.stack([X0 - k * b for k in range(3)])
    >>> obs = 500.0 * X[:, :2] / X[:, 2:]
    >>> est = estimate_landmarks(obs, np.stack([np.eye(3)] * 2), np.stack([b] * 2), 500.0, 0.5)
    >>> est.estimates[2, 0].round(6)
    array([ 4.,  2., 18.])
    >>> bool(np.isnan(est.estimates[0]).all())
    True
    """
    check_method(method)
    obs, C, b, f, sigma = _validate(observations, rotations, translations, focal, pixel_std)
    K, L, _ = obs.shape
    A, c = _cumulative_poses(C, b)
    # image k is the camera diag(f, f, 1) [A_k | -c_k]: world = camera frame 0, points in front
    cameras = CameraSet.from_pose(np.diag([f, f, 1.0]), A, -c)
    fused = fuse(obs, cameras, method=method, pixel_std=sigma, outlier_probability=1.0, history=True, orientation=1)
    estimates, covariances = _to_frames(A, c, *fused.details.history.dense(K, L))
    pairs = pair_triangulations(obs, cameras, sigma, orientation=1)
    measurements, measurement_covariances = _to_frames(A, c, pairs.points, pairs.covariances)
    converged = np.isfinite(estimates).all(axis=2) & np.isfinite(covariances).all(axis=(2, 3))
    states = fused.details.history.dense(K, L, states=True) if method == "recursive" else (None, None)
    return LandmarkEstimates(method, estimates, covariances, measurements, measurement_covariances, pairs.status,
                             converged, *states)
