"""Factorization of a long sequence of short tracks, its observations held one entry per observation.

A dense (frames × points) array of a ten-minute sequence of short tracks is tens of gigabytes
though its observations fit in a few hundred megabytes.  This fits the same model as
:mod:`~kalmansfm.structure.affine.factorization`, x_fp = M_f S_p + t_f, without that array:

1. *sequence* — a few frames that many tracks span are factorized in closed form, which fixes
   the one affine frame; every other frame is then resected from the points already determined
   and the points it sees are intersected again (:func:`~.sequential.sequential_factors`);
2. *polish* — alternating least squares over all observations: every point's 3 × 3 and every
   frame's 4 × 4 normal equations summed with ``np.bincount`` over the observation arrays
   (:func:`point_normal_equations`, :func:`frame_normal_equations`), until the cost changes by
   less than :data:`POLISH_TOL` (relative) or :data:`POLISH_ITERATIONS` sweeps;
3. *outliers* — every observation farther than :data:`OUTLIER_SIGMAS` robust σ from the fit is
   rejected (re-admitted when it fits again) and the polish repeated, until the rejected set stops
   changing (at most :data:`_REJECTION_ROUNDS` rounds).  The dense path rejects nothing; on data
   without gross errors the two agree;
4. one metric upgrade over all camera rows (:func:`~.factorization.metric_frame`), then each
   point's covariance σ̂² (Σ_f M_fᵀ M_f)⁻¹ over its own frames, σ̂ from the residuals with the
   degrees of freedom counted, and its verdict (:func:`~.uncertainty.judge_points`).

Memory follows the observations: a few arrays of N × 16 numbers at a time, nothing of
frames × points.  A sequence with no loop back is fitted like visual odometry: the small errors
of each stretch add up along it as a slowly varying affine distortion that the reprojections
barely see (each stretch is consistent in itself), and which alternating least squares corrects
only slowly; the metric upgrade of a long sequence is the check on it.  No singular values of the
whole measurement matrix are computed (there is none), so the dense path's rank check is not made.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...errors import NotEnoughDataError
from ..reconstruction import (
    AFFINE_GAUGE,
    AffineDetails,
    NoiseEstimate,
    Observations,
    Reconstruction,
)
from .factorization import metric_frame, single_threaded_blas
from .reconstruct import affine_cameras
from .sequential import OUTLIER_SIGMAS, SequentialFactors, robust_sigma, sequential_factors
from .uncertainty import GAUGE_PARAMETERS, MAX_STD_RATIO, MIN_VIEWS, judge_points

__all__ = ["DENSE_ENTRIES", "OUTLIER_SIGMAS", "POLISH_ITERATIONS", "POLISH_TOL", "FrameSystems", "PointSystems",
           "factorize_long_sequence", "fits_dense_factorization", "frame_normal_equations",
           "point_normal_equations"]

#: Observations over more than this many (frames × points) entries are factorized frame by frame
#: (:func:`factorize_long_sequence`), not as one dense array (8 bytes × 2 coordinates an entry, and the
#: dense fit's copies).
DENSE_ENTRIES = 20_000_000
#: The polish's iteration cap and relative stopping tolerance on the cost.
POLISH_ITERATIONS = 10
POLISH_TOL = 1e-6

# No residual shorter than this is an outlier, however small σ̂ (exact data).
_MIN_OUTLIER_PX = 0.01
_REJECTION_ROUNDS = 3
# A normal matrix whose smallest / largest eigenvalue is below this is not solved (the unknown is left out).
_CONDITION = 1e-15


def fits_dense_factorization(shape: tuple[int, int]) -> bool:
    """Whether observations over ``shape`` (frames, points) are factorized as one dense array.

    Examples
    --------
    >>> fits_dense_factorization((600, 5000)), fits_dense_factorization((20000, 50047))
    (True, False)
    """
    frames, points = shape
    return frames * points <= DENSE_ENTRIES


@dataclass(frozen=True)
class PointSystems:
    """Every point's least-squares system given the frames: ``normal`` (P, 3, 3) Σ M_fᵀ M_f, ``rhs`` (P, 3)
    Σ M_fᵀ (x_fp − t_f), ``count`` (P,) the observations summed."""

    normal: np.ndarray
    rhs: np.ndarray
    count: np.ndarray


@dataclass(frozen=True)
class FrameSystems:
    """Every frame's least-squares system given the points, h = (S_p, 1): ``normal`` (F, 4, 4) Σ h hᵀ,
    ``rhs`` (F, 4, 2) Σ h x_fpᵀ (one column per image coordinate), ``count`` (F,) the observations summed."""

    normal: np.ndarray
    rhs: np.ndarray
    count: np.ndarray


def _sum_by(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n, k): the rows of ``values`` (N, k) summed by ``index`` (N,)."""
    return np.stack([np.bincount(index, weights=values[:, j], minlength=n) for j in range(values.shape[1])], axis=1)


