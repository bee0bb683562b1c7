"""The files of a structure fusion: ``structure.csv`` with covariances, ``history.csv``, ``rejected.csv``, PLY.

* ``structure.csv`` — ``track_id,X,Y,Z,cov_xx,cov_xy,cov_xz,cov_yy,cov_yz,cov_zz,views,reprojection_rms,status``,
  one row per track; ``status`` is ``fused``, ``too_few_views``, ``degenerate`` or
  ``behind_camera`` (:class:`~kalmansfm.structure.pinhole.PointStatus`) and the numbers are
  ``nan`` where the point has no estimate.  Its ``track_id,X,Y,Z`` columns read like any
  ``structure.csv`` (:func:`~kalmansfm.io.structure.read_points_table`).
* ``history.csv`` — ``view,track_id,X,Y,Z,cov_xx,...,cov_zz``: each point's estimate after every
  view that observed it, from its second view on; ``view`` is that view's frame number.
* ``rejected.csv`` — ``frame,track_id,x,y,residual_px``: every observation rejected as an outlier,
  with its reprojection error at the point's final estimate.
* ``structure.ply`` — the fused points with ``track_id`` and ``uncertainty`` (√(tr Σ / 3), the RMS
  standard deviation per axis, world units) per vertex.

Numbers are written as the shortest text that reads back to the same float.
"""

from __future__ import annotations

import io

import numpy as np

from ..structure.pinhole import PointStatus
from ..structure.point_fusion import FusedStructure
from .ground_truth import _number
from .structure import structure_ply

__all__ = [
    "COVARIANCE_COLUMNS",
    "FUSED_STRUCTURE_COLUMNS",
    "HISTORY_COLUMNS",
    "REJECTED_COLUMNS",
    "fused_structure_csv",
    "fused_structure_ply",
    "history_csv",
    "point_uncertainty",
    "rejected_csv",
]

#: The upper triangle of a 3 × 3 covariance, row by row.
COVARIANCE_COLUMNS = ("cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz")
FUSED_STRUCTURE_COLUMNS = ("track_id", "X", "Y", "Z", *COVARIANCE_COLUMNS, "views", "reprojection_rms", "status")
HISTORY_COLUMNS = ("view", "track_id", "X", "Y", "Z", *COVARIANCE_COLUMNS)
REJECTED_COLUMNS = ("frame", "track_id", "x", "y", "residual_px")
_UPPER = np.triu_indices(3)


def _text(value: float) -> str:
    return "nan" if not np.isfinite(value) else _number(value)


def _rows(columns: tuple[str, ...], rows: list[list[str]]) -> str:
    out = io.StringIO()
    out.write(",".join(columns) + "\n")
    for row in rows:
        out.write(",".join(row) + "\n")
    return out.getvalue()


def point_uncertainty(covariances: np.ndarray) -> np.ndarray:
    """√(tr Σ / 3) of each (..., 3, 3) covariance: the RMS per-axis standard deviation.

    Examples
    --------
    >>> point_uncertainty(np.diag([1.0, 4.0, 4.0])[None]).tolist()
    [1.7320508075688772]
    """
    return np.sqrt(np.trace(covariances, axis1=-2, axis2=-1) / 3.0)


def fused_structure_csv(track_ids: np.ndarray, fused: FusedStructure) -> str:
    """``structure.csv`` of a fusion, one row per track.

    Examples
    --------
    >>> import numpy as np
    >>> from kalmansfm.structure.pinhole import CameraSet, project_points
    >>> from kalmansfm.structure.point_fusion import fuse
    >>> cams = CameraSet.from_pose(np.diag([500.0, 500.0, 1.0]), np.stack([np.eye(3)] * 3),
    ...                            [[0.0, 0, 0], [-1.0, 0, 0], [-2.0, 0, 0]])
    >>> obs = project_points(cams, [[0.5, 0.2, 10.0], [0.0, 0.0, -10.0]]).pixels
    >>> text = fused_structure_csv(np.array([10, 11]), fuse(obs, cams, pixel_std=0.5))
    >>> [line.split(",")[:4] + line.split(",")[-2:] for line in text.splitlines()[1:]]
    [['10', '0.5', '0.2', '10.0', '0.0', 'fused'], ['11', 'nan', 'nan', 'nan', 'nan', 'behind_camera']]
    """
    cov = fused.covariances[:, _UPPER[0], _UPPER[1]]
    rows = []
    for k, track in enumerate(np.asarray(track_ids).tolist()):
        numbers = [*fused.points[k], *cov[k]]
        rows.append([str(track), *(_text(v) for v in numbers), str(int(fused.views[k])),
                     _text(fused.reprojection_rms[k]), PointStatus(int(fused.status[k])).label])
    return _rows(FUSED_STRUCTURE_COLUMNS, rows)


def history_csv(frames: np.ndarray, track_ids: np.ndarray, fused: FusedStructure) -> str:
    """``history.csv`` of a fusion run with ``history=True`` (rows by view, then track)."""
    h = fused.history
    if h is None:
        raise ValueError("the fusion was run without history")
    cov = h.covariances[:, _UPPER[0], _UPPER[1]]
    frame_of, track_of = np.asarray(frames)[h.views].tolist(), np.asarray(track_ids)[h.points].tolist()
    rows = [[str(f), str(t), *(_text(v) for v in (*x, *c))]
            for f, t, x, c in zip(frame_of, track_of, h.estimates, cov)]
    return _rows(HISTORY_COLUMNS, rows)


def rejected_csv(frames: np.ndarray, track_ids: np.ndarray, observations: np.ndarray, fused: FusedStructure) -> str:
    """``rejected.csv``: the rejected observations, by frame then track."""
    v, n = np.nonzero(fused.rejected)
    rows = [[str(f), str(t), _text(x), _text(y), _text(r)] for f, t, (x, y), r in
            zip(np.asarray(frames)[v].tolist(), np.asarray(track_ids)[n].tolist(), observations[v, n],
                fused.residuals[v, n])]
    return _rows(REJECTED_COLUMNS, rows)


def fused_structure_ply(track_ids: np.ndarray, fused: FusedStructure, *, comment: str) -> str:
    """``structure.ply`` of the fused points, with a per-vertex ``uncertainty`` (√(tr Σ / 3))."""
    return structure_ply(track_ids, fused.points, comment=comment,
                         properties={"uncertainty": point_uncertainty(fused.covariances)})
