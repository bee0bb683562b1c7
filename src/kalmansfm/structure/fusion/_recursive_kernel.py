"""Compiled (numba) kernel of the recursive structure fusion: one pass over a chunk of points.

The same algorithm as the NumPy reference in ``tests/reference/fusion_recursive.py``
(``_recursive_states_numpy``), written per point: the NumPy version streams
every per-point array through memory several times per view and per iterated
update, this one keeps a point's 3-vector and 3 × 3 covariance in registers
while it walks through the views.  The tests compare both on the same data.

Per point, view after view (x̃ the homogeneous state (α, β, ρ, 1), Q the view's
3 × 4 matrix acting on it, R = I at unit pixel noise):

* first usable view: it becomes the pending anchor;
* second usable view: Gauss–Newton start on both views (see ``_start``), then the
  χ²(1) test of its residual;
* further views: gated iterated EKF update (``_update``), Joseph form
  P = (I - K H) P (I - K H)ᵀ + K Kᵀ.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# The constants are those of inverse_depth (passed in, one definition there).


@njit(cache=True)
def _project(Q, th0, th1, th2, J):
    """Pixel (x, y) of state θ through Q, and d(x, y)/dθ into J (2, 3)."""
    u = Q[0, 0] * th0 + Q[0, 1] * th1 + Q[0, 2] * th2 + Q[0, 3]
    v = Q[1, 0] * th0 + Q[1, 1] * th1 + Q[1, 2] * th2 + Q[1, 3]
    w = Q[2, 0] * th0 + Q[2, 1] * th1 + Q[2, 2] * th2 + Q[2, 3]
    if w == 0.0:
        w = np.finfo(np.float64).tiny
    x = u / w
    y = v / w
    for j in range(3):
        J[0, j] = (Q[0, j] - x * Q[2, j]) / w
        J[1, j] = (Q[1, j] - y * Q[2, j]) / w
    return x, y


@njit(cache=True)
def _inv3(A, out):
    """Inverse of a 3 × 3 matrix by cofactors; returns the determinant."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[1, 0] = c01 * inv
    out[2, 0] = c02 * inv
    out[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * inv
    out[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * inv
    out[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * inv
    out[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * inv
    out[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * inv
    out[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * inv
    return det


@njit(cache=True)
def _normal2(Qa, Qv, xa, ya, xv, yv, th, N, g, J):
    """Normal matrix JᵀJ, gradient Jᵀr and cost |r|² of the two start views at θ."""
    for i in range(3):
        g[i] = 0.0
        for j in range(3):
            N[i, j] = 0.0
    cost = 0.0
    for k in range(2):
        if k == 0:
            px, py = _project(Qa, th[0], th[1], th[2], J)
            rx, ry = xa - px, ya - py
        else:
            px, py = _project(Qv, th[0], th[1], th[2], J)
            rx, ry = xv - px, yv - py
        cost += rx * rx + ry * ry
        for i in range(3):
            g[i] += J[0, i] * rx + J[1, i] * ry
            for j in range(3):
                N[i, j] += J[0, i] * J[0, j] + J[1, i] * J[1, j]
    return cost


@njit(cache=True)
def _ridged_inverse(N, out, tmp):
    ridge = 1e-14 * (N[0, 0] + N[1, 1] + N[2, 2]) + np.finfo(np.float64).tiny
    for i in range(3):
        for j in range(3):
            tmp[i, j] = N[i, j]
        tmp[i, i] += ridge
    _inv3(tmp, out)


@njit(cache=True)
def _extreme_eigenvalues(A):
    """Smallest and largest eigenvalue of a symmetric 3 × 3 matrix, in closed form (trigonometric)."""
    p1 = A[0, 1] ** 2 + A[0, 2] ** 2 + A[1, 2] ** 2
    q = (A[0, 0] + A[1, 1] + A[2, 2]) / 3.0
    if p1 == 0.0:
        d0, d1, d2 = A[0, 0], A[1, 1], A[2, 2]
        return min(d0, min(d1, d2)), max(d0, max(d1, d2))
    p2 = (A[0, 0] - q) ** 2 + (A[1, 1] - q) ** 2 + (A[2, 2] - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    # B = (A - q I) / p, r = det(B) / 2 = cos(3 φ)
    b00, b11, b22 = (A[0, 0] - q) / p, (A[1, 1] - q) / p, (A[2, 2] - q) / p
    b01, b02, b12 = A[0, 1] / p, A[0, 2] / p, A[1, 2] / p
    r = 0.5 * (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02))
    r = min(max(r, -1.0), 1.0)
    phi = np.arccos(r) / 3.0
    hi = q + 2.0 * p * np.cos(phi)
    lo = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return lo, hi


@njit(cache=True)
def _start(Qa, Qv, Kinv, xa, ya, xv, yv, iterations, tolerance, max_condition, th, P, N, g, J, Nt, gt, inv, tmp,
           trial, step):
    """Two-view start: θ and its unit-σ covariance into th, P; returns (usable, cost)."""
    # (α, β, 1) ∝ K_a⁻¹ x̃_a
    m0 = Kinv[0, 0] * xa + Kinv[0, 1] * ya + Kinv[0, 2]
    m1 = Kinv[1, 0] * xa + Kinv[1, 1] * ya + Kinv[1, 2]
    m2 = Kinv[2, 0] * xa + Kinv[2, 1] * ya + Kinv[2, 2]
    m0 /= m2
    m1 /= m2
    # ρ from view v with (α, β) fixed, least squares on x (q3·θ̃) - q1·θ̃ = 0, y (q3·θ̃) - q2·θ̃ = 0
    u0 = Qv[0, 0] * m0 + Qv[0, 1] * m1 + Qv[0, 3]
    u1 = Qv[1, 0] * m0 + Qv[1, 1] * m1 + Qv[1, 3]
    u2 = Qv[2, 0] * m0 + Qv[2, 1] * m1 + Qv[2, 3]
    A0 = xv * Qv[2, 2] - Qv[0, 2]
    A1 = yv * Qv[2, 2] - Qv[1, 2]
    r0 = -(xv * u2 - u0)
    r1 = -(yv * u2 - u1)
    denom = A0 * A0 + A1 * A1
    rho = (A0 * r0 + A1 * r1) / denom if denom > 0 else 0.0
    th[0], th[1], th[2] = m0, m1, rho
    cost = _normal2(Qa, Qv, xa, ya, xv, yv, th, N, g, J)
    for _ in range(iterations):
        _ridged_inverse(N, inv, tmp)
        for i in range(3):
            step[i] = inv[i, 0] * g[0] + inv[i, 1] * g[1] + inv[i, 2] * g[2]
            trial[i] = th[i] + step[i]
        ct = _normal2(Qa, Qv, xa, ya, xv, yv, trial, Nt, gt, J)
        better = np.isfinite(ct) and ct <= cost
        if better:
            for i in range(3):
                th[i] = trial[i]
                gt_i = gt[i]
                g[i] = gt_i
                for j in range(3):
                    N[i, j] = Nt[i, j]
            cost = ct
        _ridged_inverse(N, inv, tmp)
        small = True
        for i in range(3):
            if not abs(step[i]) <= tolerance * np.sqrt(abs(inv[i, i])):
                small = False
        if not better or small:
            break
    lo, hi = _extreme_eigenvalues(N)
    usable = np.isfinite(lo) and np.isfinite(hi) and lo > hi / max_condition
    usable = usable and np.isfinite(th[0]) and np.isfinite(th[1]) and np.isfinite(th[2])
    if usable:
        _inv3(N, P)
    return usable, cost


@njit(cache=True)
def _kalman_step(prior, P, H, y, x_out, P_out, PHt, K, A, AP):
    """x = x̂ + K y, P = (I - K H) P (I - K H)ᵀ + K Kᵀ with S = H P Hᵀ + I; returns yᵀ S⁻¹ y.

    PHt, K (3, 2), A, AP (3, 3) are work buffers.
    """
    for i in range(3):
        for j in range(2):
            PHt[i, j] = P[i, 0] * H[j, 0] + P[i, 1] * H[j, 1] + P[i, 2] * H[j, 2]
    s00 = H[0, 0] * PHt[0, 0] + H[0, 1] * PHt[1, 0] + H[0, 2] * PHt[2, 0] + 1.0
    s11 = H[1, 0] * PHt[0, 1] + H[1, 1] * PHt[1, 1] + H[1, 2] * PHt[2, 1] + 1.0
    s01 = 0.5 * (H[0, 0] * PHt[0, 1] + H[0, 1] * PHt[1, 1] + H[0, 2] * PHt[2, 1]
                 + H[1, 0] * PHt[0, 0] + H[1, 1] * PHt[1, 0] + H[1, 2] * PHt[2, 0])
    det = s00 * s11 - s01 * s01
    i00, i11, i01 = s11 / det, s00 / det, -s01 / det
    for i in range(3):
        K[i, 0] = PHt[i, 0] * i00 + PHt[i, 1] * i01
        K[i, 1] = PHt[i, 0] * i01 + PHt[i, 1] * i11
        x_out[i] = prior[i] + K[i, 0] * y[0] + K[i, 1] * y[1]
    for i in range(3):
        for j in range(3):
            A[i, j] = (1.0 if i == j else 0.0) - K[i, 0] * H[0, j] - K[i, 1] * H[1, j]
    for i in range(3):
        for j in range(3):
            AP[i, j] = A[i, 0] * P[0, j] + A[i, 1] * P[1, j] + A[i, 2] * P[2, j]
    for i in range(3):
        for j in range(i, 3):
            value = (AP[i, 0] * A[j, 0] + AP[i, 1] * A[j, 1] + AP[i, 2] * A[j, 2]
                     + K[i, 0] * K[j, 0] + K[i, 1] * K[j, 1])
            P_out[i, j] = value
            P_out[j, i] = value
    return y[0] * (i00 * y[0] + i01 * y[1]) + y[1] * (i01 * y[0] + i11 * y[1])


@njit(cache=True)
def _update(Q, x, y_obs, sigma, gate, iterations, tolerance, th, P, H, prior, P0, y, xn, Pn, PHt, K, A, AP):
    """Gated iterated EKF update of (th, P) in place by the pixel (x, y_obs); returns accepted.

    The arguments after P are work buffers (no allocation per update).
    """
    for i in range(3):
        prior[i] = th[i]
        for j in range(3):
            P0[i, j] = P[i, j]
    px, py = _project(Q, prior[0], prior[1], prior[2], H)
    y[0], y[1] = x - px, y_obs - py
    nis = _kalman_step(prior, P0, H, y, xn, Pn, PHt, K, A, AP)
    if not nis / sigma**2 <= gate:
        return False
    for i in range(3):
        th[i] = xn[i]
        for j in range(3):
            P[i, j] = Pn[i, j]
    for _ in range(iterations - 1):
        # relinearise at the iterate: y = z - h(θ_i) - H_i (θ̂ - θ_i)
        px, py = _project(Q, th[0], th[1], th[2], H)
        d0, d1, d2 = prior[0] - th[0], prior[1] - th[1], prior[2] - th[2]
        y[0] = x - px - (H[0, 0] * d0 + H[0, 1] * d1 + H[0, 2] * d2)
        y[1] = y_obs - py - (H[1, 0] * d0 + H[1, 1] * d1 + H[1, 2] * d2)
        _kalman_step(prior, P0, H, y, xn, Pn, PHt, K, A, AP)
        moved = False
        for i in range(3):
            if abs(xn[i] - th[i]) > tolerance * np.sqrt(abs(Pn[i, i])):
                moved = True
        for i in range(3):
            th[i] = xn[i]
            for j in range(3):
                P[i, j] = Pn[i, j]
        if not moved:
            break
    return True


@njit(cache=True, inline="always")
def _whitened(Q, Kinv, c, Q_out, Kinv_out):
    """Q with its first two rows divided by c, K⁻¹ with its first two columns multiplied by c.

    An observation with standard deviation c σ, divided by c, has the noise of the others: the
    projection through the scaled Q of the scaled pixel, and the anchor ray through the scaled
    K⁻¹, are those of the whitened measurement (the kernel's update and start are unchanged).
    """
    for i in range(3):
        f = 1.0 / c if i < 2 else 1.0
        for j in range(4):
            Q_out[i, j] = Q[i, j] * f
        for j in range(3):
            Kinv_out[i, j] = Kinv[i, j] * (c if j < 2 else 1.0)


@njit(cache=True)
def recursive_pass(Q, Kinv, front_sign, obs, scale, weighted, sigma, gate2, gate1, start_iterations,
                   iekf_iterations, tolerance, max_condition, keep_history, theta, cov, anchor, started, stalled,
                   used, rejected, residuals, in_front, hist_theta, hist_cov, hist_mask):
    """Walk every point of a chunk through its views; all outputs are filled in place.

    Arrays are point-major (a point's views are adjacent in memory): Q (V, V, 3, 4) the
    anchor-composed cameras, Kinv (V, 3, 3), front_sign (V,) the sign a point's projective
    depth w / ρ has in front of view v (orientation × sign λ_v), obs (n, V, 2) NaN where unseen;
    with ``weighted``, scale (n, V) each observation's standard deviation relative to σ (the
    observation is whitened: :func:`_whitened`).
    Outputs: theta (n, 3), cov (n, 3, 3) at unit σ, anchor (n,), started/stalled (n,),
    used/rejected (n, V), residuals (n, V, 2) of every observation at the final state,
    in_front (n,); with keep_history, hist_* (n, V, ...) and hist_mask (n, V).
    The states and transitions are those of the NumPy reference (``_recursive_states_numpy``).
    """
    n, V = obs.shape[0], obs.shape[1]
    gate1_px = gate1 * sigma**2
    th = np.empty(3)
    P = np.empty((3, 3))
    # work buffers, allocated once per pass
    H, prior, P0, y2, xn, Pn = np.empty((2, 3)), np.empty(3), np.empty((3, 3)), np.empty(2), np.empty(3), np.empty((3, 3))
    PHt, K, A, AP = np.empty((3, 2)), np.empty((3, 2)), np.empty((3, 3)), np.empty((3, 3))
    N, g, Nt, gt, step = np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty(3), np.empty(3)
    th_h, P_h, cost_h = np.empty((3, 3)), np.empty((3, 3, 3)), np.empty(3)
    pair_f, pair_s = np.empty(3, dtype=np.int64), np.empty(3, dtype=np.int64)
    Qa_w, Qv_w, Kinv_w, Kinv_unused = np.empty((3, 4)), np.empty((3, 4)), np.empty((3, 3)), np.empty((3, 3))
    for p in range(n):
        first = -1
        second = -1
        is_started = False
        verified = False
        for v in range(V):
            x, y = obs[p, v, 0], obs[p, v, 1]
            if np.isnan(x) or np.isnan(y):
                continue
            resolve = False
            if is_started:
                if weighted:
                    c = scale[p, v]
                    _whitened(Q[first, v], Kinv[first], c, Qv_w, Kinv_unused)
                    ok = _update(Qv_w, x / c, y / c, sigma, gate2, iekf_iterations, tolerance, th, P, H, prior, P0,
                                 y2, xn, Pn, PHt, K, A, AP)
                else:
                    ok = _update(Q[first, v], x, y, sigma, gate2, iekf_iterations, tolerance, th, P, H, prior, P0,
                                 y2, xn, Pn, PHt, K, A, AP)
                if ok:
                    used[p, v] = True
                    verified = True
                    if keep_history:
                        hist_mask[p, v] = True
                        hist_theta[p, v, :] = th
                        hist_cov[p, v, :, :] = P
                elif verified:
                    rejected[p, v] = True
                else:
                    resolve = True
            elif first >= 0 and second < 0:
                if weighted:
                    ca, c = scale[p, first], scale[p, v]
                    _whitened(Q[first, first], Kinv[first], ca, Qa_w, Kinv_w)
                    _whitened(Q[first, v], Kinv[first], c, Qv_w, Kinv_unused)
                    usable, cost = _start(Qa_w, Qv_w, Kinv_w, obs[p, first, 0] / ca, obs[p, first, 1] / ca, x / c,
                                          y / c, start_iterations, tolerance, max_condition, th_h[0], P_h[0], N, g,
                                          H, Nt, gt, A, AP, xn, step)
                else:
                    usable, cost = _start(Q[first, first], Q[first, v], Kinv[first], obs[p, first, 0],
                                          obs[p, first, 1], x, y, start_iterations, tolerance, max_condition,
                                          th_h[0], P_h[0], N, g, H, Nt, gt, A, AP, xn, step)
                if not usable:
                    stalled[p] = True  # no parallax with the pending view: wait for another view
                elif cost <= gate1_px:
                    th[:] = th_h[0]
                    P[:, :] = P_h[0]
                    second = v
                    is_started = True
                    used[p, first] = True
                    used[p, v] = True
                    if keep_history:
                        hist_mask[p, v] = True
                        hist_theta[p, v, :] = th
                        hist_cov[p, v, :, :] = P
                else:
                    second = v
            elif second >= 0:
                resolve = True
            else:
                first = v
            if not resolve:
                continue
            # three observations (first, second, v) that do not agree
            provisional = is_started
            pair_f[0], pair_s[0] = second, v  # drop first
            pair_f[1], pair_s[1] = first, v  # drop second
            pair_f[2], pair_s[2] = first, second  # drop v
            best = -1
            for h in range(3):
                f, s = pair_f[h], pair_s[h]
                if weighted:
                    cf, cs = scale[p, f], scale[p, s]
                    _whitened(Q[f, f], Kinv[f], cf, Qa_w, Kinv_w)
                    _whitened(Q[f, s], Kinv[f], cs, Qv_w, Kinv_unused)
                    usable, cost = _start(Qa_w, Qv_w, Kinv_w, obs[p, f, 0] / cf, obs[p, f, 1] / cf, obs[p, s, 0] / cs,
                                          obs[p, s, 1] / cs, start_iterations, tolerance, max_condition, th_h[h],
                                          P_h[h], N, g, H, Nt, gt, A, AP, xn, step)
                else:
                    usable, cost = _start(Q[f, f], Q[f, s], Kinv[f], obs[p, f, 0], obs[p, f, 1], obs[p, s, 0],
                                          obs[p, s, 1], start_iterations, tolerance, max_condition, th_h[h], P_h[h],
                                          N, g, H, Nt, gt, A, AP, xn, step)
                cost_h[h] = cost if usable else np.inf
                if best < 0 or cost_h[h] < cost_h[best]:
                    best = h
            if cost_h[best] <= gate1_px:
                if provisional and best == 2:
                    rejected[p, v] = True  # the point's own pair wins: keep its state
                    continue
                dropped = first if best == 0 else (second if best == 1 else v)
                th[:] = th_h[best]
                P[:, :] = P_h[best]
                first, second = pair_f[best], pair_s[best]
                used[p, first] = True
                used[p, second] = True
                used[p, dropped] = False
                rejected[p, dropped] = True
                is_started = True
                verified = False
                if keep_history:
                    for u in range(v):
                        hist_mask[p, u] = False
                    hist_mask[p, v] = True
                    hist_theta[p, v, :] = th
                    hist_cov[p, v, :, :] = P
            else:
                # no consistent pair: the oldest goes, the other two remain a conflict
                used[p, first] = False
                used[p, second] = False
                rejected[p, first] = True
                is_started = False
                verified = False
                first, second = second, v
                if keep_history:
                    for u in range(v + 1):
                        hist_mask[p, u] = False
        if is_started:
            started[p] = True
            anchor[p] = first
            theta[p, :] = th
            cov[p, :, :] = P
            front = True
            for v in range(V):
                x, y = obs[p, v, 0], obs[p, v, 1]
                if np.isnan(x) or np.isnan(y):
                    continue
                Qv = Q[first, v]
                u = Qv[0, 0] * th[0] + Qv[0, 1] * th[1] + Qv[0, 2] * th[2] + Qv[0, 3]
                vv = Qv[1, 0] * th[0] + Qv[1, 1] * th[1] + Qv[1, 2] * th[2] + Qv[1, 3]
                w = Qv[2, 0] * th[0] + Qv[2, 1] * th[1] + Qv[2, 2] * th[2] + Qv[2, 3]
                residuals[p, v, 0] = x - u / w
                residuals[p, v, 1] = y - vv / w
                if used[p, v] and not w * th[2] * front_sign[v] > 0:
                    front = False
            in_front[p] = front
