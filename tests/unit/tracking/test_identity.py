"""A track keeps its identity or ends — it never swaps silently (issue 7), on the built-in scene.

Every case renders the scene with ground truth and checks each (frame, track) pair that the
tracker reports as *measured*:

- while the scene marks the marker visible, it lies within 3 px of that track's own truth;
- while the marker is *completely* covered by the card, or hidden by the solid itself or the
  image border, it is not measured at all — except in the one frame where the card's own
  marker sits exactly on the hidden one (``Occluder(marker=True)``, the crossing): there the
  two are indistinguishable, and the measurement must lie within 0.5 px of the truth;
- while the card only touches part of the marker (the scene then calls it hidden too), the
  marker is still found, within 4 px.

Each case also ends with every track either still on its own point or lost.  Both matchers
keep these guarantees; the exact frame-by-frame statuses written below for the search are
the report's rules (the differential matcher refuses a match as soon as the card enters its
window, and coasts 5 frames instead of 3, so its statuses differ).
"""

import numpy as np
import pytest

from kalmansfm.scenes import Occluder, render_scene
from kalmansfm.tracking.tracker import track
from kalmansfm.tracking.tracks import LOST, MEASURED, NO_TRACK, PREDICTED

MARKER_HALF_PX = 3.0  # the scene's 6 px markers
MATCHERS = ["search", "differential"]


def tracked_scene(seed, occluder=None, scenario="default", **options):
    scene = render_scene(seed=seed, occluder=occluder, scenario=scenario)
    first = scene.visible[0]
    tracks = track(list(scene.frames), scene.positions[0, first], track_ids=scene.track_ids[first], **options)
    column = {int(t): c for c, t in enumerate(scene.track_ids)}
    cols = [column[int(t)] for t in tracks.track_ids]
    return scene, tracks, scene.positions[:, cols], scene.visible[:, cols]


def card_cover(scene, truth):
    """(F, P) 'touched' and 'fully covered' flags of each marker by the occluder card."""
    x0, y0, x1, y1 = (scene.occluder_boxes[:, k, None] for k in range(4))
    cx, cy, h = truth[..., 0], truth[..., 1], MARKER_HALF_PX
    touched = (x0 < cx + h) & (x1 > cx - h) & (y0 < cy + h) & (y1 > cy - h)
    covered = (x0 <= cx - h) & (x1 >= cx + h) & (y0 <= cy - h) & (y1 >= cy + h)
    return touched, covered


def assert_no_silent_swap(scene, tracks, truth, visible):
    error = np.linalg.norm(tracks.positions - truth, axis=2)
    measured = tracks.measured
    touched, covered = card_cover(scene, truth)
    # Visible: on its own point.
    assert (error[measured & visible] <= 3.0).all(), np.round(error[measured & visible].max(), 2)
    # Partly under the card's edge: still its own point.
    partly = measured & ~visible & touched & ~covered
    assert (error[partly] <= 4.0).all()
    # Completely hidden (card, solid or border): never measured, but for the crossing look-alike.
    hidden = measured & ~visible & ~(touched & ~covered)
    if hidden.any():
        assert scene.occluder_marker_positions is not None
        frames, cols = np.nonzero(hidden)
        lookalike = np.linalg.norm(scene.occluder_marker_positions[frames] - truth[frames, cols], axis=1)
        assert (lookalike <= 1.0).all()
        assert (error[hidden] <= 0.5).all()
    # A track that ends does not come back.
    ended = np.cumsum(tracks.status == NO_TRACK, axis=0) > 0
    assert not (ended & (tracks.status != NO_TRACK)).any()


def assert_resumes_or_ends(tracks, truth, col, visible_again):
    """From ``visible_again`` on, the track is measured on its own point again or it has ended; True if it resumed."""
    after = tracks.status[visible_again:, col]
    measured = np.flatnonzero(after == MEASURED)
    if len(measured) == 0:
        assert (after[np.argmax(after != PREDICTED):] != PREDICTED).all() or (after == PREDICTED).all()
        return False
    error = np.linalg.norm(tracks.positions[visible_again + measured, col] - truth[visible_again + measured, col], axis=1)
    assert (error < 1.0).all(), error
    return True


