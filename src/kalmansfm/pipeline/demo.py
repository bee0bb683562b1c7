"""``kalmansfm demo``: the whole job in one call, frames → tracks → structure → report.

:func:`run_demo` renders the built-in scene (or reads your sequence), tracks, smooths,
factorizes, compares with the ground truth when there is one, writes the run folder and
builds its report.  ``kalmansfm batch`` runs it once per sequence.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import InvalidInputError, NotEnoughDataError, ReportInterrupted
from ..io.atomic import atomic_write, check_output_directory, output_directory
from ..io.frames import read_frames, stage_frames
from ..io.summary import SUMMARY_FILE, RunSummary, summary_json
from ..report.drawing import track_colors
from ..report.html import build_report
from ..scenes import Scene, render_scene
from ..scenes.files import scene_description, stage_ground_truth
from ..io.intrinsics import intrinsics_from_focal
from ..structure import Reconstruction
from ..structure.perspective import PerspectiveReconstruction, PerspectiveSettings, reconstruct_perspective
from ..tracking import TrackerSettings, Tracks, smooth_tracks, track
from .evaluate import compare_with_truth, factorize_tracks, structure_metrics, tracking_metrics
from .perspective import perspective_metrics, stage_perspective
from .stage import Stopwatch, stage_structure, stage_summary, stage_tracking

__all__ = ["DemoRun", "describe", "run_demo"]

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
    perspective : the calibrated reconstruction (``camera="perspective"``), or None.
    summary : the run's record, as written to ``summary.json``.
    report : path of ``report.html`` (None when the report was not built).
    scene : the built-in scene when it was the input.
    """

    out_dir: Path
    tracks: Tracks
    reconstruction: Reconstruction | None
    summary: RunSummary
    report: Path | None = None
    scene: Scene | None = field(default=None, repr=False)
    perspective: PerspectiveReconstruction | None = None


def _load_frames(input: str | os.PathLike[str]) -> list[np.ndarray]:
    frames = [np.asarray(f) for f in read_frames(input)]
    return [f if f.dtype == np.uint8 else np.clip(np.rint(f), 0, 255).astype(np.uint8) for f in frames]


def run_demo(
    out_dir: str | os.PathLike[str],
    *,
    input: str | os.PathLike[str] | None = None,
    seed: int = 0,
    n_frames: int = 30,
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
    out_dir : the run folder (created; earlier results are replaced only when the run succeeds).
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
        (:func:`~kalmansfm.structure.perspective.reconstruct_perspective`) of the measured,
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
    check_output_directory(out_dir)  # before the work, not after it
    clock = Stopwatch()
    scene = None
    with clock.step("frames"):
        if input is None:
            scene = render_scene(n_frames=n_frames, seed=seed)
            frames = [np.asarray(f) for f in scene.frames]
            first_visible = scene.visible[0]
            points = scene.positions[0, first_visible]
            track_ids = scene.track_ids[first_visible]
            source = scene_description(scene)
        else:
            frames = _load_frames(input)
            source = str(input)
    with clock.step("tracking"):
        tracks = track(frames, points, track_ids=track_ids, settings=settings, progress=progress)
    measured = tracks
    if smooth:
        with clock.step("smoothing"):
            tracks = smooth_tracks(tracks)

    reconstruction: Reconstruction | None = None
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
            except NotEnoughDataError as exc:
                structure_error = str(exc)
                log.warning("factorization skipped: %s", exc)
    truth = None
    if scene is not None:
        truth = compare_with_truth(tracks, reconstruction, scene.ground_truth())

    summary = RunSummary(
        command=command,
        input=source,
        settings=tracks.settings,
        smoothed=tracks.smoothed,
        tracking=tracking_metrics(tracks),
        structure=None if reconstruction is None else structure_metrics(reconstruction, weighted=weighted,
                                                                         smoothed=tracks.smoothed),
        structure_error=structure_error,
        truth=truth,
        scene=None if scene is None else scene.parameters,
        perspective=None if calibrated is None else perspective_metrics(
            calibrated, measured.observations(), measured.frames, source_k, settings_p),
        warnings=() if calibrated is None else calibrated.warnings,
    )
    with output_directory(out_dir) as out:
        with clock.step("writing"):
            names = stage_frames(out, frames, "frames/") if save_frames else []
            names += stage_tracking(out, tracks, frames, last_frame=frames[-1])
            if reconstruction is not None:
                names += stage_structure(out, reconstruction, tracks.track_ids, frames=tracks.frames,
                                         colors=track_colors(tracks.n_tracks))
            if calibrated is not None:
                names += stage_perspective(out, calibrated, measured.frames, measured.track_ids,
                                           comment=f"kalmansfm demo of {source}")
            if scene is not None:
                names += stage_ground_truth(out, scene)
        summary = stage_summary(out, summary, clock, names)

    report = None
    # An earlier run's report describes results that were just replaced: remove it, so that
    # an interrupt while the new one is built leaves no report rather than a wrong one.
    (Path(out_dir) / "report.html").unlink(missing_ok=True)
    if html:
        with clock.step("report"):
            try:
                report = build_report(out_dir, progress=progress)
            except KeyboardInterrupt:
                raise ReportInterrupted(
                    f"the new results are in {out_dir}, without report.html; run 'kalmansfm report {out_dir}'"
                ) from None
        # the report's time goes into the one timing record (summary.json is replaced atomically)
        summary = replace(summary, timings_s=clock.timings, total_s=clock.total())
        atomic_write(Path(out_dir) / SUMMARY_FILE, lambda p: p.write_text(summary_json(summary), encoding="utf-8"))
    return DemoRun(Path(out_dir), tracks, reconstruction, summary, report, scene, calibrated)


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
        lines.extend(f"warning: {w}" for w in s.warnings)
    elif f is None:
        lines.append(f"structure: not computed ({s.structure_error})")
    else:
        sv = ", ".join(f"{v:.4g}" for v in f.singular_values[:5])
        line = f"structure: singular values {sv}; rank-3 residual {f.residual_rms_px:.3f} px"
        if truth is not None and truth.shape_error_pct is not None:
            line += f"; shape error {truth.shape_error_pct:.2f} % of the object radius"
        lines.append(line)
        lines.extend(f"warning: {w}" for w in f.warnings)
    lines.append(f"time: {s.total_s:.1f} s")
    lines.append(f"report: {run.report}" if run.report is not None else f"results: {run.out_dir}")
    return "\n".join(lines)

