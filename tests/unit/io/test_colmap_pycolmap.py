"""Our COLMAP models against pycolmap, COLMAP's own Python reader and writer (a test dependency, not a runtime one).

pycolmap reads what we write (every image, every point, the same centres, points, tracks and
errors); we read what pycolmap writes; and pycolmap's own projection confirms the pixel
convention: a point projects to our pixel + 0.5.
"""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from colmap_scene import DATA, make_scene

from kalmansfm.io.cameras import read_known_cameras
from kalmansfm.io.colmap import build_colmap_model, read_colmap_model, write_colmap_model
from kalmansfm.io.oxford import read_oxford
from kalmansfm.structure.geometry.pinhole import CameraSet, project_points

SCENE = make_scene()


def merton():
    """Oxford's Merton College I: 3 real views, 717 points, cameras given as P (K without skew to 1e-15)."""
    data = read_oxford(DATA / "oxford_merton1")
    pose = data.cameras.decompose()
    frame, point = np.nonzero(np.isfinite(data.observations).all(axis=2))
    K = pose.intrinsics.copy()
    K[:, 0, 1] = 0.0  # 4.5e-13 px of rounding in the decomposition
    error = np.linalg.norm(project_points(data.cameras, data.points).pixels - data.observations, axis=2)
    rms = np.sqrt(np.nanmean(error**2, axis=0))
    model = build_colmap_model(K, pose.rotations, pose.translations, (1024, 768), ["001.jpg", "002.jpg", "003.jpg"],
                               frame, point, data.observations[frame, point], data.points, errors=rms)
    return model, pose.centers, data.points, np.bincount(point, minlength=len(data.points))


def synthetic():
    return SCENE.model(), SCENE.centres, SCENE.X, np.bincount(SCENE.points_of)


@pytest.mark.parametrize("binary", [False, True])
@pytest.mark.parametrize("source", [synthetic, merton])
def test_pycolmap_reads_our_model_with_every_image_point_and_track(tmp_path, source, binary):
    model, centres, X, views = source()
    write_colmap_model(model, tmp_path, binary=binary)
    rec = pycolmap.Reconstruction(str(tmp_path))
    assert rec.num_reg_images() == len(centres) and rec.num_points3D() == len(X)
    radius = np.linalg.norm(X - X.mean(axis=0), axis=1).max()
    ids = sorted(rec.images)
    assert [rec.images[i].name for i in ids] == list(model.images.names)
    got_centres = np.array([rec.images[i].projection_center() for i in ids])
    assert np.abs(got_centres - centres).max() <= 1e-9 * radius
    point_ids = model.points.ids
    got = np.array([rec.points3D[int(p)].xyz for p in point_ids])
    assert np.abs(got - X[point_ids - 1]).max() <= 1e-9 * radius
    np.testing.assert_array_equal([rec.points3D[int(p)].track.length() for p in point_ids], views[point_ids - 1])
    np.testing.assert_array_equal([rec.points3D[int(p)].error for p in point_ids], model.points.errors)
    np.testing.assert_array_equal([rec.points3D[int(p)].color for p in point_ids], model.points.colours)
    # pycolmap's projection of each point lands on our projection + 0.5: the principal points and the 2-D
    # points were shifted the same way
    image, point, _ = model.observations()
    ours = project_points(CameraSet.from_pose(model.intrinsics(), model.images.rotations(), model.images.translations),
                          model.points.xyz).pixels[image, point]
    theirs = np.array([rec.images[int(model.images.ids[i])].project_point(model.points.xyz[p])
                       for i, p in zip(image, point)])
    np.testing.assert_allclose(theirs, ours + 0.5, rtol=0, atol=1e-9)
    # and each image's 2-D points are where we put them, naming the same 3-D points
    for i, iid in enumerate(model.images.ids):
        rows = slice(model.images.point_starts[i], model.images.point_starts[i + 1])
        got2d = rec.images[int(iid)].points2D
        np.testing.assert_array_equal([p.xy for p in got2d], model.images.points2d[rows])
        np.testing.assert_array_equal([p.point3D_id for p in got2d], model.images.point3d_ids[rows])


