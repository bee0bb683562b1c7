"""Feature detection and description with OpenCV: SIFT (RootSIFT by default), ORB or AKAZE.

Every descriptor is returned in the form the matcher compares (:mod:`.matching`): SIFT as a
unit vector (Euclidean distance), the binary descriptors unpacked to one float per bit
(Hamming distance = squared Euclidean distance of the bits).  Features are ordered
strongest first (detector response), so "the strongest k" is a slice.
"""

from __future__ import annotations

from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import InvalidInputError
from .settings import FeatureSettings

__all__ = ["ImageFeatures", "detect_features", "detect_all"]


@dataclass(frozen=True)
class ImageFeatures:
    """The features of one image, strongest first.

    Attributes
    ----------
    keypoints : (N, 2) float64 — positions (x = column, y = row; pixel centres at integers, OpenCV's
        convention).
    scales : (N,) float32 — the detector's feature diameter (pixels).
    orientations : (N,) float32 — dominant orientation (degrees, OpenCV's convention; -1 when none).
    responses : (N,) float32 — detector response (descending).
    descriptors : (N, D) float32 — unit vectors (SIFT, RootSIFT) or bits as 0/1 (ORB, AKAZE).
    binary : True when the descriptors are bits (Hamming distance).
    """

    keypoints: np.ndarray
    scales: np.ndarray
    orientations: np.ndarray
    responses: np.ndarray
    descriptors: np.ndarray
    binary: bool

    def __len__(self) -> int:
        return int(self.keypoints.shape[0])

    def strongest(self, count: int) -> np.ndarray:
        """(min(count, N), D) descriptors of the ``count`` strongest features."""
        return self.descriptors[:count]


def _check_grey(image: object, name: str) -> np.ndarray:
    array = np.asarray(image)
    if array.ndim != 2 or array.dtype != np.uint8:
        raise InvalidInputError(f"{name} must be a 2-D uint8 grey image; got shape {array.shape}, dtype {array.dtype}")
    if min(array.shape) < 16:
        raise InvalidInputError(f"{name} must be at least 16 x 16 pixels; got {array.shape[1]} x {array.shape[0]}")
    return np.ascontiguousarray(array)


def _detector(settings: FeatureSettings) -> cv2.Feature2D:
    if settings.detector == "sift":
        return cv2.SIFT_create(nfeatures=settings.max_features, contrastThreshold=settings.contrast_threshold,
                               sigma=settings.sift_sigma)
    if settings.detector == "orb":
        return cv2.ORB_create(nfeatures=settings.max_features or 5000)
    if not hasattr(cv2, "AKAZE_create"):  # OpenCV 5 moved AKAZE to the contrib modules
        raise InvalidInputError(f"detector 'akaze' needs OpenCV's AKAZE, which this OpenCV ({cv2.__version__}) does "
                                "not have (OpenCV 5: install opencv-contrib-python-headless); use 'sift' or 'orb'")
    return cv2.AKAZE_create()


#: where OpenCV's SIFT places a feature, relative to where it is, in pixels of the image it was given.
_SIFT_UPSCALE_OFFSET = 0.25


def _sift_input(grey: np.ndarray, settings: FeatureSettings) -> tuple[np.ndarray, np.ndarray]:
    """The image SIFT is run on (resized by ``sift_upsampling / 2``), and (2,) image pixels per resized pixel."""
    scale = settings.sift_upsampling / 2.0
    if settings.detector != "sift" or scale == 1.0:
        return grey, np.ones(2)
    height, width = grey.shape
    size = (max(round(width * scale), 8), max(round(height * scale), 8))
    interpolation = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
    resized = cv2.resize(grey, size, interpolation=interpolation)
    return resized, np.array([width / size[0], height / size[1]])


