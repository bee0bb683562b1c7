"""The covariance of a factorized point, judged on data with truth (NEES), and the unreliable-point rules."""

from pathlib import Path

import numpy as np
import pytest
import scipy.io
from scipy.spatial.transform import Rotation

from kalmansfm.errors import InvalidInputError
from kalmansfm.structure import PointStatus, align_affine
from kalmansfm.structure import factorize as reconstruct_affine
from kalmansfm.structure.affine.factorization import factor_affine as factorize
from kalmansfm.structure.affine.uncertainty import MAX_STD_RATIO, MIN_VIEWS, point_uncertainty

HOTEL = Path(__file__).resolve().parents[4] / "shared" / "data" / "cmu_hotel"
CHI2_3_1SIGMA, CHI2_3_3SIGMA = 3.5267, 14.156  # χ²₃ quantiles of 0.6827 and 0.9973


def scene(rng, frames=20, points=150, noise=0.5, turn_deg=20.0, noise_per_point=None):
    """An orthographic scene turning about a random axis; 30 % of the points seen in a window of 2–6 frames."""
    shape = rng.normal(size=(points, 3)) * [80.0, 60.0, 40.0]
    axis = rng.normal(size=3)
    rotations = Rotation.from_rotvec(np.linspace(0, np.radians(turn_deg), frames)[:, None] * axis / np.linalg.norm(axis))
    x = np.einsum("fij,pj->fpi", rotations.as_matrix()[:, :2], shape) + rng.normal(size=(frames, 1, 2)) * 20 + 300
    sigma = np.full(points, noise) if noise_per_point is None else noise_per_point
    x += rng.normal(size=x.shape) * sigma[None, :, None]
    for p in range(int(0.3 * points)):
        length = rng.integers(2, 7)
        start = rng.integers(0, frames - length + 1)
        x[np.r_[0:start, start + length:frames], p] = np.nan
    return shape, x


def affine_nees(estimate, covariances, truth, anchors):
    """NEES after the best affine map onto the truth: the gauge of Σ_p (the motion's common error removed)."""
    fit = align_affine(estimate[anchors], truth[anchors])
    error = estimate @ fit.rotation.T + fit.translation - truth
    mapped = fit.rotation @ covariances @ fit.rotation.T
    return np.einsum("pi,pij,pj->p", error, np.linalg.inv(mapped), error)


@pytest.fixture(scope="module")
def synthetic_nees():
    rng = np.random.default_rng(1)
    values, views, sigma = [], [], []
    for _ in range(20):
        shape, x = scene(rng)
        rec = factorize(x)
        u = point_uncertainty(rec, x)
        values.append(affine_nees(rec.points, u.covariances, shape, u.views == 20))
        views.append(u.views)
        sigma.append(u.noise_std)
    return np.concatenate(values), np.concatenate(views), np.array(sigma)


def test_nees_is_three_on_synthetic_affine_scenes(synthetic_nees):
    """3000 points: mean NEES 3 ± 0.15 (its standard error is 0.045), 1σ and 3σ rates of a χ²₃."""
    nees, views, sigma = synthetic_nees
    assert nees.mean() == pytest.approx(3.0, abs=0.15)
    assert np.mean(nees <= CHI2_3_1SIGMA) == pytest.approx(0.683, abs=0.03)
    assert np.mean(nees <= CHI2_3_3SIGMA) >= 0.99
    # the residual σ, degrees of freedom counted, recovers the true 0.5 px
    assert sigma.mean() == pytest.approx(0.5, abs=0.01)


def test_short_tracks_are_as_honest_as_long_ones(synthetic_nees):
    """The points seen in 2–3 frames (~370 of them): their much larger covariances still fit their errors."""
    nees, views, _ = synthetic_nees
    short = nees[views <= 3]
    assert len(short) > 300
    assert short.mean() == pytest.approx(3.0, abs=0.45)
    assert np.mean(short <= CHI2_3_3SIGMA) >= 0.98


