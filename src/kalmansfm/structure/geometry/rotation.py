"""Rotations as vectors: the exponential and logarithm maps of SO(3), batched.

A rotation vector ω (radians, axis × angle) stands for the rotation
exp([ω]×), where [ω]× is the cross-product matrix ([ω]× v = ω × v).
"""

from __future__ import annotations

import numpy as np

__all__ = ["cross_matrix", "rotation_exp", "rotation_log"]

# Below this angle (radians) the series expansions replace sin θ / θ and (1 - cos θ) / θ².
_SMALL_ANGLE = 1e-6


def cross_matrix(vectors: np.ndarray) -> np.ndarray:
    """(..., 3) vectors → (..., 3, 3) cross-product matrices [v]×, with [v]× u = v × u.

    Examples
    --------
    >>> cross_matrix(np.array([1.0, 2.0, 3.0])) @ np.array([0.0, 0.0, 1.0])
    array([ 2., -1.,  0.])
    """
    v = np.asarray(vectors, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def rotation_exp(vectors: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: (..., 3) rotation vectors → (..., 3, 3) rotation matrices.

    exp([ω]×) = I + (sin θ / θ) [ω]× + ((1 - cos θ) / θ²) [ω]×², θ = |ω|.

    Examples
    --------
    >>> R = rotation_exp(np.array([0.0, 0.0, np.pi / 2]))
    >>> (R @ [1.0, 0.0, 0.0]).round(12).tolist()
    [0.0, 1.0, 0.0]
    """
    v = np.asarray(vectors, dtype=np.float64)
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    K = cross_matrix(v)
    return np.eye(3) + a * K + b * (K @ K)


def rotation_log(rotations: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices → (..., 3) rotation vectors with angle in [0, π].

    Examples
    --------
    >>> w = np.array([[0.1, -0.2, 0.3], [0.0, 3.0, 0.0]])
    >>> np.allclose(rotation_log(rotation_exp(w)), w)
    True
    """
    R = np.asarray(rotations, dtype=np.float64)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    axis_sin = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1) / 2
    small = theta < _SMALL_ANGLE
    near_pi = theta > np.pi - 1e-3
    factor = np.where(small, 1.0 + theta**2 / 6.0, theta / np.where(small, 1.0, np.sin(np.where(near_pi, 1.0, theta))))
    out = axis_sin * factor[..., None]
    if np.any(near_pi):
        # sin θ ≈ 0: read the axis off the symmetric part, (R + Rᵀ) / 2 = cos θ I + (1 - cos θ) a aᵀ,
        # its sign off the antisymmetric part (sin θ a)
        c = cos[near_pi][..., None, None]
        B = ((R[near_pi] + np.swapaxes(R[near_pi], -1, -2)) / 2.0 - c * np.eye(3)) / (1.0 - c)
        col = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        a = np.take_along_axis(B, col[..., None, None].repeat(3, -1), axis=-2)[..., 0, :]
        a /= np.linalg.norm(a, axis=-1, keepdims=True)
        sign = np.where(np.sum(a * axis_sin[near_pi], axis=-1) < 0, -1.0, 1.0)
        out[near_pi] = a * sign[..., None] * theta[near_pi][..., None]
    return out
