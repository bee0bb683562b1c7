"""Smoothing on the command line: track --smooth, reconstruct's default, demo --smooth/--no-smooth."""

import cv2
import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary
from kalmansfm.io.tracks import read_tracks_csv, read_tracks_npz
from kalmansfm.pipeline import DemoRequest, read_tracks_for_factorization, run_demo
from kalmansfm.scenes import render_scene
from kalmansfm.tracking.smoothing import smooth_tracks


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A small scene tracked twice: as the tracker writes it, and with --smooth."""
    root = tmp_path_factory.mktemp("smoothing")
    folder = root / "frames"
    folder.mkdir()
    scene = render_scene(n_frames=8, image_size=(160, 120))
    for k, frame in enumerate(scene.frames):
        cv2.imwrite(str(folder / f"f{k}.png"), frame)
    visible = np.flatnonzero(scene.visible[0])
    rows = "".join(f"{x},{y},{i}\n" for (x, y), i in zip(scene.positions[0, visible], visible))
    (root / "points.csv").write_text("x,y,track_id\n" + rows)
    common = [str(folder), "--points", str(root / "points.csv"), "--quiet"]
    assert main(["track", *common, "--out", str(root / "filtered")]) == 0
    assert main(["track", *common, "--out", str(root / "smoothed"), "--smooth"]) == 0
    return root


def test_track_smooth_writes_the_smoothed_tracks_and_says_so(tracked):
    filtered = read_tracks_npz(tracked / "filtered" / "tracks.npz")
    smoothed = read_tracks_npz(tracked / "smoothed" / "tracks.npz")
    assert filtered.smoothed is False and smoothed.smoothed is True
    expected = smooth_tracks(filtered)
    np.testing.assert_array_equal(smoothed.states, expected.states)
    np.testing.assert_array_equal(smoothed.covariances, expected.covariances)
    assert not np.array_equal(smoothed.states, filtered.states, equal_nan=True)
    from_csv = read_tracks_csv(tracked / "smoothed" / "tracks.csv")
    np.testing.assert_allclose(from_csv.positions, expected.positions, atol=1e-6)
    assert read_summary(tracked / "smoothed" / "summary.json").smoothed is True
    assert read_summary(tracked / "filtered" / "summary.json").smoothed is False


def test_track_smooth_lag(tracked, tmp_path):
    common = [str(tracked / "frames"), "--points", str(tracked / "points.csv"), "--quiet"]
    assert main(["track", *common, "--out", str(tmp_path / "lag"), "--smooth-lag", "2"]) == 0
    lagged = read_tracks_npz(tmp_path / "lag" / "tracks.npz")
    assert lagged.smoothed == 2
    expected = smooth_tracks(read_tracks_npz(tracked / "filtered" / "tracks.npz"), lag=2)
    np.testing.assert_array_equal(lagged.states, expected.states)


def test_reconstruct_smooths_a_tracker_npz_by_default(tracked, tmp_path, capsys):
    npz = tracked / "filtered" / "tracks.npz"
    assert main(["reconstruct", str(npz), "--out", str(tmp_path / "default"), "--no-plot", "-q"]) == 0
    assert "smoothed" in capsys.readouterr().out
    assert main(["reconstruct", str(npz), "--out", str(tmp_path / "raw"), "--no-plot", "--no-smooth", "-q"]) == 0
    default = read_summary(tmp_path / "default" / "summary.json").reconstruction
    raw = read_summary(tmp_path / "raw" / "summary.json").reconstruction
    assert default.smoothed is True and raw.smoothed is False
    assert default.singular_values != raw.singular_values
    # the observations are the smoothed measured positions, weighted by the smoothed std
    positions = read_tracks_for_factorization(npz)
    smoothed = smooth_tracks(read_tracks_npz(npz))
    measured = smoothed.measured
    np.testing.assert_array_equal(positions.observations()[measured], smoothed.positions[measured])
    np.testing.assert_array_equal(positions.position_std[measured], smoothed.position_std[measured])
    assert np.isnan(positions.observations()[~measured]).all()


def test_reconstruct_does_not_smooth_twice(tracked, tmp_path):
    npz = tracked / "smoothed" / "tracks.npz"
    assert main(["reconstruct", str(npz), "--out", str(tmp_path / "o"), "--no-plot", "-q"]) == 0
    assert read_summary(tmp_path / "o" / "summary.json").smoothed is True
    stored = read_tracks_npz(npz)
    measured = stored.measured
    np.testing.assert_array_equal(read_tracks_for_factorization(npz).observations()[measured], stored.positions[measured])


def test_a_csv_is_read_as_it_is_unless_smoothing_is_required(tracked, tmp_path, capsys):
    csv = tracked / "filtered" / "tracks.csv"
    assert main(["reconstruct", str(csv), "--out", str(tmp_path / "csv"), "--no-plot", "-q"]) == 0
    assert read_summary(tmp_path / "csv" / "summary.json").smoothed is False
    capsys.readouterr()
    assert main(["reconstruct", str(csv), "--out", str(tmp_path / "forced"), "--smooth", "-q"]) == 2
    err = capsys.readouterr().err
    assert "cannot smooth" in err and "tracks.npz" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "forced").exists()


def test_run_demo_smooths_unless_asked_not_to(tmp_path):
    options = dict(n_frames=8, html=False, save_frames=False)
    plain = run_demo(DemoRequest(tmp_path / "plain", smooth=False, **options))
    smoothed = run_demo(DemoRequest(tmp_path / "smoothed", **options))
    assert plain.summary.smoothed is False and smoothed.summary.smoothed is True
    np.testing.assert_array_equal(smoothed.tracks.states, smooth_tracks(plain.tracks).states)
    assert read_tracks_npz(tmp_path / "smoothed" / "tracks.npz").smoothed is True


def test_demo_no_smooth_flag(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "d"), "--frames", "8", "--no-smooth", "--quiet"]) == 0
    assert read_summary(tmp_path / "d" / "summary.json").smoothed is False
