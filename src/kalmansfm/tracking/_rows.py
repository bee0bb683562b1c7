"""What the tracker keeps per track beside its Kalman filter, and what a frame adds to the tracks (internal).

:class:`Rows` holds one row per track in the filter's order; the matchers
(:mod:`._search_step`, :mod:`._differential_step`) read them and return new rows in a
:class:`StepOutcome` (a frame of the tracks already in the filter) or a
:class:`StartOutcome` (the second frame of new tracks).  :class:`FrameRecord` is what
one frame contributes to the finished :class:`~kalmansfm.tracking.tracks.Tracks`.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from .alignment import AnchorTemplates
from .matching import TemplateSpectra

# A new track's velocity comes from one frame difference: its first innovations may be a few pixels.
INITIAL_INNOVATION_SQ = 2.0


@dataclass(frozen=True)
class FrameRecord:
    """One frame of the tracks present in it: ids, states (k, 4), covariances (k, 4, 4), status codes, scores."""

    ids: np.ndarray
    states: np.ndarray
    covariances: np.ndarray
    status: np.ndarray
    scores: np.ndarray


def concatenate_records(records: list[FrameRecord]) -> FrameRecord:
    """The records of one frame (tracks in the filter, new tracks, redetected ones) as one."""
    if not records:
        return FrameRecord(np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros((0, 4, 4)), np.zeros(0, np.int8), np.zeros(0))
    if len(records) == 1:
        return records[0]
    return FrameRecord(*(np.concatenate([getattr(r, f) for r in records]) for f in ("ids", "states", "covariances", "status", "scores")))


@dataclass(frozen=True)
class Rows:
    """Per-track state beside the Kalman filter, one row per live track in the filter's order.

    ``misses`` counts the frames a track has coasted, ``innovation_sq`` is its
    exponentially weighted mean squared innovation, ``candidates`` a re-acquisition
    waiting for the next frame's confirmation (NaN: none), ``strikes`` the accepted
    frames in a row its anchor did not measure.  ``templates`` is the search's current
    template, or the differential matcher's patch at the last measurement (the chain's
    reference); ``anchors`` the anchor templates (:class:`TemplateSpectra` for the search,
    :class:`AnchorTemplates` for the differential matcher).  The differential matcher also
    keeps ``chain`` (where the flow continues from: the last measured position),
    ``chain_cov`` (that measurement's noise), ``anchor_cov`` (the noise of where the anchor
    was cut; 0 at a first appearance) and ``retired`` (lost tracks still in the filter
    until the next compaction).
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

    def take(self, index: np.ndarray) -> Rows:
        """The rows at ``index`` (indices or a boolean mask)."""
        return Rows(*(None if (v := getattr(self, f.name)) is None else (v.take(index) if f.name == "anchors" else v[index])
                      for f in fields(Rows)))

    def append(self, other: Rows) -> Rows:
        """These rows followed by ``other``'s."""
        values = []
        for f in fields(Rows):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if mine is None:
                values.append(None)
            elif f.name == "anchors":
                values.append(mine.append(theirs.templates))
            else:
                values.append(np.concatenate([mine, theirs]))
        return Rows(*values)


def common_rows(n: int) -> tuple[np.ndarray, ...]:
    """ids, misses, innovation_sq, candidates and strikes of ``n`` new rows (both matchers)."""
    return (np.zeros(n, np.int64), np.zeros(n, np.int64), np.full(n, INITIAL_INNOVATION_SQ), np.full((n, 2), np.nan),
            np.zeros(n, np.int64))


@dataclass(frozen=True)
class StepOutcome:
    """A matcher's frame for the tracks in the filter, after the update: their new rows, where
    they were measured (``good``), where a re-acquisition candidate was set, the squared
    innovations ‖z - p⁻‖² and the frame's scores."""

    rows: Rows
    good: np.ndarray
    new_candidate: np.ndarray
    innovation_sq: np.ndarray
    scores: np.ndarray


@dataclass(frozen=True)
class StartOutcome:
    """A matcher's second frame of new tracks: their rows, their second positions, where they
    were found, and the scores."""

    rows: Rows
    second: np.ndarray
    found: np.ndarray
    scores: np.ndarray
