"""One structure.csv for every command: the writer, the reader, and the plain layout of ground truth."""

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.io.ground_truth import POINTS_FILE, GroundTruth, ground_truth_files
from kalmansfm.io.structure import STRUCTURE_COLUMNS, read_points_table, structure_csv, structure_ply
from kalmansfm.structure import PointStatus, rms_std


def random_covariances(rng, n):
    a = rng.normal(size=(n, 3, 3))
    return a @ a.transpose(0, 2, 1) + 0.1 * np.eye(3)


def test_every_status_round_trips_exactly_and_rows_without_a_point_stay_in_the_file(tmp_path):
    rng = np.random.default_rng(0)
    n = len(PointStatus)
    points = rng.normal(size=(n, 3)) * 1e3
    covariances = random_covariances(rng, n)
    status = np.array([s.value for s in PointStatus])
    points[1] = covariances[1] = np.nan  # too_few_views: no point
    rms = rng.uniform(0.1, 2.0, n)
    text = structure_csv(np.arange(10, 10 + n), points, covariances=covariances, views=np.arange(n) + 2,
                         status=status, reprojection_rms=rms)
    lines = text.splitlines()
    assert lines[0] == ",".join(STRUCTURE_COLUMNS) and len(lines) == n + 1
    assert [line.split(",")[-1] for line in lines[1:]] == [s.label for s in PointStatus]
    assert lines[2].split(",")[1:10] == [""] * 9  # no value: an empty cell, not "nan"
    (tmp_path / "structure.csv").write_text(text)
    table = read_points_table(tmp_path / "structure.csv")
    keep = np.ones(n, bool)
    keep[1] = False
    assert table.track_ids.tolist() == (10 + np.flatnonzero(keep)).tolist()
    np.testing.assert_array_equal(table.points, points[keep])
    np.testing.assert_array_equal(table.covariances, covariances[keep])  # symmetric, bit for bit
    np.testing.assert_array_equal(table.reprojection_rms, rms[keep])
    assert table.status.tolist() == status[keep].tolist() and table.views.tolist() == (np.arange(n) + 2)[keep].tolist()
    assert table.reliable.tolist() == (status[keep] == PointStatus.OK).tolist()


def test_without_reprojection_rms_its_cells_are_empty_and_read_as_nan(tmp_path):
    text = structure_csv([1, 2, 3, 4], np.eye(4, 3), covariances=np.stack([np.eye(3)] * 4), views=[3] * 4,
                         status=[0] * 4)
    assert {line.split(",")[11] for line in text.splitlines()[1:]} == {""}
    (tmp_path / "s.csv").write_text(text)
    assert np.isnan(read_points_table(tmp_path / "s.csv").reprojection_rms).all()


def test_the_plain_layout_is_ground_truth_and_reads_without_uncertainty(tmp_path):
    truth = GroundTruth(track_ids=np.array([4, 7]), positions=np.zeros((1, 2, 2)), visible=np.ones((1, 2), bool),
                        points_3d=np.array([[0.1, 0.2, 0.3], [1.0, 2.0, 3.0]]))
    text = ground_truth_files(truth)[POINTS_FILE]
    assert text == structure_csv([4, 7], truth.points_3d) == "track_id,X,Y,Z\n4,0.1,0.2,0.3\n7,1.0,2.0,3.0\n"
    (tmp_path / "points.csv").write_text(text)
    table = read_points_table(tmp_path / "points.csv")
    assert table.covariances is None and table.status is None and table.reliable.all()
    np.testing.assert_array_equal(table.points, truth.points_3d)


@pytest.mark.parametrize("cell, message", [
    ("fused", "column 'status' must be one of ok, too_few_views, degenerate, behind_camera, unreliable; got 'fused'"),
    ("OK", "got 'OK'"),
])
def test_a_status_word_that_is_not_a_label_is_named(tmp_path, cell, message):
    line = structure_csv([1], [[0.0, 0.0, 1.0]], covariances=np.eye(3)[None], views=[2], status=[0])
    (tmp_path / "s.csv").write_text(line.replace(",ok\n", f",{cell}\n"))
    with pytest.raises(InvalidInputError, match=message):
        read_points_table(tmp_path / "s.csv")


def test_uncertainty_only_with_its_companions():
    with pytest.raises(InvalidInputError, match="together"):
        structure_csv([1], [[0.0, 0.0, 1.0]], covariances=np.eye(3)[None])
    with pytest.raises(InvalidInputError, match=r"reprojection_rms \(1,\)"):
        structure_csv([1], [[0.0, 0.0, 1.0]], covariances=np.eye(3)[None], views=[2], status=[0],
                      reprojection_rms=[1.0, 2.0])


def test_the_ply_carries_the_points_with_coordinates_and_their_properties():
    cov = np.stack([np.diag([1.0, 4.0, 4.0]), np.full((3, 3), np.nan)])
    ply = structure_ply([5, 6], [[1.0, 2.0, 3.0], [np.nan] * 3], properties={"uncertainty": rms_std(cov)})
    assert "element vertex 1" in ply and ply.splitlines()[-1] == "1 2 3 5 1.73205081"
