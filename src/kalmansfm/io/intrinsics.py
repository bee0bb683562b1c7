"""Camera intrinsics in and out: ``K.csv`` (or a COLMAP model's cameras) for calibrated reconstruction, and ``--focal``.

``K.csv`` has the header ``frame,fx,fy,cx,cy,skew`` and either one row, used
for every frame (its frame value is then ignored), or one row per frame; every
frame of the tracks must have one.  ``frame`` and ``skew`` may be left out for one
camera: ``fx,fy,cx,cy`` and a single row serve every frame (skew 0).
K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] in pixels, x = column and y = row.

A COLMAP model's ``cameras.txt`` / ``cameras.bin`` (or its folder) is read too
(:mod:`kalmansfm.io.colmap`; PINHOLE and SIMPLE_PINHOLE cameras, the principal point
converted to kalmansfm's pixel convention): one camera serves every frame; with several,
the model's images say which frame uses which (matched as
:func:`~kalmansfm.io.cameras.read_known_cameras` matches them).

Every problem raises :class:`~kalmansfm.InvalidInputError` naming the file and the 1-based line:
what :func:`~kalmansfm.structure.geometry.camera_checks.intrinsics_problem` refuses (fx, fy <= 0, absurd
focal lengths or skew), a frame given twice, a frame without a row.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .._validation import check_positive
from ..errors import InvalidInputError
from ..structure.geometry.camera_checks import intrinsics_problem
from ..structure.geometry.pinhole import intrinsic_matrices
from ._csv import index_column, number, number_column, read_rows, where
from .cameras import MAX_CAMERAS_BYTES, is_colmap_path, match_image_names
from .colmap import locate_colmap_model, read_colmap_cameras, read_colmap_model

__all__ = ["INTRINSICS_COLUMNS", "intrinsics_csv", "intrinsics_from_focal", "read_intrinsics"]

#: Header of ``K.csv``.
INTRINSICS_COLUMNS = ("frame", "fx", "fy", "cx", "cy", "skew")
#: The columns ``K.csv`` must have (``frame`` and ``skew`` may be left out for a single camera).
REQUIRED_COLUMNS = ("fx", "fy", "cx", "cy")


def read_intrinsics(path: str | os.PathLike[str], frames: object,
                    frame_names: Sequence[str] | Mapping[int, str] | None = None) -> np.ndarray:
    """K of each of the given frames from ``K.csv`` or a COLMAP model's cameras.

    Parameters
    ----------
    path : the CSV, or a COLMAP ``cameras.txt`` / ``cameras.bin`` or model folder (see the module notes).
    frames : (F,) int — the frame numbers that need a K (e.g. the tracks' frames).
    frame_names : optional, COLMAP models with several cameras only — each frame's name, to match the
        model's images to frames by name (else by order).

    Returns
    -------
    (F, 3, 3) float64, in the order of ``frames``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "K.csv"
    >>> _ = f.write_text("frame,fx,fy,cx,cy,skew\\n0,800,810,320,240,0\\n")
    >>> read_intrinsics(f, [3, 4])[1].tolist()
    [[800.0, 0.0, 320.0], [0.0, 810.0, 240.0], [0.0, 0.0, 1.0]]
    >>> _ = f.write_text("fx,fy,cx,cy\\n800,800,320,240\\n")
    >>> read_intrinsics(f, [0, 1]).shape
    (2, 3, 3)
    >>> _ = f.write_text("frame,fx,fy,cx,cy,skew\\n0,800,800,320,240,0\\n1,800,800,320,240,0\\n")
    >>> read_intrinsics(f, [0, 2])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: ... no intrinsics for frame 2 (K.csv has frames 0-1; give one row for all frames or one per frame)
    """
    wanted = np.asarray(frames, dtype=np.int64).ravel()
    if is_colmap_path(path):
        return _colmap_intrinsics(path, wanted, frame_names)
    file = Path(path)
    header, header_line, rows = read_rows(file, ",".join(INTRINSICS_COLUMNS), required=REQUIRED_COLUMNS,
                                          max_bytes=MAX_CAMERAS_BYTES)
    lines = np.array([n for n, _ in rows])
    index = {name: i for i, name in enumerate(header)}
    column = {c: np.array([r[index[c]] for _, r in rows], dtype=object) for c in INTRINSICS_COLUMNS if c in index}
    fx, fy, cx, cy = (number_column(file, column[c], lines, c) for c in REQUIRED_COLUMNS)
    skew = number_column(file, column["skew"], lines, "skew") if "skew" in column else np.zeros(len(rows))
    bad = ~((fx > 0) & (fy > 0))
    if bad.any():
        i = int(np.argmax(bad))
        raise InvalidInputError(f"{where(file, lines[i])}: fx and fy must be > 0 (pixels; K would be singular); "
                                f"got {fx[i]}, {fy[i]}")
    K = intrinsic_matrices(fx, fy, cx, cy, skew)
    problem = intrinsics_problem(K)
    if problem is not None:
        raise InvalidInputError(f"{where(file, lines[problem[0]])}: {problem[1]}")
    if len(rows) == 1:
        return np.repeat(K, len(wanted), axis=0)
    if "frame" not in column:
        raise InvalidInputError(f"{where(file, header_line)}: {len(rows)} rows need a frame column to say which frame "
                                f"each is for (one row without it serves every frame)")
    given = index_column(file, column["frame"], lines, "frame")
    order = np.argsort(given, kind="stable")
    sorted_frames = given[order]
    twice = np.flatnonzero(np.diff(sorted_frames) == 0)
    if twice.size:
        dup = sorted_frames[twice[0]]
        at = lines[given == dup]
        raise InvalidInputError(f"{where(file, at[0], at[1])}: frame {dup} has two rows")
    pos = np.clip(np.searchsorted(sorted_frames, wanted), 0, len(given) - 1)
    found = sorted_frames[pos] == wanted
    if not found.all():
        missing = wanted[~found][0]
        raise InvalidInputError(f"{where(file)}: no intrinsics for frame {missing} ({file.name} has frames {given.min()}-"
                                f"{given.max()}; give one row for all frames or one per frame)")
    return K[order[pos]]


def _colmap_intrinsics(path: str | os.PathLike[str], wanted: np.ndarray,
                       frame_names: Sequence[str] | Mapping[int, str] | None) -> np.ndarray:
    """K per frame from a COLMAP model: its one camera, or through its images when it has several."""
    folder, ext = locate_colmap_model(path, ("cameras",))
    file = folder / f"cameras{ext}"
    cameras = read_colmap_cameras(file)
    K = cameras.intrinsics()
    problem = intrinsics_problem(K) if len(K) else (0, "holds no camera")
    if problem is not None:
        raise InvalidInputError(f"{where(file)}: camera {cameras.ids[problem[0]] if len(K) else ''}: {problem[1]}")
    if len(K) == 1:
        return np.repeat(K, len(wanted), axis=0)
    images = folder / f"images{ext}"
    if not images.is_file():
        raise InvalidInputError(f"{where(file)}: holds {len(K)} cameras; which frame uses which is in "
                                f"images{ext}, which is not beside it")
    model = read_colmap_model(images, points=False)
    image_frames, rule = match_image_names(model.images.names, frame_names, where(images))
    order = np.argsort(image_frames)
    pos = np.clip(np.searchsorted(image_frames[order], wanted), 0, len(order) - 1)
    found = image_frames[order][pos] == wanted if len(order) else np.zeros(len(wanted), dtype=bool)
    if not found.all():
        raise InvalidInputError(f"{where(images)}: no image for frame {wanted[~found][0]} (images matched to "
                                f"frames by {rule})")
    return model.intrinsics()[order[pos]]


def intrinsics_from_focal(focal: float, image_size: tuple[int, int], n_frames: int) -> np.ndarray:
    """K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]] for every frame: square pixels, principal point at the centre.

    Examples
    --------
    >>> intrinsics_from_focal(700.0, (640, 480), 2)[0].tolist()
    [[700.0, 0.0, 320.0], [0.0, 700.0, 240.0], [0.0, 0.0, 1.0]]
    """
    f = check_positive("focal", focal, "pixels")
    if not 1e-3 <= f <= 1e7:
        raise InvalidInputError(f"focal must be between 0.001 and 1e+07 pixels; got {f:g}")
    width, height = (check_positive("image width", image_size[0], "pixels"),
                     check_positive("image height", image_size[1], "pixels"))
    return np.repeat(intrinsic_matrices(f, f, width / 2, height / 2, 0.0), n_frames, axis=0)


def intrinsics_csv(frames: object, intrinsics: np.ndarray) -> str:
    """``K.csv`` text, one row per frame (reads back exactly with :func:`read_intrinsics`).

    Examples
    --------
    >>> print(intrinsics_csv([5], np.array([[[800.0, 0.5, 320.0], [0, 790.0, 240.0], [0, 0, 1]]])))
    frame,fx,fy,cx,cy,skew
    5,800.0,790.0,320.0,240.0,0.5
    <BLANKLINE>
    """
    K = np.asarray(intrinsics, dtype=np.float64)
    lines = [",".join(INTRINSICS_COLUMNS)]
    for frame, k in zip(np.asarray(frames).ravel(), K):
        values = (k[0, 0], k[1, 1], k[0, 2], k[1, 2], k[0, 1])
        lines.append(",".join([str(int(frame))] + [number(v) for v in values]))
    return "\n".join(lines) + "\n"
