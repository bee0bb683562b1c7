"""Plots with Matplotlib: uncertainty and status over time, singular values, shape, camera motion, errors.

Every function returns PNG bytes; nothing here writes files.  Tracks keep the colours
of :func:`kalmansfm.report.drawing.track_colors` (by track id).  Axes holding 3D points get
robust limits (:func:`robust_half_width`: a few far points do not shrink the rest to a
blob; the ones outside are counted in the title) and few ticks.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LinearSegmentedColormap  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402

from ..io.structure import CameraMotion  # noqa: E402
from ..structure.geometry.orthographic import camera_rotation_matrices  # noqa: E402
from ..tracking.tracks import INITIALISING, Tracks, TrackStatus  # noqa: E402
from .drawing import track_colors  # noqa: E402

__all__ = [
    "covariance_trace_figure",
    "match_graph_figure",
    "status_timeline_figure",
    "survival_figure",
    "singular_values_figure",
    "shape_views",
    "shape_views_figure",
    "camera_rotations",
    "camera_rotation_figure",
    "track_error_figure",
    "rotation_error_figure",
    "fusion_convergence_figure",
    "uncertainty_colors",
    "camera_path_figure",
    "robust_half_width",
    "STATUS_COLORS",
]

#: The colour of each track status in the status plot (indexed by the status code).
STATUS_COLORS = ("#f0f0f0", "#2ca02c", "#ff9f1c", "#d62728", "#9ecae1")
# Ticks per axis of the shape plots: few enough that labels like -6000 do not run together.
_SHAPE_TICKS = 4
# The track-life panel is an image of at most this many rows (tracks) and columns (frames).
_LIFE_ROWS, _LIFE_COLUMNS = 400, 800
_LIFE_COLOURS = LinearSegmentedColormap.from_list("life", ["#ffffff", "#2ca02c"])
# Points farther from the median than this many times the median distance are left outside the axes.
_STRAY_FACTOR = 4.0


def _figure_png(fig: plt.Figure) -> bytes:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def covariance_trace_figure(tracks: Tracks) -> bytes | None:
    """Mean trace of the state covariance over the tracks the filter estimates, per frame.

    The initialising frames of each track (its start point and start-up match, whose
    covariance is the start-up prior Σ0) are not plotted; the frames before the filter
    runs for any track are shaded and the legend gives trace(Σ0).
    """
    traces = tracks.covariance_trace()
    if traces is None or not np.isfinite(traces).any():
        return None
    frames = np.arange(traces.shape[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # frames where no track is active give NaN
        mean, low, high = np.nanmean(traces, 1), np.nanmin(traces, 1), np.nanmax(traces, 1)
    fig, ax = plt.subplots(figsize=(7, 3))
    first = int(np.flatnonzero(np.isfinite(mean))[0])
    if (tracks.status[:first] == INITIALISING).any():
        prior = "" if tracks.settings is None else f", trace(Σ0) = {np.trace(tracks.settings.model.P0):g}"
        ax.axvspan(-0.5, first - 0.5, color="#9ecae1", alpha=0.35, lw=0,
                   label=f"initialising: start-up prior, not plotted{prior}")
    ax.fill_between(frames, low, high, color="#1f77b4", alpha=0.2, label="min–max over tracks")
    ax.plot(frames, mean, color="#1f77b4", marker=".", label="mean over tracks")
    ax.set_xlim(-0.5, len(frames) - 0.5)
    ax.set_xlabel("frame")
    ax.set_ylabel("trace of state covariance")
    ax.grid(alpha=0.3)
    if tracks.smoothed is not False:
        # a smoothed estimate near the end has fewer later frames to lean on: the trace rises to the filter's
        ax.set_title("smoothed tracks: the last frames have no later measurements, so their uncertainty rises "
                     "to the filter's (the smoother's end effect)", fontsize=8)
    _legend_below(ax, ncol=3)
    return _figure_png(fig)


def _legend_below(ax: Any, ncol: int = 3, **kwargs: Any) -> None:
    """The axes' legend under the plot, where it hides no data."""
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.2), ncol=ncol, frameon=False, fontsize=8, **kwargs)


