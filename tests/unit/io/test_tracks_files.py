import numpy as np
import pytest

from kalmansfm import InvalidInputError
from kalmansfm.io.structure import motion_csv, structure_csv, structure_ply
from kalmansfm.io.tracks import read_tracks

TRACKER_HEADER = "frame,track_id,x,y,vx,vy,std_x,std_y,status\n"


def test_tracker_csv_uses_only_measured_rows(tmp_path):
    f = tmp_path / "tracks.csv"
    f.write_text(
        TRACKER_HEADER
        + "0,3,10.0,20.0,0,0,2.0,2.0,measured\n"
        + "0,8,30.0,40.0,0,0,1.0,0.5,measured\n"
        + "1,3,11.0,21.0,1,1,3.0,3.0,predicted\n"
        + "1,8,nan,nan,0,0,nan,nan,lost\n"
        + "2,3,12.0,22.0,1,1,2.5,2.5,measured\n"
    )
    t = read_tracks(f)
    assert t.track_ids.tolist() == [3, 8] and t.frames.tolist() == [0, 1, 2]
    np.testing.assert_array_equal(t.observations()[0], [[10, 20], [30, 40]])
    assert np.isnan(t.observations()[1]).all()
    np.testing.assert_array_equal(t.observations()[2, 0], [12, 22])
    np.testing.assert_array_equal(t.position_std[0, 1], [1.0, 0.5])
    np.testing.assert_array_equal(t.observation_weights()[0, 1], [1.0, 4.0])


def test_plain_csv_with_comments(tmp_path):
    f = tmp_path / "plain.csv"
    f.write_text("# made by hand\nframe,track_id,x,y\n1,1,5,6\n2,1,7,8\n")
    t = read_tracks(f)
    assert t.position_std is None and t.observation_weights() is None
    np.testing.assert_array_equal(t.observations()[:, 0], [[5, 6], [7, 8]])


def make_npz(path, **overrides):
    rng = np.random.default_rng(0)
    arrays = {
        "positions": rng.uniform(0, 100, size=(4, 3, 2)),
        "covariances": np.broadcast_to(np.diag([4.0, 9.0, 1.0, 1.0]), (4, 3, 4, 4)).copy(),
        "status": np.array([[1, 1, 0], [1, 2, 1], [1, 3, 1], [1, 1, 1]]),
        "track_ids": np.array([5, 2, 9]),
    }
    arrays.update(overrides)
    arrays = {k: v for k, v in arrays.items() if v is not None}
    np.savez(path, **arrays)
    return arrays


def test_npz_uses_status_1_and_sorts_track_ids(tmp_path):
    f = tmp_path / "tracks.npz"
    arrays = make_npz(f)
    t = read_tracks(f)
    assert t.track_ids.tolist() == [2, 5, 9]
    np.testing.assert_array_equal(t.observations()[:, 1], arrays["positions"][:, 0])  # track 5
    assert np.isnan(t.observations()[1, 0]).all() and np.isnan(t.observations()[0, 2]).all()
    np.testing.assert_allclose(t.position_std[0, 1], [2.0, 3.0])


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("frame,track_id,x\n0,1,2\n", "line 1: missing column\\(s\\) y; expected frame,track_id,x,y; got frame,track_id,x"),
        ("frame,track_id,x,y\n0,1,2,3\n0,2,abc,3\n", "line 3: x must be a number; got 'abc'"),
        ("frame,track_id,x,y\n0,1,2,3\n0,2,nan,3\n", "line 3: x must be finite"),
        ("frame,track_id,x,y\n0,1,2,3\n0,2,inf,3\n", "line 3: x must be finite"),
        ("frame,track_id,x,y\n0,1,2,3\n0.5,2,1,3\n", "line 3: frame must be an integer"),
        ("frame,track_id,x,y\n0,1,2,3\n0,1,2,3\n", "bad.csv: lines 2 and 3: frame 0, track_id 1 given twice"),
        ("frame,track_id,x,y\n0,1,2\n", "line 2: 3 fields, the header has 4"),
        (TRACKER_HEADER + "0,1,2,3,0,0,1,1,flying\n", "line 2: status must be"),
        (TRACKER_HEADER + "0,1,2,3,0,0,0,1,measured\n", "line 2: std_x and std_y must be > 0"),
        ("", "empty file"),
        ("frame,track_id,x,y\n", r"line 1: no rows after the header$"),
    ],
)
def test_malformed_csv(tmp_path, text, message):
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(InvalidInputError, match=message) as err:
        read_tracks(f)
    assert str(f) in str(err.value)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"status": None}, "missing array\\(s\\) status"),
        ({"positions": np.zeros((4, 3))}, "positions must be a numeric \\(frames, points, 2\\)"),
        ({"status": np.ones((4, 2), int)}, "status must be an integer \\(4, 3\\)"),
        ({"track_ids": np.array([1, 2])}, "track_ids must be an integer \\(3,\\)"),
        ({"track_ids": np.array([1, 1, 2])}, "distinct"),
        ({"status": np.full((4, 3), 7)}, "status\\[0, 0\\] = 7"),
        ({"covariances": np.zeros((4, 3, 2, 2))}, "covariances must be a real numeric array of shape"),
        ({"positions": np.full((4, 3, 2), np.nan)}, "positions\\[0, 0\\].*not finite"),
    ],
)
def test_malformed_npz(tmp_path, overrides, message):
    f = tmp_path / "bad.npz"
    make_npz(f, **overrides)
    with pytest.raises(InvalidInputError, match=message) as err:
        read_tracks(f)
    assert str(f) in str(err.value)


