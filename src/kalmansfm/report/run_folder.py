"""Read the files of a finished run folder, checking each one at the boundary.

A run folder is what ``kalmansfm demo`` (and the other pipeline commands)
write: ``summary.json`` plus any of the optional files listed in
:func:`load_run`.  Every reader here raises :class:`InvalidInputError` naming
the file, the row or the field when a file exists but cannot be used; a file
that does not exist is simply ``None`` so the report omits its section.
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InvalidInputError
from ..io.npz import load_npz

__all__ = [
    "RunFolder",
    "TrackArrays",
    "PointTable",
    "CameraMotion",
    "CsvTable",
    "load_run",
    "read_summary",
]

# Status codes of tracks.npz.
STATUS_NONE, STATUS_MEASURED, STATUS_PREDICTED, STATUS_LOST = 0, 1, 2, 3

# Pre-rendered figures a run may carry, embedded as they are when present.
RUN_FIGURES = ("covariance_trace.png", "tracks.png", "structure.png", "task7.png")

_FRAME_NAME = re.compile(r"^frame_(\d+)\.png$")


@dataclass(frozen=True)
class TrackArrays:
    """The contents of ``tracks.npz``.

    Attributes
    ----------
    positions : (F, P, 2) float64, x = column, y = row, NaN where there is no estimate
    status : (F, P) int, 0 none, 1 measured, 2 predicted, 3 lost
    track_ids : (P,) int
    covariances : (F, P, 4, 4) float64 or None, state covariance (position block first)
    states : (F, P, 4) float64 or None, (x, y, vx, vy)
    """

    positions: np.ndarray
    status: np.ndarray
    track_ids: np.ndarray
    covariances: np.ndarray | None
    states: np.ndarray | None


@dataclass(frozen=True)
class PointTable:
    """3D points keyed by track id (``structure.csv``, ``ground_truth_points.csv``)."""

    track_ids: np.ndarray
    points: np.ndarray  # (P, 3)


@dataclass(frozen=True)
class CameraMotion:
    """The factorization's per-frame camera rows (``motion.csv``).

    ``i_rows`` and ``j_rows`` are the (F, 3) image x and y axes expressed in the
    world frame; ``translations`` is (F, 2) in pixels.
    """

    frames: np.ndarray
    i_rows: np.ndarray
    j_rows: np.ndarray
    translations: np.ndarray


@dataclass(frozen=True)
class CsvTable:
    """A CSV file shown verbatim (``fusion_tables/*.csv``)."""

    name: str
    header: list[str]
    rows: list[list[str]]


@dataclass(frozen=True)
class RunFolder:
    """Everything the report reads from one run folder; missing files are ``None``."""

    path: Path
    summary: dict[str, Any]
    frame_paths: tuple[Path, ...]
    tracks: TrackArrays | None
    structure: PointTable | None
    motion: CameraMotion | None
    ground_truth_tracks: np.ndarray | None  # (F, P, 2) in the order of tracks.track_ids, NaN if not visible
    ground_truth_points: PointTable | None
    fusion_tables: tuple[CsvTable, ...]
    figures: dict[str, Path]
    data_files: tuple[str, ...]


def read_summary(path: str | Path) -> dict[str, Any]:
    """Read and check ``summary.json``.

    Raises
    ------
    InvalidInputError
        If the file is missing, is not JSON, or is not a JSON object.

    Examples
    --------
    >>> import json, tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "summary.json"
    >>> _ = p.write_text(json.dumps({"input": "built-in scene (seed 0)"}))
    >>> read_summary(p)["input"]
    'built-in scene (seed 0)'
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(
            f"{path}: not found; a run folder must contain the summary.json that kalmansfm writes"
        )
    try:
        summary = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InvalidInputError(f"{path}: is not UTF-8 text; expected a JSON object") from None
    except json.JSONDecodeError as exc:
        raise InvalidInputError(
            f"{path}: is not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})"
        ) from None
    if not isinstance(summary, dict):
        raise InvalidInputError(f"{path}: expected a JSON object at the top level; got {type(summary).__name__}")
    for key in ("parameters", "timings_s", "tracking", "factorization"):
        if key in summary and summary[key] is not None and not isinstance(summary[key], dict):
            raise InvalidInputError(
                f"{path}: field {key!r} must be an object; got {type(summary[key]).__name__}"
            )
    per_track = (summary.get("tracking") or {}).get("per_track")
    if per_track is not None and not (
        isinstance(per_track, list) and all(isinstance(row, dict) for row in per_track)
    ):
        raise InvalidInputError(f"{path}: field 'tracking.per_track' must be a list of objects")
    return summary


def _read_tracks(path: Path) -> TrackArrays:
    arrays = load_npz(path)
    missing = [name for name in ("positions", "status", "track_ids") if name not in arrays]
    if missing:
        raise InvalidInputError(f"{path}: missing array(s) {', '.join(missing)}; found {sorted(arrays)}")
    positions = np.asarray(arrays["positions"], dtype=float)
    if positions.ndim != 3 or positions.shape[2] != 2:
        raise InvalidInputError(f"{path}: positions must have shape (frames, points, 2); got {positions.shape}")
    n_frames, n_points = positions.shape[:2]
    status = np.asarray(arrays["status"])
    if status.shape != (n_frames, n_points):
        raise InvalidInputError(
            f"{path}: status must have shape {(n_frames, n_points)} like positions; got {status.shape}"
        )
    track_ids = np.asarray(arrays["track_ids"])
    if track_ids.shape != (n_points,):
        raise InvalidInputError(f"{path}: track_ids must have shape ({n_points},); got {track_ids.shape}")
    covariances = arrays.get("covariances")
    if covariances is not None:
        covariances = np.asarray(covariances, dtype=float)
        if covariances.shape != (n_frames, n_points, 4, 4):
            raise InvalidInputError(
                f"{path}: covariances must have shape {(n_frames, n_points, 4, 4)}; got {covariances.shape}"
            )
    states = arrays.get("states")
    if states is not None:
        states = np.asarray(states, dtype=float)
        if states.shape != (n_frames, n_points, 4):
            raise InvalidInputError(f"{path}: states must have shape {(n_frames, n_points, 4)}; got {states.shape}")
    return TrackArrays(positions, status.astype(int), track_ids.astype(int), covariances, states)


def _read_csv_columns(path: Path, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Numeric columns of a CSV file with a header row, checked row by row."""
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            reader = csv.DictReader(handle)
            header = reader.fieldnames or []
            missing = [c for c in columns if c not in header]
            if missing:
                raise InvalidInputError(
                    f"{path}: missing column(s) {', '.join(missing)}; expected {','.join(columns)}, "
                    f"got header {','.join(header) or '(empty file)'}"
                )
            values: dict[str, list[float]] = {c: [] for c in columns}
            for row in reader:
                for c in columns:
                    try:
                        values[c].append(float(row[c]))
                    except (TypeError, ValueError):
                        raise InvalidInputError(
                            f"{path}, line {reader.line_num}: column {c!r} must be a number; got {row[c]!r}"
                        ) from None
    except UnicodeDecodeError:
        raise InvalidInputError(f"{path}: is not UTF-8 text") from None
    return {c: np.asarray(v, dtype=float) for c, v in values.items()}


def _read_points(path: Path) -> PointTable | None:
    """The finite rows (a point that could not be recovered may be NaN); None if there are none."""
    cols = _read_csv_columns(path, ("track_id", "X", "Y", "Z"))
    points = np.column_stack([cols["X"], cols["Y"], cols["Z"]])
    keep = np.isfinite(points).all(axis=1)
    if not keep.any():
        return None
    return PointTable(cols["track_id"][keep].astype(int), points[keep])


def _read_motion(path: Path) -> CameraMotion | None:
    """The frames with finite, non-zero camera rows; None if there are none."""
    names = ("frame", "i_x", "i_y", "i_z", "j_x", "j_y", "j_z", "t_x", "t_y")
    cols = _read_csv_columns(path, names)
    i_rows = np.column_stack([cols["i_x"], cols["i_y"], cols["i_z"]])
    j_rows = np.column_stack([cols["j_x"], cols["j_y"], cols["j_z"]])
    translations = np.column_stack([cols["t_x"], cols["t_y"]])
    keep = (
        np.isfinite(np.hstack([i_rows, j_rows, translations])).all(axis=1)
        & (np.linalg.norm(i_rows, axis=1) > 0)
        & (np.linalg.norm(np.cross(i_rows, j_rows), axis=1) > 0)
    )
    if not keep.any():
        return None
    return CameraMotion(cols["frame"][keep].astype(int), i_rows[keep], j_rows[keep], translations[keep])


def _read_ground_truth_tracks(path: Path, tracks: TrackArrays) -> np.ndarray:
    cols = _read_csv_columns(path, ("frame", "track_id", "x", "y", "visible"))
    n_frames = tracks.positions.shape[0]
    truth = np.full(tracks.positions.shape, np.nan)
    column_of = {int(t): k for k, t in enumerate(tracks.track_ids)}
    frames = cols["frame"].astype(int)
    ids = cols["track_id"].astype(int)
    keep = (cols["visible"] != 0) & (frames >= 0) & (frames < n_frames) & np.isin(ids, tracks.track_ids)
    columns = np.array([column_of[int(t)] for t in ids[keep]], dtype=int)
    truth[frames[keep], columns, 0] = cols["x"][keep]
    truth[frames[keep], columns, 1] = cols["y"][keep]
    return truth


def _read_csv_table(path: Path) -> CsvTable:
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            rows = [row for row in csv.reader(handle) if row and not row[0].startswith("#")]
    except UnicodeDecodeError:
        raise InvalidInputError(f"{path}: is not UTF-8 text") from None
    if not rows:
        raise InvalidInputError(f"{path}: is empty; expected a header row and data rows")
    return CsvTable(path.stem, rows[0], rows[1:])


def _frame_paths(folder: Path) -> tuple[Path, ...]:
    if not folder.is_dir():
        return ()
    numbered = []
    for p in folder.iterdir():
        match = _FRAME_NAME.match(p.name)
        if match:
            numbered.append((int(match.group(1)), p))
    return tuple(p for _, p in sorted(numbered))


def load_run(run_dir: str | Path) -> RunFolder:
    """Read every report input of a run folder.

    Parameters
    ----------
    run_dir : path
        Folder with ``summary.json`` and optionally ``frames/frame_NNN.png``,
        ``tracks.npz``, ``structure.csv``, ``motion.csv``,
        ``ground_truth_tracks.csv``, ``ground_truth_points.csv``,
        ``fusion_tables/*.csv`` and the pre-rendered figures
        ``covariance_trace.png``, ``tracks.png``, ``structure.png``, ``task7.png``.

    Raises
    ------
    InvalidInputError
        If ``run_dir`` is not a folder, ``summary.json`` is missing or broken, or
        an optional file exists but does not have the documented layout.
    """
    folder = Path(run_dir)
    if not folder.is_dir():
        raise InvalidInputError(f"run folder {folder} does not exist or is not a folder")
    summary = read_summary(folder / "summary.json")
    tracks = _read_tracks(folder / "tracks.npz") if (folder / "tracks.npz").is_file() else None
    gt_tracks_path = folder / "ground_truth_tracks.csv"
    ground_truth_tracks = (
        _read_ground_truth_tracks(gt_tracks_path, tracks) if tracks is not None and gt_tracks_path.is_file() else None
    )
    optional_points = {
        name: _read_points(folder / name) if (folder / name).is_file() else None
        for name in ("structure.csv", "ground_truth_points.csv")
    }
    motion = _read_motion(folder / "motion.csv") if (folder / "motion.csv").is_file() else None
    table_dir = folder / "fusion_tables"
    fusion_tables = tuple(_read_csv_table(p) for p in sorted(table_dir.glob("*.csv"))) if table_dir.is_dir() else ()
    figures = {name: folder / name for name in RUN_FIGURES if (folder / name).is_file()}
    data_files = tuple(
        name
        for name in (
            "summary.json",
            "tracks.csv",
            "tracks.npz",
            "structure.csv",
            "structure.ply",
            "motion.csv",
            "ground_truth_tracks.csv",
            "ground_truth_points.csv",
        )
        if (folder / name).is_file()
    )
    return RunFolder(
        path=folder,
        summary=summary,
        frame_paths=_frame_paths(folder / "frames"),
        tracks=tracks,
        structure=optional_points["structure.csv"],
        motion=motion,
        ground_truth_tracks=ground_truth_tracks,
        ground_truth_points=optional_points["ground_truth_points.csv"],
        fusion_tables=fusion_tables,
        figures=figures,
        data_files=data_files,
    )
