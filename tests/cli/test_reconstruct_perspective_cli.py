"""``kalmansfm reconstruct --camera perspective|auto``: the run folder, its report, and one line per bad input."""

import numpy as np
import pytest

from cli_run import exit_code
from kalmansfm.cli.main import main
from kalmansfm.io import load_run, read_summary
from kalmansfm.io.intrinsics import intrinsics_csv, read_intrinsics
from kalmansfm.io.cameras import POSE_COLUMNS, POSE_STD_COLUMNS, read_cameras
from kalmansfm.io.structure import STRUCTURE_COLUMNS
from kalmansfm.io.tracks import observations_csv
from kalmansfm.pipeline import Perspective, ReconstructRequest, run_reconstruct
from kalmansfm.report import build_report
from kalmansfm.scenes.perspective import perspective_scene
from kalmansfm.structure.geometry.alignment import align_similarity
from kalmansfm.structure.points import rms_std


def tracks_text(observations, frames):
    return observations_csv(observations, np.asarray(frames), np.arange(observations.shape[1]) + 500)


@pytest.fixture(scope="module")
def scene():
    return perspective_scene(frames=7, points=150, pixel_std=0.5, outlier_fraction=0.02, seed=4)


@pytest.fixture
def files(tmp_path, scene):
    frames = np.arange(7) + 20
    (tmp_path / "tracks.csv").write_text(tracks_text(scene.observations, frames))
    (tmp_path / "K.csv").write_text(intrinsics_csv(frames, scene.intrinsics))
    return tmp_path


def args(folder, *more):
    return ["reconstruct", str(folder / "tracks.csv"), "--out", str(folder / "run"), "--quiet", *more]


def test_perspective_run_folder_files_report_and_accuracy(files, scene, capsys):
    assert main(args(files, "--camera", "perspective", "--intrinsics", str(files / "K.csv"))) == 0
    printed = capsys.readouterr().out
    assert "registered: 7" in printed and "reprojection RMS" in printed
    run = files / "run"
    assert sorted(p.name for p in run.iterdir()) == [
        "cameras.csv", "reconstruction.npz", "reconstruction.png", "structure.csv", "structure.ply", "summary.json"]
    assert (run / "structure.csv").read_text().splitlines()[0] == ",".join(STRUCTURE_COLUMNS)
    assert (run / "cameras.csv").read_text().splitlines()[0] == ",".join(POSE_COLUMNS + POSE_STD_COLUMNS)
    assert "free-network gauge" in (run / "structure.ply").read_text().splitlines()[2]
    summary = read_summary(run / "summary.json")
    p = summary.reconstruction
    assert p.kind == "perspective" and p.registered_frames == 7 and p.reconstructed >= 140
    assert p.noise_std == pytest.approx(0.5, rel=0.1)
    assert p.initial_pair[0] >= 20  # frame numbers of the file, not indices
    # the files hold the reconstruction: points match the truth after alignment, cameras by frame number
    cams = read_cameras(run / "cameras.csv")
    assert cams.frames.tolist() == list(range(20, 27))
    table = load_run(run)
    al = align_similarity(table.structure.points, scene.points[table.structure.track_ids - 500])
    cov = table.structure.covariances
    assert al.rms < 0.05 and cov.shape == (len(table.structure.track_ids), 3, 3) and np.isfinite(cov).all()
    html = build_report(run).read_text()
    assert "calibrated cameras, unknown motion: bundle adjustment" in html and "camera_centres" in html


