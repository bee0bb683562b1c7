"""Which image pairs to match: all of them for a small set; otherwise a sequential window and,
for revisits and closed loops whatever the image order, the most similar images by retrieval.

The retrieval's similarity of two images is the number of mutual ratio-test matches between
their ``retrieval_features`` strongest features (:func:`image_similarity`): one matrix product
per image against the stacked features of all the others.  It costs n² m² D multiply-adds for
n images of m features (47 images × 128 features: 0.1–0.3 s on one core), small next to matching
the full feature sets of every pair; for thousands of images a vocabulary would be the next step.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from ..errors import NotEnoughDataError
from .detection import ImageFeatures
from .settings import FeatureSettings

__all__ = ["PairSelection", "image_similarity", "select_pairs"]


@dataclass(frozen=True)
class PairSelection:
    """The image pairs chosen for matching.

    Attributes
    ----------
    pairs : (E, 2) int64 — (i, j) with i < j, sorted.
    sequential : (E,) bool — the pair is in the sequential window (or the set is matched exhaustively).
    retrieved : (E,) bool — one image is among the other's most similar.
    similarity : (n, n) int64 — :func:`image_similarity` (zeros when every pair is matched).
    exhaustive : every pair was chosen.
    """

    pairs: np.ndarray
    sequential: np.ndarray
    retrieved: np.ndarray
    similarity: np.ndarray
    exhaustive: bool

    def __len__(self) -> int:
        return int(self.pairs.shape[0])


def image_similarity(features: Sequence[ImageFeatures], settings: FeatureSettings | None = None) -> np.ndarray:
    """(n, n) number of mutual ratio-test matches between the strongest features of every two images.

    Symmetric (mutual nearest neighbours passing the ratio test both ways, as :func:`~.matching.match_descriptors`),
    zero on the diagonal.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> d = rng.normal(size=(3, 40, 128)).astype(np.float32)
    >>> d[2, :30] = d[0, :30] + 0.01                      # images 0 and 2 share 30 features
    >>> d /= np.linalg.norm(d, axis=2, keepdims=True)
    >>> z = np.zeros((40, 2)); o = np.zeros(40, np.float32)
    >>> feats = [ImageFeatures(z, o, o, o, d[k], False) for k in range(3)]
    >>> image_similarity(feats, FeatureSettings(retrieval_features=40)).tolist()
    [[0, 0, 30], [0, 0, 0], [30, 0, 0]]
    """
    settings = FeatureSettings() if settings is None else settings
    n = len(features)
    m = settings.retrieval_features
    if n == 0:
        return np.zeros((0, 0), np.int64)
    width = features[0].descriptors.shape[1]
    stacked = np.zeros((n, m, width), np.float32)
    valid = np.zeros((n, m), bool)
    for k, f in enumerate(features):
        strongest = f.strongest(m)
        stacked[k, : len(strongest)] = strongest
        valid[k, : len(strongest)] = True
    norms = np.einsum("kij,kij->ki", stacked, stacked)
    binary = features[0].binary
    factor = settings.ratio if binary else settings.ratio**2
    ranks = np.arange(m)

    def later(i: int) -> np.ndarray:
        """Matches of image i with each later image j (the test of :func:`~.matching.match_descriptors`)."""
        others = stacked[i + 1:]
        k = len(others)
        # d[a, j, b]: feature a of image i against feature b of image i + 1 + j (squared distance, or Hamming)
        products = (stacked[i] @ others.reshape(k * m, width).T).reshape(m, k, m)
        d = norms[i][:, None, None] + norms[i + 1:][None] - 2.0 * products
        np.maximum(d, 0.0, out=d)
        d[~valid[i]] = np.inf  # padding rows and columns (images with fewer features) match nothing
        d[:, ~valid[i + 1:]] = np.inf
        # the two smallest along an axis by two reductions (the smallest masked with inf, then put back),
        # not a partition: 3× faster here
        best_b = np.argmin(d, axis=2)[..., None]                          # (m, k, 1)
        smallest = np.take_along_axis(d, best_b, axis=2)
        np.put_along_axis(d, best_b, np.inf, axis=2)
        second = d.min(axis=2)                                            # (m, k)
        np.put_along_axis(d, best_b, smallest, axis=2)
        best_b, smallest = best_b[..., 0], smallest[..., 0]
        best_a = np.argmin(d, axis=0)[None]                               # (1, k, m)
        np.put_along_axis(d, best_a, np.inf, axis=0)
        col_second = d.min(axis=0)                                        # (k, m)
        columns = np.arange(k)[None, :]
        mutual = best_a[0][columns, best_b] == ranks[:, None]
        ok = mutual & np.isfinite(smallest) & (smallest < factor * second) \
            & (smallest < factor * col_second[columns, best_b])
        return ok.sum(axis=0)

    counts = np.zeros((n, n), np.int64)
    with ThreadPoolExecutor(max_workers=settings.thread_count) as pool:
        for i, found in enumerate(pool.map(later, range(n - 1))):
            counts[i, i + 1:] = found
    return counts + counts.T


def select_pairs(features: Sequence[ImageFeatures], settings: FeatureSettings | None = None) -> PairSelection:
    """The pairs to match: every pair up to ``exhaustive_max_images`` images; beyond, the next
    ``pair_window`` images of each and its ``retrieval_neighbours`` most similar images.

    Raises
    ------
    NotEnoughDataError
        Fewer than 2 images.

    Examples
    --------
    >>> z = np.zeros((0, 2)); e = np.zeros(0, np.float32)
    >>> feats = [ImageFeatures(z, e, e, e, np.zeros((0, 128), np.float32), False)] * 4
    >>> select_pairs(feats).pairs.tolist()
    [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    """
    settings = FeatureSettings() if settings is None else settings
    n = len(features)
    if n < 2:
        raise NotEnoughDataError(f"pairs need >= 2 images; got {n}")
    if n <= settings.exhaustive_max_images:
        a, b = np.triu_indices(n, 1)
        pairs = np.stack([a, b], axis=1).astype(np.int64)
        every = np.ones(len(pairs), bool)
        return PairSelection(pairs, every, np.zeros(len(pairs), bool), np.zeros((n, n), np.int64), True)
    window = np.zeros((n, n), bool)
    for step in range(1, settings.pair_window + 1):
        idx = np.arange(n - step)
        window[idx, idx + step] = True
    similarity = image_similarity(features, settings)
    retrieved = np.zeros((n, n), bool)
    k = min(settings.retrieval_neighbours, n - 1)
    if k:
        nearest = np.argsort(-similarity, axis=1, kind="stable")[:, :k]
        rows = np.repeat(np.arange(n), k)
        cols = nearest.ravel()
        strong = similarity[rows, cols] >= settings.min_retrieval_matches
        retrieved[rows[strong], cols[strong]] = True
        retrieved |= retrieved.T
    chosen = np.triu(window | retrieved, 1)
    a, b = np.nonzero(chosen)
    return PairSelection(np.stack([a, b], axis=1).astype(np.int64), window[a, b], retrieved[a, b], similarity, False)
