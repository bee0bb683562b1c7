"""``fuse``: the driver of structure fusion with known cameras — chunks, σ passes, and the assembled record.

Thomas & Oliensis, *Fusing Structure by Kalman Filtering* (``004_cd423c68da9c9743.txt``)
fuse each new view's information about a point into its running estimate.  Here
the cameras are known 3 × 4 projection matrices (:class:`~.pinhole.CameraSet`)
and the points are independent given them, so everything is batched over points
and processed in chunks of points.

Methods
-------
``recursive`` (the paper's Kalman fusion, default)
    Each point's state is its *inverse depth* in the first view that sees it
    (the anchor): θ = (α, β, ρ) with X = C_a + o R_aᵀ (α, β, 1) / ρ, C_a and R_a
    the anchor's centre and rotation and o the scene orientation (+1, or -1 for
    a mirrored reconstruction).  Its homogeneous point is linear in θ, X̃ = H_a θ̃,
    so view v acts on θ as the 3 × 4 matrix P_v H_a: the projection is a ratio of
    affine functions of θ, far more linear than in (X, Y, Z), and the state stays
    valid when the depth is barely determined (ρ near or below zero).  A point
    starts at its first two usable views (Gauss–Newton on their four
    coordinates from a linear start; covariance σ² (JᵀJ)⁻¹); every further view
    is an iterated extended Kalman update on its 2-D projection (each iteration
    is :func:`~kalmansfm.estimation.kalman.kalman_update` with the model
    linearised at the current iterate).  All points seen in a view are updated
    at once (the NumPy reference); by default a numba kernel runs the same
    transitions point by point.  The (X, Y, Z) estimate is θ̂'s image; its
    covariance is the second-order image of θ's (:func:`_theta_to_point`).
``batch`` (the reference)
    Per point, maximum likelihood over all its views: linear triangulation, then
    Gauss–Newton in (X, Y, Z) (:func:`~kalmansfm.structure.geometry.refinement.refine_points`).
``pairs`` (the report's scheme, over-confident)
    Consecutive observations of a point, two views at a time, are triangulated by
    the report's midpoint (:func:`~.triangulation.triangulate_midpoint`) with
    first-order covariance and fused as independent measurements.  Consecutive
    pairs share an image and the covariances are evaluated at noisy points: kept
    for fidelity to the report, documented as over-confident.

Outliers
--------
An observation is tested before it is used, with σ the pixel noise:

* a further view (recursive): the innovation ν = z - h(θ̂) with S = H P Hᵀ + σ² I;
  νᵀ S⁻¹ ν beyond the χ²(2) quantile of ``outlier_probability`` → rejected;
* the first pair of a point (recursive) is provisional until the next view passes
  the gate; a pair whose Gauss–Newton residual (1 degree of freedom) fails the
  χ²(1) quantile is kept as a conflict.  Three observations that do not agree are
  resolved: the one whose removal leaves the most consistent pair (which must pass
  χ²(1)) is rejected and the point continues from that pair; with no consistent
  pair the oldest is rejected;
* batch: the leave-one-out residual of every observation, rᵀ (σ² (I - J N⁻¹ Jᵀ))⁻¹ r,
  worst first, one per point per round, until all pass; a two-view point whose
  residual fails the χ²(1) test loses both observations.
``pairs`` rejects nothing (the report's scheme has no outlier test).

Pixel noise
-----------
``pixel_std="auto"`` estimates σ from the residuals with the degrees of freedom
counted: σ² = Σ |r|² / (2 n_observations - 3 n_points) over the fused points and
their accepted observations.  It starts from a robust value (the median squared
residual of an ungated pass) and alternates gating and re-estimation until σ
changes by less than 0.5 %.  Estimates given fixed gating decisions do not depend
on σ (every covariance scales with σ²), so the state is kept at unit σ and the
covariances are scaled by the final σ².
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from typing import Any

import numpy as np

from ...errors import InvalidInputError, NotEnoughDataError
from ...estimation.noise_model import SerialCorrelation
from ..geometry.pinhole import CameraSet
from ..points import PointStatus
from ..reconstruction import Observations, Reconstruction
from .assemble import BlockResults, assemble
from .batch import run_batch
from .blocks import Block, chunks, dense_block, fits_one_block, orientation_of_blocks, sparse_blocks
from .chunks import Chunk, ChunkResult
from .inputs import are_poses, validate_inputs, validate_sparse_inputs
from .inverse_depth import ViewGeometry
from .pairs import run_pairs
from .recursive import COMPILED_MIN_POINTS, run_recursive
from .robust import ObservationResiduals, observation_residuals, reweigh, serial_correlation
from .settings import FusionSettings

__all__ = ["fuse"]

# Auto σ: stop re-estimating when it changes by less than this fraction; at most this many passes.
_SIGMA_TOLERANCE = 5e-3
_MAX_SIGMA_PASSES = 8
# Reweighted passes under a fitted noise model (iteratively reweighted least squares after the pilot).
_REWEIGHTED_PASSES = 2
# Residual degrees of freedom needed to fit a noise model beyond one Gaussian σ.
_MIN_MODEL_DOF = 50
# A lag-one correlation of the errors along the tracks above this (and clearly above 0) is warned about.
_CORRELATED = 0.3


_RUNNERS: dict[str, Callable[[Chunk], ChunkResult]] = {"recursive": run_recursive, "batch": run_batch, "pairs": run_pairs}


def _run_chunk(job: Chunk) -> ChunkResult:
    return _RUNNERS[job.method](job)


def _sum_squares(results: Iterable[ChunkResult]) -> tuple[float, int, int]:
    """Σ |r|² over accepted observations of fused points, their count, and the fused points."""
    total, n_obs, n_pts = 0.0, 0, 0
    for res in results:
        ok = res.status == PointStatus.OK
        u = res.used & ok[None]
        total += float(np.sum(np.where(u, res.residuals, 0.0) ** 2))
        n_obs += int(u.sum())
        n_pts += int(ok.sum())
    return total, n_obs, n_pts


def fuse(
    observations: object,
    cameras: CameraSet | object,
    method: str | None = None,
    pixel_std: float | str | None = None,
    outlier_probability: float | None = None,
    history: bool | None = None,
    *,
    chunk_points: int | None = None,
    orientation: int | None = None,
    noise_model: str | None = None,
    track_scales: bool | None = None,
    settings: FusionSettings | None = None,
    executor: Any | None = None,
    progress: Callable[[int, int], object] | None = None,
) -> Reconstruction:
    """Fuse each point's observations over many views with known cameras into a 3-D point and its covariance.

    Parameters
    ----------
    observations : (V, N, 2) float, or Observations
        Pixel positions (x = column, y = row) of N points in the V views of
        ``cameras``, in the same view order; NaN where a point is not seen.  Or the
        same per observation (:class:`~kalmansfm.structure.Observations` of shape
        (V, N), frame = view index): beyond :data:`~.blocks.ONE_BLOCK_VIEWS` views or
        :data:`~.blocks.ONE_BLOCK_ENTRIES` view × point entries (a long sequence of short
        tracks) they are fused in blocks of tracks, each over only the views it is seen in,
        so that memory follows the observations; the result is the one the dense array gives.
    cameras : CameraSet or (V, 3, 4) projection matrices.
    method : {"recursive", "batch", "pairs"}, default "recursive"
        ``"recursive"``: the paper's Kalman fusion, view by view (inverse-depth
        state, iterated EKF updates); ``"batch"``: per-point maximum likelihood
        over all views (the reference); ``"pairs"``: the report's fusion of
        consecutive two-view triangulations (over-confident, no outlier test).
    pixel_std : float > 0, "auto" or None, default "auto"
        Image noise σ in pixels; ``"auto"`` (or None) estimates it from the residuals
        with 2 degrees of freedom per observation minus 3 per point, after outlier
        rejection.
    outlier_probability : float in (0, 1], default :data:`DEFAULT_OUTLIER_PROBABILITY`
        Observations beyond the χ² quantile of this probability are rejected
        (1 disables the test).
    history : bool, default False
        Also return every point's estimate after every view that observed it.
    chunk_points : int, default :data:`DEFAULT_CHUNK_POINTS`
        Points processed together; bounds the memory.
    orientation : +1, -1 or None
        +1: points lie in front of the cameras (positive depth with P = λ K [R | t]);
        -1: a mirrored reconstruction; None: the sign most points agree on.
    settings : FusionSettings, optional
        All the options above at once (the defaults are :class:`FusionSettings`'s);
        then none of them may be given as well.
    executor : object with a ``map(fn, items)`` method, optional
        Runs the chunks (a ``concurrent.futures.Executor``, or
        :class:`kalmansfm.pipeline.cluster.ScatteringExecutor` on Dask); by default
        they run one after the other here.
    progress : called after each chunk with (points done in this pass, points of the pass), e.g. for a
        progress bar; a fit of σ or of a noise model passes over the points (or some of them) more than
        once, each pass from 0.

    Returns
    -------
    Reconstruction
        ``kind="fusion"``: the cameras as given (``frame_ids`` are the camera set's frames),
        per-point estimates, covariances (σ² scaled, in the cameras' own frame) and status; a
        point that cannot be estimated gets a status, never an exception.  The observations
        record which were used and which rejected as outliers, with their residuals; ``noise``
        is the σ used; ``details`` holds the orientation, the passes and, when asked for,
        the history.

    Raises
    ------
    InvalidInputError
        Bad shapes, infinite observations, invalid cameras or settings; ``settings``
        given together with one of the options it holds.
    NotEnoughDataError
        Fewer than 2 cameras, or ``pixel_std="auto"`` without redundant observations.

    Examples
    --------
    Three cameras along x, 50 points, noise 0.5 px:

    >>> import numpy as np
    >>> from kalmansfm.structure.geometry.pinhole import CameraSet, project_points
    >>> rng = np.random.default_rng(0)
    >>> K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    >>> cams = CameraSet.from_pose(K, np.stack([np.eye(3)] * 3), [[0, 0, 0], [-0.5, 0, 0], [-1.0, 0, 0]])
    >>> X = rng.uniform([-1, -1, 4], [1, 1, 6], size=(50, 3))
    >>> obs = project_points(cams, X).pixels + rng.normal(scale=0.5, size=(3, 50, 2))
    >>> fused = fuse(obs, cams)
    >>> fused.status_counts()["ok"], round(fused.noise.std, 1)
    (50, 0.5)
    >>> err = fused.points - X
    >>> nees = np.einsum("ni,ni->n", err, np.linalg.solve(fused.point_covariances, err[..., None])[..., 0])
    >>> bool(2.0 < nees.mean() < 4.5)
    True
    """
    options = {"method": method, "pixel_std": pixel_std, "outlier_probability": outlier_probability,
               "history": history, "chunk_points": chunk_points, "orientation": orientation,
               "noise_model": noise_model, "track_scales": track_scales}
    given = {name: value for name, value in options.items() if value is not None}
    if settings is not None:
        if given:
            raise InvalidInputError(f"fuse: give {', '.join(given)} inside settings, not beside it "
                                    "(settings would silently win)")
    else:
        if isinstance(given.get("pixel_std"), str):
            if given["pixel_std"] != "auto":
                raise InvalidInputError(f"pixel_std must be a number (pixels) or 'auto'; got {pixel_std!r}")
            del given["pixel_std"]
        settings = FusionSettings(**given)
    return _fuse(observations, cameras, settings, executor, progress)


def _fuse(observations: object, cameras: CameraSet | object, settings: FusionSettings,
          executor: Any | None, progress: Callable[[int, int], object] | None = None) -> Reconstruction:
    if isinstance(observations, Observations):
        cams = validate_sparse_inputs(observations, cameras)
        if fits_one_block(observations.shape):  # small enough to be fused as if given densely
            observations = observations.dense()
    if isinstance(observations, Observations):
        blocks, dense = sparse_blocks(observations), False
        n_points = observations.shape[1]
    else:
        cams, obs = validate_inputs(observations, cameras)
        blocks, dense = [dense_block(obs)], True
        n_points = obs.shape[1]
    orientation = orientation_of_blocks(cams, blocks) if settings.orientation is None else settings.orientation
    geometries: dict[int, ViewGeometry] = {}

    def geometry(k: int) -> ViewGeometry:
        # one block's geometry is kept; many blocks' would together grow with views × views per block
        if len(blocks) == 1:
            if k not in geometries:
                geometries[k] = blocks[k].geometry(cams.matrices, orientation)
            return geometries[k]
        return blocks[k].geometry(cams.matrices, orientation)

    slices = [chunks(b.points.size, settings.chunk_points) for b in blocks]
    # many small blocks make a large fusion: the compiled kernel pays for its compilation there
    compiled = None if len(blocks) == 1 else n_points >= COMPILED_MIN_POINTS

    def run(sigma: float, gate2: float, gate1: float, keep_history: bool, scales: list[np.ndarray] | None = None,
            subsets: list[np.ndarray] | None = None) -> list[list[ChunkResult]]:
        owners: list[int] = []

        def jobs() -> Iterator[Chunk]:  # made one at a time: a block's data lives while its chunks run
            for k, block in enumerate(blocks):
                data, sc = block.observations, None if scales is None else scales[k]
                if sc is not None:
                    data = np.where(np.isnan(sc)[..., None], np.nan, data)
                parts = slices[k]
                if subsets is not None:  # a subset of the points, in chunks of its own
                    data, sc = data[:, subsets[k]], None if sc is None else sc[:, subsets[k]]
                    parts = chunks(subsets[k].size, settings.chunk_points)
                g = geometry(k)
                for s in parts:
                    owners.append(k)
                    yield Chunk(settings.method, g, data[:, s], sigma, gate2, gate1, keep_history,
                                None if sc is None else sc[:, s], compiled)
        mapper = map if executor is None else executor.map
        done: list[ChunkResult] = []
        points_done = 0
        for result in mapper(_run_chunk, jobs()):
            done.append(result)
            if progress is not None and result.points.shape[0]:
                points_done += result.points.shape[0]
                progress(points_done, n_points if subsets is None else sum(int(x.size) for x in subsets))
        grouped: list[list[ChunkResult]] = [[] for _ in blocks]
        for k, result in zip(owners, done):
            grouped[k].append(result)
        return grouped

    def every(grouped: list[list[ChunkResult]]) -> list[ChunkResult]:
        return [r for results in grouped for r in results]

    passes = 1
    notes: list[str] = []
    fitted = settings.pixel_std is None and settings.noise_model != "gaussian" and settings.method != "pairs"
    if settings.pixel_std is not None:
        sigma = settings.pixel_std
        results = run(sigma, settings.gate2, settings.gate1, settings.history)
        sigma_out = sigma
    else:
        # Pilot without gates: a robust σ from the median squared residual, |r|² / σ² ≈ χ²(2) (median 2 ln 2),
        # with the degrees of freedom counted.
        results = run(1.0, np.inf, np.inf, False)
        sq = np.concatenate([np.where(r.used & (r.status == PointStatus.OK)[None], r.residuals, np.nan).ravel() ** 2
                             for r in every(results)])
        sq = sq[np.isfinite(sq)]
        total, n_obs, n_pts = _sum_squares(every(results))
        dof = 2 * n_obs - 3 * n_pts
        if n_pts == 0:
            raise NotEnoughDataError(f"pixel_std='auto' needs fused points to estimate the noise from, and none was "
                                     f"fused: {_why_nothing_fused(blocks, every(results), cams, orientation)}")
        if dof <= 0 or sq.size == 0:
            raise NotEnoughDataError(
                f"pixel_std='auto' needs more observations than unknowns (2 per observation - 3 per point > 0); "
                f"got {n_obs} observations of {n_pts} points: give pixel_std")
        sigma = float(np.sqrt(np.median(sq) / (2 * np.log(2)) * 2 * n_obs / dof))
        if not sigma > 0:
            raise NotEnoughDataError("pixel_std='auto': the residuals are all zero, the noise cannot be estimated; "
                                     "give pixel_std")
        sigma_out = sigma
        previous: tuple[float, float] | None = None
        # a fitted noise model starts from one gated pass at the robust σ (its own outlier decisions follow)
        gaussian_passes = 1 if fitted and dof >= _MIN_MODEL_DOF else _MAX_SIGMA_PASSES
        for _ in range(gaussian_passes):
            results = run(sigma, settings.gate2, settings.gate1, settings.history)
            passes += 1
            total, n_obs, n_pts = _sum_squares(every(results))
            dof = 2 * n_obs - 3 * n_pts
            if dof <= 0:
                raise NotEnoughDataError(
                    f"pixel_std='auto' needs 2 × observations - 3 × points > 0 after outlier rejection; got {dof}")
            sigma_out = float(np.sqrt(total / dof))
            if abs(sigma_out / sigma - 1.0) < _SIGMA_TOLERANCE:
                break
            sigma, previous = _next_sigma(sigma, sigma_out, previous), (sigma, sigma_out)
    fit, correlation = None, None
    scales: list[np.ndarray] | None = None
    rejected: list[np.ndarray] | None = None
    if fitted and dof < _MIN_MODEL_DOF:
        notes.append(f"{dof} residual degrees of freedom are too few to fit the {settings.noise_model!r} noise "
                     f"model (at least {_MIN_MODEL_DOF}): one Gaussian σ and the χ² gate were used")
        fitted = False
    if fitted:
        for i in range(_REWEIGHTED_PASSES):
            residuals, where = _residuals(blocks, geometry, results, slices, scales)
            reweighting = reweigh(residuals, settings.noise_model, settings.outlier_probability, settings.track_scales)
            previous_scales = scales
            scales = _scattered(reweighting.scales, where, blocks, 1.0)
            rejected = [r.astype(bool) for r in _scattered(reweighting.rejected, where, blocks, 0.0)]
            fit, sigma_out = reweighting.fit, reweighting.fit.sigma
            last = i == _REWEIGHTED_PASSES - 1
            if settings.history:
                results = run(sigma_out, np.inf, np.inf, last, scales)
            else:
                # a point whose observations and weights did not change keeps its estimate: refuse only the others
                changed = [_changed_points(results[k], blocks[k].observations, scales[k],
                                           None if previous_scales is None else previous_scales[k])
                           for k in range(len(blocks))]
                update = run(sigma_out, np.inf, np.inf, False, scales, changed)
                for k in range(len(blocks)):
                    results[k], slices[k] = _merged(results[k], slices[k], changed[k], update[k])
            passes += 1
        # a diagnostic: errors correlated along the tracks are not what the covariances assume
        ok_points = sum(int(np.count_nonzero(r.status == PointStatus.OK)) for r in every(results))
        correlation = serial_correlation(((geometry(k), results[k], slices[k], blocks[k].observations, scales[k],
                                           blocks[k].views) for k in range(len(blocks))), sigma_out, ok_points)
        notes.extend(_correlation_warning(correlation))
    parts = [BlockResults(block, results[k], slices[k], None if scales is None else scales[k],
                          None if rejected is None else rejected[k]) for k, block in enumerate(blocks)]
    return assemble(settings, cams, n_points, parts, geometry, orientation, sigma_out, settings.pixel_std is None,
                    passes, fit, correlation, tuple(notes), dense)


def _residuals(blocks: list[Block], geometry: Callable[[int], ViewGeometry], results: list[list[ChunkResult]],
               slices: list[list[slice]], scales: list[np.ndarray] | None
               ) -> tuple[ObservationResiduals, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every block's residuals with global (view, point) indices, and where each lives: (block, local view, point)."""
    found = [observation_residuals(geometry(k), results[k], slices[k], block.observations,
                                   None if scales is None else scales[k]) for k, block in enumerate(blocks)]
    cat = np.concatenate
    residuals = ObservationResiduals(cat([b.views[r.view] for b, r in zip(blocks, found)]),
                                     cat([b.points[r.point] for b, r in zip(blocks, found)]),
                                     cat([r.squared for r in found]), cat([r.dof for r in found]))
    where = (cat([np.full(r.view.size, k) for k, r in enumerate(found)]), cat([r.view for r in found]),
             cat([r.point for r in found]))
    return residuals, where


def _scattered(values: np.ndarray, where: tuple[np.ndarray, np.ndarray, np.ndarray], blocks: list[Block],
               fill: float) -> list[np.ndarray]:
    """Per-observation ``values`` laid out as each block's (views, points) array, ``fill`` where there is none."""
    block, view, point = where
    out = []
    for k, b in enumerate(blocks):
        grid = np.full((b.views.size, b.points.size), fill, dtype=np.float64)
        mine = block == k
        grid[view[mine], point[mine]] = values[mine]
        out.append(grid)
    return out


def _changed_points(results: list[ChunkResult], obs: np.ndarray, scales: np.ndarray,
                    previous: np.ndarray | None) -> np.ndarray:
    """Points whose kept observations or weights differ from the pass that gave ``results``."""
    used = np.concatenate([r.used for r in results], axis=1)
    kept = np.isfinite(obs[..., 0]) & np.isfinite(scales)
    before = np.ones_like(scales) if previous is None else previous
    reweighed = kept & ~(scales == before)
    return np.flatnonzero(np.any(kept != used, axis=0) | np.any(reweighed, axis=0))


def _merged(results: list[ChunkResult], slices: list[slice], points: np.ndarray, update: list[ChunkResult]
            ) -> tuple[list[ChunkResult], list[slice]]:
    """All points as one chunk: ``results`` with the given points replaced by ``update`` (their own chunks)."""
    def whole(parts: list[ChunkResult]) -> dict:
        anchored = parts[0].anchors is not None
        return {"points": np.concatenate([r.points for r in parts]),
                "covariances": np.concatenate([r.covariances for r in parts]),
                "status": np.concatenate([r.status for r in parts]),
                "used": np.concatenate([r.used for r in parts], axis=1),
                "rejected": np.concatenate([r.rejected for r in parts], axis=1),
                "residuals": np.concatenate([r.residuals for r in parts], axis=1),
                "anchors": np.concatenate([r.anchors for r in parts]) if anchored else None}
    merged = whole(results)
    if points.size:
        new = whole(update)
        for name in ("points", "covariances", "status", "anchors"):
            if merged[name] is not None:
                merged[name][points] = new[name]
        for name in ("used", "rejected", "residuals"):
            merged[name][:, points] = new[name]
    n = merged["status"].size
    return [ChunkResult(history=None, **merged)], [slice(0, n)]


def _why_nothing_fused(blocks: list[Block], results: list[ChunkResult], cams: CameraSet, orientation: int) -> str:
    """Why no point was fused, in plain words, from the statuses of an ungated pass."""
    tracks = sum(int(np.count_nonzero(np.isfinite(b.observations[..., 0]).sum(axis=0) >= 2)) for b in blocks)
    if tracks == 0:
        return "no track is seen in two views (every track was seen once), so there is nothing to triangulate"
    status = np.concatenate([r.status for r in results])
    behind = int(np.count_nonzero(status == PointStatus.BEHIND_CAMERA))
    degenerate = int(np.count_nonzero(status == PointStatus.DEGENERATE))
    if behind >= degenerate and behind:
        how = ("the cameras are poses K [R | t] with det R = +1, which put the points in front at positive depth"
               if are_poses(cams) else f"orientation {orientation:+d}")
        return f"the {behind} points seen in two or more views lie behind the cameras that see them ({how})"
    return (f"none of the {tracks} tracks seen in two or more views has parallax between its views (the camera "
            "centres coincide, as in a pure rotation, or the points are too far away for the baseline): their "
            "depth is not determined")


def _correlation_warning(c: SerialCorrelation) -> list[str]:
    """A warning when the residuals are clearly correlated along the tracks (lag-one ρ > 0.3, 3 standard errors)."""
    clear = (c.correlation > _CORRELATED) & (c.correlation - 3 * np.nan_to_num(c.correlation_se, nan=np.inf) > 0)
    if not clear.any():
        return []
    values = ", ".join(f"{axis} {r:.2f} ± {se:.2f}" for axis, r, se in zip("xy", c.correlation, c.correlation_se))
    return [f"the observation errors are correlated along the tracks (lag-one correlation {values}): the "
            "covariances assume independent errors, and an error that neighbouring views share is not averaged "
            "out (a point's error can exceed its covariance; docs/fusion.md, split-half test)"]


def _next_sigma(sigma: float, estimate: float, previous: tuple[float, float] | None) -> float:
    """The next σ to gate with: the fixed point σ = σ̂(σ) of the secant through the last two passes.

    σ̂ grows with the gating σ (a wider gate admits larger residuals) with a slope
    s < 1; plain iteration σ ← σ̂(σ) shrinks the error only by s per pass, the
    secant step σ + (σ̂ - σ) / (1 - s) lands on the fixed point of the line.
    """
    if previous is None or previous[0] == sigma:
        return estimate
    slope = (estimate - previous[1]) / (sigma - previous[0])
    slope = min(max(slope, 0.0), 0.9)
    return sigma + (estimate - sigma) / (1.0 - slope)


