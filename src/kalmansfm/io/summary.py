"""``summary.json``: the one record of a run, its schema, its writer and its reader.

Every command that writes a run folder (``demo``, ``track``, ``reconstruct``, ``fuse``,
``scene``, each sequence of ``batch``) describes it with one :class:`RunSummary`; the report, the
batch runner and anyone scripting against the folder read it back with
:func:`read_summary`.  The JSON layout is the record's own (field names as keys, nested
records as objects, non-finite numbers as null) and carries ``schema_version``.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..errors import InvalidInputError
from ..tracking.settings import TrackerSettings
from ._csv import where
from .records import from_json, to_json

__all__ = [
    "SCHEMA_VERSION",
    "SUMMARY_FILE",
    "RunSource",
    "RunSummary",
    "Versions",
    "TrackMetrics",
    "TrackingMetrics",
    "ReconstructionMetrics",
    "Similarity",
    "TruthComparison",
    "read_summary",
    "run_files",
    "run_source",
    "summary_json",
]

#: Version of the ``summary.json`` layout; readers refuse other versions.  Version 4 replaced the
#: ``structure``, ``fusion`` and ``perspective`` records by one ``reconstruction``
#: (:class:`ReconstructionMetrics`) for every method; version 3 added the run's ``source``.
SCHEMA_VERSION = 4
SUMMARY_FILE = "summary.json"


@dataclass(frozen=True)
class Versions:
    """The software a run was made with."""

    kalmansfm: str = __version__
    python: str = field(default_factory=platform.python_version)
    numpy: str = np.__version__


@dataclass(frozen=True)
class TrackMetrics:
    """One track's statistics (no ground truth needed)."""

    track_id: int
    frames_measured: int
    frames_predicted: int
    lost_at: int | None
    mean_std_px: float | None


@dataclass(frozen=True)
class TrackingMetrics:
    """What the tracker did, without ground truth.

    Attributes
    ----------
    frames, tracks : F and P.
    measured_fraction : of the track-frames with a position, the fraction measured.
    alive_in_last_frame : tracks with a position in the last frame.
    survival_of_first_frame_tracks : fraction of frame 0's tracks alive in the last frame.
    lost : tracks declared lost.
    mean_covariance_trace : per frame, the mean trace of the state covariance over the
        tracks alive (None where none is).
    per_track : one :class:`TrackMetrics` per column of the tracks.
    """

    frames: int
    tracks: int
    measured_fraction: float
    alive_in_last_frame: int
    survival_of_first_frame_tracks: float
    lost: int
    mean_covariance_trace: tuple[float | None, ...]
    per_track: tuple[TrackMetrics, ...]


