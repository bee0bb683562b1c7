"""``summary.json``: the one record of a run, its schema, its writer and its reader.

Every command that writes a run folder (``demo``, ``track``, ``reconstruct``, ``scene``,
each sequence of ``batch``) describes it with one :class:`RunSummary`; the report, the
batch runner and anyone scripting against the folder read it back with
:func:`read_summary`.  The JSON layout is the record's own (field names as keys, nested
records as objects, non-finite numbers as null) and carries ``schema_version``.
"""

from __future__ import annotations

import json
import os
import platform
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..errors import InvalidInputError
from ..tracking.settings import TrackerSettings
from .records import from_json, to_json

__all__ = [
    "SCHEMA_VERSION",
    "SUMMARY_FILE",
    "RunSummary",
    "Versions",
    "TrackMetrics",
    "TrackingMetrics",
    "StructureMetrics",
    "Similarity",
    "TruthComparison",
    "read_summary",
    "summary_json",
]

#: Version of the ``summary.json`` layout; readers refuse other versions.
SCHEMA_VERSION = 2
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
class StructureMetrics:
    """A factorization's figures (the recovered points and motion are in their own files).

    Attributes
    ----------
    method : ``"closed-form"`` or ``"als"`` (missing data or weights).
    frames, points : size of the measurement matrix.
    reconstructed_frames, reconstructed_points : how many got a camera / a 3D point.
    iterations : refinement iterations (0 for the closed form).
    singular_values : the leading singular values of the registered measurement matrix.
    residual_rms_px : RMS residual of the rank-3 fit, pixels.
    weighted : observations weighted by the tracker's posterior variances.
    smoothed : the positions were RTS-smoothed (True, or the lag), or not (False).
    warnings : degeneracies found (not clearly rank 3, little rotation, …).
    """

    method: str
    frames: int
    points: int
    reconstructed_frames: int
    reconstructed_points: int
    iterations: int
    singular_values: tuple[float, ...]
    residual_rms_px: float
    weighted: bool
    smoothed: bool | int
    warnings: tuple[str, ...] = ()


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
    visible_measured_fraction: float | None = None
    rms_error_per_frame_px: tuple[float | None, ...] = ()
    per_track_rms_error_px: tuple[float | None, ...] = ()
    shape_error_pct: float | None = None
    rotation_error_deg: tuple[float | None, ...] = ()
    alignment: Similarity | None = None


@dataclass(frozen=True)
class RunSummary:
    """Everything known about one run, written as ``summary.json``.

    Attributes
    ----------
    command : the command that made the run (``demo``, ``track``, ``reconstruct``, ``scene``, ``batch``).
    input : what was read: a path, or a description of the built-in scene.
    created : ISO time stamp (UTC).
    versions : software versions.
    settings : the tracker's settings (runs that tracked).
    smoothed : the tracks were RTS-smoothed (True or the lag) or not.
    tracking : tracking statistics.
    structure : the factorization's figures.
    structure_error : why there is no structure when factorization was attempted and failed.
    truth : the comparison with ground truth, when there is one.
    scene : the parameters of a rendered built-in scene.
    timings_s : seconds per step, in order.
    total_s : the run's wall-clock time from start to the last file.
    files : the files of the run folder this run wrote (relative paths); readers use only these.
    warnings : things the user should know about the result.
    schema_version : the layout version.
    """

    command: str
    input: str
    created: str = field(default_factory=lambda: datetime.now(timezone.utc).isoformat(timespec="seconds"))
    versions: Versions = field(default_factory=Versions)
    settings: TrackerSettings | None = None
    smoothed: bool | int = False
    tracking: TrackingMetrics | None = None
    structure: StructureMetrics | None = None
    structure_error: str | None = None
    truth: TruthComparison | None = None
    scene: Any = None
    timings_s: tuple[tuple[str, float], ...] = ()
    total_s: float | None = None
    files: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()
    schema_version: int = SCHEMA_VERSION


def summary_json(summary: RunSummary) -> str:
    """The text of ``summary.json`` for ``summary``.

    Examples
    --------
    >>> text = summary_json(RunSummary(command="track", input="clip.mp4"))
    >>> import json; json.loads(text)["schema_version"]
    2
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
        raise InvalidInputError(f"{path}: not found; a run folder must contain the summary.json that kalmansfm writes")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InvalidInputError(f"{path}: is not UTF-8 text; expected a JSON object") from None
    except json.JSONDecodeError as exc:
        raise InvalidInputError(f"{path}: is not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    if not isinstance(data, dict):
        raise InvalidInputError(f"{path}: expected a JSON object at the top level; got {type(data).__name__}")
    version = data.get("schema_version")
    if version != SCHEMA_VERSION:
        raise InvalidInputError(
            f"{path}: schema_version {version!r} is not {SCHEMA_VERSION}; it was written by another kalmansfm version "
            f"(rerun the command that made it)"
        )
    return from_json(RunSummary, data, str(path))
