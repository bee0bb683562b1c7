"""A reconstruction's files: ``structure.csv``, ``structure.ply`` (ASCII) and ``motion.csv``, written and read.

``structure.csv`` has one layout for every command (``reconstruct``, ``demo``, ``fuse``,
``reconstruct --camera perspective``)::

    track_id,X,Y,Z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz,views,reprojection_rms,status

one row per track: its point, the upper triangle of the point's 3 × 3 covariance (the units
and gauge of the reconstruction: pixels² in the factorization's gauge, world units² for a
fusion with known cameras, the free-network gauge of a perspective run), the views that
were used, the RMS length of the point's reprojection errors in pixels, and its status
(:class:`~kalmansfm.structure.PointStatus`: ``ok``, ``too_few_views``, ``degenerate``,
``behind_camera`` or ``unreliable``).  A cell is empty where there is no value: the numbers
of a track without a point, a reprojection RMS the method does not give.

The plain layout ``track_id,X,Y,Z`` (``ground_truth_points.csv``, points from other tools)
is read by the same reader; it lists only the points that have coordinates.  Numbers are
written as the shortest text that reads back to the same float.

``structure.ply`` holds the points that have coordinates, with ``track_id`` and any
per-vertex properties given (the commands add ``uncertainty``, √(tr Σ / 3)).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._validation import LabelledEnum
from ..errors import InvalidInputError
from ..structure.points import PointStatus
from ._csv import csv_text, number, read_rows, where

MOTION_COLUMNS = ("frame", "i_x", "i_y", "i_z", "j_x", "j_y", "j_z", "t_x", "t_y")
#: The plain layout: a point per track (ground truth, other tools).
POINT_COLUMNS = ("track_id", "X", "Y", "Z")
#: The upper triangle of a point's covariance, row by row.
COVARIANCE_COLUMNS = ("cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")
#: The layout of every ``structure.csv`` a command writes.
STRUCTURE_COLUMNS = (*POINT_COLUMNS, *COVARIANCE_COLUMNS, "views", "reprojection_rms", "status")
_UPPER = np.triu_indices(3)

__all__ = [
    "COVARIANCE_COLUMNS",
    "POINT_COLUMNS",
    "STRUCTURE_COLUMNS",
    "CameraMotion",
    "PointTable",
    "motion_csv",
    "read_motion_csv",
    "read_points_table",
    "structure_csv",
    "structure_ply",
]


def _check(track_ids: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The ids (int64) and (P, 3) points, checked against each other."""
    ids = np.asarray(track_ids)
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or ids.shape != (pts.shape[0],):
        raise InvalidInputError(f"need points (P, 3) and track_ids (P,); got {pts.shape} and {ids.shape}")
    return ids.astype(np.int64), pts


