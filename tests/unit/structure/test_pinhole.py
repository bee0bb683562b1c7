"""Projective cameras: decomposition, projection, Jacobians, linear triangulation, Gauss–Newton refinement."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kalmansfm.errors import InvalidInputError
from kalmansfm.structure import PointStatus
from kalmansfm.structure.geometry.pinhole import (
    CameraSet,
    camera_centres,
    decompose_projection,
    intrinsic_matrices,
    project_points,
    projection_jacobians,
    scene_orientation,
    triangulate_points,
)
from kalmansfm.structure.geometry.refinement import refine_points


def ring_cameras(views: int, radius: float = 10.0, seed: int = 0) -> CameraSet:
    """Cameras on an arc around the origin, looking at it, with varied intrinsics."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(-0.6, 0.6, views)
    R, t, K = [], [], []
    for a in angles:
        # camera looks along +z of its frame towards the origin from (r sin a, 0, -r cos a)
        rot = Rotation.from_euler("y", -a).as_matrix() @ Rotation.from_rotvec(rng.normal(scale=0.02, size=3)).as_matrix()
        centre = np.array([radius * np.sin(a), 0.3 * rng.normal(), -radius * np.cos(a)])
        R.append(rot)
        t.append(-rot @ centre)
        f = 800 + 50 * rng.normal()
        K.append([[f, 0.5, 320 + 5 * rng.normal()], [0, 1.02 * f, 240 + 5 * rng.normal()], [0, 0, 1]])
    return CameraSet.from_pose(np.array(K), np.array(R), np.array(t), frames=np.arange(views) * 3 + 1)


def test_decomposition_recovers_k_r_t_and_the_sign_of_mirrored_cameras():
    rng = np.random.default_rng(1)
    R = Rotation.random(6, random_state=2).as_matrix()
    K = np.array([[900.0, 3.0, 310.0], [0.0, 870.0, 250.0], [0.0, 0.0, 1.0]])
    t = rng.normal(size=(6, 3))
    scale = np.array([1.0, -2.0, 0.5, -0.01, 3.0, -1.0])
    P = scale[:, None, None] * np.einsum("ij,vjk->vik", K, np.concatenate([R, t[:, :, None]], axis=2))
    pose = decompose_projection(P)
    np.testing.assert_allclose(pose.intrinsics, np.broadcast_to(K, (6, 3, 3)), atol=1e-9)
    np.testing.assert_allclose(pose.rotations, R, atol=1e-12)
    np.testing.assert_allclose(pose.translations, t, atol=1e-12)
    np.testing.assert_allclose(pose.scales, scale, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.det(pose.rotations), 1.0)
    np.testing.assert_allclose(CameraSet.from_matrices(P).centers, pose.centers, atol=1e-9)


def test_one_k_builder_and_one_centre_formula_agree_with_the_camera_set():
    cams = ring_cameras(5)
    pose = cams.decompose()
    K = pose.intrinsics
    built = intrinsic_matrices(K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 0, 1])
    np.testing.assert_array_equal(built, K)
    assert intrinsic_matrices(700.0, 700.0, 320.0, 240.0, 0.0).shape == (1, 3, 3)
    # -Rᵀ t, batched or one pose, is the null vector of P
    C = camera_centres(pose.rotations, pose.translations)
    np.testing.assert_allclose(C, cams.centers, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(camera_centres(pose.rotations[2], pose.translations[2]), C[2])
    assert np.isnan(camera_centres(np.full((3, 3), np.nan), np.zeros(3))).all()


def test_projection_depths_are_camera_z_and_flip_with_the_sign_of_p():
    cams = ring_cameras(4)
    X = np.random.default_rng(3).normal(size=(20, 3))
    p = project_points(cams, X)
    pose = cams.decompose()
    z = np.einsum("vij,nj->vni", pose.rotations, X)[..., 2] + pose.translations[:, None, 2]
    np.testing.assert_allclose(p.depths, z, rtol=1e-12)
    flipped = project_points(-3.0 * cams.matrices, X)
    np.testing.assert_allclose(flipped.pixels, p.pixels, rtol=1e-12)
    np.testing.assert_allclose(flipped.depths, p.depths, rtol=1e-12)  # depth is a property of the camera, not of P's sign
    assert scene_orientation(p.depths) == 1


def test_jacobian_matches_central_differences():
    cams = ring_cameras(3)
    X = np.random.default_rng(4).normal(size=(5, 3))
    J = projection_jacobians(cams, X)
    h = 1e-6
    for i in range(3):
        d = np.zeros(3)
        d[i] = h
        num = (project_points(cams, X + d).pixels - project_points(cams, X - d).pixels) / (2 * h)
        np.testing.assert_allclose(J[..., i], num, rtol=1e-6, atol=1e-6)


def test_linear_triangulation_is_exact_on_exact_data_and_flags_degenerate_points():
    cams = ring_cameras(5)
    X = np.random.default_rng(5).uniform(-2, 2, size=(50, 3))
    obs = project_points(cams, X).pixels
    obs[2:, 0] = np.nan  # point 0 seen in two views only
    obs[1:, 1] = np.nan  # point 1 seen once
    tri = triangulate_points(cams, obs)
    assert tri.status[1] == PointStatus.TOO_FEW_VIEWS and np.isnan(tri.points[1]).all()
    ok = tri.status == PointStatus.OK
    assert ok.sum() == 49
    np.testing.assert_allclose(tri.points[ok], X[ok], atol=1e-9)
    np.testing.assert_array_equal(tri.views[:3], [2, 1, 5])
    # two cameras with the same centre: no parallax
    same = CameraSet.from_pose(np.diag([500.0, 500.0, 1.0]), Rotation.from_euler("y", [[0.0], [0.1]]).as_matrix(),
                               np.zeros((2, 3)))
    ob = project_points(same, [[0.1, 0.2, 5.0]]).pixels
    assert triangulate_points(same, ob).status[0] == PointStatus.DEGENERATE


def test_mirrored_reconstruction_is_consistent_and_a_point_behind_every_camera_is_flagged():
    cams = ring_cameras(4)
    X = np.random.default_rng(6).uniform(-2, 2, size=(30, 3))
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])  # world reflected: the same images from mirrored points
    mirrored = CameraSet.from_matrices(cams.matrices @ mirror)
    Xm = X * [1, 1, -1]
    obs = project_points(cams, X).pixels
    np.testing.assert_allclose(project_points(mirrored, Xm).pixels, obs, atol=1e-9)
    tri = triangulate_points(mirrored, obs)
    assert tri.orientation == -1 and np.all(tri.status == PointStatus.OK)
    np.testing.assert_allclose(tri.points, Xm, atol=1e-8)
    # with the orientation fixed to +1 every point is behind
    assert np.all(triangulate_points(mirrored, obs, orientation=1).status == PointStatus.BEHIND_CAMERA)
    # in a normal scene, one point behind all cameras among many in front
    behind = np.vstack([X, [[0.0, 0.0, -30.0]]])
    obs_b = project_points(cams, behind).pixels
    tri_b = triangulate_points(cams, obs_b)
    assert tri_b.status[-1] == PointStatus.BEHIND_CAMERA and np.all(tri_b.status[:-1] == PointStatus.OK)
    fit = refine_points(cams, obs_b, behind, orientation=1)
    assert fit.status[-1] == PointStatus.BEHIND_CAMERA and np.all(fit.status[:-1] == PointStatus.OK)


