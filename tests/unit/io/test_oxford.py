"""The Oxford VGG reader: both layouts on the real folders, and errors that name the file."""

from pathlib import Path

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.io.oxford import read_oxford
from kalmansfm.io.tracks import observations_csv, read_tracks
from kalmansfm.structure.geometry.pinhole import project_points

DATA = Path(__file__).resolve().parents[4] / "shared" / "data"


@pytest.mark.parametrize("name, frames, points", [("oxford_model_house", range(10), 672),
                                                  ("oxford_merton1", range(1, 4), 717)])
def test_the_real_sets_read_with_their_cameras_matching_their_corners(name, frames, points):
    data = read_oxford(DATA / name)
    assert data.observations.shape == (len(frames), points, 2) and data.points.shape == (points, 3)
    assert data.cameras.frames.tolist() == list(frames)  # the N of the file names
    # the READMEs: the cameras project the 3-D points onto the matched corners, median error well below 1 px
    error = np.linalg.norm(project_points(data.cameras, data.points).pixels - data.observations, axis=2)
    assert np.nanmedian(error) < 0.5


def test_the_observations_go_to_a_tracks_file_and_back(tmp_path):
    data = read_oxford(DATA / "oxford_merton1")
    (tmp_path / "tracks.csv").write_text(observations_csv(data.observations, data.cameras.frames))
    tracks = read_tracks(tmp_path / "tracks.csv")
    seen = np.isfinite(data.observations).all(axis=2).any(axis=0)
    assert tracks.track_ids.tolist() == np.flatnonzero(seen).tolist()
    np.testing.assert_array_equal(tracks.observations(), data.observations[:, seen])


def write_merton_like(root, table="0 1\n1 *\n"):
    (root / "2D").mkdir(parents=True)
    (root / "3D").mkdir()
    for n in (0, 1):
        (root / "2D" / f"00{n}.P").write_text("1 0 0 0\n0 1 0 0\n0 0 1 5\n")
        (root / "2D" / f"00{n}.corners").write_text("10 20\n30 40\n")
    (root / "2D" / "nview-corners").write_text(table)
    (root / "3D" / "p3d").write_text("0 0 0\n1 1 1\n")


@pytest.mark.parametrize("table, message", [
    ("0 5\n1 *\n", r"nview-corners: column 2 refers to corner 5, but 001.corners lists 2"),
    ("0 1\n", r"nview-corners: 1 rows, but .*p3d holds 2 points"),
    ("0 1 1\n1 * 0\n", r"nview-corners: expected 2 finite numbers per line"),
])
def test_a_broken_folder_is_named(tmp_path, table, message):
    write_merton_like(tmp_path / "set", table)
    with pytest.raises(InvalidInputError, match=message):
        read_oxford(tmp_path / "set")


def test_a_folder_of_neither_layout(tmp_path):
    with pytest.raises(InvalidInputError, match="not an Oxford VGG data set folder"):
        read_oxford(tmp_path)
