"""The identity rules both matchers share (internal): a track stays on its own point or ends.

A template re-cut at every match can slide onto whatever passes over its point (an
occluding card, a look-alike marker crossing it), and the model's gate (Q = 16 px²) is far
wider than the few tenths of a pixel a smoothly moving point departs from its prediction.
Two rules here (``docs/tracking.md``, "identity"):

- *innovation plausibility*: every match must satisfy
  ‖z - p⁻‖² ≤ κ² (k + 1) (m + floor²), with m the track's exponentially weighted mean
  squared innovation, k the frames it has coasted and κ = ``max_innovation_ratio``
  (:func:`plausible_radius_sq`);
- *re-acquisition confirmed over two frames*: the first match after a coast is only a
  candidate (the track stays predicted); the track is measured again when the next
  frame's match lies where the candidate moved with the track's velocity, within
  κ √(m + floor²) (:func:`confirm_reacquisitions`).  A look-alike that crosses the hidden
  point's gate moves differently and is never taken.

The matchers add their own (re-acquisition by the anchor only, clean anchor renewal).
"""

from __future__ import annotations

import numpy as np

from ._rows import Rows
from .settings import TrackerSettings

# Innovation plausibility of every match: ‖z - p⁻‖² ≤ κ² (m + floor²), with m the track's
# exponentially weighted mean squared innovation (weight of the newest frame below).
INNOVATION_FLOOR_PX = 1.5
INNOVATION_WEIGHT = 0.3


def plausible_radius_sq(settings: TrackerSettings, rows: Rows, coasted: np.ndarray) -> np.ndarray:
    """κ² (k + 1)(m + floor²) per track: the squared distance from the prediction a match may lie after coasting k frames."""
    scale_sq = settings.max_innovation_ratio**2 * (1.0 + coasted)
    return scale_sq * (rows.innovation_sq + INNOVATION_FLOOR_PX**2)


def confirmation_radius(settings: TrackerSettings, rows: Rows) -> np.ndarray:
    """κ √(m + floor²) per track: how far a confirming match may lie from where its candidate moved."""
    return settings.max_innovation_ratio * np.sqrt(rows.innovation_sq + INNOVATION_FLOOR_PX**2)


def confirm_reacquisitions(
    settings: TrackerSettings, rows: Rows, velocity: np.ndarray, z: np.ndarray, good: np.ndarray, coasting: np.ndarray,
    strict: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hold a coasting track's first trusted match back until the next frame confirms it.

    A match that ends a coast becomes a *candidate*; the track stays predicted in this
    frame.  In the next frame, a match that lies where the candidate moved with the
    track's velocity (``velocity``, the predicted one), ‖z - (candidate + v)‖² ≤ κ² (m + floor²),
    confirms it and the track is measured again.  Anything else (no match, or a match
    elsewhere) drops the candidate; a new match at the ``strict`` level becomes the next
    candidate.  A look-alike that passes through the gate once (another marker crossing
    the hidden one) thus never becomes a measurement: it would have to move as the hidden
    point moves.

    Returns the accepted matches, where a new candidate was set, and the candidates.
    """
    reacquired = good & coasting
    expected = rows.candidates + velocity
    offset = np.linalg.norm(z - expected, axis=1)
    # False where there was no candidate (NaN)
    confirmed = reacquired & (offset <= confirmation_radius(settings, rows))
    new_candidate = reacquired & ~confirmed & strict
    candidates = np.where(new_candidate[:, None], z, np.nan)
    return (good & ~coasting) | confirmed, new_candidate, candidates


def mean_squared_innovation(rows: Rows, good: np.ndarray, innovation_sq: np.ndarray) -> np.ndarray:
    """The exponentially weighted mean of the squared one-frame innovation of accepted matches
    (after coasting k frames, the innovation's square over k + 1)."""
    return np.where(
        good, (1.0 - INNOVATION_WEIGHT) * rows.innovation_sq + INNOVATION_WEIGHT * innovation_sq / (1.0 + rows.misses),
        rows.innovation_sq,
    )
