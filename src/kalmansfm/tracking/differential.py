"""Differential measurement: Lucas–Kanade started from the Kalman prediction, checked, with its own noise.

One call of :func:`measure_differential` measures every track in the current
frame at once (``docs/tracking.md`` has the measurements behind each choice):

1. **Flow from the prediction.**  OpenCV's pyramidal Lucas–Kanade
   (``calcOpticalFlowPyrLK`` with ``OPTFLOW_USE_INITIAL_FLOW``) follows each
   track from its previous position, starting at the predicted position p⁻.
   The pyramid depth is per track: the gate reaches c·√λmax(Σ⁻) from p⁻ (less
   where the track's plausible radius is smaller), and L levels capture about
   ``capture_px``·2^L pixels (measured), so a confident track runs on fewer
   levels.  Tracks are grouped by depth, one OpenCV call per group.
2. **Anchor.**  Each track carries an *anchor*: a template cut at its first
   appearance (or at a later keyframe chosen by the caller).  It is aligned to
   the frame from the flow's match by robust, centre-weighted Gauss–Newton steps
   with gain and offset (:func:`~kalmansfm.tracking.alignment.align_templates`, a compiled kernel).
3. **Forward–backward check** where the anchor does not settle the match: the
   flow from the current frame back to the previous one, started at the match
   minus the predicted motion, must land within ``forward_backward_px`` of where
   the track was.  A first appearance that matches very well (NCC ≥
   ``anchor_ncc``) where the flow ended is the point itself: no flow back.
4. **Chain.**  Elsewhere the previous frame's patch is aligned from the flow's
   match by the same robust steps.  The anchor's position is the measurement
   where it matches very well or explains the patch nearly as well as the
   previous frame does (``trust_ratio``), so the track does not drift; the
   chain's otherwise.
5. **Appearance.**  The anchor's centre-weighted NCC at the measurement must be
   at least ``min_ncc`` — or ``rescue_ncc`` where the chain is clean (a mild
   appearance change that the previous frame's patch follows).
6. **Gate and plausibility.**  (z - p⁻)ᵀ (Σ⁻)⁻¹ (z - p⁻) ≤ c², ‖z - p⁻‖ at most the
   track's plausible radius, and the point in the image.
7. **Noise from the refinement.**  R = σ² (Σ w ∇T ∇Tᵀ)⁻¹ of the refinement that
   measured, plus what it inherits (the anchor's covariance when it was cut at a
   keyframe; the previous measurement's for a chained match, whose error is the
   previous one's plus the flow's), plus a floor of (0.12 px)² per axis.

Coasting tracks (no measured position in the previous frame) are not followed by
flow, which would follow whatever hid them: their anchor is searched by SSD in the
gate (:func:`~kalmansfm.tracking.matching.match_templates`), then aligned and taken
only at NCC ≥ ``reacquire_ncc``.

The thresholds are a :class:`DifferentialSettings` (the tracker builds one from its
:class:`~kalmansfm.tracking.settings.TrackerSettings`), what the tracker knows of each
track before the frame a :class:`TrackPredictions`; each numbered step above is one
function below.

Coordinates: x = column, y = row, pixel centres at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .._validation import check_count, check_positive
from ..errors import InvalidInputError
from .alignment import Alignment, AnchorTemplates, DifferentialFrame, align_templates, prepare_differential_frame
from .matching import match_templates
from .settings import DEFAULT_GATE_PROBABILITY, TrackerSettings, gate_radius_for_probability

__all__ = [
    "ACCEPTED",
    "REJECTION_NAMES",
    "Alignment",
    "AnchorTemplates",
    "DifferentialFrame",
    "DifferentialMeasurement",
    "DifferentialSettings",
    "TrackPredictions",
    "align_templates",
    "measure_differential",
    "prepare_differential_frame",
    "pyramid_levels",
]

#: rejection code: the measurement was accepted
ACCEPTED = 0
#: the window around the prediction or the match does not fit in the image
OUTSIDE = 1
#: the flow did not converge (OpenCV status 0), or the coasting track's anchor was not found in its gate
NOT_FOUND = 2
#: the match lies outside the gate ellipse
GATE = 3
#: the flow back to the previous frame misses the previous position
FORWARD_BACKWARD = 4
#: the anchor does not match the patch at the measured position (NCC below ``min_ncc``)
APPEARANCE = 5
#: the anchor's structure tensor is too weak to locate it (flat or edge-only patch)
TEXTURELESS = 6
#: the match lies farther from the prediction than the track's own recent innovations allow
IMPLAUSIBLE = 7

REJECTION_NAMES = {
    ACCEPTED: "accepted",
    OUTSIDE: "outside",
    NOT_FOUND: "not found",
    GATE: "gate",
    FORWARD_BACKWARD: "forward-backward",
    APPEARANCE: "appearance",
    TEXTURELESS: "textureless",
    IMPLAUSIBLE: "implausible",
}

#: a pyramid of L levels above the image captures displacements of about this times 2^L px (window 7–21)
CAPTURE_PX = 4.0
_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
# What σ² H⁻¹ does not see (bilinear interpolation, an appearance that changes slowly): a
# floor of (0.12 px)² on each axis of R, calibrated on the built-in scene's seeds 0-9 (NEES
# 2.35, 1σ rate 0.68) and checked on held-out seeds (tests, docs/tracking.md).
_MODEL_NOISE_PX = 0.12


def pyramid_levels(reach_px: np.ndarray, max_level: int, capture_px: float = CAPTURE_PX) -> np.ndarray:
    """Fewest pyramid levels L with ``capture_px``·2^L ≥ reach, clipped to 0…``max_level``.

    Examples
    --------
    >>> pyramid_levels(np.array([1.0, 4.0, 4.1, 10.0, 17.0, 100.0, np.nan]), max_level=3).tolist()
    [0, 0, 1, 2, 3, 3, 3]
    """
    reach = np.asarray(reach_px, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        levels = np.ceil(np.log2(np.maximum(reach, 1e-12) / capture_px))
    levels = np.where(np.isfinite(levels), levels, max_level)
    return np.clip(levels, 0, max_level).astype(np.int64)


@dataclass(frozen=True)
class DifferentialSettings:
    """How :func:`measure_differential` follows and judges a match; validated on construction.

    The fields the tracker's settings also have take their defaults from
    :class:`~kalmansfm.tracking.settings.TrackerSettings` (one definition), and
    :meth:`from_tracker` copies them from the settings a tracker runs with; the others are
    the matcher's own thresholds (``docs/tracking.md`` has the measurements behind them).

    Attributes
    ----------
    gate_radius : c of the gate (z - p⁻)ᵀ (Σ⁻)⁻¹ (z - p⁻) ≤ c².
    window : side of the flow's window (odd).
    max_level : deepest pyramid level the flow may use.
    forward_backward_px : largest distance between the flow back and the previous position.
    min_ncc : the anchor must match the patch at the measured position at least this well
        (appearance check: an occluder, a jump to another point, a vanishing marker).
    anchor_ncc : at or above this NCC the anchor's alignment is the measurement.
    reacquire_ncc : a coasting track is found again only where its anchor matches this well.
    trust_ratio : the anchor's alignment is also the measurement when its residual
        variance is at most this times the chain's (it explains the patch nearly as well
        as the previous frame does).
    anchor_agreement_px : the anchor's alignment must end this close to the flow's match.
    rescue_ncc : a chained match whose anchor matches at least this well (below
        ``min_ncc``) is still accepted when the chain is clean (a mild appearance change).
    clean_ncc, clean_forward_backward_px : a chained match is *clean* where the previous
        frame's patch matches it at this NCC or better and the flow back lands this close.
    min_eigenvalue : smallest structure-tensor eigenvalue per pixel (grey levels²/px²)
        of the template that locates the point.
    capture_px : displacement a single-level flow captures (sets the pyramid depth).
    iterations : Gauss–Newton steps of the anchor's and the chain's alignments.
    fallback_noise : ((xx, xy), (xy, yy)) noise R (px²) for a match whose own cannot be
        estimated (its template's structure tensor is singular, next to the image border);
        None refuses such matches (TEXTURELESS).

    Examples
    --------
    >>> s = DifferentialSettings.from_tracker(TrackerSettings(min_ncc=0.85))
    >>> s.min_ncc, s.trust_ratio, s.fallback_noise
    (0.85, 3.0, ((4.0, 0.0), (0.0, 4.0)))
    >>> DifferentialSettings(iterations=-1)
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: iterations must be a non-negative integer; got -1
    """

    gate_radius: float = gate_radius_for_probability(DEFAULT_GATE_PROBABILITY)
    window: int = TrackerSettings.window
    max_level: int = TrackerSettings.max_pyramid_level
    forward_backward_px: float = TrackerSettings.forward_backward_px
    min_ncc: float = TrackerSettings.min_ncc
    anchor_ncc: float = TrackerSettings.anchor_ncc
    reacquire_ncc: float = TrackerSettings.reacquire_ncc
    trust_ratio: float = 3.0
    anchor_agreement_px: float = 1.5
    rescue_ncc: float = 0.7
    clean_ncc: float = 0.9
    clean_forward_backward_px: float = 0.25
    min_eigenvalue: float = 0.1
    capture_px: float = CAPTURE_PX
    iterations: int = 2
    fallback_noise: tuple[tuple[float, float], tuple[float, float]] | None = None

    def __post_init__(self) -> None:
        for name in ("gate_radius", "forward_backward_px", "min_ncc", "anchor_ncc", "reacquire_ncc", "trust_ratio",
                     "anchor_agreement_px", "rescue_ncc", "clean_ncc", "clean_forward_backward_px", "min_eigenvalue",
                     "capture_px"):
            object.__setattr__(self, name, check_positive(name, getattr(self, name)))
        object.__setattr__(self, "max_level", check_count("max_level", self.max_level, 0))
        object.__setattr__(self, "iterations", check_count("iterations", self.iterations, 0))
        if check_count("window", self.window, 3) % 2 == 0:
            raise InvalidInputError(f"window must be an odd integer >= 3; got {self.window}")
        if self.fallback_noise is not None:
            R = np.asarray(self.fallback_noise, dtype=np.float64)
            if R.shape != (2, 2) or not np.isfinite(R).all() or R[0, 1] != R[1, 0] or not np.all(np.linalg.eigvalsh(R) > 0):
                raise InvalidInputError(f"fallback_noise must be a symmetric positive definite 2×2 covariance; "
                                        f"got {self.fallback_noise!r}")
            object.__setattr__(self, "fallback_noise", tuple(tuple(float(v) for v in row) for row in R))

    @classmethod
    def from_tracker(cls, settings: TrackerSettings, **overrides: object) -> DifferentialSettings:
        """The differential matcher's settings of a tracker: its gate, window, pyramid and NCC
        levels, and its model's R as the fallback noise; ``overrides`` on top."""
        values = dict(gate_radius=settings.effective_gate_radius, window=settings.window,
                      max_level=settings.max_pyramid_level, forward_backward_px=settings.forward_backward_px,
                      min_ncc=settings.min_ncc, anchor_ncc=settings.anchor_ncc, reacquire_ncc=settings.reacquire_ncc,
                      fallback_noise=tuple(map(tuple, settings.model.R.tolist())))
        return cls(**{**values, **overrides})


@dataclass(frozen=True, eq=False)
class TrackPredictions:
    """What the tracker knows of k tracks before it measures them in the current frame (one row each).

    Attributes
    ----------
    previous_positions : (k, 2) positions (x, y) in the previous frame (where the chain continues from).
    previous_patches : (k, w, w) patches of the previous frame at those positions (the last
        measurement's ``patches``); the chain's appearance and noise are judged against them.
    predicted_positions : (k, 2) predicted positions p⁻ in the current frame.
    predicted_covariances : (k, 2, 2) predicted position covariances Σ⁻.
    anchors : the k anchor templates (w×w).
    coasting : (k,) True for tracks not measured in the previous frame: their anchor is
        searched in the gate instead of followed by flow (default: none).
    previous_covariances : (k, 2, 2) noise of the previous measurement (default 0); a
        chained (not anchored) match adds its own to it, as its error is the previous
        one's plus the flow's.
    anchor_covariances : (k, 2, 2) uncertainty of where each anchor was cut (default 0:
        the anchor defines the point).
    max_innovation_px : (k,) largest plausible distance ‖z - p⁻‖ per track (from its
        recent innovations), or None; farther matches are refused, the flow's pyramid
        reaches no farther, and a coasting track's anchor is searched only within it.
    """

    previous_positions: np.ndarray
    previous_patches: np.ndarray
    predicted_positions: np.ndarray
    predicted_covariances: np.ndarray
    anchors: AnchorTemplates
    coasting: np.ndarray | None = None
    previous_covariances: np.ndarray | None = None
    anchor_covariances: np.ndarray | None = None
    max_innovation_px: np.ndarray | None = None

    def __post_init__(self) -> None:
        p_prev = np.asarray(self.previous_positions, dtype=np.float64).reshape(-1, 2)
        predicted = np.asarray(self.predicted_positions, dtype=np.float64).reshape(-1, 2)
        sigma = np.asarray(self.predicted_covariances, dtype=np.float64).reshape(-1, 2, 2)
        k = len(p_prev)
        w = self.anchors.templates.shape[-1]
        patches = np.asarray(self.previous_patches)
        if predicted.shape[0] != k or sigma.shape[0] != k or self.anchors.templates.shape != (k, w, w) or patches.shape != (k, w, w):
            raise InvalidInputError(
                f"measure_differential needs one row per track and {w}×{w} patches; got {k} previous positions, "
                f"{predicted.shape[0]} predictions, {sigma.shape[0]} covariances, anchors {self.anchors.templates.shape}, "
                f"patches {patches.shape}"
            )
        zero = np.zeros((k, 2, 2))
        values = dict(
            previous_positions=p_prev, previous_patches=patches, predicted_positions=predicted, predicted_covariances=sigma,
            coasting=np.zeros(k, bool) if self.coasting is None else np.asarray(self.coasting, bool),
            previous_covariances=zero if self.previous_covariances is None else np.asarray(self.previous_covariances, dtype=np.float64),
            anchor_covariances=zero if self.anchor_covariances is None else np.asarray(self.anchor_covariances, dtype=np.float64),
            max_innovation_px=None if self.max_innovation_px is None else np.asarray(self.max_innovation_px, dtype=np.float64).reshape(k),
        )
        for name, value in values.items():
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.previous_positions)


