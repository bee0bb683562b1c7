"""``kalmansfm reconstruct IMAGES --camera perspective``: cameras straight from images, views accounted for."""

import csv

import cv2
import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io import read_summary
from kalmansfm.io.cameras import read_cameras
from kalmansfm.io.intrinsics import intrinsics_csv
from kalmansfm.report import build_report
from kalmansfm.scenes.textured import textured_views
from kalmansfm.structure import align_similarity


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    base = tmp_path_factory.mktemp("images")
    views = textured_views(frames=8, arc_deg=140.0, seed=6)
    (base / "images").mkdir()
    for k, image in enumerate(views.images):
        cv2.imwrite(str(base / "images" / f"view{k}.png"), image)
    (base / "K.csv").write_text(intrinsics_csv([0], views.intrinsics[None]))
    return base, views


def test_images_give_every_camera_and_the_run_keeps_the_match_graph(folder, capsys):
    base, views = folder
    assert main(["reconstruct", str(base / "images"), "--camera", "perspective", "--intrinsics", str(base / "K.csv"),
                 "--out", str(base / "run"), "-q"]) == 0
    printed = capsys.readouterr().out
    assert "registered: 8/8" in printed and "match graph:" in printed
    run = base / "run"
    summary = read_summary(run / "summary.json")
    assert summary.reconstruction.registered_frames == 8 and summary.reconstruction.kind == "perspective"
    for name in ("pairs.csv", "views.csv", "tracks.csv", "cameras.csv", "reconstruction.npz"):
        assert name in summary.files
    with open(run / "views.csv") as handle:
        rows = list(csv.DictReader(handle))
    assert [r["image"] for r in rows] == [f"view{k}.png" for k in range(8)]
    assert {r["status"] for r in rows} == {"registered"}
    # the cameras are the true ones up to a similarity
    cams = read_cameras(run / "cameras.csv")
    centres = cams.decompose().centers
    fit = align_similarity(centres, views.centres[cams.frames])
    radius = np.sqrt(np.mean(np.sum((views.centres - views.centres.mean(0)) ** 2, axis=1)))
    assert fit.rms < 0.01 * radius
    html = build_report(run).read_text()
    assert "Views and the match graph" in html


def test_images_need_a_perspective_camera_and_a_folder_of_one_image_is_refused(folder, tmp_path, capsys):
    base, _ = folder
    assert main(["reconstruct", str(base / "images"), "--out", str(tmp_path / "a")]) == 2
    assert "holds images: reconstruct them with --camera perspective" in capsys.readouterr().err
    one = tmp_path / "one"
    one.mkdir()
    cv2.imwrite(str(one / "a.png"), np.zeros((40, 40), np.uint8))
    assert main(["reconstruct", str(one), "--camera", "perspective", "--focal", "500", "--out",
                 str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and not (tmp_path / "b").exists()


def test_track_by_features_gives_measured_tracks_that_the_perspective_back_end_takes(folder, capsys):
    base, views = folder
    assert main(["track", str(base / "images"), "--matcher", "features", "--out", str(base / "tracks"), "-q"]) == 0
    assert "tracked" in capsys.readouterr().out
    from kalmansfm.io.tracks import read_tracks

    tracks = read_tracks(base / "tracks" / "tracks.csv")
    assert tracks.n_frames == 8 and tracks.n_tracks > 100 and tracks.states is None
    # the views see the object from 140° apart at the ends: tracks span many frames, not only neighbours
    assert (np.isfinite(tracks.positions[..., 0]).sum(axis=0) >= 4).sum() > 50
    assert main(["reconstruct", str(base / "tracks"), "--camera", "perspective", "--intrinsics", str(base / "K.csv"),
                 "--out", str(base / "from-tracks"), "-q"]) == 0
    assert "registered: 8" in capsys.readouterr().out


def test_track_by_features_refuses_start_points_and_smoothing(folder, tmp_path, capsys):
    base, _ = folder
    assert main(["track", str(base / "images"), "--matcher", "features", "--smooth", "--out", str(tmp_path / "t")]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert "give neither --points nor --smooth" in line


@pytest.mark.slow
def test_images_matched_on_a_local_dask_cluster_give_the_same_cameras(folder):
    """Issue 26: ``--workers`` spreads the pair matching over Dask processes; the result is the one made here."""
    base, _ = folder
    common = ["reconstruct", str(base / "images"), "--camera", "perspective", "--intrinsics", str(base / "K.csv"), "-q"]
    assert main([*common, "--out", str(base / "here")]) == 0
    assert main([*common, "--out", str(base / "dask"), "--workers", "2"]) == 0
    assert (base / "dask" / "pairs.csv").read_text() == (base / "here" / "pairs.csv").read_text()
    a, b = read_cameras(base / "here" / "cameras.csv"), read_cameras(base / "dask" / "cameras.csv")
    np.testing.assert_allclose(a.matrices, b.matrices, rtol=1e-6, atol=1e-9)


def test_workers_are_for_images_not_tracks(tmp_path, capsys):
    tracks = tmp_path / "tracks.csv"
    tracks.write_text("frame,track_id,x,y\n0,0,1,1\n1,0,2,2\n")
    assert main(["reconstruct", str(tracks), "--out", str(tmp_path / "run"), "--workers", "2"]) == 2
    assert "--workers and --scheduler spread the matching of image pairs" in capsys.readouterr().err


def test_the_front_end_options_reach_the_detection_and_are_checked(folder, tmp_path, capsys):
    base, _ = folder
    common = ["reconstruct", str(base / "images"), "--camera", "perspective", "--intrinsics", str(base / "K.csv")]
    assert main([*common, "--max-features", "300", "--sift-upsampling", "2", "--out", str(tmp_path / "a"), "-q"]) == 0
    assert "median 300 features per image" in capsys.readouterr().out
    options = read_summary(tmp_path / "a" / "summary.json").source.options
    recorded = dict(options)["settings"]  # the run's source records the settings as JSON
    assert '"sift_upsampling":2.0' in recorded and '"max_features":300' in recorded
    assert main([*common, "--sift-upsampling", "3", "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--sift-upsampling must be in [0.25, 2]" in err[0] and not (tmp_path / "b").exists()
    tracks = tmp_path / "tracks.csv"
    tracks.write_text("frame,track_id,x,y\n0,0,1,2\n1,0,2,3\n")
    assert main(["reconstruct", str(tracks), "--camera", "perspective", "--focal", "500", "--image-size", "64", "48",
                 "--max-features", "300", "--detector", "orb", "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--detector, --max-features: the feature front end's options apply to images" in err[0]
