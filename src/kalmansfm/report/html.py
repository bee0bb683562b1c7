"""The self-contained HTML report of a run folder.

:func:`build_report` reads only the files of a finished run (see
:func:`kalmansfm.report.run_folder.load_run`) and writes one HTML file in which
every image is an embedded PNG data URI and all CSS and JavaScript are inline,
so the file can be mailed, archived or opened offline.  A section appears only
when its inputs exist.
"""

from __future__ import annotations

import base64
import datetime as _dt
import html
import json
import logging
import math
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from ..errors import InvalidInputError
from ..io.atomic import output_directory
from ..structure.alignment import align_similarity
from . import figures
from ._assets import CSS, ERROR_TRAP_JS, JS
from .run_folder import RunFolder, load_run

__all__ = ["build_report", "render_report"]

log = logging.getLogger("kalmansfm")

#: Frames shown in the static strip.
STRIP_FRAMES = 6
#: At most this many frames go into the animated player (evenly subsampled beyond) ...
MAX_PLAYER_FRAMES = 120
#: ... and fewer if their PNGs would take more than this many bytes.
MAX_PLAYER_BYTES = 8_000_000

_esc = html.escape


# --- small formatting helpers ------------------------------------------------


def _data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def _img(png: bytes, alt: str, *, css_class: str = "", width: int | None = None) -> str:
    attrs = f' class="{css_class}"' if css_class else ""
    if width:
        attrs += f' width="{width}"'
    return f'<img src="{_data_uri(png)}" alt="{_esc(alt)}"{attrs}>'


def _figure(png: bytes, caption: str, alt: str | None = None) -> str:
    return f"<figure>{_img(png, alt or caption)}<figcaption>{caption}</figcaption></figure>"


def _number(value: Any, digits: int = 4) -> str:
    """A value for a table cell: None → an em dash, floats to ``digits`` significant digits."""
    if value is None:
        return "—"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "—"
        return f"{value:.{digits}g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_number(v, digits) for v in value)
    if isinstance(value, dict):
        return _esc(json.dumps(value))
    return _esc(str(value))


def _percent(value: Any) -> str:
    return "—" if not isinstance(value, (int, float)) or isinstance(value, bool) else f"{100 * value:.1f} %"


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class _Html(str):
    """Markup that a table cell inserts as it is (already escaped)."""


