"""The search matcher: the report's gated exhaustive template search, one frame for all tracks (internal).

Per frame, with one batched :class:`~kalmansfm.estimation.KalmanFilter` holding every
live track (:class:`~kalmansfm.tracking.tracker.Tracker` drives it):

1. predict s⁻ = Φ s, Σ⁻ = Φ Σ Φᵀ + Q;
2. search each track's template inside its gate ellipse
   (p - p⁻)ᵀ (Σ⁻_pos)⁻¹ (p - p⁻) ≤ c² (:func:`~kalmansfm.tracking.matching.match_templates`);
3. accept the refined best match as the measurement z when its dissimilarity is
   below ``max_dissimilarity`` and its innovation is plausible for this track
   (:mod:`._identity`); otherwise the row of z is NaN and the track coasts;
4. update; a track that coasted ``max_misses`` frames in a row and misses again
   is lost (the tracker decides that).

A new track starts as in the report: its template is located in the next frame by an
SSD search around its first position (a gate of Σ0's position block around it).

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

Beside the shared identity rules (:mod:`._identity`), two of the search's own keep a
track on its own point: *re-acquisition by the anchor only* (a coasting track is
searched with its anchor, and only a match at the trusted level
``anchor_dissimilarity`` can start a re-acquisition) and *clean anchor renewal* (the
anchor is replaced only on a frame where the current template's own match is as clean
as a trusted anchor's, so a partly hidden patch never becomes an anchor).  A track
predicted where its window does not fit in the image is not measured.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..estimation.kalman import KalmanFilter
from ._identity import confirm_reacquisitions, confirmation_radius, plausible_radius_sq
from ._rows import Rows, StartOutcome, StepOutcome, common_rows
from .matching import PreparedFrame, TemplateSpectra, match_templates, prepare_frame, refine_translation, sample_patches
from .settings import TrackerSettings

# The second frame of a new track is found by an SSD search at this level (the report's start-up).
_START_DISSIMILARITY = 0.5


class SearchMatcher:
    """The search matcher of a tracker with these settings (module docs)."""

    template_dtype = np.float64

    def __init__(self, settings: TrackerSettings) -> None:
        self.settings = settings
        self.gate_radius = settings.effective_gate_radius
        self.window = settings.window

    def empty_rows(self, n: int = 0) -> Rows:
        """Rows of ``n`` new tracks: the current template and the anchors' spectra."""
        w = self.window
        return Rows(*common_rows(n), np.zeros((n, w, w)), TemplateSpectra(np.zeros((n, w, w))))

    def prepare(self, image: np.ndarray) -> PreparedFrame:
        """The frame made ready for the gated search (once per frame)."""
        return prepare_frame(image, self.window, self.settings.max_search_radius)

    def cut_templates(self, frame: PreparedFrame, points: np.ndarray) -> np.ndarray:
        """The templates of new tracks at ``points``."""
        return sample_patches(frame.image, points, self.window)

    def remember(self, frame: PreparedFrame) -> None:
        """The search needs nothing of the previous frame."""

    def start(self, frame: PreparedFrame, ids: np.ndarray, first: np.ndarray, templates: np.ndarray) -> StartOutcome:
        """Second frame of new tracks: SSD search around the first position (a gate of Σ0's position block)."""
        n = len(ids)
        P0_pos = np.broadcast_to(self.settings.model.P0[:2, :2], (n, 2, 2))
        match = match_templates(frame, templates, first, P0_pos, self.gate_radius, "ssd", self.settings.max_search_radius)
        found = match.searched & (match.dissimilarity <= _START_DISSIMILARITY)
        second = np.where(found[:, None], match.positions, first)
        current = np.where(found[:, None, None], sample_patches(frame, second, self.window), templates)
        rows = replace(self.empty_rows(n), ids=ids, misses=(~found).astype(np.int64), templates=current, anchors=TemplateSpectra(templates))
        return StartOutcome(rows, second, found, match.dissimilarity)

    def step(self, frame: PreparedFrame, kf: KalmanFilter, rows: Rows) -> StepOutcome:
        """Predict, search, check, update the tracks in the filter; see the module docs."""
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
            radius = confirmation_radius(self.settings, rows)
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
                z, dissimilarity, agrees = self._anchor_check(frame, rows, z, tracking, dissimilarity)
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
        plausible = innovation_sq <= plausible_radius_sq(self.settings, rows, rows.misses)
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
        good, new_candidate, candidates = confirm_reacquisitions(self.settings, rows, kf.x_prior[:, 2:], z, good, coasting,
                                                                 strict)
        strikes = rows.strikes
        anchors = rows.anchors
        if anchored:
            strikes, anchors = self._update_anchor_strikes(frame, rows, z, good, good & confirmed, dissimilarity)
        z[~good] = np.nan
        kf.update(z)
        templates = rows.templates
        if self.settings.template_policy != "first" and good.any():
            templates = templates.copy()
            templates[good] = sample_patches(frame, z[good], self.window)
        rows = replace(rows, candidates=candidates, strikes=strikes, anchors=anchors, templates=templates)
        return StepOutcome(rows, good, new_candidate, innovation_sq, dissimilarity)

    def _anchor_check(
        self, frame: PreparedFrame, rows: Rows, z: np.ndarray, tracking: np.ndarray, dissimilarity: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Re-locate the anchor template near the current template's match; see the module docs.

        Returns the measurements (the anchor's position where it is trusted), their
        dissimilarities, and where the anchor is trusted.
        """
        # A tiny isotropic gate of about 2 px around the current match; the other tracks
        # get no prediction and are not searched (the anchor bank is indexed by track).
        around = np.where(tracking[:, None], z, np.nan)
        tight = np.broadcast_to(np.eye(2) * (2.0 / self.gate_radius) ** 2, (len(z), 2, 2))
        anchor = match_templates(frame, rows.anchors, around, tight, self.gate_radius, self.settings.score, 4)  # type: ignore[arg-type]
        agrees = tracking & anchor.searched & (anchor.dissimilarity <= self.settings.anchor_threshold)
        z = np.where(agrees[:, None], anchor.positions, z)
        dissimilarity = np.where(agrees, anchor.dissimilarity, dissimilarity)
        return z, dissimilarity, agrees

    def _update_anchor_strikes(
        self, frame: PreparedFrame, rows: Rows, z: np.ndarray, good: np.ndarray, confirmed: np.ndarray, dissimilarity: np.ndarray
    ) -> tuple[np.ndarray, TemplateSpectra]:
        """Count frames in a row whose accepted match the anchor did not confirm; renew the anchor after ``anchor_patience``.

        The view has then changed for good, and the current template's match becomes
        the new anchor — but only on a frame where that match is itself as clean as a
        trusted anchor's, so that a partly occluded patch never becomes an anchor.

        Returns the strikes and the anchors.
        """
        strikes = rows.strikes.copy()
        strikes[confirmed] = 0
        unconfirmed = good & ~confirmed
        strikes[unconfirmed] += 1
        anchors = rows.anchors
        renew = np.flatnonzero(unconfirmed & (strikes >= self.settings.anchor_patience) & (dissimilarity <= self.settings.anchor_threshold))
        if len(renew):
            anchors = anchors.replace(renew, sample_patches(frame, z[renew], self.window))
            strikes[renew] = 0
        return strikes, anchors  # type: ignore[return-value]
