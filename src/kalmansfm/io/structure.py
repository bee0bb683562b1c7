"""Write a reconstruction: ``structure.csv``, ``structure.ply`` (ASCII) and ``motion.csv``.

Points or frames that could not be reconstructed (NaN) are left out of the files.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError

__all__ = ["structure_csv", "structure_ply", "motion_csv", "write_text"]


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


def structure_ply(track_ids: np.ndarray, points: np.ndarray, *, comment: str = "kalmansfm reconstruction") -> str:
    """ASCII PLY text: one vertex (``float x, y, z``, ``int track_id``) per reconstructed point.

    Opens in MeshLab, Open3D and CloudCompare.

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
    """
    ids, pts = _check(track_ids, points)
    header = [
        "ply",
        "format ascii 1.0",
        f"comment {' '.join(comment.split())}",
        f"element vertex {len(ids)}",
        "property float x",
        "property float y",
        "property float z",
        "property int track_id",
        "end_header",
    ]
    body = [f"{x:.9g} {y:.9g} {z:.9g} {i}" for i, (x, y, z) in zip(ids.tolist(), pts.tolist())]
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
    out.write("frame,i_x,i_y,i_z,j_x,j_y,j_z,t_x,t_y\n")
    for frame, values in zip(f[keep].tolist(), rows[keep].tolist()):
        out.write(f"{frame}," + ",".join(f"{v:.10g}" for v in values) + "\n")
    return out.getvalue()


def write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` to ``path`` (UTF-8) and return the path."""
    target = Path(path)
    target.write_text(text, encoding="utf-8")
    return target
