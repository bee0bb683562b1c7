"""``kalmansfm track``: track points through a sequence read from disk and write the tracker's run folder."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .._validation import check_count
from ..io.atomic import check_output_directory, output_directory
from ..io.frames import read_frames
from ..io.summary import RunSummary, run_source
from ..io.tracks import check_points_inside, read_points_csv
from ..tracking import TrackerSettings, Tracks, smooth_tracks, track
from .evaluate import tracking_metrics
from .stage import Stopwatch, stage_summary, stage_tracking

__all__ = ["TrackRun", "run_track"]


@dataclass(frozen=True)
class TrackRun:
    """The tracks of one ``track`` run and the summary written beside them."""

    out_dir: Path
    tracks: Tracks
    summary: RunSummary


def run_track(
    input: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    points: str | os.PathLike[str] | None = None,
    settings: TrackerSettings | None = None,
    smooth: bool | int = False,
    progress: bool = False,
) -> TrackRun:
    """Track points through ``input`` and write tracks.csv, tracks.npz, the pictures and summary.json to ``out_dir``.

    Parameters
    ----------
    input : a folder of images (natural order), a glob or a video.
    out_dir : the run folder: new, empty or an earlier run, which is replaced whole when this
        run succeeds (:func:`~kalmansfm.io.output_directory`).
    points : a CSV with ``x,y[,track_id]`` of frame-0 points; None detects corners.
    settings : the tracker's settings (default settings when None).
    smooth : False, True (fixed-interval RTS smoothing) or a lag L (fixed-lag smoothing).
    progress : a progress bar on stderr.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.scenes import render_scene, write_scene
    >>> base = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_scene(render_scene(n_frames=5), base / "scene")
    >>> run = run_track(base / "scene", base / "tracks", points=base / "scene" / "points.csv")
    >>> run.summary.tracking.frames, "tracks.npz" in run.summary.files
    (5, True)
    """
    if not isinstance(smooth, bool):
        smooth = check_count("smooth", smooth, 0)  # a lag in frames, checked before any decoding
    check_output_directory(out_dir, inputs=[input, points])
    clock = Stopwatch()
    sequence = read_frames(input)
    start = track_ids = lines = None
    if points is not None:
        start, track_ids, lines = read_points_csv(points, with_lines=True)
    source = run_source(input, [*sequence.paths, *([points] if points is not None else [])],
                        {"settings": settings or TrackerSettings(), "smooth": smooth})
    with clock.step("tracking"):  # decoding included, as when the tracker read the frames lazily
        frames = list(sequence)  # decoded once: tracked, then drawn (tracks.png, tracks.gif)
        if points is not None:
            check_points_inside(start, frames[0].shape[1], frames[0].shape[0], str(points), lines)
        tracks = track(frames, start, track_ids=track_ids, settings=settings, progress=progress)
    if smooth is not False:
        with clock.step("smoothing"):
            tracks = smooth_tracks(tracks, lag=None if smooth is True else int(smooth))
    summary = RunSummary(command="track", input=str(input), source=source, settings=tracks.settings,
                         smoothed=tracks.smoothed, tracking=tracking_metrics(tracks))
    with output_directory(out_dir, inputs=[input, points]) as out:
        with clock.step("writing"):
            names = stage_tracking(out, tracks, frames, last_frame=frames[-1])
        summary = stage_summary(out, summary, clock, names)
    return TrackRun(Path(out_dir), tracks, summary)
