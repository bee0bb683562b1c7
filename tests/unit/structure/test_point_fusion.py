"""Structure fusion with known cameras: consistency on scenes with truth, outliers, statuses, kernels, chunks."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from scipy import stats
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

import kalmansfm.structure.fusion.recursive as recursive_method
from kalmansfm.structure.fusion.recursive_numpy import recursive_states_numpy
from kalmansfm.errors import InvalidInputError, NotEnoughDataError
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure import PointStatus
from kalmansfm.structure.geometry.pinhole import CameraSet, project_each, project_points
from kalmansfm.structure.fusion import FusionSettings, fuse, iterated_update


def nees(errors, covariances):
    return np.einsum("ni,ni->n", errors, np.linalg.solve(covariances, errors[..., None])[..., 0])


@pytest.fixture(scope="module")
def outlier_scene():
    return known_camera_scene(points=3000, views=10, pixel_std=0.7, outlier_fraction=0.05, visibility=0.6, seed=3)


@pytest.fixture(scope="module")
def fused(outlier_scene):
    return {m: fuse(outlier_scene.observations, outlier_scene.cameras, method=m, history=True)
            for m in ("recursive", "batch")}


@pytest.mark.parametrize("method", ["recursive", "batch"])
def test_covariances_are_honest_and_outliers_found_on_a_scene_with_planted_mismatches(outlier_scene, fused, method):
    s, f = outlier_scene, fused[method]
    ok = f.reconstructed
    assert ok.mean() > 0.99
    # auto σ, counted with the degrees of freedom after rejection, finds the true noise
    assert f.noise.estimated and abs(f.noise.std / s.pixel_std - 1) < 0.03
    e = f.points[ok] - s.points[ok]
    n = nees(e, f.point_covariances[ok])
    assert abs(np.median(n) - stats.chi2.median(3)) < 0.2
    z = np.abs(e) / np.sqrt(np.diagonal(f.point_covariances[ok], axis1=1, axis2=2))
    assert np.all(np.abs((z <= 1).mean(axis=0) - 0.683) < 0.03)
    assert np.all((z <= 3).mean(axis=0) > 0.99)
    # the two-view (first) estimates are honest too
    first = f.details.history.first()
    good = np.isfinite(first.estimates).all(axis=1)
    n2 = nees(first.estimates[good] - s.points[first.points[good]], first.covariances[good])
    assert abs(np.median(n2) - stats.chi2.median(3)) < 0.25
    # outliers: recall and false rejections
    observed = np.isfinite(s.observations[..., 0])
    recall = (f.observations.rejected_mask() & s.outliers).sum() / s.outliers.sum()
    false = (f.observations.rejected_mask() & ~s.outliers).sum() / (observed & ~s.outliers).sum()
    assert recall > 0.99
    assert false < 0.005
    # views counts the accepted observations
    np.testing.assert_array_equal(f.views, (observed & ~f.observations.rejected_mask()).sum(axis=0) * ok)


def test_recursive_and_batch_agree_within_a_small_fraction_of_the_uncertainty(fused):
    a, b = fused["recursive"], fused["batch"]
    both = a.reconstructed & b.reconstructed & (a.observations.rejected_mask() == b.observations.rejected_mask()).all(axis=0)
    assert both.mean() > 0.98
    d = a.points[both] - b.points[both]
    n = nees(d, b.point_covariances[both])
    assert np.median(n) < 1e-3
    assert np.quantile(n, 0.99) < 0.05


def test_pairs_is_the_reports_scheme_and_is_over_confident():
    s = known_camera_scene(points=2000, views=10, pixel_std=0.5, seed=4)
    f = fuse(s.observations, s.cameras, method="pairs", pixel_std=0.5)
    assert f.reconstructed.all() and not f.observations.rejected_mask().any()
    n = nees(f.points - s.points, f.point_covariances)
    assert n.mean() > 4  # consecutive pairs share images, counted twice (a consistent mean is 3 ± 0.1 here)


def test_compiled_kernel_matches_the_numpy_reference(monkeypatch):
    s = known_camera_scene(points=1500, views=9, pixel_std=0.5, outlier_fraction=0.1, visibility=0.6, seed=5)
    monkeypatch.setattr(recursive_method, "_STATES", recursive_method.recursive_states)  # the kernel, whatever the size
    compiled = fuse(s.observations, s.cameras, pixel_std=0.5, history=True)
    monkeypatch.setattr(recursive_method, "_STATES", recursive_states_numpy)
    reference = fuse(s.observations, s.cameras, pixel_std=0.5, history=True)
    np.testing.assert_array_equal(compiled.point_status, reference.point_status)
    np.testing.assert_array_equal(compiled.observations.rejected_mask(), reference.observations.rejected_mask())
    np.testing.assert_array_equal(compiled.views, reference.views)
    scale = np.sqrt(np.diagonal(reference.point_covariances, axis1=1, axis2=2))
    assert np.nanmax(np.abs(compiled.points - reference.points) / scale) < 1e-6
    np.testing.assert_allclose(compiled.point_covariances, reference.point_covariances, rtol=1e-6, atol=0)
    np.testing.assert_array_equal(compiled.details.history.views, reference.details.history.views)
    np.testing.assert_array_equal(compiled.details.history.points, reference.details.history.points)
    np.testing.assert_allclose(compiled.details.history.estimates, reference.details.history.estimates, rtol=0, atol=1e-7)


@pytest.mark.parametrize("method", ["recursive", "batch", "pairs"])
def test_chunks_and_an_executor_give_the_same_result(method):
    s = known_camera_scene(points=300, views=6, pixel_std=0.5, outlier_fraction=0.05, visibility=0.7, seed=6)
    whole = fuse(s.observations, s.cameras, method=method, history=True)
    with ThreadPoolExecutor(2) as pool:
        parts = fuse(s.observations, s.cameras, method=method, history=True, chunk_points=70, executor=pool)
    np.testing.assert_array_equal(whole.point_status, parts.point_status)
    np.testing.assert_array_equal(whole.observations.rejected_mask(), parts.observations.rejected_mask())
    np.testing.assert_allclose(whole.points, parts.points, rtol=1e-12)
    assert whole.noise.std == pytest.approx(parts.noise.std, rel=1e-12)
    np.testing.assert_array_equal(whole.details.history.points, parts.details.history.points)


def test_history_ends_at_the_final_estimate_and_grows_more_certain():
    s = known_camera_scene(points=200, views=8, pixel_std=0.5, seed=7)
    f = fuse(s.observations, s.cameras, pixel_std=0.5, history=True)
    X, C = f.details.history.dense(8, 200)
    assert np.isnan(X[0]).all()  # one view gives no estimate
    np.testing.assert_allclose(X[-1], f.points, rtol=1e-12)
    np.testing.assert_allclose(C[-1], f.point_covariances, rtol=1e-12)
    trace = np.trace(C[1:], axis1=2, axis2=3)  # NaN after a view whose observation was rejected
    step = np.diff(trace, axis=0)
    assert np.isfinite(step).mean() > 0.95
    assert np.all(step[np.isfinite(step)] < 0)  # every accepted view adds information


def test_statuses_behind_every_camera_one_view_and_no_baseline():
    K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    R = np.stack([np.eye(3)] * 3)
    cams = CameraSet.from_pose(K, R, [[0.0, 0, 0], [-0.5, 0, 0], [-1.0, 0, 0]])
    X = np.array([[0.1, 0.2, 5.0], [0.3, -0.2, 6.0], [-0.2, 0.1, 4.0], [0.0, 0.1, -5.0], [0.2, 0.0, 5.0]])
    obs = project_points(cams, X).pixels + np.random.default_rng(0).normal(scale=0.3, size=(3, 5, 2))
    obs[1:, 2] = np.nan  # seen once
    f = fuse(obs, cams, pixel_std=0.3)
    labels = [PointStatus(s).label for s in f.point_status]
    assert labels == ["ok", "ok", "too_few_views", "behind_camera", "ok"]
    assert np.isnan(f.points[2:4]).all() and np.isnan(f.point_covariances[3]).all()
    # every camera at the same centre: no parallax, no depth
    same = CameraSet.from_pose(K, np.stack([np.eye(3)] * 3), np.zeros((3, 3)))
    o = project_points(same, X[:3]).pixels
    for method in ("recursive", "batch", "pairs"):
        g = fuse(o, same, method=method, pixel_std=0.3)
        assert np.all(g.point_status == PointStatus.DEGENERATE), method


def test_mirrored_reconstruction_is_fused_in_its_own_frame():
    s = known_camera_scene(points=100, views=5, pixel_std=0.5, seed=8)
    mirror = np.diag([1.0, -1.0, 1.0, 1.0])  # a reflected world gives the same images
    cams = CameraSet.from_matrices(s.cameras.matrices @ mirror)
    for method in ("recursive", "batch", "pairs"):
        f = fuse(s.observations, cams, method=method, pixel_std=0.5)
        assert f.details.orientation == -1 and f.reconstructed.all(), method
        n = nees(f.points - s.points * [1, -1, 1], f.point_covariances)
        assert 2 < n.mean() < (4 if method != "pairs" else 40), method


def test_bad_arguments_raise_one_clear_error():
    s = known_camera_scene(points=10, views=3, seed=9)
    with pytest.raises(InvalidInputError, match="method must be one of"):
        fuse(s.observations, s.cameras, method="kalman")
    with pytest.raises(InvalidInputError, match="pixel_std must be a number"):
        fuse(s.observations, s.cameras, pixel_std="guess")
    with pytest.raises(InvalidInputError, match="outlier_probability must be in"):
        fuse(s.observations, s.cameras, outlier_probability=1.5)
    with pytest.raises(InvalidInputError, match=r"observations must have shape \(3 views"):
        fuse(s.observations[:2], s.cameras)
    with pytest.raises(NotEnoughDataError, match=">= 2 cameras"):
        fuse(s.observations[:1], s.cameras.subset([0]))
    once = s.observations.copy()
    once[1:] = np.nan  # every point seen once: nothing to estimate σ from
    with pytest.raises(NotEnoughDataError, match="pixel_std='auto' needs"):
        fuse(once, s.cameras)
    with pytest.raises(InvalidInputError, match="chunk_points"):
        FusionSettings(chunk_points=0)


def test_the_iterated_update_reaches_the_map_estimate_and_the_gate_keeps_the_prior():
    """The IEKF's fixed point minimises (θ - θ̂)ᵀ P⁻¹ (θ - θ̂) + |z - h(θ)|² (unit σ): solved here by least squares."""
    rng = np.random.default_rng(7)
    n = 6
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R = Rotation.from_rotvec(rng.normal(size=(n, 3)) * 0.2).as_matrix()
    Q = np.einsum("ij,njk->nik", K, np.concatenate([R, rng.normal(size=(n, 3, 1))], axis=2))
    truth = rng.uniform([-1, -1, 4], [1, 1, 6], size=(n, 3))
    a = rng.normal(size=(n, 3, 3)) * 0.3
    P = a @ a.transpose(0, 2, 1) + 0.05 * np.eye(3)
    prior = truth + np.einsum("nij,nj->ni", np.linalg.cholesky(P), rng.normal(size=(n, 3))) * 0.5
    z = project_each(Q, truth)[0] + rng.normal(size=(n, 2))
    up = iterated_update(Q, prior, P, z, pixel_std=1.0, gate=1e9)
    assert up.accepted.all()
    for k in range(n):
        L_inv = np.linalg.inv(np.linalg.cholesky(P[k]))

        def residuals(th, k=k, L_inv=L_inv):
            return np.concatenate([L_inv @ (th - prior[k]), z[k] - project_each(Q[k], th)[0]])

        best = least_squares(residuals, prior[k], xtol=1e-14, ftol=1e-14, gtol=1e-14).x
        np.testing.assert_allclose(up.states[k], best, atol=1e-6 * np.sqrt(P[k].diagonal()).max())
    # a tight gate rejects them all and leaves the prior untouched
    tight = iterated_update(Q, prior, P, z + 1e3, pixel_std=1.0, gate=13.8)
    assert not tight.accepted.any() and np.array_equal(tight.states, prior) and np.array_equal(tight.covariances, P)


