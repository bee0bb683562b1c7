"""Guided matching: the predicted position and its covariance, the gate, and the descriptor test inside it."""

import numpy as np
import pytest

from kalmansfm.features import ImageFeatures
from kalmansfm.mapping import Prediction, guided_search, pose_from_correspondences, predict_points
from kalmansfm.structure.geometry.rotation import rotation_exp

K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])


def project(X, R, t):
    h = (X @ R.T + t) @ K.T
    return h[:, :2] / h[:, 2:]


def test_predicted_covariance_is_the_projected_point_and_camera_covariance():
    rng = np.random.default_rng(0)
    X = rng.uniform(-1, 1, (5, 3)) + [0, 0, 6]
    R = rotation_exp(np.array([0.1, -0.2, 0.05]))
    C = np.array([0.3, -0.1, -0.5])
    t = -R @ C
    A = rng.normal(size=(5, 3, 3)) * 1e-3
    cov_X = A @ A.transpose(0, 2, 1)
    B = rng.normal(size=(6, 6)) * 1e-3
    cov_c = B @ B.T
    p = predict_points(X, cov_X, R, t, K, cov_c, pixel_std=0.4)
    np.testing.assert_allclose(p.pixels, project(X, R, t), atol=1e-9)
    # numerical Jacobians: the point, the camera's small rotation (on the left) and its centre
    eps = 1e-6
    for k in range(5):
        J_X = np.stack([(project(X[k:k + 1] + eps * e, R, t) - project(X[k:k + 1] - eps * e, R, t))[0] / (2 * eps)
                        for e in np.eye(3)], axis=1)
        columns = []
        for e in np.eye(3):
            Rp, Rm = rotation_exp(eps * e) @ R, rotation_exp(-eps * e) @ R
            columns.append((project(X[k:k + 1], Rp, -Rp @ C) - project(X[k:k + 1], Rm, -Rm @ C))[0] / (2 * eps))
        for e in np.eye(3):
            columns.append((project(X[k:k + 1], R, -R @ (C + eps * e)) - project(X[k:k + 1], R, -R @ (C - eps * e)))[0]
                           / (2 * eps))
        J_c = np.stack(columns, axis=1)
        expected = J_X @ cov_X[k] @ J_X.T + J_c @ cov_c @ J_c.T + 0.16 * np.eye(2)
        np.testing.assert_allclose(p.covariances[k], expected, rtol=1e-5)
    assert np.all(p.depths > 0)


def view_with(keypoints, descriptors):
    z = np.zeros(len(keypoints), np.float32)
    return ImageFeatures(np.asarray(keypoints, float), z, z, z, np.asarray(descriptors, np.float32), False)


def gate(**kwargs):
    return dict(dict(gate_chi2=9.21, gate_floor_px=1.0, max_gate_px=10.0, ratio=0.8, max_distance=0.9), **kwargs)


def test_a_planted_feature_is_found_inside_the_gate_and_refused_outside():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(3, 32))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # the prediction's covariance is elongated along x: 2 px² along x, 0.1 px² along y
    S = np.array([[[4.0, 0.0], [0.0, 0.1]]])
    prediction = Prediction(np.array([[100.0, 100.0]]), S, np.ones(1))
    inside = view_with([[104.0, 100.0]], d[:1])          # 2σ along x: inside the 99 % gate (χ² 4 < 9.21)
    across = view_with([[100.0, 103.0]], d[:1])          # 3 px along y is 9.5σ: outside, though nearer
    m = guided_search(prediction, d[:1], inside, **gate())
    assert m.predictions.tolist() == [0] and m.features.tolist() == [0] and m.mahalanobis[0] == pytest.approx(4.0)
    assert len(guided_search(prediction, d[:1], across, **gate())) == 0
    # the pixel floor admits a feature within 1 px whatever the covariance says
    near = view_with([[100.0, 100.8]], d[:1])
    assert len(guided_search(prediction, d[:1], near, **gate())) == 1
    # a feature inside the gate whose descriptor is unlike the point's is refused
    assert len(guided_search(prediction, d[:1], view_with([[104.0, 100.0]], d[1:2]), **gate(max_distance=0.5))) == 0


def test_two_alike_candidates_in_one_gate_are_ambiguous():
    rng = np.random.default_rng(2)
    d = rng.normal(size=(1, 32))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    twins = d + 0.02 * rng.normal(size=(2, 32))
    prediction = Prediction(np.array([[50.0, 50.0]]), np.eye(2)[None] * 4.0, np.ones(1))
    view = view_with([[51.0, 50.0], [50.0, 52.0]], twins)
    assert len(guided_search(prediction, d, view, **gate())) == 0
    # with only one of them in the gate, it is taken
    assert len(guided_search(prediction, d, view_with([[51.0, 50.0], [50.0, 80.0]], twins), **gate())) == 1


def test_pose_from_correspondences_with_mismatches():
    rng = np.random.default_rng(3)
    X = rng.uniform(-1, 1, (60, 3)) + [0, 0, 5]
    R = rotation_exp(np.array([0.05, 0.3, -0.1]))
    t = np.array([0.2, -0.1, 0.4])
    x = project(X, R, t) + rng.normal(0, 0.3, (60, 2))
    x[:12] += rng.uniform(20, 60, (12, 2))
    R_hat, t_hat, inliers = pose_from_correspondences(X, x, K, 2.0, 12)
    assert inliers[12:].all() and not inliers[:12].any()
    np.testing.assert_allclose(R_hat, R, atol=2e-3)
    np.testing.assert_allclose(t_hat, t, atol=2e-2)
    assert pose_from_correspondences(X[:8], x[:8], K, 2.0, 12) is None
