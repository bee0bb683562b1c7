"""The RTS smoother equals the closed-form batch least-squares (GLS) answer; fixed-lag equals truncated smoothing."""

import numpy as np
import pytest

from kalmansfm import InvalidInputError, KalmanFilter
from kalmansfm.estimation.smoothing import FilterRun, smooth
from kalmansfm.estimation.models import constant_velocity_2d


def random_system(rng, n=3, m=2):
    F = np.eye(n) + 0.3 * rng.normal(size=(n, n))
    H = rng.normal(size=(m, n))
    A = rng.normal(size=(n, n))
    Q = A @ A.T + 0.1 * np.eye(n)
    B = rng.normal(size=(m, m))
    R = B @ B.T + 0.2 * np.eye(m)
    C = rng.normal(size=(n, n))
    P0 = C @ C.T + np.eye(n)
    return F, H, Q, R, P0


def gls_smoother(x0, P0, zs, F, H, Q, R):
    """Posterior mean and block-diagonal covariance of x_0..x_T for ONE filter, by stacked weighted least squares.

    Unknowns x_0..x_T; whitened residuals: prior L0⁻¹(x_0 - x0), dynamics Lq⁻¹(x_t - F x_{t-1}),
    measurements of the observed components Lr⁻¹(z_t - H x_t).  Solved directly with lstsq.
    """
    T = zs.shape[0]
    n = x0.size
    rows, rhs = [], []

    def add(block_cols, target, cov):
        W = np.linalg.inv(np.linalg.cholesky(cov))
        row = np.zeros((target.size, (T + 1) * n))
        for t, M in block_cols:
            row[:, t * n:(t + 1) * n] = W @ M
        rows.append(row)
        rhs.append(W @ target)

    add([(0, np.eye(n))], x0, P0)
    for t in range(1, T + 1):
        add([(t, np.eye(n)), (t - 1, -F)], np.zeros(n), Q)
        z = zs[t - 1]
        obs = ~np.isnan(z)
        if obs.any():
            add([(t, H[obs])], z[obs], R[np.ix_(obs, obs)])
    A = np.vstack(rows)
    b = np.concatenate(rhs)
    mean = np.linalg.lstsq(A, b, rcond=None)[0].reshape(T + 1, n)
    cov = np.linalg.inv(A.T @ A)
    blocks = np.stack([cov[t * n:(t + 1) * n, t * n:(t + 1) * n] for t in range(T + 1)])
    return mean, blocks


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rts_smoother_equals_batch_least_squares(seed):
    rng = np.random.default_rng(seed)
    F, H, Q, R, P0 = random_system(rng)
    N, T = 4, 12
    x0 = rng.normal(size=(N, 3))
    zs = rng.normal(scale=3.0, size=(T, N, 2))
    zs[rng.random((T, N)) < 0.25] = np.nan          # missing rows
    zs[rng.random((T, N, 2)) < 0.15] = np.nan       # partial rows
    kf = KalmanFilter(x0, P0, F, H, Q, R)
    result = smooth(kf.run(zs))
    for i in range(N):
        mean, cov = gls_smoother(x0[i], P0, zs[:, i], F, H, Q, R)
        np.testing.assert_allclose(result.x_initial[i], mean[0], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(result.x[:, i], mean[1:], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(result.P_initial[i], cov[0], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(result.P[:, i], cov[1:], rtol=1e-9, atol=1e-9)


def test_smoother_on_the_decoupled_constant_velocity_model_equals_least_squares():
    m = constant_velocity_2d()
    rng = np.random.default_rng(5)
    N, T = 3, 15
    x0 = rng.normal(scale=20, size=(N, 4))
    zs = rng.normal(scale=20, size=(T, N, 2))
    zs[rng.random((T, N)) < 0.3] = np.nan
    kf = KalmanFilter(x0, m.P0, m.F, m.H, m.Q, m.R)
    assert kf.decoupled
    result = smooth(kf.run(zs))
    for i in range(N):
        mean, cov = gls_smoother(x0[i], m.P0, zs[:, i], m.F, m.H, m.Q, m.R)
        np.testing.assert_allclose(result.x[:, i], mean[1:], rtol=1e-9, atol=1e-8)
        np.testing.assert_allclose(result.P[:, i], cov[1:], rtol=1e-9, atol=1e-9)


def test_time_varying_transition_is_used_by_the_smoother():
    """Variable frame interval: per-step F and Q passed to run() reach the smoother."""
    rng = np.random.default_rng(3)
    T, N = 8, 2
    dts = rng.uniform(0.5, 2.0, size=T)
    Fs = np.stack([constant_velocity_2d(dt=dt).F for dt in dts])
    Qs = np.stack([constant_velocity_2d().Q * dt for dt in dts])
    m = constant_velocity_2d()
    x0 = rng.normal(size=(N, 4))
    zs = rng.normal(scale=5, size=(T, N, 2))
    result = smooth(KalmanFilter(x0, m.P0, m.F, m.H, m.Q, m.R).run(zs, F=Fs, Q=Qs))
    # The same run on the general (dense) code path, forced by a per-filter H.
    dense = KalmanFilter(x0, m.P0, m.F, np.broadcast_to(m.H, (N, 2, 4)), m.Q, m.R)
    assert not dense.decoupled
    ref = smooth(dense.run(zs, F=Fs, Q=Qs))
    np.testing.assert_allclose(result.x, ref.x, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(result.P, ref.P, rtol=1e-10, atol=1e-10)
    # and differs from smoothing with the constant model
    plain = smooth(KalmanFilter(x0, m.P0, m.F, m.H, m.Q, m.R).run(zs))
    assert np.abs(plain.x - result.x).max() > 1e-3


@pytest.mark.parametrize("lag", [0, 1, 3, 20])
def test_fixed_lag_equals_smoothing_the_truncated_run(lag):
    rng = np.random.default_rng(11)
    F, H, Q, R, P0 = random_system(rng)
    N, T = 3, 9
    x0 = rng.normal(size=(N, 3))
    zs = rng.normal(size=(T, N, 2))
    zs[rng.random((T, N)) < 0.2] = np.nan
    full_run = KalmanFilter(x0, P0, F, H, Q, R).run(zs)
    lagged = smooth(full_run, lag=lag)
    assert lagged.lag == lag
    for t in range(T):
        horizon = min(t + lag, T - 1)
        truncated = smooth(KalmanFilter(x0, P0, F, H, Q, R).run(zs[: horizon + 1]))
        np.testing.assert_allclose(lagged.x[t], truncated.x[t], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(lagged.P[t], truncated.P[t], rtol=1e-10, atol=1e-10)
    if lag == 0:
        np.testing.assert_allclose(lagged.x, full_run.x, rtol=1e-12, atol=1e-12)


def test_from_steps_rebuilds_the_run_of_an_online_filter():
    m = constant_velocity_2d()
    rng = np.random.default_rng(4)
    zs = rng.normal(size=(6, 5, 2))
    zs[2, 1] = np.nan
    x0 = rng.normal(size=(5, 4))
    batch = KalmanFilter(x0, m.P0, m.F, m.H, m.Q, m.R).run(zs)
    kf = KalmanFilter(x0, m.P0, m.F, m.H, m.Q, m.R)
    steps = {"x_prior": [], "P_prior": [], "x": [], "P": []}
    for z in zs:
        kf.predict()
        kf.update(z)
        for name in steps:
            steps[name].append(getattr(kf, name).copy())
    online = FilterRun.from_steps(x0, m.P0, F=m.F, **steps)
    np.testing.assert_array_equal(smooth(online).x, smooth(batch).x)
    np.testing.assert_array_equal(smooth(online).P, smooth(batch).P)


def test_smooth_rejects_bad_arguments():
    m = constant_velocity_2d()
    run = KalmanFilter(np.zeros((2, 4)), m.P0, m.F, m.H, m.Q, m.R).run(np.zeros((3, 2, 2)))
    with pytest.raises(InvalidInputError, match="lag"):
        smooth(run, lag=-1)
    with pytest.raises(InvalidInputError, match="FilterRun"):
        smooth("not a run")
    with pytest.raises(InvalidInputError, match=r"zs must have shape"):
        KalmanFilter(np.zeros((2, 4)), m.P0, m.F, m.H, m.Q, m.R).run(np.zeros((3, 5, 2)))
    with pytest.raises(InvalidInputError, match="one matrix per step"):
        KalmanFilter(np.zeros((2, 4)), m.P0, m.F, m.H, m.Q, m.R).run(np.zeros((3, 2, 2)), F=m.F)


def test_per_filter_transitions_are_smoothed_filter_by_filter():
    rng = np.random.default_rng(8)
    dts = np.array([0.5, 1.5])
    Fs = np.stack([constant_velocity_2d(dt=dt).F for dt in dts])
    m = constant_velocity_2d()
    x0 = rng.normal(size=(2, 4))
    zs = rng.normal(scale=3, size=(7, 2, 2))
    zs[3, 0] = np.nan
    run = KalmanFilter(x0, m.P0, Fs, m.H, m.Q, m.R).run(zs)
    assert run.F.shape == (7, 2, 4, 4)
    together = smooth(run)
    for i in range(2):
        mean, cov = gls_smoother(x0[i], m.P0, zs[:, i], Fs[i], m.H, m.Q, m.R)
        np.testing.assert_allclose(together.x[:, i], mean[1:], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(together.P[:, i], cov[1:], rtol=1e-9, atol=1e-9)
