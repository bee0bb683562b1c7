"""The self-contained HTML report of a run folder.

:func:`build_report` reads only the files of a finished run (see
:func:`kalmansfm.io.run_folder.load_run`) and writes one HTML file in which
every image is an embedded PNG data URI and all CSS and JavaScript are inline,
so the file can be mailed, archived or opened offline.  A section appears only
when its inputs exist.
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from ..errors import InvalidInputError
from ..io.atomic import atomic_write
from ..io.frames import encode_jpeg, encode_png
from ..io.records import to_json
from ..io.run_folder import RunFolder, load_run
from ..io.structure import PointTable
from ..io.summary import SUMMARY_FILE, RunSummary
from ..structure.geometry.orthographic import camera_rotation_matrices
from ..structure.points import rms_std
from . import figures
from . import markup as m
from .reconstruction import reconstruction_cards, section_reconstruction
from ._assets import CSS, ERROR_TRAP_JS, JS
from .drawing import gate_radius_of, render_tracked_frames, track_colors

__all__ = ["build_report", "render_report"]

log = logging.getLogger("kalmansfm")

#: Frames shown in the static strip.
STRIP_FRAMES = 6
#: Rows a long table shows before "show all".
TABLE_ROWS = 20
#: At most this many frames go into the animated player (evenly subsampled beyond) ...
MAX_PLAYER_FRAMES = 300
#: ... and fewer if their JPEGs would take more than this many bytes.
MAX_PLAYER_BYTES = 5_000_000

def _total_seconds(summary: RunSummary) -> float | None:
    if summary.total_s is not None and math.isfinite(summary.total_s):
        return summary.total_s
    return None


# --- sections ------------------------------------------------------------------


def _section_header(run: RunFolder) -> str:
    s = run.summary
    tracking, truth = s.tracking, s.truth
    cards = []
    if tracking is not None:
        cards.append(("frames", m.number(tracking.frames)))
        cards.append(("tracks", m.number(tracking.tracks)))
        cards.append(("of track-frames measured", m.percent(tracking.measured_fraction)))
    if truth is not None and m.is_number(truth.tracking_rms_error_px):
        cards.append(("tracking RMS error vs truth", f"{truth.tracking_rms_error_px:.2f} px"))
    if truth is not None and m.is_number(truth.within_2px):
        cards.append(("estimates within 2 px of truth", m.percent(truth.within_2px)))
    if s.reconstruction is not None:
        cards += reconstruction_cards(s.reconstruction)
    if truth is not None and m.is_number(truth.shape_error_pct):
        cards.append(("3D shape error vs truth", f"{truth.shape_error_pct:.2f} %"))
    total = _total_seconds(s)
    if total is not None:
        cards.append(("time taken", f"{total:.2f} s"))
    warnings = "".join(f'<p class="warn">{m.esc(w)}</p>' for w in s.all_warnings)
    meta = [
        f"input: <strong>{m.esc(s.input)}</strong>",
        f"kalmansfm {m.esc(s.versions.kalmansfm)}",
        f"run created {m.esc(s.created)}",
    ]
    command = f'<p class="meta">command: <code>{m.esc(s.command)}</code></p>'
    return (
        f'<header><div class="wrap"><h1>kalmansfm report</h1><p class="meta">{" · ".join(meta)}</p>'
        f"{command}{m.cards(cards) if cards else ''}{warnings}</div></header>"
    )


def _settings_rows(run: RunFolder) -> list[tuple[str, Any]]:
    settings = run.summary.settings
    if settings is None:
        return []
    rows: list[tuple[str, Any]] = []
    for name, value in to_json(settings).items():
        if name == "model":
            for matrix, entries in value.items():
                full = np.asarray(entries, dtype=float)
                square = full.shape[0] == full.shape[1]
                diagonal = square and np.array_equal(full, np.diag(np.diagonal(full)))
                shown = f"diag({m.number(np.diagonal(full).tolist())})" if diagonal else m.number(entries)
                rows.append((f"model {matrix}", m.Html(m.esc(shown))))
        else:
            rows.append((name, value))
    rows.append(("gate radius c (used)", settings.effective_gate_radius))
    rows.append(("smoothed", run.summary.smoothed))
    return rows


def _section_parameters(run: RunFolder) -> str | None:
    rows = _settings_rows(run)
    timings = run.summary.timings_s
    if not rows and not timings:
        return None
    parts = ['<div class="two">']
    if rows:
        parts.append("<div><h3>Tracker settings</h3>" + m.table(["name", "value"], rows) + "</div>")
    if timings:
        table_rows: list[Sequence[Any]] = [(step, m.Html(f"{seconds:.3f}")) for step, seconds in timings]
        total = _total_seconds(run.summary)
        if total is not None:
            table_rows.append((m.Html("<strong>total (the whole run)</strong>"), m.Html(f"{total:.3f}")))
        parts.append("<div><h3>Time per step (s)</h3>" + m.table(["step", "seconds"], table_rows, numeric=[False, True]) + "</div>")
    parts.append("</div>")
    return "".join(parts)


def _legend(radius: float, known: bool) -> str:
    source = "the tracker's gate radius" if known else "the default gate radius; the tracks carry no settings"
    return (
        '<p class="legend note"><span>● filled: measured</span><span>○ ring: predicted (no measurement)</span>'
        "<span>✕: lost</span><span>■ square: initialising (a track's first two frames: its start point and "
        "start-up match; no ellipse, the covariance is the start-up prior)</span>"
        f"<span>ellipse: Mahalanobis radius c = {radius:.3g} ({source}) around the position "
        "covariance (upper-left 2×2 block of the state covariance)</span>"
        "<span>line: the track's path so far</span></p>"
    )


def _section_sequence(run: RunFolder, frames: list[np.ndarray], progress: bool) -> str | None:
    tracks = run.tracks
    if tracks is None and not frames:
        return None
    parts = []
    if tracks is None:
        # frames without tracks: just the strip of raw frames
        picks = np.unique(np.linspace(0, len(frames) - 1, min(STRIP_FRAMES, len(frames))).round().astype(int))
        strip = "".join(
            f"<figure>{m.img(encode_png(frames[f]), f'frame {f}')}<figcaption>frame {f}</figcaption></figure>"
            for f in picks
        )
        return f'<p class="note">No tracks.npz in this run; the frames alone.</p><div class="strip">{strip}</div>'
    n_frames = tracks.positions.shape[0]
    if frames and len(frames) != n_frames:
        log.warning("report: %d frame images but tracks.npz has %d frames", len(frames), n_frames)
        parts.append(
            f'<p class="warn">The run has {len(frames)} frame images but tracks.npz holds {n_frames} frames; '
            "tracks are drawn on the nearest available frame.</p>"
        )
    strip_indices = np.unique(np.linspace(0, n_frames - 1, min(STRIP_FRAMES, n_frames)).round().astype(int)).tolist()

    def draw(f: int) -> str:
        (image,) = render_tracked_frames(frames or None, tracks, [f])
        # JPEG: a drawn frame is a sixth of its PNG, so the player covers a long clip within its budget
        return m.data_uri(encode_jpeg(image), "image/jpeg")

    rendered = {f: draw(f) for f in strip_indices}
    # the player's size budget, from the size of the frames drawn so far
    frame_bytes = max(len(uri) for uri in rendered.values())
    player_count = int(min(MAX_PLAYER_FRAMES, n_frames, max(2, MAX_PLAYER_BYTES // frame_bytes)))
    player_indices = np.unique(np.linspace(0, n_frames - 1, player_count).round().astype(int)).tolist()
    todo = [f for f in player_indices if f not in rendered]
    for f in tqdm(todo, desc="report frames", unit="frame", disable=not progress, leave=False):
        rendered[f] = draw(f)
    background = "" if frames else "No frame images in this run: tracks drawn on grey. "
    gate_note = "" if tracks.covariances is not None else "tracks.npz holds no covariances, so no gates are drawn."
    if len(player_indices) > 1:
        payload = json.dumps([{"frame": f, "src": rendered[f]} for f in player_indices], allow_nan=False)
        stride_note = (
            f" ({len(player_indices)} of the {n_frames} frames, evenly spaced)"
            if len(player_indices) < n_frames
            else ""
        )
        parts.append(
            '<h3 id="player">Animated</h3><div class="player">'
            '<div class="controls"><button id="player-prev" type="button">◀</button>'
            '<button id="player-play" type="button">play</button>'
            '<button id="player-next" type="button">▶</button>'
            f'<input id="player-slider" type="range" min="0" max="{len(player_indices) - 1}" value="0" '
            'aria-label="frame">'
            f'<span id="player-label">frame {player_indices[0]}</span>{m.esc(stride_note)}</div>'
            f'<img id="player-image" src="{rendered[player_indices[0]]}" alt="tracked frame"></div>'
            f'<script type="application/json" id="player-frames">{payload}</script>'
        )
    strip = "".join(
        f'<figure><img src="{rendered[f]}" alt="frame {f} with tracks"><figcaption>frame {f}</figcaption></figure>'
        for f in strip_indices
    )
    parts.append(f'<h3>Frame strip</h3><div class="strip">{strip}</div>')
    parts.append(_legend(gate_radius_of(tracks), tracks.settings is not None))
    if background or gate_note:
        parts.append(f'<p class="note">{m.esc(background + gate_note)}</p>')
    return "".join(parts)


def _section_uncertainty(run: RunFolder) -> str | None:
    parts = []
    if "covariance_trace.png" in run.figures:
        parts.append(m.figure(run.figures["covariance_trace.png"].read_bytes(), "Covariance trace per frame (from the run)."))
    elif run.tracks is not None:
        png = figures.covariance_trace_figure(run.tracks)
        if png is not None:
            parts.append(
                m.figure(
                    png,
                    "Trace of the 4×4 state covariance per frame: mean and range over the tracks the filter "
                    "estimates. A track's first two frames (initialising, shaded while every track starts) carry "
                    "the start-up prior and are not plotted. The trace rises while tracks coast on predictions "
                    "and settles once measured.",
                )
            )
    if run.tracks is not None:
        parts.append(
            m.figure(
                figures.status_timeline_figure(run.tracks),
                "Status of every track in every frame: initialising (its first two frames), measured, "
                "predicted (coasting) or lost.",
            )
        )
        survival = figures.survival_figure(run.tracks)
        if survival is not None:
            parts.append(
                m.figure(
                    survival,
                    "Survival: the share of the first frame's tracks measured (solid) or alive (dashed) in each "
                    "frame, and every track's life from its first to its last measured frame, sorted by length.",
                )
            )
    return "".join(parts) or None


def _section_tracks(run: RunFolder) -> str | None:
    tracking = run.summary.tracking
    if tracking is None and "tracks.png" not in run.figures:
        return None
    parts = []
    truth = run.summary.truth
    if tracking is not None:
        rows: list[tuple[str, Any]] = [
            ("frames", tracking.frames),
            ("tracks", tracking.tracks),
            ("fraction of track-frames measured", tracking.measured_fraction),
            ("tracks alive in the last frame", tracking.alive_in_last_frame),
        ]
        if truth is not None:
            rows += [
                ("fraction of visible points measured", truth.visible_measured_fraction),
                ("RMS error vs ground truth (px)", truth.tracking_rms_error_px),
                ("fraction within 2 px of ground truth", truth.within_2px),
            ]
        parts.append(m.table(["", "value"], [r for r in rows if r[1] is not None]))
    if tracking is not None and tracking.per_track:
        ids = [row.track_id for row in tracking.per_track]
        colors = track_colors(ids)
        errors = truth.per_track_rms_error_px if truth is not None else ()
        header = ["track", "measured", "predicted", "lost at frame", "mean std (px)", "RMS error (px)"]
        rows = []
        for k, row in enumerate(tracking.per_track):
            swatch = f'<span class="swatch" style="background:{colors[k]}"></span>'
            cells = [m.Html(f"{swatch}{row.track_id}"), row.frames_measured, row.frames_predicted, row.lost_at,
                     row.mean_std_px, errors[k] if k < len(errors) else None]
            rows.append(cells)
        parts.append("<h3>Per track</h3>")
        parts.append(
            '<p class="note">Click a column header to sort. Each track has one colour everywhere: here, in the '
            "drawings of the frames and in the plots of the shape. Measured frames include the two "
            "initialising ones; the mean std leaves them out (their covariance is the start-up prior).</p>"
        )
        parts.append(m.table(header, rows, sortable=True, numeric=[True] * len(header), fold=TABLE_ROWS, drop_empty=True))
    if "tracks.png" in run.figures:
        parts.append(m.figure(run.figures["tracks.png"].read_bytes(), "The tracks over the last frame (from the run)."))
    return "".join(parts) or None


def _by_uncertainty(run: RunFolder) -> bool:
    """Colour the points by their uncertainty: runs with covariances and no tracks to match by colour.

    A factorization's points keep their tracks' colours, so that a point can be found in the player.
    """
    r = run.summary.reconstruction
    return (run.structure is not None and run.structure.covariances is not None
            and (r is None or r.kind != "affine"))


def _shape_payload(run: RunFolder, structure: PointTable, truth_here: np.ndarray | None,
                   motion_rotations: np.ndarray | None) -> dict[str, Any]:
    reliable = structure.reliable
    core = structure.points[reliable] if reliable.any() else structure.points
    centre, half = figures.robust_half_width(core)
    points = structure.points - centre
    # the view's scale: the farthest of the points inside the robust axes (a stray point does not shrink the rest)
    inside = np.abs(core - centre).max(axis=1) <= half
    radius = float(np.linalg.norm(core[inside] - centre, axis=1).max()) if inside.any() else half
    payload: dict[str, Any] = {
        "points": np.round(points, 6).tolist(),
        "labels": structure.track_ids.tolist(),
        "colors": track_colors(structure.track_ids),
        "unreliable": (~reliable).tolist(),
        "radius": radius or 1.0,
        "truth": None if truth_here is None else np.round(truth_here - centre, 6).tolist(),
        "cameras": [],
        "camera_frames": [],
    }
    if structure.covariances is not None:
        # the same points coloured by their uncertainty √(tr Σ / 3) (viridis, log scale)
        payload["uncertainty_colors"] = figures.uncertainty_colors(rms_std(structure.covariances))[0]
    if motion_rotations is not None:
        payload["cameras"] = np.round(motion_rotations, 6).tolist()
        payload["camera_frames"] = run.motion.frames.tolist()
    if run.cameras is not None and len(run.cameras.frames):
        pose = run.cameras.decompose()
        centres = pose.centers - centre
        payload["cameras"] = np.round(pose.rotations, 6).tolist()
        payload["camera_frames"] = run.cameras.frames.tolist()
        payload["camera_centres"] = np.round(centres, 6).tolist()
        payload["radius"] = max(radius, float(np.linalg.norm(centres, axis=1).max()) / 1.6)
    return payload


def _matched_truth(run: RunFolder) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Recovered points, ground-truth points and ids, matched by track id (in the order of structure.csv)."""
    if run.structure is None or run.ground_truth_points is None or run.summary.truth is None:
        return None
    if run.summary.truth.alignment is None:
        return None
    common, in_structure, in_truth = np.intersect1d(
        run.structure.track_ids, run.ground_truth_points.track_ids, return_indices=True
    )
    if len(common) < 3:
        return None
    order = np.argsort(in_structure)
    return run.structure.points[in_structure[order]], run.ground_truth_points.points[in_truth[order]], common[order]


