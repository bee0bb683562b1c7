"""The records of a COLMAP sparse model and its pixel convention (:mod:`kalmansfm.io.colmap` reads, writes, builds them).

The records hold the files' numbers exactly as written (COLMAP's pixel convention, quaternions as
given), so that a model reads and writes back bit for bit; :func:`to_colmap_pixels` and
:func:`from_colmap_pixels` are the one place where coordinates cross between COLMAP's convention
and kalmansfm's (see :mod:`kalmansfm.io.colmap`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..errors import InvalidInputError
from . import _colmap_files as files

__all__ = [
    "COLMAP_PIXEL_OFFSET",
    "MODEL_PARTS",
    "SUPPORTED_MODELS",
    "ColmapCameras",
    "ColmapImages",
    "ColmapModel",
    "ColmapPoints",
    "first_duplicate",
    "from_colmap_pixels",
    "model_problem",
    "rows_of",
    "to_colmap_pixels",
]

#: The three files of a model, without their extension.
MODEL_PARTS = ("cameras", "images", "points3D")

#: COLMAP coordinate = kalmansfm coordinate + this, for 2-D points and principal points (see the module notes).
COLMAP_PIXEL_OFFSET = 0.5
#: The camera models read and written (no lens distortion).
SUPPORTED_MODELS = tuple(files.SUPPORTED_MODELS)


def to_colmap_pixels(xy: object) -> np.ndarray:
    """kalmansfm pixel coordinates (pixel centres at integers) to COLMAP's (centre of the top-left pixel at 0.5).

    Examples
    --------
    >>> to_colmap_pixels([[0.0, 0.0], [319.5, 239.5]]).tolist()
    [[0.5, 0.5], [320.0, 240.0]]
    """
    return np.asarray(xy, dtype=np.float64) + COLMAP_PIXEL_OFFSET


def from_colmap_pixels(xy: object) -> np.ndarray:
    """COLMAP pixel coordinates to kalmansfm's: the inverse of :func:`to_colmap_pixels`.

    Examples
    --------
    >>> from_colmap_pixels([320.0, 240.0]).tolist()
    [319.5, 239.5]
    """
    return np.asarray(xy, dtype=np.float64) - COLMAP_PIXEL_OFFSET


def _readonly(value: object, dtype: type, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    array = np.array(value, dtype=dtype)
    if array.size == 0:
        array = array.reshape((0, *shape_tail))
    if array.ndim != 1 + len(shape_tail) or array.shape[1:] != shape_tail:
        raise InvalidInputError(f"{name} must have shape (n{''.join(f', {d}' for d in shape_tail)}); got {array.shape}")
    array.setflags(write=False)
    return array


def _freeze(record: object, spec: dict[str, tuple[type, tuple[int, ...]]]) -> None:
    for name, (dtype, tail) in spec.items():
        object.__setattr__(record, name, _readonly(getattr(record, name), dtype, tail, name))


def _lengths_match(owner: str, **arrays: np.ndarray) -> None:
    sizes = {name: len(a) for name, a in arrays.items()}
    if len(set(sizes.values())) > 1:
        raise InvalidInputError(f"{owner}: {', '.join(sizes)} must have one entry each; got {sizes}")


def _starts_ok(owner: str, starts: np.ndarray, n: int, total: int, name: str) -> None:
    if len(starts) != n + 1 or starts[0] != 0 or starts[-1] != total or (np.diff(starts) < 0).any():
        raise InvalidInputError(f"{owner}: {name} must rise from 0 to {total} in {n + 1} entries")


@dataclass(frozen=True)
class ColmapCameras:
    """The cameras of a model, as the file holds them (COLMAP pixel convention).

    Attributes
    ----------
    ids : (C,) int64 — CAMERA_ID.
    models : tuple of C str — ``PINHOLE`` or ``SIMPLE_PINHOLE`` (then fx = fy).
    sizes : (C, 2) int64 — width, height in pixels.
    params : (C, 4) float64 — fx, fy, cx, cy, the principal point in COLMAP's convention.
    """

    ids: np.ndarray
    models: tuple[str, ...]
    sizes: np.ndarray
    params: np.ndarray

    def __post_init__(self) -> None:
        _freeze(self, {"ids": (np.int64, ()), "sizes": (np.int64, (2,)), "params": (np.float64, (4,))})
        object.__setattr__(self, "models", tuple(self.models))
        _lengths_match("cameras", ids=self.ids, models=self.models, sizes=self.sizes, params=self.params)
        unknown = [m for m in self.models if m not in SUPPORTED_MODELS]
        if unknown:
            raise InvalidInputError(f"cameras: {files.unsupported_model(unknown[0])}")
        simple = np.array([m == "SIMPLE_PINHOLE" for m in self.models], dtype=bool)
        if (simple & (self.params[:, 0] != self.params[:, 1])).any():
            raise InvalidInputError("cameras: a SIMPLE_PINHOLE camera has one focal length: fx must equal fy")

    def intrinsics(self) -> np.ndarray:
        """(C, 3, 3) K of each camera in kalmansfm's pixel convention (principal point - 0.5)."""
        K = np.zeros((len(self.ids), 3, 3))
        K[:, 0, 0], K[:, 1, 1], K[:, 2, 2] = self.params[:, 0], self.params[:, 1], 1.0
        K[:, :2, 2] = from_colmap_pixels(self.params[:, 2:])
        return K


