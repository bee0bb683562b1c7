"""Affine factors of a long sequence by resection and intersection, frame after frame (affine visual odometry).

The :data:`INITIAL_FRAMES` consecutive frames that most tracks span (among the first few hundred) are
factorized in closed form from the tracks seen in all of them; that fixes the one affine frame of the
whole sequence.  Every other frame, going backwards from them to the first frame and then forwards to
the last, is

* *resected*: its 2 × 4 affine camera [M_f | t_f] fitted by trimmed, weighted least squares to the
  points it sees that are already well determined (seen in :data:`RESECTION_VIEWS` frames, their own
  fit consistent with the noise), with the errors of those points allowed for: each weighted by
  σ² / (σ² + its projected covariance), and their covariances σ² N_p⁻¹ taken out of the normal
  matrix (plain least squares on noisy points shrinks the camera in their poorly seen directions);
* *intersected*: each point it sees adds M_fᵀ M_f and M_fᵀ (x − t_f) to its 3 × 3 normal equations
  and is solved again, so it is the least-squares point over all its frames so far (an observation
  the resection found farther than 4 σ from a trusted point's prediction is held out).

Only new cameras are solved from known points and new points from known cameras: nothing is
estimated between pieces of the sequence.  The estimate still drifts as visual odometry does: each
camera's step along the poorly seen parallax direction is a little wrong, and the errors of the
points it then places carry into the next cameras.  Every :data:`_REGAUGE_FRAMES` frames the affine
gauge is moved, exactly, to one where the latest camera rows are orthonormal on average and the
latest points centred (far along the sequence the first gauge's numbers lose their precision).  The
work per frame is a few small array operations over the points that frame sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import NotEnoughDataError
from . import factorization

__all__ = ["INITIAL_FRAMES", "OUTLIER_SIGMAS", "RESECTION_VIEWS", "SequentialFactors", "robust_sigma",
           "sequential_factors"]

#: Frames of the closed-form factorization that starts the sequence.
INITIAL_FRAMES = 10
#: A point takes part in resecting a frame when seen in at least this many frames already (or, when
#: fewer than :data:`_ENOUGH_POINTS` of a frame's are, in :data:`_FEWEST_VIEWS`): a point seen in a
#: few nearby frames is poorly placed along the parallax direction, and a camera fitted to such points
#: takes a wrong step along it — the steps' errors compound along the sequence.  (On the sliding
#: benchmark scene 5 gave the lowest reprojection RMS of 3, 5, 8 and 12; 3 let the gauge run away.)
RESECTION_VIEWS = 5
_FEWEST_VIEWS = 3
_ENOUGH_POINTS = 16
# Fewest such points a frame is resected from (4 × 2 unknowns; a margin against outliers).
_MIN_RESECTION_POINTS = 8
# The initial window is the best spanned one starting among this many first frames.
_INITIAL_SEARCH = 500
_INITIAL_ITERATIONS = 200
_INITIAL_TOL = 1e-10
#: An observation farther from the fit than this many robust σ (:func:`robust_sigma`) is an outlier: 1 in 3 000
#: of Gaussian observations is.  The resection's test and the long sequence's global one.
OUTLIER_SIGMAS = 4.0
# The floor of σ (exact data).
_MIN_SIGMA = 1e-3
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
_RESECTION_ROUNDS = 5
# Every this many frames resected the affine gauge is refitted to the latest of them (exactly: no estimate).
_REGAUGE_FRAMES = 64
# A camera row this large in the last gauge has drifted beyond the precision of one gauge for the sequence.
_FAR = 1e100
# A point's normal matrix whose smallest / largest eigenvalue is below this is not solved.
_CONDITION = 1e-14


@dataclass(frozen=True)
class SequentialFactors:
    """Affine factors of a sequence, x_fp ≈ M_f S_p + t_f, in one affine gauge for all of it (the camera rows'
    second moments the identity, the points centred).

    Attributes
    ----------
    motion : (F, 2, 3) camera rows M_f, NaN for a frame not resected.
    translation : (F, 2) t_f, NaN likewise.
    shape : (P, 3) S_p, NaN for a point seen in fewer than two resected frames.
    rejected : (N,) observations held out as outliers (in the order given).
    sigma : robust σ of one image coordinate, from the initial factorization (px).
    initial_start, initial_frames : the first frame and number of frames of the initial factorization.
    resected : frames resected after it.
    """

    motion: np.ndarray
    translation: np.ndarray
    shape: np.ndarray
    rejected: np.ndarray
    sigma: float
    initial_start: int
    initial_frames: int
    resected: int


def robust_sigma(residual: np.ndarray) -> float:
    """σ of one coordinate from 2-D residual lengths (their median is σ √(2 ln 2), the Rayleigh median), at least
    10⁻³; NaN lengths are left out.

    Examples
    --------
    >>> round(robust_sigma(np.array([1.0, np.sqrt(2 * np.log(2)), 5.0, np.nan])), 6)
    1.0
    """
    finite = residual[np.isfinite(residual)]
    return max(float(np.median(finite)) / _RAYLEIGH_MEDIAN, _MIN_SIGMA) if finite.size else _MIN_SIGMA


def _initial_fit(entries: np.ndarray, point: np.ndarray, frame: np.ndarray, xy: np.ndarray, n_frames: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Cameras of the initial frames (NaN elsewhere), the observations it rejected, and σ.

    The tracks seen in every one of the frames ``entries`` cover form a complete block, factorized in
    closed form (the exact least-squares fit: the missing-data iterations converge slowly on short
    tracks along the poorly seen depth direction); a track with an observation farther than the
    residual test's bound is left out and the block factorized again.
    """
    frames = np.unique(frame[entries])
    _, inverse, counts = np.unique(point[entries], return_inverse=True, return_counts=True)
    entries = entries[counts[inverse] == frames.size]
    rejected = np.zeros(entries.size, dtype=bool)
    for attempt in range(3):
        kept = entries[~rejected]
        points, local_p = np.unique(point[kept], return_inverse=True)
        if points.size < 4 or frames.size < 3:
            raise NotEnoughDataError(f"factorize needs >= 4 tracks seen in each of the first {frames.size} frames "
                                     f"(>= 3); {points.size} are")
        local_f = np.searchsorted(frames, frame[kept])
        block = np.empty((frames.size, points.size, 2))
        block[local_f, local_p] = xy[kept]
        fit = factorization._general_fit(block, None, _INITIAL_ITERATIONS, _INITIAL_TOL, 0, [], None)
        motion, translation = fit.motion, fit.translation
        predicted = np.einsum("fci,pi->fpc", motion, fit.shape) + translation[:, None]
        residual = np.linalg.norm(predicted - block, axis=2)
        sigma = robust_sigma(residual.ravel())
        bad_track = (residual > OUTLIER_SIGMAS * sigma).any(axis=0)
        if not bad_track.any() or attempt == 2:
            break
        rejected |= np.isin(point[entries], points[bad_track])
    all_motion, all_translation = np.full((n_frames, 2, 3), np.nan), np.full((n_frames, 2), np.nan)
    all_motion[frames], all_translation[frames] = motion, translation
    return all_motion, all_translation, sigma


