"""Landmark estimation from a moving camera (Task 7 on the fusion engine): exactness, agreement with
fuse_recursive, flags, bad input."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kalmansfm import InvalidInputError, NotEnoughDataError, fuse_recursive
from kalmansfm.experiments.moving_camera import report_path
from kalmansfm.structure.fusion.landmark import estimate_landmarks, project
from kalmansfm.structure.points import PointStatus

F = 500.0


def _random_path(seed, K=6, L=8):
    rng = np.random.default_rng(seed)
    C = Rotation.from_rotvec(rng.normal(scale=0.05, size=(K - 1, 3))).as_matrix()
    b = rng.normal(scale=1.0, size=(K - 1, 3))
    X = np.empty((K, L, 3))
    X[0] = np.column_stack([rng.uniform(-5, 5, (L, 2)), rng.uniform(20, 30, L)])
    for k in range(K - 1):
        X[k + 1] = X[k] @ C[k].T - b[k]
    return X, C, b


@pytest.mark.parametrize("method", ["pairs", "batch", "recursive"])
@pytest.mark.parametrize("seed", range(3))
def test_noise_free_observations_give_the_truth(method, seed):
    X, C, b = _random_path(seed)
    est = estimate_landmarks(project(X, F), C, b, F, 1.0, method=method)
    np.testing.assert_allclose(est.estimates[1:], X[1:], rtol=1e-7, atol=1e-7)
    assert np.isnan(est.estimates[0]).all()  # one image: no depth
    assert est.converged[1:].all() and not est.converged[0].any()
    np.testing.assert_allclose(est.measurements[1:], X[1:], rtol=1e-9)
    assert (est.measurement_status[0] == PointStatus.TOO_FEW_VIEWS).all()  # no pair ends at image 0
    assert (est.measurement_status[1:] == PointStatus.OK).all()


def test_pairs_is_fuse_recursive_on_the_pair_triangulations():
    X, C, b = _random_path(4)
    rng = np.random.default_rng(1)
    obs = project(X, F) + rng.normal(scale=0.5, size=X.shape[:2] + (2,))
    est = estimate_landmarks(obs, C, b, F, 0.5, method="pairs")
    ref = fuse_recursive(est.measurements[1:], est.measurement_covariances[1:], C[1:], b[1:])
    np.testing.assert_allclose(est.estimates[1:], ref.estimates, rtol=1e-10)
    np.testing.assert_allclose(est.covariances[1:], ref.covariances, rtol=1e-8, atol=1e-14)


def test_batch_covariance_shrinks_and_errors_stay_within_bounds_on_the_report_path():
    path = report_path()
    rng = np.random.default_rng(3)
    obs = project(path.landmark, F)[:, None] + rng.normal(scale=2.0, size=(25, 1, 2))
    est = estimate_landmarks(obs, path.rotations, path.translations, F, 2.0, method="batch")
    std = est.standard_deviations[1:, 0]
    assert np.all(np.diff(np.linalg.norm(std, axis=1))[5:] < 0)  # more images, less uncertainty
    err = est.estimates[-1, 0] - path.landmark[-1]
    nees = err @ np.linalg.solve(est.covariances[-1, 0], err)
    assert nees < 16.27  # chi2(3) 99.9 % quantile


def test_missing_observations_are_skipped_and_flagged():
    X, C, b = _random_path(5, K=5, L=3)
    obs = project(X, F)
    obs[1, 0] = np.nan  # landmark 0 unseen in image 1: its pairs are (0, 2), (2, 3), (3, 4)
    obs[0, 2] = np.nan  # landmark 2 first seen in image 1
    for method in ("pairs", "batch", "recursive"):
        est = estimate_landmarks(obs, C, b, F, 1.0, method=method)
        assert PointStatus(est.measurement_status[1, 0]).label == "too_few_views"
        np.testing.assert_allclose(est.measurements[2, 0], X[2, 0], rtol=1e-9)  # the pair (0, 2)
        assert np.isnan(est.estimates[1, 0]).all() and not est.converged[1, 0]
        assert np.isnan(est.estimates[1, 2]).all() and not est.converged[1, 2]
        np.testing.assert_allclose(est.estimates[2, 0], X[2, 0], rtol=1e-7)  # images 0 and 2
        np.testing.assert_allclose(est.estimates[4], X[4], rtol=1e-7)


def test_a_landmark_on_the_baseline_is_nan_and_flagged_not_inf():
    # Camera moves along Z; a landmark straight ahead has no parallax.
    K = 4
    C = np.stack([np.eye(3)] * (K - 1))
    b = np.tile([0.0, 0.0, 1.0], (K - 1, 1))
    X = np.stack([np.array([[0.0, 0.0, 30.0 - k], [3.0, 2.0, 30.0 - k]]) for k in range(K)])
    for method in ("pairs", "batch", "recursive"):
        est = estimate_landmarks(project(X, F), C, b, F, 1.0, method=method)
        assert not np.isinf(est.estimates).any() and not np.isinf(est.covariances).any()
        assert not est.converged[:, 0].any() or np.isnan(est.covariances[:, 0]).all()
        np.testing.assert_allclose(est.estimates[-1, 1], X[-1, 1], rtol=1e-7)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"observations": np.zeros((1, 2, 2))}, NotEnoughDataError, ">= 2 images"),
        ({"observations": np.zeros((3, 2, 3))}, InvalidInputError, "observations must have shape"),
        ({"rotations": np.stack([np.eye(3)] * 3)}, InvalidInputError, r"rotations must have shape \(2, 3, 3\)"),
        ({"translations": np.zeros((2, 3))}, InvalidInputError, "translations\\[0\\] is zero"),
        ({"focal": 0.0}, InvalidInputError, "focal must be finite and > 0"),
        ({"pixel_std": -1.0}, InvalidInputError, "pixel_std must be finite and > 0"),
        ({"pixel_std": 0.0}, InvalidInputError, "pixel_std must be finite and > 0"),
        ({"method": "ekf"}, InvalidInputError, "method must be one of recursive, batch, pairs"),
    ],
)
def test_bad_input_raises_with_a_clear_message(kwargs, error, match):
    args = {
        "observations": np.array([[[10.0, 5.0]], [[11.0, 5.0]], [[12.0, 5.0]]]),
        "rotations": np.stack([np.eye(3)] * 2),
        "translations": np.tile([1.0, 0.0, 0.0], (2, 1)),
        "focal": F,
        "pixel_std": 1.0,
    }
    args.update(kwargs)
    with pytest.raises(error, match=match):
        estimate_landmarks(**args)
