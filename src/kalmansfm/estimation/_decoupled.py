"""Structure-exploiting kernels for the constant-velocity model (internal).

When F, Q, H, R and P couple only x with vx and y with vy (the constant-velocity
model with diagonal-block noises), the 4-state filter with a 2-vector
measurement splits into two independent 2-state filters with a scalar
measurement.  Each 2×2 covariance block has three unique numbers
(p00 = var(position), p01 = cov(position, velocity), p11 = var(velocity)), and
the x and y blocks are one and the same array while their histories coincide.

Layout (structure of arrays, so every operation is elementwise on (N,) rows):

* ``X`` (4, N): rows x, y, vx, vy;
* ``C`` (B, 3, N) or (B, 3) when all filters share it: B = 1 when the x and y
  blocks are identical, else 2 (x block, y block); rows p00, p01, p11.

The structure tests (:func:`cv_transition_dt`, :func:`axis_blocks`, ...), the
conversions and :class:`DecoupledUpdate` serve the filter's engine, which runs the
compiled kernels of :mod:`._kernels` (or their NumPy twins, :mod:`._numpy_kernels`).
Their textbook NumPy reference, predict then update, is ``tests/reference/decoupled.py``.
"""

from __future__ import annotations

import numpy as np

# The structure tests run on every predict and update: a single 4×4 or 2×2 matrix is compared
# as Python numbers (≈ 1 µs), not with NumPy fancy indexing (≈ 20 µs per call).
_COUPLING = ((0, 1), (0, 3), (2, 1), (2, 3), (1, 0), (1, 2), (3, 0), (3, 2))  # x–y entries of a 4×4 matrix


def cv_transition_dt(F: np.ndarray) -> float | None:
    """dt if F is [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], else None."""
    if F.shape != (4, 4):
        return None
    f = F.tolist()
    dt = f[0][2]
    return float(dt) if f == [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]] else None


def is_position_measurement(H: np.ndarray) -> bool:
    """H = [[1, 0, 0, 0], [0, 1, 0, 0]]: the position is measured."""
    return H.shape == (2, 4) and H.tolist() == [[1, 0, 0, 0], [0, 1, 0, 0]]


def axis_blocks(M: np.ndarray) -> np.ndarray | None:
    """(..., 4, 4) matrix with no x–y coupling → (..., 2, 3) unique entries [[p00, p01, p11] of x, of y]."""
    if M.shape[-2:] != (4, 4):
        return None
    if M.ndim == 2:
        m = M.tolist()
        if any(m[i][j] != 0 for i, j in _COUPLING):
            return None
        return np.array([[m[0][0], m[0][2], m[2][2]], [m[1][1], m[1][3], m[3][3]]], dtype=M.dtype)
    flat = M.reshape(*M.shape[:-2], 16)
    if np.any(flat[..., [4 * i + j for i, j in _COUPLING]] != 0):
        return None
    return flat[..., [0, 2, 10, 5, 7, 15]].reshape(*M.shape[:-2], 2, 3)


def diagonal_noise(R: np.ndarray) -> np.ndarray | None:
    """(..., 2, 2) diagonal R → (..., 2) variances of x and y, else None."""
    if R.shape[-2:] != (2, 2):
        return None
    if R.ndim == 2:
        r = R.tolist()
        return None if r[0][1] != 0 or r[1][0] != 0 else np.array([r[0][0], r[1][1]], dtype=R.dtype)
    if np.any(R[..., 0, 1] != 0) or np.any(R[..., 1, 0] != 0):
        return None
    return np.stack([R[..., 0, 0], R[..., 1, 1]], axis=-1)


def compact_covariance(blocks: np.ndarray) -> np.ndarray:
    """(2, 3) or (N, 2, 3) blocks → C as (B, 3) or (B, 3, N) with B = 1 when x and y blocks agree."""
    if blocks.ndim == 2:
        return blocks[:1].copy() if np.array_equal(blocks[0], blocks[1]) else blocks.copy()
    C = np.ascontiguousarray(np.moveaxis(blocks, 0, -1))  # (2, 3, N)
    return C[:1].copy() if np.array_equal(C[0], C[1]) else C


def dense_covariance(C: np.ndarray, N: int) -> np.ndarray:
    """C (B, 3[, N]) → (N, 4, 4) (or (4, 4) when C is shared)."""
    shared = C.ndim == 2
    blocks = C if C.shape[0] == 2 else np.concatenate([C, C])
    if shared:
        P = np.zeros((4, 4), dtype=C.dtype)
    else:
        P = np.zeros((N, 4, 4), dtype=C.dtype)
        blocks = np.moveaxis(blocks, -1, 0)  # (N, 2, 3)
    for axis, (i, j) in enumerate(((0, 2), (1, 3))):
        p00, p01, p11 = (blocks[..., axis, k] for k in range(3))
        P[..., i, i] = p00
        P[..., i, j] = p01
        P[..., j, i] = p01
        P[..., j, j] = p11
    return P