def status_timeline_figure(tracks: Tracks) -> bytes:
    """Each track's status per frame as a coloured strip (initialising, measured, predicted, lost)."""
    cmap = matplotlib.colors.ListedColormap(STATUS_COLORS)
    top = len(TrackStatus) - 1
    n_frames, n_tracks = tracks.status.shape
    fig, ax = plt.subplots(figsize=(7, min(6.0, 1.0 + 0.22 * n_tracks)))
    ax.imshow(tracks.status.T.clip(0, top), cmap=cmap, vmin=-0.5, vmax=top + 0.5, aspect="auto",
              interpolation="nearest")
    ax.set_xlabel("frame")
    ax.set_ylabel("track id")
    if n_tracks <= 30:
        ax.set_yticks(range(n_tracks), [str(t) for t in tracks.track_ids])
    shown = (TrackStatus.INITIALISING, TrackStatus.MEASURED, TrackStatus.PREDICTED, TrackStatus.LOST)
    handles = [matplotlib.patches.Patch(color=STATUS_COLORS[s], label=s.label) for s in shown]
    ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.25), ncol=4, frameon=False)
    return _figure_png(fig)


def survival_figure(tracks: Tracks) -> bytes | None:
    """Track survival: the share of the first frame's tracks still measured per frame, and each track's life.

    Left: per frame, the fraction of the tracks started in frame 0 that are measured
    there, and that are alive (measured or coasting).  Right: every track as a
    horizontal bar from its first to its last measured frame, sorted by length, so
    that a tracker that keeps its tracks shows long bars.
    """
    if tracks.n_tracks == 0:
        return None
    measured = tracks.status == TrackStatus.MEASURED
    started = tracks.status[0] != TrackStatus.NONE
    frames = np.arange(tracks.n_frames)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.2))
    if started.any():
        left.plot(frames, measured[:, started].mean(axis=1), color="#2ca02c", label="measured")
        left.plot(frames, tracks.alive[:, started].mean(axis=1), color="#ff9f1c", linestyle="--", label="measured or coasting")
    left.set_ylim(0, 1.02)
    left.set_xlabel("frame")
    left.set_ylabel("share of frame 0's tracks")
    left.grid(alpha=0.3)
    _legend_below(left, ncol=2)
    ever = measured.any(axis=0)
    first = np.argmax(measured, axis=0)[ever]
    last = (tracks.n_frames - 1 - np.argmax(measured[::-1], axis=0))[ever]
    order = np.argsort(last - first, kind="stable")
    # the bars as one image (a bar per row, at most _LIFE_ROWS × _LIFE_COLUMNS cells, each the share of it covered):
    # one artist, not a patch per track
    rows = max(1, min(len(order), _LIFE_ROWS))
    columns = max(1, min(tracks.n_frames, _LIFE_COLUMNS))
    edges = np.linspace(0, tracks.n_frames, columns + 1)
    lo, hi = first[order], last[order] + 1
    group = np.arange(len(order)) * rows // max(len(order), 1)
    life = np.zeros((rows, columns))
    for start in range(0, len(order), 4096):  # blocks of tracks bound the temporaries
        b = slice(start, start + 4096)
        covered = np.clip(np.minimum(hi[b, None], edges[1:]) - np.maximum(lo[b, None], edges[:-1]), 0, None)
        np.add.at(life, group[b], covered / np.diff(edges))
    life /= np.maximum(np.bincount(group, minlength=rows), 1)[:, None]
    right.imshow(life, cmap=_LIFE_COLOURS, vmin=0, vmax=1, aspect="auto", interpolation="nearest", origin="lower",
                 extent=(0, tracks.n_frames, -0.5, len(order) - 0.5))
    right.set_xlim(0, tracks.n_frames)
    right.set_xlabel("frame")
    right.set_ylabel("tracks, by measured life")
    right.set_yticks([])
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


