"""Maximum-likelihood points for known cameras: Levenberg–Marquardt-damped Gauss–Newton, batched over points.

Each point is refined independently on the sum of its squared reprojection errors.  The normal
equations of every point are sums over the views that see it; they are formed either on the dense
(views × points) arrays, or on the list of observations when the points are seen by few of the views
(a long sequence, a wide-baseline image set: on dinoRing's front end a track is seen by 7 of 48 views,
and the list is 4× faster).  Both give the same sums to rounding; the dense form is the reference the
tests hold the listed one to.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..._validation import as_float_array, check_positive
from ...errors import InvalidInputError
from ..points import PointStatus
from .batched import jacobian_products, solve3
from .pinhole import (
    CameraSet,
    _cameras_and_observations,
    _depth_scales,
    _project_jacobian,
    _with_jacobian,
    project_points,
    scene_orientation,
)

__all__ = ["LISTED_FILL", "RefinedPoints", "refine_points"]

# Normal matrices with a condition number above this carry no usable covariance.
_MAX_CONDITION = 1e12
# Iterate while the squared Gauss–Newton step, in standard deviations, exceeds this fraction of
# (1 + cost); a point is "converged" once it is below _CONVERGED.
_STOP_DECREMENT = 1e-18
_CONVERGED = 1e-6
#: Below this share of (view, point) pairs observed, the normal equations are summed over the list of
#: observations instead of the dense arrays (break-even measured at about 0.45 for 48 views).
LISTED_FILL = 0.3


@dataclass(frozen=True)
class RefinedPoints:
    """Points refined by Gauss–Newton on the reprojection error, with their covariances.

    Attributes
    ----------
    points : (N, 3) — the minimiser of Σ |x_obs - π(P X)|² over the visible views;
        NaN where the status is not OK.
    covariances : (N, 3, 3) — σ² (JᵀJ)⁻¹ at the solution (J the stacked 2 × 3
        Jacobians of the visible views); NaN where the status is not OK.
    residuals : (V, N, 2) — observed minus projected pixels at the solution, NaN
        where not visible (or the point failed).
    reprojection_rms : (N,) — RMS of the 2-D residual lengths over visible views.
    views : (N,) int — observations used.
    status : (N,) int8 — :class:`PointStatus` values.
    converged : (N,) bool — the remaining Gauss–Newton step is below 10⁻³ standard deviations.
    pixel_std : float — the σ the covariances were scaled with.
    orientation : +1 or -1 — the scene orientation used for cheirality.
    """

    points: np.ndarray
    covariances: np.ndarray
    residuals: np.ndarray
    reprojection_rms: np.ndarray
    views: np.ndarray
    status: np.ndarray
    converged: np.ndarray
    pixel_std: float
    orientation: int


class _DenseEquations:
    """Normal equations on the (V, N) arrays; the residuals kept as (V, N, 2), 0 where unused."""

    def __init__(self, P: np.ndarray, obs: np.ndarray, seen: np.ndarray, orientation: int) -> None:
        self.P, self.obs, self.seen, self.orientation = P, obs, seen, orientation
        self.residuals = np.zeros(obs.shape)

    def evaluate(self, points: np.ndarray, X: np.ndarray, keep: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Residuals, JᵀJ (n, 3, 3), Jᵀr (n, 3), cost (n,) and cheirality (n,) of the points ``points`` at X."""
        seen = self.seen[:, points]
        pix, w, J = _project_jacobian(self.P, X)
        r = np.where(seen[..., None], self.obs[:, points] - pix, 0.0)
        J = np.where(seen[..., None, None], J, 0.0)
        JtJ, Jtr = jacobian_products(J, r)
        cost = np.einsum("vna,vna->n", r, r)
        depth_sign = np.sign(_depth_scales(self.P))[:, None] * w
        in_front = ~np.any(seen & (depth_sign * self.orientation <= 0), axis=0)
        if keep:
            self.residuals[:, points] = r
        return r, JtJ, Jtr, cost, in_front

    def accept(self, points: np.ndarray, residuals: np.ndarray, ok: np.ndarray) -> None:
        """Keep the residuals of ``points[ok]``, evaluated by :meth:`evaluate` on ``points``."""
        self.residuals[:, points[ok]] = residuals[:, ok]

    def dense_residuals(self) -> np.ndarray:
        return self.residuals