def point_normal_equations(motion: np.ndarray, translation: np.ndarray, frame: np.ndarray, point: np.ndarray,
                           xy: np.ndarray, n_points: int) -> PointSystems:
    """The normal equations of every point given the frames' ``motion`` (F, 2, 3) and ``translation`` (F, 2).

    Sums over the observations ``frame``, ``point`` (N,) at ``xy`` (N, 2) with no (frames × points) array.

    Examples
    --------
    >>> m = np.array([[[1.0, 0, 0], [0, 1, 0]], [[0, 0, 1], [0, 1, 0]]])
    >>> s = point_normal_equations(m, np.zeros((2, 2)), np.array([0, 1]), np.array([0, 0]), np.array([[1.0, 2], [3, 4]]), 1)
    >>> s.normal[0].tolist(), s.rhs[0].tolist(), s.count.tolist()
    ([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]], [1.0, 6.0, 3.0], [2])
    """
    gram = np.einsum("fci,fcj->fij", motion, motion).reshape(-1, 9)
    normal = _sum_by(point, gram[frame], n_points).reshape(-1, 3, 3)
    rhs = _sum_by(point, np.einsum("nci,nc->ni", motion[frame], xy - translation[frame]), n_points)
    return PointSystems(normal, rhs, np.bincount(point, minlength=n_points))


def frame_normal_equations(points: np.ndarray, frame: np.ndarray, point: np.ndarray, xy: np.ndarray,
                           n_frames: int) -> FrameSystems:
    """The normal equations of every frame's two camera rows and translation given the ``points`` (P, 3).

    Examples
    --------
    >>> s = frame_normal_equations(np.eye(3), np.array([0, 0]), np.array([0, 2]), np.array([[1.0, 2], [3, 4]]), 1)
    >>> s.normal[0].tolist()
    [[1.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 1.0], [1.0, 0.0, 1.0, 2.0]]
    >>> s.rhs[0].tolist(), s.count.tolist()
    ([[1.0, 2.0], [0.0, 0.0], [3.0, 4.0], [4.0, 6.0]], [2])
    """
    h = np.hstack([points[point], np.ones((point.size, 1))])
    normal = _sum_by(frame, (h[:, :, None] * h[:, None, :]).reshape(-1, 16), n_frames).reshape(-1, 4, 4)
    rhs = _sum_by(frame, (h[:, :, None] * xy[:, None, :]).reshape(-1, 8), n_frames).reshape(-1, 4, 2)
    return FrameSystems(normal, rhs, np.bincount(frame, minlength=n_frames))


def _solvable(normal: np.ndarray, count: np.ndarray, least: int) -> np.ndarray:
    """Which systems have ``least`` observations and a well-conditioned normal matrix."""
    ok = count >= least
    if ok.any():
        eig = np.linalg.eigvalsh(normal[ok])
        ok[ok] = eig[:, 0] > _CONDITION * np.maximum(eig[:, -1], np.finfo(float).tiny)
    return ok