def _section_shape(run: RunFolder, motion_rotations: np.ndarray | None) -> str | None:
    structure = run.structure
    if structure is None or not len(structure.points):
        if "structure.png" in run.figures:
            return m.figure(run.figures["structure.png"].read_bytes(), "Recovered structure (from the run).")
        return None
    parts = []
    matched = _matched_truth(run)
    truth_here = None
    if matched is not None and len(matched[2]) == len(structure.track_ids):
        # the truth moved onto the recovered points by the inverse of the run's alignment
        truth_here = run.summary.truth.alignment.invert(matched[1])  # type: ignore[union-attr]
    payload = json.dumps(_shape_payload(run, structure, truth_here, motion_rotations), allow_nan=False)
    truth_toggle = (
        '<label><input id="view3d-truth" type="checkbox" checked> ground truth (rings, aligned)</label>'
        if truth_here is not None
        else ""
    )
    camera_slider = (
        '<label>view from camera <input id="view3d-camera" type="range" min="0" max="0" value="0" '
        'aria-label="camera"></label> <span id="view3d-camera-label"></span>'
        if run.motion is not None or run.cameras is not None
        else ""
    )
    if run.cameras is not None:
        squares = "Purple squares: the camera centres (the camera path). "
    elif run.motion is not None:
        squares = "Purple squares: the direction each camera looked from (the recovered camera path). "
    else:
        squares = ""
    colour_choice = ""
    if structure.covariances is not None:
        by_uncertainty = _by_uncertainty(run)
        colour_choice = (
            '<label>colour: <select id="view3d-colour">'
            f'<option value="track"{"" if by_uncertainty else " selected"}>track (as in the player)</option>'
            f'<option value="uncertainty"{" selected" if by_uncertainty else ""}>uncertainty √(tr Σ / 3): dark = '
            "certain, yellow = uncertain</option></select></label>"
        )
    unreliable = int((~structure.reliable).sum())
    unreliable_toggle = ""
    if unreliable:
        unreliable_toggle = (
            f'<label><input id="view3d-unreliable" type="checkbox"> the {unreliable} unreliable points '
            "(hollow)</label>"
        )
        views = structure.views[~structure.reliable]  # type: ignore[index]
        parts.append(
            f'<p class="warn">{unreliable} of {len(structure.track_ids)} points are unreliable (marked in '
            f"structure.csv; seen in {m.number(int(views.min()))}–{m.number(int(views.max()))} frames): their depth "
            "is barely constrained by the frames that saw them. They are left out of the plots; the box below "
            "shows them in the interactive view.</p>"
        )
    labels = "" if len(structure.track_ids) <= 60 else ", point under the pointer: its track id"
    parts.append(
        '<h3 id="interactive-3d">Interactive view</h3>'
        f'<p class="note">Drag to rotate, wheel to zoom{labels}. {squares}</p>'
        f'<div class="controls"><button id="view3d-reset" type="button">reset</button>{truth_toggle}'
        f"{unreliable_toggle}{colour_choice}{camera_slider}</div>"
        '<canvas id="view3d" class="view3d" width="720" height="440"></canvas>'
        f'<script type="application/json" id="shape-data">{payload}</script>'
        "<noscript><p class='note'>The interactive view needs JavaScript; the fixed views follow.</p></noscript>"
    )
    if "structure.png" in run.figures:
        parts.append(m.figure(run.figures["structure.png"].read_bytes(), "Recovered structure (from the run)."))
    else:
        shown = structure.reliable
        parts.append(
            m.figure(
                figures.shape_views_figure(structure.points[shown], structure.track_ids[shown].tolist(),
                                           hidden=unreliable),
                f"The {int(shown.sum())} reliable recovered 3D points from four viewpoints (Y down, as in the image).",
            )
        )
    return "".join(parts)


