"""A small tracking loop around :func:`kalmansfm.tracking.differential.measure_differential`.

Prototype of the tracker's differential mode, used by the benchmarks to measure the
design before it goes into :class:`~kalmansfm.tracking.tracker.Tracker`: one batched
:class:`~kalmansfm.estimation.KalmanFilter` (the report's constant-velocity model),
tracks fixed at the first frame; a track coasts on rejected frames and is lost after
``max_misses`` in a row.  As in the template tracker, every match must be plausible
(‖z - p⁻‖² ≤ κ² (k + 1) (m + floor²), m the track's mean squared innovation, k the
frames coasted), and a coasting track's first match is only a candidate that the next
frame must confirm where it moved.  Anchors are cut at the first appearance and renewed
(a keyframe) after ``anchor_patience`` accepted frames in a row that the anchor did not measure.
"""

from __future__ import annotations

import numpy as np

from kalmansfm.estimation.kalman import KalmanFilter
from kalmansfm.estimation.models import constant_velocity_2d
from kalmansfm.tracking.differential import AnchorTemplates, measure_differential, prepare_differential_frame
from kalmansfm.tracking.matching import gate_radius_for_probability

_INITIAL_INNOVATION_SQ = 2.0
_INNOVATION_WEIGHT = 0.3


class PrototypeTracker:
    """Differential tracker prototype; ``feed`` frames, then read ``positions``, ``status``, ``covariances``."""

    def __init__(self, points, *, anchor_window=11, max_misses=3, anchor_patience=3, gate_probability=0.95, model=None,
                 kappa=3.0, floor_px=1.5, renew_ncc=None, **options):
        self.renew_ncc = renew_ncc
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        self.anchor_window = anchor_window
        self.max_misses = max_misses
        self.anchor_patience = anchor_patience
        self.gate_radius = gate_radius_for_probability(gate_probability)
        self.model = constant_velocity_2d() if model is None else model
        self.kappa, self.floor_px = kappa, floor_px
        self.options = options
        self.history: dict[str, list[np.ndarray]] = {k: [] for k in ("positions", "status", "covariances", "rejections", "levels", "noise")}
        self.kf = None
        self.frame = None

    def feed(self, image):
        frame = prepare_differential_frame(image, self.anchor_window)
        n = len(self.points)
        if self.frame is None:
            self.patches = frame.patches(self.points)
            self.anchors = AnchorTemplates(self.patches)
            self.anchor_cov = np.zeros((n, 2, 2))
            self.strikes = np.zeros(n, np.int64)
            self.renewals = np.zeros(n, np.int64)
            self.anchored_count = np.zeros(n, np.int64)
            self.misses = np.zeros(n, np.int64)
            self.alive = np.ones(n, bool)
            self.last = self.points.copy()
            self.last_cov = np.zeros((n, 2, 2))
            self.innovation_sq = np.full(n, _INITIAL_INNOVATION_SQ)
            self.candidates = np.full((n, 2), np.nan)
            self._record(self.points, np.ones(n, np.int8), np.zeros((n, 2, 2)), np.zeros(n, np.int8), np.zeros(n, np.int64), np.zeros((n, 2, 2)))
        elif self.kf is None:
            P0 = self.model.P0
            m = measure_differential(
                self.frame, frame, self.points, self.patches, self.points, np.broadcast_to(P0[:2, :2], (n, 2, 2)), self.anchors,
                gate_radius=self.gate_radius, **self.options,
            )
            second = np.where(m.accepted[:, None], m.positions, self.points)
            states = np.concatenate([second, second - self.points], axis=1)
            self.kf = KalmanFilter(states, P0, self.model.F, self.model.H, self.model.Q, self.model.R)
            self.misses = (~m.accepted).astype(np.int64)
            self.last = second
            self.last_cov = np.where(m.accepted[:, None, None], m.noise_covariances, 0.0)
            self.patches = np.where(m.accepted[:, None, None], m.patches, self.patches)
            self._record(second, np.where(m.accepted, 1, 2).astype(np.int8), np.broadcast_to(P0[:2, :2], (n, 2, 2)), m.rejection, m.levels, m.noise_covariances)
        else:
            self._step(frame, n)
        self.frame = frame

    def _step(self, frame, n):
        kf = self.kf
        kf.predict()
        predicted = kf.x_prior[:, :2].copy()
        sigma = np.array(kf.P_prior[:, :2, :2])
        coasting = self.misses > 0
        limit = self.kappa * np.sqrt((1.0 + self.misses) * (self.innovation_sq + self.floor_px**2))
        has_candidate = np.isfinite(self.candidates[:, 0])
        # A candidate is looked for where it should have moved, within the confirmation radius.
        centre = np.where(has_candidate[:, None], self.candidates + kf.x_prior[:, 2:], predicted)
        limit = np.where(has_candidate, self.kappa * np.sqrt(self.innovation_sq + self.floor_px**2), limit)
        m = measure_differential(
            self.frame, frame, self.last, self.patches, centre, sigma, self.anchors,
            coasting=coasting, previous_covariances=self.last_cov, anchor_covariances=self.anchor_cov,
            max_innovation_px=limit, gate_radius=self.gate_radius, fallback_noise=self.model.R, **self.options,
        )
        accepted = m.accepted & self.alive
        # A coasting track's first match is a candidate; the next frame's match where it moved confirms it.
        confirmed = accepted & coasting & has_candidate
        self.candidates = np.where((accepted & coasting & ~has_candidate)[:, None], m.positions, np.nan)
        accepted = (accepted & ~coasting) | confirmed
        innovation = np.sum((m.positions - predicted) ** 2, axis=1)
        self.innovation_sq = np.where(
            accepted, (1 - _INNOVATION_WEIGHT) * self.innovation_sq + _INNOVATION_WEIGHT * innovation / (1.0 + self.misses), self.innovation_sq
        )
        z = np.where(accepted[:, None], m.positions, np.nan)
        R = np.where(accepted[:, None, None], m.noise_covariances, np.broadcast_to(self.model.R, (n, 2, 2)))
        R = 0.5 * (R + np.swapaxes(R, 1, 2)) + np.eye(2) * 1e-6
        kf.update(z, R=R)
        new_candidate = np.isfinite(self.candidates[:, 0])
        self.misses = np.where(accepted, 0, self.misses + 1)
        # A candidate found on the frame after the last allowed miss gets one more frame.
        lost = self.alive & (self.misses > self.max_misses) & ~(new_candidate & (self.misses == self.max_misses + 1))
        self.alive &= ~lost
        x = np.array(kf.x[:, :2])
        P = np.array(kf.P[:, :2, :2])
        status = np.where(accepted, 1, 2).astype(np.int8)
        status[lost] = 3
        status[~self.alive & ~lost] = 0
        self.last = np.where(accepted[:, None], m.positions, x)
        self.last_cov = np.where(accepted[:, None, None], R, self.last_cov)
        self.patches = np.where(accepted[:, None, None], m.patches, self.patches)
        # Anchor renewal: accepted but not anchored for anchor_patience frames in a row.
        failing = ~m.anchored if self.renew_ncc is None else ~(m.anchor_ncc >= self.renew_ncc)
        strikes = np.where(accepted & failing, self.strikes + 1, np.where(accepted & ~failing, 0, self.strikes))
        renew = np.flatnonzero(accepted & (strikes >= self.anchor_patience))
        if len(renew):
            self.anchors = self.anchors.replace(renew, m.patches[renew])
            self.anchor_cov = self.anchor_cov.copy()
            self.anchor_cov[renew] = self.last_cov[renew]
            strikes[renew] = 0
            self.renewals[renew] += 1
        self.strikes = strikes
        self.anchored_count += m.anchored & accepted
        shown = np.where(self.alive[:, None], x, np.nan)
        self._record(shown, status, np.where(self.alive[:, None, None], P, np.nan), m.rejection, m.levels, np.where(accepted[:, None, None], R, np.nan))

    def _record(self, positions, status, cov, rejection, levels, noise):
        for key, value in (("positions", positions), ("status", status), ("covariances", cov), ("rejections", rejection), ("levels", levels), ("noise", noise)):
            self.history[key].append(np.array(value))

    def __getattr__(self, name):
        if name in ("positions", "status", "covariances", "rejections", "levels", "noise"):
            return np.stack(self.__dict__["history"][name])
        raise AttributeError(name)