@dataclass(frozen=True)
class ColmapImages:
    """The registered images of a model, as the file holds them (COLMAP pixel convention).

    Attributes
    ----------
    ids : (I,) int64 — IMAGE_ID.
    camera_ids : (I,) int64 — the camera of each image.
    names : tuple of I str — file names, relative to the image folder.
    quaternions : (I, 4) float64 — world-to-camera rotation as (w, x, y, z), as written (not normalised).
    translations : (I, 3) float64 — world-to-camera translation: x_cam = R X + t.
    point_starts : (I + 1,) int64 — image i's 2-D points are rows ``point_starts[i]:point_starts[i + 1]``.
    points2d : (M, 2) float64 — x, y of every 2-D point, COLMAP's convention.
    point3d_ids : (M,) int64 — the 3-D point of each 2-D point, -1 where none.
    """

    ids: np.ndarray
    camera_ids: np.ndarray
    names: tuple[str, ...]
    quaternions: np.ndarray
    translations: np.ndarray
    point_starts: np.ndarray
    points2d: np.ndarray
    point3d_ids: np.ndarray

    def __post_init__(self) -> None:
        _freeze(self, {"ids": (np.int64, ()), "camera_ids": (np.int64, ()), "quaternions": (np.float64, (4,)),
                       "translations": (np.float64, (3,)), "point_starts": (np.int64, ()),
                       "points2d": (np.float64, (2,)), "point3d_ids": (np.int64, ())})
        object.__setattr__(self, "names", tuple(str(n) for n in self.names))
        _lengths_match("images", ids=self.ids, camera_ids=self.camera_ids, names=self.names,
                       quaternions=self.quaternions, translations=self.translations)
        _lengths_match("images", points2d=self.points2d, point3d_ids=self.point3d_ids)
        _starts_ok("images", self.point_starts, len(self.ids), len(self.points2d), "point_starts")
        norms = np.linalg.norm(self.quaternions, axis=1)
        bad = ~(np.isfinite(norms) & (norms > 0)) | ~np.isfinite(self.translations).all(axis=1)
        if bad.any():
            i = int(np.argmax(bad))
            raise InvalidInputError(f"images: image {self.ids[i]} ({self.names[i]}): its pose must be finite with a "
                                    f"nonzero quaternion; got {self.quaternions[i].tolist()}, "
                                    f"{self.translations[i].tolist()}")

    def rotations(self) -> np.ndarray:
        """(I, 3, 3) world-to-camera rotations R of the (normalised) quaternions."""
        if not len(self.ids):
            return np.zeros((0, 3, 3))
        return Rotation.from_quat(self.quaternions[:, [1, 2, 3, 0]]).as_matrix()

    def image_index(self) -> np.ndarray:
        """(M,) int64 — the image (row of these arrays) of each 2-D point."""
        return np.repeat(np.arange(len(self.ids)), np.diff(self.point_starts))


