"""Structure fusion with known cameras: every point's 3-D position and covariance, refined view by view.

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
    Gauss–Newton in (X, Y, Z) (:func:`~.pinhole.refine_points`).
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

from collections.abc import Callable, Iterable
from typing import Any
from dataclasses import dataclass

import numpy as np
from scipy import stats

from ...errors import InvalidInputError, NotEnoughDataError
from ..._validation import as_float_array, check_count, check_positive
from ...estimation.kalman import kalman_update
from ..geometry.pinhole import (
    CameraSet,
    _inverse3,
    _solve3,
    decompose_projection,
    project_each,
    project_points,
    projection_jacobians,
    refine_points,
    triangulate_points,
)
from ..points import PointStatus
from ..geometry.triangulation import triangulate_midpoint

__all__ = [
    "DEFAULT_CHUNK_POINTS",
    "DEFAULT_OUTLIER_PROBABILITY",
    "FUSION_METHODS",
    "FusedStructure",
    "FusionHistory",
    "FusionSettings",
    "GatedUpdate",
    "PairTriangulations",
    "fuse",
    "iterated_update",
    "pair_triangulations",
]

FUSION_METHODS = ("recursive", "batch", "pairs")
DEFAULT_OUTLIER_PROBABILITY = 0.999
DEFAULT_CHUNK_POINTS = 65_536

# Iterated EKF: at most this many relinearisations; stop when no component moves more than
# _IEKF_TOLERANCE of its own standard deviation.
_IEKF_ITERATIONS = 10
_IEKF_TOLERANCE = 1e-6
# Gauss–Newton iterations of the two-view start.
_START_ITERATIONS = 20
# A two-view (unit-σ) normal matrix more ill-conditioned than this carries no depth at all.
_MAX_CONDITION = 1e14
# Auto σ: stop re-estimating when it changes by less than this fraction; at most this many passes.
_SIGMA_TOLERANCE = 5e-3
_MAX_SIGMA_PASSES = 8
# States converted from inverse depth to (X, Y, Z) together (bounds the temporaries).
_CONVERSION_BLOCK = 16_384
# Points used to decide the scene orientation (the sign of the depths most points agree on).
_ORIENTATION_SAMPLE = 2_000


@dataclass(frozen=True)
class FusionSettings:
    """How :func:`fuse` runs; validated on construction.

    Attributes
    ----------
    method : ``"recursive"``, ``"batch"`` or ``"pairs"``.
    pixel_std : float > 0 in pixels, or None to estimate it (``"auto"``).
    outlier_probability : in (0, 1]; the gate is the χ² quantile of this probability
        (1 turns outlier rejection off).
    history : keep every point's estimate after every view that observed it.
    chunk_points : points processed together (bounds the memory).
    orientation : +1 (points in front of the cameras), -1 (a mirrored reconstruction) or
        None to take the sign most points' depths agree on.
    """

    method: str = "recursive"
    pixel_std: float | None = None
    outlier_probability: float = DEFAULT_OUTLIER_PROBABILITY
    history: bool = False
    chunk_points: int = DEFAULT_CHUNK_POINTS
    orientation: int | None = None

    def __post_init__(self) -> None:
        if self.method not in FUSION_METHODS:
            raise InvalidInputError(f"method must be one of {', '.join(FUSION_METHODS)}; got {self.method!r}")
        if self.pixel_std is not None:
            object.__setattr__(self, "pixel_std", check_positive("pixel_std", self.pixel_std, "pixels"))
        try:
            p = float(self.outlier_probability)
        except (TypeError, ValueError):
            raise InvalidInputError(f"outlier_probability must be a number in (0, 1]; got "
                                    f"{self.outlier_probability!r}") from None
        if not 0.0 < p <= 1.0:
            raise InvalidInputError(f"outlier_probability must be in (0, 1]; got {p}")
        object.__setattr__(self, "outlier_probability", p)
        object.__setattr__(self, "chunk_points", check_count("chunk_points", self.chunk_points, 1))
        object.__setattr__(self, "history", bool(self.history))
        if self.orientation is not None:
            object.__setattr__(self, "orientation", _check_orientation(self.orientation))

    @property
    def gate2(self) -> float:
        """χ²(2) quantile of ``outlier_probability`` (inf when 1)."""
        return float(stats.chi2.ppf(self.outlier_probability, 2)) if self.outlier_probability < 1 else np.inf

    @property
    def gate1(self) -> float:
        """χ²(1) quantile of ``outlier_probability`` (inf when 1)."""
        return float(stats.chi2.ppf(self.outlier_probability, 1)) if self.outlier_probability < 1 else np.inf


@dataclass(frozen=True)
class FusionHistory:
    """Each point's estimate after every view that observed it, from its second view on.

    Entries are sorted by view, then point.

    Attributes
    ----------
    views : (H,) int64 — view index (into the cameras) after which the estimate holds.
    points : (H,) int64 — point index.
    estimates : (H, 3) — NaN where the estimate has no finite (X, Y, Z) yet (depth undetermined).
    covariances : (H, 3, 3).
    states, state_covariances : (H, 3), (H, 3, 3) or None — for ``recursive``, the filter's own
        state: the inverse depth (α, β, ρ) in the anchor view (X = C_a + o R_aᵀ (α, β, 1) / ρ).
    anchors : (H,) int or None — the anchor view of each state.
    """

    views: np.ndarray
    points: np.ndarray
    estimates: np.ndarray
    covariances: np.ndarray
    states: np.ndarray | None = None
    state_covariances: np.ndarray | None = None
    anchors: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.views.shape[0])

    def dense(self, n_views: int, n_points: int, *, states: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(V, N, 3) estimates and (V, N, 3, 3) covariances (the filter states with ``states``), NaN where none."""
        values, covariances = (self.states, self.state_covariances) if states else (self.estimates, self.covariances)
        if values is None:
            raise InvalidInputError("this history has no filter states (only method='recursive' keeps them)")
        X = np.full((n_views, n_points, 3), np.nan)
        C = np.full((n_views, n_points, 3, 3), np.nan)
        X[self.views, self.points] = values
        C[self.views, self.points] = covariances
        return X, C

    def first(self) -> FusionHistory:
        """The first entry of every point (its two-view estimate for ``recursive``)."""
        order = np.lexsort((self.views, self.points))
        pts = self.points[order]
        keep = order[np.r_[True, pts[1:] != pts[:-1]]] if pts.size else order
        return self._take(keep)

    def _take(self, index: np.ndarray) -> FusionHistory:
        return FusionHistory(*(None if a is None else a[index] for a in (
            self.views, self.points, self.estimates, self.covariances, self.states, self.state_covariances,
            self.anchors)))


