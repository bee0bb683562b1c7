"""Structure-exploiting kernels for the constant-velocity model (internal).

When F, Q, H, R and P couple only x with vx and y with vy (the constant-velocity
model with diagonal-block noises), the 4-state filter with a 2-vector
measurement splits into two independent 2-state filters with a scalar
measurement.  Each 2×2 covariance block has three unique numbers
(p00 = var(position), p01 = cov(position, velocity), p11 = var(velocity)), and
the x and y blocks are one and the same array while their histories coincide.

Layout (structure of arrays, so every operation is elementwise on (N,) rows):

* ``X`` (4, N): rows x, y, vx, vy;
* ``C`` (B, 3, N) or (B, 3) when all filters share it: B = 1 when the x and y
  blocks are identical, else 2 (x block, y block); rows p00, p01, p11.

The structure tests (:func:`cv_transition_dt`, :func:`axis_blocks`, ...), the
conversions and :class:`DecoupledUpdate` serve the filter.  :func:`predict` and
:func:`update` are the NumPy reference of the compiled kernels in
:mod:`._kernels` (the tests compare the two; the filter runs the kernels): work
is done in chunks of tracks so that the temporaries stay in the CPU cache, all
operations writing into preallocated buffers (``out=``).
"""

from __future__ import annotations

import numpy as np

from ..errors import SingularCovarianceError

CHUNK = 16384

# The structure tests run on every predict and update: a single 4×4 or 2×2 matrix is compared
# as Python numbers (≈ 1 µs), not with NumPy fancy indexing (≈ 20 µs per call).
_COUPLING = ((0, 1), (0, 3), (2, 1), (2, 3), (1, 0), (1, 2), (3, 0), (3, 2))  # x–y entries of a 4×4 matrix


def cv_transition_dt(F: np.ndarray) -> float | None:
    """dt if F is [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], else None."""
    if F.shape != (4, 4):
        return None
    f = F.tolist()
    dt = f[0][2]
    return float(dt) if f == [[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]] else None


def is_position_measurement(H: np.ndarray) -> bool:
    """H = [[1, 0, 0, 0], [0, 1, 0, 0]]: the position is measured."""
    return H.shape == (2, 4) and H.tolist() == [[1, 0, 0, 0], [0, 1, 0, 0]]


def axis_blocks(M: np.ndarray) -> np.ndarray | None:
    """(..., 4, 4) matrix with no x–y coupling → (..., 2, 3) unique entries [[p00, p01, p11] of x, of y]."""
    if M.shape[-2:] != (4, 4):
        return None
    if M.ndim == 2:
        m = M.tolist()
        if any(m[i][j] != 0 for i, j in _COUPLING):
            return None
        return np.array([[m[0][0], m[0][2], m[2][2]], [m[1][1], m[1][3], m[3][3]]], dtype=M.dtype)
    flat = M.reshape(*M.shape[:-2], 16)
    if np.any(flat[..., [4 * i + j for i, j in _COUPLING]] != 0):
        return None
    return flat[..., [0, 2, 10, 5, 7, 15]].reshape(*M.shape[:-2], 2, 3)


def diagonal_noise(R: np.ndarray) -> np.ndarray | None:
    """(..., 2, 2) diagonal R → (..., 2) variances of x and y, else None."""
    if R.shape[-2:] != (2, 2):
        return None
    if R.ndim == 2:
        r = R.tolist()
        return None if r[0][1] != 0 or r[1][0] != 0 else np.array([r[0][0], r[1][1]], dtype=R.dtype)
    if np.any(R[..., 0, 1] != 0) or np.any(R[..., 1, 0] != 0):
        return None
    return np.stack([R[..., 0, 0], R[..., 1, 1]], axis=-1)


def compact_covariance(blocks: np.ndarray) -> np.ndarray:
    """(2, 3) or (N, 2, 3) blocks → C as (B, 3) or (B, 3, N) with B = 1 when x and y blocks agree."""
    if blocks.ndim == 2:
        return blocks[:1].copy() if np.array_equal(blocks[0], blocks[1]) else blocks.copy()
    C = np.ascontiguousarray(np.moveaxis(blocks, 0, -1))  # (2, 3, N)
    return C[:1].copy() if np.array_equal(C[0], C[1]) else C


