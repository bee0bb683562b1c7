"""Tracks out and back in: ``tracks.csv`` (long format), ``tracks.npz`` (arrays), and start-point CSVs.

``tracks.csv`` has one row per (frame, track) while the track exists::

    frame,track_id,x,y,vx,vy,std_x,std_y,status

with ``status`` one of ``initialising`` (a track's first two frames: the start point and
the start-up match, with the filter's start-up prior as standard deviations),
``measured``, ``predicted`` (coasting: x, y are the prediction) and ``lost`` (the frame
of the loss; the numbers are empty).  Other tools
give less, and :func:`read_tracks` accepts any CSV with at least ``frame,track_id,x,y``:
``vx,vy`` (velocities), ``std_x,std_y`` (position standard deviations) and ``status``
are optional and every row without a status is a measurement.  Comments, blank lines, a
byte-order mark and the other rules every CSV reader shares: docs/formats.md (:func:`._csv.read_rows`).

``tracks.npz`` holds ``status (F,P)`` int8 (:class:`~kalmansfm.tracking.tracks.TrackStatus`
values), ``track_ids (P,)``, ``frames (F,)``, the bits ``present`` of the (frame, track) entries
that have a value, and for those entries only (frame-major) ``entry_positions (n,2)`` and
optionally ``entry_states (n,4)``, ``entry_covariances_upper (n,10)`` (the upper triangle, row by
row; ``entry_covariances (n,4,4)`` when one is not symmetric) and ``entry_scores (n,)``; then
``image_size`` (width, height) and ``meta``: a JSON object with the schema version, the tracker's
settings (:class:`~kalmansfm.tracking.settings.TrackerSettings`) and whether the tracks are
smoothed.  Files of the dense layout (``positions (F,P,2)``, ``states``, ``covariances``, ``scores``
as whole arrays) read as well.

Every reader returns :class:`~kalmansfm.tracking.tracks.Tracks`; :func:`read_tracks` (any
format) puts the track ids in ascending order, :func:`read_tracks_npz` keeps the file's
column order.  They report every problem as an :class:`~kalmansfm.InvalidInputError`
naming the file and the line (CSV) or the array entry (NPZ).
"""

from __future__ import annotations

import io
import json
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._validation import check_fits_in_memory
from ..errors import InvalidInputError
from ..structure.reconstruction import Observations
from ..tracking.settings import TrackerSettings
from ..tracking.tracks import (
    LOST,
    MEASUREMENT_CODES,
    NO_TRACK,
    POSITION_CODES,
    Tracks,
    TrackStatus,
)
from ._csv import MAX_COORDINATE_PX, MAX_CSV_BYTES, MAX_INDEX, NOT_FINITE_FIELD, csv_text, index_column, number, number_column, read_file_bytes, read_rows, where
from .npz import load_npz, save_npz
from .records import from_json, to_json

__all__ = [
    "MAX_COORDINATE_PX",
    "MAX_INDEX",
    "TRACK_CSV_COLUMNS",
    "OBSERVATION_COLUMNS",
    "check_dense_size",
    "check_points_inside",
    "observations_csv",
    "read_points_csv",
    "read_tracks",
    "read_tracks_csv",
    "read_tracks_npz",
    "read_track_observations",
    "TrackObservations",
    "tracks_to_csv",
    "write_tracks_csv",
    "write_tracks_npz",
]

#: The columns of the tracker's ``tracks.csv``.
TRACK_CSV_COLUMNS = ("frame", "track_id", "x", "y", "vx", "vy", "std_x", "std_y", "status")
#: The least a tracks CSV holds: one measured position per row (what other tools and converters write).
OBSERVATION_COLUMNS = ("frame", "track_id", "x", "y")
_REQUIRED = OBSERVATION_COLUMNS
#: Version 2 keeps only the entries where a track exists (``present`` bits, ``entry_*`` arrays); version 1
#: files (dense arrays) are read as well.
_NPZ_SCHEMA = 2
# The upper triangle of a 4 × 4 matrix, row by row.
_UPPER4 = np.triu_indices(4)


# --- writing --------------------------------------------------------------------------------


# A number is written with 6 decimals, trailing zeros and a bare point dropped, empty when not finite; these
# rewrite a whole text of "%.6f" fields that way at once.
_TRAILING_ZEROS = re.compile(r"(\.\d*?)0+(?=[,\n])")
_BARE_POINT = re.compile(r"\.(?=[,\n])")


