"""Ground-truth files of a synthetic scene: writing a :class:`~kalmansfm.scenes.Scene` and reading it back.

A scene folder holds ``frame_000.png …`` and

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
``summary.json``
    The parameters used to render.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ..errors import InvalidInputError
from .atomic import output_directory

if TYPE_CHECKING:
    from ..scenes.polyhedron import Scene

__all__ = ["GroundTruth", "write_scene", "read_ground_truth", "read_ground_truth_tracks", "frame_name"]

TRACKS_FILE = "ground_truth_tracks.csv"
POINTS_FILE = "ground_truth_points.csv"
MOTION_FILE = "ground_truth_motion.csv"
OCCLUDER_FILE = "ground_truth_occluder.csv"
START_POINTS_FILE = "points.csv"
MOTION_COLUMNS = ["frame", "r11", "r12", "r13", "r21", "r22", "r23", "t_x", "t_y", "scale"]


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
    """

    track_ids: np.ndarray
    positions: np.ndarray
    visible: np.ndarray
    points_3d: np.ndarray | None = None
    rotation_rows: np.ndarray | None = None
    translations: np.ndarray | None = None
    scales: np.ndarray | None = None


def frame_name(index: int, n_frames: int) -> str:
    """File name of frame ``index`` in a sequence of ``n_frames`` (at least three digits).

    Examples
    --------
    >>> frame_name(7, 30), frame_name(7, 5000)
    ('frame_007.png', 'frame_0007.png')
    """
    digits = max(3, len(str(max(n_frames - 1, 0))))
    return f"frame_{index:0{digits}d}.png"


def _csv_text(header: list[str], rows: Iterable[Iterable[object]]) -> str:
    lines = [",".join(header)]
    lines.extend(",".join(str(v) for v in row) for row in rows)
    return "\n".join(lines) + "\n"


def _number(value: float) -> str:
    # the shortest text that reads back as the same float: ground truth stays exact
    return "" if not np.isfinite(value) else repr(float(value))


def scene_files(scene: Scene, *, frames: bool = True) -> dict[str, bytes | str]:
    """The files of a scene folder by name: frame PNGs (bytes) and ground-truth CSVs (text).

    ``frames=False`` leaves the PNGs out (the ground truth alone).
    """
    n_frames, n_points = scene.visible.shape
    files: dict[str, bytes | str] = {}
    if frames:
        for f in range(n_frames):
            ok, png = cv2.imencode(".png", scene.frames[f])
            if not ok:  # pragma: no cover - OpenCV always encodes uint8 grey images
                raise RuntimeError(f"could not encode frame {f} as PNG")
            files[frame_name(f, n_frames)] = png.tobytes()
    ids = scene.track_ids
    tracks = (
        (f, int(ids[p]), _number(scene.positions[f, p, 0]), _number(scene.positions[f, p, 1]), int(scene.visible[f, p]))
        for f in range(n_frames)
        for p in range(n_points)
    )
    points = ((int(ids[p]), *(_number(v) for v in scene.points_3d[p])) for p in range(n_points))
    motion = (
        (f, *(_number(v) for v in scene.rotations[f, :2].ravel()), *(_number(v) for v in scene.translations[f]),
         _number(scene.scale))
        for f in range(n_frames)
    )
    start = (
        (int(ids[p]), _number(scene.positions[0, p, 0]), _number(scene.positions[0, p, 1]))
        for p in range(n_points)
        if scene.visible[0, p]
    )
    files[TRACKS_FILE] = _csv_text(["frame", "track_id", "x", "y", "visible"], tracks)
    files[POINTS_FILE] = _csv_text(["track_id", "X", "Y", "Z"], points)
    files[MOTION_FILE] = _csv_text(MOTION_COLUMNS, motion)
    files[START_POINTS_FILE] = _csv_text(["track_id", "x", "y"], start)
    if scene.occluder_boxes is not None and np.isfinite(scene.occluder_boxes).any():
        marker = (
            scene.occluder_marker_positions
            if scene.occluder_marker_positions is not None
            else np.full((n_frames, 2), np.nan)
        )
        rows = (
            (f, *(_number(v) for v in scene.occluder_boxes[f]), *(_number(v) for v in marker[f]))
            for f in range(n_frames)
        )
        header = ["frame", "x0", "y0", "x1", "y1", "marker_x", "marker_y"]
        files[OCCLUDER_FILE] = _csv_text(header, rows)
    return files


