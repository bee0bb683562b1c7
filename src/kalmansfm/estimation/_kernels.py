"""Compiled kernels (numba) of the batched Kalman filter: one pass over memory per step (internal).

Every kernel loops once over the tracks and keeps a track's numbers in registers
(constant-velocity kernels) or in per-chunk scratch arrays that stay in the CPU
cache (dense kernels) between reading its state and covariance and writing them
back, so a step reads and writes each track's state and covariance once.  NumPy
needs one pass over memory per expression instead, which is what these kernels
replace.  The NumPy references, which the tests compare every kernel against, are
``tests/reference/decoupled.py`` (``predict`` then ``update``) for the
constant-velocity kernels and :func:`~kalmansfm.estimation.kalman.kalman_predict`
then :func:`~kalmansfm.estimation.kalman.kalman_update` for the dense ones.  Every
kernel also has a NumPy twin in :mod:`._numpy_kernels` (the same arithmetic, bit for
bit) that runs small problems, where compiling the kernel would cost more than it saves.

Storage is structure of arrays: the track index is the last (contiguous) axis of
every per-track array, so the loop over tracks reads each row as a stream and
LLVM vectorises it.

Constant-velocity (decoupled) layout, as in :mod:`._decoupled`:

* ``X`` (4, N) rows x, y, vx, vy;
* ``C`` (B, 3, N) covariance blocks, rows p00 = var(position), p01 =
  cov(position, velocity), p11 = var(velocity); B = 1 while the x and y blocks
  are identical (one block serves both axes), else 2 (x block, y block);
* ``z`` (N,) complex: the measured position x + i y (the user's (N, 2) array
  viewed as complex numbers, which the loop reads as one stream), NaN = missing;
* ``Y`` (2, N) innovations z - H x⁻, NaN where not measured.

A prediction is fused into the following update: the kernels take the posterior
of the previous step and the transition (dt, q, u) and compute the prior in
registers.  With dt = 0, q = 0 and no u the prediction is the identity exactly
(x + 0·v = x, p + 0 = p), so the same kernel is also the update alone.

The constant-velocity arithmetic is written in the order of the NumPy reference
and numba does not reassociate or contract (no fastmath), so those kernels return
the reference's numbers bit for bit; the dense kernels sum in another order and
agree to rounding.  The constants are of the arrays' dtype, so float32 stays
float32.  A missing measurement takes no branch: its gain is selected as 0, which
keeps the loop vectorisable.
"""

from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager

import numba
import numpy as np
from numba import njit, prange

from .._compilation import watch_compilation

watch_compilation()  # one line on stderr when a kernel is compiled (not when it is loaded from the cache)

# cache=True: compiled once per machine (in __pycache__ next to this file, or numba's
# user cache directory when the package is installed read-only).
_JIT = {"cache": True, "nogil": True}


@njit(inline="always", **_JIT)
def _predict_block(p00, p01, p11, dt, q0, q1, q2):
    """P⁻ = A P Aᵀ + Q_b for one block, A = [[1, dt], [0, 1]]."""
    # a = p01 + dt p11 (the new p01 before noise); p00⁻ = p00 + dt (p01 + a) + q00
    a = p01 + dt * p11
    return p00 + dt * (p01 + a) + q0, a + q1, p11 + q2


@njit(inline="always", **_JIT)
def _update_block(p00, p01, p11, r, s, g, one, two, joseph):
    """Posterior block after a scalar measurement of the position; g = 1/s, or 0 when not measured."""
    k0 = p00 * g
    k1 = p01 * g
    a = one - k0
    if joseph:
        # Joseph form with I - k h, h = [1, 0]: p00 = a² p00 + r k0², p01 = a (p01 - k1 p00) + r k0 k1,
        # p11 = p11 - 2 k1 p01 + k1² s
        return ((a * a) * p00 + (k0 * k0) * r, a * (p01 - k1 * p00) + (k0 * k1) * r,
                p11 - k1 * (p01 * two - k1 * s), k0, k1)
    # simple form P = (I - k h) P
    return a * p00, a * p01, p11 - k1 * p01, k0, k1


