"""COLMAP sparse models with our own reader and writer: lossless round trips, the pixel convention, the
covariance side-car, no empty track written, and one clear line for every bad model (issue 28)."""

from __future__ import annotations

import dataclasses
import os
import struct
import warnings

import numpy as np
import pytest
from colmap_scene import make_scene
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kalmansfm.errors import InvalidInputError
from kalmansfm.io._colmap_records import rows_of
from kalmansfm.io.colmap import (
    COVARIANCE_FILE,
    ColmapModel,
    ColmapPoints,
    build_colmap_model,
    locate_colmap_model,
    read_colmap_model,
    write_colmap_model,
)
from kalmansfm.structure.geometry.pinhole import CameraSet, project_points

SCENE = make_scene()


def assert_same_model(a: ColmapModel, b: ColmapModel) -> None:
    """Every array equal bit for bit (NaN where NaN), every name and gauge equal."""
    for part in ("cameras", "images", "points"):
        x, y = getattr(a, part), getattr(b, part)
        for name in x.__dataclass_fields__:
            u, v = getattr(x, name), getattr(y, name)
            if isinstance(u, tuple):
                assert u == v, (part, name)
            else:
                np.testing.assert_array_equal(u, v, err_msg=f"{part}.{name}")
    np.testing.assert_array_equal(a.covariances, b.covariances)
    assert a.covariance_gauge == b.covariance_gauge


def test_the_builder_writes_what_the_reconstruction_says_in_colmap_pixels():
    model = SCENE.model()
    K, R = SCENE.K, SCENE.R
    assert model.images.ids.tolist() == list(range(1, 7)) and model.images.names == tuple(SCENE.names)
    assert len(model.cameras.ids) == 5 and set(model.cameras.models) == {"PINHOLE"}  # frames 0 and 3 share one
    np.testing.assert_array_equal(model.intrinsics(), K)  # back in our convention exactly (x.5 ± 0.5)
    np.testing.assert_array_equal(model.cameras.params[0], [K[0, 0, 0], K[0, 1, 1], K[0, 0, 2] + 0.5, K[0, 1, 2] + 0.5])
    np.testing.assert_allclose(model.images.rotations(), R, atol=1e-15)
    assert (model.images.quaternions[:, 0] >= 0).all()
    image, point, xy = model.observations()
    order = np.lexsort((SCENE.points_of, SCENE.frames))
    np.testing.assert_array_equal(image, SCENE.frames[order])
    np.testing.assert_array_equal(point, SCENE.points_of[order])
    np.testing.assert_allclose(xy, SCENE.xy[order], rtol=0, atol=1e-12)  # ± 0.5 is exact but for the last bit
    np.testing.assert_array_equal(model.images.points2d, SCENE.xy[order] + 0.5)
    np.testing.assert_array_equal(model.points.track_lengths, np.bincount(SCENE.points_of))
    np.testing.assert_array_equal(model.points.colours, SCENE.colours)
    np.testing.assert_array_equal(model.points.errors, SCENE.errors)


@pytest.mark.parametrize("binary", [False, True])
def test_a_written_model_reads_back_bit_for_bit(tmp_path, binary):
    model = SCENE.model()
    written = write_colmap_model(model, tmp_path / "sparse" / "0", binary=binary)
    ext = ".bin" if binary else ".txt"
    assert [f.name for f in written.files] == [f"points3D{ext}", f"images{ext}", f"cameras{ext}", COVARIANCE_FILE]
    assert not [p for p in (tmp_path / "sparse" / "0").iterdir() if p.name.endswith(".tmp")]
    back = read_colmap_model(tmp_path)  # found in sparse/0
    assert_same_model(back, model)
    assert back.covariance_gauge == "free-network gauge (test)"