def _initial_window(frame: np.ndarray, point: np.ndarray, n_frames: int, n_points: int) -> int:
    """First of the :data:`INITIAL_FRAMES` frames (starting among the first :data:`_INITIAL_SEARCH`) most tracks span."""
    first = np.full(n_points, n_frames, dtype=np.int64)
    last = np.full(n_points, -1, dtype=np.int64)
    np.minimum.at(first, point, frame)
    np.maximum.at(last, point, frame)
    starts = np.arange(int(frame.min()) if frame.size else 0, max(n_frames - INITIAL_FRAMES, 0) + 1)[:_INITIAL_SEARCH]
    spanned = [int(np.count_nonzero((first <= s) & (last >= s + INITIAL_FRAMES - 1))) for s in starts.tolist()]
    return int(starts[int(np.argmax(spanned))]) if spanned else 0


class _Points:
    """Every point's running normal equations Σ MᵀM, Σ Mᵀ(x − t) and views, its solution and its fit's cost.

    The cost (the sum of squared residuals of its least-squares fit, in px²) is accumulated from each new
    observation's innovation, r = x − M S − t weighted by (I + M N⁻¹ Mᵀ)⁻¹ (recursive least squares): the
    same number as Σ|x − t|² − Σ (x − t)ᵀ M S, which loses every digit when the affine gauge makes M S large.
    """

    def __init__(self, n_points: int) -> None:
        self.normal = np.zeros((n_points, 3, 3))
        self.rhs = np.zeros((n_points, 3))
        self.cost = np.zeros(n_points)
        self.views = np.zeros(n_points, dtype=np.int64)
        self.shape = np.full((n_points, 3), np.nan)

    def add(self, points: np.ndarray, motion: np.ndarray, translation: np.ndarray, xy: np.ndarray) -> None:
        """Add one observation of each of ``points`` (distinct) by cameras ``motion`` (n, 2, 3), and re-solve them."""
        centred = xy - translation
        solved = np.isfinite(self.shape[points, 0])
        if solved.any():
            p, m = points[solved], motion[solved]
            innovation = centred[solved] - np.einsum("nci,ni->nc", m, self.shape[p])
            spread = m @ np.linalg.solve(self.normal[p], m.transpose(0, 2, 1))
            weight = np.linalg.inv(np.eye(2) + spread)
            self.cost[p] += np.einsum("nc,ncd,nd->n", innovation, weight, innovation)
        self.normal[points] += np.einsum("nci,ncj->nij", motion, motion)
        self.rhs[points] += np.einsum("nci,nc->ni", motion, centred)
        self.views[points] += 1
        again = points[self.views[points] >= 2]
        normal = self.normal[again]
        eigenvalues = np.linalg.eigvalsh(normal)
        ok = eigenvalues[:, 0] > _CONDITION * np.maximum(eigenvalues[:, -1], np.finfo(float).tiny)
        self.shape[again[ok]] = np.linalg.solve(normal[ok], self.rhs[again[ok]][..., None])[..., 0]

    def trusted(self, points: np.ndarray, sigma: float, least_views: int) -> np.ndarray:
        """Which ``points`` are solved, seen ``least_views`` times, and fit their own observations to the noise."""
        views = self.views[points]
        solved = np.isfinite(self.shape[points, 0]) & (views >= least_views)
        return solved & (self.cost[points] <= sigma**2 * (3.0 * (2 * views - 3) + 9.0))

    def regauge(self, mixing: np.ndarray, origin: np.ndarray) -> None:
        """Move every point into the affine gauge S' = A⁻¹ (S − b) of cameras M' = M A, t' = t + M b
        (``mixing`` = A, ``origin`` = b)."""
        self.rhs = (self.rhs - self.normal @ origin) @ mixing
        self.normal = mixing.T @ self.normal @ mixing
        self.shape = np.linalg.solve(mixing, (self.shape - origin).T).T

    def covariance(self, points: np.ndarray, sigma: float) -> np.ndarray:
        return sigma**2 * np.linalg.inv(self.normal[points])


