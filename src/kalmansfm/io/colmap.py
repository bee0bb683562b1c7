"""COLMAP sparse models out and in: what 3D Gaussian Splatting, nerfstudio, OpenMVS and COLMAP itself read.

A model is a folder holding ``cameras``, ``images`` and ``points3D``, as text (``.txt``) or
binary (``.bin``) files (colmap.github.io/format.html); :func:`write_colmap_model` writes one and
:func:`read_colmap_model` reads one (ours, or one COLMAP or pycolmap wrote), both with our own
code.  :func:`build_colmap_model` makes the record from the arrays of a reconstruction.

Pixel convention
----------------
kalmansfm puts pixel centres at integer coordinates (x = column, y = row; the centre of the top-left
pixel is (0, 0)).  COLMAP puts the top-left *corner* of the image at (0, 0), so the centre of the
top-left pixel is (0.5, 0.5) (COLMAP's database documentation; pycolmap's default principal point of
a W × H camera is (W/2, H/2), the image centre in that convention).  A COLMAP coordinate is ours
plus ``COLMAP_PIXEL_OFFSET`` = 0.5, for the 2-D points and the principal point alike.  The records
below hold the files' numbers exactly as written (so that a model reads and writes back bit for
bit); the shift is applied in one place each way: :func:`to_colmap_pixels` (used by
:func:`build_colmap_model`) and :func:`from_colmap_pixels` (used by :meth:`ColmapModel.intrinsics`
and :meth:`ColmapModel.observations`).

Cameras
-------
``PINHOLE`` (fx, fy, cx, cy) and ``SIMPLE_PINHOLE`` (f, cx, cy) are read; other models carry lens
distortion, which kalmansfm does not model yet, and are refused naming the model.  The builder
writes ``PINHOLE``, one camera per distinct (K, image size); COLMAP has no skew, so a K with skew
is refused.

Covariances
-----------
A side-car ``points3D_covariance.txt`` (not part of COLMAP's format; other tools ignore it) holds
one line per written point that has a covariance: ``POINT3D_ID COV_XX COV_XY COV_XZ COV_YY COV_YZ
COV_ZZ`` in world units squared, after a ``# GAUGE: …`` line that says how the covariances are to
be read (e.g. the free-network gauge of a perspective reconstruction).  :func:`read_colmap_model`
reads it back when present.

Every problem of a file is an :class:`~kalmansfm.InvalidInputError` with one line naming the file.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError
from ..structure.geometry.camera_checks import check_rotations, intrinsics_problem
from . import _colmap_files as files
from ._colmap_records import (
    COLMAP_PIXEL_OFFSET,
    MODEL_PARTS,
    SUPPORTED_MODELS,
    ColmapCameras,
    ColmapImages,
    ColmapModel,
    ColmapPoints,
    first_duplicate,
    from_colmap_pixels,
    model_problem,
    rows_of,
    to_colmap_pixels,
)
from ._csv import read_file_bytes, where
from .atomic import atomic_write

__all__ = [
    "COLMAP_PIXEL_OFFSET",
    "COVARIANCE_FILE",
    "SKEW_FILE",
    "SUPPORTED_MODELS",
    "ColmapCameras",
    "ColmapImages",
    "ColmapModel",
    "ColmapPoints",
    "ColmapWritten",
    "build_colmap_model",
    "from_colmap_pixels",
    "locate_colmap_model",
    "read_colmap_cameras",
    "read_colmap_model",
    "read_skew",
    "skew_text",
    "to_colmap_pixels",
    "write_colmap_model",
]

#: The side-car of point covariances.
COVARIANCE_FILE = "points3D_covariance.txt"
#: The side-car of the skew of each image's K (COLMAP's cameras have none; see io.reconstruction.colmap_of).
SKEW_FILE = "cameras_skew.txt"
#: The largest model file read (COLMAP's images file holds every keypoint of every image).
MAX_MODEL_BYTES = 1 << 33
#: Colour written for points without one (mid grey, rather than COLMAP's black, which viewers show as a hole).
DEFAULT_COLOUR = (128, 128, 128)
# COLMAP's ERROR of a point whose reprojection error was not computed.
_NO_ERROR = -1.0
_COVARIANCE_ENTRIES = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


# --- building from a reconstruction -------------------------------------------------------------


def build_colmap_model(intrinsics: object, rotations: object, translations: object, image_sizes: object,
                       image_names: Sequence[str], observation_frames: object, observation_points: object,
                       observation_xy: object, points: object, *, colours: object | None = None,
                       errors: object | None = None, keep: object | None = None, point_ids: object | None = None,
                       covariances: object | None = None, covariance_gauge: str | None = None) -> ColmapModel:
    """A COLMAP model of a reconstruction: its frames as images, its points with their tracks.

    Frames whose pose is not finite (not registered) are left out with their observations; so are
    points not in ``keep``, not finite, or seen in no written frame — no point is written with an
    empty track.  Image ids are frame index + 1, cameras are numbered from 1, one per distinct
    (K, image size), all ``PINHOLE``.  Pixel coordinates are converted to COLMAP's convention here
    (:func:`to_colmap_pixels`).

    Parameters
    ----------
    intrinsics : (F, 3, 3) or (3, 3) — K of each frame (kalmansfm pixels), without skew.
    rotations, translations : (F, 3, 3), (F, 3) — world-to-camera pose, x_cam = R X + t; NaN for a
        frame not to write.  Rotations orthonormal to 1e-3 are replaced by the nearest rotation.
    image_sizes : (F, 2) or (2,) int — width, height.
    image_names : F str — unique, no whitespace at either end and no line break (the text format
        splits on them).
    observation_frames, observation_points : (N,) int — frame index and point index of each observation.
    observation_xy : (N, 2) — x, y in kalmansfm pixels.
    points : (P, 3).
    colours : (P, 3) uint8, optional — default mid grey.
    errors : (P,), optional — the reprojection RMS of each point in pixels (COLMAP's ERROR); NaN or
        missing: -1, COLMAP's "not computed".
    keep : (P,) bool, optional — the points to write (e.g. status ``ok``); default all.
    point_ids : (P,) int, optional — POINT3D_ID of each point (>= 1, distinct); default index + 1.
    covariances : (P, 3, 3), optional — written to ``points3D_covariance.txt``; needs ``covariance_gauge``.
    covariance_gauge : str, optional — one line saying how the covariances are to be read.

    Returns
    -------
    ColmapModel

    Examples
    --------
    >>> m = build_colmap_model(np.diag([500.0, 500.0, 1.0]), np.stack([np.eye(3)] * 3),
    ...                        [[0.0, 0.0, 4.0], [np.nan] * 3, [-1.0, 0.0, 4.0]], (640, 480),
    ...                        ["a.png", "b.png", "c.png"], [0, 1, 2, 0], [0, 0, 0, 1],
    ...                        [[62.5, 0.0], [1.0, 1.0], [-62.5, 0.0], [5.0, 5.0]],
    ...                        [[0.5, 0.0, 0.0], [0.0, 0.0, 1.0]], keep=[True, False])
    >>> m.images.ids.tolist(), m.points.ids.tolist(), m.points.track_image_ids.tolist()
    ([1, 3], [1], [1, 3])
    >>> m.cameras.models, m.cameras.params.tolist()
    (('PINHOLE',), [[500.0, 500.0, 0.5, 0.5]])
    """
    names = list(image_names)
    F = len(names)
    K = np.broadcast_to(_floats("intrinsics", intrinsics), (F, 3, 3)) if np.ndim(intrinsics) == 2 else \
        _floats("intrinsics", intrinsics)
    R, t = _floats("rotations", rotations), _floats("translations", translations)
    size = np.broadcast_to(np.asarray(image_sizes), (F, 2)) if np.ndim(image_sizes) == 1 else np.asarray(image_sizes)
    if K.shape != (F, 3, 3) or R.shape != (F, 3, 3) or t.shape != (F, 3) or size.shape != (F, 2):
        raise InvalidInputError(f"build_colmap_model needs, for the {F} image names, (F, 3, 3) intrinsics and "
                                f"rotations, (F, 3) translations and (F, 2) image sizes; got {K.shape}, {R.shape}, "
                                f"{t.shape}, {size.shape}")
    X = _floats("points", points)
    P = len(X)
    if X.shape != (P, 3):
        raise InvalidInputError(f"points must have shape (P, 3); got {X.shape}")
    frame = _indices("observation_frames", observation_frames, F)
    point = _indices("observation_points", observation_points, P)
    xy = _floats("observation_xy", observation_xy).reshape(-1, 2) if len(frame) else np.zeros((0, 2))
    if not (len(frame) == len(point) == len(xy)):
        raise InvalidInputError(f"observation_frames, observation_points and observation_xy need one entry per "
                                f"observation; got {len(frame)}, {len(point)}, {len(xy)}")
    registered = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(t).all(axis=1)
    _check_frames(K[registered], R[registered], size[registered], [n for n, r in zip(names, registered) if r])
    wanted = _per_point("keep", keep, P, bool, True) & np.isfinite(X).all(axis=1)
    use = registered[frame] & wanted[point] & np.isfinite(xy).all(axis=1)
    frame, point, xy = frame[use], point[use], xy[use]
    order = np.lexsort((point, frame))
    frame, point, xy = frame[order], point[order], xy[order]
    if len(frame) > 1 and ((np.diff(frame) == 0) & (np.diff(point) == 0)).any():
        k = int(np.argmax((np.diff(frame) == 0) & (np.diff(point) == 0)))
        raise InvalidInputError(f"point {point[k]} is observed twice in frame {frame[k]}")
    written = np.flatnonzero(np.bincount(point, minlength=P) > 0)
    ids = _per_point("point_ids", point_ids, P, np.int64, None)
    ids = np.arange(1, P + 1) if ids is None else ids
    if (ids[written] < 1).any() or first_duplicate(ids[written]) is not None:
        raise InvalidInputError("point_ids must be distinct integers >= 1")
    cameras, camera_of = _distinct_cameras(K[registered], size[registered])
    frames = np.flatnonzero(registered)
    image_row = np.full(F, -1)
    image_row[frames] = np.arange(len(frames))
    starts = np.concatenate([[0], np.cumsum(np.bincount(image_row[frame], minlength=len(frames)))])
    quaternions = Rotation.from_matrix(check_rotations(R[registered]).rotations).as_quat()[:, [3, 0, 1, 2]] \
        if len(frames) else np.zeros((0, 4))
    quaternions *= np.where(quaternions[:, :1] < 0, -1.0, 1.0)  # w >= 0, as COLMAP writes them
    images = ColmapImages(frames + 1, camera_of, [names[f] for f in frames], quaternions, t[registered], starts,
                          to_colmap_pixels(xy), ids[point])
    # each observation is, in order, element (frame, index within the frame) of its point's track
    index_in_image = np.arange(len(frame)) - starts[image_row[frame]]
    by_point = np.lexsort((frame, point))
    track_starts = np.concatenate([[0], np.cumsum(np.bincount(point, minlength=P)[written])])
    rgb = _colours(colours, P)
    err = _per_point("errors", errors, P, np.float64, np.nan)
    pts = ColmapPoints(ids[written], X[written], rgb[written], np.where(np.isfinite(err), err, _NO_ERROR)[written],
                       track_starts, frame[by_point] + 1, index_in_image[by_point])
    cov = None
    if covariances is not None:
        if covariance_gauge is None:
            raise InvalidInputError("covariances need a covariance_gauge: the one line that says how to read them")
        cov = _floats("covariances", covariances)
        if cov.shape != (P, 3, 3):
            raise InvalidInputError(f"covariances must have shape ({P}, 3, 3); got {cov.shape}")
        cov = cov[written]
    return ColmapModel(ColmapCameras(*cameras), images, pts, cov, covariance_gauge if cov is not None else None)


def _floats(name: str, value: object) -> np.ndarray:
    try:
        array = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be an array of real numbers") from None
    return array


def _indices(name: str, value: object, bound: int) -> np.ndarray:
    array = np.asarray(value).ravel()
    if array.size and (array.dtype.kind not in "iu" or array.min() < 0 or array.max() >= bound):
        raise InvalidInputError(f"{name} must be integers in 0 … {bound - 1}")
    return array.astype(np.int64)


def _per_point(name: str, value: object | None, P: int, dtype: type, default: object) -> np.ndarray:
    if value is None:
        return None if default is None else np.full(P, default, dtype=dtype)  # type: ignore[return-value]
    array = np.asarray(value)
    if array.shape != (P,):
        raise InvalidInputError(f"{name} must have one entry per point, shape ({P},); got {array.shape}")
    return array.astype(dtype)


def _colours(colours: object | None, P: int) -> np.ndarray:
    if colours is None:
        return np.tile(np.array(DEFAULT_COLOUR, dtype=np.uint8), (P, 1))
    rgb = np.asarray(colours)
    if rgb.shape != (P, 3) or rgb.dtype != np.uint8:
        raise InvalidInputError(f"colours must be a ({P}, 3) uint8 array; got {rgb.dtype} {rgb.shape}")
    return rgb


def _check_frames(K: np.ndarray, R: np.ndarray, size: np.ndarray, names: list[str]) -> None:
    """Refuse what COLMAP cannot hold: K that is not a camera or has skew, a non-rotation, a bad size or name."""
    problem = intrinsics_problem(K) if len(K) else None
    if problem is not None:
        raise InvalidInputError(f"intrinsics of image {names[problem[0]]}: {problem[1]}")
    skewed = np.abs(K[:, 0, 1]) > 1e-9 * K[:, 0, 0]
    lower = (K[:, 1, 0] != 0) | (K[:, 2, 0] != 0) | (K[:, 2, 1] != 0) | (K[:, 2, 2] != 1)
    if (skewed | lower).any():
        i = int(np.argmax(skewed | lower))
        raise InvalidInputError(f"intrinsics of image {names[i]}: COLMAP's PINHOLE camera is [[fx, 0, cx], [0, fy, cy], "
                                f"[0, 0, 1]] (no skew); got {K[i].tolist()}")
    checked = check_rotations(R)
    bad = checked.not_rotations | checked.reflections
    if bad.any():
        i = int(np.argmax(bad))
        raise InvalidInputError(f"rotation of image {names[i]} is not a rotation "
                                f"(|R Rᵀ - I| = {checked.deviations[i]:.3g}, "
                                f"det {np.linalg.det(R[i]):.3g})")
    if size.size and (size.dtype.kind not in "iu" or (size < 1).any()):
        raise InvalidInputError(f"image sizes must be positive integers (width, height); got {size[0].tolist()} …")
    for name in names:
        if not name or name != name.strip() or any(c in name for c in "\r\n\0"):
            raise InvalidInputError(f"image name {name!r} cannot be written: it must be non-empty, without spaces at "
                                    f"either end or line breaks")
    if len(set(names)) != len(names):
        raise InvalidInputError(f"image names must be unique; {next(n for n in names if names.count(n) > 1)!r} repeats")


def _distinct_cameras(K: np.ndarray, size: np.ndarray) -> tuple[tuple, np.ndarray]:
    """One PINHOLE camera per distinct (fx, fy, cx, cy, width, height), ids from 1 in order of first use."""
    params = np.zeros((len(K), 4))
    params[:, 0], params[:, 1], params[:, 2:] = K[:, 0, 0], K[:, 1, 1], to_colmap_pixels(K[:, :2, 2])
    key = np.concatenate([params, size.astype(np.float64)], axis=1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(first))
    chosen = np.sort(first)
    cameras = (np.arange(1, len(first) + 1), ("PINHOLE",) * len(first), size[chosen].astype(np.int64), params[chosen])
    return cameras, rank[inverse.ravel()] + 1


# --- reading ------------------------------------------------------------------------------------


def locate_colmap_model(path: str | os.PathLike[str], parts: Sequence[str] = MODEL_PARTS) -> tuple[Path, str]:
    """The folder and the format (``.bin`` or ``.txt``) of the COLMAP model at ``path``.

    ``path`` is a model folder, a folder holding one in ``sparse/0/``, ``0/`` or ``sparse/``, or one
    of the model's files.  Binary is preferred when a folder holds both (as COLMAP does).  Only the
    given ``parts`` are needed (the known-cameras reader needs no ``points3D``).

    Raises
    ------
    InvalidInputError
        ``PATH: no such file or folder``, ``PATH: no COLMAP model (…)``, ``PATH: incomplete COLMAP
        model: …``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> root = pathlib.Path(tempfile.mkdtemp())
    >>> (root / "sparse" / "0").mkdir(parents=True)
    >>> for part in MODEL_PARTS: _ = (root / "sparse" / "0" / f"{part}.bin").write_bytes(bytes(8))
    >>> folder, ext = locate_colmap_model(root)
    >>> folder.relative_to(root).as_posix(), ext
    ('sparse/0', '.bin')
    """
    given = Path(path)
    if given.is_file() or (given.exists() and not given.is_dir()):
        stem, ext = given.stem, given.suffix
        if stem in MODEL_PARTS and ext in (".bin", ".txt"):
            missing = [p for p in parts if not (given.parent / f"{p}{ext}").exists()]
            if missing:
                raise InvalidInputError(f"{where(given.parent)}: incomplete COLMAP model: no "
                                        f"{', '.join(p + ext for p in missing)} beside {given.name}")
            return given.parent, ext
        raise InvalidInputError(f"{where(given)}: not a COLMAP model file (cameras, images or points3D .bin/.txt)")
    if not given.is_dir():
        raise InvalidInputError(f"{where(given)}: no such file or folder")
    for folder in (given, given / "sparse" / "0", given / "0", given / "sparse"):
        # any kind of entry counts (a FIFO in place of a file is then refused by name, unread)
        present = {ext: [p for p in parts if (folder / f"{p}{ext}").exists()] for ext in (".bin", ".txt")}
        for ext in (".bin", ".txt"):
            if len(present[ext]) == len(parts):
                return folder, ext
        found = present[".bin"] + present[".txt"]
        if found:
            have = [p + e for e in (".bin", ".txt") for p in present[e]]
            ext = ".bin" if len(present[".bin"]) >= len(present[".txt"]) else ".txt"
            lacking = [p + ext for p in parts if p not in present[ext]]
            raise InvalidInputError(f"{where(folder)}: incomplete COLMAP model: has {', '.join(have)} but no "
                                    f"{', '.join(lacking)}")
    raise InvalidInputError(f"{where(given)}: no COLMAP model (expected {', '.join(parts)} as .bin or .txt files "
                            f"here, in sparse/0/ or in 0/)")


def _read_part(folder: Path, part: str, ext: str) -> dict:
    file = folder / f"{part}{ext}"
    data = read_file_bytes(file, "COLMAP model file", MAX_MODEL_BYTES)
    if ext == ".bin":
        parse = {"cameras": files.parse_cameras_binary, "images": files.parse_images_binary,
                 "points3D": files.parse_points_binary}[part]
        return parse(data, file)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InvalidInputError(f"{where(file)}: not a COLMAP text file (not UTF-8: byte 0x{data[exc.start]:02x} at "
                                f"offset {exc.start})") from None
    if "\0" in text:
        raise InvalidInputError(f"{where(file)}: not a COLMAP text file (holds NUL bytes; a binary model is named .bin)")
    parse = {"cameras": files.parse_cameras_text, "images": files.parse_images_text,
             "points3D": files.parse_points_text}[part]
    return parse(text, file)


def read_colmap_cameras(path: str | os.PathLike[str]) -> ColmapCameras:
    """Read only the cameras of a COLMAP model (``cameras.txt`` / ``.bin``, or the folder holding it).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "cameras.txt"
    >>> _ = f.write_text("# id model w h params\\n1 SIMPLE_PINHOLE 640 480 800 320 240\\n")
    >>> cameras = read_colmap_cameras(f)
    >>> cameras.models, cameras.intrinsics()[0].tolist()
    (('SIMPLE_PINHOLE',), [[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])
    """
    folder, ext = locate_colmap_model(path, ("cameras",))
    return ColmapCameras(**_read_part(folder, "cameras", ext))


def read_colmap_model(path: str | os.PathLike[str], *, points: bool = True) -> ColmapModel:
    """Read a COLMAP sparse model, text or binary (:func:`locate_colmap_model` finds it), and its covariance side-car.

    Parameters
    ----------
    path : the model folder, a folder holding ``sparse/0`` or ``0``, or one of the model's files.
    points : read ``points3D`` (False: cameras and images only, an empty set of points — all the
        2-D points then say -1).

    Returns
    -------
    ColmapModel
        The files' numbers as they are (COLMAP's pixel convention; :meth:`ColmapModel.intrinsics` and
        :meth:`ColmapModel.observations` convert).  The images' 2-D points name the 3-D points whose
        tracks hold them (as COLMAP's own reader sets them).

    Raises
    ------
    InvalidInputError
        One line naming the file: no model, a truncated or corrupt binary file, a camera model other
        than PINHOLE / SIMPLE_PINHOLE, an image naming a missing camera, a track naming a missing image.

    Examples
    --------
    >>> import tempfile
    >>> model = build_colmap_model(np.diag([500.0, 500.0, 1.0]), np.stack([np.eye(3)] * 2),
    ...                            [[0.0, 0.0, 4.0], [-1.0, 0.0, 4.0]], (640, 480), ["a.png", "b.png"],
    ...                            [0, 1], [0, 0], [[62.5, 0.0], [-62.5, 0.0]], [[0.5, 0.0, 0.0]])
    >>> folder = write_colmap_model(model, tempfile.mkdtemp(), binary=True).folder
    >>> back = read_colmap_model(folder)
    >>> back.points.xyz.tolist(), back.observations()[2].tolist()
    ([[0.5, 0.0, 0.0]], [[62.5, 0.0], [-62.5, 0.0]])
    """
    parts = MODEL_PARTS if points else MODEL_PARTS[:2]
    folder, ext = locate_colmap_model(path, parts)
    names = {part: where(folder / f"{part}{ext}") for part in MODEL_PARTS}
    cameras = ColmapCameras(**_read_part(folder, "cameras", ext))
    raw_images = _read_part(folder, "images", ext)
    points_read = ColmapPoints(**_read_part(folder, "points3D", ext)) if points else None
    images = ColmapImages(**raw_images)
    problem = model_problem(cameras, images, points_read, names, point_ids=False)
    if problem:
        raise InvalidInputError(problem)
    # the tracks say which 3-D point each 2-D point belongs to (COLMAP's reader sets them so too)
    owner = np.full(len(images.point3d_ids), -1, dtype=np.int64)
    if points_read is not None:
        row = rows_of(images.ids, points_read.track_image_ids)
        owner[images.point_starts[row] + points_read.track_point2d] = np.repeat(points_read.ids,
                                                                                points_read.track_lengths)
    images = ColmapImages(**{**{f.name: getattr(images, f.name) for f in fields(images)}, "point3d_ids": owner})
    if points_read is None:
        points_read = ColmapPoints(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), [0], [], [])
    covariances, gauge = _read_covariances(folder / COVARIANCE_FILE, points_read.ids) if points else (None, None)
    return ColmapModel(cameras, images, points_read, covariances, gauge)


# --- writing ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ColmapWritten:
    """What :func:`write_colmap_model` wrote.

    Attributes
    ----------
    folder : Path — the model folder.
    files : tuple of Path — the files written, ``cameras``, ``images``, ``points3D`` and the covariance side-car.
    images, points : int — how many of each were written.
    dropped_empty_tracks : int — points of the model left out because no image sees them.
    """

    folder: Path
    files: tuple[Path, ...]
    images: int
    points: int
    dropped_empty_tracks: int


def write_colmap_model(model: ColmapModel, folder: str | os.PathLike[str], binary: bool = False) -> ColmapWritten:
    """Write ``model`` as a COLMAP sparse model into ``folder`` (created if missing), text or binary.

    Each file is written under a temporary name and renamed into place (:func:`~kalmansfm.io.atomic.atomic_write`),
    all contents rendered before the first is written; a points with an empty track is left out
    (OpenMVS's reader stops on one).  A ``points3D_covariance.txt`` is written when the model has
    covariances, and an older one removed when it has none (it would describe other points).  A
    folder that holds a model in the other format, or COLMAP's rig files (``rigs``, ``frames``), is
    refused: readers would take those for part of this model.

    Examples
    --------
    >>> import tempfile
    >>> model = build_colmap_model(np.diag([500.0, 500.0, 1.0]), np.stack([np.eye(3)] * 2),
    ...                            [[0.0, 0.0, 4.0], [-1.0, 0.0, 4.0]], (640, 480), ["a.png", "b.png"],
    ...                            [0, 1], [0, 0], [[62.5, 0.0], [-62.5, 0.0]], [[0.5, 0.0, 0.0]])
    >>> written = write_colmap_model(model, tempfile.mkdtemp())
    >>> [f.name for f in written.files], written.points
    (['points3D.txt', 'images.txt', 'cameras.txt'], 1)
    """
    out = Path(folder)
    ext, other = (".bin", ".txt") if binary else (".txt", ".bin")
    if out.exists() and not out.is_dir():
        raise InvalidInputError(f"{where(out)}: exists and is not a folder")
    clashing = [f"{p}{other}" for p in MODEL_PARTS] + [f"{p}{e}" for p in ("rigs", "frames") for e in (".bin", ".txt")]
    present = [name for name in clashing if (out / name).exists()]
    if present:
        raise InvalidInputError(f"{where(out)}: already holds {', '.join(present)} of another COLMAP model; write into "
                                f"an empty folder or remove them")
    model, dropped = _without_empty_tracks(model)
    cameras = {f.name: getattr(model.cameras, f.name) for f in fields(model.cameras)}
    images = {f.name: getattr(model.images, f.name) for f in fields(model.images)}
    points = {f.name: getattr(model.points, f.name) for f in fields(model.points)}
    if not binary:
        text = [" " in n or "\t" in n for n in model.images.names]
        if any(text):
            name = model.images.names[text.index(True)]
            raise InvalidInputError(f"image name {name!r} holds a space, which COLMAP's text format cannot hold: write the "
                                    f"binary format or rename the image")
        contents = {"points3D": files.points_text(points).encode(), "images": files.images_text(images).encode(),
                    "cameras": files.cameras_text(cameras).encode()}
    else:
        contents = {"points3D": files.points_binary(points), "images": files.images_binary(images),
                    "cameras": files.cameras_binary(cameras)}
    side_car = _covariance_text(model) if model.covariances is not None else None
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for part, data in contents.items():  # cameras last: a folder with cameras is taken for a model
        written.append(atomic_write(out / f"{part}{ext}", lambda tmp, data=data: tmp.write_bytes(data)))
    if side_car is not None:
        written.append(atomic_write(out / COVARIANCE_FILE, lambda tmp: tmp.write_text(side_car, encoding="utf-8")))
    elif (out / COVARIANCE_FILE).is_file():
        (out / COVARIANCE_FILE).unlink()
    return ColmapWritten(out, tuple(written), len(model.images.ids), len(model.points.ids), dropped)


def _without_empty_tracks(model: ColmapModel) -> tuple[ColmapModel, int]:
    lengths = model.points.track_lengths
    empty = lengths == 0
    if not empty.any():
        return model, 0
    p = model.points
    kept = ColmapPoints(p.ids[~empty], p.xyz[~empty], p.colours[~empty], p.errors[~empty],
                        np.concatenate([[0], np.cumsum(lengths[~empty])]), p.track_image_ids, p.track_point2d)
    cov = None if model.covariances is None else model.covariances[~empty]
    return ColmapModel(model.cameras, model.images, kept, cov, model.covariance_gauge), int(empty.sum())


# --- the covariance side-car ---------------------------------------------------------------------


def _covariance_text(model: ColmapModel) -> str:
    cov = model.covariances
    has = np.isfinite(cov).all(axis=(1, 2))
    entries = np.stack([cov[:, i, j] for i, j in _COVARIANCE_ENTRIES], axis=1)[has]
    lines = ["# kalmansfm point covariances, one line per point of points3D that has one (world units squared):",
             "#   POINT3D_ID, COV_XX, COV_XY, COV_XZ, COV_YY, COV_YZ, COV_ZZ",
             f"# GAUGE: {model.covariance_gauge}",
             f"# Number of points: {int(has.sum())}"]
    lines += [f"{pid} " + " ".join(repr(v) for v in row) for pid, row in zip(model.points.ids[has].tolist(),
                                                                               entries.tolist())]
    return "\n".join(lines) + "\n"


_GAUGE = re.compile(r"^\s*#\s*GAUGE:\s?(?P<text>.*?)\s*$")


def _read_covariances(file: Path, ids: np.ndarray) -> tuple[np.ndarray | None, str | None]:
    """Covariances (P, 3, 3), NaN for points the side-car does not list, and its gauge; (None, None) without one."""
    if not file.exists():
        return None, None
    data = read_file_bytes(file, "text file", MAX_MODEL_BYTES)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InvalidInputError(f"{where(file)}: not UTF-8 text") from None
    gauge = next((m["text"] for m in map(_GAUGE.match, text.splitlines()) if m), None)
    rows = [(n, line.split()) for n, line in enumerate(text.splitlines(), start=1)
            if line.strip() and not line.lstrip().startswith("#")]
    bad = [n for n, tokens in rows if len(tokens) != 7]
    if bad:
        raise InvalidInputError(f"{where(file, bad[0])}: expected POINT3D_ID COV_XX COV_XY COV_XZ COV_YY COV_YZ COV_ZZ")
    try:
        listed = np.array([t[0] for _, t in rows], dtype=np.int64)
        values = np.array([t[1:] for _, t in rows], dtype=np.float64).reshape(-1, 6)
    except (ValueError, OverflowError):
        raise InvalidInputError(f"{where(file)}: POINT3D_ID must be integers and the covariances numbers") from None
    for test, what in ((np.isfinite(values).all(axis=1), "covariances must be finite"),
                       (np.isin(listed, ids), "names a point that points3D does not hold")):
        if not test.all():
            raise InvalidInputError(f"{where(file, rows[int(np.argmin(test))][0])}: {what}")
    dup = first_duplicate(listed)
    if dup is not None:
        raise InvalidInputError(f"{where(file)}: point {dup} is listed twice")
    cov = np.full((len(ids), 3, 3), np.nan)
    at = rows_of(ids, listed)
    for k, (i, j) in enumerate(_COVARIANCE_ENTRIES):
        cov[at, i, j] = cov[at, j, i] = values[:, k]
    return cov, gauge


def skew_text(names: list[str], skew: np.ndarray) -> str:
    """``cameras_skew.txt``: one ``IMAGE_NAME SKEW`` line per image whose K has a skew."""
    lines = ["# kalmansfm: the skew (K[0, 1], pixels) of each image's camera; COLMAP's cameras have none, so the",
             "# 2-D points of these images were mapped to the camera without it (x0 = K0 K^-1 x)"]
    lines += [f"{name} {value!r}" for name, value in zip(names, skew.tolist()) if value != 0.0]
    return "\n".join(lines) + "\n"


def read_skew(folder: Path) -> dict[str, float]:
    """The skew side-car of a model folder as image name → skew ({} when there is none)."""
    file = folder / SKEW_FILE
    if not file.is_file():
        return {}
    out = {}
    for number, line in enumerate(file.read_text(encoding="utf-8").splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        name, _, value = line.rpartition(" ")
        try:
            out[name] = float(value)
        except ValueError:
            raise InvalidInputError(f"{where(file, number)}: expected IMAGE_NAME SKEW; got {line!r}") from None
    return out