@pytest.mark.parametrize("matcher", MATCHERS)
def test_hidden_marker_does_not_latch_onto_the_card(matcher):
    """The default card hides marker 0 in frames 10-12 and later passes others; seed 1 used to follow it with track 6."""
    resumed = 0
    for seed in range(5):
        scene, tracks, truth, visible = tracked_scene(seed, Occluder(), matcher=matcher)
        assert_no_silent_swap(scene, tracks, truth, visible)
        col = int(np.flatnonzero(tracks.track_ids == 0)[0])
        if matcher == "differential":
            resumed += assert_resumes_or_ends(tracks, truth, col, 13)
            continue
        # The marker the card was placed for coasts through its 3 frames.  In frame 13 it is
        # visible again: a trusted anchor match there is only a candidate (predicted), measured
        # from frame 14 when frame 14 confirms it; otherwise the track ends.
        after = tracks.status[13:20, col].tolist()
        if after == [PREDICTED] + [MEASURED] * 6:
            resumed += 1
            assert np.linalg.norm(tracks.positions[19, col] - truth[19, col]) < 1.0
        else:
            assert after in ([LOST] + [NO_TRACK] * 6, [PREDICTED, LOST] + [NO_TRACK] * 5), after
    # search: seeds 3 and 4; on 0-2 the anchor re-matches at 0.31-0.71 > 0.3 and the track ends.
    # differential: 4 of the 5 resume (its anchor is a keyframe renewed as the view turns).
    assert resumed >= (2 if matcher == "search" else 4)


@pytest.mark.parametrize("matcher", MATCHERS)
@pytest.mark.parametrize(("seed", "track_id", "n_frames"), [(0, 2, 3), (1, 2, 3), (3, 2, 3), (5, 2, 1), (2, 6, 3), (4, 0, 3)])
def test_two_markers_crossing(seed, track_id, n_frames, matcher):
    """The card carries a marker of its own across the hidden one (it used to take over tracks 2 and 7)."""
    occluder = Occluder(track_id=track_id, n_frames=n_frames, marker=True)
    scene, tracks, truth, visible = tracked_scene(seed, occluder, matcher=matcher)
    assert_no_silent_swap(scene, tracks, truth, visible)
    col = int(np.flatnonzero(tracks.track_ids == track_id)[0])
    if matcher == "differential":
        assert_resumes_or_ends(tracks, truth, col, 10 + n_frames)
        return
    # First frame visible again: a re-acquisition candidate if the track coasted (on seed 5 the
    # one-frame card only grazes the marker, and the track stays measured); measured from the
    # next frame on.
    first = 10 + n_frames
    coasted = bool((tracks.status[10:first, col] == PREDICTED).any())
    assert coasted == (seed != 5)
    assert tracks.status[first : first + 5, col].tolist() == [PREDICTED if coasted else MEASURED] + [MEASURED] * 4


@pytest.mark.parametrize("matcher", MATCHERS)
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_markers_leaving_the_image_end_cleanly(seed, matcher):
    """``scenario="exit"``: markers leave through the left border; their tracks end, none jumps elsewhere."""
    scene, tracks, truth, visible = tracked_scene(seed, scenario="exit", matcher=matcher)
    assert_no_silent_swap(scene, tracks, truth, visible)
    gone = ~visible[-1]
    assert gone.sum() >= 3
    assert (tracks.status[-1, gone] != MEASURED).all()


@pytest.mark.parametrize("matcher", MATCHERS)
def test_exit_with_a_crossing_card_and_a_long_full_height_occlusion(matcher):
    for seed in (3, 5):
        scene, tracks, truth, visible = tracked_scene(seed, Occluder(track_id=6, n_frames=3, marker=True), scenario="exit", matcher=matcher)
        assert_no_silent_swap(scene, tracks, truth, visible)
    # A full-height pole hiding marker 0 for 4 frames: it and the others it passes end or resume.
    scene, tracks, truth, visible = tracked_scene(2, Occluder(track_id=0, first_frame=12, n_frames=4, height_px=None), matcher=matcher)
    assert_no_silent_swap(scene, tracks, truth, visible)
    col = int(np.flatnonzero(tracks.track_ids == 0)[0])
    if matcher == "search":  # 4 frames > its 3 allowed misses
        assert (tracks.status[16:, col] == NO_TRACK).all()
    else:
        assert_resumes_or_ends(tracks, truth, col, 16)


