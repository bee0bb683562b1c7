"""Lost tracks found again under their own id (issue 26): an occluder hides part of a moving texture for ten frames.

The texture moves one pixel to the left per frame, so the truth of every track is its first position minus
the frames since.  Tracks under the occluder are lost; when it lifts, the redetection finds their corners
again, and with ``reattach_frames`` they must come back under their old ids — at their true positions, no
identity swapped — while without it they stay lost.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.tracking import TrackerSettings, track
from kalmansfm.tracking.smoothing import smooth_tracks
from kalmansfm.tracking.tracks import LOST, MEASURED


@pytest.fixture(scope="module")
def occluded():
    rng = np.random.default_rng(3)
    world = cv2.GaussianBlur((rng.random((200, 400)) * 255).astype(np.float32), (0, 0), 2.0)
    world = cv2.normalize(world, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)
    frames = []
    for t in range(36):
        frame = world[20:180, 20 + t: 260 + t].copy()
        if 10 <= t < 20:
            frame[40:120, 60:140] = 0
        frames.append(frame)
    return frames


def _returned(tracks):
    """Columns lost and then measured again, with their largest distance from the truth after the return."""
    out = {}
    for p in range(tracks.n_tracks):
        status = tracks.status[:, p]
        if not (status == LOST).any():
            continue
        lost = int(np.argmax(status == LOST))
        again = np.flatnonzero(status == MEASURED)
        again = again[again > lost]
        if again.size:
            first = int(np.argmax(status != 0))
            truth = tracks.positions[first, p] - np.stack([again - first, np.zeros(again.size)], axis=1)
            out[int(tracks.track_ids[p])] = float(np.abs(tracks.positions[again, p] - truth).max())
    return out


@pytest.mark.parametrize("matcher", ["differential", "search"])
def test_tracks_hidden_by_an_occluder_come_back_under_their_own_ids(occluded, matcher):
    common = {"matcher": matcher, "redetect": True, "redetect_every": 5, "max_features": 120}
    without = track(occluded, settings=TrackerSettings(**common))
    assert _returned(without) == {}
    tracks = track(occluded, settings=TrackerSettings(**common, reattach_frames=20))
    returned = _returned(tracks)
    assert len(returned) >= 8
    assert max(returned.values()) <= 1.0  # every one at its own feature: no identity swapped
    # fewer ids: the returned ones were not counted as new tracks
    assert tracks.n_tracks <= without.n_tracks - len(returned) // 2
    # a track with two filter chains is smoothed chain by chain
    smoothed = smooth_tracks(tracks)
    again = [p for p in range(tracks.n_tracks) if int(tracks.track_ids[p]) in returned]
    assert np.isfinite(smoothed.positions[:, again][tracks.status[:, again] == MEASURED]).all()


def test_reattach_needs_redetect():
    with pytest.raises(InvalidInputError, match=r"reattach_frames \(5\) needs redetect"):
        TrackerSettings(reattach_frames=5)
    with pytest.raises(InvalidInputError, match="reattach_frames must be"):
        TrackerSettings(redetect=True, reattach_frames=-1)
