import numpy as np
import pytest

from kalmansfm.cli import main as cli
from kalmansfm.io import read_ground_truth
from kalmansfm.scenes import render_scene


def test_writes_frames_and_ground_truth(tmp_path, capsys):
    out = tmp_path / "scene"
    code = cli.main(["scene", "--out", str(out), "--frames", "4", "--size", "160x120", "--seed", "3", "--quiet"])
    assert code == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "frame_000.png", "frame_001.png", "frame_002.png", "frame_003.png",
        "ground_truth_motion.csv", "ground_truth_points.csv", "ground_truth_tracks.csv",
        "points.csv", "summary.json",
    ]
    assert "scene" in capsys.readouterr().out
    truth = read_ground_truth(out)
    scene = render_scene(n_frames=4, image_size=(160, 120), seed=3)
    np.testing.assert_allclose(truth.positions, scene.positions, atol=0)
    np.testing.assert_array_equal(truth.visible, scene.visible)
    np.testing.assert_allclose(truth.points_3d, scene.points_3d, atol=0)
    # the motion file reproduces the tracks: x = scale * R[:2] X + t
    projected = truth.scales[:, None, None] * np.einsum("fij,pj->fpi", truth.rotation_rows, truth.points_3d)
    np.testing.assert_allclose(projected + truth.translations[:, None], truth.positions, atol=1e-9)
    import cv2

    frame = cv2.imread(str(out / "frame_002.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(frame, scene.frames[2])
    start = np.genfromtxt(out / "points.csv", delimiter=",", names=True)
    np.testing.assert_array_equal(start["track_id"].astype(int), np.flatnonzero(scene.visible[0]))


def test_occluder_writes_its_file(tmp_path):
    out = tmp_path / "occluded"
    assert cli.main(["scene", "--out", str(out), "--frames", "8", "--occluder", "1,3,2", "--occluder-marker", "-q"]) == 0
    truth = read_ground_truth(out)
    assert not truth.visible[3:5, 1].any() and truth.visible[[2, 5], 1].all()
    rows = np.genfromtxt(out / "ground_truth_occluder.csv", delimiter=",", names=True)
    assert len(rows) == 8 and np.isfinite(rows["marker_x"]).all()


def run_cli(argv):
    """Exit code of the command line, whether it returns or exits through argparse."""
    try:
        return cli.main(argv)
    except SystemExit as stop:
        return stop.code


@pytest.mark.parametrize(
    "options, message",
    [
        (["--size", "0x240"], "--size"),
        (["--size", "320"], "WIDTHxHEIGHT"),
        (["--frames", "2"], "--frames must be an integer >= 3"),
        (["--noise", "-1"], "--noise must be a finite number >= 0"),
        (["--occluder", "99,1,2"], "--occluder TRACK must be in 0 … 9"),
    ],
)
def test_bad_options_exit_2_with_one_line_and_no_folder(tmp_path, capsys, options, message):
    out = tmp_path / "never"
    assert run_cli(["scene", "--out", str(out), *options]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not out.exists()