def test_refined_covariances_are_consistent_nees_and_sigma_rates():
    """NEES of σ² (JᵀJ)⁻¹ on 4000 noisy points: mean near 3, 1σ / 3σ rates near 0.683 / 0.997."""
    rng = np.random.default_rng(7)
    cams = ring_cameras(6)
    X = rng.uniform(-2, 2, size=(4000, 3))
    sigma = 1.5
    obs = project_points(cams, X).pixels + rng.normal(scale=sigma, size=(6, 4000, 2))
    obs[rng.random((6, 4000)) < 0.4] = np.nan
    tri = triangulate_points(cams, obs)
    fit = refine_points(cams, obs, tri.points, pixel_std=sigma)
    ok = fit.status == PointStatus.OK
    assert ok.mean() > 0.9 and fit.converged[ok].all()
    e = fit.points[ok] - X[ok]
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(fit.covariances[ok], e[..., None])[..., 0])
    assert 2.85 < nees.mean() < 3.15
    z = np.abs(e) / np.sqrt(np.diagonal(fit.covariances[ok], axis1=1, axis2=2))
    assert np.all(np.abs((z <= 1).mean(axis=0) - 0.683) < 0.03)
    assert np.all((z <= 3).mean(axis=0) > 0.99)
    # the residuals are the observations minus the reprojection of the refined point
    np.testing.assert_allclose(fit.residuals[:, ok], obs[:, ok] - project_points(cams, fit.points[ok]).pixels,
                               atol=1e-9)


def test_refinement_reaches_the_minimum_from_a_poor_start():
    cams = ring_cameras(4)
    rng = np.random.default_rng(8)
    X = rng.uniform(-2, 2, size=(200, 3))
    obs = project_points(cams, X).pixels + rng.normal(scale=0.5, size=(4, 200, 2))
    best = refine_points(cams, obs, X).points
    start = X + rng.normal(scale=0.3, size=X.shape)
    fit = refine_points(cams, obs, start)
    np.testing.assert_allclose(fit.points, best, atol=1e-7)
    # gradient zero at the solution: Jᵀ r = 0
    J = projection_jacobians(cams, fit.points)
    g = np.einsum("vnai,vna->ni", J, fit.residuals)
    assert np.abs(g).max() < 1e-6 * np.abs(J).max()


@pytest.mark.parametrize(
    "matrices, frames, message",
    [
        (np.zeros((2, 3, 4)), [0, 1], "not invertible"),
        (np.full((1, 3, 4), np.nan), [0], "must be finite"),
        (np.stack([np.eye(3, 4)] * 2), [5, 5], "must be different"),
        (np.eye(3), [0], "shape"),
    ],
)
def test_camera_set_rejects_bad_matrices_naming_the_frame(matrices, frames, message):
    with pytest.raises(InvalidInputError, match=message):
        CameraSet.from_matrices(matrices, frames)
