"""Figures of the HTML report: tracked frames drawn with OpenCV, plots with Matplotlib.

Every function returns image arrays (BGR, uint8) or PNG bytes; nothing here
writes files.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Sequence

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy.stats import chi2  # noqa: E402

from ..structure.cameras import camera_rotation_matrices as _rotations_from_rows  # noqa: E402
from .run_folder import STATUS_LOST, STATUS_MEASURED, STATUS_PREDICTED, CameraMotion, TrackArrays  # noqa: E402

__all__ = [
    "track_colors",
    "gate_ellipses",
    "render_tracked_frames",
    "png_bytes",
    "covariance_trace_figure",
    "status_timeline_figure",
    "singular_values_figure",
    "shape_views_figure",
    "camera_rotation_matrices",
    "camera_rotations",
    "camera_rotation_figure",
    "track_error_per_frame",
    "track_error_figure",
    "rotation_error_figure",
]

# Drawing works in 1/16 px so that sub-pixel positions are drawn where they are.
_SHIFT = 4
_ONE = 1 << _SHIFT


_PALETTE = [matplotlib.colors.to_hex(c) for c in plt.get_cmap("tab10").colors] + [
    matplotlib.colors.to_hex(c) for c in plt.get_cmap("tab20b").colors
]


def track_colors(count: int) -> list[str]:
    """``count`` distinct colours as ``#rrggbb`` (Matplotlib's tab10, then tab20b, cycled).

    Examples
    --------
    >>> track_colors(2)
    ['#1f77b4', '#ff7f0e']
    """
    return [_PALETTE[k % len(_PALETTE)] for k in range(count)]


def _bgr(hex_color: str) -> tuple[int, int, int]:
    r, g, b = (int(hex_color[k : k + 2], 16) for k in (1, 3, 5))
    return (b, g, r)


def gate_ellipses(covariances: np.ndarray, probability: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Semi-axes and orientation of the ``probability`` ellipse of each position covariance.

    Parameters
    ----------
    covariances : (..., 4, 4) or (..., 2, 2) float
        State covariances; the upper-left 2×2 block is the position covariance.
    probability : float
        Probability mass inside the ellipse (0.95 → squared Mahalanobis radius 5.991).

    Returns
    -------
    semi_axes : (..., 2) float, major then minor semi-axis in pixels
    angle_deg : (...) float, direction of the major axis from the +x (column) axis towards +y (row)

    Examples
    --------
    >>> axes, angle = gate_ellipses(np.diag([4.0, 1.0, 1.0, 1.0]))
    >>> np.round(axes, 3), float(angle)
    (array([4.895, 2.448]), 0.0)
    """
    block = np.asarray(covariances, dtype=float)[..., :2, :2]
    block = 0.5 * (block + np.swapaxes(block, -1, -2))
    eigenvalues, eigenvectors = np.linalg.eigh(block)
    # Ellipse {p : (p - c)^T C^-1 (p - c) <= chi2_2(probability)}: semi-axes sqrt(chi2 * lambda)
    radius2 = chi2.ppf(probability, df=2)
    semi_axes = np.sqrt(radius2 * np.clip(eigenvalues[..., ::-1], 0.0, None))
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


def _blank_canvas(tracks: TrackArrays) -> np.ndarray:
    finite = tracks.positions[np.isfinite(tracks.positions).all(axis=-1)]
    extent = np.ceil(finite.max(axis=0)) + 10 if finite.size else np.array([320.0, 240.0])
    width, height = (int(max(16, v)) for v in extent)
    return np.full((height, width), 96, dtype=np.uint8)


