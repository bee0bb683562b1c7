"""Image tracking: corner detection, gated template search and the Kalman tracker."""

from .detect import detect_corners
from .matching import MatchResult, match_templates
from .settings import DEFAULT_GATE_PROBABILITY, TrackerSettings, gate_radius_for_probability
from .smoothing import smooth_tracks
from .tracker import FrameEstimate, Tracker, track
from .tracks import LOST, MEASURED, NO_TRACK, PREDICTED, Tracks, TrackStatus

__all__ = [
    "DEFAULT_GATE_PROBABILITY",
    "LOST",
    "MEASURED",
    "NO_TRACK",
    "PREDICTED",
    "FrameEstimate",
    "MatchResult",
    "TrackStatus",
    "Tracker",
    "TrackerSettings",
    "Tracks",
    "detect_corners",
    "gate_radius_for_probability",
    "match_templates",
    "smooth_tracks",
    "track",
]
