"""Factorization as a :class:`~kalmansfm.structure.Reconstruction`: shape, affine cameras and each point's covariance."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from ..geometry.orthographic import camera_rotation_matrices
from ..reconstruction import AFFINE_GAUGE, AffineDetails, FrameStatus, NoiseEstimate, Observations, Reconstruction
from .factorization import DEFAULT_MAX_ITERATIONS, AffineFactors, factor_affine, single_threaded_blas
from .uncertainty import MAX_STD_RATIO, MIN_VIEWS, PointUncertainty, point_uncertainty

__all__ = ["AffineCameras", "affine_cameras", "factorize"]


@single_threaded_blas  # the points' covariances too: small products and 3 × 3 eigen-decompositions
def factorize(
    positions: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    tol: float = 1e-10,
    rng: np.random.Generator | int | None = 0,
    min_views: int = MIN_VIEWS,
    max_std_ratio: float = MAX_STD_RATIO,
    progress: Callable[[int, int], object] | None = None,
) -> Reconstruction:
    """Recover 3D shape and affine camera motion from point tracks (Tomasi–Kanade), each point with its covariance.

    Parameters
    ----------
    positions : (F, P, 2) float — x = column, y = row of point p in frame f; NaN where the
        point is not observed.  Needs F ≥ 3 frames and P ≥ 4 points.  Only read, never
        modified (large complete input is used where it lies; see
        :func:`~kalmansfm.structure.affine.factorization.factor_affine`).
    weights : (F, P) or (F, P, 2) float ≥ 0, optional — least-squares weights, typically
        1 / σ² from the tracker's posterior standard deviations
        (:meth:`kalmansfm.tracking.Tracks.observation_weights`); a zero weight ignores the entry.
    max_iterations, tol, rng : the fit's iteration cap, relative stopping tolerance and the
        seed of the randomized SVD of large complete inputs.
    min_views, max_std_ratio : a reconstructed point is ``ok`` when seen in at least
        ``min_views`` frames and its largest 1σ axis is at most ``max_std_ratio`` times the
        shape's radius, ``unreliable`` otherwise (docs/factorization.md).
    progress : callable, optional — called after each iteration of the weighted fit (missing
        data or weights) with (iterations done, ``max_iterations``), e.g. to drive a progress
        bar; it usually stops well before ``max_iterations``. Default: silent.

    Returns
    -------
    Reconstruction
        ``kind="affine"``, ``camera_model="affine"``: ``motion`` (F, 2, 3) holds the camera rows
        and ``image_translation`` (F, 2) the image of the centroid; ``points`` (P, 3) is the
        centred shape in pixels in the gauge where frame 0's rows are the X and Y axes; the
        covariances take the motion as exact (``covariance_gauge``); ``noise.std`` is σ̂ (pixels
        without weights, the standard deviation of unit weight with them); ``details`` holds the
        singular values, iterations and metric matrix.

    Notes
    -----
    Orthographic projection leaves the mirror (Necker) ambiguity: the depth-reversed shape
    with mirrored camera rows (:meth:`~kalmansfm.structure.Reconstruction.mirrored`) explains
    every image identically; one of the two is returned.  Degeneracies (a W not clearly of
    rank 3, a flat shape, a metric system too ill-conditioned to fix depth) are warnings.

    Raises
    ------
    InvalidInputError
        Wrong shape, infinite values, bad weights or bounds.
    NotEnoughDataError
        Fewer than 3 usable frames or 4 usable points.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> shape = rng.normal(size=(8, 3)) * 10
    >>> frames = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(5)]
    >>> tracks = np.stack([shape @ m.T + [100, 50] for m in frames])
    >>> rec = factorize(tracks)
    >>> rec.points.shape, rec.motion.shape, rec.reprojection_rms < 1e-9
    ((8, 3), (5, 2, 3), True)
    >>> bool(np.allclose(rec.motion @ rec.motion.transpose(0, 2, 1), np.eye(2)))
    True
    >>> bool(np.allclose(rec.project(), tracks))
    True
    """
    factors = factor_affine(positions, weights=weights, max_iterations=max_iterations, tol=tol, rng=rng,
                            progress=progress)
    uncertainty = point_uncertainty(factors, positions, weights=weights, min_views=min_views,
                                    max_std_ratio=max_std_ratio)
    return affine_reconstruction(factors, uncertainty, positions, weighted=weights is not None)


@dataclass(frozen=True)
class AffineCameras:
    """Affine cameras as a :class:`~kalmansfm.structure.Reconstruction` holds them.

    Attributes
    ----------
    projections : (F, 3, 4) [M_f t_f; 0 0 0 1]; NaN for a frame without motion.
    rotations : (F, 3, 3) the nearest rotation to the camera rows, completed by their cross product.
    frame_status : (F,) int8 ``registered`` where the frame has motion, ``not_connected`` elsewhere.
    """

    projections: np.ndarray
    rotations: np.ndarray
    frame_status: np.ndarray


def affine_cameras(motion: np.ndarray, translation: np.ndarray) -> AffineCameras:
    """The projections, rotations and statuses of affine cameras (F, 2, 3) rows and (F, 2) translations.

    Examples
    --------
    >>> c = affine_cameras(np.stack([np.eye(3)[:2], np.full((2, 3), np.nan)]), np.array([[1.0, 2.0], [0.0, 0.0]]))
    >>> c.projections[0].tolist(), c.frame_status.tolist()
    ([[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 0.0, 1.0]], [0, 1])
    """
    frames = motion.shape[0]
    known = np.isfinite(motion).all(axis=(1, 2)) & np.isfinite(translation).all(axis=1)
    projections = np.full((frames, 3, 4), np.nan)
    projections[known, :2, :3] = motion[known]
    projections[known, :2, 3] = translation[known]
    projections[known, 2] = (0.0, 0.0, 0.0, 1.0)
    rotations = np.full((frames, 3, 3), np.nan)
    if known.any():
        rotations[known] = camera_rotation_matrices(motion[known])
    status = np.where(known, FrameStatus.REGISTERED, FrameStatus.NOT_CONNECTED).astype(np.int8)
    return AffineCameras(projections, rotations, status)


def affine_reconstruction(factors: AffineFactors, uncertainty: PointUncertainty, positions: np.ndarray, *,
                          weighted: bool) -> Reconstruction:
    """The :class:`~kalmansfm.structure.Reconstruction` of a factorization and its points' uncertainty."""
    cameras = affine_cameras(factors.motion, factors.translation)
    return Reconstruction(
        kind="affine",
        method=factors.method,
        camera_model="affine",
        projections=cameras.projections,
        rotations=cameras.rotations,
        frame_status=cameras.frame_status,
        points=factors.points,
        point_covariances=uncertainty.covariances,
        point_status=uncertainty.status,
        views=uncertainty.views,
        point_reprojection_rms=uncertainty.reprojection_rms,
        covariance_gauge=AFFINE_GAUGE,
        # the residual lengths are measured when first read (large complete input: only then)
        observations=Observations.from_dense(np.asarray(positions), used=factors.observed,
                                             residuals=partial(getattr, factors, "residuals")),
        noise=NoiseEstimate(std=uncertainty.noise_std, estimated=True, degrees_of_freedom=uncertainty.dof,
                            unit="unit weight" if weighted else "px"),
        reprojection_rms=factors.residual_rms,
        details=AffineDetails(singular_values=factors.singular_values, iterations=factors.iterations,
                              metric_matrix=factors.metric_matrix, weighted=weighted,
                              shape_radius=uncertainty.radius_px, min_views=uncertainty.min_views,
                              max_std_ratio=uncertainty.max_std_ratio),
        warnings=(*uncertainty.warnings, *factors.warnings),
    )
