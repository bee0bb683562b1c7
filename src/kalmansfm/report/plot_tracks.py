"""Pictures of tracks: the mean covariance trace per frame, paths over the last frame, an animated GIF."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..tracking.tracks import LOST, MEASURED, PREDICTED, Tracks  # noqa: E402

__all__ = ["plot_covariance_trace", "plot_tracks", "write_tracks_gif"]


def plot_covariance_trace(tracks: Tracks, path: str | os.PathLike[str]) -> Path:
    """Save the mean trace of the posterior covariance per frame (the report's Figure 1).

    Examples
    --------
    >>> import tempfile
    >>> t = Tracks.empty(3, 1); t.status[:] = 1; t.covariances[:, 0] = np.eye(4)
    >>> plot_covariance_trace(t, Path(tempfile.mkdtemp()) / "c.png").stat().st_size > 0
    True
    """
    path = Path(path)
    trace = tracks.mean_covariance_trace()
    fig, ax = plt.subplots(figsize=(5.5, 3.5), dpi=100)
    ax.plot(np.arange(len(trace)), trace, marker="o", markersize=3)
    ax.set_xlabel("frame")
    ax.set_ylabel("mean trace of posterior covariance (px²)")
    ax.set_title("Posterior covariance trace, averaged over live tracks")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, format="png")
    plt.close(fig)
    return path


def _colours(n: int) -> np.ndarray:
    return plt.get_cmap("hsv")(np.linspace(0, 1, max(n, 1), endpoint=False))[:, :3]


def plot_tracks(tracks: Tracks, last_frame: np.ndarray, path: str | os.PathLike[str], tail: int | None = None) -> Path:
    """Save the last frame with each track's path drawn (dots where it ends, × where it coasts).

    Parameters
    ----------
    tracks : the tracks.
    last_frame : (H, W) grey image of the last frame.
    path : output PNG.
    tail : draw only the last ``tail`` frames of each path (default all).
    """
    path = Path(path)
    height, width = last_frame.shape[:2]
    scale = min(1.0, 900.0 / width)
    fig, ax = plt.subplots(figsize=(width * scale / 100 + 0.2, height * scale / 100 + 0.2), dpi=100)
    ax.imshow(last_frame, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
    start = 0 if tail is None else max(0, tracks.n_frames - tail)
    positions = tracks.positions[start:]
    colours = _colours(tracks.n_tracks)
    for p in range(tracks.n_tracks):
        xy = positions[:, p]
        if np.isnan(xy).all():
            continue
        ax.plot(xy[:, 0], xy[:, 1], "-", color=colours[p], linewidth=1.0)
    last = tracks.status[-1]
    end = tracks.positions[-1]
    ax.scatter(end[last == MEASURED, 0], end[last == MEASURED, 1], s=10, c=colours[last == MEASURED], zorder=3)
    ax.scatter(end[last == PREDICTED, 0], end[last == PREDICTED, 1], s=25, marker="x", c="red", zorder=3)
    ax.set_xlim(-0.5, width - 0.5)
    ax.set_ylim(height - 0.5, -0.5)
    ax.set_axis_off()
    alive = int(tracks.alive[-1].sum())
    ax.set_title(f"{alive} of {tracks.n_tracks} tracks alive in the last frame", fontsize=9)
    fig.tight_layout(pad=0.1)
    fig.savefig(path, format="png")
    plt.close(fig)
    return path


def write_tracks_gif(
    frames: Iterable[np.ndarray],
    tracks: Tracks,
    path: str | os.PathLike[str],
    gate_radius: float = 2.4477,
    max_width: int = 320,
    max_frames: int = 150,
    fps: float = 10.0,
) -> Path:
    """Animated GIF of the frames with each track's position and its uncertainty ellipse.

    The ellipse is (p - p̂)ᵀ Σ_pos⁻¹ (p - p̂) = c² of the posterior position covariance
    (green measured, orange coasting).  Frames are shrunk to ``max_width`` and only
    the first ``max_frames`` are kept, so the file stays small.
    """
    from PIL import Image

    path = Path(path)
    images = []
    for f, frame in enumerate(frames):
        if f >= min(max_frames, tracks.n_frames):
            break
        height, width = frame.shape[:2]
        scale = min(1.0, max_width / width)
        small = cv2.resize(frame, (round(width * scale), round(height * scale)), interpolation=cv2.INTER_AREA)
        rgb = cv2.cvtColor(small, cv2.COLOR_GRAY2RGB) if small.ndim == 2 else small
        status = tracks.status[f]
        cov = tracks.covariances[f, :, :2, :2]
        for p in np.flatnonzero((status == MEASURED) | (status == PREDICTED)):
            x, y = tracks.positions[f, p] * scale
            evals, evecs = np.linalg.eigh(cov[p])
            axes = (gate_radius * np.sqrt(np.maximum(evals, 0)) * scale).clip(1, 1e4)
            angle = float(np.degrees(np.arctan2(evecs[1, 1], evecs[0, 1])))
            colour = (0, 220, 0) if status[p] == MEASURED else (255, 140, 0)
            cv2.ellipse(rgb, (round(x), round(y)), (round(axes[1]), round(axes[0])), angle, 0, 360, colour, 1)
        for p in np.flatnonzero(status == LOST):
            prev = tracks.positions[max(f - 1, 0), p] * scale
            if np.isfinite(prev).all():
                cv2.drawMarker(rgb, (round(prev[0]), round(prev[1])), (255, 0, 0), cv2.MARKER_TILTED_CROSS, 6)
        images.append(Image.fromarray(rgb))
    if images:
        images[0].save(
            path, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0, optimize=True
        )
    return path
