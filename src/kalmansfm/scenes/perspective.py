"""A synthetic perspective sequence with ground truth: a camera walking around an object.

The camera moves along an arc around a cloud of points and looks at its
centre, as a hand-held walk-around or turntable capture does.  Each point is
tracked over a contiguous run of frames (a video tracker's partial tracks),
its projections get Gaussian pixel noise, and a chosen fraction of the
observations is replaced by gross mismatches.  Two degenerate variants exist
for tests: all points on one plane, and a camera that only rotates.  One
seeded generator draws everything, so a scene is reproducible from its
parameters.  (:mod:`.known_cameras` draws the other synthetic perspective scene, for
fusion with known cameras; the two share the arc, the look-at rotation and the
mismatches, :mod:`._arc`.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from .._validation import check_count, check_positive
from ..structure.geometry.pinhole import CameraSet, intrinsic_matrices
from ..structure.reconstruction import Observations
from ._arc import arc_centres, look_at, mismatches

__all__ = ["PerspectiveScene", "SlidingSequence", "perspective_scene", "sliding_sequence"]


@dataclass(frozen=True)
class PerspectiveScene:
    """Ground truth and observations of a synthetic perspective sequence.

    Attributes
    ----------
    observations : (F, P, 2) pixels (x = column, y = row), NaN where unseen.
    intrinsics : (F, 3, 3) — K of every frame.
    rotations : (F, 3, 3) — world → camera, x_cam = R (X - C).
    centres : (F, 3) — camera centres.
    points : (P, 3) — true points.
    outliers : (F, P) bool — observations replaced by a gross mismatch.
    pixel_std : σ of the Gaussian noise of the other observations (pixels).
    viewing_distance : mean distance from the camera centres to the points' centroid.
    image_size : (width, height) in pixels.
    """

    observations: np.ndarray
    intrinsics: np.ndarray
    rotations: np.ndarray
    centres: np.ndarray
    points: np.ndarray
    outliers: np.ndarray
    pixel_std: float
    viewing_distance: float
    image_size: tuple[int, int]


def perspective_scene(
    frames: int = 10,
    points: int = 400,
    pixel_std: float = 0.7,
    outlier_fraction: float = 0.0,
    min_track_length: int = 3,
    arc_degrees: float = 40.0,
    distance: float = 4.0,
    focal: float = 800.0,
    image_size: tuple[int, int] = (1280, 960),
    layout: str = "volume",
    seed: int = 0,
) -> PerspectiveScene:
    """Draw a walk-around sequence.

    Parameters
    ----------
    frames : int >= 2 — camera positions, evenly spaced along the arc.
    points : int >= 1 — points drawn uniformly in the cube [-1, 1]³ (or the square
        [-1, 1]² of the plane Z = 0 for ``layout="planar"``).
    pixel_std : float > 0 — Gaussian image noise σ (pixels).
    outlier_fraction : float in [0, 1) — share of observations replaced by a gross
        mismatch 8-60 px away from the true projection.
    min_track_length : int >= 2 — each point is tracked over a run of
        ``min_track_length`` … ``frames`` consecutive frames (uniformly drawn).
    arc_degrees : angle of the arc of camera centres, seen from the points' centroid.
    distance : radius of the arc (the object has radius ~1.7).
    focal : focal length in pixels (square pixels, no skew, principal point at the centre).
    image_size : (width, height) pixels; projections outside the image are unseen.
    layout : ``"volume"``, ``"planar"`` (all points on one plane) or ``"rotation"``
        (every frame at the same centre, turning across the arc's directions: no parallax).
    seed : seed of ``np.random.default_rng``.

    Returns
    -------
    PerspectiveScene

    Examples
    --------
    >>> s = perspective_scene(frames=6, points=50, outlier_fraction=0.05, seed=1)
    >>> s.observations.shape, s.intrinsics.shape, round(s.viewing_distance, 3)
    ((6, 50, 2), (6, 3, 3), 4.0)
    >>> bool(np.isfinite(s.observations[..., 0]).sum(axis=0).min() >= 3)
    True
    """
    F = check_count("frames", frames, 2)
    P = check_count("points", points, 1)
    sigma = check_positive("pixel_std", pixel_std, "pixels")
    shortest = check_count("min_track_length", min_track_length, 2)
    if shortest > F:
        raise InvalidInputError(f"min_track_length must be <= frames ({F}); got {shortest}")
    if not 0.0 <= outlier_fraction < 1.0:
        raise InvalidInputError(f"outlier_fraction must be in [0, 1); got {outlier_fraction}")
    if layout not in ("volume", "planar", "rotation"):
        raise InvalidInputError(f"layout must be 'volume', 'planar' or 'rotation'; got {layout!r}")
    arc = np.radians(check_positive("arc_degrees", arc_degrees, "degrees"))
    radius = check_positive("distance", distance)
    f = check_positive("focal", focal, "pixels")
    width, height = (check_count("image width", image_size[0], 1), check_count("image height", image_size[1], 1))
    rng = np.random.default_rng(check_count("seed", seed, 0))
    X = rng.uniform(-1.0, 1.0, size=(P, 3))
    if layout == "planar":
        X[:, 2] = 0.0
    angles = np.linspace(-arc / 2, arc / 2, F)
    arc_points = arc_centres(angles, radius, 0.3)
    if layout == "rotation":
        centres = np.repeat(arc_points[F // 2][None], F, axis=0)
        targets = arc_points[F // 2] + (np.zeros(3) - arc_points) * 1.0
    else:
        centres = arc_points
        targets = np.zeros((F, 3))
    # image y pointing down (world −Y up), each camera aimed a little off the target
    rotations = look_at(centres, targets + rng.normal(0.0, 0.05, (F, 3)), up=(0.0, -1.0, 0.0))
    K = intrinsic_matrices(f, f, width / 2.0, height / 2.0, 0.0)[0]
    x_cam = np.einsum("fij,fpj->fpi", rotations, X[None] - centres[:, None])
    clean = f * x_cam[..., :2] / x_cam[..., 2:3] + K[:2, 2]
    obs = clean + rng.normal(scale=sigma, size=clean.shape)
    inside = (x_cam[..., 2] > 0) & (clean[..., 0] >= 0) & (clean[..., 0] < width) \
        & (clean[..., 1] >= 0) & (clean[..., 1] < height)
    length = rng.integers(shortest, F + 1, size=P)
    start = rng.integers(0, F - length + 1)
    frame = np.arange(F)[:, None]
    seen = inside & (frame >= start) & (frame < start + length)
    outliers = seen & (rng.random((F, P)) < outlier_fraction)
    obs[outliers] = clean[outliers] + mismatches(rng, int(outliers.sum()), 8.0, 60.0)
    obs[~seen] = np.nan
    viewing = float(np.mean(np.linalg.norm(centres - X.mean(axis=0), axis=1)))
    return PerspectiveScene(obs, np.repeat(K[None], F, axis=0), rotations, centres, X, outliers, sigma,
                            viewing, (width, height))


@dataclass(frozen=True)
class SlidingSequence:
    """Ground truth and observations (one entry each) of a long video-like sequence of short tracks.

    Attributes
    ----------
    observations : :class:`~kalmansfm.structure.Observations` of shape (frames, tracks).
    cameras : the true cameras (K [R | t] per frame).
    points : (P, 3) true points.
    outliers : (N,) bool — which observations are gross mismatches.
    """

    observations: Observations
    cameras: CameraSet
    points: np.ndarray
    outliers: np.ndarray


def sliding_sequence(frames: int, tracks: int, *, step: float = 0.02, mean_track_length: float = 17.0,
                     pixel_std: float = 0.5, outlier_fraction: float = 0.01, seed: int = 0) -> SlidingSequence:
    """A camera sliding sideways (``step`` metres a frame, a gentle sway and yaw) past a wall of points 4–8 m away.

    Each track is seen in a run of consecutive frames of geometric length (mean about
    ``mean_track_length``), with Gaussian noise of ``pixel_std`` pixels and a share
    ``outlier_fraction`` of gross mismatches (20–40 px off); 640 × 480 images, focal 800 px.
    The scene of a long video's many short tracks (issue 29), held per observation.

    Examples
    --------
    >>> s = sliding_sequence(200, 300, seed=1)
    >>> s.observations.shape, len(s.observations) > 200 * 20, s.cameras.matrices.shape
    ((200, 300), True, (200, 3, 4))
    """
    frames, tracks = check_count("frames", frames, 2), check_count("tracks", tracks, 1)
    rng = np.random.default_rng(seed)
    width, height, focal = 640, 480, 800.0
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]])
    f = np.arange(frames)
    centres = np.stack([step * f, 0.05 * np.sin(f / 40), np.zeros(frames)], axis=1)
    yaw = 0.05 * np.sin(f / 60)
    R = np.zeros((frames, 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = np.cos(yaw), -np.sin(yaw), 1, np.sin(yaw), np.cos(yaw)
    cams = CameraSet.from_pose(K, R, -np.einsum("fij,fj->fi", R, centres))
    length = np.minimum(rng.geometric(1 / mean_track_length, size=tracks) + 1, frames)
    start = rng.integers(0, frames - length + 1)
    depth = rng.uniform(4.0, 8.0, size=tracks)
    middle = step * (start + length / 2)
    points = np.stack([middle + rng.uniform(-0.5, 0.5, tracks) * 0.35 * depth * width / focal,
                       rng.uniform(-0.3, 0.3, tracks) * depth, depth], axis=1)
    track = np.repeat(np.arange(tracks), length)
    frame = np.concatenate([np.arange(s, s + n) for s, n in zip(start.tolist(), length.tolist())])
    h = np.einsum("nij,nj->ni", cams.matrices[frame], np.c_[points[track], np.ones(track.size)])
    xy = h[:, :2] / h[:, 2:] + rng.normal(scale=pixel_std, size=(track.size, 2))
    wild = rng.random(track.size) < outlier_fraction
    xy[wild] += rng.uniform(20, 40, size=(int(wild.sum()), 2)) * rng.choice([-1, 1], size=(int(wild.sum()), 2))
    order = np.lexsort((track, frame))
    observations = Observations.from_sparse((frames, tracks), frame[order], track[order], xy[order])
    return SlidingSequence(observations, cams, points, wild[order])