def test_missing_and_garbage_files(tmp_path):
    with pytest.raises(InvalidInputError, match="no such file"):
        read_tracks(tmp_path / "nope.csv")
    garbage = tmp_path / "x.npz"
    garbage.write_bytes(b"not a zip")
    with pytest.raises(InvalidInputError, match="not a readable NPZ"):
        read_tracks(garbage)


def parse_ascii_ply(text):
    """A minimal ASCII PLY reader: header → vertex count and property names, then rows."""
    lines = text.splitlines()
    assert lines[0] == "ply" and lines[1] == "format ascii 1.0"
    end = lines.index("end_header")
    count, props = None, []
    for line in lines[2:end]:
        words = line.split()
        if words[0] == "element":
            assert words[1] == "vertex"
            count = int(words[2])
        elif words[0] == "property":
            props.append((words[1], words[2]))
        else:
            assert words[0] == "comment"
    rows = [line.split() for line in lines[end + 1 :]]
    assert len(rows) == count and all(len(r) == len(props) for r in rows)
    return {name: np.array([(int if kind == "int" else float)(r[i]) for r in rows]) for i, (kind, name) in enumerate(props)}


def test_ply_parses_and_round_trips():
    points = np.array([[1.5, -2.0, 3.25], [np.nan, 0, 0], [0.1, 0.2, 0.3]])
    ply = parse_ascii_ply(structure_ply([10, 11, 12], points, comment="a\nb"))
    assert ply["track_id"].tolist() == [10, 12]
    np.testing.assert_allclose(np.stack([ply["x"], ply["y"], ply["z"]], axis=1), points[[0, 2]], rtol=1e-7)


def test_csv_writers_round_trip():
    points = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    rows = np.loadtxt(structure_csv([7, 9], points).splitlines()[1:], delimiter=",")
    np.testing.assert_array_equal(rows, [[7, 1, 2, 3], [9, 4, 5, 6]])
    motion = np.stack([np.eye(3)[:2], np.full((2, 3), np.nan)])
    text = motion_csv([0, 1], motion, np.array([[1.0, 2.0], [3.0, 4.0]]))
    assert text.splitlines()[0] == "frame,i_x,i_y,i_z,j_x,j_y,j_z,t_x,t_y"
    assert text.splitlines()[1:] == ["0,1.0,0.0,0.0,0.0,1.0,0.0,1.0,2.0"]


def test_motion_csv_numbers_read_back_as_the_same_floats_and_old_files_still_read(tmp_path):
    from kalmansfm.io.structure import read_motion_csv

    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    motion = np.stack([q[:2], (q * 1.0000001)[:2]])
    translation = rng.normal(size=(2, 2)) * 123.456789
    path = tmp_path / "motion.csv"
    path.write_text(motion_csv([0, 1], motion, translation))
    back = read_motion_csv(path)
    np.testing.assert_array_equal(np.stack([back.i_rows, back.j_rows], axis=1), motion)  # bit for bit
    np.testing.assert_array_equal(back.translations, translation)
    # a file of the earlier writer ('%.10g')
    old = tmp_path / "old_motion.csv"
    old.write_text("frame,i_x,i_y,i_z,j_x,j_y,j_z,t_x,t_y\n0,1,0,0,0,1,0,5,6\n3,0.6,0.8,0,-0.8,0.6,0,1.234567891,-2\n")
    back = read_motion_csv(old)
    assert back.frames.tolist() == [0, 3]
    np.testing.assert_array_equal(back.translations, [[5.0, 6.0], [1.234567891, -2.0]])


