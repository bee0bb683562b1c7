"""The record of a fusion: every block's chunk results put together as one :class:`~..reconstruction.Reconstruction`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...estimation.noise_model import NoiseFit, SerialCorrelation
from ..geometry.pinhole import CameraSet, project_points
from ..points import PointStatus
from ..reconstruction import (
    KNOWN_CAMERAS_GAUGE,
    FrameStatus,
    FusionDetails,
    NoiseEstimate,
    Observations,
    Reconstruction,
)
from .blocks import Block
from .chunks import ChunkResult
from .history import FusionHistory
from .inputs import are_poses
from .inverse_depth import ViewGeometry, theta_to_point
from .settings import UNRELIABLE_RELATIVE_DEPTH, FusionSettings

__all__ = ["BlockResults", "assemble"]

# States converted from inverse depth to (X, Y, Z) together (bounds the temporaries).
_CONVERSION_BLOCK = 16_384
# A point whose distance from its first camera has a relative standard deviation above this is unreliable, above
# _NO_DEPTH (three standard deviations reach infinity) degenerate.
_UNRELIABLE_DEPTH = UNRELIABLE_RELATIVE_DEPTH
_NO_DEPTH = 1.0 / 3.0


@dataclass(frozen=True)
class BlockResults:
    """One block's last pass: its chunk results, their slices, and under a fitted model its weights and rejections."""

    block: Block
    results: list[ChunkResult]
    slices: list[slice]
    scales: np.ndarray | None = None  # (V_b, n_b) standard deviation relative to σ, NaN where left out
    rejected: np.ndarray | None = None  # (V_b, n_b) left out as outliers by the model


@dataclass
class _Points:
    """The assembled per-point arrays of all blocks, and the observations' entries."""

    points: np.ndarray
    cov: np.ndarray
    status: np.ndarray
    views: np.ndarray
    rms: np.ndarray
    entries: list[tuple[np.ndarray, ...]]


