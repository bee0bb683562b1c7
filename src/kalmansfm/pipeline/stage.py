"""The files a command stages into its run folder, and the run's clock.

Every command writes through an :class:`~kalmansfm.io.atomic.OutputDirectory`; the
helpers here stage the same files the same way for every command that has them and
return their names, which the run's :class:`~kalmansfm.io.summary.RunSummary` lists.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np

from ..io.atomic import OutputDirectory
from ..io.cameras import cameras_csv, pose_cameras_csv
from ..io.fusion import history_csv_chunks, rejected_csv
from ..io.reconstruction import RECONSTRUCTION_FILE, write_reconstruction
from ..io.structure import motion_csv, structure_csv, structure_ply
from ..io.summary import SUMMARY_FILE, RunSummary, summary_json
from ..io.tracks import observations_csv, write_tracks_csv, write_tracks_npz
from ..report.drawing import tracks_gif, tracks_overview_png
from ..report.figures import (
    camera_path_figure,
    covariance_trace_figure,
    fusion_convergence_figure,
    shape_views_figure,
)
from ..structure import CameraSet, Reconstruction, rms_std
from ..tracking.tracks import Tracks

__all__ = ["Stopwatch", "bar_progress", "stage_reconstruction", "stage_summary", "stage_tracking"]


class Stopwatch:
    """Wall-clock seconds per named step, and the total since the clock was made.

    Examples
    --------
    >>> clock = Stopwatch()
    >>> with clock.step("work"):
    ...     pass
    >>> [name for name, _ in clock.timings], clock.total() >= 0
    (['work'], True)
    """

    def __init__(self) -> None:
        self._start = time.perf_counter()
        self._steps: list[tuple[str, float]] = []

    @contextmanager
    def step(self, name: str) -> Iterator[None]:
        """Time the block as step ``name``."""
        started = time.perf_counter()
        try:
            yield
        finally:
            self._steps.append((name, time.perf_counter() - started))

    @property
    def timings(self) -> tuple[tuple[str, float], ...]:
        """(step, seconds) in the order the steps ran."""
        return tuple(self._steps)

    def total(self) -> float:
        """Seconds since the clock was made."""
        return time.perf_counter() - self._start


def bar_progress(bar: Any) -> Callable[[int, int], None]:
    """A ``progress(done, total)`` callback that moves ``bar`` (a tqdm bar) to ``done`` of ``total``, starting it
    again when ``done`` falls back (a fusion that fits σ or a noise model passes over the points more than once).

    Examples
    --------
    >>> import io
    >>> from tqdm import tqdm
    >>> with tqdm(file=io.StringIO()) as bar:
    ...     advance = bar_progress(bar)
    ...     advance(6, 10); advance(10, 10); advance(4, 10)
    ...     bar.n, bar.total
    (4, 10)
    """
    def advance(done: int, total: int) -> None:
        if done < bar.n:
            bar.reset(total)
        bar.total = total
        bar.update(done - bar.n)

    return advance


def stage_tracking(
    out: OutputDirectory, tracks: Tracks, frames: Iterable[np.ndarray], *, last_frame: np.ndarray, gif: bool = True
) -> list[str]:
    """Stage the tracker's files: tracks.csv, tracks.npz, covariance_trace.png, tracks.png (and tracks.gif).

    ``frames`` may be a lazily decoded source (it is read once, for the GIF); ``last_frame``
    is drawn under the paths in tracks.png.
    """
    with ThreadPoolExecutor(max_workers=1) as pool:
        # zlib compresses tracks.npz outside the interpreter lock while this thread formats and draws
        # (0.2 s of a long clip's 1 s of writing; drawing in a thread gains little: it is Python between calls)
        archive = pool.submit(write_tracks_npz, tracks, out.file("tracks.npz"))
        if tracks.states is None:  # tracks without a filter (matched by features): the observations alone
            out.write_text("tracks.csv", observations_csv(tracks.positions, tracks.frames, tracks.track_ids))
        else:
            write_tracks_csv(tracks, out.file("tracks.csv"))
        names = ["tracks.csv", "tracks.npz"]
        trace = covariance_trace_figure(tracks)
        if trace is not None:
            out.write_bytes("covariance_trace.png", trace)
            names.append("covariance_trace.png")
        out.write_bytes("tracks.png", tracks_overview_png(tracks, last_frame))
        names.append("tracks.png")
        if gif:
            out.write_bytes("tracks.gif", tracks_gif(frames, tracks))
            names.append("tracks.gif")
        try:
            archive.result()
        except OSError:
            out.last_file = "tracks.npz"  # the file that failed, not the last one this thread wrote (a full disk)
            raise
    return names


def stage_reconstruction(out: OutputDirectory, rec: Reconstruction, *, comment: str, plot: bool = True,
                         image_names: list[str] | None = None,
                         image_size: tuple[int, int] | None = None) -> list[str]:
    """Stage the files of any reconstruction and return their names.

    Every reconstruction: ``structure.csv`` (each track's point, covariance, views, reprojection
    RMS and status) and ``structure.ply`` (each point's ``uncertainty`` √(tr Σ / 3); the header
    says how the covariances are to be read).  Then what its data hold:

    * affine cameras: ``motion.csv`` (camera rows and image translation per frame) and
      ``structure.png`` (the reliable points; the unreliable ones are counted);
    * pinhole cameras: ``cameras.csv`` — cameras given to a fusion as their 3 × 4 matrices (sign
      kept: a mirrored frame stays mirrored), estimated ones as K, R, t with ``rotation_std_deg`` and
      ``centre_std``, and then ``reconstruction.png`` (the camera path, points coloured by uncertainty);
    * a fusion history: ``history.csv`` and ``fusion.png`` (uncertainty against views);
      observations rejected by a fusion's outlier test: ``rejected.csv``.

    And always ``reconstruction.npz``: the whole record (:mod:`kalmansfm.io.reconstruction`), with the
    frames' image names and size when known — what ``kalmansfm export`` reads.  ``comment`` goes into
    the PLY header.
    """
    frames, ids = rec.frame_ids, rec.track_ids
    out.write_text("structure.csv", structure_csv(ids, rec.points, covariances=rec.point_covariances, views=rec.views,
                                                  status=rec.point_status,
                                                  reprojection_rms=rec.point_reprojection_rms))
    out.write_text("structure.ply", structure_ply(ids, rec.points, comment=f"{comment}; covariances in the "
                                                  f"{rec.covariance_gauge}",
                                                  properties={"uncertainty": rms_std(rec.point_covariances)}))
    write_reconstruction(rec, out.file(RECONSTRUCTION_FILE), image_names=image_names, image_size=image_size)
    names = ["structure.csv", "structure.ply", RECONSTRUCTION_FILE]
    registered = rec.registered
    if rec.camera_model == "affine":
        out.write_text("motion.csv", motion_csv(frames, rec.motion, rec.image_translation))
        names.append("motion.csv")
        estimated = rec.estimated
        shown = estimated & rec.reconstructed
        if plot and shown.any():
            out.write_bytes("structure.png", shape_views_figure(rec.points[shown], ids[shown].tolist(),
                                                               hidden=int((estimated & ~shown).sum())))
            names.append("structure.png")
    else:
        if rec.pose_covariances is None:  # cameras given, not estimated: as 3 × 4 matrices, their sign kept
            text = cameras_csv(CameraSet(rec.projections[registered], frames[registered]))
        else:
            text = pose_cameras_csv(frames[registered], rec.intrinsics[registered], rec.rotations[registered],
                                    rec.translations[registered],
                                    rotation_std_deg=np.degrees(rms_std(rec.pose_covariances[registered, :3, :3])),
                                    centre_std=rms_std(rec.pose_covariances[registered, 3:, 3:]))
        out.write_text("cameras.csv", text)
        names.append("cameras.csv")
        ok = rec.reconstructed
        if plot and ok.any() and registered.any() and rec.pose_covariances is not None:
            out.write_bytes("reconstruction.png", camera_path_figure(
                rec.centres[registered], frames[registered].tolist(), rec.points[ok], rec.point_std[ok]))
            names.append("reconstruction.png")
    history = getattr(rec.details, "history", None)
    if history is not None:
        out.write_chunks("history.csv", history_csv_chunks(rec))
        names.append("history.csv")
    if rec.kind == "fusion":
        out.write_text("rejected.csv", rejected_csv(rec))
        names.append("rejected.csv")
    figure = _convergence_png(history) if plot and history is not None else None
    if figure is not None:
        out.write_bytes("fusion.png", figure)
        names.append("fusion.png")
    return names


def _convergence_png(history) -> bytes | None:
    """fusion.png: uncertainty against the number of views behind each history entry."""
    if len(history) == 0:
        return None
    order = np.lexsort((history.views, history.points))
    points = history.points[order]
    starts = np.r_[0, np.flatnonzero(np.diff(points)) + 1]
    ordinal = np.arange(points.size) - np.repeat(starts, np.diff(np.r_[starts, points.size]))
    # the k-th estimate of a point rests on k + 2 observations (its first comes from two views)
    return fusion_convergence_figure(ordinal + 2, rms_std(history.covariances[order]), points)


def stage_summary(out: OutputDirectory, summary: RunSummary, clock: Stopwatch, files: list[str]) -> RunSummary:
    """Stage ``summary.json``: ``summary`` with the run's ``files`` (and itself) and the clock's timings so far.

    Returns the summary as written: the run's one timing record and total.
    """
    final = replace(summary, files=(*files, SUMMARY_FILE), timings_s=clock.timings, total_s=clock.total())
    out.write_text(SUMMARY_FILE, summary_json(final))
    return final