def test_tracks_too_large_for_dense_arrays_are_refused_naming_the_file(tmp_path, monkeypatch):
    """A long sequence of short tracks whose dense (frames x tracks) arrays and the estimators' copies
    exceed the machine's memory is refused before the dense arrays are made (CSV and npz alike):
    one line naming the file, the counts and what to do, instead of the system killing the run."""
    import kalmansfm._validation as validation
    from kalmansfm.errors import InvalidInputError
    from kalmansfm.io.tracks import read_tracks, write_tracks_npz

    csv = tmp_path / "long.csv"
    rows = "".join(f"{k},{k},{k + 1.0},2.0\n" for k in range(10))  # ten one-frame tracks on ten frames
    csv.write_text("frame,track_id,x,y\n" + rows, encoding="utf-8")
    fine = read_tracks(csv)  # 10 x 10 entries of 17 bytes, three copies: 5 100 bytes
    npz = write_tracks_npz(fine, tmp_path / "long.npz")
    monkeypatch.setattr(validation, "physical_memory", lambda: 5_000)
    for path in (csv, npz):
        with pytest.raises(InvalidInputError, match=rf"{path.name}: 10 frames x 10 tracks, held as dense .*"
                                                    r"\(10 entries fill 10\.00% of them\).* about 5 KB of memory, "
                                                    r"more than this machine's 5 KB; .*split the sequence"):
            read_tracks(path)
    monkeypatch.setattr(validation, "physical_memory", lambda: 5_200)
    assert read_tracks(npz).positions.shape == (10, 10, 2)
    monkeypatch.setattr(validation, "physical_memory", lambda: None)  # unknown: no check
    assert read_tracks(csv).positions.shape == (10, 10, 2)


def test_observations_are_read_per_observation_where_dense_arrays_would_not_fit(tmp_path, monkeypatch):
    """Issue 29: the per-observation reader needs memory for the observations, not for frames x tracks."""
    from kalmansfm import _validation as validation
    from kalmansfm.io.tracks import read_track_observations

    csv = tmp_path / "long.csv"
    rows = "".join(f"{k},{k},{k + 1.0},2.0\n{k + 1},{k},{k + 2.0},2.5\n" for k in range(10))  # two-frame tracks
    csv.write_text("frame,track_id,x,y\n" + rows, encoding="utf-8")
    dense = read_tracks(csv).observations()
    monkeypatch.setattr(validation, "physical_memory", lambda: 5_000)
    with pytest.raises(InvalidInputError, match="split the sequence"):
        read_tracks(csv)
    sparse = read_track_observations(csv)
    assert sparse.frame.size == 20 and np.array_equal(sparse.observations().dense(), dense, equal_nan=True)


def test_a_plain_observations_file_reads_the_same_through_numpy_and_its_faults_through_the_general_reader(tmp_path):
    """The fast parse of a frame,track_id,x,y file of numbers gives what the general reader gives; a file it does not
    take (comments, a bad cell, a pair twice) goes to the general reader and its one-line message."""
    from kalmansfm.io import tracks as tracks_module
    from kalmansfm.io.tracks import read_track_observations

    rng = np.random.default_rng(5)
    frame = rng.integers(0, 40, 300)
    track = rng.integers(0, 90, 300)
    keep = np.unique(frame * 1000 + track, return_index=True)[1]
    rows = "".join(f"{f},{t},{x!r},{y!r}\n" for f, t, (x, y) in zip(frame[keep], track[keep],
                                                                     rng.uniform(-5, 700, (keep.size, 2)).tolist()))
    plain = tmp_path / "plain.csv"
    plain.write_text("frame,track_id,x,y\n" + rows)
    fast = read_track_observations(plain)
    assert tracks_module._plain_observations(plain) is not None
    general = read_track_observations(_with_comment(tmp_path, rows))  # the general reader (a comment line)
    for name in ("frames", "track_ids", "frame", "track", "xy"):
        assert np.array_equal(getattr(fast, name), getattr(general, name)), name
    bad = tmp_path / "bad.csv"
    bad.write_text("frame,track_id,x,y\n0,1,2.0,3.0\n1,1,2.5,nan\n")
    with pytest.raises(InvalidInputError, match=r"bad.csv: line 3: y must be finite"):
        read_track_observations(bad)
    twice = tmp_path / "twice.csv"
    twice.write_text("frame,track_id,x,y\n0,1,2.0,3.0\n0,1,2.5,3.5\n")
    with pytest.raises(InvalidInputError, match=r"twice.csv: lines 2 and 3: frame 0, track_id 1 given twice"):
        read_track_observations(twice)


def _with_comment(folder, rows):
    path = folder / "commented.csv"
    path.write_text("frame,track_id,x,y\n# the same rows\n" + rows)
    return path
