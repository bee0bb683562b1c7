"""Numerical health of the KalmanFilter over 10⁶ filter-steps, at extreme scales, and with singular S.

10⁶ steps are run as 1000 filters × 1000 steps: the batched filter does the same
arithmetic for every filter of the batch, so one long run of a batch is 10⁶
independent predict/update steps, each with its own measurement pattern (the
covariances are per filter as soon as the patterns differ).  One filter for 10⁶
steps would take minutes in a Python loop; the 1000 steps still reach the
filter's steady state and, through random outages, its growth far away from it.

Both arithmetic paths are covered: the general dense path (forced by a process
noise that couples x with y) and the decoupled constant-velocity fast path.
"""

from __future__ import annotations

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError, SingularCovarianceError
from kalmansfm.estimation.kalman import KalmanFilter, kalman_update
from kalmansfm.estimation.models import constant_velocity_2d

# Small process noise makes P shrink towards a badly conditioned steady state: the
# regime where the simple update P = (I - KH) P loses symmetry and definiteness.
MODEL = constant_velocity_2d(position_noise_std=1e-3, velocity_noise_std=1e-3, measurement_noise_std=1.0)


def _process_noise(path: str) -> np.ndarray:
    Q = MODEL.Q.copy()
    if path == "general":
        Q[0, 1] = Q[1, 0] = 0.5 * np.sqrt(Q[0, 0] * Q[1, 1])  # couples x and y: no fast path
    return Q


def _measurements(rng: np.random.Generator, steps: int, filters: int) -> np.ndarray:
    """Noisy positions of constant-velocity targets; 30 % rows missing, 5 % half rows, 1 % long outages."""
    truth = np.zeros((filters, 4))
    truth[:, 2:] = rng.normal(0.0, 2.0, (filters, 2))
    zs = np.empty((steps, filters, 2))
    for t in range(steps):
        truth = truth @ MODEL.F.T
        zs[t] = truth[:, :2] + rng.normal(0.0, 1.0, (filters, 2))
    zs[rng.random((steps, filters)) < 0.30] = np.nan
    zs[rng.random((steps, filters)) < 0.05, 1] = np.nan
    for f in rng.choice(filters, filters // 100, replace=False):
        start = rng.integers(0, steps - 100)
        zs[start : start + 100, f] = np.nan  # 100 steps without a measurement
    return zs


@pytest.mark.parametrize("path", ["general", "decoupled"])
def test_million_steps_keep_every_covariance_symmetric_and_positive_definite(path):
    filters, steps = 1000, 1000
    rng = np.random.default_rng(7)
    zs = _measurements(rng, steps, filters)
    kf = KalmanFilter(np.zeros((filters, 4)), MODEL.P0, MODEL.F, MODEL.H, _process_noise(path), MODEL.R)
    worst_ratio = np.inf
    for t in range(steps):
        kf.predict()
        kf.update(zs[t])
        P = kf.P
        assert np.array_equal(P, np.swapaxes(P, -1, -2)), f"P not exactly symmetric at step {t}"
        eig = np.linalg.eigvalsh(P)
        worst_ratio = min(worst_ratio, float((eig[:, 0] / eig[:, -1]).min()))
        assert eig[:, 0].min() > 0, f"P not positive definite at step {t}"
    assert kf.decoupled == (path == "decoupled")
    assert np.isfinite(kf.x).all()
    # the smallest eigenvalue is far from rounding noise (measured: 1.4e-6 relative on both paths)
    assert worst_ratio > 1e-9


@pytest.mark.parametrize("path", ["general", "decoupled"])
@pytest.mark.parametrize("scale", [1e6, 1e-6])
def test_pixels_times_a_million_or_a_millionth_give_the_same_answer_up_to_scale(path, scale):
    """x, P, Q, R and z scaled by s (covariances by s²): x/s and P/s² agree to 1e-12 of their size.

    Powers of ten are not exact in binary, so the answers differ by rounding only
    (measured: 1e-14 of the largest entry after 300 steps).
    """
    filters, steps = 100, 300
    zs = _measurements(np.random.default_rng(3), steps, filters)
    Q = _process_noise(path)

    def run(s: float):
        kf = KalmanFilter(np.zeros((filters, 4)), MODEL.P0 * s**2, MODEL.F, MODEL.H, Q * s**2, MODEL.R * s**2)
        result = kf.run(zs * s)
        return result.x / s, result.P / s**2, result.nis

    x1, P1, nis1 = run(1.0)
    xs, Ps, niss = run(scale)
    np.testing.assert_allclose(xs, x1, rtol=0, atol=1e-12 * np.abs(x1).max())
    size = np.abs(P1).max(axis=(-2, -1), keepdims=True)
    assert np.all(np.abs(Ps - P1) <= 1e-12 * size)
    np.testing.assert_allclose(niss, nis1, rtol=1e-9, atol=1e-12, equal_nan=True)  # NIS has no unit


def test_a_singular_innovation_covariance_raises_a_clear_error_general_path():
    # P = 0 and R = 0: S = H P Hᵀ + R = 0
    with pytest.raises(SingularCovarianceError, match=r"innovation covariance.*not positive definite"):
        kalman_update(np.zeros((3, 4)), np.zeros((4, 4)), np.ones((3, 2)), MODEL.H, np.zeros((2, 2)))
    # rank one: two measurement rows of the same state, no noise
    H = np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0]])
    with pytest.raises(SingularCovarianceError, match="check that R is positive definite"):
        kalman_update(np.zeros((2, 4)), np.eye(4), np.ones((2, 2)), H, np.zeros((2, 2)))
    # the same with per-filter covariances and a missing row
    P = np.broadcast_to(np.eye(4), (2, 4, 4)).copy()
    with pytest.raises(SingularCovarianceError):
        kalman_update(np.zeros((2, 4)), P, np.array([[1.0, 1.0], [np.nan, np.nan]]), H, np.zeros((2, 2)))


