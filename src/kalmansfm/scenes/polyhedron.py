"""The built-in synthetic scene: a textured house-shaped polyhedron with dark corner markers.

The scene imitates the experiment of the report: a solid with black tape on
its corners moves across a textured background while turning slowly, seen by
a scaled orthographic camera, so that the Tomasi–Kanade factorization applies
exactly to the exact corner positions.

Rendering
---------
The background and the textured faces are drawn on a canvas ``supersample``
times finer than the image and averaged down by area.  A final pixel ``(c, r)``
covers ``[c - 0.5, c + 0.5] x [r - 0.5, r + 0.5]``; a fine pixel ``i`` covers
final coordinates ``[i / s - 0.5, (i + 1) / s - 0.5]``, so a final coordinate
``x`` sits at fine coordinate ``(x + 0.5) s - 0.5`` (fine pixel centres at
integers).  The corner markers and the occluder are axis-aligned rectangles in
the image and are composited with their exact area coverage per pixel, so the
dark centroid of an isolated marker is its corner's position to far below
0.05 px.  Faces are culled when they turn their back to the camera; the solid
is convex, so back-face culling is exact hidden-surface removal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..errors import InvalidInputError, NotEnoughDataError
from ..io.ground_truth import GroundTruth
from .._validation import check_choice, check_count, check_fits_in_memory

__all__ = [
    "DEFAULT_SCENE_FRAMES",
    "DEFAULT_SCENE_NOISE",
    "DEFAULT_SCENE_SEED",
    "DEFAULT_SCENE_SIZE",
    "MAX_IMAGE_SIDE",
    "Occluder",
    "Scene",
    "render_scene",
    "SCENARIOS",
]

#: Motion variants of the scene: ``"default"`` stays in the image;
#: ``"exit"`` accelerates the object out through the left border, so the
#: markers leave the image one after the other in the last frames.
SCENARIOS = ("default", "exit")
#: The built-in scene's defaults, shared by :func:`render_scene`, the pipeline and the CLI:
#: number of frames, image size (width, height) in pixels, seed of the textures and the noise,
#: and the pixel noise standard deviation in grey levels.
DEFAULT_SCENE_FRAMES = 30
DEFAULT_SCENE_SIZE = (320, 240)
DEFAULT_SCENE_SEED = 0
DEFAULT_SCENE_NOISE = 2.0
#: Largest width or height of a rendered frame (a 4096×3072 frame takes ~6 s to draw; 40000×40000 would take hours).
MAX_IMAGE_SIDE = 4096

_MARKER_INTENSITY = 20.0


@dataclass(frozen=True)
class Occluder:
    """A flat textured card passing in front of the scene that hides one chosen marker.

    The card moves horizontally at ``speed_px`` pixels per frame; its position
    and width are chosen so that the marker of ``track_id`` is completely
    covered in frames ``first_frame … first_frame + n_frames - 1`` and is not
    touched in any other frame.  Other markers it passes over are hidden too,
    and the ground truth ``visible`` says so.

    Parameters
    ----------
    track_id : int
        The corner whose marker is hidden.
    first_frame : int
        First frame in which it is hidden.
    n_frames : int
        Number of consecutive frames in which it is hidden (>= 1).
    speed_px : float
        Horizontal speed of the card (pixels per frame, positive = rightwards).
        Relative to the marker it must move more than about one marker size
        per frame, so that a card width exists that covers the marker in
        exactly ``n_frames`` frames; otherwise :class:`InvalidInputError`.  A
        speed opposite to the object's leftward motion works best.
    height_px : float or None
        Height of the card, centred on the marker's mean row while hidden;
        None spans the whole image height (a pole in front of the camera).
    marker : bool
        Put a dark marker of the same size on the card, at the hidden
        marker's mean row, so that two markers cross: the card's marker passes
        over the hidden one in the middle of the occlusion (a test of identity
        swaps).  Its positions are ``Scene.occluder_marker_positions``.
    """

    track_id: int = 0
    first_frame: int = 10
    n_frames: int = 3
    speed_px: float = 6.0
    height_px: float | None = 40.0
    marker: bool = False


@dataclass(frozen=True)
class Scene:
    """A rendered sequence with its exact ground truth.

    Attributes
    ----------
    frames : (F, H, W) uint8
        Grey images.
    points_3d : (P, 3) float64
        Corners in the object frame, centred at the origin.
    positions : (F, P, 2) float64
        Exact projected corner positions, x = column, y = row, pixel centres at
        integer coordinates; given also where the corner is not visible.
    visible : (F, P) bool
        True where the corner's marker is entirely visible: the corner lies on
        a face turned towards the camera, the occluder does not touch its
        marker, and the whole marker is inside the image.
    rotations : (F, 3, 3) float64
        Object-to-camera rotations; the camera looks along +z.
    translations : (F, 2) float64
        Image position of the object's origin.
    scale : float
        Pixels per object unit; ``positions[f] = scale * points_3d @ rotations[f][:2].T + translations[f]``.
    object_radius : float
        RMS distance of the corners from their centroid (object units).
    track_ids : (P,) int64
        Identity of each corner.
    parameters : dict
        Every parameter used to render (JSON-serialisable).
    occluder_boxes : (F, 4) float64
        The occluder rectangle ``x0, y0, x1, y1`` per frame (NaN without occluder).
    occluder_marker_positions : (F, 2) float64
        Centre of the occluder's own marker, x, y (NaN without one); it is not
        one of the corners and has no 3D point.
    faces : tuple of tuple of int
        The solid's faces as corner indices (convex polygons).
    """

    frames: np.ndarray
    points_3d: np.ndarray
    positions: np.ndarray
    visible: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    scale: float
    object_radius: float
    track_ids: np.ndarray
    parameters: dict[str, Any] = field(default_factory=dict)
    occluder_boxes: np.ndarray | None = None
    occluder_marker_positions: np.ndarray | None = None
    faces: tuple[tuple[int, ...], ...] = ()

    @property
    def n_frames(self) -> int:
        """Number of frames F."""
        return int(self.frames.shape[0])

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return int(self.frames.shape[2]), int(self.frames.shape[1])

    def ground_truth(self) -> GroundTruth:
        """The scene's ground truth as the record the ground-truth files hold."""
        n_frames = self.n_frames
        return GroundTruth(
            track_ids=np.asarray(self.track_ids),
            positions=self.positions,
            visible=self.visible,
            points_3d=self.points_3d,
            rotation_rows=self.rotations[:, :2],
            translations=self.translations,
            scales=np.full(n_frames, self.scale),
            occluder_boxes=self.occluder_boxes,
            occluder_markers=self.occluder_marker_positions,
        )


