import numpy as np
import pytest

from kalmansfm import InvalidInputError
from kalmansfm.structure import subspace_angle, truncated_svd


def low_rank_plus_noise(rng, m=300, n=4000, noise=1.0):
    signal = (rng.normal(size=(m, 3)) * [5.0, 3.0, 2.0]) @ rng.normal(size=(3, n)) * 20
    offsets = rng.uniform(100, 300, size=m)
    return signal + noise * rng.normal(size=(m, n)) + offsets[:, None], offsets


def test_randomized_equals_lapack_subspace_with_implicit_centring():
    rng = np.random.default_rng(0)
    w, offsets = low_rank_plus_noise(rng)
    fast = truncated_svd(w, 3, row_offsets=offsets, method="randomized", tol=1e-10)
    exact = np.linalg.svd(w - offsets[:, None], full_matrices=False)
    assert fast.method == "randomized" and fast.angle_bound <= 1e-10
    assert subspace_angle(fast.u, exact.U[:, :3]) < 1e-9
    assert subspace_angle(fast.vt.T, exact.Vh[:3].T) < 1e-9
    np.testing.assert_allclose(fast.s, exact.S[:3], rtol=1e-12)
    # the certified bound really bounds the angle
    assert subspace_angle(fast.u, exact.U[:, :3]) <= max(fast.angle_bound, 1e-13)


def test_lapack_path_and_extra_singular_values():
    rng = np.random.default_rng(1)
    w, _ = low_rank_plus_noise(rng, m=40, n=60)
    result = truncated_svd(w, 3)
    s = np.linalg.svd(w, compute_uv=False)
    assert result.method == "lapack"
    np.testing.assert_allclose(np.concatenate([result.s, result.extra_singular_values]), s)


def test_subspace_angle_resolves_tiny_angles():
    a = np.eye(4)[:, :2]
    b = a.copy()
    b[2, 0] = 1e-11
    assert subspace_angle(a, b) == pytest.approx(1e-11, rel=1e-6)


@pytest.mark.parametrize("kwargs", [{"rank": 0}, {"method": "magic"}, {"row_offsets": np.zeros(3)}])
def test_bad_arguments(kwargs):
    with pytest.raises(InvalidInputError):
        truncated_svd(np.ones((10, 20)), **{"rank": 3, **kwargs})


def test_randomized_certificate_bounds_the_true_angle_at_each_stopping_point():
    rng = np.random.default_rng(3)
    w, offsets = low_rank_plus_noise(rng, m=200, n=3000, noise=3.0)
    exact = np.linalg.svd(w - offsets[:, None], full_matrices=False)
    found = {}
    for passes in (3, 5, 7):
        fast = truncated_svd(w, 3, row_offsets=offsets, method="randomized", tol=0.0, max_passes=passes)
        assert fast.passes == passes and fast.certified
        angle = subspace_angle(fast.u, exact.U[:, :3])
        assert angle <= fast.angle_bound * (1 + 1e-6) + 1e-14
        found[passes] = (angle, fast.angle_bound)
    # the bound is tight, not just valid: within a factor 2 of the angle after 3 products
    angle, bound = found[3]
    assert bound > 1e-9 and angle > 0.5 * bound


def test_randomized_on_an_exactly_rank_two_matrix_stops_early():
    rng = np.random.default_rng(4)
    w = rng.normal(size=(150, 2)) @ rng.normal(size=(2, 2500))
    fast = truncated_svd(w, 3, method="randomized")
    assert fast.passes <= 5
    np.testing.assert_allclose(fast.s[:2], np.linalg.svd(w, compute_uv=False)[:2], rtol=1e-12)
    assert fast.s[2] < 1e-9 * fast.s[0]
