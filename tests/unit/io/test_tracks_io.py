"""tracks.csv / tracks.npz round trips and the points CSV reader."""

import numpy as np
import pytest

from kalmansfm.errors import InvalidInputError
from kalmansfm.io.tracks import (
    read_points_csv,
    read_tracks_csv,
    read_tracks_npz,
    write_tracks_csv,
    write_tracks_npz,
)
from kalmansfm.tracking.tracks import Tracks


def sample_tracks():
    rng = np.random.default_rng(0)
    t = Tracks.empty(4, 3, image_size=(64, 48))
    t.track_ids[:] = [5, 7, 9]
    t.status[:] = [[1, 1, 0], [1, 2, 0], [2, 3, 1], [1, 0, 1]]
    alive = (t.status == 1) | (t.status == 2)
    t.states[alive] = rng.uniform(0, 40, (alive.sum(), 4))
    t.positions[alive] = t.states[alive][:, :2]
    A = rng.normal(size=(alive.sum(), 4, 4))
    t.covariances[alive] = A @ np.swapaxes(A, 1, 2) + np.eye(4)
    return t


def test_npz_round_trip_is_exact(tmp_path):
    t = sample_tracks()
    back = read_tracks_npz(write_tracks_npz(t, tmp_path / "tracks.npz"))
    for name in ("positions", "states", "covariances", "status", "track_ids"):
        np.testing.assert_array_equal(getattr(back, name), getattr(t, name))
    assert back.image_size == (64, 48)


def test_csv_round_trip(tmp_path):
    t = sample_tracks()
    path = write_tracks_csv(t, tmp_path / "tracks.csv")
    lines = path.read_text().splitlines()
    assert lines[0] == "frame,track_id,x,y,vx,vy,std_x,std_y,status"
    assert len(lines) == 1 + int((t.status != 0).sum())
    assert lines[-1].endswith(",measured") and "lost" in path.read_text()
    back = read_tracks_csv(path)
    np.testing.assert_array_equal(back.status, t.status)
    np.testing.assert_array_equal(back.track_ids, t.track_ids)
    np.testing.assert_allclose(back.states, t.states, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(back.position_std, t.position_std, atol=1e-6, equal_nan=True)


def test_points_csv(tmp_path):
    p = tmp_path / "p.csv"
    p.write_text("y,x\n1,2\n3,4\n")
    points, ids = read_points_csv(p)
    np.testing.assert_array_equal(points, [[2, 1], [4, 3]])
    assert ids is None
    p.write_text("x,y\n1,2\n3,oops\n")
    with pytest.raises(InvalidInputError, match=r"p\.csv: line 3: x and y must be numbers"):
        read_points_csv(p)
    p.write_text("u,v\n1,2\n")
    with pytest.raises(InvalidInputError, match=r"p\.csv: line 1: missing column\(s\) x, y; expected x,y; got u,v$"):
        read_points_csv(p)
    p.write_text("x,y,track_id\n1,2,4\n3,4,4\n")
    with pytest.raises(InvalidInputError, match=r"p\.csv: line 3: track_id 4 repeats line 2$"):
        read_points_csv(p)


def test_tracks_without_a_single_track_round_trip(tmp_path):
    """A clip where no corner was found: zero tracks, still a valid tracks.npz."""
    from kalmansfm.io.tracks import read_tracks_npz, write_tracks_npz
    from kalmansfm.tracking import Tracks

    empty = Tracks.empty(3, 0)
    back = read_tracks_npz(write_tracks_npz(empty, tmp_path / "t.npz"))
    assert back.positions.shape == (3, 0, 2) and back.covariances.shape == (3, 0, 4, 4)
