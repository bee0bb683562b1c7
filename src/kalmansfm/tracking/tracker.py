"""The Kalman tracker: predict, measure, update — for all tracks at once.

Two matchers measure the tracks (``TrackerSettings.matcher``; ``docs/tracking.md``):

- ``"differential"`` (default): Lucas–Kanade started from each track's prediction,
  checked by the gate, a forward–backward flow and its anchor's appearance, anchored to
  its first appearance or a keyframe, with a measurement noise R from the refinement
  itself (:mod:`kalmansfm.tracking.differential`; :meth:`Tracker._step_differential`).
  A coasting track is searched with its anchor and, as below, re-acquired only when a
  second frame confirms the candidate.
- ``"search"``: the report's gated exhaustive template search, described below.

Per frame of the search, with one batched :class:`~kalmansfm.estimation.KalmanFilter`
holding every live track:

1. predict s⁻ = Φ s, Σ⁻ = Φ Σ Φᵀ + Q;
2. search each track's template inside its gate ellipse
   (p - p⁻)ᵀ (Σ⁻_pos)⁻¹ (p - p⁻) ≤ c² (:func:`~kalmansfm.tracking.matching.match_templates`);
3. accept the refined best match as the measurement z when its dissimilarity is
   below ``max_dissimilarity`` and its innovation is plausible for this track (see
   below); otherwise the row of z is NaN and the track coasts;
4. update; a track that coasted ``max_misses`` frames in a row and misses again
   is lost.

A new track (from ``points`` or from the detector) starts as in the report: its
template is located in the next frame by an SSD search around its first position
(a gate of Σ0's position block around it), and the filter starts there with
s0 = [x₁, y₁, x₁ - x₀, y₁ - y₀] and Σ0.

Template policy ("anchored", the default): every track keeps its *anchor*, the
patch cut at its first position, and a *current* template.  Each frame the current
template is searched in the gate; the anchor is then searched in a small box around
that match.  If the anchor still matches well there, its position is the
measurement and the current template is re-cut at it, so the position does not
drift.  If the anchor no longer matches (the view has changed), the current
template's match is used (and the current template re-cut there), and once that has
lasted ``anchor_patience`` frames the anchor is replaced by the current template.
Drift can then only accumulate at these rare anchor renewals, not at every frame.
The anchor is trusted only when it matches very well (``anchor_dissimilarity``),
because the peak of a template that matches poorly is biased.  ``template_policy="first"`` uses the anchor only,
``"last"`` re-cuts the template at every match (drifts).

Identity safety.  A template re-cut at every match can slide onto whatever passes
over its point (an occluding card, a look-alike marker crossing it), and the
model's gate (Q = 16 px²) is far wider than the few tenths of a pixel a smoothly
moving point departs from its prediction.  Four rules keep a track on its own
point or end it:

- *innovation plausibility*: every match must satisfy
  ‖z - p⁻‖² ≤ κ² (k + 1) (m + floor²), with m the track's exponentially weighted
  mean squared innovation, k the frames it has coasted and κ = ``max_innovation_ratio``;
- *re-acquisition by the anchor only*: a coasting track is searched with its anchor,
  and only a match at the trusted level ``anchor_dissimilarity`` can start a
  re-acquisition;
- *re-acquisition confirmed over two frames*: that first match is only a candidate
  (the track stays predicted); the track is measured again when the next frame's
  match lies where the candidate moved with the track's velocity, within
  κ √(m + floor²).  A look-alike that crosses the hidden point's gate moves
  differently and is never taken.  A candidate found on the frame after the last
  allowed miss gets this one extra frame before the track is lost;
- *clean anchor renewal*: the anchor is replaced only on a frame where the current
  template's own match is as clean as a trusted anchor's, so a partly hidden
  patch never becomes an anchor.

A track predicted where its window does not fit in the image is not measured.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from .._validation import as_float_array
from ..errors import InvalidInputError, NotEnoughDataError
from ..estimation.kalman import KalmanFilter
from ..estimation.models import initial_state
from .detect import detect_corners
from .grey import colour_to_grey
from .differential import AnchorTemplates, DifferentialFrame, measure_differential, prepare_differential_frame
from .matching import PreparedFrame, TemplateSpectra, match_templates, prepare_frame, refine_translation, sample_patches
from .settings import TrackerSettings
from .smoothing import smooth_tracks
from .tracks import INITIALISING, LOST, MEASURED, PREDICTED, Tracks

__all__ = ["FrameEstimate", "Tracker", "track"]

# Innovation plausibility of every match: ‖z - p⁻‖² ≤ κ² (m + floor²), with m the track's
# exponentially weighted mean squared innovation (weight of the newest frame below).
_INNOVATION_FLOOR_PX = 1.5
_INNOVATION_WEIGHT = 0.3
# A new track's velocity comes from one frame difference: its first innovations may be a few pixels.
_INITIAL_INNOVATION_SQ = 2.0
# The second frame of a new track is found by an SSD search at this level (the report's start-up).
_START_DISSIMILARITY = 0.5


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


@dataclass(frozen=True)
class _FrameRecord:
    ids: np.ndarray
    states: np.ndarray
    covariances: np.ndarray
    status: np.ndarray
    scores: np.ndarray


@dataclass(frozen=True)
class _Rows:
    """Per-track state beside the Kalman filter, one row per live track in the filter's order.

    ``templates`` is the search's current template, or the differential matcher's patch
    at the last measurement (the chain's reference); ``anchors`` the anchor templates
    (:class:`TemplateSpectra` for the search, :class:`AnchorTemplates` for the
    differential matcher).  The differential matcher also keeps ``chain`` (where the
    flow continues from: the last measured position), ``chain_cov`` (that measurement's
    noise), ``anchor_cov`` (the noise of where the anchor was cut; 0 at a first appearance)
    and ``retired`` (lost tracks still in the filter until the next compaction).
    """

    ids: np.ndarray
    misses: np.ndarray
    innovation_sq: np.ndarray
    candidates: np.ndarray
    strikes: np.ndarray
    templates: np.ndarray
    anchors: TemplateSpectra | AnchorTemplates
    chain: np.ndarray | None = None
    chain_cov: np.ndarray | None = None
    anchor_cov: np.ndarray | None = None
    retired: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.ids)

    def take(self, index: np.ndarray) -> _Rows:
        """The rows at ``index`` (indices or a boolean mask)."""
        return _Rows(*(None if (v := getattr(self, f.name)) is None else (v.take(index) if f.name == "anchors" else v[index])
                       for f in fields(_Rows)))

    def append(self, other: _Rows) -> _Rows:
        """These rows followed by ``other``'s."""
        values = []
        for f in fields(_Rows):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if mine is None:
                values.append(None)
            elif f.name == "anchors":
                values.append(mine.append(theirs.templates))
            else:
                values.append(np.concatenate([mine, theirs]))
        return _Rows(*values)


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
        self._records: list[_FrameRecord] = []
        self._differential = s.matcher == "differential"
        # Tracks in the filter, and their rows of per-track state.
        self._kf: KalmanFilter | None = None
        self._rows = self._empty_rows()
        # The previous frame (the differential matcher's flow starts there), and the factor
        # that brings the frames' grey levels to 0…255 for the flow.
        self._previous: DifferentialFrame | None = None
        self._grey_scale: float | None = None
        # Tracks started in the previous frame and waiting for their second frame.
        self._pending_ids = np.zeros(0, np.int64)
        self._pending_positions = np.zeros((0, 2))
        self._pending_templates = np.zeros((0, self.window, self.window), np.float32 if self._differential else np.float64)

    def _empty_rows(self, n: int = 0) -> _Rows:
        w = self.window
        common = (np.zeros(n, np.int64), np.zeros(n, np.int64), np.full(n, _INITIAL_INNOVATION_SQ), np.full((n, 2), np.nan), np.zeros(n, np.int64))
        if not self._differential:
            return _Rows(*common, np.zeros((n, w, w)), TemplateSpectra(np.zeros((n, w, w))))
        return _Rows(*common, np.zeros((n, w, w), np.float32), AnchorTemplates(np.zeros((n, w, w), np.float32)),
                     np.zeros((n, 2)), np.zeros((n, 2, 2)), np.zeros((n, 2, 2)), np.zeros(n, bool))

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
        frame = self._prepare(image)
        self._start_pending(frame, points, ids)
        self._records.append(self._pending_record())
        self._previous = frame if self._differential else None

    def _prepare(self, image: np.ndarray) -> PreparedFrame | DifferentialFrame:
        if self._differential:
            if self._grey_scale is None:
                # The flow reads 8-bit images: frames in another range (16-bit, 0…1 floats) are
                # scaled once, by the first frame's brightest pixel, the same for the whole sequence.
                brightest = float(image.max()) if image.size else 0.0
                self._grey_scale = 255.0 / brightest if brightest > 255.0 or 0.0 < brightest <= 1.0 else 1.0
            return prepare_differential_frame(image, self.window, self.settings.max_search_radius, self._grey_scale)
        return prepare_frame(image, self.window, self.settings.max_search_radius)

    def _start_pending(self, frame: PreparedFrame | DifferentialFrame, points: np.ndarray, ids: np.ndarray) -> None:
        if self._differential:
            templates = frame.patches(points)  # type: ignore[union-attr]
        else:
            templates = sample_patches(frame.image, points, self.window)
        self._pending_ids = np.concatenate([self._pending_ids, ids])
        self._pending_positions = np.concatenate([self._pending_positions, points])
        self._pending_templates = np.concatenate([self._pending_templates, templates])

    def _pending_record(self) -> _FrameRecord:
        n = len(self._pending_ids)
        states = np.concatenate([self._pending_positions, np.zeros((n, 2))], axis=1)
        return _FrameRecord(
            ids=self._pending_ids.copy(),
            states=states,
            covariances=np.broadcast_to(self.model.P0, (n, 4, 4)).copy(),
            status=np.full(n, INITIALISING, np.int8),
            scores=np.zeros(n),
        )

    def _next_frame(self, image: np.ndarray) -> None:
        frame = self._prepare(image)
        records: list[_FrameRecord] = []
        if self._kf is not None and len(self._rows):
            records.append(self._step_differential(frame) if self._differential else self._step_filter(frame))  # type: ignore[arg-type]
        if len(self._pending_ids):
            records.append(self._start_differential(frame) if self._differential else self._start_filter(frame))  # type: ignore[arg-type]
        record = _concatenate_records(records)
        if self.settings.redetect and self._frame_index % self.settings.redetect_every == 0:
            new = self._detect_new(frame.image)
            if len(new):
                ids = np.arange(self._next_id, self._next_id + len(new), dtype=np.int64)
                self._next_id += len(new)
                self._start_pending(frame, new, ids)
                record = _concatenate_records([record, self._pending_record()])
        self._records.append(record)
        if self._differential:
            self._previous = frame  # type: ignore[assignment]

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

    def _start_filter(self, frame: PreparedFrame) -> _FrameRecord:
        """Second frame of new tracks: SSD search around the first position, s0 and Σ0."""
        ids, first, templates = self._take_pending()
        n = len(ids)
        P0_pos = np.broadcast_to(self.model.P0[:2, :2], (n, 2, 2))
        match = match_templates(frame, templates, first, P0_pos, self.gate_radius, "ssd", self.settings.max_search_radius)
        found = match.searched & (match.dissimilarity <= _START_DISSIMILARITY)
        second = np.where(found[:, None], match.positions, first)
        current = np.where(found[:, None, None], sample_patches(frame, second, self.window), templates)
        rows = replace(self._empty_rows(n), ids=ids, misses=(~found).astype(np.int64), templates=current, anchors=TemplateSpectra(templates))
        return self._add_to_filter(rows, first, second, found, match.dissimilarity)

    def _start_differential(self, frame: DifferentialFrame) -> _FrameRecord:
        """Second frame of new tracks: the flow from the first position (gate of Σ0), s0 and Σ0."""
        ids, first, templates = self._take_pending()
        n = len(ids)
        anchors = AnchorTemplates(templates)
        m = self._measure(frame, first, templates, first, np.broadcast_to(self.model.P0[:2, :2], (n, 2, 2)), anchors)
        found = m.accepted
        second = np.where(found[:, None], m.positions, first)
        rows = replace(
            self._empty_rows(n), ids=ids, misses=(~found).astype(np.int64), anchors=anchors,
            templates=np.where(found[:, None, None], m.patches, templates), chain=second,
            chain_cov=np.where(found[:, None, None], m.carried_covariances, 0.0),
        )
        return self._add_to_filter(rows, first, second, found, 1.0 - m.anchor_ncc)

    def _measure(self, frame: DifferentialFrame, previous_positions: np.ndarray, previous_patches: np.ndarray,
                 predicted: np.ndarray, covariances: np.ndarray, anchors: AnchorTemplates, **extra: Any) -> Any:
        s = self.settings
        assert self._previous is not None  # internal invariant: the first frame was prepared
        return measure_differential(
            self._previous, frame, previous_positions, previous_patches, predicted, covariances, anchors,
            gate_radius=self.gate_radius, window=self.window, max_level=s.max_pyramid_level,
            forward_backward_px=s.forward_backward_px, min_ncc=s.min_ncc, anchor_ncc=s.anchor_ncc,
            reacquire_ncc=s.reacquire_ncc, fallback_noise=self.model.R, **extra,
        )

    def _add_to_filter(self, rows: _Rows, first: np.ndarray, second: np.ndarray, found: np.ndarray, scores: np.ndarray) -> _FrameRecord:
        """Start the filter of new tracks at their second frame: s0 = [x₁, y₁, x₁ - x₀, y₁ - y₀], Σ0."""
        n = len(rows)
        states = initial_state(first, second)
        covariances = np.broadcast_to(self.model.P0, (n, 4, 4)).copy()
        # Found: still initialising (a measurement, with the start-up prior Σ0 as covariance).
        record = _FrameRecord(rows.ids.copy(), states, covariances, np.where(found, INITIALISING, PREDICTED).astype(np.int8), scores)
        if self._kf is not None and len(self._rows):
            # The filter is built again: retired rows leave it now.
            live = self._live()
            states = np.concatenate([self._kf.x[live], states])
            covariances = np.concatenate([np.broadcast_to(self._kf.P, (len(self._rows), 4, 4))[live], covariances])
            rows = self._rows.take(live).append(rows)
        self._set_filter(rows, states, covariances)
        return record

    def _set_filter(self, rows: _Rows, states: np.ndarray, covariances: np.ndarray) -> None:
        m = self.model
        if len(rows):
            shared = bool(np.all(covariances == covariances[:1]))
            P = covariances[0] if shared else covariances
            self._kf = KalmanFilter(states, P, m.F, m.H, m.Q, m.R)
        else:
            self._kf = None
        self._rows = rows

    def _plausible_radius_sq(self, coasted: np.ndarray) -> np.ndarray:
        """κ² (k + 1)(m + floor²) per track: the squared distance from the prediction a match may lie after coasting k frames."""
        scale_sq = self.settings.max_innovation_ratio**2 * (1.0 + coasted)
        return scale_sq * (self._rows.innovation_sq + _INNOVATION_FLOOR_PX**2)

    def _confirmation_radius(self) -> np.ndarray:
        """κ √(m + floor²) per track: how far a confirming match may lie from where its candidate moved."""
        return self.settings.max_innovation_ratio * np.sqrt(self._rows.innovation_sq + _INNOVATION_FLOOR_PX**2)

    def _step_filter(self, frame: PreparedFrame) -> _FrameRecord:
        kf = self._kf
        assert kf is not None  # internal invariant, not user input
        rows = self._rows
        kf.predict()
        predicted = kf.x_prior[:, :2].copy()
        prior_P = np.array(kf.P_prior)
        coasting = rows.misses > 0
        anchored = self.settings.template_policy == "anchored"
        search_templates = rows.templates
        if anchored and coasting.any():
            # The current template may have caught part of whatever hid the point: a
            # coasting track is searched with its anchor, the last verified appearance.
            search_templates = np.where(coasting[:, None, None], rows.anchors.templates, rows.templates)
        search_centres, search_covariances = predicted, prior_P[:, :2, :2]
        has_candidate = np.isfinite(rows.candidates[:, 0])
        if has_candidate.any():
            # A re-acquisition candidate is looked for where it should have moved, within
            # the confirmation radius, not in the coast's grown gate (where a look-alike
            # may match better than the point itself).
            radius = self._confirmation_radius()
            search_centres = np.where(has_candidate[:, None], rows.candidates + kf.x_prior[:, 2:], predicted)
            search_covariances = np.where(
                has_candidate[:, None, None], np.eye(2) * (radius / self.gate_radius)[:, None, None] ** 2, search_covariances
            )
        match = match_templates(
            frame, search_templates, search_centres, search_covariances, self.gate_radius, self.settings.score, self.settings.max_search_radius
        )
        z = match.positions.copy()
        dissimilarity = match.dissimilarity
        found = match.searched & (dissimilarity <= self.settings.match_threshold)
        used = search_templates
        # A coasting track starts a re-acquisition only with a match at the strict level
        # (its anchor matching as well as a trusted anchor does, not merely acceptably), so
        # that it does not latch on to a look-alike in its grown gate; the next frame, whose
        # match must also lie where that candidate moved, needs only the acceptable level.
        strict_level = self.settings.anchor_threshold if anchored else self.settings.reacquire_threshold
        strict = found & (dissimilarity <= strict_level)
        if anchored:
            confirmed = coasting & (strict | (found & has_candidate))
            tracking = found & ~coasting
            if tracking.any():
                z, dissimilarity, agrees = self._anchor_check(frame, z, tracking, dissimilarity)
                confirmed |= agrees
            used = np.where(confirmed[:, None, None], rows.anchors.templates, rows.templates)
            accepted = confirmed | tracking
        else:
            accepted = np.where(coasting, strict | (found & has_candidate), found)
        # The match must also move as the track has been moving.  Its innovation ‖z - p⁻‖²
        # must stay within κ² (m + floor²), m the track's recent mean squared innovation,
        # κ = max_innovation_ratio.  The model's own gate (Q = 16 px²) is far wider than
        # the few tenths of a pixel a smoothly moving point deviates from its
        # prediction, so a look-alike that a template slides onto (a card passing over
        # a hidden marker, carrying texture or a marker of its own) is accepted by the
        # gate but jumps against a streak of small innovations.  While coasting, the
        # prediction error grows about linearly with the frames missed.
        innovation_sq = np.sum((z - predicted) ** 2, axis=1)
        plausible = innovation_sq <= self._plausible_radius_sq(rows.misses)
        # A track predicted where its window does not fit in the image (leaving it) is not
        # measured: its gate is clipped to the image, and the best match of a clipped
        # gate is wherever the image ends, not the point.
        half_w = self.window // 2
        height, width = frame.shape
        centre = np.round(predicted)
        plausible &= (
            (centre[:, 0] >= half_w) & (centre[:, 0] <= width - 1 - half_w) & (centre[:, 1] >= half_w) & (centre[:, 1] <= height - 1 - half_w)
        )
        good = accepted & plausible
        if self.settings.refine and good.any():
            z[good] = refine_translation(frame, used[good], z[good])
        good, new_candidate, candidates = self._confirm_reacquisitions(z, good, coasting, strict)
        strikes = rows.strikes
        anchors = rows.anchors
        if anchored:
            strikes, anchors = self._update_anchor_strikes(frame, z, good, good & confirmed, dissimilarity)
        z[~good] = np.nan
        kf.update(z)
        templates = rows.templates
        if self.settings.template_policy != "first" and good.any():
            templates = templates.copy()
            templates[good] = sample_patches(frame, z[good], self.window)
        rows = replace(rows, candidates=candidates, strikes=strikes, anchors=anchors, templates=templates)
        return self._finish_step(rows, good, new_candidate, innovation_sq, dissimilarity)

    def _finish_step(
        self, rows: _Rows, good: np.ndarray, new_candidate: np.ndarray, innovation_sq: np.ndarray, scores: np.ndarray
    ) -> _FrameRecord:
        """After the update: innovation statistics, misses and losses, the frame's record; lost tracks leave the filter."""
        kf = self._kf
        assert kf is not None  # internal invariant, not user input
        # Exponentially weighted mean of the squared one-frame innovation of accepted matches
        # (after coasting k frames, the innovation's square over k + 1).
        mean_sq = np.where(
            good, (1.0 - _INNOVATION_WEIGHT) * rows.innovation_sq + _INNOVATION_WEIGHT * innovation_sq / (1.0 + rows.misses), rows.innovation_sq
        )
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
        states[lost[shown]] = np.nan
        covariances[lost[shown]] = np.nan
        record = _FrameRecord(rows.ids[shown].copy(), states, covariances, status[shown], np.asarray(scores)[shown])
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

    def _step_differential(self, frame: DifferentialFrame) -> _FrameRecord:
        """Predict, measure by flow from the prediction (or re-acquire by the anchor), update; see the module docs."""
        kf = self._kf
        assert kf is not None  # internal invariant, not user input
        rows = self._rows
        kf.predict()
        predicted = kf.x_prior[:, :2].copy()
        coasting = rows.misses > 0
        # A re-acquisition candidate is looked for where it should have moved, within the
        # confirmation radius; every other track within its plausible radius.
        has_candidate = np.isfinite(rows.candidates[:, 0])
        centres = np.where(has_candidate[:, None], rows.candidates + kf.x_prior[:, 2:], predicted)
        centres[rows.retired] = np.nan  # retired rows are not measured
        limit = np.where(has_candidate, self._confirmation_radius(), np.sqrt(self._plausible_radius_sq(rows.misses)))
        m = self._measure(
            frame, rows.chain, rows.templates, centres, np.array(kf.P_prior[:, :2, :2]), rows.anchors,
            coasting=coasting, previous_covariances=rows.chain_cov, anchor_covariances=rows.anchor_cov, max_innovation_px=limit,
        )
        good, new_candidate, candidates = self._confirm_reacquisitions(m.positions, m.accepted, coasting, m.accepted)
        z = np.where(good[:, None], m.positions, np.nan)
        # R from the refinement itself; the model's R where nothing was measured (unused).
        noise = np.where(good[:, None, None], m.noise_covariances, self.model.R)
        kf.update(z, R=0.5 * (noise + np.swapaxes(noise, 1, 2)))
        innovation_sq = np.sum((m.positions - predicted) ** 2, axis=1)
        # A keyframe: the anchor is renewed at the measurement after anchor_patience accepted
        # frames in a row that it did not measure (its appearance has changed for good), and at
        # once when it matches below the re-acquisition level (it could no longer find the point
        # again) — on the first such frame whose measurement is clean, so that a keyframe is never
        # cut at a doubtful match (the passing edge of an occluder, a chain that just slipped).
        strikes = np.where(good & ~m.anchored, rows.strikes + 1, np.where(good, 0, rows.strikes))
        due = (strikes >= self.settings.anchor_patience) | ~(m.anchor_ncc >= self.settings.reacquire_ncc)
        renew = np.flatnonzero(good & m.keyframe_ok & due)
        anchors, anchor_cov = rows.anchors, rows.anchor_cov
        if len(renew):
            anchors = anchors.replace(renew, m.patches[renew])  # type: ignore[union-attr]
            anchor_cov = anchor_cov.copy()  # type: ignore[union-attr]
            anchor_cov[renew] = m.carried_covariances[renew]
            strikes[renew] = 0
        rows = replace(
            rows, candidates=candidates, strikes=strikes, anchors=anchors, anchor_cov=anchor_cov,
            templates=np.where(good[:, None, None], m.patches, rows.templates),
            chain=np.where(good[:, None], m.positions, rows.chain),
            chain_cov=np.where(good[:, None, None], m.carried_covariances, rows.chain_cov),
        )
        return self._finish_step(rows, good, new_candidate, innovation_sq, 1.0 - m.anchor_ncc)

    def _confirm_reacquisitions(
        self, z: np.ndarray, good: np.ndarray, coasting: np.ndarray, strict: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Hold a coasting track's first trusted match back until the next frame confirms it.

        A match that ends a coast becomes a *candidate*; the track stays predicted in this
        frame.  In the next frame, a match that lies where the candidate moved with the
        track's velocity, ‖z - (candidate + v)‖² ≤ κ² (m + floor²), confirms it and the
        track is measured again.  Anything else (no match, or a match elsewhere) drops the
        candidate; a new match at the ``strict`` level becomes the next candidate.  A
        look-alike that passes through the gate once (another marker crossing the hidden
        one) thus never becomes a measurement: it would have to move as the hidden point
        moves.

        Returns the accepted matches, where a new candidate was set, and the candidates.
        """
        kf = self._kf
        assert kf is not None  # internal invariant, not user input
        reacquired = good & coasting
        expected = self._rows.candidates + kf.x_prior[:, 2:]
        offset = np.linalg.norm(z - expected, axis=1)
        # False where there was no candidate (NaN)
        confirmed = reacquired & (offset <= self._confirmation_radius())
        new_candidate = reacquired & ~confirmed & strict
        candidates = np.where(new_candidate[:, None], z, np.nan)
        return (good & ~coasting) | confirmed, new_candidate, candidates

    def _anchor_check(
        self, frame: PreparedFrame, z: np.ndarray, tracking: np.ndarray, dissimilarity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Re-locate the anchor template near the current template's match; see the module docs.

        Returns the measurements (the anchor's position where it is trusted), their
        dissimilarities, and where the anchor is trusted.
        """
        # A tiny isotropic gate of about 2 px around the current match; the other tracks
        # get no prediction and are not searched (the anchor bank is indexed by track).
        around = np.where(tracking[:, None], z, np.nan)
        tight = np.broadcast_to(np.eye(2) * (2.0 / self.gate_radius) ** 2, (len(z), 2, 2))
        anchor = match_templates(frame, self._rows.anchors, around, tight, self.gate_radius, self.settings.score, 4)  # type: ignore[arg-type]
        agrees = tracking & anchor.searched & (anchor.dissimilarity <= self.settings.anchor_threshold)
        z = np.where(agrees[:, None], anchor.positions, z)
        dissimilarity = np.where(agrees, anchor.dissimilarity, dissimilarity)
        return z, dissimilarity, agrees

    def _update_anchor_strikes(
        self, frame: PreparedFrame, z: np.ndarray, good: np.ndarray, confirmed: np.ndarray, dissimilarity: np.ndarray
    ) -> tuple[np.ndarray, TemplateSpectra]:
        """Count frames in a row whose accepted match the anchor did not confirm; renew the anchor after ``anchor_patience``.

        The view has then changed for good, and the current template's match becomes
        the new anchor — but only on a frame where that match is itself as clean as a
        trusted anchor's, so that a partly occluded patch never becomes an anchor.

        Returns the strikes and the anchors.
        """
        strikes = self._rows.strikes.copy()
        strikes[confirmed] = 0
        unconfirmed = good & ~confirmed
        strikes[unconfirmed] += 1
        anchors = self._rows.anchors
        renew = np.flatnonzero(unconfirmed & (strikes >= self.settings.anchor_patience) & (dissimilarity <= self.settings.anchor_threshold))
        if len(renew):
            anchors = anchors.replace(renew, sample_patches(frame, z[renew], self.window))
            strikes[renew] = 0
        return strikes, anchors  # type: ignore[return-value]

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


def _concatenate_records(records: list[_FrameRecord]) -> _FrameRecord:
    if not records:
        return _FrameRecord(np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros((0, 4, 4)), np.zeros(0, np.int8), np.zeros(0))
    if len(records) == 1:
        return records[0]
    return _FrameRecord(*(np.concatenate([getattr(r, f) for r in records]) for f in ("ids", "states", "covariances", "status", "scores")))


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