def _describe(raw: np.ndarray | None, count: int, settings: FeatureSettings) -> np.ndarray:
    """Descriptors in the matcher's form (unit vectors, or unpacked bits)."""
    if raw is None or count == 0:
        width = 128 if settings.detector == "sift" else (256 if settings.detector == "orb" else 488)
        return np.zeros((0, width), np.float32)
    if settings.binary:
        return np.unpackbits(raw, axis=1).astype(np.float32)
    d = raw.astype(np.float32)
    if settings.root_sift:
        # RootSIFT: L1-normalise, square root; the result has unit L2 norm
        d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), np.float32(1e-12)))
    else:
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), np.float32(1e-12))
    return d


def detect_features(image: object, settings: FeatureSettings | None = None) -> ImageFeatures:
    """Detect and describe the features of one grey image.

    Parameters
    ----------
    image : (H, W) uint8 grey image.
    settings : FeatureSettings, default ``FeatureSettings()``.

    Returns
    -------
    ImageFeatures
        Strongest first; at most ``settings.max_features`` when that is > 0.

    Raises
    ------
    InvalidInputError
        Not a 2-D uint8 image, or smaller than 16 × 16.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> image = cv2.GaussianBlur((rng.random((120, 160)) * 255).astype(np.uint8), (0, 0), 2)
    >>> f = detect_features(image)
    >>> len(f) > 20, f.descriptors.shape[1], bool(np.allclose(np.linalg.norm(f.descriptors, axis=1), 1, atol=1e-5))
    (True, 128, True)
    >>> bool(np.all(np.diff(f.responses) <= 0))
    True
    """
    settings = FeatureSettings() if settings is None else settings
    grey = _check_grey(image, "image")
    resized, factor = _sift_input(grey, settings)
    keypoints, raw = _detector(settings).detectAndCompute(resized, None)
    count = len(keypoints)
    # OpenCV gives keypoint objects; their attributes are read once per feature here (C++ getters,
    # ~0.3 µs each: 10 ms for 30 000 features, next to 60 ms for detecting them)
    attributes = np.array([(k.size, k.angle, k.response) for k in keypoints], np.float32).reshape(count, 3)
    positions = np.asarray(cv2.KeyPoint_convert(keypoints) if count else np.zeros((0, 2)), np.float64)
    positions = positions.reshape(count, 2)
    if settings.detector == "sift":
        # OpenCV enlarges SIFT's first octave by linear interpolation, pixel centres at integers in neither
        # image, and halves the positions found there: each lands a quarter pixel right of and below its
        # feature (enable_precise_upscale avoids that, and loses a third of the features)
        positions -= _SIFT_UPSCALE_OFFSET
    if resized is not grey:  # back to the image's pixels: pixel centres at integers in both
        positions = (positions + 0.5) * factor - 0.5
        attributes[:, 0] *= np.float32(factor.mean())
    descriptors = _describe(raw, count, settings)
    order = np.argsort(-attributes[:, 2], kind="stable")
    if settings.max_features:
        order = order[: settings.max_features]
    return ImageFeatures(positions[order], attributes[order, 0], attributes[order, 1], attributes[order, 2],
                         np.ascontiguousarray(descriptors[order]), settings.binary)


def detect_all(images: Iterable[object], settings: FeatureSettings | None = None) -> tuple[ImageFeatures, ...]:
    """:func:`detect_features` of every image, on ``settings.thread_count`` threads (OpenCV releases the GIL).

    ``images`` may be lazy (a generator, a :class:`~kalmansfm.io.frames.FrameSource`): each image is handed
    to the threads as soon as it is read, so reading overlaps detection.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> images = [cv2.GaussianBlur((rng.random((80, 80)) * 255).astype(np.uint8), (0, 0), 2) for _ in range(3)]
    >>> [len(f) > 0 for f in detect_all(images)]
    [True, True, True]
    """
    settings = FeatureSettings() if settings is None else settings
    checked = (_check_grey(image, f"image {k}") for k, image in enumerate(images))
    with ThreadPoolExecutor(max_workers=settings.thread_count) as pool:
        # map submits every image as the generator yields it, before the first result is awaited
        return tuple(pool.map(lambda image: detect_features(image, settings), checked))
