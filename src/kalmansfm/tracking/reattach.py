"""Lost tracks found again at keyframes: the filter's prediction gates a descriptor match (issue 26).

A track the tracker loses (occlusion, leaving the image, a blur) keeps, for ``reattach_frames``
frames, its last state and covariance, its last template and the ORB descriptor of its last keyframe.  At each
redetection (a keyframe) the new corners are described as well, and a lost track takes a corner
as its own again when

* the corner lies inside the track's gate: the constant-velocity prediction carried over the
  frames it was lost, x = Fᵏ x_lost, P = Fᵏ P Fᵏᵀ + Σ Fʲ Q Fʲᵀ, and the χ²₂ test of the
  tracker's gate probability on H P Hᵀ + R;
* the corner's patch matches the track's last template (normalised cross-correlation at least
  the tracker's ``reacquire_ncc``, as when a coasting track is found again): the gate of a track
  lost for several frames is wide, and a descriptor alone can take a look-alike;
* among those corners it is the nearest in descriptor space, passing the ratio test against the
  second nearest, and the track is the corner's nearest among the tracks that accept it (mutual).

The corner then starts as a new track would (it waits a frame and starts its filter from Σ0),
under the old id: the identity survives the gap.  This is the seed's predict-then-search, with
a descriptor in place of the template where the track was out of sight.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..estimation.models import LinearGaussianModel

__all__ = ["DESCRIPTOR_SIZE", "LostTracks", "describe", "match_lost"]

#: Length of a descriptor (bits of ORB's test pattern).
DESCRIPTOR_SIZE = 256
# The descriptor's support: this many times the tracker's window (at least ORB's 31 pixels).
_SUPPORT = 3.0
# Ratio test: the best descriptor distance at most this share of the second best.
_RATIO = 0.8
# A descriptor distance above this (√ of 80 of the 256 bits differing) is no match whatever the ratio.
_MAX_DISTANCE = float(np.sqrt(80.0))


def describe(image: np.ndarray, points: np.ndarray, window: int) -> np.ndarray:
    """(n, 256) ORB descriptors of ``image`` at ``points`` (x, y) as 0/1 floats; NaN rows where none could be made.

    ORB (a binary test pattern, steered by the patch's orientation) costs a fraction of a
    millisecond for a frame's tracks, where SIFT's scale space costs tens; the gate and the patch
    check (:func:`match_lost`) carry most of the decision, the descriptor tells look-alikes apart.
    The Euclidean distance of two such rows is the square root of their Hamming distance.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> image = cv2.GaussianBlur((rng.random((120, 120)) * 255).astype(np.uint8), (0, 0), 1.5)
    >>> d = describe(image, np.array([[60.0, 60.0], [1.0, 1.0]]), 11)
    >>> d.shape, bool(np.isfinite(d[0]).all()), bool(np.isnan(d[1]).all())
    ((2, 256), True, True)
    """
    out = np.full((len(points), DESCRIPTOR_SIZE), np.nan, np.float32)
    if not len(points):
        return out
    grey = image if image.dtype == np.uint8 else np.clip(np.rint(image), 0, 255).astype(np.uint8)
    size = max(_SUPPORT * window, 31.0)
    keypoints = [cv2.KeyPoint(float(x), float(y), size, -1, 0, 0, k) for k, (x, y) in enumerate(points)]
    kept, descriptors = cv2.ORB_create(edgeThreshold=int(size), patchSize=int(size)).compute(grey, keypoints)
    if descriptors is None or not kept:
        return out
    index = np.array([k.class_id for k in kept])
    out[index] = np.unpackbits(descriptors, axis=1).astype(np.float32)
    return out


@dataclass
class LostTracks:
    """Tracks lost recently, as they were when lost: id, frame, state, covariance, keyframe descriptor, template."""

    ids: np.ndarray
    frames: np.ndarray
    states: np.ndarray
    covariances: np.ndarray
    descriptors: np.ndarray
    templates: np.ndarray

    @classmethod
    def empty(cls, window: int = 11) -> LostTracks:
        """No lost track (templates of ``window`` pixels)."""
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros((0, 4, 4)),
                   np.zeros((0, DESCRIPTOR_SIZE), np.float32), np.zeros((0, window, window), np.float32))

    def add(self, ids: np.ndarray, frame: int, states: np.ndarray, covariances: np.ndarray,
            descriptors: np.ndarray, templates: np.ndarray) -> None:
        """Keep tracks lost in ``frame`` (those without a descriptor cannot be found again and are not kept)."""
        known = np.isfinite(descriptors).all(axis=1) & np.isfinite(states).all(axis=1)
        self.ids = np.concatenate([self.ids, ids[known]])
        self.frames = np.concatenate([self.frames, np.full(int(known.sum()), frame, np.int64)])
        self.states = np.concatenate([self.states, states[known]])
        self.covariances = np.concatenate([self.covariances, covariances[known]])
        self.descriptors = np.concatenate([self.descriptors, descriptors[known]])
        self.templates = np.concatenate([self.templates, np.asarray(templates, np.float32)[known]])

    def keep(self, mask: np.ndarray) -> None:
        """Keep only the entries of ``mask``."""
        self.ids, self.frames, self.states, self.covariances, self.descriptors, self.templates = (
            a[mask] for a in (self.ids, self.frames, self.states, self.covariances, self.descriptors, self.templates))


def _predicted(lost: LostTracks, frame: int, model: LinearGaussianModel) -> tuple[np.ndarray, np.ndarray]:
    """States and covariances of the lost tracks carried to ``frame`` by the motion model (one step per frame)."""
    x, P = lost.states.copy(), lost.covariances.copy()
    steps = frame - lost.frames
    for k in range(int(steps.max(initial=0))):
        on = steps > k
        x[on] = x[on] @ model.F.T
        P[on] = model.F @ P[on] @ model.F.T + model.Q
    return x, P


def _ncc(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(n, m) normalised cross-correlation of n templates with m patches of the same size."""
    a = first.reshape(len(first), -1).astype(np.float64)
    b = second.reshape(len(second), -1).astype(np.float64)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b /= np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    return a @ b.T


def match_lost(lost: LostTracks, frame: int, points: np.ndarray, descriptors: np.ndarray, patches: np.ndarray,
               model: LinearGaussianModel, gate_radius: float, min_ncc: float) -> tuple[np.ndarray, np.ndarray]:
    """Which new corners are lost tracks found again: (corner indices, lost-track indices), one to one.

    Parameters
    ----------
    lost : the lost tracks.
    frame : the keyframe's index.
    points : (m, 2) the new corners; descriptors : (m, DESCRIPTOR_SIZE) theirs (:func:`describe`); patches :
        (m, w, w) the patch around each (the tracker's templates).
    model : the tracker's motion model (F, Q, H, R).
    gate_radius : the tracker's Mahalanobis gate radius c (χ²₂ quantile of its gate probability).
    min_ncc : the least normalised cross-correlation of a corner's patch with the track's template.

    Examples
    --------
    A track lost at (10, 10) moving 1 px per frame, five frames later: the corner at (15, 10)
    with its descriptor is it, the one at (200, 200) with the same descriptor is outside its gate.

    >>> from kalmansfm.estimation.models import constant_velocity_2d
    >>> d = np.zeros((1, DESCRIPTOR_SIZE), np.float32); d[0, :8] = 1.0
    >>> patch = np.arange(121.0).reshape(1, 11, 11)
    >>> lost = LostTracks.empty()
    >>> lost.add(np.array([7]), 0, np.array([[10.0, 10, 1, 0]]), np.eye(4)[None] * 4.0, d, patch)
    >>> match_lost(lost, 5, np.array([[200.0, 200.0], [15.0, 10.0]]), np.repeat(d, 2, axis=0),
    ...            np.repeat(patch, 2, axis=0), constant_velocity_2d(), 3.0, 0.9)
    (array([1]), array([0]))
    """
    none = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if not len(lost.ids) or not len(points):
        return none
    x, P = _predicted(lost, frame, model)
    S = model.H @ P @ model.H.T + model.R  # (n, 2, 2)
    r = points[None, :, :] - (x @ model.H.T)[:, None, :]  # (n, m, 2)
    d2 = np.einsum("nmi,nij,nmj->nm", r, np.linalg.inv(S), r)
    distance = np.linalg.norm(lost.descriptors[:, None, :] - descriptors[None, :, :], axis=2)
    alike = _ncc(lost.templates, patches) >= min_ncc
    distance = np.where((d2 <= gate_radius**2) & alike & np.isfinite(distance), distance, np.inf)
    if distance.shape[1] < 1 or not np.isfinite(distance).any():
        return none
    order = np.argsort(distance, axis=1)
    best = order[:, 0]
    rows = np.arange(len(best))
    first = distance[rows, best]
    second = distance[rows, order[:, 1]] if distance.shape[1] > 1 else np.full(len(best), np.inf)
    good = np.isfinite(first) & (first <= _MAX_DISTANCE) & (first < _RATIO * second)
    mutual = np.argmin(distance, axis=0)[best] == rows
    chosen = np.flatnonzero(good & mutual)
    return best[chosen].astype(np.int64), chosen.astype(np.int64)