@njit(inline="always", **_JIT)
def _prior_state(X, u, dt, i):
    """x⁻ = F x (+ u) of track i: position += dt · velocity."""
    x = X[0, i] + dt * X[2, i]
    y = X[1, i] + dt * X[3, i]
    vx = X[2, i]
    vy = X[3, i]
    if u is not None:
        x += u[0, i]
        y += u[1, i]
        vx += u[2, i]
        vy += u[3, i]
    return x, y, vx, vy


@njit(inline="always", **_JIT)
def _innovation(z, i, x, y, Yo, inf):
    """y = z - H x⁻ of track i, written to Yo (NaN where not measured); returns it, the measured flags and ±inf."""
    zi = z[i]
    ex = zi.real - x
    ey = zi.imag - y
    Yo[0, i] = ex
    Yo[1, i] = ey
    return ex, ey, ex == ex, ey == ey, (abs(zi.real) == inf) | (abs(zi.imag) == inf)


@njit(inline="always", **_JIT)
def _axis(C, Co, b, i, dt, q0, q1, q2, r, measured, one, two, zero, joseph):
    """Covariance block b of track i: prior, then posterior written to Co (the prior where not measured).

    Returns the gains (k0, k1) (0 when not measured) and whether a measured innovation
    variance p00⁻ + r is not > 0.
    """
    p00, p01, p11 = _predict_block(C[b, 0, i], C[b, 1, i], C[b, 2, i], dt, q0, q1, q2)
    s = p00 + r
    Co[b, 0, i], Co[b, 1, i], Co[b, 2, i], k0, k1 = _update_block(p00, p01, p11, r, s, (one if measured else zero) / s,
                                                                  one, two, joseph)
    return k0, k1, measured & (not s > zero)


@njit(inline="always", **_JIT)
def _posterior_state(Xo, i, x, y, vx, vy, kx0, kx1, ky0, ky1, ex, ey, mx, my, zero):
    """x = x⁻ + k0 y, v = v⁻ + k1 y per axis, with y = 0 where not measured (its gain is 0 too)."""
    ex = ex if mx else zero
    ey = ey if my else zero
    Xo[0, i] = x + kx0 * ex
    Xo[1, i] = y + ky0 * ey
    Xo[2, i] = vx + kx1 * ex
    Xo[3, i] = vy + ky1 * ey


def cv_step(X, C, z, dt, q, r, u, joseph, Xo, Co, Yo):
    """Predict (x⁻ = F x + u, P⁻ = F P Fᵀ + Q) and update on z, for every track, in one pass.

    Parameters
    ----------
    X (4, N), C (B, 3, N) : posterior of the previous step (B = 2 needs Co with 2 blocks).
    z (N,) complex : measured positions, NaN = missing (a component or both).
    dt : frame interval (of X's dtype); q (2, 3) process noise blocks of x and y.
    r (2, 1) or (2, N) : measurement variances of x and y.
    u : None or (4, N) known offset added to the predicted state.
    joseph : Joseph-form covariance update, else P = (I - K H) P.
    Xo (4, N), Co (B, 3, N), Yo (2, N) : outputs (posterior, innovations).

    Returns
    -------
    (n_infinite, n_partial, n_singular) : measurements holding ±inf; rows with one
    component missing (only counted when B = 1: the single block cannot hold two
    histories, and the caller runs the step again with B = 2); measured tracks
    whose innovation variance p00⁻ + r is not > 0.  The outputs are only valid
    when all three are 0.

    One block or two are two compiled loops: a branch between them inside the loop
    would be if-converted by the vectoriser, i.e. both sides computed for every track.
    """
    if Co.shape[0] == 2:
        return _cv_step_two_blocks(X, C, z, dt, q, r, u, joseph, Xo, Co, Yo)
    return _cv_step_one_block(X, C, z, dt, q, r, u, joseph, Xo, Co, Yo)


