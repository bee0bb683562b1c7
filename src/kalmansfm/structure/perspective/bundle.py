"""Bundle adjustment of calibrated cameras and points, and covariances in the free-network gauge.

Model
-----
Camera j has known intrinsics K_j (upper triangular, skew allowed), a rotation
R_j and a centre C_j; a point X_i is seen at the pixel

    x_ij = π(K_j R_j (X_i - C_j)),      π(u, v, w) = (u / w, v / w)

(x = column, y = row; the camera-frame depth is the third coordinate of
R_j (X_i - C_j); x_cam = R X + t with t = -R C).  The bundle adjustment
minimises ½ Σ ρ(|x_ij - observed_ij|²) over all rotations, centres and points;
ρ is the identity (least squares) or a robust loss.  A rotation is updated on
the left, R ← exp([δω]×) R, so δω is a small rotation of the camera frame.

Solver
------
Levenberg–Marquardt on the normal equations

    [U  W] [δc]   [-g_c]
    [Wᵀ V] [δp] = [-g_p]

with U block diagonal over cameras (6 × 6), V block diagonal over points
(3 × 3) and W the camera–point coupling.  The points are eliminated (Schur
complement): S δc = -g_c + W V⁻¹ g_p with S = U - W V⁻¹ Wᵀ, a dense
6n × 6n system (n cameras) solved by Cholesky; then δp = V⁻¹ (-g_p - Wᵀ δc).
Everything is batched over observations.  The problem has a 7-dimensional
gauge freedom (a similarity of the world); the damping keeps S invertible.

Covariance in the free-network gauge
------------------------------------
At the least-squares solution the parameter covariance is σ² N⁻ with
N = JᵀJ singular along the 7 similarity directions.  We report the covariance
of the points *after a least-squares similarity alignment over all points*:
with G (3m × 7) the point part of the similarity directions (translation,
rotation, scale), the aligned points' error is P⊥ δp with
P⊥ = I - G (GᵀG)⁻¹ Gᵀ, whose covariance σ² P⊥ N⁻_pp P⊥ does not depend on
which generalised inverse is used.  It is computed without any dense inverse
over all points: N⁻_pp = V⁻¹ + V⁻¹ Wᵀ S⁻ W V⁻¹ with S⁻ = (S + Q Qᵀ)⁻¹ (Q an
orthonormal basis of the camera part of the gauge directions, so S⁻ is a
generalised inverse of S); the diagonal 3 × 3 blocks of that need only the
camera pairs that share a point, and the projection P⊥ is a rank-7 correction.
Camera covariances are given in the same gauge (the similarity that aligns the
points applied to the cameras too).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg
import scipy.sparse
from threadpoolctl import threadpool_limits

from ...errors import InvalidInputError
from ..._validation import as_float_array, check_choice, check_positive
from ..geometry.alignment import Alignment, align_similarity
from ..geometry.pinhole import project_each
from ..geometry.rotation import cross_matrix, rotation_exp, rotation_log
from ._schur_kernel import schur_coupling_kernel

__all__ = [
    "BUNDLE_LOSSES",
    "BundleResult",
    "GaugeComparison",
    "GaugeCovariances",
    "ObservationList",
    "bundle_adjust",
    "camera_frame_projections",
    "compare_in_gauge",
    "coupling_reference",
    "free_network_covariances",
    "reduced_camera_matrix",
    "reprojection_residuals",
    "residuals_and_jacobians",
    "similarity_free_covariances",
    "single_threaded_blas",
]

#: robust losses ρ(s) of the squared residual length s (pixels²) scaled by the loss scale.
BUNDLE_LOSSES = ("linear", "huber", "cauchy")

# The reference coupling (coupling_reference) and the point-covariance pass use dense BLAS while the dense
# (6n × 3m) coupling arrays stay below this many bytes; beyond it sparse matrices.
_DENSE_COUPLING_BYTES = 256e6
# Pairs of observations of one point processed together in the point-covariance pass.
_PAIR_CHUNK = 200_000
# Every BLAS call here is small (6n × 6n systems, 3 × 3 and 6 × 3 blocks): BLAS threads only add
# synchronisation, and on a busy machine waiting for them costs 10× the work (measured: the Oxford house
# pipeline 3.4 s with 2 OpenBLAS threads under load 4.9, 0.2 s with one).
single_threaded_blas = threadpool_limits.wrap(limits=1, user_api="blas")
# Levenberg–Marquardt: initial damping, and the clamp on the diagonal that scales it.  The reconstruction starts
# every adjustment near its minimum: at 1e-4 the damping held back the weakly determined directions for 4–5 extra
# steps (dinoRing: 111 steps in all, 65 at 1e-6, same minima); a step that raises the cost still raises it.
_INITIAL_DAMPING = 1e-6
_DIAGONAL_CLAMP = (1e-6, 1e32)
_MAX_DAMPING = 1e16


@dataclass(frozen=True)
class ObservationList:
    """Observations as parallel lists: observation k is point ``points[k]`` seen by camera ``cameras[k]``.

    Attributes
    ----------
    cameras : (N,) int64 — camera index of each observation.
    points : (N,) int64 — point index of each observation.
    pixels : (N, 2) float64 — observed (x, y).
    """

    cameras: np.ndarray
    points: np.ndarray
    pixels: np.ndarray

    @classmethod
    def from_dense(cls, observations: np.ndarray, mask: np.ndarray | None = None) -> ObservationList:
        """From (F, P, 2) positions (NaN where unseen), optionally restricted by a (F, P) mask.

        Examples
        --------
        >>> obs = np.full((2, 3, 2), np.nan); obs[0, 1] = [5.0, 6.0]; obs[1, 2] = [7.0, 8.0]
        >>> o = ObservationList.from_dense(obs)
        >>> o.cameras.tolist(), o.points.tolist(), o.pixels.tolist()
        ([0, 1], [1, 2], [[5.0, 6.0], [7.0, 8.0]])
        """
        seen = np.isfinite(observations).all(axis=-1)
        if mask is not None:
            seen &= mask
        cams, pts = np.nonzero(seen)
        return cls(cams.astype(np.int64), pts.astype(np.int64), observations[cams, pts])

    def __len__(self) -> int:
        return int(self.cameras.shape[0])

    @cached_property
    def by_point(self) -> tuple[np.ndarray, np.ndarray]:
        """The observations grouped by point: point p owns ``order[starts[p]:starts[p + 1]]`` (computed once).

        Examples
        --------
        >>> order, starts = ObservationList(np.array([0, 1, 1]), np.array([1, 0, 1]), np.zeros((3, 2))).by_point
        >>> order.tolist(), starts.tolist()
        ([1, 0, 2], [0, 1, 3])
        """
        order = np.argsort(self.points, kind="stable").astype(np.int64)
        count = np.bincount(self.points, minlength=int(self.points.max()) + 1 if len(self.points) else 0)
        return order, np.concatenate([[0], np.cumsum(count)]).astype(np.int64)


@dataclass(frozen=True)
class BundleResult:
    """Refined cameras and points.

    Attributes
    ----------
    rotations : (n, 3, 3) world → camera rotations.
    centres : (n, 3) camera centres.
    points : (m, 3).
    cost : final ½ Σ ρ(|r|²) (pixels², ρ the loss used).
    initial_cost : the same at the start.
    iterations : accepted plus rejected Levenberg–Marquardt steps.
    converged : a tolerance was met (False: the iteration cap, or no step could lower the cost).
    """

    rotations: np.ndarray
    centres: np.ndarray
    points: np.ndarray
    cost: float
    initial_cost: float
    iterations: int
    converged: bool


@dataclass(frozen=True)
class GaugeCovariances:
    """Covariances in the free-network gauge (points similarity-aligned over all points).

    Attributes
    ----------
    points : (m, 3, 3) — covariance of each point after a least-squares similarity
        alignment of all points onto any reference (σ² P⊥ N⁻ P⊥, diagonal blocks).
    cameras : (n, 6, 6) — covariance of (δω, δC) of each camera in the same gauge:
        δω the small rotation of the camera frame (R_true = exp([δω]×) R), δC the centre.
    gauge_residual : |S Q| / |S|, how exactly the 7 similarity directions are null
        directions of the reduced camera matrix (≈ 1e-15 at a converged solution).
    """

    points: np.ndarray
    cameras: np.ndarray
    gauge_residual: float


def _accumulate(index: np.ndarray, blocks: np.ndarray, count: int) -> np.ndarray:
    """Sum the (N, ...) ``blocks`` into (count, ...) by ``index``.

    One sparse product (count × N) · (N, entries): the summation matrix in compressed-column form
    has one 1 per column and needs no sorting (12× faster than a bincount per entry for 6 × 6 blocks).
    """
    N = len(blocks)
    flat = blocks.reshape(N, -1)
    summation = scipy.sparse.csc_matrix((np.ones(N), index, np.arange(N + 1)), shape=(count, N))
    return np.asarray(summation @ flat).reshape((count,) + blocks.shape[1:])


def camera_frame_projections(intrinsics: np.ndarray) -> np.ndarray:
    """(n, 3, 4) [K | 0]: projects camera-frame points."""
    return np.concatenate([intrinsics, np.zeros(intrinsics.shape[:-1] + (1,))], axis=-1)


def residuals_and_jacobians(rotations: np.ndarray, centres: np.ndarray, points: np.ndarray, obs: ObservationList,
               kz: np.ndarray, jacobians: bool = True):
    """Residuals (N, 2) = projected - observed, depths (N,) and, if asked, d r / d(ω, C) (N, 2, 6), d r / dX (N, 2, 3)."""
    R = rotations[obs.cameras]
    x_cam = np.einsum("nij,nj->ni", R, points[obs.points] - centres[obs.cameras])
    pix, depth, J_cam = project_each(kz[obs.cameras], x_cam)
    r = pix - obs.pixels
    if not jacobians:
        return r, depth
    # x_cam = R (X - C):  d x_cam / dX = R,  d x_cam / dC = -R,  d x_cam / dω = -[x_cam]× (R ← exp([ω]×) R)
    J_point = J_cam @ R
    # row a of J_cam times -[x]×  is  (x × a)ᵀ
    J_rot = np.cross(x_cam[:, None, :], J_cam)
    return r, depth, np.concatenate([J_rot, -J_point], axis=2), J_point


def _loss_weights(r: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """IRLS weights ρ'(s) of each observation, s = |r|² / scale²."""
    if loss == "linear":
        return np.ones(len(r))
    s = np.einsum("na,na->n", r, r) / scale**2
    if loss == "huber":
        return np.where(s <= 1.0, 1.0, 1.0 / np.sqrt(np.maximum(s, 1.0)))
    return 1.0 / (1.0 + s)  # cauchy