def dense_covariance(C: np.ndarray, N: int) -> np.ndarray:
    """C (B, 3[, N]) → (N, 4, 4) (or (4, 4) when C is shared)."""
    shared = C.ndim == 2
    blocks = C if C.shape[0] == 2 else np.concatenate([C, C])
    if shared:
        P = np.zeros((4, 4), dtype=C.dtype)
    else:
        P = np.zeros((N, 4, 4), dtype=C.dtype)
        blocks = np.moveaxis(blocks, -1, 0)  # (N, 2, 3)
    for axis, (i, j) in enumerate(((0, 2), (1, 3))):
        p00, p01, p11 = (blocks[..., axis, k] for k in range(3))
        P[..., i, i] = p00
        P[..., i, j] = p01
        P[..., j, i] = p01
        P[..., j, j] = p11
    return P


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


class DecoupledUpdate:
    """What one decoupled update produced, expanded to the public (N, ...) arrays on access.

    ``C_prior`` is the prior's covariance blocks, or a function that computes them
    (the compiled step keeps the prior virtual until someone asks).  ``Y`` (2, N) is
    z - H x⁻ with 0 or NaN where not measured; ``missing`` (N, 2) says where, or is
    None: then the components where ``Y`` is NaN are the missing ones.
    """

    def __init__(self, C_prior, Y, r, missing, N):
        self._C_prior_source = C_prior
        self._Y = Y
        self._r = r  # (2,) or (2, N) measurement variances of x and y
        self._missing = missing
        self._N = N
        self._cache: dict[str, np.ndarray] = {}

    @property
    def _C_prior(self) -> np.ndarray:
        if callable(self._C_prior_source):
            self._C_prior_source = self._C_prior_source()
        return self._C_prior_source

    @property
    def _measured(self) -> np.ndarray:
        if "measured" not in self._cache:
            self._cache["measured"] = (~np.isnan(self._Y.T) if self._missing is None else ~self._missing)
        return self._cache["measured"]

    def _s(self) -> np.ndarray:
        """(2, 1) or (2, N) innovation variances p00⁻ + r per axis."""
        p00 = self._C_prior[:, 0]
        if p00.shape[0] == 1:
            p00 = np.concatenate([p00, p00])
        p00 = p00 if p00.ndim == 2 else p00[:, None]
        r = self._r if self._r.ndim == 2 else self._r[:, None]
        return p00 + r

    @property
    def measured(self) -> np.ndarray:
        return self._measured

    @property
    def y(self) -> np.ndarray:
        if "y" not in self._cache:
            # with missing None, Y already holds NaN where not measured
            Y = self._Y if self._missing is None else np.where(self._missing.T, np.nan, self._Y)
            self._cache["y"] = Y.T
        return self._cache["y"]

    @property
    def S(self) -> np.ndarray:
        if "S" not in self._cache:
            s = np.broadcast_to(self._s(), (2, self._N)).T
            S = np.zeros((self._N, 2, 2), dtype=s.dtype)
            S[:, 0, 0] = s[:, 0]
            S[:, 1, 1] = s[:, 1]
            self._cache["S"] = S
        return self._cache["S"]

    @property
    def K(self) -> np.ndarray:
        if "K" not in self._cache:
            C = self._C_prior
            s = self._s()
            K = np.zeros((self._N, 4, 2), dtype=s.dtype)
            for axis, (i, j) in enumerate(((0, 2), (1, 3))):
                c = C[axis] if C.shape[0] == 2 else C[0]
                g = np.where(self._measured[:, axis], 1.0 / s[axis], 0.0)
                K[:, i, axis] = c[0] * g
                K[:, j, axis] = c[1] * g
            self._cache["K"] = K
        return self._cache["K"]

    @property
    def nis(self) -> np.ndarray:
        if "nis" not in self._cache:
            s = self._s()
            terms = np.where(self._measured.T, self._Y * self._Y / s, 0.0)
            nis = terms.sum(axis=0)
            nis[~self._measured.any(axis=1)] = np.nan
            self._cache["nis"] = nis
        return self._cache["nis"]

    @property
    def log_likelihood(self) -> np.ndarray:
        if "log_likelihood" not in self._cache:
            s = self._s()
            per_axis = np.where(self._measured.T, np.log(2.0 * np.pi * s) + self._Y * self._Y / s, 0.0)
            ll = -0.5 * per_axis.sum(axis=0)
            ll[~self._measured.any(axis=1)] = np.nan
            self._cache["log_likelihood"] = ll
        return self._cache["log_likelihood"]


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
