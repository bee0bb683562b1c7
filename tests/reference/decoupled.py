"""NumPy reference of the decoupled constant-velocity kernels: predict, then update, as separate passes.

This is the filter's arithmetic before the compiled kernels (it ran in the filter until
they replaced it) and the independent reference the tests compare them with: the
constant-velocity kernels of :mod:`kalmansfm.estimation._kernels` fuse the two steps into
one pass and must return these numbers to the last bit.  Work is done in chunks of tracks
so that the temporaries stay in the CPU cache, every operation writing into preallocated
buffers (``out=``).  Layout as in :mod:`kalmansfm.estimation._decoupled`: X (4, N), C (B, 3)
shared or (B, 3, N).

It lives with the tests because nothing in the package runs it.
"""

from __future__ import annotations

import numpy as np

from kalmansfm.errors import SingularCovarianceError
from kalmansfm.estimation._decoupled import DecoupledUpdate

CHUNK = 16384


def _chunks(N: int):
    for start in range(0, N, CHUNK):
        yield slice(start, min(start + CHUNK, N))


def predict(
    X: np.ndarray, C: np.ndarray, dt: float, q: np.ndarray, u: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray]:
    """x⁻ = F x + u and, per block, P⁻ = A P Aᵀ + Q_b with A = [[1, dt], [0, 1]].

    ``q`` (B, 3) process noise blocks (matching C's B), ``u`` None or (4,) or (4, N).
    """
    N = X.shape[1]
    Xn = np.empty_like(X)
    Cn = np.empty_like(C)
    if C.ndim == 2:
        _predict_cov(C[:, 0], C[:, 1], C[:, 2], dt, q, Cn[:, 0], Cn[:, 1], Cn[:, 2], None)
    tmp = np.empty((3, min(N, CHUNK)), dtype=X.dtype)
    qb = q[:, :, None]
    for sl in _chunks(N):
        k = sl.stop - sl.start
        # position += dt * velocity
        np.multiply(X[2:4, sl], dt, out=tmp[:2, :k])
        np.add(X[0:2, sl], tmp[:2, :k], out=Xn[0:2, sl])
        Xn[2:4, sl] = X[2:4, sl]
        if u is not None:
            Xn[:, sl] += u[:, None] if u.ndim == 1 else u[:, sl]
        if C.ndim == 3:
            c = C[:, :, sl]
            o = Cn[:, :, sl]
            _predict_cov(c[:, 0], c[:, 1], c[:, 2], dt, qb, o[:, 0], o[:, 1], o[:, 2], tmp[: C.shape[0], :k])
    return Xn, Cn


def _predict_cov(p00, p01, p11, dt, q, o00, o01, o11, tmp) -> None:
    # a = p01 + dt p11 (the new p01 before noise)
    a = np.multiply(p11, dt, out=o01)
    np.add(a, p01, out=a)
    # p00⁻ = p00 + dt (p01 + a) + q00 = p00 + 2 dt p01 + dt² p11 + q00
    t = np.add(p01, a, out=tmp if tmp is not None else None)
    np.multiply(t, dt, out=t)
    np.add(t, p00, out=o00)
    np.add(o00, q[:, 0], out=o00)
    np.add(a, q[:, 1], out=o01)
    np.add(p11, q[:, 2], out=o11)


