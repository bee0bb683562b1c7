"""Tracks by union–find over verified matches: one feature per image per track, conflicting components split."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm.features import FeatureTracks, ImageFeatures, MatchGraph, PairSelection, build_tracks, merge_tracks
from kalmansfm.features.tracks import union_reference, union_without_conflicts


def features(count, seed=0):
    rng = np.random.default_rng(seed)
    z = np.zeros(count, np.float32)
    return ImageFeatures(rng.uniform(0, 100, (count, 2)), z, z, z, np.zeros((count, 4), np.float32), False)


def graph(pairs, matches, distances=None):
    pairs = np.array(pairs, np.int64)
    matches = tuple(np.array(m, np.int64).reshape(-1, 2) for m in matches)
    if distances is None:
        distances = tuple(np.zeros(len(m)) for m in matches)
    n = int(pairs.max()) + 1
    selection = PairSelection(pairs, np.ones(len(pairs), bool), np.zeros(len(pairs), bool), np.zeros((n, n), np.int64),
                              True)
    counts = np.array([len(m) for m in matches], np.int64)
    return MatchGraph(pairs, counts, counts, matches, tuple(np.asarray(d, float) for d in distances), selection)


def test_chains_become_one_track_per_point():
    f = [features(5, k) for k in range(4)]
    # point A: features 0, 1, 2, 3 of images 0..3 through a chain; point B: feature 4 in images 0 and 2
    g = graph([[0, 1], [1, 2], [2, 3], [0, 2]], [[[0, 1]], [[1, 2]], [[2, 3]], [[4, 4]]])
    tracks = build_tracks(f, g)
    assert tracks.feature_index.T.tolist() == [[0, 1, 2, 3], [4, -1, 4, -1]]
    np.testing.assert_array_equal(tracks.observations[3, 0], f[3].keypoints[3])
    assert np.isnan(tracks.observations[1, 1]).all() and tracks.split_components == 0


def test_a_conflicting_merge_is_split_keeping_the_strongest_matches():
    f = [features(3, k) for k in range(3)]
    # image 0's features 0 and 1 both reach image 2's feature 0 through image 1: the component holds two
    # features of image 0; the weakest match (distance 0.9) is the one that must go
    g = graph([[0, 1], [1, 2], [0, 2]], [[[0, 0]], [[0, 0]], [[1, 0]]], [[0.1], [0.2], [0.9]])
    tracks = build_tracks(f, g)
    assert tracks.split_components == 1
    assert tracks.feature_index.T.tolist() == [[0, 0, 0]]
    seen = tracks.seen
    assert np.all(seen.sum(axis=0) >= 2)
    # one feature per image per track, always
    for image in range(3):
        ids = tracks.feature_index[image][seen[image]]
        assert len(set(ids.tolist())) == len(ids)


def test_merge_tracks_refuses_two_features_of_one_image():
    obs = np.zeros((3, 3, 2))
    fi = np.array([[0, -1, 5], [-1, 1, -1], [2, 2, -1]])
    obs[fi < 0] = np.nan
    t = FeatureTracks(obs, fi)
    merged = merge_tracks(t, np.array([0, 1]), np.array([2, 0]))
    # tracks 0 and 2 hold different features of image 0 (0 and 5): refused; tracks 1 and 0 share image 2's
    # feature 2 (the same observation): merged
    assert merged.feature_index.T.tolist() == [[0, 1, 2], [5, -1, -1]]


def random_elements(rng, count, images):
    """Elements owning 1-3 entries (image, feature) with distinct images."""
    sizes = rng.integers(1, 4, count)
    start = np.concatenate([[0], np.cumsum(sizes)])
    image = np.concatenate([rng.choice(images, s, replace=False) for s in sizes])
    feature = rng.integers(0, 3, len(image))
    return start, image, feature


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), count=st.integers(1, 30), images=st.integers(3, 6), edges=st.integers(0, 60))
def test_union_kernel_matches_the_python_reference(seed, count, images, edges):
    rng = np.random.default_rng(seed)
    start, image, feature = random_elements(rng, count, images)
    a, b = rng.integers(0, count, edges), rng.integers(0, count, edges)
    labels = union_without_conflicts(start, image, feature, a, b, images)
    kernel_sets = {frozenset(np.flatnonzero(labels == root).tolist()) for root in np.unique(labels)}
    reference_sets = {frozenset(s) for s in union_reference(start, image, feature, a, b, images)}
    assert kernel_sets == reference_sets
    for members in kernel_sets:  # no set holds two different features of one image
        seen = {}
        for e in members:
            for k in range(start[e], start[e + 1]):
                assert seen.setdefault(int(image[k]), int(feature[k])) == int(feature[k])
