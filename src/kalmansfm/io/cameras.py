"""Known cameras in and out: the cameras CSV, COLMAP models as known cameras, and tracks matched to their frames.

Two CSV layouts are read, told apart by the header:

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

A COLMAP sparse model (its folder, a folder holding ``sparse/0``, or one of its files; text or
binary, :mod:`kalmansfm.io.colmap`) is read as known cameras too: each registered image is a
camera, matched to a frame by its name when the caller gives the frames' names, else by order
(the images' names in natural order are frames 0, 1, …); :class:`KnownCameras` says which.

What is refused, with one line naming the file and the line: missing columns (the message names
both layouts), a frame given twice, a non-number or non-finite entry, a matrix that is not a
camera (singular left 3 × 3 block, K that is not a camera's:
:func:`~kalmansfm.structure.geometry.camera_checks.intrinsics_problem`), R that is not a rotation
(a reflection, or farther from orthonormal than rounding explains).  R orthonormal only to
rounding (up to 1e-3, e.g. printed to six digits) is replaced by the nearest rotation, with a
warning saying how far it was off.  Projection-matrix entries are not pixels and have no bound
beyond being finite (georeferenced cameras have p14 ≈ 1e8).  Comments, blank lines and the rest of
the rules every CSV reader shares are in docs/formats.md (:func:`._csv.read_rows`).
"""

from __future__ import annotations

import os
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError, KalmanSfmWarning, NotEnoughDataError
from ..structure.geometry.camera_checks import (
    ROTATION_ROUNDED,
    check_rotations,
    intrinsics_problem,
    projection_scale_problem,
)
from ..structure.geometry.pinhole import CameraSet, intrinsic_matrices
from ..structure.reconstruction import Observations
from ._csv import csv_text, index_column, number, read_rows, where
from .colmap import MODEL_PARTS, locate_colmap_model, read_colmap_model, read_skew
from .frames import natural_key
from .tracks import TrackObservations

__all__ = [
    "MATRIX_COLUMNS",
    "POSE_COLUMNS",
    "POSE_STD_COLUMNS",
    "CameraObservations",
    "KnownCameras",
    "cameras_csv",
    "is_colmap_path",
    "match_camera_observations",
    "match_cameras",
    "match_image_names",
    "pose_cameras_csv",
    "read_cameras",
    "read_known_cameras",
]

#: Header of the projection-matrix layout.
MATRIX_COLUMNS = ("frame",) + tuple(f"p{i}{j}" for i in range(1, 4) for j in range(1, 5))
#: Header of the intrinsics + pose layout.
POSE_COLUMNS = ("frame", "fx", "fy", "cx", "cy", "skew") + tuple(f"r{i}{j}" for i in range(1, 4)
                                                                 for j in range(1, 4)) + ("t1", "t2", "t3")
#: The optional columns after :data:`POSE_COLUMNS` in the cameras.csv of a perspective reconstruction.
POSE_STD_COLUMNS = ("rotation_std_deg", "centre_std")
#: The layouts a cameras CSV may have, by the name its messages use.
CAMERA_LAYOUTS = {"projection-matrix": MATRIX_COLUMNS, "intrinsics + pose": POSE_COLUMNS}
#: The largest cameras CSV read (a row is under 500 bytes: this is 10⁵ cameras and more).
MAX_CAMERAS_BYTES = 64 << 20

# Same limit as CameraSet (a left block this close to singular is not a camera).
_SINGULAR_RATIO = 1e-12


@dataclass(frozen=True)
class KnownCameras:
    """Cameras read from a file, and how their frames were found.

    Attributes
    ----------
    cameras : CameraSet — one camera per frame.
    source_format : str — ``"projection-matrix CSV"``, ``"intrinsics + pose CSV"``, ``"COLMAP text"``
        or ``"COLMAP binary"``.
    matched_by : str — how cameras got their frame: ``"frame column"`` (CSV), ``"name"`` (a COLMAP
        image name equal to a frame's name), ``"frame number"`` (names ``frame_N.ext``, as ``kalmansfm
        export`` writes them) or ``"order"`` (COLMAP images in natural name order are frames 0, 1, …).
    image_names : tuple of str — the COLMAP image name of each camera (empty for a CSV).
    warnings : tuple of str — what was accepted but deserves attention (rotations repaired).
    """

    cameras: CameraSet
    source_format: str
    matched_by: str
    image_names: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()


def is_colmap_path(path: str | os.PathLike[str]) -> bool:
    """True when ``path`` names a COLMAP model rather than a CSV: a folder, or a ``.bin`` / model ``.txt`` file.

    Examples
    --------
    >>> is_colmap_path("sparse/0/cameras.txt"), is_colmap_path("run/cameras.csv")
    (True, False)
    """
    given = Path(path)
    return given.is_dir() or given.suffix == ".bin" or (given.suffix == ".txt" and given.stem in MODEL_PARTS)


