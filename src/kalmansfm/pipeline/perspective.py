"""A perspective camera's intrinsics in a run: from its ``K.csv`` or its focal length.

Shared by ``kalmansfm reconstruct`` (``Perspective`` or ``Auto`` camera) and ``kalmansfm demo``.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidInputError
from ..io.intrinsics import intrinsics_from_focal, read_intrinsics
from .requests import Perspective

__all__ = ["CAMERA_MODELS", "resolve_intrinsics"]

#: the camera models a reconstruction request may name (``reconstruct --camera``).
CAMERA_MODELS = ("affine", "perspective", "auto")


def resolve_intrinsics(frames: np.ndarray, camera: Perspective,
                       image_size: tuple[int, int] | None = None) -> tuple[np.ndarray, str]:
    """K of every frame, and a description of where it came from for the summary.

    From the camera's ``intrinsics`` file, or from its ``focal`` length with the principal point at
    the centre of the image: the camera's ``image_size`` or else ``image_size`` (what the input
    records); one of them must exist.  Returns (F, 3, 3) and the description.
    """
    if camera.intrinsics is not None:
        return read_intrinsics(camera.intrinsics, frames), str(camera.intrinsics)
    size = camera.image_size if camera.image_size is not None else image_size
    if size is None:
        raise InvalidInputError("focal needs the image size for the principal point: give image_size (width, height); "
                                "the tracks file does not record it", fields=("focal", "image_size"))
    focal = float(camera.focal)  # type: ignore[arg-type]
    K = intrinsics_from_focal(focal, size, len(frames))
    return K, f"focal {focal:g} px, principal point at the centre of the {size[0]}x{size[1]} image"
