"""The feature front end's settings: one frozen, validated object (every default defined here, once)."""

from __future__ import annotations

import os
from dataclasses import dataclass

from .._validation import check_choice, check_count, check_positive
from ..errors import InvalidInputError

__all__ = ["DETECTORS", "FeatureSettings"]

#: Detectors and descriptors (OpenCV): SIFT (RootSIFT by default), ORB and AKAZE (binary, Hamming distance).
DETECTORS = ("sift", "orb", "akaze")


@dataclass(frozen=True)
class FeatureSettings:
    """How features are detected, matched and verified; validated on construction.

    Attributes
    ----------
    detector : ``"sift"`` (default), ``"orb"`` or ``"akaze"``.
    root_sift : SIFT descriptors as RootSIFT (L1-normalised, square-rooted: Euclidean distance becomes the
        Hellinger kernel, which matches better); ignored by the binary detectors.
    max_features : keep at most this many features per image, the strongest (0 = all).  With the low
        contrast threshold below, a weakly textured image keeps all it has and a rich one its strongest
        (templeRing: 2 110 per view at 0.005, matching cost grows with the square).
    contrast_threshold : SIFT's contrast threshold.  OpenCV's default 0.04 finds 148 features per dinoRing
        view (median), 0.02 219, 0.01 376, 0.005 800; dinoRing's cameras came out 0.95 % of the ring radius off
        with 0.02 and 0.23 % with 0.005 (docs/front-end.md).
    sift_upsampling : how much SIFT's first octave enlarges the image.  OpenCV always doubles it; the image is
        resized by ``sift_upsampling / 2`` first (2 = OpenCV's own detection, 1 = no enlargement).  Most of a
        weakly textured image's features come from that first octave (616 of 798 on a dinoRing view), and
        its cost is the area: 1.4 builds a pyramid of half the pixels of OpenCV's.
    sift_sigma : SIFT's base blur, in pixels of the first octave.  With the upsampling it sets the finest
        scale in pixels of the image: 1.2 / 1.4 = 0.86, next to OpenCV's 1.6 / 2 = 0.8.  Together the two
        defaults take dinoRing's detection from 1.1 s to 0.5 s, and the cameras stay within the targets of
        all three Middlebury sets (docs/front-end.md).
    ratio : Lowe's ratio test: a nearest neighbour is kept when its distance is below ``ratio`` times the
        second nearest's; matches must also be mutual nearest neighbours.
    exhaustive_max_images : up to this many images every pair is matched; beyond it the pairs are a
        sequential window and the retrieval's nearest neighbours.
    pair_window : each image is matched with the next ``pair_window`` images (0 = none; image order is free).
    retrieval_neighbours : each image is matched with the images most similar to it (a cheap matching of
        their strongest features, :func:`~.pairs.image_similarity`).
    retrieval_features : strongest features per image used for that similarity.
    min_retrieval_matches : a retrieval neighbour must share at least this many of those matches.
    verification_threshold_px : inlier distance of the epipolar geometry (essential matrix when K is known,
        fundamental matrix otherwise; OpenCV's USAC MAGSAC++), pixels.
    min_inliers : a pair is verified with at least this many geometric inliers.
    confidence : RANSAC confidence of the verification.
    workers : threads for detection and matching (0 = one per core).
    seed : seed of OpenCV's random generator (RANSAC), for reproducible runs.
    """

    detector: str = "sift"
    root_sift: bool = True
    max_features: int = 1600
    contrast_threshold: float = 0.005
    sift_upsampling: float = 1.4
    sift_sigma: float = 1.2
    ratio: float = 0.8
    exhaustive_max_images: int = 12
    pair_window: int = 2
    retrieval_neighbours: int = 6
    retrieval_features: int = 128
    min_retrieval_matches: int = 4
    verification_threshold_px: float = 1.5
    min_inliers: int = 15
    confidence: float = 0.9999
    workers: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        check_choice("detector", self.detector, DETECTORS)
        if not isinstance(self.root_sift, (bool,)):
            raise InvalidInputError(f"root_sift must be True or False; got {self.root_sift!r}")
        for name in ("max_features", "pair_window", "retrieval_neighbours", "workers", "seed"):
            object.__setattr__(self, name, check_count(name, getattr(self, name), 0))
        for name, low in (("exhaustive_max_images", 2), ("retrieval_features", 8), ("min_retrieval_matches", 1),
                          ("min_inliers", 5)):
            object.__setattr__(self, name, check_count(name, getattr(self, name), low))
        for name in ("contrast_threshold", "sift_sigma"):
            object.__setattr__(self, name, check_positive(name, getattr(self, name)))
        upsampling = check_positive("sift_upsampling", self.sift_upsampling)
        if not 0.25 <= upsampling <= 2.0:
            raise InvalidInputError(f"sift_upsampling must be in [0.25, 2] (OpenCV's SIFT enlarges by 2 at most); "
                                    f"got {upsampling}")
        object.__setattr__(self, "sift_upsampling", upsampling)
        object.__setattr__(self, "verification_threshold_px",
                           check_positive("verification_threshold_px", self.verification_threshold_px, "pixels"))
        for name in ("ratio", "confidence"):
            value = check_positive(name, getattr(self, name))
            if not value < 1.0:
                raise InvalidInputError(f"{name} must be in (0, 1); got {value}")
            object.__setattr__(self, name, value)

    @property
    def binary(self) -> bool:
        """True for the binary descriptors (ORB, AKAZE), compared by Hamming distance."""
        return self.detector != "sift"

    @property
    def thread_count(self) -> int:
        """``workers``, or the number of cores when it is 0."""
        return self.workers or (os.cpu_count() or 1)