def structure_csv(
    track_ids: np.ndarray,
    points: np.ndarray,
    *,
    covariances: np.ndarray | None = None,
    views: np.ndarray | None = None,
    status: np.ndarray | None = None,
    reprojection_rms: np.ndarray | None = None,
) -> str:
    """``structure.csv`` text: every track with its point, covariance, views, reprojection RMS and status.

    Parameters
    ----------
    track_ids : (P,) int; points : (P, 3) float, NaN for a track without a point.
    covariances : (P, 3, 3), views : (P,), status : (P,) :class:`~kalmansfm.structure.PointStatus`
        codes — given together (the full layout, a row per track), or none of them (the plain
        ``track_id,X,Y,Z`` layout of the points that have coordinates).
    reprojection_rms : (P,) pixels, optional with the full layout (empty cells without it).

    Examples
    --------
    >>> print(structure_csv([3, 5], [[0.0, 1.0, 2.0], [np.nan] * 3]), end="")
    track_id,X,Y,Z
    3,0.0,1.0,2.0
    >>> print(structure_csv([3, 5], [[0.0, 1.0, 2.5], [np.nan] * 3], covariances=[np.eye(3) * 4, np.full((3, 3), np.nan)],
    ...                     views=[7, 1], status=[0, 1], reprojection_rms=[0.25, np.nan]), end="")
    track_id,X,Y,Z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz,views,reprojection_rms,status
    3,0.0,1.0,2.5,4.0,0.0,0.0,4.0,0.0,4.0,7,0.25,ok
    5,,,,,,,,,,1,,too_few_views
    """
    ids, pts = _check(track_ids, points)
    given = [a is not None for a in (covariances, views, status)]
    if not any(given):
        if reprojection_rms is not None:
            raise InvalidInputError("structure_csv: reprojection_rms needs covariances, views and status")
        keep = np.isfinite(pts).all(axis=1)
        return csv_text(POINT_COLUMNS, ([i, *map(number, p)] for i, p in zip(ids[keep].tolist(), pts[keep])))
    if not all(given):
        raise InvalidInputError("structure_csv needs covariances, views and status together, or none of them")
    n = len(ids)
    cov = np.asarray(covariances, dtype=np.float64)
    seen = np.asarray(views)
    codes = np.asarray(status)
    rms = np.full(n, np.nan) if reprojection_rms is None else np.asarray(reprojection_rms, dtype=np.float64)
    if cov.shape != (n, 3, 3) or seen.shape != (n,) or codes.shape != (n,) or rms.shape != (n,):
        raise InvalidInputError(
            f"need covariances ({n}, 3, 3), views ({n},), status ({n},) and reprojection_rms ({n},); "
            f"got {cov.shape}, {seen.shape}, {codes.shape}, {rms.shape}"
        )
    words = [PointStatus(int(c)).label for c in codes]
    numbers = np.hstack([pts, cov[:, _UPPER[0], _UPPER[1]]])
    rows = ([i, *map(number, row), int(k), number(r), w]
            for i, row, k, r, w in zip(ids.tolist(), numbers, seen.tolist(), rms, words))
    return csv_text(STRUCTURE_COLUMNS, rows)