def read_known_cameras(path: str | os.PathLike[str],
                       frame_names: Sequence[str] | Mapping[int, str] | None = None) -> KnownCameras:
    """Read known cameras from a cameras CSV (either layout) or a COLMAP model (see the module notes).

    Parameters
    ----------
    path : the CSV, or the COLMAP model (folder or one of its files).
    frame_names : optional, COLMAP only — the name of each frame (a sequence: frame i is
        ``frame_names[i]``; or a frame → name mapping), to match images by name: equal names, or
        equal file names when the image's name has folders.  Without it, images are frames 0, 1, …
        in the natural order of their names.

    Returns
    -------
    KnownCameras

    Raises
    ------
    InvalidInputError
        One line naming the file (see the module notes); for a COLMAP model also an unsupported camera
        model, an image whose name matches no frame, two images matching one frame.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "cameras.csv"
    >>> header = "frame,fx,fy,cx,cy,skew,r11,r12,r13,r21,r22,r23,r31,r32,r33,t1,t2,t3"
    >>> _ = f.write_text(header + "\\n4,500,500,320,240,0,1,0,0,0,1,0,0,0,0.9999995,0,0,5\\n")
    >>> known = read_known_cameras(f)
    >>> known.source_format, known.cameras.frames.tolist()
    ('intrinsics + pose CSV', [4])
    >>> known.warnings[0]  # doctest: +ELLIPSIS
    '...cameras.csv: 1 of 1 rotation(s) orthonormal only to 1e-06 ...; replaced by the nearest rotation(s) (SVD)'
    """
    if is_colmap_path(path):
        return _colmap_cameras(path, frame_names)
    return _csv_cameras(Path(path))


