"""Fuzzing the file readers with hypothesis: any bytes or text either read or raise InvalidInputError.

Readers: ``read_points_csv``, ``read_tracks_csv``, ``read_tracks_npz`` (io/tracks.py),
``read_tracks`` (any format), ``read_ground_truth_tracks``
and ``read_ground_truth`` (io/ground_truth.py), ``read_cameras``, ``read_intrinsics``,
``read_points_table``, ``read_motion_csv`` and the run folder's table reader (all on
``io._csv.read_rows``; tests/unit/io/test_csv_rules.py checks the rules they share).  Every other exception type is a bug.
Round trips check that what we write reads back unchanged.  The example counts are
bounded so that the whole file runs in well under 20 s in CI.
"""

from __future__ import annotations

import io
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kalmansfm.errors import InvalidInputError
from kalmansfm.io.cameras import read_cameras
from kalmansfm.io.ground_truth import read_ground_truth, read_ground_truth_tracks
from kalmansfm.io.intrinsics import read_intrinsics
from kalmansfm.io.run_folder import _read_csv_table
from kalmansfm.io.structure import read_motion_csv, read_points_table
from kalmansfm.io.tracks import (
    read_points_csv,
    read_tracks,
    read_tracks_csv,
    read_tracks_npz,
    tracks_to_csv,
    write_tracks_npz,
)
from kalmansfm.tracking.tracks import Tracks

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
WORK = Path(tempfile.mkdtemp(prefix="kalmansfm-fuzz-"))

# Tokens that make a CSV almost right: the header words of every format, numbers good and bad.
WORDS = ["frame", "track_id", "x", "y", "vx", "vy", "std_x", "std_y", "status", "visible", "X", "Y", "Z",
         "measured", "predicted", "lost", "p11", "fx", "i_x", "ok", "1", "0", "-1", "2.5", "1e308", "1e400", "nan", "inf", "-inf", "",
         " ", "abc", "#", '"', "\x00", "é", "1.0.0", "0x10", "99999999999999999999"]
SEPARATORS = [",", ",", ",", "\n", "\n", "\r\n", ";", "\t"]
csv_text = st.lists(st.one_of(st.sampled_from(WORDS), st.sampled_from(SEPARATORS)), max_size=60).map("".join)
any_text = st.one_of(csv_text, st.text(max_size=200))

TEXT_READERS = {
    "points": read_points_csv,
    "tracks_csv": read_tracks_csv,
    "tracks_any_csv": read_tracks,
    "ground_truth_tracks": read_ground_truth_tracks,
    "cameras": read_cameras,
    "intrinsics": lambda path: read_intrinsics(path, [0, 1, 2]),
    "structure": read_points_table,
    "motion": read_motion_csv,
    "run_table": _read_csv_table,
}


def _file(name: str, data: bytes) -> Path:
    path = WORK / name
    path.write_bytes(data)
    return path


def _read_or_refuse(reader, path: Path) -> object | None:
    try:
        return reader(path)
    except InvalidInputError:
        return None


@pytest.mark.parametrize("reader", list(TEXT_READERS), ids=list(TEXT_READERS))
@FUZZ
@given(data=st.one_of(any_text.map(lambda t: t.encode("utf-8")), st.binary(max_size=300)))
def test_csv_readers_read_or_refuse_any_bytes(reader, data):
    _read_or_refuse(TEXT_READERS[reader], _file(f"{reader}.csv", data))


@FUZZ
@given(tracks=csv_text, points=csv_text, motion=csv_text)
def test_ground_truth_folder_reads_or_refuses_any_text(tracks, points, motion):
    folder = WORK / "scene"
    folder.mkdir(exist_ok=True)
    header = "frame,track_id,x,y,visible\n"
    (folder / "ground_truth_tracks.csv").write_text(header + tracks, encoding="utf-8")
    (folder / "ground_truth_points.csv").write_text("track_id,X,Y,Z\n" + points, encoding="utf-8")
    (folder / "ground_truth_motion.csv").write_text(motion, encoding="utf-8")
    _read_or_refuse(read_ground_truth, folder)


# --- NPZ: arrays of arbitrary shapes and dtypes under the expected names ------------------------

dtypes = st.sampled_from([np.float64, np.float32, np.int64, np.int8, np.bool_, np.complex128, "U3"])
shapes = st.lists(st.integers(0, 4), min_size=0, max_size=4).map(tuple)


@st.composite
def npz_bytes(draw) -> bytes:
    names = draw(st.sets(st.sampled_from(["positions", "states", "covariances", "status", "track_ids", "frames",
                                          "scores", "image_size", "other"]), max_size=9))
    arrays = {}
    for name in names:
        shape, dtype = draw(shapes), draw(dtypes)
        values = draw(st.sampled_from([0, 1, 3, -1, np.nan, np.inf]))
        arrays[name] = np.full(shape, values if np.dtype(dtype).kind in "fc" else (values if np.isfinite(values) else 7)).astype(dtype)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    data = buffer.getvalue()
    if draw(st.booleans()):
        cut = draw(st.integers(0, len(data)))
        data = data[:cut]  # a truncated archive
    return data


@FUZZ
@given(data=st.one_of(npz_bytes(), st.binary(max_size=200)))
def test_npz_readers_read_or_refuse_any_archive(data):
    path = _file("fuzz.npz", data)
    _read_or_refuse(read_tracks, path)
    _read_or_refuse(read_tracks_npz, path)


