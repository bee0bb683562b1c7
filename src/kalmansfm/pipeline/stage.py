"""The files a command stages into its run folder, and the run's clock.

Every command writes through an :class:`~kalmansfm.io.atomic.OutputDirectory`; the
helpers here stage the same files the same way for every command that has them and
return their names, which the run's :class:`~kalmansfm.io.summary.RunSummary` lists.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import replace

import numpy as np

from ..io.atomic import OutputDirectory
from ..io.structure import motion_csv, structure_csv, structure_ply
from ..io.summary import SUMMARY_FILE, RunSummary, summary_json
from ..io.tracks import write_tracks_csv, write_tracks_npz
from ..report.drawing import tracks_gif, tracks_overview_png
from ..report.figures import covariance_trace_figure, shape_views_figure
from ..structure import Reconstruction
from ..tracking.tracks import Tracks

__all__ = ["Stopwatch", "stage_structure", "stage_summary", "stage_tracking"]


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


def stage_tracking(
    out: OutputDirectory, tracks: Tracks, frames: Iterable[np.ndarray], *, last_frame: np.ndarray, gif: bool = True
) -> list[str]:
    """Stage the tracker's files: tracks.csv, tracks.npz, covariance_trace.png, tracks.png (and tracks.gif).

    ``frames`` may be a lazily decoded source (it is read once, for the GIF); ``last_frame``
    is drawn under the paths in tracks.png.
    """
    write_tracks_csv(tracks, out.file("tracks.csv"))
    write_tracks_npz(tracks, out.file("tracks.npz"))
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
    return names


def stage_structure(
    out: OutputDirectory,
    reconstruction: Reconstruction,
    track_ids: np.ndarray,
    *,
    frames: np.ndarray | None = None,
    comment: str = "kalmansfm reconstruction",
    colors: list[str] | None = None,
    plot: bool = True,
) -> list[str]:
    """Stage the factorization's files: structure.csv, structure.ply, motion.csv (and structure.png).

    ``frames`` are the frame numbers written in motion.csv (default 0, 1, …);
    ``comment`` goes into the PLY header; ``colors`` are the tracks' colours in the plot.
    """
    out.write_text("structure.csv", structure_csv(track_ids, reconstruction.points))
    out.write_text("structure.ply", structure_ply(track_ids, reconstruction.points, comment=comment))
    if frames is None:
        frames = np.arange(reconstruction.motion.shape[0])
    out.write_text("motion.csv", motion_csv(frames, reconstruction.motion, reconstruction.translation))
    names = ["structure.csv", "structure.ply", "motion.csv"]
    finite = np.isfinite(reconstruction.points).all(axis=1)
    if plot and finite.any():
        chosen = None if colors is None else [c for c, ok in zip(colors, finite) if ok]
        out.write_bytes("structure.png", shape_views_figure(reconstruction.points[finite], track_ids[finite].tolist(),
                                                           colors=chosen))
        names.append("structure.png")
    return names


def stage_summary(out: OutputDirectory, summary: RunSummary, clock: Stopwatch, files: list[str]) -> RunSummary:
    """Stage ``summary.json``: ``summary`` with the run's ``files`` (and itself) and the clock's timings so far.

    Returns the summary as written: the run's one timing record and total.
    """
    final = replace(summary, files=(*files, SUMMARY_FILE), timings_s=clock.timings, total_s=clock.total())
    out.write_text(SUMMARY_FILE, summary_json(final))
    return final
