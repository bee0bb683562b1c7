"""Shape and motion from image tracks: Tomasi–Kanade factorization with a metric upgrade.

Model (orthographic camera, report section 3): the image position of point p
in frame f is x_fp = M_f S_p + t_f with M_f = [i_f; j_f] the first two rows of
the camera rotation, S_p the 3D point and t_f the image of the centroid.
Stacking the centred coordinates of all frames gives W (2F × P) = R S, of
rank 3.

Complete data, no weights (the report's algorithm):

1. centre each frame: W = x − t with t_f the mean of frame f's points;
2. rank-3 truncation W ≈ U′ D′ V′ᵀ (LAPACK for small W; for large W the
   certified subspace iteration of :mod:`~kalmansfm.structure.affine._measurement`, which
   reads the (F, P, 2) array itself where it lies — W is never built, the centring happens
   inside its passes and its last pass also sums each point's squared residuals);
3. affine factors R* = U′ D′^½ and S* = D′^½ V′ᵀ;
4. metric upgrade: the symmetric A = Q Qᵀ (6 unknowns) from the linear
   least-squares system i*ᵀ A i* = 1, j*ᵀ A j* = 1, i*ᵀ A j* = 0 over all frames;
   Q by Cholesky; R = R* Q, S = Q⁻¹ S*;
5. gauge: rotate so that frame 0's rows are the camera x and y axes.

Missing data (NaN) or weights: the same model is fitted by weighted alternating
least squares (ALS, :mod:`~kalmansfm.structure.affine._als`) over the observed entries only,
with the translation t_f as unknowns (a frame centroid is meaningless when points are missing):

1. initialise from the largest complete block of frames × points (found
   greedily by dropping the frame or the points with the most holes), factored as
   above without the metric step;
2. extend: solve every point seen in ≥ 2 known frames (3 unknowns), every frame
   seeing ≥ 4 known points (8 unknowns), and repeat until nothing new is reached;
3. refine: alternate the two batched linear least-squares steps (points given
   frames: a 3 × 3 system per point; frames given points: a 4 × 4 system per
   image row) until the weighted cost stops decreasing;
4. metric upgrade and gauge as above; the shape is finally re-centred.

Points or frames that are never reached (too few observations, or not linked to
the rest) come out as NaN and are named in ``warnings``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from threadpoolctl import threadpool_limits

from ...errors import InvalidInputError, NotEnoughDataError
from ..._validation import as_float_array, check_count
from ._als import row_blocks, weighted_als
from .lowrank import truncated_svd

__all__ = ["DEFAULT_MAX_ITERATIONS", "AffineFactors", "MetricFrame", "factor_affine", "metric_frame", "metric_upgrade"]

# The large sums of a factorization are numba kernels; its BLAS and LAPACK calls are small or
# medium (SVDs of a few hundred rows, thin products): BLAS threads only add synchronisation, and on
# a busy machine waiting for them costs far more than the work (measured at load 7 on the 2 shared
# cores: an 80 × 700 SVD 0.3–3.6 s with 2 OpenBLAS threads, 0.01 s with one).
single_threaded_blas = threadpool_limits.wrap(limits=1, user_api="blas")

#: Default cap on the alternating least-squares iterations (missing data or weights).
DEFAULT_MAX_ITERATIONS = 500

# Frames × points up to which the complete-data path uses a full LAPACK SVD.
_LAPACK_LIMIT = 2_000_000
# Largest principal angle (rad) to the exact rank-3 subspace certified for large complete input.
_SUBSPACE_TOL = 1e-9
# σ₃ / σ₄ below this: W is not convincingly rank 3.
_RANK_GAP = 2.0
# Shape thinner than this (smallest / largest spread) is called coplanar.
_FLAT_RATIO = 1e-3
# Condition number of the metric system above this: too little rotation to fix depth.
_METRIC_CONDITION = 1e7


@dataclass(frozen=True, eq=False)
class AffineFactors:
    """Shape and affine camera motion fitted to image tracks: what :func:`factor_affine` returns.

    :func:`~kalmansfm.structure.factorize` turns it, with each point's covariance, into the
    :class:`~kalmansfm.structure.Reconstruction` every method returns.

    Attributes
    ----------
    points : (P, 3) float — the shape S, centred on its centroid, in the gauge where
        frame 0's camera rows are the x and y axes. NaN for a point that could not be
        reconstructed.
    motion : (F, 2, 3) float — rows i_f and j_f of each frame's camera (unit length and
        orthogonal up to noise). NaN for a frame that could not be reconstructed.
    translation : (F, 2) float — image position of the shape's centroid in each frame.
    singular_values : (k,) float — leading singular values of the centred 2F × P
        measurement matrix (with missing data: of the matrix completed by the model).
    residual_rms : float — RMS over observed (frame, point) pairs of the 2D distance
        between observed and reprojected positions, in pixels.
    point_residual_sums : (P,) float — each point's sum over the frames that used it of the
        squared distances, pixels² (0 for a point not reconstructed).
    residuals : (F, P) float — the distances themselves; NaN where not observed. float32 when
        ``positions`` was a float32 array, else float64. For large complete input they are
        computed from ``positions`` and the model on first access (an array half the size
        of the input that the fit itself does not need).
    observed : (F, P) bool — which entries were used (for large complete input, where all
        were, a read-only all-True view that takes no memory).
    warnings : tuple of str — degeneracies, fallbacks and dropped frames/points.
    method : ``"svd"`` (closed form, complete unweighted data) or ``"als"``.
    iterations : ALS iterations run (0 for ``"svd"``).
    metric_matrix : (3, 3) — A = Q Qᵀ actually used (after any positive-definite repair),
        in the affine gauge of R*.
    depth_determined : False when the factorization warned that depth is not determined
        (W not clearly rank 3, an ill-conditioned or repaired metric upgrade, a (nearly)
        coplanar or collinear shape): no point's depth is then to be trusted.
    """

    points: np.ndarray
    motion: np.ndarray
    translation: np.ndarray
    singular_values: np.ndarray
    residual_rms: float
    point_residual_sums: np.ndarray
    observed: np.ndarray
    warnings: tuple[str, ...]
    method: str
    iterations: int
    metric_matrix: np.ndarray
    depth_determined: bool = True
    # the (F, P) distances when the fit measured them; else the positions to measure them from
    _residuals: np.ndarray | None = field(default=None, repr=False)
    _positions: np.ndarray | None = field(default=None, repr=False)
    _residual_dtype: np.dtype = field(default=np.dtype(np.float64), repr=False)

    @cached_property
    def residuals(self) -> np.ndarray:
        """(F, P) distances between observed and reprojected positions (see the class notes)."""
        if self._residuals is not None:
            return self._residuals
        assert self._positions is not None
        return _reprojection_residuals(self._positions, None, self.motion, self.points, self.translation,
                                       self._residual_dtype).residuals

    def reprojected(self) -> np.ndarray:
        """(F, P, 2) image positions predicted by the model, M_f S_p + t_f."""
        return (np.matmul(self.motion, self.points.T) + self.translation[:, :, None]).transpose(0, 2, 1)



@single_threaded_blas
def factor_affine(
    positions: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    tol: float = 1e-10,
    rng: np.random.Generator | int | None = 0,
    progress: Callable[[int, int], object] | None = None,
) -> AffineFactors:
    """Fit 3D shape and affine camera motion to point tracks (Tomasi–Kanade); the core of :func:`~kalmansfm.structure.factorize`.

    Parameters
    ----------
    positions : (F, P, 2) float — x = column, y = row of point p in frame f; NaN where the
        point is not observed. Needs F ≥ 3 frames and P ≥ 4 points. Only read, never
        modified. Large complete input without weights (2F·P > 2·10⁶) is used where it
        lies: a float64 or float32 array that is C-ordered or (F, 2, P) in memory (as
        ``(R[:, :2] @ S.T).transpose(0, 2, 1)`` makes it) is neither copied nor converted
        (float32 stays float32 in memory; the arithmetic is float64), and neither a 2F × P
        matrix nor an (F, P) array is made: the peak memory beyond the input is the start's
        samples and a few arrays of P numbers (5 % of the input at 1000 × 100 000). Other
        dtypes or layouts are converted once. No ``copy=False`` option is needed: there is
        no copy to avoid.
    weights : (F, P) or (F, P, 2) float ≥ 0, optional — per-entry least-squares weights,
        typically 1 / σ² from the tracker's posterior standard deviations. A zero weight
        ignores the entry. Without weights every observation counts equally.
    max_iterations : ALS iteration cap (missing data or weights).
    tol : ALS stops when the weighted cost decreases by less than this fraction.
    rng : seed or generator for the randomized SVD of large complete inputs.
    progress : callable, optional — called after each ALS iteration with (iterations done,
        ``max_iterations``), e.g. to drive a progress bar; the ALS usually stops well before
        ``max_iterations``. Not called by the closed form (no iterations). Default: silent.

    Returns
    -------
    AffineFactors

    Notes
    -----
    The result is defined up to the ambiguities of orthographic projection: a rotation
    (fixed here by making frame 0's camera rows the x and y axes), and the *mirror*
    (Necker) ambiguity — the depth-reversed shape ``points * (1, 1, -1)`` with motion
    ``motion * (1, 1, -1)`` reproduces every image identically, so no data can decide
    between them. One of the two is returned; :meth:`~kalmansfm.structure.Reconstruction.mirrored` gives
    the other. The scale is fixed by unit-length camera rows (pixels).

    The closed form (no NaN, no weights) is the report's algorithm; otherwise the fit is
    weighted alternating least squares over the observed entries (see the module notes).
    For large complete input the rank-3 subspace is certified to 1e-9 rad (Davis–Kahan
    bound) and each point's squared residuals are summed in the same pass over ``positions``
    (the reprojection M S + t equals the rank-3 part of W plus the centroids). The first
    such call in a new environment compiles three numba kernels (a few seconds, cached on
    disk); so does the first ALS of large input (2F·P > 2·10⁶; two kernels).
    Degenerate input is flagged in ``warnings`` rather than raised: a rank-2 W (coplanar
    points, or no rotation out of the image plane), a flat shape, a metric system too
    ill-conditioned to fix depth, and a non-positive-definite A (replaced by the nearest
    positive-definite matrix).

    Raises
    ------
    InvalidInputError
        Wrong shape, infinite values, negative or non-finite weights, ``max_iterations``
        below 1 or a negative ``tol``.
    NotEnoughDataError
        Fewer than 3 usable frames or 4 usable points, or all points at one place in every frame.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> shape = rng.normal(size=(8, 3)) * 10
    >>> frames = [np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(5)]
    >>> tracks = np.stack([shape @ m.T + [100, 50] for m in frames])
    >>> rec = factor_affine(tracks)
    >>> rec.points.shape, rec.motion.shape, rec.residual_rms < 1e-9
    ((8, 3), (5, 2, 3), True)
    >>> rows = rec.motion @ rec.motion.transpose(0, 2, 1)
    >>> bool(np.allclose(rows, np.eye(2)))
    True
    """
    max_iterations = check_count("max_iterations", max_iterations, 1)
    if not (np.isfinite(tol) and tol >= 0):
        raise InvalidInputError(f"tol must be a finite number >= 0; got {tol!r}")
    notes: list[str] = []
    fit = _streamed_closed_form(positions, weights, rng, notes)
    if fit is None:
        fit = _general_fit(positions, weights, max_iterations, tol, rng, notes, progress)
    f_ok, p_ok, motion_aff, shape_aff = fit.f_ok, fit.p_ok, fit.motion, fit.shape
    if not fit.singular_values[0] > 0:
        raise NotEnoughDataError(
            "factorize needs points that spread out; in every frame all observed points are at one place"
        )
    before = len(notes)
    _check_rank(fit.singular_values, motion_aff[f_ok], shape_aff[p_ok], notes)

    metric = metric_frame(motion_aff, shape_aff, fit.translation, f_ok, p_ok, notes)
    motion, shape, translation, a_matrix = metric.motion, metric.shape, metric.translation, metric.metric_matrix
    # the rank, metric and shape checks each add a note when the depth is not determined
    depth_determined = len(notes) == before

    frames, points = fit.positions.shape[:2]
    full_motion = np.full((frames, 2, 3), np.nan)
    full_translation = np.full((frames, 2), np.nan)
    full_points = np.full((points, 3), np.nan)
    f_index, p_index = np.flatnonzero(fit.use_f)[f_ok], np.flatnonzero(fit.use_p)[p_ok]
    full_motion[f_index] = motion[f_ok]
    full_translation[f_index] = translation[f_ok]
    full_points[p_index] = shape[p_ok]

    if fit.point_residual_sums is None:
        measured = _reprojection_residuals(fit.positions, fit.observed, full_motion, full_points, full_translation,
                                           fit.residual_dtype)
        residuals, used, point_sums = measured.residuals, measured.used, measured.point_sums
        residual_rms = measured.rms
        positions_kept = None
    else:
        # Complete data: the reprojection M S + t is the rank-3 part of W plus the centroids
        # (the upgrade and the gauge only re-parametrise it), so the squared distances summed
        # in the SVD's last pass are those of the reprojection residuals. The distances
        # themselves are measured only if asked for (AffineFactors.residuals).
        # every entry was used: a read-only all-True view rather than another (F, P) array
        residuals, used, point_sums = None, np.broadcast_to(np.True_, (frames, points)), fit.point_residual_sums
        residual_rms = float(np.sqrt(fit.residual_sum / (frames * points)))
        positions_kept = fit.positions
    return AffineFactors(
        points=full_points,
        motion=full_motion,
        translation=full_translation,
        singular_values=fit.singular_values,
        residual_rms=residual_rms,
        point_residual_sums=point_sums,
        observed=used,
        warnings=tuple(notes),
        method=fit.method,
        iterations=fit.iterations,
        metric_matrix=a_matrix,
        _residuals=residuals,
        _positions=positions_kept,
        _residual_dtype=fit.residual_dtype,
        depth_determined=depth_determined,
    )


@dataclass(frozen=True)
class _AffineFit:
    """Affine factors R* (``motion``), S* (``shape``) and ``translation`` on the usable frames
    (``use_f``) × points (``use_p``) of ``positions``, of which ``f_ok`` / ``p_ok`` were reached.
    ``point_residual_sums`` / ``residual_sum`` are set when the fit already measured them (complete data)."""

    positions: np.ndarray
    observed: np.ndarray | None
    use_f: np.ndarray
    use_p: np.ndarray
    f_ok: np.ndarray
    p_ok: np.ndarray
    motion: np.ndarray
    shape: np.ndarray
    translation: np.ndarray
    singular_values: np.ndarray
    method: str
    iterations: int
    residual_dtype: np.dtype
    point_residual_sums: np.ndarray | None = None
    residual_sum: float = 0.0


def _streamed_closed_form(positions: object, weights: object, rng: object, notes: list[str]) -> _AffineFit | None:
    """The closed form straight from a large complete (F, P, 2) array, or None (general path).

    W is never built: :func:`~kalmansfm.structure.affine._measurement.streamed_rank` reads
    ``positions`` three times where it lies (a float32 array stays float32 in memory; the
    sums are float64; other dtypes, and layouts the kernels do not read, are converted
    once). Returns None for small input, weights, or as soon as a NaN or an infinity
    is met.
    """
    if weights is not None or not isinstance(positions, np.ndarray) or positions.ndim != 3:
        return None
    if positions.dtype.kind not in "fiu":  # others (and their errors) are the general path's
        return None
    frames, points, coordinates = positions.shape
    if coordinates != 2 or frames < 3 or points < 4 or 2 * frames * points <= _LAPACK_LIMIT:
        return None
    # Imported here: numba (≈ 0.2 s to import) is only needed once an input is this large.
    from ._measurement import readable_in_place, streamed_rank

    dtype = positions.dtype if positions.dtype in (np.float32, np.float64) else np.dtype(np.float64)
    x = positions if readable_in_place(positions) else np.ascontiguousarray(positions, dtype=dtype)
    fit = streamed_rank(x, 3, tol=_SUBSPACE_TOL, max_passes=12, rng=np.random.default_rng(rng))
    if fit is None:
        return None
    if fit.angle_bound > _SUBSPACE_TOL and not fit.undetermined:
        notes.append(
            f"rank-3 subspace certified only to {fit.angle_bound:.2g} rad after {fit.passes} passes "
            f"(target {_SUBSPACE_TOL:g}; σ3 and σ4 too close)"
        )
    root = np.sqrt(fit.s)
    every_f, every_p = np.ones(frames, bool), np.ones(points, bool)
    return _AffineFit(
        positions=x, observed=None, use_f=every_f, use_p=every_p, f_ok=every_f, p_ok=every_p,
        motion=(fit.u * root).reshape(frames, 2, 3), shape=fit.vt.T * root, translation=fit.centroids,
        singular_values=np.concatenate([fit.s, fit.extra_singular_values]), method="svd", iterations=0,
        residual_dtype=dtype, point_residual_sums=fit.point_residual_sums, residual_sum=fit.residual_sum,
    )


def _general_fit(
    positions: object, weights: object, max_iterations: int, tol: float, rng: object, notes: list[str],
    progress: Callable[[int, int], object] | None,
) -> _AffineFit:
    """Validation, usable frames and points, then the closed form or weighted ALS."""
    residual_dtype = np.dtype(np.float32 if getattr(positions, "dtype", None) == np.float32 else np.float64)
    x, w, observed = _validate(positions, weights)
    if w is not None:
        observed &= (w > 0).any(axis=2)
    use_f, use_p = _usable(observed, notes)
    everything = bool(use_f.all() and use_p.all())

    def subset(a: np.ndarray) -> np.ndarray:
        return a if everything else a[np.ix_(use_f, use_p)]

    xs, obs = subset(x), subset(observed)
    complete = bool(obs.all())
    uniform = w is None or bool(np.ptp(subset(w)[obs]) == 0.0)
    if complete and uniform:
        motion_aff, shape_aff, translation, sv = _closed_form(xs, rng)
        method, iterations = "svd", 0
        f_ok, p_ok = np.ones(int(use_f.sum()), bool), np.ones(int(use_p.sum()), bool)
    else:
        motion_aff, shape_aff, translation, iterations, f_ok, p_ok = weighted_als(
            xs, None if w is None else subset(w), obs, max_iterations, tol, notes, progress
        )
        method = "als"
        sv = _completed_singular_values(xs, obs, motion_aff, shape_aff, translation, f_ok, p_ok, rng)
        if not f_ok.all():
            notes.append(f"{int((~f_ok).sum())} frame(s) not linked to the reconstructed points: left NaN")
        if not p_ok.all():
            notes.append(f"{int((~p_ok).sum())} point(s) not linked to the reconstructed frames: left NaN")
        if f_ok.sum() < 3 or p_ok.sum() < 4:
            raise NotEnoughDataError(
                f"factorize needs >= 3 frames and >= 4 points linked by observations; "
                f"reached {int(f_ok.sum())} frames and {int(p_ok.sum())} points"
            )
    return _AffineFit(
        positions=x, observed=observed, use_f=use_f, use_p=use_p, f_ok=f_ok, p_ok=p_ok, motion=motion_aff,
        shape=shape_aff, translation=translation, singular_values=sv, method=method, iterations=iterations,
        residual_dtype=residual_dtype,
    )


@dataclass(frozen=True)
class MetricFrame:
    """Affine factors moved into the metric frame: orthonormal camera rows, frame 0's as the X and Y axes.

    Attributes
    ----------
    motion : (F, 2, 3) camera rows R = R* Q in the gauge (NaN where the affine motion was).
    shape : (P, 3) S = Q⁻¹ S* in the same gauge, centred on the centroid of the points reached.
    translation : (F, 2) image of that centroid.
    metric_matrix : (3, 3) A = Q Qᵀ used (after any positive-definite repair).
    """

    motion: np.ndarray
    shape: np.ndarray
    translation: np.ndarray
    metric_matrix: np.ndarray


def metric_frame(motion_aff: np.ndarray, shape_aff: np.ndarray, translation: np.ndarray, f_ok: np.ndarray,
                 p_ok: np.ndarray, notes: list[str]) -> MetricFrame:
    """The metric upgrade of affine factors (frames ``f_ok`` and points ``p_ok`` reached), the gauge and the centring.

    Appends to ``notes`` when the metric system is ill-determined or repaired and when the
    shape comes out (nearly) coplanar.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> rows = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0][:2] for _ in range(6)])
    >>> mixing = rng.normal(size=(3, 3))
    >>> shape = rng.normal(size=(10, 3))
    >>> m = metric_frame(rows @ mixing, shape @ np.linalg.inv(mixing).T, np.zeros((6, 2)), np.ones(6, bool),
    ...                  np.ones(10, bool), [])
    >>> bool(np.allclose(m.motion[0], np.eye(3)[:2])), bool(np.allclose(m.motion @ m.shape.T + m.translation[..., None],
    ...                                                                  rows @ shape.T))
    (True, True)
    """
    a_matrix, q = metric_upgrade(motion_aff[f_ok].reshape(-1, 3), notes)
    motion = motion_aff @ q  # R = R* Q
    shape = np.linalg.solve(q, shape_aff.T).T  # S = Q⁻¹ S*
    # Gauge: the orthonormal 2 × 3 nearest to frame 0's rows becomes [I 0].
    first = int(np.flatnonzero(f_ok)[0])
    u, _, vt = np.linalg.svd(motion[first], full_matrices=False)
    axes = u @ vt
    basis = np.vstack([axes, np.cross(axes[0], axes[1])])  # rows: camera x, y, z of frame 0
    motion = motion @ basis.T
    shape = shape @ basis.T
    # Centre the shape; the shift goes into the translation: x = M (S − c) + (t + M c).
    centroid = shape[p_ok].mean(axis=0)
    shape = shape - centroid
    translation = translation + motion @ centroid
    _check_shape(shape[p_ok], notes)
    return MetricFrame(motion, shape, translation, a_matrix)


def metric_upgrade(affine_rows: np.ndarray, notes: list[str] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Solve the metric constraints for A = Q Qᵀ and return ``(A, Q)``.

    Parameters
    ----------
    affine_rows : (2F, 3) — rows i*_f, j*_f of the affine motion R*, frame by frame.
    notes : list to which a message is appended when A had to be repaired or is
        ill-determined.

    Returns
    -------
    (A, Q) : the (repaired) symmetric positive-definite A and its Cholesky factor Q.

    Examples
    --------
    >>> rot = np.linalg.qr(np.random.default_rng(3).normal(size=(3, 3)))[0]
    >>> frames = np.vstack([np.eye(3)[:2], rot[:2], rot.T[:2]])
    >>> a, q = metric_upgrade(frames @ np.diag([2.0, 1.0, 0.5]))
    >>> np.round(np.diag(a), 6)
    array([0.25, 1.  , 4.  ])
    """
    notes = [] if notes is None else notes
    i_rows, j_rows = affine_rows[0::2], affine_rows[1::2]
    # |i|² = 1, |j|² = 1, i·j = 0, each linear in the 6 entries of the symmetric A
    system = np.vstack([_quadratic_terms(i_rows, i_rows), _quadratic_terms(j_rows, j_rows), _quadratic_terms(i_rows, j_rows)])
    target = np.concatenate([np.ones(2 * len(i_rows)), np.zeros(len(i_rows))])
    scale = np.abs(system).max(axis=0)
    scale[scale == 0] = 1.0
    solution, _, rank, sv = np.linalg.lstsq(system / scale, target, rcond=None)
    solution /= scale
    if rank < 6 or sv[-1] < sv[0] / _METRIC_CONDITION:
        notes.append(
            "the metric constraints barely determine A (condition "
            f"{sv[0] / max(sv[-1], np.finfo(float).tiny):.3g}): too little rotation; depth scale unreliable"
        )
    a11, a12, a13, a22, a23, a33 = solution
    a_matrix = np.array([[a11, a12, a13], [a12, a22, a23], [a13, a23, a33]])
    eigenvalues, eigenvectors = np.linalg.eigh(a_matrix)
    if eigenvalues[0] <= 1e-12 * abs(eigenvalues[-1]):
        # Nearest positive-definite matrix (Frobenius norm): clip the eigenvalues.
        floor = 1e-6 * max(abs(eigenvalues).max(), np.finfo(float).tiny)
        repaired = np.maximum(np.abs(eigenvalues) if eigenvalues[-1] <= 0 else eigenvalues, floor)
        notes.append(
            f"metric matrix A not positive definite (eigenvalues {np.array2string(eigenvalues, precision=3)}); "
            "used the nearest positive-definite matrix"
        )
        a_matrix = (eigenvectors * repaired) @ eigenvectors.T
    q = np.linalg.cholesky(a_matrix)
    return a_matrix, q


