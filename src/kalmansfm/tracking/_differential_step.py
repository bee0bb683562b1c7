"""The differential matcher's frame: Lucas–Kanade from the prediction, checked, with its own noise (internal).

:class:`~kalmansfm.tracking.tracker.Tracker` drives it; the measurement itself, every
check and the noise, is :func:`~kalmansfm.tracking.differential.measure_differential`,
with the thresholds of :class:`~kalmansfm.tracking.differential.DifferentialSettings`
built once from the tracker's settings.  Here, per frame: predict; measure every track
from its prediction (a coasting track within its plausible radius, a re-acquisition
candidate where it should have moved); accept under the shared identity rules
(:mod:`._identity`); update with the measurement's own noise R; renew anchors at clean
keyframes (``docs/tracking.md``, steps 1–11).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..estimation.kalman import KalmanFilter
from ._identity import confirm_reacquisitions, confirmation_radius, plausible_radius_sq
from ._rows import Rows, StartOutcome, StepOutcome, common_rows
from .alignment import AnchorTemplates, DifferentialFrame, prepare_differential_frame
from .differential import DifferentialMeasurement, DifferentialSettings, TrackPredictions, measure_differential
from .settings import TrackerSettings


class DifferentialMatcher:
    """The differential matcher of a tracker with these settings (module docs); it keeps the previous
    frame (the flow starts there) and the factor that brings the frames' grey levels to 0…255."""

    template_dtype = np.float32

    def __init__(self, settings: TrackerSettings) -> None:
        self.settings = settings
        self.window = settings.window
        self.parameters = DifferentialSettings.from_tracker(settings)
        self._previous: DifferentialFrame | None = None
        self._grey_scale: float | None = None

    def empty_rows(self, n: int = 0) -> Rows:
        """Rows of ``n`` new tracks: the chain's patch and position, the anchors and the noises they carry."""
        w = self.window
        return Rows(*common_rows(n), np.zeros((n, w, w), np.float32), AnchorTemplates(np.zeros((n, w, w), np.float32)),
                    np.zeros((n, 2)), np.zeros((n, 2, 2)), np.zeros((n, 2, 2)), np.zeros(n, bool))

    def prepare(self, image: np.ndarray) -> DifferentialFrame:
        """The frame made ready for the flow and the alignment (once per frame)."""
        if self._grey_scale is None:
            # The flow reads 8-bit images: frames in another range (16-bit, 0…1 floats) are
            # scaled once, by the first frame's brightest pixel, the same for the whole sequence.
            brightest = float(image.max()) if image.size else 0.0
            self._grey_scale = 255.0 / brightest if brightest > 255.0 or 0.0 < brightest <= 1.0 else 1.0
        return prepare_differential_frame(image, self.window, self.settings.max_search_radius, self._grey_scale)

    def cut_templates(self, frame: DifferentialFrame, points: np.ndarray) -> np.ndarray:
        """The anchors of new tracks at ``points``."""
        return frame.patches(points)

    def remember(self, frame: DifferentialFrame) -> None:
        """``frame`` is the previous one from the next frame on (the flow starts there)."""
        self._previous = frame

    def _measure(self, frame: DifferentialFrame, tracks: TrackPredictions) -> DifferentialMeasurement:
        assert self._previous is not None  # internal invariant: the first frame was prepared
        return measure_differential(self._previous, frame, tracks, self.parameters)

    def start(self, frame: DifferentialFrame, ids: np.ndarray, first: np.ndarray, templates: np.ndarray) -> StartOutcome:
        """Second frame of new tracks: the flow from the first position (gate of Σ0)."""
        n = len(ids)
        anchors = AnchorTemplates(templates)
        m = self._measure(frame, TrackPredictions(first, templates, first, np.broadcast_to(self.settings.model.P0[:2, :2], (n, 2, 2)),
                                                  anchors))
        found = m.accepted
        second = np.where(found[:, None], m.positions, first)
        rows = replace(
            self.empty_rows(n), ids=ids, misses=(~found).astype(np.int64), anchors=anchors,
            templates=np.where(found[:, None, None], m.patches, templates), chain=second,
            chain_cov=np.where(found[:, None, None], m.carried_covariances, 0.0),
        )
        return StartOutcome(rows, second, found, 1.0 - m.anchor_ncc)

    def step(self, frame: DifferentialFrame, kf: KalmanFilter, rows: Rows) -> StepOutcome:
        """Predict, measure by flow from the prediction (or re-acquire by the anchor), update; see the module docs."""
        kf.predict()
        predicted = kf.x_prior[:, :2].copy()
        coasting = rows.misses > 0
        # A re-acquisition candidate is looked for where it should have moved, within the
        # confirmation radius; every other track within its plausible radius.
        has_candidate = np.isfinite(rows.candidates[:, 0])
        centres = np.where(has_candidate[:, None], rows.candidates + kf.x_prior[:, 2:], predicted)
        centres[rows.retired] = np.nan  # retired rows are not measured
        limit = np.where(has_candidate, confirmation_radius(self.settings, rows), np.sqrt(plausible_radius_sq(self.settings, rows, rows.misses)))
        m = self._measure(frame, TrackPredictions(
            rows.chain, rows.templates, centres, np.array(kf.P_prior[:, :2, :2]), rows.anchors,
            coasting=coasting, previous_covariances=rows.chain_cov, anchor_covariances=rows.anchor_cov, max_innovation_px=limit,
        ))
        good, new_candidate, candidates = confirm_reacquisitions(self.settings, rows, kf.x_prior[:, 2:], m.positions,
                                                                 m.accepted, coasting, m.accepted)
        z = np.where(good[:, None], m.positions, np.nan)
        # R from the refinement itself; the model's R where nothing was measured (unused).
        noise = np.where(good[:, None, None], m.noise_covariances, self.settings.model.R)
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
        return StepOutcome(rows, good, new_candidate, innovation_sq, 1.0 - m.anchor_ncc)