def _to_points(g: ViewGeometry, anchors: np.ndarray | None, x: np.ndarray, cov: np.ndarray, sigma: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y, Z) and covariance at pixel noise σ from a chunk's unit-σ states (inverse depth when anchored).

    Converted in blocks, so the temporaries of the second-order term stay small.
    """
    if anchors is None:
        return x, cov * sigma**2
    X, C = np.empty_like(x), np.empty_like(cov)
    for start in range(0, x.shape[0], _CONVERSION_BLOCK):
        b = slice(start, start + _CONVERSION_BLOCK)
        X[b], C[b] = theta_to_point(g, np.maximum(anchors[b], 0), x[b], cov[b] * sigma**2)
    return X, C


def _judge_depth(g: ViewGeometry, points: np.ndarray, cov: np.ndarray, status: np.ndarray, used: np.ndarray
                 ) -> np.ndarray:
    """Points whose depth the views do not fix are not ``ok``.

    σ_d / d, the standard deviation of a point's distance from the first camera that used it
    relative to that distance (= σ_ρ / ρ of its inverse depth), says how much the views'
    parallax fixes it.  Beyond :data:`_UNRELIABLE_DEPTH` the Gaussian covariance no longer
    describes the (skewed, far-reaching) error and the point is ``unreliable``; beyond
    :data:`_NO_DEPTH`, where three standard deviations reach infinity, it is ``degenerate``.
    """
    ok = np.flatnonzero(status == PointStatus.OK)
    first = np.argmax(used[:, ok], axis=0)
    ray = points[ok] - g.C[first]
    distance = np.linalg.norm(ray, axis=1)
    u = ray / np.where(distance > 0, distance, 1.0)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        relative = np.sqrt(np.abs(np.einsum("ni,nij,nj->n", u, cov[ok], u))) / distance
    relative = np.where(np.isfinite(relative), relative, np.inf)
    status = status.copy()
    status[ok[relative > _NO_DEPTH]] = PointStatus.DEGENERATE
    status[ok[(relative > _UNRELIABLE_DEPTH) & (relative <= _NO_DEPTH)]] = PointStatus.UNRELIABLE
    return status


def _depth_notes(status: np.ndarray, weak: int) -> list[str]:
    notes = []
    degenerate = int(np.count_nonzero(status == PointStatus.DEGENERATE))
    if degenerate:
        notes.append(f"{degenerate} of {status.size} points are 'degenerate': their views have (almost) no parallax, "
                     "the depth is not determined (infinity is within three standard deviations)")
    if weak:
        notes.append(f"{weak} of {status.size} points are 'unreliable': their distance is uncertain by more than "
                     f"{_UNRELIABLE_DEPTH:.0%} (little parallax); their covariance does not describe a skewed error")
    return notes


def _assemble_history(parts: list[BlockResults], geometry: Callable[[int], ViewGeometry], sigma: float
                      ) -> FusionHistory:
    """The chunks' histories in one :class:`FusionHistory`, sorted by view then point (global indices).

    Every entry is written once, straight to its sorted place (no second copy of the history).
    """
    pieces = [(k, part, r, chunk) for k, part in enumerate(parts) for r, chunk in zip(part.results, part.slices)]
    sizes = [r.history[0].size for _, _, r, _ in pieces]
    starts = np.cumsum([0, *sizes])
    cat = np.concatenate
    views = cat([part.block.views[r.history[0]] for _, part, r, _ in pieces] or [np.zeros(0, np.int64)]).astype(np.int64)
    points = cat([part.block.points[r.history[1] + chunk.start] for _, part, r, chunk in pieces]
                 or [np.zeros(0, np.int64)]).astype(np.int64)
    order = np.lexsort((points, views))
    place = np.empty_like(order)
    place[order] = np.arange(order.size)
    H = order.size
    hx, hc = np.empty((H, 3)), np.empty((H, 3, 3))
    states = bool(pieces) and pieces[0][2].anchors is not None
    hs, hsc, ha = (np.empty((H, 3)), np.empty((H, 3, 3)), np.empty(H, np.int64)) if states else (None, None, None)
    g, current = None, -1
    for (k, part, r, _), begin, end in zip(pieces, starts[:-1], starts[1:]):
        if k != current:  # one block's geometry at a time
            g, current = geometry(k), k
        _, local, x, cov = r.history
        where = place[begin:end]
        anchors = None if r.anchors is None else r.anchors[local]
        hx[where], hc[where] = _to_points(g, anchors, x, cov, sigma)
        if states:
            hs[where], hsc[where], ha[where] = x, cov * sigma**2, part.block.views[anchors]
    return FusionHistory(views[order], points[order], hx, hc, hs, hsc, ha)


def assemble(settings: FusionSettings, cams: CameraSet, n_points: int, parts: list[BlockResults],
             geometry: Callable[[int], ViewGeometry], orientation: int, sigma: float,
             estimated: bool, passes: int, fit: NoiseFit | None = None,
             correlation: SerialCorrelation | None = None, warnings: tuple[str, ...] = (),
             dense: bool = True) -> Reconstruction:
    """The fusion's record from the last pass of every block.

    ``geometry(k)``: block k's per-view quantities.  ``fit``: the fitted noise model when the passes were weighted by it (each part then holds its
    scales and rejections).  ``dense``: the observations came as one (V, N, 2) array (one block),
    and the record keeps them so; otherwise they are kept per observation.
    """
    # the covariances' scale: σ, times √((ν + 4) / (ν + 2)) for a Student-t core (its weights' information)
    sigma_cov = sigma if fit is None else sigma * np.sqrt(fit.covariance_factor)
    V = len(cams)
    points, cov = np.full((n_points, 3), np.nan), np.full((n_points, 3, 3), np.nan)
    status = np.zeros(n_points, dtype=np.int8)
    views, rms = np.zeros(n_points, dtype=np.int64), np.full(n_points, np.nan)
    entries = []  # per block: frame, point, xy, used, residual length, rejected, observation σ
    weak = behind = used_total = ok_total = 0
    square_sum, kept_total = 0.0, 0
    for k, part in enumerate(parts):
        block, g = part.block, geometry(k)
        obs = block.observations
        converted = [_to_points(g, r.anchors, r.points, r.covariances, sigma_cov) for r in part.results]
        X = np.concatenate([x for x, _ in converted])
        C = np.concatenate([c for _, c in converted])
        st = np.concatenate([r.status for r in part.results])
        used = np.concatenate([r.used for r in part.results], axis=1)
        rejected = np.concatenate([r.rejected for r in part.results], axis=1)
        lengths = np.concatenate([r.residuals for r in part.results], axis=1)
        was_ok = st == PointStatus.OK
        st = _judge_depth(g, X, C, st, used)
        weak += int(np.count_nonzero(was_ok & (st == PointStatus.UNRELIABLE)))
        has_point = np.isin(st, (PointStatus.OK, PointStatus.UNRELIABLE))
        X[~has_point], C[~has_point] = np.nan, np.nan
        used &= has_point[None]
        behind += int(np.count_nonzero(st == PointStatus.BEHIND_CAMERA))
        ok = st == PointStatus.OK
        seen = np.isfinite(obs).all(axis=2)
        if fit is not None:
            # the model's outliers were left out of the last pass: their residuals at the final points
            rejected = part.rejected & ok[None]
            pix = project_points(g.P, np.where(ok[:, None], X, 0.0)).pixels
            lengths = np.where(seen & ok[None], np.linalg.norm(obs - pix, axis=2), np.nan)
        n_views = used.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            point_rms = np.sqrt(np.sum(np.where(used, lengths, 0.0) ** 2, axis=0) / n_views)
        members = block.points
        points[members], cov[members], status[members] = X, C, st
        views[members], rms[members] = n_views, np.where(ok, point_rms, np.nan)
        used_total += int(used[:, ok].sum())
        ok_total += int(ok.sum())
        # the RMS over every observation of a fused point that was not rejected
        kept = seen & ~rejected & ok[None]
        square_sum += float(np.sum(lengths[kept] ** 2))
        kept_total += int(kept.sum())
        with np.errstate(divide="ignore"):
            std = None if fit is None else np.where(seen, fit.sigma * part.scales, np.nan)
        entries.append((used, rejected, lengths, std))
    warnings = (*warnings, *_depth_notes(status, weak))
    if behind and settings.orientation is None and are_poses(cams):
        warnings = (*warnings, f"{behind} of {status.size} points lie behind the cameras that see them: the cameras "
                    "are poses K [R | t] with det R = +1, which put the points in front at positive depth (a "
                    "mirrored world frame needs orientation=-1)")
    observations, observation_std = _observations(parts, entries, (V, n_points), dense)
    dof = int(2 * used_total - 3 * ok_total)
    if fit is None:
        noise = NoiseEstimate(std=float(sigma), estimated=estimated, degrees_of_freedom=dof)
    else:
        parameters = fit.parameters() + (() if correlation is None else correlation.parameters())
        noise = NoiseEstimate(std=float(sigma), estimated=True, degrees_of_freedom=int(round(fit.degrees_of_freedom)),
                              model=fit.model, parameters=parameters, observation_std=observation_std)
    overall = float(np.sqrt(square_sum / kept_total)) if kept_total else float("nan")
    hist = _assemble_history(parts, geometry, sigma_cov) if settings.history else None
    pose = cams.decompose()
    return Reconstruction(
        kind="fusion",
        method=settings.method,
        camera_model="pinhole",
        projections=np.array(cams.matrices),
        rotations=pose.rotations,
        frame_status=np.full(V, FrameStatus.REGISTERED, dtype=np.int8),
        points=points,
        point_covariances=cov,
        point_status=status,
        views=views,
        point_reprojection_rms=rms,
        covariance_gauge=KNOWN_CAMERAS_GAUGE,
        observations=observations,
        noise=noise,
        reprojection_rms=overall,
        details=FusionDetails(outlier_probability=settings.outlier_probability, orientation=orientation, passes=passes,
                              history=hist),
        intrinsics=pose.intrinsics,
        translations=pose.translations,
        frame_ids=cams.frames,
        warnings=warnings,
    )


def _observations(parts: list[BlockResults], entries: list[tuple], shape: tuple[int, int], dense: bool
                  ) -> tuple[Observations, np.ndarray | None]:
    """The record's observations (dense for one dense block, else per observation) and each one's σ in their order."""
    if dense:
        (used, rejected, lengths, std), obs = entries[0], parts[0].block.observations
        observations = Observations.from_dense(obs, used=used, residuals=lengths, rejected=rejected)
        return observations, None if std is None else std[observations.frame, observations.point]
    columns: list[list[np.ndarray]] = [[] for _ in range(7)]
    for part, (used, rejected, lengths, std) in zip(parts, entries):
        obs = part.block.observations
        v, p = np.nonzero(np.isfinite(obs).all(axis=2))
        values = (part.block.views[v], part.block.points[p], obs[v, p], used[v, p], lengths[v, p], rejected[v, p],
                  None if std is None else std[v, p])
        for column, value in zip(columns, values):
            column.append(value)
    frame, point = np.concatenate(columns[0]), np.concatenate(columns[1])
    order = np.lexsort((point, frame))  # by frame, then point, as dense observations are
    xy, used, residual, rejected = (np.concatenate(c)[order] for c in columns[2:6])
    observations = Observations.from_sparse(shape, frame[order], point[order], xy, used=used, residual=residual,
                                            rejected=rejected)
    std = None if columns[6][0] is None else np.concatenate(columns[6])[order]
    return observations, std
