"""Point tracks: the one container every layer passes around, and the one status code.

:class:`Tracks` holds what the tracker produced (states and covariances included) and
equally what a file holds that has only positions (a plain ``frame,track_id,x,y`` CSV):
the optional arrays are then None.  :class:`TrackStatus` is the status of a track in a
frame; files store its integer value (``tracks.npz``) or its lower-case name (``tracks.csv``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from .settings import TrackerSettings

__all__ = ["TrackStatus", "Tracks", "NO_TRACK", "MEASURED", "PREDICTED", "LOST"]


class TrackStatus(IntEnum):
    """Status of a track in one frame.

    Examples
    --------
    >>> TrackStatus(1).label, TrackStatus.from_label("predicted").value
    ('measured', 2)
    """

    #: the track does not exist in this frame (not started yet, or lost earlier)
    NONE = 0
    #: the template was found; the position is the Kalman posterior
    MEASURED = 1
    #: no acceptable match; the track coasts on its prediction
    PREDICTED = 2
    #: the frame in which the track was declared lost (no position); NONE afterwards
    LOST = 3

    @property
    def label(self) -> str:
        """The word files use for this status (``none``, ``measured``, ``predicted``, ``lost``)."""
        return self.name.lower()

    @classmethod
    def from_label(cls, label: str) -> TrackStatus:
        """The status named ``label`` (as :attr:`label` writes it); raises ``KeyError`` otherwise."""
        if label != label.lower():
            raise KeyError(label)
        return cls[label.upper()]


# Short names for array comparisons (``tracks.status == MEASURED``).
NO_TRACK, MEASURED, PREDICTED, LOST = TrackStatus


def _as_array(value: Any, dtype: type) -> np.ndarray | None:
    return None if value is None else np.asarray(value, dtype=dtype)


@dataclass(frozen=True)
class Tracks:
    """Point tracks over a sequence, column p being the track ``track_ids[p]``.

    Attributes
    ----------
    positions : (F, P, 2) float64
        Position (x = column, y = row) of each track in each frame: the Kalman posterior
        where measured, the prediction while coasting; NaN where the track has no
        estimate (status NONE or LOST).
    status : (F, P) int8
        :class:`TrackStatus` codes.
    track_ids : (P,) int64
        Identity of each column; kept through coasting and re-acquisition.
    states : (F, P, 4) float64 or None
        Kalman state [x, y, vx, vy] (pixels, pixels per frame), NaN where none; None
        when the source holds positions only.
    covariances : (F, P, 4, 4) float64 or None
        State covariance (the prior while coasting), NaN where none.  A ``tracks.csv``
        gives only the position variances (the other entries NaN).
    frames : (F,) int64
        Frame number of each row (default 0 … F-1).
    scores : (F, P) float64 or None
        Dissimilarity of the best match; NaN where nothing was searched.
    image_size : (width, height) of the frames, or None.
    settings : the :class:`~kalmansfm.tracking.settings.TrackerSettings` that made the
        tracks, or None when unknown.
    smoothed : False for online estimates; True (fixed interval) or the lag L when the
        states are Rauch–Tung–Striebel smoothed.

    Examples
    --------
    >>> t = Tracks.empty(frames=3, tracks=2)
    >>> t.positions.shape, t.status.dtype.name, t.n_frames, t.n_tracks, t.frames.tolist()
    ((3, 2, 2), 'int8', 3, 2, [0, 1, 2])
    """

    positions: np.ndarray
    status: np.ndarray
    track_ids: np.ndarray
    states: np.ndarray | None = None
    covariances: np.ndarray | None = None
    frames: np.ndarray | None = None
    scores: np.ndarray | None = None
    image_size: tuple[int, int] | None = None
    settings: TrackerSettings | None = None
    smoothed: bool | int = False

    def __post_init__(self) -> None:
        status = np.asarray(self.status)
        if status.ndim != 2:
            raise InvalidInputError(f"Tracks.status must have shape (frames, tracks); got {status.shape}")
        F, P = status.shape
        frames = np.arange(F, dtype=np.int64) if self.frames is None else np.asarray(self.frames, dtype=np.int64)
        object.__setattr__(self, "frames", frames)
        object.__setattr__(self, "status", status.astype(np.int8, copy=False))
        object.__setattr__(self, "track_ids", np.asarray(self.track_ids, dtype=np.int64))
        for name in ("positions", "states", "covariances", "scores"):
            object.__setattr__(self, name, _as_array(getattr(self, name), np.float64))
        expected = {
            "positions": (F, P, 2),
            "track_ids": (P,),
            "frames": (F,),
            "states": (F, P, 4),
            "covariances": (F, P, 4, 4),
            "scores": (F, P),
        }
        for name, shape in expected.items():
            value = getattr(self, name)
            if value is not None and value.shape != shape:
                raise InvalidInputError(f"Tracks.{name} must have shape {shape}; got {value.shape}")

    @classmethod
    def empty(cls, frames: int, tracks: int, **extra: Any) -> Tracks:
        """Tracks with every estimate NaN (states and covariances included) and every status NONE."""
        return cls(
            positions=np.full((frames, tracks, 2), np.nan),
            status=np.zeros((frames, tracks), np.int8),
            track_ids=np.arange(tracks, dtype=np.int64),
            states=np.full((frames, tracks, 4), np.nan),
            covariances=np.full((frames, tracks, 4, 4), np.nan),
            **extra,
        )

    def replace(self, **changes: Any) -> Tracks:
        """A copy with some fields changed (checked again)."""
        return replace(self, **changes)

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return int(self.status.shape[0])

    @property
    def n_tracks(self) -> int:
        """Number of tracks P."""
        return int(self.status.shape[1])

    @property
    def measured(self) -> np.ndarray:
        """(F, P) True where the track was measured."""
        return self.status == MEASURED

    @property
    def alive(self) -> np.ndarray:
        """(F, P) True where the track has a position (measured or coasting)."""
        return (self.status == MEASURED) | (self.status == PREDICTED)

    @property
    def position_std(self) -> np.ndarray | None:
        """(F, P, 2) standard deviations of x and y from the covariances, or None without covariances."""
        if self.covariances is None:
            return None
        return np.sqrt(np.diagonal(self.covariances[..., :2, :2], axis1=-2, axis2=-1))

    def observations(self) -> np.ndarray:
        """(F, P, 2) the measured positions, NaN elsewhere (a coasting prediction is no observation)."""
        return np.where(self.measured[..., None], self.positions, np.nan)

    def observation_weights(self) -> np.ndarray | None:
        """(F, P, 2) least-squares weights 1 / σ² of the observations (0 elsewhere), or None without covariances."""
        std = self.position_std
        if std is None:
            return None
        with np.errstate(divide="ignore", invalid="ignore"):
            weights = np.where(self.measured[..., None], 1.0 / std**2, 0.0)
        return np.nan_to_num(weights, nan=0.0, posinf=0.0)

    def covariance_trace(self) -> np.ndarray | None:
        """(F, P) trace of each state covariance where the track is alive (NaN elsewhere), or None."""
        if self.covariances is None:
            return None
        return np.where(self.alive, np.trace(self.covariances, axis1=-2, axis2=-1), np.nan)

    def mean_covariance_trace(self) -> np.ndarray:
        """(F,) mean trace of the covariance over the tracks alive in each frame (the report's Figure 1)."""
        trace = self.covariance_trace()
        if trace is None:
            return np.full(self.n_frames, np.nan)
        counts = np.sum(self.alive, axis=1)
        return np.where(counts > 0, np.nansum(trace, axis=1) / np.maximum(counts, 1), np.nan)

    def survival(self) -> np.ndarray:
        """(F,) fraction of the tracks started in frame 0 that are alive in each frame."""
        started = self.alive[0]
        if not started.any():
            return np.zeros(self.n_frames)
        return self.alive[:, started].mean(axis=1)
