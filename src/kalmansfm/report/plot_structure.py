"""The recovered 3D shape as a scatter plot with track ids, from two viewpoints (report Figure 2)."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["plot_structure"]


def plot_structure(
    points: np.ndarray,
    track_ids: np.ndarray,
    path: str | os.PathLike[str],
    *,
    title: str = "Recovered shape",
    views: tuple[tuple[float, float], ...] = ((20.0, -60.0), (75.0, -90.0)),
    max_labels: int = 60,
) -> Path:
    """Save a PNG with one 3D scatter per ``(elevation, azimuth)`` in ``views``.

    Points are labelled with their track id when there are at most ``max_labels`` of
    them. NaN points are skipped. Returns ``path``.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> out = pathlib.Path(tempfile.mkdtemp()) / "s.png"
    >>> plot_structure(np.eye(3), [1, 2, 3], out).stat().st_size > 0
    True
    """
    pts = np.asarray(points, dtype=np.float64)
    ids = np.asarray(track_ids)
    keep = np.isfinite(pts).all(axis=1)
    pts, ids = pts[keep], ids[keep]
    fig = plt.figure(figsize=(5.0 * len(views), 5.0))
    for k, (elevation, azimuth) in enumerate(views, start=1):
        ax = fig.add_subplot(1, len(views), k, projection="3d")
        ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], c=pts[:, 2], cmap="viridis", s=18, depthshade=False)
        if len(pts) <= max_labels:
            for (x, y, z), i in zip(pts, ids):
                ax.text(x, y, z, f" {i}", fontsize=7)
        ax.set_xlabel("X (px)")
        ax.set_ylabel("Y (px)")
        ax.set_zlabel("Z (px)")
        if len(pts):
            span = float(np.ptp(pts, axis=0).max()) or 1.0
            centre = (pts.max(axis=0) + pts.min(axis=0)) / 2
            for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
                setter(c - span / 2, c + span / 2)
        # Image y points down: invert it so the shape appears upright as the first camera saw it.
        ax.invert_yaxis()
        ax.view_init(elev=elevation, azim=azimuth)
        ax.set_title(f"elevation {elevation:g}°, azimuth {azimuth:g}°", fontsize=9)
    fig.suptitle(title)
    fig.tight_layout()
    target = Path(path)
    fig.savefig(target, dpi=110, format="png")
    plt.close(fig)
    return target