def _table(
    header: Sequence[str], rows: Iterable[Sequence[Any]], *, sortable: bool = False, numeric: Sequence[bool] = ()
) -> str:
    css = ' class="sortable"' if sortable else ""
    head = "".join(f"<th>{_esc(h)}</th>" for h in header)
    body = []
    for row in rows:
        cells = []
        for k, value in enumerate(row):
            is_num = numeric[k] if k < len(numeric) else _is_number(value)
            sort_key = f' data-sort="{value}"' if _is_number(value) else ""
            css_cell = ' class="num"' if is_num else ""
            cells.append(f"<td{css_cell}{sort_key}>{value if isinstance(value, _Html) else _number(value)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table{css}><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _cards(items: Sequence[tuple[str, str]]) -> str:
    cards = "".join(
        f'<div class="card"><div class="value">{value}</div><div class="label">{_esc(label)}</div></div>'
        for label, value in items
    )
    return f'<div class="cards">{cards}</div>'


def _get(mapping: Any, *keys: str) -> Any:
    for key in keys:
        if not isinstance(mapping, dict):
            return None
        mapping = mapping.get(key)
    return mapping


# --- sections ------------------------------------------------------------------


def _gate_probability(summary: dict[str, Any]) -> float:
    value = _get(summary, "parameters", "gate_probability")
    return float(value) if _is_number(value) and 0 < value < 1 else 0.95


def _read_frames(run: RunFolder) -> list[np.ndarray]:
    frames = []
    for path in run.frame_paths:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise InvalidInputError(f"{path}: cannot be read as a PNG image")
        if image.dtype != np.uint8:
            image = cv2.convertScaleAbs(image, alpha=255.0 / max(float(image.max()), 1.0))
        if image.ndim == 3 and image.shape[2] == 4:
            image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
        frames.append(image)
    return frames


def _section_header(run: RunFolder) -> str:
    s = run.summary
    tracking = s.get("tracking") or {}
    factorization = s.get("factorization") or {}
    timings = s.get("timings_s") or {}
    total_time = sum(v for v in timings.values() if _is_number(v)) if timings else None
    cards = []
    if _is_number(tracking.get("frames")):
        cards.append(("frames", _number(tracking["frames"])))
    if _is_number(tracking.get("tracks")):
        cards.append(("tracks", _number(tracking["tracks"])))
    if _is_number(tracking.get("fraction_tracked")):
        cards.append(("of track-frames measured", _percent(tracking["fraction_tracked"])))
    if _is_number(tracking.get("rms_error_px")):
        cards.append(("tracking RMS error vs truth", f"{tracking['rms_error_px']:.2f} px"))
    if _is_number(tracking.get("within_2px")):
        cards.append(("estimates within 2 px of truth", _percent(tracking["within_2px"])))
    if _is_number(factorization.get("residual_rms_px")):
        cards.append(("factorization residual RMS", f"{factorization['residual_rms_px']:.3g} px"))
    if _is_number(factorization.get("shape_error_pct")):
        cards.append(("3D shape error vs truth", f"{factorization['shape_error_pct']:.2f} %"))
    if total_time is not None and timings:
        cards.append(("time taken", f"{total_time:.2f} s"))
    meta = [
        f"input: <strong>{_esc(str(s.get('input', 'unknown')))}</strong>",
        f"kalmansfm {_esc(str(s.get('kalmansfm_version', '?')))}",
        f"run created {_esc(str(s.get('created', '?')))}",
    ]
    command = f'<p class="meta">command: <code>{_esc(str(s["command"]))}</code></p>' if s.get("command") else ""
    return (
        f'<header><div class="wrap"><h1>kalmansfm report</h1><p class="meta">{" · ".join(meta)}</p>'
        f"{command}{_cards(cards) if cards else ''}</div></header>"
    )


def _section_parameters(run: RunFolder) -> str | None:
    parameters = run.summary.get("parameters") or {}
    timings = run.summary.get("timings_s") or {}
    if not parameters and not timings:
        return None
    parts = ['<div class="two">']
    if parameters:
        parts.append("<div><h3>Parameters</h3>" + _table(["name", "value"], sorted(parameters.items())) + "</div>")
    if timings:
        rows = list(timings.items())
        total = sum(v for v in timings.values() if _is_number(v))
        rows.append((_Html("<strong>total</strong>"), total))
        parts.append("<div><h3>Time per step (s)</h3>" + _table(["step", "seconds"], rows) + "</div>")
    parts.append("</div>")
    return "".join(parts)


def _legend(probability: float) -> str:
    return (
        '<p class="legend note"><span>● filled: measured</span><span>○ ring: predicted (no measurement)</span>'
        f"<span>✕: lost</span><span>ellipse: {100 * probability:g} % region of the position covariance "
        "(upper-left 2×2 block of the state covariance)</span>"
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
            f"<figure>{_img(figures.png_bytes(frames[f]), f'frame {f}')}<figcaption>frame {f}</figcaption></figure>"
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
    probability = _gate_probability(run.summary)
    strip_indices = np.unique(np.linspace(0, n_frames - 1, min(STRIP_FRAMES, n_frames)).round().astype(int)).tolist()

    def draw(f: int) -> str:
        (image,) = figures.render_tracked_frames(frames or None, tracks, [f], gate_probability=probability)
        return _data_uri(figures.png_bytes(image))

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
            f" (every {n_frames / len(player_indices):.1f}th frame of {n_frames})"
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
            f'<span id="player-label">frame {player_indices[0]}</span>{_esc(stride_note)}</div>'
            f'<img id="player-image" src="{rendered[player_indices[0]]}" alt="tracked frame"></div>'
            f'<script type="application/json" id="player-frames">{payload}</script>'
        )
    strip = "".join(
        f'<figure><img src="{rendered[f]}" alt="frame {f} with tracks"><figcaption>frame {f}</figcaption></figure>'
        for f in strip_indices
    )
    parts.append(f'<h3>Frame strip</h3><div class="strip">{strip}</div>')
    parts.append(_legend(probability))
    if background or gate_note:
        parts.append(f'<p class="note">{_esc(background + gate_note)}</p>')
    return "".join(parts)


def _section_uncertainty(run: RunFolder) -> str | None:
    parts = []
    if "covariance_trace.png" in run.figures:
        parts.append(_figure(run.figures["covariance_trace.png"].read_bytes(), "Covariance trace per frame (from the run)."))
    elif run.tracks is not None:
        png = figures.covariance_trace_figure(run.tracks)
        if png is not None:
            parts.append(
                _figure(
                    png,
                    "Trace of the 4×4 state covariance per frame: mean and range over the tracks with an "
                    "estimate. It rises while tracks coast on predictions and settles once measured.",
                )
            )
    if run.tracks is not None:
        parts.append(
            _figure(
                figures.status_timeline_figure(run.tracks),
                "Status of every track in every frame: measured, predicted (coasting) or lost.",
            )
        )
    return "".join(parts) or None


def _section_tracks(run: RunFolder) -> str | None:
    tracking = run.summary.get("tracking") or {}
    per_track = tracking.get("per_track") or []
    if not tracking and "tracks.png" not in run.figures:
        return None
    parts = []
    if tracking:
        keys = [
            ("frames", "frames"),
            ("tracks", "tracks"),
            ("fraction_tracked", "fraction of track-frames measured"),
            ("rms_error_px", "RMS error vs ground truth (px)"),
            ("within_2px", "fraction within 2 px of ground truth"),
        ]
        rows = [(label, tracking[key]) for key, label in keys if tracking.get(key) is not None]
        if rows:
            parts.append(_table(["", "value"], rows))
    if per_track:
        ids = run.tracks.track_ids.tolist() if run.tracks is not None else []
        colors = figures.track_colors(len(ids))
        color_of = dict(zip(ids, colors))
        columns = ["track_id", "frames_measured", "frames_predicted", "lost_at", "rms_error_px", "mean_std_px"]
        extra = sorted({k for row in per_track for k in row} - set(columns))
        header = ["track", "measured", "predicted", "lost at frame", "RMS error (px)", "mean std (px)", *extra]
        rows = []
        for row in per_track:
            track = row.get("track_id")
            swatch = f'<span class="swatch" style="background:{color_of[track]}"></span>' if track in color_of else ""
            first = _Html(f"{swatch}{_number(track)}")
            rows.append([first, *(row.get(c) for c in columns[1:]), *(row.get(c) for c in extra)])
        parts.append("<h3>Per track</h3>")
        parts.append('<p class="note">Click a column header to sort. Colours match the drawings.</p>')
        parts.append(_table(header, rows, sortable=True, numeric=[True] * len(header)))
    if "tracks.png" in run.figures:
        parts.append(_figure(run.figures["tracks.png"].read_bytes(), "Tracks (from the run)."))
    return "".join(parts) or None


def _section_factorization(run: RunFolder) -> str | None:
    factorization = run.summary.get("factorization") or {}
    if not factorization:
        return None
    parts = []
    values = factorization.get("singular_values") or []
    numbers = [float(v) for v in values if _is_number(v)]
    facts = []
    if _is_number(factorization.get("residual_rms_px")):
        facts.append(("residual RMS after the rank-3 fit (px)", factorization["residual_rms_px"]))
    if len(numbers) >= 4 and numbers[3] > 0:
        facts.append(("σ3 / σ4 (large = clearly rank 3)", numbers[2] / numbers[3]))
    if facts:
        parts.append(_table(["", "value"], facts))
    for warning in factorization.get("warnings") or []:
        parts.append(f'<p class="warn">{_esc(str(warning))}</p>')
    if numbers:
        shown = numbers[:12]
        parts.append('<div class="two">')
        parts.append(
            _figure(
                figures.singular_values_figure(numbers),
                "Singular values of the registered measurement matrix. Noise-free orthographic tracks "
                "have rank 3; the values after the third measure noise and model error.",
            )
        )
        parts.append(
            "<div>"
            + _table(["k", "σk"], [(k + 1, v) for k, v in enumerate(shown)])
            + (f'<p class="note">{len(numbers) - len(shown)} more not listed.</p>' if len(numbers) > len(shown) else "")
            + "</div></div>"
        )
    return "".join(parts) or None


def _colors_of(run: RunFolder, track_ids: np.ndarray) -> list[str]:
    """The colour each track has in the drawings of the sequence (by its column in tracks.npz)."""
    if run.tracks is None:
        return figures.track_colors(len(track_ids))
    palette = figures.track_colors(len(run.tracks.track_ids))
    column_of = {int(t): k for k, t in enumerate(run.tracks.track_ids)}
    grey = "#7f7f7f"
    return [palette[column_of[int(t)]] if int(t) in column_of else grey for t in track_ids]


def _shape_payload(run: RunFolder, aligned_truth: np.ndarray | None) -> dict[str, Any]:
    structure = run.structure
    centre = structure.points.mean(axis=0)
    points = structure.points - centre
    radius = float(np.linalg.norm(points, axis=1).max()) or 1.0
    payload: dict[str, Any] = {
        "points": np.round(points, 6).tolist(),
        "labels": structure.track_ids.tolist(),
        "colors": _colors_of(run, structure.track_ids),
        "radius": radius,
        "truth": None if aligned_truth is None else np.round(aligned_truth - centre, 6).tolist(),
        "cameras": [],
        "camera_frames": [],
    }
    if run.motion is not None and len(run.motion.frames):
        payload["cameras"] = np.round(figures.camera_rotation_matrices(run.motion), 6).tolist()
        payload["camera_frames"] = run.motion.frames.tolist()
    return payload


def _matched_truth(run: RunFolder) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Recovered points, ground-truth points and ids, matched by track id."""
    if run.structure is None or run.ground_truth_points is None:
        return None
    common, in_structure, in_truth = np.intersect1d(
        run.structure.track_ids, run.ground_truth_points.track_ids, return_indices=True
    )
    if len(common) < 3:
        return None
    return run.structure.points[in_structure], run.ground_truth_points.points[in_truth], common


def _best_alignment(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float, bool]:
    proper = align_similarity(source, target)
    mirrored = align_similarity(source, target, allow_reflection=True)
    if mirrored.rms < 0.5 * proper.rms:
        return mirrored.aligned, mirrored.rms, True
    return proper.aligned, proper.rms, False


def _section_shape(run: RunFolder) -> str | None:
    if run.structure is None and "structure.png" not in run.figures:
        return None
    parts = []
    if run.structure is not None and len(run.structure.points):
        matched = _matched_truth(run)
        aligned_truth = None
        if matched is not None and len(matched[2]) == len(run.structure.track_ids):
            # truth moved onto the recovered points, in the order of structure.csv
            order = np.argsort(np.argsort(run.structure.track_ids))
            recovered, truth, _ = matched
            aligned_truth = _best_alignment(truth, recovered)[0][order]
        payload = json.dumps(_shape_payload(run, aligned_truth), allow_nan=False)
        truth_toggle = (
            '<label><input id="view3d-truth" type="checkbox" checked> ground truth (rings, aligned)</label>'
            if aligned_truth is not None
            else ""
        )
        camera_slider = (
            '<label>view from camera <input id="view3d-camera" type="range" min="0" max="0" value="0" '
            'aria-label="camera"></label> <span id="view3d-camera-label"></span>'
            if run.motion is not None
            else ""
        )
        parts.append(
            '<h3 id="interactive-3d">Interactive view</h3>'
            '<p class="note">Drag to rotate, wheel to zoom. Purple squares: the direction each camera looked from '
            "(the recovered camera path).</p>"
            f'<div class="controls"><button id="view3d-reset" type="button">reset</button>{truth_toggle}'
            f"{camera_slider}</div>"
            '<canvas id="view3d" class="view3d" width="720" height="440"></canvas>'
            f'<script type="application/json" id="shape-data">{payload}</script>'
            "<noscript><p class='note'>The interactive view needs JavaScript; the fixed views follow.</p></noscript>"
        )
        parts.append(
            _figure(
                figures.shape_views_figure(
                    run.structure.points,
                    run.structure.track_ids.tolist(),
                    colors=_colors_of(run, run.structure.track_ids),
                ),
                f"The {len(run.structure.points)} recovered 3D points from four viewpoints (Y down, as in the image).",
            )
        )
    if "structure.png" in run.figures:
        parts.append(_figure(run.figures["structure.png"].read_bytes(), "Recovered structure (from the run)."))
    return "".join(parts)


def _section_motion(run: RunFolder) -> str | None:
    if run.motion is None or len(run.motion.frames) == 0:
        return None
    _, total = figures.camera_rotations(run.motion)
    return _figure(
        figures.camera_rotation_figure(run.motion),
        "Camera rotation recovered per frame, relative to the first frame (rows i, j of the motion matrix "
        f"and k = i × j, snapped to the nearest rotation); largest total rotation {float(total.max()):.2f}°. "
        "Right: the image translation of the shape's centroid.",
    )


def _section_ground_truth(run: RunFolder) -> str | None:
    parts = []
    tracking = run.summary.get("tracking") or {}
    factorization = run.summary.get("factorization") or {}
    if run.tracks is not None and run.ground_truth_tracks is not None:
        rms, distances = figures.track_error_per_frame(run.tracks.positions, run.ground_truth_tracks)
        facts = [("frames with a comparison", int(np.isfinite(rms).sum()))]
        if np.isfinite(distances).any():
            facts.append(("median error (px)", float(np.nanmedian(distances))))
            facts.append(("worst error (px)", float(np.nanmax(distances))))
        if _is_number(tracking.get("rms_error_px")):
            facts.append(("RMS error (px, from summary)", tracking["rms_error_px"]))
        parts.append("<h3>Tracking error</h3>" + _table(["", "value"], facts))
        parts.append(
            _figure(
                figures.track_error_figure(run.tracks.positions, run.ground_truth_tracks),
                "Distance between each track's estimate and the true image position per frame (faint lines, "
                "one per track) and their RMS (black); frames where the point is not visible are left out.",
            )
        )
    matched = _matched_truth(run)
    if matched is not None:
        recovered, truth, ids = matched
        aligned, rms, mirrored = _best_alignment(recovered, truth)
        spread = float(np.sqrt(((truth - truth.mean(0)) ** 2).sum(axis=1).mean()))
        facts = [("points compared", len(ids)), ("RMS distance after alignment (truth units)", rms)]
        if spread > 0:
            facts.append(("relative to the shape's RMS radius", f"{100 * rms / spread:.2f} %"))
        if _is_number(factorization.get("shape_error_pct")):
            facts.append(("shape error (%, from summary)", factorization["shape_error_pct"]))
        parts.append("<h3>3D shape</h3>" + _table(["", "value"], facts))
        if mirrored:
            parts.append(
                '<p class="warn">The recovered shape fits the truth best as a mirror image: the depth-reversal '
                "ambiguity of orthographic factorization.</p>"
            )
        parts.append(
            _figure(
                figures.shape_views_figure(aligned, ids.tolist(), colors=_colors_of(run, ids), truth=truth),
                "Recovered points after the best similarity transform onto the ground truth (dots) and the "
                "ground truth (rings).",
            )
        )
    errors = factorization.get("rotation_error_deg")
    if isinstance(errors, list) and errors and all(_is_number(v) for v in errors):
        parts.append("<h3>Camera rotation</h3>")
        parts.append(_figure(figures.rotation_error_figure(errors), "Camera rotation error per frame (degrees)."))
    if not parts and _is_number(factorization.get("shape_error_pct")):
        parts.append(_table(["", "value"], [("shape error (%)", factorization["shape_error_pct"])]))
    return "".join(parts) or None


def _section_tables(run: RunFolder) -> str | None:
    parts = []
    for table in run.fusion_tables:
        parts.append(f"<h3>{_esc(table.name)}</h3>")
        parts.append(_table(table.header, table.rows))
    if "task7.png" in run.figures:
        parts.append(_figure(run.figures["task7.png"].read_bytes(), "Task 7 (from the run)."))
    return "".join(parts) or None


def _section_files(run: RunFolder) -> str | None:
    if set(run.data_files) <= {"summary.json"} and not run.frame_paths:
        return None
    items = [f'<li><a href="{_esc(name)}">{_esc(name)}</a></li>' for name in run.data_files]
    if run.frame_paths:
        items.append(f'<li><a href="frames/">frames/</a> ({len(run.frame_paths)} PNG images)</li>')
    return (
        '<p class="note">The data behind this report, next to it in the run folder '
        "(links work while the report sits in its run folder).</p><ul>" + "".join(items) + "</ul>"
    )


# --- assembly -------------------------------------------------------------------------


def render_report(run: RunFolder, *, progress: bool = False) -> str:
    """The report of a loaded run folder as one HTML string.

    Parameters
    ----------
    run : RunFolder
        What :func:`kalmansfm.report.run_folder.load_run` read.
    progress : bool
        Show a progress bar (stderr) while frames are drawn.
    """
    frames = _read_frames(run) if run.frame_paths else []
    candidates = [
        ("parameters", "Parameters", lambda: _section_parameters(run)),
        ("sequence", "Sequence with tracks and gates", lambda: _section_sequence(run, frames, progress)),
        ("uncertainty", "Uncertainty over time", lambda: _section_uncertainty(run)),
        ("tracks", "Tracking statistics", lambda: _section_tracks(run)),
        ("factorization", "Factorization", lambda: _section_factorization(run)),
        ("shape", "Recovered 3D shape", lambda: _section_shape(run)),
        ("motion", "Recovered camera motion", lambda: _section_motion(run)),
        ("ground-truth", "Comparison with ground truth", lambda: _section_ground_truth(run)),
        ("tables", "Tables", lambda: _section_tables(run)),
        ("files", "Files", lambda: _section_files(run)),
    ]
    sections = []
    for anchor, title, build in candidates:
        body = build()
        if body:
            sections.append((anchor, title, body))
    nav = "".join(f'<a href="#{anchor}">{_esc(title)}</a>' for anchor, title, _ in sections)
    body_html = "".join(
        f'<section id="{anchor}"><div class="wrap"><h2>{_esc(title)}</h2>{body}</div></section>'
        for anchor, title, body in sections
    )
    title = f"kalmansfm report: {run.summary.get('input', run.path.name)}"
    version = _esc(str(run.summary.get("kalmansfm_version", "?")))
    built = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>{_esc(title)}</title><style>{CSS}</style><script>{ERROR_TRAP_JS}</script></head><body>"
        f"{_section_header(run)}"
        f'<nav aria-label="sections"><div class="wrap">{nav}</div></nav>'
        f"<main>{body_html}</main>"
        f'<footer><div class="wrap">Written by kalmansfm {version} on {built} from the files of '
        f"<code>{_esc(str(run.path))}</code>. Rebuild with <code>kalmansfm report DIR</code>."
        '<p id="js-status" data-ready="no" hidden></p></div></footer>'
        f"<script>{JS}</script></body></html>\n"
    )


def build_report(
    run_dir: str | Path, *, out_name: str = "report.html", progress: bool = False
) -> Path:
    """Write the self-contained HTML report of a finished run folder.

    Parameters
    ----------
    run_dir : path
        A run folder: ``summary.json`` plus any of the optional files (frames,
        tracks, structure, motion, ground truth, tables); see
        :func:`kalmansfm.report.run_folder.load_run`.
    out_name : str
        File name of the report inside ``run_dir``.
    progress : bool
        Show a progress bar on stderr while frames are drawn.

    Returns
    -------
    Path
        The report, ``run_dir / out_name``, written atomically.

    Raises
    ------
    InvalidInputError
        If ``summary.json`` is missing or broken, or an optional file exists
        but cannot be read; the message names the file.

    Examples
    --------
    >>> import json, tempfile, pathlib
    >>> run = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (run / "summary.json").write_text(json.dumps({"input": "demo", "parameters": {"window_px": 7}}))
    >>> path = build_report(run)
    >>> path.name, "window_px" in path.read_text()
    ('report.html', True)
    """
    name = Path(out_name)
    if name.name != out_name or not out_name or out_name in (".", ".."):
        raise InvalidInputError(f"out_name must be a plain file name; got {out_name!r}")
    run = load_run(run_dir)
    document = render_report(run, progress=progress)
    with output_directory(run.path) as out:
        out.write_text(out_name, document)
    report = run.path / out_name
    log.info("report: %s (%.1f MB)", report, report.stat().st_size / 1e6)
    return report
