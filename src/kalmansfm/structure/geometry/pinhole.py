"""Projective cameras with known poses: projection and linear triangulation (refinement: :mod:`.refinement`).

The shared geometric core of structure fusion with known cameras.  Everything
is batched over points (and over views where that makes sense): no Python loop
runs per point.

Conventions
-----------
* A camera is a 3 × 4 projection matrix P taking homogeneous world points
  X̃ = (X, Y, Z, 1) to homogeneous pixels: (u, v, w) = P X̃, pixel (x, y) =
  (u / w, v / w), x the column and y the row.  ``w`` is the *projective depth*.
* Any P with an invertible left 3 × 3 block M factors as P = λ K [R | t] with K
  upper triangular, positive diagonal, K[2, 2] = 1, R a rotation (det +1) and λ
  a signed scale (:func:`decompose_projection`).  A point's camera coordinates
  are x_cam = R X + t; its *depth* is x_cam[2] = w / λ.
* A point is in front of a camera when its depth is positive.  Some
  reconstructions live in a mirrored frame (a reflection of the world, or an
  overall sign absorbed into P): every point then has negative depth in every
  camera.  Cheirality is therefore judged against the scene's ``orientation``
  (+1 or -1, :func:`scene_orientation`, the sign most observations agree on),
  never by assuming that R is a proper rotation of the original world.
* Arrays: observations ``(V, N, 2)`` (views, points, (x, y)), NaN where a point
  is not seen; points ``(N, 3)``; per-point covariances ``(N, 3, 3)``.

Example
-------
>>> import numpy as np
>>> K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
>>> t = np.array([[0.0, 0.0, 5.0], [-1.0, 0.0, 5.0]])
>>> cams = CameraSet.from_pose(K, np.stack([np.eye(3)] * 2), t)
>>> X = np.array([[0.2, -0.1, 1.0]])
>>> obs = project_points(cams, X).pixels
>>> triangulate_points(cams, obs).points.round(9)
array([[ 0.2, -0.1,  1. ]])
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from ...errors import InvalidInputError, KalmanSfmWarning
from ..._validation import as_float_array, check_finite
from ..points import PointStatus
from .camera_checks import ROTATION_ROUNDED, check_rotations, intrinsics_problem, projection_scale_problem
from .batched import jacobian_products

__all__ = [
    "CameraPose",
    "CameraSet",
    "Projection",
    "Triangulation",
    "camera_centres",
    "decompose_projection",
    "intrinsic_matrices",
    "project_each",
    "project_points",
    "projection_jacobians",
    "scene_orientation",
    "triangulate_points",
]

# A left 3 × 3 block whose smallest/largest singular value ratio is below this is not invertible.
_SINGULAR_RATIO = 1e-12
# Linear triangulation: second-smallest/largest eigenvalue ratio of AᵀA below this → the
# solution is not unique (one view, or every ray through the same centre).
_DLT_RANK_RATIO = 1e-14
# |w_h| / |X_h| of the homogeneous solution below this → a point at infinity (no parallax).
_AT_INFINITY = 1e-10


def intrinsic_matrices(fx: object, fy: object, cx: object, cy: object, skew: object) -> np.ndarray:
    """Intrinsic matrices K = [[fx, skew, cx], [0, fy, cy], [0, 0, 1]] from their five numbers.

    Parameters
    ----------
    fx, fy, cx, cy, skew : scalars or (n,) arrays (broadcast together) — focal lengths,
        principal point and skew, in pixels.  Not validated: the caller checks fx, fy > 0.

    Returns
    -------
    (n, 3, 3) float64 — n = 1 for scalars.

    Examples
    --------
    >>> intrinsic_matrices(800.0, 810.0, 320.0, 240.0, 0.5)[0].tolist()
    [[800.0, 0.5, 320.0], [0.0, 810.0, 240.0], [0.0, 0.0, 1.0]]
    """
    fx, fy, cx, cy, skew = np.broadcast_arrays(*(np.atleast_1d(np.asarray(v, dtype=np.float64))
                                                 for v in (fx, fy, cx, cy, skew)))
    K = np.zeros((len(fx), 3, 3))
    K[:, 0, 0], K[:, 0, 1], K[:, 0, 2], K[:, 1, 1], K[:, 1, 2], K[:, 2, 2] = fx, skew, cx, fy, cy, 1.0
    return K


def camera_centres(rotations: object, translations: object) -> np.ndarray:
    """Camera centres C = -Rᵀ t of poses with x_cam = R X + t (NaN poses give NaN centres).

    Parameters
    ----------
    rotations : (..., 3, 3).
    translations : (..., 3).

    Returns
    -------
    (..., 3) float64.

    Examples
    --------
    >>> camera_centres(np.eye(3), [0.0, 0.0, 2.0]).tolist()
    [-0.0, -0.0, -2.0]
    """
    return -np.einsum("...ji,...j->...i", np.asarray(rotations, dtype=np.float64),
                      np.asarray(translations, dtype=np.float64))


def _readonly(array: np.ndarray) -> np.ndarray:
    array = np.ascontiguousarray(array)
    array.setflags(write=False)
    return array


@dataclass(frozen=True)
class CameraSet:
    """V projective cameras and the frame number each belongs to.

    Attributes
    ----------
    matrices : (V, 3, 4) float64 — projection matrices, pixels = P X̃ dehomogenised
        (x = column, y = row).  Finite, with an invertible left 3 × 3 block.
    frames : (V,) int64 — the frame (image) number of each camera, all different.

    Build one with :meth:`from_matrices` or :meth:`from_pose`; the constructor
    validates and freezes both arrays.

    Examples
    --------
    >>> P = np.hstack([np.eye(3), [[0.0], [0.0], [2.0]]])
    >>> cams = CameraSet.from_matrices([P, P + [[0, 0, 0, 1], [0] * 4, [0] * 4]], frames=[10, 11])
    >>> len(cams), cams.frames.tolist(), cams.centers.round(6).tolist()
    (2, [10, 11], [[0.0, 0.0, -2.0], [-1.0, 0.0, -2.0]])
    """

    matrices: np.ndarray
    frames: np.ndarray

    def __post_init__(self) -> None:
        P = as_float_array("camera matrices", self.matrices)
        if P.ndim == 2:
            P = P[None]
        if P.ndim != 3 or P.shape[1:] != (3, 4) or P.shape[0] == 0:
            raise InvalidInputError(f"camera matrices must have shape (V, 3, 4) with V >= 1; got {P.shape}")
        frames = np.asarray(self.frames)
        if frames.shape != (P.shape[0],):
            raise InvalidInputError(f"frames must have shape ({P.shape[0]},), one per camera; got {frames.shape}")
        if frames.size and not np.issubdtype(frames.dtype, np.integer):
            as_float = as_float_array("frames", frames)
            if not np.all(np.isfinite(as_float) & (as_float == np.round(as_float))):
                raise InvalidInputError("frames must be integers")
            frames = as_float.astype(np.int64)
        frames = frames.astype(np.int64)
        _, first, counts = np.unique(frames, return_index=True, return_counts=True)
        if np.any(counts > 1):
            raise InvalidInputError(f"frames must be different; frame {frames[first[counts > 1][0]]} has "
                                    f"{counts.max()} cameras")
        bad = ~np.isfinite(P).all(axis=(1, 2))
        if bad.any():
            v = int(np.flatnonzero(bad)[0])
            raise InvalidInputError(f"camera matrix of frame {frames[v]} must be finite; got {P[v].tolist()}")
        scale = projection_scale_problem(P)
        if scale is not None:
            raise InvalidInputError(f"camera matrix of frame {frames[scale[0]]} {scale[1]}")
        with np.errstate(all="ignore"):
            sv = np.linalg.svd(P[:, :, :3], compute_uv=False)
            singular = ~(np.isfinite(sv).all(axis=1) & (sv[:, -1] > _SINGULAR_RATIO * sv[:, 0]))
        if singular.any():
            v = int(np.flatnonzero(singular)[0])
            raise InvalidInputError(
                f"camera matrix of frame {frames[v]} is not a camera: its left 3x3 block is not invertible "
                f"(singular values {np.array2string(sv[v], precision=3)})"
            )
        object.__setattr__(self, "matrices", _readonly(P))
        object.__setattr__(self, "frames", _readonly(frames))

    @classmethod
    def from_matrices(cls, matrices: object, frames: object | None = None) -> CameraSet:
        """Cameras from (V, 3, 4) projection matrices; frames default to 0..V-1."""
        P = as_float_array("camera matrices", matrices)
        V = P.shape[0] if P.ndim == 3 else 1
        return cls(P, np.arange(V) if frames is None else np.asarray(frames))

    @classmethod
    def from_pose(cls, intrinsics: object, rotations: object, translations: object,
                  frames: object | None = None) -> CameraSet:
        """Cameras P = K [R | t] from intrinsics, rotations and translations (x_cam = R X + t).

        Parameters
        ----------
        intrinsics : (3, 3) or (V, 3, 3) — K (:func:`.camera_checks.intrinsics_problem` says what is refused).
        rotations : (V, 3, 3) — rotations.  Matrices orthonormal only to rounding (|R Rᵀ - I| up to
            1e-3, e.g. printed to six digits) are replaced by the nearest rotation with a
            :class:`~kalmansfm.KalmanSfmWarning` saying how far they were off; a reflection
            (det R = -1) or a matrix farther from orthonormal is refused.
        translations : (V, 3).
        frames : (V,) int, optional — default 0..V-1.

        Examples
        --------
        >>> cams = CameraSet.from_pose(np.diag([500.0, 500.0, 1.0]), np.eye(3)[None], [[0.0, 0.0, 4.0]])
        >>> cams.matrices[0, :, 3].tolist()
        [0.0, 0.0, 4.0]
        """
        R = as_float_array("rotations", rotations)
        t = as_float_array("translations", translations)
        if R.ndim == 2:
            R = R[None]
        if t.ndim == 1:
            t = t[None]
        if R.ndim != 3 or R.shape[1:] != (3, 3):
            raise InvalidInputError(f"rotations must have shape (V, 3, 3); got {R.shape}")
        V = R.shape[0]
        if t.shape != (V, 3):
            raise InvalidInputError(f"translations must have shape ({V}, 3); got {t.shape}")
        K = np.broadcast_to(as_float_array("intrinsics", intrinsics), (V, 3, 3)) if np.ndim(intrinsics) == 2 else \
            as_float_array("intrinsics", intrinsics)
        if K.shape != (V, 3, 3):
            raise InvalidInputError(f"intrinsics must have shape (3, 3) or ({V}, 3, 3); got {K.shape}")
        for name, a in (("intrinsics", K), ("rotations", R), ("translations", t)):
            check_finite(name, a)
        problem = intrinsics_problem(K)
        if problem is not None:
            raise InvalidInputError(f"intrinsics[{problem[0]}]: {problem[1]}")
        checked = check_rotations(R)
        if checked.not_rotations.any():
            v = int(np.argmax(checked.not_rotations))
            raise InvalidInputError(f"rotations[{v}] is not a rotation: R Rᵀ differs from I by "
                                    f"{checked.deviations[v]:.3g} (more than the {ROTATION_ROUNDED:g} that rounding "
                                    f"explains)")
        if checked.reflections.any():
            v = int(np.argmax(checked.reflections))
            raise InvalidInputError(f"rotations[{v}] is a reflection (det R = -1), not a rotation")
        if checked.warning() is not None:
            warnings.warn(f"rotations: {checked.warning()}", KalmanSfmWarning, stacklevel=2)
        R = checked.rotations
        with np.errstate(all="ignore"):
            P = np.einsum("vij,vjk->vik", K, np.concatenate([R, t[:, :, None]], axis=2))
        return cls(P, np.arange(V) if frames is None else np.asarray(frames))

    def __len__(self) -> int:
        return int(self.matrices.shape[0])

    @property
    def centers(self) -> np.ndarray:
        """(V, 3) camera centres C with P (C, 1) = 0."""
        M, p4 = self.matrices[:, :, :3], self.matrices[:, :, 3]
        return -np.linalg.solve(M, p4[..., None])[..., 0]

    def decompose(self) -> CameraPose:
        """K, R, t and the signed scale of every camera (:func:`decompose_projection`)."""
        return decompose_projection(self.matrices)

    def subset(self, views: object) -> CameraSet:
        """The cameras at the given view indices (or boolean mask), in that order."""
        index = np.arange(len(self))[np.asarray(views)]
        return CameraSet(self.matrices[index], self.frames[index])

    def view_of(self, frames: object) -> np.ndarray:
        """View index of each frame number; -1 where no camera has that frame.

        Examples
        --------
        >>> cams = CameraSet.from_matrices(np.stack([np.eye(3, 4)] * 2), frames=[4, 7])
        >>> cams.view_of([7, 5, 4]).tolist()
        [1, -1, 0]
        """
        f = np.asarray(frames, dtype=np.int64)
        order = np.argsort(self.frames)
        sorted_frames = self.frames[order]
        pos = np.clip(np.searchsorted(sorted_frames, f), 0, len(self) - 1)
        return np.where(sorted_frames[pos] == f, order[pos], -1)


def _matrices(cameras: CameraSet | np.ndarray) -> np.ndarray:
    """The (V, 3, 4) matrices of a CameraSet or of an array already validated by the caller."""
    if isinstance(cameras, CameraSet):
        return cameras.matrices
    P = np.asarray(cameras, dtype=np.float64)
    return P[None] if P.ndim == 2 else P


@dataclass(frozen=True)
class CameraPose:
    """P = scale · K [R | t] for each of V cameras.

    Attributes
    ----------
    intrinsics : (V, 3, 3) — K, upper triangular, positive diagonal, K[2, 2] = 1.
    rotations : (V, 3, 3) — R, det +1.
    translations : (V, 3) — t, with x_cam = R X + t.
    scales : (V,) — the signed λ; a negative λ (det of the left block < 0) is how a
        mirrored frame or a sign flip of P shows up.
    """

    intrinsics: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    scales: np.ndarray

    @property
    def centers(self) -> np.ndarray:
        """(V, 3) camera centres -Rᵀ t."""
        return camera_centres(self.rotations, self.translations)


def decompose_projection(matrices: object) -> CameraPose:
    """Factor projection matrices as P = λ K [R | t] by a batched RQ decomposition.

    K is upper triangular with a positive diagonal and K[2, 2] = 1, R is a
    rotation (det +1), λ is signed: sign(λ) = sign(det M), M the left 3 × 3 block.

    Parameters
    ----------
    matrices : (3, 4) or (V, 3, 4), each with an invertible left 3 × 3 block.

    Returns
    -------
    CameraPose

    Examples
    --------
    >>> K = np.array([[700.0, 2.0, 300.0], [0.0, 650.0, 200.0], [0.0, 0.0, 1.0]])
    >>> c, s = np.cos(0.4), np.sin(0.4)
    >>> R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    >>> P = -3.0 * K @ np.hstack([R, [[1.0], [2.0], [3.0]]])
    >>> pose = decompose_projection(P)
    >>> bool(np.allclose(pose.intrinsics[0], K) and np.allclose(pose.rotations[0], R))
    True
    >>> pose.scales.round(9).tolist(), pose.translations.round(9).tolist()
    ([-3.0], [[1.0, 2.0, 3.0]])
    """
    P = as_float_array("matrices", matrices)
    if P.ndim == 2:
        P = P[None]
    if P.ndim != 3 or P.shape[1:] != (3, 4):
        raise InvalidInputError(f"matrices must have shape (3, 4) or (V, 3, 4); got {P.shape}")
    check_finite("matrices", P)
    M = P[:, :, :3]
    flip = np.eye(3)[::-1]
    # RQ via QR: (flip M)ᵀ = Q U  ⇒  M = (flip Uᵀ flip)(flip Qᵀ), the first factor upper triangular.
    Q, U = np.linalg.qr(np.swapaxes(flip @ M, 1, 2))
    K = flip @ np.swapaxes(U, 1, 2) @ flip
    R = flip @ np.swapaxes(Q, 1, 2)
    # Make K's diagonal positive: K R = (K D)(D R) with D = diag(sign(diag K)).
    d = np.sign(np.diagonal(K, axis1=1, axis2=2))
    d = np.where(d == 0, 1.0, d)
    K = K * d[:, None, :]
    R = d[:, :, None] * R
    # A reflection left in R goes into the scale: K R = (-1) K (-R), det(-R) = +1.
    sign = np.sign(np.linalg.det(R))
    R = sign[:, None, None] * R
    scale = sign * K[:, 2, 2]
    K = K / K[:, 2:3, 2:3]
    # p4 = λ K t
    t = np.linalg.solve(K, P[:, :, 3][..., None])[..., 0] / scale[:, None]
    return CameraPose(K, R, t, scale)


@dataclass(frozen=True)
class Projection:
    """Points projected into V cameras.

    Attributes
    ----------
    pixels : (V, N, 2) — (x, y) = (u / w, v / w); NaN where w = 0.
    projective_depths : (V, N) — w, the third homogeneous coordinate.
    depths : (V, N) — the depth in the camera frame, w / λ (P = λ K [R | t]); its
        sign, compared with the scene's orientation, says in front (same) or behind.
    """

    pixels: np.ndarray
    projective_depths: np.ndarray
    depths: np.ndarray


def _depth_scales(P: np.ndarray) -> np.ndarray:
    """(V,) λ of P = λ K [R | t]: |λ| = |m3| (the third row of M), sign(λ) = sign(det M)."""
    M = P[:, :, :3]
    return np.sign(np.linalg.det(M)) * np.linalg.norm(M[:, 2], axis=1)


def project_points(cameras: CameraSet | np.ndarray, points: object) -> Projection:
    """Project N points into every camera.

    Parameters
    ----------
    cameras : CameraSet, or (V, 3, 4) projection matrices.
    points : (N, 3) world points (NaN rows project to NaN).

    Returns
    -------
    Projection

    Examples
    --------
    >>> cams = CameraSet.from_pose(np.diag([100.0, 100.0, 1.0]), np.eye(3)[None], [[0.0, 0.0, 2.0]])
    >>> p = project_points(cams, [[0.5, -0.2, 3.0]])
    >>> p.pixels.tolist(), p.depths.tolist()
    ([[[10.0, -4.0]]], [[5.0]])
    """
    P = _matrices(cameras)
    X = as_float_array("points", points)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InvalidInputError(f"points must have shape (N, 3); got {X.shape}")
    uvw = _camera_coordinates(P, X)
    w = uvw[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        pixels = uvw[..., :2] / np.where(w == 0, np.nan, w)[..., None]
    return Projection(pixels, w, w / _depth_scales(P)[:, None])


def _project_jacobian(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (V, N, 2), projective depth w (V, N) and d pixel / d X (V, N, 2, 3); no validation."""
    return _with_jacobian(P[:, None, :, :3], _camera_coordinates(P, X))