@dataclass(frozen=True)
class ColmapPoints:
    """The 3-D points of a model.

    Attributes
    ----------
    ids : (P,) int64 — POINT3D_ID.
    xyz : (P, 3) float64 — world coordinates.
    colours : (P, 3) uint8 — R, G, B.
    errors : (P,) float64 — ERROR, the reprojection error in pixels (-1: not computed).
    track_starts : (P + 1,) int64 — point k's track is rows ``track_starts[k]:track_starts[k + 1]``.
    track_image_ids : (T,) int64 — the image of each track element.
    track_point2d : (T,) int64 — the index of the 2-D point within that image.
    """

    ids: np.ndarray
    xyz: np.ndarray
    colours: np.ndarray
    errors: np.ndarray
    track_starts: np.ndarray
    track_image_ids: np.ndarray
    track_point2d: np.ndarray

    def __post_init__(self) -> None:
        _freeze(self, {"ids": (np.int64, ()), "xyz": (np.float64, (3,)), "colours": (np.uint8, (3,)),
                       "errors": (np.float64, ()), "track_starts": (np.int64, ()), "track_image_ids": (np.int64, ()),
                       "track_point2d": (np.int64, ())})
        _lengths_match("points3D", ids=self.ids, xyz=self.xyz, colours=self.colours, errors=self.errors)
        _lengths_match("points3D", track_image_ids=self.track_image_ids, track_point2d=self.track_point2d)
        _starts_ok("points3D", self.track_starts, len(self.ids), len(self.track_image_ids), "track_starts")

    @property
    def track_lengths(self) -> np.ndarray:
        """(P,) int64 — the number of images that see each point."""
        return np.diff(self.track_starts)