@njit(parallel=True, **_JIT)
def _cv_step_one_block(X, C, z, dt, q, r, u, joseph, Xo, Co, Yo):
    """:func:`cv_step` with one block for both axes (C, Co (1, 3, N); q[0] = q[1], r[0] = r[1])."""
    one, two, zero, inf = X.dtype.type(1.0), X.dtype.type(2.0), X.dtype.type(0.0), X.dtype.type(np.inf)
    qx0, qx1, qx2 = q[0, 0], q[0, 1], q[0, 2]  # scalars: an array view made inside the loop stops vectorisation
    per_track_r = r.shape[1] > 1
    n_infinite = 0
    n_partial = 0
    n_singular = 0
    for i in prange(X.shape[1]):
        x, y, vx, vy = _prior_state(X, u, dt, i)
        ex, ey, mx, my, infinite = _innovation(z, i, x, y, Yo, inf)
        n_infinite += infinite
        n_partial += mx != my
        k0, k1, singular = _axis(C, Co, 0, i, dt, qx0, qx1, qx2, r[0, i] if per_track_r else r[0, 0], mx,
                                 one, two, zero, joseph)
        n_singular += singular
        _posterior_state(Xo, i, x, y, vx, vy, k0, k1, k0, k1, ex, ey, mx, my, zero)
    return n_infinite, n_partial, n_singular


@njit(parallel=True, **_JIT)
def _cv_step_two_blocks(X, C, z, dt, q, r, u, joseph, Xo, Co, Yo):
    """:func:`cv_step` with an x block and a y block (C, Co (2, 3, N))."""
    one, two, zero, inf = X.dtype.type(1.0), X.dtype.type(2.0), X.dtype.type(0.0), X.dtype.type(np.inf)
    qx0, qx1, qx2, qy0, qy1, qy2 = q[0, 0], q[0, 1], q[0, 2], q[1, 0], q[1, 1], q[1, 2]
    per_track_r = r.shape[1] > 1
    n_infinite = 0
    n_singular = 0
    for i in prange(X.shape[1]):
        x, y, vx, vy = _prior_state(X, u, dt, i)
        ex, ey, mx, my, infinite = _innovation(z, i, x, y, Yo, inf)
        n_infinite += infinite
        kx0, kx1, singular_x = _axis(C, Co, 0, i, dt, qx0, qx1, qx2, r[0, i] if per_track_r else r[0, 0], mx,
                                     one, two, zero, joseph)
        ky0, ky1, singular_y = _axis(C, Co, 1, i, dt, qy0, qy1, qy2, r[1, i] if per_track_r else r[1, 0], my,
                                     one, two, zero, joseph)
        n_singular += singular_x | singular_y  # one update of a reduction variable per iteration (parfor rule)
        _posterior_state(Xo, i, x, y, vx, vy, kx0, kx1, ky0, ky1, ex, ey, mx, my, zero)
    return n_infinite, 0, n_singular


@njit(**_JIT)
def cv_shared_blocks(C, dt, q, r, joseph):
    """Prior, posterior and gains of covariance blocks that every track shares (all measured).

    C (B, 3), q (2, 3), r (2,) → (prior (B, 3), posterior (B, 3), gains (2, 2) as [k0, k1] of x and y).
    Same arithmetic as :func:`cv_step`, so shared and per-track runs agree to the last bit.
    A block whose innovation variance is not > 0 gets NaN (the caller raises).
    """
    one = C.dtype.type(1.0)
    two = C.dtype.type(2.0)
    B = C.shape[0]
    prior = np.empty_like(C)
    post = np.empty_like(C)
    gains = np.empty((2, 2), dtype=C.dtype)
    for b in range(B):
        p00, p01, p11 = _predict_block(C[b, 0], C[b, 1], C[b, 2], dt, q[b, 0], q[b, 1], q[b, 2])
        s = p00 + r[b]
        g = one / s if s > 0 else C.dtype.type(np.nan)
        o00, o01, o11, k0, k1 = _update_block(p00, p01, p11, r[b], s, g, one, two, joseph)
        prior[b, 0], prior[b, 1], prior[b, 2] = p00, p01, p11
        post[b, 0], post[b, 1], post[b, 2] = o00, o01, o11
        gains[b, 0], gains[b, 1] = k0, k1
    if B == 1:
        gains[1, 0], gains[1, 1] = gains[0, 0], gains[0, 1]
    return prior, post, gains