def test_text_and_binary_convert_into_each_other_losslessly(tmp_path):
    rng = np.random.default_rng(5)
    awkward = SCENE.xy + rng.normal(scale=1e-7, size=SCENE.xy.shape) * [1.0, 1e-9]  # digits that text must keep
    model = SCENE.model(errors=None, covariances=None)
    model = build_colmap_model(SCENE.K, SCENE.R, SCENE.t, SCENE.size, SCENE.names, SCENE.frames, SCENE.points_of,
                               awkward, SCENE.X * np.pi)
    write_colmap_model(model, tmp_path / "text")
    text = read_colmap_model(tmp_path / "text")
    write_colmap_model(text, tmp_path / "bin", binary=True)
    binary = read_colmap_model(tmp_path / "bin")
    write_colmap_model(binary, tmp_path / "text2")
    assert_same_model(text, model)
    assert_same_model(binary, model)
    assert (tmp_path / "text" / "images.txt").read_bytes() == (tmp_path / "text2" / "images.txt").read_bytes()
    assert (model.points.errors == -1).all() and model.covariances is None  # COLMAP's "not computed"


def test_frames_without_pose_points_not_kept_or_unseen_are_left_out_and_no_track_is_empty():
    t = SCENE.t.copy()
    t[2] = np.nan  # frame 2 not registered
    keep = np.ones(len(SCENE.X), dtype=bool)
    keep[::3] = False
    only_in_2 = np.flatnonzero(np.bincount(SCENE.points_of[SCENE.frames != 2], minlength=len(SCENE.X)) == 0)
    model = build_colmap_model(SCENE.K, SCENE.R, t, SCENE.size, SCENE.names, SCENE.frames, SCENE.points_of, SCENE.xy,
                               SCENE.X, keep=keep, point_ids=np.arange(len(SCENE.X)) + 100)
    assert 3 not in model.images.ids and len(model.images.ids) == 5
    expected = np.setdiff1d(np.flatnonzero(keep), only_in_2) + 100
    np.testing.assert_array_equal(model.points.ids, expected)
    assert (model.points.track_lengths > 0).all()
    assert set(model.points.track_image_ids.tolist()) <= set(model.images.ids.tolist())


def test_a_point_with_an_empty_track_is_never_written(tmp_path):
    model = SCENE.model()
    p = model.points
    lengths = p.track_lengths.copy()
    # a model read from elsewhere may hold a point that no image sees: give point 1 an empty track
    lonely = ColmapPoints(np.append(p.ids, 10_000), np.vstack([p.xyz, [0.0, 0.0, 0.0]]), np.vstack([p.colours, [1, 2, 3]]),
                          np.append(p.errors, 0.5), np.append(p.track_starts, p.track_starts[-1]), p.track_image_ids,
                          p.track_point2d)
    odd = ColmapModel(model.cameras, model.images, lonely)
    assert odd.points.track_lengths[-1] == 0
    written = write_colmap_model(odd, tmp_path, binary=True)
    assert written.dropped_empty_tracks == 1 and written.points == len(lengths)
    back = read_colmap_model(tmp_path)
    assert 10_000 not in back.points.ids and (back.points.track_lengths > 0).all()
    assert not (tmp_path / COVARIANCE_FILE).exists()


def test_the_covariance_side_car_holds_the_six_entries_and_the_gauge(tmp_path):
    cov = SCENE.covariances.copy()
    cov[4] = np.nan  # a point without covariance has no line
    model = SCENE.model(covariances=cov, covariance_gauge="free-network gauge: aligned on all points")
    write_colmap_model(model, tmp_path)
    lines = (tmp_path / COVARIANCE_FILE).read_text().splitlines()
    assert "# GAUGE: free-network gauge: aligned on all points" in lines
    data = [line.split() for line in lines if not line.startswith("#")]
    assert len(data) == len(SCENE.X) - 1
    first = np.array(data[0][1:], dtype=float)
    np.testing.assert_array_equal(first, cov[0][[0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]])
    back = read_colmap_model(tmp_path)
    np.testing.assert_array_equal(back.covariances, cov)
    assert back.covariance_gauge == "free-network gauge: aligned on all points"
    write_colmap_model(SCENE.model(covariances=None), tmp_path)  # a model without covariances
    assert not (tmp_path / COVARIANCE_FILE).exists()  # the old side-car described other points
    assert read_colmap_model(tmp_path).covariances is None


