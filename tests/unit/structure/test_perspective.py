"""Calibrated reconstruction with unknown motion: accuracy, consistency, outliers, degenerate input."""

import numpy as np
import pytest
from scipy.stats import chi2

from kalmansfm.errors import InvalidInputError, NotEnoughDataError
from kalmansfm.scenes.perspective import perspective_scene
from kalmansfm.structure import PointStatus
from kalmansfm.structure.perspective.bundle import compare_in_gauge
from kalmansfm.structure.perspective.reconstruct import (
    FrameStatus,
    PerspectiveSettings,
    reconstruct_perspective,
)


def aligned_errors(rec, scene):
    """The comparison in the free-network gauge: points (reconstructed ones) and, for the batch method whose
    camera covariances are in that gauge, cameras (registered ones)."""
    ok, reg = rec.reconstructed, rec.registered
    if rec.method != "batch":
        return compare_in_gauge(rec.points[ok], rec.point_covariances[ok], scene.points[ok],
                                centres=rec.centres[reg], reference_centres=scene.centres[reg])
    return compare_in_gauge(rec.points[ok], rec.point_covariances[ok], scene.points[ok],
                            rotations=rec.rotations[reg], centres=rec.centres[reg],
                            camera_covariances=rec.pose_covariances[reg], reference_rotations=scene.rotations[reg],
                            reference_centres=scene.centres[reg])


@pytest.fixture(scope="module")
def walkarounds():
    """Four walk-arounds with 3 % gross outliers and partial tracks, reconstructed by bundle adjustment."""
    out = []
    for seed in range(4):
        s = perspective_scene(frames=10, points=400, pixel_std=0.7, outlier_fraction=0.03, seed=seed)
        out.append((s, reconstruct_perspective(s.observations, s.intrinsics)))
    return out


def test_points_are_accurate_and_their_gauge_covariances_consistent(walkarounds):
    nees, reconstructed = [], []
    for scene, rec in walkarounds:
        assert rec.registered.all()
        reconstructed.append(rec.reconstructed.mean())
        out = aligned_errors(rec, scene)
        e = out.point_errors
        nees.append(out.point_nees)
        # the pixel noise is recovered from the residuals (degrees of freedom counted)
        assert rec.noise.std == pytest.approx(scene.pixel_std, rel=0.06)
        assert np.median(np.linalg.norm(e, axis=1)) < 0.01  # object radius ~1.7
    n = np.concatenate(nees)
    assert 2.5 < n.mean() < 3.5
    assert np.mean(n < chi2.ppf(0.99, 3)) >= 0.97
    assert min(reconstructed) >= 0.95


def test_camera_centres_within_half_a_percent_of_the_viewing_distance(walkarounds):
    nees = []
    for scene, rec in walkarounds:
        out = aligned_errors(rec, scene)
        assert np.linalg.norm(out.centre_errors, axis=1).max() < 0.005 * scene.viewing_distance
        # and the camera covariances (same gauge) describe those errors
        nees.append(out.camera_nees)
    assert 3.5 < np.concatenate(nees).mean() < 8.0  # 6 degrees of freedom


def test_gross_outliers_are_rejected_and_good_observations_kept(walkarounds):
    for scene, rec in walkarounds:
        seen = np.isfinite(scene.observations[..., 0]) & rec.reconstructed[None]
        planted = scene.outliers & seen
        assert np.mean(~rec.observations.used_mask()[planted]) > 0.9
        good = seen & ~scene.outliers
        assert np.mean(~rec.observations.used_mask()[good]) < 0.02