def _centre(shape: np.ndarray) -> np.ndarray:
    """The mean of the solved points of ``shape`` (n, 3), the origin when none is."""
    solved = np.isfinite(shape[:, 0])
    return shape[solved].mean(axis=0) if solved.any() else np.zeros(3)


def _whitening(rows: np.ndarray) -> np.ndarray:
    """A with the camera ``rows`` (n, 3) @ A of identity second moments (the affine gauge fitting them)."""
    eigenvalues, eigenvectors = np.linalg.eigh(rows.T @ rows / len(rows))
    return (eigenvectors / np.sqrt(np.maximum(eigenvalues, np.finfo(float).tiny))) @ eigenvectors.T


def _resect(shape: np.ndarray, covariance: np.ndarray, xy: np.ndarray, sigma: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """One frame's (M, t) from points ``shape`` (k, 3) of ``covariance`` (k, 3, 3) seen at ``xy``, and its inliers.

    Trimmed least squares: the first rounds keep the observations within a few median residuals (a
    gross error pulls the first fit), the last those within the residual test's bound.
    """
    h = np.hstack([shape, np.ones((len(shape), 1))])
    keep = np.ones(len(shape), dtype=bool)
    weight = np.ones(len(shape))
    for round_ in range(_RESECTION_ROUNDS):
        w = weight * keep
        normal = (h * w[:, None]).T @ h
        corrected = normal.copy()
        # E[ĥĥᵀ] = hhᵀ + Cov: take the points' errors out
        corrected[:3, :3] -= np.einsum("n,nij->ij", w, covariance)
        rhs = (h * w[:, None]).T @ xy
        try:
            np.linalg.cholesky(corrected)
            solution = np.linalg.solve(corrected, rhs)
        except np.linalg.LinAlgError:
            try:
                solution = np.linalg.solve(normal, rhs)
            except np.linalg.LinAlgError:
                return None
        motion = solution[:3].T
        residual = np.linalg.norm(h @ solution - xy, axis=1)
        spread = np.einsum("ci,nij,cj->n", motion, covariance, motion)  # the points' own error, projected
        weight = sigma**2 / (sigma**2 + 0.5 * spread)  # generalised least squares: a vaguer point counts less
        bound = OUTLIER_SIGMAS**2 * (sigma**2 + spread)
        if round_ < _RESECTION_ROUNDS - 2:
            bound = np.maximum(bound, (3.0 * float(np.median(residual[keep]))) ** 2)
        inside = residual**2 <= bound
        if inside.sum() < _MIN_RESECTION_POINTS:
            return None
        if np.array_equal(inside, keep) and round_ >= _RESECTION_ROUNDS - 2:
            break
        keep = inside
    return motion, solution[3], keep


def sequential_factors(frame: np.ndarray, point: np.ndarray, xy: np.ndarray, shape: tuple[int, int]
                       ) -> SequentialFactors:
    """Affine factors of observations ``frame``, ``point`` (N,) at ``xy`` (N, 2), frame after frame.

    Frames are taken in their order (the observations' first axis is the sequence); each pair
    (frame, point) is observed at most once.  See the module notes.

    Raises
    ------
    NotEnoughDataError
        The first :data:`INITIAL_FRAMES` frames do not determine an affine reconstruction.

    Examples
    --------
    A camera turning slowly past 200 tracks of 15 frames each over 150 frames:

    >>> rng = np.random.default_rng(0)
    >>> start = rng.integers(0, 135, 200)
    >>> frame = np.concatenate([np.arange(s, s + 15) for s in start]); point = np.repeat(np.arange(200), 15)
    >>> world = rng.normal(0, 50, (200, 3))
    >>> a = np.radians(0.3 * np.arange(150)); z, o = np.zeros(150), np.ones(150)
    >>> rows = np.stack([np.c_[np.cos(a), z, np.sin(a)], np.c_[z, o, z]], axis=1)
    >>> xy = np.einsum("nci,ni->nc", rows[frame], world[point]) + rng.normal(0, 0.5, (frame.size, 2))
    >>> fit = sequential_factors(frame, point, xy, (150, 200))
    >>> predicted = np.einsum("nci,ni->nc", fit.motion[frame], fit.shape[point]) + fit.translation[frame]
    >>> int(np.isfinite(fit.motion[:, 0, 0]).sum()), bool(np.nanmedian(np.linalg.norm(predicted - xy, axis=1)) < 1)
    (142, True)
    """
    n_frames, n_points = shape
    order = np.argsort(frame, kind="stable")
    frame_s, point_s, xy_s = frame[order], point[order], xy[order]
    bounds = np.searchsorted(frame_s, np.arange(n_frames + 1))
    start = _initial_window(frame_s, point_s, n_frames, n_points)
    end = min(start + INITIAL_FRAMES, n_frames)
    rejected_s = np.zeros(frame_s.size, dtype=bool)
    motion, translation, sigma = _initial_fit(np.arange(bounds[start], bounds[end]), point_s, frame_s, xy_s, n_frames)
    points = _Points(n_points)
    for f in range(start, end):
        taken = np.arange(bounds[f], bounds[f + 1])
        points.add(point_s[taken], np.broadcast_to(motion[f], (taken.size, 2, 3)), translation[f], xy_s[taken])
    resected = 0
    recent: list[int] = list(range(start, end))
    for f in [*range(start - 1, -1, -1), *range(end, n_frames)]:
        if f == end:
            recent = list(range(start, end))
        if len(recent) >= _REGAUGE_FRAMES:
            # the camera rows drift far from the initial gauge's (the parallax direction grows with the
            # distance travelled); the points' normal equations would lose precision there
            window = recent[-_REGAUGE_FRAMES:]
            mixing = _whitening(motion[window].reshape(-1, 3))
            origin = _centre(points.shape[point_s[bounds[min(window)]:bounds[max(window) + 1]]])
            translation = translation + motion @ origin
            motion = motion @ mixing
            points.regauge(mixing, origin)
            recent = recent[-_REGAUGE_FRAMES // 2:]
        lo, hi = bounds[f], bounds[f + 1]
        seen, at = point_s[lo:hi], xy_s[lo:hi]
        trusted = points.trusted(seen, sigma, RESECTION_VIEWS)
        if trusted.sum() < _ENOUGH_POINTS:
            trusted = points.trusted(seen, sigma, _FEWEST_VIEWS)
        if trusted.sum() < _MIN_RESECTION_POINTS:
            continue
        covariance = points.covariance(seen[trusted], sigma)
        camera = _resect(points.shape[seen[trusted]], covariance, at[trusted], sigma)
        if camera is None:
            continue
        m, t, inliers = camera
        motion[f], translation[f] = m, t
        resected += 1
        recent.append(f)
        # an observation a trusted point does not predict stays out of the points' equations
        outlier = np.zeros(seen.size, dtype=bool)
        outlier[np.flatnonzero(trusted)[~inliers]] = True
        rejected_s[lo:hi] = outlier
        taken = ~outlier
        points.add(seen[taken], np.broadcast_to(m, (int(taken.sum()), 2, 3)), t, at[taken])
    # one gauge for the whole sequence: the camera rows' second moments the identity, the points centred
    reached = np.isfinite(motion).all(axis=(1, 2)) & (np.abs(motion).max(axis=(1, 2), initial=0.0) < _FAR)
    motion[~reached], translation[~reached] = np.nan, np.nan  # beyond float64's reach of the last gauge: lost
    mixing = _whitening(motion[reached].reshape(-1, 3))
    origin = _centre(points.shape)
    translation = translation + motion @ origin
    motion = motion @ mixing
    points.regauge(mixing, origin)
    rejected = np.empty_like(rejected_s)
    rejected[order] = rejected_s
    return SequentialFactors(motion, translation, points.shape, rejected, sigma, start, end - start, resected)