def render_tracked_frames(
    frames: Sequence[np.ndarray] | None,
    tracks: TrackArrays,
    indices: Sequence[int],
    *,
    gate_probability: float = 0.95,
    target_width: int = 560,
) -> list[np.ndarray]:
    """Draw tracks, current points and gate ellipses onto the frames ``indices``.

    Parameters
    ----------
    frames : sequence of (H, W) or (H, W, 3) uint8 images, or None
        The sequence; when None the tracks are drawn on a plain grey canvas.
    tracks : TrackArrays
        Positions, status codes and (optionally) covariances of every track.
    indices : sequence of int
        Frames to draw.
    gate_probability : float
        Probability of the ellipse drawn from the position block of each covariance.
    target_width : int
        Approximate display width in pixels; small frames are enlarged by an
        integer factor (nearest neighbour, pixels stay visible), big ones shrunk.

    Returns
    -------
    list of (h, w, 3) uint8 BGR images
        Measured points are filled discs, predicted ones rings, lost ones crosses;
        each track has its own colour (see :func:`track_colors`).
    """
    n_tracks = tracks.positions.shape[1]
    # tracks sharing a colour are drawn together: one OpenCV call per colour and kind of mark
    palette_size = len(_PALETTE)
    groups = [(_bgr(_PALETTE[c]), np.arange(c, n_tracks, palette_size)) for c in range(min(palette_size, n_tracks))]
    positions = tracks.positions
    blank = _blank_canvas(tracks) if not frames else None
    label_tracks = n_tracks <= 40
    rendered = []
    for f in indices:
        image = frames[min(f, len(frames) - 1)] if frames else blank
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        scale = _display_scale(image.shape[1], target_width)
        interpolation = cv2.INTER_NEAREST if scale >= 1 else cv2.INTER_AREA
        canvas = cv2.resize(image, None, fx=scale, fy=scale, interpolation=interpolation)
        # pixel (x, y) has its centre at ((x + 0.5) * scale - 0.5) on the resized canvas
        shown = ((positions[: f + 1] + 0.5) * scale - 0.5) * _ONE
        marker = max(3.0, round(3 * scale**0.5)) * _ONE
        thickness = max(1, int(round(scale / 3)))
        status = tracks.status[f]
        current = shown[-1]
        visible = np.isfinite(current).all(axis=1)
        gates = None
        if tracks.covariances is not None:
            semi_axes, angles = gate_ellipses(tracks.covariances[f], gate_probability)
            gates = _ellipse_polygons(current, semi_axes * scale * _ONE, angles)
        for color, members in groups:
            # the path so far: one 2-point line per pair of consecutive known positions (gaps stay open)
            path = shown[:, members]
            pairs = np.stack([path[:-1], path[1:]], axis=2)  # (f, n, 2 ends, 2)
            pairs = pairs[np.isfinite(pairs).all(axis=(2, 3))]
            if len(pairs):
                cv2.polylines(canvas, list(pairs.astype(np.int32)), False, color, 1, cv2.LINE_AA, _SHIFT)
            here = members[visible[members]]
            active = here[np.isin(status[here], (STATUS_MEASURED, STATUS_PREDICTED))]
            if gates is not None and len(active):
                polygons = gates[active]
                polygons = polygons[np.isfinite(polygons).all(axis=(1, 2))]
                cv2.polylines(canvas, list(polygons.astype(np.int32)), True, color, 1, cv2.LINE_AA, _SHIFT)
            measured = here[status[here] == STATUS_MEASURED]
            if len(measured):
                discs = list(_circle_polygons(current[measured], marker).astype(np.int32))
                cv2.fillPoly(canvas, discs, color, cv2.LINE_AA, _SHIFT)
                cv2.polylines(canvas, discs, True, (20, 20, 20), 1, cv2.LINE_AA, _SHIFT)
            predicted = here[status[here] == STATUS_PREDICTED]
            if len(predicted):
                rings = list(_circle_polygons(current[predicted], marker).astype(np.int32))
                cv2.polylines(canvas, rings, True, color, thickness + 1, cv2.LINE_AA, _SHIFT)
            lost = here[status[here] == STATUS_LOST]
            if len(lost):
                arms = np.array([[[-1, -1], [1, 1]], [[-1, 1], [1, -1]]]) * marker
                crosses = (current[lost][:, None, None, :] + arms).reshape(-1, 2, 2)
                cv2.polylines(canvas, list(crosses.astype(np.int32)), False, color, thickness + 1, cv2.LINE_AA, _SHIFT)
            if label_tracks:
                for p in here:
                    at = (int(current[p, 0] + marker) // _ONE + 2, int(current[p, 1] - marker) // _ONE)
                    label = str(int(tracks.track_ids[p]))
                    cv2.putText(canvas, label, at, cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1, cv2.LINE_AA)
        counts = np.bincount(status.clip(0, 3), minlength=4)
        caption = f"frame {f}  measured {counts[1]}  predicted {counts[2]}  lost {counts[3]}"
        cv2.rectangle(canvas, (0, 0), (min(canvas.shape[1], 8 + 7 * len(caption)), 18), (0, 0, 0), -1)
        cv2.putText(canvas, caption, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        rendered.append(canvas)
    return rendered


_ANGLES = np.linspace(0, 2 * np.pi, 40, endpoint=False)
_UNIT_CIRCLE = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=1)  # (40, 2)


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


def png_bytes(image: np.ndarray) -> bytes:
    """Encode a uint8 image (grey or BGR) as PNG."""
    ok, encoded = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:  # pragma: no cover - OpenCV fails only on unsupported dtypes
        raise RuntimeError("OpenCV could not encode the image as PNG")
    return encoded.tobytes()


def _figure_png(fig: plt.Figure) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def covariance_trace_figure(tracks: TrackArrays) -> bytes | None:
    """Mean trace of the state covariance over the tracks with an estimate, per frame."""
    if tracks.covariances is None:
        return None
    active = np.isin(tracks.status, (STATUS_MEASURED, STATUS_PREDICTED))
    traces = np.where(active, np.trace(tracks.covariances, axis1=-2, axis2=-1), np.nan)
    if not np.isfinite(traces).any():
        return None
    frames = np.arange(traces.shape[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames where no track is active give NaN
        mean, low, high = np.nanmean(traces, 1), np.nanmin(traces, 1), np.nanmax(traces, 1)
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.fill_between(frames, low, high, color="#1f77b4", alpha=0.2, label="min–max over tracks")
    ax.plot(frames, mean, color="#1f77b4", marker=".", label="mean over tracks")
    ax.set_xlabel("frame")
    ax.set_ylabel("trace of state covariance")
    ax.grid(alpha=0.3)
    ax.legend()
    return _figure_png(fig)


def status_timeline_figure(tracks: TrackArrays) -> bytes:
    """Each track's status per frame as a coloured strip (none, measured, predicted, lost)."""
    palette = np.array(["#f0f0f0", "#2ca02c", "#ff9f1c", "#d62728"])
    cmap = matplotlib.colors.ListedColormap(palette)
    n_frames, n_tracks = tracks.status.shape
    fig, ax = plt.subplots(figsize=(7, min(6.0, 1.0 + 0.22 * n_tracks)))
    ax.imshow(tracks.status.T.clip(0, 3), cmap=cmap, vmin=-0.5, vmax=3.5, aspect="auto", interpolation="nearest")
    ax.set_xlabel("frame")
    ax.set_ylabel("track id")
    if n_tracks <= 30:
        ax.set_yticks(range(n_tracks), [str(t) for t in tracks.track_ids])
    handles = [matplotlib.patches.Patch(color=c, label=n) for c, n in zip(palette[1:], ("measured", "predicted", "lost"))]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.25), ncol=3, frameon=False)
    return _figure_png(fig)


def singular_values_figure(singular_values: Sequence[float]) -> bytes:
    """Singular values of the measurement matrix on a log scale; the first three highlighted."""
    values = np.asarray(singular_values, dtype=float)
    index = np.arange(1, len(values) + 1)
    fig, ax = plt.subplots(figsize=(6, 3))
    ax.bar(index, np.where(values > 0, values, np.nan), color=np.where(index <= 3, "#1f77b4", "#bbbbbb"))
    if (values > 0).any():
        ax.set_yscale("log")
    ax.set_xlabel("index k")
    ax.set_ylabel("singular value σk")
    ax.set_xticks(index if len(index) <= 20 else index[:: max(1, len(index) // 10)])
    ax.grid(alpha=0.3, axis="y")
    ax.set_title("rank 3 expected: σ1..σ3 (blue) ≫ the rest", fontsize=10)
    return _figure_png(fig)


def shape_views_figure(
    points: np.ndarray,
    labels: Sequence[int],
    *,
    colors: Sequence[str] | None = None,
    truth: np.ndarray | None = None,
) -> bytes:
    """The 3D points seen from the front (X–Y), the side (Z–Y), the top (X–Z) and obliquely.

    The three orthographic views are exact 2D projections; Y grows downwards as
    the image rows it comes from.  With ``truth`` (same order as ``points``)
    both sets are drawn, the truth as rings.
    """
    pts = np.asarray(points, dtype=float)
    colors = list(colors) if colors is not None else track_colors(len(pts))
    everything = pts if truth is None else np.vstack([pts, truth])
    centre = (everything.max(0) + everything.min(0)) / 2
    half = max(float((everything.max(0) - everything.min(0)).max()) / 2, 1e-9) * 1.12
    fig = plt.figure(figsize=(13, 3.4))
    views = (("front (X–Y)", 0, 1), ("side (Z–Y)", 2, 1), ("top (X–Z)", 0, 2))
    names = "XYZ"
    annotate = len(pts) <= 40
    for k, (title, a, b) in enumerate(views):
        ax = fig.add_subplot(1, 4, k + 1)
        ax.scatter(pts[:, a], pts[:, b], c=colors, s=22, edgecolors="k", linewidths=0.4, zorder=3, label="recovered")
        if truth is not None:
            ax.scatter(truth[:, a], truth[:, b], facecolors="none", edgecolors="k", s=60, zorder=2, label="ground truth")
        if annotate:
            for p, label in zip(pts, labels):
                ax.annotate(str(label), (p[a], p[b]), textcoords="offset points", xytext=(4, 3), fontsize=7)
        ax.set_xlim(centre[a] - half, centre[a] + half)
        low, high = centre[b] - half, centre[b] + half
        ax.set_ylim((high, low) if b == 1 else (low, high))
        ax.set_aspect("equal")
        ax.set_xlabel(names[a])
        ax.set_ylabel(names[b])
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.set_title(title, fontsize=10)
    ax = fig.add_subplot(1, 4, 4, projection="3d")
    ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=colors, s=22, depthshade=False)
    if truth is not None:
        ax.scatter(truth[:, 0], truth[:, 1], truth[:, 2], facecolors="none", edgecolors="k", s=60)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] + half, centre[1] - half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=25.0, azim=-60.0, vertical_axis="y")
    ax.set_xlabel("X")
    ax.set_ylabel("Y")
    ax.set_zlabel("Z")
    ax.tick_params(labelsize=6)
    ax.set_title("oblique", fontsize=10)
    if truth is not None:
        fig.axes[0].legend(loc="best", fontsize=7)
    fig.tight_layout()
    return _figure_png(fig)


def camera_rotation_matrices(motion: CameraMotion) -> np.ndarray:
    """(F, 3, 3) world → camera rotations from the rows of ``motion.csv``."""
    return _rotations_from_rows(np.stack([motion.i_rows, motion.j_rows], axis=1))


def camera_rotations(motion: CameraMotion) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's camera rotation relative to the first frame.

    The rows ``i``, ``j`` of the factorization, with ``k = i × j``, form the
    camera rotation ``R_f`` (world → camera f) up to noise and scale; they are
    snapped to the nearest rotation.  ``R_f R_0^T`` is then decomposed into
    angles about the camera's x (tilt), y (pan) and optical (roll) axes.

    Returns
    -------
    angles_deg : (F, 3) float, tilt, pan, roll (x-y-z extrinsic angles, unwrapped)
    total_deg : (F,) float, the angle of the whole rotation ``R_f R_0^T``
    """
    from scipy.spatial.transform import Rotation

    rotations = camera_rotation_matrices(motion)
    relative = rotations @ rotations[0].T
    angles = np.degrees(np.unwrap(Rotation.from_matrix(relative).as_euler("xyz"), axis=0))
    total = np.degrees(Rotation.from_matrix(relative).magnitude())
    return angles, total


def camera_rotation_figure(motion: CameraMotion) -> bytes:
    """Recovered camera rotation per frame (relative to the first frame) and translation."""
    angles, total = camera_rotations(motion)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.2))
    for k, name in enumerate(("tilt (about image x)", "pan (about image y)", "roll (about optical axis)")):
        left.plot(motion.frames, angles[:, k], marker=".", label=name)
    left.plot(motion.frames, total, color="k", linestyle="--", label="total angle")
    left.set_xlabel("frame")
    left.set_ylabel("degrees from frame %d" % motion.frames[0])
    left.grid(alpha=0.3)
    left.legend(fontsize=8)
    right.plot(motion.frames, motion.translations[:, 0], marker=".", label="t_x")
    right.plot(motion.frames, motion.translations[:, 1], marker=".", label="t_y")
    right.set_xlabel("frame")
    right.set_ylabel("image translation (px)")
    right.grid(alpha=0.3)
    right.legend(fontsize=8)
    return _figure_png(fig)


def track_error_per_frame(positions: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame RMS and per-(frame, track) distance between estimates and ground truth.

    Returns
    -------
    rms : (F,) float, NaN in frames with no comparable track
    distances : (F, P) float, NaN where either is missing
    """
    distances = np.linalg.norm(positions - truth, axis=-1)
    counts = np.isfinite(distances).sum(axis=1)
    sums = np.nansum(distances**2, axis=1)
    rms = np.where(counts > 0, np.sqrt(sums / np.maximum(counts, 1)), np.nan)
    return rms, distances


def track_error_figure(positions: np.ndarray, truth: np.ndarray) -> bytes:
    """Tracking error against ground truth per frame: RMS over tracks and each track faintly."""
    rms, distances = track_error_per_frame(positions, truth)
    frames = np.arange(len(rms))
    fig, ax = plt.subplots(figsize=(7, 3))
    for p, color in enumerate(track_colors(distances.shape[1])):
        ax.plot(frames, distances[:, p], color=color, alpha=0.35, linewidth=0.8)
    ax.plot(frames, rms, color="k", marker=".", linewidth=2, label="RMS over tracks")
    ax.axhline(2.0, color="#d62728", linestyle=":", label="2 px")
    ax.set_xlabel("frame")
    ax.set_ylabel("error (px)")
    ax.grid(alpha=0.3)
    ax.legend()
    return _figure_png(fig)


def rotation_error_figure(errors_deg: Sequence[float]) -> bytes:
    """Camera rotation error per frame against ground truth."""
    values = np.asarray(errors_deg, dtype=float)
    fig, ax = plt.subplots(figsize=(7, 2.8))
    ax.plot(np.arange(len(values)), values, marker=".", color="#9467bd")
    ax.set_xlabel("frame")
    ax.set_ylabel("rotation error (deg)")
    ax.grid(alpha=0.3)
    return _figure_png(fig)
