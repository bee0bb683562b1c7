"""Golden: a perspective run of the Oxford Model House leaves as a COLMAP model that pycolmap reads, and comes back.

Issue 28's targets: pycolmap reads the text and the binary model (all registered images, every
``ok`` point; camera centres and points equal to ours to 1e-9 of the scene radius; each point's
track length its ``views``); ``fuse --cameras MODEL`` with the house tracks gives back the run's
points (median difference ≤ 1e-6 of the radius); our reader gives the same reconstruction back.
The house's K has a skew of -0.1 to -26 px, which COLMAP's cameras cannot hold: the export maps it
out of the 2-D points and keeps it in ``cameras_skew.txt``.
"""

import numpy as np
import pytest

from kalmansfm.cli.main import main
from kalmansfm.io.colmap import read_colmap_model, read_skew
from kalmansfm.io.intrinsics import intrinsics_csv
from kalmansfm.io.oxford import read_oxford
from kalmansfm.io.reconstruction import read_reconstruction, reconstruction_of_colmap
from kalmansfm.io.structure import read_points_table
from kalmansfm.structure.geometry.pinhole import decompose_projection

from _oxford import DATA, convert

pycolmap = pytest.importorskip("pycolmap")


@pytest.fixture(scope="module")
def house(tmp_path_factory):
    """The house's tracks and K.csv, a perspective run of them, and its text and binary exports."""
    out = tmp_path_factory.mktemp("house")
    data = read_oxford(DATA / "oxford_model_house")
    convert("oxford_model_house", out)
    (out / "K.csv").write_text(intrinsics_csv(data.cameras.frames, decompose_projection(data.cameras.matrices).intrinsics))
    assert main(["reconstruct", str(out / "tracks.csv"), "--camera", "perspective", "--intrinsics", str(out / "K.csv"),
                 "--out", str(out / "run"), "-q"]) == 0
    assert main(["export", str(out / "run"), "--colmap", str(out / "text"), "-q"]) == 0
    assert main(["export", str(out / "run"), "--colmap", str(out / "binary"), "--binary", "-q"]) == 0
    return out


def radius(points):
    return np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))


@pytest.mark.parametrize("kind", ["text", "binary"])
def test_pycolmap_reads_every_registered_image_and_ok_point_as_ours(house, kind):
    rec = read_reconstruction(house / "run" / "reconstruction.npz")
    model = pycolmap.Reconstruction(str(house / kind / "sparse" / "0"))
    ok, reg = rec.reconstructed, rec.registered
    assert model.num_reg_images() == reg.sum() and model.num_points3D() == ok.sum()
    scale = radius(rec.points[ok])
    for point_id, point in model.points3D.items():
        track = point_id - 1  # ids are track id + 1
        k = int(np.searchsorted(rec.track_ids, track))
        assert np.abs(point.xyz - rec.points[k]).max() <= 1e-9 * scale
        assert point.track.length() == rec.views[k]
        assert point.error == pytest.approx(rec.point_reprojection_rms[k], rel=1e-12)
    for image in model.images.values():
        f = image.image_id - 1
        centre = image.projection_center()
        assert np.abs(centre - rec.centres[f]).max() <= 1e-9 * scale


def test_the_skew_is_mapped_out_and_kept_aside(house):
    skew = read_skew(house / "text" / "sparse" / "0")
    rec = read_reconstruction(house / "run" / "reconstruction.npz")
    assert len(skew) == rec.registered.sum() and max(abs(s) for s in skew.values()) > 20  # up to -26 px
    # pycolmap projects our 3-D points onto the model's (zero-skew) 2-D points: the model is consistent
    model = pycolmap.Reconstruction(str(house / "text" / "sparse" / "0"))
    worst = 0.0
    for image in model.images.values():
        camera = model.cameras[image.camera_id]
        for p2d in image.points2D:
            if p2d.has_point3D():
                projected = camera.img_from_cam(image.cam_from_world() * model.points3D[p2d.point3D_id].xyz)
                worst = max(worst, float(np.linalg.norm(projected - p2d.xy)))
    assert worst < 3.0  # the reprojection error of bundle adjustment, not the skew's shear


def test_our_reader_gives_the_reconstruction_back(house):
    rec = read_reconstruction(house / "run" / "reconstruction.npz")
    folder = house / "binary" / "sparse" / "0"
    back = reconstruction_of_colmap(read_colmap_model(folder), read_skew(folder))
    ok = rec.reconstructed
    np.testing.assert_allclose(back.points, rec.points[ok], rtol=0, atol=1e-12 * radius(rec.points[ok]))
    np.testing.assert_array_equal(back.track_ids, rec.track_ids[ok])
    np.testing.assert_allclose(back.intrinsics, rec.intrinsics[rec.registered], rtol=1e-14)
    np.testing.assert_allclose(back.point_covariances, rec.point_covariances[ok], rtol=1e-12)
    # the 2-D points come back to the original pixels (the skew put back)
    obs = rec.observations
    used = obs.used & ok[obs.point]
    mine = {(int(f), int(rec.track_ids[p])): xy for f, p, xy in zip(obs.frame[used], obs.point[used], obs.xy[used])}
    theirs = {(int(back.frame_ids[f]), int(back.track_ids[p])): xy for f, p, xy in
              zip(back.observations.frame, back.observations.point, back.observations.xy)}
    assert mine.keys() == theirs.keys()
    assert max(np.abs(mine[k] - theirs[k]).max() for k in mine) < 1e-9


def test_fuse_with_the_model_as_cameras_gives_the_points_back(house):
    assert main(["fuse", str(house / "tracks.csv"), "--cameras", str(house / "binary"), "--method", "batch",
                 "--out", str(house / "refused"), "-q"]) == 0
    run = read_points_table(house / "run" / "structure.csv")
    fused = read_points_table(house / "refused" / "structure.csv")
    ok = run.reliable & fused.reliable
    diff = np.linalg.norm(run.points[ok] - fused.points[ok], axis=1) / radius(run.points[run.reliable])
    assert ok.sum() >= 0.95 * run.reliable.sum() and np.median(diff) <= 1e-6


def test_an_affine_run_and_a_run_without_images_are_refused_in_one_line(house, tmp_path, capsys):
    assert main(["reconstruct", str(house / "tracks.csv"), "--out", str(tmp_path / "affine"), "-q"]) == 0
    capsys.readouterr()
    assert main(["export", str(tmp_path / "affine"), "--colmap", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "affine" in err[0] and "pinhole" in err[0] and not (tmp_path / "x").exists()
    assert main(["export", str(house / "run"), "--colmap", str(tmp_path / "y"), "--images", "copy"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "source images" in err[0] and not (tmp_path / "y").exists()
