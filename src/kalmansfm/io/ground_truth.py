"""Ground-truth files of a run or a scene folder: their schema, writer and reader.

A folder with ground truth holds

``ground_truth_tracks.csv``
    ``frame,track_id,x,y,visible``: every corner in every frame (x = column,
    y = row, pixel centres at integers; visible 1 or 0).
``ground_truth_points.csv``
    ``track_id,X,Y,Z``: the corners in the object frame (centred).
``ground_truth_motion.csv``
    ``frame,r11,r12,r13,r21,r22,r23,t_x,t_y,scale``: the first two rows of
    the rotation, the translation and the scale, so that
    ``[x, y] = scale * [[r11, r12, r13], [r21, r22, r23]] @ [X, Y, Z] + [t_x, t_y]``.
``points.csv``
    ``track_id,x,y``: the corners visible in frame 0, the input of
    ``kalmansfm track --points``.
``ground_truth_occluder.csv`` (only with an occluder)
    ``frame,x0,y0,x1,y1,marker_x,marker_y``: the card's rectangle and the
    centre of its marker (empty without one).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ._csv import MAX_INDEX, csv_text, number, read_rows, where
from .structure import structure_csv

__all__ = ["GroundTruth", "ground_truth_files", "read_ground_truth", "read_ground_truth_tracks", "GROUND_TRUTH_FILES"]

TRACKS_FILE = "ground_truth_tracks.csv"
POINTS_FILE = "ground_truth_points.csv"
MOTION_FILE = "ground_truth_motion.csv"
OCCLUDER_FILE = "ground_truth_occluder.csv"
START_POINTS_FILE = "points.csv"
MOTION_COLUMNS = ["frame", "r11", "r12", "r13", "r21", "r22", "r23", "t_x", "t_y", "scale"]
#: Every file name this module writes.
GROUND_TRUTH_FILES = (TRACKS_FILE, POINTS_FILE, MOTION_FILE, OCCLUDER_FILE, START_POINTS_FILE)


@dataclass(frozen=True)
class GroundTruth:
    """Ground truth read from a scene folder.

    Attributes
    ----------
    track_ids : (P,) int64
        Sorted track identities; column ``p`` of the arrays below is ``track_ids[p]``.
    positions : (F, P, 2) float64
        x = column, y = row.
    visible : (F, P) bool
    points_3d : (P, 3) float64 or None
        None when ``ground_truth_points.csv`` is absent.
    rotation_rows : (F, 2, 3) float64 or None
        First two rows of each frame's rotation.
    translations : (F, 2) float64 or None
    scales : (F,) float64 or None
    occluder_boxes : (F, 4) float64 or None
        An occluding card's rectangle ``x0, y0, x1, y1`` per frame (NaN where there is none).
    occluder_markers : (F, 2) float64 or None
        Centre of the card's own marker (NaN without one).
    """

    track_ids: np.ndarray
    positions: np.ndarray
    visible: np.ndarray
    points_3d: np.ndarray | None = None
    rotation_rows: np.ndarray | None = None
    translations: np.ndarray | None = None
    scales: np.ndarray | None = None
    occluder_boxes: np.ndarray | None = None
    occluder_markers: np.ndarray | None = None

    def aligned_to(self, track_ids: np.ndarray) -> np.ndarray:
        """(F, P, 2) the true positions of the tracks ``track_ids`` (P,), NaN where not visible or unknown."""
        index = np.searchsorted(self.track_ids, track_ids)
        index = np.minimum(index, max(len(self.track_ids) - 1, 0))
        known = (len(self.track_ids) > 0) & (self.track_ids[index] == track_ids)
        truth = np.full((self.positions.shape[0], len(track_ids), 2), np.nan)
        truth[:, known] = np.where(self.visible[:, index[known], None], self.positions[:, index[known]], np.nan)
        return truth


def ground_truth_files(truth: GroundTruth) -> dict[str, str]:
    """The ground-truth CSV texts of ``truth`` by file name (see the module notes).

    Numbers are written at full (round-trip) precision, so the ground truth stays exact.
    The 3D points, the motion and the occluder are written when ``truth`` has them.
    """
    n_frames, n_points = truth.visible.shape
    ids = truth.track_ids
    tracks = (
        (f, int(ids[p]), number(truth.positions[f, p, 0]), number(truth.positions[f, p, 1]), int(truth.visible[f, p]))
        for f in range(n_frames)
        for p in range(n_points)
    )
    start = (
        (int(ids[p]), number(truth.positions[0, p, 0]), number(truth.positions[0, p, 1]))
        for p in range(n_points)
        if truth.visible[0, p]
    )
    files = {
        TRACKS_FILE: csv_text(["frame", "track_id", "x", "y", "visible"], tracks),
        START_POINTS_FILE: csv_text(["track_id", "x", "y"], start),
    }
    if truth.points_3d is not None:
        files[POINTS_FILE] = structure_csv(ids, truth.points_3d)
    if truth.rotation_rows is not None and truth.translations is not None and truth.scales is not None:
        motion = (
            (f, *(number(v) for v in truth.rotation_rows[f].ravel()), *(number(v) for v in truth.translations[f]),
             number(truth.scales[f]))
            for f in range(n_frames)
        )
        files[MOTION_FILE] = csv_text(MOTION_COLUMNS, motion)
    if truth.occluder_boxes is not None and np.isfinite(truth.occluder_boxes).any():
        marker = truth.occluder_markers if truth.occluder_markers is not None else np.full((n_frames, 2), np.nan)
        rows = (
            (f, *(number(v) for v in truth.occluder_boxes[f]), *(number(v) for v in marker[f]))
            for f in range(n_frames)
        )
        files[OCCLUDER_FILE] = csv_text(["frame", "x0", "y0", "x1", "y1", "marker_x", "marker_y"], rows)
    return files


def _read_table(path: Path, required: list[str], *, allow_no_rows: bool = False) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Columns of a CSV file with a header, as float arrays (an empty cell is NaN), and the file line of each row.

    Checks the required columns.
    """
    header, _, rows = read_rows(path, required=required, allow_no_rows=allow_no_rows)
    values = []
    for line_number, row in rows:
        try:
            values.append([float(v) if v.strip() else np.nan for v in row])
        except ValueError:
            raise InvalidInputError(f"{where(path, line_number)}: expected numbers, got {','.join(row)}") from None
    table = np.array(values, dtype=np.float64).reshape(len(values), len(header))
    return {name: table[:, k] for k, name in enumerate(header)}, np.array([n for n, _ in rows], dtype=np.int64)


