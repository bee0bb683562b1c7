"""``kalmansfm fuse``: each tracked point's 3-D position and covariance from known cameras, as a run folder."""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np  # noqa: F401 (the examples use it)
from tqdm import tqdm

from .._version import __version__
from ..io.atomic import check_output_directory, output_directory
from ..io.cameras import CameraObservations, match_camera_observations, read_known_cameras
from ..io.summary import RunSummary, run_source
from ..io.tracks import read_track_observations
from ..structure import Reconstruction
from ..structure.fusion import fuse
from .cluster import check_cluster, executor_for
from .evaluate import reconstruction_metrics
from .reconstruct import tracks_file
from .requests import FuseRequest, request_options
from .stage import Stopwatch, bar_progress, stage_reconstruction, stage_summary

__all__ = ["FuseRun", "run_fuse"]

log = logging.getLogger("kalmansfm")


@dataclass(frozen=True)
class FuseRun:
    """What ``fuse`` read, computed and wrote."""

    out_dir: Path
    data: CameraObservations
    reconstruction: Reconstruction
    summary: RunSummary


def run_fuse(request: FuseRequest) -> FuseRun:
    """Fuse the tracks of ``request.tracks`` with the cameras of ``request.cameras`` and write the run folder.

    Writes ``structure.csv`` (points, covariances, views, reprojection RMS, status),
    ``history.csv``, ``rejected.csv``, ``cameras.csv`` (the cameras as given), ``structure.ply`` (with a per-vertex uncertainty),
    ``fusion.png`` and ``summary.json`` to ``request.out``, all or nothing
    (:func:`~kalmansfm.pipeline.stage.stage_reconstruction`).  Frames of the tracks without a
    camera are skipped with one warning; only measured rows of the tracks are observations.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.io.cameras import cameras_csv
    >>> from kalmansfm.scenes.known_cameras import known_camera_scene
    >>> s = known_camera_scene(points=30, views=4, seed=0)
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (folder / "cameras.csv").write_text(cameras_csv(s.cameras))
    >>> v, n = np.nonzero(np.isfinite(s.observations[..., 0]))
    >>> rows = [f"{a},{b},{x},{y}" for a, b, (x, y) in zip(v, n, s.observations[v, n])]
    >>> _ = (folder / "tracks.csv").write_text("frame,track_id,x,y\\n" + "\\n".join(rows) + "\\n")
    >>> run = run_fuse(FuseRequest(folder / "tracks.csv", folder / "cameras.csv", folder / "fused", plot=False))
    >>> run.summary.reconstruction.reconstructed, sorted(run.summary.files)[:3]
    (30, ['cameras.csv', 'history.csv', 'reconstruction.npz'])
    """
    request = replace(request, tracks=tracks_file(request.tracks))
    settings = request.settings
    check_cluster(request.scheduler, request.workers)
    inputs = [request.tracks, request.cameras]
    check_output_directory(request.out, inputs=inputs)
    clock = Stopwatch()
    with clock.step("reading"):
        known = read_known_cameras(request.cameras)
        cameras = known.cameras
        tracks = read_track_observations(request.tracks)
        # where the chunks are fused (scheduler, workers) does not change the result
        source = run_source(request.tracks, inputs, request_options(request))
        data = match_camera_observations(tracks, cameras, source=str(request.tracks))
    warnings = list(known.warnings)
    if known.matched_by == "order":
        warnings.append(f"the images of the COLMAP model {request.cameras.name} were matched to frames by the "
                        "natural order of their names (frame 0 = the first name)")
    if data.frames_without_camera.size:
        shown = ", ".join(str(f) for f in data.frames_without_camera[:8])
        more = f", … ({data.frames_without_camera.size} in all)" if data.frames_without_camera.size > 8 else ""
        warnings.append(f"frames of {request.tracks.name} without a camera in {request.cameras.name} "
                        f"were skipped: {shown}{more}")
    views, points = data.observations.shape
    log.info("fusing %d tracks over %d views (%s)", points, views, settings.method)
    observations = data.observations  # per observation: fuse holds them densely only where that is small
    with clock.step("fusion"), tqdm(total=points, desc="fusion", unit="point", disable=not request.progress,
                                    leave=False) as bar:
        with executor_for(request.scheduler, request.workers) as executor:
            rec = fuse(observations, data.cameras, settings=settings, executor=executor, progress=bar_progress(bar))
    rec = rec.with_ids(track_ids=data.track_ids)
    metrics = reconstruction_metrics(rec, skipped_frames=tuple(int(f) for f in data.frames_without_camera))
    summary = RunSummary(command="fuse", input=f"{request.tracks} with cameras {request.cameras}", source=source,
                         reconstruction=metrics, warnings=tuple(warnings))
    with output_directory(request.out, inputs=inputs) as out:
        with clock.step("writing"):
            names = stage_reconstruction(out, rec, comment=f"kalmansfm {__version__} fuse {request.tracks.name}",
                                         plot=request.plot, image_size=tracks.image_size)
        summary = stage_summary(out, summary, clock, names)
    return FuseRun(request.out, data, rec, summary)