def _solve_points(systems: PointSystems, previous: np.ndarray) -> np.ndarray:
    """Every point solved from its system; one that is not solvable keeps its ``previous`` value."""
    shape = previous.copy()
    ok = _solvable(systems.normal, systems.count, 2)
    shape[ok] = np.linalg.solve(systems.normal[ok], systems.rhs[ok][..., None])[..., 0]
    return shape


def _solve_frames(systems: FrameSystems, motion: np.ndarray, translation: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Every frame solved from its system; one that is not solvable keeps its ``motion`` and ``translation``."""
    motion, translation = motion.copy(), translation.copy()
    ok = _solvable(systems.normal, systems.count, 4)
    solution = np.linalg.solve(systems.normal[ok], systems.rhs[ok])  # (n, 4, 2): column c is [m_c | t_c]
    motion[ok] = solution[:, :3].transpose(0, 2, 1)
    translation[ok] = solution[:, 3]
    return motion, translation


def _residuals(motion: np.ndarray, translation: np.ndarray, shape: np.ndarray, frame: np.ndarray, point: np.ndarray,
               xy: np.ndarray) -> np.ndarray:
    """(N,) |M_f S_p + t_f − x| for every observation, NaN where its frame or point is unknown."""
    predicted = np.einsum("nci,ni->nc", motion[frame], shape[point]) + translation[frame]
    return np.linalg.norm(predicted - xy, axis=1)


def _outlier_threshold(residual: np.ndarray) -> float:
    """:data:`OUTLIER_SIGMAS` robust σ of the finite residual lengths (at least :data:`_MIN_OUTLIER_PX`)."""
    return max(OUTLIER_SIGMAS * robust_sigma(residual), _MIN_OUTLIER_PX)


@dataclass(frozen=True)
class _Polished:
    motion: np.ndarray
    translation: np.ndarray
    shape: np.ndarray
    iterations: int
    converged: bool


def _polish(motion: np.ndarray, translation: np.ndarray, shape: np.ndarray, frame: np.ndarray, point: np.ndarray,
            xy: np.ndarray, taking_part: np.ndarray, tick: Callable[[], object]) -> _Polished:
    """Alternating least squares over the observations ``taking_part`` until the cost settles (``tick`` after each)."""
    n_frames, n_points = motion.shape[0], shape.shape[0]
    previous = np.inf
    converged = False
    iterations = 0
    while iterations < POLISH_ITERATIONS:
        sel = taking_part & np.isfinite(motion[:, 0, 0])[frame]
        shape = _solve_points(point_normal_equations(motion, translation, frame[sel], point[sel], xy[sel], n_points),
                              shape)
        sel = taking_part & np.isfinite(shape[:, 0])[point]
        motion, translation = _solve_frames(frame_normal_equations(shape, frame[sel], point[sel], xy[sel], n_frames),
                                           motion, translation)
        iterations += 1
        tick()
        residual = _residuals(motion, translation, shape, frame[taking_part], point[taking_part], xy[taking_part])
        cost = float(np.sum(np.square(residual[np.isfinite(residual)])))
        if abs(previous - cost) <= POLISH_TOL * cost:
            converged = True
            break
        previous = cost
    return _Polished(motion, translation, shape, iterations, converged)


@single_threaded_blas
def factorize_long_sequence(observations: Observations, *, min_views: int = MIN_VIEWS,
                            max_std_ratio: float = MAX_STD_RATIO,
                            progress: Callable[[int, int], object] | None = None) -> Reconstruction:
    """Affine shape and motion of sparse observations too many for one dense array (see the module notes).

    Parameters
    ----------
    observations : the tracks' observations, one entry per (frame, point)
        (:meth:`~kalmansfm.structure.reconstruction.Observations.from_sparse`); frames = the
        observations' first axis, in sequence order.
    min_views, max_std_ratio : the reliability bound of :func:`~kalmansfm.structure.factorize`.
    progress : called with (steps done, steps at most) after the frame-by-frame pass and after each
        polish iteration, e.g. for a progress bar.

    Returns
    -------
    Reconstruction
        As :func:`~kalmansfm.structure.factorize` returns it (``kind="affine"``,
        ``method="sequential"``), its observations kept sparse with each one's residual and
        whether it was used or rejected; ``details.singular_values`` is empty (no measurement
        matrix is formed) and ``details.iterations`` counts the polish's iterations.

    Raises
    ------
    NotEnoughDataError
        No window of frames determines an affine reconstruction.

    Examples
    --------
    A camera turning slowly about the vertical axis past 400 short tracks over 300 frames:

    >>> rng = np.random.default_rng(0)
    >>> frames, tracks = 300, 400
    >>> start = rng.integers(0, frames - 20, tracks)
    >>> frame = np.concatenate([np.arange(s, s + 20) for s in start]); point = np.repeat(np.arange(tracks), 20)
    >>> world = np.c_[rng.uniform(-1, 1, (tracks, 2)) * 100, rng.normal(0, 30, tracks)]
    >>> angle = np.radians(0.2 * np.arange(frames))
    >>> rows = np.stack([np.c_[np.cos(angle), 0 * angle, np.sin(angle)], np.c_[0 * angle, 1 + 0 * angle, 0 * angle]], 1)
    >>> xy = np.einsum("nci,ni->nc", rows[frame], world[point]) + 320 + rng.normal(0, 0.5, (frame.size, 2))
    >>> rec = factorize_long_sequence(Observations.from_sparse((frames, tracks), frame, point, xy))
    >>> rec.method, int(rec.registered.sum()), bool(rec.reprojection_rms < 1.0)
    ('sequential', 296, True)
    """
    frame, point, xy = observations.frame, observations.point, observations.xy
    budget = 1 + _REJECTION_ROUNDS * POLISH_ITERATIONS
    done = 0

    def tick() -> None:
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, budget)

    start = sequential_factors(frame, point, xy, observations.shape)
    tick()
    motion, translation, shape = start.motion, start.translation, start.shape
    rejected = start.rejected
    iterations, converged = 0, True
    for _ in range(_REJECTION_ROUNDS):
        polished = _polish(motion, translation, shape, frame, point, xy, ~rejected, tick)
        motion, translation, shape = polished.motion, polished.translation, polished.shape
        iterations += polished.iterations
        converged = polished.converged
        residual = _residuals(motion, translation, shape, frame, point, xy)
        threshold = _outlier_threshold(residual)
        now_rejected = residual > threshold
        if np.array_equal(now_rejected, rejected):
            break
        rejected = now_rejected
    f_ok, p_ok = np.isfinite(motion).all(axis=(1, 2)), np.isfinite(shape).all(axis=1)
    if f_ok.sum() < 3 or p_ok.sum() < 4:
        raise NotEnoughDataError(f"factorize needs >= 3 frames and >= 4 points linked by observations; reached "
                                 f"{int(f_ok.sum())} frames and {int(p_ok.sum())} points")
    notes: list[str] = []
    metric = metric_frame(motion, shape, translation, f_ok, p_ok, notes)
    depth_determined = not notes
    motion, shape, translation = metric.motion, metric.shape, metric.translation
    residual = _residuals(motion, translation, shape, frame, point, xy)
    used = np.isfinite(residual) & ~rejected
    return _reconstruction(observations, motion, translation, shape, residual, used, rejected, metric.metric_matrix,
                           depth_determined, min_views, max_std_ratio, iterations,
                           _notes(start, notes, f_ok, p_ok, rejected, threshold, converged, iterations))


def _notes(start: SequentialFactors, notes: list[str], f_ok: np.ndarray, p_ok: np.ndarray, rejected: np.ndarray,
           threshold: float, converged: bool, iterations: int) -> list[str]:
    frames, points = f_ok.size, p_ok.size
    said = [f"factorized frame by frame from frames {start.initial_start}-{start.initial_start + start.initial_frames - 1} "
            f"(the sequential path: {frames} frames x {points} tracks are too many for one dense array), refined over "
            f"all {rejected.size} observations"]
    if rejected.any():
        said.append(f"{int(rejected.sum())} observations ({rejected.mean():.2%}) farther than {threshold:.3g} px "
                    f"({OUTLIER_SIGMAS:g} robust σ) from the fit were rejected as outliers")
    if not converged:
        said.append(f"the refinement stopped after {iterations} iterations without converging")
    if not f_ok.all():
        said.append(f"{int((~f_ok).sum())} frame(s) not linked to the reconstructed points: left NaN")
    if not p_ok.all():
        said.append(f"{int((~p_ok).sum())} point(s) seen in fewer than 2 reconstructed frames or not linked: left NaN")
    return said + notes


def _reconstruction(observations: Observations, motion: np.ndarray, translation: np.ndarray, shape: np.ndarray,
                    residual: np.ndarray, used: np.ndarray, rejected: np.ndarray, metric_matrix: np.ndarray,
                    depth_determined: bool, min_views: int, max_std_ratio: float, iterations: int,
                    notes: list[str]) -> Reconstruction:
    """Each point's covariance and verdict, and the record, from the final factors."""
    frame, point = observations.frame, observations.point
    n_points = observations.shape[1]
    f_ok, p_ok = np.isfinite(motion).all(axis=(1, 2)), np.isfinite(shape).all(axis=1)
    views = np.bincount(point[used], minlength=n_points).astype(np.int64)
    squared = np.bincount(point[used], weights=residual[used] ** 2, minlength=n_points)
    reprojection_rms = np.where(views > 0, np.sqrt(squared / np.maximum(views, 1)), np.nan)
    dof = 2 * int(used.sum()) - (3 * int(p_ok.sum()) + 8 * int(f_ok.sum()) - GAUGE_PARAMETERS)
    noise_var = float(squared.sum()) / dof if dof > 0 else np.nan
    normal = point_normal_equations(motion, np.zeros_like(translation), frame[used], point[used],
                                    np.zeros((int(used.sum()), 2)), n_points).normal
    covariances = np.full((n_points, 3, 3), np.nan)
    solvable = p_ok & (views >= 2) & np.isfinite(noise_var)
    if solvable.any():
        eigenvalues, eigenvectors = np.linalg.eigh(normal[solvable])
        floor = np.maximum(eigenvalues[:, -1:], np.finfo(float).tiny) * 1e-15  # as the dense path's covariances
        inverse = (eigenvectors / np.maximum(eigenvalues, floor)[:, None, :]) @ eigenvectors.transpose(0, 2, 1)
        covariances[solvable] = noise_var * inverse
    seen = np.bincount(point[f_ok[frame]], minlength=n_points)
    uncertainty = judge_points(shape, covariances, views, seen, reprojection_rms, noise_var, dof, p_ok,
                               min_views=min_views, max_std_ratio=max_std_ratio, depth_determined=depth_determined)
    cameras = affine_cameras(motion, translation)
    return Reconstruction(
        kind="affine",
        method="sequential",
        camera_model="affine",
        projections=cameras.projections,
        rotations=cameras.rotations,
        frame_status=cameras.frame_status,
        points=shape,
        point_covariances=uncertainty.covariances,
        point_status=uncertainty.status,
        views=uncertainty.views,
        point_reprojection_rms=uncertainty.reprojection_rms,
        covariance_gauge=AFFINE_GAUGE,
        observations=Observations.from_sparse(observations.shape, frame, point, observations.xy, used=used,
                                              residual=residual, rejected=rejected),
        noise=NoiseEstimate(std=uncertainty.noise_std, estimated=True, degrees_of_freedom=uncertainty.dof, unit="px"),
        reprojection_rms=float(np.sqrt(squared.sum() / max(int(used.sum()), 1))),
        details=AffineDetails(singular_values=np.zeros(0), iterations=iterations, metric_matrix=metric_matrix,
                              weighted=False, shape_radius=uncertainty.radius_px, min_views=uncertainty.min_views,
                              max_std_ratio=uncertainty.max_std_ratio),
        warnings=(*uncertainty.warnings, *notes),
    )