def _quadratic_terms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rows c with c · (a11, a12, a13, a22, a23, a33) = aᵀ A b for symmetric A."""
    return np.stack(
        [
            a[:, 0] * b[:, 0],
            a[:, 0] * b[:, 1] + a[:, 1] * b[:, 0],
            a[:, 0] * b[:, 2] + a[:, 2] * b[:, 0],
            a[:, 1] * b[:, 1],
            a[:, 1] * b[:, 2] + a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 2],
        ],
        axis=1,
    )


def _validate(positions: object, weights: object) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    x = as_float_array("positions", positions)
    if x.ndim != 3 or x.shape[2] != 2:
        raise InvalidInputError(f"positions must have shape (frames, points, 2); got {x.shape}")
    frames, points = x.shape[:2]
    # Observed = both coordinates finite; checked a block of frames at a time so that no
    # full-size temporary is made (positions can be gigabytes).
    observed = np.empty((frames, points), bool)
    for block in row_blocks(frames, points):
        chunk = x[block]
        np.logical_and(np.isfinite(chunk[..., 0]), np.isfinite(chunk[..., 1]), out=observed[block])
        if not observed[block].all() and np.isinf(chunk).any():
            bad = tuple(int(i) for i in np.argwhere(np.isinf(chunk))[0])
            bad = (bad[0] + block.start, *bad[1:])
            raise InvalidInputError(f"positions must be finite or NaN (missing); entry {bad} is {x[bad]}")
    if frames < 3 or points < 4:
        raise NotEnoughDataError(f"factorize needs >= 3 frames and >= 4 points; got {frames} frames, {points} points")
    if weights is None:
        return x, None, observed
    try:
        w = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"weights must be numeric; could not convert them ({exc})") from None
    if w.shape == (frames, points):
        w = np.repeat(w[:, :, None], 2, axis=2)
    if w.shape != (frames, points, 2):
        raise InvalidInputError(f"weights must have shape ({frames}, {points}) or ({frames}, {points}, 2); got {w.shape}")
    finite_obs = np.isfinite(x)
    bad = finite_obs & ~(np.isfinite(w) & (w >= 0))
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise InvalidInputError(f"weights must be finite and >= 0 where positions are observed; entry {where} is {w[where]}")
    return x, np.where(finite_obs, w, 0.0), observed


def _usable(observed: np.ndarray, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Drop points seen in < 2 frames and frames seeing < 4 points, until stable."""
    use_f = np.ones(observed.shape[0], bool)
    use_p = np.ones(observed.shape[1], bool)
    if observed.all():  # the shape was checked: >= 3 frames, >= 4 points
        return use_f, use_p
    while True:
        sub = observed & use_f[:, None] & use_p[None, :]
        new_p = use_p & (sub.sum(axis=0) >= 2)
        new_f = use_f & ((sub & new_p[None, :]).sum(axis=1) >= 4)
        if (new_p == use_p).all() and (new_f == use_f).all():
            break
        use_f, use_p = new_f, new_p
    if not observed.any():
        raise NotEnoughDataError("factorize got no observed positions (all NaN)")
    if use_f.sum() < 3 or use_p.sum() < 4:
        raise NotEnoughDataError(
            "factorize needs >= 3 frames that each see >= 4 points seen in >= 2 frames; "
            f"got {int(use_f.sum())} such frames and {int(use_p.sum())} such points"
        )
    if not use_p.all():
        notes.append(f"{int((~use_p).sum())} point(s) observed in fewer than 2 usable frames: left NaN")
    if not use_f.all():
        notes.append(f"{int((~use_f).sum())} frame(s) observing fewer than 4 usable points: left NaN")
    return use_f, use_p


