"""``kalmansfm reconstruct``: shape and motion from a tracks file, written as a run folder."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from .._version import __version__
from ..errors import InvalidInputError
from ..io.atomic import check_output_directory, output_directory
from ..io.summary import RunSummary
from ..io.tracks import read_tracks
from ..structure import Reconstruction
from ..tracking import Tracks, smooth_tracks
from .evaluate import factorize_tracks, structure_metrics
from .stage import Stopwatch, stage_structure, stage_summary

__all__ = ["ReconstructRun", "read_tracks_for_factorization", "run_reconstruct"]

log = logging.getLogger("kalmansfm")


@dataclass(frozen=True)
class ReconstructRun:
    """The observations used, the reconstruction and the summary of one ``reconstruct`` run."""

    out_dir: Path
    tracks: Tracks
    reconstruction: Reconstruction
    summary: RunSummary


def read_tracks_for_factorization(path: str | os.PathLike[str], *, smooth: bool | None = None) -> Tracks:
    """The tracks of a file for factorization, RTS-smoothed when possible.

    Smoothing (:func:`~kalmansfm.tracking.smooth_tracks`) needs the tracker's states and
    full covariances, i.e. its ``tracks.npz``; a CSV holds only positions (and perhaps
    velocities and position standard deviations), which is not enough to rebuild the
    filter's priors.  Only measured entries are observations (:meth:`Tracks.observations`).

    Parameters
    ----------
    path : ``tracks.npz``, ``tracks.csv`` or a ``frame,track_id,x,y`` CSV.
    smooth : None (default) smooths a tracker's ``tracks.npz`` that is not smoothed
        yet and reads anything else as it is (logging why); True requires smoothing
        (or tracks already smoothed) and raises otherwise; False never smooths.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.io.tracks import write_tracks_npz
    >>> from kalmansfm.scenes import render_scene
    >>> from kalmansfm.tracking import track
    >>> scene = render_scene(n_frames=8)
    >>> tracks = track(list(scene.frames), scene.positions[0, scene.visible[0]])
    >>> path = write_tracks_npz(tracks, pathlib.Path(tempfile.mkdtemp()) / "tracks.npz")
    >>> read_tracks_for_factorization(path).smoothed, read_tracks_for_factorization(path, smooth=False).smoothed
    (True, False)
    """
    tracks = read_tracks(path)
    if smooth is False or tracks.smoothed is not False:
        return tracks
    if tracks.states is None or tracks.covariances is None or Path(path).suffix.lower() != ".npz":
        reason = f"{path} holds no tracker states and covariances (smoothing needs the tracker's tracks.npz)"
    else:
        try:
            return smooth_tracks(tracks)
        except InvalidInputError as exc:
            if smooth:
                raise
            reason = f"{path} cannot be smoothed: {exc}"
    if smooth:
        raise InvalidInputError(f"cannot smooth the tracks: {reason}")
    log.info("using the tracks as they are: %s", reason)
    return tracks


def run_reconstruct(
    tracks_path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    weighted: bool = True,
    smooth: bool | None = None,
    max_iterations: int = 500,
    plot: bool = True,
) -> ReconstructRun:
    """Factorize the tracks of ``tracks_path`` and write structure.csv, structure.ply, motion.csv,
    structure.png and summary.json to ``out_dir``.

    Parameters
    ----------
    tracks_path : ``tracks.npz``, ``tracks.csv`` or a ``frame,track_id,x,y`` CSV.
    out_dir : the run folder.
    weighted : weight observations by 1 / σ² when the file has standard deviations.
    smooth : see :func:`read_tracks_for_factorization`.
    max_iterations : cap on the missing-data refinement iterations.
    plot : draw structure.png.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.experiments import report_tracks
    >>> from kalmansfm.io.tracks import write_tracks_npz
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_tracks_npz(report_tracks(), folder / "tracks.npz")
    >>> run = run_reconstruct(folder / "tracks.npz", folder / "shape", plot=False)
    >>> round(run.summary.structure.residual_rms_px, 2)
    2.88
    """
    check_output_directory(out_dir)
    clock = Stopwatch()
    tracks = read_tracks_for_factorization(tracks_path, smooth=smooth)
    has_weights = weighted and tracks.covariances is not None
    log.info("read %d frames x %d tracks from %s", tracks.n_frames, tracks.n_tracks, tracks_path)
    with clock.step("factorization"):
        reconstruction = factorize_tracks(tracks, weighted=has_weights, max_iterations=max_iterations)
    summary = RunSummary(command="reconstruct", input=str(tracks_path), settings=tracks.settings,
                         smoothed=tracks.smoothed,
                         structure=structure_metrics(reconstruction, weighted=has_weights, smoothed=tracks.smoothed))
    name = Path(tracks_path).name
    with output_directory(out_dir) as out:
        with clock.step("writing"):
            names = stage_structure(out, reconstruction, tracks.track_ids, frames=tracks.frames,
                                    comment=f"kalmansfm {__version__} from {name}", plot=plot)
        summary = stage_summary(out, summary, clock, names)
    return ReconstructRun(Path(out_dir), tracks, reconstruction, summary)
