"""Landmarks from a moving camera with known motion: the report's pair fusion and a consistent estimator.

Task 7 of Thomas & Oliensis (``004_cd423c68da9c9743.txt``, section 7): a camera
moves with known motion and tracks landmarks; the goal is each landmark's
position in the current camera frame after every image, with an uncertainty
one can trust.

Two methods, same inputs and outputs:

``method="pairs"`` (the report's scheme)
    Each consecutive image pair (k-1, k) is triangulated
    (:func:`~kalmansfm.structure.triangulation.triangulate_midpoint`, eqs. 29-31)
    and given its first-order covariance (eq. 34); these "measurements" are
    fused by the Kalman filter with the motion x_k = C_{k-1} x_{k-1} - b_{k-1}
    (eq. 23, the same filter as :func:`~kalmansfm.fuse_recursive`).  The filter
    assumes the measurements independent, but consecutive pairs share an image,
    and the first-order covariance is evaluated at the noisy image points; the
    fused covariance is therefore too small (see ``docs/task7.md``).

``method="batch"`` (Gauss-Newton maximum likelihood)
    After every image k, the landmark is re-estimated from *all* its image
    observations 0..k by minimising the reprojection error
    sum_j |(u_j - f X_j / Z_j) / sigma|^2 over the three coordinates of the
    landmark (poses known), with a Levenberg-Marquardt-damped Gauss-Newton
    iteration warm-started from the previous image's solution.  Its covariance
    is the inverse of the Gauss-Newton normal matrix JᵀWJ at the solution, moved
    into frame k.  Each image is used once, so nothing is double-counted.

Poses: ``rotations[k]`` and ``translations[k]`` (C_k, b_k) take a point's
coordinates from camera frame k to camera frame k+1, X_{k+1} = C_k X_k - b_k.
Image coordinates follow :mod:`kalmansfm.structure.triangulation`:
(x, y) = (f X / Z, f Y / Z) from the principal point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError, NotEnoughDataError
from .._validation import as_float_array, check_finite
from ..estimation.kalman import kalman_predict, kalman_update
from .triangulation import TRIANGULATION_PARALLEL_RAYS, check_focal, check_motion, triangulate_midpoint

__all__ = ["METHODS", "TRIANGULATION_NOT_OBSERVED", "LandmarkEstimates", "estimate_landmarks", "project"]

METHODS = ("pairs", "batch")
#: measurement status where a pair could not be formed (first image, or a landmark missing in one image).
TRIANGULATION_NOT_OBSERVED = 3

_MAX_ITERATIONS = 60
_STEP_TOLERANCE = 1e-6
_STOP_TOLERANCE = 1e-18


@dataclass(frozen=True)
class LandmarkEstimates:
    """Estimates of L landmarks after each of K images, in the camera frame of that image.

    Attributes
    ----------
    method : "pairs" or "batch".
    estimates : (K, L, 3) — the landmark in camera frame k after image k; NaN
        where the method has no estimate yet (always at k = 0: one image gives no depth).
    covariances : (K, L, 3, 3) — the method's covariance of ``estimates``.
    measurements : (K, L, 3) — the single-pair triangulation from images (k-1, k),
        in frame k; NaN at k = 0 and where it failed.
    measurement_covariances : (K, L, 3, 3) — its first-order covariance (eq. 34).
    measurement_status : (K, L) int8 — triangulation status codes
        (``TRIANGULATION_OK``, ``..._PARALLEL_RAYS``, ``..._BEHIND_CAMERA``,
        ``TRIANGULATION_NOT_OBSERVED``).
    converged : (K, L) bool — an estimate exists and (for ``batch``) the
        Gauss-Newton iteration met its step tolerance.
    """

    method: str
    estimates: np.ndarray
    covariances: np.ndarray
    measurements: np.ndarray
    measurement_covariances: np.ndarray
    measurement_status: np.ndarray
    converged: np.ndarray

    @property
    def standard_deviations(self) -> np.ndarray:
        """(K, L, 3) per-axis standard deviations of ``estimates``."""
        return np.sqrt(np.diagonal(self.covariances, axis1=-2, axis2=-1))

    @property
    def measurement_standard_deviations(self) -> np.ndarray:
        """(K, L, 3) per-axis standard deviations of ``measurements``."""
        return np.sqrt(np.diagonal(self.measurement_covariances, axis1=-2, axis2=-1))


def project(points: np.ndarray, focal: float) -> np.ndarray:
    """Pinhole projection (..., 3) -> (..., 2): (x, y) = (f X / Z, f Y / Z).

    Examples
    --------
    >>> project(np.array([1.0, 2.0, 10.0]), 500.0)
    array([ 50., 100.])
    """
    points = np.asarray(points, dtype=float)
    return focal * points[..., :2] / points[..., 2:3]


def _cumulative_poses(C: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A_k, c_k with X_k = A_k X_0 - c_k for k = 0..K-1."""
    K = C.shape[0] + 1
    A = np.empty((K, 3, 3))
    c = np.empty((K, 3))
    A[0], c[0] = np.eye(3), 0.0
    for k in range(K - 1):
        # X_{k+1} = C_k (A_k X_0 - c_k) - b_k
        A[k + 1] = C[k] @ A[k]
        c[k + 1] = C[k] @ c[k] + b[k]
    return A, c


