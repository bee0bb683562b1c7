"""The match graph: the chosen image pairs matched (:mod:`.matching`) and verified (:mod:`.verification`)."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from .detection import ImageFeatures
from .matching import match_descriptors
from .pairs import PairSelection, select_pairs
from .settings import FeatureSettings
from .verification import verify_matches

__all__ = ["MatchGraph", "match_images"]


@dataclass(frozen=True)
class MatchGraph:
    """Every pair that was matched, and the verified matches of those that passed.

    Attributes
    ----------
    candidates : (C, 2) int64 — the pairs matched (i < j), from :func:`~.pairs.select_pairs`.
    putative_counts : (C,) int64 — mutual ratio-test matches of each candidate pair.
    inlier_counts : (C,) int64 — of those, consistent with the pair's epipolar geometry (0 when
        the pair failed verification).
    matches : tuple of C (k, 2) int64 arrays — the verified matches (feature indices in image i, in
        image j); empty for a pair that failed.
    distances : tuple of C (k,) float64 arrays — their descriptor distances.
    selection : the pair selection the candidates came from.
    """

    candidates: np.ndarray
    putative_counts: np.ndarray
    inlier_counts: np.ndarray
    matches: tuple[np.ndarray, ...]
    distances: tuple[np.ndarray, ...]
    selection: PairSelection

    @property
    def verified(self) -> np.ndarray:
        """(C,) bool — pairs that passed verification."""
        return self.inlier_counts > 0

    @property
    def pairs(self) -> np.ndarray:
        """(E, 2) the verified pairs."""
        return self.candidates[self.verified]

    def degree(self, count: int) -> np.ndarray:
        """(count,) number of verified pairs each image belongs to."""
        return np.bincount(self.pairs.ravel(), minlength=count)


def match_images(features: Sequence[ImageFeatures], intrinsics: np.ndarray | None = None,
                 settings: FeatureSettings | None = None, selection: PairSelection | None = None) -> MatchGraph:
    """Match and verify the chosen pairs of images, on ``settings.thread_count`` threads.

    Parameters
    ----------
    features : one :class:`ImageFeatures` per image.
    intrinsics : (n, 3, 3) K per image (essential matrices), or None (fundamental matrices).
    settings : FeatureSettings.
    selection : the pairs; default :func:`~.pairs.select_pairs`.

    Returns
    -------
    MatchGraph

    Examples
    --------
    >>> import cv2
    >>> rng = np.random.default_rng(2)
    >>> scene = cv2.GaussianBlur((rng.random((200, 260)) * 255).astype(np.uint8), (0, 0), 1.5)
    >>> images = [np.ascontiguousarray(scene[20:180, 10 + 20 * k: 210 + 20 * k]) for k in range(3)]
    >>> from kalmansfm.features import detect_all
    >>> graph = match_images(detect_all(images))
    >>> graph.candidates.tolist(), bool((graph.inlier_counts > 50).all())
    ([[0, 1], [0, 2], [1, 2]], True)
    """
    settings = FeatureSettings() if settings is None else settings
    n = len(features)
    if intrinsics is not None:
        intrinsics = np.asarray(intrinsics, np.float64)
        if intrinsics.shape != (n, 3, 3):
            raise InvalidInputError(f"intrinsics must have shape ({n}, 3, 3), one K per image; got {intrinsics.shape}")
    selection = select_pairs(features, settings) if selection is None else selection

    def one(pair: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
        i, j = int(pair[0]), int(pair[1])
        found = match_descriptors(features[i].descriptors, features[j].descriptors, settings.ratio, features[i].binary)
        if len(found) < settings.min_inliers:
            return len(found), np.zeros((0, 2), np.int64), np.zeros(0)
        K = (None, None) if intrinsics is None else (intrinsics[i], intrinsics[j])
        ok = verify_matches(features[i].keypoints[found.pairs[:, 0]], features[j].keypoints[found.pairs[:, 1]],
                            K[0], K[1], settings)
        return len(found), found.pairs[ok], found.distances[ok]

    with ThreadPoolExecutor(max_workers=settings.thread_count) as pool:
        results = list(pool.map(one, selection.pairs))
    putative = np.array([r[0] for r in results], np.int64)
    matches = tuple(r[1] for r in results)
    distances = tuple(r[2] for r in results)
    inliers = np.array([len(m) for m in matches], np.int64)
    return MatchGraph(selection.pairs, putative, inliers, matches, distances, selection)
