"""Inverse depth anchored at a view: the state of recursive fusion, its two-view start and its gated update.

A point's state is θ = (α, β, ρ) in its anchor view a: X = C_a + o R_aᵀ (α, β, 1) / ρ, with
C_a, R_a the anchor's centre and rotation and o the scene orientation.  Its homogeneous point
is linear in θ, X̃ = H_a θ̃, so a view v acts on θ as the 3 × 4 matrix Q_av = P_v H_a.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...estimation.kalman import kalman_update
from ..geometry.batched import inverse3, solve3
from ..geometry.pinhole import decompose_projection, project_each

__all__ = ["GatedUpdate", "ViewGeometry", "iterated_update", "pair_starts", "residuals_and_cheirality", "start_pairs",
           "theta_to_point", "view_geometry"]

# Iterated EKF: at most this many relinearisations; stop when no component moves more than
# IEKF_TOLERANCE of its own standard deviation.
IEKF_ITERATIONS = 10
IEKF_TOLERANCE = 1e-6
# Gauss–Newton iterations of the two-view start.
START_ITERATIONS = 20
# A two-view (unit-σ) normal matrix more ill-conditioned than this carries no depth at all.
MAX_CONDITION = 1e14


@dataclass(frozen=True)
class ViewGeometry:
    """Per-view quantities shared by every chunk."""

    P: np.ndarray  # (V, 3, 4)
    K_inv: np.ndarray  # (V, 3, 3)
    R: np.ndarray  # (V, 3, 3) det +1
    t: np.ndarray  # (V, 3)
    C: np.ndarray  # (V, 3) centres
    orientation: int
    Q: np.ndarray  # (V anchor, V, 3, 4): P_v H_a, the cameras acting on (α, β, ρ, 1)
    depth_sign: np.ndarray  # (V,) sign of λ in P = λ K [R | t]: depth = w / λ


def view_geometry(P: np.ndarray, orientation: int) -> ViewGeometry:
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
    return ViewGeometry(P, np.linalg.inv(pose.intrinsics), R, pose.translations, C, o, Q, np.sign(pose.scales))


def theta_to_point(g: ViewGeometry, anchor: np.ndarray, theta: np.ndarray, cov: np.ndarray
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


def start_pairs(g: ViewGeometry, a: int, v: int, xa: np.ndarray, xv: np.ndarray, ca: np.ndarray | None = None,
                cv: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two-view start in inverse depth anchored at view a: θ, unit-σ covariance, cost (px²), usable.

    ``ca``, ``cv`` (n,): each observation's standard deviation relative to σ (default 1); the
    normal equations and the cost are then whitened.
    """
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
    scale = np.ones((2, n)) if ca is None else np.stack([ca, cv])

    def normal_equations(th: np.ndarray, o: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pix, _, J = project_each(cams[:, None], th[None])
        r = (o - pix) / c[..., None]
        J = J / c[..., None, None]
        return (np.einsum("vnai,vnaj->nij", J, J), np.einsum("vnai,vna->ni", J, r),
                np.einsum("vna,vna->n", r, r))

    N, g_, cost = normal_equations(theta, obs, scale)
    active = np.ones(n, dtype=bool)
    for _ in range(START_ITERATIONS):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        step = solve3(N[idx], g_[idx])
        trial = theta[idx] + step
        Nt, gt, ct = normal_equations(trial, obs[:, idx], scale[:, idx])
        better = np.isfinite(ct) & (ct <= cost[idx])
        acc = idx[better]
        theta[acc], N[acc], g_[acc], cost[acc] = trial[better], Nt[better], gt[better], ct[better]
        small = np.abs(step) <= IEKF_TOLERANCE * np.sqrt(np.abs(np.diagonal(inverse3(N[idx]), axis1=1, axis2=2)))
        active[idx] = better & ~small.all(axis=1)
    evals = np.linalg.eigvalsh(N)
    usable = np.isfinite(evals).all(axis=1) & (evals[:, 0] > evals[:, 2] / MAX_CONDITION) & np.isfinite(theta).all(1)
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
                    observations: np.ndarray, pixel_std: float, gate: float,
                    scales: np.ndarray | None = None) -> GatedUpdate:
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
    scales : (n,) each observation's standard deviation relative to σ (default 1): the
        update is made with the whitened residual and Jacobian (measurement noise c² σ²).

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
    c = np.ones(prior.shape[0]) if scales is None else np.asarray(scales, dtype=np.float64)
    eye2 = np.eye(2)
    pix, _, H = project_each(Q, prior)
    H = H / c[:, None, None]
    # The first iterate is the ordinary EKF update; its innovation decides the gate.
    first = kalman_update(prior, P, (z - pix) / c[:, None] + np.einsum("nij,nj->ni", H, prior), H, eye2)
    nis = first.nis / pixel_std**2
    accept = nis <= gate
    theta, cov = prior.copy(), P.copy()
    theta[accept], cov[accept] = first.x[accept], first.P[accept]
    # Relinearise at the latest iterate: θ_{i+1} = θ̂ + K_i (z - h(θ_i) - H_i (θ̂ - θ_i)),
    # one kalman_update with the pseudo-measurement z - h(θ_i) + H_i θ_i.
    active = np.flatnonzero(accept)
    for _ in range(IEKF_ITERATIONS - 1):
        if active.size == 0:
            break
        pix, _, H = project_each(Q[active], theta[active])
        H = H / c[active, None, None]
        z_lin = (z[active] - pix) / c[active, None] + np.einsum("nij,nj->ni", H, theta[active])
        res = kalman_update(prior[active], P[active], z_lin, H, eye2)
        moved = np.abs(res.x - theta[active]) > IEKF_TOLERANCE * np.sqrt(
            np.abs(np.diagonal(res.P, axis1=1, axis2=2)))
        theta[active], cov[active] = res.x, res.P
        active = active[moved.any(axis=1)]
    return GatedUpdate(theta, cov, accept)


def residuals_and_cheirality(g: ViewGeometry, obs: np.ndarray, theta: np.ndarray, anchor: np.ndarray,
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


def pair_starts(g: ViewGeometry, first: np.ndarray, second: np.ndarray, obs: np.ndarray, idx: np.ndarray,
                scales: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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
        ca = None if scales is None else scales[a, idx[sel]]
        cv = None if scales is None else scales[v, idx[sel]]
        th, P, c, usable = start_pairs(g, a, v, obs[a, idx[sel]], obs[v, idx[sel]], ca, cv)
        theta[sel], cov[sel] = th, P
        cost[sel] = np.where(usable, c, np.inf)
    return theta, cov, cost
