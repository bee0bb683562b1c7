"""KalmanFilter over random shape combinations and NaN patterns equals a textbook per-filter loop."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm.estimation.kalman import KalmanFilter


def _spd(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def _reference_step(x, P, F, H, Q, R, z):
    """One filter, one step: predict, then update with the measured components of z only."""
    x, P = F @ x, F @ P @ F.T + Q
    seen = ~np.isnan(z)
    if seen.any():
        Hs, Rs = H[seen], R[np.ix_(seen, seen)]
        S = Hs @ P @ Hs.T + Rs
        K = np.linalg.solve(S, Hs @ P).T
        x = x + K @ (z[seen] - Hs @ x)
        I_KH = np.eye(len(x)) - K @ Hs
        P = I_KH @ P @ I_KH.T + K @ Rs @ K.T
    return x, P


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    N=st.integers(1, 5),
    n=st.integers(1, 4),
    m=st.integers(1, 3),
    steps=st.integers(1, 6),
    per_filter_P=st.booleans(),
    per_filter_R=st.booleans(),
    p_missing=st.sampled_from([0.0, 0.3, 0.7, 1.0]),
)
def test_random_shapes_and_nan_patterns_match_the_textbook_loop(seed, N, n, m, steps, per_filter_P, per_filter_R,
                                                                p_missing):
    rng = np.random.default_rng(seed)
    F = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    H = rng.normal(size=(m, n))
    Q = _spd(rng, n, 0.1)
    P0 = np.stack([_spd(rng, n, 1.0) for _ in range(N)]) if per_filter_P else _spd(rng, n, 1.0)
    R = np.stack([_spd(rng, m, 0.5) for _ in range(N)]) if per_filter_R else _spd(rng, m, 0.5)
    x0 = rng.normal(size=(N, n))
    zs = rng.normal(size=(steps, N, m))
    zs[rng.random((steps, N, m)) < p_missing] = np.nan  # whole rows, single components, everything

    kf = KalmanFilter(x0, P0, F, H, Q, R)
    xs = np.empty((steps, N, n))
    Ps = np.empty((steps, N, n, n))
    for t in range(steps):
        kf.predict()
        kf.update(zs[t])
        xs[t], Ps[t] = kf.x, kf.P

    for i in range(N):
        x, P = x0[i], P0[i] if per_filter_P else P0
        Ri = R[i] if per_filter_R else R
        for t in range(steps):
            x, P = _reference_step(x, P, F, H, Q, Ri, zs[t, i])
            np.testing.assert_allclose(xs[t, i], x, rtol=1e-8, atol=1e-8 * (1 + np.abs(x).max()))
            np.testing.assert_allclose(Ps[t, i], P, rtol=1e-8, atol=1e-9 * np.abs(P).max())
    assert np.array_equal(Ps, np.swapaxes(Ps, -1, -2))
    assert (np.linalg.eigvalsh(Ps)[..., 0] > 0).all()
