"""A reconstruction's files: ``structure.csv``, ``structure.ply`` (ASCII) and ``motion.csv``, written and read.

Points or frames that could not be reconstructed (NaN) are left out of the files.
``structure.csv`` (``track_id,X,Y,Z``) has the layout of ``ground_truth_points.csv``,
so one reader serves both.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError

MOTION_COLUMNS = ("frame", "i_x", "i_y", "i_z", "j_x", "j_y", "j_z", "t_x", "t_y")

__all__ = ["CameraMotion", "PointTable", "motion_csv", "read_motion_csv", "read_points_table", "structure_csv", "structure_ply"]


def _check(track_ids: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ids = np.asarray(track_ids)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or ids.shape != (pts.shape[0],):
        raise InvalidInputError(f"need points (P, 3) and track_ids (P,); got {pts.shape} and {ids.shape}")
    keep = np.isfinite(pts).all(axis=1)
    return ids[keep].astype(np.int64), pts[keep]


def structure_csv(track_ids: np.ndarray, points: np.ndarray) -> str:
    """``track_id,X,Y,Z`` text, one line per reconstructed point.

    Examples
    --------
    >>> print(structure_csv([3, 5], [[0.0, 1.0, 2.0], [np.nan] * 3]), end="")
    track_id,X,Y,Z
    3,0,1,2
    """
    ids, pts = _check(track_ids, points)
    out = io.StringIO()
    out.write("track_id,X,Y,Z\n")
    for i, (x, y, z) in zip(ids.tolist(), pts.tolist()):
        out.write(f"{i},{x:.10g},{y:.10g},{z:.10g}\n")
    return out.getvalue()


def structure_ply(track_ids: np.ndarray, points: np.ndarray, *, comment: str = "kalmansfm reconstruction",
                  properties: dict[str, np.ndarray] | None = None) -> str:
    """ASCII PLY text: one vertex (``float x, y, z``, ``int track_id``) per reconstructed point.

    ``properties`` adds a ``float`` vertex property per name, one value per point (e.g. an
    uncertainty).  Opens in MeshLab, Open3D and CloudCompare.

    Examples
    --------
    >>> print(structure_ply([4], [[1.0, 2.0, 3.0]]), end="")
    ply
    format ascii 1.0
    comment kalmansfm reconstruction
    element vertex 1
    property float x
    property float y
    property float z
    property int track_id
    end_header
    1 2 3 4
    >>> structure_ply([4], [[1.0, 2.0, 3.0]], properties={"uncertainty": [0.25]}).splitlines()[-3:]
    ['property float uncertainty', 'end_header', '1 2 3 4 0.25']
    """
    pts_all = np.asarray(points, dtype=np.float64)
    extra = {name: np.asarray(values, dtype=np.float64) for name, values in (properties or {}).items()}
    for name, values in extra.items():
        if values.shape != pts_all.shape[:1]:
            raise InvalidInputError(f"property {name} needs one value per point ({pts_all.shape[0]}); got {values.shape}")
    keep = np.isfinite(pts_all).all(axis=1) if pts_all.ndim == 2 else None
    ids, pts = _check(track_ids, points)
    columns = [values[keep] for values in extra.values()]
    header = [
        "ply",
        "format ascii 1.0",
        f"comment {' '.join(comment.split())}",
        f"element vertex {len(ids)}",
        "property float x",
        "property float y",
        "property float z",
        "property int track_id",
        *(f"property float {name}" for name in extra),
        "end_header",
    ]
    body = [" ".join([f"{x:.9g} {y:.9g} {z:.9g} {i}", *(f"{c[k]:.9g}" for c in columns)])
            for k, (i, (x, y, z)) in enumerate(zip(ids.tolist(), pts.tolist()))]
    return "\n".join(header + body) + "\n"


def motion_csv(frames: np.ndarray, motion: np.ndarray, translation: np.ndarray) -> str:
    """``frame,i_x,i_y,i_z,j_x,j_y,j_z,t_x,t_y`` text, one line per reconstructed frame.

    Examples
    --------
    >>> print(motion_csv([0], np.eye(3)[None, :2], np.array([[5.0, 6.0]])), end="")
    frame,i_x,i_y,i_z,j_x,j_y,j_z,t_x,t_y
    0,1,0,0,0,1,0,5,6
    """
    f = np.asarray(frames)
    m = np.asarray(motion, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    if m.shape != (f.shape[0], 2, 3) or t.shape != (f.shape[0], 2):
        raise InvalidInputError(f"need frames (F,), motion (F, 2, 3), translation (F, 2); got {f.shape}, {m.shape}, {t.shape}")
    rows = np.hstack([m.reshape(-1, 6), t])
    keep = np.isfinite(rows).all(axis=1)
    out = io.StringIO()
    out.write(",".join(MOTION_COLUMNS) + "\n")
    for frame, values in zip(f[keep].tolist(), rows[keep].tolist()):
        out.write(f"{frame}," + ",".join(f"{v:.10g}" for v in values) + "\n")
    return out.getvalue()



@dataclass(frozen=True)
class PointTable:
    """3D points keyed by track id (``structure.csv``, ``ground_truth_points.csv``)."""

    track_ids: np.ndarray  # (P,)
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

    @property
    def rows(self) -> np.ndarray:
        """(F, 2, 3) the camera rows i, j of each frame."""
        return np.stack([self.i_rows, self.j_rows], axis=1)


def _read_columns(path: Path, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
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
    except csv.Error as exc:
        raise InvalidInputError(f"{path}: not a readable CSV file ({exc})") from None
    return {c: np.asarray(v, dtype=float) for c, v in values.items()}


def read_points_table(path: str | Path) -> PointTable | None:
    """The finite rows of a ``track_id,X,Y,Z`` file; None if there are none.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "structure.csv"
    >>> _ = f.write_text(structure_csv([3, 5], [[0.0, 1.0, 2.0], [4.0, 5.0, 6.0]]))
    >>> read_points_table(f).track_ids.tolist()
    [3, 5]
    """
    cols = _read_columns(Path(path), ("track_id", "X", "Y", "Z"))
    points = np.column_stack([cols["X"], cols["Y"], cols["Z"]])
    keep = np.isfinite(points).all(axis=1) & np.isfinite(cols["track_id"])
    if not keep.any():
        return None
    return PointTable(cols["track_id"][keep].astype(np.int64), points[keep])


def read_motion_csv(path: str | Path) -> CameraMotion | None:
    """The frames of ``motion.csv`` with finite, non-degenerate camera rows; None if there are none."""
    cols = _read_columns(Path(path), MOTION_COLUMNS)
    i_rows = np.column_stack([cols["i_x"], cols["i_y"], cols["i_z"]])
    j_rows = np.column_stack([cols["j_x"], cols["j_y"], cols["j_z"]])
    translations = np.column_stack([cols["t_x"], cols["t_y"]])
    with np.errstate(invalid="ignore", over="ignore"):
        keep = (
            np.isfinite(np.hstack([i_rows, j_rows, translations, cols["frame"][:, None]])).all(axis=1)
            & (np.linalg.norm(i_rows, axis=1) > 0)
            & (np.linalg.norm(np.cross(i_rows, j_rows), axis=1) > 0)
        )
    if not keep.any():
        return None
    return CameraMotion(cols["frame"][keep].astype(np.int64), i_rows[keep], j_rows[keep], translations[keep])
