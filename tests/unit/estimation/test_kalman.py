import numpy as np
import pytest

from kalmansfm import InvalidInputError, KalmanFilter, SingularCovarianceError
from kalmansfm.estimation.kalman import kalman_update
from kalmansfm.estimation.models import constant_velocity_2d, initial_state


def textbook_step(x, P, z, F, H, Q, R):
    """One predict + update of a single filter, written out independently (simple form)."""
    x = F @ x
    P = F @ P @ F.T + Q
    if z is None:
        return x, P
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    return x + K @ (z - H @ x), (np.eye(len(x)) - K @ H) @ P


def make(n=6, shared=True, seed=0):
    m = constant_velocity_2d()
    rng = np.random.default_rng(seed)
    x0 = rng.normal(scale=50, size=(n, 4))
    P0 = m.P0 if shared else np.broadcast_to(m.P0, (n, 4, 4)).copy()
    return KalmanFilter(x0, P0, m.F, m.H, m.Q, m.R), x0, m


def test_matches_textbook_filter_with_missing_rows():
    kf, x0, m = make()
    rng = np.random.default_rng(1)
    states = [(x0[i], m.P0) for i in range(6)]
    for step in range(15):
        z = rng.normal(scale=20, size=(6, 2))
        z[rng.random(6) < 0.3] = np.nan
        kf.predict()
        kf.update(z)
        for i in range(6):
            zi = None if np.isnan(z[i]).all() else z[i]
            states[i] = textbook_step(*states[i], zi, m.F, m.H, m.Q, m.R)
            np.testing.assert_allclose(kf.x[i], states[i][0], rtol=1e-12, atol=1e-9)
            np.testing.assert_allclose(kf.P[i], states[i][1], rtol=1e-12, atol=1e-10)


def test_shared_and_per_filter_covariances_give_identical_results():
    a, _, _ = make(shared=True)
    b, _, _ = make(shared=False)
    rng = np.random.default_rng(2)
    for step in range(20):
        z = rng.normal(size=(6, 2))
        if step in (4, 9):
            z[2] = np.nan
        for kf in (a, b):
            kf.predict()
            kf.update(z)
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.P, b.P)


def test_covariance_stays_shared_while_every_filter_is_measured():
    kf, _, _ = make(n=1000)
    for _ in range(5):
        kf.predict()
        kf.update(np.zeros((1000, 2)))
    assert kf.shared_covariance
    assert kf.P.shape == (1000, 4, 4)
    assert not kf.P.flags.writeable  # a broadcast view, not 1000 copies
    kf.predict()
    z = np.zeros((1000, 2))
    z[3] = np.nan
    kf.update(z)
    assert not kf.shared_covariance
    assert kf.P[3, 0, 0] > kf.P[4, 0, 0]


def test_missing_row_only_predicts():
    kf, _, _ = make(n=2)
    kf.predict()
    kf.update(np.array([[1.0, 1.0], [np.nan, np.nan]]))
    np.testing.assert_array_equal(kf.x[1], kf.x_prior[1])
    np.testing.assert_array_equal(kf.P[1], kf.P_prior[1])
    assert np.isnan(kf.nis[1]) and np.isfinite(kf.nis[0])
    np.testing.assert_array_equal(kf.K[1], 0.0)


def test_partial_measurement_equals_reduced_model_update():
    m = constant_velocity_2d()
    x0 = np.array([[10.0, 20.0, 1.0, -1.0]])
    full = KalmanFilter(x0, m.P0, m.F, m.H, m.Q, m.R)
    reduced = KalmanFilter(x0, m.P0, m.F, m.H[1:], m.Q, m.R[1:, 1:])
    for kf in (full, reduced):
        kf.predict()
    full.update(np.array([[np.nan, 25.0]]))
    reduced.update(np.array([[25.0]]))
    np.testing.assert_allclose(full.x, reduced.x, rtol=1e-14)
    np.testing.assert_allclose(full.P, reduced.P, rtol=1e-14)
    assert np.isnan(full.y[0, 0]) and full.y[0, 1] == pytest.approx(reduced.y[0, 0])


