"""Guided matching (active search): predict where a known point must appear in a view, and look for
its feature only inside the gate that prediction allows.

For a point X with covariance Σ_X, a camera (R, t) with covariance Σ_c of (δω, δC) and intrinsics K,
the predicted pixel is x̂ = π(K (R X + t)); to first order its error has covariance

    S = J_X Σ_X J_Xᵀ + J_c Σ_c J_cᵀ + σ² I,

J_X = ∂x/∂X = J_y R, J_c = [∂x/∂δω, ∂x/∂C] = [-J_y [y]×, -J_y R] with y = R X + t the camera-frame
point and J_y = (K_{1:2} - x̂ e₃ᵀ) / y₃ (the rotation is updated on the left, R ← exp([δω]×) R, as in the
bundle adjustment).  A feature f of the view is a candidate when (x_f - x̂)ᵀ S⁻¹ (x_f - x̂) is inside the χ²₂
quantile of the gate probability, or within a pixel floor, and never beyond a pixel ceiling.  Among the
candidates of one gate the descriptor nearest to the point's (its descriptor in the view that saw it from
nearest) wins if it passes a ratio test against the second candidate and an absolute distance bound.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from ..errors import InvalidInputError
from ..features import ImageFeatures
from ..structure.geometry.rotation import cross_matrix

__all__ = ["GuidedMatches", "Prediction", "guided_search", "pose_from_correspondences", "predict_points"]

# Candidates examined per gate (nearest first); a gate holding more features than this is ambiguous anyway.
_MAX_CANDIDATES = 8


@dataclass(frozen=True)
class Prediction:
    """Where points should appear in one view.

    Attributes
    ----------
    pixels : (n, 2) predicted positions.
    covariances : (n, 2, 2) covariance S of each prediction's error (pixels²).
    depths : (n,) camera-frame depth (the point is in front when > 0).
    """

    pixels: np.ndarray
    covariances: np.ndarray
    depths: np.ndarray


@dataclass(frozen=True)
class GuidedMatches:
    """Features found inside the gates.

    Attributes
    ----------
    predictions : (k,) index of the prediction (the point) each match belongs to.
    features : (k,) index of the matched feature in the view.
    distances : (k,) descriptor distance.
    mahalanobis : (k,) squared Mahalanobis distance of the feature to the prediction.
    """

    predictions: np.ndarray
    features: np.ndarray
    distances: np.ndarray
    mahalanobis: np.ndarray

    def __len__(self) -> int:
        return int(self.predictions.shape[0])


def predict_points(points: np.ndarray, point_covariances: np.ndarray | None, rotation: np.ndarray,
                   translation: np.ndarray, intrinsics: np.ndarray, camera_covariance: np.ndarray | None,
                   pixel_std: float) -> Prediction:
    """Project (n, 3) points into one camera with the first-order covariance of the projection.

    ``point_covariances`` (n, 3, 3) and ``camera_covariance`` (6, 6, over (δω, δC)) may be None (no
    uncertainty from them); NaN covariances count as none.

    Examples
    --------
    >>> K = np.array([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])
    >>> p = predict_points(np.array([[0.0, 0, 2]]), np.eye(3)[None] * 1e-4, np.eye(3), np.zeros(3), K, None, 0.5)
    >>> p.pixels.tolist(), np.round(p.covariances[0], 4).tolist()
    ([[50.0, 50.0]], [[0.5, 0.0], [0.0, 0.5]])
    """
    X = np.asarray(points, np.float64)
    y = X @ rotation.T + translation
    depth = y[:, 2]
    safe = np.where(np.abs(depth) > 1e-12, depth, 1e-12)
    h = y @ intrinsics.T
    pixels = h[:, :2] / safe[:, None]
    # J_y = (K_{1:2} - x e3ᵀ) / y3
    J_y = (intrinsics[None, :2, :] - pixels[:, :, None] * np.array([0.0, 0.0, 1.0])) / safe[:, None, None]
    J_X = J_y @ rotation
    S = np.repeat((pixel_std**2 * np.eye(2))[None], len(X), axis=0)
    if point_covariances is not None:
        cov = np.nan_to_num(np.asarray(point_covariances, np.float64))
        S = S + J_X @ cov @ J_X.transpose(0, 2, 1)
    if camera_covariance is not None and np.isfinite(camera_covariance).all():
        J_c = np.concatenate([-J_y @ cross_matrix(y), -J_X], axis=2)  # (n, 2, 6)
        S = S + J_c @ camera_covariance @ J_c.transpose(0, 2, 1)
    return Prediction(pixels, S, depth)


def guided_search(prediction: Prediction, reference_descriptors: np.ndarray, view: ImageFeatures, *,
                  gate_chi2: float, gate_floor_px: float, max_gate_px: float, ratio: float,
                  max_distance: float) -> GuidedMatches:
    """For each prediction, the view's feature inside its gate whose descriptor matches the point's.

    Parameters
    ----------
    prediction : where the points should be (:func:`predict_points`).
    reference_descriptors : (n, D) — each point's descriptor (in the form the view's features hold them).
    view : the view's features.
    gate_chi2 : squared Mahalanobis radius of the gate (χ²₂ quantile of the gate probability).
    gate_floor_px, max_gate_px : a feature within ``gate_floor_px`` is inside whatever S says; one
        beyond ``max_gate_px`` never is.
    ratio : best descriptor distance < ratio × second best among the gate's candidates.
    max_distance : and ≤ this (Euclidean for unit vectors, Hamming for bits).

    Returns
    -------
    GuidedMatches
        At most one feature per prediction; a feature may be chosen by several predictions (the caller
        resolves that).

    Examples
    --------
    A feature planted 1 px from the prediction is found; the same descriptor 30 px away is not.

    >>> z = np.zeros(2, np.float32)
    >>> d = np.eye(4, dtype=np.float32)[:2]
    >>> view = ImageFeatures(np.array([[101.0, 100.0], [130.0, 50.0]]), z, z, z, d, False)
    >>> pred = Prediction(np.array([[100.0, 100.0], [100.0, 50.0]]), np.repeat(np.eye(2)[None], 2, 0), np.ones(2))
    >>> m = guided_search(pred, d, view, gate_chi2=9.21, gate_floor_px=1.5, max_gate_px=10.0, ratio=0.8,
    ...                   max_distance=0.5)
    >>> m.predictions.tolist(), m.features.tolist()
    ([0], [0])
    """
    n = len(prediction.pixels)
    empty = GuidedMatches(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    if n == 0 or len(view) == 0:
        return empty
    reference = np.asarray(reference_descriptors, np.float32)
    if reference.shape != (n, view.descriptors.shape[1]):
        raise InvalidInputError(f"reference_descriptors must have shape ({n}, {view.descriptors.shape[1]}); "
                                f"got {reference.shape}")
    k = min(_MAX_CANDIDATES, len(view))
    distance_px, feature = cKDTree(view.keypoints).query(prediction.pixels, k=k, distance_upper_bound=max_gate_px)
    distance_px = distance_px.reshape(n, k)
    feature = feature.reshape(n, k)
    found = np.isfinite(distance_px)
    rows, slot = np.nonzero(found)
    candidate = feature[rows, slot]
    residual = view.keypoints[candidate] - prediction.pixels[rows]
    S = prediction.covariances[rows]
    det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
    # rᵀ S⁻¹ r for a 2 × 2 S, by its adjugate
    mahalanobis = (S[:, 1, 1] * residual[:, 0] ** 2 - 2 * S[:, 0, 1] * residual[:, 0] * residual[:, 1]
                   + S[:, 0, 0] * residual[:, 1] ** 2) / np.where(det > 0, det, np.inf)
    inside = (mahalanobis <= gate_chi2) | (distance_px[rows, slot] <= gate_floor_px)
    rows, candidate, mahalanobis = rows[inside], candidate[inside], mahalanobis[inside]
    if len(rows) == 0:
        return empty
    a, b = reference[rows], view.descriptors[candidate]
    d2 = np.einsum("ij,ij->i", a, a) + np.einsum("ij,ij->i", b, b) - 2.0 * np.einsum("ij,ij->i", a, b)
    distance = np.rint(np.maximum(d2, 0.0)) if view.binary else np.sqrt(np.maximum(d2, 0.0))
    # best and second best per prediction: sort by (prediction, distance)
    order = np.lexsort((distance, rows))
    rows, candidate, distance, mahalanobis = rows[order], candidate[order], distance[order], mahalanobis[order]
    first = np.r_[True, rows[1:] != rows[:-1]]
    start = np.flatnonzero(first)
    has_second = np.r_[start[1:] - start[:-1] > 1, len(rows) - start[-1] > 1]
    second = np.full(len(start), np.inf)
    second[has_second] = distance[start[has_second] + 1]
    best = distance[start]
    accept = (best <= max_distance) & (best < ratio * second)
    chosen = start[accept]
    return GuidedMatches(rows[chosen].astype(np.int64), candidate[chosen].astype(np.int64), distance[chosen],
                         mahalanobis[chosen])


def pose_from_correspondences(points: np.ndarray, pixels: np.ndarray, intrinsics: np.ndarray, threshold_px: float,
                              min_inliers: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A camera pose from 2-D–3-D correspondences: PnP with RANSAC (SQPnP), refined on the inliers.

    Returns (rotation, translation, (n,) inlier mask), or None with fewer than ``min_inliers`` inliers.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> X = rng.uniform(-1, 1, (40, 3)) + [0, 0, 5]
    >>> K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    >>> h = X @ K.T
    >>> R, t, ok = pose_from_correspondences(X, h[:, :2] / h[:, 2:], K, 2.0, 12)
    >>> bool(np.allclose(R, np.eye(3), atol=1e-6)), int(ok.sum())
    (True, 40)
    """
    if len(points) < max(min_inliers, 4):
        return None
    cv2.setRNGSeed(seed)
    h = np.c_[pixels, np.ones(len(pixels))] @ np.linalg.inv(intrinsics).T
    x = np.ascontiguousarray(h[:, :2] / h[:, 2:])
    X = np.ascontiguousarray(points, np.float64)
    focal = np.sqrt(intrinsics[0, 0] * intrinsics[1, 1])
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(X, x, np.eye(3), None, reprojectionError=threshold_px / focal,
                                                 confidence=0.9999, iterationsCount=1000, flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inliers is None or len(inliers) < min_inliers:
        return None
    mask = np.zeros(len(X), bool)
    mask[inliers.ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(X[mask], x[mask], np.eye(3), None, rvec, tvec)
    return cv2.Rodrigues(rvec)[0], tvec.ravel(), mask