def structure_ply(track_ids: np.ndarray, points: np.ndarray, *, comment: str = "kalmansfm reconstruction",
                  properties: dict[str, np.ndarray] | None = None) -> str:
    """ASCII PLY text: one vertex (``float x, y, z``, ``int track_id``) per point that has coordinates.

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
    ids, pts = _check(track_ids, points)
    keep = np.isfinite(pts).all(axis=1)
    extra = {name: np.asarray(values, dtype=np.float64) for name, values in (properties or {}).items()}
    for name, values in extra.items():
        if values.shape != keep.shape:
            raise InvalidInputError(f"property {name} needs one value per point ({keep.shape[0]}); got {values.shape}")
    columns = [values[keep] for values in extra.values()]
    ids, pts = ids[keep], pts[keep]
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

    Numbers are written as every CSV writer of ``io`` writes them (:func:`._csv.number`, the
    shortest text that reads back as the same float); older files, written with 10
    significant digits, are read as well.

    Examples
    --------
    >>> print(motion_csv([0], np.eye(3)[None, :2], np.array([[5.0, 6.0]])), end="")
    frame,i_x,i_y,i_z,j_x,j_y,j_z,t_x,t_y
    0,1.0,0.0,0.0,0.0,1.0,0.0,5.0,6.0
    """
    f = np.asarray(frames)
    m = np.asarray(motion, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    if m.shape != (f.shape[0], 2, 3) or t.shape != (f.shape[0], 2):
        raise InvalidInputError(f"need frames (F,), motion (F, 2, 3), translation (F, 2); got {f.shape}, {m.shape}, {t.shape}")
    rows = np.hstack([m.reshape(-1, 6), t])
    keep = np.isfinite(rows).all(axis=1)
    return csv_text(MOTION_COLUMNS, ([frame, *(number(v) for v in values)]
                                     for frame, values in zip(f[keep].tolist(), rows[keep].tolist())))


@dataclass(frozen=True)
class PointTable:
    """3D points keyed by track id (``structure.csv``, ``ground_truth_points.csv``): the rows with coordinates.

    ``covariances`` (P, 3, 3), ``views`` (P,), ``reprojection_rms`` (P,) and ``status`` (P,)
    :class:`~kalmansfm.structure.PointStatus` codes are None when the file does not give them.
    """

    track_ids: np.ndarray  # (P,)
    points: np.ndarray  # (P, 3)
    covariances: np.ndarray | None = None
    views: np.ndarray | None = None
    status: np.ndarray | None = None
    reprojection_rms: np.ndarray | None = None

    @property
    def reliable(self) -> np.ndarray:
        """(P,) True for the points with status ``ok`` (all of them when the file gives no status)."""
        if self.status is None:
            return np.ones(len(self.track_ids), bool)
        return self.status == PointStatus.OK


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


def _read_columns(
    path: Path, columns: tuple[str, ...], optional: tuple[str, ...] = (),
    words: dict[str, type[LabelledEnum]] | None = None,
) -> dict[str, np.ndarray]:
    """Columns of a CSV file with a header row, checked row by row.

    ``columns`` must be there; ``optional`` ones are read when the header has them.  Columns
    are numbers (an empty cell is NaN: no value), except those named in ``words``, which
    hold a label of the status enum given (read as its code).
    """
    words = words or {}
    header, _, rows = read_rows(path, required=columns, allow_no_rows=True)
    index = {name: i for i, name in enumerate(header)}
    wanted = [*columns, *(c for c in optional if c in index)]
    values: dict[str, list[float]] = {c: [] for c in wanted}
    for line, fields in rows:
        for c in wanted:
            cell = fields[index[c]]
            try:
                if c in words:
                    values[c].append(words[c].from_label(cell).value)  # type: ignore[arg-type]
                else:
                    values[c].append(np.nan if cell == "" else float(cell))
            except (TypeError, ValueError, KeyError, AttributeError):
                expected = "one of " + ", ".join(s.label for s in words[c]) if c in words else "a number"
                raise InvalidInputError(f"{where(path, line)}: column {c!r} must be {expected}; got {cell!r}") from None
    return {c: np.asarray(v, dtype=float) for c, v in values.items()}


def read_points_table(path: str | Path) -> PointTable | None:
    """The rows with coordinates of a ``structure.csv`` (either layout); None if there are none.

    Of the columns after ``track_id,X,Y,Z``, those the file has are read (the covariance
    when all six ``cov_*`` are there).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "structure.csv"
    >>> _ = f.write_text(structure_csv([3, 5, 8], [[0.0, 1.0, 2.0], [4.0, 5.0, 6.0], [np.nan] * 3],
    ...                                covariances=np.stack([np.eye(3)] * 3), views=[9, 2, 1], status=[0, 4, 1]))
    >>> table = read_points_table(f)
    >>> table.track_ids.tolist(), table.views.tolist(), table.reliable.tolist(), table.covariances.shape
    ([3, 5], [9, 2], [True, False], (2, 3, 3))
    """
    more = (*COVARIANCE_COLUMNS, "views", "reprojection_rms", "status")
    cols = _read_columns(Path(path), POINT_COLUMNS, more, {"status": PointStatus})
    points = np.column_stack([cols["X"], cols["Y"], cols["Z"]])
    keep = np.isfinite(points).all(axis=1) & np.isfinite(cols["track_id"])
    if not keep.any():
        return None
    found: dict[str, np.ndarray] = {}
    if all(c in cols for c in COVARIANCE_COLUMNS):
        upper = np.column_stack([cols[c] for c in COVARIANCE_COLUMNS])[keep]
        covariances = np.empty((len(upper), 3, 3))
        covariances[:, _UPPER[0], _UPPER[1]] = upper
        covariances[:, _UPPER[1], _UPPER[0]] = upper
        found["covariances"] = covariances
    if "views" in cols:
        found["views"] = np.nan_to_num(cols["views"][keep]).astype(np.int64)
    if "status" in cols:
        found["status"] = cols["status"][keep].astype(np.int8)
    if "reprojection_rms" in cols:
        found["reprojection_rms"] = cols["reprojection_rms"][keep]
    return PointTable(cols["track_id"][keep].astype(np.int64), points[keep], **found)


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