@dataclass(frozen=True)
class ReconstructionMetrics:
    """A reconstruction's figures, whatever made it (the points and cameras are in their own files).

    Built by :func:`kalmansfm.pipeline.evaluate.reconstruction_metrics` from a
    :class:`~kalmansfm.structure.Reconstruction`; the fields after ``warnings`` belong to some
    methods only and are None (or empty) for the others.

    Attributes
    ----------
    kind : ``"affine"`` (factorization), ``"fusion"`` (known cameras) or ``"perspective"``
        (calibrated, unknown motion).
    method : the method within it (``svd``/``als``; ``recursive``/``batch``/``pairs``; ``batch``/``recursive``).
    camera_model : ``"affine"`` or ``"pinhole"``.
    frames, registered_frames : frames of the input and how many got a camera; ``unregistered``
        lists the others (frame numbers).
    points : tracks read; ``reconstructed`` (status ``ok``), ``unreliable``, ``too_few_views``,
        ``degenerate`` and ``behind_camera`` count them by :class:`~kalmansfm.structure.PointStatus`.
    observations : measured positions in the frames; ``used`` of them made the estimate and an
        outlier test ``rejected`` some of the rest.
    noise_std : σ the covariances are scaled with (pixels, or of unit weight: ``noise_unit``);
        ``noise_estimated`` when it came from the residuals with ``degrees_of_freedom``;
        ``noise_model`` names the model.
    reprojection_rms_px : RMS length of the reprojection errors over the observations used.
    median_point_std : median over ``ok`` points of √(tr Σ / 3), in the points' unit.
    median_centre_std : median over registered cameras of the centre's √(tr Σ_C / 3) (estimated poses only).
    covariance_gauge : how the covariances are to be read.
    warnings : the reconstruction's own warnings.
    singular_values, iterations, weighted, smoothed : factorization: the leading singular values
        of the measurement matrix, ALS iterations, weighting by the tracker's variances, and
        whether the tracks were RTS-smoothed (True or the lag).
    initial_pair, outlier_threshold_px : calibrated: the frames it started from, the outlier threshold.
    outlier_probability : the χ² gate's probability (fusion and calibrated).
    orientation, passes : fusion: +1, or -1 for a mirrored scene; passes over the data.
    intrinsics : calibrated: where K came from (a K.csv, or the focal length and image size).
    camera_choice : with ``--camera auto``, which model was kept and why.
    skipped_frames : frames that had observations but no camera (fusion: skipped).
    noise_parameters : the noise model's other fitted parameters, (name, value) pairs (e.g. the outlier
        share, the tails' degrees of freedom, the serial correlation of the residuals along a track).
    """

    kind: str
    method: str
    camera_model: str
    frames: int
    registered_frames: int
    unregistered: tuple[int, ...]
    points: int
    reconstructed: int
    unreliable: int
    too_few_views: int
    degenerate: int
    behind_camera: int
    observations: int
    used: int
    rejected: int
    noise_std: float | None
    noise_estimated: bool
    noise_unit: str
    noise_model: str
    degrees_of_freedom: int
    reprojection_rms_px: float | None
    median_point_std: float | None
    median_centre_std: float | None
    covariance_gauge: str
    warnings: tuple[str, ...] = ()
    singular_values: tuple[float, ...] = ()
    iterations: int | None = None
    weighted: bool | None = None
    smoothed: bool | int | None = None
    initial_pair: tuple[int, int] | None = None
    outlier_threshold_px: float | None = None
    outlier_probability: float | None = None
    orientation: int | None = None
    passes: int | None = None
    intrinsics: str | None = None
    camera_choice: str | None = None
    skipped_frames: tuple[int, ...] = ()
    noise_parameters: tuple[tuple[str, float], ...] = ()


