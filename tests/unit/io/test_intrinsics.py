"""K.csv: one row for all frames or one per frame; errors name file and line."""

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
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
    ("frame,fx,fy,cx\n0,1,1,1\n", r"line 1: missing column\(s\) cy, skew"),
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
