"""Read point tracks (the tracker's ``tracks.csv`` / ``tracks.npz``, or a plain CSV) for factorization.

Accepted files:

* ``tracks.csv`` written by the tracker, long format with the header
  ``frame,track_id,x,y,vx,vy,std_x,std_y,status`` and ``status`` one of
  ``measured``, ``predicted``, ``lost``. Only ``measured`` rows are observations
  (a coasting prediction is not evidence of where the point was).
* A plain CSV with at least ``frame,track_id,x,y``: every row is an observation.
  Optional ``std_x,std_y`` columns give per-entry standard deviations.
* ``tracks.npz`` with ``positions (F, P, 2)`` (NaN where none), ``status (F, P)``
  int codes 0 = no track, 1 = measured, 2 = predicted, 3 = lost, ``track_ids (P,)``
  and optionally ``covariances (F, P, 4, 4)`` and ``frames (F,)``. Entries with
  status 1 are observations.

Lines starting with ``#`` in a CSV are comments. Every problem is reported as an
:class:`~kalmansfm.InvalidInputError` naming the file, the 1-based line (CSV) or
the array entry (NPZ), and what is wrong.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError
from .npz import load_npz

__all__ = ["TrackPositions", "read_track_positions", "STATUS_CODES"]

#: Status codes of ``tracks.npz``.
STATUS_CODES = {"none": 0, "measured": 1, "predicted": 2, "lost": 3}
_REQUIRED = ("frame", "track_id", "x", "y")


@dataclass(frozen=True)
class TrackPositions:
    """Observed track positions, ready for :func:`~kalmansfm.factorize`.

    Attributes
    ----------
    positions : (F, P, 2) float — x = column, y = row; NaN where not observed.
    track_ids : (P,) int — the track id of each column, ascending.
    frames : (F,) int — the frame number of each row, ascending.
    std : (F, P, 2) float or None — standard deviation of each observed coordinate
        (NaN where not observed), when the file has it.
    smoothed : False, or True / the lag when the positions are RTS-smoothed tracker
        estimates (:func:`kalmansfm.pipeline.read_tracks_for_factorization`).
    """

    positions: np.ndarray
    track_ids: np.ndarray
    frames: np.ndarray
    std: np.ndarray | None
    smoothed: bool | int = False

    @property
    def weights(self) -> np.ndarray | None:
        """(F, P, 2) inverse variances 1 / std², or None."""
        return None if self.std is None else 1.0 / self.std**2


def read_track_positions(path: str | os.PathLike[str]) -> TrackPositions:
    """Read tracks from a ``.csv`` or ``.npz`` file (see the module notes for the formats).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "t.csv"
    >>> _ = f.write_text("frame,track_id,x,y\\n0,7,1.5,2.0\\n1,7,2.5,2.0\\n1,9,4.0,1.0\\n")
    >>> t = read_track_positions(f)
    >>> t.positions.shape, t.track_ids.tolist(), t.frames.tolist()
    ((2, 2, 2), [7, 9], [0, 1])
    >>> t.positions[0, 1]
    array([nan, nan])
    """
    file = Path(path)
    if not file.is_file():
        raise InvalidInputError(f"{file}: no such file")
    if file.suffix.lower() == ".npz":
        return _read_npz(file)
    return _read_csv(file)


def _read_csv(file: Path) -> TrackPositions:
    try:
        with open(file, newline="", encoding="utf-8") as handle:
            numbered = [(n, row) for n, row in enumerate(csv.reader(handle), start=1) if row and not row[0].lstrip().startswith("#")]
    except UnicodeDecodeError:
        raise InvalidInputError(f"{file}: not a text CSV file") from None
    if not numbered:
        raise InvalidInputError(f"{file}: empty file; expected a header with columns {','.join(_REQUIRED)}")
    header_line, header = numbered[0]
    header = [h.strip() for h in header]
    missing = [c for c in _REQUIRED if c not in header]
    if missing:
        raise InvalidInputError(f"{file}: line {header_line}: header lacks column(s) {', '.join(missing)}; got {','.join(header)}")
    rows = numbered[1:]
    if not rows:
        raise InvalidInputError(f"{file}: no data rows after the header")
    column = {name: i for i, name in enumerate(header)}
    for n, row in rows:
        if len(row) != len(header):
            raise InvalidInputError(f"{file}: line {n}: {len(row)} fields, header has {len(header)}")
    lines = np.array([n for n, _ in rows])
    table = np.array([row for _, row in rows], dtype=object)

    if "status" in column:
        status = np.char.strip(table[:, column["status"]].astype(str))
        known = np.isin(status, ["measured", "predicted", "lost"])
        if not known.all():
            i = int(np.argmax(~known))
            raise InvalidInputError(
                f"{file}: line {lines[i]}: status must be measured, predicted or lost; got {status[i]!r}"
            )
        use = status == "measured"
    else:
        use = np.ones(len(rows), bool)

    frame = _integers(file, table[:, column["frame"]], lines, "frame")
    track = _integers(file, table[:, column["track_id"]], lines, "track_id")
    if (frame < 0).any():
        i = int(np.argmax(frame < 0))
        raise InvalidInputError(f"{file}: line {lines[i]}: frame must be >= 0; got {frame[i]}")
    xy = np.stack([_floats(file, table[use, column[c]], lines[use], c) for c in ("x", "y")], axis=1)
    has_std = "std_x" in column and "std_y" in column
    std = None
    if has_std:
        std = np.stack([_floats(file, table[use, column[c]], lines[use], c) for c in ("std_x", "std_y")], axis=1)
        bad = ~(std > 0)
        if bad.any():
            i = int(np.argmax(bad.any(axis=1)))
            raise InvalidInputError(f"{file}: line {lines[use][i]}: std_x and std_y must be > 0; got {std[i].tolist()}")

    frames = np.unique(frame)
    track_ids = np.unique(track)
    fi = np.searchsorted(frames, frame[use])
    pi = np.searchsorted(track_ids, track[use])
    key = fi.astype(np.int64) * len(track_ids) + pi
    unique_keys, first, counts = np.unique(key, return_index=True, return_counts=True)
    if (counts > 1).any():
        dup = unique_keys[counts > 1][0]
        where = lines[use][key == dup]
        raise InvalidInputError(
            f"{file}: lines {where[0]} and {where[1]}: frame {frame[use][key == dup][0]}, "
            f"track_id {track[use][key == dup][0]} observed twice"
        )
    positions = np.full((len(frames), len(track_ids), 2), np.nan)
    positions[fi, pi] = xy
    full_std = None
    if std is not None:
        full_std = np.full_like(positions, np.nan)
        full_std[fi, pi] = std
    return TrackPositions(positions, track_ids, frames, full_std)


def _integers(file: Path, values: np.ndarray, lines: np.ndarray, name: str) -> np.ndarray:
    out = np.empty(len(values), dtype=np.int64)
    for i, text in enumerate(values):
        try:
            number = float(text)
        except ValueError:
            raise InvalidInputError(f"{file}: line {lines[i]}: {name} must be an integer; got {text!r}") from None
        if not np.isfinite(number) or number != int(number):
            raise InvalidInputError(f"{file}: line {lines[i]}: {name} must be an integer; got {text!r}")
        out[i] = int(number)
    return out


def _floats(file: Path, values: np.ndarray, lines: np.ndarray, name: str) -> np.ndarray:
    try:
        out = np.array(values, dtype=np.float64)
    except ValueError:
        out = None
    if out is None or not np.isfinite(out).all():
        for i, text in enumerate(values):
            try:
                number = float(text)
            except ValueError:
                raise InvalidInputError(f"{file}: line {lines[i]}: {name} must be a number; got {text!r}") from None
            if not np.isfinite(number):
                raise InvalidInputError(f"{file}: line {lines[i]}: {name} must be finite; got {text.strip()!r}")
    return out


def _read_npz(file: Path) -> TrackPositions:
    arrays = load_npz(file)
    missing = [k for k in ("positions", "status", "track_ids") if k not in arrays]
    if missing:
        raise InvalidInputError(f"{file}: missing array(s) {', '.join(missing)}; has {', '.join(sorted(arrays)) or 'none'}")
    positions, status, track_ids = arrays["positions"], arrays["status"], arrays["track_ids"]
    if positions.ndim != 3 or positions.shape[2] != 2 or not np.issubdtype(positions.dtype, np.number):
        raise InvalidInputError(f"{file}: positions must be a numeric (frames, points, 2) array; got shape {positions.shape}")
    frames_n, points_n = positions.shape[:2]
    if status.shape != (frames_n, points_n) or not np.issubdtype(status.dtype, np.integer):
        raise InvalidInputError(f"{file}: status must be an integer ({frames_n}, {points_n}) array; got {status.dtype} {status.shape}")
    if track_ids.shape != (points_n,) or not np.issubdtype(track_ids.dtype, np.integer):
        raise InvalidInputError(f"{file}: track_ids must be an integer ({points_n},) array; got {track_ids.dtype} {track_ids.shape}")
    if len(np.unique(track_ids)) != points_n:
        raise InvalidInputError(f"{file}: track_ids must be distinct")
    bad_code = ~np.isin(status, list(STATUS_CODES.values()))
    if bad_code.any():
        f, p = np.argwhere(bad_code)[0]
        raise InvalidInputError(f"{file}: status[{f}, {p}] = {status[f, p]}; expected 0, 1, 2 or 3")
    measured = status == STATUS_CODES["measured"]
    xy = positions.astype(np.float64)
    bad = measured & ~np.isfinite(xy).all(axis=2)
    if bad.any():
        f, p = np.argwhere(bad)[0]
        raise InvalidInputError(f"{file}: positions[{f}, {p}] = {xy[f, p].tolist()} is not finite but status says measured")
    frames = np.arange(frames_n)
    if "frames" in arrays:
        frames = arrays["frames"]
        if frames.shape != (frames_n,) or not np.issubdtype(frames.dtype, np.integer):
            raise InvalidInputError(f"{file}: frames must be an integer ({frames_n},) array; got {frames.dtype} {frames.shape}")
    std = None
    if "covariances" in arrays:
        cov = arrays["covariances"]
        if cov.shape != (frames_n, points_n, 4, 4):
            raise InvalidInputError(f"{file}: covariances must have shape ({frames_n}, {points_n}, 4, 4); got {cov.shape}")
        variances = np.stack([cov[..., 0, 0], cov[..., 1, 1]], axis=-1).astype(np.float64)
        bad = measured & ~(np.isfinite(variances) & (variances > 0)).all(axis=2)
        if bad.any():
            f, p = np.argwhere(bad)[0]
            raise InvalidInputError(f"{file}: covariances[{f}, {p}] has a non-positive or non-finite position variance")
        std = np.where(measured[..., None], np.sqrt(np.abs(variances)), np.nan)
    order = np.argsort(track_ids, kind="stable")
    positions_out = np.where(measured[..., None], xy, np.nan)[:, order]
    return TrackPositions(positions_out, track_ids[order].astype(np.int64), frames.astype(np.int64),
                          None if std is None else std[:, order])