@dataclass(frozen=True)
class DifferentialMeasurement:
    """What :func:`measure_differential` found for each of k tracks.

    Attributes
    ----------
    positions : (k, 2) measured positions (x, y); NaN where rejected.
    accepted : (k,) True where the measurement passed every check.
    noise_covariances : (k, 2, 2) measurement noise R (px²) for the Kalman update: the
        refinement's σ² H⁻¹, what it inherits, and a floor of (0.12 px)² per axis; NaN where rejected.
    rejection : (k,) int8 reason code, 0 where accepted (see :data:`REJECTION_NAMES`).
    anchored : (k,) True where the position is the anchor's alignment (drift-free).
    anchor_ncc : (k,) NCC of the anchor at the measured position (NaN if not computed).
    forward_backward_px : (k,) distance between the previous position and the flow
        back from the match (NaN for coasting tracks, failed flows, and tracks whose
        anchor matched very well, where it is not run).
    levels : (k,) pyramid levels used for the flow (-1 for coasting tracks, searched instead).
    patches : (k, w, w) the frame's patches at the measured positions (the next frame's
        ``previous_patches``); NaN where rejected.
    carried_covariances : (k, 2, 2) the part of ``noise_covariances`` that a later chained
        measurement (the next frame's ``previous_covariances``) or an anchor cut here
        (``anchor_covariances``) inherits: R without its model floor of (0.12 px)² per axis.
    keyframe_ok : (k,) True where a new anchor may be cut at the measurement: it is
        anchored, or chained cleanly (the previous frame's patch matches at NCC ≥
        ``clean_ncc`` and the flow back lands within ``clean_forward_backward_px``).
    """

    positions: np.ndarray
    accepted: np.ndarray
    noise_covariances: np.ndarray
    rejection: np.ndarray
    anchored: np.ndarray
    anchor_ncc: np.ndarray
    forward_backward_px: np.ndarray
    levels: np.ndarray
    patches: np.ndarray
    carried_covariances: np.ndarray
    keyframe_ok: np.ndarray


