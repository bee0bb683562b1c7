"""Geometric verification of a pair's matches: the epipolar geometry by OpenCV's USAC (MAGSAC++).

With both intrinsics known, the essential matrix on normalised coordinates (five-point
minimal solver); the pixel threshold becomes ``threshold / sqrt(fx_a fx_b)``-ish in normalised units
(the geometric mean of the two focal lengths).  Without intrinsics, the fundamental
matrix on pixels.  Only the inlier mask is kept: the reconstruction recomputes every pose.
"""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import InvalidInputError
from .settings import FeatureSettings

__all__ = ["normalised_points", "verify_matches"]


def normalised_points(pixels: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """(k, 2) normalised coordinates K⁻¹ (x, y, 1) of (k, 2) pixels.

    Examples
    --------
    >>> K = np.array([[100.0, 0, 50], [0, 200, 40], [0, 0, 1]])
    >>> normalised_points(np.array([[150.0, 240.0]]), K).tolist()
    [[1.0, 1.0]]
    """
    h = np.c_[pixels, np.ones(len(pixels))] @ np.linalg.inv(intrinsics).T
    return h[:, :2] / h[:, 2:]


def verify_matches(first: np.ndarray, second: np.ndarray, intrinsics_first: np.ndarray | None = None,
                   intrinsics_second: np.ndarray | None = None,
                   settings: FeatureSettings | None = None) -> np.ndarray:
    """(k,) bool — the matches consistent with one epipolar geometry (USAC MAGSAC++).

    Parameters
    ----------
    first, second : (k, 2) pixel positions of the k matches in the two images.
    intrinsics_first, intrinsics_second : (3, 3) K of each image, or both None (then the
        fundamental matrix is estimated on pixels).
    settings : FeatureSettings — ``verification_threshold_px``, ``confidence``, ``min_inliers``.

    Returns
    -------
    (k,) bool
        All False when fewer than ``min_inliers`` matches are consistent.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> X = rng.uniform(-1, 1, (60, 3)) + [0, 0, 6]
    >>> K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    >>> def project(X, R, t):
    ...     h = (X @ R.T + t) @ K.T
    ...     return h[:, :2] / h[:, 2:]
    >>> R = cv2.Rodrigues(np.array([0.0, 0.2, 0.0]))[0]
    >>> a, b = project(X, np.eye(3), np.zeros(3)), project(X, R, np.array([-1.0, 0, 0]))
    >>> b[:10] = rng.uniform(0, 640, (10, 2))                 # 10 wrong matches
    >>> ok = verify_matches(a, b, K, K)
    >>> int(ok[10:].sum()), int(ok[:10].sum())
    (50, 0)
    """
    settings = FeatureSettings() if settings is None else settings
    a = np.ascontiguousarray(first, dtype=np.float64)
    b = np.ascontiguousarray(second, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 2:
        raise InvalidInputError(f"matched positions must be two (k, 2) arrays; got {a.shape} and {b.shape}")
    if (intrinsics_first is None) != (intrinsics_second is None):
        raise InvalidInputError("give the intrinsics of both images or of neither")
    inliers = np.zeros(len(a), bool)
    if len(a) < max(settings.min_inliers, 8):
        return inliers
    cv2.setRNGSeed(settings.seed)
    if intrinsics_first is not None:
        Ka = np.asarray(intrinsics_first, np.float64)
        Kb = np.asarray(intrinsics_second, np.float64)
        focal = np.sqrt(np.sqrt(Ka[0, 0] * Ka[1, 1]) * np.sqrt(Kb[0, 0] * Kb[1, 1]))
        E, mask = cv2.findEssentialMat(normalised_points(a, Ka), normalised_points(b, Kb), np.eye(3),
                                       method=cv2.USAC_MAGSAC, prob=settings.confidence,
                                       threshold=settings.verification_threshold_px / focal)
        model_found = E is not None and E.shape == (3, 3)
    else:
        F, mask = cv2.findFundamentalMat(a, b, cv2.USAC_MAGSAC, settings.verification_threshold_px,
                                         settings.confidence)
        model_found = F is not None and F.shape == (3, 3)
    if not model_found or mask is None:
        return inliers
    inliers = mask.ravel() > 0
    if inliers.sum() < settings.min_inliers:
        inliers[:] = False
    return inliers