def robust_half_width(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and half-width of cubic axes that hold the bulk of ``points`` (N, 3).

    The centre is the median.  Each point's reach is its largest per-axis distance from
    it; the axes hold every point whose reach is at most 4 × the median reach (a Gaussian
    or box-shaped cloud lies well within that), so that a few points far from the rest stay
    outside instead of shrinking the others to a blob.

    Examples
    --------
    >>> pts = np.vstack([np.random.default_rng(0).uniform(-1, 1, (99, 3)), [[0, 0, 5000.0]]])
    >>> centre, half = robust_half_width(pts)
    >>> bool(half < 2.0), bool((np.abs(pts[:99] - centre) <= half).all())
    (True, True)
    """
    pts = np.asarray(points, dtype=float)
    pts = pts[np.isfinite(pts).all(axis=1)]
    if not len(pts):
        return np.zeros(3), 1.0
    centre = np.median(pts, axis=0)
    reach = np.abs(pts - centre).max(axis=1)
    half = float(reach[reach <= _STRAY_FACTOR * np.median(reach)].max())
    return centre, max(half * 1.05, 1e-9)


def _few_ticks(ax: plt.Axes, axes: str = "xy") -> None:
    for name in axes:
        getattr(ax, f"{name}axis").set_major_locator(MaxNLocator(_SHAPE_TICKS, steps=[1, 2, 2.5, 5, 10]))


def shape_views_figure(
    points: np.ndarray,
    labels: Sequence[int],
    *,
    truth: np.ndarray | None = None,
    hidden: int = 0,
) -> bytes:
    """The 3D points seen from the front (X–Y), the side (Z–Y), the top (X–Z) and obliquely.

    The three orthographic views are exact 2D projections; Y grows downwards as
    the image rows it comes from.  ``labels`` are the points' track ids (they give the
    colours).  With ``truth`` (same order as ``points``) both sets are drawn, the truth
    as rings.  The axes hold the bulk of the points (:func:`robust_half_width`); points
    outside them, and ``hidden`` points left out by the caller (unreliable ones), are
    counted in the title.
    """
    return _figure_png(shape_views(points, labels, truth=truth, hidden=hidden))


def shape_views(
    points: np.ndarray, labels: Sequence[int], *, truth: np.ndarray | None = None, hidden: int = 0
) -> plt.Figure:
    """The Matplotlib figure of :func:`shape_views_figure` (the caller closes it)."""
    pts = np.asarray(points, dtype=float)
    colors = track_colors(labels)
    everything = pts if truth is None else np.vstack([pts, truth])
    centre, half = robust_half_width(everything)
    outside = int((np.abs(pts - centre).max(axis=1) > half).sum())
    fig = plt.figure(figsize=(13, 3.6))
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
        _few_ticks(ax)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        ax.set_title(title, fontsize=10)
    ax = fig.add_subplot(1, 4, 4, projection="3d")
    # a 3D axes draws points beyond its limits too: only the ones inside
    inside = np.abs(pts - centre).max(axis=1) <= half
    ax.scatter(pts[inside, 0], pts[inside, 1], pts[inside, 2], c=[c for c, ok in zip(colors, inside) if ok], s=22,
               depthshade=False)
    if truth is not None:
        near = np.abs(truth - centre).max(axis=1) <= half
        ax.scatter(truth[near, 0], truth[near, 1], truth[near, 2], facecolors="none", edgecolors="k", s=60)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] + half, centre[1] - half)
    ax.set_zlim(centre[2] - half, centre[2] + half)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=25.0, azim=-60.0, vertical_axis="y")
    ax.set_xlabel("X")
    ax.set_ylabel("Y")
    ax.set_zlabel("Z")
    _few_ticks(ax, "xyz")
    ax.tick_params(labelsize=6)
    ax.set_title("oblique", fontsize=10)
    if truth is not None:
        fig.axes[0].legend(loc="best", fontsize=7)
    notes = [f"{len(pts)} points"]
    if outside:
        notes.append(f"{outside} outside the axes")
    if hidden:
        notes.append(f"{hidden} unreliable not shown")
    fig.suptitle("; ".join(notes), fontsize=9, y=1.0)
    fig.tight_layout()
    return fig


def camera_rotations(motion: CameraMotion, matrices: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's camera rotation relative to the first frame.

    The rows ``i``, ``j`` of the factorization, with ``k = i × j``, form the
    camera rotation ``R_f`` (world → camera f) up to noise and scale; they are
    snapped to the nearest rotation.  ``R_f R_0^T`` is then decomposed into
    angles about the camera's x (tilt), y (pan) and optical (roll) axes.

    Parameters
    ----------
    motion : CameraMotion
    matrices : (F, 3, 3), optional
        ``camera_rotation_matrices(motion.rows)`` when the caller has it already.

    Returns
    -------
    angles_deg : (F, 3) float, tilt, pan, roll (x-y-z extrinsic angles, unwrapped)
    total_deg : (F,) float, the angle of the whole rotation ``R_f R_0^T``
    """
    from scipy.spatial.transform import Rotation

    rotations = camera_rotation_matrices(motion.rows) if matrices is None else matrices
    relative = rotations @ rotations[0].T
    angles = np.degrees(np.unwrap(Rotation.from_matrix(relative).as_euler("xyz"), axis=0))
    total = np.degrees(Rotation.from_matrix(relative).magnitude())
    return angles, total


