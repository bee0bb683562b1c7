"""The whole job in one call: frames → tracks → structure → report.

:func:`run_pipeline` is what ``kalmansfm demo`` (and ``kalmansfm batch`` for each
sequence) runs.  The saving helpers :func:`save_tracking` and
:func:`save_structure` are shared with ``kalmansfm track`` and
``kalmansfm reconstruct`` so that every command writes the same files the
same way.
"""

from __future__ import annotations

import json
import logging
import platform
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from . import __version__
from .errors import InvalidInputError, NotEnoughDataError, ReportInterrupted
from .io.atomic import OutputDirectory, check_output_directory, output_directory
from .io.ground_truth import frame_name, scene_files
from .io.npz import load_npz
from .io.structure import motion_csv, structure_csv, structure_ply
from .io.track_table import TrackPositions, read_track_positions
from .io.tracks import read_tracks_npz, write_tracks_csv, write_tracks_npz
from .report.plot_structure import plot_structure
from .report.plot_tracks import plot_covariance_trace, plot_tracks, write_tracks_gif
from .scenes import Scene, render_scene
from .structure import Reconstruction, align_similarity, factorize
from .structure.cameras import camera_rotation_matrices, rotation_angle_deg
from .tracking.smoothing import smooth_tracks
from .tracking.tracker import track
from .tracking.tracks import Tracks

__all__ = [
    "PipelineResult",
    "run_pipeline",
    "save_tracking",
    "save_structure",
    "tracking_summary",
    "structure_summary",
    "compare_with_scene",
    "factorize_tracks",
    "read_tracks_for_factorization",
    "describe",
]

log = logging.getLogger("kalmansfm")

MEASURED = 1


@dataclass(frozen=True)
class PipelineResult:
    """What one run produced.

    Attributes
    ----------
    out_dir : the run folder.
    tracks : the tracker's output.
    reconstruction : the factorization, or None when it was not possible (the reason
        is in ``summary["factorization"]["error"]``).
    summary : the content of ``summary.json``.
    report : path of ``report.html`` (None when the report was not built).
    """

    out_dir: Path
    tracks: Tracks
    reconstruction: Reconstruction | None
    summary: dict[str, Any]
    report: Path | None = None
    scene: Scene | None = field(default=None, repr=False)


def save_tracking(
    out: OutputDirectory,
    tracks: Tracks,
    frames: Iterable[np.ndarray],
    *,
    last_frame: np.ndarray | None = None,
    gif: bool = True,
) -> None:
    """Stage the tracker's files: tracks.csv, tracks.npz, covariance_trace.png, tracks.png (and tracks.gif).

    ``frames`` may be a lazily decoded source; then give ``last_frame`` (drawn under
    the paths in tracks.png) so the frames are not decoded once more just for it.
    """
    write_tracks_csv(tracks, out.file("tracks.csv"))
    write_tracks_npz(tracks, out.file("tracks.npz"))
    plot_covariance_trace(tracks, out.file("covariance_trace.png"))
    plot_tracks(tracks, frames[-1] if last_frame is None else last_frame, out.file("tracks.png"))  # type: ignore[index]
    if gif:
        write_tracks_gif(frames, tracks, out.file("tracks.gif"), gate_radius=tracks.parameters["gate_radius"])


def save_structure(
    out: OutputDirectory,
    reconstruction: Reconstruction,
    track_ids: np.ndarray,
    *,
    frames: np.ndarray | None = None,
    title: str = "Recovered shape",
    comment: str = "kalmansfm reconstruction",
    plot: bool = True,
) -> None:
    """Stage the factorization's files: structure.csv, structure.ply, motion.csv (and structure.png).

    ``frames`` are the frame numbers written in motion.csv (default 0, 1, …);
    ``title`` heads the plot and ``comment`` goes into the PLY header.
    """
    out.write_text("structure.csv", structure_csv(track_ids, reconstruction.points))
    out.write_text("structure.ply", structure_ply(track_ids, reconstruction.points, comment=comment))
    if frames is None:
        frames = np.arange(reconstruction.motion.shape[0])
    out.write_text("motion.csv", motion_csv(frames, reconstruction.motion, reconstruction.translation))
    if plot:
        plot_structure(reconstruction.points, track_ids, out.file("structure.png"), title=title)