def read_cameras(path: str | os.PathLike[str],
                 frame_names: Sequence[str] | Mapping[int, str] | None = None) -> CameraSet:
    """Read known cameras (a cameras CSV or a COLMAP model): :func:`read_known_cameras`' cameras.

    Its warnings (rotations repaired) are issued as :class:`~kalmansfm.KalmanSfmWarning`; call
    :func:`read_known_cameras` to get them, and how frames were matched, as data.

    Returns
    -------
    CameraSet
        One camera per row (CSV, in the order of the file) or per registered image (COLMAP).

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
    known = read_known_cameras(path, frame_names)
    for message in known.warnings:
        warnings.warn(message, KalmanSfmWarning, stacklevel=2)
    return known.cameras


def _column(file: Path, values: np.ndarray, lines: np.ndarray, name: str) -> np.ndarray:
    """One column of finite numbers (no bound: projection-matrix entries and translations are not pixels)."""
    try:
        out = np.array(values.tolist(), dtype=np.float64)
    except ValueError:
        out = None
    if out is None or not np.isfinite(out).all():
        for i, text in enumerate(values.tolist()):
            try:
                value = float(text)
            except ValueError:
                raise InvalidInputError(f"{where(file, lines[i])}: {name} must be a number; got {text!r}") from None
            if not np.isfinite(value):
                raise InvalidInputError(f"{where(file, lines[i])}: {name} must be finite; got {text.strip()!r}")
    return out  # type: ignore[return-value]


def _csv_cameras(file: Path) -> KnownCameras:
    header, _, rows = read_rows(file, required=CAMERA_LAYOUTS, max_bytes=MAX_CAMERAS_BYTES)
    column = {name: i for i, name in enumerate(header)}
    layout = MATRIX_COLUMNS if all(c in column for c in MATRIX_COLUMNS) else POSE_COLUMNS
    table = np.array([row for _, row in rows], dtype=object)
    lines = np.array([n for n, _ in rows])
    frames = index_column(file, table[:, column["frame"]], lines, "frame")
    values = np.stack([_column(file, table[:, column[c]], lines, c) for c in layout[1:]], axis=1)
    _, first, counts = np.unique(frames, return_index=True, return_counts=True)
    if np.any(counts > 1):
        dup = frames[first[counts > 1][0]]
        at = lines[frames == dup]
        raise InvalidInputError(f"{where(file, at[0], at[1])}: frame {dup} has two cameras")
    notes: list[str] = []
    if layout is MATRIX_COLUMNS:
        P = values.reshape(-1, 3, 4)
        source = "projection-matrix CSV"
    else:
        fx, fy, cx, cy, skew = values[:, :5].T
        K = intrinsic_matrices(fx, fy, cx, cy, skew)
        problem = intrinsics_problem(K)
        if problem is not None:
            raise InvalidInputError(f"{where(file, lines[problem[0]])}: {problem[1]}")
        checked = check_rotations(values[:, 5:14])
        for bad, why in ((checked.not_rotations, lambda i: f"R Rᵀ differs from I by {checked.deviations[i]:.3g}, more "
                                                           f"than the {ROTATION_ROUNDED:g} that rounding explains"),
                         (checked.reflections, lambda i: "det R = -1: a reflection")):
            if bad.any():
                i = int(np.argmax(bad))
                raise InvalidInputError(f"{where(file, lines[i])}: r11..r33 is not a rotation ({why(i)})")
        if checked.warning() is not None:
            notes.append(f"{where(file)}: {checked.warning()}")
        with np.errstate(all="ignore"):
            P = K @ np.concatenate([checked.rotations, values[:, 14:17, None]], axis=2)
        source = "intrinsics + pose CSV"
    _check_matrices(P, [where(file, n) for n in lines], frames)
    return KnownCameras(CameraSet(P, frames), source, "frame column", (), tuple(notes))


def _check_matrices(P: np.ndarray, places: list[str], frames: np.ndarray) -> None:
    """Finite (no overflow of K [R | t]) with an invertible left 3 × 3 block: what makes P a camera.

    ``places`` says where each camera comes from (``FILE: line N``), for the message.
    """
    with np.errstate(all="ignore"):
        finite = np.isfinite(P).all(axis=(1, 2))
        sv = np.linalg.svd(np.where(finite[:, None, None], P, 0.0)[:, :, :3], compute_uv=False)
        singular = ~(sv[:, -1] > _SINGULAR_RATIO * sv[:, 0])
    if not finite.all():
        i = int(np.argmin(finite))
        raise InvalidInputError(f"{places[i]}: frame {frames[i]}: its projection matrix overflows "
                                f"(numbers near the floating-point limit)")
    scale = projection_scale_problem(P)
    if scale is not None:
        raise InvalidInputError(f"{places[scale[0]]}: frame {frames[scale[0]]}: its projection matrix {scale[1]}")
    if singular.any():
        i = int(np.argmax(singular))
        raise InvalidInputError(f"{places[i]}: frame {frames[i]}: not a camera, the left 3x3 block of "
                                f"its projection matrix is not invertible")


_FRAME_NAME = re.compile(r"frame_(\d+)\.\w+")


def match_image_names(names: Sequence[str], frame_names: Sequence[str] | Mapping[int, str] | None,
                      source: str) -> tuple[np.ndarray, str]:
    """The frame of each image name: by name when frame names are given, else by natural order.

    Parameters
    ----------
    names : the images' names (COLMAP ``NAME``, possibly with folders).
    frame_names : the name of each frame (sequence: frame i; or frame → name), or None.
    source : how the images are named in messages (their file).

    Returns
    -------
    frames : (I,) int64 — the frame of each image.
    rule : ``"name"``, ``"frame number"`` (every name is ``frame_N.ext``, as ``kalmansfm export`` names
        frames without source images) or ``"order"``.

    Examples
    --------
    >>> match_image_names(["img10.png", "img9.png"], None, "images.txt")
    (array([1, 0]), 'order')
    >>> match_image_names(["frame_000020.png", "frame_000021.png"], None, "images.txt")
    (array([20, 21]), 'frame number')
    >>> match_image_names(["images/b.png", "a.png"], ["a.png", "b.png"], "images.txt")
    (array([1, 0]), 'name')
    """
    if frame_names is None:
        numbered = [_FRAME_NAME.fullmatch(Path(name).name) for name in names]
        if names and all(numbered) and len({int(m.group(1)) for m in numbered}) == len(names):  # type: ignore[union-attr]
            # the names kalmansfm export gives frames whose source images it does not know
            return np.array([int(m.group(1)) for m in numbered], dtype=np.int64), "frame number"  # type: ignore[union-attr]
        order = sorted(range(len(names)), key=lambda i: (natural_key(names[i]), i))
        frames = np.empty(len(names), dtype=np.int64)
        frames[order] = np.arange(len(names))
        return frames, "order"
    by_frame = dict(frame_names.items()) if isinstance(frame_names, Mapping) else dict(enumerate(frame_names))
    exact = {str(name): int(f) for f, name in by_frame.items()}
    base: dict[str, list[int]] = {}
    for f, name in by_frame.items():
        base.setdefault(Path(str(name)).name, []).append(int(f))
    frames = np.empty(len(names), dtype=np.int64)
    for i, name in enumerate(names):
        if name in exact:
            frames[i] = exact[name]
        elif len(base.get(Path(name).name, [])) == 1:
            frames[i] = base[Path(name).name][0]
        else:
            shown = ", ".join(list(map(str, by_frame.values()))[:4]) + (", …" if len(by_frame) > 4 else "")
            raise InvalidInputError(f"{source}: image {name!r} matches no frame name (frames: {shown})")
    dup = np.unique(frames, return_counts=True)
    if (dup[1] > 1).any():
        frame = int(dup[0][dup[1] > 1][0])
        both = [names[i] for i in np.flatnonzero(frames == frame)[:2]]
        raise InvalidInputError(f"{source}: images {both[0]!r} and {both[1]!r} both match frame {frame}")
    return frames, "name"


def _colmap_cameras(path: str | os.PathLike[str], frame_names: Sequence[str] | Mapping[int, str] | None
                    ) -> KnownCameras:
    folder, ext = locate_colmap_model(path, MODEL_PARTS[:2])
    file = folder / f"images{ext}"
    model = read_colmap_model(file, points=False)
    images = model.images
    if not len(images.ids):
        raise NotEnoughDataError(f"{where(file)}: the COLMAP model has no registered image")
    K = model.intrinsics()
    problem = intrinsics_problem(K)
    if problem is not None:
        i = problem[0]
        raise InvalidInputError(f"{where(folder / f'cameras{ext}')}: camera {images.camera_ids[i]} (of image "
                                f"{images.names[i]!r}): {problem[1]}")
    frames, rule = match_image_names(images.names, frame_names, where(file))
    skew = read_skew(folder)
    if skew:  # the skew kalmansfm export mapped out of the 2-D points: the original K again
        K = np.array(K, dtype=np.float64)
        K[:, 0, 1] = [skew.get(name, 0.0) for name in images.names]
    with np.errstate(all="ignore"):
        P = K @ np.concatenate([images.rotations(), images.translations[:, :, None]], axis=2)
    _check_matrices(P, [f"{where(file)}: image {name!r}" for name in images.names], frames)
    source = "COLMAP binary" if ext == ".bin" else "COLMAP text"
    return KnownCameras(CameraSet(P, frames), source, rule, images.names, ())


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
    observations : (V, N, 2) — track positions in those frames, NaN where not observed; or, from
        :func:`match_camera_observations`, the same per observation (:class:`~kalmansfm.structure.Observations`).
    track_ids : (N,) — the track of each column.
    frames_without_camera : (k,) int — frames with observations but no camera (skipped).
    """

    cameras: CameraSet
    observations: np.ndarray | Observations
    track_ids: np.ndarray
    frames_without_camera: np.ndarray