@dataclass(frozen=True)
class FusedStructure:
    """Fused 3-D points with covariances, from known cameras.

    Attributes
    ----------
    method : the method used.
    points : (N, 3) — NaN where the status is not OK.
    covariances : (N, 3, 3) — NaN where the status is not OK.
    status : (N,) int8 — :class:`~.points.PointStatus` values (``ok``, ``too_few_views``,
        ``degenerate``, ``behind_camera``).
    views : (N,) int — observations used (accepted) per point.
    reprojection_rms : (N,) — RMS reprojection error (pixels) over the accepted observations.
    residuals : (V, N) — length of each observation's reprojection error at the final
        estimate (pixels), rejected ones included; NaN where not observed or the point
        has no estimate.
    rejected : (V, N) bool — observations rejected as outliers.
    pixel_std : σ (pixels) the covariances are scaled with.
    pixel_std_estimated : σ was estimated from the residuals (``"auto"``).
    degrees_of_freedom : 2 × accepted observations - 3 × fused points.
    orientation : +1, or -1 for a mirrored reconstruction (points at negative depth).
    passes : passes over the data (more than 1 when σ was estimated).
    history : :class:`FusionHistory` or None (only when asked for).
    """

    method: str
    points: np.ndarray
    covariances: np.ndarray
    status: np.ndarray
    views: np.ndarray
    reprojection_rms: np.ndarray
    residuals: np.ndarray
    rejected: np.ndarray
    pixel_std: float
    pixel_std_estimated: bool
    degrees_of_freedom: int
    orientation: int
    passes: int
    history: FusionHistory | None = None

    @property
    def fused(self) -> np.ndarray:
        """(N,) bool — points with an estimate (status OK)."""
        return self.status == PointStatus.OK

    @property
    def standard_deviations(self) -> np.ndarray:
        """(N, 3) per-axis standard deviations."""
        return np.sqrt(np.diagonal(self.covariances, axis1=-2, axis2=-1))

    def status_counts(self) -> dict[str, int]:
        """Points per status label."""
        return {s.label: int(np.count_nonzero(self.status == s)) for s in PointStatus}


# ---------------------------------------------------------------------------------------------
# Inverse depth anchored at a view.


@dataclass(frozen=True)
class _Geometry:
    """Per-view quantities shared by every chunk."""

    P: np.ndarray  # (V, 3, 4)
    K_inv: np.ndarray  # (V, 3, 3)
    R: np.ndarray  # (V, 3, 3) det +1
    t: np.ndarray  # (V, 3)
    C: np.ndarray  # (V, 3) centres
    orientation: int
    Q: np.ndarray  # (V anchor, V, 3, 4): P_v H_a, the cameras acting on (α, β, ρ, 1)
    depth_sign: np.ndarray  # (V,) sign of λ in P = λ K [R | t]: depth = w / λ


def _geometry(P: np.ndarray, orientation: int) -> _Geometry:
    pose = decompose_projection(P)
    R, C, o = pose.rotations, pose.centers, orientation
    V = P.shape[0]
    # X̃ = H_a (α, β, ρ, 1) with X = C_a + o R_aᵀ (α, β, 1) / ρ:
    # columns α, β, 1 → (o R_aᵀ e_i, 0) and ρ → (C_a, 1).
    H = np.zeros((V, 4, 4))
    Rt = np.swapaxes(R, 1, 2)
    H[:, :3, 0], H[:, :3, 1], H[:, :3, 3] = o * Rt[:, :, 0], o * Rt[:, :, 1], o * Rt[:, :, 2]
    H[:, :3, 2], H[:, 3, 2] = C, 1.0
    Q = np.einsum("vij,ajk->avik", P, H)
    return _Geometry(P, np.linalg.inv(pose.intrinsics), R, pose.translations, C, o, Q, np.sign(pose.scales))