@FUZZ
@given(npz=npz_bytes())
def test_npz_with_right_names_and_consistent_shapes_still_validates_values(npz):
    """A well-formed tracks.npz with random values: the observations are the status-1 entries, finite."""
    path = _file("consistent.npz", npz)
    result = _read_or_refuse(read_tracks, path)
    if result is not None:
        observations = result.observations()
        assert observations.ndim == 3 and observations.shape[2] == 2
        observed = np.isfinite(observations).all(axis=2)
        assert np.array_equal(observed, np.isfinite(observations).any(axis=2))
        assert np.array_equal(observed, result.status == 1)


# --- round trips --------------------------------------------------------------------------------

@st.composite
def random_tracks(draw) -> Tracks:
    frames, count = draw(st.integers(1, 6)), draw(st.integers(1, 5))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    status = rng.integers(0, 4, (frames, count)).astype(np.int8)
    tracks = Tracks.empty(frames, count)
    tracks.track_ids[:] = rng.choice(1000, count, replace=False)
    states = np.round(rng.uniform(-500, 500, (frames, count, 4)), 3)
    std = np.round(rng.uniform(0.1, 5, (frames, count, 2)), 3)
    alive = (status == 1) | (status == 2)
    tracks.status[:] = status
    tracks.states[alive] = states[alive]
    tracks.positions[alive] = states[alive][:, :2]
    tracks.covariances[alive] = 0.0
    tracks.covariances[alive, 0, 0] = std[alive][:, 0] ** 2
    tracks.covariances[alive, 1, 1] = std[alive][:, 1] ** 2
    return tracks


@settings(max_examples=40, deadline=None)
@given(tracks=random_tracks())
def test_tracks_csv_round_trip(tracks):
    path = _file("round.csv", tracks_to_csv(tracks).encode())
    if not (tracks.status != 0).any():
        with pytest.raises(InvalidInputError, match=r": line 1: no rows after the header$"):
            read_tracks_csv(path)
        return
    back = read_tracks_csv(path)
    present = np.isin(tracks.track_ids, back.track_ids)
    rows = (tracks.status != 0).any(axis=1)  # frames with a row in the CSV
    np.testing.assert_array_equal(back.frames, np.flatnonzero(rows))
    order = np.argsort(tracks.track_ids[present])
    np.testing.assert_array_equal(back.track_ids, tracks.track_ids[present][order])
    np.testing.assert_array_equal(back.status, tracks.status[rows][:, present][:, order])
    np.testing.assert_allclose(back.states, tracks.states[rows][:, present][:, order], atol=1e-6, equal_nan=True)
    variances = np.diagonal(tracks.covariances[rows][:, present][:, order][..., :2, :2], axis1=-2, axis2=-1)
    np.testing.assert_allclose(np.diagonal(back.covariances[..., :2, :2], axis1=-2, axis2=-1), variances,
                               rtol=1e-5, equal_nan=True)


@settings(max_examples=40, deadline=None)
@given(tracks=random_tracks())
def test_tracks_npz_round_trip_and_factorization_view(tracks):
    path = WORK / "round.npz"
    write_tracks_npz(tracks, path)
    back = read_tracks_npz(path)
    for name in ("positions", "states", "covariances", "status", "track_ids"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tracks, name))
    table = _read_or_refuse(read_tracks, path)
    if table is not None:  # only the measured entries are observations; columns sorted by id
        order = np.argsort(tracks.track_ids)
        measured = (tracks.status == 1)[:, order]
        np.testing.assert_array_equal(np.isfinite(table.observations()[..., 0]), measured)
        np.testing.assert_array_equal(table.observations()[measured], tracks.positions[:, order][measured])


@settings(max_examples=40, deadline=None)
@given(
    points=st.lists(st.tuples(st.floats(-1e6, 1e6), st.floats(-1e6, 1e6)), min_size=1, max_size=8),
    with_ids=st.booleans(),
)
def test_points_csv_round_trip_is_exact(points, with_ids):
    xy = np.array(points, dtype=np.float64)
    ids = np.arange(len(points)) * 3 + 1
    header = "x,y,track_id" if with_ids else "x,y"
    rows = [f"{x!r},{y!r}" + (f",{i}" if with_ids else "") for (x, y), i in zip(xy.tolist(), ids)]
    back, back_ids = read_points_csv(_file("points.csv", ("\n".join([header, *rows]) + "\n").encode()))
    np.testing.assert_array_equal(back, xy)
    assert (back_ids is None) == (not with_ids)
    if with_ids:
        np.testing.assert_array_equal(back_ids, ids)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    frames=st.integers(1, 5),
    count=st.integers(1, 5),
    holes=st.floats(0, 0.7),
)
def test_track_table_csv_round_trip(seed, frames, count, holes):
    rng = np.random.default_rng(seed)
    positions = rng.uniform(0, 640, (frames, count, 2))
    positions[rng.random((frames, count)) < holes] = np.nan
    ids = np.sort(rng.choice(100, count, replace=False))
    rows = [f"{f},{ids[p]},{float(positions[f, p, 0])!r},{float(positions[f, p, 1])!r}"
            for f in range(frames) for p in range(count) if np.isfinite(positions[f, p, 0])]
    path = _file("table.csv", ("frame,track_id,x,y\n" + "\n".join(rows) + "\n").encode())
    if not rows:
        with pytest.raises(InvalidInputError, match=r": line 1: no rows after the header$"):
            read_tracks(path)
        return
    table = read_tracks(path)
    kept_frames = np.isfinite(positions[..., 0]).any(axis=1)
    kept_ids = np.isfinite(positions[..., 0]).any(axis=0)
    np.testing.assert_array_equal(table.frames, np.flatnonzero(kept_frames))
    np.testing.assert_array_equal(table.track_ids, ids[kept_ids])
    np.testing.assert_array_equal(table.positions, positions[kept_frames][:, kept_ids])
