"""Fusion under a fitted noise model, and no false confidence: no parallax, points behind poses, parallel rays, flat shapes."""

import numpy as np
import pytest
from scipy import stats

import kalmansfm.structure.fusion.recursive as recursive_method
from kalmansfm.structure.fusion.recursive_numpy import recursive_states_numpy
from kalmansfm.errors import InvalidInputError, NotEnoughDataError
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure import PointStatus, factorize, triangulate_midpoint
from kalmansfm.structure.fusion import FusionSettings, fuse
from kalmansfm.structure.fusion.weighted import refine_weighted
from kalmansfm.structure.geometry.pinhole import CameraSet, project_points
from kalmansfm.structure.geometry.refinement import refine_points

CHI3_999 = stats.chi2.ppf(0.999, 3)


def nees(errors, covariances):
    return np.einsum("ni,ni->n", errors, np.linalg.solve(covariances, errors[..., None])[..., 0])


@pytest.fixture(scope="module")
def scene():
    return known_camera_scene(points=1500, views=10, pixel_std=0.6, outlier_fraction=0.03, visibility=0.6, seed=11)


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_the_mixture_model_rejects_what_it_fits_and_its_covariances_are_honest(scene, method):
    f = fuse(scene.observations, scene.cameras, method=method)
    assert f.noise.model == "mixture" and f.noise.estimated
    p = dict(f.noise.parameters)
    share = p["outlier_share"]
    observed = np.isfinite(scene.observations[..., 0])
    rejected = f.observations.rejected_mask()
    # the gate says what it does: the rejected share is the fitted outlier share, which is the planted one
    assert 0.5 < rejected.sum() / observed.sum() / share < 2
    assert abs(share - scene.outliers.sum() / observed.sum()) < 4 * p["outlier_share_se"] + 0.003
    assert (rejected & scene.outliers).sum() / scene.outliers.sum() > 0.97
    assert abs(f.noise.std / scene.pixel_std - 1) < 3 * p["sigma_se"] / scene.pixel_std + 0.02
    ok = f.reconstructed
    n = nees(f.points[ok] - scene.points[ok], f.point_covariances[ok])
    assert 1.9 < np.median(n) < 2.9 and np.mean(n <= stats.chi2.ppf(0.99, 3)) > 0.98
    # each observation's σ under the model, NaN where left out
    std = f.observations.grid(f.noise.observation_std)
    assert np.all(np.isnan(std[rejected])) and np.allclose(std[observed & ~rejected & ok[None]], f.noise.std)


def test_split_halves_of_a_synthetic_scene_agree_within_their_covariances(scene):
    obs = scene.observations
    seen = np.isfinite(obs[..., 0])
    keep = seen.sum(axis=0) >= 4
    rank = np.cumsum(seen, axis=0) - 1
    halves = [np.where((seen & (rank % 2 == parity) & keep[None])[..., None], obs, np.nan) for parity in (0, 1)]
    a, b = (fuse(h, scene.cameras) for h in halves)
    ok = a.reconstructed & b.reconstructed
    n = nees(a.points[ok] - b.points[ok], a.point_covariances[ok] + b.point_covariances[ok])
    assert ok.sum() > 500
    assert 1.9 < np.median(n) < 2.9 and np.mean(n <= stats.chi2.ppf(0.99, 3)) > 0.97


def test_student_t_weights_and_track_scales_are_reported_with_their_parameters(scene):
    f = fuse(scene.observations, scene.cameras, noise_model="student-t+uniform", track_scales=True)
    names = dict(f.noise.parameters)
    assert {"tail_dof", "outlier_share", "track_spread", "serial_correlation_x"} <= names.keys()
    assert "student-t+uniform" in f.noise.describe()
    # the synthetic noise is white: no warning about correlated errors
    assert not any("correlated" in w for w in f.warnings)


