"""What the synthetic perspective scenes share: cameras on an arc looking at the object, and gross mismatches."""

from __future__ import annotations

import numpy as np


def arc_centres(angles: np.ndarray, radius: float, wobble: float) -> np.ndarray:
    """(F, 3) camera centres on an arc of ``radius`` around the origin at ``angles`` (radians, 0 = −Z).

    The height wobbles by ``wobble`` · sin 3θ, so that the centres are not all on one plane.

    Examples
    --------
    >>> arc_centres(np.array([0.0]), 4.0, 0.3).tolist()
    [[0.0, 0.0, -4.0]]
    """
    return np.stack([radius * np.sin(angles), wobble * np.sin(3 * angles), -radius * np.cos(angles)], axis=1)


def look_at(centres: np.ndarray, targets: np.ndarray, up: tuple[float, float, float]) -> np.ndarray:
    """(F, 3, 3) world → camera rotations of cameras at ``centres`` looking at ``targets``.

    The rows are the image x axis (``up`` × forward, normalised), the image y axis
    (forward × x) and the viewing direction; ``up`` picks which way the image is turned.

    Examples
    --------
    >>> R = look_at(np.array([[0.0, 0.0, -4.0]]), np.zeros((1, 3)), up=(0.0, 1.0, 0.0))
    >>> R[0].tolist()
    [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    forward = targets - centres
    forward = forward / np.linalg.norm(forward, axis=1, keepdims=True)
    right = np.cross(np.asarray(up, dtype=np.float64), forward)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    return np.stack([right, np.cross(forward, right), forward], axis=1)


def mismatches(rng: np.random.Generator, count: int, low: float, high: float) -> np.ndarray:
    """(count, 2) offsets of gross mismatches: uniform directions, lengths uniform in [``low``, ``high``] pixels.

    Examples
    --------
    >>> d = mismatches(np.random.default_rng(0), 5, 20.0, 80.0)
    >>> bool(np.all((np.linalg.norm(d, axis=1) >= 20.0) & (np.linalg.norm(d, axis=1) <= 80.0)))
    True
    """
    angle = rng.uniform(0.0, 2.0 * np.pi, count)
    length = rng.uniform(low, high, count)
    return np.stack([np.cos(angle), np.sin(angle)], axis=1) * length[:, None]