def test_known_cameras_reproject_the_model_points_where_pycolmap_would():
    """COLMAP's convention (pixel centre at +0.5) and ours give the same camera once K and points both shift."""
    model = SCENE.model()
    cams = CameraSet.from_pose(model.intrinsics(), model.images.rotations(), model.images.translations)
    image, point, xy = model.observations()
    projected = project_points(cams, model.points.xyz).pixels[image, point]
    truth = project_points(CameraSet.from_pose(SCENE.K, SCENE.R, SCENE.t), SCENE.X).pixels[image,
                                                                                          model.points.ids[point] - 1]
    np.testing.assert_allclose(projected, truth, atol=1e-9)


def write_text_model(folder, cameras="1 PINHOLE 640 480 500 500 320 240\n",
                     images="1 1 0 0 0 0 0 4 1 a.png\n10 20 1 30 40 -1\n2 1 0 0 0 -1 0 4 1 b.png\n15 20 1\n",
                     points="1 0 0 1 10 20 30 0.5 1 0 2 0\n"):
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in (("cameras", cameras), ("images", images), ("points3D", points)):
        if text is not None:
            (folder / f"{name}.txt").write_text(text)
    return folder


def test_a_hand_written_text_model_reads_with_empty_points_lines_and_point_ids_from_the_tracks(tmp_path):
    folder = write_text_model(tmp_path, images="# c\n1 1 0 0 0 0 0 4 1 a b.png\n10 20 7 30 40 -1\n"
                                               "2 1 0 0 0 -1 0 4 1 b.png\n\n3 1 0 0 0 1 0 4 1 c.png\n15 20 -1",
                              points="1 0 0 1 10 20 30 0.5 1 0 3 0\n")
    model = read_colmap_model(folder)
    assert model.images.names == ("a b.png", "b.png", "c.png")  # a name keeps its spaces
    assert np.diff(model.images.point_starts).tolist() == [2, 0, 1]
    # the tracks say which 3-D point a 2-D point belongs to (the file's 7 named no point), as in COLMAP
    assert model.images.point3d_ids.tolist() == [1, -1, 1]
    with pytest.raises(InvalidInputError, match="holds a space, which COLMAP's text format cannot hold"):
        write_colmap_model(model, tmp_path / "out")
    write_colmap_model(model, tmp_path / "out", binary=True)
    assert read_colmap_model(tmp_path / "out").images.names[0] == "a b.png"


def truncated(tmp_path, name, keep):
    folder = tmp_path / "bin"
    write_colmap_model(SCENE.model(covariances=None), folder, binary=True)
    data = (folder / name).read_bytes()
    (folder / name).write_bytes(data[:keep(len(data))])
    return folder