def camera_rotation_figure(motion: CameraMotion, rotations: tuple[np.ndarray, np.ndarray] | None = None) -> bytes:
    """Recovered camera rotation per frame (relative to the first frame) and translation.

    ``rotations`` is :func:`camera_rotations` of ``motion`` when the caller has it already.
    """
    angles, total = camera_rotations(motion) if rotations is None else rotations
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.2))
    for k, name in enumerate(("tilt (about image x)", "pan (about image y)", "roll (about optical axis)")):
        left.plot(motion.frames, angles[:, k], marker=".", label=name)
    left.plot(motion.frames, total, color="k", linestyle="--", label="total angle")
    left.set_xlabel("frame")
    left.set_ylabel("degrees from frame %d" % motion.frames[0])
    left.grid(alpha=0.3)
    _legend_below(left, ncol=2)
    right.plot(motion.frames, motion.translations[:, 0], marker=".", label="t_x")
    right.plot(motion.frames, motion.translations[:, 1], marker=".", label="t_y")
    right.set_xlabel("frame")
    right.set_ylabel("image translation (px)")
    right.grid(alpha=0.3)
    _legend_below(right, ncol=2)
    return _figure_png(fig)


def track_error_figure(positions: np.ndarray, truth: np.ndarray, track_ids: Sequence[int],
                       rms_per_frame: np.ndarray) -> bytes:
    """Tracking error against ground truth per frame: each track (``track_ids``) faintly, and the RMS over
    tracks the run's summary measured (``rms_per_frame``, NaN where none) in black."""
    distances = np.linalg.norm(positions - truth, axis=-1)
    rms = np.asarray(rms_per_frame, dtype=float)
    if rms.shape != distances.shape[:1]:  # a summary without per-frame figures: the tracks alone
        rms = np.full(distances.shape[0], np.nan)
    frames = np.arange(len(rms))
    fig, ax = plt.subplots(figsize=(7, 3))
    for p, color in enumerate(track_colors(track_ids)):
        ax.plot(frames, distances[:, p], color=color, alpha=0.35, linewidth=0.8)
    ax.plot(frames, rms, color="k", marker=".", linewidth=2, label="RMS over tracks")
    ax.axhline(2.0, color="#d62728", linestyle=":", label="2 px")
    ax.set_xlabel("frame")
    ax.set_ylabel("error (px)")
    ax.grid(alpha=0.3)
    _legend_below(ax)
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


