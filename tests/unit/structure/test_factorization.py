from pathlib import Path

import numpy as np
import pytest

from kalmansfm import NotEnoughDataError, InvalidInputError
from kalmansfm.structure import align_similarity, factorize, metric_upgrade

from factorization_scenes import orthographic_scene

HOUSE = Path(__file__).resolve().parents[3] / ".." / "shared" / "data" / "cmu_house" / "labels"


def relative_shape_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    fit = align_similarity(estimate, truth, allow_reflection=True)
    radius = np.sqrt(np.mean(np.sum((truth - truth.mean(axis=0)) ** 2, axis=1)))
    return fit.rms / radius


def test_noise_free_scene_recovers_shape_and_orthonormal_motion():
    positions, shape, _ = orthographic_scene(np.random.default_rng(1))
    rec = factorize(positions)
    assert rec.method == "svd" and rec.warnings == ()
    assert relative_shape_error(rec.points, shape) < 1e-6
    gram = rec.motion @ rec.motion.transpose(0, 2, 1)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(2), gram.shape), atol=1e-9)
    np.testing.assert_allclose(rec.motion[0], np.eye(3)[:2], atol=1e-9)  # gauge
    np.testing.assert_allclose(rec.points.mean(axis=0), 0.0, atol=1e-9)
    assert rec.reprojection_rms < 1e-9
    np.testing.assert_allclose(rec.project(), positions, atol=1e-8)


def test_the_mirror_image_explains_the_data_equally_well():
    positions, shape, _ = orthographic_scene(np.random.default_rng(2))
    rec = factorize(positions)
    mirror = rec.mirrored()
    np.testing.assert_allclose(mirror.project(), positions, atol=1e-8)
    assert relative_shape_error(mirror.points, shape) < 1e-6
    # Exactly one of the pair is a proper rotation of the truth.
    proper = [align_similarity(p, shape).rms < 1e-6 for p in (rec.points, mirror.points)]
    assert sorted(proper) == [False, True]


def test_complete_data_residual_is_the_rank3_floor():
    positions, _, _ = orthographic_scene(np.random.default_rng(3), noise_px=0.5)
    rec = factorize(positions)
    frames, points = positions.shape[:2]
    w = positions.transpose(0, 2, 1).reshape(2 * frames, points)
    s = np.linalg.svd(w - w.mean(axis=1, keepdims=True), compute_uv=False)
    np.testing.assert_allclose(rec.details.singular_values, s, rtol=1e-10)
    assert rec.reprojection_rms == pytest.approx(np.sqrt(np.sum(s[3:] ** 2) / (frames * points)), rel=1e-9)


@pytest.mark.parametrize("pattern", ["random", "occluder"])
def test_missing_data_matches_complete_answer(pattern):
    rng = np.random.default_rng(4)
    positions, shape, _ = orthographic_scene(rng, frames=15, points=30)
    holes = positions.copy()
    if pattern == "random":
        holes[rng.random(holes.shape[:2]) < 0.3] = np.nan
    else:  # a band of points hidden by an occluder for a stretch of frames, tracks starting late
        holes[4:11, 5:17] = np.nan
        holes[:6, 25:] = np.nan
    rec = factorize(holes)
    complete = factorize(positions)
    assert rec.method == "als" and rec.warnings == ()
    assert relative_shape_error(rec.points, complete.points) < 1e-6
    assert relative_shape_error(rec.points, shape) < 1e-6
    np.testing.assert_allclose(rec.project(), positions, atol=1e-5)
    assert np.isnan(rec.observations.residual_matrix()[~rec.observations.used_mask()]).all()


def test_unreachable_points_and_frames_are_nan_and_flagged():
    positions, _, _ = orthographic_scene(np.random.default_rng(5), frames=8, points=12)
    positions[:, 0] = np.nan  # never seen
    positions[1:, 1] = np.nan  # seen once
    positions[3, 2:] = np.nan  # frame 3 sees only point 1... and nothing usable
    rec = factorize(positions)
    assert np.isnan(rec.points[:2]).all() and np.isfinite(rec.points[2:]).all()
    assert np.isnan(rec.motion[3]).all()
    assert any("fewer than 2" in w for w in rec.warnings)
    assert any("fewer than 4" in w for w in rec.warnings)