def write_scene(scene: Scene, path: str | os.PathLike[str]) -> list[Path]:
    """Write a scene's frames as PNG and its ground truth as CSV into the folder ``path``.

    The files appear together or not at all (see :func:`kalmansfm.io.output_directory`).

    Returns
    -------
    list of Path
        The files written.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.scenes import render_scene
    >>> folder = pathlib.Path(tempfile.mkdtemp()) / "scene"
    >>> files = write_scene(render_scene(n_frames=3, pixel_noise_std=0.0), folder)
    >>> sorted(p.name for p in files)[:4]
    ['frame_000.png', 'frame_001.png', 'frame_002.png', 'ground_truth_motion.csv']
    >>> read_ground_truth(folder).positions.shape
    (3, 10, 2)
    """
    from .. import __version__

    files = scene_files(scene)
    summary = {"command": "scene", "kalmansfm_version": __version__, "parameters": scene.parameters}
    with output_directory(path) as out:
        written = [
            out.write_bytes(name, data) if isinstance(data, bytes) else out.write_text(name, data)
            for name, data in files.items()
        ]
        written.append(out.write_text("summary.json", json.dumps(summary, indent=2) + "\n"))
    return written


def _read_table(path: Path, required: list[str]) -> dict[str, np.ndarray]:
    """Columns of a CSV file with a header, as float arrays; checks the required columns."""
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such file")
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.reader(handle)
            header = next(reader, None)
            if header is None:
                raise InvalidInputError(f"{path}: empty file; expected a header with {', '.join(required)}")
            header = [h.strip() for h in header]
            missing = [c for c in required if c not in header]
            if missing:
                raise InvalidInputError(f"{path}: missing column(s) {', '.join(missing)}; header is {','.join(header)}")
            rows = []
            for line_number, row in enumerate(reader, start=2):
                if not row:
                    continue
                if len(row) != len(header):
                    raise InvalidInputError(f"{path}, row {line_number}: expected {len(header)} fields, got {len(row)}")
                try:
                    rows.append([float(v) if v.strip() else np.nan for v in row])
                except ValueError:
                    raise InvalidInputError(f"{path}, row {line_number}: expected numbers, got {','.join(row)}") from None
    except UnicodeDecodeError:
        raise InvalidInputError(f"{path}: not a UTF-8 text CSV file") from None
    except csv.Error as exc:
        raise InvalidInputError(f"{path}: not a readable CSV file ({exc})") from None
    table = np.array(rows, dtype=np.float64).reshape(len(rows), len(header))
    return {name: table[:, k] for k, name in enumerate(header)}


# Frame numbers and track ids index dense arrays: refuse numbers that would need absurd memory.
MAX_INDEX = 10_000_000


def _as_index(values: np.ndarray, path: Path, column: str) -> np.ndarray:
    if len(values) and (not np.all(np.isfinite(values)) or np.any(values != np.round(values)) or values.min() < 0):
        raise InvalidInputError(f"{path}: column {column} must hold non-negative integers")
    if len(values) and values.max() > MAX_INDEX:
        raise InvalidInputError(f"{path}: column {column} holds {values.max():.0f}; at most {MAX_INDEX} is supported")
    return values.astype(np.int64)


def read_ground_truth_tracks(path: str | os.PathLike[str]) -> GroundTruth:
    """Read ``ground_truth_tracks.csv`` (``frame,track_id,x,y,visible``) into dense arrays.

    Frames and tracks missing from the file are NaN / not visible.
    """
    path = Path(path)
    table = _read_table(path, ["frame", "track_id", "x", "y", "visible"])
    frames = _as_index(table["frame"], path, "frame")
    ids = _as_index(table["track_id"], path, "track_id")
    if len(frames) == 0:
        raise InvalidInputError(f"{path}: no rows")
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
    if points_path.is_file():
        table = _read_table(points_path, ["track_id", "X", "Y", "Z"])
        ids = _as_index(table["track_id"], points_path, "track_id")
        points_3d = np.full((len(tracks.track_ids), 3), np.nan)
        where = np.searchsorted(tracks.track_ids, ids)
        known = (where < len(tracks.track_ids)) & (tracks.track_ids[np.minimum(where, len(tracks.track_ids) - 1)] == ids)
        if not known.all():
            raise InvalidInputError(f"{points_path}: track_id {ids[~known][0]} is not in {TRACKS_FILE}")
        points_3d[where] = np.column_stack([table["X"], table["Y"], table["Z"]])
    motion_path = folder / MOTION_FILE
    if motion_path.is_file():
        table = _read_table(motion_path, MOTION_COLUMNS)
        frames = _as_index(table["frame"], motion_path, "frame")
        n_frames = tracks.positions.shape[0]
        if len(frames) != n_frames or not np.array_equal(np.sort(frames), np.arange(n_frames)):
            raise InvalidInputError(f"{motion_path}: expected one row for each frame 0 … {n_frames - 1}")
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
