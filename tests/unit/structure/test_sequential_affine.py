"""The affine factorization of a long sequence of short tracks, frame by frame (issue 29)."""

import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary
from kalmansfm.structure import factorize
from kalmansfm.structure.affine import long_sequence
from kalmansfm.errors import NotEnoughDataError
from kalmansfm.structure.affine.long_sequence import factorize_long_sequence, frame_normal_equations, point_normal_equations
from kalmansfm.structure.affine.sequential import sequential_factors
from kalmansfm.structure.reconstruction import Observations


def turning_sequence(frames=300, tracks=400, length=20, noise=0.5, seed=0):
    """A camera turning slowly about the vertical axis past short tracks (consecutive frames)."""
    rng = np.random.default_rng(seed)
    start = rng.integers(0, frames - length, tracks)
    frame = np.concatenate([np.arange(s, s + length) for s in start])
    point = np.repeat(np.arange(tracks), length)
    world = np.c_[rng.uniform(-1, 1, (tracks, 2)) * 100, rng.normal(0, 30, tracks)]
    angle = np.radians(0.2 * np.arange(frames))
    zero, one = np.zeros(frames), np.ones(frames)
    rows = np.stack([np.c_[np.cos(angle), zero, np.sin(angle)], np.c_[zero, one, zero]], axis=1)
    xy = np.einsum("nci,ni->nc", rows[frame], world[point]) + 320 + rng.normal(0, noise, (frame.size, 2))
    return frame, point, xy


def test_normal_equations_match_a_dense_reference():
    rng = np.random.default_rng(3)
    frames, points = 5, 7
    motion, translation = rng.normal(size=(frames, 2, 3)), rng.normal(size=(frames, 2))
    shape = rng.normal(size=(points, 3))
    seen = rng.random((frames, points)) < 0.6
    frame, point = np.nonzero(seen)
    xy = rng.normal(size=(frame.size, 2)) * 10
    got = point_normal_equations(motion, translation, frame, point, xy, points)
    frame_got = frame_normal_equations(shape, frame, point, xy, frames)
    for p in range(points):
        rows = [(motion[f], xy[k] - translation[f]) for k, f in enumerate(frame) if point[k] == p]
        normal = sum((m.T @ m for m, _ in rows), np.zeros((3, 3)))
        rhs = sum((m.T @ r for m, r in rows), np.zeros(3))
        assert np.allclose(got.normal[p], normal, atol=1e-10, rtol=0) and np.allclose(got.rhs[p], rhs, atol=1e-10, rtol=0)
        assert got.count[p] == seen[:, p].sum()
    for f in range(frames):
        h = np.c_[shape[point[frame == f]], np.ones((frame == f).sum())]
        assert np.allclose(frame_got.normal[f], h.T @ h, atol=1e-10, rtol=0)
        assert np.allclose(frame_got.rhs[f], h.T @ xy[frame == f], atol=1e-10, rtol=0)
        assert frame_got.count[f] == seen[f].sum()


def sliding_sequence(frames=300, tracks=900, noise=0.5, outliers=0.0, seed=0):
    """A camera sliding along x past a wall of points 4-8 m deep (f = 800 px, 0.02 m a frame), tracks of geometric
    lengths (mean 17) over consecutive frames; exactly rank 3 in the affine sense (s = (X/Z, 1/Z, Y/Z)).
    Returns the observations and which of them are planted gross errors (±(20-40) px in each coordinate)."""
    rng = np.random.default_rng(seed)
    length = np.minimum(rng.geometric(1 / 17, size=tracks) + 1, frames)
    start = rng.integers(0, frames - length + 1)
    depth = rng.uniform(4.0, 8.0, size=tracks)
    middle = 0.02 * (start + length / 2)
    world = np.c_[middle + rng.uniform(-0.14, 0.14, tracks) * depth, rng.uniform(-0.3, 0.3, tracks) * depth, depth]
    point = np.repeat(np.arange(tracks), length)
    frame = np.concatenate([np.arange(s, s + n) for s, n in zip(start.tolist(), length.tolist())])
    centre = 0.02 * frame
    xy = np.c_[800 * (world[point, 0] - centre) / world[point, 2] + 320, 800 * world[point, 1] / world[point, 2] + 240]
    xy += rng.normal(0, noise, xy.shape)
    wild = rng.random(frame.size) < outliers
    xy[wild] += rng.choice([-1, 1], size=(wild.sum(), 2)) * rng.uniform(20, 40, size=(wild.sum(), 2))
    return frame, point, xy, wild


def optimum_rms(noise, observations, frames, points):
    """The expected 2-D reprojection RMS of the least-squares fit: σ √(2 − parameters / observations)."""
    return noise * np.sqrt(2.0 - (8 * frames + 3 * points - 12) / observations)


def test_sequential_fits_a_sliding_sequence_to_the_noise_level_where_the_dense_path_does_not():
    frame, point, xy, _ = sliding_sequence()
    observations = Observations.from_sparse((300, 900), frame, point, xy)
    rec = factorize_long_sequence(observations)
    dense = factorize(observations.dense())  # its missing-data iterations stop short on short tracks
    assert rec.method == "sequential" and rec.kind == "affine"
    assert rec.registered.sum() >= dense.registered.sum() - 2
    assert rec.reprojection_rms <= 1.03 * dense.reprojection_rms
    expected = optimum_rms(0.5, frame.size, rec.registered.sum(), np.isfinite(rec.points[:, 0]).sum())
    assert rec.reprojection_rms == pytest.approx(expected, rel=0.03)
    assert 0.47 < rec.noise.std < 0.53
    assert any("frame by frame" in w for w in rec.warnings)


