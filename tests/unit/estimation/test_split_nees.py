"""Split-half NEES under errors correlated along each track: the prediction against fuse's measured statistic.

Points seen by 12 cameras on an arc, each track's pixel errors an AR(1) process over the views
with a known ρ per axis.  Each track's views are split alternately, each half fused alone with
the known cameras and the known σ (batch, no gate); the NEES of the difference against the
reported (independent-error) covariances is then compared with its distribution predicted from
ρ by :func:`split_covariances` and :func:`predict_nees`.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from kalmansfm.errors import InvalidInputError
from kalmansfm.estimation.noise_model import SerialCorrelation
from kalmansfm.estimation.split_nees import (
    nees_weights,
    predict_nees,
    split_covariances,
)
from kalmansfm.structure.fusion import fuse
from kalmansfm.structure.geometry.pinhole import CameraSet, project_each, project_points

VIEWS, POINTS, SIGMA = 12, 300, 0.5
CHI2_MEDIAN = float(stats.chi2.median(3))


def _arc_cameras() -> CameraSet:
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    angles = np.linspace(-0.4, 0.4, VIEWS)
    R = np.stack([np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]) for a in angles])
    centres = np.stack([5 * np.sin(angles), np.zeros(VIEWS), 5 - 5 * np.cos(angles)], axis=1)
    return CameraSet.from_pose(K, R, -np.einsum("vij,vj->vi", R, centres))


def _ar1_errors(rng: np.random.Generator, rho: float) -> np.ndarray:
    """(V, N, 2) errors, stationary AR(1) over the views with marginal σ, independent per track and axis."""
    e = np.empty((VIEWS, POINTS, 2))
    e[0] = rng.standard_normal((POINTS, 2))
    for v in range(1, VIEWS):
        e[v] = rho * e[v - 1] + np.sqrt(1 - rho**2) * rng.standard_normal((POINTS, 2))
    return SIGMA * e


def _measured_and_predicted(rho: float, seed: int):
    rng = np.random.default_rng(seed)
    cams = _arc_cameras()
    X = rng.uniform([-1, -1, 4], [1, 1, 6], size=(POINTS, 3))
    obs = project_points(cams, X).pixels + _ar1_errors(rng, rho)
    first = (np.arange(VIEWS) % 2 == 0)[:, None, None]
    halves = [np.where(mask, obs, np.nan) for mask in (first, ~first)]
    fused = [fuse(h, cams, method="batch", pixel_std=SIGMA, outlier_probability=1.0) for h in halves]
    assert all(f.reconstructed.all() for f in fused)
    d = fused[0].points - fused[1].points
    S = fused[0].point_covariances + fused[1].point_covariances
    measured = float(np.median(np.einsum("ni,ni->n", d, np.linalg.solve(S, d[..., None])[..., 0])))
    # the model: whitened Jacobians at the true points, each half's views, AR(1) with the known ρ
    _, _, J = project_each(cams.matrices[:, None], X[None])  # (V, N, 2, 3)
    J = np.transpose(J, (1, 0, 2, 3)) / SIGMA
    designs = [np.where(mask[:, 0, 0][None, :, None, None], J, np.nan) for mask in (first, ~first)]
    known = SerialCorrelation(np.full(2, rho), np.zeros(2), np.ones(2), np.zeros(2), POINTS)
    cov = split_covariances(designs[0], designs[1], np.arange(VIEWS), known)
    return measured, predict_nees(S, cov.difference, draws=200, seed=seed)


def test_alternating_halves_of_correlated_tracks_agree_better_than_their_covariances_say():
    measured, predicted = _measured_and_predicted(rho=0.8, seed=3)
    assert measured < 0.6 * CHI2_MEDIAN
    assert predicted.median < 0.6 * CHI2_MEDIAN
    assert abs(measured - predicted.median) < 3 * predicted.median_spread


def test_independent_errors_give_chi2_3_measured_and_predicted():
    measured, predicted = _measured_and_predicted(rho=0.0, seed=4)
    assert predicted.median == pytest.approx(CHI2_MEDIAN, abs=0.05)
    assert abs(measured - CHI2_MEDIAN) < 3 * predicted.median_spread
    assert predicted.share_within(float(stats.chi2.ppf(0.99, 3))) == pytest.approx(0.99, abs=0.003)


def test_split_covariances_of_the_mean_match_the_ar1_algebra():
    # the mean of positions {0, 2} against {1, 3}, one coordinate, Var = ρ^|lag|
    rho = 0.6
    first = np.array([1.0, np.nan, 1.0, np.nan]).reshape(1, 4, 1, 1)
    second = np.array([np.nan, 1.0, np.nan, 1.0]).reshape(1, 4, 1, 1)
    c = split_covariances(first, second, np.arange(4), SerialCorrelation(np.array([rho]), np.zeros(1), np.ones(1),
                                                                        np.zeros(1), 1))
    assert c.first[0, 0, 0] == pytest.approx((2 + 2 * rho**2) / 4)
    assert c.second[0, 0, 0] == pytest.approx((2 + 2 * rho**2) / 4)
    assert c.cross[0, 0, 0] == pytest.approx((rho + rho**3 + rho + rho) / 4)


def test_nees_weights_are_invariant_to_a_common_change_of_coordinates():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(5, 3, 3))
    S = A @ np.swapaxes(A, 1, 2) + np.eye(3)
    B = rng.normal(size=(5, 3, 3))
    C = B @ np.swapaxes(B, 1, 2)
    T = rng.normal(size=(3, 3)) + 3 * np.eye(3)
    moved = nees_weights(T @ S @ T.T, T @ C @ T.T)
    np.testing.assert_allclose(moved, nees_weights(S, C), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(nees_weights(S, C), np.sort(np.linalg.eigvals(np.linalg.solve(S, C)).real, axis=1),
                               rtol=1e-9)


def test_bad_inputs_are_named():
    eye = np.broadcast_to(np.eye(3), (2, 3, 3))
    with pytest.raises(InvalidInputError, match="assumed and actual"):
        nees_weights(eye, eye[:1])
    with pytest.raises(InvalidInputError, match="positive definite"):
        nees_weights(-eye, eye)
    with pytest.raises(InvalidInputError, match="draws"):
        predict_nees(eye, eye, draws=1)
    with pytest.raises(InvalidInputError, match="first_design"):
        split_covariances(np.ones((1, 2, 1, 1)), np.ones((1, 3, 1, 1)), np.arange(2), SerialCorrelation.independent(1))
