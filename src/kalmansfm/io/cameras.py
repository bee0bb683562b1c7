"""Known cameras in and out: the cameras CSV, and tracks matched to its frames.

Two layouts are read, told apart by the header:

* ``frame,p11,p12,p13,p14,p21,...,p34`` — each frame's 3 × 4 projection matrix,
  row-major, mapping homogeneous world points to pixels (x = column, y = row);
* ``frame,fx,fy,cx,cy,skew,r11,...,r33,t1,t2,t3`` — intrinsics
  K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]], rotation R (row-major) and
  translation t with x_cam = R X + t, so P = K [R | t].

The intrinsics + pose layout is also what ``kalmansfm reconstruct --camera perspective``
(and ``demo --camera perspective``) writes as its ``cameras.csv``, one row per registered
frame with the K it used, followed by two optional columns that :func:`read_cameras`
ignores: ``rotation_std_deg``, the RMS per-axis standard deviation of the camera's
rotation in degrees, and ``centre_std``, that of its centre in world units (both in the
reconstruction's free-network gauge).  Such a file can be given to ``kalmansfm fuse --cameras``
as it is.  Writers: :func:`cameras_csv` (projection-matrix layout) and
:func:`pose_cameras_csv` (intrinsics + pose, optionally with the two standard deviations);
numbers are the shortest text that reads back to the same float.

Other columns are ignored; comments, blank lines and the rest of the rules every CSV reader
shares are in docs/formats.md (:func:`._csv.read_rows`).  Every problem
raises :class:`~kalmansfm.InvalidInputError` naming the file and the 1-based line:
missing columns, a frame given twice, a non-number or non-finite entry, a matrix
that is not a camera (singular left 3 × 3 block, fx or fy <= 0, R not a rotation).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError, NotEnoughDataError
from ..structure.geometry.pinhole import CameraSet, intrinsic_matrices
from ._csv import csv_text, number, read_rows, where
from .tracks import _floats, _indices

__all__ = [
    "MATRIX_COLUMNS",
    "POSE_COLUMNS",
    "POSE_STD_COLUMNS",
    "CameraObservations",
    "cameras_csv",
    "match_cameras",
    "pose_cameras_csv",
    "read_cameras",
]

#: Header of the projection-matrix layout.
MATRIX_COLUMNS = ("frame",) + tuple(f"p{i}{j}" for i in range(1, 4) for j in range(1, 5))
#: Header of the intrinsics + pose layout.
POSE_COLUMNS = ("frame", "fx", "fy", "cx", "cy", "skew") + tuple(f"r{i}{j}" for i in range(1, 4)
                                                                 for j in range(1, 4)) + ("t1", "t2", "t3")
#: The optional columns after :data:`POSE_COLUMNS` in the cameras.csv of a perspective reconstruction.
POSE_STD_COLUMNS = ("rotation_std_deg", "centre_std")

# Same limits as CameraSet (a left block this close to singular is not a camera).
_SINGULAR_RATIO = 1e-12
_ROTATION_TOLERANCE = 1e-6


def read_cameras(path: str | os.PathLike[str]) -> CameraSet:
    """Read a cameras CSV (either layout, see the module notes).

    Returns
    -------
    CameraSet
        One camera per row, in the order of the file.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "cameras.csv"
    >>> header = "frame,fx,fy,cx,cy,skew,r11,r12,r13,r21,r22,r23,r31,r32,r33,t1,t2,t3"
    >>> _ = f.write_text(header + "\\n4,500,500,320,240,0,1,0,0,0,1,0,0,0,1,0,0,5\\n")
    >>> cams = read_cameras(f)
    >>> cams.frames.tolist(), cams.matrices[0, 0].tolist()
    ([4], [500.0, 0.0, 320.0, 1600.0])
    """
    file = Path(path)
    header, header_line, rows = read_rows(file, f"{','.join(MATRIX_COLUMNS)} or {','.join(POSE_COLUMNS)}")
    column = {name: i for i, name in enumerate(header)}
    if all(c in column for c in MATRIX_COLUMNS):
        layout = MATRIX_COLUMNS
    elif all(c in column for c in POSE_COLUMNS):
        layout = POSE_COLUMNS
    else:
        missing_p = [c for c in MATRIX_COLUMNS if c not in column]
        missing_k = [c for c in POSE_COLUMNS if c not in column]
        closer, missing = ("projection-matrix", missing_p) if len(missing_p) <= len(missing_k) else \
            ("intrinsics + pose", missing_k)
        raise InvalidInputError(f"{where(file, header_line)}: header lacks column(s) {', '.join(missing)} "
                                f"of the {closer} layout; got {','.join(header)}")
    table = np.array([row for _, row in rows], dtype=object)
    lines = np.array([n for n, _ in rows])
    frames = _indices(file, table[:, column["frame"]], lines, "frame")
    values = np.stack([_floats(file, table[:, column[c]], lines, c) for c in layout[1:]], axis=1)
    _, first, counts = np.unique(frames, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup = frames[first[counts > 1][0]]
        at = lines[frames == dup]
        raise InvalidInputError(f"{where(file, at[0], at[1])}: frame {dup} has two cameras")
    if layout is MATRIX_COLUMNS:
        P = values.reshape(-1, 3, 4)
    else:
        fx, fy, cx, cy, skew = values[:, :5].T
        bad = ~((fx > 0) & (fy > 0))
        if bad.any():
            i = int(np.argmax(bad))
            raise InvalidInputError(f"{where(file, lines[i])}: fx and fy must be > 0 (pixels); got {fx[i]}, {fy[i]}")
        K = intrinsic_matrices(fx, fy, cx, cy, skew)
        R = values[:, 5:14].reshape(-1, 3, 3)
        off = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
        bad = ~(off <= _ROTATION_TOLERANCE)
        if bad.any():
            i = int(np.argmax(bad))
            raise InvalidInputError(f"{where(file, lines[i])}: r11..r33 is not a rotation (R Rᵀ differs from I "
                                    f"by {off[i]:.3g})")
        P = K @ np.concatenate([R, values[:, 14:17, None]], axis=2)
    sv = np.linalg.svd(P[:, :, :3], compute_uv=False)
    singular = ~(sv[:, -1] > _SINGULAR_RATIO * sv[:, 0])
    if singular.any():
        i = int(np.argmax(singular))
        raise InvalidInputError(f"{where(file, lines[i])}: frame {frames[i]}: not a camera, the left 3x3 block of "
                                f"its projection matrix is not invertible")
    return CameraSet(P, frames)


def cameras_csv(cameras: CameraSet) -> str:
    """The cameras as CSV text in the projection-matrix layout (shortest text that reads back exactly).

    Examples
    --------
    >>> print(cameras_csv(CameraSet.from_matrices(np.eye(3, 4)[None], frames=[2])).splitlines()[1])
    2,1.0,0.0,0.0,0.0,0.0,1.0,0.0,0.0,0.0,0.0,1.0,0.0
    """
    lines = [",".join(MATRIX_COLUMNS)]
    for frame, P in zip(cameras.frames, cameras.matrices):
        lines.append(",".join([str(int(frame))] + [number(x) for x in P.ravel()]))
    return "\n".join(lines) + "\n"


def pose_cameras_csv(frames: object, intrinsics: object, rotations: object, translations: object, *,
                     rotation_std_deg: object | None = None, centre_std: object | None = None) -> str:
    """Cameras as CSV text in the intrinsics + pose layout, P = K [R | t] (see the module notes).

    Parameters
    ----------
    frames : (n,) int — frame number of each camera.
    intrinsics : (n, 3, 3) — K of each camera; fx, fy, cx, cy and skew are written (K[2] is [0, 0, 1]).
    rotations : (n, 3, 3) — R, x_cam = R X + t.
    translations : (n, 3) — t.
    rotation_std_deg, centre_std : (n,), optional — given together: the columns
        ``rotation_std_deg,centre_std`` are appended (RMS per-axis standard deviation of
        the rotation in degrees and of the centre in world units); a non-finite value is an empty cell.

    Returns
    -------
    str
        Header and one row per camera; the K, R and t read back exactly with :func:`read_cameras`.

    Examples
    --------
    >>> K = np.array([[[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]])
    >>> text = pose_cameras_csv([4], K, np.eye(3)[None], [[0.0, 0.0, 5.0]], rotation_std_deg=[0.1],
    ...                         centre_std=[0.02])
    >>> text.splitlines()[0].endswith("t1,t2,t3,rotation_std_deg,centre_std")
    True
    >>> text.splitlines()[1]
    '4,500.0,500.0,320.0,240.0,0.0,1.0,0.0,0.0,0.0,1.0,0.0,0.0,0.0,1.0,0.0,0.0,5.0,0.1,0.02'
    """
    frame = np.asarray(frames).ravel()
    K = np.asarray(intrinsics, dtype=np.float64)
    R = np.asarray(rotations, dtype=np.float64)
    t = np.asarray(translations, dtype=np.float64)
    n = len(frame)
    if K.shape != (n, 3, 3) or R.shape != (n, 3, 3) or t.shape != (n, 3):
        raise InvalidInputError(f"pose_cameras_csv needs (n, 3, 3) intrinsics and rotations and (n, 3) translations "
                                f"for the {n} frames; got {K.shape}, {R.shape}, {t.shape}")
    if (rotation_std_deg is None) != (centre_std is None):
        raise InvalidInputError("rotation_std_deg and centre_std are written together: give both or neither")
    columns = [K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 0, 1], *R.reshape(n, 9).T, *t.T]
    header = POSE_COLUMNS
    if rotation_std_deg is not None:
        stds = [np.asarray(v, dtype=np.float64).ravel() for v in (rotation_std_deg, centre_std)]
        if any(v.shape != (n,) for v in stds):
            raise InvalidInputError(f"rotation_std_deg and centre_std need one value per frame ({n}); "
                                    f"got {stds[0].shape}, {stds[1].shape}")
        columns += stds
        header = POSE_COLUMNS + POSE_STD_COLUMNS
    rows = ([str(int(f)), *(number(c[i]) for c in columns)] for i, f in enumerate(frame))
    return csv_text(header, rows)


@dataclass(frozen=True)
class CameraObservations:
    """Track positions arranged by camera: the input of :func:`~kalmansfm.structure.fusion.fuse`.

    Attributes
    ----------
    cameras : CameraSet — the cameras of the frames that have observations, in frame order.
    observations : (V, N, 2) — track positions in those frames, NaN where not observed.
    track_ids : (N,) — the track of each column.
    frames_without_camera : (k,) int — frames with observations but no camera (skipped).
    """

    cameras: CameraSet
    observations: np.ndarray
    track_ids: np.ndarray
    frames_without_camera: np.ndarray


def match_cameras(positions: np.ndarray, frames: np.ndarray, track_ids: np.ndarray,
                  cameras: CameraSet, source: str = "the tracks") -> CameraObservations:
    """Keep the frames that have a camera, in frame order, and drop frames without one.

    Parameters
    ----------
    positions : (F, N, 2) — observed positions, NaN where none (e.g. :meth:`~kalmansfm.tracking.Tracks.observations`).
    frames : (F,) int — frame number of each row of ``positions``.
    track_ids : (N,) int.
    cameras : CameraSet.
    source : how the tracks are named in the error message (e.g. their file).

    Raises
    ------
    NotEnoughDataError
        Fewer than 2 frames of the tracks have a camera.

    Examples
    --------
    >>> cams = CameraSet.from_matrices(np.stack([np.eye(3, 4)] * 2), frames=[0, 2])
    >>> m = match_cameras(np.zeros((3, 1, 2)), np.array([0, 1, 2]), np.array([5]), cams)
    >>> m.cameras.frames.tolist(), m.frames_without_camera.tolist()
    ([0, 2], [1])
    """
    view = cameras.view_of(frames)
    observed = np.isfinite(positions).all(axis=2).any(axis=1)
    missing = np.asarray(frames)[(view < 0) & observed]
    keep = np.flatnonzero(view >= 0)
    if keep.size < 2:
        raise NotEnoughDataError(f"{source}: {keep.size} of its {len(frames)} frame(s) have a camera; "
                                 f"fusing needs >= 2 (camera frames: {_frame_list(cameras.frames)})")
    order = keep[np.argsort(np.asarray(frames)[keep], kind="stable")]
    return CameraObservations(cameras.subset(view[order]), positions[order], np.asarray(track_ids), missing)


def _frame_list(frames: np.ndarray, shown: int = 6) -> str:
    head = ", ".join(str(int(f)) for f in frames[:shown])
    return head + (f", ... ({len(frames)} in all)" if len(frames) > shown else "")
