"""The result of tracking: per-frame Kalman estimates and a status code for every track."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import InvalidInputError

__all__ = ["NO_TRACK", "MEASURED", "PREDICTED", "LOST", "STATUS_NAMES", "Tracks"]

#: status code: the track does not exist in this frame (not started yet, or lost earlier)
NO_TRACK = 0
#: status code: the template was found; the position is the Kalman posterior
MEASURED = 1
#: status code: no acceptable match; the track coasts on its prediction
PREDICTED = 2
#: status code: the frame in which the track was declared lost (no position); 0 afterwards
LOST = 3

STATUS_NAMES = {NO_TRACK: "none", MEASURED: "measured", PREDICTED: "predicted", LOST: "lost"}


@dataclass(frozen=True)
class Tracks:
    """Tracked points over a sequence.

    Attributes
    ----------
    positions : (F, P, 2) float64
        Posterior position (x = column, y = row) of each track in each frame; the
        prediction while the track coasts; NaN where the track has no estimate
        (status 0 or 3).
    states : (F, P, 4) float64
        Kalman state [x, y, vx, vy] (pixels, pixels per frame), NaN where none.
    covariances : (F, P, 4, 4) float64
        Posterior state covariance (the prior when coasting), NaN where none.
    status : (F, P) int8
        0 no track, 1 measured, 2 predicted (coasting), 3 lost (only in the frame of
        the loss, 0 afterwards).  See :data:`STATUS_NAMES`.
    track_ids : (P,) int64
        Identity of each column; kept through coasting and re-acquisition.
    scores : (F, P) float64
        Dissimilarity of the best match (SSD / template energy, or 1 - NCC); NaN
        where nothing was searched.
    image_size : (width, height) of the frames.
    parameters : the options the tracker ran with.

    Examples
    --------
    >>> t = Tracks.empty(frames=3, tracks=2)
    >>> t.positions.shape, t.status.dtype.name, t.n_frames, t.n_tracks
    ((3, 2, 2), 'int8', 3, 2)
    """

    positions: np.ndarray
    states: np.ndarray
    covariances: np.ndarray
    status: np.ndarray
    track_ids: np.ndarray
    scores: np.ndarray | None = None
    image_size: tuple[int, int] | None = None
    parameters: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        F, P = self.status.shape if self.status.ndim == 2 else (None, None)
        expected = {
            "positions": (F, P, 2),
            "states": (F, P, 4),
            "covariances": (F, P, 4, 4),
            "status": (F, P),
            "track_ids": (P,),
        }
        if F is None:
            raise InvalidInputError(f"status must have shape (frames, tracks); got {self.status.shape}")
        for name, shape in expected.items():
            got = getattr(self, name).shape
            if got != shape:
                raise InvalidInputError(f"Tracks.{name} must have shape {shape}; got {got}")
        if self.scores is not None and self.scores.shape != (F, P):
            raise InvalidInputError(f"Tracks.scores must have shape {(F, P)}; got {self.scores.shape}")

    @classmethod
    def empty(cls, frames: int, tracks: int, **extra: Any) -> Tracks:
        """Tracks with every estimate NaN and every status 0."""
        return cls(
            positions=np.full((frames, tracks, 2), np.nan),
            states=np.full((frames, tracks, 4), np.nan),
            covariances=np.full((frames, tracks, 4, 4), np.nan),
            status=np.zeros((frames, tracks), np.int8),
            track_ids=np.arange(tracks, dtype=np.int64),
            **extra,
        )

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
    def position_std(self) -> np.ndarray:
        """(F, P, 2) standard deviations of x and y from the covariances."""
        return np.sqrt(np.diagonal(self.covariances[..., :2, :2], axis1=-2, axis2=-1))

    def mean_covariance_trace(self) -> np.ndarray:
        """(F,) mean trace of the posterior covariance over the tracks alive in each frame (the report's Figure 1)."""
        trace = np.trace(self.covariances, axis1=-2, axis2=-1)
        trace = np.where(self.alive, trace, np.nan)
        counts = np.sum(self.alive, axis=1)
        total = np.nansum(trace, axis=1)
        return np.where(counts > 0, total / np.maximum(counts, 1), np.nan)

    def survival(self) -> np.ndarray:
        """(F,) fraction of the tracks started in frame 0 that are alive in each frame."""
        started = self.alive[0]
        if not started.any():
            return np.zeros(self.n_frames)
        return self.alive[:, started].mean(axis=1)
