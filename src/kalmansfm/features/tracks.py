"""Tracks from the match graph: a union–find over every verified match, one feature per image per track.

1. Every verified match joins its two features (connected components of the match graph over
   all features, :func:`scipy.sparse.csgraph.connected_components`: the union–find, vectorised).
2. A component holding two features of one image is inconsistent (a chain of matches drifted,
   or a repeated structure).  It is split: its matches are replayed strongest first (smallest
   descriptor distance) through a union–find that refuses any merge putting two features of one
   image in one set (:func:`union_without_conflicts`, a numba kernel).
3. Components of two or more features become tracks, as dense (F, P, 2) positions with NaN and
   the feature index of each observation.

:func:`merge_tracks` applies the same constrained union to whole tracks (tracks found to be one
point), and :func:`add_observations` writes new (view, track, feature) observations.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from ..errors import InvalidInputError
from ._union_kernel import union_kernel
from .detection import ImageFeatures
from .graph import MatchGraph

__all__ = ["FeatureTracks", "add_observations", "build_tracks", "merge_tracks", "union_reference",
           "union_without_conflicts"]


@dataclass(frozen=True)
class FeatureTracks:
    """Tracks of features over F images: at most one feature per image per track.

    Attributes
    ----------
    observations : (F, P, 2) float64 — pixel positions (x = column, y = row), NaN where a track is not seen.
    feature_index : (F, P) int64 — index of the observed feature in that image's
        :class:`~.detection.ImageFeatures`, -1 where not seen.
    split_components : components of the match graph that held two features of one image and were split.
    """

    observations: np.ndarray
    feature_index: np.ndarray
    split_components: int = 0

    @property
    def views(self) -> np.ndarray:
        """(P,) number of images that see each track."""
        return (self.feature_index >= 0).sum(axis=0)

    @property
    def seen(self) -> np.ndarray:
        """(F, P) bool — the track is observed in the image."""
        return self.feature_index >= 0

    def subset(self, tracks: np.ndarray) -> FeatureTracks:
        """The tracks selected by an index or boolean array, in that order."""
        return FeatureTracks(self.observations[:, tracks], self.feature_index[:, tracks], self.split_components)


def union_without_conflicts(entry_start: np.ndarray, entry_image: np.ndarray, entry_feature: np.ndarray,
                            first: np.ndarray, second: np.ndarray, image_count: int) -> np.ndarray:
    """Labels of a union–find over elements that refuses to merge two sets holding different features of one image.

    Parameters
    ----------
    entry_start : (n + 1,) int64 — element e owns the entries ``entry_start[e]:entry_start[e + 1]``.
    entry_image, entry_feature : (total,) int64 — each entry's image and feature (any id unique per image).
    first, second : (E,) int64 — the edges, applied in this order (strongest first).
    image_count : number of images (entry_image < image_count).

    Returns
    -------
    (n,) int64
        The representative element of each element's set.

    Examples
    --------
    Three features of images 0, 1, 0: the edge 1–2 would put two features of image 0 together
    after 0–1 and is refused.

    >>> labels = union_without_conflicts(np.array([0, 1, 2, 3]), np.array([0, 1, 0]), np.array([0, 1, 2]),
    ...                                  np.array([0, 1]), np.array([1, 2]), 2)
    >>> labels[0] == labels[1], labels[1] == labels[2]
    (np.True_, np.False_)
    """
    start = np.ascontiguousarray(entry_start, np.int64)
    count = len(start) - 1
    a = np.ascontiguousarray(first, np.int64)
    b = np.ascontiguousarray(second, np.int64)
    if count < 0 or len(a) != len(b) or (len(a) and (min(a.min(), b.min()) < 0 or max(a.max(), b.max()) >= count)):
        raise InvalidInputError(f"edges must join elements 0..{count - 1}; got {len(a)} and {len(b)} endpoints")
    return union_kernel(count, start, np.ascontiguousarray(entry_image, np.int64),
                        np.ascontiguousarray(entry_feature, np.int64), a, b, int(image_count))


def union_reference(entry_start: np.ndarray, entry_image: np.ndarray, entry_feature: np.ndarray,
                    first: np.ndarray, second: np.ndarray, image_count: int) -> list[set[int]]:
    """The same constrained union in plain Python with sets (the tests' reference); the sets of elements.

    Examples
    --------
    >>> union_reference(np.array([0, 1, 2, 3]), np.array([0, 1, 0]), np.array([0, 1, 2]), [0, 1], [1, 2], 2)
    [{0, 1}, {2}]
    """
    owner = {e: {e} for e in range(len(entry_start) - 1)}
    member_of = list(range(len(entry_start) - 1))
    entries = {e: {(int(entry_image[k]), int(entry_feature[k])) for k in range(entry_start[e], entry_start[e + 1])}
               for e in owner}
    for x, y in zip(np.asarray(first).tolist(), np.asarray(second).tolist()):
        rx, ry = member_of[x], member_of[y]
        if rx == ry:
            continue
        images_x = {}
        for image, feature in entries[rx]:
            images_x[image] = feature
        if any(image in images_x and images_x[image] != feature for image, feature in entries[ry]):
            continue
        owner[rx] |= owner.pop(ry)
        entries[rx] |= entries.pop(ry)
        for e in owner[rx]:
            member_of[e] = rx
    return [set(s) for s in owner.values()]


def _dense_tracks(labels: np.ndarray, image_of: np.ndarray, local_index: np.ndarray, positions: np.ndarray,
                  image_count: int, split: int) -> FeatureTracks:
    """Tracks from a label per feature (features of a label = a track when there are >= 2 of them)."""
    _, compact, size = np.unique(labels, return_inverse=True, return_counts=True)
    keep = size >= 2
    # track order: by each track's smallest feature (stable whatever the labels were)
    first_feature = np.full(len(size), np.iinfo(np.int64).max)
    np.minimum.at(first_feature, compact, np.arange(len(labels)))
    kept = np.flatnonzero(keep)
    order = kept[np.argsort(first_feature[kept], kind="stable")]
    track_of = np.full(len(size), -1)
    track_of[order] = np.arange(len(order))
    mine = track_of[compact] >= 0
    P = len(order)
    observations = np.full((image_count, P, 2), np.nan)
    feature_index = np.full((image_count, P), -1, np.int64)
    observations[image_of[mine], track_of[compact[mine]]] = positions[mine]
    feature_index[image_of[mine], track_of[compact[mine]]] = local_index[mine]
    return FeatureTracks(observations, feature_index, split)


def build_tracks(features: Sequence[ImageFeatures], graph: MatchGraph) -> FeatureTracks:
    """Tracks over every verified match of the graph (union–find), split where they hold two features of one image.

    Examples
    --------
    Image 0's feature 0 matches image 1's feature 0 and image 2's feature 1; image 1's feature 0
    matches image 2's feature 1 too: one track seen in the three images.

    >>> from kalmansfm.features.pairs import PairSelection
    >>> z = np.zeros(2, np.float32)
    >>> f = ImageFeatures(np.array([[1.0, 2.0], [3.0, 4.0]]), z, z, z, np.zeros((2, 4), np.float32), False)
    >>> pairs = np.array([[0, 1], [0, 2], [1, 2]])
    >>> sel = PairSelection(pairs, np.ones(3, bool), np.zeros(3, bool), np.zeros((3, 3), np.int64), True)
    >>> m = (np.array([[0, 0]]), np.array([[0, 1]]), np.array([[0, 1]]))
    >>> graph = MatchGraph(pairs, np.ones(3, np.int64), np.ones(3, np.int64), m, (np.zeros(1),) * 3, sel)
    >>> tracks = build_tracks([f, f, f], graph)
    >>> tracks.feature_index.T.tolist(), tracks.observations[2, 0].tolist()
    ([[0, 0, 1]], [3.0, 4.0])
    """
    F = len(features)
    sizes = np.array([len(f) for f in features], np.int64)
    offset = np.concatenate([[0], np.cumsum(sizes)])
    N = int(offset[-1])
    image_of = np.repeat(np.arange(F), sizes)
    local_index = np.arange(N) - offset[image_of]
    positions = np.concatenate([f.keypoints for f in features]) if N else np.zeros((0, 2))
    used = np.flatnonzero(graph.inlier_counts > 0)
    if len(used) == 0:
        return FeatureTracks(np.zeros((F, 0, 2)), np.zeros((F, 0), np.int64))
    a = np.concatenate([offset[graph.candidates[e, 0]] + graph.matches[e][:, 0] for e in used])
    b = np.concatenate([offset[graph.candidates[e, 1]] + graph.matches[e][:, 1] for e in used])
    strength = np.concatenate([graph.distances[e] for e in used])
    adjacency = coo_matrix((np.ones(len(a)), (a, b)), shape=(N, N))
    _, labels = connected_components(adjacency, directed=False)
    # components holding two features of one image
    key = labels * F + image_of
    unique_keys, per_key = np.unique(key, return_counts=True)
    conflicted = np.zeros(labels.max() + 1, bool)
    conflicted[unique_keys[per_key > 1] // F] = True
    split = int(conflicted.sum())
    if split:
        inside = conflicted[labels[a]]
        order = np.argsort(strength[inside], kind="stable")
        replayed = union_without_conflicts(np.arange(N + 1), image_of, np.arange(N), a[inside][order],
                                           b[inside][order], F)
        # features of conflicted components take their new set's root (offset to stay apart from the rest)
        moved = conflicted[labels]
        labels = labels.copy()
        labels[moved] = labels.max() + 1 + replayed[moved]
    return _dense_tracks(labels, image_of, local_index, positions, F, split)


def merge_tracks(tracks: FeatureTracks, first: np.ndarray, second: np.ndarray) -> FeatureTracks:
    """Tracks joined along the edges (first[k], second[k]) (strongest first), unless a join would put two
    different features of one image in one track; the merged tracks take the place of the first of them.

    Examples
    --------
    >>> fi = np.array([[0, -1, 1], [-1, 0, 0]])
    >>> obs = np.where(fi[..., None] >= 0, 1.0, np.nan) * np.ones(2)
    >>> t = FeatureTracks(obs, fi)
    >>> merge_tracks(t, np.array([0, 0]), np.array([1, 2])).feature_index.tolist()   # 0+1 merge; 2 conflicts
    [[0, 1], [0, 0]]
    """
    F, P = tracks.feature_index.shape
    seen = tracks.seen.T  # (P, F)
    track_of_entry, image_of_entry = np.nonzero(seen)
    entry_start = np.concatenate([[0], np.cumsum(seen.sum(axis=1))])
    labels = union_without_conflicts(entry_start, image_of_entry, tracks.feature_index.T[seen], first, second, F)
    roots, compact = np.unique(labels, return_inverse=True)
    first_member = np.full(len(roots), P)
    np.minimum.at(first_member, compact, np.arange(P))
    order = np.argsort(first_member, kind="stable")
    new_of_root = np.empty(len(roots), np.int64)
    new_of_root[order] = np.arange(len(roots))
    target = new_of_root[compact]
    observations = np.full((F, len(roots), 2), np.nan)
    feature_index = np.full((F, len(roots)), -1, np.int64)
    frames, old = np.nonzero(tracks.seen)
    observations[frames, target[old]] = tracks.observations[frames, old]
    feature_index[frames, target[old]] = tracks.feature_index[frames, old]
    return FeatureTracks(observations, feature_index, tracks.split_components)


def add_observations(tracks: FeatureTracks, features: Sequence[ImageFeatures], views: np.ndarray,
                     track_ids: np.ndarray, feature_ids: np.ndarray) -> FeatureTracks:
    """Tracks with the observations (views[k], track_ids[k]) set to feature ``feature_ids[k]`` of that view.

    Examples
    --------
    >>> z = np.zeros(1, np.float32)
    >>> f = ImageFeatures(np.array([[5.0, 6.0]]), z, z, z, np.zeros((1, 4), np.float32), False)
    >>> t = FeatureTracks(np.full((2, 1, 2), np.nan), np.full((2, 1), -1))
    >>> add_observations(t, [f, f], np.array([1]), np.array([0]), np.array([0])).observations[1, 0].tolist()
    [5.0, 6.0]
    """
    observations = tracks.observations.copy()
    feature_index = tracks.feature_index.copy()
    views = np.asarray(views, np.int64)
    feature_ids = np.asarray(feature_ids, np.int64)
    positions = np.zeros((len(views), 2))
    for v in np.unique(views):  # one gather per view
        mine = views == v
        positions[mine] = features[v].keypoints[feature_ids[mine]]
    observations[views, track_ids] = positions
    feature_index[views, track_ids] = feature_ids
    return FeatureTracks(observations, feature_index, tracks.split_components)
