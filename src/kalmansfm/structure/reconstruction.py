"""One record for every reconstruction: cameras, points with covariances, and the observations behind them.

Every way kalmansfm reconstructs returns a :class:`Reconstruction` — factorization with affine
cameras (:func:`~kalmansfm.structure.factorize`), fusion with known cameras
(:func:`~kalmansfm.structure.fuse`) and calibrated reconstruction with unknown motion
(:func:`~kalmansfm.structure.reconstruct_perspective`) — so that staging, the run summary,
the report, exports and ``batch`` never branch on the method.  The layout follows the usual
sparse-model one (cameras, frames with poses, points with tracks):

* **frames**: each frame's camera as a 3 × 4 projection matrix ``projections`` (a pinhole
  camera K [R | t]; an affine camera [[M, t], [0, 0, 0, 1]] with M the two camera rows), its
  ``rotations`` (world → camera), for pinhole cameras ``intrinsics`` and ``translations``
  (x_cam = R X + t) and, where known, the pose covariance; a :class:`FrameStatus` each;
* **points**: position, covariance (read in the stated ``covariance_gauge``), a
  :class:`~kalmansfm.structure.PointStatus`, the views used, the RMS reprojection error;
* **observations**: the 2-D positions that made the points (:class:`Observations`: which
  frame, which point, where, whether the estimate used it, its reprojection error);
* the **noise** the covariances are scaled with (:class:`NoiseEstimate`), warnings, and the
  method's own figures in ``details`` (:class:`AffineDetails`, :class:`FusionDetails`,
  :class:`PerspectiveDetails`).

Frames and points are indexed 0 … F−1 and 0 … P−1; ``frame_ids`` and ``track_ids`` give the
numbers files use (by default the indices).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, Union

import numpy as np

from .._validation import LabelledEnum, check_choice
from ..errors import InvalidInputError
from .points import PointStatus, rms_std

__all__ = [
    "AFFINE_GAUGE",
    "CAMERA_MODELS",
    "FREE_NETWORK_GAUGE",
    "KNOWN_CAMERAS_GAUGE",
    "RECONSTRUCTION_KINDS",
    "SEGMENTED_GAUGE",
    "AffineDetails",
    "FrameStatus",
    "FusionDetails",
    "NoiseEstimate",
    "Observations",
    "PerspectiveDetails",
    "Reconstruction",
]

#: the camera models a reconstruction may have.
CAMERA_MODELS = ("affine", "pinhole")
#: which problem produced a reconstruction: factorization with affine cameras, fusion with known
#: cameras, calibrated reconstruction with unknown motion.
RECONSTRUCTION_KINDS = ("affine", "fusion", "perspective")

#: how an affine reconstruction's point covariances are to be read.
AFFINE_GAUGE = ("affine gauge of the factorization: the shape centred on its centroid, frame 0's camera rows as "
                "the X and Y axes, the motion taken as exact")
#: how the covariances of fusion with known cameras are to be read.
KNOWN_CAMERAS_GAUGE = "world frame of the given cameras (the cameras taken as exact)"
#: how a calibrated reconstruction's covariances are to be read.
FREE_NETWORK_GAUGE = ("free-network gauge: the covariance of each point after a least-squares similarity "
                      "alignment (translation, rotation, scale) of all reconstructed points onto any reference")
#: how the covariances of a calibrated reconstruction made in windows of frames are to be read
#: (:func:`~kalmansfm.structure.perspective.segmented.reconstruct_segmented`).
SEGMENTED_GAUGE = ("cameras of the segmented reconstruction taken as exact: each point's covariance given the "
                   "chained cameras (it leaves out the cameras' uncertainty and the chain's drift); world frame of "
                   "the first window's initial pair (its first camera at the origin, unit baseline); the camera "
                   "covariances are each window's free-network ones carried into that frame")


class FrameStatus(LabelledEnum):
    """Outcome for one frame; its ``label`` (``registered``, ``not_connected``, ``pose_failed``) is the word files use.

    Examples
    --------
    >>> [s.label for s in FrameStatus]
    ['registered', 'not_connected', 'pose_failed']
    """

    REGISTERED = 0  #: the frame has a camera
    NOT_CONNECTED = 1  #: it shares too few tracks with the reconstructed points
    POSE_FAILED = 2  #: no consistent pose from the points it shares


@dataclass(frozen=True, eq=False)
class Observations:
    """The 2-D observations behind a reconstruction, one entry per (frame, point) observation.

    Stored either densely — the (F, P, 2) positions with NaN where a point is not seen, as
    the estimators take them, kept by reference — or sparsely as parallel arrays; the
    sparse arrays are built on first use, the dense ones on request.

    Attributes
    ----------
    shape : (F, P), frames × points.

    Examples
    --------
    >>> xy = np.full((2, 3, 2), np.nan); xy[0, 0] = 5, 6; xy[1, 2] = 7, 8
    >>> obs = Observations.from_dense(xy, used=np.array([[True, False, False], [False, False, False]]))
    >>> obs.frame.tolist(), obs.point.tolist(), obs.xy.tolist(), obs.used.tolist()
    ([0, 1], [0, 2], [[5.0, 6.0], [7.0, 8.0]], [True, False])
    >>> len(obs), obs.n_used, obs.used_per_point().tolist()
    (2, 1, [1, 0, 0])
    >>> np.array_equal(Observations.from_sparse((2, 3), obs.frame, obs.point, obs.xy).dense(), xy, equal_nan=True)
    True
    """

    shape: tuple[int, int]
    _positions: np.ndarray | None = field(default=None, repr=False)
    _used: np.ndarray | None = field(default=None, repr=False)
    _residuals: np.ndarray | Callable[[], np.ndarray] | None = field(default=None, repr=False)
    _rejected: np.ndarray | None = field(default=None, repr=False)
    _sparse: tuple[np.ndarray, ...] | None = field(default=None, repr=False)

    @classmethod
    def from_dense(cls, positions: np.ndarray, *, used: np.ndarray | None = None,
                   residuals: np.ndarray | Callable[[], np.ndarray] | None = None,
                   rejected: np.ndarray | None = None) -> Observations:
        """Observations of (F, P, 2) ``positions`` (NaN where none); ``used`` (F, P) defaults to every one.

        ``residuals`` (F, P) is each observation's reprojection error length in pixels (NaN where
        unknown), or a function returning it, called when the residuals are first read (a large
        reconstruction then makes the array only if it is used); ``rejected`` (F, P) marks the
        observations an outlier test rejected (default none).
        """
        positions = np.asarray(positions)
        if positions.ndim != 3 or positions.shape[2] != 2:
            raise InvalidInputError(f"observations must have shape (frames, points, 2); got {positions.shape}")
        shape = (int(positions.shape[0]), int(positions.shape[1]))
        for name, a in (("used", used), ("residuals", residuals), ("rejected", rejected)):
            if a is not None and not callable(a) and np.shape(a) != shape:
                raise InvalidInputError(f"{name} must have shape {shape}; got {np.shape(a)}")
        return cls(shape, positions, None if used is None else np.asarray(used, dtype=bool),
                   residuals if residuals is None or callable(residuals) else np.asarray(residuals),
                   None if rejected is None else np.asarray(rejected, dtype=bool))

    @classmethod
    def from_sparse(cls, shape: tuple[int, int], frame: np.ndarray, point: np.ndarray, xy: np.ndarray, *,
                    used: np.ndarray | None = None, residual: np.ndarray | None = None,
                    rejected: np.ndarray | None = None) -> Observations:
        """Observations given as parallel arrays: ``frame``, ``point`` (N,) indices and ``xy`` (N, 2)."""
        frame = np.asarray(frame, dtype=np.int64)
        point = np.asarray(point, dtype=np.int64)
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        n = frame.shape[0]
        if point.shape != (n,) or xy.shape != (n, 2):
            raise InvalidInputError(f"frame, point and xy must describe the same {n} observations; got "
                                    f"{point.shape} and {xy.shape}")
        if n and (frame.min() < 0 or frame.max() >= shape[0] or point.min() < 0 or point.max() >= shape[1]):
            raise InvalidInputError(f"observation indices must lie within {shape} (frames, points)")
        used = np.ones(n, dtype=bool) if used is None else np.asarray(used, dtype=bool)
        residual = np.full(n, np.nan) if residual is None else np.asarray(residual, dtype=np.float64)
        rejected = np.zeros(n, dtype=bool) if rejected is None else np.asarray(rejected, dtype=bool)
        return cls((int(shape[0]), int(shape[1])), _sparse=(frame, point, xy, used, residual, rejected))

    @cached_property
    def _residual_values(self) -> np.ndarray | None:
        return self._residuals() if callable(self._residuals) else self._residuals

    @cached_property
    def _arrays(self) -> tuple[np.ndarray, ...]:
        if self._sparse is not None:
            return self._sparse
        positions = self._positions
        assert positions is not None
        seen = np.isfinite(positions).all(axis=2)
        frame, point = np.nonzero(seen)
        used = np.ones(frame.size, dtype=bool) if self._used is None else self._used[frame, point]
        residual = np.full(frame.size, np.nan) if self._residual_values is None else \
            np.asarray(self._residual_values[frame, point], dtype=np.float64)
        rejected = np.zeros(frame.size, dtype=bool) if self._rejected is None else self._rejected[frame, point]
        return (frame.astype(np.int64), point.astype(np.int64), positions[frame, point].astype(np.float64), used,
                residual, rejected)

    @property
    def frame(self) -> np.ndarray:
        """(N,) int64 — the frame index of each observation (sorted by frame, then point, when dense)."""
        return self._arrays[0]

    @property
    def point(self) -> np.ndarray:
        """(N,) int64 — the point index of each observation."""
        return self._arrays[1]

    @property
    def xy(self) -> np.ndarray:
        """(N, 2) float64 — the observed position, x = column, y = row (pixels)."""
        return self._arrays[2]

    @property
    def used(self) -> np.ndarray:
        """(N,) bool — the final estimate used the observation (not rejected as an outlier)."""
        return self._arrays[3]

    @property
    def residual(self) -> np.ndarray:
        """(N,) float64 — length of the reprojection error at the final estimate (pixels), NaN where unknown."""
        return self._arrays[4]

    @property
    def rejected(self) -> np.ndarray:
        """(N,) bool — an outlier test rejected the observation (a subset of the unused ones)."""
        return self._arrays[5]

    @property
    def n_rejected(self) -> int:
        """How many observations an outlier test rejected."""
        if self._sparse is None and "_arrays" not in self.__dict__:
            return 0 if self._rejected is None else int(np.count_nonzero(self._rejected & self.seen()))
        return int(np.count_nonzero(self.rejected))

    def rejected_mask(self) -> np.ndarray:
        """(F, P) bool — where an outlier test rejected an observation."""
        if self._sparse is None:
            return np.zeros(self.shape, dtype=bool) if self._rejected is None else self._rejected & self.seen()
        out = np.zeros(self.shape, dtype=bool)
        out[self.frame[self.rejected], self.point[self.rejected]] = True
        return out

    def __len__(self) -> int:
        if self._sparse is None and self._positions is not None and "_arrays" not in self.__dict__:
            return int(np.count_nonzero(self.seen()))
        return int(self.frame.size)

    @property
    def n_used(self) -> int:
        """How many observations the estimate used."""
        if self._sparse is None and "_arrays" not in self.__dict__:
            return int(np.count_nonzero(self.used_mask()))
        return int(np.count_nonzero(self.used))

    def seen(self) -> np.ndarray:
        """(F, P) bool — where there is an observation."""
        if self._positions is not None:
            return np.isfinite(self._positions).all(axis=2)
        out = np.zeros(self.shape, dtype=bool)
        out[self.frame, self.point] = True
        return out

    def used_mask(self) -> np.ndarray:
        """(F, P) bool — where the estimate used an observation."""
        if self._positions is not None and self._sparse is None:
            seen = self.seen()
            return seen if self._used is None else seen & self._used
        out = np.zeros(self.shape, dtype=bool)
        out[self.frame[self.used], self.point[self.used]] = True
        return out

    def used_per_point(self) -> np.ndarray:
        """(P,) int — observations used per point."""
        if self._sparse is None and "_arrays" not in self.__dict__:
            return self.used_mask().sum(axis=0).astype(np.int64)
        return np.bincount(self.point[self.used], minlength=self.shape[1]).astype(np.int64)

    def dense(self) -> np.ndarray:
        """(F, P, 2) positions, NaN where there is no observation."""
        if self._positions is not None:
            return self._positions
        out = np.full((*self.shape, 2), np.nan)
        out[self.frame, self.point] = self.xy
        return out

    def grid(self, values: np.ndarray) -> np.ndarray:
        """(F, P) array of ``values`` given per observation (in this object's order), NaN where there is none.

        Examples
        --------
        >>> obs = Observations.from_sparse((2, 2), [0, 1], [1, 0], [[1.0, 2.0], [3.0, 4.0]])
        >>> obs.grid(np.array([0.5, 0.25])).tolist()
        [[nan, 0.5], [0.25, nan]]
        """
        out = np.full(self.shape, np.nan)
        out[self.frame, self.point] = values
        return out

    def residual_matrix(self) -> np.ndarray:
        """(F, P) reprojection error lengths, NaN where there is no observation or no value."""
        if self._residual_values is not None:
            return self._residual_values
        return self.grid(self.residual)


@dataclass(frozen=True)
class NoiseEstimate:
    """The image noise a reconstruction's covariances are scaled with.

    Attributes
    ----------
    std : σ — pixels, or the standard deviation of unit weight when the observations were
        weighted (``unit == "unit weight"``: 1 when the given weights are right).
    estimated : σ came from the residuals (degrees of freedom counted); False when it was given.
    degrees_of_freedom : the residual degrees of freedom behind σ (observations' coordinates
        minus the parameters fitted, gauge counted).
    model : the noise model (``"gaussian"``).
    unit : ``"px"`` or ``"unit weight"``.
    parameters : other fitted parameters of the model, as (name, value) pairs.
    observation_std : (M,) each observation's own standard deviation under the model, one per
        entry of the reconstruction's :class:`Observations` in their order (pixels; NaN where
        it was left out; ``observations.grid(std)`` lays it out as frames × points), or None when
        every observation has σ.

    Examples
    --------
    >>> NoiseEstimate(0.5, True, 120).describe()
    'σ 0.5 px (gaussian, estimated, 120 degrees of freedom)'
    """

    std: float
    estimated: bool
    degrees_of_freedom: int
    model: str = "gaussian"
    unit: str = "px"
    parameters: tuple[tuple[str, float], ...] = ()
    observation_std: np.ndarray | None = field(default=None, compare=False, repr=False)

    def describe(self) -> str:
        """One line saying what σ is and where it came from."""
        unit = " px" if self.unit == "px" else f" ({self.unit})"
        how = f"estimated, {self.degrees_of_freedom} degrees of freedom" if self.estimated else "given"
        shown = {"tail_dof": "ν", "outlier_share": "outliers", "track_spread": "track spread α",
                 "serial_correlation_x": "ρx", "serial_correlation_y": "ρy"}
        extra = "".join(f", {shown[k]} {v:.3g}" for k, v in self.parameters if k in shown)
        return f"σ {self.std:.3g}{unit} ({self.model}{extra}, {how})"


@dataclass(frozen=True)
class AffineDetails:
    """What only a factorization has.

    Attributes
    ----------
    singular_values : (k,) leading singular values of the centred 2F × P measurement matrix
        (with missing data: of the matrix completed by the model).
    iterations : ALS iterations run (0 for the closed form).
    metric_matrix : (3, 3) A = Q Qᵀ actually used (after any positive-definite repair).
    weighted : the observations were weighted (1 / σ² of the tracker).
    shape_radius : the shape's radius (median distance of the well-seen points from their
        median) the reliability bound is relative to, in the points' unit.
    min_views, max_std_ratio : a point is reliable when seen in at least ``min_views`` frames
        and its largest 1σ axis is at most ``max_std_ratio`` × ``shape_radius``.
    """

    singular_values: np.ndarray
    iterations: int
    metric_matrix: np.ndarray
    weighted: bool
    shape_radius: float
    min_views: int
    max_std_ratio: float

    @property
    def bound(self) -> float:
        """The largest 1σ axis a reliable point may have."""
        return self.max_std_ratio * self.shape_radius


@dataclass(frozen=True)
class FusionDetails:
    """What only fusion with known cameras has.

    Attributes
    ----------
    outlier_probability : the χ² gate's probability (1: no outlier test).
    orientation : +1, or -1 for a mirrored reconstruction (points at negative depth).
    passes : passes over the data (more than 1 when σ was estimated).
    history : each point's estimate after every view (``FusionHistory``), or None.
    """

    outlier_probability: float
    orientation: int
    passes: int
    history: Any = None


@dataclass(frozen=True)
class PerspectiveDetails:
    """What only calibrated reconstruction with unknown motion has.

    Attributes
    ----------
    initial_pair : the two frame indices the reconstruction started from.
    outlier_threshold_px, outlier_probability : the outlier test.
    """

    initial_pair: tuple[int, int]
    outlier_threshold_px: float
    outlier_probability: float


Details = Union[AffineDetails, FusionDetails, PerspectiveDetails]


@dataclass(frozen=True)
class Reconstruction:
    """Cameras and 3-D points with covariances, from any method.

    Attributes
    ----------
    kind : which problem: ``"affine"`` (factorization), ``"fusion"`` (known cameras) or
        ``"perspective"`` (calibrated, unknown motion).
    method : the method within it (``"svd"``/``"als"``; ``"recursive"``/``"batch"``/``"pairs"``;
        ``"batch"``/``"recursive"``).
    camera_model : ``"affine"`` or ``"pinhole"``.
    projections : (F, 3, 4) each frame's camera matrix; NaN where the frame has none.
    rotations : (F, 3, 3) world → camera rotations (for affine cameras the nearest rotation
        to the camera rows completed by their cross product); NaN where none.
    intrinsics : (F, 3, 3) K of pinhole cameras, or None.
    translations : (F, 3) t of pinhole cameras (x_cam = R X + t), or None.
    pose_covariances : (F, 6, 6) covariance of (δω, δC), the small rotation of the camera
        frame and the centre, or None (cameras taken as exact).
    frame_status : (F,) int8 :class:`FrameStatus`.
    points : (P, 3) — NaN where not reconstructed.
    point_covariances : (P, 3, 3) in ``covariance_gauge``; NaN where unknown.
    point_status : (P,) int8 :class:`~kalmansfm.structure.PointStatus`.
    views : (P,) int — observations used per point.
    point_reprojection_rms : (P,) RMS length of each point's reprojection errors over the
        observations used (pixels); NaN where none.
    covariance_gauge : how the covariances are to be read.
    observations : :class:`Observations`.
    noise : :class:`NoiseEstimate`.
    reprojection_rms : RMS length of the reprojection errors over the observations used (pixels).
    details : the method's own figures.
    warnings : things the user should know about the result.
    frame_ids : (F,) int64 — frame numbers (default 0 … F−1).
    track_ids : (P,) int64 — point (track) numbers (default 0 … P−1).
    timings : seconds per stage (not compared).

    Examples
    --------
    >>> from kalmansfm.structure import factorize
    >>> rng = np.random.default_rng(0)
    >>> shape = rng.normal(size=(20, 3)) * 50
    >>> rows = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(6)]
    >>> tracks = np.stack([shape @ m.T + 100 for m in rows]) + rng.normal(scale=0.3, size=(6, 20, 2))
    >>> rec = factorize(tracks)
    >>> rec.kind, rec.camera_model, rec.points.shape, rec.point_covariances.shape, int(rec.registered.sum())
    ('affine', 'affine', (20, 3), (20, 3, 3), 6)
    >>> len(rec.observations), round(rec.noise.std, 1), rec.status_counts()["ok"]
    (120, 0.3, 20)
    """

    kind: str
    method: str
    camera_model: str
    projections: np.ndarray
    rotations: np.ndarray
    frame_status: np.ndarray
    points: np.ndarray
    point_covariances: np.ndarray
    point_status: np.ndarray
    views: np.ndarray
    point_reprojection_rms: np.ndarray
    covariance_gauge: str
    observations: Observations
    noise: NoiseEstimate
    reprojection_rms: float
    details: Details
    intrinsics: np.ndarray | None = None
    translations: np.ndarray | None = None
    pose_covariances: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    frame_ids: np.ndarray | None = None
    track_ids: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        check_choice("kind", self.kind, RECONSTRUCTION_KINDS)
        check_choice("camera_model", self.camera_model, CAMERA_MODELS)
        F, P = self.observations.shape
        if self.projections.shape != (F, 3, 4) or self.points.shape != (P, 3):
            raise InvalidInputError(f"a reconstruction of {F} frames and {P} points needs ({F}, 3, 4) projections and "
                                    f"({P}, 3) points; got {self.projections.shape} and {self.points.shape}")
        object.__setattr__(self, "frame_ids", np.arange(F, dtype=np.int64) if self.frame_ids is None
                           else np.asarray(self.frame_ids, dtype=np.int64))
        object.__setattr__(self, "track_ids", np.arange(P, dtype=np.int64) if self.track_ids is None
                           else np.asarray(self.track_ids, dtype=np.int64))
        if self.frame_ids.shape != (F,) or self.track_ids.shape != (P,):
            raise InvalidInputError(f"frame_ids and track_ids must have shapes ({F},) and ({P},); got "
                                    f"{self.frame_ids.shape} and {self.track_ids.shape}")

    # --- sizes and masks ---------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """F."""
        return int(self.projections.shape[0])

    @property
    def n_points(self) -> int:
        """P."""
        return int(self.points.shape[0])

    @property
    def registered(self) -> np.ndarray:
        """(F,) bool — frames with a camera."""
        return self.frame_status == FrameStatus.REGISTERED

    @property
    def reconstructed(self) -> np.ndarray:
        """(P,) bool — points with status ``ok``."""
        return self.point_status == PointStatus.OK

    @property
    def estimated(self) -> np.ndarray:
        """(P,) bool — points with a position (``ok`` or ``unreliable``)."""
        return np.isfinite(self.points).all(axis=1)

    def status_counts(self) -> dict[str, int]:
        """Points per :class:`~kalmansfm.structure.PointStatus` label."""
        return {s.label: int(np.count_nonzero(self.point_status == s)) for s in PointStatus}

    @property
    def point_std(self) -> np.ndarray:
        """(P,) √(tr Σ / 3) of each point's covariance (NaN where unknown)."""
        return rms_std(self.point_covariances)

    # --- cameras -----------------------------------------------------------------------------
    @property
    def centres(self) -> np.ndarray:
        """(F, 3) camera centres (pinhole: −Rᵀ t; affine: NaN, the centre is at infinity)."""
        if self.translations is None:
            return np.full((self.n_frames, 3), np.nan)
        return -np.einsum("fji,fj->fi", self.rotations, self.translations)

    @property
    def motion(self) -> np.ndarray:
        """(F, 2, 3) the first two rows of each camera's M (affine cameras: the camera rows i_f, j_f)."""
        return self.projections[:, :2, :3]

    @property
    def image_translation(self) -> np.ndarray:
        """(F, 2) the last column of each camera's first two rows (affine: the image of the centroid)."""
        return self.projections[:, :2, 3]

    def project(self, points: np.ndarray | None = None) -> np.ndarray:
        """(F, N, 2) image positions of ``points`` (default: this reconstruction's) in every frame."""
        X = self.points if points is None else np.asarray(points, dtype=np.float64)
        h = np.einsum("fij,nj->fni", self.projections[:, :, :3], X) + self.projections[:, None, :, 3]
        return h[..., :2] / h[..., 2:3]

    def mirrored(self) -> Reconstruction:
        """An affine reconstruction's depth-reversed twin, which explains the tracks exactly as well.

        Under orthography (S, M) and (D S, M D), D = diag(1, 1, −1), give the same images.
        """
        if self.camera_model != "affine":
            raise InvalidInputError("only an affine reconstruction has a depth-reversed twin")
        flip = np.array([1.0, 1.0, -1.0])
        projections = self.projections.copy()
        projections[:, :2, :3] *= flip
        D = np.diag(flip)
        return replace(self, points=self.points * flip, projections=projections,
                       rotations=D @ self.rotations @ D,
                       point_covariances=D @ self.point_covariances @ D)

    def with_ids(self, frame_ids: np.ndarray | None = None, track_ids: np.ndarray | None = None) -> Reconstruction:
        """The same reconstruction with the frame and track numbers files use."""
        return replace(self, frame_ids=self.frame_ids if frame_ids is None else frame_ids,
                       track_ids=self.track_ids if track_ids is None else track_ids)

    def summary(self) -> str:
        """A few lines that say what this reconstruction is."""
        counts = self.status_counts()
        lines = [f"{self.kind} reconstruction ({self.method}, {self.camera_model} cameras): "
                 f"{int(self.registered.sum())} of {self.n_frames} frames, {counts['ok']} of {self.n_points} points ok",
                 f"{self.observations.n_used} of {len(self.observations)} observations used; reprojection RMS "
                 f"{self.reprojection_rms:.3g} px; {self.noise.describe()}",
                 f"covariances: {self.covariance_gauge}"]
        return "\n".join([*lines, *(f"warning: {w}" for w in self.warnings)])
