"""NumPy twins of the compiled Kalman kernels: the same arithmetic in the same order, bit for bit (internal).

A numba kernel is compiled the first time it runs on a machine (1–4 s each; then it is
loaded from the cache).  A filter of a few hundred tracks would spend longer compiling
than it ever saves, so below :data:`~kalmansfm.estimation.engine.COMPILED_MIN_TRACKS`
tracks the engine runs these functions instead (:func:`~kalmansfm.estimation.engine.kernels_for`).
Each one has the signature, the outputs and the return value of its namesake in
:mod:`._kernels`, and is vectorised over the tracks instead of looping over them.

Every expression follows the kernel's order of operations.  NumPy rounds each binary
operation once, as the kernels do (numba neither reassociates nor contracts to FMA
without fastmath), and the constants are of the arrays' dtype, so the twins return the
kernels' numbers to the last bit in float64 and float32 alike; a sum the kernel starts
from zero starts from zero here too (0 + x, not x, keeps the sign of a zero).  The tests
compare every twin with its kernel bit for bit (``tests/property/test_kalman_kernels_property.py``).
Which one runs is thus invisible in the results.
"""

from __future__ import annotations

from contextlib import nullcontext

import numpy as np

__all__ = [
    "cv_predict",
    "cv_shared_blocks",
    "cv_step",
    "cv_step_shared",
    "dense_predict",
    "dense_predict_states",
    "dense_step",
    "dense_step_shared",
    "threads_for",
]


def threads_for(N: int) -> nullcontext:
    """The twins run on the calling thread (the compiled kernels' ``threads_for`` picks numba threads)."""
    return nullcontext()


def _count(mask: np.ndarray) -> int:
    return int(np.count_nonzero(mask))


# -- constant-velocity (decoupled) kernels -----------------------------------------------------

def _prior_state(X, u, dt):
    """x⁻ = F x (+ u): position += dt · velocity (``_kernels._prior_state``)."""
    x = X[0] + dt * X[2]
    y = X[1] + dt * X[3]
    vx = X[2]
    vy = X[3]
    if u is not None:
        x = x + u[0]
        y = y + u[1]
        vx = vx + u[2]
        vy = vy + u[3]
    return x, y, vx, vy


def _predict_block(p00, p01, p11, dt, q0, q1, q2):
    """P⁻ = A P Aᵀ + Q_b for one block, A = [[1, dt], [0, 1]] (``_kernels._predict_block``)."""
    a = p01 + dt * p11
    return p00 + dt * (p01 + a) + q0, a + q1, p11 + q2


def _update_block(p00, p01, p11, r, s, g, one, two, joseph):
    """Posterior block after a scalar measurement of the position; g = 1/s, or 0 when not measured."""
    k0 = p00 * g
    k1 = p01 * g
    a = one - k0
    if joseph:
        return ((a * a) * p00 + (k0 * k0) * r, a * (p01 - k1 * p00) + (k0 * k1) * r,
                p11 - k1 * (p01 * two - k1 * s), k0, k1)
    return a * p00, a * p01, p11 - k1 * p01, k0, k1


def _axis(C, Co, b, dt, q, r, measured, one, two, zero, joseph):
    """Covariance block b of every track: prior, posterior into Co; returns (k0, k1, singular mask)."""
    p00, p01, p11 = _predict_block(C[b, 0], C[b, 1], C[b, 2], dt, q[b, 0], q[b, 1], q[b, 2])
    s = p00 + r
    g = np.where(measured, one, zero) / s
    Co[b, 0], Co[b, 1], Co[b, 2], k0, k1 = _update_block(p00, p01, p11, r, s, g, one, two, joseph)
    return k0, k1, measured & ~(s > zero)


def cv_step(X, C, z, dt, q, r, u, joseph, Xo, Co, Yo):
    """:func:`kalmansfm.estimation._kernels.cv_step` in NumPy (same arguments, outputs and counts)."""
    dtype = X.dtype.type
    one, two, zero, inf = dtype(1.0), dtype(2.0), dtype(0.0), dtype(np.inf)
    two_blocks = Co.shape[0] == 2
    with np.errstate(all="ignore"):
        x, y, vx, vy = _prior_state(X, u, dt)
        zx, zy = z.real, z.imag
        ex = zx - x
        ey = zy - y
        Yo[0] = ex
        Yo[1] = ey
        mx = ex == ex
        my = ey == ey
        n_infinite = _count((np.abs(zx) == inf) | (np.abs(zy) == inf))
        per_track_r = r.shape[1] > 1
        rx = r[0] if per_track_r else r[0, 0]
        kx0, kx1, singular = _axis(C, Co, 0, dt, q, rx, mx, one, two, zero, joseph)
        if two_blocks:
            ry = r[1] if per_track_r else r[1, 0]
            ky0, ky1, singular_y = _axis(C, Co, 1, dt, q, ry, my, one, two, zero, joseph)
            singular = singular | singular_y
            n_partial = 0
        else:
            ky0, ky1 = kx0, kx1
            n_partial = _count(mx != my)
        ex = np.where(mx, ex, zero)
        ey = np.where(my, ey, zero)
        Xo[0] = x + kx0 * ex
        Xo[1] = y + ky0 * ey
        Xo[2] = vx + kx1 * ex
        Xo[3] = vy + ky1 * ey
    return n_infinite, n_partial, _count(singular)