def _flow(
    source: np.ndarray, target: np.ndarray, points: np.ndarray, start: np.ndarray, window: int, levels: int
) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV pyramidal LK from ``points`` in ``source`` to ``target``, started at ``start``; (positions, converged)."""
    found, status, _ = cv2.calcOpticalFlowPyrLK(
        source,
        target,
        np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 1, 2),
        np.ascontiguousarray(start, dtype=np.float32).reshape(-1, 1, 2),
        winSize=(window, window),
        maxLevel=int(levels),
        criteria=_LK_CRITERIA,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    return found.reshape(-1, 2).astype(np.float64), status.reshape(-1) == 1


def _forward_backward(
    previous: DifferentialFrame, current: DifferentialFrame, p_prev: np.ndarray, z: np.ndarray, predicted: np.ndarray,
    window: int, max_level: int, capture_px: float, tolerance_px: float,
) -> np.ndarray:
    """Distance between the previous positions and the flow back from the matches (NaN where it fails).

    The flow back starts where the predicted motion says the match came from,
    z - (p⁻ - p), i.e. the innovation z - p⁻ away from p: if the match is right it has
    to travel that far (± the tolerance), which sets its pyramid depth.
    """
    error = np.full(len(z), np.nan)
    start = z - (predicted - p_prev)
    levels = pyramid_levels(np.linalg.norm(z - predicted, axis=1) + tolerance_px, max_level, capture_px)
    for level in np.unique(levels):
        rows = np.flatnonzero(levels == level)
        back, ok = _flow(current.grey, previous.grey, z[rows], start[rows], window, level)
        error[rows] = np.where(ok, np.linalg.norm(back - p_prev[rows], axis=1), np.nan)
    return error


def _inside(positions: np.ndarray, shape: tuple[int, int], margin: float) -> np.ndarray:
    """True where (x, y) lies at least ``margin`` px inside the pixel centres' range (negative: outside allowed)."""
    height, width = shape
    x, y = positions[:, 0], positions[:, 1]
    with np.errstate(invalid="ignore"):
        return (x >= margin) & (x <= width - 1 - margin) & (y >= margin) & (y <= height - 1 - margin)


