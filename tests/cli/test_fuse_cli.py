"""``kalmansfm fuse``: the run folder it writes, its report, and one clear line for every bad input."""

import re
import shutil

import numpy as np
import pytest

from cli_run import exit_code
from kalmansfm.cli.main import main
from kalmansfm.io import load_run, read_summary
from kalmansfm.io.cameras import MATRIX_COLUMNS, cameras_csv, read_cameras
from kalmansfm.io.fusion import HISTORY_COLUMNS, REJECTED_COLUMNS
from kalmansfm.io.structure import STRUCTURE_COLUMNS, read_points_table
from kalmansfm.io.tracks import observations_csv
from kalmansfm.report import build_report
from kalmansfm.scenes.known_cameras import known_camera_scene
from kalmansfm.structure.geometry.pinhole import CameraSet


@pytest.fixture
def scene_files(tmp_path):
    s = known_camera_scene(points=60, views=5, pixel_std=0.5, outlier_fraction=0.05, seed=1)
    frames = np.array([10, 11, 12, 13, 14])
    cams = CameraSet(s.cameras.matrices, frames)
    (tmp_path / "cameras.csv").write_text(cameras_csv(cams))
    (tmp_path / "tracks.csv").write_text(observations_csv(s.observations, frames, np.arange(60) + 100))
    return s, tmp_path


def fuse_args(folder, *more):
    return ["fuse", str(folder / "tracks.csv"), "--cameras", str(folder / "cameras.csv"), "--out",
            str(folder / "run"), "--quiet", *more]


def test_fuse_writes_the_run_folder_and_its_report(scene_files, capsys):
    s, folder = scene_files
    assert main(fuse_args(folder)) == 0
    printed = capsys.readouterr().out
    assert "fused: 60" in printed and "pixel noise: 0.4" in printed and "estimated" in printed
    run = folder / "run"
    assert sorted(p.name for p in run.iterdir()) == [
        "cameras.csv", "fusion.png", "history.csv", "reconstruction.npz", "rejected.csv", "structure.csv", "structure.ply", "summary.json"]
    lines = (run / "structure.csv").read_text().splitlines()
    assert lines[0] == ",".join(STRUCTURE_COLUMNS) and len(lines) == 61
    assert (run / "history.csv").read_text().splitlines()[0] == ",".join(HISTORY_COLUMNS)
    rejected = (run / "rejected.csv").read_text().splitlines()
    assert rejected[0] == ",".join(REJECTED_COLUMNS) and len(rejected) - 1 >= 0.8 * s.outliers.sum()
    # the history's view column holds the frame numbers of the cameras
    assert {int(r.split(",")[0]) for r in (run / "history.csv").read_text().splitlines()[1:]} <= set(range(11, 15))
    # the cameras it was given, as given: the run folder is a whole model (and re-fuses to the same points)
    assert read_cameras(run / "cameras.csv").matrices.tolist() == read_cameras(folder / "cameras.csv").matrices.tolist()
    ply = (run / "structure.ply").read_text()
    assert "property float uncertainty" in ply and "element vertex 60" in ply
    points = read_points_table(run / "structure.csv")
    assert points.track_ids.tolist() == list(range(100, 160))
    assert np.sqrt(np.mean(np.sum((points.points - s.points) ** 2, axis=1))) < 0.05
    summary = read_summary(run / "summary.json")
    assert summary.command == "fuse" and summary.reconstruction.reconstructed == 60 and summary.reconstruction.noise_estimated
    assert "fusion.png" in load_run(run).figures
    html = build_report(run).read_text()
    assert "known cameras: recursive fusion" in html and "points reconstructed" in html


def test_methods_and_fixed_noise(scene_files, capsys):
    _, folder = scene_files
    for method in ("batch", "pairs"):
        assert main(fuse_args(folder, "--method", method, "--pixel-std", "0.5", "--no-plot")) == 0
        assert read_summary(folder / "run" / "summary.json").reconstruction.method == method
        printed = capsys.readouterr().out
        assert "pixel noise: 0.5 px (" in printed and "; given)" in printed


def test_frames_without_a_camera_are_skipped_with_one_warning(scene_files, capsys):
    s, folder = scene_files
    cams = CameraSet(s.cameras.matrices[:4], [10, 11, 12, 13])  # no camera for frame 14
    (folder / "cameras.csv").write_text(cameras_csv(cams))
    assert main(fuse_args(folder)) == 0  # quiet too: warnings are results, printed as reconstruct prints them
    captured = capsys.readouterr()
    warnings = [line for line in captured.out.splitlines() if "without a camera" in line]
    assert len(warnings) == 1 and warnings[0].startswith("warning: ") and "14" in warnings[0]
    assert "without a camera" not in captured.err
    summary = read_summary(folder / "run" / "summary.json")
    assert summary.reconstruction.skipped_frames == (14,) and summary.reconstruction.frames == 4


def test_points_behind_every_camera_get_a_status(tmp_path, capsys):
    s = known_camera_scene(points=20, views=4, pixel_std=0.3, seed=2)
    behind = s.cameras.centers.mean(axis=0) * 3  # far behind the cameras, which look at the origin
    obs = np.concatenate([s.observations, np.stack([s.cameras.matrices[v, :, :3] @ behind + s.cameras.matrices[v, :, 3]
                                                    for v in range(4)])[:, None, :2]
                          / np.stack([s.cameras.matrices[v, 2, :3] @ behind + s.cameras.matrices[v, 2, 3]
                                      for v in range(4)])[:, None, None]], axis=1)
    (tmp_path / "cameras.csv").write_text(cameras_csv(s.cameras))
    (tmp_path / "tracks.csv").write_text(observations_csv(obs, s.cameras.frames))
    assert main(fuse_args(tmp_path, "--pixel-std", "0.3")) == 0
    last = (tmp_path / "run" / "structure.csv").read_text().splitlines()[-1].split(",")
    assert last[0] == "20" and last[-1] == "behind_camera" and last[1] == ""  # no value: an empty cell