def test_settings_are_the_same_options_and_a_keyword_beside_them_is_refused():
    s = known_camera_scene(points=60, views=5, pixel_std=0.5, seed=4)
    by_keywords = fuse(s.observations, s.cameras, method="batch", pixel_std=0.5, outlier_probability=0.99)
    by_settings = fuse(s.observations, s.cameras, settings=FusionSettings("batch", 0.5, 0.99))
    np.testing.assert_array_equal(by_keywords.points, by_settings.points)
    np.testing.assert_array_equal(by_keywords.point_covariances, by_settings.point_covariances)
    with pytest.raises(InvalidInputError, match="give method, history inside settings"):
        fuse(s.observations, s.cameras, method="batch", history=True, settings=FusionSettings())
    with pytest.raises(InvalidInputError, match="pixel_std must be a number .* or 'auto'"):
        fuse(s.observations, s.cameras, pixel_std="estimate")


def test_small_fusions_take_the_numpy_pass_and_large_ones_the_kernel(monkeypatch):
    """A first fusion of a few hundred points must not wait for a kernel to compile."""
    calls = []
    monkeypatch.setattr(recursive_method, "recursive_states",
                        lambda job: calls.append("kernel") or pytest.fail("the kernel ran on a small chunk"))
    s = known_camera_scene(points=300, views=6, pixel_std=0.5, seed=8)
    assert fuse(s.observations, s.cameras, pixel_std=0.5).status_counts()["ok"] == 300 and calls == []
    monkeypatch.setattr(recursive_method, "COMPILED_MIN_POINTS", 100)
    with pytest.raises(pytest.fail.Exception):
        fuse(s.observations, s.cameras, pixel_std=0.5)