@dataclass(frozen=True)
class _Problem:
    obs: np.ndarray  # (K, L, 2), NaN where missing
    std: np.ndarray  # (K, L, 2) > 0
    C: np.ndarray  # (K-1, 3, 3)
    b: np.ndarray  # (K-1, 3)
    focal: float


def _validate(
    observations: object, rotations: object, translations: object, focal: object, pixel_std: object
) -> _Problem:
    f = check_focal(focal)
    obs = as_float_array("observations", observations)
    if obs.ndim == 2 and obs.shape[-1] == 2:
        obs = obs[:, None, :]
    if obs.ndim != 3 or obs.shape[-1] != 2:
        raise InvalidInputError(
            f"observations must have shape (K images, L landmarks, 2) as (x, y), NaN where unseen; got {obs.shape}"
        )
    K, L, _ = obs.shape
    if K < 2:
        raise NotEnoughDataError(f"estimate_landmarks needs >= 2 images; got {K}")
    if np.isinf(obs).any():
        raise InvalidInputError("observations must not contain infinity (NaN marks an unseen landmark)")
    C = as_float_array("rotations", rotations)
    b = as_float_array("translations", translations)
    if C.shape != (K - 1, 3, 3):
        raise InvalidInputError(f"rotations must have shape ({K - 1}, 3, 3) for {K} images; got {C.shape}")
    if b.shape != (K - 1, 3):
        raise InvalidInputError(f"translations must have shape ({K - 1}, 3) for {K} images; got {b.shape}")
    for k in range(K - 1):
        check_motion(C[k], b[k], what=f"s[{k}]")
    std = as_float_array("pixel_std", pixel_std)
    if std.ndim == 0 or std.shape == (2,) or std.shape == (K, L, 2):
        std = np.broadcast_to(std, (K, L, 2))
    else:
        raise InvalidInputError(f"pixel_std must be a scalar, (2,) for (x, y), or ({K}, {L}, 2); got {std.shape}")
    check_finite("pixel_std", std)
    if np.any(std <= 0):
        raise InvalidInputError(
            f"pixel_std must be > 0 (the estimators weight observations by 1/σ²); got {std.min()}"
        )
    return _Problem(obs, std, C, b, f)