def test_weights_downweight_bad_entries():
    rng = np.random.default_rng(6)
    positions, shape, _ = orthographic_scene(rng, frames=10, points=20, noise_px=0.05)
    noisy = positions.copy()
    bad = rng.random(noisy.shape[:2]) < 0.15
    noisy[bad] += rng.normal(scale=15.0, size=(bad.sum(), 2))
    std = np.where(bad, 15.0, 0.05)
    weighted = factorize(noisy, weights=1.0 / std**2)
    plain = factorize(noisy)
    assert weighted.method == "als"
    assert relative_shape_error(weighted.points, shape) < 0.1 * relative_shape_error(plain.points, shape)
    assert relative_shape_error(weighted.points, shape) < 2e-3


def test_per_coordinate_weights_equal_per_entry_weights_when_equal():
    rng = np.random.default_rng(7)
    positions, _, _ = orthographic_scene(rng, noise_px=1.0)
    w = rng.uniform(0.5, 2.0, size=positions.shape[:2])
    a = factorize(positions, weights=w)
    b = factorize(positions, weights=np.repeat(w[:, :, None], 2, axis=2))
    np.testing.assert_allclose(a.points, b.points, atol=1e-9)


def test_uniform_weights_are_the_closed_form():
    positions, _, _ = orthographic_scene(np.random.default_rng(8), noise_px=1.0)
    a = factorize(positions, weights=np.full(positions.shape[:2], 4.0))
    b = factorize(positions)
    assert a.method == "svd"
    np.testing.assert_allclose(a.points, b.points)


def test_weighted_als_converges_to_svd_answer_with_uniform_nonconstant_layout():
    # weights equal except one entry set to zero: ALS over all-but-one entry; with the entry
    # consistent with the model, the answer equals the complete closed form.
    positions, _, _ = orthographic_scene(np.random.default_rng(9))
    w = np.ones(positions.shape[:2])
    w[2, 3] = 0.0
    rec = factorize(positions, weights=w)
    assert rec.method == "als" and not rec.observations.used_mask()[2, 3]
    np.testing.assert_allclose(rec.project(), positions, atol=1e-6)


@pytest.mark.parametrize(("frames", "points"), [(2, 10), (5, 3)])
def test_too_few_frames_or_points(frames, points):
    with pytest.raises(NotEnoughDataError, match="3 frames and >= 4 points"):
        factorize(np.zeros((frames, points, 2)))


def test_all_nan_is_not_enough_data():
    with pytest.raises(NotEnoughDataError, match="all NaN"):
        factorize(np.full((5, 6, 2), np.nan))


@pytest.mark.parametrize(
    ("value", "kwargs", "message"),
    [
        (np.zeros((5, 6)), {}, "shape"),
        (np.full((5, 6, 2), np.inf), {}, "finite"),
        (np.zeros((5, 6, 2)), {"weights": -np.ones((5, 6))}, "weights"),
        (np.zeros((5, 6, 2)), {"weights": np.ones((5, 7))}, "weights must have shape"),
        (np.zeros((5, 6, 2)), {"max_iterations": -5}, r"max_iterations must be an integer >= 1; got -5"),
        (np.zeros((5, 6, 2)), {"max_iterations": 0}, r"max_iterations must be an integer >= 1; got 0"),
        (np.zeros((5, 6, 2)), {"max_iterations": 2.5}, r"max_iterations must be an integer >= 1; got 2.5"),
        (np.zeros((5, 6, 2)), {"max_iterations": True}, r"max_iterations must be an integer >= 1; got True"),
        (np.zeros((5, 6, 2)), {"tol": -1e-3}, r"tol must be a finite number >= 0"),
        (np.zeros((5, 6, 2)), {"tol": float("nan")}, r"tol must be a finite number >= 0"),
    ],
)
def test_invalid_input(value, kwargs, message):
    with pytest.raises(InvalidInputError, match=message):
        factorize(value, **kwargs)