def _section_motion(run: RunFolder, motion_rotations: np.ndarray | None) -> str | None:
    if run.motion is None or motion_rotations is None:
        return None
    rotations = figures.camera_rotations(run.motion, motion_rotations)
    total = rotations[1]
    return m.figure(
        figures.camera_rotation_figure(run.motion, rotations),
        "Camera rotation recovered per frame, relative to the first frame (rows i, j of the motion matrix "
        f"and k = i × j, snapped to the nearest rotation); largest total rotation {float(total.max()):.2f}°. "
        "Right: the image translation of the shape's centroid.",
    )


def _section_ground_truth(run: RunFolder) -> str | None:
    truth = run.summary.truth
    if truth is None:
        return None
    parts = []
    if run.tracks is not None and run.ground_truth_tracks is not None:
        per_frame = np.array([np.nan if v is None else v for v in truth.rms_error_per_frame_px], dtype=float)
        facts: list[tuple[str, Any]] = [
            ("frames with a comparison", int(np.isfinite(per_frame).sum())),
            ("RMS error of the measured estimates (px)", truth.tracking_rms_error_px),
            ("median error (px)", truth.median_error_px),
            ("worst error (px)", truth.max_error_px),
            ("within 2 px", truth.within_2px),
        ]
        parts.append("<h3>Tracking error</h3><p class=\"note\">Over the measured estimates of visible points, as "
                     "the summary counts them.</p>" + m.table(["", "value"], facts))
        measured = np.where(run.tracks.measured[..., None], run.tracks.positions, np.nan)
        parts.append(
            m.figure(
                figures.track_error_figure(measured, run.ground_truth_tracks, run.tracks.track_ids, per_frame),
                "Distance between each track's measured estimate and the true image position per frame (faint "
                "lines, one per track) and their RMS (black); frames where the point is not visible or was not "
                "measured are left out.",
            )
        )
    matched = _matched_truth(run)
    if matched is not None:
        recovered, true_points, ids = matched
        alignment = truth.alignment
        aligned = alignment.apply(recovered)  # type: ignore[union-attr]
        facts = [("points compared", len(ids)), ("shape error (% of the object's RMS radius)", truth.shape_error_pct)]
        # the unreliable points are left out of the plot, as everywhere
        shown = np.isin(ids, run.structure.track_ids[run.structure.reliable])  # type: ignore[union-attr]
        parts.append("<h3>3D shape</h3>" + m.table(["", "value"], facts))
        if alignment.mirrored:  # type: ignore[union-attr]
            parts.append(
                '<p class="warn">The recovered shape fits the truth best as a mirror image: the depth-reversal '
                "ambiguity of orthographic factorization.</p>"
            )
        parts.append(
            m.figure(
                figures.shape_views_figure(aligned[shown], ids[shown].tolist(), truth=true_points[shown],
                                           hidden=int((~shown).sum())),
                "Recovered points after the best similarity transform onto the ground truth (dots) and the "
                "ground truth (rings).",
            )
        )
    errors = [v for v in truth.rotation_error_deg if v is not None]
    if errors:
        parts.append("<h3>Camera rotation</h3>")
        parts.append(m.figure(figures.rotation_error_figure(truth.rotation_error_deg),
                             "Camera rotation error per frame (degrees)."))
    if not parts and m.is_number(truth.shape_error_pct):
        parts.append(m.table(["", "value"], [("shape error (%)", truth.shape_error_pct)]))
    return "".join(parts) or None