def test_output_frame_is_the_initial_pairs_first_camera_with_unit_baseline(walkarounds):
    rec = walkarounds[0][1]
    a, b = rec.details.initial_pair
    np.testing.assert_allclose(rec.rotations[a], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(rec.centres[a], 0.0, atol=1e-12)
    assert np.linalg.norm(rec.centres[b]) == pytest.approx(1.0, rel=1e-12)


def test_reconstruction_is_reproducible():
    s = perspective_scene(frames=6, points=120, outlier_fraction=0.03, seed=7)
    first = reconstruct_perspective(s.observations, s.intrinsics)
    second = reconstruct_perspective(s.observations, s.intrinsics)
    np.testing.assert_array_equal(first.points, second.points)
    np.testing.assert_array_equal(first.observations.used_mask(), second.observations.used_mask())


def test_planar_scene_is_refused_as_degenerate():
    s = perspective_scene(frames=8, points=200, layout="planar", outlier_fraction=0.02, seed=1)
    with pytest.raises(NotEnoughDataError, match="degenerate scene.*plane.*only rotates"):
        reconstruct_perspective(s.observations, s.intrinsics)


def test_pure_rotation_is_refused_as_degenerate():
    s = perspective_scene(frames=8, points=200, layout="rotation", seed=1)
    with pytest.raises(NotEnoughDataError, match="degenerate scene"):
        reconstruct_perspective(s.observations, s.intrinsics)
    with pytest.raises(NotEnoughDataError, match="parallax"):
        reconstruct_perspective(s.observations, s.intrinsics, method="recursive")


def test_too_few_shared_tracks_are_refused():
    s = perspective_scene(frames=4, points=20, seed=2)
    with pytest.raises(NotEnoughDataError, match="no two frames share >= 24 tracks"):
        reconstruct_perspective(s.observations, s.intrinsics)


@pytest.mark.parametrize("method", ["batch", "recursive"])
def test_a_sequence_that_falls_apart_leaves_one_piece_unregistered(method):
    s = perspective_scene(frames=10, points=400, seed=2)
    obs = s.observations.copy()
    first = np.arange(400) < 200
    obs[5:, first] = np.nan
    obs[:5, ~first] = np.nan
    rec = reconstruct_perspective(obs, s.intrinsics, method=method)
    pieces = {tuple(np.flatnonzero(rec.registered))}
    assert pieces <= {(0, 1, 2, 3, 4), (5, 6, 7, 8, 9)}
    assert np.isnan(rec.rotations[~rec.registered]).all()
    assert set(rec.frame_status[~rec.registered]) <= {FrameStatus.NOT_CONNECTED, FrameStatus.POSE_FAILED}
    assert any("could not be registered" in w for w in rec.warnings)
    # tracks of the lost piece have no point, and say why
    lost = ~rec.reconstructed
    assert np.isnan(rec.points[lost]).all()
    assert set(rec.point_status[lost]) <= {PointStatus.TOO_FEW_VIEWS, PointStatus.DEGENERATE}


def test_recursive_method_follows_batch_on_wide_steps():
    """The report's recursive fusion: close to bundle adjustment with 12° between frames, honestly reported."""
    errors = {"batch": [], "recursive": []}
    nees = []
    for seed in range(3):
        s = perspective_scene(frames=6, points=300, arc_degrees=60, outlier_fraction=0.03, seed=seed)
        for method in errors:
            rec = reconstruct_perspective(s.observations, s.intrinsics, method=method)
            assert rec.method == method and rec.registered.all()
            out = aligned_errors(rec, s)
            errors[method].append(np.median(np.linalg.norm(out.point_errors, axis=1)))
            if method == "recursive":
                nees.append(out.point_nees)
    assert np.median(errors["recursive"]) < 4 * np.median(errors["batch"])
    # per-point filtering ignores the correlation through the shared motion: over-confident (docs/perspective.md)
    n = np.concatenate(nees)
    assert 2.5 < n.mean() < 10.0
    assert np.mean(n < chi2.ppf(0.99, 3)) > 0.7


def test_bad_input_is_refused_with_the_argument_named():
    s = perspective_scene(frames=3, points=30, seed=0)
    K = s.intrinsics.copy()
    K[1] = np.nan
    with pytest.raises(InvalidInputError, match="intrinsics missing .* frame 1"):
        reconstruct_perspective(s.observations, K)
    K = s.intrinsics.copy()
    K[2, 1, 1] = 0.0
    with pytest.raises(InvalidInputError, match="intrinsics of frame 2 .* singular"):
        reconstruct_perspective(s.observations, K)
    with pytest.raises(InvalidInputError, match="one K per frame"):
        reconstruct_perspective(s.observations, s.intrinsics[:2])
    with pytest.raises(NotEnoughDataError, match=">= 2 frames"):
        reconstruct_perspective(s.observations[:1], s.intrinsics[:1])
    with pytest.raises(InvalidInputError, match="method must be one of batch, recursive"):
        PerspectiveSettings(method="sfm")
    with pytest.raises(InvalidInputError, match="refinement_rounds"):
        PerspectiveSettings(refinement_rounds=-1)
    bad = s.observations.copy()
    bad[0, 0, 0] = np.inf
    with pytest.raises(InvalidInputError, match="frame 0, point 0"):
        reconstruct_perspective(bad, s.intrinsics)


def test_a_keyword_beside_settings_is_refused_not_silently_overridden():
    s = perspective_scene(frames=3, points=30, seed=0)
    with pytest.raises(InvalidInputError, match="inside settings"):
        reconstruct_perspective(s.observations, s.intrinsics, method="recursive", settings=PerspectiveSettings())
    with pytest.raises(InvalidInputError, match="inside settings"):
        reconstruct_perspective(s.observations, s.intrinsics, outlier_threshold_px=2.0,
                                settings=PerspectiveSettings())


def test_settled_tracks_are_those_a_full_fusion_gives_back_unchanged():
    """The refinement fuses again only the tracks its outlier test flags; fusing every track must agree:
    the settled ones keep their points (to the fusion's convergence) and all their observations."""
    from kalmansfm.structure.perspective.incremental import _Incremental

    s = perspective_scene(frames=10, points=400, pixel_std=0.7, outlier_fraction=0.03, seed=1)
    state = _Incremental(s.observations, np.broadcast_to(s.intrinsics, (10, 3, 3)).copy(), PerspectiveSettings())
    state.initialize()
    state.grow()
    state.refine()
    gate = 2.5
    settled = state._settled(gate)
    # outliers were injected: some tracks hold rejected observations, and they are never settled
    registered = state.registered
    rejected = (state.seen & ~state.inlier)[registered].any(axis=0)
    assert rejected.any() and not (settled & rejected).any()
    assert settled.sum() > 0.8 * state.has_point.sum()
    points, inlier = state.X.copy(), state.inlier.copy()
    frames = np.flatnonzero(registered)
    state._triangulate(np.flatnonzero(state.seen[frames].sum(axis=0) >= 2), gate_px=gate, readmit=True)
    np.testing.assert_array_equal(state.inlier[:, settled], inlier[:, settled])
    scale = np.linalg.norm(points[settled], axis=1)
    assert np.all(np.linalg.norm(state.X[settled] - points[settled], axis=1) < 1e-5 * scale)


def test_a_start_from_some_tracks_reaches_the_reconstruction_from_scratch(walkarounds):
    """Started from the poses of a rough reconstruction (no refinement rounds) of a fifth of the tracks, the
    reconstruction of all of them lands where the one from an initial pair does (the same least-squares optimum,
    up to the gauge), in the start's frame."""
    from kalmansfm.structure.geometry.alignment import align_similarity

    scene, full = walkarounds[1]
    some = reconstruct_perspective(scene.observations[:, ::5], scene.intrinsics,
                                   settings=PerspectiveSettings(refinement_rounds=0))
    started = reconstruct_perspective(scene.observations, scene.intrinsics, start=some)
    assert started.details.initial_pair == some.details.initial_pair
    a, b = some.details.initial_pair
    np.testing.assert_allclose(started.centres[a], 0.0, atol=1e-12)
    assert np.linalg.norm(started.centres[b]) == pytest.approx(1.0, rel=1e-12)
    assert started.registered.all()
    np.testing.assert_array_equal(started.observations.used_mask(), full.observations.used_mask())
    assert started.noise.std == pytest.approx(full.noise.std, rel=1e-5)
    both = np.concatenate([started.centres, started.points[full.reconstructed]])
    alignment = align_similarity(both, np.concatenate([full.centres, full.points[full.reconstructed]]))
    assert alignment.rms < 1e-5 * np.linalg.norm(full.centres, axis=1).max()


def test_a_start_that_does_not_fit_is_refused():
    s = perspective_scene(frames=6, points=120, seed=2)
    rec = reconstruct_perspective(s.observations, s.intrinsics)
    with pytest.raises(InvalidInputError, match="same 5 frames; got a perspective reconstruction of 6 frames"):
        reconstruct_perspective(s.observations[:5], s.intrinsics[:5], start=rec)
    with pytest.raises(InvalidInputError, match="start poses are for the batch method"):
        reconstruct_perspective(s.observations, s.intrinsics, settings=PerspectiveSettings(method="recursive"),
                                start=rec)