def _theta_to_point(g: _Geometry, anchor: np.ndarray, theta: np.ndarray, cov: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y, Z) and its covariance from inverse depth; NaN where ρ <= 0.

    In the anchor's oriented frame the point is Y = (α, β, 1) / ρ, and X = C_a + o R_aᵀ Y.
    The estimate is the state's image Y(θ̂) (so exact data give the exact point, and the
    estimate is the maximum-likelihood point whenever θ̂ is).  The covariance is the
    second-order image of N(θ̂, P): with G = dY/dθ and H_i the Hessian of Y_i,

        cov = G P Gᵀ + ½ [tr(H_i P H_j P)]_ij

    The first-order term alone is over-confident when σ_ρ / ρ is not small (the depth
    1/ρ is skewed towards the far side); the second term vanishes with P.
    """
    a, b, rho = theta[:, 0], theta[:, 1], theta[:, 2]
    ok = rho > 0
    r = np.where(ok, rho, 1.0)
    n = theta.shape[0]
    G = np.zeros((n, 3, 3))
    G[:, 0, 0] = G[:, 1, 1] = 1.0 / r
    G[:, 0, 2], G[:, 1, 2], G[:, 2, 2] = -a / r**2, -b / r**2, -1.0 / r**2
    Hs = np.zeros((n, 3, 3, 3))  # Hs[:, i] = d²Y_i / dθ²
    Hs[:, 0, 0, 2] = Hs[:, 0, 2, 0] = Hs[:, 1, 1, 2] = Hs[:, 1, 2, 1] = -1.0 / r**2
    Hs[:, 0, 2, 2], Hs[:, 1, 2, 2], Hs[:, 2, 2, 2] = 2 * a / r**3, 2 * b / r**3, 2.0 / r**3
    HP = Hs @ cov[:, None]  # (n, 3, 3, 3)
    Y = np.stack([a, b, np.ones_like(a)], axis=1) / r[:, None]
    # tr(H_i P H_j P) = Σ_ab (H_i P)_ab (H_j P)_ba, as one batched (3 × 9)(9 × 3) product
    second = HP.reshape(n, 3, 9) @ np.swapaxes(HP, 2, 3).reshape(n, 3, 9).transpose(0, 2, 1)
    cov_Y = G @ cov @ np.swapaxes(G, 1, 2) + 0.5 * second
    Rt = np.swapaxes(g.R[anchor], 1, 2)
    X = g.C[anchor] + g.orientation * np.einsum("nij,nj->ni", Rt, Y)
    cov_X = Rt @ cov_Y @ np.swapaxes(Rt, 1, 2)
    X[~ok], cov_X[~ok] = np.nan, np.nan
    return X, cov_X


def _start_pairs(g: _Geometry, a: int, v: int, xa: np.ndarray, xv: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two-view start in inverse depth anchored at view a: θ, unit-σ covariance, cost (px²), usable."""
    n = xa.shape[0]
    # (α, β, 1) ∝ K_a⁻¹ x̃_a: the anchor view fixes the ray, whatever the depth
    m = np.concatenate([xa, np.ones((n, 1))], axis=1) @ g.K_inv[a].T
    m = m / m[:, 2:3]
    # ρ from view v with (α, β) fixed: x (q3·θ̃) - q1·θ̃ = 0 is linear in ρ, least squares over its 2 rows
    Qv = g.Q[a, v]
    base = np.concatenate([m[:, :2], np.zeros((n, 1)), np.ones((n, 1))], axis=1)  # θ̃ with ρ = 0
    u0 = base @ Qv.T  # (n, 3)
    du = Qv[:, 2]  # d(u, v, w)/dρ
    A = xv * du[2] - du[:2]  # (n, 2)
    rhs = -(xv * u0[:, 2:3] - u0[:, :2])
    denom = np.einsum("ni,ni->n", A, A)
    rho = np.where(denom > 0, np.einsum("ni,ni->n", A, rhs) / np.where(denom > 0, denom, 1.0), 0.0)
    theta = np.concatenate([m[:, :2], rho[:, None]], axis=1)
    cams = np.stack([g.Q[a, a], Qv])  # (2, 3, 4)
    obs = np.stack([xa, xv])  # (2, n, 2)

    def normal_equations(th: np.ndarray, o: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pix, _, J = project_each(cams[:, None], th[None])
        r = o - pix
        return (np.einsum("vnai,vnaj->nij", J, J), np.einsum("vnai,vna->ni", J, r),
                np.einsum("vna,vna->n", r, r))

    N, g_, cost = normal_equations(theta, obs)
    active = np.ones(n, dtype=bool)
    for _ in range(_START_ITERATIONS):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        step = _solve3(N[idx], g_[idx])
        trial = theta[idx] + step
        Nt, gt, ct = normal_equations(trial, obs[:, idx])
        better = np.isfinite(ct) & (ct <= cost[idx])
        acc = idx[better]
        theta[acc], N[acc], g_[acc], cost[acc] = trial[better], Nt[better], gt[better], ct[better]
        small = np.abs(step) <= _IEKF_TOLERANCE * np.sqrt(np.abs(np.diagonal(_inverse3(N[idx]), axis1=1, axis2=2)))
        active[idx] = better & ~small.all(axis=1)
    evals = np.linalg.eigvalsh(N)
    usable = np.isfinite(evals).all(axis=1) & (evals[:, 0] > evals[:, 2] / _MAX_CONDITION) & np.isfinite(theta).all(1)
    cov = np.full((n, 3, 3), np.nan)
    cov[usable] = np.linalg.inv(N[usable])
    return theta, cov, cost, usable


@dataclass(frozen=True)
class GatedUpdate:
    """The result of :func:`iterated_update` for n states.

    Attributes
    ----------
    states : (n, 3) — the posterior state, or the prior where the observation was rejected.
    covariances : (n, 3, 3) — its covariance, in the units of the prior's (divided by σ²).
    accepted : (n,) bool — the observations that passed the gate.
    """

    states: np.ndarray
    covariances: np.ndarray
    accepted: np.ndarray


def iterated_update(cameras: np.ndarray, prior: np.ndarray, prior_covariances: np.ndarray,
                    observations: np.ndarray, pixel_std: float, gate: float) -> GatedUpdate:
    """Gated iterated extended Kalman update of n 3-vector states, each by one 2-D projection.

    Each state θ is seen through its own 3 × 4 matrix: pixel = (u / w, v / w) with
    (u, v, w) = Q (θ, 1) — a camera acting on a point, or on a point's inverse depth (``fuse``'s
    recursive method), or a calibrated frame on a point in its own coordinates (the recursive
    perspective reconstruction).  The covariances are *unit-σ*: divided by σ², so that the
    measurement noise is the identity.  The observation is used when its normalised innovation at
    the prior, νᵀ S⁻¹ ν / σ² with ν = z − h(θ̂) and S = H P Hᵀ + I, is at most ``gate`` (a χ²(2)
    quantile); the update is then iterated, relinearising h at the latest iterate, until no
    component moves by more than 1e-6 of its standard deviation (at most 10 iterations).

    Parameters
    ----------
    cameras : (n, 3, 4) the matrix Q of each state.
    prior : (n, 3) states; prior_covariances : (n, 3, 3) their unit-σ covariances.
    observations : (n, 2) pixels (x = column, y = row).
    pixel_std : σ of the image noise, pixels (scales the gate only).
    gate : bound on νᵀ S⁻¹ ν / σ².

    Shapes are not validated: this is the kernel of the fusion loops.

    Returns
    -------
    GatedUpdate

    Examples
    --------
    A camera with a focal length of 100 px at the origin; a point 4 in front, believed 0.1 off
    in X, is seen at the centre; a second observation 40 px away fails the gate:

    >>> Q = np.broadcast_to(np.hstack([np.diag([100.0, 100.0, 1.0]), np.zeros((3, 1))]), (2, 3, 4))
    >>> prior, cov = np.array([[0.1, 0.0, 4.0]] * 2), np.stack([np.diag([0.01, 0.01, 1.0])] * 2)
    >>> up = iterated_update(Q, prior, cov, np.array([[0.0, 0.0], [40.0, 0.0]]), pixel_std=1.0, gate=13.8)
    >>> up.accepted.tolist(), bool(abs(up.states[0, 0]) < 0.02), bool(up.covariances[0, 0, 0] < 0.01)
    ([True, False], True, True)
    >>> np.array_equal(up.states[1], prior[1])
    True
    """
    Q, P, z = cameras, prior_covariances, observations
    eye2 = np.eye(2)
    pix, _, H = project_each(Q, prior)
    # The first iterate is the ordinary EKF update; its innovation decides the gate.
    first = kalman_update(prior, P, z - pix + np.einsum("nij,nj->ni", H, prior), H, eye2)
    nis = first.nis / pixel_std**2
    accept = nis <= gate
    theta, cov = prior.copy(), P.copy()
    theta[accept], cov[accept] = first.x[accept], first.P[accept]
    # Relinearise at the latest iterate: θ_{i+1} = θ̂ + K_i (z - h(θ_i) - H_i (θ̂ - θ_i)),
    # one kalman_update with the pseudo-measurement z - h(θ_i) + H_i θ_i.
    active = np.flatnonzero(accept)
    for _ in range(_IEKF_ITERATIONS - 1):
        if active.size == 0:
            break
        pix, _, H = project_each(Q[active], theta[active])
        z_lin = z[active] - pix + np.einsum("nij,nj->ni", H, theta[active])
        res = kalman_update(prior[active], P[active], z_lin, H, eye2)
        moved = np.abs(res.x - theta[active]) > _IEKF_TOLERANCE * np.sqrt(
            np.abs(np.diagonal(res.P, axis1=1, axis2=2)))
        theta[active], cov[active] = res.x, res.P
        active = active[moved.any(axis=1)]
    return GatedUpdate(theta, cov, accept)


@dataclass(frozen=True)
class _Chunk:
    """One chunk's job (picklable, so an executor can run it elsewhere)."""

    method: str
    geometry: _Geometry
    observations: np.ndarray  # (V, n, 2)
    sigma: float  # pixel σ the gates use
    gate2: float
    gate1: float
    history: bool


@dataclass(frozen=True)
class _ChunkResult:
    points: np.ndarray  # (n, 3)
    covariances: np.ndarray  # (n, 3, 3), unit σ
    status: np.ndarray
    used: np.ndarray  # (V, n) bool accepted observations
    rejected: np.ndarray  # (V, n) bool
    residuals: np.ndarray  # (V, n) length of observed - projected, NaN where unseen or no estimate
    # views, local points, states and their unit-σ covariances (θ for recursive, else X)
    history: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None
    anchors: np.ndarray | None = None  # (n,) for states in inverse depth: points/covariances hold θ and its P


@dataclass(frozen=True)
class _States:
    """What a recursive pass leaves: unit-σ inverse-depth states and the bookkeeping."""

    theta: np.ndarray  # (n, 3), NaN where not started
    cov: np.ndarray  # (n, 3, 3)
    anchor: np.ndarray  # (n,) -1 where not started
    started: np.ndarray  # (n,) bool
    stalled: np.ndarray  # (n,) bool: a pair without parallax was met
    used: np.ndarray  # (V, n) bool
    rejected: np.ndarray  # (V, n) bool
    residuals: np.ndarray  # (V, n, 2) observed - projected at the final state, every observation; NaN elsewhere
    in_front: np.ndarray  # (n,) bool: positive oriented depth in every used view (started points)
    history: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None


def _residuals_and_cheirality(g: _Geometry, obs: np.ndarray, theta: np.ndarray, anchor: np.ndarray,
                              started: np.ndarray, used: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of every observation at the final θ, and whether the point is in front of its used views.

    With X̃ = H_a θ̃ = ρ (X, 1), the projective depth through Q = P_v H_a is ρ w, so the
    depth's sign in view v is sign(w_θ) sign(ρ) sign(λ_v).
    """
    V, n, _ = obs.shape
    residuals = np.full((V, n, 2), np.nan)
    in_front = np.zeros(n, dtype=bool)
    for a in np.unique(anchor[started]):  # one group per anchor view, not per point
        idx = np.flatnonzero(started & (anchor == a))
        pix, w, _ = project_each(g.Q[a][:, None], theta[idx][None])
        residuals[:, idx] = obs[:, idx] - pix
        depth_sign = np.sign(w) * np.sign(theta[idx, 2]) * g.depth_sign[:, None]
        in_front[idx] = ~np.any(used[:, idx] & (depth_sign * g.orientation <= 0), axis=0)
    return residuals, in_front


def _pair_starts(g: _Geometry, first: np.ndarray, second: np.ndarray, obs: np.ndarray, idx: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two-view starts of points idx from views (first, second), which vary per point.

    Returns θ (m, 3), unit-σ covariance (m, 3, 3) and the pair cost in px² (inf where the
    pair has no parallax).  One group per pair of views, not per point.
    """
    m = idx.size
    theta, cov, cost = np.full((m, 3), np.nan), np.full((m, 3, 3), np.nan), np.full(m, np.inf)
    codes = first * obs.shape[0] + second
    for code in np.unique(codes):
        a, v = divmod(int(code), obs.shape[0])
        sel = np.flatnonzero(codes == code)
        th, P, c, usable = _start_pairs(g, a, v, obs[a, idx[sel]], obs[v, idx[sel]])
        theta[sel], cov[sel] = th, P
        cost[sel] = np.where(usable, c, np.inf)
    return theta, cov, cost


def _recursive_states_numpy(job: _Chunk) -> _States:
    """The reference implementation, vectorised over the points of each view.

    Each point is in one of five states when a view sees it:

    * nothing yet: the view becomes its first pending observation;
    * one pending observation a: the pair (a, v) starts the point *provisionally* if it is
      consistent (χ²(1) test); an inconsistent pair is kept as a *conflict* (a, v);
      a pair without parallax is skipped (the point waits for another view);
    * provisional (started from the pair (a, b)) or conflict (a, b): the view must agree;
      a provisional point updated by it is *verified*; otherwise the triple (a, b, v) is
      resolved (``_resolve``);
    * verified: gated iterated EKF update; a failed gate rejects the observation.
    """
    g, obs = job.geometry, job.observations
    V, n, _ = obs.shape
    seen_all = np.isfinite(obs).all(axis=2)
    theta = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    first = np.full(n, -1)  # the start pair, or the pending observation(s)
    second = np.full(n, -1)
    started = np.zeros(n, dtype=bool)
    verified = np.zeros(n, dtype=bool)
    used = np.zeros((V, n), dtype=bool)
    rejected = np.zeros((V, n), dtype=bool)
    stalled = np.zeros(n, dtype=bool)  # a pair without parallax was met
    restart = np.zeros(n, dtype=np.int64)  # history before this view belongs to an abandoned start
    hist: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    gate1_px = job.gate1 * job.sigma**2

    def resolve(idx: np.ndarray, a: np.ndarray, b: np.ndarray, c: int, provisional: np.ndarray) -> None:
        """Three observations (a, b, c) that do not agree: drop the one whose removal leaves the
        most consistent pair, if that pair is consistent; otherwise drop the oldest, keep a conflict.

        A provisional point whose own pair (a, b) wins keeps its state (c is rejected).
        """
        cv = np.full(idx.size, c)
        hyps = [(b, cv), (a, cv), (a, b)]  # drop a, drop b, drop c
        fits = [_pair_starts(g, f, s_, obs, idx) for f, s_ in hyps]
        costs = np.stack([f[2] for f in fits], axis=1)
        k = np.argmin(costs, axis=1)
        ok = costs[np.arange(idx.size), k] <= gate1_px
        keep = ok & provisional & (k == 2)
        rejected[c, idx[keep]] = True
        new = ok & ~keep
        dropped = np.where(k == 0, a, np.where(k == 1, b, cv))
        for h, (f, s_) in enumerate(hyps):
            sel = new & (k == h)
            pts = idx[sel]
            theta[pts], cov[pts] = fits[h][0][sel], fits[h][1][sel]
            first[pts], second[pts] = f[sel], s_[sel]
            used[f[sel], pts] = used[s_[sel], pts] = True
            if job.history and pts.size:
                hist.append((c, pts, fits[h][0][sel], fits[h][1][sel]))
        pts = idx[new]
        used[dropped[new], pts], rejected[dropped[new], pts] = False, True
        started[pts], verified[pts] = True, False
        restart[pts] = c
        # no consistent pair: the oldest goes, the other two remain a conflict
        pts = idx[~ok]
        used[a[~ok], pts] = used[b[~ok], pts] = False
        rejected[a[~ok], pts] = True
        theta[pts], cov[pts] = np.nan, np.nan
        started[pts], verified[pts] = False, False
        first[pts], second[pts] = b[~ok], c
        restart[pts] = c + 1

    for v in range(V):
        seen = seen_all[v]
        # states at the start of the view (a point changes state at most once per view)
        verified_now = seen & started & verified
        provisional_now = seen & started & ~verified
        single_now = seen & ~started & (first >= 0) & (second < 0)
        conflict_now = seen & ~started & (second >= 0)
        empty_now = seen & ~started & (first < 0)

        # updates: gated iterated EKF, all points at once
        idx = np.flatnonzero(verified_now | provisional_now)
        if idx.size:
            up = iterated_update(g.Q[first[idx], v], theta[idx], cov[idx], obs[v, idx], job.sigma, job.gate2)
            th, P, ok = up.states, up.covariances, up.accepted
            acc = idx[ok]
            theta[acc], cov[acc] = th[ok], P[ok]
            used[v, acc] = True
            verified[acc] = True
            rejected[v, idx[~ok & verified_now[idx]]] = True
            if job.history:
                hist.append((v, acc, th[ok], P[ok]))
            fail = idx[~ok & provisional_now[idx]]
            if fail.size:
                resolve(fail, first[fail], second[fail], v, np.ones(fail.size, dtype=bool))
        # second observation: a provisional start or a conflict
        idx = np.flatnonzero(single_now)
        if idx.size:
            th, P, cost = _pair_starts(g, first[idx], np.full(idx.size, v), obs, idx)
            usable = np.isfinite(cost)
            stalled[idx[~usable]] = True  # no parallax with the pending view: wait for another view
            go_mask = usable & (cost <= gate1_px)
            go = idx[go_mask]
            theta[go], cov[go], second[go], started[go] = th[go_mask], P[go_mask], v, True
            used[first[go], go] = used[v, go] = True
            second[idx[usable & ~go_mask]] = v
            if job.history and go.size:
                hist.append((v, go, th[go_mask], P[go_mask]))
        idx = np.flatnonzero(conflict_now)
        if idx.size:
            resolve(idx, first[idx], second[idx], v, np.zeros(idx.size, dtype=bool))
        first[empty_now] = v

    anchor = np.where(started, first, -1)
    residuals, in_front = _residuals_and_cheirality(g, obs, theta, anchor, started, used)
    history = None
    if job.history:
        views, pts, th, P = _concat_history(hist)
        current = views >= restart[pts]  # the estimates of the point's final start only
        history = (views[current], pts[current], th[current], P[current])
    return _States(theta, cov, anchor, started, stalled, used, rejected, residuals, in_front, history)


def _recursive_states_compiled(job: _Chunk) -> _States:
    """The numba kernel (:mod:`._recursive_kernel`), point by point; same results as the reference."""
    from ._recursive_kernel import recursive_pass

    g = job.geometry
    V, n, _ = job.observations.shape
    # point-major copies: a point's views sit together in memory while the kernel walks through them
    obs = np.ascontiguousarray(job.observations.transpose(1, 0, 2))
    theta = np.full((n, 3), np.nan)
    cov = np.full((n, 3, 3), np.nan)
    anchor = np.full(n, -1, dtype=np.int64)
    started = np.zeros(n, dtype=bool)
    stalled = np.zeros(n, dtype=bool)
    used = np.zeros((n, V), dtype=bool)
    rejected = np.zeros((n, V), dtype=bool)
    residuals = np.full((n, V, 2), np.nan)
    in_front = np.zeros(n, dtype=bool)
    shape = (n, V) if job.history else (0, 0)
    hist_theta, hist_cov = np.zeros(shape + (3,)), np.zeros(shape + (3, 3))
    hist_mask = np.zeros(shape, dtype=bool)
    recursive_pass(np.ascontiguousarray(g.Q), np.ascontiguousarray(g.K_inv), g.depth_sign * float(g.orientation),
                   obs, float(job.sigma), float(job.gate2), float(job.gate1), _START_ITERATIONS, _IEKF_ITERATIONS,
                   _IEKF_TOLERANCE, _MAX_CONDITION, bool(job.history), theta, cov, anchor, started, stalled, used,
                   rejected, residuals, in_front, hist_theta, hist_cov, hist_mask)
    history = None
    if job.history:
        views, pts = np.nonzero(hist_mask.T)
        history = (views, pts, hist_theta[pts, views], hist_cov[pts, views])
    return _States(theta, cov, anchor, started, stalled, used.T, rejected.T, residuals.transpose(1, 0, 2), in_front,
                   history)


#: The recursive pass runs the compiled kernel; the NumPy reference is kept for the tests to compare.
_RECURSIVE_STATES = _recursive_states_compiled


def _recursive(job: _Chunk) -> _ChunkResult:
    n = job.observations.shape[1]
    st = _RECURSIVE_STATES(job)
    theta, cov, started = st.theta, st.cov, st.started
    status = np.full(n, PointStatus.OK, dtype=np.int8)
    status[~started] = np.where(st.stalled[~started], PointStatus.DEGENERATE, PointStatus.TOO_FEW_VIEWS)
    # ρ <= 0: the estimate lies beyond infinity; clearly so (3σ) is a point behind the cameras,
    # otherwise the depth is not determined yet
    rho_std = np.sqrt(np.abs(cov[:, 2, 2]))
    no_depth = started & ~(theta[:, 2] > 0)
    status[no_depth] = np.where(theta[no_depth, 2] + 3 * rho_std[no_depth] < 0, PointStatus.BEHIND_CAMERA,
                                PointStatus.DEGENERATE)
    status[(status == PointStatus.OK) & ~st.in_front] = PointStatus.BEHIND_CAMERA
    # The state goes out in inverse depth: its (X, Y, Z) image depends on σ (second-order terms), known later.
    return _finish(theta, cov, status, st.used, st.rejected, st.residuals, st.history, st.anchor)


def _finish(X, C, status, used, rejected, residuals, history, anchors=None) -> _ChunkResult:
    ok = status == PointStatus.OK
    X = np.where(ok[:, None], X, np.nan)
    C = np.where(ok[:, None, None], C, np.nan)
    lengths = np.where(ok[None, :], np.linalg.norm(residuals, axis=2), np.nan)
    return _ChunkResult(X, C, status, used & ok, rejected, lengths, history, anchors)


def _leave_one_out(P: np.ndarray, X: np.ndarray, r: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(V, n) rᵀ (I - J N⁻¹ Jᵀ)⁻¹ r of each used observation (unit σ), NaN elsewhere."""
    J = projection_jacobians(P, X)
    J = np.where(mask[..., None, None], J, 0.0)
    N_inv = _inverse3(np.einsum("vnai,vnaj->nij", J, J))
    hat = np.einsum("vnai,nij,vnbj->vnab", J, N_inv, J)
    A = np.eye(2) - hat
    det = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    det = np.where(mask & (det > 1e-12), det, np.nan)
    # 2 × 2 inverse quadratic form: rᵀ adj(A) r / det(A)
    q = (A[..., 1, 1] * r[..., 0] ** 2 - (A[..., 0, 1] + A[..., 1, 0]) * r[..., 0] * r[..., 1]
         + A[..., 0, 0] * r[..., 1] ** 2)
    return q / det


def _batch_fit(P: np.ndarray, obs: np.ndarray, mask: np.ndarray, start: np.ndarray | None, orientation: int):
    if start is None:
        start = triangulate_points(P, obs, visible=mask, orientation=orientation).points
    return refine_points(P, obs, start, visible=mask, pixel_std=1.0, orientation=orientation)


def _batch(job: _Chunk) -> _ChunkResult:
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
        hist = _concat_history(hist_parts)
    # residuals of every observation (rejected included) at the final estimate
    ok = status == PointStatus.OK
    pix = project_points(g.P, np.where(ok[:, None], X, 0.0)).pixels
    residuals = np.where(np.isfinite(obs).all(axis=2)[..., None], obs - pix, np.nan)
    return _finish(X, C, status, mask, rejected, residuals, hist)


def _concat_history(parts: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    if not parts:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    return (np.concatenate([np.full(p[1].size, p[0]) for p in parts]), np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]), np.concatenate([p[3] for p in parts]))


def _pair_triangulation(g: _Geometry, a: int, v: int, xa: np.ndarray, xv: np.ndarray
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


def _pair_table(g: _Geometry, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
    cams, obs = _validate(observations, cameras)
    sigma = check_positive("pixel_std", pixel_std, "pixels")
    g = _geometry(cams.matrices, _orientation(cams, obs) if orientation is None else _check_orientation(orientation))
    X, C, status, previous = _pair_table(g, obs)
    return PairTriangulations(X, C * sigma**2, status, previous)


def _pairs(job: _Chunk) -> _ChunkResult:
    g, obs = job.geometry, job.observations
    V, n, _ = obs.shape
    seen_all = np.isfinite(obs).all(axis=2)
    p, R, st, previous = _pair_table(g, obs)
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
    return _finish(x, P, status, used, np.zeros((V, n), dtype=bool), residuals,
                   _concat_history(hist) if job.history else None)


_RUNNERS: dict[str, Callable[[_Chunk], _ChunkResult]] = {"recursive": _recursive, "batch": _batch, "pairs": _pairs}


def _run_chunk(job: _Chunk) -> _ChunkResult:
    return _RUNNERS[job.method](job)


# ---------------------------------------------------------------------------------------------
# Driver: chunks, σ passes, assembly.


def _validate(observations: object, cameras: object) -> tuple[CameraSet, np.ndarray]:
    cams = cameras if isinstance(cameras, CameraSet) else CameraSet.from_matrices(cameras)
    obs = as_float_array("observations", observations)
    V = len(cams)
    if obs.ndim != 3 or obs.shape[0] != V or obs.shape[2] != 2:
        raise InvalidInputError(
            f"observations must have shape ({V} views, N points, 2) as (x, y), NaN where unseen; got {obs.shape}")
    if np.isinf(obs).any():
        raise InvalidInputError("observations must not contain infinity (NaN marks an unseen point)")
    if V < 2:
        raise NotEnoughDataError(f"fusing structure needs >= 2 cameras; got {V}")
    # a point with one NaN coordinate is unseen in that view
    obs = np.where(np.isnan(obs).any(axis=2, keepdims=True), np.nan, obs)
    return cams, obs


def _orientation(cams: CameraSet, obs: np.ndarray) -> int:
    """The sign of the depths most (linearly triangulated) points agree on."""
    counts = np.isfinite(obs[..., 0]).sum(axis=0)
    sample = np.flatnonzero(counts >= 2)[:_ORIENTATION_SAMPLE]
    if sample.size == 0:
        return 1
    return triangulate_points(cams, obs[:, sample]).orientation


def _check_orientation(orientation: object) -> int:
    if orientation not in (1, -1) or isinstance(orientation, bool):
        raise InvalidInputError(f"orientation must be +1, -1 or None; got {orientation!r}")
    return int(orientation)  # type: ignore[arg-type]


def _chunks(n: int, size: int) -> list[slice]:
    return [slice(s, min(s + size, n)) for s in range(0, n, size)] or [slice(0, 0)]


def _sum_squares(results: Iterable[_ChunkResult]) -> tuple[float, int, int]:
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
    settings: FusionSettings | None = None,
    executor: Any | None = None,
) -> FusedStructure:
    """Fuse each point's observations over many views with known cameras into a 3-D point and its covariance.

    Parameters
    ----------
    observations : (V, N, 2) float
        Pixel positions (x = column, y = row) of N points in the V views of
        ``cameras``, in the same view order; NaN where a point is not seen.
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

    Returns
    -------
    FusedStructure
        Per-point estimates, covariances (σ² scaled) and status; a point that
        cannot be estimated gets a status, never an exception.

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
    >>> fused.status_counts()["ok"], round(fused.pixel_std, 1)
    (50, 0.5)
    >>> err = fused.points - X
    >>> nees = np.einsum("ni,ni->n", err, np.linalg.solve(fused.covariances, err[..., None])[..., 0])
    >>> bool(2.0 < nees.mean() < 4.5)
    True
    """
    options = {"method": method, "pixel_std": pixel_std, "outlier_probability": outlier_probability,
               "history": history, "chunk_points": chunk_points, "orientation": orientation}
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
    return _fuse(observations, cameras, settings, executor)


def _fuse(observations: object, cameras: CameraSet | object, settings: FusionSettings,
          executor: Any | None) -> FusedStructure:
    cams, obs = _validate(observations, cameras)
    orientation = _orientation(cams, obs) if settings.orientation is None else settings.orientation
    geometry = _geometry(cams.matrices, orientation)
    V, N, _ = obs.shape
    slices = _chunks(N, settings.chunk_points)

    def run(sigma: float, gate2: float, gate1: float, keep_history: bool) -> list[_ChunkResult]:
        jobs = [_Chunk(settings.method, geometry, obs[:, s], sigma, gate2, gate1, keep_history) for s in slices]
        mapper = map if executor is None else executor.map
        return list(mapper(_run_chunk, jobs))

    passes = 1
    if settings.pixel_std is not None:
        sigma = settings.pixel_std
        results = run(sigma, settings.gate2, settings.gate1, settings.history)
        sigma_out = sigma
    else:
        # Pilot without gates: a robust σ from the median squared residual, |r|² / σ² ≈ χ²(2) (median 2 ln 2),
        # with the degrees of freedom counted.
        results = run(1.0, np.inf, np.inf, False)
        sq = np.concatenate([np.where(r.used & (r.status == PointStatus.OK)[None], r.residuals, np.nan).ravel() ** 2
                             for r in results])
        sq = sq[np.isfinite(sq)]
        total, n_obs, n_pts = _sum_squares(results)
        dof = 2 * n_obs - 3 * n_pts
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
        for _ in range(_MAX_SIGMA_PASSES):
            results = run(sigma, settings.gate2, settings.gate1, settings.history)
            passes += 1
            total, n_obs, n_pts = _sum_squares(results)
            dof = 2 * n_obs - 3 * n_pts
            if dof <= 0:
                raise NotEnoughDataError(
                    f"pixel_std='auto' needs 2 × observations - 3 × points > 0 after outlier rejection; got {dof}")
            sigma_out = float(np.sqrt(total / dof))
            if abs(sigma_out / sigma - 1.0) < _SIGMA_TOLERANCE:
                break
            sigma, previous = _next_sigma(sigma, sigma_out, previous), (sigma, sigma_out)
    return _assemble(settings, geometry, results, slices, V, N, sigma_out, settings.pixel_std is None, passes)


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


def _to_points(g: _Geometry, anchors: np.ndarray | None, x: np.ndarray, cov: np.ndarray, sigma: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y, Z) and covariance at pixel noise σ from a chunk's unit-σ states (inverse depth when anchored).

    Converted in blocks, so the temporaries of the second-order term stay small.
    """
    if anchors is None:
        return x, cov * sigma**2
    X, C = np.empty_like(x), np.empty_like(cov)
    for start in range(0, x.shape[0], _CONVERSION_BLOCK):
        b = slice(start, start + _CONVERSION_BLOCK)
        X[b], C[b] = _theta_to_point(g, np.maximum(anchors[b], 0), x[b], cov[b] * sigma**2)
    return X, C


def _assemble_history(g: _Geometry, results: list[_ChunkResult], slices: list[slice], sigma: float) -> FusionHistory:
    """The chunks' histories in one :class:`FusionHistory`, sorted by view then point.

    Every entry is written once, straight to its sorted place (no second copy of the history).
    """
    sizes = [r.history[0].size for r in results]
    starts = np.cumsum([0, *sizes])
    views = np.concatenate([r.history[0] for r in results]).astype(np.int64)
    points = np.concatenate([r.history[1] + chunk.start for r, chunk in zip(results, slices)]).astype(np.int64)
    order = np.lexsort((points, views))
    place = np.empty_like(order)
    place[order] = np.arange(order.size)
    H = order.size
    hx, hc = np.empty((H, 3)), np.empty((H, 3, 3))
    states = results[0].anchors is not None
    hs, hsc, ha = (np.empty((H, 3)), np.empty((H, 3, 3)), np.empty(H, np.int64)) if states else (None, None, None)
    for r, begin, end in zip(results, starts[:-1], starts[1:]):
        _, local, x, cov = r.history
        where = place[begin:end]
        anchors = None if r.anchors is None else r.anchors[local]
        hx[where], hc[where] = _to_points(g, anchors, x, cov, sigma)
        if states:
            hs[where], hsc[where], ha[where] = x, cov * sigma**2, anchors
    return FusionHistory(views[order], points[order], hx, hc, hs, hsc, ha)


def _assemble(settings: FusionSettings, g: _Geometry, results: list[_ChunkResult], slices: list[slice], V: int,
              N: int, sigma: float, estimated: bool, passes: int) -> FusedStructure:
    converted = [_to_points(g, r.anchors, r.points, r.covariances, sigma) for r in results]
    points = np.concatenate([x for x, _ in converted])
    cov = np.concatenate([c for _, c in converted])
    status = np.concatenate([r.status for r in results])
    used = np.concatenate([r.used for r in results], axis=1)
    rejected = np.concatenate([r.rejected for r in results], axis=1)
    lengths = np.concatenate([r.residuals for r in results], axis=1)
    ok = status == PointStatus.OK
    views = used.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.sum(np.where(used, lengths, 0.0) ** 2, axis=0) / views)
    rms = np.where(ok, rms, np.nan)
    dof = int(2 * used[:, ok].sum() - 3 * ok.sum())
    hist = None
    if settings.history:
        hist = _assemble_history(g, results, slices, sigma)
    return FusedStructure(settings.method, points, cov, status, views, rms, lengths, rejected, float(sigma),
                          estimated, dof, g.orientation, passes, hist)
