"""``kalmansfm demo``: the whole job in one call, frames → tracks → structure → report.

:func:`run_demo` renders the built-in scene (or reads your sequence), tracks, smooths,
factorizes, compares with the ground truth when there is one, writes the run folder and
builds its report.  ``kalmansfm batch`` runs it once per sequence.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError, NotEnoughDataError
from ..io.atomic import check_output_directory, output_directory
from ..io.frames import FrameSource, read_frames, stage_frames
from ..io.intrinsics import intrinsics_from_focal
from ..io.summary import RunSource, RunSummary, run_source
from ..report.html import build_report
from ..scenes import DEFAULT_SCENE_FRAMES, DEFAULT_SCENE_SEED, Scene, render_scene
from ..scenes.files import scene_description, stage_ground_truth
from ..structure import PointUncertainty, Reconstruction
from ..structure.perspective.reconstruct import PerspectiveReconstruction, PerspectiveSettings, reconstruct_perspective
from ..tracking import TrackerSettings, Tracks, smooth_tracks, track
from .evaluate import compare_with_truth, factorize_tracks, structure_metrics, structure_uncertainty, tracking_metrics
from .perspective import perspective_metrics, stage_perspective
from .stage import Stopwatch, stage_structure, stage_summary, stage_tracking

__all__ = ["DemoRun", "demo_source", "describe", "run_demo"]

log = logging.getLogger("kalmansfm")


@dataclass(frozen=True)
class DemoRun:
    """What one run produced.

    Attributes
    ----------
    out_dir : the run folder.
    tracks : the tracker's output (smoothed when the run smoothed).
    reconstruction : the factorization, or None when it was not possible or the camera is
        perspective (the reason is ``summary.structure_error``).
    summary : the run's record, as written to ``summary.json``: its ``total_s`` is the time
        from the start to the last result file, the time the report shows.
    report : path of ``report.html`` (None when the report was not built).
    scene : the built-in scene when it was the input.
    uncertainty : each reconstructed point's covariance and status (None without a reconstruction).
    report_s : seconds spent building ``report.html`` once the results were staged (None without it);
        not part of ``summary.total_s``.
    perspective : the calibrated reconstruction (``camera="perspective"``), or None.
    """

    out_dir: Path
    tracks: Tracks
    reconstruction: Reconstruction | None
    summary: RunSummary
    report: Path | None = None
    scene: Scene | None = field(default=None, repr=False)
    uncertainty: PointUncertainty | None = field(default=None, repr=False)
    report_s: float | None = None
    perspective: PerspectiveReconstruction | None = None


def demo_source(
    sequence: FrameSource | None,
    *,
    seed: int = DEFAULT_SCENE_SEED,
    n_frames: int = DEFAULT_SCENE_FRAMES,
    points: np.ndarray | None = None,
    track_ids: np.ndarray | None = None,
    settings: TrackerSettings | None = None,
    weighted: bool = True,
    smooth: bool = True,
    save_frames: bool = True,
    html: bool = True,
    camera: str = "affine",
    focal: float | None = None,
    perspective: PerspectiveSettings | None = None,
) -> RunSource:
    """What a :func:`run_demo` of these arguments is made from (its ``summary.source``).

    ``sequence`` is the footage (:func:`~kalmansfm.io.read_frames`), or None for the
    built-in scene of ``seed`` and ``n_frames``.  ``batch`` compares it with a finished
    run's before it keeps that run instead of computing it again.  A perspective run
    records its focal length and :class:`~kalmansfm.structure.PerspectiveSettings` too.

    Examples
    --------
    >>> demo_source(None, seed=1) == demo_source(None, seed=1), demo_source(None, seed=1) == demo_source(None, seed=2)
    (True, False)
    """
    options = {"settings": settings or TrackerSettings(), "weighted": weighted, "smooth": smooth,
               "save_frames": save_frames, "html": html, "points": points, "track_ids": track_ids, "camera": camera}
    if camera == "perspective":
        options.update(focal=focal, perspective=perspective or PerspectiveSettings())
    if sequence is None:
        return run_source("built-in scene", [], {**options, "seed": seed, "n_frames": n_frames})
    return run_source(sequence.description, sequence.paths, options)


def run_demo(
    out_dir: str | os.PathLike[str],
    *,
    input: str | os.PathLike[str] | None = None,
    seed: int = DEFAULT_SCENE_SEED,
    n_frames: int = DEFAULT_SCENE_FRAMES,
    points: np.ndarray | None = None,
    track_ids: np.ndarray | None = None,
    settings: TrackerSettings | None = None,
    weighted: bool = True,
    smooth: bool = True,
    save_frames: bool = True,
    html: bool = True,
    progress: bool = False,
    command: str = "demo",
    camera: str = "affine",
    focal: float | None = None,
    perspective: PerspectiveSettings | None = None,
) -> DemoRun:
    """Track, factorize, compare with ground truth when known, and write a run folder with its report.

    Parameters
    ----------
    out_dir : the run folder: new, empty or an earlier run, which is replaced whole (report
        included) only when this run succeeds (:func:`~kalmansfm.io.output_directory`).
    input : a folder of images, a glob or a video; None renders the built-in scene
        (:func:`kalmansfm.scenes.render_scene` with ``seed`` and ``n_frames``),
        whose frame-0 corners are the points tracked and whose ground truth is compared.
    points, track_ids : frame-0 points to track in ``input`` (None: detect corners).
    settings : the tracker's settings (default settings when None).
    weighted : weight the factorization by the tracker's posterior variances.
    smooth : RTS-smooth the tracks (:func:`~kalmansfm.tracking.smooth_tracks`) before they
        are written, scored and factorized (see "Smoothing the tracker" in docs/kalman.md).
    save_frames : copy the frames into ``frames/`` of the run folder (the report draws on them).
    html : build ``report.html``.
    progress : progress bars on stderr.
    command : recorded in ``summary.json``.
    camera : ``"affine"`` (factorization) or ``"perspective"``: calibrated reconstruction
        (:func:`~kalmansfm.structure.perspective.reconstruct.reconstruct_perspective`) of the measured,
        unsmoothed tracks with the focal length ``focal`` (pixels) and the principal point at the
        image centre; needs ``input``.
    perspective : its settings.

    Returns
    -------
    DemoRun

    Examples
    --------
    >>> import tempfile, pathlib
    >>> run = run_demo(pathlib.Path(tempfile.mkdtemp()) / "demo", html=False)
    >>> sorted(p.name for p in run.out_dir.iterdir() if p.suffix == ".csv")
    ['ground_truth_motion.csv', 'ground_truth_points.csv', 'ground_truth_tracks.csv', 'motion.csv', \
'points.csv', 'structure.csv', 'tracks.csv']
    >>> run.summary.truth.tracking_rms_error_px < 0.5
    True
    """
    if camera not in ("affine", "perspective"):
        raise InvalidInputError(f"camera must be 'affine' or 'perspective'; got {camera!r}")
    if camera == "perspective" and (input is None or focal is None):
        raise InvalidInputError("--camera perspective needs your own sequence (--input; the built-in scene is seen "
                                "by an affine camera) and its focal length in pixels (--focal)")
    check_output_directory(out_dir, inputs=[input])  # before the work, not after it
    clock = Stopwatch()
    scene = None
    options = {"points": points, "track_ids": track_ids, "settings": settings, "weighted": weighted,
               "smooth": smooth, "save_frames": save_frames, "html": html, "camera": camera, "focal": focal,
               "perspective": perspective}
    with clock.step("frames"):
        if input is None:
            made_from = demo_source(None, seed=seed, n_frames=n_frames, **options)
            scene = render_scene(n_frames=n_frames, seed=seed)
            frames = [np.asarray(f) for f in scene.frames]
            first_visible = scene.visible[0]
            points = scene.positions[0, first_visible]
            track_ids = scene.track_ids[first_visible]
            source = scene_description(scene)
        else:
            sequence = read_frames(input)
            made_from = demo_source(sequence, **options)
            frames = list(sequence)  # FrameSource yields (H, W) uint8 grey frames
            source = str(input)
    with clock.step("tracking"):
        tracks = track(frames, points, track_ids=track_ids, settings=settings, progress=progress)
    measured = tracks
    if smooth:
        with clock.step("smoothing"):
            tracks = smooth_tracks(tracks)

    reconstruction: Reconstruction | None = None
    uncertainty: PointUncertainty | None = None
    calibrated: PerspectiveReconstruction | None = None
    structure_error = None
    if camera == "perspective":
        settings_p = perspective or PerspectiveSettings()
        height, width = frames[0].shape[:2]
        K = intrinsics_from_focal(focal, (width, height), measured.n_frames)  # type: ignore[arg-type]
        source_k = f"focal {focal:g} px, principal point at the centre of the {width}x{height} image"
        with clock.step("perspective reconstruction"):
            try:
                # the measured positions: smoothing would correlate the errors of neighbouring frames
                calibrated = reconstruct_perspective(measured.observations(), K, settings=settings_p)
            except NotEnoughDataError as exc:
                structure_error = str(exc)
                log.warning("perspective reconstruction skipped: %s", exc)
    else:
        with clock.step("factorization"):
            try:
                reconstruction = factorize_tracks(tracks, weighted=weighted)
                uncertainty = structure_uncertainty(tracks, reconstruction, weighted=weighted)
            except NotEnoughDataError as exc:
                structure_error = str(exc)
                log.warning("factorization skipped: %s", exc)
    truth = None
    if scene is not None:
        truth = compare_with_truth(tracks, reconstruction, scene.ground_truth())

    summary = RunSummary(
        command=command,
        input=source,
        source=made_from,
        settings=tracks.settings,
        smoothed=tracks.smoothed,
        tracking=tracking_metrics(tracks),
        structure=None if reconstruction is None else structure_metrics(reconstruction, weighted=weighted,
                                                                         smoothed=tracks.smoothed,
                                                                         uncertainty=uncertainty),
        structure_error=structure_error,
        truth=truth,
        scene=None if scene is None else scene.parameters,
        perspective=None if calibrated is None else perspective_metrics(
            calibrated, measured.observations(), measured.frames, source_k, settings_p),
        warnings=calibrated.warnings if calibrated is not None else () if uncertainty is None else uncertainty.warnings,
    )
    with output_directory(out_dir, inputs=[input]) as out:
        with clock.step("writing"):
            names = stage_frames(out, frames, "frames/") if save_frames else []
            names += stage_tracking(out, tracks, frames, last_frame=frames[-1])
            if reconstruction is not None and uncertainty is not None:  # computed together
                names += stage_structure(out, reconstruction, tracks.track_ids, uncertainty=uncertainty,
                                         frames=tracks.frames)
            if calibrated is not None:
                names += stage_perspective(out, calibrated, measured.frames, measured.track_ids, K,
                                           comment=f"kalmansfm demo of {source}")
            if scene is not None:
                names += stage_ground_truth(out, scene)
        summary = stage_summary(out, summary, clock, names)
        report = report_s = None
        if html:
            # Built from the staged run, as 'kalmansfm report' builds it from a finished one, so that the
            # folder gets its report together with its results or not at all. It shows the run's one
            # timing record; its own time is kept apart (DemoRun.report_s), not a step of the run.
            started = time.perf_counter()
            report = build_report(out.staging, progress=progress, shown_as=out.path)
            report_s = time.perf_counter() - started
    return DemoRun(Path(out_dir), tracks, reconstruction, summary, report, scene, uncertainty, report_s, calibrated)


def describe(run: DemoRun) -> str:
    """A few lines for the terminal: tracking, structure, ground-truth errors, time, where the report is."""
    s = run.summary
    t, truth = s.tracking, s.truth
    lines = [f"input: {s.input}"]
    if t is None:  # every demo run tracks; a summary read from elsewhere may not
        return "\n".join(lines + [f"results: {run.out_dir}"])
    if truth is not None and truth.visible_measured_fraction is not None:
        line = f"tracking: {t.tracks} tracks over {t.frames} frames, {truth.visible_measured_fraction:.1%} of visible points measured"
    else:
        line = f"tracking: {t.tracks} tracks over {t.frames} frames, {t.measured_fraction:.1%} of track-frames measured"
    if truth is not None and truth.tracking_rms_error_px is not None:
        line += f", RMS error {truth.tracking_rms_error_px:.3f} px ({truth.within_2px:.1%} within 2 px)"
    lines.append(line)
    f, p = s.structure, s.perspective
    if p is not None:
        lines.append(f"perspective reconstruction: {p.registered_frames} of {p.frames} frames registered, "
                     f"{p.reconstructed} of {p.points} points; reprojection RMS {p.reprojection_rms_px:.3f} px, "
                     f"pixel noise sigma {p.pixel_std_px:.3f} px")
    elif f is None:
        lines.append(f"structure: not computed ({s.structure_error})")
    else:
        sv = ", ".join(f"{v:.4g}" for v in f.singular_values[:5])
        line = f"structure: singular values {sv}; rank-3 residual {f.residual_rms_px:.3f} px"
        if truth is not None and truth.shape_error_pct is not None:
            line += f"; shape error {truth.shape_error_pct:.2f} % of the object radius"
        lines.append(line)
    lines.extend(s.warning_lines())
    if s.total_s is not None:
        extra = f" (and {run.report_s:.2f} s to build the report)" if run.report_s is not None else ""
        lines.append(f"time: {s.total_s:.2f} s{extra}")
    lines.append(f"report: {run.report}" if run.report is not None else f"results: {run.out_dir}")
    return "\n".join(lines)