def tracks_to_csv(tracks: Tracks) -> str:
    """The long-format CSV text of ``tracks`` (needs their states and covariances).

    Examples
    --------
    >>> t = Tracks.empty(2, 1)
    >>> t.status[0, 0] = 1; t.states[0, 0] = [1.5, 2.0, 0.5, 0.0]; t.covariances[0, 0] = np.eye(4) * 4.0
    >>> t.status[1, 0] = 3
    >>> print(tracks_to_csv(t), end="")
    frame,track_id,x,y,vx,vy,std_x,std_y,status
    0,0,1.5,2,0.5,0,2,2,measured
    1,0,,,,,,,lost
    """
    if tracks.states is None or tracks.position_std is None:
        raise InvalidInputError("tracks.csv needs the tracks' states and covariances")
    rows, cols = np.nonzero(tracks.status != NO_TRACK)
    order = np.lexsort((cols, rows))
    rows, cols = rows[order], cols[order]
    status = tracks.status[rows, cols]
    values = np.concatenate([tracks.states[rows, cols], tracks.position_std[rows, cols]], axis=1)
    lost = status == LOST
    values[lost] = np.nan
    words = np.array([s.label for s in TrackStatus])[status]
    frames = tracks.frames[rows].tolist()  # type: ignore[index]
    ids = tracks.track_ids[cols].tolist()
    # one format per row and two or three passes over the whole text: a third of the time of formatting each
    # number; a lost row has no values and its own format, so the pass that empties NaN fields is needed only
    # when a row with values has a non-finite one
    row = "%d,%d," + ",".join(["%.6f"] * values.shape[1]) + ",%s\n"
    empty = "%d,%d" + "," * values.shape[1] + f",{TrackStatus.LOST.label}\n"
    text = "".join([empty % (f, i) if gone else row % (f, i, *v, word)
                    for f, i, v, word, gone in zip(frames, ids, values.tolist(), words.tolist(), lost.tolist())])
    if not np.isfinite(values[~lost]).all():
        text = NOT_FINITE_FIELD.sub("", text)
    text = _BARE_POINT.sub("", _TRAILING_ZEROS.sub(r"\1", text))
    return ",".join(TRACK_CSV_COLUMNS) + "\n" + text


def observations_csv(observations: np.ndarray, frames: np.ndarray, track_ids: np.ndarray | None = None) -> str:
    """``frame,track_id,x,y`` text of every finite position of ``observations``, by frame then track.

    Parameters
    ----------
    observations : (F, P, 2) float, x = column, y = row, NaN where not seen.
    frames : (F,) the frame number of each row; track_ids : (P,) (default 0 … P − 1).

    Numbers are written in full (they read back as the same floats).

    Examples
    --------
    >>> obs = np.array([[[1.5, 2.0], [np.nan, np.nan]], [[3.0, 4.25], [5.0, 6.0]]])
    >>> print(observations_csv(obs, [10, 11], [7, 9]), end="")
    frame,track_id,x,y
    10,7,1.5,2.0
    11,7,3.0,4.25
    11,9,5.0,6.0
    """
    x = np.asarray(observations, dtype=np.float64)
    f = np.asarray(frames)
    ids = np.arange(x.shape[1]) if track_ids is None else np.asarray(track_ids)
    if x.ndim != 3 or x.shape[2] != 2 or f.shape != x.shape[:1] or ids.shape != x.shape[1:2]:
        raise InvalidInputError(f"need observations (F, P, 2), frames (F,) and track_ids (P,); "
                                f"got {x.shape}, {f.shape} and {ids.shape}")
    v, n = np.nonzero(np.isfinite(x).all(axis=2))
    rows = ([int(a), int(b), number(px), number(py)] for a, b, (px, py) in zip(f[v], ids[n], x[v, n].tolist()))
    return csv_text(OBSERVATION_COLUMNS, rows)


def write_tracks_csv(tracks: Tracks, path: str | os.PathLike[str]) -> Path:
    """Write ``tracks.csv`` (see the module notes) to ``path``."""
    path = Path(path)
    path.write_text(tracks_to_csv(tracks), encoding="utf-8")
    return path


