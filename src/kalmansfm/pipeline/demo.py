"""``kalmansfm demo``: the whole job in one call, frames → tracks → structure → report.

:func:`run_demo` renders the built-in scene (or reads your sequence), tracks, smooths,
factorizes, compares with the ground truth when there is one, writes the run folder and
builds its report.  ``kalmansfm batch`` runs it once per sequence.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import NotEnoughDataError
from ..io.atomic import check_output_directory, output_directory
from ..io.frames import FrameSource, read_frames, stage_frames
from ..io.summary import RunSource, RunSummary, run_source
from ..report.html import build_report
from ..scenes import Scene, render_scene
from ..scenes.files import scene_description, stage_ground_truth
from ..structure import Reconstruction
from ..structure.perspective import reconstruct_perspective
from ..tracking import Tracks, smooth_tracks, track
from .evaluate import compare_with_truth, factorize_tracks, reconstruction_metrics, tracking_metrics
from .perspective import resolve_intrinsics
from .requests import DemoRequest, Perspective, request_options
from .stage import Stopwatch, stage_reconstruction, stage_summary, stage_tracking

__all__ = ["DemoRun", "demo_source", "describe", "run_demo"]



@dataclass(frozen=True)
class DemoRun:
    """What one run produced.

    Attributes
    ----------
    out_dir : the run folder.
    tracks : the tracker's output (smoothed when the run smoothed).
    reconstruction : the reconstruction (factorization, or calibrated with a perspective camera), or
        None when it was not possible (the reason is ``summary.structure_error``).
    summary : the run's record, as written to ``summary.json``: its ``total_s`` is the time
        from the start to the last result file, the time the report shows.
    report : path of ``report.html`` (None when the report was not built).
    scene : the built-in scene when it was the input.
    report_s : seconds spent building ``report.html`` once the results were staged (None without it);
        not part of ``summary.total_s``.
    """

    out_dir: Path
    tracks: Tracks
    reconstruction: Reconstruction | None
    summary: RunSummary
    report: Path | None = None
    scene: Scene | None = field(default=None, repr=False)
    report_s: float | None = None


def demo_source(request: DemoRequest, sequence: FrameSource | None = None) -> RunSource:
    """What a :func:`run_demo` of ``request`` is made from (its ``summary.source``).

    ``sequence`` is the request's footage as read (:func:`~kalmansfm.io.read_frames`), or None
    for the built-in scene.  ``batch`` compares it with a finished run's before it keeps that
    run instead of computing it again.

    Examples
    --------
    >>> a, b = DemoRequest("x", seed=1), DemoRequest("y", seed=1)
    >>> demo_source(a) == demo_source(b), demo_source(a) == demo_source(DemoRequest("x", seed=2))
    (True, False)
    """
    options = request_options(request)
    if sequence is None:
        return run_source("built-in scene", [], options)
    camera = request.camera
    extra = [camera.intrinsics] if isinstance(camera, Perspective) and camera.intrinsics is not None else []
    return run_source(sequence.description, [*sequence.paths, *extra], options)


def run_demo(request: DemoRequest) -> DemoRun:
    """Track, reconstruct, compare with ground truth when known, and write a run folder with its report.

    Parameters
    ----------
    request : what to run (:class:`~kalmansfm.pipeline.requests.DemoRequest`): the run folder (new,
        empty or an earlier run, replaced whole, report included, only when this run succeeds),
        the input (None: the built-in scene), the tracker's settings, smoothing, the camera.

    Returns
    -------
    DemoRun

    Examples
    --------
    >>> import tempfile, pathlib
    >>> run = run_demo(DemoRequest(pathlib.Path(tempfile.mkdtemp()) / "demo", html=False))
    >>> sorted(p.name for p in run.out_dir.iterdir() if p.suffix == ".csv")
    ['ground_truth_motion.csv', 'ground_truth_points.csv', 'ground_truth_tracks.csv', 'motion.csv', \
'points.csv', 'structure.csv', 'tracks.csv']
    >>> run.summary.truth.tracking_rms_error_px < 0.5
    True
    """
    inputs = [request.input]
    camera = request.camera
    if isinstance(camera, Perspective) and camera.intrinsics is not None:
        inputs.append(camera.intrinsics)
    check_output_directory(request.out, inputs=inputs)  # before the work, not after it
    clock = Stopwatch()
    scene = None
    image_names = None
    video = None  # the video file the frames are all the frames of
    points, track_ids = request.points, request.track_ids
    with clock.step("frames"):
        if request.input is None:
            made_from = demo_source(request)
            scene = render_scene(n_frames=request.n_frames, seed=request.seed)
            frames = [np.asarray(f) for f in scene.frames]
            first_visible = scene.visible[0]
            points = scene.positions[0, first_visible]
            track_ids = scene.track_ids[first_visible]
            source = scene_description(scene)
        else:
            sequence = read_frames(request.input)
            made_from = demo_source(request, sequence)
            frames = list(sequence)  # FrameSource yields (H, W) uint8 grey frames
            video = sequence.video
            source = str(request.input)
            if len(sequence.paths) == len(frames):  # a folder or glob of images: their names
                image_names = [Path(p).name for p in sequence.paths]
    with clock.step("tracking"):
        tracks = track(frames, points, track_ids=track_ids, settings=request.tracker, progress=request.progress)
    measured = tracks
    if request.smooth:
        with clock.step("smoothing"):
            tracks = smooth_tracks(tracks)

    reconstruction: Reconstruction | None = None
    structure_error = None
    intrinsics_source = None
    if isinstance(camera, Perspective):
        height, width = frames[0].shape[:2]
        K, intrinsics_source = resolve_intrinsics(measured.frames, camera, (width, height))
        with clock.step("perspective reconstruction"):
            try:
                # the measured positions: smoothing would correlate the errors of neighbouring frames
                reconstruction = reconstruct_perspective(measured.observations(), K, settings=camera.settings)
                reconstruction = reconstruction.with_ids(measured.frames, measured.track_ids)
            except NotEnoughDataError as exc:
                structure_error = str(exc)
    else:
        with clock.step("factorization"):
            try:
                reconstruction = factorize_tracks(tracks, weighted=camera.weighted, max_iterations=camera.max_iterations,
                                                  progress=request.progress)
            except NotEnoughDataError as exc:
                structure_error = str(exc)
    truth = None
    if scene is not None:
        truth = compare_with_truth(tracks, reconstruction, scene.ground_truth())

    metrics = None
    if reconstruction is not None:
        metrics = reconstruction_metrics(reconstruction, intrinsics=intrinsics_source,
                                         smoothed=tracks.smoothed if reconstruction.kind == "affine" else None)
    summary = RunSummary(
        command=request.command,
        input=source,
        source=made_from,
        settings=tracks.settings,
        smoothed=tracks.smoothed,
        tracking=tracking_metrics(tracks),
        reconstruction=metrics,
        structure_error=structure_error,
        truth=truth,
        scene=None if scene is None else scene.parameters,
    )
    with output_directory(request.out, inputs=inputs) as out:
        with clock.step("writing"), tqdm(total=4, desc="writing", unit="part", disable=not request.progress,
                                         leave=False) as bar:
            names = stage_frames(out, frames, "frames/", source=video) if request.save_frames else []
            bar.update()
            names += stage_tracking(out, tracks, frames, last_frame=frames[-1])
            bar.update()
            if reconstruction is not None:
                names += stage_reconstruction(out, reconstruction, comment=f"kalmansfm demo of {source}",
                                              image_names=image_names,
                                              image_size=(frames[0].shape[1], frames[0].shape[0]))
            bar.update()
            if scene is not None:
                names += stage_ground_truth(out, scene)
            bar.update()
        summary = stage_summary(out, summary, clock, names)
        report = report_s = None
        if request.html:
            # Built from the staged run, as 'kalmansfm report' builds it from a finished one, so that the
            # folder gets its report together with its results or not at all. It shows the run's one
            # timing record; its own time is kept apart (DemoRun.report_s), not a step of the run.
            started = time.perf_counter()
            report = build_report(out.staging, progress=request.progress, shown_as=out.path,
                                  frames=frames if request.save_frames else None)
            report_s = time.perf_counter() - started
    return DemoRun(request.out, tracks, reconstruction, summary, report, scene, report_s)


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
    r = s.reconstruction
    if r is None:
        lines.append(f"structure: not computed ({s.structure_error})")
    elif r.kind == "perspective":
        lines.append(f"perspective reconstruction: {r.registered_frames} of {r.frames} frames registered, "
                     f"{r.reconstructed} of {r.points} points; reprojection RMS {r.reprojection_rms_px:.3f} px, "
                     f"pixel noise sigma {r.noise_std:.3f} px")
    else:
        sv = ", ".join(f"{v:.4g}" for v in r.singular_values[:5])
        line = f"structure: singular values {sv}; rank-3 residual {r.reprojection_rms_px:.3f} px"
        if truth is not None and truth.shape_error_pct is not None:
            line += f"; shape error {truth.shape_error_pct:.2f} % of the object radius"
        lines.append(line)
    lines.extend(s.warning_lines())
    if s.total_s is not None:
        extra = f" (and {run.report_s:.2f} s to build the report)" if run.report_s is not None else ""
        lines.append(f"time: {s.total_s:.2f} s{extra}")
    lines.append(f"report: {run.report}" if run.report is not None else f"results: {run.out_dir}")
    return "\n".join(lines)
