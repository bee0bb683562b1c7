"""A partially measured row updates exactly like the reduced model (the measured rows of H, block of R)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm import KalmanFilter
from kalmansfm.estimation.kalman import kalman_update
from kalmansfm.estimation.models import constant_velocity_2d


@st.composite
def partial_problems(draw):
    n = draw(st.integers(1, 5))
    m = draw(st.integers(2, 4))
    N = draw(st.integers(1, 6))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    A = rng.normal(size=(N, n, n))
    P = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(n)
    B = rng.normal(size=(m, m))
    R = B @ B.T + 0.1 * np.eye(m)
    H = rng.normal(size=(m, n))
    x = rng.normal(scale=draw(st.sampled_from([1e-2, 1.0, 1e3])), size=(N, n))
    z = rng.normal(scale=10.0, size=(N, m))
    z[rng.random((N, m)) < draw(st.sampled_from([0.2, 0.5, 0.8]))] = np.nan
    return x, P, z, H, R


@settings(max_examples=60, deadline=None)
@given(partial_problems())
def test_partial_update_equals_the_reduced_model_update(problem):
    x, P, z, H, R = problem
    full = kalman_update(x, P, z, H, R)
    for i in range(x.shape[0]):
        obs = ~np.isnan(z[i])
        if not obs.any():
            np.testing.assert_array_equal(full.x[i], x[i])
            np.testing.assert_array_equal(full.P[i], P[i])
            continue
        reduced = kalman_update(x[i:i + 1], P[i], z[i:i + 1, obs], H[obs], R[np.ix_(obs, obs)])
        np.testing.assert_allclose(full.x[i], reduced.x[0], rtol=1e-10, atol=1e-10 * np.abs(x).max())
        np.testing.assert_allclose(full.P[i], reduced.P, rtol=1e-10, atol=1e-12 * np.abs(P[i]).max())
        np.testing.assert_allclose(full.nis[i], reduced.nis[0], rtol=1e-9)
        np.testing.assert_allclose(full.log_likelihood[i], reduced.log_likelihood[0], rtol=1e-9, atol=1e-12)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.1, 0.5]))
def test_decoupled_filter_partial_rows_equal_single_axis_filters(seed, p_missing):
    """In the decoupled form, a row with only x (or y) measured equals a filter measuring that axis alone."""
    rng = np.random.default_rng(seed)
    m = constant_velocity_2d()
    N = 8
    x0 = rng.normal(scale=10, size=(N, 4))
    kf = KalmanFilter(x0, m.P0, m.F, m.H, m.Q, m.R)
    z = rng.normal(scale=10, size=(N, 2))
    z[rng.random((N, 2)) < p_missing] = np.nan
    kf.predict()
    kf.update(z)
    assert kf.decoupled
    for i in range(N):
        obs = ~np.isnan(z[i])
        single = KalmanFilter(x0[i], m.P0, m.F, m.H[obs] if obs.any() else m.H, m.Q,
                              m.R[np.ix_(obs, obs)] if obs.any() else m.R)
        single.predict()
        if obs.any():
            single.update(z[i, obs])
        np.testing.assert_allclose(kf.x[i], single.x, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(kf.P[i], single.P, rtol=1e-12, atol=1e-12)
