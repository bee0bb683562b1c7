"""What each run function is asked to do: one frozen, validated request per command.

A request holds every option that shapes a run's result, with the library's defaults, and is
checked when it is made: a bad field raises :class:`~kalmansfm.errors.InvalidInputError` naming
the field (``fields`` on the exception lists the names it mentions, so that the command line can
put its own flag names in their place).  The request, less where the run is written
(``out``) and how it shows progress, is what the run's ``summary.json`` records as its source
(:func:`request_options`), so that ``batch`` can tell whether a finished run answers the same request.

The camera of a reconstruction is one of

* :class:`Affine` — orthographic cameras: Tomasi–Kanade factorization;
* :class:`Perspective` — calibrated pinhole cameras with unknown motion, from ``intrinsics`` (a
  ``K.csv``) or ``focal`` (pixels, principal point at the image centre);
* :class:`Auto` — both, keeping the perspective model when it explains the tracks at least as well.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Union

import numpy as np

from .._validation import check_count, check_positive
from ..errors import InvalidInputError
from ..features import FeatureSettings
from ..scenes import DEFAULT_SCENE_FRAMES, DEFAULT_SCENE_SEED
from ..structure.affine.factorization import DEFAULT_MAX_ITERATIONS
from ..structure.fusion import FusionSettings
from ..structure.perspective import PerspectiveSettings
from ..tracking import TrackerSettings

__all__ = [
    "Affine",
    "Auto",
    "Camera",
    "DemoRequest",
    "FuseRequest",
    "Perspective",
    "ReconstructRequest",
    "TrackRequest",
    "request_options",
]

PathLike = Union[str, "os.PathLike[str]"]


def _path(value: PathLike | None) -> Path | None:
    return None if value is None else Path(value)


@dataclass(frozen=True)
class Affine:
    """Affine (orthographic) cameras: factorization of the tracks.

    Every camera request names its ``model`` (``affine``, ``perspective``, ``auto``), as the
    run's recorded options show it.

    Attributes
    ----------
    weighted : weight each observation by 1 / σ², σ the tracker's posterior standard deviation
        (when the tracks carry it).
    max_iterations : cap on the missing-data refinement iterations.

    Examples
    --------
    >>> Affine().max_iterations
    500
    >>> Affine(max_iterations=0)
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: max_iterations must be an integer >= 1; got 0
    """

    weighted: bool = True
    max_iterations: int = DEFAULT_MAX_ITERATIONS
    model: str = field(default="affine", init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "weighted", bool(self.weighted))
        object.__setattr__(self, "max_iterations", check_count("max_iterations", self.max_iterations, 1))


@dataclass(frozen=True)
class Perspective:
    """Calibrated pinhole cameras with unknown motion.

    Attributes
    ----------
    intrinsics : a ``K.csv`` (one row for every frame, or one per frame) …
    focal : … or the focal length in pixels, the principal point at the image centre; exactly
        one of the two.
    image_size : (width, height) for ``focal`` when the input does not record it.
    settings : how the reconstruction runs (method, outlier test, …).

    Examples
    --------
    >>> Perspective(focal=800.0).focal
    800.0
    >>> Perspective()
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: a perspective camera needs its calibration: give intrinsics (a K.csv) or focal (pixels), exactly one
    """

    intrinsics: Path | None = None
    focal: float | None = None
    image_size: tuple[int, int] | None = None
    settings: PerspectiveSettings = field(default_factory=PerspectiveSettings)
    model: str = field(default="perspective", init=False)

    def __post_init__(self) -> None:
        if (self.intrinsics is None) == (self.focal is None):
            raise InvalidInputError("a perspective camera needs its calibration: give intrinsics (a K.csv) or focal "
                                    "(pixels), exactly one", fields=("intrinsics", "focal"))
        object.__setattr__(self, "intrinsics", _path(self.intrinsics))
        if self.focal is not None:
            object.__setattr__(self, "focal", check_positive("focal", self.focal, "pixels"))
        if self.image_size is not None:
            size = tuple(self.image_size)
            if len(size) != 2:
                raise InvalidInputError(f"image_size must be (width, height); got {self.image_size!r}",
                                        fields=("image_size",))
            object.__setattr__(self, "image_size", (check_count("image_size", size[0], 1),
                                                    check_count("image_size", size[1], 1)))
        if not isinstance(self.settings, PerspectiveSettings):
            raise InvalidInputError(f"settings must be a PerspectiveSettings; got {type(self.settings).__name__}",
                                    fields=("settings",))


@dataclass(frozen=True)
class Auto:
    """Both camera models; the perspective one is kept when its reprojection RMS over its inliers is
    at most the affine one's (the affine one when the perspective reconstruction is impossible)."""

    perspective: Perspective
    affine: Affine = field(default_factory=Affine)
    model: str = field(default="auto", init=False)


Camera = Union[Affine, Perspective, Auto]


def _check_camera(camera: object, allowed: tuple[type, ...]) -> None:
    if not isinstance(camera, allowed):
        names = " or ".join(kind.__name__ for kind in allowed)
        raise InvalidInputError(f"camera must be {names}; got {type(camera).__name__}", fields=("camera",))


@dataclass(frozen=True)
class ReconstructRequest:
    """``reconstruct``: shape and cameras from a tracks file.

    Attributes
    ----------
    tracks : ``tracks.npz``, ``tracks.csv`` or a ``frame,track_id,x,y`` CSV.
    out : the run folder.
    camera : :class:`Affine`, :class:`Perspective` or :class:`Auto`.
    smooth : None smooths a tracker's ``tracks.npz`` that is not smoothed yet for the affine
        model and reads anything else as it is; True requires smoothing; False never smooths.
    plot : draw the figures.
    progress : progress bars on stderr.

    Examples
    --------
    >>> ReconstructRequest("t.csv", "out").camera
    Affine(weighted=True, max_iterations=500, model='affine')
    """

    tracks: Path
    out: Path
    camera: Camera = field(default_factory=Affine)
    smooth: bool | None = None
    plot: bool = True
    progress: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "tracks", Path(self.tracks))
        object.__setattr__(self, "out", Path(self.out))
        _check_camera(self.camera, (Affine, Perspective, Auto))


