"""The segmented affine factorization of long sequences of short tracks (issue 29)."""

import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary
from kalmansfm.structure import factorize
from kalmansfm.structure.affine import segmented
from kalmansfm.structure.affine.segmented import factorize_segmented, frame_normal_equations, point_normal_equations
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


@pytest.mark.xfail(strict=True, reason="not met yet: the sparse ALS refinement stops after 300 iterations short of the "
                   "dense optimum (reprojections differ by ~0.6 px median); issue 29, branch seqaffine")
def test_segmented_agrees_with_the_dense_path_on_a_long_sequence():
    frame, point, xy = turning_sequence()
    shape = (300, 400)
    rec = factorize_segmented(Observations.from_sparse(shape, frame, point, xy))
    dense = factorize(Observations.from_sparse(shape, frame, point, xy).dense())
    assert rec.method == "segmented" and rec.kind == "affine"
    assert np.array_equal(rec.registered, dense.registered) and rec.registered.sum() >= 290
    # both at the noise level (0.5 px per coordinate: the 2-D residual RMS a little below 0.5 √2)
    assert rec.reprojection_rms == pytest.approx(dense.reprojection_rms, rel=0.03)
    assert 0.45 < rec.noise.std < 0.55
    # the reprojections are gauge-free: the two models predict the same image positions
    mine = np.einsum("nci,ni->nc", rec.motion[frame], rec.points[point]) + rec.image_translation[frame]
    theirs = np.einsum("nci,ni->nc", dense.motion[frame], dense.points[point]) + dense.image_translation[frame]
    assert np.nanmedian(np.linalg.norm(mine - theirs, axis=1)) < 0.1
    assert any("windows" in w for w in rec.warnings)


@pytest.mark.xfail(strict=True, reason="not met yet: with the refinement short of convergence 2 % of the good "
                   "observations are rejected and 29 % of the gross errors kept; issue 29, branch seqaffine")
def test_gross_errors_are_rejected():
    frame, point, xy = turning_sequence(seed=1)
    rng = np.random.default_rng(5)
    wild = rng.random(frame.size) < 0.01
    xy[wild] += rng.choice([-1, 1], size=(wild.sum(), 2)) * rng.uniform(20, 40, size=(wild.sum(), 2))
    rec = factorize_segmented(Observations.from_sparse((300, 400), frame, point, xy))
    rejected = rec.observations.rejected
    # most gross errors go (those of 20-40 px that the not fully converged refinement still absorbs stay)
    assert rejected[wild].mean() > 0.6 and rejected[~wild].mean() < 0.01
    assert 0.45 < rec.noise.std < 0.55


def _write(path, frame, point, xy):
    rows = "\n".join(f"{f},{p},{x:.4f},{y:.4f}" for f, p, (x, y) in zip(frame, point, xy))
    path.write_text("frame,track_id,x,y\n" + rows + "\n")


def test_reconstruct_takes_the_segmented_path_for_a_long_sequence(tmp_path, monkeypatch, capsys):
    frame, point, xy = turning_sequence()
    _write(tmp_path / "tracks.csv", frame, point, xy)
    monkeypatch.setattr(segmented, "DENSE_ENTRIES", 10_000)  # 300 x 400 no longer fits densely
    out = tmp_path / "run"
    assert main(["reconstruct", str(tmp_path / "tracks.csv"), "--out", str(out), "--quiet", "--no-plot"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "motion.csv", "reconstruction.npz", "structure.csv", "structure.ply", "summary.json"]
    summary = read_summary(out / "summary.json").reconstruction
    assert summary.method == "segmented" and summary.frames == len(np.unique(frame)) and summary.points == 400
    assert summary.reprojection_rms_px < 0.7
    assert np.loadtxt(out / "motion.csv", delimiter=",", skiprows=1).shape == (summary.registered_frames, 9)


def test_reconstruct_of_a_bad_long_sequence_says_one_line(tmp_path, monkeypatch, capsys):
    frame, point, xy = turning_sequence(frames=60, tracks=40)
    _write(tmp_path / "tracks.csv", frame, point, xy)
    with open(tmp_path / "tracks.csv", "a") as handle:
        handle.write("61,3,abc,4.0\n")
    monkeypatch.setattr(segmented, "DENSE_ENTRIES", 100)
    assert main(["reconstruct", str(tmp_path / "tracks.csv"), "--out", str(tmp_path / "run"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "tracks.csv" in err[0] and not (tmp_path / "run").exists()