def test_coplanar_points_are_flagged():
    rng = np.random.default_rng(10)
    positions, shape, rotations = orthographic_scene(rng)
    flat = shape * [1.0, 1.0, 0.0]
    positions = np.einsum("fij,pj->fpi", rotations[:, :2], flat) + 50.0
    rec = factorize(positions)
    assert any("coplanar" in w for w in rec.warnings)
    assert any("not clearly rank 3" in w for w in rec.warnings)


def test_no_rotation_is_flagged():
    rng = np.random.default_rng(11)
    positions, _, _ = orthographic_scene(rng)
    angles = rng.uniform(0, np.pi, size=len(positions))
    in_plane = np.stack([[[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]] for a in angles])
    moved = np.einsum("fij,pj->fpi", in_plane, positions[0]) + rng.uniform(0, 50, (len(positions), 1, 2))
    rec = factorize(moved)
    assert any("no rotation out of the image plane" in w for w in rec.warnings)


def test_non_positive_definite_metric_matrix_is_repaired_and_flagged():
    r2 = np.sqrt(2.0)
    # Affine rows whose exact metric solution is A = diag(1, 1, -1).
    rows = np.array(
        [[r2, 0, 1], [0, 1, 0], [1, 0, 0], [0, r2, 1], [1, 0, 0], [0, 1, 0], [0, r2, 1], [1, 0, 0]], dtype=float
    )
    notes = []
    a, q = metric_upgrade(rows, notes)
    assert any("not positive definite" in n for n in notes)
    assert np.linalg.eigvalsh(a)[0] > 0
    np.testing.assert_allclose(q @ q.T, a, atol=1e-12)


def test_metric_upgrade_recovers_known_ambiguity():
    rng = np.random.default_rng(12)
    _, _, rotations = orthographic_scene(rng, frames=6)
    mix = rng.normal(size=(3, 3))
    affine = rotations[:, :2].reshape(-1, 3) @ np.linalg.inv(mix)
    a, q = metric_upgrade(affine)
    np.testing.assert_allclose(a, mix @ mix.T, rtol=1e-9, atol=1e-9)


# Real data: the 30 hand-labelled CMU house landmarks, 111 frames, all visible.
@pytest.fixture(scope="module")
def house() -> np.ndarray:
    if not HOUSE.is_dir():
        pytest.fail(f"real data missing: {HOUSE}")
    # label file house{k} belongs to frame k - 1; labels are 1-based pixel coordinates
    return np.stack([np.loadtxt(HOUSE / f"house{f + 1}") for f in range(111)]) - 1.0


def test_cmu_house_residual_is_the_rank3_floor(house):
    rec = factorize(house)
    assert rec.reprojection_rms == pytest.approx(0.995, abs=5e-4)  # 0.99508 measured
    lengths = np.linalg.norm(rec.motion, axis=2)
    cosine = np.sum(rec.motion[:, 0] * rec.motion[:, 1], axis=1) / lengths.prod(axis=1)
    assert np.abs(lengths - 1).max() < 0.02
    assert np.abs(cosine).max() < 0.02


def test_cmu_house_with_30_percent_missing_stays_within_3_percent(house):
    complete = factorize(house)
    holes = house.copy()
    holes[np.random.default_rng(0).random(holes.shape[:2]) < 0.3] = np.nan
    rec = factorize(holes)
    assert rec.method == "als" and rec.warnings == ()
    assert relative_shape_error(rec.points, complete.points) < 0.03


def test_rank_warning_reports_the_measured_ratio_not_a_guessed_cause():
    # A rigid, clearly 3D scene plus a few tracks that jump about (tracker failures): W is
    # not rank 3, but nothing is coplanar, so the warning must not claim it.
    rng = np.random.default_rng(13)
    positions, shape, _ = orthographic_scene(rng, frames=20, points=40)
    positions[:, :4] += rng.normal(scale=60.0, size=(20, 4, 2))
    rec = factorize(positions)
    rank_notes = [w for w in rec.warnings if "not clearly rank 3" in w]
    assert len(rank_notes) == 1
    note = rank_notes[0]
    sv = rec.details.singular_values
    assert f"σ3/σ4 = {sv[2] / sv[3]:.3g}" in note and sv[2] / sv[3] < 2.0
    assert "coplanar" not in note and "no rotation" not in note
    # the rigid part is still recovered well
    assert relative_shape_error(rec.points[4:], shape[4:]) < 0.1