def _as_index(values: np.ndarray, path: Path, column: str, lines: np.ndarray) -> np.ndarray:
    """The column as integers; the first row that is not one in 0 … MAX_INDEX is refused, naming its line."""
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(values) | (values != np.round(values)) | (values < 0)
    if bad.any():
        k = int(np.argmax(bad))
        raise InvalidInputError(f"{where(path, lines[k])}: column {column} must hold non-negative integers; "
                                f"got {values[k]:g}")
    if len(values) and values.max() > MAX_INDEX:
        k = int(np.argmax(values))
        raise InvalidInputError(f"{where(path, lines[k])}: column {column} holds {values[k]:.0f}; "
                                f"at most {MAX_INDEX} is supported")
    return values.astype(np.int64)


def read_ground_truth_tracks(path: str | os.PathLike[str]) -> GroundTruth:
    """Read ``ground_truth_tracks.csv`` (``frame,track_id,x,y,visible``) into dense arrays.

    Frames and tracks missing from the file are NaN / not visible.
    """
    path = Path(path)
    table, lines = _read_table(path, ["frame", "track_id", "x", "y", "visible"])
    frames = _as_index(table["frame"], path, "frame", lines)
    ids = _as_index(table["track_id"], path, "track_id", lines)
    track_ids, column = np.unique(ids, return_inverse=True)
    positions = np.full((frames.max() + 1, len(track_ids), 2), np.nan)
    visible = np.zeros((frames.max() + 1, len(track_ids)), dtype=bool)
    positions[frames, column, 0] = table["x"]
    positions[frames, column, 1] = table["y"]
    visible[frames, column] = table["visible"] > 0
    return GroundTruth(track_ids=track_ids, positions=positions, visible=visible)


def read_ground_truth(directory: str | os.PathLike[str]) -> GroundTruth:
    """Read the ground truth of a scene folder written by :func:`write_scene`.

    ``ground_truth_tracks.csv`` is required; the 3D points and the motion are
    read when their files are present.
    """
    folder = Path(directory)
    tracks = read_ground_truth_tracks(folder / TRACKS_FILE)
    points_3d = rotation_rows = translations = scales = None
    points_path = folder / POINTS_FILE
    if points_path.exists():  # present: read (a folder or FIFO in its place is refused by the reader)
        table, lines = _read_table(points_path, ["track_id", "X", "Y", "Z"], allow_no_rows=True)
        ids = _as_index(table["track_id"], points_path, "track_id", lines)
        points_3d = np.full((len(tracks.track_ids), 3), np.nan)
        slot = np.searchsorted(tracks.track_ids, ids)
        known = (slot < len(tracks.track_ids)) & (tracks.track_ids[np.minimum(slot, len(tracks.track_ids) - 1)] == ids)
        if not known.all():
            k = int(np.argmin(known))
            raise InvalidInputError(f"{where(points_path, lines[k])}: track_id {ids[k]} is not in {TRACKS_FILE}")
        points_3d[slot] = np.column_stack([table["X"], table["Y"], table["Z"]])
    motion_path = folder / MOTION_FILE
    if motion_path.exists():
        table, lines = _read_table(motion_path, MOTION_COLUMNS, allow_no_rows=True)
        frames = _as_index(table["frame"], motion_path, "frame", lines)
        n_frames = tracks.positions.shape[0]
        if len(frames) != n_frames or not np.array_equal(np.sort(frames), np.arange(n_frames)):
            raise InvalidInputError(f"{where(motion_path)}: expected one row for each frame 0 … {n_frames - 1}")
        order = np.argsort(frames)
        rotation_rows = np.column_stack([table[c] for c in MOTION_COLUMNS[1:7]])[order].reshape(-1, 2, 3)
        translations = np.column_stack([table["t_x"], table["t_y"]])[order]
        scales = table["scale"][order]
    return GroundTruth(
        track_ids=tracks.track_ids,
        positions=tracks.positions,
        visible=tracks.visible,
        points_3d=points_3d,
        rotation_rows=rotation_rows,
        translations=translations,
        scales=scales,
    )