def write_tracks_npz(tracks: Tracks, path: str | os.PathLike[str]) -> Path:
    """Write ``tracks`` to a compressed ``.npz`` at ``path``, holding only the entries where a track exists.

    Positions, states, covariances (their upper triangle, when every one is symmetric) and scores
    are kept for the (frame, track) entries that have a value, in frame-major order, next to the
    dense ``status``: a long clip with many short tracks takes the room of its estimates, not of
    frames × tracks.  :func:`read_tracks_npz` rebuilds the dense arrays exactly.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> t = Tracks.empty(3, 2); t.status[1, 0] = 1; t.positions[1, 0] = 4.0, 5.0; t.covariances[1, 0] = np.eye(4)
    >>> back = read_tracks_npz(write_tracks_npz(t, pathlib.Path(tempfile.mkdtemp()) / "t.npz"))
    >>> bool(np.array_equal(back.positions, t.positions, equal_nan=True)), back.status.tolist()
    (True, [[0, 0], [1, 0], [0, 0]])
    """
    path = Path(path)
    present = np.isfinite(tracks.positions).any(axis=2)  # status is kept whole: a lost track has no values
    for name in ("states", "covariances"):
        values = getattr(tracks, name)
        if values is not None:
            present |= np.isfinite(values).reshape(*values.shape[:2], int(np.prod(values.shape[2:]))).any(axis=2)
    arrays = {
        "status": tracks.status.astype(np.int8),
        "track_ids": tracks.track_ids.astype(np.int64),
        "frames": tracks.frames,
        "present": np.packbits(present, axis=None),
    }
    positions = tracks.positions[present]
    if tracks.states is not None:
        arrays["entry_states"] = tracks.states[present]
    # the tracker's positions are its states' first two entries: kept once, unless they differ
    if tracks.states is None or not np.array_equal(positions, arrays["entry_states"][:, :2], equal_nan=True):
        arrays["entry_positions"] = positions
    if tracks.covariances is not None:
        covariances = tracks.covariances[present]
        if np.array_equal(covariances, np.swapaxes(covariances, 1, 2), equal_nan=True):
            arrays["entry_covariances_upper"] = covariances[:, _UPPER4[0], _UPPER4[1]]
        else:
            arrays["entry_covariances"] = covariances
    if tracks.scores is not None:
        arrays["entry_scores"] = tracks.scores[present]
    if tracks.image_size is not None:
        arrays["image_size"] = np.asarray(tracks.image_size, dtype=np.int64)
    meta = {"schema_version": _NPZ_SCHEMA, "settings": to_json(tracks.settings), "smoothed": tracks.smoothed}
    arrays["meta"] = np.array(json.dumps(meta))
    with open(path, "wb") as handle:
        save_npz(handle, arrays)
    return path


#: The estimators (factorization, fusion, bundle adjustment) hold about this many copies of the dense
#: (frames, tracks) arrays a reader builds; a file whose copies cannot fit is refused before reading on.
ESTIMATOR_COPIES = 3


def check_dense_size(file: Path, n_frames: int, n_tracks: int, n_entries: int, bytes_per_entry: int) -> None:
    """Refuse, with one line naming ``file``, tracks whose dense arrays and the estimators' copies exceed memory.

    A tracker's npz, smoothing and the report hold tracks as (frames, tracks, ...) arrays; a long
    sequence of many short tracks fills a tiny share of them (fusion and reconstruction read such a
    CSV per observation instead, :func:`read_track_observations`),
    and running out of memory would end in the system killing the process.
    """
    share = n_entries / max(1, n_frames * n_tracks)
    check_fits_in_memory(
        float(n_frames) * n_tracks * bytes_per_entry * ESTIMATOR_COPIES,
        f"{where(file)}: {n_frames} frames x {n_tracks} tracks, held as dense frames x tracks arrays "
        f"({n_entries} entries fill {share:.2%} of them) with the estimators' copies",
        "fuse and reconstruct read a tracks CSV per observation (without --smooth); or split the sequence into "
        "shorter segments of frames",
    )


