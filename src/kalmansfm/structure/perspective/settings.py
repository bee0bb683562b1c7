"""Settings of calibrated reconstruction, the check of its inputs, and how its result is assembled.

Shared by the batch method (:mod:`.incremental`) and the recursive one
(:mod:`.recursive`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from ...errors import InvalidInputError, NotEnoughDataError
from ..._validation import as_float_array, check_choice, check_count, check_positive
from ..points import PointStatus
from ..reconstruction import (
    FREE_NETWORK_GAUGE,
    FrameStatus,
    NoiseEstimate,
    Observations,
    PerspectiveDetails,
    Reconstruction,
)

__all__ = [
    "COVARIANCE_GAUGE",
    "DEFAULT_OUTLIER_THRESHOLD_PX",
    "PERSPECTIVE_METHODS",
    "FrameStatus",
    "PerspectiveSettings",
    "perspective_reconstruction",
    "validate_intrinsics",
    "validate_tracks_and_intrinsics",
]

#: how the point covariances are to be read (written into summary.json and the PLY header).
COVARIANCE_GAUGE = FREE_NETWORK_GAUGE
#: the methods of :func:`reconstruct_perspective`.
PERSPECTIVE_METHODS = ("batch", "recursive")
#: an observation farther than this from where the other views put its point is an outlier (pixels).
DEFAULT_OUTLIER_THRESHOLD_PX = 4.0


@dataclass(frozen=True)
class PerspectiveSettings:
    """How :func:`reconstruct_perspective` runs; validated on construction.

    Attributes
    ----------
    method : ``"batch"`` (bundle adjustment) or ``"recursive"`` (the report's
        relative orientations and recursive fusion).
    outlier_threshold_px : an observation whose leave-one-out residual exceeds this
        (and the χ² bound below) is an outlier; also the RANSAC inlier threshold.
    outlier_probability : in (0, 1); the χ²(2) quantile of this probability, times
        the estimated σ², is the other bound.
    min_triangulation_angle_deg : a track whose rays span less than this angle is
        ``degenerate``.
    min_pair_angle_deg : the initial pair's median triangulation angle must reach this.
    min_registration_points : a frame is registered only with at least this many
        PnP inliers (and a pair needs twice as many shared inliers).
    max_initial_pairs : frame pairs tried as the initial pair.
    refinement_rounds : at most this many refinement rounds of [re-estimate the points with the outlier test →
        bundle adjustment] after the growth (they stop earlier when a round changes nothing); 0 leaves one robust
        bundle adjustment of all tracks (a rough reconstruction that only seeds another, as the front end's first).
    seed : seed of the RANSAC random generator (OpenCV's), for reproducible runs.
    """

    method: str = "batch"
    outlier_threshold_px: float = DEFAULT_OUTLIER_THRESHOLD_PX
    outlier_probability: float = 0.999
    min_triangulation_angle_deg: float = 1.0
    min_pair_angle_deg: float = 2.0
    min_registration_points: int = 12
    max_initial_pairs: int = 40
    refinement_rounds: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        check_choice("method", self.method, PERSPECTIVE_METHODS)
        object.__setattr__(self, "outlier_threshold_px",
                           check_positive("outlier_threshold_px", self.outlier_threshold_px, "pixels"))
        p = check_positive("outlier_probability", self.outlier_probability)
        if not p < 1.0:
            raise InvalidInputError(f"outlier_probability must be in (0, 1); got {p}")
        object.__setattr__(self, "outlier_probability", p)
        for name in ("min_triangulation_angle_deg", "min_pair_angle_deg"):
            object.__setattr__(self, name, check_positive(name, getattr(self, name), "degrees"))
        object.__setattr__(self, "min_registration_points",
                           check_count("min_registration_points", self.min_registration_points, 6))
        object.__setattr__(self, "max_initial_pairs", check_count("max_initial_pairs", self.max_initial_pairs, 1))
        object.__setattr__(self, "refinement_rounds", check_count("refinement_rounds", self.refinement_rounds, 0))
        object.__setattr__(self, "seed", check_count("seed", self.seed, 0))

    @property
    def chi2_bound(self) -> float:
        """χ²(2) quantile of ``outlier_probability``."""
        return float(stats.chi2.ppf(self.outlier_probability, 2))


def perspective_reconstruction(method: str, observations: np.ndarray, intrinsics: np.ndarray, settings: PerspectiveSettings,
                               *, points: np.ndarray, point_covariances: np.ndarray, point_status: np.ndarray,
                               rotations: np.ndarray, translations: np.ndarray, pose_covariances: np.ndarray,
                               frame_status: np.ndarray, inliers: np.ndarray, pixel_std: float,
                               reprojection_rms: float, degrees_of_freedom: int,
                               initial_pair: tuple[int, int], warnings: tuple[str, ...],
                               timings: dict[str, float] | None = None) -> Reconstruction:
    """The :class:`~kalmansfm.structure.Reconstruction` of a calibrated reconstruction (both methods).

    ``observations`` (F, P, 2) are the tracks, ``intrinsics`` (F, 3, 3) K, ``inliers`` (F, P) the
    observations the estimate used; the residual of every observation of a reconstructed point
    in a registered frame is measured here, the covariances are in the free-network gauge.
    """
    registered = frame_status == FrameStatus.REGISTERED
    reconstructed = point_status == PointStatus.OK
    seen = np.isfinite(observations).all(axis=2)
    measurable = seen & registered[:, None] & reconstructed[None, :]
    frames, tracks = np.nonzero(measurable)
    x_cam = np.einsum("nij,nj->ni", rotations[frames], points[tracks]) + translations[frames]
    pix = np.einsum("nij,nj->ni", intrinsics[frames], x_cam)
    residuals = np.full(seen.shape, np.nan)
    residuals[frames, tracks] = np.linalg.norm(pix[:, :2] / pix[:, 2:] - observations[frames, tracks], axis=1)
    used = inliers & seen
    point_rms = residual_rms_per_point(observations, intrinsics, rotations, translations, points, used)
    projections = np.full((len(frame_status), 3, 4), np.nan)
    projections[registered] = intrinsics[registered] @ np.concatenate(
        [rotations[registered], translations[registered, :, None]], axis=2)
    return Reconstruction(
        kind="perspective",
        method=method,
        camera_model="pinhole",
        projections=projections,
        rotations=rotations,
        frame_status=np.asarray(frame_status, dtype=np.int8),
        points=points,
        point_covariances=point_covariances,
        point_status=np.asarray(point_status, dtype=np.int8),
        views=used.sum(axis=0).astype(np.int64),
        point_reprojection_rms=point_rms,
        covariance_gauge=COVARIANCE_GAUGE,
        observations=Observations.from_dense(observations, used=used, residuals=residuals),
        noise=NoiseEstimate(std=float(pixel_std), estimated=True, degrees_of_freedom=int(degrees_of_freedom)),
        reprojection_rms=float(reprojection_rms),
        details=PerspectiveDetails(initial_pair=(int(initial_pair[0]), int(initial_pair[1])),
                                   outlier_threshold_px=settings.outlier_threshold_px,
                                   outlier_probability=settings.outlier_probability),
        intrinsics=intrinsics,
        translations=translations,
        pose_covariances=pose_covariances,
        warnings=tuple(warnings),
        timings=dict(timings or {}),
    )


def validate_tracks_and_intrinsics(observations: object, intrinsics: object) -> tuple[np.ndarray, np.ndarray]:
    """Check (F, P, 2) tracks and (3, 3) or (F, 3, 3) intrinsics; return them as float arrays, K per frame.

    Examples
    --------
    >>> obs, K = validate_tracks_and_intrinsics(np.zeros((2, 5, 2)), np.eye(3))
    >>> K.shape
    (2, 3, 3)
    >>> validate_tracks_and_intrinsics(np.zeros((2, 5, 2)), np.diag([1.0, 0.0, 1.0]))
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: intrinsics of frame 0 must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (a singular or malformed K); got [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    obs = as_float_array("observations", observations)
    if obs.ndim != 3 or obs.shape[2] != 2:
        raise InvalidInputError(f"observations must have shape (frames, points, 2) as (x, y); got {obs.shape}")
    F, P, _ = obs.shape
    if F < 2:
        raise NotEnoughDataError(f"a reconstruction needs >= 2 frames; got {F}")
    partial = np.isnan(obs).any(axis=2) & ~np.isnan(obs).all(axis=2)
    if partial.any() or np.isinf(obs).any():
        f, p = np.argwhere(partial | np.isinf(obs).any(axis=2))[0]
        raise InvalidInputError(f"observations must be finite (x, y) or NaN in both; frame {f}, point {p} "
                                f"is {obs[f, p].tolist()}")
    return obs, validate_intrinsics(intrinsics, F)


def validate_intrinsics(intrinsics: object, n_frames: int) -> np.ndarray:
    """Check (3, 3) or (F, 3, 3) intrinsics of ``n_frames`` frames; return K per frame as (F, 3, 3) floats.

    Examples
    --------
    >>> validate_intrinsics(np.eye(3), 4).shape
    (4, 3, 3)
    """
    F = n_frames
    K = as_float_array("intrinsics", intrinsics)
    if K.shape == (3, 3):
        K = np.repeat(K[None], F, axis=0)
    if K.shape != (F, 3, 3):
        raise InvalidInputError(f"intrinsics must have shape (3, 3) or ({F}, 3, 3), one K per frame; got {K.shape}")
    missing = ~np.isfinite(K).all(axis=(1, 2))
    if missing.any():
        raise InvalidInputError(f"intrinsics missing (not finite) for frame {int(np.flatnonzero(missing)[0])}")
    lower = np.abs(K[:, [1, 2, 2], [0, 0, 1]]).max(axis=1) > 0
    diag = K[:, [0, 1], [0, 1]]
    bad = lower | (diag <= 0).any(axis=1) | (K[:, 2, 2] != 1.0)
    if bad.any():
        f = int(np.flatnonzero(bad)[0])
        raise InvalidInputError(f"intrinsics of frame {f} must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 "
                                f"(a singular or malformed K); got {K[f].tolist()}")
    return K


def residual_rms_per_point(observations: np.ndarray, intrinsics: np.ndarray, rotations: np.ndarray,
                           translations: np.ndarray, points: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """(P,) RMS reprojection error length of each point over its inlier observations (NaN without any)."""
    frames, tracks = np.nonzero(inliers)
    x_cam = np.einsum("nij,nj->ni", rotations[frames], points[tracks]) + translations[frames]
    pix = np.einsum("nij,nj->ni", intrinsics[frames], x_cam)
    sq = np.sum((pix[:, :2] / pix[:, 2:] - observations[frames, tracks]) ** 2, axis=1)
    count = np.bincount(tracks, minlength=points.shape[0])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.bincount(tracks, weights=sq, minlength=points.shape[0]) / count)


def frame_runs(frames: np.ndarray) -> str:
    """Frame numbers as runs, e.g. ``0-4, 7, 9-12``.

    Examples
    --------
    >>> frame_runs(np.array([0, 1, 2, 4, 6, 7]))
    '0-2, 4, 6-7'
    """
    frames = np.asarray(frames)
    runs = np.split(frames, np.flatnonzero(np.diff(frames) > 1) + 1)
    return ", ".join(f"{r[0]}" if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in runs if len(r))
