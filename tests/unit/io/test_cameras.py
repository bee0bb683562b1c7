"""The cameras CSV: both layouts, exact round trip, and one clear error per bad file."""

import os
import warnings
from pathlib import Path

import numpy as np
import pytest
from colmap_scene import DATA, make_scene
from scipy.spatial.transform import Rotation

from kalmansfm.errors import InvalidInputError, KalmanSfmWarning, NotEnoughDataError
from kalmansfm.io.cameras import (
    MATRIX_COLUMNS,
    MAX_CAMERAS_BYTES,
    POSE_COLUMNS,
    POSE_STD_COLUMNS,
    cameras_csv,
    match_cameras,
    pose_cameras_csv,
    read_cameras,
    read_known_cameras,
)
from kalmansfm.io.colmap import build_colmap_model, write_colmap_model
from kalmansfm.structure.geometry.pinhole import CameraSet

R = Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix()
POSE_ROW = [7, 800.0, 780.0, 320.0, 240.0, 0.5, *R.ravel(), 0.1, -0.2, 4.0]


def write(tmp_path, header, rows, name="cameras.csv"):
    f = tmp_path / name
    f.write_text(",".join(header) + "\n" + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    return f


def test_pose_layout_builds_k_r_t(tmp_path):
    cams = read_cameras(write(tmp_path, POSE_COLUMNS, [POSE_ROW]))
    K = np.array([[800.0, 0.5, 320.0], [0.0, 780.0, 240.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(cams.matrices[0], K @ np.hstack([R, [[0.1], [-0.2], [4.0]]]), rtol=1e-12)
    pose = cams.decompose()
    np.testing.assert_allclose(pose.intrinsics[0], K, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(pose.rotations[0], R, atol=1e-12)
    assert cams.frames.tolist() == [7]


def test_matrix_layout_round_trips_exactly(tmp_path):
    P = np.random.default_rng(0).normal(size=(4, 3, 4)) * [[1e3], [1e3], [1e-3]]
    cams = CameraSet.from_matrices(P, frames=[3, 1, 10, 2])
    f = tmp_path / "c.csv"
    f.write_text("# exported by a test\n" + cameras_csv(cams))
    back = read_cameras(f)
    np.testing.assert_array_equal(back.matrices, cams.matrices)
    np.testing.assert_array_equal(back.frames, cams.frames)


def test_pose_layout_with_the_std_columns_round_trips_k_r_t(tmp_path):
    rng = np.random.default_rng(3)
    R = Rotation.random(3, random_state=4).as_matrix()
    t = rng.normal(size=(3, 3)) * [1e-3, 1.0, 1e3]
    K = np.array([[[800.0 + 10 * v, 0.25 * v, 320.1], [0.0, 790.0 + v, 240.7], [0.0, 0.0, 1.0]] for v in range(3)])
    f = tmp_path / "cameras.csv"
    f.write_text(pose_cameras_csv([9, 4, 6], K, R, t, rotation_std_deg=[0.1, np.nan, 0.3],
                                  centre_std=[1e-3, 2e-3, 3e-3]))
    lines = f.read_text().splitlines()
    assert lines[0] == ",".join(POSE_COLUMNS + POSE_STD_COLUMNS)
    assert lines[2].endswith(",,0.002")  # no value is an empty cell
    table = np.genfromtxt(f, delimiter=",", names=True)
    np.testing.assert_array_equal(table["centre_std"], [1e-3, 2e-3, 3e-3])
    back = read_cameras(f)
    assert back.frames.tolist() == [9, 4, 6]
    # the same product as CameraSet.from_pose, from the very same K, R and t
    np.testing.assert_array_equal(back.matrices, K @ np.concatenate([R, t[:, :, None]], axis=2))
    np.testing.assert_allclose(back.matrices, CameraSet.from_pose(K, R, t).matrices, rtol=1e-15, atol=1e-12)
    plain = pose_cameras_csv([1], K[:1], R[:1], t[:1])
    assert plain.splitlines()[0] == ",".join(POSE_COLUMNS)


@pytest.mark.parametrize("extra, message", [
    ({"rotation_std_deg": [0.1]}, "give both or neither"),
    ({"rotation_std_deg": [0.1, 0.2], "centre_std": [0.1]}, "one value per frame"),
])
def test_pose_writer_refuses_mismatched_columns(extra, message):
    with pytest.raises(InvalidInputError, match=message):
        pose_cameras_csv([1], np.eye(3)[None], np.eye(3)[None], np.zeros((1, 3)), **extra)
    with pytest.raises(InvalidInputError, match="needs"):
        pose_cameras_csv([1, 2], np.eye(3)[None], np.eye(3)[None], np.zeros((1, 3)))


def bad_pose(index, value):
    row = list(POSE_ROW)
    row[index] = value
    return row


@pytest.mark.parametrize(
    "header, rows, message",
    [
        (MATRIX_COLUMNS[:-1], [[0] + [1.0] * 11], r"line 1: missing column\(s\) p34 of the projection-matrix layout; "
         r"expected the projection-matrix layout frame,p11,.*,p34 or the intrinsics \+ pose layout frame,fx,.*,t3; got "),
        (POSE_COLUMNS[:-2], [POSE_ROW[:-2]], r"missing column\(s\) t2, t3 of the intrinsics \+ pose layout; expected"),
        (POSE_COLUMNS, [POSE_ROW, POSE_ROW], "lines 2 and 3: frame 7 has two cameras"),
        (POSE_COLUMNS, [bad_pose(3, "nan")], "line 2: cx must be finite"),
        (POSE_COLUMNS, [bad_pose(2, "x")], "line 2: fy must be a number"),
        (POSE_COLUMNS, [bad_pose(1, -800.0)], "line 2: fx and fy must be > 0"),
        (POSE_COLUMNS, [bad_pose(6, 2.0)], "line 2: r11..r33 is not a rotation"),
        (MATRIX_COLUMNS, [[0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0], [5, 1, 2, 3, 0, 2, 4, 6, 0, 0, 0, 1, 0]],
         "line 3: frame 5: not a camera"),
        (MATRIX_COLUMNS, [[1.5] + [1.0] * 12], "line 2: frame must be an integer"),
        (MATRIX_COLUMNS, [], r"line 1: no rows after the header$"),
    ],
)
def test_bad_camera_files_name_the_file_and_line(tmp_path, header, rows, message):
    f = write(tmp_path, header, rows)
    with pytest.raises(InvalidInputError, match=message) as info:
        read_cameras(f)
    assert str(f) in str(info.value) and "\n" not in str(info.value)


def test_missing_and_ragged_files(tmp_path):
    with pytest.raises(InvalidInputError, match="no such file"):
        read_cameras(tmp_path / "none.csv")
    f = tmp_path / "ragged.csv"
    f.write_text(",".join(MATRIX_COLUMNS) + "\n0,1,2\n")
    with pytest.raises(InvalidInputError, match="line 2: 3 fields, the header has 13"):
        read_cameras(f)


def test_tracks_are_matched_to_camera_frames():
    cams = CameraSet.from_matrices(np.stack([np.eye(3, 4)] * 3), frames=[9, 2, 5])
    positions = np.arange(4 * 2 * 2, dtype=float).reshape(4, 2, 2)
    positions[3] = np.nan  # frame 7: no observation, no camera — not reported
    m = match_cameras(positions, np.array([2, 4, 9, 7]), np.array([10, 11]), cams)
    assert m.cameras.frames.tolist() == [2, 9]
    np.testing.assert_array_equal(m.observations, positions[[0, 2]])
    assert m.frames_without_camera.tolist() == [4]
    with pytest.raises(NotEnoughDataError, match="tracks.csv: 1 of its 2 frame"):
        match_cameras(positions[:2], np.array([2, 4]), np.array([10, 11]), cams, source="tracks.csv")


# --- camera files that tell the truth (issues 27, 30) ------------------------------------------------------------


def dinoring_cameras_csv(tmp_path):
    """Middlebury dinoRing's published K, R, t (R orthonormal only to 1.6e-6) as a cameras.csv."""
    rows = [line.split() for line in (DATA / "middlebury_dinoring" / "dinoR_par.txt").read_text().splitlines()[1:]]
    values = np.array([r[1:] for r in rows], dtype=float)
    K, R, t = values[:, :9].reshape(-1, 3, 3), values[:, 9:18].reshape(-1, 3, 3), values[:, 18:]
    f = tmp_path / "dino_cameras.csv"
    f.write_text(pose_cameras_csv(np.arange(len(rows)), K, R, t))
    return f, K, R, t


def test_dinoring_published_rotations_are_accepted_with_a_warning_saying_how_far_they_were_off(tmp_path):
    f, K, R, t = dinoring_cameras_csv(tmp_path)
    off = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    assert 1e-6 < off.max() < 2e-6 and (off > 1e-6).sum() == 29  # the data set's README
    known = read_known_cameras(f)
    assert len(known.warnings) == 1
    assert f"48 of 48 rotation(s) orthonormal only to {off.max():.2g}" in known.warnings[0]
    assert str(f) in known.warnings[0]
    pose = known.cameras.decompose()
    np.testing.assert_allclose(pose.rotations @ np.swapaxes(pose.rotations, 1, 2), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-14)
    assert np.abs(pose.rotations - R).max() < 2e-6  # the nearest rotation moved them by the rounding only
    np.testing.assert_allclose(pose.intrinsics, K, rtol=1e-9, atol=1e-9)
    with pytest.warns(KalmanSfmWarning, match="orthonormal only to 1.6e-06"):
        read_cameras(f)


def test_a_reflection_or_a_matrix_far_from_a_rotation_is_refused_with_its_deviation(tmp_path):
    mirrored = POSE_ROW[:6] + list((R @ np.diag([1.0, 1.0, -1.0])).ravel()) + POSE_ROW[15:]
    with pytest.raises(InvalidInputError, match=r"line 2: r11\.\.r33 is not a rotation \(det R = -1: a reflection\)"):
        read_cameras(write(tmp_path, POSE_COLUMNS, [mirrored]))
    skewed = POSE_ROW[:6] + list((R * 1.01).ravel()) + POSE_ROW[15:]
    with pytest.raises(InvalidInputError, match=r"line 2: r11\.\.r33 is not a rotation \(R Rᵀ differs from I by "
                                                r"0\.0201, more than the 0\.001 that rounding explains\)"):
        read_cameras(write(tmp_path, POSE_COLUMNS, [skewed]))


def test_georeferenced_projection_matrices_are_cameras(tmp_path):
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    centres = np.array([[4.2e5, 5.1e6, 310.0], [4.2e5 + 3.0, 5.1e6, 311.0]])  # UTM metres
    t = -np.einsum("ij,vj->vi", R, centres)
    P = K @ np.concatenate([np.stack([R] * 2), t[:, :, None]], axis=2)
    assert np.abs(P[:, :, 3]).max() > 1e8
    f = tmp_path / "geo.csv"
    f.write_text(cameras_csv(CameraSet.from_matrices(P)))
    cams = read_cameras(f)
    np.testing.assert_array_equal(cams.matrices, P)
    np.testing.assert_allclose(cams.centers, centres, rtol=1e-12)
    pose = write(tmp_path, POSE_COLUMNS, [[v, *K[[0, 1, 0, 1, 0], [0, 1, 2, 2, 1]], *R.ravel(), *t[v]] for v in range(2)])
    np.testing.assert_allclose(read_cameras(pose).matrices, P, rtol=1e-15)


@pytest.mark.parametrize("index, value, message", [
    (5, 1e6, r"line 2: skew 1e\+06 px is larger than the focal length 800 px"),
    (1, 1e300, r"line 2: fx and fy must be at most 1e\+07 px; got 1e\+300, 780"),
    (3, 1e300, r"line 2: cx and cy must be within ±1e\+07 px"),
    (16, 1e300, r"line 2: frame 7: its projection matrix has entries up to 7\.8e\+302; a projection matrix is "
                r"defined up to scale"),
    (16, 1e308, r"line 2: frame 7: its projection matrix overflows"),
])
def test_absurd_numbers_are_refused_with_one_line_and_no_numpy_warning(tmp_path, index, value, message):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidInputError, match=message):
            read_cameras(write(tmp_path, POSE_COLUMNS, [bad_pose(index, value)]))


def test_a_k_file_given_as_cameras_names_both_layouts(tmp_path):
    f = tmp_path / "K.csv"
    f.write_text("frame,fx,fy,cx,cy,skew\n0,800,800,320,240,0\n")
    with pytest.raises(InvalidInputError) as info:
        read_cameras(f)
    message = str(info.value)
    assert ",".join(MATRIX_COLUMNS) in message and ",".join(POSE_COLUMNS) in message
    assert message.endswith("; got frame,fx,fy,cx,cy,skew") and "missing column(s) r11, r12" in message


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")
@pytest.mark.parametrize("make, message", [
    (lambda d: d, "is a folder, not a text CSV"),
    (lambda d: os.mkfifo(d / "fifo.csv") or d / "fifo.csv", "is a FIFO, not a text CSV"),
    (lambda d: Path("/dev/zero"), "is a device, not a text CSV"),
])
def test_what_is_not_a_regular_file_is_refused_unread(tmp_path, make, message):
    path = make(tmp_path)
    if path == tmp_path:  # a folder with no model is also no COLMAP model: the CSV reader is not asked
        with pytest.raises(InvalidInputError, match="no COLMAP model"):
            read_cameras(path)
        from kalmansfm.io._csv import read_rows
        with pytest.raises(InvalidInputError, match=message):
            read_rows(path, "x")
        return
    with pytest.raises(InvalidInputError, match=f"{path.name}: {message}"):
        read_cameras(path)  # neither blocks (FIFO) nor runs out of memory (/dev/zero)


def test_a_file_larger_than_any_cameras_file_is_refused_before_it_is_read(tmp_path):
    f = tmp_path / "huge.csv"
    with open(f, "wb") as handle:
        handle.truncate(MAX_CAMERAS_BYTES + 1)  # sparse: no disk used
    with pytest.raises(InvalidInputError, match=rf"huge\.csv: is larger than the {MAX_CAMERAS_BYTES} bytes"):
        read_cameras(f)


# --- COLMAP models as known cameras (issue 28) ------------------------------------------------------------------


def colmap_folder(tmp_path, names, binary=False):
    scene = make_scene(frames=len(names), points=30, seed=2)
    model = build_colmap_model(scene.K, scene.R, scene.t, scene.size, names, scene.frames, scene.points_of, scene.xy,
                               scene.X)
    write_colmap_model(model, tmp_path / "sparse" / "0", binary=binary)
    return scene


@pytest.mark.parametrize("binary", [False, True])
def test_a_colmap_model_gives_known_cameras_by_natural_order_of_names(tmp_path, binary):
    names = ["img10.png", "img9.png", "img100.png", "img1.png"]  # natural order: 1, 9, 10, 100
    scene = colmap_folder(tmp_path, names, binary)
    known = read_known_cameras(tmp_path)
    assert known.matched_by == "order" and known.source_format == ("COLMAP binary" if binary else "COLMAP text")
    assert dict(zip(known.image_names, known.cameras.frames.tolist())) == {"img1.png": 0, "img9.png": 1,
                                                                            "img10.png": 2, "img100.png": 3}
    truth = CameraSet.from_pose(scene.K, scene.R, scene.t)
    by_frame = known.cameras.view_of([2, 1, 3, 0])  # images 0..3 in the order written
    np.testing.assert_allclose(known.cameras.matrices[by_frame], truth.matrices, rtol=1e-12, atol=1e-9)


def test_a_colmap_model_gives_known_cameras_by_frame_name(tmp_path):
    colmap_folder(tmp_path, ["images/b.png", "images/a.png", "c.png"])
    known = read_known_cameras(tmp_path / "sparse" / "0" / "cameras.txt", frame_names=["a.png", "b.png", "c.png"])
    assert known.matched_by == "name" and known.cameras.frames.tolist() == [1, 0, 2]
    cams = read_cameras(tmp_path, frame_names={5: "c.png", 7: "a.png", 9: "images/b.png"})
    assert cams.frames.tolist() == [9, 7, 5]
    with pytest.raises(InvalidInputError, match=r"images\.txt: image 'c\.png' matches no frame name \(frames: a\.png, "
                                                r"b\.png\)"):
        read_cameras(tmp_path, frame_names=["a.png", "b.png"])
    colmap_folder(tmp_path / "two", ["images/b.png", "other/b.png", "a.png"])
    with pytest.raises(InvalidInputError, match=r"images 'images/b\.png' and 'other/b\.png' both match frame 1"):
        read_cameras(tmp_path / "two", frame_names=["a.png", "b.png"])


def test_a_colmap_model_with_a_distorting_camera_is_refused_naming_the_model(tmp_path):
    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "cameras.txt").write_text("1 SIMPLE_RADIAL 640 480 500 320 240 0.01\n")
    (folder / "images.txt").write_text("1 1 0 0 0 0 0 4 1 a.png\n\n")
    with pytest.raises(InvalidInputError, match=r"cameras\.txt: line 1: camera model SIMPLE_RADIAL has lens distortion"):
        read_cameras(folder)
