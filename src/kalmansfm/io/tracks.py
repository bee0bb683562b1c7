"""Tracks out and back in: ``tracks.csv`` (long format) and ``tracks.npz`` (arrays), plus points CSVs.

``tracks.csv`` has one row per (frame, track) while the track exists::

    frame,track_id,x,y,vx,vy,std_x,std_y,status

with ``status`` one of ``measured``, ``predicted`` (coasting: x, y are the
prediction) and ``lost`` (the frame of the loss; the numbers are empty).
``tracks.npz`` holds ``positions (F,P,2)``, ``states (F,P,4)``,
``covariances (F,P,4,4)``, ``status (F,P)`` int8 (0 none, 1 measured,
2 predicted, 3 lost) and ``track_ids (P,)``, plus ``scores``, ``image_size`` and
``parameters`` (the tracker's options as a JSON string, e.g. its noise levels and
whether the tracks were smoothed).
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from .npz import load_npz
from ..tracking.tracks import LOST, MEASURED, NO_TRACK, PREDICTED, Tracks

__all__ = ["read_points_csv", "read_tracks_csv", "read_tracks_npz", "tracks_to_csv", "write_tracks_csv", "write_tracks_npz"]

# Frame numbers index a dense (frames, tracks, 4, 4) array: refuse numbers that would need absurd memory.
MAX_FRAMES = 1_000_000
CSV_COLUMNS = ("frame", "track_id", "x", "y", "vx", "vy", "std_x", "std_y", "status")
_WORDS = {MEASURED: "measured", PREDICTED: "predicted", LOST: "lost"}
_CODES = {word: code for code, word in _WORDS.items()}


def _number(value: float) -> str:
    return "" if not np.isfinite(value) else f"{value:.6f}".rstrip("0").rstrip(".")


def tracks_to_csv(tracks: Tracks) -> str:
    """The long-format CSV text of ``tracks``.

    Examples
    --------
    >>> t = Tracks.empty(2, 1)
    >>> t.status[0, 0] = 1; t.states[0, 0] = [1.5, 2.0, 0.5, 0.0]; t.covariances[0, 0] = np.eye(4) * 4.0
    >>> t.status[1, 0] = 3
    >>> print(tracks_to_csv(t), end="")
    frame,track_id,x,y,vx,vy,std_x,std_y,status
    0,0,1.5,2,0.5,0,2,2,measured
    1,0,,,,,,,lost
    """
    frames, cols = np.nonzero(tracks.status != NO_TRACK)
    order = np.lexsort((cols, frames))
    frames, cols = frames[order], cols[order]
    states = tracks.states[frames, cols]
    std = np.sqrt(np.diagonal(tracks.covariances[frames, cols][:, :2, :2], axis1=1, axis2=2))
    status = tracks.status[frames, cols]
    out = io.StringIO()
    out.write(",".join(CSV_COLUMNS) + "\n")
    ids = tracks.track_ids[cols]
    for f, i, s, sd, code in zip(frames.tolist(), ids.tolist(), states, std, status.tolist()):
        if code == LOST:
            s = np.full(4, np.nan)
            sd = np.full(2, np.nan)
        values = ",".join(_number(v) for v in (*s, *sd))
        out.write(f"{f},{i},{values},{_WORDS[code]}\n")
    return out.getvalue()


def write_tracks_csv(tracks: Tracks, path: str | os.PathLike[str]) -> Path:
    """Write ``tracks.csv`` (see the module docs) to ``path``."""
    path = Path(path)
    path.write_text(tracks_to_csv(tracks), encoding="utf-8")
    return path


def write_tracks_npz(tracks: Tracks, path: str | os.PathLike[str]) -> Path:
    """Write the arrays of ``tracks`` to a compressed ``.npz`` file at ``path``."""
    path = Path(path)
    extra = {} if tracks.scores is None else {"scores": tracks.scores}
    if tracks.image_size is not None:
        extra["image_size"] = np.asarray(tracks.image_size, dtype=np.int64)
    if tracks.parameters:
        extra["parameters"] = np.array(json.dumps(tracks.parameters, default=str))
    with open(path, "wb") as handle:
        np.savez_compressed(
            handle,
            positions=tracks.positions,
            states=tracks.states,
            covariances=tracks.covariances,
            status=tracks.status.astype(np.int8),
            track_ids=tracks.track_ids.astype(np.int64),
            **extra,
        )
    return path


def read_tracks_npz(path: str | os.PathLike[str]) -> Tracks:
    """Read a file written by :func:`write_tracks_npz`."""
    path = Path(path)
    arrays = load_npz(path)
    missing = {"positions", "states", "covariances", "status", "track_ids"} - set(arrays)
    if missing:
        raise InvalidInputError(f"{path} lacks the arrays {sorted(missing)}")
    for name in ("positions", "states", "covariances", "scores"):
        if name in arrays and arrays[name].dtype.kind not in "fiub":
            raise InvalidInputError(f"{path}: {name} must be a real numeric array; got dtype {arrays[name].dtype}")
    for name in ("status", "track_ids"):
        if arrays[name].dtype.kind not in "iub":
            raise InvalidInputError(f"{path}: {name} must be an integer array; got dtype {arrays[name].dtype}")
    size = arrays.get("image_size")
    if size is not None and (size.shape != (2,) or size.dtype.kind not in "iu" or (size <= 0).any()):
        raise InvalidInputError(f"{path}: image_size must be two positive integers (width, height); got {size!r}")
    parameters = {}
    if "parameters" in arrays:
        try:
            parameters = json.loads(str(arrays["parameters"]))
        except ValueError as exc:
            raise InvalidInputError(f"{path}: the parameters array is not valid JSON ({exc})") from None
        if not isinstance(parameters, dict):
            raise InvalidInputError(f"{path}: the parameters array must hold a JSON object; got {type(parameters).__name__}")
    return Tracks(
        positions=arrays["positions"],
        states=arrays["states"],
        covariances=arrays["covariances"],
        status=arrays["status"].astype(np.int8),
        track_ids=arrays["track_ids"].astype(np.int64),
        scores=arrays.get("scores"),
        image_size=None if size is None else (int(size[0]), int(size[1])),
        parameters=parameters,
    )


def read_tracks_csv(path: str | os.PathLike[str], n_frames: int | None = None) -> Tracks:
    """Read a ``tracks.csv``; covariances hold only the x, y variances (the rest NaN).

    Parameters
    ----------
    path : the CSV file.
    n_frames : number of frames (default: last frame in the file + 1).
    """
    path = Path(path)
    rows = _read_csv_rows(path, required=CSV_COLUMNS)
    if not rows:
        raise InvalidInputError(f"{path} holds no tracks")
    parsed = []
    for line, row in rows:
        try:
            frame, track_id = int(row["frame"]), int(row["track_id"])
            numbers = [float(row[c]) if row[c].strip() else np.nan for c in ("x", "y", "vx", "vy", "std_x", "std_y")]
            code = _CODES[row["status"].strip()]
        except (ValueError, KeyError):
            raise InvalidInputError(f"{path} row {line}: expected integers, numbers and a status word; got {dict(row)}") from None
        limit = MAX_FRAMES if n_frames is None else int(n_frames)
        if not 0 <= frame < limit:
            raise InvalidInputError(f"{path} row {line}: frame must be in 0 … {limit - 1}; got {frame}")
        parsed.append((frame, track_id, numbers, code))
    ids = sorted({p[1] for p in parsed})
    column = {i: c for c, i in enumerate(ids)}
    F = max(p[0] for p in parsed) + 1 if n_frames is None else int(n_frames)
    tracks = Tracks.empty(F, len(ids))
    tracks.track_ids[:] = ids
    for frame, track_id, numbers, code in parsed:
        c = column[track_id]
        tracks.status[frame, c] = code
        tracks.states[frame, c] = numbers[:4]
        tracks.positions[frame, c] = numbers[:2]
        tracks.covariances[frame, c, 0, 0] = numbers[4] ** 2
        tracks.covariances[frame, c, 1, 1] = numbers[5] ** 2
    return tracks


def _read_csv_rows(path: Path, required: tuple[str, ...]) -> list[tuple[int, dict[str, str]]]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InvalidInputError(f"{path} does not exist") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidInputError(f"{path} is not a readable text CSV ({exc})") from None
    reader = csv.DictReader(io.StringIO(text))
    header = [h.strip() for h in (reader.fieldnames or [])]
    reader.fieldnames = header
    missing = [c for c in required if c not in header]
    if missing:
        raise InvalidInputError(f"{path} row 1 (header): missing column(s) {', '.join(missing)}; got {header}")
    rows = []
    for row in reader:
        line = reader.line_num
        if None in row or any(v is None for v in row.values()):
            raise InvalidInputError(f"{path} row {line}: expected {len(header)} fields like the header")
        if not any(v.strip() for v in row.values()):
            continue
        rows.append((line, row))
    return rows


def read_points_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray | None]:
    """Points to track from a CSV with a header holding ``x``, ``y`` and optionally ``track_id``.

    Returns
    -------
    points : (P, 2) float64 (x, y).
    track_ids : (P,) int64, or None when the file has no ``track_id`` column.

    Raises
    ------
    InvalidInputError
        Naming the file and the row (1-based line number, header = 1) of the problem.

    Examples
    --------
    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "points.csv"
    >>> _ = p.write_text("x,y,track_id\\n118,78,7\\n117,89,8\\n")
    >>> read_points_csv(p)
    (array([[118.,  78.],
           [117.,  89.]]), array([7, 8]))
    """
    path = Path(path)
    rows = _read_csv_rows(path, required=("x", "y"))
    if not rows:
        raise InvalidInputError(f"{path}: no points after the header")
    has_ids = "track_id" in (rows[0][1].keys())
    points = np.empty((len(rows), 2))
    ids = np.empty(len(rows), np.int64)
    seen: dict[int, int] = {}
    for k, (line, row) in enumerate(rows):
        try:
            points[k] = float(row["x"]), float(row["y"])
        except ValueError:
            raise InvalidInputError(f"{path} row {line}: x and y must be numbers; got x={row['x']!r}, y={row['y']!r}") from None
        if not np.isfinite(points[k]).all():
            raise InvalidInputError(f"{path} row {line}: x and y must be finite; got {row['x']}, {row['y']}")
        if has_ids:
            try:
                ids[k] = int(row["track_id"])
            except ValueError:
                raise InvalidInputError(f"{path} row {line}: track_id must be an integer; got {row['track_id']!r}") from None
            if int(ids[k]) in seen:
                raise InvalidInputError(f"{path} row {line}: track_id {ids[k]} repeats row {seen[int(ids[k])]}")
            seen[int(ids[k])] = line
    return points, (ids if has_ids else None)


def check_points_inside(points: np.ndarray, width: int, height: int, source: str) -> None:
    """Raise naming the CSV row (header = row 1) of the first point outside a ``width``×``height`` image."""
    outside = (points[:, 0] < 0) | (points[:, 0] > width - 1) | (points[:, 1] < 0) | (points[:, 1] > height - 1)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        raise InvalidInputError(
            f"{source} row {k + 2}: point ({points[k, 0]:g}, {points[k, 1]:g}) lies outside the {width}×{height} image"
        )
