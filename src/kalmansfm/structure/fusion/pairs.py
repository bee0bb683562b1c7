"""The report's pair method: consecutive two-view midpoint triangulations fused as independent measurements."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..._validation import check_positive
from ...estimation.kalman import kalman_update
from ..geometry.pinhole import CameraSet, project_points
from ..geometry.triangulation import triangulate_midpoint
from ..points import PointStatus
from .chunks import Chunk, ChunkResult, concat_history, finish
from .blocks import dense_block, orientation_of_blocks
from .inputs import validate_inputs
from .inverse_depth import ViewGeometry, view_geometry
from .settings import check_orientation

__all__ = ["PairTriangulations", "pair_triangulations", "run_pairs"]


def _pair_triangulation(g: ViewGeometry, a: int, v: int, xa: np.ndarray, xv: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The report's midpoint triangulation of views (a, v) in world coordinates, unit-σ pixel covariance.

    Works in the oriented camera frames o (R X + t) (depth positive in front, also for a
    mirrored scene) and normalised image coordinates K⁻¹ x̃ (focal 1); the Jacobian
    with respect to them is chained to pixels through the linear map K⁻¹.
    """
    o = g.orientation
    R_rel = g.R[v] @ g.R[a].T
    # x'_v = R_rel x'_a - b with x' = o (R X + t): b = o (R_rel t_a - t_v)
    b = o * (R_rel @ g.t[a] - g.t[v])
    if not np.any(np.abs(b) > 1e-12 * (1.0 + np.abs(g.t[a]).max())):
        nan = np.full((xa.shape[0], 3), np.nan)
        return nan, np.full((xa.shape[0], 3, 3), np.nan), np.full(xa.shape[0], PointStatus.DEGENERATE)

    def normalised(K_inv: np.ndarray, x: np.ndarray) -> np.ndarray:
        h = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1) @ K_inv.T
        return h[:, :2] / h[:, 2:3]

    tri = triangulate_midpoint(normalised(g.K_inv[a], xa), normalised(g.K_inv[v], xv), R_rel, b, 1.0)
    # d(normalised)/d(pixel) is the upper-left 2 × 2 block of K⁻¹ (K⁻¹ has last row (0, 0, 1))
    D = np.zeros((4, 4))
    D[:2, :2], D[2:, 2:] = g.K_inv[a][:2, :2], g.K_inv[v][:2, :2]
    J = tri.jacobians @ D
    cov_cam = J @ np.swapaxes(J, 1, 2)
    # back to the world: X = o R_vᵀ (p - o t_v) ... with o² = 1: X = R_vᵀ (o p - t_v)
    X = (o * tri.points - g.t[v]) @ g.R[v]
    cov = g.R[v].T @ cov_cam @ g.R[v]
    return X, cov, tri.status