def test_weights_scale_the_unit_noise_not_the_covariance():
    """With per-point noise and weights c/σ² (noise covariance σ̂² W⁻¹), NEES stays near 3 and σ̂ comes out as √c."""
    rng = np.random.default_rng(7)
    values = []
    for _ in range(8):
        noise = rng.uniform(0.3, 1.5, size=150)
        shape, x = scene(rng, noise_per_point=noise)
        weights = np.broadcast_to(7.0 / noise**2, x.shape[:2])
        rec = factorize(x, weights=weights)
        u = point_uncertainty(rec, x, weights=weights)
        assert u.noise_std == pytest.approx(np.sqrt(7.0), rel=0.05)
        values.append(affine_nees(rec.points, u.covariances, shape, u.views == 20))
        # the same weights scaled by 10: the same covariances
        scaled = point_uncertainty(rec, x, weights=10 * weights)
        np.testing.assert_allclose(scaled.covariances, u.covariances, rtol=1e-9)
    assert np.concatenate(values).mean() == pytest.approx(3.0, abs=0.25)


def test_cmu_hotel_landmarks_cut_to_short_windows():
    """Real labels (frames 0–50): landmarks cut to 3, 5 or 8 frames against the factorization of all 51.

    Labelling noise is not Gaussian (heavy tails: the mean NEES is 4–8), so the bulk is checked:
    the median NEES near χ²₃'s 2.37 and most errors within the 3σ ellipsoid.
    """
    mat = scipy.io.loadmat(HOTEL / "tracks" / "cmum.mat", squeeze_me=True, struct_as_record=False)
    x = np.stack([np.asarray(mat["CMUM"].hotel.XTs[k], float).T for k in range(51)]) - 1.0
    reference = factorize(x)
    u_reference = point_uncertainty(reference, x)
    rng = np.random.default_rng(0)
    values = []
    for length in (3, 5, 8):
        for chunk in np.array_split(rng.permutation(30), 6):
            cut = x.copy()
            for p in chunk:
                start = rng.integers(0, 51 - length + 1)
                cut[np.r_[0:start, start + length:51], p] = np.nan
            rec = factorize(cut)
            u = point_uncertainty(rec, cut)
            kept = np.setdiff1d(np.arange(30), chunk)
            fit = align_affine(rec.points[kept], reference.points[kept])
            error = rec.points[chunk] @ fit.rotation.T + fit.translation - reference.points[chunk]
            covariance = fit.rotation @ u.covariances[chunk] @ fit.rotation.T + u_reference.covariances[chunk]
            values += np.einsum("pi,pij,pj->p", error, np.linalg.inv(covariance), error).tolist()
    values = np.array(values)
    assert 1.5 <= np.median(values) <= 3.5
    assert np.mean(values <= CHI2_3_3SIGMA) >= 0.9


def test_status_rules_views_and_the_uncertainty_bound():
    rng = np.random.default_rng(3)
    shape = rng.normal(size=(40, 3)) * 50
    rotations = Rotation.from_rotvec(rng.normal(size=(12, 3)) * 0.3).as_matrix()
    x = np.einsum("fij,pj->fpi", rotations[:, :2], shape) + 200 + rng.normal(scale=0.3, size=(12, 40, 2))
    x[3:, 0] = np.nan  # point 0: 3 views, below MIN_VIEWS
    x[4:, 1] = np.nan  # point 1: 4 views
    rec = factorize(x)
    u = point_uncertainty(rec, x)
    assert u.views[:3].tolist() == [3, 4, 12]
    assert u.status[0] == PointStatus.UNRELIABLE and u.status[1] == PointStatus.OK == u.status[2]
    assert u.bound_px == pytest.approx(MAX_STD_RATIO * u.radius_px)
    # a bound below the points' own uncertainty marks them all; min_views 3 accepts point 0
    assert not point_uncertainty(rec, x, max_std_ratio=1e-6).reliable.any()
    assert point_uncertainty(rec, x, min_views=3).reliable[0]
    assert MIN_VIEWS == 4
    assert "1 of 40 reconstructed points are unreliable (1 seen in fewer than 4 frames" in u.warnings[0]


