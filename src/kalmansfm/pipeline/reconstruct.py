"""``kalmansfm reconstruct``: shape and motion from a tracks file, written as a run folder.

Three camera models: ``affine`` (the seed's orthographic factorization, the default),
``perspective`` (calibrated reconstruction with unknown motion: bundle adjustment or the
report's recursive fusion, :func:`~kalmansfm.structure.perspective.reconstruct.reconstruct_perspective`)
and ``auto``, which runs both and keeps the perspective model when its reprojection RMS
over its inliers is at most the affine model's over all observations (and the affine one
when the perspective reconstruction is impossible, e.g. without parallax).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

from .._validation import check_count
from .._version import __version__
from ..errors import InvalidInputError, NotEnoughDataError
from ..io.atomic import check_output_directory, output_directory
from ..io.summary import RunSummary, run_source
from ..io.tracks import read_tracks
from ..structure import PointUncertainty, Reconstruction
from ..structure.affine.factorization import DEFAULT_MAX_ITERATIONS
from ..structure.perspective.reconstruct import PerspectiveReconstruction, PerspectiveSettings, reconstruct_perspective
from ..tracking import Tracks, smooth_tracks
from .evaluate import factorize_tracks, structure_metrics, structure_uncertainty
from .perspective import CAMERA_MODELS, perspective_metrics, resolve_intrinsics, stage_perspective
from .stage import Stopwatch, stage_structure, stage_summary

__all__ = ["ReconstructRun", "read_tracks_for_factorization", "run_reconstruct"]

log = logging.getLogger("kalmansfm")


@dataclass(frozen=True)
class ReconstructRun:
    """The observations used, the reconstruction and the summary of one ``reconstruct`` run.

    ``reconstruction`` is the affine factorization and ``perspective`` the calibrated
    reconstruction; the one of the camera model written is set (both may be with ``auto``).
    ``uncertainty`` holds the affine points' covariances and status.
    """

    out_dir: Path
    tracks: Tracks
    reconstruction: Reconstruction | None
    summary: RunSummary
    perspective: PerspectiveReconstruction | None = None
    uncertainty: PointUncertainty | None = None


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
    camera: str = "affine",
    intrinsics: str | os.PathLike[str] | None = None,
    focal: float | None = None,
    image_size: tuple[int, int] | None = None,
    perspective: PerspectiveSettings | None = None,
    weighted: bool = True,
    smooth: bool | None = None,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    plot: bool = True,
) -> ReconstructRun:
    """Reconstruct the tracks of ``tracks_path`` and write the run folder ``out_dir``, all or nothing.

    Affine (factorization): structure.csv, structure.ply, motion.csv, structure.png, summary.json.
    Perspective: structure.csv with covariances and status, cameras.csv, structure.ply with a
    per-point uncertainty, reconstruction.png (camera path, points coloured by uncertainty),
    summary.json.

    Every affine point gets its covariance and status in structure.csv
    (:func:`~kalmansfm.structure.point_uncertainty`); unreliable points are left out of
    structure.png and counted in the summary's warnings.

    Parameters
    ----------
    tracks_path : ``tracks.npz``, ``tracks.csv`` or a ``frame,track_id,x,y`` CSV.
    out_dir : the run folder: new, empty or an earlier run, replaced whole when this run succeeds.
    camera : ``"affine"``, ``"perspective"`` or ``"auto"`` (see the module notes).
    intrinsics : ``K.csv`` (:mod:`kalmansfm.io.intrinsics`), for perspective and auto …
    focal : … or the focal length in pixels, principal point at the image centre; the image
        size is ``image_size`` (width, height) or the one recorded in the tracks file.
    perspective : :class:`~kalmansfm.structure.perspective.reconstruct.PerspectiveSettings` (method,
        outlier threshold, …).
    weighted : factorization: weight observations by 1 / σ² when the file has standard deviations.
    smooth : see :func:`read_tracks_for_factorization`; the perspective model reads the tracks
        as they are unless ``smooth`` is True.
    max_iterations : factorization: cap on the missing-data refinement iterations.
    plot : draw structure.png / reconstruction.png.

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
    if camera not in CAMERA_MODELS:
        raise InvalidInputError(f"camera must be one of {', '.join(CAMERA_MODELS)}; got {camera!r}")
    max_iterations = check_count("max_iterations", max_iterations, 1)
    inputs = [tracks_path] if camera == "affine" else [tracks_path, intrinsics]
    check_output_directory(out_dir, inputs=inputs)
    clock = Stopwatch()
    name = Path(tracks_path).name
    if camera == "affine":
        tracks = read_tracks_for_factorization(tracks_path, smooth=smooth)
    else:
        tracks = read_tracks_for_factorization(tracks_path, smooth=bool(smooth))
        K, source = resolve_intrinsics(tracks.frames, intrinsics=intrinsics, focal=focal, image_size=image_size,
                                       tracks_image_size=tracks.image_size)
    settings = perspective or PerspectiveSettings()
    options: dict[str, object] = {"camera": camera, "weighted": weighted, "smooth": smooth,
                                  "max_iterations": max_iterations, "plot": plot}
    if camera != "affine":
        options.update(focal=focal, image_size=image_size, perspective=settings)
    made_from = run_source(tracks_path, [p for p in inputs if p is not None], options)
    log.info("read %d frames x %d tracks from %s", tracks.n_frames, tracks.n_tracks, tracks_path)
    reconstruction: Reconstruction | None = None
    uncertainty: PointUncertainty | None = None
    rec: PerspectiveReconstruction | None = None
    has_weights = weighted and tracks.covariances is not None
    if camera in ("affine", "auto"):
        with clock.step("factorization"):
            reconstruction = factorize_tracks(tracks, weighted=has_weights, max_iterations=max_iterations)
            uncertainty = structure_uncertainty(tracks, reconstruction, weighted=has_weights)
    choice = None
    if camera in ("perspective", "auto"):
        with clock.step("perspective reconstruction"):
            try:
                rec = reconstruct_perspective(tracks.observations(), K, settings=settings)
            except NotEnoughDataError as exc:
                if camera == "perspective":
                    raise
                choice = f"affine: the perspective reconstruction was impossible ({exc})"
    if camera == "auto" and reconstruction is not None and rec is not None:
        affine_rms = reconstruction.residual_rms
        if rec.reprojection_rms <= affine_rms:
            choice = (f"perspective: reprojection RMS {rec.reprojection_rms:.3g} px over its inliers <= the affine "
                      f"model's {affine_rms:.3g} px")
        else:
            choice = (f"affine: reprojection RMS {affine_rms:.3g} px < the perspective model's "
                      f"{rec.reprojection_rms:.3g} px over its inliers")
    use_perspective = rec is not None and (camera == "perspective" or (choice or "").startswith("perspective"))
    if use_perspective:
        assert rec is not None
        summary = RunSummary(command="reconstruct", input=str(tracks_path), source=made_from,
                             settings=tracks.settings, smoothed=tracks.smoothed,
                             perspective=perspective_metrics(rec, tracks.observations(), tracks.frames, source,
                                                             settings, camera_choice=choice),
                             warnings=rec.warnings)
    else:
        assert reconstruction is not None and uncertainty is not None
        summary = RunSummary(command="reconstruct", input=str(tracks_path), source=made_from,
                             settings=tracks.settings, smoothed=tracks.smoothed,
                             structure=structure_metrics(reconstruction, weighted=has_weights, smoothed=tracks.smoothed,
                                                         uncertainty=uncertainty),
                             warnings=(*(() if choice is None else (f"--camera auto chose {choice}",)),
                                       *uncertainty.warnings))
    with output_directory(out_dir, inputs=inputs) as out:
        with clock.step("writing"):
            if use_perspective:
                names = stage_perspective(out, rec, tracks.frames, tracks.track_ids, K,  # type: ignore[arg-type]
                                          comment=f"kalmansfm {__version__} from {name}", plot=plot)
            else:
                names = stage_structure(out, reconstruction, tracks.track_ids,  # type: ignore[arg-type]
                                        uncertainty=uncertainty,  # type: ignore[arg-type]
                                        frames=tracks.frames, comment=f"kalmansfm {__version__} from {name}", plot=plot)
        summary = stage_summary(out, summary, clock, names)
    return ReconstructRun(Path(out_dir), tracks, reconstruction, summary, rec, uncertainty)
