"""Mutual nearest neighbours with the ratio test, on descriptors whose correspondence is known."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm.errors import InvalidInputError
from kalmansfm.features import matching
from kalmansfm.features.matching import match_descriptors, squared_distances


def unit(rows):
    return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def known_pair(seed, n=300, extra=100, noise=0.05):
    """b holds a permuted, perturbed copy of a's first n descriptors plus ``extra`` unrelated ones."""
    rng = np.random.default_rng(seed)
    a = unit(rng.normal(size=(n + extra, 128)))
    permutation = rng.permutation(n + extra)
    b = np.empty_like(a)
    b[: n] = unit(a[:n] + noise * rng.normal(size=(n, 128)))
    b[n:] = unit(rng.normal(size=(extra, 128)))
    return a, b[permutation], permutation


def test_recovers_a_known_correspondence():
    a, b, permutation = known_pair(0)
    found = match_descriptors(a, b, ratio=0.8)
    inverse = np.argsort(permutation)  # where row k of the unpermuted b went
    truth = {(k, int(inverse[k])) for k in range(300)}
    assert {tuple(p) for p in found.pairs.tolist()} == truth  # all 300, and nothing among the unrelated rows
    np.testing.assert_allclose(found.distances, np.linalg.norm(a[found.pairs[:, 0]] - b[found.pairs[:, 1]], axis=1),
                               atol=1e-5)


def test_ratio_test_refuses_an_ambiguous_match():
    rng = np.random.default_rng(1)
    a = unit(rng.normal(size=(3, 64)))
    twins = unit(a[0] + 0.01 * rng.normal(size=(2, 64)))
    # b: two near-identical copies of a[0] (ambiguous), a[1] itself, and nothing like a[2]
    b = np.concatenate([twins, a[1:2], unit(rng.normal(size=(1, 64)))])
    assert match_descriptors(a, b, ratio=0.8).pairs.tolist() == [[1, 2]]
    # mutual nearest neighbours alone (ratio 1) accept a[0] with its nearer twin
    nearer = int(np.argmin(np.linalg.norm(twins - a[0], axis=1)))
    assert [0, nearer] in match_descriptors(a, b, ratio=1.0).pairs.tolist()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(1, 60), m=st.integers(1, 60))
def test_symmetric_and_one_to_one(seed, n, m):
    rng = np.random.default_rng(seed)
    a, b = unit(rng.normal(size=(n, 8))), unit(rng.normal(size=(m, 8)))
    b[: min(n, m) // 2] = unit(a[: min(n, m) // 2] + 0.05 * rng.normal(size=(min(n, m) // 2, 8)))
    ab = match_descriptors(a, b, 0.9).pairs
    ba = match_descriptors(b, a, 0.9).pairs[:, ::-1]
    assert sorted(map(tuple, ab.tolist())) == sorted(map(tuple, ba.tolist()))
    assert len(set(ab[:, 0])) == len(ab) and len(set(ab[:, 1])) == len(ab)


def test_row_blocks_give_the_same_matches(monkeypatch):
    a, b, _ = known_pair(2, n=200, extra=50, noise=0.12)
    whole = match_descriptors(a, b, 0.9)
    monkeypatch.setattr(matching, "_ROW_BLOCK", 7)
    blocked = match_descriptors(a, b, 0.9)
    np.testing.assert_array_equal(whole.pairs, blocked.pairs)
    np.testing.assert_allclose(whole.distances, blocked.distances, rtol=1e-5)  # float32 products summed in blocks
    assert len(whole) > 100


def test_binary_descriptors_use_hamming_distance():
    rng = np.random.default_rng(3)
    a = rng.integers(0, 2, (50, 256)).astype(np.float32)
    b = a.copy()
    flip = rng.random(b.shape) < 0.05
    b[flip] = 1 - b[flip]
    d = squared_distances(a, b, binary=True)
    np.testing.assert_array_equal(d, (a[:, None, :] != b[None, :, :]).sum(axis=2))
    found = match_descriptors(a, b, 0.8, binary=True)
    assert found.pairs.tolist() == [[k, k] for k in range(50)]
    np.testing.assert_array_equal(found.distances, flip.sum(axis=1))


def test_empty_sets_and_bad_shapes():
    assert len(match_descriptors(np.zeros((0, 8)), np.ones((3, 8)))) == 0
    with pytest.raises(InvalidInputError, match="one D"):
        match_descriptors(np.zeros((2, 8)), np.zeros((2, 9)))
    with pytest.raises(InvalidInputError, match="ratio"):
        match_descriptors(np.zeros((2, 8)), np.zeros((2, 8)), ratio=1.5)
