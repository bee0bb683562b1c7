"""``kalmansfm track``: track points through a sequence read from disk and write the tracker's run folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.atomic import check_output_directory, output_directory
from ..io.frames import read_frames
from ..io.summary import RunSummary, run_source
from ..io.tracks import check_points_inside, read_points_csv
from ..features import FeatureSettings, build_tracks, detect_all, match_images
from ..tracking import Tracks, TrackStatus, smooth_tracks, track
from .evaluate import tracking_metrics
from .requests import TrackRequest, request_options
from .stage import Stopwatch, stage_summary, stage_tracking

__all__ = ["TrackRun", "feature_tracks", "run_track"]


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
        if request.features is not None:
            tracks = feature_tracks(frames, request.features)
        else:
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


def feature_tracks(frames: list[np.ndarray], settings: FeatureSettings) -> Tracks:
    """Tracks by descriptor matching: features of every frame, matched over the chosen pairs (a window of
    neighbours and the most similar frames anywhere), verified by a fundamental matrix, joined by union–find.

    Every observation is ``measured``; there is no filter, so no state or covariance.
    """
    features = detect_all(frames, settings)
    graph = match_images(features, None, settings)
    found = build_tracks(features, graph)
    positions = found.observations
    status = np.where(np.isfinite(positions).all(axis=2), TrackStatus.MEASURED, TrackStatus.NONE).astype(np.int8)
    height, width = frames[0].shape[:2]
    return Tracks(positions=positions, status=status, track_ids=np.arange(positions.shape[1], dtype=np.int64),
                  frames=np.arange(len(frames), dtype=np.int64), image_size=(width, height))
