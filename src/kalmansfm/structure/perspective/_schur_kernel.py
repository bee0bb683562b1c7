"""Compiled (numba) kernel of the bundle adjustment's Schur complement: the camera–camera coupling W V⁻¹ Wᵀ.

With the points eliminated, the reduced camera matrix is S = U - Σ_p W_p V_p⁻¹ W_pᵀ, where point p
couples every pair (a, b) of its observations: the 6 × 6 block Y_a W_bᵀ (Y_a = W_a V_p⁻¹) is added at
the cameras (camera of a, camera of b).  The observations are walked point by point, only the
pairs that exist are formed (a dense (6n × 3m) product touches the 80–90 % of zeros of cameras that
do not see a point), and each block is computed once for a ≤ b and added with its transpose
(Y_b W_aᵀ = (Y_a W_bᵀ)ᵀ because V_p⁻¹ is symmetric).  The NumPy reference is
:func:`kalmansfm.structure.perspective.bundle.coupling_reference` (a dense product).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..._compilation import watch_compilation

watch_compilation()  # one line on stderr when the kernel is compiled (not when it is loaded from the cache)


@njit(cache=True)
def schur_coupling_kernel(order: np.ndarray, starts: np.ndarray, cameras: np.ndarray, left: np.ndarray,
                          right: np.ndarray, camera_count: int) -> np.ndarray:
    """(6n, 6n) Σ over pairs (a, b) of observations of one point of left_a right_bᵀ at (camera a, camera b).

    ``order`` lists the observations grouped by point, point p owning ``order[starts[p]:starts[p + 1]]``;
    ``left``, ``right`` are (N, 6, 3) with left_a right_bᵀ = (left_b right_aᵀ)ᵀ (the symmetric case).
    """
    out = np.zeros((camera_count, 6, camera_count, 6))
    for p in range(starts.shape[0] - 1):
        for ia in range(starts[p], starts[p + 1]):
            a = order[ia]
            ca = cameras[a]
            for ib in range(ia, starts[p + 1]):
                b = order[ib]
                cb = cameras[b]
                for i in range(6):
                    for j in range(6):
                        s = left[a, i, 0] * right[b, j, 0] + left[a, i, 1] * right[b, j, 1] \
                            + left[a, i, 2] * right[b, j, 2]
                        out[ca, i, cb, j] += s
                        if ib != ia:
                            out[cb, j, ca, i] += s
    return out.reshape(6 * camera_count, 6 * camera_count)