@njit(parallel=True, **_JIT)
def cv_step_shared(X, z, dt, gains, u, Xo, Yo):
    """States of :func:`cv_step` when every track shares the covariance: the gains are the same for all.

    Returns (n_infinite, n_missing): the outputs are only valid when every track
    was measured (n_missing = 0); otherwise the covariances stop being shared and
    the caller runs :func:`cv_step` instead.
    """
    N = X.shape[1]
    inf = X.dtype.type(np.inf)
    kx0, kx1, ky0, ky1 = gains[0, 0], gains[0, 1], gains[1, 0], gains[1, 1]
    n_infinite = 0
    n_missing = 0
    for i in prange(N):
        x, y, vx, vy = _prior_state(X, u, dt, i)
        zi = z[i]
        n_infinite += (abs(zi.real) == inf) | (abs(zi.imag) == inf)
        ex = zi.real - x
        ey = zi.imag - y
        n_missing += (ex != ex) | (ey != ey)
        Yo[0, i] = ex
        Yo[1, i] = ey
        Xo[0, i] = x + kx0 * ex
        Xo[1, i] = y + ky0 * ey
        Xo[2, i] = vx + kx1 * ex
        Xo[3, i] = vy + ky1 * ey
    return n_infinite, n_missing


@njit(parallel=True, **_JIT)
def cv_predict(X, C, dt, q, u, Xo, Co):
    """The prior alone: Xo = F X (+ u), Co = A C Aᵀ + Q per block; C (B, 3, M) with M = N or 1 (shared)."""
    for i in prange(X.shape[1]):
        x, y, vx, vy = _prior_state(X, u, dt, i)
        Xo[0, i] = x
        Xo[1, i] = y
        Xo[2, i] = vx
        Xo[3, i] = vy
    B = C.shape[0]
    for i in prange(C.shape[2]):
        for b in range(B):
            Co[b, 0, i], Co[b, 1, i], Co[b, 2, i] = _predict_block(C[b, 0, i], C[b, 1, i], C[b, 2, i], dt,
                                                                   q[b, 0], q[b, 1], q[b, 2])


# -- general dense model ------------------------------------------------------------------------
#
# Any n, m.  States x (n, N), covariances P (n, n, N), innovations (m, N).
# Tracks are processed in chunks of CHUNK: a chunk copies its tracks' numbers into scratch
# arrays (n, n, CHUNK) etc. that stay in the CPU cache, every small-matrix operation is then a
# loop over the chunk's tracks innermost (which LLVM vectorises), and the results are written
# back: main memory is read and written once per step.  A model matrix is (1, r, c), shared by
# all tracks, or (N, r, c), one per track; the chunk's copy makes both the same to the
# arithmetic (and one compiled kernel serves both).  The known input u is (n, N), or (n, 0)
# for none.  A range kernel allocates its scratch once and walks through its chunks; the
# tracks are split in ranges between threads.

CHUNK = 128
TRACKS_PER_THREAD = 8192  # fewer tracks than this per thread: fewer threads (see threads_for)


@njit(**_JIT)
def _load_model(M, s0, k, out):
    """out[a, b, j] = the (a, b) entry of track s0 + j's matrix; M (1, r, c) shared or (N, r, c)."""
    if M.shape[0] == 1:
        for a in range(M.shape[1]):
            for b in range(M.shape[2]):
                v = M[0, a, b]
                for j in range(k):
                    out[a, b, j] = v
    else:
        for j in range(k):
            for a in range(M.shape[1]):
                for b in range(M.shape[2]):
                    out[a, b, j] = M[s0 + j, a, b]


@njit(**_JIT)
def _load_covariance(P, s0, k, out):
    """out[a, b, j] = P[a, b, s0 + j] (structure-of-arrays covariances (n, n, N))."""
    for a in range(P.shape[0]):
        for b in range(P.shape[1]):
            for j in range(k):
                out[a, b, j] = P[a, b, s0 + j]


@njit(**_JIT)
def _product(A, B, out, k, zero, transposed=False):
    """out[a, b] = Σ_c A[a, c] B[c, b] (A B), or Σ_c A[a, c] B[b, c] (A Bᵀ) when ``transposed``, for tracks j < k."""
    for a in range(out.shape[0]):
        for b in range(out.shape[1]):
            for j in range(k):
                out[a, b, j] = zero
            for c in range(A.shape[1]):
                Bc = B[b, c] if transposed else B[c, b]
                for j in range(k):
                    out[a, b, j] += A[a, c, j] * Bc[j]


