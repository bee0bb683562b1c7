"""Golden covariance sequence of the constant-velocity tracker (000_3a84a3544ad80a84.txt, section 2.2).

With Q = diag(16,16,4,4), R = diag(4,4), Σ0 = diag(100,100,25,25) and a measurement
every frame, the report prints these posterior covariances (one frame late: the
values below are what its "Frame# 4" block shows, which is the posterior after
the first update).  Printed precision: 8 decimals for the first entries, the
plateau of Figure 1 ≈ 28.85.
"""

import numpy as np
import pytest

from kalmansfm import KalmanFilter
from kalmansfm.estimation.models import constant_velocity_2d

# (P[0,0], P[0,2], P[2,2]) after update 1, 2, ... as printed under Frame# 4, 5, ... of Point 1.
PRINTED = [
    (3.88965517, 0.68965517, 24.68965517),
    (3.67973495, 2.0320265, 15.79679735),
    (3.63252676, 1.63790392, 12.49632222),
    (3.59395662, 1.43477724, 11.42645575),
    (3.57772462, 1.3577455, 11.06088545),
    (3.57166684, 1.32982785, 10.93222514),
    (3.5694706, 1.31979359, 10.88638041),
    (3.56868012, 1.31619138, 10.86996516),
    (3.56839611, 1.31489815, 10.86407649),
    (3.5682941, 1.31443379, 10.86196254),
    (3.56825747, 1.31426704, 10.86120347),
]


def _posterior_sequence(n_filters: int, steps: int) -> list[np.ndarray]:
    model = constant_velocity_2d()
    rng = np.random.default_rng(7)
    kf = KalmanFilter(rng.normal(size=(n_filters, 4)), model.P0, model.F, model.H, model.Q, model.R)
    out = []
    for _ in range(steps):
        kf.predict()
        kf.update(rng.normal(size=(n_filters, 2)))
        out.append(kf.P.copy())
    return out


def test_posterior_covariances_match_the_printed_sequence():
    seq = _posterior_sequence(3, len(PRINTED))
    for k, (p00, p02, p22) in enumerate(PRINTED):
        P = seq[k][1]
        assert P[0, 0] == pytest.approx(p00, abs=6e-9)
        assert P[0, 2] == pytest.approx(p02, abs=6e-9)
        assert P[2, 2] == pytest.approx(p22, abs=6e-9)
        # x and y decouple into two identical blocks
        np.testing.assert_allclose(P[[1, 1, 3], [1, 3, 3]], P[[0, 0, 2], [0, 2, 2]], rtol=0, atol=1e-12)
        assert P[0, 1] == 0.0 and P[0, 3] == 0.0


def test_covariance_converges_to_the_figure_1_plateau():
    P = _posterior_sequence(2, 60)[-1][0]
    assert P[0, 0] == pytest.approx(3.568237, abs=5e-7)
    assert P[0, 2] == pytest.approx(1.314174, abs=5e-7)
    assert P[2, 2] == pytest.approx(10.860778, abs=5e-7)
    assert np.trace(P) == pytest.approx(28.858030, abs=5e-7)


def test_first_update_from_the_report_initial_state():
    """Point 1 starts at s0 = [115, 78, -3, 0]; the prediction for frame 3 is [112, 78, -3, 0]."""
    model = constant_velocity_2d()
    kf = KalmanFilter([115.0, 78.0, -3.0, 0.0], model.P0, model.F, model.H, model.Q, model.R)
    kf.predict()
    np.testing.assert_array_equal(kf.x_prior, [112.0, 78.0, -3.0, 0.0])
    np.testing.assert_allclose(np.diag(kf.P_prior), [141.0, 141.0, 29.0, 29.0])
    # A measurement at the prediction leaves the state there.
    kf.update([112.0, 78.0])
    np.testing.assert_allclose(kf.x, [112.0, 78.0, -3.0, 0.0])
    # Gain on position: (141) / (141 + 4)
    assert kf.K[0, 0] == pytest.approx(141.0 / 145.0)