def _section_tables(run: RunFolder) -> str | None:
    parts = []
    for table in run.fusion_tables:
        parts.append(f"<h3>{m.esc(table.name)}</h3>")
        parts.append(m.table(table.header, table.rows))
    return "".join(parts) or None


def _section_files(run: RunFolder) -> str | None:
    if set(run.data_files) <= {"summary.json"} and not run.frame_paths:
        return None
    items = [f'<li><a href="{m.esc(name)}">{m.esc(name)}</a></li>' for name in run.data_files]
    if run.frame_paths:
        items.append(f'<li><a href="frames/">frames/</a> ({len(run.frame_paths)} PNG images)</li>')
    return (
        '<p class="note">The data behind this report, next to it in the run folder '
        "(links work while the report sits in its run folder).</p><ul>" + "".join(items) + "</ul>"
    )


# --- assembly -------------------------------------------------------------------------


def _sections(run: RunFolder, sequence: Callable[[], str | None]) -> list[tuple[str, str, str]]:
    """(anchor, title, HTML) of each section the run has; ``sequence`` draws the frames' section."""
    # the factorization's camera rotations, computed once for the 3-D view and the motion section
    motion_rotations = (camera_rotation_matrices(run.motion.rows)
                        if run.motion is not None and len(run.motion.frames) else None)
    candidates = [
        ("sequence", "Sequence with tracks and gates", sequence),
        ("uncertainty", "Uncertainty over time", lambda: _section_uncertainty(run)),
        ("tracks", "Tracking statistics", lambda: _section_tracks(run)),
        ("reconstruction", "Reconstruction", lambda: section_reconstruction(run)),
        ("shape", "Recovered 3D shape", lambda: _section_shape(run, motion_rotations)),
        ("motion", "Recovered camera motion", lambda: _section_motion(run, motion_rotations)),
        ("ground-truth", "Comparison with ground truth", lambda: _section_ground_truth(run)),
        ("tables", "Tables", lambda: _section_tables(run)),
        ("parameters", "Parameters", lambda: _section_parameters(run)),
        ("files", "Files", lambda: _section_files(run)),
    ]
    built = [(anchor, title, build()) for anchor, title, build in candidates]
    return [(anchor, title, body) for anchor, title, body in built if body]