def _closed_form(x: np.ndarray, rng: object) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Report eqs. 14–24: centre, rank-3 SVD, R* = U′D′^½, S* = D′^½V′ᵀ."""
    frames, points = x.shape[:2]
    w, centroids = _centred_measurement_matrix(x)
    method = "lapack" if w.size <= _LAPACK_LIMIT else "randomized"
    svd = truncated_svd(w, 3, method=method, rng=rng)
    root = np.sqrt(svd.s)
    motion = (svd.u * root).reshape(frames, 2, 3)
    shape = (svd.vt.T * root)
    sv = np.concatenate([svd.s, svd.extra_singular_values])
    return motion, shape, centroids.reshape(frames, 2), sv


def _centred_measurement_matrix(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """W (2F × P, C order; row 2f is x of frame f, row 2f+1 its y) centred on each row's mean.

    Built a block of frames at a time: the (F, P, 2) → (2F, P) transpose and the centring
    of a block happen while it is in cache, and W is the only full-size array made.
    """
    frames, points = x.shape[:2]
    w = np.empty((frames, 2, points))
    centroids = np.empty((frames, 2))
    for block in row_blocks(frames, points):
        rows = w[block]
        np.copyto(rows, x[block].transpose(0, 2, 1))
        centroids[block] = rows.mean(axis=2)
        rows -= centroids[block, :, None]
    return w.reshape(2 * frames, points), centroids.reshape(-1)


@dataclass(frozen=True)
class _Residuals:
    """Distances |M_f S_p + t_f − x_fp| (F, P), NaN where unused; the mask of used entries (None:
    all were); each point's sum of their squares; their RMS."""

    residuals: np.ndarray
    used: np.ndarray | None
    point_sums: np.ndarray
    rms: float


