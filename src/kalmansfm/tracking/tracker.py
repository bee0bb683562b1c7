"""The Kalman tracker: predict, measure, update — for all tracks at once.

Two matchers measure the tracks (``TrackerSettings.matcher``; ``docs/tracking.md``):

- ``"differential"`` (default): Lucas–Kanade started from each track's prediction,
  checked by the gate, a forward–backward flow and its anchor's appearance, anchored to
  its first appearance or a keyframe, with a measurement noise R from the refinement
  itself (:mod:`._differential_step`, :mod:`kalmansfm.tracking.differential`);
- ``"search"``: the report's gated exhaustive template search with anchored templates
  (:mod:`._search_step`).

The tracker holds every live track in one batched
:class:`~kalmansfm.estimation.KalmanFilter` and one row of per-track state beside it
(:mod:`._rows`).  Per frame the matcher predicts, measures and updates the tracks in the
filter; the tracker then applies what both matchers share (:mod:`._identity`): a
track's innovation statistics, its misses, and its loss after ``max_misses`` frames of
coasting (a re-acquisition candidate found on the last allowed frame gets one more
frame to be confirmed).  A new track (from ``points``, the detector, or ``redetect``)
waits one frame: in the next one the matcher finds it again near its first position
(a gate of Σ0's position block around it), and the filter starts there with
s0 = [x₁, y₁, x₁ - x₀, y₁ - y₀] and Σ0, as in the report.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from .._validation import as_float_array
from ..errors import InvalidInputError, NotEnoughDataError
from ..estimation.kalman import KalmanFilter
from ..estimation.models import initial_state
from ._differential_step import DifferentialMatcher
from ._identity import mean_squared_innovation
from ._rows import FrameRecord, Rows, StepOutcome, concatenate_records
from ._search_step import SearchMatcher
from .detect import detect_corners
from .grey import colour_to_grey
from .reattach import DESCRIPTOR_SIZE, LostTracks, describe, match_lost
from .settings import TrackerSettings
from .smoothing import smooth_tracks
from .tracks import INITIALISING, LOST, MEASURED, PREDICTED, Tracks

__all__ = ["FrameEstimate", "Tracker", "track"]


@dataclass(frozen=True)
class FrameEstimate:
    """What the tracker knows after one frame (returned by :meth:`Tracker.feed`).

    Attributes
    ----------
    frame_index : index of the frame just processed.
    track_ids : (k,) ids of the tracks present in this frame (including the ones lost in it).
    positions : (k, 2) posterior (or predicted) positions, NaN for tracks lost in this frame.
    status : (k,) int8 codes (1 measured, 2 predicted, 3 lost, 4 initialising: the track's first two frames).
    """

    frame_index: int
    track_ids: np.ndarray
    positions: np.ndarray
    status: np.ndarray


def _as_grey(frame: object, index: int, keep_8_bits: bool = False) -> np.ndarray:
    """The frame as a 2D float32 array (exact for 8- and 16-bit images; single precision is all the matcher uses).

    Colour (BGR or BGRA) becomes grey by :func:`~kalmansfm.tracking.grey.colour_to_grey`, as in the frame readers.

    With ``keep_8_bits`` a 2D uint8 frame is returned as it is (the differential matcher reads 8 bits).
    """
    array = np.asarray(frame)
    if array.ndim == 3 and array.shape[2] in (3, 4) and array.dtype.kind in "buif":
        array = colour_to_grey(np.ascontiguousarray(array))  # BGR(A), the one policy of the readers too
    if keep_8_bits and array.ndim == 2 and array.dtype == np.uint8:
        return np.ascontiguousarray(array)
    if array.ndim != 2:
        raise InvalidInputError(f"frame {index} must be a 2D grey image (H, W); got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.number):
        raise InvalidInputError(f"frame {index} must be numeric; got dtype {array.dtype}")
    return np.ascontiguousarray(array, dtype=np.float32)


class Tracker:
    """Streaming Kalman tracker (differential or search matcher): feed one frame at a time.

    Parameters
    ----------
    points : (P, 2) positions (x, y) to track from the first frame fed, or None to
        detect corners there.
    track_ids : optional (P,) integer ids for ``points`` (default 0 … P-1).
    settings : :class:`~kalmansfm.tracking.settings.TrackerSettings` (window, score,
        gate, misses, thresholds, motion model, detection, …); default settings when None.
    **options : individual settings instead of (or on top of) ``settings``, e.g. ``window=15``.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> import cv2
    >>> world = cv2.GaussianBlur(rng.uniform(0, 255, (80, 140)), (0, 0), 1.5)
    >>> frames = [world[10:70, 10 + 2 * k: 90 + 2 * k] for k in range(6)]   # moves 2 px left per frame
    >>> tracker = Tracker(points=np.array([[40.0, 30.0]]))
    >>> for f in frames:
    ...     estimate = tracker.feed(f)
    >>> np.round(estimate.positions, 1), estimate.status
    (array([[30., 30.]]), array([1], dtype=int8))
    """

    def __init__(
        self,
        points: object | None = None,
        *,
        track_ids: object | None = None,
        settings: TrackerSettings | None = None,
        **options: Any,
    ) -> None:
        self.settings = make_settings(settings, options)
        s = self.settings
        self.gate_radius = s.effective_gate_radius
        self.model = s.model
        self.window = s.window

        self._initial_points = None if points is None else self._check_points(points)
        self._initial_ids = None
        if track_ids is not None:
            ids = np.asarray(track_ids)
            if self._initial_points is None or ids.shape != (len(self._initial_points),):
                raise InvalidInputError("track_ids must have one integer per point")
            if len(np.unique(ids)) != len(ids):
                raise InvalidInputError("track_ids must be unique")
            self._initial_ids = ids.astype(np.int64)

        self._frame_index = -1
        self._shape: tuple[int, int] | None = None
        self._next_id = 0
        self._records: list[FrameRecord] = []
        self._differential = s.matcher == "differential"
        self._matcher = DifferentialMatcher(s) if self._differential else SearchMatcher(s)
        # Tracks in the filter, and their rows of per-track state.
        self._kf: KalmanFilter | None = None
        self._rows = self._matcher.empty_rows()
        # Tracks started in the previous frame and waiting for their second frame.
        self._pending_ids = np.zeros(0, np.int64)
        self._pending_positions = np.zeros((0, 2))
        self._pending_templates = np.zeros((0, self.window, self.window), self._matcher.template_dtype)
        # Re-attachment: recently lost tracks, and each live track's descriptor at its last keyframe.
        self._lost = LostTracks.empty(self.window)
        self._described_ids = np.zeros(0, np.int64)
        self._descriptors = np.zeros((0, DESCRIPTOR_SIZE), np.float32)

    # -- validation -------------------------------------------------------------
    @staticmethod
    def _check_points(points: object) -> np.ndarray:
        arr = as_float_array("points", points)
        if arr.ndim != 2 or arr.shape[1] != 2:
            raise InvalidInputError(f"points must have shape (P, 2) as (x, y); got {arr.shape}")
        if not np.isfinite(arr).all():
            row = int(np.argwhere(~np.isfinite(arr))[0, 0])
            raise InvalidInputError(f"points row {row} is not finite: {arr[row].tolist()}")
        return arr

    def _check_inside(self, points: np.ndarray) -> None:
        height, width = self._shape  # type: ignore[misc]
        outside = (points[:, 0] < 0) | (points[:, 0] > width - 1) | (points[:, 1] < 0) | (points[:, 1] > height - 1)
        if outside.any():
            row = int(np.flatnonzero(outside)[0])
            raise InvalidInputError(
                f"points row {row} ({points[row, 0]:g}, {points[row, 1]:g}) lies outside the "
                f"{width}×{height} image (x must be in [0, {width - 1}], y in [0, {height - 1}])"
            )

    # -- streaming --------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Number of frames fed so far."""
        return self._frame_index + 1

    def feed(self, frame: object) -> FrameEstimate:
        """Process the next frame and return the estimates for it."""
        image = _as_grey(frame, self._frame_index + 1, keep_8_bits=self._differential)
        if self._shape is None:
            self._shape = image.shape  # type: ignore[assignment]
            if min(image.shape) < self.window:
                raise InvalidInputError(f"frames of {image.shape[1]}×{image.shape[0]} are smaller than the {self.window}-pixel window")
        elif image.shape != self._shape:
            raise InvalidInputError(
                f"frame {self._frame_index + 1} has size {image.shape[1]}×{image.shape[0]}, "
                f"but the first frame has {self._shape[1]}×{self._shape[0]}"
            )
        self._frame_index += 1
        if self._frame_index == 0:
            self._first_frame(image)
        else:
            self._next_frame(image)
        return self._estimate()

    def _first_frame(self, image: np.ndarray) -> None:
        if self._initial_points is not None:
            self._check_inside(self._initial_points)
            points = self._initial_points
        else:
            points = detect_corners(
                np.asarray(image, dtype=np.float32), self.settings.max_features, self.settings.quality_level, self.settings.min_distance_px, border_px=self.window // 2
            )
        if self._initial_ids is not None:
            ids = self._initial_ids
            self._next_id = int(ids.max()) + 1 if len(ids) else 0
        else:
            ids = np.arange(len(points), dtype=np.int64)
            self._next_id = len(points)
        frame = self._matcher.prepare(image)
        self._start_pending(frame, points, ids)
        self._records.append(self._pending_record())
        self._matcher.remember(frame)

    def _start_pending(self, frame: object, points: np.ndarray, ids: np.ndarray) -> None:
        templates = self._matcher.cut_templates(frame, points)
        self._pending_ids = np.concatenate([self._pending_ids, ids])
        self._pending_positions = np.concatenate([self._pending_positions, points])
        self._pending_templates = np.concatenate([self._pending_templates, templates])

    def _pending_record(self) -> FrameRecord:
        n = len(self._pending_ids)
        states = np.concatenate([self._pending_positions, np.zeros((n, 2))], axis=1)
        return FrameRecord(
            ids=self._pending_ids.copy(),
            states=states,
            covariances=np.broadcast_to(self.model.P0, (n, 4, 4)).copy(),
            status=np.full(n, INITIALISING, np.int8),
            scores=np.zeros(n),
        )

    def _next_frame(self, image: np.ndarray) -> None:
        frame = self._matcher.prepare(image)
        records: list[FrameRecord] = []
        if self._kf is not None and len(self._rows):
            records.append(self._finish_step(self._matcher.step(frame, self._kf, self._rows)))
        if len(self._pending_ids):
            ids, first, templates = self._take_pending()
            start = self._matcher.start(frame, ids, first, templates)
            records.append(self._add_to_filter(start.rows, first, start.second, start.found, start.scores))
        record = concatenate_records(records)
        if self.settings.redetect and self._frame_index % self.settings.redetect_every == 0:
            new = self._detect_new(frame.image)
            measured = record.status == MEASURED
            described = np.zeros((0, DESCRIPTOR_SIZE), np.float32)
            if self.settings.reattach_frames:  # the new corners and the measured tracks, on one image pyramid
                described = describe(frame.image, np.concatenate([new, record.states[measured, :2]]), self.window)
                self._remember_descriptors(record.ids[measured], described[len(new):])
            if len(new):
                ids = self._ids_for(frame, new, described[:len(new)])
                self._start_pending(frame, new, ids)
                record = concatenate_records([record, self._pending_record()])
        self._records.append(record)
        self._matcher.remember(frame)

    def _ids_for(self, frame: Any, corners: np.ndarray, descriptors: np.ndarray) -> np.ndarray:
        """Ids of redetected corners: a lost track's own where it is found again (re-attachment), else new ones."""
        ids = np.full(len(corners), -1, np.int64)
        if self.settings.reattach_frames:
            lost = self._lost
            lost.keep(lost.frames >= self._frame_index - self.settings.reattach_frames)
            corner, track = match_lost(lost, self._frame_index, corners, descriptors,
                                       self._matcher.cut_templates(frame, corners), self.model, self.gate_radius,
                                       self.settings.reacquire_ncc)
            ids[corner] = lost.ids[track]
            kept = np.ones(len(lost.ids), bool)
            kept[track] = False
            lost.keep(kept)
        fresh = ids < 0
        ids[fresh] = np.arange(self._next_id, self._next_id + int(fresh.sum()), dtype=np.int64)
        self._next_id += int(fresh.sum())
        return ids

    def _remember_descriptors(self, ids: np.ndarray, descriptors: np.ndarray) -> None:
        """Keyframe: the descriptors of the tracks measured in it (older ones kept for the live tracks not)."""
        live = np.isin(self._described_ids, self._rows.ids) & ~np.isin(self._described_ids, ids)
        self._described_ids = np.concatenate([self._described_ids[live], ids])
        self._descriptors = np.concatenate([self._descriptors[live], descriptors])

    def _remember_lost(self, ids: np.ndarray, states: np.ndarray, covariances: np.ndarray, templates: np.ndarray
                       ) -> None:
        """Tracks lost in this frame, kept for re-attachment with their last keyframe's descriptor."""
        same = self._described_ids[:, None] == ids[None, :]  # (described, lost): a few hundred by a few
        known = same.any(axis=0)
        descriptors = np.full((len(ids), DESCRIPTOR_SIZE), np.nan, np.float32)
        if known.any():
            descriptors[known] = self._descriptors[np.argmax(same[:, known], axis=0)]
        self._lost.add(ids, self._frame_index, states, covariances, descriptors, templates)

    def _live(self) -> np.ndarray:
        """Rows of the filter that are tracks (not retired)."""
        retired = self._rows.retired
        return np.ones(len(self._rows), bool) if retired is None else ~retired

    def _detect_new(self, image: np.ndarray) -> np.ndarray:
        live = self._live()
        room = self.settings.max_features - int(live.sum())
        if room <= 0:
            return np.zeros((0, 2))
        occupied = self._kf.x[live, :2] if self._kf is not None and len(self._rows) else np.zeros((0, 2))
        return detect_corners(
            image, room, self.settings.quality_level, self.settings.min_distance_px, border_px=self.window // 2, exclude=occupied
        )

    def _take_pending(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pending tracks (ids, first positions, templates), now leaving the pending list."""
        taken = self._pending_ids, self._pending_positions, self._pending_templates
        self._pending_ids = np.zeros(0, np.int64)
        self._pending_positions = np.zeros((0, 2))
        self._pending_templates = self._pending_templates[:0]
        return taken

    def _add_to_filter(self, rows: Rows, first: np.ndarray, second: np.ndarray, found: np.ndarray, scores: np.ndarray) -> FrameRecord:
        """Start the filter of new tracks at their second frame: s0 = [x₁, y₁, x₁ - x₀, y₁ - y₀], Σ0."""
        n = len(rows)
        states = initial_state(first, second)
        covariances = np.broadcast_to(self.model.P0, (n, 4, 4)).copy()
        # Found: still initialising (a measurement, with the start-up prior Σ0 as covariance).
        record = FrameRecord(rows.ids.copy(), states, covariances, np.where(found, INITIALISING, PREDICTED).astype(np.int8), scores)
        if self._kf is not None and len(self._rows):
            # The filter is built again: retired rows leave it now.
            live = self._live()
            states = np.concatenate([self._kf.x[live], states])
            covariances = np.concatenate([np.broadcast_to(self._kf.P, (len(self._rows), 4, 4))[live], covariances])
            rows = self._rows.take(live).append(rows)
        self._set_filter(rows, states, covariances)
        return record

    def _set_filter(self, rows: Rows, states: np.ndarray, covariances: np.ndarray) -> None:
        m = self.model
        if len(rows):
            shared = bool(np.all(covariances == covariances[:1]))
            P = covariances[0] if shared else covariances
            self._kf = KalmanFilter(states, P, m.F, m.H, m.Q, m.R)
        else:
            self._kf = None
        self._rows = rows

    def _finish_step(self, step: StepOutcome) -> FrameRecord:
        """After the update: innovation statistics, misses and losses, the frame's record; lost tracks leave the filter."""
        kf = self._kf
        assert kf is not None  # internal invariant, not user input
        rows, good, new_candidate, scores = step.rows, step.good, step.new_candidate, step.scores
        mean_sq = mean_squared_innovation(rows, good, step.innovation_sq)
        misses = np.where(good, 0, rows.misses + 1)
        # A candidate found on the last allowed frame gets one more frame to be confirmed.
        limit = self.settings.coast_limit
        lost = (misses > limit) & ~(new_candidate & (misses == limit + 1))
        status = np.where(good, MEASURED, PREDICTED).astype(np.int8)
        status[lost] = LOST
        if rows.retired is None:
            states, covariances = np.array(kf.x), np.array(kf.P)
            shown = slice(None)
        else:
            # Retired rows (lost earlier) are no tracks: not in the record, not lost again.
            lost &= ~rows.retired
            shown = np.flatnonzero(~rows.retired)
            states, covariances = kf.x[shown], np.broadcast_to(kf.P, (len(rows), 4, 4))[shown]
        if self.settings.reattach_frames and lost.any():
            self._remember_lost(rows.ids[lost], np.array(kf.x)[lost], np.broadcast_to(kf.P, (len(rows), 4, 4))[lost],
                                rows.templates[lost])
        states[lost[shown]] = np.nan
        covariances[lost[shown]] = np.nan
        record = FrameRecord(rows.ids[shown].copy(), states, covariances, status[shown], np.asarray(scores)[shown])
        rows = replace(rows, misses=misses, innovation_sq=mean_sq)
        self._rows = rows
        if not lost.any():
            return record
        if rows.retired is None:
            keep = ~lost
            self._set_filter(rows.take(keep), kf.x[keep], np.broadcast_to(kf.P, (len(rows), 4, 4))[keep])
            return record
        # Building the filter again validates every covariance: lost tracks of the differential
        # matcher are retired in place (predicted, never measured) and leave it together.
        retired = rows.retired | lost
        self._rows = rows = replace(rows, retired=retired)
        if retired.sum() > max(32, len(rows) // 8):
            keep = ~retired
            self._set_filter(rows.take(keep), kf.x[keep], np.broadcast_to(kf.P, (len(rows), 4, 4))[keep])
        return record

    def _estimate(self) -> FrameEstimate:
        r = self._records[-1]
        return FrameEstimate(self._frame_index, r.ids, r.states[:, :2].copy(), r.status)

    # -- result -----------------------------------------------------------------
    def result(self) -> Tracks:
        """All frames fed so far as :class:`~kalmansfm.tracking.tracks.Tracks`.

        Columns follow the order in which the tracks were created (ids may be user-given
        in any order).
        """
        if not self._records:
            raise NotEnoughDataError("no frame was fed to the tracker")
        ids = np.concatenate([r.ids for r in self._records])
        frame_of = np.repeat(np.arange(len(self._records)), [len(r.ids) for r in self._records])
        # Column of every record entry: ids ranked by their first appearance.
        unique, first, column = np.unique(ids, return_index=True, return_inverse=True)
        rank = np.empty(len(unique), np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(len(unique))
        column = rank[column]
        order = unique[np.argsort(first, kind="stable")]
        F, P = len(self._records), len(order)
        tracks = Tracks.empty(F, P)
        scores = np.full((F, P), np.nan)
        tracks.states[frame_of, column] = np.concatenate([r.states for r in self._records])
        tracks.covariances[frame_of, column] = np.concatenate([r.covariances for r in self._records])
        tracks.status[frame_of, column] = np.concatenate([r.status for r in self._records])
        scores[frame_of, column] = np.concatenate([r.scores for r in self._records])
        height, width = self._shape  # type: ignore[misc]
        return Tracks(
            positions=tracks.states[..., :2].copy(),
            status=tracks.status,
            track_ids=order,
            states=tracks.states,
            covariances=tracks.covariances,
            scores=scores,
            image_size=(int(width), int(height)),
            settings=self.settings,
        )


def make_settings(settings: TrackerSettings | None, options: dict[str, Any]) -> TrackerSettings:
    """``settings`` (default settings when None) with the keyword ``options`` applied on top.

    Raises
    ------
    InvalidInputError
        An option that is not a tracker setting, or an invalid value.
    """
    unknown = sorted(set(options) - set(TrackerSettings.option_names()))
    if unknown:
        raise InvalidInputError(f"unknown tracker option(s) {', '.join(unknown)}; the options are the fields of TrackerSettings")
    if settings is None:
        return TrackerSettings(**options)
    if not isinstance(settings, TrackerSettings):
        raise InvalidInputError(f"settings must be a TrackerSettings; got {type(settings).__name__}")
    return replace(settings, **options) if options else settings


def track(
    frames: Iterable[Any],
    points: object | None = None,
    *,
    track_ids: object | None = None,
    settings: TrackerSettings | None = None,
    progress: bool = False,
    smooth: bool | int = False,
    **options: Any,
) -> Tracks:
    """Track points through a sequence of frames.

    Parameters
    ----------
    frames : a sequence or iterator of 2D grey arrays (uint8 or float); to read a folder,
        a glob or a video use :func:`kalmansfm.io.read_frames` first.
    points : (P, 2) positions (x, y) in frame 0, or None to detect corners.
    track_ids : optional (P,) integer ids for ``points``.
    settings : :class:`~kalmansfm.tracking.settings.TrackerSettings` (default settings when None).
    progress : show a tqdm progress bar on stderr.
    smooth : False (online estimates), True (Rauch–Tung–Striebel smoothing of each
        finished track over its whole life) or an int L (fixed-lag smoothing: frame t
        uses the frames up to t + L); see :func:`kalmansfm.tracking.smoothing.smooth_tracks`.
    **options : individual settings on top of ``settings`` (``window``, ``score``,
        ``gate_probability``, ``gate_radius``, ``max_misses``, ``template_policy``, ``redetect``, …).

    Returns
    -------
    Tracks
        With ``settings`` the settings used.

    Raises
    ------
    NotEnoughDataError
        Fewer than 3 frames.

    Examples
    --------
    >>> import cv2
    >>> rng = np.random.default_rng(2)
    >>> world = cv2.GaussianBlur(rng.uniform(0, 255, (100, 160)), (0, 0), 1.5)
    >>> frames = [world[20:80, 20 + k: 100 + k] for k in range(5)]   # the scene moves 1 px left per frame
    >>> tracks = track(frames, np.array([[40.0, 30.0], [50.0, 20.0]]))
    >>> tracks.positions.shape, tracks.status[-1].tolist()
    ((5, 2, 2), [1, 1])
    >>> np.round(tracks.positions[-1], 1).tolist()
    [[36.0, 30.0], [46.0, 20.0]]
    """
    if isinstance(frames, (str, bytes)) or hasattr(frames, "__fspath__"):
        raise InvalidInputError(
            "frames must be images (arrays), not a path; read a folder, glob or video with kalmansfm.io.read_frames"
        )
    total = getattr(frames, "count", None)
    if callable(total):  # list.count and tuple.count are methods, not a frame count
        total = None
    if total is None and hasattr(frames, "__len__"):
        total = len(frames)  # type: ignore[arg-type]
    tracker = Tracker(points, track_ids=track_ids, settings=settings, **options)
    try:
        iterator: Iterable[Any] = iter(frames)
    except TypeError:
        raise InvalidInputError(f"frames must be an iterable of 2D arrays; got {type(frames).__name__}") from None
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, total=total, unit="frame", desc="tracking", leave=False)
    for frame in iterator:
        tracker.feed(frame)
    if tracker.n_frames < 3:
        raise NotEnoughDataError(f"tracking needs at least 3 frames; got {tracker.n_frames}")
    if smooth is False:
        return tracker.result()
    return smooth_tracks(tracker.result(), lag=None if smooth is True else int(smooth))
