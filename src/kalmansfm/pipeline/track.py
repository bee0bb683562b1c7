"""``kalmansfm track``: track points through a sequence read from disk and write the tracker's run folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..io.atomic import check_output_directory, output_directory
from ..io.frames import read_frames
from ..io.summary import RunSummary, run_source
from ..io.tracks import check_points_inside, read_points_csv
from ..tracking import Tracks, smooth_tracks, track
from .evaluate import tracking_metrics
from .requests import TrackRequest, request_options
from .stage import Stopwatch, stage_summary, stage_tracking

__all__ = ["TrackRun", "run_track"]


@dataclass(frozen=True)
class TrackRun:
    """The tracks of one ``track`` run and the summary written beside them."""

    out_dir: Path
    tracks: Tracks
    summary: RunSummary


def run_track(request: TrackRequest) -> TrackRun:
    """Track points through ``request.input`` and write tracks.csv, tracks.npz, the pictures and summary.json.

    Parameters
    ----------
    request : the input (a folder of images in natural order, a glob or a video), the run folder
        (new, empty or an earlier run, replaced whole when this run succeeds), the frame-0 points
        (None: detect corners), the tracker's settings and smoothing
        (:class:`~kalmansfm.pipeline.requests.TrackRequest`).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.scenes import render_scene, write_scene
    >>> base = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_scene(render_scene(n_frames=5), base / "scene")
    >>> run = run_track(TrackRequest(base / "scene", base / "tracks", points=base / "scene" / "points.csv"))
    >>> run.summary.tracking.frames, "tracks.npz" in run.summary.files
    (5, True)
    """
    inputs = [request.input, request.points]
    check_output_directory(request.out, inputs=inputs)
    clock = Stopwatch()
    sequence = read_frames(request.input)
    start = track_ids = lines = None
    if request.points is not None:
        start, track_ids, lines = read_points_csv(request.points, with_lines=True)
    source = run_source(request.input, [*sequence.paths, *([request.points] if request.points is not None else [])],
                        request_options(request))
    with clock.step("tracking"):  # decoding included, as when the tracker read the frames lazily
        frames = list(sequence)  # decoded once: tracked, then drawn (tracks.png, tracks.gif)
        if request.points is not None:
            check_points_inside(start, frames[0].shape[1], frames[0].shape[0], str(request.points), lines)
        tracks = track(frames, start, track_ids=track_ids, settings=request.settings, progress=request.progress)
    if request.smooth is not False:
        with clock.step("smoothing"):
            tracks = smooth_tracks(tracks, lag=None if request.smooth is True else int(request.smooth))
    summary = RunSummary(command="track", input=str(request.input), source=source, settings=tracks.settings,
                         smoothed=tracks.smoothed, tracking=tracking_metrics(tracks))
    with output_directory(request.out, inputs=inputs) as out:
        with clock.step("writing"):
            names = stage_tracking(out, tracks, frames, last_frame=frames[-1])
        summary = stage_summary(out, summary, clock, names)
    return TrackRun(request.out, tracks, summary)
