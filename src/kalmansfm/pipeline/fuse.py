"""``kalmansfm fuse``: each tracked point's 3-D position and covariance from known cameras, as a run folder."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .._version import __version__
from ..io.atomic import check_output_directory, output_directory
from ..io.cameras import CameraObservations, match_cameras, read_cameras
from ..io.fusion import history_csv, rejected_csv
from ..io.summary import FusionMetrics, RunSummary, run_source
from ..io.tracks import read_tracks
from ..report.figures import fusion_convergence_figure
from ..structure.fusion.point_fusion import FusedStructure, FusionSettings, fuse
from ..structure.points import PointStatus, rms_std
from .cluster import ScatteringExecutor, check_cluster, dask_client
from .stage import Stopwatch, stage_points, stage_summary

__all__ = ["FuseRun", "run_fuse"]

log = logging.getLogger("kalmansfm")


@dataclass(frozen=True)
class FuseRun:
    """What ``fuse`` read, computed and wrote."""

    out_dir: Path
    data: CameraObservations
    fused: FusedStructure
    summary: RunSummary


def fusion_metrics(data: CameraObservations, fused: FusedStructure, settings: FusionSettings) -> FusionMetrics:
    """The summary's record of a fusion."""
    counts = fused.status_counts()
    ok = fused.fused
    observed = np.isfinite(data.observations).all(axis=2)
    used = observed & ~fused.rejected & ok[None]
    rms = float(np.sqrt(np.mean(fused.residuals[used] ** 2))) if used.any() else None
    return FusionMetrics(
        method=fused.method,
        cameras=len(data.cameras),
        points=int(ok.size),
        fused=counts[PointStatus.OK.label],
        too_few_views=counts["too_few_views"],
        degenerate=counts["degenerate"],
        behind_camera=counts["behind_camera"],
        observations=int(observed.sum()),
        rejected=int(fused.rejected.sum()),
        pixel_std_px=fused.pixel_std,
        pixel_std_estimated=fused.pixel_std_estimated,
        degrees_of_freedom=fused.degrees_of_freedom,
        outlier_probability=settings.outlier_probability,
        reprojection_rms_px=rms,
        median_std=float(np.median(rms_std(fused.covariances[ok]))) if ok.any() else None,
        orientation=fused.orientation,
        passes=fused.passes,
        frames_without_camera=tuple(int(f) for f in data.frames_without_camera),
    )


def _convergence_png(fused: FusedStructure) -> bytes | None:
    """fusion.png: uncertainty against the number of views behind each history entry."""
    h = fused.history
    if h is None or len(h) == 0:
        return None
    order = np.lexsort((h.views, h.points))
    points = h.points[order]
    starts = np.r_[0, np.flatnonzero(np.diff(points)) + 1]
    ordinal = np.arange(points.size) - np.repeat(starts, np.diff(np.r_[starts, points.size]))
    # the k-th estimate of a point rests on k + 2 observations (its first comes from two views)
    return fusion_convergence_figure(ordinal + 2, rms_std(h.covariances[order]), points)


def run_fuse(
    tracks_path: str | os.PathLike[str],
    cameras_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    settings: FusionSettings | None = None,
    *,
    scheduler: str | None = None,
    n_workers: int | None = None,
    plot: bool = True,
) -> FuseRun:
    """Fuse the tracks of ``tracks_path`` with the cameras of ``cameras_path`` and write the run folder.

    Writes ``structure.csv`` (points, covariances, views, reprojection RMS, status),
    ``history.csv``, ``rejected.csv``, ``structure.ply`` (with a per-vertex uncertainty),
    ``fusion.png`` and ``summary.json`` to ``out_dir``, all or nothing.

    Parameters
    ----------
    tracks_path : ``tracks.csv``, ``tracks.npz`` or a ``frame,track_id,x,y[,status]`` CSV; only
        measured rows are observations.
    cameras_path : a cameras CSV (:mod:`kalmansfm.io.cameras`); frames of the tracks without a
        camera are skipped with one warning.
    out_dir : the run folder: new, empty or an earlier run, replaced whole when this run succeeds
        (:func:`~kalmansfm.io.output_directory`).
    settings : :class:`~kalmansfm.structure.fusion.point_fusion.FusionSettings` (method, pixel noise,
        outlier probability, chunk size); the history is always kept (history.csv).
    scheduler, n_workers : fuse the chunks on Dask — an existing scheduler's address, or a
        local cluster of ``n_workers`` processes; neither: in this process.
    plot : draw fusion.png.

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
    >>> run = run_fuse(folder / "tracks.csv", folder / "cameras.csv", folder / "fused", plot=False)
    >>> run.summary.fusion.fused, sorted(run.summary.files)[:3]
    (30, ['history.csv', 'rejected.csv', 'structure.csv'])
    """
    settings = replace(settings or FusionSettings(), history=True)
    check_cluster(scheduler, n_workers)
    inputs = [tracks_path, cameras_path]
    check_output_directory(out_dir, inputs=inputs)
    clock = Stopwatch()
    with clock.step("reading"):
        cameras = read_cameras(cameras_path)
        tracks = read_tracks(tracks_path)
        # where the chunks are fused (scheduler, workers) does not change the result
        source = run_source(tracks_path, inputs, {"settings": settings, "plot": plot})
        data = match_cameras(tracks.observations(), tracks.frames, tracks.track_ids, cameras, source=str(tracks_path))
    warnings = []
    if data.frames_without_camera.size:
        shown = ", ".join(str(f) for f in data.frames_without_camera[:8])
        more = f", … ({data.frames_without_camera.size} in all)" if data.frames_without_camera.size > 8 else ""
        warnings.append(f"frames of {Path(tracks_path).name} without a camera in {Path(cameras_path).name} "
                        f"were skipped: {shown}{more}")
    log.info("fusing %d tracks over %d views (%s)", data.observations.shape[1], len(data.cameras), settings.method)
    with clock.step("fusion"):
        if scheduler is None and n_workers is None:
            fused = fuse(data.observations, data.cameras, settings=settings)
        else:
            with dask_client(scheduler, n_workers) as client:
                fused = fuse(data.observations, data.cameras, settings=settings,
                             executor=ScatteringExecutor(client))
    summary = RunSummary(command="fuse", input=f"{tracks_path} with cameras {cameras_path}", source=source,
                         fusion=fusion_metrics(data, fused, settings), warnings=tuple(warnings))
    frames, ids = data.cameras.frames, data.track_ids
    with output_directory(out_dir, inputs=inputs) as out:
        with clock.step("writing"):
            names = stage_points(out, ids, fused.points, fused.covariances, fused.views, fused.status,
                                 fused.reprojection_rms, comment=f"kalmansfm {__version__} fuse {Path(tracks_path).name}")
            out.write_text("history.csv", history_csv(frames, ids, fused))
            out.write_text("rejected.csv", rejected_csv(frames, ids, data.observations, fused))
            names += ["history.csv", "rejected.csv"]
            figure = _convergence_png(fused) if plot else None
            if figure is not None:
                out.write_bytes("fusion.png", figure)
                names.append("fusion.png")
        summary = stage_summary(out, summary, clock, names)
    return FuseRun(Path(out_dir), data, fused, summary)
