"""One set of CSV rules for every reader of ``io`` (``io/_csv.read_rows``, docs/formats.md).

Each reader gets the file its writer writes (or, for inputs from other tools, a hand-written one)
and must read it to the same result with a byte-order mark, ``#`` comment lines, blank lines,
CRLF line ends and spaces around the header names; a ragged row, an empty file, a missing file,
a file that is not UTF-8 and (where the format needs rows) a header-only file are each refused
with an :class:`~kalmansfm.InvalidInputError` naming the file (and the line where there is one).
Each reader's own checks (a non-number cell, a missing column) name ``FILE: line N`` the same way,
N counting the comment and blank lines before it.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from kalmansfm.errors import InvalidInputError
from kalmansfm.io._csv import read_rows
from kalmansfm.io.cameras import cameras_csv, pose_cameras_csv, read_cameras
from kalmansfm.io.ground_truth import (
    MOTION_FILE,
    POINTS_FILE,
    TRACKS_FILE,
    GroundTruth,
    ground_truth_files,
    read_ground_truth,
    read_ground_truth_tracks,
)
from kalmansfm.io.intrinsics import intrinsics_csv, read_intrinsics
from kalmansfm.io.run_folder import _read_csv_table
from kalmansfm.io.structure import motion_csv, read_motion_csv, read_points_table, structure_csv
from kalmansfm.io.tracks import observations_csv, read_points_csv, read_tracks, tracks_to_csv
from kalmansfm.structure.geometry.pinhole import CameraSet
from kalmansfm.tracking.tracks import Tracks

RNG = np.random.default_rng(7)


def _tracks() -> Tracks:
    t = Tracks.empty(3, 2)
    t.track_ids[:] = [4, 9]
    t.status[:] = [[1, 1], [2, 1], [3, 1]]
    for f in range(3):
        for p in range(2):
            if t.status[f, p] != 3:
                t.states[f, p] = [10.5 * f + p, 20.25 + p, 0.5, -0.25]
                t.positions[f, p] = t.states[f, p, :2]
                t.covariances[f, p] = np.eye(4) * 2.25
    return t


def _truth() -> GroundTruth:
    F, P = 3, 2
    rot = Rotation.from_euler("xyz", RNG.normal(size=(F, 3)) * 0.1).as_matrix()
    return GroundTruth(
        track_ids=np.array([0, 1]), positions=RNG.uniform(0, 100, (F, P, 2)), visible=np.array([[1, 1], [1, 0], [0, 1]], bool),
        points_3d=RNG.normal(size=(P, 3)), rotation_rows=rot[:, :2], translations=RNG.normal(size=(F, 2)),
        scales=np.full(F, 1.5),
    )


_R = Rotation.from_euler("xyz", [0.1, -0.2, 0.3]).as_matrix()
_K = np.array([[[800.0, 0.5, 320.0], [0.0, 780.0, 240.0], [0.0, 0.0, 1.0]]] * 2)
_TRUTH = _truth()
_TRUTH_FILES = ground_truth_files(_TRUTH)


def _in_truth_folder(name: str) -> Callable[[Path], object]:
    """Read ``name`` (ground-truth points or motion) through read_ground_truth, the other files clean."""
    def read(path: Path) -> object:
        assert path.name == name
        (path.parent / TRACKS_FILE).write_text(_TRUTH_FILES[TRACKS_FILE], encoding="utf-8")
        return read_ground_truth(path.parent)
    return read


@dataclasses.dataclass(frozen=True)
class Case:
    text: str  # the valid file
    read: Callable[[Path], object]
    header_only: str | None = re.escape(": line 2: no rows after the header")  # its error; None: it reads
    optional: bool = False  # the file may be absent (its reader then gives no error)


CASES = {
    "tracks.csv": Case(tracks_to_csv(_tracks()), read_tracks),
    "tracks.csv (observations)": Case(observations_csv(np.array([[[1.5, 2.0], [3.0, 4.0]], [[5.0, 6.0], [np.nan] * 2]]),
                                                       [0, 1], [3, 8]), read_tracks),
    "points.csv": Case("track_id,x,y\n7,118.5,78\n8,117,89.25\n", read_points_csv),
    "cameras.csv (projection matrices)": Case(
        cameras_csv(CameraSet.from_matrices(np.stack([np.eye(3, 4), np.eye(3, 4) + 0.1]), frames=[2, 5])), read_cameras),
    "cameras.csv (intrinsics + pose)": Case(
        pose_cameras_csv([0, 3], _K, np.stack([_R, _R.T]), [[0.1, 0.2, 4.0], [0.0, -0.1, 5.0]],
                         rotation_std_deg=[0.1, np.nan], centre_std=[0.02, 0.03]), read_cameras),
    "K.csv": Case(intrinsics_csv([0, 1], _K), lambda p: read_intrinsics(p, [1, 0])),
    "structure.csv": Case(structure_csv([3, 5, 8], [[0.0, 1.0, 2.5], [4.0, 5.0, 6.0], [np.nan] * 3],
                                        covariances=np.stack([np.eye(3)] * 3), views=[7, 3, 1], status=[0, 4, 1],
                                        reprojection_rms=[0.25, 0.5, np.nan]), read_points_table, header_only=None),
    "structure.csv (plain)": Case(structure_csv([3, 5], [[0.0, 1.0, 2.5], [4.0, 5.0, 6.0]]), read_points_table,
                                  header_only=None),
    "motion.csv": Case(motion_csv([0, 1], np.stack([np.eye(3)[:2], _R[:2]]), np.array([[5.0, 6.0], [7.0, 8.0]])),
                       read_motion_csv, header_only=None),
    "ground_truth_tracks.csv": Case(_TRUTH_FILES[TRACKS_FILE], read_ground_truth_tracks),
    "ground_truth_points.csv": Case(_TRUTH_FILES[POINTS_FILE], _in_truth_folder(POINTS_FILE), header_only=None,
                                    optional=True),
    "ground_truth_motion.csv": Case(_TRUTH_FILES[MOTION_FILE], _in_truth_folder(MOTION_FILE),
                                    header_only="expected one row for each frame",
                                    optional=True),
    "points.csv (scene)": Case(_TRUTH_FILES["points.csv"], read_points_csv),
    "fusion_tables/task1.csv": Case("k,estimate,variance\n1,100.06,1.0\n2,100.38,0.5\n", _read_csv_table,
                                    header_only=None),
}


def _lines(text: str) -> list[str]:
    assert text.endswith("\n") and "\r" not in text
    return text[:-1].split("\n")


# Variants of a valid text that must read the same: each takes the file's lines, gives the bytes.
VARIANTS = {
    "bom": lambda lines: b"\xef\xbb\xbf" + ("\n".join(lines) + "\n").encode(),
    "comments": lambda lines: ("# written by hand, \"quoted\", with commas\n" + lines[0] + "\n  # indented comment\n"
                               + "\n".join(lines[1:]) + "\n# the end\n").encode(),
    "blank lines": lambda lines: ("\n" + lines[0] + "\n\n   \n" + "\n".join(lines[1:]) + "\n\n"
                                  + "," * (lines[0].count(",")) + "\n").encode(),
    "crlf": lambda lines: ("\r\n".join(lines) + "\r\n").encode(),
    "no final newline": lambda lines: "\n".join(lines).encode(),
    "spaces around header names": lambda lines: (" " + lines[0].replace(",", " , ") + " \n"
                                                 + "\n".join(lines[1:]) + "\n").encode(),
}


def _same(a: object, b: object) -> None:
    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        assert type(a) is type(b)
        for field in dataclasses.fields(a):
            _same(getattr(a, field.name), getattr(b, field.name))
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    elif isinstance(a, (tuple, list)):
        assert type(a) is type(b) and len(a) == len(b)
        for x, y in zip(a, b):
            _same(x, y)
    else:
        assert a == b


def _write(tmp_path: Path, name: str, data: bytes) -> Path:
    path = tmp_path / name.split(" ")[0]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def _refused(case: Case, path: Path, message: str) -> str:
    with pytest.raises(InvalidInputError, match=message) as info:
        case.read(path)
    text = str(info.value)
    assert str(path) in text and "\n" not in text
    return text


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("name", list(CASES))
def test_every_reader_reads_the_variants_of_a_valid_file_alike(tmp_path, name, variant):
    case = CASES[name]
    plain = case.read(_write(tmp_path / "plain", name, case.text.encode()))
    assert plain is not None
    other = case.read(_write(tmp_path / "variant", name, VARIANTS[variant](_lines(case.text))))
    _same(plain, other)


@pytest.mark.parametrize("name", list(CASES))
def test_a_ragged_row_is_refused_naming_its_line(tmp_path, name):
    lines = _lines(CASES[name].text)
    text = "# a comment\n" + lines[0] + "\n\n" + lines[1] + "\n1,2\n" + "\n".join(lines[2:]) + "\n"
    n_fields = lines[0].count(",") + 1
    _refused(CASES[name], _write(tmp_path, name, text.encode()), f": line 5: 2 fields, the header has {n_fields}$")


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n\n", "\ufeff"])
@pytest.mark.parametrize("name", list(CASES))
def test_an_empty_file_is_refused(tmp_path, name, text):
    _refused(CASES[name], _write(tmp_path, name, text.encode()), ": empty file; expected a header ")


@pytest.mark.parametrize("name", list(CASES))
def test_a_header_only_file_is_refused_where_the_format_needs_rows(tmp_path, name):
    case = CASES[name]
    path = _write(tmp_path, name, ("# c\n" + _lines(case.text)[0] + "\n\n").encode())
    if case.header_only is not None:
        _refused(case, path, case.header_only)
    else:
        case.read(path)  # no error


@pytest.mark.parametrize("name", list(CASES))
def test_a_missing_file_is_refused(tmp_path, name):
    case = CASES[name]
    path = tmp_path / "folder" / name.split(" ")[0]
    path.parent.mkdir(parents=True)
    if case.optional:  # read through its folder: an absent optional file is not an error
        case.read(path)
        return
    _refused(case, path, ": no such file$")


@pytest.mark.parametrize("data", [b"\xff\xfeh\x00e\x00", "x,y\n1,2\n".encode("utf-16"), b"frame,x\n1,\x002\n"])
@pytest.mark.parametrize("name", list(CASES))
def test_a_file_that_is_not_utf8_text_is_refused(tmp_path, name, data):
    _refused(CASES[name], _write(tmp_path, name, data), re.escape(": not a readable text CSV ("))


@pytest.mark.parametrize("name", list(CASES))
def test_a_missing_column_gets_the_one_message_of_every_reader(tmp_path, name):
    lines = _lines(CASES[name].text)
    renamed = ",".join(f"renamed_{c}" for c in lines[0].split(","))
    path = _write(tmp_path, name, ("# c\n" + "\n".join([renamed, *lines[1:]]) + "\n").encode())
    if name.startswith("fusion_tables"):  # any columns: shown as they are
        CASES[name].read(path)
        return
    text = _refused(CASES[name], path, rf": line 2: missing column\(s\) [^;]+; expected [^;]+; got {re.escape(renamed)}$")
    if name.startswith("cameras.csv"):  # two layouts: both are named
        assert "the projection-matrix layout frame,p11," in text and "or the intrinsics + pose layout frame,fx," in text


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")
@pytest.mark.parametrize("kind", ["folder", "FIFO"])
@pytest.mark.parametrize("name", list(CASES))
def test_what_is_not_a_regular_file_is_refused_unread(request, tmp_path, name, kind):
    path = tmp_path / "folder" / name.split(" ")[0]
    path.parent.mkdir(parents=True)
    path.mkdir() if kind == "folder" else os.mkfifo(path)  # a FIFO opened for reading would block the test
    if name.startswith(("cameras.csv", "K.csv")) and kind == "folder":  # a folder of cameras is a COLMAP model
        _refused(CASES[name], path, ": no COLMAP model")
        return
    if name.startswith("tracks.csv") and kind == "folder":  # a tracks file may be CSV or NPZ: 'a file'
        _refused(CASES[name], path, ": is a folder, not a file; give a tracks file")
        return
    _refused(CASES[name], path, f": is a {kind}, not a text CSV$")


def test_read_rows_gives_file_lines_and_keeps_cells_as_written(tmp_path):
    f = tmp_path / "t.csv"
    f.write_bytes(b"\xef\xbb\xbf# c\r\n a ,b\r\n\r\n,\r\n 1 ,\"2,5\"\r\n  # c\r\n3,4\r\n")
    header, header_line, rows = read_rows(f, "a,b")
    assert header == ["a", "b"] and header_line == 2
    assert rows == [(5, [" 1 ", "2,5"]), (7, ["3", "4"])]
    f.write_text('a,b\n1,"two\nlines"\n2,3\n')
    assert read_rows(f, "a,b").rows == [(2, ["1", "two\nlines"]), (4, ["2", "3"])]  # a row starts on its first line


def test_points_outside_the_image_name_their_file_line(tmp_path):
    from kalmansfm.io.tracks import check_points_inside

    f = tmp_path / "points.csv"
    f.write_text("# start points\nx,y\n\n10,10\n500,20\n")
    points, ids, lines = read_points_csv(f, with_lines=True)
    assert ids is None and lines.tolist() == [4, 5]
    with pytest.raises(InvalidInputError, match="points.csv: line 5: point \\(500, 20\\) lies outside"):
        check_points_inside(points, 160, 120, str(f), lines)


# Every reader with columns to check; the fusion tables are read as text (no schema to break).
SCHEMA_CASES = [name for name in CASES if not name.startswith("fusion_tables/")]


def _key_column(header: str) -> int:
    """A column every layout of the file needs (x, X or frame, else track_id), by its place in the header."""
    names = header.split(",")
    return names.index(next(n for n in ("x", "X", "frame", "track_id") if n in names))


@pytest.mark.parametrize("name", SCHEMA_CASES)
def test_a_non_number_cell_is_refused_naming_its_file_line(tmp_path, name):
    lines = _lines(CASES[name].text)
    assert len(lines) >= 3
    fields = lines[2].split(",")
    fields[_key_column(lines[0])] = "one"
    # line 1 header, 2 a good row, 3 a comment, 4 blank, 5 the bad row
    text = "\n".join([lines[0], lines[1], "# a comment", "", ",".join(fields), *lines[3:]]) + "\n"
    path = _write(tmp_path, name, text.encode())
    message = _refused(CASES[name], path, re.escape(f"{path}: line 5: ") + ".*one")
    assert message.startswith(f"{path}: line 5: ")


@pytest.mark.parametrize("name", SCHEMA_CASES)
def test_a_missing_column_is_refused_naming_the_header_line(tmp_path, name):
    lines = _lines(CASES[name].text)
    names = lines[0].split(",")
    gone = names[_key_column(lines[0])]
    names[_key_column(lines[0])] = "renamed"
    # line 1 a comment, 2 blank, 3 the header
    text = "\n".join(["# a comment", "", ",".join(names), *lines[1:]]) + "\n"
    path = _write(tmp_path, name, text.encode())
    message = _refused(CASES[name], path, re.escape(f"{path}: line 3: ") + r".*\b" + re.escape(gone) + r"\b")
    assert message.startswith(f"{path}: line 3: ") and "column" in message
