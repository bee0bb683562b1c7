"""The Oxford VGG multi-view data sets (Model House, Merton College I): matches, cameras and 3-D points.

A VGG folder (``../shared/data/oxford_model_house``, ``../shared/data/oxford_merton1``; see
their READMEs) holds, per view, a corner list (``x y`` per line) and a 3 × 4 camera matrix,
an n-view match table whose row i links point i of the data set's own 3-D reconstruction to
a corner of each view (a 0-based row of that view's corner list, ``*`` = not seen), and
those 3-D points.  The two sets differ only in where the files sit:

=================  ====================================  =====================================
                   Model House                           Merton College I
=================  ====================================  =====================================
cameras            ``3D/house.00N.P``                    ``2D/00N.P``
corners            ``2D/house.00N.corners``              ``2D/00N.corners``
matches            ``2D/house.nview-corners``            ``2D/nview-corners``
3-D points         ``3D/house.p3d``                      ``3D/p3d``
=================  ====================================  =====================================

The frame number of a view is the N of its file names.  ``examples/oxford_to_csv.py`` writes
a set as kalmansfm's ``tracks.csv``, ``cameras.csv`` and ``points3d.csv``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from ..structure.geometry.pinhole import CameraSet
from ._csv import where

__all__ = ["OxfordDataset", "read_oxford"]


@dataclass(frozen=True)
class OxfordDataset:
    """A VGG data set in kalmansfm's terms.

    Attributes
    ----------
    cameras : the views' projection matrices with their frame numbers.
    observations : (V, N, 2) float — the corner of point n in view v (x = column, y = row),
        NaN where the point is not seen; point n is row n of the match table.
    points : (N, 3) float — the data set's own reconstruction of the points.
    """

    cameras: CameraSet
    observations: np.ndarray
    points: np.ndarray


def _layout(root: Path) -> tuple[list[Path], list[Path], Path, Path, list[int]]:
    """Camera files, corner files, match table, 3-D points and frame numbers of a VGG folder."""
    if (root / "2D" / "house.nview-corners").is_file():  # Model House
        views = sorted(root.glob("3D/house.*.P"))
        corners = [root / "2D" / p.name.replace(".P", ".corners") for p in views]
        return views, corners, root / "2D" / "house.nview-corners", root / "3D" / "house.p3d", [
            int(p.name.split(".")[1]) for p in views]
    if (root / "2D" / "nview-corners").is_file():  # Merton College I
        views = sorted(root.glob("2D/*.P"))
        return views, [p.with_suffix(".corners") for p in views], root / "2D" / "nview-corners", root / "3D" / "p3d", [
            int(p.stem) for p in views]
    raise InvalidInputError(f"{where(root)}: not an Oxford VGG data set folder (expected 2D/house.nview-corners or "
                            "2D/nview-corners)")


def _table(path: Path, columns: int, *, matches: bool = False) -> np.ndarray:
    """A whitespace-separated table of ``columns`` numbers per line (``*`` → -1 in a match table)."""
    try:
        if matches:
            table = np.genfromtxt(path, dtype=float, missing_values="*", filling_values=-1)
        else:
            table = np.loadtxt(path, dtype=float, ndmin=2)
    except (OSError, ValueError) as exc:
        raise InvalidInputError(f"{where(path)}: not a table of numbers ({exc})") from None
    table = np.atleast_2d(table)
    if table.shape[1] != columns or not np.isfinite(table).all():
        raise InvalidInputError(f"{where(path)}: expected {columns} finite numbers per line; got a {table.shape} table")
    return table


def read_oxford(folder: str | os.PathLike[str]) -> OxfordDataset:
    """Read a Model House or Merton College I folder (see the module notes for the layouts).

    Raises
    ------
    InvalidInputError
        The folder has neither layout, a file is missing or not a table of numbers, or a
        match points past the end of its view's corner list.

    Examples
    --------
    A Merton-style folder of two views and two points, the second seen in view 0 only:

    >>> import tempfile
    >>> root = Path(tempfile.mkdtemp()); (root / "2D").mkdir(); (root / "3D").mkdir()
    >>> for n in (0, 1):
    ...     _ = (root / "2D" / f"00{n}.P").write_text("1 0 0 0\\n0 1 0 0\\n0 0 1 5\\n")
    ...     _ = (root / "2D" / f"00{n}.corners").write_text("10 20\\n30 40\\n")
    >>> _ = (root / "2D" / "nview-corners").write_text("0 1\\n1 *\\n")
    >>> _ = (root / "3D" / "p3d").write_text("0 0 0\\n1 1 1\\n")
    >>> data = read_oxford(root)
    >>> data.cameras.frames.tolist(), data.observations[:, 0].tolist(), data.observations[:, 1].tolist()
    ([0, 1], [[10.0, 20.0], [30.0, 40.0]], [[30.0, 40.0], [nan, nan]])
    """
    root = Path(folder)
    views, corner_files, match_file, points_file, frames = _layout(root)
    if not views:
        raise InvalidInputError(f"{where(root)}: no camera files (*.P)")
    P = np.stack([_table(p, 4) for p in views])
    if P.shape[1:] != (3, 4):
        raise InvalidInputError(f"{where(root)}: every camera file must hold 3 lines of 4 numbers")
    match = _table(match_file, len(views), matches=True).astype(np.int64)
    points = _table(points_file, 3)
    if len(points) != len(match):
        raise InvalidInputError(f"{where(match_file)}: {len(match)} rows, but {points_file} holds {len(points)} points")
    observations = np.full((len(views), len(points), 2), np.nan)
    for v, corner_file in enumerate(corner_files):  # one match-table column per view (a handful of views)
        xy = _table(corner_file, 2)
        seen = match[:, v] >= 0
        if seen.any() and match[seen, v].max() >= len(xy):
            raise InvalidInputError(f"{where(match_file)}: column {v + 1} refers to corner {match[seen, v].max()}, but "
                                    f"{corner_file.name} lists {len(xy)}")
        observations[v, seen] = xy[match[seen, v]]
    return OxfordDataset(CameraSet.from_matrices(P, frames), observations, points)
