"""K.csv (one row for all frames, or one per frame) and COLMAP cameras as intrinsics; errors name file and line."""

import os
import warnings

import numpy as np
import pytest
from colmap_scene import make_scene

from kalmansfm.errors import InvalidInputError
from kalmansfm.io.colmap import build_colmap_model, write_colmap_model
from kalmansfm.io.intrinsics import intrinsics_csv, intrinsics_from_focal, read_intrinsics


def test_per_frame_rows_read_back_exactly(tmp_path):
    K = np.array([[[812.25, 0.125, 321.5], [0, 799.0, 241.75], [0, 0, 1]],
                  [[700.0, 0.0, 300.0], [0, 701.0, 200.0], [0, 0, 1]]])
    f = tmp_path / "K.csv"
    f.write_text(intrinsics_csv([10, 3], K))
    np.testing.assert_array_equal(read_intrinsics(f, [3, 10, 3]), K[[1, 0, 1]])


def test_one_row_serves_every_frame(tmp_path):
    f = tmp_path / "K.csv"
    f.write_text("frame,fx,fy,cx,cy,skew\n0,500,500,320,240,0\n")
    K = read_intrinsics(f, np.arange(4))
    assert K.shape == (4, 3, 3) and np.all(K[:, 0, 0] == 500)


@pytest.mark.parametrize("text, message", [
    ("frame,fx,fy,cx\n0,1,1,1\n", r"line 1: missing column\(s\) cy; expected fx,fy,cx,cy; got frame,fx,fy,cx$"),
    ("frame,fx,fy,cx,cy,skew\n", r"line 1: no rows after the header$"),
    ("frame,fx,fy,cx,cy,skew\n0,800,0,320,240,0\n", "line 2: fx and fy must be > 0"),
    ("frame,fx,fy,cx,cy,skew\n0,800,abc,320,240,0\n", "line 2: fy must be a number"),
    ("frame,fx,fy,cx,cy,skew\n0,800,800,nan,240,0\n", "line 2: cx must be finite"),
    ("frame,fx,fy,cx,cy,skew\n0,1,1,1,1,0\n0,1,1,1,1,0\n", "lines 2 and 3: frame 0 has two rows"),
    ("frame,fx,fy,cx,cy,skew\n0,1,1,1,1,0\n1,1,1,1,1,0\n", "no intrinsics for frame 2"),
])
def test_bad_files_name_the_file_and_line(tmp_path, text, message):
    f = tmp_path / "K.csv"
    f.write_text(text)
    with pytest.raises(InvalidInputError, match=message):
        read_intrinsics(f, [0, 1, 2])


def test_focal_shortcut_needs_a_positive_focal_and_image_size():
    assert intrinsics_from_focal(900, (1920, 1080), 3)[2, 1, 2] == 540
    with pytest.raises(InvalidInputError, match="focal must be finite and > 0"):
        intrinsics_from_focal(-1, (640, 480), 1)
    with pytest.raises(InvalidInputError, match="image height"):
        intrinsics_from_focal(500, (640, 0), 1)


def test_one_camera_may_be_just_fx_fy_cx_cy(tmp_path):
    f = tmp_path / "K.csv"
    f.write_text("fx,fy,cx,cy\n800,810,320,240\n")
    K = read_intrinsics(f, [0, 5, 9])
    np.testing.assert_array_equal(K, np.broadcast_to([[800.0, 0, 320], [0, 810, 240], [0, 0, 1]], (3, 3, 3)))
    f.write_text("fx,fy,cx,cy\n800,810,320,240\n800,810,320,240\n")
    with pytest.raises(InvalidInputError, match=r"K\.csv: line 1: 2 rows need a frame column"):
        read_intrinsics(f, [0, 1])


@pytest.mark.parametrize("row, message", [
    ("0,800,800,320,240,1e6", r"line 2: skew 1e\+06 px is larger than the focal length 800 px"),
    ("0,800,0.5,320,240,0", r"line 2: fy / fx = 0\.000625: pixels that far from square"),
    ("0,1e300,800,320,240,0", r"line 2: fx must be within ±1e\+07 px"),
])
def test_absurd_intrinsics_are_refused_with_one_line_and_no_numpy_warning(tmp_path, row, message):
    f = tmp_path / "K.csv"
    f.write_text("frame,fx,fy,cx,cy,skew\n" + row + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidInputError, match=message):
            read_intrinsics(f, [0])


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")
def test_a_fifo_device_or_folder_as_k_file_is_refused_unread(tmp_path):
    os.mkfifo(tmp_path / "K.csv")
    with pytest.raises(InvalidInputError, match=r"K\.csv: is a FIFO, not a text CSV"):
        read_intrinsics(tmp_path / "K.csv", [0])  # would hang if opened for reading
    with pytest.raises(InvalidInputError, match=r"zero: is a device, not a text CSV"):
        read_intrinsics("/dev/zero", [0])
    with pytest.raises(InvalidInputError, match=r"no COLMAP model"):
        read_intrinsics(tmp_path, [0])  # a folder is read as a COLMAP model, and has none


def test_a_colmap_cameras_file_gives_k_in_our_pixel_convention(tmp_path):
    f = tmp_path / "cameras.txt"
    f.write_text("# Camera list\n7 SIMPLE_PINHOLE 640 480 800 320 240\n")
    K = read_intrinsics(f, [0, 1])
    np.testing.assert_array_equal(K[1], [[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
    f.write_text("7 OPENCV 640 480 800 800 320 240 0.1 0 0 0\n")
    with pytest.raises(InvalidInputError, match=r"camera model OPENCV has lens distortion.*until lens distortion is "
                                                r"supported"):
        read_intrinsics(f, [0])
    f.write_text("1 PINHOLE 640 480 800 800 320 240\n2 PINHOLE 640 480 900 900 320 240\n")
    with pytest.raises(InvalidInputError, match=r"cameras\.txt: holds 2 cameras; which frame uses which is in "
                                                r"images\.txt, which is not beside it"):
        read_intrinsics(f, [0])


@pytest.mark.parametrize("binary", [False, True])
def test_a_colmap_model_with_several_cameras_gives_each_frame_its_own(tmp_path, binary):
    scene = make_scene(frames=4, points=20, seed=4)
    names = ["c.png", "a.png", "d.png", "b.png"]
    model = build_colmap_model(scene.K, scene.R, scene.t, scene.size, names, scene.frames, scene.points_of, scene.xy,
                               scene.X)
    write_colmap_model(model, tmp_path, binary=binary)
    # by order: a, b, c, d are frames 0..3 — the scene's frames 1, 3, 0, 2
    np.testing.assert_array_equal(read_intrinsics(tmp_path, [0, 1, 2, 3]), scene.K[[1, 3, 0, 2]])
    by_name = {4: "d.png", 6: "c.png", 8: "b.png", 9: "a.png"}
    np.testing.assert_array_equal(read_intrinsics(tmp_path, [4, 6], frame_names=by_name), scene.K[[2, 0]])
    with pytest.raises(InvalidInputError, match=r"images\.(txt|bin): no image for frame 7 \(images matched to frames "
                                                r"by order\)"):
        read_intrinsics(tmp_path, [0, 7])