def update(
    X: np.ndarray, C: np.ndarray, z: np.ndarray, r: np.ndarray, joseph: bool, missing_z: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, DecoupledUpdate]:
    """Condition on position measurements z (N, 2), NaN = not measured; r (2,) or (2, N) variances.

    ``missing_z`` (N, 2) is ``isnan(z)``, or None when the caller has checked that z is
    finite (saves a pass over z).  The x and y blocks are split (B 1 → 2) when their
    measurements or noises differ.
    """
    N = X.shape[1]
    any_missing = missing_z is not None and bool(missing_z.any())
    partial = any_missing and bool(np.any(missing_z[:, 0] != missing_z[:, 1]))
    # Y (2, N) = z - H x⁻ is filled chunk by chunk: transposing z inside the cache costs
    # ~1 ns per track, over the whole array ~40 ns.
    Y = np.empty((2, N), dtype=X.dtype)
    r_differs = not np.array_equal(r[0], r[1])
    if C.shape[0] == 1 and (partial or r_differs):
        C = np.concatenate([C, C])
    B = C.shape[0]
    if not any_missing and C.ndim == 2 and r.ndim == 1:
        # Shared covariance, everyone measured: one scalar update per block, then the states.
        Cn = np.empty_like(C)
        g = np.empty((B, 2), dtype=X.dtype)  # gains k0, k1 per block
        for b in range(B):
            p00, p01, p11 = C[b]
            rb = r[b] if B == 2 else r[0]
            s = p00 + rb
            if not s > 0:
                raise SingularCovarianceError("the innovation covariance S = H P Hᵀ + R is not positive definite")
            g1 = 1.0 / s
            # same operation order as the per-filter kernel, so shared and per-filter runs agree bitwise
            k0, k1 = p00 * g1, p01 * g1
            Cn[b] = _joseph_or_simple(p00, p01, p11, rb, s, k0, k1, joseph)
            g[b] = k0, k1
        gk = np.concatenate([g, g]) if B == 1 else g
        Xn = np.empty_like(X)
        tmp = np.empty((2, min(N, CHUNK)), dtype=X.dtype)
        for sl in _chunks(N):
            k = sl.stop - sl.start
            y = np.subtract(z[sl].T, X[0:2, sl], out=Y[:, sl])
            # x = x⁻ + k0 y, v = v⁻ + k1 y
            np.multiply(y, gk[:, :1], out=tmp[:, :k])
            np.add(X[0:2, sl], tmp[:, :k], out=Xn[0:2, sl])
            np.multiply(y, gk[:, 1:], out=tmp[:, :k])
            np.add(X[2:4, sl], tmp[:, :k], out=Xn[2:4, sl])
        return Xn, Cn, DecoupledUpdate(C, Y, r, missing_z, N)

    Cn = np.empty((B, 3, N), dtype=X.dtype)
    Xn = np.empty_like(X)
    rb_all = r if B == 2 else r[:1]
    buf = np.empty((8, min(N, CHUNK)), dtype=X.dtype)
    both = np.empty((2, min(N, CHUNK)), dtype=X.dtype)
    # A zero s (singular S) gives an infinite gain and NaN in the new covariance, raised as
    # SingularCovarianceError below without NumPy's divide/invalid warnings before it.
    with np.errstate(divide="ignore", invalid="ignore"):
        for sl in _chunks(N):
            k = sl.stop - sl.start
            t = buf[:, :k]
            s, g, k0, k1 = t[0], t[1], t[2], t[3]
            # Y = z - H x⁻, stored with 0 where not measured (the y property puts the NaN back)
            Ys = np.subtract(z[sl].T, X[0:2, sl], out=Y[:, sl])
            if any_missing:
                missing = missing_z[sl].T
                np.copyto(Ys, 0.0, where=missing)
            for b in range(B):
                c = C[b] if C.ndim == 2 else C[b, :, sl]
                p00, p01, p11 = c[0], c[1], c[2]
                rb = rb_all[b] if rb_all.ndim == 1 else rb_all[b, sl]
                np.add(p00, rb, out=s)
                # g = 1 / s where measured, 0 where not: the gain vanishes and the prior passes through.
                np.divide(1.0, s, out=g)
                if any_missing:
                    np.copyto(g, 0.0, where=missing[b])
                np.multiply(p00, g, out=k0)
                np.multiply(p01, g, out=k1)
                _block_update_inplace(p00, p01, p11, rb, s, k0, k1, Cn[b, :, sl], t[4:8], joseph)
                # x = x⁻ + k0 y, v = v⁻ + k1 y (both axes at once when they share the block)
                rows = slice(b, b + 1) if B == 2 else slice(0, 2)
                tmp = both[: rows.stop - rows.start, :k]
                np.multiply(k0, Ys[rows], out=tmp)
                np.add(X[rows, sl], tmp, out=Xn[rows, sl])
                np.multiply(k1, Ys[rows], out=tmp)
                np.add(X[rows.start + 2 : rows.stop + 2, sl], tmp, out=Xn[rows.start + 2 : rows.stop + 2, sl])
    if not np.all(np.isfinite(Cn[:, 0])):
        raise SingularCovarianceError("the innovation covariance S = H P Hᵀ + R is not positive definite")
    return Xn, Cn, DecoupledUpdate(C, Y, r, missing_z, N)


def _joseph_or_simple(p00, p01, p11, r, s, k0, k1, joseph):
    if joseph:
        a = 1.0 - k0
        return ((a * a) * p00 + (k0 * k0) * r, a * (p01 - k1 * p00) + (k0 * k1) * r,
                p11 - k1 * (p01 * 2.0 - k1 * s))
    a = 1.0 - k0
    return a * p00, a * p01, p11 - k1 * p01


def _block_update_inplace(p00, p01, p11, r, s, k0, k1, o, t, joseph) -> None:
    """Posterior of one 2×2 block with scalar measurement of the position, into o = (p00, p01, p11)."""
    a, u, v, w = t[0], t[1], t[2], t[3]
    np.subtract(1.0, k0, out=a)
    if joseph:
        # Joseph form with A = I - k h, h = [1, 0]:
        # p00 = a² p00 + r k0²
        np.multiply(a, a, out=u)
        np.multiply(u, p00, out=u)
        np.multiply(k0, k0, out=v)
        np.multiply(v, r, out=v)
        np.add(u, v, out=o[0])
        # p01 = a (p01 - k1 p00) + r k0 k1
        np.multiply(k1, p00, out=u)
        np.subtract(p01, u, out=u)
        np.multiply(a, u, out=u)
        np.multiply(k0, k1, out=v)
        np.multiply(v, r, out=v)
        np.add(u, v, out=o[1])
        # p11 = p11 - 2 k1 p01 + k1² s = p11 - k1 (2 p01 - k1 s)
        np.multiply(k1, s, out=u)
        np.multiply(p01, 2.0, out=w)
        np.subtract(w, u, out=w)
        np.multiply(k1, w, out=w)
        np.subtract(p11, w, out=o[2])
    else:
        # Simple form P = (I - k h) P
        np.multiply(a, p00, out=o[0])
        np.multiply(a, p01, out=o[1])
        np.multiply(k1, p01, out=u)
        np.subtract(p11, u, out=o[2])