def test_points_left_out_get_their_reason_and_every_point_its_residual_rms():
    rng = np.random.default_rng(4)
    shape = rng.normal(size=(20, 3)) * 50
    rotations = Rotation.from_rotvec(rng.normal(size=(8, 3)) * 0.3).as_matrix()
    x = np.einsum("fij,pj->fpi", rotations[:, :2], shape) + 200 + rng.normal(scale=0.3, size=(8, 20, 2))
    x[1:, 0] = np.nan  # point 0: one view, the factorization leaves it out
    rec = factorize(x)
    u = point_uncertainty(rec, x)
    assert np.isnan(rec.points[0]).all() and u.status[0] == PointStatus.TOO_FEW_VIEWS
    assert np.isnan(u.reprojection_rms[0]) and u.warnings == ()
    # the point's RMS is that of the factorization's own residual distances over the frames that saw it
    expected = np.sqrt(np.nanmean(rec.residuals[:, 1:] ** 2, axis=0))
    np.testing.assert_allclose(u.reprojection_rms[1:], expected, rtol=1e-12)


def test_a_point_seen_while_the_camera_barely_turned_is_unreliable_in_depth():
    """Seen in 6 frames that turn 0.05° in all, while the rest of the sequence turns 30°: its depth is unconstrained."""
    rng = np.random.default_rng(5)
    shape = rng.normal(size=(30, 3)) * 50
    angles = np.concatenate([np.linspace(0, 0.05, 6), np.linspace(1, 30, 10)])
    rotations = Rotation.from_rotvec(np.radians(angles)[:, None] * [0.3, 1.0, 0.1] / np.linalg.norm([0.3, 1.0, 0.1]))
    x = np.einsum("fij,pj->fpi", rotations.as_matrix()[:, :2], shape) + 200 + rng.normal(scale=0.3, size=(16, 30, 2))
    x[6:, 0] = np.nan
    rec = factorize(x)
    u = point_uncertainty(rec, x)
    assert u.views[0] == 6
    std = np.sqrt(np.diag(u.covariances[0]))
    assert std[2] > 100 * max(std[0], std[1])  # about σ / sin(0.05°) in Z
    assert u.largest_std[0] > u.bound_px
    assert u.status[0] == PointStatus.UNRELIABLE
    assert u.reliable[1:].all()


def test_bad_arguments_name_themselves():
    x = np.random.default_rng(0).normal(size=(5, 6, 2))
    rec = factorize(x)
    with pytest.raises(InvalidInputError, match=r"positions must have the reconstruction's shape \(5, 6, 2\)"):
        point_uncertainty(rec, x[:4])
    with pytest.raises(InvalidInputError, match="weights must have shape"):
        point_uncertainty(rec, x, weights=np.ones((5, 5)))
    with pytest.raises(InvalidInputError, match="weights must be finite and >= 0"):
        point_uncertainty(rec, x, weights=-np.ones((5, 6)))
    with pytest.raises(InvalidInputError, match="min_views must be an integer >= 2"):
        point_uncertainty(rec, x, min_views=1)
    with pytest.raises(InvalidInputError, match="max_std_ratio must be a finite number > 0"):
        point_uncertainty(rec, x, max_std_ratio=0.0)


def test_the_reconstruction_carries_the_same_covariances_status_and_noise():
    shape, x = scene(np.random.default_rng(11))
    weights = np.where(np.isfinite(x[..., 0]), 2.0, 0.0)
    u = point_uncertainty(factorize(x, weights=weights), x, weights=weights)
    rec = reconstruct_affine(x, weights=weights)
    np.testing.assert_array_equal(rec.point_covariances, u.covariances)
    np.testing.assert_array_equal(rec.point_status, u.status)
    np.testing.assert_array_equal(rec.views, u.views)
    assert rec.noise.std == u.noise_std and rec.noise.degrees_of_freedom == u.dof and rec.noise.unit == "unit weight"
    assert rec.details.bound == pytest.approx(u.bound_px) and rec.warnings[:len(u.warnings)] == u.warnings
