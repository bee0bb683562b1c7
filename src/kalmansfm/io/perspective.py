"""The files of a calibrated (perspective) reconstruction: ``structure.csv``, ``cameras.csv``, PLY.

* ``structure.csv`` — the columns of a fusion's structure
  (:data:`~kalmansfm.io.fusion.FUSED_STRUCTURE_COLUMNS`:
  ``track_id,X,Y,Z,cov_xx,…,cov_zz,views,reprojection_rms,status``), one row per track;
  ``status`` is ``reconstructed``, ``too_few_views`` or ``degenerate``
  (:class:`~kalmansfm.structure.perspective.ReconstructedPointStatus`), numbers ``nan`` where the
  track has no point.  The covariances are in the free-network gauge
  (:data:`~kalmansfm.structure.perspective.COVARIANCE_GAUGE`, also in summary.json and the PLY header).
* ``cameras.csv`` — ``frame,r11,…,r33,t1,t2,t3,rotation_std_deg,centre_std``: each registered
  frame's rotation and translation with x_cam = R X + t, and the RMS per-axis standard deviations
  of its rotation (degrees) and of its centre (world units); unregistered frames are absent.
* ``structure.ply`` — the points with ``track_id`` and ``uncertainty`` (√(tr Σ / 3)) per vertex.

Numbers are written as the shortest text that reads back to the same float.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ..structure.perspective import COVARIANCE_GAUGE, PerspectiveReconstruction, ReconstructedPointStatus
from .fusion import COVARIANCE_COLUMNS, FUSED_STRUCTURE_COLUMNS, _rows, _text, point_uncertainty
from .structure import _read_columns, structure_ply

__all__ = [
    "CAMERA_POSE_COLUMNS",
    "PerspectiveCameras",
    "perspective_cameras_csv",
    "perspective_structure_csv",
    "perspective_structure_ply",
    "read_perspective_cameras",
    "read_point_covariances",
]

#: Header of ``cameras.csv``.
CAMERA_POSE_COLUMNS = ("frame", *(f"r{i}{j}" for i in range(1, 4) for j in range(1, 4)), "t1", "t2", "t3",
                       "rotation_std_deg", "centre_std")
_UPPER = np.triu_indices(3)


@dataclass(frozen=True)
class PerspectiveCameras:
    """The registered cameras of ``cameras.csv``.

    Attributes
    ----------
    frames : (n,) int64.
    rotations : (n, 3, 3), x_cam = R X + t.
    translations : (n, 3).
    """

    frames: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray

    @property
    def centres(self) -> np.ndarray:
        """(n, 3) camera centres -Rᵀ t."""
        return -np.einsum("nji,nj->ni", self.rotations, self.translations)


def perspective_structure_csv(track_ids: np.ndarray, rec: PerspectiveReconstruction) -> str:
    """``structure.csv`` of a perspective reconstruction, one row per track.

    Examples
    --------
    >>> from kalmansfm.scenes.perspective import perspective_scene
    >>> from kalmansfm.structure.perspective import reconstruct_perspective
    >>> s = perspective_scene(frames=4, points=60, seed=1)
    >>> text = perspective_structure_csv(np.arange(60), reconstruct_perspective(s.observations, s.intrinsics))
    >>> text.splitlines()[0].split(",")[-3:], text.splitlines()[1].split(",")[-1]
    (['views', 'reprojection_rms', 'status'], 'reconstructed')
    """
    cov = rec.point_covariances[:, _UPPER[0], _UPPER[1]]
    rows = []
    for k, track in enumerate(np.asarray(track_ids).tolist()):
        numbers = [*rec.points[k], *cov[k]]
        rows.append([str(track), *(_text(v) for v in numbers), str(int(rec.views[k])),
                     _text(rec.point_reprojection_rms[k]), ReconstructedPointStatus(int(rec.point_status[k])).label])
    return _rows(FUSED_STRUCTURE_COLUMNS, rows)


def perspective_cameras_csv(frames: np.ndarray, rec: PerspectiveReconstruction) -> str:
    """``cameras.csv``: the registered frames' R, t and their standard deviations (see the module notes)."""
    rows = []
    rot_var = np.trace(rec.camera_covariances[:, :3, :3], axis1=1, axis2=2) / 3.0
    centre_var = np.trace(rec.camera_covariances[:, 3:, 3:], axis1=1, axis2=2) / 3.0
    for f in np.flatnonzero(rec.registered):
        numbers = [*rec.rotations[f].ravel(), *rec.translations[f], np.degrees(np.sqrt(rot_var[f])),
                   np.sqrt(centre_var[f])]
        rows.append([str(int(np.asarray(frames)[f])), *(_text(v) for v in numbers)])
    return _rows(CAMERA_POSE_COLUMNS, rows)


def perspective_structure_ply(track_ids: np.ndarray, rec: PerspectiveReconstruction, *, comment: str) -> str:
    """``structure.ply`` with a per-vertex ``uncertainty`` (√(tr Σ / 3)); the header names the gauge."""
    return structure_ply(track_ids, rec.points, comment=f"{comment}; covariances in the {COVARIANCE_GAUGE}",
                         properties={"uncertainty": point_uncertainty(rec.point_covariances)})


def read_perspective_cameras(path: str | os.PathLike[str]) -> PerspectiveCameras:
    """Read ``cameras.csv`` (the columns ``frame,r11,…,r33,t1,t2,t3``; the others are optional).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "cameras.csv"
    >>> _ = f.write_text(",".join(CAMERA_POSE_COLUMNS[:13]) + "\\n3,1,0,0,0,1,0,0,0,1,0,0,2\\n")
    >>> read_perspective_cameras(f).centres.tolist()
    [[-0.0, -0.0, -2.0]]
    """
    file = Path(path)
    cols = _read_columns(file, CAMERA_POSE_COLUMNS[:13])
    R = np.stack([cols[c] for c in CAMERA_POSE_COLUMNS[1:10]], axis=1).reshape(-1, 3, 3)
    t = np.stack([cols["t1"], cols["t2"], cols["t3"]], axis=1)
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        raise InvalidInputError(f"{file}: camera rotations and translations must be finite")
    return PerspectiveCameras(cols["frame"].astype(np.int64), R, t)


def read_point_covariances(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray] | None:
    """Track ids and (P, 3, 3) covariances of the finite rows of a ``structure.csv`` that has ``cov_*`` columns.

    None when the file has no covariance columns (a factorization's structure.csv).
    """
    file = Path(path)
    with file.open(encoding="utf-8") as handle:
        header = handle.readline().strip().split(",")
    if not all(c in header for c in COVARIANCE_COLUMNS):
        return None
    cols = _read_columns(file, ("track_id", "X", *COVARIANCE_COLUMNS))
    keep = np.isfinite(cols["X"]) & np.isfinite(cols["track_id"])
    upper = np.stack([cols[c][keep] for c in COVARIANCE_COLUMNS], axis=1)
    cov = np.zeros((int(keep.sum()), 3, 3))
    cov[:, _UPPER[0], _UPPER[1]] = upper
    cov[:, _UPPER[1], _UPPER[0]] = upper
    return cols["track_id"][keep].astype(np.int64), cov