def _pair_measurements(pr: _Problem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    K, L, _ = pr.obs.shape
    p = np.full((K, L, 3), np.nan)
    R = np.full((K, L, 3, 3), np.nan)
    status = np.full((K, L), TRIANGULATION_NOT_OBSERVED, dtype=np.int8)
    for k in range(1, K):
        seen = ~np.isnan(pr.obs[k - 1]).any(-1) & ~np.isnan(pr.obs[k]).any(-1)
        if not seen.any():
            continue
        std4 = np.concatenate([pr.std[k - 1, seen], pr.std[k, seen]], axis=1)
        tri = triangulate_midpoint(pr.obs[k - 1, seen], pr.obs[k, seen], pr.C[k - 1], pr.b[k - 1], pr.focal, std4)
        p[k, seen], R[k, seen], status[k, seen] = tri.points, tri.covariances, tri.status
    return p, R, status


def _fuse_pairs(
    p: np.ndarray, R: np.ndarray, status: np.ndarray, C: np.ndarray, b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Kalman fusion of the pair triangulations, as fuse_recursive, starting each landmark at its first pair."""
    K, L, _ = p.shape
    usable = (status != TRIANGULATION_NOT_OBSERVED) & (status != TRIANGULATION_PARALLEL_RAYS)
    # A singular first-order covariance (e.g. no noise on some coordinates) cannot be fused.
    usable &= np.linalg.eigvalsh(np.where(usable[..., None, None], R, np.eye(3)))[..., 0] > 0
    xs = np.full((K, L, 3), np.nan)
    Ps = np.full((K, L, 3, 3), np.nan)
    x = np.zeros((L, 3))
    P = np.broadcast_to(np.eye(3), (L, 3, 3)).copy()
    started = np.zeros(L, dtype=bool)
    for k in range(1, K):
        if started.any():
            # eq. 23 (no process noise): x_k = C_{k-1} x_{k-1} - b_{k-1}
            x, P = kalman_predict(x, P, C[k - 1], np.zeros((3, 3)), -b[k - 1])
        update = usable[k] & started
        if update.any():
            z = np.where(update[:, None], p[k], np.nan)
            Rk = np.where(update[:, None, None], R[k], np.eye(3))
            res = kalman_update(x, P, z, np.eye(3), Rk)
            x, P = res.x, np.broadcast_to(res.P, (L, 3, 3)).copy()
        start = usable[k] & ~started
        x[start], P[start] = p[k, start], R[k, start]
        started |= start
        xs[k, started], Ps[k, started] = x[started], P[started]
    return xs, Ps


def _reprojection(
    X0: np.ndarray, A: np.ndarray, c: np.ndarray, obs: np.ndarray, w: np.ndarray, focal: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened residuals (J, L, 2), their Jacobian w.r.t. X0 (J, L, 2, 3) and min depth (L,) over seen views."""
    Xj = np.einsum("jab,lb->jla", A, X0) - c[:, None, :]
    Z = Xj[..., 2]
    seen = ~np.isnan(obs[..., 0])
    Zs = np.where(seen, Z, np.inf)
    Zsafe = np.where(np.abs(Z) > 0, Z, 1.0)
    pred = focal * Xj[..., :2] / Zsafe[..., None]
    r = np.where(seen[..., None], (obs - pred) * w, 0.0)
    # d(f X/Z, f Y/Z)/dX_j = (f/Z) [[1, 0, -X/Z], [0, 1, -Y/Z]], then dX_j/dX0 = A_j
    D = np.zeros(Xj.shape[:2] + (2, 3))
    D[..., 0, 0] = D[..., 1, 1] = 1.0
    D[..., 0, 2] = -Xj[..., 0] / Zsafe
    D[..., 1, 2] = -Xj[..., 1] / Zsafe
    D *= (focal / Zsafe)[..., None, None]
    Jac = np.einsum("jlab,jbc->jlac", D, A) * w[..., None]
    Jac = np.where(seen[..., None, None], Jac, 0.0)
    return r, Jac, Zs.min(axis=0)


def _gauss_newton(
    X0: np.ndarray, A: np.ndarray, c: np.ndarray, obs: np.ndarray, w: np.ndarray, focal: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt-damped Gauss-Newton over L independent 3-vectors; returns X0, normal matrix, converged.

    Converged means the undamped Gauss-Newton step δ = N⁻¹ g left is negligible
    against the estimate's own uncertainty: δᵀ N δ = gᵀ N⁻¹ g < 1e-6 (the
    squared step length in standard deviations).
    """
    L = X0.shape[0]
    X0 = X0.copy()
    lam = np.full(L, 1e-3)
    r, Jac, _ = _reprojection(X0, A, c, obs, w, focal)
    cost = np.sum(r**2, axis=(0, 2))
    eye = np.eye(3)
    stalled = np.zeros(L, dtype=bool)
    for _ in range(_MAX_ITERATIONS):
        N = np.einsum("vlai,vlaj->lij", Jac, Jac)
        g = np.einsum("vlai,vla->li", Jac, r)
        # A tiny ridge keeps the solves defined where N is (numerically) singular.
        ridge = 1e-14 * np.trace(N, axis1=1, axis2=2) + np.finfo(float).tiny
        gn_step = np.linalg.solve(N + ridge[:, None, None] * eye, g[..., None])[..., 0]
        decrement = np.einsum("li,li->l", g, gn_step)  # gᵀ N⁻¹ g, the squared GN step in standard deviations
        # Iterate to full precision (exact data) while steps still lower the cost; once the step is
        # statistically negligible, one step without progress ends the iteration.
        active = (decrement >= _STOP_TOLERANCE * (1.0 + cost)) & (lam < 1e12)
        active &= ~((decrement < _STEP_TOLERANCE) & stalled)
        if not active.any():
            break
        # Only the landmarks still iterating are stepped (the others would cost as much for nothing).
        a = np.flatnonzero(active)
        Na = N[a]
        damped = Na + (lam[a, None, None] * np.diagonal(Na, axis1=1, axis2=2)[:, :, None] + ridge[a, None, None]) * eye
        step = np.linalg.solve(damped, g[a, :, None])[..., 0]
        X_new = X0[a] + step
        r_new, J_new, z_new = _reprojection(X_new, A, c, obs[:, a], w[:, a], focal)
        cost_new = np.sum(r_new**2, axis=(0, 2))
        # Accept a step that keeps the point in front of every camera and does not raise the cost.
        ok = (z_new > 0) & (cost_new <= cost[a]) & np.isfinite(cost_new)
        acc = a[ok]
        X0[acc] = X_new[ok]
        r[:, acc] = r_new[:, ok]
        Jac[:, acc] = J_new[:, ok]
        stalled[a] = ~ok | (cost[a] - cost_new <= 1e-14 * cost[a])
        cost[acc] = cost_new[ok]
        lam[a] = np.where(ok, np.maximum(lam[a] / 10.0, 1e-12), np.minimum(lam[a] * 10.0, 1e12))
    N = np.einsum("vlai,vlaj->lij", Jac, Jac)
    g = np.einsum("vlai,vla->li", Jac, r)
    ridge = 1e-14 * np.trace(N, axis1=1, axis2=2) + np.finfo(float).tiny
    decrement = np.einsum("li,li->l", g, np.linalg.solve(N + ridge[:, None, None] * eye, g[..., None])[..., 0])
    return X0, N, decrement < _STEP_TOLERANCE


def _initial_depth_search(obs0: np.ndarray, obs1: np.ndarray, A1: np.ndarray, c1: np.ndarray, w: np.ndarray,
                          focal: float) -> np.ndarray:
    """Points on the first image's ray at the depth (log-spaced grid) that best explains the second image."""
    baseline = max(float(np.linalg.norm(c1)), 1e-9)
    depths = baseline * np.geomspace(1e-2, 1e5, 141)
    ray = np.concatenate([obs0, np.full(obs0.shape[:-1] + (1,), focal)], axis=-1) / focal  # (L, 3), Z = 1
    cand = depths[:, None, None] * ray[None]  # (G, L, 3)
    X1 = np.einsum("ab,glb->gla", A1, cand) - c1
    Z = X1[..., 2]
    pred = focal * X1[..., :2] / np.where(Z > 0, Z, 1.0)[..., None]
    cost = np.where(Z > 0, np.sum(((obs1 - pred) * w) ** 2, axis=-1), np.inf)
    best = np.argmin(cost, axis=0)
    return cand[best, np.arange(obs0.shape[0])]


def _batch(pr: _Problem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    K, L, _ = pr.obs.shape
    A, c = _cumulative_poses(pr.C, pr.b)
    w = 1.0 / pr.std
    seen = ~np.isnan(pr.obs).any(-1)  # (K, L)
    obs = np.where(seen[..., None], pr.obs, np.nan)
    xs = np.full((K, L, 3), np.nan)
    Ps = np.full((K, L, 3, 3), np.nan)
    converged = np.zeros((K, L), dtype=bool)
    X0 = np.full((L, 3), np.nan)
    first = np.argmax(seen, axis=0)  # first image each landmark is seen in
    n_seen = np.cumsum(seen, axis=0)
    for k in range(1, K):
        ready = n_seen[k] >= 2
        # Start landmarks that have just reached two observations: search the depth along their first ray.
        new = ready & np.isnan(X0[:, 0])
        if new.any():
            idx = np.flatnonzero(new)
            j0 = first[idx]
            rays = pr.obs[j0, idx]
            # The first ray in its own frame, then moved to frame 0: X0 = A_j0ᵀ (X_j0 + c_j0).
            init_j0 = np.empty((idx.size, 3))
            for j in np.unique(j0):
                sel = j0 == j
                # depth searched against the current image k
                A_rel = A[k] @ A[j].T
                c_rel = c[k] - A_rel @ c[j]
                init_j0[sel] = _initial_depth_search(rays[sel], pr.obs[k, idx[sel]], A_rel, c_rel,
                                                     w[k, idx[sel]], pr.focal)
                init_j0[sel] = (init_j0[sel] + c[j]) @ A[j]
            X0[idx] = init_j0
        if not ready.any():
            continue
        idx = np.flatnonzero(ready)
        X, N, ok = _gauss_newton(X0[idx], A[: k + 1], c[: k + 1], obs[: k + 1, idx], w[: k + 1, idx], pr.focal)
        X0[idx] = X
        eig = np.linalg.eigvalsh(N)
        # A normal matrix this ill-conditioned (no depth information at all) has no usable inverse.
        good = np.isfinite(eig).all(axis=1) & (eig[:, 0] > 1e-13 * eig[:, -1])
        P0 = np.full((idx.size, 3, 3), np.nan)
        P0[good] = np.linalg.inv(N[good])
        # X_k = A_k X0 - c_k ; Cov_k = A_k Cov_0 A_kᵀ
        xs[k, idx] = X @ A[k].T - c[k]
        Ps[k, idx] = A[k] @ P0 @ A[k].T
        converged[k, idx] = ok & good
    return xs, Ps, converged


def estimate_landmarks(
    observations: object,
    rotations: object,
    translations: object,
    focal: float,
    pixel_std: object,
    method: str = "batch",
) -> LandmarkEstimates:
    """Estimate landmarks after every image from a camera with known motion.

    Parameters
    ----------
    observations : (K, L, 2) float, or (K, 2) for one landmark
        Image coordinates (x, y) of L landmarks in K images (from the principal
        point, pixels); NaN where a landmark is not seen.
    rotations : (K-1, 3, 3)
        C_k with X_{k+1} = C_k X_k - b_k (camera frame k to k+1).
    translations : (K-1, 3)
        b_k, non-zero (no triangulation without a baseline).
    focal : float
        Focal length f > 0 in pixels.
    pixel_std : float, (2,) or (K, L, 2)
        Standard deviation (> 0) of the image noise in x and y, pixels.
    method : {"batch", "pairs"}
        ``"batch"``: Gauss-Newton maximum likelihood on all observations so far,
        re-solved after every image (consistent).  ``"pairs"``: the report's
        Kalman fusion of consecutive-pair triangulations (over-confident).

    Returns
    -------
    LandmarkEstimates
        Estimates in the camera frame of each image, the pair triangulations and
        status flags.  A landmark that cannot be estimated yet is NaN there, with
        ``converged`` False; nothing raises in the middle of a sequence.

    Examples
    --------
    A landmark seen from three positions along the optical axis, no noise:

    >>> import numpy as np
    >>> X0 = np.array([4.0, 2.0, 20.0]); b = np.array([0.0, 0.0, 1.0])
    >>> X = np.stack([X0 - k * b for k in range(3)])
    >>> obs = 500.0 * X[:, :2] / X[:, 2:]
    >>> est = estimate_landmarks(obs, np.stack([np.eye(3)] * 2), np.stack([b] * 2), 500.0, 0.5)
    >>> est.estimates[2, 0].round(6)
    array([ 4.,  2., 18.])
    >>> bool(np.isnan(est.estimates[0]).all())
    True
    """
    if method not in METHODS:
        raise InvalidInputError(f"method must be one of {', '.join(METHODS)}; got {method!r}")
    pr = _validate(observations, rotations, translations, focal, pixel_std)
    p, R, status = _pair_measurements(pr)
    if method == "pairs":
        xs, Ps = _fuse_pairs(p, R, status, pr.C, pr.b)
        converged = ~np.isnan(xs[..., 0])
    else:
        xs, Ps, converged = _batch(pr)
    return LandmarkEstimates(method, xs, Ps, p, R, status, converged)
