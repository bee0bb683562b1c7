"""The files a structure fusion adds to its ``structure.csv`` and PLY (:mod:`kalmansfm.io.structure`).

* ``history.csv`` — ``view,track_id,X,Y,Z,cov_xx,...,cov_zz``: each point's estimate after every
  view that observed it, from its second view on; ``view`` is that view's frame number.
* ``rejected.csv`` — ``frame,track_id,x,y,residual_px``: every observation rejected as an outlier,
  with its reprojection error at the point's final estimate.

Numbers are written as the shortest text that reads back to the same float (empty where there
is none).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from ..structure.reconstruction import Reconstruction
from ._csv import CSV_CHUNK_ROWS, NOT_FINITE_FIELD, csv_text, number
from .structure import COVARIANCE_COLUMNS

__all__ = ["HISTORY_COLUMNS", "REJECTED_COLUMNS", "history_csv_chunks", "rejected_csv"]

HISTORY_COLUMNS = ("view", "track_id", "X", "Y", "Z", *COVARIANCE_COLUMNS)
REJECTED_COLUMNS = ("frame", "track_id", "x", "y", "residual_px")
_UPPER = np.triu_indices(3)


def history_csv_chunks(reconstruction: Reconstruction) -> Iterator[str]:
    """``history.csv`` of a fusion run with ``history=True`` (rows by view, then track), in pieces to be written as
    they come (a long run's history is large).

    Numbers as :func:`~kalmansfm.io._csv.number` writes them (``%r``: the shortest text that reads back the same
    float), empty where not finite, formatted a row at a time.

    Examples
    --------
    >>> from kalmansfm.scenes.known_cameras import known_camera_scene
    >>> from kalmansfm.structure.fusion import fuse
    >>> s = known_camera_scene(points=3, views=3, seed=0)
    >>> text = "".join(history_csv_chunks(fuse(s.observations, s.cameras, pixel_std=0.5, history=True)))
    >>> text.splitlines()[0].split(",")[:5], len(text.splitlines())
    (['view', 'track_id', 'X', 'Y', 'Z'], 7)
    """
    h = getattr(reconstruction.details, "history", None)
    if h is None:
        raise ValueError("the fusion was run without history")
    cov = h.covariances[:, _UPPER[0], _UPPER[1]]
    frame_of = reconstruction.frame_ids[h.views]
    track_of = reconstruction.track_ids[h.points]
    row = "%d,%d," + ",".join(["%r"] * (3 + len(COVARIANCE_COLUMNS))) + "\n"
    yield ",".join(HISTORY_COLUMNS) + "\n"
    for start in range(0, len(h), CSV_CHUNK_ROWS):
        b = slice(start, start + CSV_CHUNK_ROWS)
        values = np.concatenate([h.estimates[b], cov[b]], axis=1).tolist()
        text = "".join([row % (f, t, *v) for f, t, v in zip(frame_of[b].tolist(), track_of[b].tolist(), values)])
        yield NOT_FINITE_FIELD.sub("", text)


def rejected_csv(reconstruction: Reconstruction) -> str:
    """``rejected.csv``: the observations an outlier test rejected, by frame then track."""
    obs = reconstruction.observations
    pick = obs.rejected
    frames = reconstruction.frame_ids[obs.frame[pick]].tolist()
    tracks = reconstruction.track_ids[obs.point[pick]].tolist()
    rows = ([f, t, number(x), number(y), number(r)] for f, t, (x, y), r in
            zip(frames, tracks, obs.xy[pick], obs.residual[pick]))
    return csv_text(REJECTED_COLUMNS, rows)