def test_the_gaussian_option_is_the_old_chi_square_gate(scene):
    f = fuse(scene.observations, scene.cameras, settings=FusionSettings(noise_model="gaussian"))
    assert f.noise.model == "gaussian" and f.noise.parameters == () and f.noise.observation_std is None
    given = fuse(scene.observations, scene.cameras, pixel_std=0.6)
    assert given.noise.model == "gaussian" and not given.noise.estimated


def test_too_few_residuals_for_a_model_fall_back_to_one_gaussian_sigma():
    s = known_camera_scene(points=10, views=3, pixel_std=0.5, seed=2)  # 30 residual degrees of freedom
    f = fuse(s.observations, s.cameras)
    assert f.noise.model == "gaussian" and any("too few to fit" in w for w in f.warnings)


def test_the_weighted_kernel_matches_the_numpy_reference(monkeypatch):
    s = known_camera_scene(points=800, views=8, pixel_std=0.5, outlier_fraction=0.05, visibility=0.6, seed=5)
    monkeypatch.setattr(recursive_method, "_STATES", recursive_method.recursive_states)  # the kernel, whatever the size
    compiled = fuse(s.observations, s.cameras, noise_model="student-t", track_scales=True, history=True)
    monkeypatch.setattr(recursive_method, "_STATES", recursive_states_numpy)
    reference = fuse(s.observations, s.cameras, noise_model="student-t", track_scales=True, history=True)
    np.testing.assert_array_equal(compiled.point_status, reference.point_status)
    np.testing.assert_array_equal(compiled.observations.rejected_mask(), reference.observations.rejected_mask())
    scale = np.sqrt(np.diagonal(reference.point_covariances, axis1=1, axis2=2))
    assert np.nanmax(np.abs(compiled.points - reference.points) / scale) < 1e-5
    np.testing.assert_allclose(compiled.point_covariances, reference.point_covariances, rtol=1e-5, atol=0)


def test_weighted_refinement_with_equal_weights_is_the_plain_one():
    s = known_camera_scene(points=200, views=6, pixel_std=0.5, seed=7)
    P = np.asarray(s.cameras.matrices)
    plain = refine_points(P, s.observations, s.points, orientation=1)
    weighted = refine_weighted(P, np.sign(s.cameras.decompose().scales), s.observations, s.points,
                               np.full(s.observations.shape[:2], 4.0), 1)
    ok = plain.status == PointStatus.OK
    np.testing.assert_array_equal(weighted.status, plain.status)
    np.testing.assert_allclose(weighted.points[ok], plain.points[ok], atol=1e-7)
    cov = np.linalg.inv(weighted.normal[ok]) * 4.0
    np.testing.assert_allclose(cov, plain.covariances[ok], rtol=1e-5, atol=1e-6 * np.abs(plain.covariances[ok]).max())


def _line_of_cameras(baseline, distance, seed=0, n=150, views=7):
    rng = np.random.default_rng(seed)
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    centres = np.stack([np.linspace(0, baseline, views), np.zeros(views), np.zeros(views)], axis=1)
    cams = CameraSet.from_pose(K, np.stack([np.eye(3)] * views), -centres)
    X = rng.normal(size=(n, 3)) * distance * 0.1 + [baseline / 2, 0, distance]
    return cams, X, project_points(cams, X).pixels + rng.normal(scale=0.5, size=(views, n, 2))


@pytest.mark.parametrize("method", ["recursive", "batch"])
@pytest.mark.parametrize("baseline, distance", [(1e-7, 5.0), (6.0, 1e6), (6.0, 1e4), (6.0, 2e3)])
def test_without_parallax_no_point_is_confidently_wrong(method, baseline, distance):
    cams, X, obs = _line_of_cameras(baseline, distance)
    f = fuse(obs, cams, method=method, pixel_std=0.5)
    ok = f.reconstructed
    beyond = nees(f.points[ok] - X[ok], f.point_covariances[ok]) > CHI3_999
    assert beyond.sum() <= 0.01 * max(ok.sum(), 1)
    if distance >= 1e4:
        assert ok.sum() == 0 and any("parallax" in w for w in f.warnings)