def render_report(run: RunFolder, *, progress: bool = False, frames: Sequence[np.ndarray] | None = None) -> str:
    """The report of a loaded run folder as one HTML string.

    Parameters
    ----------
    run : RunFolder
        What :func:`kalmansfm.io.run_folder.load_run` read.
    progress : bool
        Show a progress bar (stderr) while frames are drawn.
    frames : the run's frames when the caller holds them (else they are read from the run folder).
    """
    shown = list(frames) if frames is not None else run.read_frames()
    sections = _sections(run, lambda: _section_sequence(run, shown, progress))
    nav = "".join(f'<a href="#{anchor}">{m.esc(title)}</a>' for anchor, title, _ in sections)
    body_html = "".join(
        f'<section id="{anchor}"><div class="wrap"><h2>{m.esc(title)}</h2>{body}</div></section>'
        for anchor, title, body in sections
    )
    title = f"kalmansfm report: {run.summary.input}"
    version = m.esc(run.summary.versions.kalmansfm)
    built = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{m.esc(title)}</title><style>{CSS}</style><script>{ERROR_TRAP_JS}</script></head><body>"
        f"{_section_header(run)}"
        f'<nav aria-label="sections"><div class="wrap">{nav}</div></nav>'
        f"<main>{body_html}</main>"
        f'<footer><div class="wrap">Written by kalmansfm {version} on {built} from the files of '
        f"<code>{m.esc(str(run.path))}</code>. Rebuild with <code>kalmansfm report DIR</code>."
        '<p id="js-status" data-ready="no" hidden></p></div></footer>'
        f"<script>{JS}</script></body></html>\n"
    )