@njit(**_JIT)
def _prior_chunk(x, P, F, Q, u, s0, k, xp, Pp, Fc, W):
    """xp = F x (+ u), Pp = F P Fᵀ + Q (upper triangle mirrored) for tracks s0 .. s0 + k; uses Fc, W."""
    n = x.shape[0]
    zero = x.dtype.type(0.0)
    _load_model(F, s0, k, Fc)
    _load_covariance(P, s0, k, W)
    for a in range(n):
        for j in range(k):
            xp[a, j] = zero
        for b in range(n):
            for j in range(k):
                xp[a, j] += Fc[a, b, j] * x[b, s0 + j]
        if u.shape[1] > 0:
            for j in range(k):
                xp[a, j] += u[a, s0 + j]
    # Pp = (F P) Fᵀ + Q
    _product(Fc, W, Pp, k, zero)
    _product(Pp, Fc, W, k, zero, True)
    _load_model(Q, s0, k, Pp)
    for a in range(n):
        for b in range(a, n):
            for j in range(k):
                Pp[a, b, j] += W[a, b, j]
                Pp[b, a, j] = Pp[a, b, j]


@njit(**_JIT)
def _predict_range(x, P, F, Q, u, xo, Po, start, stop):
    """:func:`dense_predict` for tracks start .. stop."""
    n = x.shape[0]
    xp = np.empty((n, CHUNK), dtype=x.dtype)
    Pp = np.empty((n, n, CHUNK), dtype=x.dtype)
    Fc = np.empty_like(Pp)
    W = np.empty_like(Pp)
    for s0 in range(start, stop, CHUNK):
        k = min(stop, s0 + CHUNK) - s0
        _prior_chunk(x, P, F, Q, u, s0, k, xp, Pp, Fc, W)
        for a in range(n):
            for j in range(k):
                xo[a, s0 + j] = xp[a, j]
            for b in range(n):
                for j in range(k):
                    Po[a, b, s0 + j] = Pp[a, b, j]


def dense_predict(x, P, F, Q, u, xo, Po):
    """The prior alone: xo = F x (+ u), Po = F P Fᵀ + Q; P, Po (n, n, N); F, Q, u as in :func:`dense_step`."""
    _over_threads(_predict_range, x.shape[1], x, P, F, Q, u, xo, Po)