def _cost(r: np.ndarray, loss: str, scale: float) -> float:
    """½ Σ scale² ρ(|r|² / scale²) with ρ(s) = s (linear), Huber, or log(1 + s) (Cauchy)."""
    s = np.einsum("na,na->n", r, r)
    if loss == "linear":
        return 0.5 * float(s.sum())
    z = s / scale**2
    rho = np.where(z <= 1.0, z, 2.0 * np.sqrt(z) - 1.0) if loss == "huber" else np.log1p(z)
    return 0.5 * scale**2 * float(rho.sum())


@dataclass(frozen=True)
class _Blocks:
    """Normal-equation blocks: U (n, 6, 6), V (m, 3, 3), W (N, 6, 3) per observation, gradients g_c, g_p."""

    U: np.ndarray
    V: np.ndarray
    W: np.ndarray
    g_cam: np.ndarray
    g_point: np.ndarray


def _normal_blocks(obs: ObservationList, n: int, m: int, r: np.ndarray, J_c: np.ndarray, J_p: np.ndarray,
                   weights: np.ndarray) -> _Blocks:
    J = np.concatenate([J_c, J_p], axis=2)  # (N, 2, 9): the camera and point blocks in one product
    J_w = J * weights[:, None, None]
    H = np.swapaxes(J_w, 1, 2) @ J
    g = np.einsum("nki,nk->ni", J_w, r)
    U = _accumulate(obs.cameras, H[:, :6, :6], n)
    V = _accumulate(obs.points, H[:, 6:, 6:], m)
    return _Blocks(U, V, np.ascontiguousarray(H[:, :6, 6:]), _accumulate(obs.cameras, g[:, :6], n),
                   _accumulate(obs.points, g[:, 6:], m))


