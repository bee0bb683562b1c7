import numpy as np
import pytest

from kalmansfm import InvalidInputError
from kalmansfm.io import read_ground_truth, read_ground_truth_tracks


def test_sparse_tracks_file_becomes_dense_arrays(tmp_path):
    path = tmp_path / "t.csv"
    path.write_text("frame,track_id,x,y,visible\n0,4,1.5,2.5,1\n2,7,3.0,4.0,0\n")
    truth = read_ground_truth_tracks(path)
    np.testing.assert_array_equal(truth.track_ids, [4, 7])
    assert truth.positions.shape == (3, 2, 2)
    np.testing.assert_array_equal(truth.positions[0, 0], [1.5, 2.5])
    assert np.isnan(truth.positions[1]).all()
    np.testing.assert_array_equal(truth.visible, [[True, False], [False, False], [False, False]])


@pytest.mark.parametrize(
    "text, message",
    [
        ("frame,track_id,x,y\n0,0,1,2\n", r"line 1: missing column\(s\) visible"),
        ("frame,track_id,x,y,visible\n0,0,one,2,1\n", "line 2: expected numbers, got 0,0,one,2,1"),
        ("frame,track_id,x,y,visible\n0,0,1,2\n", "line 2: 4 fields, the header has 5"),
        ("frame,track_id,x,y,visible\n0.5,0,1,2,1\n", "line 2: column frame must hold non-negative integers; got 0.5"),
        ("", "empty"),
    ],
)
def test_malformed_files_name_the_file_and_row(tmp_path, text, message):
    (tmp_path / "ground_truth_tracks.csv").write_text(text)
    with pytest.raises(InvalidInputError, match=message):
        read_ground_truth(tmp_path)


def test_missing_folder_is_reported(tmp_path):
    with pytest.raises(InvalidInputError, match="no such file"):
        read_ground_truth(tmp_path / "nothing")
