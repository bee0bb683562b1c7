"""A synthetic perspective scene with known cameras, noisy observations and planted gross outliers.

Cameras sit on an arc around a cloud of points and look at its centre (a
turntable / walk-around capture); each point is seen by a random subset of
views, its projections get Gaussian pixel noise, and a chosen fraction of the
observations is replaced by gross mismatches (uniformly placed 20-80 px away).
Everything is drawn from one seeded generator, so a scene is reproducible from
its parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from .._validation import check_count, check_positive
from ..structure.pinhole import CameraSet, project_points

__all__ = ["KnownCameraScene", "known_camera_scene"]

_IMAGE_SIZE = (1280, 960)  # width, height in pixels
_FOCAL = 1000.0


@dataclass(frozen=True)
class KnownCameraScene:
    """Ground truth and observations of a known-camera scene.

    Attributes
    ----------
    cameras : CameraSet — V views.
    points : (N, 3) true points.
    observations : (V, N, 2) pixels (x = column, y = row), NaN where unseen.
    outliers : (V, N) bool — observations replaced by a gross mismatch.
    pixel_std : the Gaussian noise σ of the other observations (pixels).
    """

    cameras: CameraSet
    points: np.ndarray
    observations: np.ndarray
    outliers: np.ndarray
    pixel_std: float


def known_camera_scene(
    points: int = 1000,
    views: int = 12,
    pixel_std: float = 0.5,
    outlier_fraction: float = 0.0,
    visibility: float = 1.0,
    arc_degrees: float = 60.0,
    seed: int = 0,
) -> KnownCameraScene:
    """Draw a scene: ``points`` in a 2 m cube, ``views`` cameras on a 6 m arc around it.

    Parameters
    ----------
    points, views : int — N >= 1 and V >= 2.
    pixel_std : float > 0 — Gaussian image noise σ (pixels).
    outlier_fraction : float in [0, 1) — share of observations replaced by a gross mismatch.
    visibility : float in (0, 1] — probability that a point is seen in a view (every point
        is seen at least in its first two views, so it can be triangulated).
    arc_degrees : float > 0 — angle spanned by the camera arc.
    seed : int — seed of ``np.random.default_rng``.

    Examples
    --------
    >>> s = known_camera_scene(points=5, views=3, outlier_fraction=0.2, seed=1)
    >>> s.observations.shape, len(s.cameras)
    ((3, 5, 2), 3)
    """
    n = check_count("points", points, 1)
    v = check_count("views", views, 2)
    sigma = check_positive("pixel_std", pixel_std, "pixels")
    arc = np.radians(check_positive("arc_degrees", arc_degrees, "degrees"))
    if not 0.0 <= outlier_fraction < 1.0:
        raise InvalidInputError(f"outlier_fraction must be in [0, 1); got {outlier_fraction}")
    if not 0.0 < visibility <= 1.0:
        raise InvalidInputError(f"visibility must be in (0, 1]; got {visibility}")
    rng = np.random.default_rng(check_count("seed", seed, 0))
    X = rng.uniform(-1.0, 1.0, size=(n, 3))
    angles = np.linspace(-arc / 2, arc / 2, v)
    radius = 6.0
    R = np.empty((v, 3, 3))
    t = np.empty((v, 3))
    for i, a in enumerate(angles):  # one 3 × 3 pose per view, not per point
        centre = np.array([radius * np.sin(a), 0.5 * np.sin(3 * a), -radius * np.cos(a)])
        forward = -centre / np.linalg.norm(centre)
        right = np.cross([0.0, 1.0, 0.0], forward)
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        R[i] = np.stack([right, down, forward])
        t[i] = -R[i] @ centre
    K = np.array([[_FOCAL, 0.0, _IMAGE_SIZE[0] / 2], [0.0, _FOCAL, _IMAGE_SIZE[1] / 2], [0.0, 0.0, 1.0]])
    cameras = CameraSet.from_pose(K, R, t)
    clean = project_points(cameras, X).pixels
    obs = clean + rng.normal(scale=sigma, size=clean.shape)
    seen = rng.random((v, n)) < visibility
    seen[:2] = True
    obs[~seen] = np.nan
    outliers = seen & (rng.random((v, n)) < outlier_fraction)
    k = int(outliers.sum())
    angle = rng.uniform(0, 2 * np.pi, k)
    distance = rng.uniform(20.0, 80.0, k)
    obs[outliers] = clean[outliers] + np.stack([np.cos(angle), np.sin(angle)], axis=1) * distance[:, None]
    return KnownCameraScene(cameras, X, obs, outliers, sigma)
