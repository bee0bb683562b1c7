"""Corner detection (Shi–Tomasi minimum eigenvalue or Harris) to start tracks automatically."""

from __future__ import annotations

import cv2
import numpy as np

from ..errors import InvalidInputError

__all__ = ["detect_corners"]


def detect_corners(
    image: np.ndarray,
    max_features: int = 200,
    quality_level: float = 0.01,
    min_distance_px: float = 10.0,
    border_px: int = 0,
    exclude: np.ndarray | None = None,
    harris: bool = False,
    block_size: int = 3,
) -> np.ndarray:
    """Strong corners of a grey image, strongest first.

    Parameters
    ----------
    image : (H, W) grey image (uint8 or float).
    max_features : at most this many corners.
    quality_level : corners weaker than this fraction of the strongest one are dropped.
    min_distance_px : minimum distance between two returned corners.
    border_px : no corner closer than this to the image border (e.g. half a template).
    exclude : optional (K, 2) positions (x, y); no corner within ``min_distance_px`` of them
        (used to add features only in empty regions).
    harris : use the Harris response instead of Shi–Tomasi's minimum eigenvalue.
    block_size : neighbourhood of the structure tensor.

    Returns
    -------
    (N, 2) float64 corners (x, y), N ≤ ``max_features``.

    Examples
    --------
    >>> img = np.zeros((60, 60), np.uint8); img[20:40, 20:40] = 255
    >>> sorted(detect_corners(img, max_features=4, min_distance_px=5).tolist())
    [[20.0, 20.0], [20.0, 39.0], [39.0, 20.0], [39.0, 39.0]]
    >>> len(detect_corners(img, max_features=4, min_distance_px=5, exclude=np.array([[20.0, 20.0]])))
    3
    """
    if max_features < 1:
        raise InvalidInputError(f"max_features must be >= 1; got {max_features}")
    if not 0.0 < quality_level < 1.0:
        raise InvalidInputError(f"quality_level must be in (0, 1); got {quality_level}")
    grey = np.asarray(image)
    if grey.dtype != np.uint8:
        grey = grey.astype(np.float32)
    height, width = grey.shape
    mask = np.zeros((height, width), np.uint8)
    b = int(border_px)
    if 2 * b >= min(height, width):
        return np.zeros((0, 2))
    mask[b : height - b, b : width - b] = 255
    if exclude is not None and len(exclude):
        for_mask = np.asarray(exclude, dtype=np.float64).reshape(-1, 2)
        for_mask = for_mask[np.isfinite(for_mask).all(axis=1)]
        # Rasterise the exclusion discs in one vectorised step.
        taken = np.zeros((height, width), bool)
        radius = float(min_distance_px)
        r = int(np.ceil(radius))
        offsets = np.array([(dx, dy) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dx * dx + dy * dy <= radius * radius])
        centres = np.round(for_mask).astype(int)
        pts = (centres[:, None, :] + offsets[None, :, :]).reshape(-1, 2)
        keep = (pts[:, 0] >= 0) & (pts[:, 0] < width) & (pts[:, 1] >= 0) & (pts[:, 1] < height)
        taken[pts[keep, 1], pts[keep, 0]] = True
        mask[taken] = 0
    corners = cv2.goodFeaturesToTrack(
        grey,
        maxCorners=int(max_features),
        qualityLevel=float(quality_level),
        minDistance=float(min_distance_px),
        mask=mask,
        blockSize=int(block_size),
        useHarrisDetector=bool(harris),
    )
    if corners is None:
        return np.zeros((0, 2))
    return corners.reshape(-1, 2).astype(np.float64)
