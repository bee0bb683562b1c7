"""Weighted maximum-likelihood points for known cameras: the batch method's reweighted passes.

Each observation carries a precision π (its weight relative to 1/σ², from a fitted noise
model; 0 = not used).  Per point, Levenberg–Marquardt-damped Gauss–Newton minimises
Σ_v π_v |x_v − proj(P_v X)|² from a start, keeping every step on the oriented side of the
cameras that see it — :func:`~kalmansfm.structure.geometry.refinement.refine_points` with
weights.  The unit-σ covariance is (Σ π Jᵀ J)⁻¹.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.batched import solve3
from ..geometry.pinhole import project_each
from ..points import PointStatus

__all__ = ["WeightedPoints", "refine_weighted"]

# Steps stop when the squared Gauss–Newton step is below this (in unit-σ standard deviations).
_CONVERGED = 1e-10
# A point whose weighted normal matrix is more ill-conditioned than this is not determined.
_MAX_CONDITION = 1e12


@dataclass(frozen=True)
class WeightedPoints:
    """Weighted least-squares points.

    Attributes
    ----------
    points : (n, 3); NaN where the status is not OK.
    normal : (n, 3, 3) Σ π Jᵀ J at the solution (its inverse is the unit-σ covariance).
    residuals : (V, n, 2) observed − projected for every observation (used or not); NaN
        where not seen or the point failed.
    status : (n,) int8 :class:`~kalmansfm.structure.PointStatus`.
    """

    points: np.ndarray
    normal: np.ndarray
    residuals: np.ndarray
    status: np.ndarray


def _normal(P: np.ndarray, depth_sign: np.ndarray, X: np.ndarray, obs: np.ndarray, precision: np.ndarray,
            orientation: int):
    pix, w, J = project_each(P[:, None], X[None])
    r = np.where(precision[..., None] > 0, obs - pix, 0.0)
    Jw = J * precision[..., None, None]
    N = np.einsum("vnai,vnaj->nij", Jw, J)
    g = np.einsum("vnai,vna->ni", Jw, r)
    cost = np.einsum("vn,vna,vna->n", precision, r, r)
    front = ~np.any((precision > 0) & (depth_sign[:, None] * w * orientation <= 0), axis=0)
    return N, g, cost, front


def refine_weighted(P: np.ndarray, depth_sign: np.ndarray, observations: np.ndarray, start: np.ndarray,
                    precision: np.ndarray, orientation: int, max_iterations: int = 30) -> WeightedPoints:
    """Refine points from ``start`` by weighted Gauss–Newton (batched over points; no validation).

    Parameters
    ----------
    P : (V, 3, 4) cameras; depth_sign : (V,) the sign of λ in P = λ K [R | t].
    observations : (V, n, 2) pixels, NaN where unseen.
    start : (n, 3) starting points (NaN rows are DEGENERATE).
    precision : (V, n) weights relative to 1/σ² (0 where unused; NaN observations count as 0).
    orientation : +1 or -1.

    Examples
    --------
    Two cameras 1 apart, a point 4 in front, its second observation down-weighted:

    >>> P = np.stack([np.hstack([np.diag([500.0, 500, 1]), [[0.0], [0], [0]]]),
    ...               np.hstack([np.diag([500.0, 500, 1]), [[-500.0], [0], [0]]])])
    >>> X = np.array([[0.3, 0.1, 4.0]])
    >>> obs = project_each(P[:, None], X[None])[0] + [[[0.5, 0.0]], [[0.0, 0.0]]]
    >>> fit = refine_weighted(P, np.ones(2), obs, X, np.array([[1.0], [4.0]]), 1)
    >>> fit.status.tolist(), bool(np.abs(fit.residuals[1]).max() < np.abs(fit.residuals[0]).max())
    ([0], True)
    """
    V, n, _ = observations.shape
    seen = np.isfinite(observations).all(axis=2)
    pi = np.where(seen, np.nan_to_num(precision), 0.0)
    obs = np.where(seen[..., None], observations, 0.0)
    X = np.array(start, dtype=np.float64)
    status = np.full(n, PointStatus.OK, dtype=np.int8)
    status[(pi > 0).sum(axis=0) < 2] = PointStatus.TOO_FEW_VIEWS
    status[~np.isfinite(X).all(axis=1) & (status == PointStatus.OK)] = PointStatus.DEGENERATE
    live = status == PointStatus.OK
    X[~live] = 0.0
    pi[:, ~live] = 0.0
    N, g, cost, front = _normal(P, depth_sign, X, obs, pi, orientation)
    lam = np.full(n, 1e-4)
    active = live.copy()
    for _ in range(max_iterations):
        step = solve3(N, g)
        decrement = np.einsum("ni,ni->n", g, step)
        active &= (decrement > _CONVERGED) & (lam < 1e12)
        if not active.any():
            break
        a = np.flatnonzero(active)
        damped = N[a] + lam[a, None, None] * np.diagonal(N[a], axis1=1, axis2=2)[:, :, None] * np.eye(3)
        X_new = X[a] + solve3(damped, g[a])
        N_new, g_new, cost_new, front_new = _normal(P, depth_sign, X_new, obs[:, a], pi[:, a], orientation)
        better = front_new & np.isfinite(cost_new) & (cost_new <= cost[a])
        acc = a[better]
        X[acc], N[acc], g[acc], cost[acc], front[acc] = X_new[better], N_new[better], g_new[better], \
            cost_new[better], True
        lam[a] = np.where(better, np.maximum(lam[a] / 10.0, 1e-12), np.minimum(lam[a] * 10.0, 1e12))
    evals = np.linalg.eigvalsh(N)
    conditioned = np.isfinite(evals).all(axis=1) & (evals[:, 0] > evals[:, 2] / _MAX_CONDITION)
    status[live & ~conditioned] = PointStatus.DEGENERATE
    status[live & conditioned & ~front] = PointStatus.BEHIND_CAMERA
    ok = status == PointStatus.OK
    X[~ok] = np.nan
    pix = project_each(P[:, None], np.where(ok[:, None], X, 0.0)[None])[0]
    residuals = np.where((seen & ok[None])[..., None], observations - pix, np.nan)
    return WeightedPoints(X, N, residuals, status)