@njit(**_JIT)
def _step_range(x, P, z, F, Q, H, R, u, predict, joseph, xo, Po, yo, start, stop):
    """:func:`dense_step` for tracks start .. stop; returns its two counts for these tracks."""
    n = x.shape[0]
    m = z.shape[1]
    one = x.dtype.type(1.0)
    zero = x.dtype.type(0.0)
    half = x.dtype.type(0.5)
    inf = x.dtype.type(np.inf)
    xp = np.empty((n, CHUNK), dtype=x.dtype)
    Pp = np.empty((n, n, CHUNK), dtype=x.dtype)
    Fc = np.empty_like(Pp)
    W = np.empty_like(Pp)
    A = np.empty_like(Pp)
    Hc = np.empty((m, n, CHUNK), dtype=x.dtype)
    Rc = np.empty((m, m, CHUNK), dtype=x.dtype)
    S = np.empty_like(Rc)
    PHt = np.empty((n, m, CHUNK), dtype=x.dtype)
    K = np.empty_like(PHt)
    e = np.empty((m, CHUNK), dtype=x.dtype)
    seen = np.empty_like(e)  # 1 where measured, else 0
    n_infinite = 0
    n_singular = 0
    for s0 in range(start, stop, CHUNK):
        k = min(stop, s0 + CHUNK) - s0
        if predict:
            _prior_chunk(x, P, F, Q, u, s0, k, xp, Pp, Fc, W)
        else:
            _load_covariance(P, s0, k, Pp)
            for a in range(n):
                for j in range(k):
                    xp[a, j] = x[a, s0 + j]
        _load_model(H, s0, k, Hc)
        _load_model(R, s0, k, Rc)
        # e = z - H x⁻ (NaN where not measured: yo; then 0 for the update)
        for r in range(m):
            for j in range(k):
                e[r, j] = z[s0 + j, r]
            for j in range(k):
                n_infinite += abs(e[r, j]) == inf
            for b in range(n):
                for j in range(k):
                    e[r, j] -= Hc[r, b, j] * xp[b, j]
            for j in range(k):
                yo[r, s0 + j] = e[r, j]
            for j in range(k):
                measured = e[r, j] == e[r, j]
                seen[r, j] = one if measured else zero
                e[r, j] = e[r, j] if measured else zero
        # P Hᵀ (n, m); S = H P Hᵀ + R (lower triangle) with the unmeasured rows and columns
        # replaced by the identity's; then the unmeasured columns of P Hᵀ set to 0
        _product(Pp, Hc, PHt, k, zero, True)
        for r in range(m):
            for t in range(r + 1):
                for j in range(k):
                    S[r, t, j] = Rc[r, t, j]
                for a in range(n):
                    for j in range(k):
                        S[r, t, j] += Hc[r, a, j] * PHt[a, t, j]
                diagonal = one if r == t else zero
                for j in range(k):
                    S[r, t, j] = S[r, t, j] * (seen[r, j] * seen[t, j]) + diagonal * (one - seen[r, j])
        for a in range(n):
            for r in range(m):
                for j in range(k):
                    PHt[a, r, j] *= seen[r, j]
        # Cholesky S = L Lᵀ in place (lower triangle)
        for r in range(m):
            for t in range(r):
                for j in range(k):
                    S[r, r, j] -= S[r, t, j] * S[r, t, j]
            for j in range(k):
                d = S[r, r, j]
                n_singular += not d > zero
                S[r, r, j] = np.sqrt(d) if d > zero else one
            for t in range(r + 1, m):
                for w in range(r):
                    for j in range(k):
                        S[t, r, j] -= S[t, w, j] * S[r, w, j]
                for j in range(k):
                    S[t, r, j] /= S[r, r, j]
        # K = P Hᵀ S⁻¹: every row of P Hᵀ solved with L, then with Lᵀ
        for a in range(n):
            for r in range(m):
                for j in range(k):
                    K[a, r, j] = PHt[a, r, j]
                for t in range(r):
                    for j in range(k):
                        K[a, r, j] -= S[r, t, j] * K[a, t, j]
                for j in range(k):
                    K[a, r, j] /= S[r, r, j]
            for r in range(m - 1, -1, -1):
                for t in range(r + 1, m):
                    for j in range(k):
                        K[a, r, j] -= S[t, r, j] * K[a, t, j]
                for j in range(k):
                    K[a, r, j] /= S[r, r, j]
        # x = x⁻ + K e
        for a in range(n):
            for r in range(m):
                for j in range(k):
                    xp[a, j] += K[a, r, j] * e[r, j]
            for j in range(k):
                xo[a, s0 + j] = xp[a, j]
        # A = I - K H, W = A P⁻
        _product(K, Hc, A, k, zero)
        for a in range(n):
            for b in range(n):
                diagonal = one if a == b else zero
                for j in range(k):
                    A[a, b, j] = diagonal - A[a, b, j]
        _product(A, Pp, W, k, zero)
        if joseph:
            # Joseph form: P = (I - KH) P (I - KH)ᵀ + K R Kᵀ, symmetric PSD even when K is not optimal
            # (K R goes into PHt and the result into Pp, neither needed any more).
            _product(W, A, Pp, k, zero, True)
            _product(K, Rc, PHt, k, zero)
            for a in range(n):
                for b in range(a, n):
                    for r in range(m):
                        for j in range(k):
                            Pp[a, b, j] += PHt[a, r, j] * K[b, r, j]
                    for j in range(k):
                        Po[a, b, s0 + j] = Pp[a, b, j]
                        Po[b, a, s0 + j] = Pp[a, b, j]
        else:
            # simple form P = (I - KH) P, symmetrised
            for a in range(n):
                for b in range(a, n):
                    for j in range(k):
                        v = half * (W[a, b, j] + W[b, a, j])
                        Po[a, b, s0 + j] = v
                        Po[b, a, s0 + j] = v
    return n_infinite, n_singular


