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
