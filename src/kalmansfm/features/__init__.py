"""The feature front end: detection and description (OpenCV), mutual ratio-test matching, the choice of
image pairs (sequential window, exhaustive for small sets, retrieval for revisits and loops), geometric
verification (USAC) and tracks over all verified pairs (union–find, split where inconsistent).

Arrays in, frozen records out; no files (``kalmansfm.io`` reads images) and no cameras (``kalmansfm.mapping``
turns tracks into cameras and points, and matches again where the cameras predict).
"""

from .detection import ImageFeatures, detect_all, detect_features
from .graph import MatchGraph, match_images
from .matching import DescriptorMatches, match_descriptors, squared_distances
from .pairs import PairSelection, image_similarity, select_pairs
from .settings import DETECTORS, FeatureSettings
from .tracks import FeatureTracks, add_observations, build_tracks, merge_tracks, union_without_conflicts
from .verification import normalised_points, verify_matches

__all__ = [
    "DETECTORS",
    "DescriptorMatches",
    "FeatureSettings",
    "FeatureTracks",
    "ImageFeatures",
    "MatchGraph",
    "PairSelection",
    "add_observations",
    "build_tracks",
    "detect_all",
    "detect_features",
    "image_similarity",
    "match_descriptors",
    "match_images",
    "merge_tracks",
    "normalised_points",
    "select_pairs",
    "squared_distances",
    "union_without_conflicts",
    "verify_matches",
]