def _shown(text: str) -> str:
    """``text`` with the surrogates Python makes of undecodable file-name bytes turned back into UTF-8 where they
    spell it (a name such as 'dé' under the C locale), else into ``\\xNN`` escapes."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def build_report(
    run_dir: str | Path, *, out_name: str = "report.html", progress: bool = False, shown_as: str | Path | None = None,
    frames: Sequence[np.ndarray] | None = None,
) -> Path:
    """Write the self-contained HTML report of a finished run folder.

    Parameters
    ----------
    run_dir : path
        A run folder: ``summary.json`` plus the files it lists (frames, tracks,
        structure, motion, ground truth, tables); see :func:`kalmansfm.io.load_run`.
    out_name : str
        File name of the report inside ``run_dir``: a plain ``.html`` name that is not one of
        the run's files.
    progress : bool
        Show a progress bar on stderr while frames are drawn.
    shown_as : path, optional
        The folder the run will be known by, when ``run_dir`` is the staging folder of a run
        being built (:class:`kalmansfm.io.OutputDirectory`); the report names it.
    frames : sequence of images, optional
        The run's frames, when the caller still holds them (a run just made): they are then not
        decoded again from the run folder.

    Returns
    -------
    Path
        The report, ``shown_as / out_name`` (default ``run_dir / out_name``), written atomically.

    Raises
    ------
    InvalidInputError
        If ``summary.json`` is missing or broken, a listed file is missing or cannot be
        read (the message names the file), or ``out_name`` would overwrite a file of the run.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> from kalmansfm.io import RunSummary, summary_json
    >>> from kalmansfm.tracking import TrackerSettings
    >>> run = pathlib.Path(tempfile.mkdtemp())
    >>> summary = RunSummary(command="track", input="clip.mp4", settings=TrackerSettings(window=7))
    >>> _ = (run / "summary.json").write_text(summary_json(summary))
    >>> path = build_report(run)
    >>> path.name, "Tracker settings" in path.read_text()
    ('report.html', True)
    """
    name = Path(out_name)
    if name.name != out_name or not out_name or out_name in (".", ".."):
        raise InvalidInputError(f"out_name must be a plain file name; got {out_name!r}")
    run = load_run(run_dir)
    owned = {SUMMARY_FILE, *(f.split("/")[0] for f in run.summary.files)}
    if out_name in owned:
        raise InvalidInputError(f"out_name {out_name} would overwrite the run's own {out_name}; choose another name")
    if name.suffix.lower() != ".html":
        raise InvalidInputError(f"out_name must end in .html (the report is an HTML file); got {out_name!r}")
    target = run.path / out_name
    if target.exists() and not target.is_file():
        raise InvalidInputError(f"out_name {out_name}: {target} exists and is not a file; choose another name")
    folder = run.path if shown_as is None else Path(shown_as)
    document = render_report(replace(run, path=folder), progress=progress, frames=frames)
    # a name that is not UTF-8 (or one the C locale left as surrogates) is shown as its bytes, not a crash
    atomic_write(target, lambda path: path.write_text(_shown(document), encoding="utf-8"))
    return folder / out_name