# ---------------------------------------------------------------------------------------------
# Geometry
# ---------------------------------------------------------------------------------------------


def _house() -> tuple[np.ndarray, list[list[int]]]:
    """Corners and faces (vertex indices) of a convex house: a box with a gable roof.

    Object axes: x to the right, y down (as image rows), z away from the camera.
    """
    half_width, half_depth = 1.0, 0.75
    bottom, eave, ridge = 0.75, -0.25, -0.95
    front, back = -half_depth, half_depth
    corners = np.array(
        [
            [-half_width, bottom, front],  # 0 front bottom left
            [half_width, bottom, front],  # 1 front bottom right
            [half_width, eave, front],  # 2 front eave right
            [0.0, ridge, front],  # 3 front ridge
            [-half_width, eave, front],  # 4 front eave left
            [-half_width, bottom, back],  # 5 back bottom left
            [half_width, bottom, back],  # 6 back bottom right
            [half_width, eave, back],  # 7 back eave right
            [0.0, ridge, back],  # 8 back ridge
            [-half_width, eave, back],  # 9 back eave left
        ]
    )
    faces = [
        [0, 1, 2, 3, 4],  # front gable
        [5, 9, 8, 7, 6],  # back gable
        [0, 4, 9, 5],  # left wall
        [1, 6, 7, 2],  # right wall
        [0, 5, 6, 1],  # floor
        [4, 3, 8, 9],  # left roof
        [3, 2, 7, 8],  # right roof
    ]
    return corners - corners.mean(axis=0), faces


