"""The rank-3 part of a large complete measurement matrix, computed from the tracks array itself.

W (2F × P) stacks the image coordinates of every frame: W[2f + c, p] = positions[f, p, c]
(row 2f is x of frame f, row 2f + 1 its y). That is the (F, P, 2) array read in another
order, so nothing here builds W: three passes over ``positions`` give the leading rank-3
subspace of the centred W_c = W − c 1ᵀ (c the frame centroids), its certificate and each
point's sum of squared residuals of the rank-3 fit.

``positions`` is read where it lies in either of the two row-major layouts: C-ordered
(F, P, 2) (x and y interleaved, as a tracker stores them) or (F, 2, P) in memory — a
C-ordered (F, 2, P) array seen through ``transpose(0, 2, 1)``, which is what rendering
a scene as camera rows times points gives (``R[:, :2] @ S.T``), and which is W itself.

1. *First pass* (one read of ``positions``): the centroids, ‖W_c‖²_F and Y = W_c Zᵀ for
   a start block Z: the ℓ = k + 1 leading right singular vectors of 64 rows of W_c drawn
   with probability proportional to their squared norm (estimated beforehand on a sample
   of columns). The first left block is U = orth(Y). A NaN or an infinity anywhere shows
   in the pass's sums, and the caller takes the general path.
2. *Round trips* (one read each): Z = Uᵀ W_c and Y = W_c Zᵀ = A U (A = W_c W_cᵀ) with the
   same column block of ``positions`` in cache for both. Rayleigh–Ritz on span(U) gives
   the Ritz pairs and the Davis–Kahan bound of :mod:`~kalmansfm.structure.affine.lowrank`. They
   stop when the next iterate, reduced to its k leading Ritz directions, is predicted to
   be within ``tol``.
3. *Projection pass* (one read): with that k-column U fixed, Z = Uᵀ W_c, the residual
   r = W_c − U Z of every entry, each point's Σ_f |r_fp|² (what the points' uncertainty
   needs), Σ r² and r Zᵀ. The last two give the certificate without another product and
   without cancellation: A U − U (Uᵀ A U) = r Zᵀ, and σₖ₊₁² ≤ ‖r‖²_F. If the bound misses
   ``tol`` the pass is repeated with U = orth(A U). No (F, P) array is written: the
   distances |r_fp| themselves are recomputed only if someone asks for them.

The centring happens inside the kernels (each entry minus its centroid in registers).
Every compiled kernel has a NumPy reference below it (``*_reference``); the tests compare
them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from .lowrank import ritz_certificate

# Points in the column sample used to estimate centroids and row norms before the first pass.
_SAMPLE_POINTS = 1024
# Rows of W_c whose leading right subspace starts the iteration.
_START_ROWS = 64
# Bytes of the float64 copy of a column block of all frames (read twice per pass, from L2/L3).
# 2 MB measured best (1000 frames: 128 points; 0.26 s per round trip against 0.33 s at 64 points).
_BLOCK_BYTES = 1 << 21
# The projection pass starts when the predicted bound is below this fraction of ``tol``.
_PREDICTION_MARGIN = 0.25


@dataclass(frozen=True)
class StreamedRank:
    """Rank-k fit of the centred measurement matrix of a complete (F, P, 2) array.

    ``u`` (2F, k) · diag(``s``) · ``vt`` (k, P) is the rank-k part of W_c; ``centroids``
    (F, 2) the frame centroids; ``point_residual_sums`` (P,) each point's Σ_f |r_fp|², r_fp
    the difference between the observed position and its rank-k fit; ``residual_sum`` Σ of
    the squared entries of W_c − U diag(s) Vᵀ; ``extra_singular_values`` the Ritz estimate of σₖ₊₁;
    ``angle_bound``/``certified`` as in :class:`~kalmansfm.structure.affine.lowrank.TruncatedSVD`;
    ``passes`` the number of reads of the array.
    """

    u: np.ndarray
    s: np.ndarray
    vt: np.ndarray
    extra_singular_values: np.ndarray
    centroids: np.ndarray
    point_residual_sums: np.ndarray
    residual_sum: float
    angle_bound: float
    certified: bool
    undetermined: bool
    passes: int


def readable_in_place(positions: np.ndarray) -> bool:
    """True when the kernels read ``positions`` (F, P, 2) as it is: float32 or float64, and
    C-ordered or (F, 2, P) in memory."""
    return positions.dtype in (np.float32, np.float64) and _kernel_layout(positions) is not None


def _kernel_layout(positions: np.ndarray) -> tuple[np.ndarray, bool] | None:
    """(the C-ordered 3-D array the kernels index, planar) with planar True for (F, 2, P); None otherwise."""
    if positions.flags.c_contiguous:
        return positions, False
    planar = positions.transpose(0, 2, 1)
    if planar.flags.c_contiguous:
        return planar, True
    return None


def streamed_rank(
    positions: np.ndarray, rank: int, *, tol: float, max_passes: int, rng: np.random.Generator
) -> StreamedRank | None:
    """Rank-``rank`` fit of the centred W of ``positions`` ((F, P, 2) float32/float64).

    Read where it lies when C-ordered or (F, 2, P) in memory (:func:`readable_in_place`);
    any other layout is copied to C order once. Returns None when ``positions`` holds a NaN
    or an infinity (or overflows), so that the caller can take the general path.
    """
    frames, points = positions.shape[:2]
    layout = _kernel_layout(positions)
    if layout is None:
        positions = np.ascontiguousarray(positions)
        layout = positions, False
    data, planar = layout
    width = rank + 1
    begun = _start(positions, width, rng)
    if begun is None:
        return None
    shift, start = begun
    sums, squares, y = _first_pass(data, planar, shift, start)
    if not (np.isfinite(sums).all() and np.isfinite(squares).all() and np.isfinite(y).all()):
        return None
    offset = sums / points
    centroids = shift + offset
    frobenius = float((squares - sums * offset).sum())  # Σ (x − c)² = Σ (x − s)² − P (c − s)²
    if frobenius <= 0.0:
        return None
    # W_c Zᵀ = (W − s 1ᵀ) Zᵀ − (c − s)(Z 1)ᵀ
    y -= offset[:, :, None] * start.sum(axis=1)
    del start
    u = _orthonormal(y, frames, width)
    passes = 1
    block = _block_points(frames)
    while True:
        z, y = _round_trip(data, planar, centroids, u, block)
        passes += 1
        ritz = ritz_certificate(z, y.reshape(2 * frames, width), u.reshape(2 * frames, width), rank, frobenius)
        ritz_next = float(ritz.singular_values[rank]) ** 2  # Ritz estimate of σₖ₊₁²
        # U's k leading Ritz directions after one more product with A: closer by about (σₖ₊₁ / σₖ)²
        predicted = ritz.bound * ritz_next / max(float(ritz.singular_values[rank - 1]) ** 2, np.finfo(float).tiny)
        if ritz.undetermined or predicted <= _PREDICTION_MARGIN * tol or passes + 2 > max_passes:
            break
        u = _orthonormal(y, frames, width)
    # the projection pass works on the k leading Ritz directions of A U
    u = _orthonormal(y.reshape(2 * frames, width) @ ritz.vectors[:, :rank], frames, rank)
    del z, ritz

    point_sums = np.empty(points)
    while True:
        z, ry, residual_sum = _projection_pass(data, planar, centroids, u, block, point_sums)
        passes += 1
        # A U − U (Uᵀ A U) = r Zᵀ; σₖ₊₁² ≤ ‖r‖²_F (certified whenever below λₖ)
        ritz = ritz_certificate(z, ry.reshape(2 * frames, rank), None, rank, frobenius, upper_next=residual_sum,
                                fallback_next=ritz_next)
        if ritz.bound <= tol or ritz.undetermined or passes + 1 > max_passes:
            break
        a_u = u.reshape(2 * frames, rank) @ (z @ z.T) + ry.reshape(2 * frames, rank)
        u = _orthonormal(a_u, frames, rank)
    # The returned triplets: Z = Uᵀ W_c = G Σ Bᵀ, so W_c ≈ (U G) Σ Bᵀ.
    return StreamedRank(
        u=u.reshape(2 * frames, rank) @ ritz.vectors,
        s=ritz.singular_values,
        vt=ritz.right,
        extra_singular_values=np.sqrt([max(ritz_next, 0.0)]),
        centroids=centroids,
        point_residual_sums=point_sums,
        residual_sum=residual_sum,
        angle_bound=ritz.bound,
        certified=ritz.certified,
        undetermined=ritz.undetermined,
        passes=passes,
    )


def _start(positions: np.ndarray, width: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray] | None:
    """Approximate centroids (F, 2) and a start block Z (width, P) close to the leading right
    singular subspace of W_c, with rows summing to zero.

    A sample of columns gives the approximate centroids (only the shift that keeps the first
    pass's sums small) and the squared row norms; ``_START_ROWS`` rows of W_c drawn with
    probability proportional to those norms (length-squared sampling) give Z as their
    ``width`` leading right singular vectors. A single row holds the signal plus its whole
    noise; the leading subspace of many rows averages the noise down, which saves a round trip.
    None if the sample holds a NaN or an infinity, or W_c is zero on it.
    """
    frames, points = positions.shape[:2]
    sample = np.sort(rng.choice(points, size=min(points, _SAMPLE_POINTS), replace=False))
    sampled = positions[:, sample].astype(np.float64)
    if not np.isfinite(sampled).all():
        return None
    shift = sampled.mean(axis=1)
    sampled -= shift[:, None]
    estimate = np.einsum("fpc,fpc->fc", sampled, sampled).reshape(-1)
    total = float(estimate.sum())
    if total == 0.0:
        return None
    # a pinch of uniform keeps every row possible
    probability = estimate + 1e-3 * total / estimate.size
    count = min(2 * frames, max(width, _START_ROWS))
    rows = np.sort(rng.choice(2 * frames, size=count, replace=False, p=probability / probability.sum()))
    chosen = positions[rows // 2, :, rows % 2].astype(np.float64, copy=False)
    if not np.isfinite(chosen).all():
        return None
    chosen -= chosen.mean(axis=1, keepdims=True)  # rows of W_c (their own mean removed exactly)
    # leading right singular vectors of the chosen rows, from their (count × count) Gram matrix
    _, vectors = np.linalg.eigh(chosen @ chosen.T)
    return shift, vectors[:, ::-1][:, :width].T @ chosen


def _orthonormal(columns: np.ndarray, frames: int, width: int) -> np.ndarray:
    """orth() of a (2F, width) block, returned as (F, 2, width) for the kernels."""
    q, _ = np.linalg.qr(columns.reshape(2 * frames, width))
    return np.ascontiguousarray(q).reshape(frames, 2, width)


def _block_points(frames: int) -> int:
    """Points per column block so that the float64 copy of a block of all frames is about ``_BLOCK_BYTES``."""
    points = _BLOCK_BYTES // (frames * 2 * 8)
    return int(min(1024, max(16, 1 << max(0, int(points).bit_length() - 1))))


# --- compiled kernels and their NumPy references -------------------------------------------------

# Reassociation and contraction (vectorised sums, FMA) but not the no-NaN/no-inf assumptions of
# full fastmath: a NaN or infinity in ``positions`` must reach the first pass's sums.
_JIT = {"cache": True, "fastmath": {"reassoc", "contract", "nsz", "arcp"}, "nogil": True}


@numba.njit(**_JIT)
def _first_pass(x, planar, shift, start):  # pragma: no cover - compiled; see _first_pass_reference
    """Row sums and squared norms of D = W − s 1ᵀ (per frame and coordinate) and D Zᵀ."""
    frames, points = x.shape[0], start.shape[1]
    width = start.shape[0]
    sums = np.zeros((frames, 2))
    squares = np.zeros((frames, 2))
    y = np.zeros((frames, 2, width))
    chunk = 1024
    bx = np.empty(chunk)
    by = np.empty(chunk)
    for f in range(frames):
        for p0 in range(0, points, chunk):
            n = min(chunk, points - p0)
            _load_row(x, planar, shift, f, p0, n, bx, by)
            a0 = 0.0
            a1 = 0.0
            b0 = 0.0
            b1 = 0.0
            for q in range(n):
                a0 += bx[q]
                a1 += by[q]
                b0 += bx[q] * bx[q]
                b1 += by[q] * by[q]
            sums[f, 0] += a0
            sums[f, 1] += a1
            squares[f, 0] += b0
            squares[f, 1] += b1
            _add_products(bx, by, start, p0, n, y, f)
    return sums, squares, y


def _first_pass_reference(x, shift, start):
    """The (F, P, 2) ``x`` of any layout."""
    d = x - shift[:, None, :]
    return d.sum(axis=1), (d * d).sum(axis=1), np.einsum("fpc,jp->fcj", d, start)


@numba.njit(**_JIT, inline="always")
def _load_row(x, planar, centre, f, p0, n, bx, by):  # pragma: no cover - compiled
    """bx, by = x and y of points p0 … p0+n of frame f minus ``centre[f]`` (de-interleaved unless
    ``planar``: then ``x`` is (F, 2, P) and its rows are copied as they are)."""
    cx = centre[f, 0]
    cy = centre[f, 1]
    if planar:
        xs = x[f, 0, p0 : p0 + n]
        ys = x[f, 1, p0 : p0 + n]
        for q in range(n):
            bx[q] = xs[q] - cx
            by[q] = ys[q] - cy
    else:
        segment = x[f, p0 : p0 + n]  # indexed from 0 below: a plain stride-2 load that LLVM vectorizes
        for q in range(n):
            bx[q] = segment[q, 0] - cx
            by[q] = segment[q, 1] - cy


@numba.njit(**_JIT, inline="always")
def _add_products(bx, by, z, p0, n, y, f):  # pragma: no cover - compiled
    """y[f, 0, j] += Σ_q bx[q] z[j, p0 + q] and y[f, 1, j] += Σ_q by[q] z[j, p0 + q], every j."""
    for j in range(z.shape[0]):
        zj = z[j, p0 : p0 + n]
        s0 = 0.0
        s1 = 0.0
        for q in range(n):
            s0 += bx[q] * zj[q]
            s1 += by[q] * zj[q]
        y[f, 0, j] += s0
        y[f, 1, j] += s1


@numba.njit(**_JIT, inline="always")
def _load_block(x, planar, centroids, u, p0, n, block, z):  # pragma: no cover - compiled
    """Copy points p0 … p0+n of every frame, centred, into ``block`` (F, 2, n) and set
    z[:, p0:p0+n] = Uᵀ W_c for those columns, while each row is in L1."""
    frames = x.shape[0]
    width = u.shape[2]
    z[:, p0 : p0 + n] = 0.0
    for f in range(frames):
        bx = block[f, 0]
        by = block[f, 1]
        _load_row(x, planar, centroids, f, p0, n, bx, by)
        for j in range(width):
            a0 = u[f, 0, j]
            a1 = u[f, 1, j]
            zj = z[j, p0 : p0 + n]  # (a row slice stays C-contiguous for numba; z[:, a:b][j] would not)
            for q in range(n):
                zj[q] += a0 * bx[q] + a1 * by[q]


@numba.njit(**_JIT)
def _round_trip(x, planar, centroids, u, block_points):  # pragma: no cover - compiled; see _round_trip_reference
    """Z = Uᵀ W_c (width, P) and Y = W_c Zᵀ (F, 2, width), one column block at a time."""
    frames, points = x.shape[0], x.shape[2] if planar else x.shape[1]
    width = u.shape[2]
    z = np.empty((width, points))
    y = np.zeros((frames, 2, width))
    block = np.empty((frames, 2, block_points))
    for p0 in range(0, points, block_points):
        n = min(block_points, points - p0)
        _load_block(x, planar, centroids, u, p0, n, block, z)
        for f in range(frames):
            _add_products(block[f, 0], block[f, 1], z, p0, n, y, f)
    return z, y


def _round_trip_reference(x, centroids, u):
    frames, points = x.shape[:2]
    w = (x - centroids[:, None, :]).transpose(0, 2, 1).reshape(2 * frames, points)
    z = u.reshape(2 * frames, -1).T @ w
    return z, (w @ z.T).reshape(frames, 2, -1)


@numba.njit(**_JIT)
def _projection_pass(x, planar, centroids, u, block_points, point_sums):  # pragma: no cover - compiled
    """Z = Uᵀ W_c; r = W_c − U Z: writes Σ_f |r_fp|² of each point p to ``point_sums``, returns Z,
    r Zᵀ and Σ r²."""
    frames, points = x.shape[0], x.shape[2] if planar else x.shape[1]
    width = u.shape[2]
    z = np.empty((width, points))
    ry = np.zeros((frames, 2, width))
    block = np.empty((frames, 2, block_points))
    total = 0.0
    for p0 in range(0, points, block_points):
        n = min(block_points, points - p0)
        _load_block(x, planar, centroids, u, p0, n, block, z)
        sums = point_sums[p0 : p0 + n]
        sums[:] = 0.0
        for f in range(frames):
            rx = block[f, 0]  # overwritten by the residual of the row
            rw = block[f, 1]
            for j in range(width):
                a0 = u[f, 0, j]
                a1 = u[f, 1, j]
                zj = z[j, p0 : p0 + n]
                for q in range(n):
                    rx[q] -= a0 * zj[q]
                    rw[q] -= a1 * zj[q]
            _add_products(rx, rw, z, p0, n, ry, f)
            acc = 0.0
            for q in range(n):
                d = rx[q] * rx[q] + rw[q] * rw[q]
                acc += d
                sums[q] += d
            total += acc
    return z, ry, total


def _projection_pass_reference(x, centroids, u):
    frames, points = x.shape[:2]
    w = (x - centroids[:, None, :]).transpose(0, 2, 1).reshape(2 * frames, points)
    basis = u.reshape(2 * frames, -1)
    z = basis.T @ w
    r = w - basis @ z
    point_sums = (r.reshape(frames, 2, points) ** 2).sum(axis=(0, 1))
    return z, (r @ z.T).reshape(frames, 2, -1), float(np.sum(r * r)), point_sums
