"""Two-view triangulation with known motion, and its first-order covariance.

Section 7 of Thomas & Oliensis, *Fusing Structure by Kalman Filtering*
(``004_cd423c68da9c9743.txt``, equations 29-34).

Conventions
-----------
* Camera frame: X to the right of the image (image x), Y along image y, Z the
  optical axis pointing into the scene.  A point (X, Y, Z) is seen at image
  coordinates ``(x, y) = (f X / Z, f Y / Z)``, measured from the principal point
  in the same unit as the focal length ``f`` (pixels).  The *image vector* of
  (x, y) is ``I = (x, y, f)``, a direction of the ray through the point.
* Motion from the first ("left", earlier) camera to the second ("right",
  later) camera: a point's coordinates change as

      X_right = R X_left - b                      (report eq. 23, x_k = C x_{k-1} - b)

  so the left camera's centre lies at ``-b`` in the right frame, and ``b`` is the
  vector from the left centre to the right centre expressed in the right frame.
* The triangulated point is expressed in the **right** camera's frame.

Method (eqs. 29-31).  With ``l = R I_left`` (the left ray turned into the right
frame) and ``r = I_right``, the left ray is ``-b + beta l`` and the right ray
``alpha r``.  The point of the right ray closest to the left ray is

    p = alpha r,   alpha = ((b x l) . (l x r)) / |l x r|^2        (eqs. 30-31)

which does not depend on the lengths of ``l`` and ``r``.  Its covariance under
independent zero-mean image noise is the first-order propagation (eq. 34)

    Cov(p) = sum_c (dp/du_c)(dp/du_c)^T sigma_c^2 = J diag(sigma^2) J^T

over the four image coordinates ``u = (x_left, y_left, x_right, y_right)``;
the Jacobian ``J`` (3 x 4) is analytic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InvalidInputError
from ..._validation import as_float_array, check_finite, check_positive
from ..points import PointStatus

__all__ = [
    "TriangulationResult",
    "triangulate_midpoint",
]

# Status codes are PointStatus members (the one point status of the package):
#   OK             the point was triangulated in front of the right camera;
#   DEGENERATE     the two rays are parallel (no parallax): the point is NaN;
#   BEHIND_CAMERA  triangulated, but behind the right camera (alpha <= 0): the numbers are
#                  returned as computed, they are not a physically possible landmark;
#   TOO_FEW_VIEWS  (pair tables of fusion.pairs) no pair could be formed: the point is not
#                  seen in one of the two images.

# Rays whose directions make an angle smaller than this (radians) are treated as parallel.
_PARALLEL_SINE = 1e-12
# With a pixel noise given: rays whose parallax does not fix the depth — its standard deviation above this
# fraction of the depth, so that three standard deviations reach infinity — count as parallel too.
_NO_DEPTH = 1.0 / 3.0


@dataclass(frozen=True)
class TriangulationResult:
    """Triangulated points in the right (second) camera frame, with first-order uncertainty.

    Attributes
    ----------
    points : (L, 3) or (3,) — the point on the right ray closest to the left ray;
        NaN where the rays are parallel.
    covariances : (L, 3, 3) or (3, 3) — first-order covariance J diag(σ²) Jᵀ (eq. 34);
        NaN where the rays are parallel; zeros when no noise was given.
    jacobians : (L, 3, 4) or (3, 4) — dp/d(x_left, y_left, x_right, y_right).
    depth_scale : (L,) or () — alpha in p = alpha (x_right, y_right, f); p's depth is alpha f.
    status : (L,) or () int8 — a :class:`~.points.PointStatus` value: ``OK``,
        ``DEGENERATE`` (parallel rays; with a pixel noise given, also rays whose parallax is
        within the noise: the depth's standard deviation above a third of the depth) or
        ``BEHIND_CAMERA``.
    """

    points: np.ndarray
    covariances: np.ndarray
    jacobians: np.ndarray
    depth_scale: np.ndarray
    status: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """True where the point was triangulated in front of the right camera."""
        return self.status == PointStatus.OK

    @property
    def standard_deviations(self) -> np.ndarray:
        """Per-axis standard deviations, shaped like ``points``."""
        return np.sqrt(np.diagonal(self.covariances, axis1=-2, axis2=-1))


def _image_noise_variances(pixel_std: object, L: int) -> np.ndarray:
    """(L, 4) variances of (x_left, y_left, x_right, y_right) from a scalar, (4,) or (L, 4) std."""
    if pixel_std is None:
        return np.zeros((L, 4))
    s = as_float_array("pixel_std", pixel_std)
    if s.ndim == 0 or s.shape == (4,) or s.shape == (L, 4):
        s = np.broadcast_to(s, (L, 4))
    else:
        raise InvalidInputError(
            f"pixel_std must be a scalar, (4,) per coordinate (x_left, y_left, x_right, y_right) "
            f"or ({L}, 4); got shape {s.shape}"
        )
    check_finite("pixel_std", s)
    if np.any(s < 0):
        raise InvalidInputError(f"pixel_std must be >= 0 (a standard deviation); got {s.min()}")
    return s**2


def check_focal(focal: object) -> float:
    """Return ``focal`` as a float or raise unless it is finite and > 0 (pixels)."""
    return check_positive("focal", focal, "pixels")


def check_motion(rotation: object, translation: object, *, what: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Validate one rotation (3, 3) and translation (3,) with a non-zero baseline."""
    R = as_float_array(f"rotation{what}", rotation)
    b = as_float_array(f"translation{what}", translation)
    if R.shape != (3, 3):
        raise InvalidInputError(f"rotation{what} must have shape (3, 3); got {R.shape}")
    if b.shape != (3,):
        raise InvalidInputError(f"translation{what} must have shape (3,); got {b.shape}")
    check_finite(f"rotation{what}", R)
    check_finite(f"translation{what}", b)
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise InvalidInputError(f"rotation{what} must be a rotation matrix (RRᵀ = I, det +1)")
    if not np.any(b):
        raise InvalidInputError(
            f"translation{what} is zero: with no baseline the two rays start at the same centre and "
            "the depth cannot be triangulated"
        )
    return R, b


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.cross(a, b, axis=-1)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i->...", a, b)


def triangulate_midpoint(
    left_points: object,
    right_points: object,
    rotation: object,
    translation: object,
    focal: float,
    pixel_std: object | None = None,
) -> TriangulationResult:
    """Triangulate landmarks seen in two images taken with known relative motion.

    Parameters
    ----------
    left_points, right_points : (L, 2) or (2,) float
        Image coordinates (x, y) in the first and second image, from the principal
        point, in the unit of ``focal``.  The same landmark in the same row.
    rotation : (3, 3)
        R with X_right = R X_left - b.
    translation : (3,)
        b; the vector from the first camera centre to the second, in the second
        camera's frame.  Must be non-zero.
    focal : float
        Focal length f > 0 (pixels).
    pixel_std : float, (4,) or (L, 4), optional
        Standard deviation of the noise in (x_left, y_left, x_right, y_right); by
        default no noise (zero covariance).

    Returns
    -------
    TriangulationResult
        Points in the right camera's frame.  For ``(L, 2)`` input a landmark whose
        rays are parallel (with ``pixel_std``: parallel within the noise, the depth's
        standard deviation above a third of the depth) gets NaN and ``status ==
        PointStatus.DEGENERATE``; a single landmark given as ``(2,)`` raises instead.

    Raises
    ------
    InvalidInputError
        Wrong shapes, non-finite input, f <= 0, negative noise, zero baseline, a
        non-rotation, or parallel rays for a single ``(2,)`` landmark.

    Examples
    --------
    A point 10 m ahead, the camera moving 1 m sideways (X_right = X_left - b):

    >>> import numpy as np
    >>> f = 500.0
    >>> X_left = np.array([0.0, 0.0, 10.0]); b = np.array([1.0, 0.0, 0.0])
    >>> X_right = X_left - b
    >>> r = triangulate_midpoint(f * X_left[:2] / X_left[2], f * X_right[:2] / X_right[2],
    ...                          np.eye(3), b, f, pixel_std=1.0)
    >>> r.points.round(6)
    array([-1.,  0., 10.])
    >>> r.standard_deviations.round(3)
    array([0.02 , 0.02 , 0.283])
    """
    f = check_focal(focal)
    R, b = check_motion(rotation, translation)
    left = as_float_array("left_points", left_points)
    right = as_float_array("right_points", right_points)
    single = left.ndim == 1
    if left.shape[-1:] != (2,) or left.ndim not in (1, 2):
        raise InvalidInputError(f"left_points must have shape (L, 2) or (2,) as (x, y); got {left.shape}")
    if right.shape != left.shape:
        raise InvalidInputError(f"right_points must have the shape of left_points {left.shape}; got {right.shape}")
    check_finite("left_points", left)
    check_finite("right_points", right)
    left2 = left.reshape(-1, 2)
    right2 = right.reshape(-1, 2)
    L = left2.shape[0]
    variances = _image_noise_variances(pixel_std, L)

    ones = np.full((L, 1), f)
    # l = R I_l (eq. 33, the left image vector reckoned in the right frame), r = I_r (eq. 32).
    l = np.concatenate([left2, ones], axis=1) @ R.T
    r = np.concatenate([right2, ones], axis=1)
    n = _cross(l, r)  # l x r, normal to both rays
    q = _dot(n, n)  # |l x r|^2
    bl = _cross(np.broadcast_to(b, l.shape), l)  # b x l
    s = _dot(bl, n)  # (b x l) . (l x r)
    parallel = q <= (_PARALLEL_SINE**2) * _dot(l, l) * _dot(r, r)
    if single and parallel[0]:
        raise InvalidInputError(
            "the two rays are parallel (no parallax between the images); the point cannot be triangulated"
        )
    q_safe = np.where(parallel, 1.0, q)
    # eq. 30: alpha = (b x l).(l x r) / |l x r|^2 ; eq. 31: p = alpha r
    alpha = s / q_safe
    p = alpha[:, None] * r

    # Derivatives of l and r with respect to u = (x_l, y_l, x_r, y_r): (L, 4, 3).
    dl = np.zeros((L, 4, 3))
    dl[:, 0] = R[:, 0]
    dl[:, 1] = R[:, 1]
    dr = np.zeros((L, 4, 3))
    dr[:, 2, 0] = 1.0
    dr[:, 3, 1] = 1.0
    # dn = dl x r + l x dr ; ds = (b x dl).n + (b x l).dn ; dq = 2 n.dn
    dn = _cross(dl, r[:, None, :]) + _cross(l[:, None, :], dr)
    ds = _dot(_cross(np.broadcast_to(b, dl.shape), dl), n[:, None, :]) + _dot(bl[:, None, :], dn)
    dq = 2.0 * _dot(n[:, None, :], dn)
    # d alpha = (ds q - s dq) / q^2 ; dp = d alpha r + alpha dr
    dalpha = (ds * q_safe[:, None] - s[:, None] * dq) / q_safe[:, None] ** 2
    J = dalpha[:, None, :] * r[:, :, None] + alpha[:, None, None] * np.swapaxes(dr, 1, 2)
    # eq. 34: Cov(p) = sum_c J[:, c] J[:, c]^T sigma_c^2
    cov = np.einsum("lic,lc,ljc->lij", J, variances, J)

    if pixel_std is not None:
        # the depth's standard deviation along the right ray against the depth: no parallax beyond the noise
        rhat = r / np.linalg.norm(r, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            depth_std = np.sqrt(np.abs(np.einsum("li,lij,lj->l", rhat, cov, rhat)))
            no_depth = ~(depth_std <= _NO_DEPTH * np.abs(alpha) * np.linalg.norm(r, axis=1))
        if single and no_depth[0] and not parallel[0]:
            raise InvalidInputError(
                "the two rays are parallel within the image noise (no significant parallax): the depth is not "
                "determined, the point cannot be triangulated")
        parallel = parallel | (no_depth & np.any(variances > 0, axis=1))
    status = np.where(parallel, PointStatus.DEGENERATE, np.where(alpha > 0, PointStatus.OK, PointStatus.BEHIND_CAMERA))
    status = status.astype(np.int8)
    p[parallel] = np.nan
    J[parallel] = np.nan
    cov[parallel] = np.nan
    alpha = np.where(parallel, np.nan, alpha)
    if single:
        return TriangulationResult(p[0], cov[0], J[0], alpha[0], status[0])
    return TriangulationResult(p, cov, J, alpha, status)