class _ListedEquations:
    """Normal equations summed over the list of observations, grouped by point (``np.add.reduceat``)."""

    def __init__(self, P: np.ndarray, obs: np.ndarray, seen: np.ndarray, orientation: int) -> None:
        self.P, self.orientation, self.shape = P, orientation, obs.shape
        self.point, self.view = np.nonzero(seen.T)  # sorted by point
        self.pixels = obs[self.view, self.point]
        self.depth_sign = np.sign(_depth_scales(P))[self.view]
        self.residuals = np.zeros((len(self.point), 2))

    def _rows(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The observations of ``points`` (sorted, each seen at least once), each one's position in
        ``points`` and the first observation of each point."""
        member = np.zeros(self.shape[1], bool)
        member[points] = True
        rows = np.flatnonzero(member[self.point])
        position = np.searchsorted(points, self.point[rows])
        starts = np.flatnonzero(np.r_[True, position[1:] != position[:-1]])
        if len(starts) != len(points):  # a point without observations would shift every sum after it
            raise ValueError(f"{len(points) - len(starts)} of the points to refine have no observation")
        return rows, position, starts

    def evaluate(self, points: np.ndarray, X: np.ndarray, keep: bool = False
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        rows, position, starts = self._rows(points)
        M = self.P[self.view[rows]]
        uvw = (M[:, :, :3] @ X[position][:, :, None])[:, :, 0] + M[:, :, 3]
        pix, w, J = _with_jacobian(M[:, :, :3], uvw)
        r = self.pixels[rows] - pix
        Jt = np.swapaxes(J, 1, 2)
        behind = self.depth_sign[rows] * w * self.orientation <= 0
        terms = np.concatenate([(Jt @ J).reshape(-1, 9), (Jt @ r[:, :, None])[:, :, 0],
                                np.einsum("ma,ma->m", r, r)[:, None], behind[:, None]], axis=1)
        sums = np.add.reduceat(terms, starts, axis=0)
        if keep:
            self.residuals[rows] = r
        return (rows, r), sums[:, :9].reshape(-1, 3, 3), sums[:, 9:12], sums[:, 12], sums[:, 13] == 0

    def accept(self, points: np.ndarray, residuals: tuple[np.ndarray, np.ndarray], ok: np.ndarray) -> None:
        rows, r = residuals
        take = ok[np.searchsorted(points, self.point[rows])]
        self.residuals[rows[take]] = r[take]

    def dense_residuals(self) -> np.ndarray:
        out = np.zeros(self.shape)
        out[self.view, self.point] = self.residuals
        return out


def refine_points(cameras: CameraSet | np.ndarray, observations: object, initial: object,
                  visible: object | None = None, pixel_std: float = 1.0, orientation: int | None = None,
                  max_iterations: int = 50, listed: bool | None = None) -> RefinedPoints:
    """Maximum-likelihood points for known cameras: Levenberg–Marquardt-damped Gauss–Newton, batched over points.

    Minimises, for each point independently, the sum of squared reprojection
    errors over its visible views.  Steps must lower the cost and keep the point
    on the oriented side of every camera that sees it; the damping adapts per
    point, and points leave the iteration as soon as their step is negligible.

    Parameters
    ----------
    cameras : CameraSet, or (V, 3, 4) projection matrices.
    observations : (V, N, 2) — (x, y), NaN where unseen.
    initial : (N, 3) — starting points (e.g. :func:`~.pinhole.triangulate_points`); NaN rows
        are reported DEGENERATE.
    visible : (V, N) bool, optional — further restricts the observations used.
    pixel_std : float > 0 — σ of the image noise in pixels; the covariance is σ² (JᵀJ)⁻¹.
    orientation : +1, -1 or None — scene orientation; None: the sign most
        observations' depths at ``initial`` agree on.
    max_iterations : int — per point.
    listed : sum the normal equations over the list of observations (True) or the dense arrays
        (False); None: listed when fewer than :data:`LISTED_FILL` of the (view, point) pairs are used.
        The result is the same to rounding.

    Returns
    -------
    RefinedPoints

    Examples
    --------
    >>> cams = CameraSet.from_pose(np.diag([500.0, 500.0, 1.0]), np.stack([np.eye(3)] * 3),
    ...                            [[0.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]])
    >>> X = np.array([[0.3, 0.1, 4.0]])
    >>> obs = project_points(cams, X).pixels + [[[0.5, 0.0]], [[0.0, 0.0]], [[0.0, 0.0]]]
    >>> fit = refine_points(cams, obs, X, pixel_std=0.5)
    >>> fit.status.tolist(), fit.converged.tolist(), bool(np.all(np.diagonal(fit.covariances[0]) > 0))
    ([0], [True], True)
    >>> float(fit.reprojection_rms[0]) < 0.5
    True
    """
    P, obs, seen = _cameras_and_observations(cameras, observations, visible)
    V, N = seen.shape
    X = as_float_array("initial", initial).copy()
    if X.shape != (N, 3):
        raise InvalidInputError(f"initial must have shape ({N}, 3), one point per observation column; got {X.shape}")
    sigma = check_positive("pixel_std", pixel_std, "pixels")
    views = seen.sum(axis=0)
    status = np.full(N, PointStatus.OK, dtype=np.int8)
    status[~np.isfinite(X).all(axis=1)] = PointStatus.DEGENERATE
    status[views < 2] = PointStatus.TOO_FEW_VIEWS
    live = status == PointStatus.OK
    X[~live] = 0.0
    if orientation is None:
        orientation = scene_orientation(project_points(P, X).depths, seen & live)
    seen_live = seen & live
    if listed is None:
        listed = seen_live.sum() < LISTED_FILL * seen_live.size
    equations = (_ListedEquations if listed else _DenseEquations)(P, obs, seen_live, orientation)
    JtJ, Jtr = np.zeros((N, 3, 3)), np.zeros((N, 3))
    cost, in_front = np.zeros(N), np.ones(N, dtype=bool)
    L = np.flatnonzero(live)
    if L.size:
        _, JtJ[L], Jtr[L], cost[L], in_front[L] = equations.evaluate(L, X[L], keep=True)
    lam = np.full(N, 1e-4)
    stalled = np.zeros(N, dtype=bool)
    active = live.copy()
    for _ in range(max_iterations):
        gn = solve3(JtJ, Jtr)
        # gᵀ N⁻¹ g / σ²: the squared Gauss–Newton step measured in standard deviations
        decrement = np.einsum("ni,ni->n", Jtr, gn) / sigma**2
        active &= (decrement >= _STOP_DECREMENT * (1.0 + cost / sigma**2)) & (lam < 1e12)
        active &= ~((decrement < _CONVERGED) & stalled)
        if not active.any():
            break
        a = np.flatnonzero(active)
        Na = JtJ[a]
        # Levenberg–Marquardt: (N + λ diag N) δ = Jᵀ r
        damped = Na + lam[a, None, None] * np.diagonal(Na, axis1=1, axis2=2)[:, :, None] * np.eye(3)
        X_new = X[a] + solve3(damped, Jtr[a])
        r_new, JtJ_new, Jtr_new, cost_new, front_new = equations.evaluate(a, X_new)
        ok = front_new & np.isfinite(cost_new) & (cost_new <= cost[a])
        acc = a[ok]
        equations.accept(a, r_new, ok)
        X[acc], JtJ[acc], Jtr[acc] = X_new[ok], JtJ_new[ok], Jtr_new[ok]
        stalled[a] = ~ok | (cost[a] - cost_new <= 1e-14 * cost[a])
        cost[acc] = cost_new[ok]
        in_front[acc] = True
        lam[a] = np.where(ok, np.maximum(lam[a] / 10.0, 1e-12), np.minimum(lam[a] * 10.0, 1e12))
    decrement = np.einsum("ni,ni->n", Jtr, solve3(JtJ, Jtr)) / sigma**2
    evals = np.linalg.eigvalsh(JtJ)
    conditioned = np.isfinite(evals).all(axis=1) & (evals[:, 0] > evals[:, 2] / _MAX_CONDITION)
    status[live & ~conditioned] = PointStatus.DEGENERATE
    status[live & conditioned & ~in_front] = PointStatus.BEHIND_CAMERA
    ok = status == PointStatus.OK
    cov = np.full((N, 3, 3), np.nan)
    cov[ok] = sigma**2 * np.linalg.inv(JtJ[ok])
    X[~ok] = np.nan
    residuals = np.where((seen & ok)[..., None], equations.dense_residuals(), np.nan)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.where(ok, cost, np.nan) / np.maximum(views, 1))
    return RefinedPoints(X, cov, residuals, rms, views, status, ok & (decrement < _CONVERGED), sigma,
                         int(orientation))