@dataclass(eq=False)
class _Measuring:
    """The per-track arrays that the steps of :func:`measure_differential` fill in (k rows)."""

    rejection: np.ndarray
    z: np.ndarray
    forward_backward: np.ndarray
    levels: np.ndarray
    anchored: np.ndarray
    keyframe_ok: np.ndarray
    ncc: np.ndarray
    noise: np.ndarray
    patches: np.ndarray

    @classmethod
    def start(cls, k: int, w: int) -> _Measuring:
        return cls(np.full(k, ACCEPTED, np.int8), np.full((k, 2), np.nan), np.full(k, np.nan), np.full(k, -1, np.int64),
                   np.zeros(k, bool), np.zeros(k, bool), np.full(k, np.nan), np.full((k, 2, 2), np.nan),
                   np.full((k, w, w), np.nan, np.float32))


@dataclass(frozen=True)
class _Gate:
    """The gate of every track: Σ⁻ = [[a, b], [b, d]], its largest eigenvalue and how far the search reaches."""

    a: np.ndarray
    b: np.ndarray
    d: np.ndarray
    lambda_max: np.ndarray
    reach: np.ndarray


def _gate(tracks: TrackPredictions, settings: DifferentialSettings) -> _Gate:
    """The gate ellipse reaches c·√λmax(Σ⁻) from the prediction; matches beyond the plausible
    radius are refused anyway, so the search reaches no farther than that either."""
    sigma = tracks.predicted_covariances
    a, b, d = sigma[:, 0, 0], sigma[:, 0, 1], sigma[:, 1, 1]
    lambda_max = 0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b)
    reach = settings.gate_radius * np.sqrt(np.maximum(lambda_max, 0.0))
    if tracks.max_innovation_px is not None:
        reach = np.minimum(reach, tracks.max_innovation_px)
    return _Gate(a, b, d, lambda_max, reach)


