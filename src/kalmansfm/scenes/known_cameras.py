"""A synthetic perspective scene with known cameras, noisy observations and planted gross outliers.

Cameras sit on an arc around a cloud of points and look at its centre (a
turntable / walk-around capture); each point is seen by a random subset of
views, its projections get Gaussian pixel noise, and a chosen fraction of the
observations is replaced by gross mismatches (uniformly placed 20-80 px away).
Everything is drawn from one seeded generator, so a scene is reproducible from
its parameters.

It is not :mod:`.perspective`'s walk-around: visibility here is a random subset of
the views (every point in its first two), with no image border, exact aiming and the
image turned the other way; the fusion figures of ``docs/fusion.md`` were measured on
these draws.  The arc of centres, the look-at rotation and the mismatches are shared
(:mod:`._arc`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from .._validation import check_count, check_positive
from ..structure.geometry.pinhole import CameraSet, intrinsic_matrices, project_points
from ._arc import arc_centres, look_at, mismatches

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
    centres = arc_centres(angles, 6.0, 0.5)
    R = look_at(centres, np.zeros((v, 3)), up=(0.0, 1.0, 0.0))  # aimed at the origin, image y along +Y
    t = -(R @ centres[:, :, None])[:, :, 0]
    K = intrinsic_matrices(_FOCAL, _FOCAL, _IMAGE_SIZE[0] / 2, _IMAGE_SIZE[1] / 2, 0.0)[0]
    cameras = CameraSet.from_pose(K, R, t)
    clean = project_points(cameras, X).pixels
    obs = clean + rng.normal(scale=sigma, size=clean.shape)
    seen = rng.random((v, n)) < visibility
    seen[:2] = True
    obs[~seen] = np.nan
    outliers = seen & (rng.random((v, n)) < outlier_fraction)
    obs[outliers] = clean[outliers] + mismatches(rng, int(outliers.sum()), 20.0, 80.0)
    return KnownCameraScene(cameras, X, obs, outliers, sigma)