@dataclass(frozen=True)
class ColmapModel:
    """A COLMAP sparse model: cameras, registered images and 3-D points, as the files hold them.

    Attributes
    ----------
    cameras : ColmapCameras.
    images : ColmapImages — each names one of the cameras.
    points : ColmapPoints — each track element names an image and one of its 2-D points, whose
        ``point3d_ids`` entry names the point back (the images' ids are what the tracks say).
    covariances : (P, 3, 3) float64 or None — each point's covariance (NaN where it has none), from
        ``points3D_covariance.txt``.
    covariance_gauge : str or None — how the covariances are to be read (the side-car's ``# GAUGE:`` line).

    Examples
    --------
    >>> from kalmansfm.io.colmap import build_colmap_model
    >>> model = build_colmap_model(np.diag([500.0, 500.0, 1.0]), np.stack([np.eye(3)] * 2),
    ...                            [[0.0, 0.0, 4.0], [-1.0, 0.0, 4.0]], (640, 480), ["a.png", "b.png"],
    ...                            [0, 1], [0, 0], [[62.5, 0.0], [-62.5, 0.0]], [[0.5, 0.0, 0.0]])
    >>> model.images.names, model.points.track_lengths.tolist()
    (('a.png', 'b.png'), [2])
    >>> model.images.points2d.tolist()  # COLMAP's convention: ours + 0.5
    [[63.0, 0.5], [-62.0, 0.5]]
    """

    cameras: ColmapCameras
    images: ColmapImages
    points: ColmapPoints
    covariances: np.ndarray | None = None
    covariance_gauge: str | None = None

    def __post_init__(self) -> None:
        problem = model_problem(self.cameras, self.images, self.points, {part: part for part in MODEL_PARTS})
        if problem:
            raise InvalidInputError(problem)
        if self.covariances is not None:
            cov = np.array(self.covariances, dtype=np.float64)
            if cov.shape != (len(self.points.ids), 3, 3):
                raise InvalidInputError(f"covariances must have shape ({len(self.points.ids)}, 3, 3), one per point; "
                                        f"got {cov.shape}")
            cov.setflags(write=False)
            object.__setattr__(self, "covariances", cov)
        if self.covariance_gauge is not None and ("\n" in self.covariance_gauge or "\r" in self.covariance_gauge):
            raise InvalidInputError("covariance_gauge must be one line of text")

    def intrinsics(self) -> np.ndarray:
        """(I, 3, 3) K of each image in kalmansfm's pixel convention (principal point - 0.5)."""
        return self.cameras.intrinsics()[rows_of(self.cameras.ids, self.images.camera_ids)]

    def image_sizes(self) -> np.ndarray:
        """(I, 2) int64 — width, height of each image (its camera's)."""
        return self.cameras.sizes[rows_of(self.cameras.ids, self.images.camera_ids)]

    def observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The 2-D points that belong to a 3-D point, in kalmansfm's pixel convention.

        Returns
        -------
        image : (N,) int64 — row of ``images``.
        point : (N,) int64 — row of ``points``.
        xy : (N, 2) float64 — x, y (pixel centres at integers).
        """
        image = self.images.image_index()
        has = self.images.point3d_ids >= 0
        point = rows_of(self.points.ids, self.images.point3d_ids[has])
        return image[has], point, from_colmap_pixels(self.images.points2d[has])


def rows_of(ids: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """Row of each wanted id in ``ids`` (all present), by one sort and a search.

    Examples
    --------
    >>> rows_of(np.array([7, 3, 9]), np.array([9, 7])).tolist()
    [2, 0]
    """
    order = np.argsort(ids, kind="stable")
    return order[np.searchsorted(ids, wanted, sorter=order)]


def first_duplicate(ids: np.ndarray) -> int | None:
    """The smallest id given more than once, or None.

    Examples
    --------
    >>> first_duplicate(np.array([4, 2, 4, 2])), first_duplicate(np.array([1, 2]))
    (2, None)
    """
    unique, counts = np.unique(ids, return_counts=True)
    return int(unique[counts > 1][0]) if (counts > 1).any() else None


def model_problem(cameras: ColmapCameras, images: ColmapImages, points: ColmapPoints | None,
                  names: dict[str, str], *, point_ids: bool = True) -> str | None:
    """The first way the three parts of a model fail to refer to each other, naming the part; None if they agree.

    ``names`` maps ``cameras``, ``images`` and ``points3D`` to how each is named in the message
    (the file, when read from one).  ``point_ids``: also check that the images' ``point3d_ids`` are
    what the tracks say (the reader sets them from the tracks instead).
    """
    parts = (("cameras", cameras.ids), ("images", images.ids), ("points3D", None if points is None else points.ids))
    for part, ids in parts:
        dup = None if ids is None else first_duplicate(ids)
        if dup is not None:
            return f"{names[part]}: id {dup} is given twice"
    known = np.isin(images.camera_ids, cameras.ids)
    if not known.all():
        i = int(np.argmin(known))
        return (f"{names['images']}: image {images.ids[i]} ({images.names[i]}) names camera {images.camera_ids[i]}, "
                f"which {names['cameras']} does not hold")
    if points is None:
        return None
    seen = np.isin(points.track_image_ids, images.ids)
    if not seen.all():
        k = int(np.searchsorted(points.track_starts, np.argmin(seen), side="right") - 1)
        return (f"{names['points3D']}: point {points.ids[k]}'s track names image "
                f"{points.track_image_ids[np.argmin(seen)]}, "
                f"which {names['images']} does not hold")
    row = rows_of(images.ids, points.track_image_ids)
    counts = np.diff(images.point_starts)[row]
    inside = (points.track_point2d >= 0) & (points.track_point2d < counts)
    if not inside.all():
        e = int(np.argmin(inside))
        k = int(np.searchsorted(points.track_starts, e, side="right") - 1)
        return (f"{names['points3D']}: point {points.ids[k]}'s track names 2-D point {points.track_point2d[e]} of "
                f"image {points.track_image_ids[e]}, which has {counts[e]} in {names['images']}")
    flat = images.point_starts[row] + points.track_point2d
    twice = first_duplicate(flat)
    if twice is not None:
        e = int(np.argmax(flat == twice))
        return (f"{names['points3D']}: 2-D point {points.track_point2d[e]} of image {points.track_image_ids[e]} is in "
                f"two tracks")
    if not point_ids:
        return None
    owner = np.full(len(images.point3d_ids), -1, dtype=np.int64)
    owner[flat] = np.repeat(points.ids, points.track_lengths)
    if not np.array_equal(owner, images.point3d_ids):
        m = int(np.argmax(owner != images.point3d_ids))
        i = int(np.searchsorted(images.point_starts, m, side="right") - 1)
        return (f"{names['images']}: 2-D point {m - images.point_starts[i]} of image {images.ids[i]} names 3-D point "
                f"{images.point3d_ids[m]}, but the tracks of {names['points3D']} say {owner[m]}")
    return None
