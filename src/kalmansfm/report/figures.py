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
    "camera_rotations",
    "camera_rotation_figure",
    "track_error_per_frame",
    "track_error_figure",
    "rotation_error_figure",
    "align_similarity",
]

# Drawing works in 1/16 px so that sub-pixel positions are drawn where they are.
_SHIFT = 4
_ONE = 1 << _SHIFT


def track_colors(count: int) -> list[str]:
    """``count`` distinct colours as ``#rrggbb`` (Matplotlib's tab10, then tab20b, cycled).

    Examples
    --------
    >>> track_colors(2)
    ['#1f77b4', '#ff7f0e']
    """
    palette = [matplotlib.colors.to_hex(c) for c in plt.get_cmap("tab10").colors]
    palette += [matplotlib.colors.to_hex(c) for c in plt.get_cmap("tab20b").colors]
    return [palette[k % len(palette)] for k in range(count)]


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
    """Integer up-scaling for small frames, plain down-scaling for large ones."""
    if width <= 0:
        return 1.0
    if width < target_width:
        return float(max(1, target_width // width))
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
    colors = [_bgr(c) for c in track_colors(tracks.positions.shape[1])]
    positions = tracks.positions
    semi_axes = angles = None
    if tracks.covariances is not None:
        semi_axes, angles = gate_ellipses(tracks.covariances, gate_probability)
    blank = _blank_canvas(tracks) if not frames else None
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
        marker = max(3, int(round(3 * scale**0.5)))
        thickness = max(1, int(round(scale / 3)))
        for p, color in enumerate(colors):
            status = tracks.status[f, p]
            path = shown[:, p]
            finite = np.isfinite(path).all(axis=1)
            # split the path where it has gaps so a missing frame is not bridged
            for segment in np.split(path, np.flatnonzero(~finite)):
                segment = segment[np.isfinite(segment).all(axis=1)]
                if len(segment) >= 2:
                    cv2.polylines(canvas, [segment.astype(np.int32)], False, color, 1, cv2.LINE_AA, _SHIFT)
            if not finite[-1]:
                continue
            centre = tuple(int(v) for v in path[-1])
            if semi_axes is not None and status in (STATUS_MEASURED, STATUS_PREDICTED):
                axes = tuple(int(v) for v in np.nan_to_num(semi_axes[f, p] * scale * _ONE))
                cv2.ellipse(canvas, centre, axes, float(angles[f, p]), 0, 360, color, 1, cv2.LINE_AA, _SHIFT)
            if status == STATUS_MEASURED:
                cv2.circle(canvas, centre, marker * _ONE, color, -1, cv2.LINE_AA, _SHIFT)
                cv2.circle(canvas, centre, marker * _ONE, (20, 20, 20), 1, cv2.LINE_AA, _SHIFT)
            elif status == STATUS_PREDICTED:
                cv2.circle(canvas, centre, marker * _ONE, color, thickness + 1, cv2.LINE_AA, _SHIFT)
            elif status == STATUS_LOST:
                c = np.array(centre)
                d = marker * _ONE
                for a, b in (((-d, -d), (d, d)), ((-d, d), (d, -d))):
                    cv2.line(canvas, tuple(c + a), tuple(c + b), color, thickness + 1, cv2.LINE_AA, _SHIFT)
            label_at = (centre[0] // _ONE + marker + 2, centre[1] // _ONE - marker)
            cv2.putText(
                canvas, str(int(tracks.track_ids[p])), label_at, cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1, cv2.LINE_AA
            )
        counts = np.bincount(tracks.status[f].clip(0, 3), minlength=4)
        caption = f"frame {f}  measured {counts[1]}  predicted {counts[2]}  lost {counts[3]}"
        cv2.rectangle(canvas, (0, 0), (min(canvas.shape[1], 8 + 7 * len(caption)), 18), (0, 0, 0), -1)
        cv2.putText(canvas, caption, (4, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        rendered.append(canvas)
    return rendered


def png_bytes(image: np.ndarray) -> bytes:
    """Encode a uint8 image (grey or BGR) as PNG."""
    ok, encoded = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
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


def align_similarity(
    source: np.ndarray, target: np.ndarray, *, allow_reflection: bool = False
) -> tuple[np.ndarray, float]:
    """Similarity transform (scale, rotation, translation) of ``source`` that best fits ``target``.

    Least squares (Umeyama): centre both sets, take the SVD of the cross
    covariance, then the scale that matches the spreads.

    Returns
    -------
    aligned : (P, 3) float, the transformed source points
    rms : float, root mean square distance to ``target`` in target units

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> x = rng.normal(size=(6, 3))
    >>> aligned, rms = align_similarity(2.0 * x + 1.0, x)
    >>> bool(rms < 1e-12)
    True
    """
    src = np.asarray(source, dtype=float)
    dst = np.asarray(target, dtype=float)
    src_mean, dst_mean = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - src_mean, dst - dst_mean
    u, s, vt = np.linalg.svd(b.T @ a)
    signs = np.ones(3)
    if not allow_reflection and np.linalg.det(u @ vt) < 0:
        signs[-1] = -1.0
    rotation = u @ np.diag(signs) @ vt
    # scale = trace(D S) / |a|^2 minimises |b - scale R a|^2
    scale = float((s * signs).sum() / max((a**2).sum(), np.finfo(float).tiny))
    aligned = scale * a @ rotation.T + dst_mean
    rms = float(np.sqrt(((aligned - dst) ** 2).sum(axis=1).mean()))
    return aligned, rms


def shape_views_figure(
    points: np.ndarray,
    labels: Sequence[int],
    *,
    truth: np.ndarray | None = None,
) -> bytes:
    """The 3D points seen from the front (X–Y), the side (Z–Y), the top (X–Z) and obliquely.

    The three orthographic views are exact 2D projections; Y grows downwards as
    the image rows it comes from.  With ``truth`` (same order as ``points``)
    both sets are drawn, the truth as rings.
    """
    pts = np.asarray(points, dtype=float)
    colors = track_colors(len(pts))
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


def _nearest_rotation(matrices: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(matrices)
    det = np.linalg.det(u @ vt)
    u[..., :, -1] *= det[..., None]
    return u @ vt


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

    i_rows = motion.i_rows / np.linalg.norm(motion.i_rows, axis=1, keepdims=True)
    j_rows = motion.j_rows / np.linalg.norm(motion.j_rows, axis=1, keepdims=True)
    rotations = _nearest_rotation(np.stack([i_rows, j_rows, np.cross(i_rows, j_rows)], axis=1))
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


def track_error_figure(positions: np.ndarray, truth: np.ndarray, track_ids: Sequence[int]) -> bytes:
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