def test_ncc_keeps_identities_too():
    for seed in (1, 3):
        scene, tracks, truth, visible = tracked_scene(seed, Occluder(track_id=2, marker=True), score="ncc", matcher="search")
        assert_no_silent_swap(scene, tracks, truth, visible)


def test_an_implausible_jump_is_refused_even_when_the_template_matches():
    """The innovation test on its own: a copy of the tracked patch pasted 8 px away, in the gate, the original erased."""
    rng = np.random.default_rng(7)
    import cv2

    world = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)), (0, 0), 1.5)
    frames = [world[20:100, 20 + k : 140 + k].copy() for k in range(10)]  # 1 px per frame leftwards
    p0 = np.array([[60.0, 40.0]])
    jumped = [f.copy() for f in frames]
    x, y = 60 - 6, 40  # the point's true place in frame 6
    patch = jumped[6][y - 7 : y + 8, x - 7 : x + 8].copy()
    jumped[6][y - 7 : y + 8, x + 1 : x + 16] = patch  # the same patch 8 px to the right
    jumped[6][y - 7 : y + 8, x - 7 : x + 1] = 128.0  # the original half erased
    plain = track(frames, p0, matcher="search")
    assert plain.measured.all()
    tracks = track(jumped, p0, matcher="search")
    # Refused in frame 6; re-acquired (candidate) in frame 7 and confirmed in frame 8.
    assert tracks.status[6:, 0].tolist() == [PREDICTED, PREDICTED] + [MEASURED] * 2
    assert np.linalg.norm(tracks.positions[-1, 0] - (p0[0] - [9.0, 0.0])) < 0.2
    # With the test switched off (a huge ratio) the same frame is taken 8 px off.
    loose = track(jumped, p0, max_innovation_ratio=1e6, matcher="search")
    assert loose.status[6, 0] == MEASURED
    assert np.linalg.norm(loose.positions[6, 0] - (p0[0] - [6.0, 0.0])) > 3.0


def test_the_differential_matcher_refuses_the_pasted_copy_too():
    """The same pasted copy: the flow from the prediction stays on the point or refuses it (its anchor is half erased)."""
    import cv2

    rng = np.random.default_rng(7)
    world = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)), (0, 0), 1.5)
    frames = [world[20:100, 20 + k : 140 + k].copy() for k in range(10)]
    x, y = 60 - 6, 40
    patch = frames[6][y - 7 : y + 8, x - 7 : x + 8].copy()
    frames[6][y - 7 : y + 8, x + 1 : x + 16] = patch
    frames[6][y - 7 : y + 8, x - 7 : x + 1] = 128.0
    tracks = track(frames, np.array([[60.0, 40.0]]), matcher="differential")
    truth = np.array([60.0, 40.0]) - np.arange(10)[:, None] * [1.0, 0.0]
    measured = tracks.status[:, 0] == MEASURED
    assert tracks.status[6, 0] == PREDICTED
    assert (np.linalg.norm(tracks.positions[measured, 0] - truth[measured], axis=1) < 0.5).all()
    assert tracks.status[-1, 0] == MEASURED


@pytest.mark.parametrize("matcher", MATCHERS)
def test_a_lookalike_seen_once_does_not_end_a_coast(matcher):
    """Seed 18: while marker 2 is under the card, the card's own marker passes through its grown gate.

    Before re-acquisitions needed a second, consistent frame, that single frame was taken as
    the hidden marker in frame 12 (4.1 px off, reported as measured, and followed for 4
    frames). The look-alike moves at +6 px per frame while the hidden marker moves at -2.1,
    so the candidate it offers is not confirmed in frame 13, and the track ends there.
    """
    occluder = Occluder(track_id=2, first_frame=10, n_frames=6, marker=True)
    scene, tracks, truth, visible = tracked_scene(18, occluder, matcher=matcher)
    assert_no_silent_swap(scene, tracks, truth, visible)
    col = int(np.flatnonzero(tracks.track_ids == 2)[0])
    if matcher == "differential":  # it coasts 5 frames, then the track ends, as the search's does after 3
        assert tracks.status[8:18, col].tolist() == [MEASURED] * 2 + [PREDICTED] * 5 + [LOST] + [NO_TRACK] * 2
        return
    assert tracks.status[8:16, col].tolist() == [MEASURED] * 2 + [PREDICTED] * 3 + [LOST] + [NO_TRACK] * 2