def bad_cameras(tmp_path, text):
    (tmp_path / "cameras.csv").write_text(text)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda f: bad_cameras(f, "frame,p11,p12\n10,1,2\n"), r"cameras.csv: line 1: missing column\(s\) p13, .* of the projection-matrix layout; expected the "
         r"projection-matrix layout frame,p11,.* or the intrinsics \+ pose layout frame,fx,.*; got frame,p11,p12$"),
        (lambda f: bad_cameras(f, ",".join(MATRIX_COLUMNS) + "\n10" + ",0" * 12 + "\n11,1,0,0,0,0,1,0,0,0,0,1,0\n"),
         "cameras.csv: line 2: frame 10: not a camera"),
        (lambda f: bad_cameras(f, ",".join(MATRIX_COLUMNS) + "\n10,1,0,0,0,0,1,0,0,0,0,inf,0\n"),
         "cameras.csv: line 2: p33 must be finite"),
        (lambda f: bad_cameras(f, ",".join(MATRIX_COLUMNS) + "\n10,1,0,0,0,0,1,0,0,0,0,1,0\n10,1,0,0,0,0,1,0,0,0,0,1,5\n"),
         "cameras.csv: lines 2 and 3: frame 10 has two cameras"),
        (lambda f: bad_cameras(f, ",".join(MATRIX_COLUMNS) + "\n10,1,0,0,0,0,1,0,0,0,0,1,0\n"),
         r"tracks.csv: 1 of its 5 frame\(s\) have a camera; fusing needs >= 2"),
        (lambda f: bad_cameras(f, ",".join(MATRIX_COLUMNS) + "\n1,1,0,0,0,0,1,0,0,0,0,1,0\n2,1,0,0,0,0,1,0,0,0,0,1,1\n"),
         r"tracks.csv: 0 of its 5 frame\(s\) have a camera"),
        (lambda f: (f / "tracks.csv").write_text("frame,track_id,x\n10,1,2\n"),
         r"tracks.csv: line 1: missing column\(s\) y; expected frame,track_id,x,y; got frame,track_id,x$"),
        (lambda f: (f / "tracks.csv").unlink(), "tracks.csv: no such file"),
    ],
)
def test_bad_files_exit_2_with_one_line_and_write_nothing(scene_files, capsys, change, message):
    _, folder = scene_files
    change(folder)
    assert main(fuse_args(folder)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("kalmansfm fuse: error:")
    assert re.search(message, err), err
    assert not (folder / "run").exists()


@pytest.mark.parametrize(
    "options, message",
    [
        (["--pixel-std", "-1"], "--pixel-std must be finite and > 0"),
        (["--pixel-std", "lots"], "must be 'auto' or a number of pixels"),
        (["--outlier-prob", "0"], r"--outlier-prob must be in \(0, 1\]"),
        (["--method", "ekf"], "invalid choice"),
        (["--chunk-points", "0"], "--chunk-points must be an integer >= 1"),
        (["--workers", "0"], "workers must be an integer >= 1"),
        (["--workers", "2", "--scheduler", "tcp://nowhere:1"], "not both"),
    ],
)
def test_bad_options_exit_2_with_one_line_and_write_nothing(scene_files, capsys, options, message):
    _, folder = scene_files
    assert exit_code(fuse_args(folder, *options)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and re.search(message, err), err
    assert not (folder / "run").exists()


def test_pixel_std_auto_without_redundancy_is_one_line(tmp_path, capsys):
    s = known_camera_scene(points=5, views=3, seed=3)
    obs = s.observations.copy()
    obs[:, :, :] = np.nan
    obs[0] = s.observations[0]
    obs[1, 0] = s.observations[1, 0]  # one point in two views: 4 observations, 3 unknowns, 1 dof
    (tmp_path / "cameras.csv").write_text(cameras_csv(s.cameras))
    (tmp_path / "tracks.csv").write_text(observations_csv(obs, s.cameras.frames))
    assert main(fuse_args(tmp_path)) == 0  # one degree of freedom is enough to estimate σ
    obs[1, 0], obs[0, 3], obs[1, 3] = np.nan, np.nan, s.observations[1, 3]  # every point seen once
    (tmp_path / "tracks.csv").write_text(observations_csv(obs, s.cameras.frames))
    shutil.rmtree(tmp_path / "run")
    assert main(fuse_args(tmp_path)) == 2
    assert "pixel_std='auto' needs" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_chunks_on_a_local_dask_cluster_give_the_same_structure(scene_files):
    _, folder = scene_files
    assert main(fuse_args(folder, "--no-plot")) == 0
    here = np.genfromtxt(folder / "run" / "structure.csv", delimiter=",", skip_header=1)[:, :-1]
    shutil.rmtree(folder / "run")
    assert main(fuse_args(folder, "--no-plot", "--workers", "1", "--chunk-points", "25")) == 0
    there = np.genfromtxt(folder / "run" / "structure.csv", delimiter=",", skip_header=1)[:, :-1]
    # small chunks run the NumPy pass, vectorised over a chunk's points: the batched arithmetic of other
    # chunk sizes moves the last digits (1e-9 relative at most, measured)
    np.testing.assert_allclose(there, here, rtol=1e-8)
