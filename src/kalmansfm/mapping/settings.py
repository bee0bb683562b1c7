"""Settings and view status of :func:`~kalmansfm.mapping.reconstruct_images` (every default defined here, once)."""

from __future__ import annotations

from dataclasses import dataclass, field

from scipy import stats

from .._validation import LabelledEnum, check_count, check_positive
from ..errors import InvalidInputError
from ..features import FeatureSettings
from ..structure.perspective import PerspectiveSettings

__all__ = ["FEATURE_OUTLIER_THRESHOLD_PX", "MappingSettings", "ViewStatus"]

#: the back end's outlier threshold for feature tracks (pixels): SIFT positions are good to about 0.3 px, and
#: the back end's general default (4 px, made for the tracker's tracks) kept mismatches that bent dinoRing's
#: cameras (0.95 % of the ring radius with 4 px, 0.2-0.3 % with 2 px; docs/front-end.md).
FEATURE_OUTLIER_THRESHOLD_PX = 2.0


def _default_reconstruction() -> PerspectiveSettings:
    return PerspectiveSettings(outlier_threshold_px=FEATURE_OUTLIER_THRESHOLD_PX)


class ViewStatus(LabelledEnum):
    """Outcome for one image; its ``label`` is the word summaries use."""

    REGISTERED = 0  #: the view has a camera
    NO_FEATURES = 1  #: too few features were detected (blank, flat or tiny image)
    NO_MATCHES = 2  #: no verified pair with any other image
    NOT_CONNECTED = 3  #: verified pairs, but too few shared tracks with the reconstructed points
    POSE_FAILED = 4  #: shared points, but no consistent pose


@dataclass(frozen=True)
class MappingSettings:
    """How :func:`~kalmansfm.mapping.reconstruct_images` runs; validated on construction.

    Attributes
    ----------
    features : detection, matching, pair selection and verification (:class:`~kalmansfm.features.FeatureSettings`).
    reconstruction : the calibrated back end (:class:`~kalmansfm.structure.PerspectiveSettings`), by default with
        the outlier threshold :data:`FEATURE_OUTLIER_THRESHOLD_PX`.
    guided_matching : after the first reconstruction, search each view for the known points inside the gate
        their projection allows, add what matches, and reconstruct again.
    gate_probability : in (0, 1); a feature is a candidate when its Mahalanobis distance to the predicted
        position, under the point's and camera's covariance projected plus σ², is inside the χ²₂ quantile
        of this probability.
    gate_floor_px : or when it is within this many pixels (the covariances describe the noise, not the
        model's small systematic errors).
    max_gate_px : no candidate farther than this from the prediction, whatever the covariance.
    guided_ratio : among the candidates inside one gate, the best descriptor distance must be below this
        times the second best.
    unrelated_quantile : and closer than this quantile of the distances between unrelated features (random
        features of different images): the gate is the main evidence (on templeRing 95 % of the features
        alone in a gate are the point, whatever their descriptor distance), the descriptor only has to be
        more alike than a chance feature.
    max_view_angle_deg : a point is searched for in a view only if the view sees it within this angle of a
        view that already observed it (appearance changes beyond).
    skeleton_tracks_per_view : the first reconstruction uses, for every view, its this many longest tracks
        (their union); long tracks fix the cameras, and the back end's time grows with the number of tracks.
    final_tracks_per_view : the same for the final reconstruction, after guided matching (0 = every track).
    """

    features: FeatureSettings = field(default_factory=FeatureSettings)
    reconstruction: PerspectiveSettings = field(default_factory=_default_reconstruction)
    guided_matching: bool = True
    gate_probability: float = 0.99
    gate_floor_px: float = 1.5
    max_gate_px: float = 12.0
    guided_ratio: float = 0.85
    unrelated_quantile: float = 0.5
    max_view_angle_deg: float = 40.0
    skeleton_tracks_per_view: int = 50
    final_tracks_per_view: int = 200

    def __post_init__(self) -> None:
        if not isinstance(self.features, FeatureSettings):
            raise InvalidInputError(f"features must be a FeatureSettings; got {type(self.features).__name__}")
        if not isinstance(self.reconstruction, PerspectiveSettings):
            raise InvalidInputError(f"reconstruction must be a PerspectiveSettings; got "
                                    f"{type(self.reconstruction).__name__}")
        if self.reconstruction.method != "batch":
            raise InvalidInputError("reconstruct_images needs the batch (bundle adjustment) back end; got method "
                                    f"{self.reconstruction.method!r}")
        if not isinstance(self.guided_matching, bool):
            raise InvalidInputError(f"guided_matching must be True or False; got {self.guided_matching!r}")
        for name in ("gate_probability", "guided_ratio", "unrelated_quantile"):
            value = check_positive(name, getattr(self, name))
            if not value < 1.0:
                raise InvalidInputError(f"{name} must be in (0, 1); got {value}")
            object.__setattr__(self, name, value)
        for name in ("gate_floor_px", "max_gate_px"):
            object.__setattr__(self, name, check_positive(name, getattr(self, name), "pixels"))
        if self.max_gate_px < self.gate_floor_px:
            raise InvalidInputError(f"max_gate_px ({self.max_gate_px}) must be >= gate_floor_px ({self.gate_floor_px})")
        angle = check_positive("max_view_angle_deg", self.max_view_angle_deg, "degrees")
        if angle > 180.0:
            raise InvalidInputError(f"max_view_angle_deg must be in (0, 180]; got {angle}")
        object.__setattr__(self, "max_view_angle_deg", angle)
        object.__setattr__(self, "skeleton_tracks_per_view",
                           check_count("skeleton_tracks_per_view", self.skeleton_tracks_per_view, 1))
        object.__setattr__(self, "final_tracks_per_view",
                           check_count("final_tracks_per_view", self.final_tracks_per_view, 0))

    @property
    def gate_chi2(self) -> float:
        """χ²₂ quantile of ``gate_probability``: the squared Mahalanobis radius of the gate."""
        return float(stats.chi2.ppf(self.gate_probability, 2))