def fusion_convergence_figure(views_used: np.ndarray, uncertainty: np.ndarray, points: np.ndarray,
                              *, sample: int = 25) -> bytes | None:
    """How each point's uncertainty shrinks as views are fused (the paper's convergence picture).

    ``views_used`` (H,) is the number of observations behind each history entry,
    ``uncertainty`` (H,) its √(tr Σ / 3) and ``points`` (H,) the point it belongs to.
    Draws the median and the quartiles over points per number of views, and the paths of
    up to ``sample`` points (the ones with the most views).
    """
    n, u, p = np.asarray(views_used), np.asarray(uncertainty, dtype=float), np.asarray(points)
    good = np.isfinite(u) & (u > 0)
    if not good.any():
        return None
    n, u, p = n[good], u[good], p[good]
    counts = np.arange(n.min(), n.max() + 1)
    quartiles = np.array([np.quantile(u[n == k], [0.25, 0.5, 0.75]) if (n == k).any() else [np.nan] * 3
                          for k in counts])
    fig, ax = plt.subplots(figsize=(7, 3.5))
    order = np.argsort(-np.bincount(p, minlength=p.max() + 1), kind="stable")[:sample]
    for k, point in enumerate(order):
        mine = p == point
        if mine.sum() > 1:
            ax.plot(n[mine], u[mine], color="#999999", lw=0.6, alpha=0.6, label="single points" if k == 0 else None)
    ax.fill_between(counts, quartiles[:, 0], quartiles[:, 2], color="#1f77b4", alpha=0.25, label="quartiles")
    ax.plot(counts, quartiles[:, 1], color="#1f77b4", marker="o", label="median over points")
    ax.set_yscale("log")
    ax.set_xlabel("views fused")
    ax.set_ylabel("uncertainty √(tr Σ / 3)")
    ax.set_xticks(counts if len(counts) <= 20 else counts[:: max(1, len(counts) // 10)])
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return _figure_png(fig)


def uncertainty_colors(uncertainty: np.ndarray) -> tuple[list[str], float, float]:
    """Hex colours of per-point uncertainties on a log scale (viridis: dark = certain, yellow = uncertain).

    Returns the colours and the (low, high) uncertainties the scale spans (5th and 95th percentiles).
    """
    u = np.asarray(uncertainty, dtype=float)
    finite = np.isfinite(u) & (u > 0)
    if not finite.any():
        return ["#888888"] * len(u), np.nan, np.nan
    low, high = np.percentile(u[finite], [5, 95])
    high = max(high, low * 1.0001)
    t = np.clip((np.log(np.where(finite, u, low)) - np.log(low)) / (np.log(high) - np.log(low)), 0.0, 1.0)
    rgba = plt.get_cmap("viridis")(t)
    return [matplotlib.colors.to_hex(c) for c in rgba], float(low), float(high)


def camera_path_figure(centres: np.ndarray, frames: Sequence[int], points: np.ndarray,
                       uncertainty: np.ndarray) -> bytes:
    """Top (X–Z) and side (Z–Y) views of the camera centres (the path, frames labelled at its ends and every
    tenth) and of the points coloured by their uncertainty √(tr Σ / 3) on a log scale."""
    C, X, u = np.asarray(centres, float), np.asarray(points, float), np.asarray(uncertainty, float)
    colors, low, high = uncertainty_colors(u)
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8))
    for ax, (a, b, title) in zip(axes, ((0, 2, "top (X–Z)"), (2, 1, "side (Z–Y)"))):
        order = np.argsort(-np.nan_to_num(u, nan=0.0))  # most certain drawn last, on top
        ax.scatter(X[order, a], X[order, b], c=[colors[k] for k in order], s=9, linewidths=0, zorder=2)
        ax.plot(C[:, a], C[:, b], color="#9467bd", lw=1.2, zorder=3)
        ax.scatter(C[:, a], C[:, b], color="#9467bd", marker="s", s=18, zorder=4, label="camera centres")
        for k, f in enumerate(frames):
            if k in (0, len(frames) - 1) or f % 10 == 0:
                ax.annotate(str(f), (C[k, a], C[k, b]), textcoords="offset points", xytext=(4, 4), fontsize=7,
                            color="#6a3d9a")
        if b == 1:
            ax.invert_yaxis()
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("XYZ"[a])
        ax.set_ylabel("XYZ"[b])
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="best")
    if np.isfinite(low):
        mappable = matplotlib.cm.ScalarMappable(norm=matplotlib.colors.LogNorm(low, high), cmap="viridis")
        fig.colorbar(mappable, ax=axes, shrink=0.8, label="point uncertainty √(tr Σ / 3)")
    return _figure_png(fig)


def match_graph_figure(inliers: np.ndarray, registered: Sequence[bool]) -> bytes:
    """The match graph of an image set as a matrix: verified matches between images i and j (log colour),
    white where a pair was not matched or failed; the labels of views without a camera in red."""
    n = inliers.shape[0]
    fig, ax = plt.subplots(figsize=(min(9.0, 2.5 + 0.12 * n), min(8.0, 2.0 + 0.12 * n)))
    shown = np.where(inliers > 0, inliers, np.nan)
    image = ax.imshow(np.log10(shown), cmap="viridis", interpolation="nearest")
    fig.colorbar(image, ax=ax, label="log10 verified matches")
    step = max(1, -(-n // 16))
    ticks = np.arange(0, n, step)
    ax.set_xticks(ticks, [str(t) for t in ticks], fontsize=7)
    ax.set_yticks(ticks, [str(t) for t in ticks], fontsize=7)
    for label, t in zip(ax.get_yticklabels(), ticks):
        if not registered[t]:
            label.set_color("#d62728")
    ax.set_xlabel("image j")
    ax.set_ylabel("image i")
    return _figure_png(fig)
