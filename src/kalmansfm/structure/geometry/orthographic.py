"""Camera rotations from the rows of an orthographic factorization."""

from __future__ import annotations

import numpy as np

__all__ = ["camera_rotation_matrices", "rotation_angle_deg"]


def camera_rotation_matrices(rows: np.ndarray) -> np.ndarray:
    """World → camera rotations from each frame's camera rows.

    Parameters
    ----------
    rows : (F, 2, 3) the rows i_f, j_f of each frame (``Reconstruction.motion``);
        they are normalised, completed with k = i × j and snapped to the nearest
        rotation (the rows are unit length and orthogonal only up to noise).

    Returns
    -------
    (F, 3, 3) rotation matrices (det +1).

    Examples
    --------
    >>> c, s = np.cos(0.3), np.sin(0.3)
    >>> R = camera_rotation_matrices(np.array([[[c, 0, s], [0, 1.02, 0]]]))
    >>> np.allclose(R[0], [[c, 0, s], [0, 1, 0], [-s, 0, c]])
    True
    """
    rows = np.asarray(rows, dtype=np.float64)
    i = rows[..., 0, :] / np.linalg.norm(rows[..., 0, :], axis=-1, keepdims=True)
    j = rows[..., 1, :] / np.linalg.norm(rows[..., 1, :], axis=-1, keepdims=True)
    stacked = np.stack([i, j, np.cross(i, j)], axis=-2)
    # nearest rotation in the Frobenius norm: U Vᵀ with the sign of the last singular vector fixed
    u, _, vt = np.linalg.svd(stacked)
    u[..., :, -1] *= np.linalg.det(u @ vt)[..., None]
    return u @ vt


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle of the rotation taking ``b`` to ``a`` (both (..., 3, 3)), in degrees.

    Examples
    --------
    >>> c, s = np.cos(np.radians(10)), np.sin(np.radians(10))
    >>> float(rotation_angle_deg(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]), np.eye(3))).__round__(9)
    10.0
    """
    cos = (np.trace(a @ np.swapaxes(b, -1, -2), axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
