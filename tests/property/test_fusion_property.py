"""Recursive Kalman fusion equals the closed-form normalised moved weighted mean."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from kalmansfm import fuse_closed_form, fuse_recursive


@st.composite
def fusion_problems(draw):
    K = draw(st.integers(1, 8))
    L = draw(st.integers(1, 3))
    d = draw(st.sampled_from([1, 3]))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    p = rng.normal(scale=draw(st.sampled_from([1e-3, 1.0, 100.0])), size=(K, L, d))
    A = rng.normal(size=(K, L, d, d))
    R = A @ np.swapaxes(A, -1, -2) + draw(st.sampled_from([1e-3, 1.0, 10.0])) * np.eye(d)
    if d == 3:
        C = Rotation.random(max(K - 1, 0), random_state=seed).as_matrix().reshape(K - 1, 3, 3)
    else:
        C = rng.choice([-1.0, 1.0], size=(K - 1, 1, 1))
    b = rng.normal(scale=5.0, size=(K - 1, d))
    missing = rng.random((K, L)) < draw(st.sampled_from([0.0, 0.3]))
    missing[0] = False
    p[missing] = np.nan
    return p, R, C, b


@settings(max_examples=150, deadline=None)
@given(fusion_problems())
def test_recursive_equals_closed_form(problem):
    p, R, C, b = problem
    a = fuse_recursive(p, R, C, b)
    c = fuse_closed_form(p, R, C, b)
    scale = np.nanmax(np.abs(p)) + np.abs(b).sum() + 1.0
    np.testing.assert_allclose(a.estimates, c.estimates, rtol=1e-8, atol=1e-9 * scale)
    np.testing.assert_allclose(a.covariances, c.covariances, rtol=1e-8, atol=1e-10 * np.abs(c.covariances).max())


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=30), st.floats(0.01, 100))
def test_equal_variances_give_the_running_mean(values, variance):
    r = fuse_recursive(values, [variance] * len(values))
    running = np.cumsum(values) / np.arange(1, len(values) + 1)
    np.testing.assert_allclose(r.estimates, running, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(r.covariances, variance / np.arange(1, len(values) + 1), rtol=1e-12)