def _outward_normals(corners: np.ndarray, faces: list[list[int]]) -> np.ndarray:
    centre = corners.mean(axis=0)
    normals = []
    for face in faces:
        v = corners[face]
        n = np.cross(v[1] - v[0], v[2] - v[0])
        n /= np.linalg.norm(n)
        # orient away from the solid's centre (the solid is convex)
        normals.append(n if n @ (v.mean(axis=0) - centre) > 0 else -n)
    return np.array(normals)


def _rotation_xyz(yaw: np.ndarray, tilt: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """R = Rz(roll) Rx(tilt) Ry(yaw), batched over frames (angles in radians)."""
    def batch(axis: int, angle: np.ndarray) -> np.ndarray:
        c, s = np.cos(angle), np.sin(angle)
        R = np.zeros((len(angle), 3, 3))
        i, j = [k for k in range(3) if k != axis]
        R[:, axis, axis] = 1.0
        R[:, i, i] = c
        R[:, j, j] = c
        R[:, i, j] = -s
        R[:, j, i] = s
        return R

    return batch(2, roll) @ batch(0, tilt) @ batch(1, yaw)


# ---------------------------------------------------------------------------------------------
# Textures and coverage
# ---------------------------------------------------------------------------------------------


def _smooth_noise(rng: np.random.Generator, shape: tuple[int, int], blur: float, mean: float, contrast: float) -> np.ndarray:
    """Gaussian-blurred white noise scaled to standard deviation ``contrast`` around ``mean``."""
    noise = rng.standard_normal(shape).astype(np.float32)
    noise = cv2.GaussianBlur(noise, (0, 0), blur, borderType=cv2.BORDER_REFLECT)
    noise *= contrast / max(float(noise.std()), 1e-12)
    return noise + np.float32(mean)


def _interval_coverage(low: np.ndarray, high: np.ndarray, n: int) -> np.ndarray:
    """Length of ``[low, high]`` inside each pixel ``[k - 0.5, k + 0.5]``, k = 0 … n-1.

    ``low``, ``high`` have any shape S; the result has shape S + (n,).
    """
    k = np.arange(n, dtype=np.float64)
    overlap = np.minimum(high[..., None], k + 0.5)
    overlap -= np.maximum(low[..., None], k - 0.5)
    # np.clip is slow on large arrays; two in-place bounds are not
    np.maximum(overlap, 0.0, out=overlap)
    np.minimum(overlap, 1.0, out=overlap)
    return overlap


def _convex_row_coverage(vertices: np.ndarray, height: int, width: int) -> np.ndarray:
    """Coverage of the pixels of a ``height x width`` grid by a convex polygon: (height, width) float32.

    Each pixel row is sampled at its centre line; along that line the polygon
    is an interval ``[left, right]`` whose exact overlap with each pixel is
    taken, so edges carry no half-pixel bias (unlike a fill rule that includes
    every pixel an edge touches).
    """
    start, end = vertices, np.roll(vertices, -1, axis=0)
    rows = np.arange(height, dtype=np.float64)[:, None]
    dy = end[:, 1] - start[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        # x where each edge crosses the row's centre line
        x = start[:, 0] + (rows - start[:, 1]) * (end[:, 0] - start[:, 0]) / dy
    crossing = (rows >= np.minimum(start[:, 1], end[:, 1])) & (rows < np.maximum(start[:, 1], end[:, 1]))
    left = np.where(crossing, x, np.inf).min(axis=1)
    right = np.where(crossing, x, -np.inf).max(axis=1)
    right = np.maximum(right, left)  # rows outside the polygon: empty interval
    left = np.where(np.isfinite(left), left, 0.0)
    right = np.where(np.isfinite(right), right, 0.0)
    return _interval_coverage(left, right, width).astype(np.float32)


def _rectangle_coverage(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """Exact area coverage of axis-aligned boxes ``(..., K, 4)`` (x0, y0, x1, y1) summed over K.

    Returns ``(..., height, width)`` float32; NaN boxes cover nothing.
    """
    boxes = np.nan_to_num(boxes, nan=-10.0)
    cover_x = _interval_coverage(boxes[..., 0], boxes[..., 2], width)  # (..., K, W)
    cover_y = _interval_coverage(boxes[..., 1], boxes[..., 3], height)  # (..., K, H)
    # coverage(r, c) = sum_k cover_y[k, r] * cover_x[k, c]
    # contiguous float32 operands keep the batched product on BLAS
    cover = np.ascontiguousarray(np.swapaxes(cover_y, -1, -2), dtype=np.float32) @ cover_x.astype(np.float32)
    np.minimum(cover, 1.0, out=cover)
    return cover


# ---------------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------------


def _check_size(image_size: Any) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in image_size)
        ok = (width, height) == tuple(image_size)
    except (TypeError, ValueError):
        ok = False
    if not ok or not (32 <= width <= MAX_IMAGE_SIDE and 32 <= height <= MAX_IMAGE_SIDE):
        raise InvalidInputError(
            f"image_size must be (width, height) with integers in 32 … {MAX_IMAGE_SIDE}; got {image_size!r}"
        )
    return width, height


#: Peak memory of rendering, per pixel of the sequence (float32 frames, the float64 noise, the uint8 result):
#: measured 20.6 bytes (``render_scene`` of 530 vs 30 frames at 320×240, maximum resident size).
_RENDER_BYTES_PER_PIXEL = 21


def _check_memory(n_frames: int, width: int, height: int) -> None:
    """Refuse a sequence whose rendering would need more memory than the machine has, before allocating any."""
    check_fits_in_memory(float(n_frames) * width * height * _RENDER_BYTES_PER_PIXEL,
                         f"n_frames {n_frames} of {width}x{height}", "use fewer frames or smaller images")


def _check_occluder(occluder: Occluder | dict | None, n_frames: int, n_points: int) -> Occluder | None:
    if occluder is None:
        return None
    if isinstance(occluder, dict):
        try:
            occluder = Occluder(**occluder)
        except TypeError as exc:
            raise InvalidInputError(f"occluder: {exc}") from None
    if not isinstance(occluder, Occluder):
        raise InvalidInputError(f"occluder must be an Occluder, a dict of its fields or None; got {type(occluder).__name__}")
    if not 0 <= occluder.track_id < n_points:
        raise InvalidInputError(f"occluder.track_id must be in 0 … {n_points - 1}; got {occluder.track_id}")
    if occluder.n_frames < 1 or occluder.first_frame < 0 or occluder.first_frame + occluder.n_frames > n_frames:
        raise InvalidInputError(
            f"occluder must hide at least one frame within 0 … {n_frames - 1}; got {occluder.n_frames} frame(s) "
            f"from frame {occluder.first_frame}"
        )
    if occluder.height_px is not None and not occluder.height_px > 0:
        raise InvalidInputError(f"occluder.height_px must be positive or None; got {occluder.height_px}")
    return occluder


# ---------------------------------------------------------------------------------------------
# The scene
# ---------------------------------------------------------------------------------------------


def render_scene(
    n_frames: int = DEFAULT_SCENE_FRAMES,
    image_size: tuple[int, int] = DEFAULT_SCENE_SIZE,
    seed: int = DEFAULT_SCENE_SEED,
    pixel_noise_std: float = DEFAULT_SCENE_NOISE,
    occluder: Occluder | dict | None = None,
    *,
    scenario: str = SCENARIOS[0],
    marker_size_px: float = 6.0,
    yaw_deg: tuple[float, float] = (-45.0, 30.0),
    tilt_deg: tuple[float, float] = (18.0, -6.0),
    roll_deg: tuple[float, float] = (3.0, -4.0),
    supersample: int = 4,
    texture_contrast: float = 30.0,
    shading: float = 0.25,
) -> Scene:
    """Render the built-in synthetic sequence with its exact ground truth.

    A convex house-shaped polyhedron (10 corners, 7 faces, each face with its
    own random texture) carries dark square markers centred on its corners
    and moves leftwards across a textured background with some acceleration,
    while turning slowly about a mostly vertical axis.  The camera is scaled
    orthographic.  Faces turned away from the camera are hidden, and so are
    the markers of corners that lie only on such faces.

    Parameters
    ----------
    n_frames : int
        Number of frames F (>= 3).
    image_size : (int, int)
        (width, height) in pixels, each in 32 … ``MAX_IMAGE_SIDE`` (4096).  Object size and motion scale
        with ``min(width / 320, height / 240)``; the marker size does not.
    seed : int
        Seed of the textures and of the pixel noise; the geometry and motion
        do not depend on it.
    pixel_noise_std : float
        Standard deviation of the additive Gaussian noise in grey levels (>= 0).
    occluder : Occluder, dict or None
        A card that hides one marker for a few frames (see :class:`Occluder`).
    scenario : {"default", "exit"}
        ``"exit"``: the object accelerates out of the image through the left
        border, so that markers leave the image.
    marker_size_px : float
        Side of the square markers in pixels (0 draws none).
    yaw_deg, tilt_deg, roll_deg : (float, float)
        (start angle, total change over the sequence) in degrees of the
        rotations about the object's vertical axis, the camera's horizontal
        axis and the viewing axis; R = Rz(roll) Rx(tilt) Ry(yaw).
    supersample : int
        Fine-grid factor for the faces and the background (>= 1).
    texture_contrast : float
        Standard deviation of the face and background textures in grey levels.
    shading : float
        Fraction of a face's brightness that follows its angle to the light
        (0 = flat).

    Returns
    -------
    Scene

    Examples
    --------
    >>> scene = render_scene(n_frames=5)
    >>> scene.frames.shape, scene.positions.shape, scene.visible.shape
    ((5, 240, 320), (5, 10, 2), (5, 10))
    >>> f = 4
    >>> R, t = scene.rotations[f], scene.translations[f]
    >>> bool(np.allclose(scene.positions[f], scene.scale * scene.points_3d @ R[:2].T + t))
    True
    """
    n_frames = check_count("n_frames", n_frames, 3, NotEnoughDataError)
    width, height = _check_size(image_size)
    seed = check_count("seed", seed, 0)
    if not np.isfinite(pixel_noise_std) or pixel_noise_std < 0:
        raise InvalidInputError(f"pixel_noise_std must be a finite number >= 0; got {pixel_noise_std!r}")
    check_choice("scenario", scenario, SCENARIOS)
    if not 0.0 <= marker_size_px <= 30.0:
        raise InvalidInputError(f"marker_size_px must be in [0, 30] (0: no markers); got {marker_size_px}")
    if not isinstance(supersample, (int, np.integer)) or not 1 <= supersample <= 8:
        raise InvalidInputError(f"supersample must be an integer in 1 … 8; got {supersample!r}")
    _check_memory(n_frames, width, height)
    corners, faces = _house()
    occluder = _check_occluder(occluder, n_frames, len(corners))

    # --- motion ----------------------------------------------------------------------------
    size_factor = min(width / 320.0, height / 240.0)
    scale = 55.0 * size_factor
    progress = np.linspace(0.0, 1.0, n_frames)
    angles = [np.radians(start + total * progress) for start, total in (yaw_deg, tilt_deg, roll_deg)]
    rotations = _rotation_xyz(*angles)
    # the motion is defined for 30 frames and stretched to n_frames
    time = 29.0 * progress
    start = np.array([0.64 * width, 0.47 * height])
    velocity = np.array([-3.0, 0.35]) * size_factor
    acceleration = np.array([-0.045, -0.012]) * size_factor
    if scenario == "exit":
        velocity = np.array([-4.0, 0.2]) * size_factor
        acceleration = np.array([-0.30, 0.0]) * size_factor
    # t(f) = t0 + v f + a f^2 / 2
    translations = start + velocity * time[:, None] + 0.5 * acceleration * time[:, None] ** 2

    # positions[f, p] = scale * R_f[:2] X_p + t_f
    positions = scale * np.einsum("fij,pj->fpi", rotations[:, :2], corners) + translations[:, None, :]

    # --- visibility ------------------------------------------------------------------------
    normals = _outward_normals(corners, faces)
    # the camera looks along +z: a face is front-facing when its normal has negative camera z
    facing = -np.einsum("fj,pj->fp", rotations[:, 2], normals)  # (F, faces)
    front = facing > 1e-9
    incidence = np.zeros((len(faces), len(corners)), dtype=bool)
    for k, face in enumerate(faces):
        incidence[k, face] = True
    on_front_face = (front.astype(np.int64) @ incidence.astype(np.int64)) > 0  # (F, P)

    half = marker_size_px / 2.0
    marker_boxes = np.concatenate([positions - half, positions + half], axis=-1)  # (F, P, 4)
    inside = (
        (marker_boxes[..., 0] >= -0.5)
        & (marker_boxes[..., 1] >= -0.5)
        & (marker_boxes[..., 2] <= width - 0.5)
        & (marker_boxes[..., 3] <= height - 0.5)
    )
    occluder_boxes = np.full((n_frames, 4), np.nan)
    occluder_marker = np.full((n_frames, 2), np.nan)
    if occluder is not None:
        occluder_boxes, marker_row = _place_occluder(occluder, positions, half, width, height)
        if occluder.marker:
            occluder_marker[:, 0] = 0.5 * (occluder_boxes[:, 0] + occluder_boxes[:, 2])
            occluder_marker[:, 1] = marker_row
    ox0, oy0, ox1, oy1 = (occluder_boxes[:, None, k] for k in range(4))
    touched = (
        (marker_boxes[..., 0] < ox1)
        & (marker_boxes[..., 2] > ox0)
        & (marker_boxes[..., 1] < oy1)
        & (marker_boxes[..., 3] > oy0)
    )
    visible = on_front_face & inside & ~touched

    # --- pictures --------------------------------------------------------------------------
    rng = np.random.default_rng(seed)
    frames = _render_frames(
        rng,
        corners,
        faces,
        facing,
        rotations,
        translations,
        scale,
        width,
        height,
        supersample,
        texture_contrast,
        shading,
        size_factor,
    )
    # markers where the corner is on a front face (also partly outside the image), dark
    marker_cover = _rectangle_coverage(np.where(on_front_face[..., None], marker_boxes, np.nan), width, height)
    frames += marker_cover * (np.float32(_MARKER_INTENSITY) - frames)
    if occluder is not None:
        card = _rectangle_coverage(occluder_boxes[:, None, :], width, height)
        frames += card * (_card_texture(occluder_boxes, width, height) - frames)
        if occluder.marker:
            boxes = np.concatenate([occluder_marker - half, occluder_marker + half], axis=-1)[:, None, :]
            card_marker = _rectangle_coverage(boxes, width, height)
            frames += card_marker * (np.float32(_MARKER_INTENSITY) - frames)
    if pixel_noise_std > 0:
        frames += rng.normal(0.0, pixel_noise_std, size=frames.shape).astype(np.float32)
    frames = np.clip(np.rint(frames), 0, 255).astype(np.uint8)

    parameters: dict[str, Any] = {
        "n_frames": int(n_frames),
        "image_size": [width, height],
        "seed": int(seed),
        "pixel_noise_std": float(pixel_noise_std),
        "occluder": None if occluder is None else dict(occluder.__dict__),
        "scenario": scenario,
        "marker_size_px": float(marker_size_px),
        "yaw_deg": list(map(float, yaw_deg)),
        "tilt_deg": list(map(float, tilt_deg)),
        "roll_deg": list(map(float, roll_deg)),
        "supersample": int(supersample),
        "texture_contrast": float(texture_contrast),
        "shading": float(shading),
        "scale": float(scale),
        "start_px": start.tolist(),
        "velocity_px_per_frame": velocity.tolist(),
        "acceleration_px_per_frame2": acceleration.tolist(),
        "camera": "scaled orthographic",
        "solid": "convex house: box with gable roof, 10 corners, 7 faces",
    }
    for array in (corners, positions, visible, rotations, translations, occluder_boxes, occluder_marker, frames):
        array.setflags(write=False)
    track_ids = np.arange(len(corners), dtype=np.int64)
    track_ids.setflags(write=False)
    return Scene(
        frames=frames,
        points_3d=corners,
        positions=positions,
        visible=visible,
        rotations=rotations,
        translations=translations,
        scale=float(scale),
        object_radius=float(np.sqrt(np.mean(np.sum((corners - corners.mean(axis=0)) ** 2, axis=1)))),
        track_ids=track_ids,
        parameters=parameters,
        occluder_boxes=occluder_boxes,
        occluder_marker_positions=occluder_marker,
        faces=tuple(tuple(face) for face in faces),
    )


def _place_occluder(
    occluder: Occluder, positions: np.ndarray, marker_half: float, width: int, height: int
) -> tuple[np.ndarray, float]:
    """Per-frame box of a card that fully covers the target marker exactly in the chosen frames, and its row."""
    n_frames = positions.shape[0]
    target = positions[:, occluder.track_id]
    hidden = np.zeros(n_frames, dtype=bool)
    hidden[occluder.first_frame : occluder.first_frame + occluder.n_frames] = True
    frames = np.arange(n_frames, dtype=np.float64)
    middle = occluder.first_frame + (occluder.n_frames - 1) / 2.0
    # card centre x_c(f) = x_target(middle) + speed (f - middle), x_target interpolated at half frames
    centre_x = np.interp(middle, frames, target[:, 0]) + occluder.speed_px * (frames - middle)
    gap = np.abs(centre_x - target[:, 0])
    worst_hidden = gap[hidden].max()
    nearest_free = gap[~hidden].min() if (~hidden).any() else np.inf
    # full cover needs half_width >= gap + marker_half in hidden frames; no touch needs half_width <= gap - marker_half
    if not worst_hidden + marker_half < nearest_free - marker_half:
        raise InvalidInputError(
            f"occluder.speed_px={occluder.speed_px} is too close to the marker's own speed to hide it in exactly "
            f"{occluder.n_frames} frames; use a speed opposite to the object's motion (e.g. 6)"
        )
    half_width = min(0.5 * (worst_hidden + nearest_free), worst_hidden + marker_half + 0.5 * width)
    centre_y = float(target[hidden, 1].mean())
    if occluder.height_px is None:
        y0, y1 = -1.0, height + 1.0
    else:
        y0, y1 = centre_y - occluder.height_px / 2.0, centre_y + occluder.height_px / 2.0
        if y0 > target[hidden, 1].min() - marker_half or y1 < target[hidden, 1].max() + marker_half:
            raise InvalidInputError(
                f"occluder.height_px={occluder.height_px} is too small to cover the marker of track "
                f"{occluder.track_id} while it moves; use at least "
                f"{np.ptp(target[hidden, 1]) + 2 * marker_half + 1:.0f}"
            )
    boxes = np.empty((n_frames, 4))
    boxes[:, 0] = centre_x - half_width
    boxes[:, 2] = centre_x + half_width
    boxes[:, 1] = y0
    boxes[:, 3] = y1
    return boxes, centre_y


def _card_texture(boxes: np.ndarray, width: int, height: int) -> np.ndarray:
    """Light stripes that move with the card: (F, H, W) float32."""
    columns = np.arange(width, dtype=np.float64)[None, None, :] - boxes[:, None, None, 0]
    rows = np.arange(height, dtype=np.float64)[None, :, None]
    across = (35.0 * np.sin(2 * np.pi * columns / 9.0)).astype(np.float32)
    down = np.cos(2 * np.pi * rows / 23.0).astype(np.float32)
    texture = across * down
    texture += np.float32(185.0)
    return texture


def _render_frames(
    rng: np.random.Generator,
    corners: np.ndarray,
    faces: list[list[int]],
    facing: np.ndarray,
    rotations: np.ndarray,
    translations: np.ndarray,
    scale: float,
    width: int,
    height: int,
    s: int,
    contrast: float,
    shading: float,
    size_factor: float,
) -> np.ndarray:
    """Background and textured front faces, supersampled ``s`` times and area-averaged: (F, H, W) float32."""
    n_frames = len(rotations)
    fine_w, fine_h = width * s, height * s
    # the background is smooth, so it is drawn at a coarse resolution and interpolated to the fine grid
    coarse = _smooth_noise(rng, (height // 4 + 2, width // 4 + 2), 15.0 / 4, 0.0, 0.8 * contrast)
    background = _smooth_noise(rng, (height, width), 2.5, 95.0, 0.6 * contrast)
    background += cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    background = cv2.resize(background, (fine_w, fine_h), interpolation=cv2.INTER_LINEAR)

    # one texture per face in the face's own plane
    texel_units = 0.5 / scale  # half an image pixel
    textures, texture_origins, texture_axes = [], [], []
    albedo = rng.uniform(150.0, 210.0, size=len(faces))
    for k, face in enumerate(faces):
        v = corners[face]
        e1 = (v[1] - v[0]) / np.linalg.norm(v[1] - v[0])
        normal = np.cross(v[1] - v[0], v[2] - v[0])
        e2 = np.cross(normal / np.linalg.norm(normal), e1)
        a, b = (v - v[0]) @ e1, (v - v[0]) @ e2
        margin = 4 * texel_units
        origin = v[0] + (a.min() - margin) * e1 + (b.min() - margin) * e2
        shape = (
            int(np.ceil((np.ptp(b) + 2 * margin) / texel_units)) + 1,
            int(np.ceil((np.ptp(a) + 2 * margin) / texel_units)) + 1,
        )
        textures.append(_smooth_noise(rng, shape, 2.5, albedo[k], contrast))
        texture_origins.append(origin)
        texture_axes.append(np.stack([e1, e2], axis=1) * texel_units)  # (3, 2)

    light = np.array([0.3, -0.6, -0.75])
    light /= np.linalg.norm(light)
    normals = _outward_normals(corners, faces)
    frames = np.empty((n_frames, height, width), dtype=np.float32)
    canvas = np.empty((fine_h, fine_w), dtype=np.float32)
    for f in range(n_frames):
        canvas[:] = background
        projection = scale * rotations[f, :2]  # (2, 3)
        camera_normals = normals @ rotations[f].T
        for k, face in enumerate(faces):
            if facing[f, k] <= 1e-9:
                continue
            # final coordinates of the corners, then fine coordinates u = (x + 0.5) s - 0.5
            fine = (corners[face] @ projection.T + translations[f] + 0.5) * s - 0.5
            x0, y0 = np.floor(fine.min(axis=0)).astype(int) - 2
            x1, y1 = np.ceil(fine.max(axis=0)).astype(int) + 3
            x0, y0 = max(x0, 0), max(y0, 0)
            x1, y1 = min(x1, fine_w), min(y1, fine_h)
            if x1 <= x0 or y1 <= y0:
                continue
            # texel (i, j) -> fine pixel: s (scale R[:2] (origin + axes [i, j]) + t + 0.5) - 0.5 - roi origin
            linear = s * projection @ texture_axes[k]
            offset = s * (projection @ texture_origins[k] + translations[f] + 0.5) - 0.5 - np.array([x0, y0])
            warp = np.hstack([linear, offset[:, None]])
            patch = cv2.warpAffine(
                textures[k], warp, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
            )
            # Lambertian shading: brightness (1 - shading) + shading * max(0, n·l)
            patch *= np.float32((1.0 - shading) + shading * max(0.0, camera_normals[k] @ light))
            cover = _convex_row_coverage(fine - [x0, y0], y1 - y0, x1 - x0)
            roi = canvas[y0:y1, x0:x1]
            roi += cover * (patch - roi)
        frames[f] = cv2.resize(canvas, (width, height), interpolation=cv2.INTER_AREA)
    return frames