@pytest.mark.filterwarnings("error::RuntimeWarning")  # the error alone, no NumPy warning before it
@pytest.mark.parametrize("shared", [True, False])
def test_a_singular_innovation_covariance_raises_a_clear_error_decoupled_path(shared, kernel_path):
    """Reachable only with zero noise and a collapsed covariance, which the class refuses up front:
    both are set behind its back, and the decoupled step (kernel or NumPy twin) reports it."""
    N = 5
    kf = KalmanFilter(np.zeros((N, 4)), MODEL.P0, MODEL.F, MODEL.H, MODEL.Q, MODEL.R)
    X = kf._engine.state[0]
    kf._engine._fast = (X, np.zeros((1, 3)) if shared else np.zeros((1, 3, N)))
    kf.R = np.zeros((2, 2))
    with pytest.raises(SingularCovarianceError, match=r"S = H P Hᵀ \+ R is not positive definite"):
        kf.update(np.ones((N, 2)))


@pytest.mark.parametrize("path", ["general", "decoupled"])
def test_the_filter_refuses_noise_that_would_make_S_singular(path):
    """The class checks R (and P) up front, so S = H P Hᵀ + R > 0 cannot fail later."""
    with pytest.raises(InvalidInputError, match="R must be positive definite"):
        KalmanFilter(np.zeros((2, 4)), MODEL.P0, MODEL.F, MODEL.H, _process_noise(path), np.zeros((2, 2)))
    kf = KalmanFilter(np.zeros((2, 4)), MODEL.P0, MODEL.F, MODEL.H, _process_noise(path), MODEL.R)
    kf.predict()
    with pytest.raises(InvalidInputError, match="R must be positive definite"):
        kf.update(np.ones((2, 2)), R=np.array([[1.0, 1.0], [1.0, 1.0]]))
    # a scale whose square underflows to 0 is refused the same way, not turned into a singular S
    with pytest.raises(InvalidInputError, match="positive definite"):
        KalmanFilter(np.zeros((2, 4)), MODEL.P0 * 1e-340, MODEL.F, MODEL.H, _process_noise(path), MODEL.R * 1e-340)