def _camera_views(frames: np.ndarray, observed: np.ndarray, cameras: CameraSet, source: str
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows of ``frames`` that have a camera, in frame order, their views, and the observed frames without one."""
    view = cameras.view_of(frames)
    missing = np.asarray(frames)[(view < 0) & observed]
    keep = np.flatnonzero(view >= 0)
    if keep.size < 2:
        raise NotEnoughDataError(f"{source}: {keep.size} of its {len(frames)} frame(s) have a camera; "
                                 f"fusing needs >= 2 (camera frames: {_frame_list(cameras.frames)})")
    order = keep[np.argsort(np.asarray(frames)[keep], kind="stable")]
    return order, view[order], missing


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
    observed = np.isfinite(positions).all(axis=2).any(axis=1)
    order, views, missing = _camera_views(frames, observed, cameras, source)
    return CameraObservations(cameras.subset(views), positions[order], np.asarray(track_ids), missing)


def match_camera_observations(tracks: TrackObservations, cameras: CameraSet, source: str = "the tracks"
                              ) -> CameraObservations:
    """:func:`match_cameras` for tracks held per observation: the observations stay per observation.

    Examples
    --------
    >>> from kalmansfm.io.tracks import TrackObservations
    >>> t = TrackObservations(np.array([0, 1, 2]), np.array([5]), np.array([0, 1, 2]), np.array([0, 0, 0]),
    ...                       np.array([[1.0, 1], [2, 2], [3, 3]]))
    >>> cams = CameraSet.from_matrices(np.stack([np.eye(3, 4)] * 2), frames=[0, 2])
    >>> m = match_camera_observations(t, cams)
    >>> m.observations.frame.tolist(), m.observations.xy[:, 0].tolist(), m.frames_without_camera.tolist()
    ([0, 1], [1.0, 3.0], [1])
    """
    observed = np.zeros(tracks.frames.size, dtype=bool)
    observed[tracks.frame] = True
    order, views, missing = _camera_views(tracks.frames, observed, cameras, source)
    row_view = np.full(tracks.frames.size, -1)
    row_view[order] = np.arange(order.size)
    keep = row_view[tracks.frame] >= 0
    observations = Observations.from_sparse((order.size, tracks.track_ids.size), row_view[tracks.frame][keep],
                                            tracks.track[keep], tracks.xy[keep])
    return CameraObservations(cameras.subset(views), observations, np.asarray(tracks.track_ids), missing)


def _frame_list(frames: np.ndarray, shown: int = 6) -> str:
    head = ", ".join(str(int(f)) for f in frames[:shown])
    return head + (f", ... ({len(frames)} in all)" if len(frames) > shown else "")