def cv_shared_blocks(C, dt, q, r, joseph):
    """:func:`kalmansfm.estimation._kernels.cv_shared_blocks` in NumPy (scalars of C's dtype)."""
    dtype = C.dtype.type
    one, two = dtype(1.0), dtype(2.0)
    B = C.shape[0]
    prior = np.empty_like(C)
    post = np.empty_like(C)
    gains = np.empty((2, 2), dtype=C.dtype)
    with np.errstate(all="ignore"):
        for b in range(B):
            p00, p01, p11 = _predict_block(C[b, 0], C[b, 1], C[b, 2], dt, q[b, 0], q[b, 1], q[b, 2])
            s = p00 + r[b]
            g = one / s if s > 0 else dtype(np.nan)
            o00, o01, o11, k0, k1 = _update_block(p00, p01, p11, r[b], s, g, one, two, joseph)
            prior[b] = p00, p01, p11
            post[b] = o00, o01, o11
            gains[b] = k0, k1
    if B == 1:
        gains[1] = gains[0]
    return prior, post, gains


def cv_step_shared(X, z, dt, gains, u, Xo, Yo):
    """:func:`kalmansfm.estimation._kernels.cv_step_shared` in NumPy."""
    inf = X.dtype.type(np.inf)
    with np.errstate(all="ignore"):
        x, y, vx, vy = _prior_state(X, u, dt)
        zx, zy = z.real, z.imag
        n_infinite = _count((np.abs(zx) == inf) | (np.abs(zy) == inf))
        ex = zx - x
        ey = zy - y
        n_missing = _count((ex != ex) | (ey != ey))
        Yo[0] = ex
        Yo[1] = ey
        Xo[0] = x + gains[0, 0] * ex
        Xo[1] = y + gains[1, 0] * ey
        Xo[2] = vx + gains[0, 1] * ex
        Xo[3] = vy + gains[1, 1] * ey
    return n_infinite, n_missing


def cv_predict(X, C, dt, q, u, Xo, Co):
    """:func:`kalmansfm.estimation._kernels.cv_predict` in NumPy; C (B, 3, M), M = N or 1."""
    with np.errstate(all="ignore"):
        Xo[0], Xo[1], Xo[2], Xo[3] = _prior_state(X, u, dt)
        for b in range(C.shape[0]):
            Co[b, 0], Co[b, 1], Co[b, 2] = _predict_block(C[b, 0], C[b, 1], C[b, 2], dt, q[b, 0], q[b, 1], q[b, 2])


# -- general dense model ------------------------------------------------------------------------
#
# The kernels loop over (row, column, term) with the tracks innermost; here every (row, column)
# pair is one array operation over the tracks, and the terms of a sum are added in the
# kernel's order.  Arrays are (rows, columns, N) as the kernels' chunk scratch.

def _model(M: np.ndarray, N: int) -> np.ndarray:
    """(r, c, N) values of a model matrix given (1, r, c) shared or (N, r, c) (``_kernels._load_model``)."""
    return np.broadcast_to(np.moveaxis(M, 0, -1), (*M.shape[1:], N))


def _product(A, B, transposed=False):
    """out[a, b] = Σ_c A[a, c] B[c, b] (or B[b, c] when ``transposed``), the terms added from 0 in the order of c."""
    rows, terms, N = A.shape
    columns = B.shape[0] if transposed else B.shape[1]
    out = np.zeros((rows, columns, N), dtype=A.dtype)
    for c in range(terms):
        Bc = B[:, c] if transposed else B[c]  # (columns, N)
        out += A[:, c, None, :] * Bc[None, :, :]
    return out


def _upper_mirrored(M: np.ndarray) -> np.ndarray:
    """M with its lower triangle replaced by its upper one, as the kernels write a symmetric result."""
    n = M.shape[0]
    upper = np.triu(np.ones((n, n), dtype=bool))[:, :, None]
    return np.where(upper, M, np.swapaxes(M, 0, 1))


def _prior(x, P, F, Q, u):
    """x⁻ = F x (+ u), P⁻ = F P Fᵀ + Q (upper triangle mirrored), as ``_kernels._prior_chunk``."""
    n, N = x.shape
    Fc = _model(F, N)
    xp = np.zeros((n, N), dtype=x.dtype)
    for b in range(n):
        xp += Fc[:, b] * x[b]
    if u.shape[1] > 0:
        xp += u
    FP = _product(Fc, P)
    FPF = _product(FP, Fc, transposed=True)
    return xp, _upper_mirrored(_model(Q, N) + FPF)