def test_pycolmap_puts_the_default_principal_point_where_ours_is_the_image_centre():
    create = getattr(pycolmap.Camera, "create_from_model_id", None) or pycolmap.Camera.create  # 3.12 has only create
    camera = create(1, pycolmap.CameraModelId.PINHOLE, 500.0, 640, 480)
    # COLMAP's image centre is (W/2, H/2) (the top-left corner at 0); ours is ((W - 1)/2, (H - 1)/2)
    assert camera.params.tolist()[2:] == [320.0, 240.0]
    model = build_colmap_model(np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]]), np.eye(3)[None],
                               [[0.0, 0.0, 1.0]], (640, 480), ["a.png"], [], [], np.zeros((0, 2)), np.zeros((0, 3)))
    assert model.cameras.params[0].tolist() == [500.0, 500.0, 320.0, 240.0]


def pycolmap_model(scene, shared_simple: bool) -> pycolmap.Reconstruction:
    """The scene built with pycolmap's own API (other ids, a SIMPLE_PINHOLE camera, keypoints without a point)."""
    rec = pycolmap.Reconstruction()
    image_ids = 10 * np.arange(1, len(scene.names) + 1) + 3
    for f, name in enumerate(scene.names):
        K = scene.K[f]
        if shared_simple and f == 0:
            camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480,
                                     params=[K[0, 0], K[0, 2] + 0.5, K[1, 2] + 0.5], camera_id=100 + f)
        else:
            camera = pycolmap.Camera(model="PINHOLE", width=640, height=480,
                                     params=[K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5], camera_id=100 + f)
        rec.add_camera_with_trivial_rig(camera)
        mine = scene.frames == f
        keypoints = np.vstack([scene.xy[mine] + 0.5, [[1.0, 2.0]]])  # the last keypoint belongs to no point
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=100 + f, image_id=int(image_ids[f]))
        quaternion = pycolmap.Rotation3d(scene.R[f])
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(quaternion, scene.t[f]))
    # observation k is keypoint (k - first observation of its frame) of its frame's image
    first = np.searchsorted(scene.frames, scene.frames)
    for p in range(len(scene.X)):
        track = pycolmap.Track()
        for k in np.flatnonzero(scene.points_of == p):
            track.add_element(int(image_ids[scene.frames[k]]), int(k - first[k]))
        new = rec.add_point3D(scene.X[p], track, scene.colours[p])
        rec.points3D[new].error = float(scene.errors[p])
    return rec


@pytest.mark.parametrize("binary", [False, True])
def test_a_model_written_by_pycolmap_reads_back_with_equal_values(tmp_path, binary):
    scene = make_scene(frames=4, points=40, seed=3)
    rec = pycolmap_model(scene, shared_simple=True)
    (rec.write_binary if binary else rec.write_text)(str(tmp_path))
    assert (tmp_path / ("rigs.bin" if binary else "rigs.txt")).exists()  # pycolmap 3.12+ writes rigs and frames
    model = read_colmap_model(tmp_path)
    order = np.argsort(model.images.ids)
    assert [model.images.names[i] for i in order] == scene.names
    assert model.cameras.models[list(model.cameras.ids).index(100)] == "SIMPLE_PINHOLE"
    K = scene.K.copy()
    K[0, 1, 1] = K[0, 0, 0]  # frame 0's camera is a SIMPLE_PINHOLE: one focal length
    np.testing.assert_allclose(model.intrinsics()[order], K, rtol=1e-15, atol=1e-12)
    np.testing.assert_allclose(model.images.rotations()[order], scene.R, atol=1e-14)
    np.testing.assert_array_equal(model.images.translations[order], scene.t)
    ours = np.array([rec.points3D[int(p)].xyz for p in model.points.ids])
    np.testing.assert_array_equal(model.points.xyz, ours)
    np.testing.assert_array_equal(model.points.errors, [rec.points3D[int(p)].error for p in model.points.ids])
    np.testing.assert_array_equal(model.points.track_lengths, [rec.points3D[int(p)].track.length()
                                                               for p in model.points.ids])
    for i, iid in enumerate(model.images.ids):
        rows = slice(model.images.point_starts[i], model.images.point_starts[i + 1])
        theirs = rec.images[int(iid)].points2D
        np.testing.assert_array_equal(model.images.points2d[rows], [p.xy for p in theirs])
        expected = [p.point3D_id if p.has_point3D() else -1 for p in theirs]
        np.testing.assert_array_equal(model.images.point3d_ids[rows], expected)
    # and the same model serves as known cameras, by name
    known = read_known_cameras(tmp_path, frame_names=scene.names)
    assert known.matched_by == "name" and known.source_format == ("COLMAP binary" if binary else "COLMAP text")
    truth = CameraSet.from_pose(K, scene.R, scene.t)
    np.testing.assert_allclose(known.cameras.matrices[np.argsort(known.cameras.frames)], truth.matrices,
                               rtol=1e-12, atol=1e-9)
