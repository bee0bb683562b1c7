"""The batch method: per point, maximum likelihood over all its views with leave-one-out outlier rejection."""

from __future__ import annotations

import numpy as np

from ..geometry.batched import inverse3, jacobian_products
from ..geometry.pinhole import project_each, project_points, projection_jacobians, triangulate_points
from ..geometry.refinement import LISTED_FILL, refine_points
from ..points import PointStatus
from .chunks import Chunk, ChunkResult, concat_history, finish
from .weighted import refine_weighted

__all__ = ["run_batch"]


def _quadratic_form(J: np.ndarray, N_inv: np.ndarray, r: np.ndarray) -> np.ndarray:
    """rᵀ (I - J N⁻¹ Jᵀ)⁻¹ r for stacks of 2 × 3 J, 3 × 3 N⁻¹ and 2-vectors r; NaN where I - J N⁻¹ Jᵀ is singular."""
    A = np.eye(2) - J @ N_inv @ np.swapaxes(J, -1, -2)
    det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    # 2 × 2 inverse quadratic form: rᵀ adj(A) r / det(A)
    q = (A[..., 1, 1] * r[..., 0] ** 2 - (A[..., 0, 1] + A[..., 1, 0]) * r[..., 0] * r[..., 1]
         + A[..., 0, 0] * r[..., 1] ** 2)
    return q / np.where(det > 1e-12, det, np.nan)


def _leave_one_out(P: np.ndarray, X: np.ndarray, r: np.ndarray, mask: np.ndarray, listed: bool | None = None
                   ) -> np.ndarray:
    """(V, n) rᵀ (I - J N⁻¹ Jᵀ)⁻¹ r of each used observation (unit σ), NaN elsewhere.

    On the dense arrays, or on the list of the used observations (``listed``; None: when fewer than
    :data:`~kalmansfm.structure.geometry.refinement.LISTED_FILL` of them are used) — the same to rounding.
    """
    if listed is None:
        listed = mask.sum() < LISTED_FILL * mask.size
    if not listed:
        J = np.where(mask[..., None, None], projection_jacobians(P, X), 0.0)
        return np.where(mask, _quadratic_form(J, inverse3(jacobian_products(J)[0]), r), np.nan)
    out = np.full(mask.shape, np.nan)
    point, view = np.nonzero(mask.T)  # sorted by point
    if point.size:
        _, _, J = project_each(P[view], X[point])
        first = np.r_[True, point[1:] != point[:-1]]
        normal = np.add.reduceat(np.swapaxes(J, 1, 2) @ J, np.flatnonzero(first), axis=0)
        out[view, point] = _quadratic_form(J, inverse3(normal)[np.cumsum(first) - 1], r[view, point])
    return out


def _batch_fit(P: np.ndarray, obs: np.ndarray, mask: np.ndarray, start: np.ndarray | None, orientation: int):
    if start is None:
        start = triangulate_points(P, obs, visible=mask, orientation=orientation).points
    return refine_points(P, obs, start, visible=mask, pixel_std=1.0, orientation=orientation)


def _weighted_fit(job: Chunk, precision: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    g, obs = job.geometry, job.observations
    start = triangulate_points(g.P, obs, visible=precision > 0, orientation=g.orientation).points
    fit = refine_weighted(g.P, g.depth_sign, obs, start, precision, g.orientation)
    ok = fit.status == PointStatus.OK
    C = np.full(fit.normal.shape, np.nan)
    C[ok] = np.linalg.inv(fit.normal[ok])
    return fit.points, C, fit.status, fit.residuals


def _run_weighted(job: Chunk) -> ChunkResult:
    """A reweighted pass: the observations' own standard deviations, no outlier test (the caller decided)."""
    obs = job.observations
    V = obs.shape[0]
    seen = np.isfinite(obs).all(axis=2)
    with np.errstate(divide="ignore"):
        precision = np.where(seen & np.isfinite(job.scales), 1.0 / job.scales**2, 0.0)
    X, C, status, residuals = _weighted_fit(job, precision)
    mask = (precision > 0) & (status == PointStatus.OK)[None]
    hist = None
    if job.history:
        parts = []
        counts = np.cumsum(mask, axis=0)
        for v in range(1, V):
            pts = np.flatnonzero(mask[v] & (counts[v] >= 2))
            if pts.size == 0:
                continue
            prefix = np.where(np.arange(V)[:, None] <= v, precision[:, pts], 0.0)
            sub = Chunk(job.method, job.geometry, obs[:, pts], job.sigma, job.gate2, job.gate1, False)
            hx, hc, hs, _ = _weighted_fit(sub, prefix)
            good = hs == PointStatus.OK
            parts.append((v, pts[good], hx[good], hc[good]))
        hist = concat_history(parts)
    return finish(X, C, status, mask, np.zeros((V, obs.shape[1]), dtype=bool), residuals, hist)


def run_batch(job: Chunk) -> ChunkResult:
    if job.scales is not None:
        return _run_weighted(job)
    g, obs = job.geometry, job.observations
    V, n, _ = obs.shape
    mask = np.isfinite(obs).all(axis=2)
    rejected = np.zeros((V, n), dtype=bool)
    fit = _batch_fit(g.P, obs, mask, None, g.orientation)
    X, C, status, r = fit.points.copy(), fit.covariances.copy(), fit.status.copy(), fit.residuals.copy()
    todo = np.flatnonzero(status == PointStatus.OK)
    for _ in range(V):
        if todo.size == 0:
            break
        m = mask[:, todo]
        views = m.sum(axis=0)
        loo = _leave_one_out(g.P, X[todo], np.nan_to_num(r[:, todo]), m & (views >= 3)) / job.sigma**2
        worst = np.argmax(np.where(np.isfinite(loo), loo, -np.inf), axis=0)
        worst_d2 = loo[worst, np.arange(todo.size)]
        drop_one = (views >= 3) & (worst_d2 > job.gate2)
        cost = np.nansum(r[:, todo] ** 2, axis=(0, 2)) / job.sigma**2
        drop_pair = (views == 2) & (cost > job.gate1)
        mask[worst[drop_one], todo[drop_one]] = False
        rejected[worst[drop_one], todo[drop_one]] = True
        pair_pts = todo[drop_pair]
        rejected[:, pair_pts] |= mask[:, pair_pts]
        mask[:, pair_pts] = False
        changed = todo[drop_one | drop_pair]
        if changed.size == 0:
            break
        refit = _batch_fit(g.P, obs[:, changed], mask[:, changed], X[changed], g.orientation)
        X[changed], C[changed], status[changed] = refit.points, refit.covariances, refit.status
        r[:, changed] = refit.residuals
        todo = changed[refit.status == PointStatus.OK]
    hist = None
    if job.history:
        hist_parts = []
        counts = np.cumsum(mask, axis=0)
        for v in range(1, V):
            pts = np.flatnonzero(mask[v] & (counts[v] >= 2) & (status == PointStatus.OK))
            if pts.size == 0:
                continue
            prefix = mask[:, pts] & (np.arange(V)[:, None] <= v)
            f = _batch_fit(g.P, obs[:, pts], prefix, X[pts], g.orientation)
            hist_parts.append((v, pts, f.points, f.covariances))
        hist = concat_history(hist_parts)
    # residuals of every observation (rejected included) at the final estimate
    ok = status == PointStatus.OK
    pix = project_points(g.P, np.where(ok[:, None], X, 0.0)).pixels
    residuals = np.where(np.isfinite(obs).all(axis=2)[..., None], obs - pix, np.nan)
    return finish(X, C, status, mask, rejected, residuals, hist)
