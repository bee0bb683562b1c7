"""The camera file of a calibrated (perspective) reconstruction, ``cameras.csv``, written and read.

Its ``structure.csv`` and ``structure.ply`` are those of every command
(:mod:`kalmansfm.io.structure`), with the covariances in the free-network gauge
(:data:`~kalmansfm.structure.perspective.COVARIANCE_GAUGE`, also in summary.json and the PLY header).

* ``cameras.csv`` — ``frame,r11,…,r33,t1,t2,t3,rotation_std_deg,centre_std``: each registered
  frame's rotation and translation with x_cam = R X + t, and the RMS per-axis standard deviations
  of its rotation (degrees) and of its centre (world units); unregistered frames are absent.
Numbers are written as the shortest text that reads back to the same float.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ..structure.perspective import PerspectiveReconstruction
from ..structure.points import rms_std
from ._csv import csv_text, number
from .structure import _read_columns

__all__ = [
    "CAMERA_POSE_COLUMNS",
    "PerspectiveCameras",
    "perspective_cameras_csv",
    "read_perspective_cameras",
]

#: Header of ``cameras.csv``.
CAMERA_POSE_COLUMNS = ("frame", *(f"r{i}{j}" for i in range(1, 4) for j in range(1, 4)), "t1", "t2", "t3",
                       "rotation_std_deg", "centre_std")


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


def perspective_cameras_csv(frames: np.ndarray, rec: PerspectiveReconstruction) -> str:
    """``cameras.csv``: the registered frames' R, t and their standard deviations (see the module notes)."""
    rotation_std = np.degrees(rms_std(rec.camera_covariances[:, :3, :3]))
    centre_std = rms_std(rec.camera_covariances[:, 3:, 3:])
    rows = ([int(np.asarray(frames)[f]), *map(number, (*rec.rotations[f].ravel(), *rec.translations[f],
                                                       rotation_std[f], centre_std[f]))]
            for f in np.flatnonzero(rec.registered))
    return csv_text(CAMERA_POSE_COLUMNS, rows)


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