def pair_table(g: ViewGeometry, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every point's consecutive observations (u, v) triangulated, stored at view v (unit-σ covariances).

    Returns points (V, n, 3), covariances (V, n, 3, 3), status (V, n) and the pair's first
    view (V, n), -1 and ``PointStatus.TOO_FEW_VIEWS`` where no pair ends at v.
    """
    V, n, _ = obs.shape
    seen_all = np.isfinite(obs).all(axis=2)
    X = np.full((V, n, 3), np.nan)
    C = np.full((V, n, 3, 3), np.nan)
    status = np.full((V, n), PointStatus.TOO_FEW_VIEWS, dtype=np.int8)
    previous = np.full((V, n), -1)
    last = np.full(n, -1)
    for v in range(V):
        idx = np.flatnonzero(seen_all[v] & (last >= 0))
        for a in np.unique(last[idx]):  # one group per earlier view, not per point
            sel = idx[last[idx] == a]
            X[v, sel], C[v, sel], status[v, sel] = _pair_triangulation(g, int(a), v, obs[a, sel], obs[v, sel])
            previous[v, sel] = a
        last[seen_all[v]] = v
    return X, C, status, previous


@dataclass(frozen=True)
class PairTriangulations:
    """The report's two-view measurements: each point's consecutive observations triangulated.

    Attributes
    ----------
    points : (V, N, 3) — at view v, the midpoint triangulation (report eqs. 29-31) of the
        point's previous observation and its observation in v, world coordinates; NaN where
        no pair ends at v or the rays are parallel.
    covariances : (V, N, 3, 3) — first-order covariance (eq. 34) at pixel noise σ.
    status : (V, N) int8 — :class:`~.points.PointStatus`: ``OK``, ``DEGENERATE`` (parallel rays),
        ``BEHIND_CAMERA`` or ``TOO_FEW_VIEWS`` (no pair ends at v).
    previous : (V, N) int — the view of the pair's first observation, -1 where none.
    """

    points: np.ndarray
    covariances: np.ndarray
    status: np.ndarray
    previous: np.ndarray


def pair_triangulations(observations: object, cameras: CameraSet | object, pixel_std: float = 1.0,
                        orientation: int | None = None) -> PairTriangulations:
    """Triangulate every point's consecutive observations, two views at a time (the ``pairs`` method's measurements).

    Parameters
    ----------
    observations : (V, N, 2) pixels, NaN where unseen (views in the order of ``cameras``).
    cameras : CameraSet or (V, 3, 4).
    pixel_std : float > 0 — σ of the pixel noise the covariances are scaled with.
    orientation : +1, -1 or None (from the data, as :func:`fuse`).

    Examples
    --------
    >>> from kalmansfm.structure.geometry.pinhole import project_points
    >>> cams = CameraSet.from_pose(np.diag([500.0, 500.0, 1.0]), np.stack([np.eye(3)] * 3),
    ...                            [[0.0, 0, 0], [-1.0, 0, 0], [-2.0, 0, 0]])
    >>> pairs = pair_triangulations(project_points(cams, [[0.5, 0.2, 10.0]]).pixels, cams)
    >>> pairs.points[2, 0].round(6).tolist(), pairs.previous[:, 0].tolist()
    ([0.5, 0.2, 10.0], [-1, 0, 1])
    """
    cams, obs = validate_inputs(observations, cameras)
    sigma = check_positive("pixel_std", pixel_std, "pixels")
    g = view_geometry(cams.matrices, orientation_of_blocks(cams, [dense_block(obs)]) if orientation is None else check_orientation(orientation))
    X, C, status, previous = pair_table(g, obs)
    return PairTriangulations(X, C * sigma**2, status, previous)


def run_pairs(job: Chunk) -> ChunkResult:
    g, obs = job.geometry, job.observations
    V, n, _ = obs.shape
    seen_all = np.isfinite(obs).all(axis=2)
    p, R, st, previous = pair_table(g, obs)
    finite = np.isfinite(R).all(axis=(2, 3))
    # a singular first-order covariance (e.g. a point on the baseline) cannot be fused
    usable = ((st == PointStatus.OK) | (st == PointStatus.BEHIND_CAMERA)) & finite
    usable &= np.linalg.eigvalsh(np.where(usable[..., None, None], R, np.eye(3)))[..., 0] > 0
    x = np.full((n, 3), np.nan)
    P = np.full((n, 3, 3), np.nan)
    started = np.zeros(n, dtype=bool)
    used = np.zeros((V, n), dtype=bool)
    hist = []
    for v in range(V):
        sel = np.flatnonzero(usable[v])
        if sel.size == 0:
            continue
        first = ~started[sel]
        s0, s1 = sel[first], sel[~first]
        x[s0], P[s0] = p[v, s0], R[v, s0]
        if s1.size:
            # the report's fusion: the pair triangulation is a direct measurement of the point
            res = kalman_update(x[s1], P[s1], p[v, s1], np.eye(3), R[v, s1])
            x[s1], P[s1] = res.x, res.P
        started[sel] = True
        used[previous[v, sel], sel] = used[v, sel] = True
        if job.history:
            hist.append((v, sel, x[sel].copy(), P[sel].copy()))
    status = np.full(n, PointStatus.OK, dtype=np.int8)
    views = seen_all.sum(axis=0)
    status[~started] = np.where(views[~started] >= 2, PointStatus.DEGENERATE, PointStatus.TOO_FEW_VIEWS)
    depth = project_points(g.P, np.where(started[:, None], x, 0.0))
    status[np.any(used & (depth.depths * g.orientation <= 0), axis=0) & started] = PointStatus.BEHIND_CAMERA
    residuals = np.where(seen_all[..., None], obs - depth.pixels, np.nan)
    return finish(x, P, status, used, np.zeros((V, n), dtype=bool), residuals,
                   concat_history(hist) if job.history else None)
