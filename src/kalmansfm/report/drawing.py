"""Tracks drawn on frames with OpenCV: the report's player and strip, ``tracks.png`` and ``tracks.gif``.

One drawing for every picture of tracks: each track has one colour (:func:`track_colors`,
by its id, the same in every picture, table and plot), measured points are filled discs,
coasting ones rings, lost ones crosses, initialising ones (a track's first two frames) filled squares, and the ellipse around each
measured or coasting point is the tracker's gate, (p - p̂)ᵀ Σ_pos⁻¹ (p - p̂) = c² with the
gate radius c the tracker actually used.  An initialising point has no gate drawn: its
covariance is the start-up prior Σ0, the same for every new track.  Functions return images or PNG/GIF
bytes; nothing here writes files.
"""

from __future__ import annotations

import io
from collections.abc import Iterable, Sequence
from typing import Any

import cv2
import numpy as np

from ..io.frames import encode_png
from ..tracking.settings import TrackerSettings
from ..tracking.tracks import INITIALISING, LOST, MEASURED, PREDICTED, Tracks, TrackStatus

__all__ = [
    "TRACK_PALETTE",
    "gate_ellipses",
    "gate_radius_of",
    "render_tracked_frames",
    "track_colors",
    "tracks_gif",
    "tracks_overview_png",
]

# Drawing works in 1/16 px so that sub-pixel positions are drawn where they are.
_SHIFT = 4
_ONE = 1 << _SHIFT
# Past frames of each path drawn on a frame of the player and the GIF (the overview draws all).
TRAIL_FRAMES = 100


# Matplotlib's tab10 followed by tab20b, as hex: the colours of the tracks everywhere.
TRACK_PALETTE = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf",
    "#393b79", "#5254a3", "#6b6ecf", "#9c9ede", "#637939", "#8ca252", "#b5cf6b", "#cedb9c", "#8c6d31", "#bd9e39",
    "#e7ba52", "#e7cb94", "#843c39", "#ad494a", "#d6616b", "#e7969c", "#7b4173", "#a55194", "#ce6dbd", "#de9ed6",
)


def track_colors(track_ids: Sequence[int] | np.ndarray) -> list[str]:
    """The colour of each track, as ``#rrggbb``: ``TRACK_PALETTE[track_id % 30]``.

    A track's colour depends on its id alone, so it is the same in the drawings of the
    frames, the tables and the plots of the shape, whatever subset or order they show.

    Examples
    --------
    >>> track_colors([0, 1, 31])
    ['#1f77b4', '#ff7f0e', '#ff7f0e']
    """
    return [TRACK_PALETTE[k] for k in _palette_index(track_ids).tolist()]


def _palette_index(track_ids: Any) -> np.ndarray:
    return np.asarray(track_ids, dtype=np.int64).reshape(-1) % len(TRACK_PALETTE)


def _bgr(hex_color: str) -> tuple[int, int, int]:
    r, g, b = (int(hex_color[k : k + 2], 16) for k in (1, 3, 5))
    return (b, g, r)


def gate_radius_of(tracks: Tracks) -> float:
    """The gate radius c the tracks were made with (the default settings' when they carry none)."""
    settings = tracks.settings if tracks.settings is not None else TrackerSettings()
    return settings.effective_gate_radius