class DecoupledUpdate:
    """What one decoupled update produced, expanded to the public (N, ...) arrays on access.

    ``C_prior`` is the prior's covariance blocks, or a function that computes them
    (the compiled step keeps the prior virtual until someone asks).  ``Y`` (2, N) is
    z - H x⁻ with 0 or NaN where not measured; ``missing`` (N, 2) says where, or is
    None: then the components where ``Y`` is NaN are the missing ones.
    """

    def __init__(self, C_prior, Y, r, missing, N):
        self._C_prior_source = C_prior
        self._Y = Y
        self._r = r  # (2,) or (2, N) measurement variances of x and y
        self._missing = missing
        self._N = N
        self._cache: dict[str, np.ndarray] = {}

    @property
    def _C_prior(self) -> np.ndarray:
        if callable(self._C_prior_source):
            self._C_prior_source = self._C_prior_source()
        return self._C_prior_source

    @property
    def _measured(self) -> np.ndarray:
        if "measured" not in self._cache:
            self._cache["measured"] = (~np.isnan(self._Y.T) if self._missing is None else ~self._missing)
        return self._cache["measured"]

    def _s(self) -> np.ndarray:
        """(2, 1) or (2, N) innovation variances p00⁻ + r per axis."""
        p00 = self._C_prior[:, 0]
        if p00.shape[0] == 1:
            p00 = np.concatenate([p00, p00])
        p00 = p00 if p00.ndim == 2 else p00[:, None]
        r = self._r if self._r.ndim == 2 else self._r[:, None]
        return p00 + r

    @property
    def measured(self) -> np.ndarray:
        return self._measured

    @property
    def y(self) -> np.ndarray:
        if "y" not in self._cache:
            # with missing None, Y already holds NaN where not measured
            Y = self._Y if self._missing is None else np.where(self._missing.T, np.nan, self._Y)
            self._cache["y"] = Y.T
        return self._cache["y"]

    @property
    def S(self) -> np.ndarray:
        if "S" not in self._cache:
            s = np.broadcast_to(self._s(), (2, self._N)).T
            S = np.zeros((self._N, 2, 2), dtype=s.dtype)
            S[:, 0, 0] = s[:, 0]
            S[:, 1, 1] = s[:, 1]
            self._cache["S"] = S
        return self._cache["S"]

    @property
    def K(self) -> np.ndarray:
        if "K" not in self._cache:
            C = self._C_prior
            s = self._s()
            K = np.zeros((self._N, 4, 2), dtype=s.dtype)
            for axis, (i, j) in enumerate(((0, 2), (1, 3))):
                c = C[axis] if C.shape[0] == 2 else C[0]
                g = np.where(self._measured[:, axis], 1.0 / s[axis], 0.0)
                K[:, i, axis] = c[0] * g
                K[:, j, axis] = c[1] * g
            self._cache["K"] = K
        return self._cache["K"]

    @property
    def nis(self) -> np.ndarray:
        if "nis" not in self._cache:
            s = self._s()
            terms = np.where(self._measured.T, self._Y * self._Y / s, 0.0)
            nis = terms.sum(axis=0)
            nis[~self._measured.any(axis=1)] = np.nan
            self._cache["nis"] = nis
        return self._cache["nis"]

    @property
    def log_likelihood(self) -> np.ndarray:
        if "log_likelihood" not in self._cache:
            s = self._s()
            per_axis = np.where(self._measured.T, np.log(2.0 * np.pi * s) + self._Y * self._Y / s, 0.0)
            ll = -0.5 * per_axis.sum(axis=0)
            ll[~self._measured.any(axis=1)] = np.nan
            self._cache["log_likelihood"] = ll
        return self._cache["log_likelihood"]


def clearly_positive_definite_blocks(P: np.ndarray) -> bool:
    """True when every (4, 4) matrix of the stack P is exactly symmetric, has no x–y coupling and the
    smallest eigenvalue of each of its two 2×2 blocks, at least det / trace, is above 1e-9 of the
    matrix's largest entry (far above the rounding of an eigen-decomposition).

    The tracker hands over such a stack each time tracks end; this test costs a few passes over
    it, where ``check_covariance`` takes an eigen-decomposition per matrix.  False means "not
    shown here", and ``check_covariance`` decides (and words the error).
    """
    if P.ndim != 3 or P.shape[-2:] != (4, 4) or not np.isfinite(P).all():
        return False
    flat = P.reshape(P.shape[0], 16)
    if not np.array_equal(flat[:, [2, 3, 7, 1, 6, 11]], flat[:, [8, 12, 13, 4, 9, 14]]):  # Pᵀ = P
        return False
    blocks = axis_blocks(P)
    if blocks is None:
        return False
    p00, p01, p11 = blocks[..., 0], blocks[..., 1], blocks[..., 2]
    scale = np.abs(flat).max(axis=1)[:, None]
    return bool(np.all(p00 > 0) and np.all(p00 * p11 - p01 * p01 > 1e-9 * scale * (p00 + p11)))