def _reprojection_residuals(x: np.ndarray, observed: np.ndarray | None, motion: np.ndarray, points: np.ndarray,
                            translation: np.ndarray, dtype: np.dtype) -> _Residuals:
    """The reprojection residuals of the entries of ``x`` that are ``observed`` (None: all), as ``dtype``.

    Computed a block of frames at a time, so no (F, P, 2) temporary is made.
    """
    frames, n_points = x.shape[:2]
    blocks = row_blocks(frames, n_points)
    residuals = np.empty((frames, n_points), dtype)
    used = None if observed is None else np.empty((frames, n_points), bool)
    point_sums = np.zeros(n_points)
    scratch = np.empty((blocks[0].stop - blocks[0].start, n_points))
    total, count = 0.0, 0
    points_t = np.ascontiguousarray(points.T)
    for block in blocks:
        # predicted rows M_f S + t_f of the block, (B, 2, P), as three broadcast multiply-adds: many
        # tiny GEMMs would each wake the BLAS threads, which costs more than the arithmetic
        rows = motion[block][:, :, :, None]
        difference = rows[:, :, 0] * points_t[0]
        difference += rows[:, :, 1] * points_t[1]
        difference += rows[:, :, 2] * points_t[2]
        difference += translation[block, :, None]
        difference -= x[block].transpose(0, 2, 1)
        np.square(difference, out=difference)
        squared = np.add(difference[:, 0], difference[:, 1], out=scratch[: len(difference)])
        block_total = float(squared.sum())
        if np.isfinite(block_total) and (observed is None or observed[block].all()):  # the usual case
            if used is not None:
                used[block] = True
            total += block_total
            count += squared.size
            point_sums += squared.sum(axis=0)
        else:
            ok = np.isfinite(squared) if observed is None else observed[block] & np.isfinite(squared)
            if used is not None:
                used[block] = ok
            total += float(np.sum(squared, where=ok))
            count += int(ok.sum())
            point_sums += np.sum(squared, axis=0, where=ok)
            squared[~ok] = np.nan
        np.sqrt(squared, out=residuals[block])
    return _Residuals(residuals, used, point_sums, float(np.sqrt(total / count)) if count else float("nan"))


