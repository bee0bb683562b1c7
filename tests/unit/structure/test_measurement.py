"""The streamed rank-3 solver on the tracks array: kernels vs NumPy, answers vs LAPACK and factorize."""

import tracemalloc

import numpy as np
import pytest

from kalmansfm import InvalidInputError
from kalmansfm.structure import factorize, subspace_angle
from kalmansfm.structure.affine import _measurement, factorization

from factorization_scenes import orthographic_scene


def tracks(rng, frames=30, points=700, noise_px=1.0, dtype=np.float64):
    positions, shape, _ = orthographic_scene(rng, frames=frames, points=points, noise_px=noise_px)
    return positions.astype(dtype), shape


def centred_w(positions):
    frames, points = positions.shape[:2]
    w = positions.astype(np.float64).transpose(0, 2, 1).reshape(2 * frames, points)
    return w - w.mean(axis=1, keepdims=True)


def kernel_view(x, planar):
    """The array the kernels index: (F, P, 2) C-ordered, or the C-ordered (F, 2, P) of the same values."""
    return np.ascontiguousarray(x.transpose(0, 2, 1)) if planar else np.ascontiguousarray(x)


@pytest.mark.parametrize("planar", [False, True])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_compiled_kernels_equal_their_numpy_references(dtype, planar):
    rng = np.random.default_rng(0)
    x, _ = tracks(rng, frames=7, points=101, dtype=dtype)  # 101 points: a partial last block
    frames, points = x.shape[:2]
    data = kernel_view(x, planar)
    centroids = x.astype(np.float64).mean(axis=1)
    shift = centroids + rng.normal(size=centroids.shape)
    start = rng.normal(size=(4, points))
    u = np.linalg.qr(rng.normal(size=(2 * frames, 4)))[0].reshape(frames, 2, 4)
    u3 = np.ascontiguousarray(u[:, :, :3])
    xf = x.astype(np.float64)

    for got, want in zip(_measurement._first_pass(data, planar, shift, start),
                         _measurement._first_pass_reference(xf, shift, start)):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
    for got, want in zip(_measurement._round_trip(data, planar, centroids, u, 16),
                         _measurement._round_trip_reference(xf, centroids, u)):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-9)
    point_sums = np.full(points, np.nan)
    z, ry, total = _measurement._projection_pass(data, planar, centroids, u3, 16, point_sums)
    z_ref, ry_ref, total_ref, point_sums_ref = _measurement._projection_pass_reference(xf, centroids, u3)
    np.testing.assert_allclose(z, z_ref, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(ry, ry_ref, rtol=1e-9, atol=1e-6)
    assert total == pytest.approx(total_ref, rel=1e-12)
    np.testing.assert_allclose(point_sums, point_sums_ref, rtol=1e-10)


def test_streamed_rank_equals_lapack_and_its_residual_equals_the_direct_one():
    rng = np.random.default_rng(1)
    x, _ = tracks(rng, noise_px=1.0)
    fit = _measurement.streamed_rank(x, 3, tol=1e-9, max_passes=21, rng=np.random.default_rng(0))
    w = centred_w(x)
    exact = np.linalg.svd(w, full_matrices=False)
    np.testing.assert_allclose(fit.centroids, x.mean(axis=1), rtol=1e-14)
    np.testing.assert_allclose(fit.s, exact.S[:3], rtol=1e-12)
    angle = subspace_angle(fit.u, exact.U[:, :3])
    assert fit.certified and angle <= max(fit.angle_bound, 1e-13) and fit.angle_bound <= 1e-9
    assert subspace_angle(fit.vt.T, exact.Vh[:3].T) < 1e-9
    # the residuals of the rank-3 part, directly
    direct = w - (exact.U[:, :3] * exact.S[:3]) @ exact.Vh[:3]
    frames, points = x.shape[:2]
    np.testing.assert_allclose(fit.point_residual_sums, (direct.reshape(frames, 2, points) ** 2).sum(axis=(0, 1)),
                               rtol=1e-9)
    assert fit.residual_sum == pytest.approx(np.sum(direct**2), rel=1e-12)
    # ‖W‖²_F − Σσᵢ² agrees too, to the precision its cancellation leaves (‖W‖²_F / residual ≈ 10³ here)
    assert fit.residual_sum == pytest.approx(np.sum(w**2) - np.sum(exact.S[:3] ** 2), rel=1e-9)


def test_streamed_rank_stops_on_an_exactly_rank_two_matrix():
    rng = np.random.default_rng(2)
    flat = rng.normal(size=(400, 3)) * [40.0, 30.0, 0.0]
    rotations = np.linalg.qr(rng.normal(size=(12, 3, 3)))[0][:, :2]
    x = np.einsum("fij,pj->fpi", rotations, flat) + 100.0
    fit = _measurement.streamed_rank(x, 3, tol=1e-9, max_passes=21, rng=np.random.default_rng(0))
    assert fit.undetermined and fit.passes <= 4
    np.testing.assert_allclose(fit.s[:2], np.linalg.svd(centred_w(x), compute_uv=False)[:2], rtol=1e-12)
    assert fit.s[2] < 1e-9 * fit.s[0]


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_streamed_rank_declines_nan_and_inf(bad, monkeypatch):
    x, _ = tracks(np.random.default_rng(3))
    x[5, 7, 1] = bad
    # found by the first pass's sums (the compiled kernel) even where the column sample misses it
    sums, squares, _ = _measurement._first_pass(x, False, np.zeros((x.shape[0], 2)), np.zeros((4, x.shape[1])))
    assert not np.isfinite(sums[5, 1]) and not np.isfinite(squares[5, 1]) and np.isfinite(sums[4]).all()
    monkeypatch.setattr(_measurement, "_SAMPLE_POINTS", 8)
    assert _measurement.streamed_rank(x, 3, tol=1e-9, max_passes=21, rng=np.random.default_rng(0)) is None


@pytest.fixture
def stream_everything(monkeypatch):
    """Route every complete unweighted input through the streamed path (normally 2F·P > 2·10⁶)."""
    monkeypatch.setattr(factorization, "_LAPACK_LIMIT", 0)


def test_factorize_streamed_equals_the_lapack_closed_form(stream_everything):
    x, shape = tracks(np.random.default_rng(4), noise_px=0.5)
    streamed = factorize(x)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(factorization, "_LAPACK_LIMIT", 10**12)
        lapack = factorize(x)
    assert streamed.method == lapack.method == "svd" and streamed.warnings == lapack.warnings == ()
    if np.sign(streamed.points[0, 2]) != np.sign(lapack.points[0, 2]):
        streamed = streamed.mirrored()  # the singular vectors' signs pick one of the mirror pair
    for name in ("points", "motion", "image_translation"):
        np.testing.assert_allclose(getattr(streamed, name), getattr(lapack, name), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(streamed.observations.residual_matrix(), lapack.observations.residual_matrix(),
                               rtol=1e-9, atol=1e-9)
    # the lean covariance path of streamed input equals the general one
    np.testing.assert_allclose(streamed.point_covariances, lapack.point_covariances, rtol=1e-9)
    np.testing.assert_array_equal(streamed.point_status, lapack.point_status)
    np.testing.assert_allclose(streamed.details.singular_values[:3], lapack.details.singular_values[:3], rtol=1e-12)
    assert streamed.reprojection_rms == pytest.approx(lapack.reprojection_rms, rel=1e-12)
    used = streamed.observations.used_mask()
    assert used.all() and used.shape == x.shape[:2] and used.dtype == bool
    # the residuals taken from the SVD's last pass are the reprojection distances
    direct = np.sqrt(((streamed.project() - x) ** 2).sum(axis=2))
    np.testing.assert_allclose(streamed.observations.residual_matrix(), direct, rtol=1e-9, atol=1e-10)


def test_factorize_streamed_float32_keeps_float32_residuals(stream_everything):
    x, _ = tracks(np.random.default_rng(5), noise_px=0.5)
    single = x.astype(np.float32)
    rec = factorize(single)
    exact = factorize(single.astype(np.float64))  # the same float32 values, streamed as float64
    assert rec.observations.residual_matrix().dtype == np.float32 and rec.points.dtype == np.float64
    np.testing.assert_allclose(rec.points, exact.points, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(rec.observations.residual_matrix(), exact.observations.residual_matrix(), rtol=1e-6, atol=1e-6)


def test_factorize_streamed_reads_any_layout(stream_everything):
    x, _ = tracks(np.random.default_rng(6))
    fortran = np.asfortranarray(x)
    np.testing.assert_allclose(factorize(fortran).points, factorize(x).points, rtol=1e-12, atol=1e-12)


def test_factorize_large_input_with_holes_or_inf_takes_the_general_path(stream_everything):
    x, _ = tracks(np.random.default_rng(7), frames=10, points=60)
    holes = x.copy()
    holes[2, 3] = np.nan
    assert factorize(holes).method == "als"
    holes[2, 3] = np.inf
    with pytest.raises(InvalidInputError, match="finite"):
        factorize(holes)


@pytest.mark.parametrize("layout", ["C-ordered", "(F, 2, P) in memory"])
def test_factorize_streamed_allocates_little_and_measures_residuals_only_when_asked(stream_everything, layout):
    x, _ = tracks(np.random.default_rng(8), frames=400, points=10_000)
    if layout != "C-ordered":
        x = np.ascontiguousarray(x.transpose(0, 2, 1)).transpose(0, 2, 1)  # as R[:, :2] @ S.T makes it
    factorize(x[:, :100])  # compile outside the measurement
    tracemalloc.start()
    try:
        rec = factorize(x)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # no copy of the (F, P, 2) input (1.0 of it), no (2F, P) W (1.0), no (F, P) residuals (0.5): the start's
    # samples (64 rows, 1024 columns: 0.18 of the input at this size, 0.04 at 1000 x 100 000) and arrays of
    # P numbers (the (P, 3, 3) covariances among them)
    assert rec.method == "svd" and peak < 0.3 * x.nbytes
    # the residual lengths, measured when asked for, are the reprojection distances, and their per-point
    # sums those the fit measured in its last pass
    residuals = rec.observations.residual_matrix()
    direct = np.sqrt(((rec.project() - x) ** 2).sum(axis=2))
    np.testing.assert_allclose(residuals, direct, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(rec.point_reprojection_rms, np.sqrt((direct**2).mean(axis=0)), rtol=1e-9)
    assert rec.reprojection_rms == pytest.approx(np.sqrt(np.mean(direct**2)), rel=1e-9)


def test_streamed_rank_reads_the_planar_layout_in_place_with_the_same_answer():
    x, _ = tracks(np.random.default_rng(9), frames=40, points=900)
    planar = np.ascontiguousarray(x.transpose(0, 2, 1)).transpose(0, 2, 1)
    assert _measurement.readable_in_place(planar) and not planar.flags.c_contiguous
    assert not _measurement.readable_in_place(np.asfortranarray(x))
    a = _measurement.streamed_rank(x, 3, tol=1e-9, max_passes=12, rng=np.random.default_rng(0))
    b = _measurement.streamed_rank(planar, 3, tol=1e-9, max_passes=12, rng=np.random.default_rng(0))
    # the same numbers read in another order: the same sums, bit for bit
    for name in ("u", "s", "vt", "centroids", "point_residual_sums"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.residual_sum == b.residual_sum and a.passes == b.passes


def test_factorize_streamed_says_when_the_subspace_is_not_certified(stream_everything):
    # a nearly flat object: σ3 barely above the noise (σ3/σ4 ≈ 1.3), so the iteration crawls
    rng = np.random.default_rng(10)
    shape = rng.normal(size=(2000, 3)) * [40.0, 30.0, 0.15]
    rotations = np.linalg.qr(rng.normal(size=(100, 3, 3)))[0][:, :2]
    x = shape @ rotations.transpose(0, 2, 1) + 100.0 + rng.normal(size=(100, 2000, 2))
    rec = factorize(x)
    assert any("not clearly rank 3" in w for w in rec.warnings)
    assert any("rank-3 subspace certified only to" in w for w in rec.warnings)
