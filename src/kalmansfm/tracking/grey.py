"""How a colour frame becomes grey: the one policy of the tracker and of every frame reader.

:mod:`kalmansfm.io.frames` (images, videos) and the tracker (frames handed to it as arrays)
both call :func:`colour_to_grey`; the readers then bring other depths to 8 bits
(:func:`kalmansfm.io.frames.grey_uint8`), the tracker keeps them (it scales a sequence once,
by its first frame, :class:`~kalmansfm.tracking.tracker.Tracker`).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["GREY_WEIGHTS_BGR", "colour_to_grey"]

#: ITU-R BT.601 luma weights of (blue, green, red), OpenCV's channel order: those of cv2.COLOR_BGR2GRAY.
GREY_WEIGHTS_BGR = (0.114, 0.587, 0.299)

# The types cv2.cvtColor converts (integers rounded to the nearest grey level, types kept).
_OPENCV_TYPES = (np.uint8, np.uint16, np.float32)


def colour_to_grey(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) BGR or (H, W, 4) BGRA as (H, W) grey, 0.114 B + 0.587 G + 0.299 R; anything else as it is.

    8-bit, 16-bit and float32 images keep their type (OpenCV's ``cvtColor``: integers are
    rounded to the nearest level); other numeric types become float64 grey (alpha ignored).

    Examples
    --------
    >>> bgr = np.zeros((1, 2, 3), np.uint8); bgr[0, 0] = (255, 0, 0); bgr[0, 1] = (0, 0, 255)
    >>> colour_to_grey(bgr).tolist()
    [[29, 76]]
    >>> colour_to_grey(np.ones((2, 2), np.uint16)).shape
    (2, 2)
    """
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        return image
    if image.dtype in _OPENCV_TYPES:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return image[..., :3].astype(np.float64) @ np.array(GREY_WEIGHTS_BGR)