def test_with_parallax_the_points_stay_ok():
    cams, X, obs = _line_of_cameras(1.0, 5.0)
    for method in ("recursive", "batch"):
        assert fuse(obs, cams, method=method, pixel_std=0.5).reconstructed.all()


def test_auto_sigma_says_plainly_why_nothing_was_fused():
    cams, _, obs = _line_of_cameras(0.0, 5.0)  # pure rotation: every centre the same
    with pytest.raises(NotEnoughDataError, match="no parallax|has parallax"):
        fuse(obs, cams)
    once = np.full_like(obs, np.nan)
    once[np.arange(obs.shape[1]) % obs.shape[0], np.arange(obs.shape[1])] = obs[0]
    with pytest.raises(NotEnoughDataError, match="no track is seen in two views"):
        fuse(once, cams)


@pytest.mark.parametrize("method", ["recursive", "batch", "pairs"])
def test_points_behind_cameras_given_as_poses_are_behind_camera(method):
    rng = np.random.default_rng(0)
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    cams = CameraSet.from_pose(K, np.stack([np.eye(3)] * 5), [[-x, 0, 0] for x in np.linspace(0, 1, 5)])
    X = rng.uniform([-1, -1, -6], [1, 1, -4], size=(60, 3))  # z < 0: behind every camera
    obs = project_points(cams, X).pixels + rng.normal(scale=0.5, size=(5, 60, 2))
    f = fuse(obs, cams, method=method, pixel_std=0.5)
    assert f.status_counts()["behind_camera"] == 60 and f.details.orientation == 1
    assert any("behind the cameras" in w for w in f.warnings)
    with pytest.raises(NotEnoughDataError, match="behind the cameras"):
        fuse(obs, cams, method=method)
    # the same scene as bare projection matrices of unknown sign and scale: a mirrored frame, fused as such
    mirrored = CameraSet.from_matrices(-3.0 * np.asarray(cams.matrices))
    g = fuse(obs, mirrored, method=method, pixel_std=0.5)
    assert g.details.orientation == -1 and g.reconstructed.all()


def test_parallel_rays_within_the_noise_are_not_triangulated():
    f = 500.0
    b = np.array([1e-6, 0.0, 0.0])  # a micrometre of baseline, a point 10 m away
    X = np.array([0.3, 0.1, 10.0])
    left, right = f * X[:2] / X[2], f * (X - b)[:2] / (X - b)[2]
    r = triangulate_midpoint(left[None], right[None], np.eye(3), b, f, pixel_std=0.5)
    assert r.status[0] == PointStatus.DEGENERATE and np.isnan(r.points).all()
    with pytest.raises(InvalidInputError, match="parallel"):
        triangulate_midpoint(left, right, np.eye(3), b, f, pixel_std=0.5)
    # with a real baseline the same point is triangulated
    b = np.array([1.0, 0.0, 0.0])
    right = f * (X - b)[:2] / (X - b)[2]
    assert triangulate_midpoint(left[None], right[None], np.eye(3), b, f, pixel_std=0.5).status[0] == PointStatus.OK


def test_collinear_points_of_a_factorization_are_not_ok():
    rng = np.random.default_rng(0)
    t = rng.uniform(-1, 1, 150)
    shape = np.outer(t, [40.0, 30.0, 20.0]) + rng.normal(scale=0.01, size=(150, 3))
    frames = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(10)]
    tracks = np.stack([shape @ m.T + 200 for m in frames]) + rng.normal(scale=0.3, size=(10, 150, 2))
    rec = factorize(tracks)
    assert rec.status_counts()["ok"] == 0
    assert any("depth is not determined" in w and "unreliable" in w for w in rec.warnings)
