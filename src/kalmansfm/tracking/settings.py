"""The tracker's settings: one frozen, validated object that travels with the tracks it made.

Every default of the tracker is defined here, once: the command line shows these values in
its ``--help``, :class:`~kalmansfm.tracking.tracker.Tracker` runs with them, the tracks
carry them (``Tracks.settings``), ``tracks.npz`` and ``summary.json`` record them, and the
report draws the gate they define.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
from scipy.stats import chi2

from .._validation import check_count, check_positive
from ..errors import InvalidInputError
from ..estimation.models import LinearGaussianModel, constant_velocity_2d

__all__ = [
    "DEFAULT_GATE_PROBABILITY",
    "MATCHERS",
    "SCORES",
    "TEMPLATE_POLICIES",
    "TrackerSettings",
    "gate_probability_for_radius",
    "gate_radius_for_probability",
]

#: Probability that the true position lies inside the search gate (c² is its χ²₂ quantile).
DEFAULT_GATE_PROBABILITY = 0.95
#: How a track is measured in each frame: Lucas–Kanade from the prediction, or the report's gated search.
MATCHERS = ("differential", "search")
SCORES = ("ssd", "ncc")
TEMPLATE_POLICIES = ("anchored", "first", "last")
# A match is accepted below this dissimilarity (SSD / template energy, or 1 - NCC).
_DEFAULT_MAX_DISSIMILARITY = {"ssd": 0.5, "ncc": 0.3}
# The anchor must match much better than a mere "acceptable" match to be trusted as the
# drift-free position (a poorly matching template's peak is biased); tuned on the built-in
# scene (ssd) and cmu_house (ncc).
_DEFAULT_ANCHOR_DISSIMILARITY = {"ssd": 0.3, "ncc": 0.05}
# Frames a track may coast: the report's search loses a track after 3; the differential
# matcher refuses a match as soon as an occluder enters its window (a frame or two before
# the point itself is hidden), so it coasts 5 to resume after the same 3-frame occlusion
# (held-out scenes: 16 of 40 hidden markers resumed with 3, 33 of 40 with 5; docs/tracking.md).
_DEFAULT_MAX_MISSES = {"search": 3, "differential": 5}


def gate_radius_for_probability(probability: float, name: str = "gate probability") -> float:
    """Gate radius c such that a 2D Gaussian point falls in the gate with ``probability``.

    ``name`` is how an error message calls the probability (e.g. the settings field).

    c² is the ``probability`` quantile of the chi-square distribution with 2
    degrees of freedom, because (p - p⁻)ᵀ Σ⁻¹ (p - p⁻) of a 2D Gaussian is χ²₂.

    Examples
    --------
    >>> round(gate_radius_for_probability(0.95), 4)   # c² = 5.9915
    2.4477
    """
    if not 0.0 < probability < 1.0:
        raise InvalidInputError(f"{name} must be in (0, 1); got {probability}")
    return float(np.sqrt(chi2.ppf(probability, df=2)))


def gate_probability_for_radius(radius: float) -> float:
    """Probability mass of a 2D Gaussian inside the gate of Mahalanobis radius c: 1 - exp(-c²/2).

    Examples
    --------
    >>> round(gate_probability_for_radius(gate_radius_for_probability(0.9)), 12)
    0.9
    """
    return float(-np.expm1(-0.5 * radius * radius))


@dataclass(frozen=True)
class TrackerSettings:
    """How the Kalman tracker runs (see :mod:`kalmansfm.tracking.tracker`).

    Two matchers measure the tracks (``docs/tracking.md``): ``"differential"`` (default)
    follows each track by Lucas–Kanade started from its Kalman prediction, checks it
    (gate, forward–backward, appearance) and anchors it to its first appearance
    (:mod:`kalmansfm.tracking.differential`); ``"search"`` is the report's gated
    exhaustive SSD/NCC template search (:mod:`kalmansfm.tracking.matching`).  Settings
    marked (search) or (differential) apply to that matcher only.

    Attributes
    ----------
    matcher : ``"differential"`` or ``"search"``.
    window : odd side of the square template (and of the flow's window), pixels.
    score : (search) ``"ssd"`` or ``"ncc"``.
    gate_probability : probability that the true position lies in the gate; c² is its
        χ²₂ quantile (0.95 → c = 2.448).  Ignored when ``gate_radius`` is given.
    gate_radius : the gate's Mahalanobis radius c directly, or None.
    max_misses : a track coasts at most this many consecutive frames; the next miss
        loses it (unless that frame holds a re-acquisition candidate, which gets one
        frame to be confirmed); None: 3 (search), 5 (differential).
    max_dissimilarity : (search) a match is accepted at most at this dissimilarity (SSD / Σ(T - T̄)²
        for ``ssd``, 1 - NCC for ``ncc``); None: 0.5 (ssd), 0.3 (ncc).
    template_policy : (search) ``"anchored"`` (default), ``"first"`` or ``"last"``.
    model : the motion model (default: the report's constant-velocity model).
    max_features, quality_level, min_distance_px : corner detection when no start points
        are given or ``redetect`` is on.
    redetect : add corners in empty regions every ``redetect_every`` frames, new ids,
        up to ``max_features`` live tracks.
    redetect_every : frames between two redetections.
    reattach_frames : with ``redetect``, a track lost at most this many frames ago takes a
        redetected corner as its own again (same id) when the corner lies in the track's
        predicted gate and its descriptor matches the track's (:mod:`kalmansfm.tracking.reattach`);
        0 (default): a lost track stays lost.
    max_search_radius : the search box never exceeds this half-size, pixels (differential:
        the search that re-acquires a coasting track).
    anchor_dissimilarity : (search) the anchor's match is trusted at most at this dissimilarity;
        None: 0.3 (ssd), 0.05 (ncc).
    anchor_patience : frames in a row without a trusted anchor match before the current
        template (differential: the patch at the measurement) becomes the new anchor.
    refine : (search) polish accepted matches with a Gauss–Newton translation step.
    max_innovation_ratio : κ of the innovation plausibility test.
    max_pyramid_level : (differential) deepest pyramid level of the flow; the depth used
        per track follows from its gate and plausible radius.
    forward_backward_px : (differential) the flow back to the previous frame must land
        this close to where the track was.
    min_ncc : (differential) the track's anchor must match the patch at the measurement at
        least this well (normalised cross-correlation), or the track coasts.
    anchor_ncc : (differential) at this NCC the anchor's alignment is the measurement even
        where the chain explains the patch better.
    reacquire_ncc : (differential) a coasting track is found again only where its anchor
        matches at least this well.

    Examples
    --------
    >>> s = TrackerSettings(score="ncc", gate_probability=0.99)
    >>> round(s.effective_gate_radius, 3), s.match_threshold, s.anchor_threshold
    (3.035, 0.3, 0.05)
    >>> TrackerSettings(window=4)
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: window must be an odd integer >= 3; got 4
    """

    matcher: str = "differential"
    window: int = 11
    score: str = "ssd"
    gate_probability: float = DEFAULT_GATE_PROBABILITY
    gate_radius: float | None = None
    max_misses: int | None = None
    max_dissimilarity: float | None = None
    template_policy: str = "anchored"
    model: LinearGaussianModel = field(default_factory=constant_velocity_2d)
    max_features: int = 200
    quality_level: float = 0.01
    min_distance_px: float = 10.0
    redetect: bool = False
    redetect_every: int = 5
    reattach_frames: int = 0
    max_search_radius: int = 40
    anchor_dissimilarity: float | None = None
    anchor_patience: int = 4
    refine: bool = True
    max_innovation_ratio: float = 3.0
    max_pyramid_level: int = 3
    forward_backward_px: float = 1.0
    min_ncc: float = 0.8
    anchor_ncc: float = 0.97
    reacquire_ncc: float = 0.9

    def __post_init__(self) -> None:
        if self.matcher not in MATCHERS:
            raise InvalidInputError(f"matcher must be one of {MATCHERS}; got {self.matcher!r}")
        if isinstance(self.window, bool) or int(self.window) != self.window or self.window < 3 or self.window % 2 == 0:
            raise InvalidInputError(f"window must be an odd integer >= 3; got {self.window}")
        object.__setattr__(self, "window", int(self.window))
        if self.score not in SCORES:
            raise InvalidInputError(f"score must be one of {SCORES}; got {self.score!r}")
        if self.template_policy not in TEMPLATE_POLICIES:
            raise InvalidInputError(f"template_policy must be one of {TEMPLATE_POLICIES}; got {self.template_policy!r}")
        if self.gate_radius is not None:
            object.__setattr__(self, "gate_radius", check_positive("gate_radius", self.gate_radius))
            # c² must stay a normal positive float for the search's squared distances
            if not 1e-6 <= self.gate_radius <= 1e6:
                raise InvalidInputError(f"gate_radius must be between 1e-06 and 1e+06; got {self.gate_radius}")
        else:
            gate_radius_for_probability(self.gate_probability, "gate_probability")  # raises outside (0, 1)
        if self.max_misses is not None:
            object.__setattr__(self, "max_misses", check_count("max_misses", self.max_misses, 0))
        for name, minimum in (("max_features", 1), ("redetect_every", 1), ("anchor_patience", 1), ("max_pyramid_level", 0),
                              ("reattach_frames", 0)):
            object.__setattr__(self, name, check_count(name, getattr(self, name), minimum))
        if self.reattach_frames and not self.redetect:
            raise InvalidInputError(f"reattach_frames ({self.reattach_frames}) needs redetect: lost tracks are found "
                                    "again among the corners a redetection finds", fields=("reattach_frames", "redetect"))
        if check_count("max_search_radius", self.max_search_radius, 0) < 2:
            raise InvalidInputError(f"max_search_radius must be >= 2; got {self.max_search_radius}")
        for name in ("quality_level", "min_distance_px", "max_innovation_ratio", "forward_backward_px"):
            object.__setattr__(self, name, check_positive(name, getattr(self, name)))
        for name in ("min_ncc", "anchor_ncc", "reacquire_ncc"):
            object.__setattr__(self, name, check_positive(name, getattr(self, name)))
            if getattr(self, name) > 1:
                raise InvalidInputError(f"{name} must be a correlation in (0, 1]; got {getattr(self, name)}")
        for name in ("max_dissimilarity", "anchor_dissimilarity"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, check_positive(name, getattr(self, name)))
        if not isinstance(self.model, LinearGaussianModel):
            raise InvalidInputError(f"model must be a LinearGaussianModel; got {type(self.model).__name__}")
        if self.model.F.shape != (4, 4) or self.model.H.shape != (2, 4):
            raise InvalidInputError(
                f"the tracker's model must have a 4-state F and a 2×4 H (x, y measured); got F {self.model.F.shape}, "
                f"H {self.model.H.shape}"
            )

    @property
    def effective_gate_radius(self) -> float:
        """The gate's Mahalanobis radius c: ``gate_radius`` if given, else from ``gate_probability``."""
        return float(self.gate_radius) if self.gate_radius is not None else gate_radius_for_probability(self.gate_probability)

    @property
    def coast_limit(self) -> int:
        """Frames a track may coast (``max_misses`` or the matcher's default)."""
        return _DEFAULT_MAX_MISSES[self.matcher] if self.max_misses is None else int(self.max_misses)

    @property
    def match_threshold(self) -> float:
        """The dissimilarity at which a match is accepted (``max_dissimilarity`` or the score's default)."""
        return _DEFAULT_MAX_DISSIMILARITY[self.score] if self.max_dissimilarity is None else float(self.max_dissimilarity)

    @property
    def anchor_threshold(self) -> float:
        """The dissimilarity at which the anchor is trusted (``anchor_dissimilarity`` or the score's default)."""
        if self.anchor_dissimilarity is None:
            return _DEFAULT_ANCHOR_DISSIMILARITY[self.score]
        return float(self.anchor_dissimilarity)

    @property
    def reacquire_threshold(self) -> float:
        """Halfway between "acceptable" and "trusted anchor": re-acquisition level of the non-anchored policies."""
        return 0.5 * (self.match_threshold + self.anchor_threshold)

    @classmethod
    def option_names(cls) -> tuple[str, ...]:
        """The names of the settings (the keyword options of :func:`kalmansfm.track`)."""
        return tuple(f.name for f in fields(cls))
