"""``kalmansfm reconstruct``: shape and motion from a tracks file, written as a run folder.

Three camera models: ``affine`` (the seed's orthographic factorization, the default),
``perspective`` (calibrated reconstruction with unknown motion: bundle adjustment or the
report's recursive fusion, :func:`~kalmansfm.structure.perspective.reconstruct.reconstruct_perspective`)
and ``auto``, which runs both and keeps the perspective model when its reprojection RMS
over its inliers is at most the affine model's over all observations (and the affine one
when the perspective reconstruction is impossible, e.g. without parallax).

A CSV of a long sequence of short tracks, too many frames × tracks for dense arrays for a model
asked for, is read and reconstructed per observation throughout: affine frame by frame
(:func:`~kalmansfm.structure.affine.long_sequence.factorize_long_sequence`), perspective in
windows of frames (:func:`~kalmansfm.structure.perspective.segmented.reconstruct_segmented`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .._version import __version__
from ..errors import InvalidInputError, NotEnoughDataError
from ..io.atomic import check_output_directory, output_directory
from ..io.summary import RunSummary, run_source
from ..io.tracks import TrackObservations, read_track_observations, read_tracks
from ..structure import Reconstruction
from ..structure.affine.long_sequence import factorize_long_sequence, fits_dense_factorization
from ..structure.perspective import reconstruct_perspective
from ..structure.perspective.segmented import fits_dense_reconstruction, reconstruct_segmented
from ..tracking import Tracks, smooth_tracks
from .evaluate import factorize_tracks, reconstruction_metrics
from .perspective import resolve_intrinsics
from .requests import Affine, Auto, Perspective, ReconstructRequest, request_options
from .stage import Stopwatch, bar_progress, stage_reconstruction, stage_summary

__all__ = ["ReconstructRun", "read_tracks_for_factorization", "run_reconstruct", "tracks_file"]

log = logging.getLogger("kalmansfm")


@dataclass(frozen=True)
class ReconstructRun:
    """The observations used, the reconstruction written and the summary of one ``reconstruct`` run.

    ``reconstruction`` is the model written; with an :class:`~kalmansfm.pipeline.requests.Auto`
    camera ``alternative`` is the other one (None otherwise, or when it was impossible).  ``tracks``
    are per observation (:class:`~kalmansfm.io.tracks.TrackObservations`) when a long sequence, too
    many frames × tracks for dense arrays for a model asked for, was reconstructed per observation
    (affine: frame by frame; perspective: in windows of frames).
    """

    out_dir: Path
    tracks: Tracks | TrackObservations
    reconstruction: Reconstruction
    summary: RunSummary
    alternative: Reconstruction | None = None


def tracks_file(path: str | os.PathLike[str]) -> Path:
    """The tracks file to read for ``path``: the path itself, or the ``tracks.npz`` of a run folder.

    A run of ``track`` or ``demo`` keeps its tracks in ``tracks.npz``; giving its folder reads that.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> run = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (run / "tracks.npz").write_bytes(b"")
    >>> tracks_file(run).name
    'tracks.npz'
    """
    path = Path(path)
    if path.is_dir():
        inside = path / "tracks.npz"
        if inside.is_file():
            log.info("reading %s, the tracks of the run folder %s", inside, path)
            return inside
        raise InvalidInputError(f"{path}: a folder without tracks.npz; give a tracks file (tracks.npz, tracks.csv "
                                "or a frame,track_id,x,y CSV) or the folder of a track or demo run")
    return path


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


def run_reconstruct(request: ReconstructRequest) -> ReconstructRun:
    """Reconstruct the tracks of ``request.tracks`` and write the run folder ``request.out``, all or nothing.

    Every model writes structure.csv (each point with its covariance, views, reprojection RMS and
    status), structure.ply and summary.json (:func:`~kalmansfm.pipeline.stage.stage_reconstruction`);
    affine cameras add motion.csv and structure.png (unreliable points left out and counted),
    perspective ones cameras.csv and reconstruction.png.

    Parameters
    ----------
    request : the tracks, the run folder, the camera (:class:`~kalmansfm.pipeline.requests.Affine`,
        :class:`~kalmansfm.pipeline.requests.Perspective` or :class:`~kalmansfm.pipeline.requests.Auto`),
        smoothing and plotting (:class:`~kalmansfm.pipeline.requests.ReconstructRequest`).

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.experiments import report_tracks
    >>> from kalmansfm.io.tracks import write_tracks_npz
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> _ = write_tracks_npz(report_tracks(), folder / "tracks.npz")
    >>> run = run_reconstruct(ReconstructRequest(folder / "tracks.npz", folder / "shape", plot=False))
    >>> round(run.summary.reconstruction.reprojection_rms_px, 2)
    2.88
    """
    request = replace(request, tracks=tracks_file(request.tracks))
    camera = request.camera
    perspective = camera if isinstance(camera, Perspective) else camera.perspective if isinstance(camera, Auto) else None
    affine = camera if isinstance(camera, Affine) else camera.affine if isinstance(camera, Auto) else None
    inputs = [request.tracks] if perspective is None else [request.tracks, perspective.intrinsics]
    check_output_directory(request.out, inputs=inputs)
    clock = Stopwatch()
    name = request.tracks.name
    tracks: Tracks | TrackObservations | None = None
    if not request.smooth and request.tracks.suffix.lower() != ".npz":  # a tracker's npz is read densely (smoothed)
        observed = read_track_observations(request.tracks)
        shape = (observed.frames.size, observed.track_ids.size)
        if (affine is not None and not fits_dense_factorization(shape)) \
                or (perspective is not None and not fits_dense_reconstruction(shape)):
            tracks = observed  # a long sequence, too many frames x tracks for dense arrays: per observation throughout
            log.info("read %d observations over %d frames x %d tracks from %s: reconstructed per observation "
                     "(affine frame by frame, perspective in windows of frames)", observed.frame.size, *shape,
                     request.tracks)
    if tracks is None:
        tracks = read_tracks_for_factorization(request.tracks, smooth=request.smooth if perspective is None
                                               else bool(request.smooth))
        log.info("read %d frames x %d tracks from %s", tracks.n_frames, tracks.n_tracks, request.tracks)
    per_observation = isinstance(tracks, TrackObservations)
    if perspective is not None:
        K, source = resolve_intrinsics(tracks.frames, perspective, tracks.image_size)
    made_from = run_source(request.tracks, [p for p in inputs if p is not None], request_options(request))
    factorized: Reconstruction | None = None
    calibrated: Reconstruction | None = None
    if affine is not None:
        with clock.step("factorization"):
            if isinstance(tracks, TrackObservations):
                with tqdm(desc="factorization", unit="step", disable=not request.progress, leave=False) as bar:
                    factorized = factorize_long_sequence(tracks.observations(), progress=bar_progress(bar))
                factorized = factorized.with_ids(tracks.frames, tracks.track_ids)
            else:
                factorized = factorize_tracks(tracks, weighted=affine.weighted and tracks.covariances is not None,
                                              max_iterations=affine.max_iterations, progress=request.progress)
    choice = None
    if perspective is not None:
        with clock.step("perspective reconstruction"):
            try:
                calibrated = _calibrated(tracks, K, perspective, request.progress)
            except NotEnoughDataError as exc:
                if affine is None:
                    raise
                choice = f"affine: the perspective reconstruction was impossible ({exc})"
    if factorized is not None and calibrated is not None:
        affine_rms, rms = factorized.reprojection_rms, calibrated.reprojection_rms
        # as many significant digits as tell the two apart (3 at least)
        digits = next((d for d in range(3, 10) if f"{rms:.{d}g}" != f"{affine_rms:.{d}g}"), 10)
        a, p = f"{affine_rms:.{digits}g}", f"{rms:.{digits}g}"
        if rms <= affine_rms:
            choice = f"perspective: reprojection RMS {p} px over its inliers <= the affine model's {a} px"
        else:
            choice = f"affine: reprojection RMS {a} px < the perspective model's {p} px over its inliers"
    use_perspective = calibrated is not None and (affine is None or (choice or "").startswith("perspective"))
    chosen = calibrated if use_perspective else factorized
    other = factorized if use_perspective else calibrated
    assert chosen is not None
    smoothed = False if per_observation else tracks.smoothed
    metrics = reconstruction_metrics(chosen, smoothed=smoothed if chosen.kind == "affine" else None,
                                     intrinsics=source if use_perspective else None,
                                     camera_choice=choice if use_perspective else None)
    warnings = () if use_perspective or choice is None else (f"camera model chosen automatically: {choice}",)
    summary = RunSummary(command="reconstruct", input=str(request.tracks), source=made_from,
                         settings=None if per_observation else tracks.settings, smoothed=smoothed,
                         reconstruction=metrics, warnings=warnings)
    with output_directory(request.out, inputs=inputs) as out:
        with clock.step("writing"):
            names = stage_reconstruction(out, chosen, comment=f"kalmansfm {__version__} from {name}", plot=request.plot,
                                         image_size=tracks.image_size)
        summary = stage_summary(out, summary, clock, names)
    return ReconstructRun(request.out, tracks, chosen, summary, other)


def _calibrated(tracks: Tracks | TrackObservations, K: np.ndarray, camera: Perspective, progress: bool
                ) -> Reconstruction:
    """The calibrated reconstruction of the tracks: dense, or a long sequence's in windows of frames
    (:func:`~kalmansfm.structure.perspective.segmented.reconstruct_segmented`), with the tracks' ids."""
    if isinstance(tracks, Tracks):
        return reconstruct_perspective(tracks.observations(), K, settings=camera.settings).with_ids(
            tracks.frames, tracks.track_ids)
    with tqdm(total=tracks.frames.size, desc="windows of frames", unit="frame", disable=not progress,
              leave=False) as bar, tqdm(total=tracks.track_ids.size, desc="fusion", unit="point",
                                         disable=not progress, leave=False) as fusion_bar:
        rec = reconstruct_segmented(tracks.observations(), K, camera.settings,
                                    progress=bar_progress(bar), fusion_progress=bar_progress(fusion_bar))
    return rec.with_ids(tracks.frames, tracks.track_ids)