def _dense_arrays(file: Path, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The dense (frames, tracks, ...) arrays of a file written with only its present entries."""
    status = arrays["status"]
    if status.ndim != 2:
        raise InvalidInputError(f"{where(file)}: status must be a (frames, tracks) array; got shape {status.shape}")
    F, P = status.shape
    bits = arrays["present"]
    if bits.dtype != np.uint8 or bits.ndim != 1 or bits.size != (F * P + 7) // 8:
        raise InvalidInputError(f"{where(file)}: present must hold the {F} x {P} entry bits; got {bits.dtype} {bits.shape}")
    per_entry = 1 + 16 + sum(b for key, b in (("entry_states", 32), ("entry_covariances", 128),
                                              ("entry_covariances_upper", 128), ("entry_scores", 8)) if key in arrays)
    check_dense_size(file, F, P, len(arrays.get("entry_states", arrays.get("entry_positions", ()))), per_entry)
    present = np.unpackbits(bits, count=F * P).astype(bool).reshape(F, P)
    n = int(present.sum())
    dense = dict(arrays)
    if "entry_positions" not in arrays and "entry_states" in arrays:  # positions kept as the states' first two
        arrays = {**arrays, "entry_positions": np.asarray(arrays["entry_states"])[:, :2]}
    for name, tail in (("positions", (2,)), ("states", (4,)), ("covariances", (4, 4)), ("scores", ())):
        key = f"entry_{name}"
        if name == "covariances" and "entry_covariances_upper" in arrays:
            upper = arrays["entry_covariances_upper"]
            if upper.shape != (n, 10):
                raise InvalidInputError(f"{where(file)}: entry_covariances_upper must have shape ({n}, 10); got {upper.shape}")
            full = np.empty((n, 4, 4), dtype=upper.dtype)
            full[:, _UPPER4[0], _UPPER4[1]] = upper
            full[:, _UPPER4[1], _UPPER4[0]] = upper
            values = full
        elif key in arrays:
            values = arrays[key]
        else:
            continue
        if values.shape != (n, *tail) or values.dtype.kind not in "fiu":
            raise InvalidInputError(f"{where(file)}: {key} must be a numeric ({n}{''.join(f', {d}' for d in tail)}) array; "
                                    f"got {values.dtype} {values.shape}")
        out = np.full((F, P, *tail), np.nan)
        out[present] = values
        dense[name] = out
    return dense


# --- reading --------------------------------------------------------------------------------


def read_tracks(path: str | os.PathLike[str]) -> Tracks:
    """Read tracks from a ``.npz`` or a CSV file (see the module notes), track ids ascending.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "t.csv"
    >>> _ = f.write_text("frame,track_id,x,y\\n0,7,1.5,2.0\\n1,7,2.5,2.0\\n1,9,4.0,1.0\\n")
    >>> t = read_tracks(f)
    >>> t.positions.shape, t.track_ids.tolist(), t.frames.tolist()
    ((2, 2, 2), [7, 9], [0, 1])
    >>> t.observations()[0, 1]
    array([nan, nan])
    """
    file = Path(path)
    if not file.exists():
        raise InvalidInputError(f"{where(file)}: no such file")
    if file.is_dir():
        raise InvalidInputError(f"{where(file)}: is a folder, not a file; give a tracks file (tracks.npz, tracks.csv or "
                                "a frame,track_id,x,y CSV)")
    if file.suffix.lower() != ".npz":  # the CSV reader refuses a folder, a FIFO or a device unread
        return read_tracks_csv(file)
    tracks = read_tracks_npz(file)
    order = np.argsort(tracks.track_ids, kind="stable")
    if np.array_equal(order, np.arange(tracks.n_tracks)):
        return tracks
    columns = {name: getattr(tracks, name)[:, order] for name in ("positions", "status", "states", "covariances", "scores")
               if getattr(tracks, name) is not None}
    return tracks.replace(track_ids=tracks.track_ids[order], **columns)


@dataclass(frozen=True)
class _CsvRows:
    """A tracks CSV's rows, checked: frame and track index of each row, its status, and the positioned rows' values."""

    frames: np.ndarray
    track_ids: np.ndarray
    frame: np.ndarray  # (rows,) index into frames
    track: np.ndarray  # (rows,) index into track_ids
    status: np.ndarray  # (rows,)
    positioned: np.ndarray  # (rows,) bool: not lost
    xy: np.ndarray  # (positioned, 2)
    velocity: np.ndarray | None
    std: np.ndarray | None


def _read_csv_rows(file: Path) -> _CsvRows:
    header, _, rows = read_rows(file, required=_REQUIRED)
    column = {name: i for i, name in enumerate(header)}
    lines = np.array([n for n, _ in rows])
    table = np.array([row for _, row in rows], dtype=object)

    if "status" in column:
        words = [w.strip() for w in table[:, column["status"]].tolist()]
        known = {s.label: int(s) for s in TrackStatus if s != NO_TRACK}
        bad = [k for k, w in enumerate(words) if w not in known]
        if bad:
            raise InvalidInputError(
                f"{where(file, lines[bad[0]])}: status must be {', '.join(known)}; got {words[bad[0]]!r}"
            )
        status = np.array([known[w] for w in words], dtype=np.int8)
    else:
        status = np.full(len(rows), int(TrackStatus.MEASURED), dtype=np.int8)
    frame = index_column(file, table[:, column["frame"]], lines, "frame")
    track = index_column(file, table[:, column["track_id"]], lines, "track_id")
    positioned = status != LOST
    xy = np.stack([number_column(file, table[positioned, column[c]], lines[positioned], c) for c in ("x", "y")], axis=1)
    velocity = std = None
    if "vx" in column and "vy" in column:
        velocity = np.stack([number_column(file, table[positioned, column[c]], lines[positioned], c, finite=False)
                             for c in ("vx", "vy")], axis=1)
    if "std_x" in column and "std_y" in column:
        std = np.stack([number_column(file, table[positioned, column[c]], lines[positioned], c, finite=False)
                        for c in ("std_x", "std_y")], axis=1)
        measured_rows = np.isin(status[positioned], MEASUREMENT_CODES)
        bad = measured_rows & ~(std > 0).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise InvalidInputError(f"{where(file, lines[positioned][i])}: std_x and std_y must be > 0; got {std[i].tolist()}")

    frames = np.unique(frame)
    track_ids = np.unique(track)
    fi = np.searchsorted(frames, frame)
    pi = np.searchsorted(track_ids, track)
    key = fi.astype(np.int64) * len(track_ids) + pi
    unique_keys, counts = np.unique(key, return_counts=True)
    if (counts > 1).any():
        dup = unique_keys[counts > 1][0]
        at = lines[key == dup]
        raise InvalidInputError(
            f"{where(file, at[0], at[1])}: frame {frame[key == dup][0]}, track_id {track[key == dup][0]} given twice"
        )
    return _CsvRows(frames, track_ids, fi, pi, status, positioned, xy, velocity, std)


def read_tracks_csv(path: str | os.PathLike[str]) -> Tracks:
    """Read a tracks CSV: the tracker's ``tracks.csv`` or any CSV with ``frame,track_id,x,y``.

    Without a ``std_x,std_y`` pair the tracks have no covariances; without ``vx,vy`` no states.
    """
    file = Path(path)
    rows = _read_csv_rows(file)
    frames, track_ids, fi, pi, status = rows.frames, rows.track_ids, rows.frame, rows.track, rows.status
    positioned, xy, velocity, std = rows.positioned, rows.xy, rows.velocity, rows.std
    shape = (len(frames), len(track_ids))
    check_dense_size(file, *shape, len(status), 1 + 16 + (32 if velocity is not None else 0) + (128 if std is not None else 0))
    status_table = np.zeros(shape, np.int8)
    status_table[fi, pi] = status
    positions = np.full(shape + (2,), np.nan)
    fp, pp = fi[positioned], pi[positioned]
    positions[fp, pp] = xy
    states = covariances = None
    if velocity is not None:
        states = np.full(shape + (4,), np.nan)
        states[fp, pp] = np.concatenate([xy, velocity], axis=1)
    if std is not None:
        covariances = np.full(shape + (4, 4), np.nan)
        covariances[fp, pp, 0, 0] = std[:, 0] ** 2
        covariances[fp, pp, 1, 1] = std[:, 1] ** 2
    return Tracks(positions=positions, status=status_table, track_ids=track_ids, states=states,
                  covariances=covariances, frames=frames)




@dataclass(frozen=True)
class TrackObservations:
    """The measured positions of tracks, one entry per observation: memory follows the observations.

    A long sequence of short tracks fills a tiny share of a dense (frames × tracks) array;
    :func:`read_track_observations` reads a tracks file into this form instead.

    Attributes
    ----------
    frames : (F,) ascending frame numbers that hold a row of the file.
    track_ids : (P,) ascending track ids.
    frame, track : (M,) each observation's index into ``frames`` and ``track_ids``.
    xy : (M, 2) its position (x = column, y = row), pixels.
    image_size : (width, height) when the file says.
    """

    frames: np.ndarray
    track_ids: np.ndarray
    frame: np.ndarray
    track: np.ndarray
    xy: np.ndarray
    image_size: tuple[int, int] | None = None

    def observations(self) -> Observations:
        """The estimators' record of these observations, (frames, tracks) by index (``.dense()`` gives the
        (F, P, 2) positions of :meth:`Tracks.observations`)."""
        return Observations.from_sparse((self.frames.size, self.track_ids.size), self.frame, self.track, self.xy)


def read_track_observations(path: str | os.PathLike[str]) -> TrackObservations:
    """The measured positions of a tracks file (CSV or npz), one entry per observation, without dense arrays.

    The same observations as ``read_tracks(path).observations()`` (measured and initialising
    rows; coasting predictions and lost rows are none), checked the same way.  A CSV is read
    row by row into this form; an npz holds dense status arrays and is read through
    :func:`read_tracks`.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "t.csv"
    >>> _ = f.write_text("frame,track_id,x,y\\n0,7,1.5,2.0\\n1,7,2.5,2.0\\n1,9,4.0,1.0\\n")
    >>> obs = read_track_observations(f)
    >>> obs.frames.tolist(), obs.track_ids.tolist(), obs.frame.tolist(), obs.track.tolist()
    ([0, 1], [7, 9], [0, 1, 1], [0, 0, 1])
    >>> np.array_equal(obs.observations().dense(), read_tracks(f).observations(), equal_nan=True)
    True
    """
    file = Path(path)
    if file.suffix.lower() == ".npz" or not file.is_file():
        tracks = read_tracks(file)
        f, t = np.nonzero(tracks.measured)
        return TrackObservations(tracks.frames, tracks.track_ids, f, t, tracks.positions[f, t], tracks.image_size)
    plain = _plain_observations(file)
    if plain is not None:
        return plain
    rows = _read_csv_rows(file)
    measured = np.isin(rows.status, MEASUREMENT_CODES)
    xy = np.full((rows.status.size, 2), np.nan)
    xy[rows.positioned] = rows.xy
    order = np.lexsort((rows.track[measured], rows.frame[measured]))
    return TrackObservations(rows.frames, rows.track_ids, rows.frame[measured][order], rows.track[measured][order],
                             xy[measured][order])


def _plain_observations(file: Path) -> TrackObservations | None:
    """A ``frame,track_id,x,y`` file of numbers only, parsed by NumPy in one pass; None when it is anything else.

    Every row as a Python list of strings costs about 400 bytes and a microsecond or more (a ten-minute
    sequence: 0.74 GB, 9 s); NumPy's parser holds only the numbers.  A file that is not plainly that, or
    breaks any rule, is left to the general reader, which names the line (the same rules, the same result).
    """
    try:
        text = read_file_bytes(file, "text CSV", MAX_CSV_BYTES).decode("utf-8-sig")
    except (InvalidInputError, UnicodeDecodeError):
        return None
    header, _, body = text.partition("\n")
    if header.strip() != ",".join(OBSERVATION_COLUMNS) or "#" in body or '"' in body:
        return None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # an empty body warns: the general reader says it better
            values = np.loadtxt(io.StringIO(body), delimiter=",", ndmin=2, dtype=np.float64)
    except (ValueError, UserWarning):
        return None
    if values.shape[1] != 4 or not len(values):
        return None
    index, xy = values[:, :2], values[:, 2:]
    if not (np.isfinite(values).all() and (index == np.round(index)).all() and (index >= 0).all()
            and (index <= MAX_INDEX).all() and (np.abs(xy) <= MAX_COORDINATE_PX).all()):
        return None
    frames, frame = np.unique(index[:, 0].astype(np.int64), return_inverse=True)
    track_ids, track = np.unique(index[:, 1].astype(np.int64), return_inverse=True)
    key = frame.astype(np.int64) * len(track_ids) + track
    if np.unique(key).size != key.size:  # a pair given twice: the general reader names both lines
        return None
    order = np.argsort(key, kind="stable")
    return TrackObservations(frames, track_ids, frame[order], track[order], xy[order])


def _real(file: Path, arrays: dict[str, np.ndarray], name: str, shape: tuple[int, ...]) -> np.ndarray | None:
    if name not in arrays:
        return None
    value = arrays[name]
    if value.dtype.kind not in "fiu" or value.shape != shape:
        raise InvalidInputError(f"{where(file)}: {name} must be a real numeric array of shape {shape}; got {value.dtype} {value.shape}")
    return value.astype(np.float64)


def _meta(file: Path, arrays: dict[str, np.ndarray]) -> tuple[TrackerSettings | None, bool | int]:
    if "meta" not in arrays:
        return None, False
    try:
        meta = json.loads(str(arrays["meta"]))
    except ValueError as exc:
        raise InvalidInputError(f"{where(file)}: meta is not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise InvalidInputError(f"{where(file)}: meta must hold a JSON object; got {type(meta).__name__}")
    settings = None if meta.get("settings") is None else from_json(TrackerSettings, meta["settings"], f"{where(file)}: meta.settings")
    smoothed = meta.get("smoothed", False)
    if isinstance(smoothed, bool) or (isinstance(smoothed, int) and smoothed >= 0):
        return settings, smoothed
    raise InvalidInputError(f"{where(file)}: meta.smoothed must be true, false or a lag >= 0; got {smoothed!r}")


def read_tracks_npz(path: str | os.PathLike[str]) -> Tracks:
    """Read a ``tracks.npz`` (see the module notes) with its columns in the file's order.

    States, covariances and the rest are optional.
    """
    file = Path(path)
    arrays = load_npz(file)
    if "present" in arrays and "status" in arrays:  # the compact layout (schema 2)
        arrays = _dense_arrays(file, arrays)
    missing = [k for k in ("positions", "status", "track_ids") if k not in arrays]
    if missing:
        raise InvalidInputError(f"{where(file)}: missing array(s) {', '.join(missing)}; has {', '.join(sorted(arrays)) or 'none'}")
    positions, status, track_ids = arrays["positions"], arrays["status"], arrays["track_ids"]
    if positions.ndim != 3 or positions.shape[2] != 2 or positions.dtype.kind not in "fiu":
        raise InvalidInputError(f"{where(file)}: positions must be a numeric (frames, points, 2) array; got {positions.dtype} {positions.shape}")
    F, P = positions.shape[:2]
    if status.shape != (F, P) or status.dtype.kind not in "iu":
        raise InvalidInputError(f"{where(file)}: status must be an integer ({F}, {P}) array; got {status.dtype} {status.shape}")
    if track_ids.shape != (P,) or track_ids.dtype.kind not in "iu":
        raise InvalidInputError(f"{where(file)}: track_ids must be an integer ({P},) array; got {track_ids.dtype} {track_ids.shape}")
    if len(np.unique(track_ids)) != P:
        raise InvalidInputError(f"{where(file)}: track_ids must be distinct")
    if P and (track_ids.min() < 0 or track_ids.max() > MAX_INDEX):
        raise InvalidInputError(f"{where(file)}: track_ids must be in 0 … {MAX_INDEX}")
    bad_code = ~np.isin(status, [int(s) for s in TrackStatus])
    if bad_code.any():
        f, p = np.argwhere(bad_code)[0]
        raise InvalidInputError(f"{where(file)}: status[{f}, {p}] = {status[f, p]}; expected one of {', '.join(str(int(s)) for s in TrackStatus)}")
    xy = positions.astype(np.float64)
    bad = np.isin(status, POSITION_CODES) & ~np.isfinite(xy).all(axis=2)
    if bad.any():
        f, p = np.argwhere(bad)[0]
        raise InvalidInputError(f"{where(file)}: positions[{f}, {p}] = {xy[f, p].tolist()} is not finite but status says {TrackStatus(status[f, p]).label}")
    far = np.abs(np.nan_to_num(xy)) > MAX_COORDINATE_PX
    if far.any():
        f, p, _ = np.argwhere(far)[0]
        raise InvalidInputError(f"{where(file)}: positions[{f}, {p}] = {xy[f, p].tolist()} is beyond ±{MAX_COORDINATE_PX:g} px")
    frames = np.arange(F)
    if "frames" in arrays:
        frames = arrays["frames"]
        if frames.shape != (F,) or frames.dtype.kind not in "iu":
            raise InvalidInputError(f"{where(file)}: frames must be an integer ({F},) array; got {frames.dtype} {frames.shape}")
        if F and (frames.min() < 0 or frames.max() > MAX_INDEX or (np.diff(frames) <= 0).any()):
            raise InvalidInputError(f"{where(file)}: frames must be increasing frame numbers in 0 … {MAX_INDEX}")
    states = _real(file, arrays, "states", (F, P, 4))
    covariances = _real(file, arrays, "covariances", (F, P, 4, 4))
    scores = _real(file, arrays, "scores", (F, P))
    if covariances is not None:
        variances = np.stack([covariances[..., 0, 0], covariances[..., 1, 1]], axis=-1)
        bad = np.isin(status, MEASUREMENT_CODES) & ~(np.isfinite(variances) & (variances > 0)).all(axis=2)
        if bad.any():
            f, p = np.argwhere(bad)[0]
            raise InvalidInputError(f"{where(file)}: covariances[{f}, {p}] has a non-positive or non-finite position variance")
    size = arrays.get("image_size")
    if size is not None and (size.shape != (2,) or size.dtype.kind not in "iu" or (size <= 0).any()):
        raise InvalidInputError(f"{where(file)}: image_size must be two positive integers (width, height); got {size!r}")
    settings, smoothed = _meta(file, arrays)
    return Tracks(
        positions=xy,
        status=status.astype(np.int8),
        track_ids=track_ids.astype(np.int64),
        states=states,
        covariances=covariances,
        frames=frames.astype(np.int64),
        scores=scores,
        image_size=None if size is None else (int(size[0]), int(size[1])),
        settings=settings,
        smoothed=smoothed,
    )


# --- start points ------------------------------------------------------------------------------


def read_points_csv(path: str | os.PathLike[str], *, with_lines: bool = False) -> tuple:
    """Points to track from a CSV with a header holding ``x``, ``y`` and optionally ``track_id``.

    Returns
    -------
    points : (P, 2) float64 (x, y).
    track_ids : (P,) int64, or None when the file has no ``track_id`` column.
    lines : (P,) int64, only ``with_lines``: the file's 1-based line of each point
        (for :func:`check_points_inside`).

    Raises
    ------
    InvalidInputError
        ``FILE: line N: …``, N the 1-based line of the file where the problem is (the header's for a
        missing column).

    Examples
    --------
    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "points.csv"
    >>> _ = p.write_text("x,y,track_id\\n118,78,7\\n117,89,8\\n")
    >>> read_points_csv(p)
    (array([[118.,  78.],
           [117.,  89.]]), array([7, 8]))
    """
    path = Path(path)
    header, _, rows = read_rows(path, "with columns x,y (and optionally track_id)", required=("x", "y"))
    column = {name: i for i, name in enumerate(header)}
    has_ids = "track_id" in column
    points = np.empty((len(rows), 2))
    ids = np.empty(len(rows), np.int64)
    lines = np.array([line for line, _ in rows], dtype=np.int64)
    seen: dict[int, int] = {}
    for k, (line, fields) in enumerate(rows):
        x, y = fields[column["x"]], fields[column["y"]]
        try:
            points[k] = float(x), float(y)
        except ValueError:
            raise InvalidInputError(f"{where(path, line)}: x and y must be numbers; got x={x!r}, y={y!r}") from None
        if not np.isfinite(points[k]).all():
            raise InvalidInputError(f"{where(path, line)}: x and y must be finite; got {x}, {y}")
        if has_ids:
            text = fields[column["track_id"]]
            try:
                number = float(text)
            except ValueError:
                number = np.nan
            if not (np.isfinite(number) and number == int(number) and 0 <= number <= MAX_INDEX):
                raise InvalidInputError(
                    f"{where(path, line)}: track_id must be an integer in 0 … {MAX_INDEX}; got {text!r}"
                )
            ids[k] = int(number)
            if int(ids[k]) in seen:
                raise InvalidInputError(f"{where(path, line)}: track_id {ids[k]} repeats line {seen[int(ids[k])]}")
            seen[int(ids[k])] = line
    if with_lines:
        return points, (ids if has_ids else None), lines
    return points, (ids if has_ids else None)


def check_points_inside(points: np.ndarray, width: int, height: int, source: str,
                        lines: np.ndarray | None = None) -> None:
    """Raise ``SOURCE: line N: …`` for the first point outside a ``width``×``height`` image.

    ``lines`` are the file's 1-based line of each point (``read_points_csv(..., with_lines=True)``);
    without them the points are taken to follow the header on lines 2, 3, ….
    """
    outside = (points[:, 0] < 0) | (points[:, 0] > width - 1) | (points[:, 1] < 0) | (points[:, 1] > height - 1)
    if outside.any():
        k = int(np.flatnonzero(outside)[0])
        line = int(lines[k]) if lines is not None else k + 2
        raise InvalidInputError(
            f"{where(source, line)}: point ({points[k, 0]:g}, {points[k, 1]:g}) lies outside the {width}×{height} image"
        )