def test_cameras_csv_of_a_perspective_run_is_the_reconstruction_and_feeds_fuse(files, capsys):
    """One schema: the cameras.csv that reconstruct writes is read by read_cameras and by ``fuse --cameras``."""
    k_file = str(files / "K.csv")
    assert main(args(files, "--camera", "perspective", "--intrinsics", k_file)) == 0
    written = files / "run" / "cameras.csv"
    # the same reconstruction through the pipeline function the command runs, for its R and t
    same = run_reconstruct(ReconstructRequest(files / "tracks.csv", files / "again", Perspective(intrinsics=k_file)))
    assert (files / "again" / "cameras.csv").read_bytes() == written.read_bytes()
    rec, frames = same.reconstruction, same.tracks.frames
    reg = rec.registered
    cams = read_cameras(written)
    assert cams.frames.tolist() == frames[reg].tolist() == list(range(20, 27))
    # P = K [R | t] with the K of K.csv and the reconstruction's R, t, to rounding
    K = read_intrinsics(k_file, frames)[reg]
    P = K @ np.concatenate([rec.rotations[reg], rec.translations[reg][:, :, None]], axis=2)
    scale = np.abs(P).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(cams.matrices / scale, P / scale, rtol=0, atol=1e-12)
    # the uncertainty columns keep their meaning
    table = np.genfromtxt(written, delimiter=",", names=True)
    np.testing.assert_allclose(table["rotation_std_deg"],
                               np.degrees(rms_std(rec.pose_covariances[reg, :3, :3])), rtol=1e-15)
    np.testing.assert_allclose(table["centre_std"], rms_std(rec.pose_covariances[reg, 3:, 3:]), rtol=1e-15)
    capsys.readouterr()
    fuse = ["fuse", str(files / "tracks.csv"), "--cameras", str(written), "--out", str(files / "fused"), "--quiet"]
    assert exit_code(fuse) == 0
    fused = load_run(files / "fused")
    assert fused.structure is not None and np.isfinite(fused.structure.points).all(axis=1).sum() >= 140


def test_auto_keeps_the_perspective_model_on_perspective_data(files, capsys):
    assert main(args(files, "--camera", "auto", "--focal", "800", "--image-size", "1280", "960")) == 0
    assert "camera: perspective: reprojection RMS" in capsys.readouterr().out
    assert read_summary(files / "run" / "summary.json").reconstruction.camera_choice.startswith("perspective")


def test_recursive_method_from_the_command_line(files):
    assert main(args(files, "--camera", "perspective", "--intrinsics", str(files / "K.csv"), "--method",
                     "recursive")) == 0
    assert read_summary(files / "run" / "summary.json").reconstruction.method == "recursive"


@pytest.mark.parametrize("extra, k_text, message", [
    (["--camera", "perspective"], None, "needs its calibration: give --intrinsics (a K.csv) or --focal (pixels), exactly one"),
    (["--camera", "perspective", "--focal", "800"], None, "--focal needs the image size"),
    (["--intrinsics", "K.csv"], None, "describe a perspective camera: add --camera perspective"),
    (["--camera", "perspective", "--intrinsics", "K.csv"],
     "frame,fx,fy,cx,cy,skew\n20,800,800,640,480,0\n21,800,800,640,480,0\n", "no intrinsics for frame 22"),
    (["--camera", "perspective", "--intrinsics", "K.csv"],
     "frame,fx,fy,cx,cy,skew\n0,800,0,640,480,0\n", "line 2: fx and fy must be > 0"),
    (["--camera", "perspective", "--intrinsics", "K.csv", "--focal", "700"], None, "or --focal (pixels), exactly one"),
    (["--camera", "perspective", "--focal", "-3", "--image-size", "640", "480"], None, "focal must be finite and > 0"),
    (["--camera", "perspective", "--intrinsics", "K.csv", "--outlier-threshold", "0"], None,
     "--outlier-threshold must be finite and > 0"),
])
def test_bad_input_is_one_line_and_leaves_no_folder(files, capsys, extra, k_text, message):
    if k_text is not None:
        (files / "K.csv").write_text(k_text)
    extra = [str(files / e) if e == "K.csv" else e for e in extra]
    assert exit_code(args(files, *extra)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not (files / "run").exists()


def test_degenerate_scene_is_one_line(tmp_path, capsys):
    planar = perspective_scene(frames=6, points=120, layout="planar", seed=2)
    (tmp_path / "tracks.csv").write_text(tracks_text(planar.observations, np.arange(6)))
    (tmp_path / "K.csv").write_text(intrinsics_csv([0], planar.intrinsics[:1]))
    assert exit_code(args(tmp_path, "--camera", "perspective", "--intrinsics", str(tmp_path / "K.csv"))) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "degenerate scene" in err[0]
    assert not (tmp_path / "run").exists()
    # auto falls back to the affine model and says why
    assert exit_code(args(tmp_path, "--camera", "auto", "--intrinsics", str(tmp_path / "K.csv"))) == 0
    summary = read_summary(tmp_path / "run" / "summary.json")
    assert summary.reconstruction.kind == "affine" and "perspective reconstruction was impossible" in summary.warnings[0]