def test_exact_observations_are_reproduced_frame_by_frame():
    frame, point, xy, _ = sliding_sequence(frames=400, tracks=1200, noise=0.0)
    fit = sequential_factors(frame, point, xy, (400, 1200))
    predicted = np.einsum("nci,ni->nc", fit.motion[frame], fit.shape[point]) + fit.translation[frame]
    seen = np.bincount(frame, minlength=400)
    # every frame that sees enough points is resected; the fit is exact wherever it reaches
    assert np.isfinite(fit.motion[:, 0, 0])[seen >= 20].all() and not fit.rejected.any()
    reached = np.isfinite(predicted[:, 0])
    assert reached.mean() > 0.99 and np.abs(predicted[reached] - xy[reached]).max() < 1e-4  # float64 rounding only


def test_too_few_tracks_to_start_from_are_refused():
    frame = np.repeat(np.arange(20), 3)
    point = np.tile(np.arange(3), 20)
    xy = np.random.default_rng(0).normal(size=(60, 2))
    with pytest.raises(NotEnoughDataError, match="tracks seen in each of the first"):
        sequential_factors(frame, point, xy, (20, 3))


def test_gross_errors_are_rejected():
    frame, point, xy, wild = sliding_sequence(outliers=0.01, seed=1)
    steps = []
    rec = factorize_long_sequence(Observations.from_sparse((300, 900), frame, point, xy),
                                  progress=lambda done, most: steps.append((done, most)))
    # the progress: one step for the frame-by-frame pass, one per polish iteration, counted against a fixed budget
    assert [d for d, _ in steps] == list(range(1, len(steps) + 1)) and len({m for _, m in steps}) == 1
    assert steps[-1][0] == 1 + rec.details.iterations <= steps[-1][1]
    rejected = rec.observations.rejected
    assert rejected[wild].mean() >= 0.9 and rejected[~wild].mean() <= 0.02
    assert 0.45 < rec.noise.std < 0.55
    inliers = rec.observations.used & ~wild
    assert np.sqrt(np.mean(rec.observations.residual[inliers] ** 2)) < 0.75  # 0.5 √2 ≈ 0.71 less the fit's share


def test_a_turning_camera_is_fitted_to_the_noise():
    frame, point, xy = turning_sequence()
    observations = Observations.from_sparse((300, 400), frame, point, xy)
    rec = factorize_long_sequence(observations)
    dense = factorize(observations.dense())
    assert rec.reprojection_rms <= 1.03 * dense.reprojection_rms
    expected = optimum_rms(0.5, frame.size, rec.registered.sum(), np.isfinite(rec.points[:, 0]).sum())
    assert rec.reprojection_rms == pytest.approx(expected, rel=0.03)
    # the reprojections are gauge-free: the two models predict nearly the same image positions
    both = rec.registered[frame] & dense.registered[frame]
    mine = np.einsum("nci,ni->nc", rec.motion[frame], rec.points[point]) + rec.image_translation[frame]
    theirs = np.einsum("nci,ni->nc", dense.motion[frame], dense.points[point]) + dense.image_translation[frame]
    assert np.median(np.linalg.norm(mine - theirs, axis=1)[both]) < 0.3


def _write(path, frame, point, xy):
    rows = "\n".join(f"{f},{p},{x:.4f},{y:.4f}" for f, p, (x, y) in zip(frame, point, xy))
    path.write_text("frame,track_id,x,y\n" + rows + "\n")


def test_reconstruct_takes_the_frame_by_frame_path_for_a_long_sequence(tmp_path, monkeypatch, capsys):
    frame, point, xy = turning_sequence()
    _write(tmp_path / "tracks.csv", frame, point, xy)
    monkeypatch.setattr(long_sequence, "DENSE_ENTRIES", 10_000)  # 300 x 400 no longer fits densely
    out = tmp_path / "run"
    assert main(["reconstruct", str(tmp_path / "tracks.csv"), "--out", str(out), "--quiet", "--no-plot"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "motion.csv", "reconstruction.npz", "structure.csv", "structure.ply", "summary.json"]
    summary = read_summary(out / "summary.json").reconstruction
    assert summary.method == "sequential" and summary.frames == len(np.unique(frame)) and summary.points == 400
    assert summary.reprojection_rms_px < 0.7
    assert np.loadtxt(out / "motion.csv", delimiter=",", skiprows=1).shape == (summary.registered_frames, 9)
    printed = capsys.readouterr().out
    assert "method: sequential (" in printed and "singular values" not in printed  # no measurement matrix is formed


def test_reconstruct_of_a_bad_long_sequence_says_one_line(tmp_path, monkeypatch, capsys):
    frame, point, xy = turning_sequence(frames=60, tracks=40)
    _write(tmp_path / "tracks.csv", frame, point, xy)
    with open(tmp_path / "tracks.csv", "a") as handle:
        handle.write("61,3,abc,4.0\n")
    monkeypatch.setattr(long_sequence, "DENSE_ENTRIES", 100)
    assert main(["reconstruct", str(tmp_path / "tracks.csv"), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tracks.csv" in err[0] and not (tmp_path / "run").exists()
