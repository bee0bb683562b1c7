"""The camera file of a Middlebury multi-view set (``*_par.txt``): K, R, t per image.

The first line holds the number of images; each further line an image name and 21 numbers —
K row by row (9), R row by row (9), t (3), with x_cam = R X + t.  The images are returned in
natural order of their names (``frame2`` before ``frame10``), the order in which a folder of
them is read as frames.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ..structure.geometry.pinhole import camera_centres
from ._csv import MAX_CSV_BYTES, read_file_bytes, where
from .frames import natural_key

__all__ = ["MiddleburyCameras", "read_middlebury_cameras"]


@dataclass(frozen=True)
class MiddleburyCameras:
    """The cameras of a Middlebury set, one per image, in natural order of the image names.

    Attributes
    ----------
    names : the image file names.
    intrinsics, rotations : (n, 3, 3); translations : (n, 3) — x_cam = R X + t.
    """

    names: tuple[str, ...]
    intrinsics: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray

    @property
    def centres(self) -> np.ndarray:
        """(n, 3) camera centres, -Rᵀ t."""
        return camera_centres(self.rotations, self.translations)


def read_middlebury_cameras(path: str | os.PathLike[str]) -> MiddleburyCameras:
    """Read a Middlebury ``*_par.txt`` (module notes); rotations as written (see ``camera_checks`` to fix rounding).

    Raises
    ------
    InvalidInputError
        A missing or unreadable file, a count that is not the number of image lines, a line
        without a name and 21 numbers, or an image named twice — one line naming the file and line.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "ring_par.txt"
    >>> row = "1000 0 320 0 1000 240 0 0 1  1 0 0 0 1 0 0 0 1  0 0 {}"
    >>> _ = f.write_text("2\\nv10.png " + row.format(5) + "\\nv2.png " + row.format(4) + "\\n")
    >>> cams = read_middlebury_cameras(f)
    >>> cams.names, cams.translations[:, 2].tolist(), cams.centres[0].tolist()
    (('v2.png', 'v10.png'), [4.0, 5.0], [-0.0, -0.0, -4.0])
    """
    file = Path(path)
    try:
        text = read_file_bytes(file, "Middlebury camera file", MAX_CSV_BYTES).decode("utf-8")
    except UnicodeDecodeError:
        raise InvalidInputError(f"{where(file)}: not a text file") from None
    lines = [(k + 1, line.split()) for k, line in enumerate(text.splitlines()) if line.strip()]
    if not lines:
        raise InvalidInputError(f"{where(file)}: empty; expected the number of images, then a line per image")
    first_line, head = lines[0]
    if len(head) != 1 or not head[0].isdigit():
        raise InvalidInputError(f"{where(file, first_line)}: expected the number of images; got {' '.join(head)!r}")
    rows = lines[1:]
    if int(head[0]) != len(rows):
        raise InvalidInputError(f"{where(file, first_line)}: says {head[0]} images, the file has {len(rows)}")
    values = np.empty((len(rows), 21))
    for k, (number, fields) in enumerate(rows):
        if len(fields) != 22:
            raise InvalidInputError(f"{where(file, number)}: expected an image name and 21 numbers (K, R, t); "
                                    f"got {len(fields)} fields")
        try:
            values[k] = [float(v) for v in fields[1:]]
        except ValueError:
            raise InvalidInputError(f"{where(file, number)}: K, R and t must be numbers") from None
        if not np.isfinite(values[k]).all():
            raise InvalidInputError(f"{where(file, number)}: K, R and t must be finite")
    names = [fields[0] for _, fields in rows]
    seen: dict[str, int] = {}
    for (number, _), name in zip(rows, names):
        if name in seen:
            raise InvalidInputError(f"{where(file, seen[name], number)}: image {name} is given twice")
        seen[name] = number
    order = sorted(range(len(names)), key=lambda k: natural_key(names[k]))
    values = values[order]
    return MiddleburyCameras(tuple(names[k] for k in order), values[:, :9].reshape(-1, 3, 3),
                             values[:, 9:18].reshape(-1, 3, 3), values[:, 18:21])