def project_each(matrices: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project points by their own cameras, with the Jacobian; shapes broadcast, nothing is validated.

    The kernel behind :func:`project_points` and :func:`projection_jacobians`, for
    callers that pair every point with a different 3 × 4 matrix (e.g. a camera
    composed with a per-point change of coordinates such as inverse depth).  The
    left block of the matrices may be singular here.

    Parameters
    ----------
    matrices : (..., 3, 4) float64.
    points : (..., 3) float64, broadcast against ``matrices[..., 0, :3]``.

    Returns
    -------
    pixels : (..., 2) — (u / w, v / w).
    projective_depths : (..., ) — w.
    jacobians : (..., 2, 3) — d(x, y)/dX = [m1 - x m3; m2 - y m3] / w.

    Examples
    --------
    >>> P = np.hstack([np.diag([100.0, 100.0, 1.0]), np.zeros((3, 1))])
    >>> pix, w, J = project_each(P, np.array([1.0, 2.0, 4.0]))
    >>> pix.tolist(), float(w), J[0].tolist()
    ([25.0, 50.0], 4.0, [25.0, 0.0, -6.25])
    """
    M = matrices[..., :3]
    return _with_jacobian(M, (M @ points[..., None])[..., 0] + matrices[..., 3])


def _camera_coordinates(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(V, N, 3) P [X; 1] of every point in every camera, by one batched matrix product (not einsum: 20× faster)."""
    return X @ np.swapaxes(P[:, :, :3], 1, 2) + P[:, None, :, 3]


def _with_jacobian(M: np.ndarray, uvw: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels, projective depths and d pixel / dX from the homogeneous projections ``uvw`` = M X + m4."""
    w = uvw[..., 2]
    w_safe = np.where(w == 0, np.finfo(float).tiny, w)
    with np.errstate(over="ignore", invalid="ignore"):  # a point on a camera's principal plane projects to inf
        pix = uvw[..., :2] / w_safe[..., None]
        # d(u/w)/dX = (m1 - x m3) / w, d(v/w)/dX = (m2 - y m3) / w
        J = (M[..., :2, :] - pix[..., :, None] * M[..., 2:3, :]) / w_safe[..., None, None]
    return pix, w, J


def projection_jacobians(cameras: CameraSet | np.ndarray, points: object) -> np.ndarray:
    """The 2 × 3 Jacobian of each point's pixel position with respect to the point.

    d(x, y)/dX = [m1 - x m3; m2 - y m3] / w, with m_i the rows of the left 3 × 3
    block of P and w the projective depth.

    Parameters
    ----------
    cameras : CameraSet, or (V, 3, 4) projection matrices.
    points : (N, 3).

    Returns
    -------
    (V, N, 2, 3)

    Examples
    --------
    >>> cams = CameraSet.from_pose(np.diag([100.0, 100.0, 1.0]), np.eye(3)[None], [[0.0, 0.0, 0.0]])
    >>> projection_jacobians(cams, [[0.0, 0.0, 2.0]])[0, 0].tolist()
    [[50.0, 0.0, 0.0], [0.0, 50.0, 0.0]]
    """
    X = as_float_array("points", points)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InvalidInputError(f"points must have shape (N, 3); got {X.shape}")
    return _project_jacobian(_matrices(cameras), X)[2]


def scene_orientation(depths: object, visible: object | None = None) -> int:
    """+1 if most observed depths are positive (points in front), -1 if most are negative (mirrored frame).

    Parameters
    ----------
    depths : (V, N) — :attr:`Projection.depths` of triangulated points.
    visible : (V, N) bool, optional — which entries are observations (default: finite depths).

    Examples
    --------
    >>> scene_orientation([[-2.0, -3.0, 1.0]])
    -1
    """
    d = np.asarray(depths, dtype=float)
    use = np.isfinite(d) if visible is None else np.asarray(visible, dtype=bool) & np.isfinite(d)
    positive = np.count_nonzero(use & (d > 0))
    negative = np.count_nonzero(use & (d < 0))
    return -1 if negative > positive else 1


def _cameras_and_observations(cameras: CameraSet | np.ndarray, observations: object, visible: object | None
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked (V, 3, 4) matrices, (V, N, 2) observations and the (V, N) mask of those used."""
    P = cameras.matrices if isinstance(cameras, CameraSet) else CameraSet.from_matrices(cameras).matrices
    V = P.shape[0]
    obs = as_float_array("observations", observations)
    if obs.ndim != 3 or obs.shape[0] != V or obs.shape[2] != 2:
        raise InvalidInputError(f"observations must have shape ({V} views, N points, 2) as (x, y); got {obs.shape}")
    seen = np.isfinite(obs).all(axis=2)
    if visible is not None:
        vis = np.asarray(visible, dtype=bool)
        if vis.shape != seen.shape:
            raise InvalidInputError(f"visible must have shape {seen.shape} like observations[..., 0]; got {vis.shape}")
        seen &= vis
    return P, obs, seen


@dataclass(frozen=True)
class Triangulation:
    """Linear (DLT) triangulation of N points.

    Attributes
    ----------
    points : (N, 3) — NaN where the status is not OK or BEHIND_CAMERA.
    depths : (V, N) — each point's depth in every camera (:class:`Projection`).
    views : (N,) int — observations used.
    status : (N,) int8 — :class:`PointStatus` values; BEHIND_CAMERA when a view
        that sees the point has a depth against the orientation (points kept).
    orientation : +1 or -1 — the scene orientation used for cheirality.
    """

    points: np.ndarray
    depths: np.ndarray
    views: np.ndarray
    status: np.ndarray
    orientation: int


def _normalising_transforms(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Well-scaled cameras K⁻¹ P / |λ| and the world similarity X = centre + scale · Y they act on."""
    pose = decompose_projection(P)
    Pn = np.linalg.solve(pose.intrinsics, P) / np.abs(pose.scales)[:, None, None]
    C = pose.centers
    centre = C.mean(axis=0)
    spread = float(np.sqrt(np.mean(np.sum((C - centre) ** 2, axis=1))))
    scale = spread if spread > 0 else 1.0
    # Pn [centre + s Y; 1] = s [Pn_M  (Pn_M centre + p4) / s] [Y; 1]
    Pw = np.concatenate([Pn[:, :, :3], ((Pn[:, :, :3] @ centre + Pn[:, :, 3]) / scale)[..., None]], axis=2)
    return Pw, pose.intrinsics, np.append(centre, scale)


def triangulate_points(cameras: CameraSet | np.ndarray, observations: object, visible: object | None = None,
                       orientation: int | None = None) -> Triangulation:
    """Linear triangulation of many points from many views (homogeneous DLT, one 4 × 4 eigenproblem per point).

    Each observation (x, y) of camera P gives the rows x p3 - p1 and y p3 - p2 of
    A X̃ = 0; X̃ is the eigenvector of AᵀA with the smallest eigenvalue.  Pixels
    are first mapped by K⁻¹ and the world is centred and scaled on the camera
    centres, so the system is well conditioned; AᵀA is accumulated over the
    visible views of every point at once.

    Parameters
    ----------
    cameras : CameraSet, or (V, 3, 4) projection matrices.
    observations : (V, N, 2) — (x, y), NaN where unseen.
    visible : (V, N) bool, optional — further restricts the observations used
        (e.g. outliers removed).
    orientation : +1, -1 or None — the scene orientation for the cheirality status;
        None takes the sign most observed depths agree on (:func:`scene_orientation`).

    Returns
    -------
    Triangulation

    Examples
    --------
    Two cameras 1 apart along x, a point 4 in front:

    >>> cams = CameraSet.from_pose(np.diag([500.0, 500.0, 1.0]), np.stack([np.eye(3)] * 2),
    ...                            [[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    >>> obs = project_points(cams, [[0.3, 0.1, 4.0], [0.0, 0.0, 1.0]]).pixels
    >>> obs[1, 1] = np.nan
    >>> tri = triangulate_points(cams, obs)
    >>> tri.points[0].round(9).tolist(), [PointStatus(s).label for s in tri.status]
    ([0.3, 0.1, 4.0], ['ok', 'too_few_views'])
    """
    P, obs, seen = _cameras_and_observations(cameras, observations, visible)
    V, N = seen.shape
    Pw, K, world = _normalising_transforms(P)
    # normalised image points K⁻¹ (x, y, 1)
    xh = np.concatenate([np.where(seen[..., None], obs, 0.0), np.ones((V, N, 1))], axis=2)
    xn = xh @ np.swapaxes(np.linalg.inv(K), 1, 2)
    xn = xn[..., :2] / xn[..., 2:3]
    # rows a = x p3 - p1, b = y p3 - p2 of every visible view, then AᵀA = Σ a aᵀ + b bᵀ
    rows = xn[..., :, None] * Pw[:, None, 2:3, :] - Pw[:, None, :2, :]  # (V, N, 2, 4)
    rows = rows / np.linalg.norm(rows, axis=-1, keepdims=True)
    rows = np.where(seen[..., None, None], rows, 0.0)
    AtA, _ = jacobian_products(rows)
    evals, evecs = np.linalg.eigh(AtA)
    h = evecs[:, :, 0]
    views = seen.sum(axis=0)
    status = np.full(N, PointStatus.OK, dtype=np.int8)
    unique = evals[:, 1] > _DLT_RANK_RATIO * np.maximum(evals[:, 3], np.finfo(float).tiny)
    finite_point = np.abs(h[:, 3]) > _AT_INFINITY * np.linalg.norm(h[:, :3], axis=1)
    status[~(unique & finite_point)] = PointStatus.DEGENERATE
    status[views < 2] = PointStatus.TOO_FEW_VIEWS
    with np.errstate(divide="ignore", invalid="ignore"):
        X = world[:3] + world[3] * h[:, :3] / h[:, 3:4]
    X[status != PointStatus.OK] = np.nan
    depths = project_points(P, X).depths
    if orientation is None:
        orientation = scene_orientation(depths, seen)
    behind = np.any(seen & (depths * orientation <= 0), axis=0) & (status == PointStatus.OK)
    status[behind] = PointStatus.BEHIND_CAMERA
    return Triangulation(X, depths, views, status, int(orientation))
