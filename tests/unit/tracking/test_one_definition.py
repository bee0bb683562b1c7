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
