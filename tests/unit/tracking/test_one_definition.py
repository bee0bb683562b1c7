"""The tracker uses the package's one definition of each shared rule (no twins)."""

import numpy as np
import pytest

import kalmansfm.tracking.tracker as tracker_module
from kalmansfm._validation import check_positive
from kalmansfm.errors import InvalidInputError
from kalmansfm.estimation.models import initial_state
from kalmansfm.scenes import render_scene
from kalmansfm.tracking.settings import TrackerSettings


@pytest.mark.parametrize("matcher", ["differential", "search"])
def test_the_tracker_starts_its_filters_with_estimation_initial_state(matcher, monkeypatch):
    calls = []

    def spy(first, second):
        calls.append((np.array(first), np.array(second)))
        return initial_state(first, second)

    monkeypatch.setattr(tracker_module, "initial_state", spy)
    scene = render_scene(n_frames=4, seed=1)
    tracks = tracker_module.track(scene.frames, settings=TrackerSettings(matcher=matcher, max_features=20))
    assert calls, "the tracker built its initial states itself"
    first, second = calls[0]
    # the record of frame 1 holds s0 = [x1, y1, x1 - x0, y1 - y0] of the started tracks
    started = np.isin(tracks.track_ids, np.arange(len(first)))
    np.testing.assert_array_equal(tracks.states[1][started], initial_state(first, second))


@pytest.mark.parametrize("name", ["gate_radius", "quality_level", "min_distance_px", "max_innovation_ratio",
                                  "forward_backward_px", "min_ncc", "anchor_ncc", "reacquire_ncc",
                                  "max_dissimilarity", "anchor_dissimilarity"])
@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_tracker_settings_check_positive_numbers_with_the_shared_message(name, bad):
    with pytest.raises(InvalidInputError) as raised:
        TrackerSettings(**{name: bad})
    with pytest.raises(InvalidInputError) as shared:
        check_positive(name, bad)
    assert str(raised.value) == str(shared.value)
    assert str(raised.value).startswith(f"{name} must be")


@pytest.mark.parametrize("bad", [True, "fast", None, [1.0]])
def test_positive_numbers_refuse_bools_and_non_numbers(bad):
    with pytest.raises(InvalidInputError, match="quality_level must be a number"):
        TrackerSettings(quality_level=bad)
    with pytest.raises(InvalidInputError, match="focal must be a number"):
        check_positive("focal", bad)


def test_positive_settings_are_stored_as_floats():
    s = TrackerSettings(min_distance_px=7, gate_radius=3)
    assert type(s.min_distance_px) is float and s.min_distance_px == 7.0
    assert type(s.effective_gate_radius) is float


def _colour_frames(n_frames=5):
    """The built-in scene in BGR, with channels that differ (their grey is not a whole level)."""
    frames = render_scene(n_frames=n_frames, seed=2).frames
    rng = np.random.default_rng(0)
    tint = rng.integers(-9, 10, size=(1, 1, 3))
    return [np.clip(np.asarray(f, np.int16)[..., None] + tint, 0, 255).astype(np.uint8) for f in frames]


@pytest.mark.parametrize("matcher", ["differential", "search"])
def test_the_tracker_makes_colour_grey_as_the_frame_readers_do(matcher):
    from kalmansfm.io.frames import grey_uint8
    from kalmansfm.tracking.grey import colour_to_grey

    colour = _colour_frames()
    grey = [grey_uint8(f) for f in colour]
    for c, g in zip(colour, grey):
        np.testing.assert_array_equal(g, colour_to_grey(c))
        assert g.dtype == np.uint8 and g.shape == c.shape[:2]
    settings = TrackerSettings(matcher=matcher, max_features=15)
    from_colour = tracker_module.track(colour, settings=settings)
    from_grey = tracker_module.track(grey, settings=settings)
    assert from_colour.n_tracks > 5
    np.testing.assert_array_equal(from_colour.status, from_grey.status)
    np.testing.assert_array_equal(from_colour.states, from_grey.states)
    np.testing.assert_array_equal(from_colour.covariances, from_grey.covariances)


def test_colour_to_grey_policy():
    import cv2

    from kalmansfm.tracking.grey import GREY_WEIGHTS_BGR, colour_to_grey

    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 256, size=(4, 5, 3)).astype(np.uint8)
    bgra = np.concatenate([bgr, np.full((4, 5, 1), 7, np.uint8)], axis=2)
    np.testing.assert_array_equal(colour_to_grey(bgr), cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    np.testing.assert_array_equal(colour_to_grey(bgra), colour_to_grey(bgr))  # alpha ignored
    as_float = colour_to_grey(bgr.astype(np.float64))
    np.testing.assert_allclose(as_float, bgr @ np.array(GREY_WEIGHTS_BGR), rtol=1e-12)
    np.testing.assert_allclose(colour_to_grey(bgr), as_float, atol=0.5 + 1e-9)  # 8 bits: rounded
    grey = bgr[..., 0]
    assert colour_to_grey(grey) is grey
