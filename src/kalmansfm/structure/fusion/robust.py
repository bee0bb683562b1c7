"""Fusion under a fitted noise model: residual statistics, the model's weights and outlier decisions.

After a pass over the data, every observation of a fused point has a residual r (observed
minus projected at the point's estimate) and, when the estimate used it, a leverage
h = π tr(J Σ Jᵀ) (Σ the unit-σ covariance, J the projection's Jacobian, π the observation's
weight): the share of its two coordinates the fit absorbed, so that its residual has
k = 2 − h degrees of freedom (Σ h = 3 per point).  The noise model
(:func:`~kalmansfm.estimation.noise_model.fit_noise_model`) is fitted to (|r|², k), each
track a group with a pooled scale.  The next pass then

* leaves out the observations the model calls outliers: more likely from the uniform
  component than from the core (models with outliers), or beyond the core's
  ``outlier_probability`` quantile (a test of that size under the fitted model);
* weighs every other observation by its precision π — the Student-t's E[w] (iteratively
  reweighted least squares) times the track's pooled scale — i.e. gives it the standard
  deviation σ / √π.

The covariance of a point is then σ² (Σ π Jᵀ J)⁻¹: the Gaussian one given the weights.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy import stats

from ...errors import NotEnoughDataError
from ...estimation.noise_model import (
    NoiseFit,
    SerialCorrelation,
    fit_noise_model,
    fit_serial_correlation,
)
from ..geometry.pinhole import project_each
from ..points import PointStatus
from .chunks import ChunkResult
from .inverse_depth import ViewGeometry

__all__ = ["ObservationResiduals", "Reweighting", "observation_residuals", "reweigh", "serial_correlation"]

# Observations whose leverage is computed together (bounds the temporaries).
_BLOCK = 131_072
# Points whose residuals the serial correlation is fitted to (a sample of the fused ones).
_CORRELATION_SAMPLE = 2_000
# Observations the noise model's parameters are fitted to (a sample of whole tracks beyond this), and the
# multiplier that spreads the sampled tracks over the index range.
_FIT_SAMPLE = 200_000
_SAMPLE_HASH = 2_654_435_761
# Numbers in the serial correlation's moment tables at a time.
_MOMENT_ENTRIES = 20_000_000
# A residual keeps at least this many degrees of freedom (a two-view point leaves 1 for 4 coordinates).
_MIN_DOF = 0.05


@dataclass(frozen=True)
class ObservationResiduals:
    """One entry per observation of a fused point (the points whose status is ``ok``).

    Attributes
    ----------
    view, point : (M,) indices into the (V, N) observation grid.
    squared : (M,) |r|², pixels².
    dof : (M,) degrees of freedom of the residual: 2 − leverage for a used observation, 2 otherwise.
    """

    view: np.ndarray
    point: np.ndarray
    squared: np.ndarray
    dof: np.ndarray


def observation_residuals(g: ViewGeometry, results: list[ChunkResult], slices: list[slice],
                          observations: np.ndarray, scales: np.ndarray | None) -> ObservationResiduals:
    """Every observation's residual at its fused point and its degrees of freedom.

    Observations left out of the pass (outliers, NaN in its input) get their residual too,
    so that the model can take them back.  Leverages come from the unit-σ covariances.
    """
    views, points, squared, dof = [], [], [], []
    for res, chunk in zip(results, slices):
        ok = res.status == PointStatus.OK
        seen = np.isfinite(observations[:, chunk, 0]) & ok[None]
        v, p = np.nonzero(seen)
        s = np.empty(v.size)
        k = np.full(v.size, 2.0)
        used = res.used[v, p]
        for start in range(0, v.size, _BLOCK):
            b = slice(start, start + _BLOCK)
            vb, pb = v[b], p[b]
            cams = g.P[vb] if res.anchors is None else g.Q[res.anchors[pb], vb]
            pix, _, J = project_each(cams, res.points[pb])
            s[b] = np.sum((observations[vb, pb + chunk.start] - pix) ** 2, axis=1)
            h = np.einsum("mai,mij,maj->m", J, res.covariances[pb], J)
            if scales is not None:
                h = h / scales[vb, pb + chunk.start] ** 2
            k[b] = np.where(used[b], np.clip(2.0 - h, _MIN_DOF, 2.0), 2.0)
        good = np.isfinite(s)  # a residual that cannot be computed is no evidence
        views.append(v[good])
        points.append(p[good] + chunk.start)
        squared.append(s[good])
        dof.append(k[good])
    cat = np.concatenate
    return ObservationResiduals(cat(views), cat(points), cat(squared), cat(dof))


@dataclass(frozen=True)
class Reweighting:
    """What the fitted model says about every observation it was fitted to, for the next pass.

    Attributes
    ----------
    fit : the fitted :class:`~kalmansfm.estimation.noise_model.NoiseFit`.
    scales : (M,) each observation's standard deviation relative to σ; NaN where left out.
    rejected : (M,) bool — observations left out as outliers.
    """

    fit: NoiseFit
    scales: np.ndarray
    rejected: np.ndarray


def reweigh(residuals: ObservationResiduals, model: str, outlier_probability: float,
            track_scales: bool = True) -> Reweighting:
    """Fit ``model`` to the residuals (tracks as groups with ``track_scales``) and turn it into weights and rejections."""
    _, track = np.unique(residuals.point, return_inverse=True)
    groups, names = ((track,), ("track",)) if track_scales else ((), ())
    fit_on = np.arange(track.size)
    if track.size > _FIT_SAMPLE:
        # the model's few parameters from a sample of whole tracks; then every observation under them
        keep = (track * _SAMPLE_HASH) % (track.size // _FIT_SAMPLE + 1) == 0
        fit_on = np.flatnonzero(keep)
    _, sample_track = np.unique(track[fit_on], return_inverse=True)
    fit = fit_noise_model(residuals.squared[fit_on], model=model, degrees_of_freedom=residuals.dof[fit_on],
                          groups=(sample_track,) if track_scales else (), group_names=names)
    if fit_on.size < track.size:
        fit = fit_noise_model(residuals.squared, model=model, degrees_of_freedom=residuals.dof, groups=groups,
                              group_names=names, fixed=fit)
    if fit.outlier_share > 0:
        out = fit.outliers
    else:
        # beyond the core's quantile: Λ s / σ² > k F(k, ν) (χ²(k) for a Gaussian core) quantile
        u = fit.group_precision * residuals.squared / fit.sigma**2
        k = residuals.dof
        if outlier_probability >= 1:
            out = np.zeros(u.size, dtype=bool)
        elif np.isfinite(fit.tail):
            out = u > k * stats.f.ppf(outlier_probability, k, fit.tail)
        else:
            out = u > stats.chi2.ppf(outlier_probability, k)
    with np.errstate(divide="ignore"):
        # the estimate weighs by E[w] (Student-t) within a track; the track's scale enters as E[1/λ], its
        # variance with the scale's own uncertainty, so that the covariance does not take it as known
        w = fit.precision / fit.group_precision
        scales = np.where(out, np.nan, np.sqrt(fit.group_variance / w))
    return Reweighting(fit, scales, np.asarray(out, dtype=bool))


def _design(g: ViewGeometry, res: ChunkResult, observations: np.ndarray, scales: np.ndarray | None,
            idx: np.ndarray, sigma: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Residual vectors (b, V, 2) and Jacobians (b, V, 2, 3) of points ``idx`` of a chunk whitened by each
    observation's standard deviation σ × scale (NaN where unused)."""
    V = observations.shape[0]
    if res.anchors is None:
        cams = np.broadcast_to(g.P[None], (idx.size, V, 3, 4))
    else:
        cams = g.Q[res.anchors[idx]]  # (b, V, 3, 4)
    pix, _, J = project_each(cams, res.points[idx][:, None, :])
    obs = observations[:, idx].transpose(1, 0, 2)
    r = obs - pix
    c = sigma * (np.ones((idx.size, V)) if scales is None else scales[:, idx].T)
    used = res.used[:, idx].T
    r = np.where(used[..., None], r / c[..., None], np.nan)
    J = np.where(used[..., None, None], J / c[..., None, None], np.nan)
    return r, J