@dataclass(frozen=True)
class Similarity:
    """``target ≈ scale * rotation @ source + translation``; ``rotation`` may be a reflection (det -1)."""

    scale: float
    rotation: tuple[tuple[float, float, float], ...]
    translation: tuple[float, float, float]

    @property
    def mirrored(self) -> bool:
        """True when the best fit is a mirror image (the depth-reversal ambiguity)."""
        return bool(np.linalg.det(np.asarray(self.rotation)) < 0)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``scale * R p + t`` for each row p of ``points`` (N, 3)."""
        return self.scale * np.asarray(points) @ np.asarray(self.rotation).T + np.asarray(self.translation)

    def invert(self, points: np.ndarray) -> np.ndarray:
        """The source points that :meth:`apply` maps onto ``points``."""
        return (np.asarray(points) - np.asarray(self.translation)) @ np.asarray(self.rotation) / self.scale


@dataclass(frozen=True)
class TruthComparison:
    """A run compared with ground truth (synthetic scenes, labelled data).

    Attributes
    ----------
    tracking_rms_error_px : RMS distance of the measured estimates from the true positions
        (over the frame-track pairs where the point is visible and was measured).
    within_2px : fraction of those estimates within 2 px.
    median_error_px, max_error_px : the median and the largest of those distances.
    visible_measured_fraction : of the visible frame-track pairs, the fraction measured.
    rms_error_per_frame_px : per frame (None where nothing was compared).
    per_track_rms_error_px : per column of the tracks (None where nothing was compared).
    shape_error_pct : RMS distance of the recovered points from the truth after the best
        similarity (mirror allowed), in percent of the object's RMS radius.
    rotation_error_deg : per frame, the recovered camera rotation's error.
    alignment : the similarity taking the recovered points (as in ``structure.csv``) onto the truth.
    """

    tracking_rms_error_px: float | None = None
    within_2px: float | None = None
    median_error_px: float | None = None
    max_error_px: float | None = None
    visible_measured_fraction: float | None = None
    rms_error_per_frame_px: tuple[float | None, ...] = ()
    per_track_rms_error_px: tuple[float | None, ...] = ()
    shape_error_pct: float | None = None
    rotation_error_deg: tuple[float | None, ...] = ()
    alignment: Similarity | None = None


@dataclass(frozen=True)
class RunSource:
    """What a run was made from: its input files and the options that shape the result.

    Two runs with equal sources read the same files (same resolved paths, sizes and
    modification times) with the same options; ``batch`` keeps a finished run only when
    its source equals the one it would run now.  Built by :func:`run_source`.

    Attributes
    ----------
    input : the input's resolved absolute path, or a description of a generated input.
    files : number of files read.
    total_bytes : their total size.
    fingerprint : SHA-256 (hex) over each file's resolved path, size and modification time (ns).
    options : (name, value as compact JSON), sorted by name, of every option that changes the result.
    """

    input: str
    files: int = 0
    total_bytes: int = 0
    fingerprint: str = ""
    options: tuple[tuple[str, str], ...] = ()


def _option_text(value: Any) -> str:
    if isinstance(value, np.ndarray):  # start points: their digest, not hundreds of numbers
        digest = hashlib.sha256(np.ascontiguousarray(value).tobytes()).hexdigest()[:16]
        return json.dumps(f"{value.dtype}{list(value.shape)} sha256:{digest}")
    return json.dumps(to_json(value), sort_keys=True, separators=(",", ":"), allow_nan=False)


def run_source(input: str | os.PathLike[str], files: Iterable[str | os.PathLike[str]],
               options: Mapping[str, Any]) -> RunSource:
    """The :class:`RunSource` of a run that reads ``files`` (its input ``input``) with ``options``.

    ``input`` is resolved when it is a path that exists; a description of a generated
    input (the built-in scene) is kept as it is.  The files are identified by resolved
    path, size and modification time, not by content: a file rewritten with new content
    gets a new time, and hashing gigabytes of video on every ``batch`` rerun is avoided.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> f = pathlib.Path(tempfile.mkdtemp()) / "tracks.csv"
    >>> _ = f.write_text("frame,track_id,x,y\\n")
    >>> a = run_source(f, [f], {"weighted": True})
    >>> a.files, a.total_bytes, a.options
    (1, 19, (('weighted', 'true'),))
    >>> a == run_source(f, [f], {"weighted": True}), a == run_source(f, [f], {"weighted": False})
    (True, False)
    """
    where = Path(input)
    described = str(where.resolve()) if where.exists() else os.fspath(input)
    digest = hashlib.sha256()
    count = total = 0
    for file in files:
        resolved = Path(file).resolve()
        stat = resolved.stat()
        digest.update(f"{resolved}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode("utf-8", "surrogateescape"))
        count, total = count + 1, total + stat.st_size
    pairs = tuple(sorted((str(name), _option_text(value)) for name, value in options.items()))
    return RunSource(input=described, files=count, total_bytes=total, fingerprint=digest.hexdigest(), options=pairs)


@dataclass(frozen=True)
class RunSummary:
    """Everything known about one run, written as ``summary.json``.

    Attributes
    ----------
    command : the command that made the run (``demo``, ``track``, ``reconstruct``, ``fuse``, ``scene``, ``batch``).
    input : what was read: a path, or a description of the built-in scene.
    source : what the run was made from, precisely (resolved input files and options).
    created : ISO time stamp (UTC).
    versions : software versions.
    settings : the tracker's settings (runs that tracked).
    smoothed : the tracks were RTS-smoothed (True or the lag) or not.
    tracking : tracking statistics.
    reconstruction : the reconstruction's figures, whatever method made it.
    structure_error : why there is no reconstruction when one was attempted and failed.
    truth : the comparison with ground truth, when there is one.
    scene : the parameters of a rendered built-in scene.
    timings_s : seconds per step, in order.
    total_s : the run's wall-clock time from start to the last result file; building
        ``report.html`` is not part of it (``demo`` prints that time apart).
    files : the files of the run folder this run wrote (relative paths); readers use only these.
    warnings : things the user should know about the result.
    schema_version : the layout version.
    """

    command: str
    input: str
    source: RunSource | None = None
    created: str = field(default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds"))
    versions: Versions = field(default_factory=Versions)
    settings: TrackerSettings | None = None
    smoothed: bool | int = False
    tracking: TrackingMetrics | None = None
    reconstruction: ReconstructionMetrics | None = None
    structure_error: str | None = None
    truth: TruthComparison | None = None
    scene: Any = None
    timings_s: tuple[tuple[str, float], ...] = ()
    total_s: float | None = None
    files: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    schema_version: int = SCHEMA_VERSION

    @property
    def all_warnings(self) -> tuple[str, ...]:
        """The run's warnings, then its reconstruction's: what every command shows the user."""
        own = () if self.reconstruction is None else self.reconstruction.warnings
        return tuple(dict.fromkeys((*self.warnings, *own)))

    def warning_lines(self) -> list[str]:
        """:attr:`all_warnings` as the commands print them, one ``warning: …`` line each.

        Returns
        -------
        list of str
            One line (no newline) per warning, in the order of :attr:`all_warnings`.

        Examples
        --------
        >>> RunSummary(command="fuse", input="t.csv", warnings=("frames were skipped: 14",)).warning_lines()
        ['warning: frames were skipped: 14']
        """
        return [f"warning: {note}" for note in self.all_warnings]


def summary_json(summary: RunSummary) -> str:
    """The text of ``summary.json`` for ``summary``.

    Examples
    --------
    >>> text = summary_json(RunSummary(command="track", input="clip.mp4"))
    >>> import json; json.loads(text)["schema_version"]
    4
    """
    return json.dumps(to_json(summary), indent=2, allow_nan=False) + "\n"


def read_summary(path: str | os.PathLike[str]) -> RunSummary:
    """Read and check ``summary.json``.

    Raises
    ------
    InvalidInputError
        If the file is missing, is not JSON, has another schema version, or a field does
        not fit the schema (the message names the field).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "summary.json"
    >>> _ = p.write_text(summary_json(RunSummary(command="scene", input="built-in scene (seed 0)")))
    >>> read_summary(p).input
    'built-in scene (seed 0)'
    """
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"{where(path)}: not found; a run folder must contain the summary.json that kalmansfm writes")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InvalidInputError(f"{where(path)}: not UTF-8 text; expected a JSON object") from None
    except json.JSONDecodeError as exc:
        raise InvalidInputError(f"{where(path, exc.lineno)}: not valid JSON (column {exc.colno}: {exc.msg})") from None
    if not isinstance(data, dict):
        raise InvalidInputError(f"{where(path)}: expected a JSON object at the top level; got {type(data).__name__}")
    version = data.get("schema_version")
    if version != SCHEMA_VERSION:
        raise InvalidInputError(
            f"{where(path)}: schema_version {version!r} is not {SCHEMA_VERSION}; it was written by another kalmansfm version "
            f"(rerun the command that made it)"
        )
    return from_json(RunSummary, data, str(path))


def run_files(folder: str | os.PathLike[str]) -> frozenset[str] | None:
    """The top-level names of the run in ``folder`` (its summary.json and what that lists), or None.

    None when ``folder`` holds no ``summary.json`` written by kalmansfm.  A summary of any
    schema version counts, so that a run of another kalmansfm version can be replaced;
    one that lists no files claims everything in the folder.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> run_files(d) is None
    True
    >>> _ = (d / "summary.json").write_text(summary_json(RunSummary("track", "x", files=("frames/a.png", "summary.json"))))
    >>> sorted(run_files(d))
    ['frames', 'summary.json']
    """
    folder = Path(folder)
    try:
        data = json.loads((folder / SUMMARY_FILE).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if not (isinstance(data, dict) and isinstance(data.get("command"), str) and "schema_version" in data):
        return None
    listed = data.get("files")
    if not isinstance(listed, list):
        return frozenset(entry.name for entry in folder.iterdir())
    return frozenset({SUMMARY_FILE, *(str(name).split("/")[0] for name in listed)})
