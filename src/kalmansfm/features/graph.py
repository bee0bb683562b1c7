"""The match graph: the chosen image pairs matched (:mod:`.matching`) and verified (:mod:`.verification`)."""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from .detection import ImageFeatures
from .matching import match_descriptors
from .pairs import PairSelection, select_pairs
from .settings import FeatureSettings
from .verification import verify_matches

__all__ = ["PAIR_CHUNK", "MatchGraph", "PairChunk", "match_images", "match_pair_chunk"]


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


#: Pairs matched together when the matching is spread over an executor (one Dask task each).
PAIR_CHUNK = 32


@dataclass(frozen=True)
class PairChunk:
    """Pairs to match elsewhere, with what they need and nothing more: the features of their images only."""

    pairs: np.ndarray  # (k, 2) image indices into the full set
    features: dict[int, ImageFeatures]
    intrinsics: dict[int, np.ndarray] | None
    settings: FeatureSettings


def _match_pair(first: ImageFeatures, second: ImageFeatures, K: tuple[np.ndarray | None, np.ndarray | None],
                settings: FeatureSettings) -> tuple[int, np.ndarray, np.ndarray]:
    """Putative count, verified matches and their distances of one pair."""
    found = match_descriptors(first.descriptors, second.descriptors, settings.ratio, first.binary)
    if len(found) < settings.min_inliers:
        return len(found), np.zeros((0, 2), np.int64), np.zeros(0)
    ok = verify_matches(first.keypoints[found.pairs[:, 0]], second.keypoints[found.pairs[:, 1]], K[0], K[1], settings)
    return len(found), found.pairs[ok], found.distances[ok]


def match_pair_chunk(chunk: PairChunk) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Every pair of ``chunk`` matched and verified, in order (what one worker does)."""
    out = []
    for i, j in chunk.pairs.tolist():
        K = (None, None) if chunk.intrinsics is None else (chunk.intrinsics[i], chunk.intrinsics[j])
        out.append(_match_pair(chunk.features[i], chunk.features[j], K, chunk.settings))
    return out


def match_images(features: Sequence[ImageFeatures], intrinsics: np.ndarray | None = None,
                 settings: FeatureSettings | None = None, selection: PairSelection | None = None,
                 executor: Any | None = None) -> MatchGraph:
    """Match and verify the chosen pairs of images, on ``settings.thread_count`` threads or on ``executor``.

    Parameters
    ----------
    features : one :class:`ImageFeatures` per image.
    intrinsics : (n, 3, 3) K per image (essential matrices), or None (fundamental matrices).
    settings : FeatureSettings.
    selection : the pairs; default :func:`~.pairs.select_pairs`.
    executor : object with a ``map(fn, items)`` method, optional
        Matches the pairs in chunks of :data:`PAIR_CHUNK` (:class:`PairChunk`, each with the
        features of its images only) — e.g. :class:`kalmansfm.pipeline.cluster.ScatteringExecutor`
        on Dask, for large sets.  The result is the same.

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
    if executor is None:
        def one(pair: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
            i, j = int(pair[0]), int(pair[1])
            K = (None, None) if intrinsics is None else (intrinsics[i], intrinsics[j])
            return _match_pair(features[i], features[j], K, settings)

        with ThreadPoolExecutor(max_workers=settings.thread_count) as pool:
            results = list(pool.map(one, selection.pairs))
    else:
        chunks = []
        for start in range(0, len(selection.pairs), PAIR_CHUNK):
            pairs = selection.pairs[start:start + PAIR_CHUNK]
            images = np.unique(pairs).tolist()
            chunks.append(PairChunk(pairs, {v: features[v] for v in images},
                                    None if intrinsics is None else {v: intrinsics[v] for v in images}, settings))
        results = [r for done in executor.map(match_pair_chunk, chunks) for r in done]
    putative = np.array([r[0] for r in results], np.int64)
    matches = tuple(r[1] for r in results)
    distances = tuple(r[2] for r in results)
    inliers = np.array([len(m) for m in matches], np.int64)
    return MatchGraph(selection.pairs, putative, inliers, matches, distances, selection)