def test_single_filter_shapes_and_likelihood_from_the_prior():
    m = constant_velocity_2d()
    kf = KalmanFilter([0.0, 0.0, 1.0, 0.0], m.P0, m.F, m.H, m.Q, m.R)
    kf.predict()
    prior_x, prior_P = kf.x_prior.copy(), kf.P_prior.copy()
    z = np.array([3.0, -2.0])
    kf.update(z)
    assert kf.x.shape == (4,) and kf.P.shape == (4, 4) and kf.K.shape == (4, 2)
    S = m.H @ prior_P @ m.H.T + m.R
    y = z - m.H @ prior_x
    d2 = y @ np.linalg.solve(S, y)
    assert kf.nis == pytest.approx(d2)
    assert kf.log_likelihood == pytest.approx(-0.5 * (d2 + np.log(np.linalg.det(2 * np.pi * S))))


def test_per_filter_measurement_noise_and_control_input():
    m = constant_velocity_2d()
    R = np.stack([np.eye(2), 100 * np.eye(2)])
    kf = KalmanFilter(np.zeros((2, 4)), m.P0, m.F, m.H, m.Q, R)
    kf.predict(u=[1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(kf.x_prior[:, 0], [1.0, 1.0])
    kf.update(np.full((2, 2), 10.0))
    assert abs(kf.x[0, 0] - 10) < abs(kf.x[1, 0] - 10)  # the precise sensor pulls harder


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        ({"x": np.zeros((3, 5))}, "F must have shape (5, 5)"),
        ({"P": -np.eye(4)}, "P must be positive definite"),
        ({"P": np.zeros((2, 4, 4))}, "P must have shape (3, 4, 4)"),
        ({"R": np.eye(3)}, "R must have shape (3, 2, 2)"),
        ({"R": np.array([[1.0, 2.0], [0.0, 1.0]])}, "R must be symmetric"),
        ({"H": np.eye(2, 3)}, "H must have shape (m, 4)"),
        ({"x": [[1.0, np.inf, 0, 0]] * 3}, "x must be finite"),
        ({"x": "abc"}, "x must be numeric"),
    ],
)
def test_bad_construction_names_the_argument(kwargs, fragment):
    m = constant_velocity_2d()
    args = {"x": np.zeros((3, 4)), "P": m.P0, "F": m.F, "H": m.H, "Q": m.Q, "R": m.R, **kwargs}
    with pytest.raises(InvalidInputError) as err:
        KalmanFilter(**args)
    assert fragment in str(err.value)


def test_bad_measurements_are_rejected():
    kf, _, _ = make(n=3)
    kf.predict()
    with pytest.raises(InvalidInputError, match=r"z must have shape \(3, 2\)"):
        kf.update(np.zeros((2, 2)))
    with pytest.raises(InvalidInputError, match="infinity"):
        kf.update(np.full((3, 2), np.inf))


def test_singular_innovation_covariance_raises_a_clear_error():
    with pytest.raises(SingularCovarianceError, match="innovation covariance"):
        kalman_update(np.zeros((1, 2)), np.zeros((2, 2)), np.zeros((1, 2)), np.eye(2), np.zeros((2, 2)))


def test_initial_state_from_the_report_table():
    first = np.array([[118, 78], [117, 89], [122, 158], [232, 92], [254, 80], [273, 79]])
    nxt = np.array([[115, 78], [114, 89], [120, 158], [229, 91], [251, 80], [270, 78]])
    expected = [[115, 78, -3, 0], [114, 89, -3, 0], [120, 158, -2, 0], [229, 91, -3, -1], [251, 80, -3, 0],
                [270, 78, -3, -1]]
    np.testing.assert_array_equal(initial_state(first, nxt), expected)
    with pytest.raises(InvalidInputError, match="positions_next"):
        initial_state(first, nxt[:2])
