"""kalmansfm track: outputs on a small scene, and bad input -> exit 2 with nothing left behind."""

import cv2
import numpy as np
import pytest

from kalmansfm.cli import main as cli
from kalmansfm.io import RunSummary, read_summary, summary_json
from kalmansfm.io.tracks import read_tracks_npz
from kalmansfm.scenes import render_scene


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    scene = render_scene(n_frames=6, image_size=(160, 120))
    for k, frame in enumerate(scene.frames):
        cv2.imwrite(str(folder / f"f{k}.png"), frame)
    visible = np.flatnonzero(scene.visible[0])
    rows = "".join(f"{x},{y},{i}\n" for (x, y), i in zip(scene.positions[0, visible], visible))
    (folder.parent / "points.csv").write_text("x,y,track_id\n" + rows)
    return folder, scene


def test_writes_every_output(scene_folder, tmp_path, capsys):
    folder, scene = scene_folder
    out = tmp_path / "run"
    code = cli.main(["track", str(folder), "--out", str(out), "--points", str(folder.parent / "points.csv"), "--quiet"])
    assert code == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "covariance_trace.png", "summary.json", "tracks.csv", "tracks.gif", "tracks.npz", "tracks.png",
    ]
    tracks = read_tracks_npz(out / "tracks.npz")
    visible = np.flatnonzero(scene.visible[0])
    np.testing.assert_array_equal(tracks.track_ids, visible)
    error = np.linalg.norm(tracks.positions - scene.positions[:, visible], axis=2)
    assert np.nanmax(error) < 1.0
    assert read_summary(out / "summary.json").tracking.frames == 6
    assert "tracked" in capsys.readouterr().out


def test_automatic_features_with_options(scene_folder, tmp_path):
    folder, _ = scene_folder
    out = tmp_path / "auto"
    code = cli.main(["track", str(folder), "--out", str(out), "--max-features", "20", "--score", "ncc",
                     "--gate-radius", "3", "--window", "9", "--max-misses", "2", "--redetect", "--quiet"])
    assert code == 0
    settings = read_summary(out / "summary.json").settings
    assert settings.effective_gate_radius == 3.0 and settings.matcher == "differential" and settings.coast_limit == 2


@pytest.mark.parametrize("matcher", ["search", "differential"])
def test_matcher_option_runs_that_matcher_and_records_it(scene_folder, tmp_path, matcher):
    folder, scene = scene_folder
    out = tmp_path / matcher
    code = cli.main(["track", str(folder), "--out", str(out), "--points", str(folder.parent / "points.csv"),
                     "--matcher", matcher, "--quiet"])
    assert code == 0
    tracks = read_tracks_npz(out / "tracks.npz")
    assert tracks.settings.matcher == matcher
    assert read_summary(out / "summary.json").settings.coast_limit == (3 if matcher == "search" else 5)
    visible = np.flatnonzero(scene.visible[0])
    assert np.nanmax(np.linalg.norm(tracks.positions - scene.positions[:, visible], axis=2)) < 1.0


def test_unknown_matcher_is_a_usage_error(scene_folder, tmp_path, capsys):
    folder, _ = scene_folder
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["track", str(folder), "--out", str(tmp_path / "x"), "--matcher", "nearest"])
    assert exit_info.value.code == 2
    assert "invalid choice" in capsys.readouterr().err


@pytest.mark.parametrize(
    "content, message",
    [
        ("x,y\n10,10\n12,abc\n", "points.csv: line 3: x and y must be numbers"),
        ("a,b\n1,2\n", "points.csv: line 1: missing column(s) x, y"),
        ("x,y\n10,10\n500,10\n", "points.csv: line 3: point (500, 10) lies outside"),
    ],
)
def test_bad_points_file_exit_2_and_nothing_left(scene_folder, tmp_path, capsys, content, message):
    folder, _ = scene_folder
    points = tmp_path / "points.csv"
    points.write_text(content)
    out = tmp_path / "never"
    code = cli.main(["track", str(folder), "--out", str(out), "--points", str(points), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_bad_input_exit_2_and_existing_folder_left_as_it_was(tmp_path, capsys):
    out = tmp_path / "existing"
    out.mkdir()
    earlier = RunSummary(command="track", input="earlier", files=("keep.txt", "summary.json"))
    (out / "summary.json").write_text(summary_json(earlier))
    (out / "keep.txt").write_text("earlier result")
    assert cli.main(["track", str(tmp_path / "missing"), "--out", str(out), "--quiet"]) == 2
    assert "does not exist" in capsys.readouterr().err
    frames = tmp_path / "mixed"
    frames.mkdir()
    for k, size in enumerate([(40, 30), (40, 30), (41, 30)]):
        cv2.imwrite(str(frames / f"{k}.png"), np.zeros(size[::-1], np.uint8))
    assert cli.main(["track", str(frames), "--out", str(out), "--quiet"]) == 2
    assert "2.png: 41×30, but 0.png is 40×30" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt", "summary.json"]


def test_gate_options_are_exclusive(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["track", str(tmp_path), "--out", str(tmp_path / "o"), "--gate", "0.9", "--gate-radius", "2"])
    assert exc.value.code == 2