def _completed_singular_values(x, observed, motion, shape, translation, f_ok, p_ok, rng) -> np.ndarray:
    """Singular values of the centred W with holes filled by the model (known frames and points)."""
    everything = bool(f_ok.all() and p_ok.all())
    xs = x if everything else x[np.ix_(f_ok, p_ok)]
    seen = observed if everything else observed[np.ix_(f_ok, p_ok)]
    frames, points = seen.shape
    # The model's W (2F × P) = M Sᵀ + t as one GEMM, then the observed entries copied over it.
    w = motion[f_ok].reshape(-1, 3) @ shape[p_ok].T + translation[f_ok].reshape(-1, 1)
    np.copyto(w.reshape(frames, 2, points), xs.transpose(0, 2, 1), where=seen[:, None, :])
    w -= w.mean(axis=1, keepdims=True)
    k = min(3, *w.shape)
    method = "lapack" if w.size <= _LAPACK_LIMIT else "randomized"
    svd = truncated_svd(w, k, method=method, rng=rng)
    return np.concatenate([svd.s, svd.extra_singular_values])


def _check_rank(sv: np.ndarray, motion: np.ndarray, shape: np.ndarray, notes: list[str]) -> None:
    """Flag a W that is not clearly rank 3, reporting what was measured.

    The warning gives σ3/σ4 and σ3/σ1; it adds "no rotation out of the image plane" only
    when that is measured (every frame's rank-2 part a 2D similarity of frame 0's). Other
    causes — nearly planar points, little rotation, tracks that follow no single rigid
    motion (tracker failures) — cannot be told apart from W alone and are not guessed.
    """
    fourth = sv[3] if sv.size > 3 else 0.0
    if not (sv[2] <= 1e-9 * sv[0] or sv[2] < _RANK_GAP * fourth):
        return
    # Rank-2 part of the fitted W = M Sᵀ: left singular vectors of M L with L Lᵀ = SᵀS.
    gram = shape.T @ shape
    lower = np.linalg.cholesky(gram + 1e-12 * np.trace(gram) * np.eye(3))
    u, s, _ = np.linalg.svd(motion.reshape(-1, 3) @ lower, full_matrices=False)
    blocks = (u[:, :2] * s[:2]).reshape(-1, 2, 2)
    # Each frame relative to the first: T_f = B_f B_0⁻¹; a similarity has T = [[a, -b], [b, a]].
    relative = blocks @ np.linalg.pinv(blocks[0])
    deviation = np.abs(relative[:, 0, 0] - relative[:, 1, 1]) + np.abs(relative[:, 0, 1] + relative[:, 1, 0])
    size = np.linalg.norm(relative, axis=(1, 2))
    worst = float(np.max(deviation / np.maximum(size, np.finfo(float).tiny)))
    ratio = f"σ3/σ4 = {sv[2] / fourth:.3g}" if fourth > 0 else "σ4 = 0"
    measured = (
        f"W is not clearly rank 3 ({ratio}, σ3/σ1 = {sv[2] / sv[0]:.3g}; singular values "
        f"{np.array2string(sv[:4], precision=4)}): depth is not determined"
    )
    if worst <= 0.02:
        # Measured, not guessed: the rank-2 part of every frame is a 2D similarity of frame 0's.
        measured += (
            f"; every frame is a 2D similarity of the first (largest deviation {worst:.2%}): "
            "no rotation out of the image plane"
        )
    notes.append(measured)


def _check_shape(shape: np.ndarray, notes: list[str]) -> None:
    spread = np.linalg.svd(shape - shape.mean(axis=0), compute_uv=False)
    if spread[0] > 0 and spread[-1] < _FLAT_RATIO * spread[0]:
        notes.append(
            "the recovered points are (nearly) coplanar: smallest/largest spread of the shape "
            f"{spread[-1] / spread[0]:.2g} (< {_FLAT_RATIO:g})"
        )
