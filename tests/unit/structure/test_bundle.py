"""Bundle adjustment (Levenberg–Marquardt with a Schur complement) and free-network-gauge covariances."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares
from scipy.stats import chi2

import kalmansfm.structure.perspective.bundle as bundle_module
from kalmansfm.errors import InvalidInputError
from kalmansfm.scenes.perspective import perspective_scene
from kalmansfm.structure.geometry.alignment import align_similarity
from kalmansfm.structure.perspective.bundle import (
    ObservationList,
    residuals_and_jacobians,
    _similarity_directions,
    bundle_adjust,
    compare_in_gauge,
    coupling_reference,
    free_network_covariances,
    reprojection_residuals,
)
from kalmansfm.structure.geometry.rotation import rotation_exp, rotation_log
from kalmansfm.structure.perspective._schur_kernel import schur_coupling_kernel


def small_problem(seed=0, frames=5, points=40, pixel_std=0.5, skew=0.0, min_track_length=2):
    """A scene with per-frame intrinsics (one with skew), its observations and a disturbed start."""
    s = perspective_scene(frames=frames, points=points, pixel_std=pixel_std, min_track_length=min_track_length,
                          seed=seed)
    K = s.intrinsics.copy()
    K[:, 0, 0] *= np.linspace(0.95, 1.05, frames)
    K[0, 0, 1] = skew
    x = np.einsum("fij,fpj->fpi", K, np.einsum("fij,fpj->fpi", s.rotations, s.points[None] - s.centres[:, None]))
    noise = np.random.default_rng(seed + 100).normal(scale=pixel_std, size=x[..., :2].shape)
    pixels = np.where(np.isfinite(s.observations), x[..., :2] / x[..., 2:] + noise, np.nan)
    obs = ObservationList.from_dense(pixels)
    rng = np.random.default_rng(seed + 200)
    start = (rotation_exp(rng.normal(0, 0.005, (frames, 3))) @ s.rotations,
             s.centres + rng.normal(0, 0.03, (frames, 3)), s.points + rng.normal(0, 0.03, s.points.shape))
    return s, K, obs, start


def test_rotation_exp_and_log_are_inverse_including_near_pi():
    w = np.array([[0.0, 0.0, 0.0], [1e-9, 0, 0], [0.3, -0.2, 0.1], [0, np.pi - 1e-5, 0], [2.0, 1.0, -1.5]])
    w[-1] *= (np.pi - 1e-4) / np.linalg.norm(w[-1])
    R = rotation_exp(w)
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(rotation_log(R), w, atol=1e-7)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_rotation_log_of_exp_property(v):
    w = np.array(v)
    if np.linalg.norm(w) >= np.pi - 1e-3:
        w *= (np.pi - 1e-3) / np.linalg.norm(w)
    np.testing.assert_allclose(rotation_log(rotation_exp(w)), w, atol=1e-8)


def test_jacobians_match_finite_differences():
    s, K, obs, (R, C, X) = small_problem(skew=3.0)
    kz = np.concatenate([K, np.zeros((len(K), 3, 1))], axis=2)
    r, _, J_cam, J_point = residuals_and_jacobians(R, C, X, obs, kz)
    h = 1e-6
    for k in (0, 7, len(obs) - 1):
        c, p = obs.cameras[k], obs.points[k]
        for j in range(6):
            d = np.zeros((len(R), 6))
            d[c, j] = h
            rp, _ = reprojection_residuals(rotation_exp(d[:, :3]) @ R, C + d[:, 3:], X, obs, K)
            rm, _ = reprojection_residuals(rotation_exp(-d[:, :3]) @ R, C - d[:, 3:], X, obs, K)
            np.testing.assert_allclose((rp[k] - rm[k]) / (2 * h), J_cam[k, :, j], rtol=1e-5, atol=1e-4)
        for j in range(3):
            d = np.zeros_like(X)
            d[p, j] = h
            rp, _ = reprojection_residuals(R, C, X + d, obs, K)
            rm, _ = reprojection_residuals(R, C, X - d, obs, K)
            np.testing.assert_allclose((rp[k] - rm[k]) / (2 * h), J_point[k, :, j], rtol=1e-5, atol=1e-4)


def test_bundle_adjustment_reaches_the_least_squares_minimum_of_scipy():
    """An independent solver (scipy's trust-region least squares, dense exact steps) finds the same cost."""
    s, K, obs, (R0, C0, X0) = small_problem(frames=4, points=25)
    fit = bundle_adjust(R0, C0, X0, obs, K)
    assert fit.converged

    def residuals(p):
        n, m = len(R0), len(X0)
        R = rotation_exp(p[: 3 * n].reshape(n, 3)) @ R0
        r, _ = reprojection_residuals(R, p[3 * n: 6 * n].reshape(n, 3), p[6 * n:].reshape(m, 3), obs, K)
        return r.ravel()

    ref = least_squares(residuals, np.concatenate([np.zeros(3 * len(R0)), C0.ravel(), X0.ravel()]),
                        method="trf", tr_solver="exact", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert fit.cost == pytest.approx(ref.cost, rel=1e-9)
    # the same points up to the gauge (a similarity)
    n = len(R0)
    ref_points = ref.x[6 * n:].reshape(-1, 3)
    assert align_similarity(fit.points, ref_points).rms < 1e-6


def test_robust_loss_keeps_gross_outliers_from_pulling_the_solution():
    s, K, obs, (R0, C0, X0) = small_problem(frames=6, points=60, pixel_std=0.3, min_track_length=4)
    pixels = obs.pixels.copy()
    bad = np.random.default_rng(5).choice(len(obs), size=len(obs) // 20, replace=False)
    pixels[bad] += 40.0
    corrupted = ObservationList(obs.cameras, obs.points, pixels)
    plain = bundle_adjust(R0, C0, X0, corrupted, K)
    robust = bundle_adjust(R0, C0, X0, corrupted, K, loss="cauchy", loss_scale=2.0)
    err_plain = np.median(np.linalg.norm(align_similarity(plain.points, s.points).aligned - s.points, axis=1))
    err_robust = np.median(np.linalg.norm(align_similarity(robust.points, s.points).aligned - s.points, axis=1))
    assert err_robust < 0.2 * err_plain
    assert err_robust < 0.005


def dense_free_network(R, C, X, obs, K, sigma):
    """Reference: dense Jacobian, Moore–Penrose inverse of JᵀJ, then the S-transformation to the point gauge."""
    n, m = len(R), len(X)
    kz = np.concatenate([K, np.zeros((n, 3, 1))], axis=2)
    _, _, J_cam, J_point = residuals_and_jacobians(R, C, X, obs, kz)
    J = np.zeros((2 * len(obs), 6 * n + 3 * m))
    rows = np.arange(len(obs))
    for a in range(2):
        for j in range(6):
            J[2 * rows + a, 6 * obs.cameras + j] = J_cam[:, a, j]
        for j in range(3):
            J[2 * rows + a, 6 * n + 3 * obs.points + j] = J_point[:, a, j]
    cov = np.linalg.pinv(J.T @ J, hermitian=True)
    T, G = _similarity_directions(R, C, X)
    T_all = np.concatenate([T.reshape(6 * n, 7), G.reshape(3 * m, 7)])
    A = np.zeros((7, 6 * n + 3 * m))
    A[:, 6 * n:] = np.linalg.solve(G.reshape(3 * m, 7).T @ G.reshape(3 * m, 7), G.reshape(3 * m, 7).T)
    proj = np.eye(6 * n + 3 * m) - T_all @ A
    full = sigma**2 * proj @ cov @ proj.T
    points = np.stack([full[6 * n + 3 * i: 6 * n + 3 * i + 3, 6 * n + 3 * i: 6 * n + 3 * i + 3] for i in range(m)])
    cams = np.stack([full[6 * i: 6 * i + 6, 6 * i: 6 * i + 6] for i in range(n)])
    return points, cams


@pytest.mark.parametrize("dense", [True, False])
def test_free_network_covariances_equal_the_dense_pseudo_inverse(monkeypatch, dense):
    s, K, obs, (R0, C0, X0) = small_problem(frames=5, points=30, skew=2.0)
    fit = bundle_adjust(R0, C0, X0, obs, K)
    if not dense:  # force the sparse reduced-camera path
        monkeypatch.setattr(bundle_module, "_DENSE_COUPLING_BYTES", 0)
    cov = free_network_covariances(fit.rotations, fit.centres, fit.points, obs, K, pixel_std=0.7)
    ref_points, ref_cams = dense_free_network(fit.rotations, fit.centres, fit.points, obs, K, 0.7)
    assert cov.gauge_residual < 1e-10
    np.testing.assert_allclose(cov.points, ref_points, rtol=1e-7, atol=1e-9 * np.abs(ref_points).max())
    np.testing.assert_allclose(cov.cameras, ref_cams, rtol=1e-7, atol=1e-9 * np.abs(ref_cams).max())


@pytest.mark.parametrize("dense", [True, False])
def test_compiled_schur_coupling_equals_the_reference(monkeypatch, dense):
    """The numba kernel against the dense (and sparse) product, observations in a shuffled order."""
    _, _, obs, _ = small_problem(frames=6, points=40, min_track_length=2)
    rng = np.random.default_rng(5)
    shuffle = rng.permutation(len(obs))
    obs = ObservationList(obs.cameras[shuffle], obs.points[shuffle], obs.pixels[shuffle])
    n, m = 6, int(obs.points.max()) + 1
    W = rng.normal(size=(len(obs), 6, 3))
    A = rng.normal(size=(m, 3, 3))
    Y = W @ (A @ np.swapaxes(A, 1, 2) + np.eye(3))[obs.points]  # W V⁻¹ with V⁻¹ symmetric
    if not dense:
        monkeypatch.setattr(bundle_module, "_DENSE_COUPLING_BYTES", 0)
    reference = coupling_reference(obs, n, m, Y, W)
    order, starts = obs.by_point
    compiled = schur_coupling_kernel(order, starts, obs.cameras, Y, W, n)
    np.testing.assert_allclose(compiled, reference, rtol=1e-12, atol=1e-12 * np.abs(reference).max())
    np.testing.assert_allclose(compiled, compiled.T, rtol=0, atol=1e-12 * np.abs(reference).max())


def test_bundle_adjustment_takes_the_same_path_with_the_reference_coupling(monkeypatch):
    _, K, obs, start = small_problem(frames=5, points=30)
    compiled = bundle_adjust(*start, obs, K)
    m = len(start[2])
    monkeypatch.setattr(bundle_module, "schur_coupling_kernel",
                        lambda order, starts, cameras, left, right, n: coupling_reference(obs, n, m, left, right))
    reference = bundle_adjust(*start, obs, K)
    assert reference.iterations == compiled.iterations
    np.testing.assert_allclose(reference.points, compiled.points, rtol=1e-9, atol=1e-9)


def test_point_and_camera_nees_after_similarity_alignment():
    """Monte Carlo from the true start: aligned errors are consistent with the gauge covariances."""
    point_nees, camera_nees = [], []
    for seed in range(10):
        s, K, obs, _ = small_problem(seed=seed, frames=6, points=150, pixel_std=0.6, min_track_length=3)
        fit = bundle_adjust(s.rotations, s.centres, s.points, obs, K)
        r, _ = reprojection_residuals(fit.rotations, fit.centres, fit.points, obs, K)
        dof = 2 * len(obs) - 6 * len(K) - 3 * len(s.points) + 7
        sigma = np.sqrt(np.sum(r**2) / dof)
        cov = free_network_covariances(fit.rotations, fit.centres, fit.points, obs, K, sigma)
        out = compare_in_gauge(fit.points, cov.points, s.points, rotations=fit.rotations, centres=fit.centres,
                               camera_covariances=cov.cameras, reference_rotations=s.rotations,
                               reference_centres=s.centres)
        point_nees.append(out.point_nees)
        camera_nees.append(out.camera_nees)
    p, c = np.concatenate(point_nees), np.concatenate(camera_nees)
    assert 2.7 < p.mean() < 3.3
    assert np.mean(p < chi2.ppf(0.99, 3)) > 0.98
    assert 5.0 < c.mean() < 7.0


def test_bad_problems_are_refused_with_the_argument_named():
    s, K, obs, (R, C, X) = small_problem()
    with pytest.raises(InvalidInputError, match="centres must have shape"):
        bundle_adjust(R, C[:-1], X, obs, K)
    with pytest.raises(InvalidInputError, match="loss must be one of"):
        bundle_adjust(R, C, X, obs, K, loss="tukey")
    with pytest.raises(InvalidInputError, match="observation indices"):
        bundle_adjust(R, C, X[:3], obs, K)
    with pytest.raises(InvalidInputError, match="points must be finite"):
        bundle_adjust(R, C, np.where(X > 0.9, np.nan, X), obs, K)
