"""Two-view midpoint triangulation: exactness, analytic Jacobian, first-order covariance, degenerate input."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kalmansfm import InvalidInputError
from kalmansfm.structure.points import PointStatus
from kalmansfm.structure.geometry.triangulation import triangulate_midpoint

F = 500.0


def _scene(seed, L=20):
    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(rng.normal(scale=0.1, size=3)).as_matrix()
    b = rng.normal(size=3)
    X_left = np.column_stack([rng.uniform(-10, 10, (L, 2)), rng.uniform(15, 40, L)])
    X_right = X_left @ R.T - b
    return R, b, X_left, X_right


def _project(X):
    return F * X[:, :2] / X[:, 2:]


@pytest.mark.parametrize("seed", range(5))
def test_noise_free_points_are_recovered_exactly_in_the_right_frame(seed):
    R, b, X_left, X_right = _scene(seed)
    r = triangulate_midpoint(_project(X_left), _project(X_right), R, b, F)
    np.testing.assert_allclose(r.points, X_right, rtol=1e-10, atol=1e-10)
    assert np.all(r.status == PointStatus.OK)
    np.testing.assert_allclose(r.depth_scale * F, X_right[:, 2], rtol=1e-10)
    assert np.all(r.covariances == 0.0)  # no noise given


@pytest.mark.parametrize("seed", range(3))
def test_analytic_jacobian_matches_central_differences(seed):
    R, b, X_left, X_right = _scene(seed)
    rng = np.random.default_rng(100 + seed)
    u = np.concatenate([_project(X_left), _project(X_right)], axis=1) + rng.normal(scale=2.0, size=(20, 4))
    J = triangulate_midpoint(u[:, :2], u[:, 2:], R, b, F).jacobians
    h = 1e-3
    for c in range(4):
        up, um = u.copy(), u.copy()
        up[:, c] += h
        um[:, c] -= h
        fd = (
            triangulate_midpoint(up[:, :2], up[:, 2:], R, b, F).points
            - triangulate_midpoint(um[:, :2], um[:, 2:], R, b, F).points
        ) / (2 * h)
        np.testing.assert_allclose(J[:, :, c], fd, rtol=1e-6, atol=1e-9 * np.abs(fd).max())


def test_covariance_is_eq34_with_per_coordinate_variances():
    R, b, X_left, X_right = _scene(7)
    sig = np.array([0.5, 1.0, 2.0, 3.0])
    r = triangulate_midpoint(_project(X_left), _project(X_right), R, b, F, pixel_std=sig)
    expected = sum(sig[c] ** 2 * np.einsum("li,lj->lij", r.jacobians[:, :, c], r.jacobians[:, :, c]) for c in range(4))
    np.testing.assert_allclose(r.covariances, expected, rtol=1e-12)


def test_first_order_covariance_matches_monte_carlo_at_small_noise():
    R, b, X_left, X_right = _scene(3, L=1)
    u = np.concatenate([_project(X_left), _project(X_right)], axis=1)[0]
    sigma = 0.05
    rng = np.random.default_rng(0)
    n = 20000
    noisy = u + rng.normal(scale=sigma, size=(n, 4))
    p = triangulate_midpoint(noisy[:, :2], noisy[:, 2:], R, b, F).points
    predicted = triangulate_midpoint(u[:2], u[2:], R, b, F, pixel_std=sigma).covariances
    sample = np.cov(p.T)
    # Sample variances of 20000 Gaussian draws are within ~3 % (sd sqrt(2/n) = 1 %); allow 5 %.
    np.testing.assert_allclose(np.diag(sample), np.diag(predicted), rtol=0.05)


def test_readme_style_example_sideways_motion():
    b = np.array([1.0, 0.0, 0.0])
    X = np.array([0.0, 0.0, 10.0])
    r = triangulate_midpoint(F * X[:2] / X[2], F * (X - b)[:2] / (X - b)[2], np.eye(3), b, F, pixel_std=1.0)
    np.testing.assert_allclose(r.points, [-1.0, 0.0, 10.0], atol=1e-12)
    # depth variance: Z^2/(f b) each image contributes (Z^2 / (f b))^2 σ^2 -> sqrt(2) * 100/500
    assert r.standard_deviations[2] == pytest.approx(np.sqrt(2) * 100 / 500, rel=1e-9)


def test_zero_baseline_raises():
    with pytest.raises(InvalidInputError, match="translation is zero"):
        triangulate_midpoint([10.0, 5.0], [10.0, 5.0], np.eye(3), np.zeros(3), F)


@pytest.mark.parametrize("focal", [0.0, -500.0, np.nan, np.inf])
def test_bad_focal_raises(focal):
    with pytest.raises(InvalidInputError, match="focal"):
        triangulate_midpoint([10.0, 5.0], [12.0, 5.0], np.eye(3), [1.0, 0, 0], focal)


def test_negative_noise_raises():
    with pytest.raises(InvalidInputError, match="pixel_std must be >= 0"):
        triangulate_midpoint([10.0, 5.0], [12.0, 5.0], np.eye(3), [1.0, 0, 0], F, pixel_std=[1, 1, -1, 1])


def test_parallel_rays_single_landmark_raises():
    # The landmark straight along the baseline: both rays are the baseline direction.
    with pytest.raises(InvalidInputError, match="parallel"):
        triangulate_midpoint([0.0, 0.0], [0.0, 0.0], np.eye(3), [0.0, 0.0, 1.0], F)


def test_parallel_rays_among_many_give_nan_and_a_flag_never_inf():
    left = np.array([[0.0, 0.0], [100.0, 50.0]])
    right = np.array([[0.0, 0.0], [100.0 * 20 / 19, 50.0 * 20 / 19]])  # second: Z 20 -> 19
    r = triangulate_midpoint(left, right, np.eye(3), [0.0, 0.0, 1.0], F, pixel_std=1.0)
    # the package's one point status: parallel rays are a degenerate point
    assert [PointStatus(s).label for s in r.status] == ["degenerate", "ok"]
    assert np.isnan(r.points[0]).all() and np.isnan(r.covariances[0]).all()
    assert not np.isinf(r.points).any() and not np.isinf(r.covariances).any()
    np.testing.assert_allclose(r.points[1], [4.0, 2.0, 19.0], rtol=1e-9)
    assert r.valid.tolist() == [False, True]


def test_point_behind_the_camera_is_flagged():
    # Rays diverging backwards: image points that imply negative depth.
    r = triangulate_midpoint(np.array([[50.0, 0.0]]), np.array([[60.0, 0.0]]), np.eye(3), [1.0, 0.0, 0.0], F)
    assert PointStatus(r.status[0]).label == "behind_camera"
    assert r.points[0, 2] < 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"left_points": np.zeros((3, 3))}, "left_points must have shape"),
        ({"right_points": np.zeros((2, 2))}, "right_points must have the shape"),
        ({"rotation": np.eye(2)}, r"rotation must have shape \(3, 3\)"),
        ({"rotation": 2 * np.eye(3)}, "rotation matrix"),
        ({"translation": [1.0, 0.0]}, r"translation must have shape \(3,\)"),
        ({"left_points": np.array([[np.nan, 0.0]])}, "left_points must be finite"),
        ({"pixel_std": np.ones(3)}, "pixel_std must be a scalar"),
    ],
)
def test_bad_shapes_and_values_name_the_argument(kwargs, match):
    args = {
        "left_points": np.array([[10.0, 5.0]]),
        "right_points": np.array([[12.0, 5.0]]),
        "rotation": np.eye(3),
        "translation": np.array([1.0, 0.0, 0.0]),
        "focal": F,
    }
    args.update(kwargs)
    with pytest.raises(InvalidInputError, match=match):
        triangulate_midpoint(**args)