def factorize_tracks(tracks: Tracks, *, weighted: bool = True) -> Reconstruction:
    """Factorize the measured positions of ``tracks`` (coasting predictions are not observations).

    With ``weighted`` each observation is weighted by the inverse of the tracker's
    posterior standard deviation (weighted least squares).
    """
    measured = tracks.status == MEASURED
    positions = np.where(measured[..., None], tracks.positions, np.nan)
    weights = None
    if weighted:
        variances = np.diagonal(tracks.covariances[..., :2, :2], axis1=-2, axis2=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            weights = np.where(measured[..., None], 1.0 / np.sqrt(variances), 0.0)
        weights = np.nan_to_num(weights, nan=0.0, posinf=0.0)
    return factorize(positions, weights=weights)


def read_tracks_for_factorization(path: str | Path, *, smooth: bool | None = None) -> TrackPositions:
    """The observations of a tracks file for :func:`~kalmansfm.factorize`, RTS-smoothed when possible.

    Smoothing (:func:`~kalmansfm.tracking.smoothing.smooth_tracks`) needs the
    tracker's states and full covariances, i.e. its ``tracks.npz``; a ``tracks.csv``
    holds only x, y, vx, vy and the position standard deviations, which is not
    enough to rebuild the filter's priors.  Only measured entries are observations,
    as in :func:`~kalmansfm.io.track_table.read_track_positions`; with smoothing they
    are the smoothed positions weighted by the smoothed standard deviations.

    Parameters
    ----------
    path : ``tracks.npz``, ``tracks.csv`` or a ``frame,track_id,x,y`` CSV.
    smooth : None (default) smooths a tracker's ``tracks.npz`` that is not smoothed
        yet and reads anything else as it is (logging why); True requires smoothing
        (or tracks already smoothed) and raises otherwise; False never smooths.

    Returns
    -------
    TrackPositions
        With ``smoothed`` False, True or the lag of tracks smoothed earlier.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.io.tracks import write_tracks_npz
    >>> from kalmansfm.scenes import render_scene
    >>> scene = render_scene(n_frames=8)
    >>> tracks = track(list(scene.frames), scene.positions[0, scene.visible[0]])
    >>> path = write_tracks_npz(tracks, pathlib.Path(tempfile.mkdtemp()) / "tracks.npz")
    >>> read_tracks_for_factorization(path).smoothed, read_tracks_for_factorization(path, smooth=False).smoothed
    (True, False)
    """
    path = Path(path)
    observed = read_track_positions(path)
    if smooth is False:
        return observed
    reason = None
    tracks = None
    if path.suffix.lower() != ".npz":
        reason = f"{path} is a CSV; smoothing needs the tracker's tracks.npz (states and covariances)"
    else:
        names = set(load_npz(path))
        if not {"states", "covariances"} <= names:
            reason = f"{path} holds no tracker states and covariances"
        else:
            tracks = read_tracks_npz(path)
    if tracks is not None and tracks.parameters.get("smoothed"):
        return TrackPositions(observed.positions, observed.track_ids, observed.frames, observed.std,
                              smoothed=tracks.parameters["smoothed"])
    if tracks is not None:
        try:
            smoothed = smooth_tracks(tracks)
        except InvalidInputError as exc:
            if smooth:
                raise
            reason = f"{path} cannot be smoothed: {exc}"
    if reason is not None:
        if smooth:
            raise InvalidInputError(f"cannot smooth the tracks: {reason}")
        log.info("using the tracks as they are: %s", reason)
        return observed
    measured = smoothed.status == MEASURED
    order = np.argsort(smoothed.track_ids, kind="stable")
    positions = np.where(measured[..., None], smoothed.positions, np.nan)[:, order]
    std = np.where(measured[..., None], smoothed.position_std, np.nan)[:, order]
    return TrackPositions(positions, observed.track_ids, observed.frames, std, smoothed=True)


def tracking_summary(tracks: Tracks) -> dict[str, Any]:
    """Per-run and per-track statistics of a tracker output (no ground truth needed)."""
    alive = tracks.status > 0
    measured = tracks.status == MEASURED
    predicted = tracks.status == 2
    lost = tracks.status == 3
    variances = np.diagonal(tracks.covariances[..., :2, :2], axis1=-2, axis2=-1)
    std = np.sqrt(np.where(alive, variances.mean(axis=-1), np.nan))  # RMS of the x and y std
    per_track = []
    for p, tid in enumerate(tracks.track_ids):
        lost_frames = np.flatnonzero(lost[:, p])
        per_track.append(
            {
                "track_id": int(tid),
                "frames_measured": int(measured[:, p].sum()),
                "frames_predicted": int(predicted[:, p].sum()),
                "lost_at": int(lost_frames[0]) if lost_frames.size else None,
                "rms_error_px": None,
                "mean_std_px": float(np.nanmean(std[:, p])) if alive[:, p].any() else None,
            }
        )
    trace = np.where(alive, np.trace(tracks.covariances, axis1=-2, axis2=-1), 0.0)
    n_alive = alive.sum(axis=1)
    mean_trace = [float(v) if n else None for v, n in zip(trace.sum(axis=1) / np.maximum(n_alive, 1), n_alive)]
    return {
        "frames": int(tracks.status.shape[0]),
        "tracks": int(tracks.status.shape[1]),
        "fraction_tracked": float(measured.sum() / max(alive.sum(), 1)),
        "alive_in_last_frame": int(alive[-1].sum()),
        "mean_covariance_trace": mean_trace,
        "rms_error_px": None,
        "within_2px": None,
        "per_track": per_track,
    }


def structure_summary(reconstruction: Reconstruction) -> dict[str, Any]:
    """Singular values, residual and warnings of a factorization."""
    return {
        "singular_values": [float(v) for v in reconstruction.singular_values],
        "residual_rms_px": float(reconstruction.residual_rms),
        "warnings": list(reconstruction.warnings),
        "method": reconstruction.method,
        "shape_error_pct": None,
        "rotation_error_deg": None,
    }


def compare_with_scene(
    tracks: Tracks, reconstruction: Reconstruction | None, scene: Scene, summary: dict[str, Any]
) -> None:
    """Fill the ground-truth fields of ``summary`` (tracking error, shape error, rotation error) in place.

    Tracking error is over the (frame, point) pairs visible in the scene that the
    tracker measured; ``fraction_tracked`` becomes the fraction of visible pairs
    measured.  Shape error is the RMS distance after the best similarity
    alignment, in percent of the object's RMS radius, using whichever of the two
    mirror-image solutions fits better.
    """
    index = {int(t): p for p, t in enumerate(scene.track_ids)}
    cols = np.array([index.get(int(t), -1) for t in tracks.track_ids])
    known = cols >= 0
    truth = np.full(tracks.positions.shape, np.nan)
    visible = np.zeros(tracks.status.shape, bool)
    truth[:, known] = scene.positions[:, cols[known]]
    visible[:, known] = scene.visible[:, cols[known]]
    measured = (tracks.status == MEASURED) & visible
    errors = np.linalg.norm(tracks.positions - truth, axis=-1)
    t = summary["tracking"]
    if measured.any():
        t["rms_error_px"] = float(np.sqrt(np.mean(errors[measured] ** 2)))
        t["within_2px"] = float(np.mean(errors[measured] <= 2.0))
    t["fraction_tracked"] = float(measured.sum() / max((visible[:, known] if known.any() else visible).sum(), 1))
    n_measured = measured.sum(axis=1)
    sum_sq = np.where(measured, errors, 0.0) ** 2
    t["rms_error_per_frame_px"] = [
        float(np.sqrt(s / n)) if n else None for s, n in zip(sum_sq.sum(axis=1), n_measured)
    ]
    for p, row in enumerate(t["per_track"]):
        if measured[:, p].any():
            row["rms_error_px"] = float(np.sqrt(np.mean(errors[measured[:, p], p] ** 2)))

    if reconstruction is None:
        return
    ok = known & np.isfinite(reconstruction.points).all(axis=1)
    if ok.sum() < 4:
        return
    gt_points = scene.points_3d[cols[ok]]
    best = None
    for candidate in (reconstruction, reconstruction.mirrored()):
        alignment = align_similarity(candidate.points[ok], gt_points)
        if best is None or alignment.rms < best[1].rms:
            best = (candidate, alignment)
    candidate, alignment = best  # type: ignore[misc]
    radius = float(np.sqrt(np.mean(np.sum((gt_points - gt_points.mean(0)) ** 2, axis=1))))
    summary["factorization"]["shape_error_pct"] = 100.0 * alignment.rms / radius
    # target ≈ s A source  ⇒  recovered camera rows ≈ (true rows) A, up to scale.
    finite = np.isfinite(candidate.motion).all(axis=(1, 2))
    recovered = camera_rotation_matrices(np.where(finite[:, None, None], candidate.motion, 1.0))
    expected = camera_rotation_matrices(scene.rotations[:, :2] @ alignment.rotation)
    angles = rotation_angle_deg(recovered, expected)
    summary["factorization"]["rotation_error_deg"] = [float(a) if ok else None for a, ok in zip(angles, finite)]


def _encode_png(image: np.ndarray) -> bytes:
    ok, png = cv2.imencode(".png", image)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 grey image
        raise RuntimeError("could not encode a frame as PNG")
    return png.tobytes()


def _as_uint8(frame: np.ndarray) -> np.ndarray:
    if frame.dtype == np.uint8:
        return frame
    return np.clip(np.rint(frame), 0, 255).astype(np.uint8)


def run_pipeline(
    out_dir: str | Path,
    *,
    input: str | Path | None = None,
    seed: int = 0,
    n_frames: int = 30,
    points: np.ndarray | None = None,
    track_ids: np.ndarray | None = None,
    track_options: dict[str, Any] | None = None,
    weighted: bool = True,
    smooth: bool = True,
    save_frames: bool = True,
    html: bool = True,
    progress: bool = False,
    command: str = "demo",
) -> PipelineResult:
    """Track, factorize, compare with ground truth when known, and write a run folder.

    Parameters
    ----------
    out_dir : the run folder (created; earlier results are replaced only when the run succeeds).
    input : a folder of images, a glob or a video; None renders the built-in scene
        (:func:`kalmansfm.scenes.render_scene` with ``seed`` and ``n_frames``),
        whose frame-0 corners are the points tracked and whose ground truth is compared.
    points, track_ids : frame-0 points to track in ``input`` (None: detect corners).
    track_options : keyword options of :func:`kalmansfm.track`.
    weighted : weight the factorization by the tracker's posterior standard deviations.
    smooth : RTS-smooth the tracks (:func:`~kalmansfm.tracking.smoothing.smooth_tracks`)
        before they are written, scored and factorized (see "Smoothing the tracker" in
        docs/kalman.md for what it gains on the built-in scene).
    save_frames : copy the frames into ``frames/`` of the run folder (the report draws on them).
    html : build ``report.html``.
    progress : progress bars on stderr.
    command : recorded in ``summary.json``.

    Returns
    -------
    PipelineResult

    Examples
    --------
    >>> import tempfile, pathlib
    >>> run = run_pipeline(pathlib.Path(tempfile.mkdtemp()) / "demo", html=False)
    >>> sorted(p.name for p in run.out_dir.iterdir() if p.suffix == ".csv")
    ['ground_truth_motion.csv', 'ground_truth_points.csv', 'ground_truth_tracks.csv', 'motion.csv', \
'points.csv', 'structure.csv', 'tracks.csv']
    >>> run.summary["tracking"]["rms_error_px"] < 0.5
    True
    """
    check_output_directory(out_dir)  # before the work, not after it
    timings: dict[str, float] = {}
    started = time.perf_counter()
    options = dict(track_options or {})
    scene = None
    if input is None:
        scene = render_scene(n_frames=n_frames, seed=seed)
        frames = [np.asarray(f) for f in scene.frames]
        first_visible = scene.visible[0]
        points = scene.positions[0, first_visible]
        track_ids = scene.track_ids[first_visible]
        source = f"built-in scene (seed {seed}, {n_frames} frames)"
    else:
        from .io.frames import read_frames

        frames = [_as_uint8(np.asarray(f)) for f in read_frames(input)]
        source = str(input)
    timings["frames_s"] = time.perf_counter() - started

    t0 = time.perf_counter()
    tracks = track(frames, points, track_ids=track_ids, progress=progress, **options)
    timings["tracking_s"] = time.perf_counter() - t0
    if smooth:
        t0 = time.perf_counter()
        tracks = smooth_tracks(tracks)
        timings["smoothing_s"] = time.perf_counter() - t0

    summary: dict[str, Any] = {
        "kalmansfm_version": __version__,
        "command": command,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "input": source,
        "parameters": {**tracks.parameters, "smoothed": tracks.parameters.get("smoothed", False),
                       "weighted_factorization": weighted},
        "versions": {"kalmansfm": __version__, "python": platform.python_version(), "numpy": np.__version__},
        "status_codes": {"0": "no track", "1": "measured", "2": "predicted", "3": "lost"},
        "tracking": tracking_summary(tracks),
        "ground_truth": scene is not None,
    }

    t0 = time.perf_counter()
    reconstruction: Reconstruction | None
    try:
        reconstruction = factorize_tracks(tracks, weighted=weighted)
        summary["factorization"] = structure_summary(reconstruction)
    except NotEnoughDataError as exc:
        reconstruction = None
        summary["factorization"] = {"error": str(exc)}
        log.warning("factorization skipped: %s", exc)
    timings["factorization_s"] = time.perf_counter() - t0

    if scene is not None:
        compare_with_scene(tracks, reconstruction, scene, summary)

    t0 = time.perf_counter()
    with output_directory(out_dir) as out:
        if save_frames:
            for f, frame in enumerate(frames):
                out.write_bytes(f"frames/{frame_name(f, len(frames))}", _encode_png(frame))
        save_tracking(out, tracks, frames)
        if reconstruction is not None:
            save_structure(out, reconstruction, tracks.track_ids)
        if scene is not None:
            for name, data in scene_files(scene, frames=False).items():
                out.write_bytes(name, data) if isinstance(data, bytes) else out.write_text(name, data)
        timings["writing_s"] = time.perf_counter() - t0
        timings["total_s"] = time.perf_counter() - started
        summary["timings_s"] = timings
        out.write_text("summary.json", json.dumps(summary, indent=2) + "\n")

    report = None
    # An earlier run's report describes results that were just replaced: remove it, so that
    # an interrupt while the new one is built leaves no report rather than a wrong one.
    (Path(out_dir) / "report.html").unlink(missing_ok=True)
    if html:
        from .report.html import build_report

        t0 = time.perf_counter()
        try:
            report = build_report(out_dir, progress=progress)
        except KeyboardInterrupt:
            raise ReportInterrupted(
                f"the new results are in {out_dir}, without report.html; run 'kalmansfm report {out_dir}'"
            ) from None
        timings["report_s"] = time.perf_counter() - t0
        timings["total_s"] = time.perf_counter() - started
        # record the report time too (summary.json is rewritten atomically)
        from .io.atomic import atomic_write

        atomic_write(Path(out_dir) / "summary.json", lambda p: p.write_text(json.dumps(summary, indent=2) + "\n"))
    return PipelineResult(Path(out_dir), tracks, reconstruction, summary, report, scene)


def describe(result: PipelineResult) -> str:
    """A few lines for the terminal: tracking, structure, ground-truth errors, time, where the report is."""
    s = result.summary
    t, f = s["tracking"], s.get("factorization", {})
    lines = [f"input: {s['input']}"]
    line = f"tracking: {t['tracks']} tracks over {t['frames']} frames, {t['fraction_tracked']:.1%} of "
    line += "visible points measured" if s["ground_truth"] else "track-frames measured"
    if t.get("rms_error_px") is not None:
        line += f", RMS error {t['rms_error_px']:.3f} px ({t['within_2px']:.1%} within 2 px)"
    lines.append(line)
    if "error" in f:
        lines.append(f"structure: not computed ({f['error']})")
    else:
        sv = ", ".join(f"{v:.4g}" for v in f["singular_values"][:5])
        line = f"structure: singular values {sv}; rank-3 residual {f['residual_rms_px']:.3f} px"
        if f.get("shape_error_pct") is not None:
            line += f"; shape error {f['shape_error_pct']:.2f} % of the object radius"
        lines.append(line)
        lines.extend(f"warning: {w}" for w in f.get("warnings", []))
    lines.append(f"time: {s['timings_s']['total_s']:.1f} s")
    if result.report is not None:
        lines.append(f"report: {result.report}")
    else:
        lines.append(f"results: {result.out_dir}")
    return "\n".join(lines)