def dense_predict(x, P, F, Q, u, xo, Po):
    """:func:`kalmansfm.estimation._kernels.dense_predict` in NumPy."""
    with np.errstate(all="ignore"):
        xo[...], Po[...] = _prior(x, P, F, Q, u)


def dense_step(x, P, z, F, Q, H, R, u, predict, joseph, xo, Po, yo):
    """:func:`kalmansfm.estimation._kernels.dense_step` in NumPy (same arguments, outputs and counts)."""
    n, N = x.shape
    m = z.shape[1]
    dtype = x.dtype.type
    one, zero, half, inf = dtype(1.0), dtype(0.0), dtype(0.5), dtype(np.inf)
    with np.errstate(all="ignore"):
        xp, Pp = _prior(x, P, F, Q, u) if predict else (x.copy(), P)
        Hc, Rc = _model(H, N), _model(R, N)
        # e = z - H x⁻ (NaN where not measured: yo; then 0 for the update)
        e = np.array(z.T)
        n_infinite = _count(np.abs(e) == inf)
        for b in range(n):
            e -= Hc[:, b] * xp[b]
        yo[...] = e
        measured = e == e
        seen = np.where(measured, one, zero)
        e = np.where(measured, e, zero)
        # P Hᵀ; S = H P Hᵀ + R with the unmeasured rows and columns replaced by the identity's;
        # then the unmeasured columns of P Hᵀ set to 0
        PHt = _product(Pp, Hc, transposed=True)
        S = np.array(Rc)
        for a in range(n):
            S += Hc[:, a, None, :] * PHt[None, a, :, :]
        S = S * (seen[:, None, :] * seen[None, :, :]) + np.eye(m, dtype=x.dtype)[:, :, None] * (one - seen[:, None, :])
        PHt *= seen[None, :, :]
        # Cholesky S = L Lᵀ in place (lower triangle)
        n_singular = 0
        for r in range(m):
            for t in range(r):
                S[r, r] -= S[r, t] * S[r, t]
            d = S[r, r]
            positive = d > zero
            n_singular += _count(~positive)
            S[r, r] = np.where(positive, np.sqrt(d), one)
            for t in range(r + 1, m):
                for w in range(r):
                    S[t, r] -= S[t, w] * S[r, w]
                S[t, r] /= S[r, r]
        # K = P Hᵀ S⁻¹: every row of P Hᵀ solved with L, then with Lᵀ
        K = np.array(PHt)
        for r in range(m):
            for t in range(r):
                K[:, r] -= S[r, t] * K[:, t]
            K[:, r] /= S[r, r]
        for r in range(m - 1, -1, -1):
            for t in range(r + 1, m):
                K[:, r] -= S[t, r] * K[:, t]
            K[:, r] /= S[r, r]
        # x = x⁻ + K e
        for r in range(m):
            xp += K[:, r] * e[r]
        xo[...] = xp
        # A = I - K H, W = A P⁻
        A = np.eye(n, dtype=x.dtype)[:, :, None] - _product(K, Hc)
        W = _product(A, Pp)
        if joseph:
            # P = (I - KH) P (I - KH)ᵀ + K R Kᵀ
            joseph_P = _product(W, A, transposed=True)
            KR = _product(K, Rc)
            for r in range(m):
                joseph_P += KR[:, None, r] * K[None, :, r]
            Po[...] = _upper_mirrored(joseph_P)
        else:
            Po[...] = _upper_mirrored(half * (W + np.swapaxes(W, 0, 1)))
    return n_infinite, n_singular


def _predict_states(x, F, u):
    n, N = x.shape
    xp = np.zeros((n, N), dtype=x.dtype)
    for b in range(n):
        xp += F[:, b, None] * x[b]
    if u.shape[1] > 0:
        xp += u
    return xp


def dense_step_shared(x, z, F, u, H, K, predict, xo, yo):
    """:func:`kalmansfm.estimation._kernels.dense_step_shared` in NumPy."""
    n = x.shape[0]
    inf = x.dtype.type(np.inf)
    with np.errstate(all="ignore"):
        xp = _predict_states(x, F, u) if predict else x.copy()
        e = np.array(z.T)
        n_infinite = _count(np.abs(e) == inf)
        for b in range(n):
            e -= H[:, b, None] * xp[b]
        n_missing = _count(e != e)
        yo[...] = e
        for r in range(z.shape[1]):
            xp += K[:, r, None] * e[r]
        xo[...] = xp
    return n_infinite, n_missing


def dense_predict_states(x, F, u, xo):
    """:func:`kalmansfm.estimation._kernels.dense_predict_states` in NumPy."""
    with np.errstate(all="ignore"):
        xo[...] = _predict_states(x, F, u)
