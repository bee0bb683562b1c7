"""Segmented calibrated reconstruction of a long video-ordered sequence of short tracks (issue 29)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm.errors import InvalidInputError, NotEnoughDataError
from kalmansfm.scenes.perspective import sliding_sequence
from kalmansfm.structure import Observations
from kalmansfm.structure.geometry.alignment import align_similarity
from kalmansfm.structure.perspective import PerspectiveSettings
from kalmansfm.structure.perspective import segmented
from kalmansfm.structure.perspective.segmented import (
    SEGMENTED_GAUGE,
    fits_dense_reconstruction,
    reconstruct_segmented,
    robust_similarity,
    window_stop,
)

STEP = 0.02  # sliding_sequence's default


@pytest.fixture(scope="module")
def sequence():
    s = sliding_sequence(300, 900)
    return s.observations, s.cameras, s.points, s.outliers


@pytest.fixture(scope="module")
def result(sequence):
    obs, cams, _, _ = sequence
    return reconstruct_segmented(obs, cams.decompose().intrinsics, window_frames=80, overlap_frames=25)


def aligned_to_truth(rec, cams, points):
    """The registered centres and rotations after the one similarity (centres and points) onto the truth."""
    reg, ok = rec.registered, rec.reconstructed
    fit = align_similarity(np.concatenate([rec.centres[reg], rec.points[ok]]),
                           np.concatenate([cams.centers[reg], points[ok]]))
    centres = fit.aligned[: reg.sum()]
    turned = rec.rotations[reg] @ fit.rotation.T @ np.swapaxes(cams.decompose().rotations[reg], 1, 2)
    angles = np.degrees(np.arccos(np.clip((np.trace(turned, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return centres, angles


def test_the_chained_cameras_are_the_truth_up_to_one_similarity(sequence, result):
    obs, cams, points, _ = sequence
    rec = result
    assert rec.kind == "perspective" and rec.method == "segmented" and rec.covariance_gauge == SEGMENTED_GAUGE
    assert rec.registered.sum() >= 290  # a few frames at the sequence's ends see too few tracks
    centres, angles = aligned_to_truth(rec, cams, points)
    error = np.linalg.norm(centres - cams.centers[rec.registered], axis=1)
    path = STEP * 300
    assert np.median(error) < 0.005 * path and error.max() < 0.02 * path
    assert np.median(angles) < 0.5 and angles.max() < 2.0
    # scale drift along the chain: every 50-frame stretch has the truth's length within a few per cent
    frames = np.flatnonzero(rec.registered)
    a = np.flatnonzero(np.isin(frames + 50, frames))
    b = np.searchsorted(frames, frames[a] + 50)
    ratio = np.linalg.norm(centres[b] - centres[a], axis=1) / np.linalg.norm(
        cams.centers[frames[b]] - cams.centers[frames[a]], axis=1)
    assert 0.95 < ratio.min() and ratio.max() < 1.05


def test_points_residuals_and_noise_are_at_the_noise_level(sequence, result):
    obs, cams, points, wild = sequence
    rec = result
    assert rec.noise.std == pytest.approx(0.5, rel=0.1) and rec.noise.estimated
    assert rec.reprojection_rms < 0.5 * np.sqrt(2) * 1.15
    assert rec.reconstructed.sum() > 0.8 * rec.n_points
    # the observations are the input's, per observation; the gross mismatches are rejected
    assert len(rec.observations) == len(obs) and rec.observations.shape == obs.shape
    out, given = rec.observations, obs
    out_order = np.argsort(out.frame * obs.shape[1] + out.point)
    given_order = np.argsort(given.frame * obs.shape[1] + given.point)
    assert np.array_equal(out.xy[out_order], given.xy[given_order])
    used = out.used[out_order]
    assert used[wild[given_order]].mean() < 0.1 and used[~wild[given_order]].mean() > 0.9
    # the RMS is over the observations of the reconstructed points that the outlier test kept
    kept = ~out.rejected & rec.reconstructed[out.point] & np.isfinite(out.residual)
    assert np.sqrt(np.mean(out.residual[kept] ** 2)) == pytest.approx(rec.reprojection_rms, rel=1e-5)
    # covariances given the cameras: finite for the points, and the warning says how the result was made
    assert np.isfinite(rec.point_covariances[rec.reconstructed]).all()
    assert np.isfinite(rec.pose_covariances[rec.registered]).all()
    assert "windows" in rec.warnings[0]


def test_robust_similarity_recovers_an_exact_transform():
    rng = np.random.default_rng(1)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    Q *= np.sign(np.linalg.det(Q))
    source = rng.normal(size=(40, 3)) * 3
    target = 0.37 * source @ Q.T + np.array([4.0, -2.0, 9.0])
    target[[3, 17]] += 5.0  # two wrong matches
    fit = robust_similarity(source, target)
    assert fit.scale == pytest.approx(0.37, abs=1e-9)
    assert np.abs(fit.rotation - Q).max() < 1e-9 and np.abs(fit.translation - [4.0, -2.0, 9.0]).max() < 1e-9
    assert fit.inliers.sum() == 38 and not fit.inliers[[3, 17]].any()
    assert np.abs(fit.apply(source[fit.inliers]) - target[fit.inliers]).max() < 1e-9


def test_robust_similarity_needs_enough_matches():
    with pytest.raises(NotEnoughDataError, match=">= 10 matches"):
        robust_similarity(np.ones((5, 3)), np.ones((5, 3)))


@settings(max_examples=50, deadline=None)
@given(st.integers(2, 2000), st.integers(2, 300), st.data())
def test_windows_walked_from_the_first_frame_cover_every_frame_and_overlap(n_frames, window, data):
    overlap = data.draw(st.integers(0, window - 1))
    covered = np.zeros(n_frames, int)
    start, spans = 0, []
    while True:
        stop = window_stop(start, n_frames, window, overlap)
        spans.append((start, stop))
        covered[start:stop] += 1
        if stop >= n_frames:
            break
        start = stop - overlap
    assert covered.min() >= 1 and spans[-1][1] == n_frames
    # full windows, the last one up to half a step longer; each begins after the one before
    assert all(stop - start == window for start, stop in spans[:-1])
    assert spans[-1][1] - spans[-1][0] <= window + (window - overlap) // 2 or n_frames <= window
    assert all(b[0] > a[0] for a, b in zip(spans, spans[1:]))


def test_bad_windows_and_inputs_are_refused():
    with pytest.raises(InvalidInputError, match="overlap"):
        window_stop(0, 100, 50, 50)
    with pytest.raises(InvalidInputError, match="Observations"):
        reconstruct_segmented(np.zeros((3, 4, 2)), np.eye(3))


def test_the_size_threshold():
    assert fits_dense_reconstruction((36, 4983)) and not fits_dense_reconstruction((20000, 50047))
    assert not fits_dense_reconstruction((segmented.DENSE_MAX_FRAMES + 1, 10))


def test_a_sequence_cut_in_two_keeps_its_longer_part_and_says_where_it_broke():
    s = sliding_sequence(220, 650, seed=5)
    obs = s.observations
    # no track crosses frames 150-169: the parts before and after share nothing
    before = np.zeros(obs.shape[1], bool)
    after = np.zeros(obs.shape[1], bool)
    before[obs.point[obs.frame < 150]] = True
    after[obs.point[obs.frame >= 170]] = True
    keep = (before ^ after)[obs.point] & ((obs.frame < 150) | (obs.frame >= 170))
    cut = Observations.from_sparse(obs.shape, obs.frame[keep], obs.point[keep], obs.xy[keep])
    rec = reconstruct_segmented(cut, s.cameras.decompose().intrinsics, window_frames=60, overlap_frames=20)
    frames = np.flatnonzero(rec.registered)
    assert frames.max() < 150 and frames.size > 130
    assert any("broke 1 times" in w and "could not be chained" in w for w in rec.warnings)
    assert any("tried again (lower registration thresholds, then a shorter span)" in w for w in rec.warnings)
    assert np.isnan(rec.points[after & ~before]).all() and rec.reconstructed[before].mean() > 0.8


def test_the_recursive_method_is_not_used_for_windows_and_the_result_says_so():
    s = sliding_sequence(120, 360, seed=6)
    rec = reconstruct_segmented(s.observations, s.cameras.decompose().intrinsics, PerspectiveSettings(method="recursive"),
                                window_frames=70, overlap_frames=20)
    assert rec.registered.sum() > 100 and any("batch method, not 'recursive'" in w for w in rec.warnings)