def coupling_reference(obs: ObservationList, n: int, m: int, left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Σ over observations of the same point of left_a right_bᵀ, as the (6n, 6n) matrix L Rᵀ (L, R: 6n × 3m).

    The NumPy reference of the compiled coupling (:mod:`._schur_kernel`), by a dense (or, when the
    dense arrays would be large, sparse) matrix product.

    Examples
    --------
    One point seen by cameras 0 and 1: the blocks are left_a right_bᵀ at (camera a, camera b).

    >>> obs = ObservationList(np.array([0, 1]), np.array([0, 0]), np.zeros((2, 2)))
    >>> left = np.ones((2, 6, 3)); right = np.stack([np.ones((6, 3)), 2 * np.ones((6, 3))])
    >>> S = coupling_reference(obs, 2, 1, left, right)
    >>> S.shape, float(S[0, 0]), float(S[0, 6]), float(S[6, 0])
    ((12, 12), 3.0, 6.0, 3.0)
    """
    if 6 * n * 3 * m * 8 <= _DENSE_COUPLING_BYTES:
        L = np.zeros((n, 6, m, 3))
        Rm = np.zeros((n, 6, m, 3))
        L[obs.cameras, :, obs.points, :] = left
        Rm[obs.cameras, :, obs.points, :] = right
        return L.reshape(6 * n, 3 * m) @ Rm.reshape(6 * n, 3 * m).T
    rows = (6 * obs.cameras[:, None, None] + np.arange(6)[None, :, None]).repeat(3, axis=2).ravel()
    cols = (3 * obs.points[:, None, None] + np.arange(3)[None, None, :]).repeat(6, axis=1).ravel()
    L = scipy.sparse.csr_matrix((left.ravel(), (rows, cols)), shape=(6 * n, 3 * m))
    Rs = scipy.sparse.csr_matrix((right.ravel(), (rows, cols)), shape=(6 * n, 3 * m))
    return (L @ Rs.T).toarray()


def _reduced_camera_matrix(obs: ObservationList, blocks: _Blocks, U: np.ndarray, V_inv: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """S = U - W V⁻¹ Wᵀ (6n × 6n) and the per-observation Y = W V⁻¹ (N, 6, 3)."""
    n = len(U)
    Y = blocks.W @ V_inv[obs.points]
    order, starts = obs.by_point
    S = -schur_coupling_kernel(order, starts, obs.cameras, Y, blocks.W, n)
    index = np.arange(n)
    S.reshape(n, 6, n, 6)[index, :, index, :] += U  # the block diagonal U (a view into S)
    return S, Y


def reduced_camera_matrix(rotations: np.ndarray, centres: np.ndarray, points: np.ndarray,
                          observations: ObservationList, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Information of the cameras with the points eliminated, S = U - W V⁻¹ Wᵀ (6n × 6n, unit σ), and V (m, 3, 3).

    Camera j's parameters are (δω_j, δC_j) as in :func:`bundle_adjust`; S is singular
    along the 7 similarity directions.  Fixing some cameras means keeping the
    rows and columns of the others.

    Examples
    --------
    >>> X = np.random.default_rng(0).uniform(-1, 1, (20, 3))
    >>> C = np.array([[0.0, 0, -5], [1.0, 0, -5]])
    >>> K = np.diag([500.0, 500.0, 1.0])
    >>> x = np.einsum("ij,fnj->fni", K, X[None] - C[:, None])
    >>> S, V = reduced_camera_matrix(np.stack([np.eye(3)] * 2), C, X, ObservationList.from_dense(x[..., :2] / x[..., 2:]), K)
    >>> S.shape, V.shape, int(np.sum(np.linalg.eigvalsh(S) > 1e-9 * np.abs(S).max()))
    ((12, 12), (20, 3, 3), 5)
    """
    R, C, X, K = _validate_problem(rotations, centres, points, observations, intrinsics)
    r, _, J_c, J_p = residuals_and_jacobians(R, C, X, observations, camera_frame_projections(K))
    blocks = _normal_blocks(observations, len(R), len(X), r, J_c, J_p, np.ones(len(observations)))
    S, _ = _reduced_camera_matrix(observations, blocks, blocks.U, np.linalg.inv(blocks.V))
    return S, blocks.V


def _validate_problem(rotations: object, centres: object, points: object, observations: ObservationList,
                      intrinsics: object) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    R = as_float_array("rotations", rotations)
    C = as_float_array("centres", centres)
    X = as_float_array("points", points)
    K = as_float_array("intrinsics", intrinsics)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise InvalidInputError(f"rotations must have shape (n, 3, 3); got {R.shape}")
    n = R.shape[0]
    if C.shape != (n, 3):
        raise InvalidInputError(f"centres must have shape ({n}, 3), one per rotation; got {C.shape}")
    if K.shape == (3, 3):
        K = np.broadcast_to(K, (n, 3, 3))
    if K.shape != (n, 3, 3):
        raise InvalidInputError(f"intrinsics must have shape (3, 3) or ({n}, 3, 3); got {K.shape}")
    if X.ndim != 2 or X.shape[1] != 3:
        raise InvalidInputError(f"points must have shape (m, 3); got {X.shape}")
    for name, a in (("rotations", R), ("centres", C), ("points", X), ("intrinsics", K)):
        if not np.all(np.isfinite(a)):
            raise InvalidInputError(f"{name} must be finite")
    cams, pts, pix = observations.cameras, observations.points, observations.pixels
    if cams.shape != pts.shape or pix.shape != cams.shape + (2,):
        raise InvalidInputError(f"observations must be N cameras, N points and (N, 2) pixels; got {cams.shape}, "
                                f"{pts.shape}, {pix.shape}")
    if len(cams) and (cams.min() < 0 or cams.max() >= n or pts.min() < 0 or pts.max() >= len(X)):
        raise InvalidInputError(f"observation indices must address {n} cameras and {len(X)} points")
    if not np.all(np.isfinite(pix)):
        raise InvalidInputError("observed pixels must be finite")
    return R, C, X, np.ascontiguousarray(K)


@single_threaded_blas
def bundle_adjust(rotations: object, centres: object, points: object, observations: ObservationList,
                  intrinsics: object, *, loss: str = "linear", loss_scale: float = 1.0,
                  max_iterations: int = 100, function_tolerance: float = 1e-9,
                  parameter_tolerance: float = 1e-10) -> BundleResult:
    """Jointly refine camera rotations, centres and points (Levenberg–Marquardt with a Schur complement).

    Parameters
    ----------
    rotations : (n, 3, 3) world → camera rotations at the start.
    centres : (n, 3) camera centres at the start.
    points : (m, 3) points at the start; every point should have ≥ 2 observations
        (a point with fewer is kept where it is by the damping).
    observations : :class:`ObservationList` indexing these cameras and points.
    intrinsics : (3, 3) or (n, 3, 3) — K, fixed.
    loss : one of :data:`BUNDLE_LOSSES`: ``"linear"`` (least squares), ``"huber"``
        or ``"cauchy"`` (robust: observations beyond ``loss_scale`` pixels weigh less).
    loss_scale : pixels, > 0.
    max_iterations : cap on Levenberg–Marquardt steps.
    function_tolerance : stop when an accepted step lowers the cost by less than this fraction.
    parameter_tolerance : stop when the step is below this fraction of the parameters' size.

    Returns
    -------
    BundleResult

    Examples
    --------
    Four cameras around 30 points, noise-free observations, cameras disturbed:

    >>> from kalmansfm.structure.geometry.rotation import rotation_exp
    >>> rng = np.random.default_rng(1)
    >>> X = rng.uniform(-1, 1, (30, 3))
    >>> C = np.array([[-1.0, 0, -6], [-0.3, 0.2, -6], [0.3, -0.2, -6], [1.0, 0, -6]])
    >>> R = np.stack([np.eye(3)] * 4)
    >>> K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    >>> x = np.einsum("ij,fnj->fni", K, np.einsum("fij,fnj->fni", R, X[None] - C[:, None]))
    >>> obs = ObservationList.from_dense(x[..., :2] / x[..., 2:])
    >>> start_R = rotation_exp(rng.normal(0, 0.01, (4, 3))) @ R
    >>> fit = bundle_adjust(start_R, C + rng.normal(0, 0.05, (4, 3)), X, obs, K)
    >>> fit.converged, fit.cost < 1e-12 < fit.initial_cost
    (True, True)
    """
    R, C, X, K = _validate_problem(rotations, centres, points, observations, intrinsics)
    check_choice("loss", loss, BUNDLE_LOSSES)
    scale = check_positive("loss_scale", loss_scale, "pixels")
    obs = observations
    n, m = len(R), len(X)
    kz = camera_frame_projections(K)
    r, _, J_c, J_p = residuals_and_jacobians(R, C, X, obs, kz)
    cost = initial = _cost(r, loss, scale)
    damping = _INITIAL_DAMPING
    growth = 2.0
    iterations = 0
    converged = False
    while iterations < max_iterations and not converged:
        blocks = _normal_blocks(obs, n, m, r, J_c, J_p, _loss_weights(r, loss, scale))
        d_U = np.clip(np.einsum("nii->ni", blocks.U), *_DIAGONAL_CLAMP)
        d_V = np.clip(np.einsum("nii->ni", blocks.V), *_DIAGONAL_CLAMP)
        # an unobserved point has V = 0: give it a unit diagonal so that it simply stays
        d_V[np.all(blocks.V == 0, axis=(1, 2))] = 1.0
        while iterations < max_iterations:
            iterations += 1
            # Levenberg–Marquardt: (N + λ diag N) δ = -g, points eliminated by the Schur complement
            U = blocks.U + damping * d_U[:, :, None] * np.eye(6)
            V_inv = np.linalg.inv(blocks.V + damping * d_V[:, :, None] * np.eye(3))
            S, Y = _reduced_camera_matrix(obs, blocks, U, V_inv)
            rhs = -blocks.g_cam + _accumulate(obs.cameras, np.einsum("nij,nj->ni", Y, blocks.g_point[obs.points]), n)
            try:
                factor = scipy.linalg.cho_factor(S, check_finite=False)
            except np.linalg.LinAlgError:
                damping *= growth
                growth *= 2.0
                continue
            d_cam = scipy.linalg.cho_solve(factor, rhs.ravel(), check_finite=False).reshape(n, 6)
            back = _accumulate(obs.points, np.einsum("nji,nj->ni", blocks.W, d_cam[obs.cameras]), m)
            d_point = np.einsum("mij,mj->mi", V_inv, -blocks.g_point - back)
            R_new = rotation_exp(d_cam[:, :3]) @ R
            C_new = C + d_cam[:, 3:]
            X_new = X + d_point
            r_new, _, J_c_new, J_p_new = residuals_and_jacobians(R_new, C_new, X_new, obs, kz)
            cost_new = _cost(r_new, loss, scale)
            # predicted decrease of the quadratic model: ½ (-gᵀδ + λ δᵀ D δ)
            predicted = 0.5 * (-np.sum(blocks.g_cam * d_cam) - np.sum(blocks.g_point * d_point)
                               + damping * (np.sum(d_U * d_cam**2) + np.sum(d_V * d_point**2)))
            if np.isfinite(cost_new) and cost_new < cost:
                gain = (cost - cost_new) / max(predicted, np.finfo(float).tiny)
                relative = (cost - cost_new) / cost
                step = np.sqrt(np.sum(d_cam**2) + np.sum(d_point**2))
                size = np.sqrt(np.sum(C**2) + np.sum(X**2)) + 1.0
                R, C, X, r, J_c, J_p, cost = R_new, C_new, X_new, r_new, J_c_new, J_p_new, cost_new
                damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                growth = 2.0
                converged = relative < function_tolerance or step < parameter_tolerance * size
                break
            damping *= growth
            growth *= 2.0
            if damping > _MAX_DAMPING:
                # no step lowers the cost: at a minimum to working precision
                converged = True
                break
    return BundleResult(R, C, X, float(cost), float(initial), iterations, bool(converged))


def reprojection_residuals(rotations: np.ndarray, centres: np.ndarray, points: np.ndarray,
                           observations: ObservationList, intrinsics: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) projected - observed pixels and (N,) camera-frame depths of every observation.

    Examples
    --------
    >>> K = np.diag([100.0, 100.0, 1.0])
    >>> obs = ObservationList(np.array([0]), np.array([0]), np.array([[10.0, 0.0]]))
    >>> r, depth = reprojection_residuals(np.eye(3)[None], np.zeros((1, 3)), np.array([[0.2, 0.0, 2.0]]), obs, K)
    >>> r.tolist(), depth.tolist()
    ([[0.0, 0.0]], [2.0])
    """
    K = np.broadcast_to(np.asarray(intrinsics, dtype=np.float64), (len(rotations), 3, 3))
    return residuals_and_jacobians(np.asarray(rotations, float), np.asarray(centres, float), np.asarray(points, float),
                      observations, camera_frame_projections(K), jacobians=False)


def _similarity_directions(rotations: np.ndarray, centres: np.ndarray, points: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """The 7 similarity directions (translation, rotation, scale about the points' centroid).

    Returns the camera part (n, 6, 7) in (δω, δC) and the point part (m, 3, 7).
    A world change X → X + d + Ω × (X - c) + s (X - c) moves a centre the same way
    and turns each camera frame by δω = -R Ω.
    """
    c0 = points.mean(axis=0)
    Xc, Cc = points - c0, centres - c0
    G = np.zeros((len(points), 3, 7))
    G[:, :, :3] = np.eye(3)
    G[:, :, 3:6] = -cross_matrix(Xc)
    G[:, :, 6] = Xc
    T = np.zeros((len(rotations), 6, 7))
    T[:, :3, 3:6] = -rotations
    T[:, 3:, :3] = np.eye(3)
    T[:, 3:, 3:6] = -cross_matrix(Cc)
    T[:, 3:, 6] = Cc
    return T, G


def _project_out_similarity(blocks: np.ndarray, H: np.ndarray, M: np.ndarray, HtM: np.ndarray) -> np.ndarray:
    """Diagonal 3 × 3 blocks of P⊥ Σ P⊥, P⊥ = I - H Hᵀ, from Σ's blocks, H (m, 3, 7), M = Σ H and Hᵀ Σ H.

    (P⊥ Σ P⊥)_ii = Σ_ii - H_i M_iᵀ - M_i H_iᵀ + H_i (Hᵀ Σ H) H_iᵀ.
    """
    Ht = np.swapaxes(H, 1, 2)
    return blocks - H @ np.swapaxes(M, 1, 2) - M @ Ht + H @ HtM @ Ht


def similarity_free_covariances(points: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """Covariances of independent points after a least-squares similarity alignment over all of them.

    The free-network gauge of :func:`free_network_covariances` for estimates whose
    errors are independent from point to point (a per-point filter): P⊥ diag(Σ_i) P⊥.

    Parameters
    ----------
    points : (m, 3), m >= 3.
    covariances : (m, 3, 3).

    Returns
    -------
    (m, 3, 3)

    Examples
    --------
    >>> X = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    >>> free = similarity_free_covariances(X, np.stack([np.eye(3)] * 5))
    >>> bool(np.all(np.trace(free, axis1=1, axis2=2) < 3.0))  # alignment absorbs part of each error
    True
    """
    X = np.asarray(points, dtype=np.float64)
    S = np.asarray(covariances, dtype=np.float64)
    _, G = _similarity_directions(np.zeros((0, 3, 3)), np.zeros((0, 3)), X)
    H, _ = np.linalg.qr(G.reshape(-1, 7))
    H_blocks = H.reshape(len(X), 3, 7)
    M = S @ H_blocks
    return _project_out_similarity(S, H_blocks, M, np.einsum("mij,mil->jl", H_blocks, M))


def _coupled_diagonal_blocks(obs: ObservationList, n: int, m: int, Y: np.ndarray, S_g: np.ndarray) -> np.ndarray:
    """(m, 3, 3) diagonal blocks of Yᵀ S⁻ Y, Y the (6n × 3m) matrix of the per-observation blocks Y_a."""
    if 6 * n * 3 * m * 8 <= _DENSE_COUPLING_BYTES:
        # dense: Z = S⁻ Y by BLAS, then block i = Σ_rows Y[:, 3i:3i+3]ᵀ Z[:, 3i:3i+3]
        dense = np.zeros((n, 6, m, 3))
        dense[obs.cameras, :, obs.points, :] = Y
        flat = dense.reshape(6 * n, 3 * m)
        return np.einsum("ami,amj->mij", flat.reshape(6 * n, m, 3), (S_g @ flat).reshape(6 * n, m, 3))
    # sparse: only the camera pairs that share a point, Σ over pairs (a, b) of Y_aᵀ S⁻[c_a, c_b] Y_b
    first, second = _observation_pairs(obs.points, m)
    S_blocks = S_g.reshape(n, 6, n, 6)
    out = np.zeros((m, 3, 3))
    for start in range(0, len(first), _PAIR_CHUNK):
        a, b = first[start:start + _PAIR_CHUNK], second[start:start + _PAIR_CHUNK]
        term = (np.swapaxes(Y[a], 1, 2) @ S_blocks[obs.cameras[a], :, obs.cameras[b], :]) @ Y[b]
        out += _accumulate(obs.points[a], term, m)
    return out


def _observation_pairs(points: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """All ordered pairs (a, b) of observations of the same point (a = b included)."""
    order = np.argsort(points, kind="stable")
    counts = np.bincount(points, minlength=m)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    k = counts[points[order]]
    first = np.repeat(np.arange(len(points)), k)
    offset = np.arange(len(first)) - np.repeat(np.cumsum(k) - k, k)
    second = np.repeat(starts[points[order]], k) + offset
    return order[first], order[second]


@single_threaded_blas
def free_network_covariances(rotations: object, centres: object, points: object, observations: ObservationList,
                             intrinsics: object, pixel_std: float) -> GaugeCovariances:
    """Point and camera covariances of a least-squares solution, in the free-network gauge.

    The point covariances are those of the points after a least-squares similarity
    alignment over all points (see the module docstring): compare a reconstruction
    with any reference by aligning it with :func:`~.alignment.align_similarity`, then
    judge each point's error by this covariance (scaled by the alignment's s² and
    rotated by its rotation).

    Parameters
    ----------
    rotations, centres, points, observations, intrinsics : the solution and its
        (inlier) observations, as for :func:`bundle_adjust`; every point needs ≥ 2
        observations and at least 2 cameras must see the points.
    pixel_std : σ of the image noise (pixels); covariances scale with σ².

    Returns
    -------
    GaugeCovariances

    Examples
    --------
    >>> rng = np.random.default_rng(2)
    >>> X = rng.uniform(-1, 1, (40, 3))
    >>> C = np.array([[-1.0, 0, -6], [0.0, 0.5, -6], [1.0, 0, -6]])
    >>> K = np.array([[800.0, 0, 320], [0, 800, 240], [0, 0, 1]])
    >>> x = np.einsum("ij,fnj->fni", K, X[None] - C[:, None])
    >>> obs = ObservationList.from_dense(x[..., :2] / x[..., 2:])
    >>> cov = free_network_covariances(np.stack([np.eye(3)] * 3), C, X, obs, K, pixel_std=0.5)
    >>> cov.points.shape, cov.cameras.shape, cov.gauge_residual < 1e-12
    ((40, 3, 3), (3, 6, 6), True)
    >>> bool(np.all(np.linalg.eigvalsh(cov.points) > 0))
    True
    """
    R, C, X, K = _validate_problem(rotations, centres, points, observations, intrinsics)
    sigma = check_positive("pixel_std", pixel_std, "pixels")
    obs = observations
    n, m = len(R), len(X)
    r, _, J_c, J_p = residuals_and_jacobians(R, C, X, obs, camera_frame_projections(K))
    blocks = _normal_blocks(obs, n, m, r, J_c, J_p, np.ones(len(obs)))
    V_inv = np.linalg.inv(blocks.V)
    S, Y = _reduced_camera_matrix(obs, blocks, blocks.U, V_inv)
    T, G = _similarity_directions(R, C, X)
    T_flat = T.reshape(6 * n, 7)
    Q, _ = np.linalg.qr(T_flat)
    gauge_residual = float(np.linalg.norm(S @ Q) / np.linalg.norm(S))
    # (S + c Q Qᵀ)⁻¹ is a generalised inverse of S whose null space is span(Q); c only sets its scale
    S_g = np.linalg.inv(S + Q @ Q.T * (np.trace(S) / (6 * n)))
    # diagonal blocks of N⁻_pp = V⁻¹ + Σ_ab Y_aᵀ S⁻[c_a, c_b] Y_b over observation pairs of each point
    point_cov = V_inv + _coupled_diagonal_blocks(obs, n, m, Y, S_g)
    # M = N⁻_pp H with H an orthonormal basis of the point part of the gauge directions
    G_flat = G.reshape(3 * m, 7)
    H, _ = np.linalg.qr(G_flat)
    H_blocks = H.reshape(m, 3, 7)
    # N⁻_pp H = V⁻¹ H + V⁻¹ Wᵀ S⁻ (W V⁻¹ H)
    YH = _accumulate(obs.cameras, np.einsum("kij,kjl->kil", Y, H_blocks[obs.points]), n).reshape(6 * n, 7)
    Z = (S_g @ YH).reshape(n, 6, 7)
    WtZ = _accumulate(obs.points, np.einsum("kji,kjl->kil", blocks.W, Z[obs.cameras]), m)
    M = V_inv @ (H_blocks + WtZ)
    HtM = np.einsum("mij,mil->jl", H_blocks, M)
    free_points = _project_out_similarity(point_cov, H_blocks, M, HtM)
    # cameras in the same gauge: (I - T A) N⁻ (I - T A)ᵀ, A = (GᵀG)⁻¹ Gᵀ acting on the point part
    GtG_inv = np.linalg.inv(G_flat.T @ G_flat)
    YG = _accumulate(obs.cameras, np.einsum("kij,kjl->kil", Y, G[obs.points]), n).reshape(6 * n, 7)
    Gt_Spc = -(YG.T @ S_g)  # Gᵀ N⁻_pc, N⁻_pc = -V⁻¹ Wᵀ S⁻
    HtG = H.T @ G_flat
    Gt_Spp_G = HtG.T @ HtM @ HtG  # Gᵀ N⁻_pp G = (HᵀG)ᵀ Hᵀ N⁻_pp H (HᵀG), G lies in span(H)
    TA = T_flat @ GtG_inv
    cam_cov = S_g - TA @ Gt_Spc - Gt_Spc.T @ TA.T + TA @ Gt_Spp_G @ TA.T
    index = np.arange(n)
    camera_blocks = cam_cov.reshape(n, 6, n, 6)[index, :, index, :]
    sym = lambda a: 0.5 * (a + np.swapaxes(a, -1, -2))  # noqa: E731
    return GaugeCovariances(sym(sigma**2 * free_points), sym(sigma**2 * camera_blocks), gauge_residual)


@dataclass(frozen=True)
class GaugeComparison:
    """A reconstruction compared with a reference in the free-network gauge.

    Attributes
    ----------
    alignment : the least-squares similarity taking the reconstructed points onto the reference.
    point_errors : (m, 3) aligned point minus reference point.
    point_nees : (m,) eᵀ Σ⁻¹ e with Σ the point covariance moved by the alignment (s² R Σ Rᵀ);
        χ² with 3 degrees of freedom when the covariances are right.
    centre_errors : (n, 3) aligned camera centre minus reference centre (None without cameras).
    camera_nees : (n,) the same for (δω, δC) of each camera, 6 degrees of freedom (None without cameras).
    """

    alignment: Alignment
    point_errors: np.ndarray
    point_nees: np.ndarray
    centre_errors: np.ndarray | None = None
    camera_nees: np.ndarray | None = None


def compare_in_gauge(points: np.ndarray, point_covariances: np.ndarray, reference: np.ndarray, *,
                     rotations: np.ndarray | None = None, centres: np.ndarray | None = None,
                     camera_covariances: np.ndarray | None = None, reference_rotations: np.ndarray | None = None,
                     reference_centres: np.ndarray | None = None, allow_reflection: bool = False) -> GaugeComparison:
    """Align a reconstruction onto a reference (all points, equal weights) and judge its errors by its covariances.

    This is the comparison the free-network gauge is made for (:func:`free_network_covariances`).

    Parameters
    ----------
    points, point_covariances : (m, 3) and (m, 3, 3), the reconstruction's.
    reference : (m, 3) the same points in the reference frame.
    rotations, centres, camera_covariances : optional (n, 3, 3), (n, 3), (n, 6, 6) cameras with covariances of
        (δω, δC), R_true = exp([δω]×) R; centres alone give the centre errors.
    reference_rotations, reference_centres : the reference cameras.
    allow_reflection : the reference may be a mirror image (its NEES is then meaningless for the cameras).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> truth = rng.normal(size=(200, 3))
    >>> cov = np.broadcast_to(0.01 * np.eye(3), (200, 3, 3))
    >>> estimate = 2.0 * (truth + rng.normal(scale=0.1, size=truth.shape)) + 5.0  # another scale and origin
    >>> out = compare_in_gauge(estimate, 4.0 * cov, truth)
    >>> bool(2.5 < out.point_nees.mean() < 3.5)
    True
    """
    al = align_similarity(points, reference, allow_reflection=allow_reflection)
    errors = al.aligned - reference
    S = al.scale**2 * al.rotation @ point_covariances @ al.rotation.T
    nees = np.einsum("ni,nij,nj->n", errors, np.linalg.inv(S), errors)
    if centres is None or reference_centres is None:
        return GaugeComparison(al, errors, nees)
    centre_errors = al.scale * centres @ al.rotation.T + al.translation - reference_centres
    if rotations is None or camera_covariances is None or reference_rotations is None:
        return GaugeComparison(al, errors, nees, centre_errors)
    turn = np.eye(6)
    turn[3:, 3:] = al.scale * al.rotation
    Sc = turn @ camera_covariances @ turn.T
    rotation_errors = rotation_log(rotations @ al.rotation.T @ np.swapaxes(reference_rotations, 1, 2))
    v = np.concatenate([rotation_errors, centre_errors], axis=1)
    return GaugeComparison(al, errors, nees, centre_errors, np.einsum("ni,nij,nj->n", v, np.linalg.inv(Sc), v))
