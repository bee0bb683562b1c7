"""Calibrated views of a textured object from known cameras: images with ground truth for the feature front end.

A vertical cylinder (radius 1.2, height 2.4, centred at the origin; -y is up) with a random texture of
discs, boxes and strokes wrapped around its side and others on its top and on a floor disc (radius 4)
it stands on, in a flat grey background.  Cameras on a circle around it (elevated, looking at its
centre) see half of the side almost frontally whatever their angle, and the floor around it, so no two
views are related by one homography.  Each image is ray-cast: the ray of every pixel meets the side,
the top or the floor (the nearest hit) and samples that texture (OpenCV ``remap``, bilinear).  Views on
a full circle close a loop; ``order`` shuffles them, so that image order is no path.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .._validation import check_count, check_positive
from ..errors import InvalidInputError
from ..structure.geometry.pinhole import camera_centres
from ._arc import look_at

__all__ = ["TexturedViews", "textured_views"]

_RADIUS = 1.2
_HALF_HEIGHT = 1.2
# Texture of the side (width wraps around the cylinder) and of the top, pixels.
_SIDE_PX = (1024, 336)
_TOP_PX = 384
_FLOOR_RADIUS = 4.0
_FLOOR_PX = 1024


@dataclass(frozen=True)
class TexturedViews:
    """Images of the textured object and the cameras that took them.

    Attributes
    ----------
    images : (F, H, W) uint8 grey.
    intrinsics : (3, 3) K of every view.
    rotations : (F, 3, 3) world → camera (x_cam = R X + t).
    translations : (F, 3).
    angles_deg : (F,) each view's angle on the circle.
    """

    images: np.ndarray
    intrinsics: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    angles_deg: np.ndarray

    @property
    def centres(self) -> np.ndarray:
        """(F, 3) camera centres -Rᵀ t."""
        return camera_centres(self.rotations, self.translations)


def _texture(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """A random texture of overlapping discs, boxes and strokes of many sizes and grey levels on mild noise:
    distinctive blobs and corners at several scales, as SIFT wants (white noise alone matches poorly)."""
    t = np.full((height, width), 128.0, np.float32)
    t += 12.0 * cv2.GaussianBlur(rng.normal(size=t.shape).astype(np.float32), (0, 0), 3.0)
    for _ in range(int(500 * width * height / 384**2)):
        colour = float(rng.uniform(0, 255))
        x, y = int(rng.integers(0, width)), int(rng.integers(0, height))
        r = int(np.exp(rng.uniform(np.log(2), np.log(24))))
        kind = rng.integers(3)
        if kind == 0:
            cv2.circle(t, (x, y), r, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.rectangle(t, (x, y), (x + r, y + int(rng.integers(3, 40))), colour, -1, cv2.LINE_AA)
        else:
            end = (x + int(rng.integers(-60, 60)), y + int(rng.integers(-60, 60)))
            cv2.line(t, (x, y), end, colour, int(rng.integers(1, 5)), cv2.LINE_AA)
    return np.clip(cv2.GaussianBlur(t, (0, 0), 0.8), 0, 255).astype(np.uint8)


def textured_views(frames: int = 8, arc_deg: float = 120.0, *, size: tuple[int, int] = (320, 240),
                   focal_px: float = 420.0, distance: float = 6.0, elevation_deg: float = 30.0,
                   noise: float = 1.0, order: np.ndarray | None = None, seed: int = 0) -> TexturedViews:
    """Render the textured cylinder from ``frames`` cameras spread over ``arc_deg`` of a circle.

    Parameters
    ----------
    frames : number of views (>= 2).
    arc_deg : the arc the views span; 360 spreads them over the whole circle (the last view next to the
        first: a closed loop).
    size : (width, height) in pixels.
    focal_px : focal length; the principal point is the image centre.
    distance : distance of the cameras from the object's centre.
    elevation_deg : how far above the object's middle the cameras look down.
    noise : σ of the Gaussian image noise (grey levels).
    order : a permutation of the views (default: along the circle).
    seed : seed of the textures and the noise.

    Examples
    --------
    >>> views = textured_views(frames=3, seed=1)
    >>> views.images.shape, views.images.dtype.name, round(float(np.linalg.norm(views.centres[0])), 6)
    ((3, 240, 320), 'uint8', 6.0)
    """
    frames = check_count("frames", frames, 2)
    arc = check_positive("arc_deg", arc_deg, "degrees")
    if arc > 360.0:
        raise InvalidInputError(f"arc_deg must be <= 360; got {arc}")
    width, height = (check_count("size", s, 16) for s in size)
    focal = check_positive("focal_px", focal_px, "pixels")
    if check_positive("distance", distance) <= 2.0:
        raise InvalidInputError(f"distance must exceed the object's half diagonal (1.7): > 2; got {distance}")
    rng = np.random.default_rng(seed)
    side = _texture(rng, *_SIDE_PX)
    top = _texture(rng, _TOP_PX, _TOP_PX)
    floor = _texture(rng, _FLOOR_PX, _FLOOR_PX)
    step = arc / frames if arc == 360.0 else arc / max(frames - 1, 1)
    angles = np.arange(frames) * step - (0.0 if arc == 360.0 else arc / 2.0)
    index = np.arange(frames)
    if order is not None:
        index = np.asarray(order)
        if sorted(index.tolist()) != list(range(frames)):
            raise InvalidInputError(f"order must be a permutation of 0..{frames - 1}; got {index.tolist()}")
        angles = angles[index]
    theta, phi = np.radians(angles), np.radians(elevation_deg)
    centres = distance * np.stack([np.cos(phi) * np.sin(theta), -np.sin(phi) * np.ones_like(theta),
                                   -np.cos(phi) * np.cos(theta)], axis=1)
    R = look_at(centres, np.zeros_like(centres), up=(0.0, 1.0, 0.0))
    t = -np.einsum("fij,fj->fi", R, centres)
    K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    pixels = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)], axis=1) @ np.linalg.inv(K).T
    images = np.empty((frames, height, width), np.uint8)
    for f in range(frames):
        C = centres[f]
        d = pixels @ R[f]  # ray directions in the world (rows: Rᵀ K⁻¹ x)
        # side: |(C + s d)_xz| = r, the nearer root in front
        a = d[:, 0] ** 2 + d[:, 2] ** 2
        b = 2.0 * (C[0] * d[:, 0] + C[2] * d[:, 2])
        c = C[0] ** 2 + C[2] ** 2 - _RADIUS**2
        disc = b**2 - 4.0 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            s_side = (-b - np.sqrt(disc)) / (2.0 * a)
            s_top = (-_HALF_HEIGHT - C[1]) / d[:, 1]
        hit_side = (disc >= 0) & (s_side > 0) & (np.abs(C[1] + s_side * d[:, 1]) <= _HALF_HEIGHT)
        top_point = C + np.where(np.isfinite(s_top), s_top, 0.0)[:, None] * d
        hit_top = np.isfinite(s_top) & (s_top > 0) & (top_point[:, 0] ** 2 + top_point[:, 2] ** 2 <= _RADIUS**2)
        with np.errstate(invalid="ignore", divide="ignore"):
            s_floor = (_HALF_HEIGHT - C[1]) / d[:, 1]
        floor_point = C + np.where(np.isfinite(s_floor), s_floor, 0.0)[:, None] * d
        hit_floor = np.isfinite(s_floor) & (s_floor > 0) & \
            (floor_point[:, 0] ** 2 + floor_point[:, 2] ** 2 <= _FLOOR_RADIUS**2)
        # the nearest surface hit by each pixel's ray
        distances = np.stack([np.where(hit_side, s_side, np.inf), np.where(hit_top, s_top, np.inf),
                              np.where(hit_floor, s_floor, np.inf)])
        nearest = np.argmin(distances, axis=0)
        nearest[~np.isfinite(distances.min(axis=0))] = 3
        P = C + np.where(hit_side, s_side, 0.0)[:, None] * d
        around = (np.arctan2(P[:, 2], P[:, 0]) + np.pi) / (2.0 * np.pi) * _SIDE_PX[0]
        up = (P[:, 1] + _HALF_HEIGHT) / (2.0 * _HALF_HEIGHT) * (_SIDE_PX[1] - 1)
        image = np.full(xs.size, 90.0, np.float32)
        maps = [(side, around, up, cv2.BORDER_WRAP),
                (top, (top_point[:, 0] / _RADIUS + 1.0) / 2.0 * (_TOP_PX - 1),
                 (top_point[:, 2] / _RADIUS + 1.0) / 2.0 * (_TOP_PX - 1), cv2.BORDER_REPLICATE),
                (floor, (floor_point[:, 0] / _FLOOR_RADIUS + 1.0) / 2.0 * (_FLOOR_PX - 1),
                 (floor_point[:, 2] / _FLOOR_RADIUS + 1.0) / 2.0 * (_FLOOR_PX - 1), cv2.BORDER_REPLICATE)]
        for surface, (texture, u, v, border) in enumerate(maps):
            mine = nearest == surface
            sampled = cv2.remap(texture, u.reshape(height, width).astype(np.float32),
                                v.reshape(height, width).astype(np.float32), cv2.INTER_LINEAR,
                                borderMode=border).ravel()
            image[mine] = sampled[mine]
        # each view's noise from its own generator, so that a shuffled set holds the same images
        view_rng = np.random.default_rng([seed, int(index[f])])
        image += view_rng.normal(0.0, noise, image.shape).astype(np.float32)
        images[f] = np.clip(np.rint(image), 0, 255).reshape(height, width).astype(np.uint8)
    return TexturedViews(images, K, R, t, angles)
