"""The Middlebury camera file (``*_par.txt``): K, R, t per image, in natural order of the names."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.io.middlebury import read_middlebury_cameras

TEMPLE = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "middlebury_templering" / "templeR_par.txt"
ROW = "1000 0 320 0 1000 240 0 0 1 1 0 0 0 1 0 0 0 1 0 0 5"


def test_the_temple_ring_gives_47_cameras_on_its_ring():
    cams = read_middlebury_cameras(TEMPLE)
    assert len(cams.names) == 47 and cams.names[0] == "templeR0001.png" and cams.names[-1] == "templeR0047.png"
    np.testing.assert_allclose(cams.intrinsics[0], [[1520.4, 0, 302.32], [0, 1525.9, 246.87], [0, 0, 1]])
    # rotations orthonormal to the file's rounding; the centres on a ring around the object
    np.testing.assert_allclose(cams.rotations @ np.swapaxes(cams.rotations, 1, 2), np.eye(3)[None].repeat(47, 0),
                               atol=1e-6)
    radius = np.linalg.norm(cams.centres - cams.centres.mean(axis=0), axis=1)
    assert radius.std() < 0.05 * radius.mean()


@pytest.mark.parametrize("text, message", [
    ("", "empty; expected the number of images"),
    ("two\nv1.png " + ROW + "\n", "line 1: expected the number of images; got 'two'"),
    ("2\nv1.png " + ROW + "\n", "line 1: says 2 images, the file has 1"),
    ("1\nv1.png 1 2 3\n", "line 2: expected an image name and 21 numbers"),
    ("1\nv1.png " + ROW.replace("320", "x") + "\n", "line 2: K, R and t must be numbers"),
    ("1\nv1.png " + ROW.replace("320", "inf") + "\n", "line 2: K, R and t must be finite"),
    ("2\nv1.png " + ROW + "\nv1.png " + ROW + "\n", "lines 2 and 3: image v1.png is given twice"),
])
def test_a_broken_file_is_refused_naming_its_line(tmp_path, text, message):
    path = tmp_path / "ring_par.txt"
    path.write_text(text)
    with pytest.raises(InvalidInputError, match=message):
        read_middlebury_cameras(path)