def dense_step(x, P, z, F, Q, H, R, u, predict, joseph, xo, Po, yo):
    """Predict (when ``predict``) and update every track on z, in one pass over memory.

    Parameters
    ----------
    x (n, N), P (n, n, N) : the posterior of the previous step, or the prior itself
        when ``predict`` is False.
    z (N, m) : measurements, NaN = component not measured.
    F, Q (1, n, n) or (N, n, n); H (1, m, n) or (N, m, n); R (1, m, m) or (N, m, m).
    u : (n, N) known offset added to the predicted state, or (n, 0) for none.
    joseph : Joseph-form covariance update, else P = (I - K H) P symmetrised.
    xo (n, N), Po (n, n, N), yo (m, N) : outputs; yo = z - H x⁻, NaN where not measured.

    The components a track did not measure are taken out of its update exactly:
    their rows and columns of S = H P Hᵀ + R are replaced by those of the
    identity and their columns of P Hᵀ by 0, so their gains are exactly 0 and the
    others are those of the update with the measured rows of H and block of R.

    Returns
    -------
    (n_infinite, n_singular) : measurement components holding ±inf; pivots of the
    Cholesky factorisation of S (of the measured components) that are not > 0.
    Outputs are valid when both are 0.
    """
    counts = _over_threads(_step_range, x.shape[1], x, P, z, F, Q, H, R, u, predict, joseph, xo, Po, yo)
    return sum(c[0] for c in counts), sum(c[1] for c in counts)


def _over_threads(kernel, N, *args):
    """kernel(*args, start, stop) over the tracks, split between numba's number of threads.

    The range kernels release the GIL, so Python threads run them in parallel.  A numba
    ``prange`` loop around the range kernel compiled the whole kernel once more (26 s on
    top of its own 11 s at load 5, measured) and ran no faster.
    """
    parts = min(numba.get_num_threads(), N // TRACKS_PER_THREAD)
    if parts <= 1:
        return [kernel(*args, 0, N)]
    cuts = [round(N * p / parts / CHUNK) * CHUNK for p in range(parts + 1)]
    cuts[-1] = N
    return list(_threads().map(lambda p: kernel(*args, cuts[p], cuts[p + 1]), range(parts)))


@contextmanager
def threads_for(N: int) -> Iterator[None]:
    """Run the kernels inside on at most one thread per TRACKS_PER_THREAD tracks (numba's count otherwise).

    Below that, starting and joining threads costs more than it saves, and on a busy
    machine a second thread may wait for a core.
    """
    before = numba.get_num_threads()
    wanted = max(1, min(before, N // TRACKS_PER_THREAD))
    if wanted == before:
        yield
        return
    numba.set_num_threads(wanted)
    try:
        yield
    finally:
        numba.set_num_threads(before)


_POOL: list[ThreadPoolExecutor] = []


def _threads() -> ThreadPoolExecutor:
    if not _POOL:
        _POOL.append(ThreadPoolExecutor(max_workers=numba.config.NUMBA_NUM_THREADS,
                                        thread_name_prefix="kalmansfm-kernel"))
    return _POOL[0]


@njit(parallel=True, **_JIT)
def dense_step_shared(x, z, F, u, H, K, predict, xo, yo):
    """States of :func:`dense_step` when every track shares P, H and R: one gain K (n, m) for all.

    F (n, n), H (m, n), K (n, m), u (n, N) or (n, 0).  Returns (n_infinite, n_missing); the outputs are only
    valid when every component of every track was measured (otherwise the covariances
    stop being shared).
    """
    n, N = x.shape
    m = z.shape[1]
    zero = x.dtype.type(0.0)
    inf = x.dtype.type(np.inf)
    has_u = u.shape[1] > 0
    n_infinite = 0
    n_missing = 0
    for i in prange(N):
        for a in range(n):
            if predict:
                v = zero
                for b in range(n):
                    v += F[a, b] * x[b, i]
                if has_u:
                    v += u[a, i]
            else:
                v = x[a, i]
            xo[a, i] = v
        for r in range(m):
            v = z[i, r]
            n_infinite += abs(v) == inf
            for b in range(n):
                v -= H[r, b] * xo[b, i]
            n_missing += v != v
            yo[r, i] = v
        for a in range(n):
            v = xo[a, i]
            for r in range(m):
                v += K[a, r] * yo[r, i]
            xo[a, i] = v
    return n_infinite, n_missing


@njit(parallel=True, **_JIT)
def dense_predict_states(x, F, u, xo):
    """xo = F x (+ u) with a shared F (n, n), u (n, N) or (n, 0): the prior states of a shared-covariance step.

    Same summation order as :func:`dense_step_shared` and :func:`dense_step`, so all
    three give the same prior.
    """
    n, N = x.shape
    zero = x.dtype.type(0.0)
    has_u = u.shape[1] > 0
    for i in prange(N):
        for a in range(n):
            v = zero
            for b in range(n):
                v += F[a, b] * x[b, i]
            if has_u:
                v += u[a, i]
            xo[a, i] = v