def gate_ellipses(covariances: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes and orientation of the ellipse (p - c)ᵀ C⁻¹ (p - c) = radius² of each position covariance.

    Parameters
    ----------
    covariances : (..., 4, 4) or (..., 2, 2) float
        State covariances; the upper-left 2×2 block is the position covariance.
    radius : float
        Mahalanobis radius (the tracker's gate radius c; 2.448 holds 95 % of a 2D Gaussian).

    Returns
    -------
    semi_axes : (..., 2) float, major then minor semi-axis in pixels
    angle_deg : (...) float, direction of the major axis from the +x (column) axis towards +y (row)

    Examples
    --------
    >>> axes, angle = gate_ellipses(np.diag([4.0, 1.0, 1.0, 1.0]), 2.0)
    >>> np.round(axes, 3), float(angle)
    (array([4., 2.]), 0.0)
    """
    block = np.asarray(covariances, dtype=float)[..., :2, :2]
    block = 0.5 * (block + np.swapaxes(block, -1, -2))
    eigenvalues, eigenvectors = np.linalg.eigh(block)
    # semi-axes radius * sqrt(lambda) along the eigenvectors
    semi_axes = radius * np.sqrt(np.clip(eigenvalues[..., ::-1], 0.0, None))
    major = eigenvectors[..., :, 1]
    angle_deg = np.degrees(np.arctan2(major[..., 1], major[..., 0])) % 180.0
    return semi_axes, angle_deg


def _display_scale(width: int, target_width: int) -> float:
    """Integer enlargement for small frames, shrinking for big ones, 1 when close to the target."""
    if width <= 0:
        return 1.0
    if width < target_width / 1.5:
        return float(round(target_width / width))
    if width <= 1.3 * target_width:
        return 1.0
    return target_width / width


def _blank_canvas(tracks: Tracks) -> np.ndarray:
    finite = tracks.positions[np.isfinite(tracks.positions).all(axis=-1)]
    extent = np.ceil(finite.max(axis=0)) + 10 if finite.size else np.array([320.0, 240.0])
    width, height = (int(max(16, v)) for v in extent)
    return np.full((height, width), 96, dtype=np.uint8)


def render_tracked_frames(
    frames: Sequence[np.ndarray] | None,
    tracks: Tracks,
    indices: Sequence[int],
    *,
    target_width: int = 560,
    trail: int | None = TRAIL_FRAMES,
) -> list[np.ndarray]:
    """Draw tracks, current points and gate ellipses onto the frames ``indices``.

    Parameters
    ----------
    frames : sequence of (H, W) or (H, W, 3) uint8 images, or None
        The sequence; when None the tracks are drawn on a plain grey canvas.
    tracks : Tracks
        Positions, status codes and (optionally) covariances of every track; the gate
        drawn has the radius of ``tracks.settings`` (:func:`gate_radius_of`).
    indices : sequence of int
        Frames to draw.
    target_width : int
        Approximate display width in pixels; small frames are enlarged by an
        integer factor (nearest neighbour, pixels stay visible), big ones shrunk.
    trail : int or None
        How many past frames of each path to draw (None: the whole path). A bounded trail keeps
        the drawing time of a frame constant along a long clip and the picture readable.

    Returns
    -------
    list of (h, w, 3) uint8 BGR images
        Measured points are filled discs, predicted ones rings, lost ones crosses,
        initialising ones filled squares (no gate); each track has its own colour
        (see :func:`track_colors`).
    """
    n_tracks = tracks.positions.shape[1]
    # tracks sharing a colour are drawn together: one OpenCV call per colour and kind of mark
    index = _palette_index(tracks.track_ids)
    groups = [(_bgr(TRACK_PALETTE[c]), np.flatnonzero(index == c)) for c in np.unique(index).tolist()]
    positions = tracks.positions
    blank = _blank_canvas(tracks) if not frames else None
    label_tracks = n_tracks <= 40
    radius = gate_radius_of(tracks)
    rendered = []
    for f in indices:
        image = frames[min(f, len(frames) - 1)] if frames else blank
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        scale = _display_scale(image.shape[1], target_width)
        interpolation = cv2.INTER_NEAREST if scale >= 1 else cv2.INTER_AREA
        canvas = cv2.resize(image, None, fx=scale, fy=scale, interpolation=interpolation)
        # pixel (x, y) has its centre at ((x + 0.5) * scale - 0.5) on the resized canvas
        first = 0 if trail is None else max(0, f - trail)
        # a shrunken picture draws the path through every (1 / scale)-th frame back from this one: the segments
        # between the others would be under a pixel long (a long clip's GIF: half the drawing time)
        stride = max(1, int(1.0 / scale))
        shown = ((positions[f - (f - first) // stride * stride: f + 1: stride] + 0.5) * scale - 0.5) * _ONE
        marker = max(3.0, round(3 * scale**0.5)) * _ONE
        thickness = max(1, int(round(scale / 3)))
        status = tracks.status[f]
        current = shown[-1]
        visible = np.isfinite(current).all(axis=1)
        gates = None
        if tracks.covariances is not None:
            semi_axes, angles = gate_ellipses(tracks.covariances[f], radius)
            gates = _ellipse_polygons(current, semi_axes * scale * _ONE, angles)
        for color, members in groups:
            # the path so far: one 2-point line per pair of consecutive known positions (gaps stay open, but a
            # shrunken picture's stride bridges one shorter than itself)
            path = shown[:, members]
            pairs = np.stack([path[:-1], path[1:]], axis=2)  # (f, n, 2 ends, 2)
            pairs = pairs[np.isfinite(pairs).all(axis=(2, 3))]
            if len(pairs):
                cv2.polylines(canvas, list(pairs.astype(np.int32)), False, color, 1, cv2.LINE_AA, _SHIFT)
            here = members[visible[members]]
            active = here[np.isin(status[here], (MEASURED, PREDICTED))]
            if gates is not None and len(active):
                polygons = gates[active]
                polygons = polygons[np.isfinite(polygons).all(axis=(1, 2))]
                cv2.polylines(canvas, list(polygons.astype(np.int32)), True, color, 1, cv2.LINE_AA, _SHIFT)
            measured = here[status[here] == MEASURED]
            if len(measured):
                discs = list(_circle_polygons(current[measured], marker).astype(np.int32))
                cv2.fillPoly(canvas, discs, color, cv2.LINE_AA, _SHIFT)
                cv2.polylines(canvas, discs, True, (20, 20, 20), 1, cv2.LINE_AA, _SHIFT)
            starting = here[status[here] == INITIALISING]
            if len(starting):
                squares = list((current[starting][:, None, :] + _UNIT_SQUARE * 0.8 * marker).astype(np.int32))
                cv2.fillPoly(canvas, squares, color, cv2.LINE_AA, _SHIFT)
                cv2.polylines(canvas, squares, True, (20, 20, 20), 1, cv2.LINE_AA, _SHIFT)
            predicted = here[status[here] == PREDICTED]
            if len(predicted):
                rings = list(_circle_polygons(current[predicted], marker).astype(np.int32))
                cv2.polylines(canvas, rings, True, color, thickness + 1, cv2.LINE_AA, _SHIFT)
            lost = here[status[here] == LOST]
            if len(lost):
                arms = np.array([[[-1, -1], [1, 1]], [[-1, 1], [1, -1]]]) * marker
                crosses = (current[lost][:, None, None, :] + arms).reshape(-1, 2, 2)
                cv2.polylines(canvas, list(crosses.astype(np.int32)), False, color, thickness + 1, cv2.LINE_AA, _SHIFT)
            if label_tracks:
                for p in here:
                    at = (int(current[p, 0] + marker) // _ONE + 2, int(current[p, 1] - marker) // _ONE)
                    label = str(int(tracks.track_ids[p]))
                    cv2.putText(canvas, label, at, cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1, cv2.LINE_AA)
        caption = _caption(f, status)
        cv2.rectangle(canvas, (0, 0), (min(canvas.shape[1], 8 + 7 * len(caption)), 18), (0, 0, 0), -1)
        cv2.putText(canvas, caption, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        rendered.append(canvas)
    return rendered


_ANGLES = np.linspace(0, 2 * np.pi, 40, endpoint=False)
_UNIT_CIRCLE = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=1)  # (40, 2)
_UNIT_SQUARE = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])


def _caption(frame: int, status: np.ndarray) -> str:
    """``frame 3  measured 7  predicted 1  lost 0`` (and ``initialising N`` while tracks start)."""
    counts = np.bincount(status.clip(0, len(TrackStatus) - 1), minlength=len(TrackStatus))
    caption = f"frame {frame}  measured {counts[MEASURED]}  predicted {counts[PREDICTED]}  lost {counts[LOST]}"
    if counts[INITIALISING]:
        caption += f"  initialising {counts[INITIALISING]}"
    return caption


def _circle_polygons(centres: np.ndarray, radius: float) -> np.ndarray:
    """(n, 40, 2) polygons approximating circles of ``radius`` around ``centres`` (n, 2)."""
    return centres[:, None, :] + radius * _UNIT_CIRCLE


def _ellipse_polygons(centres: np.ndarray, semi_axes: np.ndarray, angle_deg: np.ndarray) -> np.ndarray:
    """(n, 40, 2) ellipse outlines: semi-axes (n, 2) major, minor; major axis at ``angle_deg`` (n,)."""
    theta = np.radians(angle_deg)
    major = np.stack([np.cos(theta), np.sin(theta)], axis=-1)  # (n, 2)
    minor = np.stack([-np.sin(theta), np.cos(theta)], axis=-1)
    # p(t) = c + a cos(t) u + b sin(t) v
    return (
        centres[:, None, :]
        + semi_axes[:, None, 0:1] * _UNIT_CIRCLE[None, :, 0:1] * major[:, None, :]
        + semi_axes[:, None, 1:2] * _UNIT_CIRCLE[None, :, 1:2] * minor[:, None, :]
    )


def tracks_overview_png(tracks: Tracks, last_frame: np.ndarray) -> bytes:
    """``tracks.png``: the last frame with every track's path, its current mark and gate."""
    (image,) = render_tracked_frames([last_frame], tracks, [tracks.n_frames - 1], target_width=900, trail=None)
    return encode_png(image)


def tracks_gif(
    frames: Iterable[np.ndarray], tracks: Tracks, *, max_width: int = 320, max_frames: int = 40, fps: float = 10.0
) -> bytes:
    """``tracks.gif``: the whole clip with the tracks drawn, at most ``max_frames`` evenly spaced frames shrunk to
    ``max_width`` — a size and a writing time that do not grow with the clip's length."""
    from PIL import Image

    shown = set(np.unique(np.linspace(0, tracks.n_frames - 1, min(max_frames, tracks.n_frames)).round().astype(int))
                .tolist()) if tracks.n_frames else set()
    images = []
    for f, frame in enumerate(frames):
        if f >= tracks.n_frames:
            break
        if f not in shown:
            continue
        (drawn,) = render_tracked_frames([frame], tracks, [f], target_width=max_width)
        # a fast octree palette per frame: a tenth of the median cut's time, the tracks' colours kept
        images.append(Image.fromarray(cv2.cvtColor(drawn, cv2.COLOR_BGR2RGB)).quantize(
            colors=255, method=Image.Quantize.FASTOCTREE))
    buffer = io.BytesIO()
    if images:
        images[0].save(buffer, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps),
                       loop=0)
    return buffer.getvalue()