@pytest.mark.parametrize("make, message", [
    (lambda d: d, r"no COLMAP model \(expected cameras, images, points3D as \.bin or \.txt files here, in sparse/0/"),
    (lambda d: d / "nothing", r"nothing: no such file or folder"),
    (lambda d: write_text_model(d, points=None), r"incomplete COLMAP model: has cameras\.txt, images\.txt but no "
                                                 r"points3D\.txt"),
    (lambda d: truncated(d, "points3D.bin", lambda n: n - 3), r"points3D\.bin: truncated or corrupt COLMAP binary "
                                                              r"file: the track of point 120 runs past its end"),
    (lambda d: truncated(d, "points3D.bin", lambda n: n // 2), r"points3D\.bin: truncated or corrupt COLMAP binary"),
    (lambda d: truncated(d, "images.bin", lambda n: n - 1), r"images\.bin: truncated or corrupt COLMAP binary file: "
                                                            r"the points of image 6 runs past its end"),
    (lambda d: truncated(d, "cameras.bin", lambda n: 4), r"cameras\.bin: truncated or corrupt COLMAP binary file"),
    (lambda d: truncated(d, "images.bin", lambda n: n + 0) and (d / "bin" / "images.bin").write_bytes(
        struct.pack("<Q", 2**40) + bytes(100)) and d / "bin", r"images\.bin: truncated or corrupt COLMAP binary file: "
                                                                r"it says 1099511627776 images"),
    (lambda d: write_text_model(d, cameras="1 OPENCV 640 480 500 500 320 240 0 0 0 0\n"),
     r"cameras\.txt: line 1: camera model OPENCV has lens distortion, which kalmansfm does not model yet: only "
     r"PINHOLE and SIMPLE_PINHOLE cameras are read until lens distortion is supported"),
    (lambda d: write_text_model(d, cameras="1 FANCY 640 480 500\n"), r"cameras\.txt: line 1: unknown camera model "
                                                                     r"'FANCY'"),
    (lambda d: write_text_model(d, cameras="1 PINHOLE 640 480 500 320 240\n"), r"line 1: a PINHOLE camera has 4 "
                                                                               r"parameters; got 3"),
    (lambda d: write_text_model(d, images="1 1 0 0 0 0 0 4 9 a.png\n10 20 -1\n"),
     r"images\.txt: image 1 \(a\.png\) names camera 9, which .*cameras\.txt does not hold"),
    (lambda d: write_text_model(d, points="1 0 0 1 10 20 30 0.5 1 0 5 0\n"),
     r"points3D\.txt: point 1's track names image 5, which .*images\.txt does not hold"),
    (lambda d: write_text_model(d, points="1 0 0 1 10 20 30 0.5 1 3\n"),
     r"points3D\.txt: point 1's track names 2-D point 3 of image 1, which has 2"),
    (lambda d: write_text_model(d, points="1 0 0 1 10 20 30 0.5 1 0\n2 0 0 1 10 20 30 0.5 1 0\n"),
     r"points3D\.txt: 2-D point 0 of image 1 is in two tracks"),
    (lambda d: write_text_model(d, points="1 0 0 nan 10 20 30 0.5 1 0\n"), r"points3D\.txt: line 1: X Y Z must be "
                                                                            r"finite"),
    (lambda d: write_text_model(d, points="1 0 0 1 10 20 300 0.5 1 0\n"), r"line 1: R G B must be integers in 0"),
    (lambda d: write_text_model(d, images="1 1 0 0 0 0 0 4 1 a.png\n10 20\n"), r"images\.txt: line 2: the points of "
                                                                               r"image 1 must be X Y POINT3D_ID"),
    (lambda d: write_text_model(d, images="1 1 0 0 0 0 0 4 1 a.png\n10 20 0.5\n"), r"images\.txt: line 2: the points "
                                                                                   r"of image 1 need a POINT3D_ID"),
    (lambda d: write_text_model(d, images="1 1 0 0 0 0 0 4 1 a.png\n10 inf 1\n"), r"images\.txt: line 2: X Y POINT3D_ID "
                                                                                  r"must be finite"),
    (lambda d: write_text_model(d, images="1 0 0 0 0 0 0 4 1 a.png\n\n", points=""), r"image 1 \(a\.png\): its pose "
                                                                                     r"must be finite with a nonzero"),
    (lambda d: write_text_model(d, cameras="1 PINHOLE 640 480 500 500 x 240\n"), r"line 1: the parameters must be "
                                                                                 r"numbers"),
])
def test_bad_models_are_refused_with_one_line_naming_the_file(tmp_path, make, message):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidInputError, match=message) as info:
            read_colmap_model(make(tmp_path))
    assert "\n" not in str(info.value)


def test_an_unsupported_binary_camera_model_is_named(tmp_path):
    folder = truncated(tmp_path, "cameras.bin", lambda n: n)
    data = bytearray((folder / "cameras.bin").read_bytes())
    data[12:16] = struct.pack("<i", 4)  # the first camera's model id: OPENCV
    (folder / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(InvalidInputError, match=r"cameras\.bin: camera 1: camera model OPENCV has lens distortion"):
        read_colmap_model(folder)
    data[12:16] = struct.pack("<i", 99)
    (folder / "cameras.bin").write_bytes(bytes(data))
    with pytest.raises(InvalidInputError, match=r"unknown camera model 'id 99'"):
        read_colmap_model(folder)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")
def test_a_fifo_or_device_in_place_of_a_model_file_is_refused_unread(tmp_path):
    folder = write_text_model(tmp_path / "m")
    (folder / "images.txt").unlink()
    os.mkfifo(folder / "images.txt")
    with pytest.raises(InvalidInputError, match=r"images\.txt: is a FIFO, not a COLMAP model file"):
        read_colmap_model(folder)  # would block forever if it were opened for reading


def test_locating_prefers_binary_and_accepts_a_file(tmp_path):
    write_colmap_model(SCENE.model(covariances=None), tmp_path / "0", binary=True)
    assert locate_colmap_model(tmp_path) == (tmp_path / "0", ".bin")
    assert locate_colmap_model(tmp_path / "0" / "images.bin") == (tmp_path / "0", ".bin")
    with pytest.raises(InvalidInputError, match=r"already holds cameras\.bin, images\.bin, points3D\.bin of another "
                                                r"COLMAP model"):
        write_colmap_model(SCENE.model(), tmp_path / "0")  # text beside binary would be shadowed


@pytest.mark.parametrize("change, message", [
    (dict(intrinsics=np.array([[800.0, 0.5, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])),
     r"COLMAP's PINHOLE camera is \[\[fx, 0, cx\], \[0, fy, cy\], \[0, 0, 1\]\] \(no skew\)"),
    (dict(rotations=np.stack([np.diag([1.0, 1.0, -1.0])] * 6)), r"rotation of image frame_0000\.png is not a rotation"),
    (dict(image_names=["a.png"] * 6), r"image names must be unique; 'a\.png' repeats"),
    (dict(image_names=[f"x{k}.png\n" for k in range(6)]), r"cannot be written: it must be non-empty"),
    (dict(image_sizes=(640.5, 480)), "image sizes must be positive integers"),
    (dict(covariance_gauge=None), "covariances need a covariance_gauge"),
])
def test_the_builder_refuses_what_colmap_cannot_hold(change, message):
    arguments = dict(intrinsics=SCENE.K, rotations=SCENE.R, translations=SCENE.t, image_sizes=SCENE.size,
                     image_names=SCENE.names, observation_frames=SCENE.frames, observation_points=SCENE.points_of,
                     observation_xy=SCENE.xy, points=SCENE.X, covariances=SCENE.covariances,
                     covariance_gauge="gauge")
    arguments.update(change)
    with pytest.raises(InvalidInputError, match=message):
        build_colmap_model(**arguments)


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(xyz=st.lists(st.tuples(finite, finite, finite), min_size=1, max_size=5),
       xy=st.lists(st.tuples(finite, finite), min_size=2, max_size=2), error=finite)
def test_any_finite_numbers_survive_text_and_binary_bit_for_bit(tmp_path_factory, xyz, xy, error):
    """Shortest round-trip text (and -0.0, subnormals, 1e308) reads back as the very same doubles."""
    model = SCENE.model(covariances=None)
    p = model.points
    n = min(len(xyz), len(p.ids))
    changed = ColmapPoints(p.ids[:n], np.array(xyz[:n]), p.colours[:n], np.full(n, error),
                           p.track_starts[:n + 1], p.track_image_ids[:p.track_starts[n]],
                           p.track_point2d[:p.track_starts[n]])
    images = model.images
    points2d = images.points2d.copy()
    points2d[:2] = xy
    owner = np.full(len(points2d), -1)
    rows = images.point_starts[rows_of(images.ids, changed.track_image_ids)] + changed.track_point2d
    owner[rows] = np.repeat(changed.ids, changed.track_lengths)
    images = dataclasses.replace(images, points2d=points2d, point3d_ids=owner)
    model = ColmapModel(model.cameras, images, changed)
    for binary in (False, True):
        folder = tmp_path_factory.mktemp("m")
        write_colmap_model(model, folder, binary=binary)
        assert_same_model(read_colmap_model(folder), model)