def _flow_from_prediction(previous: DifferentialFrame, current: DifferentialFrame, tracks: TrackPredictions,
                          followed: np.ndarray, gate: _Gate, settings: DifferentialSettings, m: _Measuring) -> None:
    """Step 1: the flow from the prediction, one OpenCV call per pyramid depth."""
    levels = pyramid_levels(gate.reach, settings.max_level, settings.capture_px)
    for level in np.unique(levels[followed]):
        rows = np.flatnonzero(followed & (levels == level))
        m.z[rows], ok = _flow(previous.grey, current.grey, tracks.previous_positions[rows],
                              tracks.predicted_positions[rows], settings.window, level)
        m.levels[rows] = level
        m.rejection[rows[~ok]] = NOT_FOUND


def _search_coasting(current: DifferentialFrame, tracks: TrackPredictions, searchable: np.ndarray, gate: _Gate,
                     settings: DifferentialSettings, m: _Measuring) -> None:
    """Coasting tracks: their anchor searched in the gate, shrunk to the plausible radius.  SSD
    needs only the frame's window sums of I²; the alignment afterwards checks the NCC."""
    searched = np.flatnonzero(searchable & tracks.coasting)
    if not len(searched):
        return
    c = settings.gate_radius
    shrink = np.minimum(1.0, (gate.reach[searched] / np.maximum(c * np.sqrt(gate.lambda_max[searched]), 1e-12)) ** 2)
    search_sigma = tracks.predicted_covariances[searched] * shrink[:, None, None]
    match = match_templates(current.prepared, tracks.anchors.templates[searched], tracks.predicted_positions[searched],
                            search_sigma, c, "ssd", current.search_radius)
    m.z[searched] = match.positions
    m.rejection[searched[~match.searched]] = NOT_FOUND