def serial_correlation(parts: Iterable[tuple[ViewGeometry, list[ChunkResult], list[slice], np.ndarray,
                                            np.ndarray | None, np.ndarray]], sigma: float, ok_points: int
                       ) -> SerialCorrelation:
    """The AR(1) correlation of the errors along the views, from a sample of the fused points' residuals.

    ``parts``: per block of points its geometry, chunk results and slices, observations, scales and
    the (global, ascending) indices of its views, which are the sequence positions; ``ok_points``: how
    many points they fused (every ``ok_points // 2000``-th is sampled).  Each sampled
    point's observations sit at its views' offsets from its first view (the lags are what count).
    """
    step = max(1, ok_points // _CORRELATION_SAMPLE)
    rs, Js, offsets = [], [], []
    for g, results, slices, observations, scales, views in parts:  # made one at a time: a block's geometry is big
        for res, chunk in zip(results, slices):
            idx = np.flatnonzero(res.status == PointStatus.OK)[::step]
            r, J = _design(g, res, observations[:, chunk], None if scales is None else scales[:, chunk], idx, sigma)
            seen = np.isfinite(r[..., 0])
            first = views[np.argmax(seen, axis=1)]
            rs.append(r)
            Js.append(J)
            offsets.append(np.where(seen, views[None, :] - first[:, None], -1))
    span = max([int(o.max(initial=-1)) + 1 for o in offsets] + [1])
    n = sum(r.shape[0] for r in rs)
    r_all, J_all = np.full((n, span, 2), np.nan), np.full((n, span, 2, 3), np.nan)
    row = 0
    for r, J, offset in zip(rs, Js, offsets):
        b, v = np.nonzero(offset >= 0)
        r_all[row + b, offset[b, v]] = r[b, v]
        J_all[row + b, offset[b, v]] = J[b, v]
        row += r.shape[0]
    try:
        # the moment tables hold (2 × span)² numbers per track: fewer tracks at a time for long spans
        return fit_serial_correlation(r_all, J_all, np.arange(span), block=max(16, _MOMENT_ENTRIES // (2 * span) ** 2))
    except NotEnoughDataError:
        return SerialCorrelation.independent()
