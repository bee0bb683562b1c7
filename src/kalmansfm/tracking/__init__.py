"""Image tracking: corner detection, gated template search and the Kalman tracker."""

from .detect import detect_corners
from .matching import MatchResult, gate_radius_for_probability, match_templates
from .smoothing import smooth_tracks
from .tracker import FrameEstimate, Tracker, track
from .tracks import LOST, MEASURED, NO_TRACK, PREDICTED, STATUS_NAMES, Tracks

__all__ = [
    "LOST",
    "MEASURED",
    "NO_TRACK",
    "PREDICTED",
    "STATUS_NAMES",
    "FrameEstimate",
    "MatchResult",
    "Tracker",
    "Tracks",
    "detect_corners",
    "gate_radius_for_probability",
    "match_templates",
    "smooth_tracks",
    "track",
]
