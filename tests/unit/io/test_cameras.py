"""The cameras CSV: both layouts, exact round trip, and one clear error per bad file."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kalmansfm.errors import InvalidInputError, NotEnoughDataError
from kalmansfm.io.cameras import (
    MATRIX_COLUMNS,
    POSE_COLUMNS,
    POSE_STD_COLUMNS,
    cameras_csv,
    match_cameras,
    pose_cameras_csv,
    read_cameras,
)
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
        (MATRIX_COLUMNS[:-1], [[0] + [1.0] * 11], r"lacks column\(s\) p34 of the projection-matrix layout"),
        (POSE_COLUMNS[:-2], [POSE_ROW[:-2]], r"lacks column\(s\) t2, t3 of the intrinsics \+ pose layout"),
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
