"""``kalmansfm reconstruct --camera perspective`` on tracks too large for one dense problem: windows of frames.

The size threshold and the windows are made small here, so that a short sequence takes the path a
long video's tracks take (issue 29).
"""

import numpy as np
import pytest

from cli_run import exit_code
from kalmansfm.cli.main import main
from kalmansfm.io import read_summary
from kalmansfm.io.cameras import read_cameras
from kalmansfm.io.intrinsics import intrinsics_csv
from kalmansfm.io.reconstruction import read_reconstruction
from kalmansfm.io.structure import read_points_table
from kalmansfm.scenes.perspective import sliding_sequence
from kalmansfm.structure.perspective import segmented

FIRST_FRAME, FIRST_TRACK = 100, 7000


@pytest.fixture(scope="module")
def scene():
    return sliding_sequence(150, 450, seed=3)


@pytest.fixture
def files(tmp_path, scene, monkeypatch):
    monkeypatch.setattr(segmented, "DENSE_MAX_FRAMES", 50)
    monkeypatch.setattr(segmented, "WINDOW_FRAMES", 60)
    monkeypatch.setattr(segmented, "WINDOW_OVERLAP", 20)
    obs = scene.observations
    rows = np.c_[obs.frame + FIRST_FRAME, obs.point + FIRST_TRACK, obs.xy]
    with open(tmp_path / "tracks.csv", "w") as handle:
        handle.write("frame,track_id,x,y\n")
        np.savetxt(handle, rows, fmt=["%d", "%d", "%.4f", "%.4f"], delimiter=",")
    frames = np.arange(obs.shape[0]) + FIRST_FRAME
    (tmp_path / "K.csv").write_text(intrinsics_csv(frames, scene.cameras.decompose().intrinsics))
    return tmp_path


def args(folder, *more):
    return ["reconstruct", str(folder / "tracks.csv"), "--out", str(folder / "run"), "--quiet", "--camera", "perspective",
            "--intrinsics", str(folder / "K.csv"), *more]


def test_a_long_sequence_is_reconstructed_in_windows_into_a_whole_run_folder(files, scene, capsys):
    assert main(args(files)) == 0
    printed = capsys.readouterr().out
    assert "method: segmented" in printed and "reconstructed in 3 windows of up to 60 frames" in printed
    run = files / "run"
    assert sorted(p.name for p in run.iterdir()) == [
        "cameras.csv", "reconstruction.npz", "reconstruction.png", "structure.csv", "structure.ply", "summary.json"]
    p = read_summary(run / "summary.json").reconstruction
    assert p.kind == "perspective" and p.method == "segmented" and p.registered_frames >= 135
    assert p.noise_std == pytest.approx(0.5, rel=0.1) and p.initial_pair[0] >= FIRST_FRAME
    assert "segmented reconstruction" in (run / "structure.ply").read_text().splitlines()[2]
    # frame numbers and track ids of the file; the record holds the observations per observation
    cams = read_cameras(run / "cameras.csv")
    assert cams.frames.min() >= FIRST_FRAME and cams.frames.max() < FIRST_FRAME + 150
    table = read_points_table(run / "structure.csv")
    assert table.track_ids.min() >= FIRST_TRACK and table.track_ids.max() < FIRST_TRACK + 450
    rec = read_reconstruction(run / "reconstruction.npz")
    assert len(rec.observations) == len(scene.observations) and rec.registered.sum() == p.registered_frames


def test_no_plot_writes_no_figure(files):
    assert main(args(files, "--no-plot")) == 0
    assert not (files / "run" / "reconstruction.png").exists()


@pytest.mark.parametrize("k_text, tracks_line, message", [
    ("frame,fx,fy,cx,cy,skew\n100,800,800,320,240,0\n101,800,800,320,240,0\n", None, "no intrinsics for frame 102"),
    (None, "105,7003,12.5,oops", "line"),
])
def test_bad_input_is_one_line_and_leaves_no_folder(files, capsys, k_text, tracks_line, message):
    if k_text is not None:
        (files / "K.csv").write_text(k_text)
    if tracks_line is not None:
        with open(files / "tracks.csv", "a") as handle:
            handle.write(tracks_line + "\n")
    assert exit_code(args(files)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (files / "run").exists()


@pytest.mark.slow
def test_tracks_beyond_the_dense_threshold_take_the_segmented_path(tmp_path, capsys):
    """The real threshold and windows (the fast tests above make them small)."""
    s = sliding_sequence(segmented.DENSE_MAX_FRAMES + 100, 3000, seed=4)
    obs = s.observations
    with open(tmp_path / "tracks.csv", "w") as handle:
        handle.write("frame,track_id,x,y\n")
        np.savetxt(handle, np.c_[obs.frame, obs.point, obs.xy], fmt=["%d", "%d", "%.4f", "%.4f"], delimiter=",")
    (tmp_path / "K.csv").write_text(intrinsics_csv(np.arange(obs.shape[0]), s.cameras.decompose().intrinsics))
    assert main(args(tmp_path, "--no-plot")) == 0
    p = read_summary(tmp_path / "run" / "summary.json").reconstruction
    assert p.method == "segmented" and p.registered_frames > 0.97 * obs.shape[0]
    assert p.noise_std == pytest.approx(0.5, rel=0.1)


def test_auto_on_a_long_sequence_runs_both_models_per_observation_and_keeps_the_better(files, capsys):
    """``--camera auto`` takes the per-observation path too (the perspective threshold is the one exceeded
    here): the affine model is factorized frame by frame, the perspective one in windows, and the perspective
    one — whose model the sliding scene follows — is kept, with the affine one's RMS in the choice."""
    argv = args(files)
    argv[argv.index("perspective")] = "auto"
    assert main(argv) == 0
    assert "camera: perspective: reprojection RMS" in capsys.readouterr().out
    p = read_summary(files / "run" / "summary.json").reconstruction
    assert p.kind == "perspective" and p.method == "segmented"
    assert "<= the affine model's" in p.camera_choice
    affine_rms = float(p.camera_choice.split("the affine model's ")[1].split(" px")[0])
    assert p.reprojection_rms_px <= affine_rms < 2.0  # the frame-by-frame factorization fits too (rank 3)