@dataclass(frozen=True)
class FuseRequest:
    """``fuse``: 3-D points with covariances from tracks and known cameras.

    Attributes
    ----------
    tracks, cameras : the tracks file and the cameras file.
    out : the run folder.
    settings : how the fusion runs (its history is always kept: ``history.csv``).
    scheduler, workers : fuse the chunks on Dask — an existing scheduler's address, or a local
        cluster of ``workers`` processes (not both); neither: in this process.
    plot : draw fusion.png.
    progress : a progress bar on stderr.
    """

    tracks: Path
    cameras: Path
    out: Path
    settings: FusionSettings = field(default_factory=FusionSettings)
    scheduler: str | None = None
    workers: int | None = None
    plot: bool = True
    progress: bool = False

    def __post_init__(self) -> None:
        for name in ("tracks", "cameras", "out"):
            object.__setattr__(self, name, Path(getattr(self, name)))
        if not isinstance(self.settings, FusionSettings):
            raise InvalidInputError(f"settings must be a FusionSettings; got {type(self.settings).__name__}",
                                    fields=("settings",))
        object.__setattr__(self, "settings", replace(self.settings, history=True))


@dataclass(frozen=True)
class TrackRequest:
    """``track``: points followed through a sequence.

    Attributes
    ----------
    input : a folder of images (natural order), a glob or a video.
    out : the run folder.
    points : a CSV of frame-0 points ``x,y[,track_id]``; None detects corners.
    settings : the tracker's settings.
    smooth : False, True (fixed-interval RTS smoothing) or a lag in frames (fixed-lag).
    progress : a progress bar on stderr.
    features : instead of the Kalman tracker, tracks by descriptor matching (:mod:`kalmansfm.features`):
        features of every frame matched over a window of neighbouring frames and the most similar
        frames anywhere in the clip (so a point that leaves and comes back keeps its track), verified
        by the epipolar geometry, joined into tracks; for wide baselines or revisits.
    """

    input: Path
    out: Path
    points: Path | None = None
    settings: TrackerSettings = field(default_factory=TrackerSettings)
    smooth: bool | int = False
    progress: bool = False
    features: FeatureSettings | None = None

    def __post_init__(self) -> None:
        if self.features is not None and (self.points is not None or self.smooth is not False):
            raise InvalidInputError("tracks matched by features begin at the features found and have no filter: "
                                    "give neither points nor smooth", fields=("points", "smooth"))
        object.__setattr__(self, "input", Path(self.input))
        object.__setattr__(self, "out", Path(self.out))
        object.__setattr__(self, "points", _path(self.points))
        if not isinstance(self.smooth, bool):
            object.__setattr__(self, "smooth", check_count("smooth", self.smooth, 0))


@dataclass(frozen=True)
class DemoRequest:
    """``demo``: frames → tracks → structure → report in one run.

    Attributes
    ----------
    out : the run folder.
    input : a folder of images, a glob or a video; None renders the built-in scene of ``seed``
        and ``n_frames`` (its frame-0 corners are tracked and its ground truth compared).
    seed, n_frames : the built-in scene.
    points, track_ids : frame-0 points to track in ``input`` ((N, 2) and (N,); None: detect corners).
    tracker : the tracker's settings.
    smooth : RTS-smooth the tracks before they are written, scored and factorized.
    camera : :class:`Affine` (default) or :class:`Perspective` (needs ``input``; the measured,
        unsmoothed tracks are reconstructed with its intrinsics or focal length).
    save_frames : copy the frames into ``frames/`` (the report draws on them).
    html : build ``report.html``.
    progress : progress bars on stderr.
    command : recorded in ``summary.json`` (``demo``, or ``batch`` for its sequences).
    """

    out: Path
    input: Path | None = None
    seed: int = DEFAULT_SCENE_SEED
    n_frames: int = DEFAULT_SCENE_FRAMES
    points: np.ndarray | None = None
    track_ids: np.ndarray | None = None
    tracker: TrackerSettings = field(default_factory=TrackerSettings)
    smooth: bool = True
    camera: Camera = field(default_factory=Affine)
    save_frames: bool = True
    html: bool = True
    progress: bool = False
    command: str = "demo"

    def __post_init__(self) -> None:
        object.__setattr__(self, "out", Path(self.out))
        object.__setattr__(self, "input", _path(self.input))
        _check_camera(self.camera, (Affine, Perspective))
        if isinstance(self.camera, Perspective):
            if self.input is None:
                raise InvalidInputError("a perspective camera needs your own sequence as input: the built-in scene "
                                        "is seen by an affine camera", fields=("input",))


#: request fields that say where and how a run is shown, not what it computes.
_NOT_RESULT = frozenset({"out", "progress", "command", "scheduler", "workers"})


def request_options(request: Any) -> dict[str, Any]:
    """The fields of ``request`` that shape the result, as the options a run's source records.

    The input files themselves (top-level paths) are left out: the source identifies them by
    their resolved paths, sizes and times.

    Examples
    --------
    >>> sorted(request_options(ReconstructRequest("t.csv", "out")))
    ['camera', 'plot', 'smooth']
    """
    return {f.name: value for f in fields(request)
            if f.name not in _NOT_RESULT and not isinstance(value := getattr(request, f.name), Path)}
