"""The report's own tracks: nine polyhedron corners over 30 frames, read off its printed tables.

Source: ``000_3a84a3544ad80a84.txt`` (Sanders, *Kalman Filtering and 3D Reconstruction
from Factorization*). Frames 1–2 come from its table of hand-picked corners, frames
3–30 from the X, Y of the posterior state it prints under ``Frame# k`` for each point.
The CSV ships as package data, ``kalmansfm/data/report_polyhedron_tracks.csv``.
"""

from __future__ import annotations

from importlib.resources import as_file, files

from ..io.tracks import read_tracks
from ..tracking.tracks import Tracks

__all__ = ["report_tracks"]


def report_tracks() -> Tracks:
    """The report's 9 tracks × 30 frames (frames numbered 1–30, track ids 1–9).

    Examples
    --------
    >>> tracks = report_tracks()
    >>> tracks.positions.shape, tracks.frames[[0, -1]].tolist(), tracks.track_ids.tolist()
    ((30, 9, 2), [1, 30], [1, 2, 3, 4, 5, 6, 7, 8, 9])
    >>> tracks.positions[0, 0].tolist(), tracks.positions[29, 0].round(3).tolist()
    ([118.0, 78.0], [13.351, 78.999])
    """
    with as_file(files("kalmansfm") / "data" / "report_polyhedron_tracks.csv") as path:
        return read_tracks(path)