def _anchor_and_chain(previous: DifferentialFrame, current: DifferentialFrame, tracks: TrackPredictions,
                      followed: np.ndarray, settings: DifferentialSettings, m: _Measuring) -> None:
    """Steps 2–5 and 7 for the tracks still standing: the anchor aligned, the flow back where it does
    not settle the match, the chain aligned, which of the two measures, appearance and noise."""
    standing = np.flatnonzero(m.rejection == ACCEPTED)
    if not len(standing):
        return
    k, w = len(tracks), current.window
    s = settings
    flowed = followed[standing]
    bank = tracks.anchors if len(standing) == k else tracks.anchors.take(standing)
    alignment = align_templates(current, bank, m.z[standing], s.iterations, s.anchor_agreement_px)
    m.ncc[standing] = alignment.ncc
    # Near the border the anchor's window reaches into the replicated edge: there the chain measures.
    away_from_border = _inside(alignment.positions, current.shape, w // 2 + 1)
    very_good = alignment.converged & (alignment.ncc >= s.anchor_ncc) & away_from_border
    # The forward–backward check where the anchor does not settle the match on its own (a first
    # appearance that matches very well where the flow ended is the point itself).
    checked = standing[flowed & ~very_good]
    p_prev, predicted = tracks.previous_positions, tracks.predicted_positions
    m.forward_backward[checked] = _forward_backward(previous, current, p_prev[checked], m.z[checked], predicted[checked],
                                                    s.window, s.max_level, s.capture_px, s.forward_backward_px)
    m.rejection[checked[~(m.forward_backward[checked] <= s.forward_backward_px)]] = FORWARD_BACKWARD
    live = m.rejection[standing] == ACCEPTED
    # The chain, where the anchor alone does not settle it: the previous frame's patch against the
    # flow's match (the flow reports neither its residual nor its appearance), aligned from the match
    # by the same robust, centre-weighted step as the anchor: OpenCV's flow weighs every pixel of its
    # window alike, so background moving behind a corner drags it (the scene over 20 seeds: median
    # RMS 0.328 → 0.255 px).
    chain_positions, chain_patches = m.z[standing].copy(), alignment.patches.copy()
    chain_variance = np.full(len(standing), np.nan)
    chain_cov = np.full((len(standing), 2, 2), np.nan)
    chain_eigenvalue = np.full(len(standing), np.nan)
    chain_ncc = np.full(len(standing), np.nan)
    judged = flowed & ~very_good & live
    if judged.any():
        chain = align_templates(current, tracks.previous_patches[standing[judged]], m.z[standing[judged]], s.iterations,
                                s.anchor_agreement_px)
        chain_positions[judged], chain_patches[judged] = chain.positions, chain.patches
        chain_variance[judged], chain_cov[judged] = chain.residual_variance, chain.covariances
        chain_eigenvalue[judged], chain_ncc[judged] = chain.min_eigenvalue, chain.ncc
    # The anchor measures where it matches very well, or explains the patch nearly as well as the
    # previous frame does; a coasting track (no chain) only at reacquire_ncc.
    as_good = alignment.residual_variance <= s.trust_ratio * chain_variance
    trusted = alignment.converged & (alignment.ncc >= s.min_ncc) & np.where(
        flowed, (very_good | as_good) & away_from_border, alignment.ncc >= s.reacquire_ncc
    )
    m.anchored[standing] = trusted
    m.z[standing] = np.where(trusted[:, None], alignment.positions, chain_positions)
    m.patches[standing] = np.where(trusted[:, None, None], alignment.patches, chain_patches)
    # Appearance: the anchor must match (an occluder, a jump to another point), but for a mild change
    # (a car that comes closer, a cyclist's legs) that the chain follows cleanly: the previous
    # frame's patch matches well and the flow back is tight.
    clean_chain = flowed & (chain_ncc >= s.clean_ncc) & (m.forward_backward[standing] <= s.clean_forward_backward_px)
    mild = (alignment.ncc >= s.rescue_ncc) & clean_chain & ~trusted
    m.rejection[standing[live & ~(alignment.ncc >= s.min_ncc) & ~mild]] = APPEARANCE
    # A keyframe may be cut only where the measurement is itself clean: anchored, or chained cleanly.
    m.keyframe_ok[standing] = trusted | clean_chain
    m.rejection[standing[live & ~flowed & ~trusted]] = NOT_FOUND
    eigenvalue = np.where(trusted | ~flowed, alignment.min_eigenvalue, chain_eigenvalue)
    # (Near the border the padded window's gradients say nothing; OpenCV's own eigenvalue test applies there.)
    m.rejection[standing[live & ~(eigenvalue >= s.min_eigenvalue) & away_from_border]] = TEXTURELESS
    # Noise: the refinement's own covariance, plus where the anchor was cut (anchored) or the
    # previous measurement's (chained: its error carries over).
    m.noise[standing] = np.where(
        (trusted | ~flowed)[:, None, None], alignment.covariances + tracks.anchor_covariances[standing],
        chain_cov + tracks.previous_covariances[standing]
    )


def _unknown_noise(settings: DifferentialSettings, m: _Measuring) -> None:
    """A match whose noise could not be estimated takes the fallback noise, or is refused without one."""
    unknown = (m.rejection == ACCEPTED) & ~np.isfinite(m.noise).all(axis=(1, 2))
    if settings.fallback_noise is None:
        m.rejection[unknown] = TEXTURELESS
    else:
        m.noise[unknown] = np.asarray(settings.fallback_noise)


def _gate_and_plausibility(current: DifferentialFrame, tracks: TrackPredictions, gate: _Gate,
                           settings: DifferentialSettings, m: _Measuring) -> None:
    """Step 6: inside the gate, within the plausible radius, and the point in the image."""
    standing = m.rejection == ACCEPTED
    offset = m.z - tracks.predicted_positions
    a, b, d = gate.a, gate.b, gate.d
    with np.errstate(invalid="ignore", divide="ignore"):
        # dᵀ Σ⁻¹ d for 2×2 Σ = [[a, b], [b, d]]: (d dx² - 2 b dx dy + a dy²) / (a d - b²)
        dx, dy = offset[:, 0], offset[:, 1]
        mahalanobis_sq = (d * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * d - b * b)
    m.rejection[standing & ~(mahalanobis_sq <= settings.gate_radius**2)] = GATE
    if tracks.max_innovation_px is not None:
        m.rejection[(m.rejection == ACCEPTED) & ~(np.linalg.norm(offset, axis=1) <= tracks.max_innovation_px)] = IMPLAUSIBLE
    # The point itself must lie in the image (a point whose window leaves the image is still
    # measured while the appearance check passes on the part that remains).
    m.rejection[(m.rejection == ACCEPTED) & ~_inside(m.z, current.shape, 0.0)] = OUTSIDE


def measure_differential(
    previous: DifferentialFrame,
    current: DifferentialFrame,
    tracks: TrackPredictions,
    settings: DifferentialSettings = DifferentialSettings(),
) -> DifferentialMeasurement:
    """Measure k tracks in ``current`` from their Kalman predictions (module docs).

    Parameters
    ----------
    previous, current : consecutive prepared frames (:func:`prepare_differential_frame`).
    tracks : the k tracks' previous positions and patches, predictions, anchors, and what
        they carry (:class:`TrackPredictions`).
    settings : the matcher's thresholds (:class:`DifferentialSettings`).

    Returns
    -------
    DifferentialMeasurement

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> world = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)), (0, 0), 2.0)
    >>> a = prepare_differential_frame(world[20:100, 20:140], 11)
    >>> b = prepare_differential_frame(world[20:100, 22:142], 11)   # the scene moves 2 px left
    >>> p = np.array([[60.0, 40.0]])
    >>> tracks = TrackPredictions(p, a.patches(p), p - [1.5, 0.0], np.eye(2)[None] * 4.0, AnchorTemplates(a.patches(p)))
    >>> m = measure_differential(a, b, tracks)
    >>> np.round(m.positions, 2), m.accepted, m.anchored, m.rejection
    (array([[58., 40.]]), array([ True]), array([ True]), array([0], dtype=int8))
    """
    if previous.shape != current.shape:
        raise InvalidInputError(f"previous and current frames differ in size: {previous.shape} vs {current.shape}")
    if tracks.anchors.templates.shape[1:] != (current.window, current.window):
        raise InvalidInputError(f"measure_differential needs {current.window}×{current.window} anchors (the frame's "
                                f"window); got {tracks.anchors.templates.shape[1:]}")
    m = _Measuring.start(len(tracks), current.window)
    searchable = _inside(tracks.predicted_positions, current.shape, -0.5) & np.isfinite(tracks.predicted_covariances).all(axis=(1, 2))
    m.rejection[~searchable] = OUTSIDE
    gate = _gate(tracks, settings)
    followed = searchable & ~tracks.coasting & _inside(tracks.previous_positions, current.shape, -0.5)
    _flow_from_prediction(previous, current, tracks, followed, gate, settings, m)
    _search_coasting(current, tracks, searchable, gate, settings, m)
    _anchor_and_chain(previous, current, tracks, followed, settings, m)
    _unknown_noise(settings, m)
    _gate_and_plausibility(current, tracks, gate, settings, m)

    accepted = m.rejection == ACCEPTED
    m.z[~accepted] = np.nan
    m.noise[~accepted] = np.nan
    m.patches[~accepted] = np.nan
    return DifferentialMeasurement(
        m.z, accepted, m.noise + np.eye(2) * _MODEL_NOISE_PX**2, m.rejection, m.anchored & accepted, m.ncc,
        m.forward_backward, m.levels, m.patches, m.noise, m.keyframe_ok & accepted,
    )
