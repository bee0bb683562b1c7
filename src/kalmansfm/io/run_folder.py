"""Read the files of a finished run folder, checking each one at the boundary.

A run folder is what ``kalmansfm demo``, ``track``, ``reconstruct`` and ``scene`` write:
``summary.json`` (:class:`~kalmansfm.io.summary.RunSummary`) plus the files it lists.
:func:`load_run` reads only the files the summary lists, so nothing left in the folder by
another run can enter a report, and only inside the folder: a listed name that is absolute,
climbs out with ``..``, or is a symbolic link leading outside is refused before anything is
read (:func:`run_file`, the rule for every reader of a run folder).  Every reader raises
:class:`~kalmansfm.InvalidInputError` naming the file, the row or the field when a file
cannot be used; a file the run did not write is simply ``None``.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import cv2
import numpy as np

from ..errors import InvalidInputError
from ..structure.geometry.pinhole import CameraSet
from ..tracking.tracks import Tracks
from ._csv import read_rows, where
from .cameras import read_cameras
from .frames import decode_image_file, is_frames_video, read_frames
from .ground_truth import POINTS_FILE, TRACKS_FILE, read_ground_truth_tracks
from .paths import path_problem
from .structure import CameraMotion, PointTable, read_motion_csv, read_points_table
from .summary import SUMMARY_FILE, RunSummary, read_summary
from .tracks import read_tracks_npz

__all__ = ["CsvTable", "RunFolder", "load_run", "run_file", "RUN_FIGURES"]

#: Pre-rendered figures a run may carry, embedded in the report as they are.
RUN_FIGURES = ("covariance_trace.png", "tracks.png", "structure.png", "fusion.png", "reconstruction.png")

_FRAME_NAME = re.compile(r"^frames/frame_(\d+)\.png$")


@dataclass(frozen=True)
class CsvTable:
    """A CSV file shown verbatim (``fusion_tables/*.csv``)."""

    name: str
    header: list[str]
    rows: list[list[str]]


@dataclass(frozen=True)
class RunFolder:
    """Everything the report reads from one run folder; files the run did not write are ``None``.

    Attributes
    ----------
    ground_truth_tracks : (F, P, 2) true positions in the order of ``tracks.track_ids``,
        NaN where not visible (from ``ground_truth_tracks.csv``).
    cameras : the registered cameras of a perspective reconstruction (``cameras.csv``, read by
        :func:`~kalmansfm.io.cameras.read_cameras`: P = K [R | t]; ``decompose()`` gives K, R, t and the centres).
    """

    path: Path
    summary: RunSummary
    frame_paths: tuple[Path, ...]
    tracks: Tracks | None
    structure: PointTable | None
    motion: CameraMotion | None
    ground_truth_tracks: np.ndarray | None
    ground_truth_points: PointTable | None
    fusion_tables: tuple[CsvTable, ...]
    figures: dict[str, Path]
    data_files: tuple[str, ...]
    cameras: CameraSet | None = None
    frames_video: Path | None = None

    def read_frames(self) -> list[np.ndarray]:
        """The run's frame images (uint8, grey or BGR), in order; [] when the run kept none.

        A long sequence's frames come from the run's frames video (``frames.mp4``, or a copy of the
        input video), short ones from its PNG files.
        """
        if self.frames_video is not None:
            return [np.asarray(frame) for frame in read_frames(self.frames_video, min_frames=1)]
        frames = []
        for path in self.frame_paths:
            image = decode_image_file(path, cv2.IMREAD_UNCHANGED)
            if image is None:
                raise InvalidInputError(f"{where(path)}: cannot be read as a PNG image")
            if image.dtype != np.uint8:
                image = cv2.convertScaleAbs(image, alpha=255.0 / max(float(image.max()), 1.0))
            if image.ndim == 3 and image.shape[2] == 4:
                image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
            frames.append(image)
        return frames


def run_file(folder: str | os.PathLike[str], name: str) -> Path:
    """The path of the run file ``name`` (as ``summary.json`` lists it) inside ``folder``; refuse one that leaves it.

    A listed name must be relative and ``/``-separated without ``.`` or ``..`` parts, and what it
    names (symbolic links followed) must lie inside the folder.  This is the rule for every
    reader of a run folder: nothing outside it is ever read or written.

    Raises
    ------
    InvalidInputError
        ``FOLDER/summary.json: lists '../../etc/passwd', which is not a file of the run folder (…)``.

    Examples
    --------
    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> run_file(d, "frames/frame_000.png") == d / "frames" / "frame_000.png"
    True
    >>> run_file(d, "../../etc/passwd")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    kalmansfm.errors.InvalidInputError: .../summary.json: lists '../../etc/passwd', which is not a file of the run folder (a run names its files relative to its folder, without '..')
    """
    base = Path(folder)
    summary = base / SUMMARY_FILE

    def refuse(why: str) -> InvalidInputError:
        return InvalidInputError(f"{where(summary)}: lists {name!r}, which is not a file of the run folder ({why})")

    text = name if isinstance(name, str) else ""
    parts = PurePosixPath(text).parts
    if (not parts or PurePosixPath(text).is_absolute() or "\\" in text or "\x00" in text or ":" in parts[0]
            or {".", ".."} & set(text.split("/")) or "" in text.split("/")):
        raise refuse("a run names its files relative to its folder, without '..'")
    path = base.joinpath(*parts)
    try:
        inside = path.resolve().is_relative_to(base.resolve())
    except (OSError, RuntimeError):
        raise refuse("a symbolic link loop") from None
    if not inside:
        raise refuse(f"it leads to {path.resolve()}, outside the folder")
    problem = path_problem(path)
    if problem is not None:
        raise refuse(f"it is {problem}")
    return path


def _read_csv_table(path: Path) -> CsvTable:
    header, _, rows = read_rows(path, "row (the table's column names)", allow_no_rows=True)
    return CsvTable(path.stem, header, [fields for _, fields in rows])


def load_run(run_dir: str | Path) -> RunFolder:
    """Read every report input of a run folder: ``summary.json`` and the files it lists.

    Parameters
    ----------
    run_dir : path
        Folder with ``summary.json``; of the files it lists, these are read:
        ``frames/frame_NNN.png``, ``tracks.npz``, ``structure.csv``, ``motion.csv``,
        ``ground_truth_tracks.csv``, ``ground_truth_points.csv``, ``fusion_tables/*.csv``, ``cameras.csv``
        and the pre-rendered figures ``covariance_trace.png``, ``tracks.png``, ``structure.png``,
        ``fusion.png``.

    Raises
    ------
    InvalidInputError
        If ``run_dir`` is not a folder, ``summary.json`` is missing or broken, or a listed
        file is missing or does not have its documented layout.
    """
    folder = Path(run_dir)
    if not folder.is_dir():
        raise InvalidInputError(f"run folder {folder} does not exist or is not a folder")
    run_file(folder, SUMMARY_FILE)
    summary = read_summary(folder / SUMMARY_FILE)
    listed = set(summary.files)
    for name in sorted(listed):
        run_file(folder, name)
    missing = sorted(name for name in listed if not (folder / name).is_file())
    if missing:
        raise InvalidInputError(
            f"{folder}: the run's summary.json lists {', '.join(missing[:3])}{' …' if len(missing) > 3 else ''}, "
            f"which {'is' if len(missing) == 1 else 'are'} missing"
        )

    def path_of(name: str) -> Path | None:
        return folder / name if name in listed else None

    tracks_path = path_of("tracks.npz")
    tracks = read_tracks_npz(tracks_path) if tracks_path else None
    truth_path = path_of(TRACKS_FILE)
    ground_truth_tracks = None
    if tracks is not None and truth_path is not None:
        ground_truth_tracks = read_ground_truth_tracks(truth_path).aligned_to(tracks.track_ids)
        if ground_truth_tracks.shape[0] != tracks.n_frames:
            raise InvalidInputError(
                f"{where(truth_path)}: holds {ground_truth_tracks.shape[0]} frames but tracks.npz holds {tracks.n_frames}"
            )
    points = {name: read_points_table(path_of(name)) if path_of(name) else None for name in ("structure.csv", POINTS_FILE)}
    motion_path = path_of("motion.csv")
    frames = sorted((int(m.group(1)), folder / name) for name in listed if (m := _FRAME_NAME.match(name)))
    return RunFolder(
        path=folder,
        summary=summary,
        frame_paths=tuple(p for _, p in frames),
        tracks=tracks,
        structure=points["structure.csv"],
        motion=read_motion_csv(motion_path) if motion_path else None,
        ground_truth_tracks=ground_truth_tracks,
        ground_truth_points=points[POINTS_FILE],
        fusion_tables=tuple(_read_csv_table(folder / name) for name in sorted(listed) if
                            name.startswith("fusion_tables/") and name.endswith(".csv")),
        figures={name: folder / name for name in RUN_FIGURES if name in listed},
        data_files=tuple(sorted(name for name in listed if "/" not in name and not name.endswith(".png"))),
        cameras=read_cameras(folder / "cameras.csv") if "cameras.csv" in listed else None,
        frames_video=next((folder / name for name in sorted(listed) if is_frames_video(name)), None),
    )
