"""Compiled sums of the weighted ALS (:mod:`~kalmansfm.structure.affine._als`), read from the tracks as they lie.

Every kernel takes ``x`` (F, P, 2) float64, the weights ``w`` (F, P, 2) (ignored when
``unit``: every weight 1), ``observed`` (F, P) and the masks ``frame_on`` (F,) and
``point_on`` (P,) of the frames and points that take part, and sums over the entries that
are observed in a frame and a point that are on. Image row 2f + c holds coordinate c of
frame f. Each kernel has a NumPy reference (``*_reference``) that the tests compare it with;
the dense formulation of :class:`~kalmansfm.structure.affine._als._DenseProblem` computes the same sums.

Each frame's entries are first copied, de-interleaved, into contiguous arrays of weights and
values (0 where an entry takes no part: the NaN of an unobserved position is selected away,
never multiplied); every sum is then a branch-free loop over contiguous arrays with at most
one array written, which LLVM vectorizes (a loop that writes several views of one buffer, or
reads a strided view, stays scalar: 4–8 ns an entry instead of about 1).
"""

from __future__ import annotations

import numba
import numpy as np

# As in _measurement: reassociation and contraction, no assumption that values are finite.
_JIT = {"cache": True, "fastmath": {"reassoc", "contract", "nsz", "arcp"}, "nogil": True}
# Points whose normal systems are summed together over all frames (their sums: 36 KB, in L1/L2).
_POINT_BLOCK = 512


@numba.njit(**_JIT)
def point_normals(x, w, unit, observed, frame_on, point_on, motion, translation, shape, normal, rhs,
                  frame_cost):  # pragma: no cover - compiled; see point_normals_reference
    """normal[p] = Σ w m mᵀ and rhs[p] = Σ w (x − t) m over the rows (m = motion[2f + c],
    t = translation[2f + c]) that observed point p; frame_cost[f] = Σ_p,c w (x − m·S_p − t)²
    with S_p = shape[p]. Points and frames that are off get zeros.

    A block of points at a time: its sums, one contiguous array per entry of the normal
    systems, stay in cache while every frame adds to them.
    """
    frames, points = observed.shape
    sums = np.empty((9, _POINT_BLOCK))  # n00 n01 n02 n11 n12 n22 and the right side, per point
    entries = np.empty((4, _POINT_BLOCK))
    s = np.empty((3, _POINT_BLOCK))
    frame_cost[:] = 0.0
    for p0 in range(0, points, _POINT_BLOCK):
        n = min(_POINT_BLOCK, points - p0)
        sums[:, :n] = 0.0
        for q in range(n):
            s[0, q], s[1, q], s[2, q] = shape[p0 + q, 0], shape[p0 + q, 1], shape[p0 + q, 2]
        for f in range(frames):
            if not frame_on[f]:
                continue
            a0, a1, a2 = motion[2 * f, 0], motion[2 * f, 1], motion[2 * f, 2]
            b0, b1, b2 = motion[2 * f + 1, 0], motion[2 * f + 1, 1], motion[2 * f + 1, 2]
            _frame_entries(x, w, unit, observed, point_on, f, p0, n, translation[2 * f], translation[2 * f + 1],
                           entries)
            wa, wb, xa, xb = entries[0], entries[1], entries[2], entries[3]
            frame_cost[f] += _block_cost(wa, wb, xa, xb, s[0], s[1], s[2], a0, a1, a2, b0, b1, b2, n)
            _add_weighted(sums[0], wa, wb, a0 * a0, b0 * b0, n)
            _add_weighted(sums[1], wa, wb, a0 * a1, b0 * b1, n)
            _add_weighted(sums[2], wa, wb, a0 * a2, b0 * b2, n)
            _add_weighted(sums[3], wa, wb, a1 * a1, b1 * b1, n)
            _add_weighted(sums[4], wa, wb, a1 * a2, b1 * b2, n)
            _add_weighted(sums[5], wa, wb, a2 * a2, b2 * b2, n)
            _add_weighted_values(sums[6], wa, wb, xa, xb, a0, b0, n)
            _add_weighted_values(sums[7], wa, wb, xa, xb, a1, b1, n)
            _add_weighted_values(sums[8], wa, wb, xa, xb, a2, b2, n)
        for q in range(n):
            p = p0 + q
            normal[p, 0, 0], normal[p, 0, 1], normal[p, 0, 2] = sums[0, q], sums[1, q], sums[2, q]
            normal[p, 1, 0], normal[p, 1, 1], normal[p, 1, 2] = sums[1, q], sums[3, q], sums[4, q]
            normal[p, 2, 0], normal[p, 2, 1], normal[p, 2, 2] = sums[2, q], sums[4, q], sums[5, q]
            rhs[p, 0], rhs[p, 1], rhs[p, 2] = sums[6, q], sums[7, q], sums[8, q]


def point_normals_reference(x, w, observed, frame_on, point_on, motion, translation, shape):
    """(normal (P, 3, 3), rhs (P, 3), frame_cost (F,)) of :func:`point_normals`; ``w`` None: unit weights."""
    weight = _entry_weights(w, observed, frame_on, point_on)  # (F, P, 2)
    m = motion.reshape(-1, 2, 3)
    t = translation.reshape(-1, 2)
    centred = np.where(weight > 0, x - t[:, None, :], 0.0)
    normal = np.einsum("fpc,fci,fcj->pij", weight, m, m)
    rhs = np.einsum("fpc,fpc,fci->pi", weight, centred, m)
    residual = np.where(weight > 0, centred - np.einsum("fci,pi->fpc", m, shape), 0.0)
    return normal, rhs, np.einsum("fpc,fpc,fpc->f", weight, residual, residual)


@numba.njit(**_JIT)
def frame_normals(x, w, unit, observed, frame_on, point_on, shape, normal,
                  rhs):  # pragma: no cover - compiled; see frame_normals_reference
    """normal[2f + c] = Σ_p w h hᵀ and rhs[2f + c] = Σ_p w x h, h = (S_p, 1), over the points that
    frame f observed. Frames and points that are off get zeros.

    One image row at a time: its 14 sums stay in registers over one loop on the points.
    """
    frames, points = observed.shape
    s = np.empty((3, points))
    for p in range(points):
        s[0, p], s[1, p], s[2, p] = shape[p, 0], shape[p, 1], shape[p, 2]
    entries = np.empty((4, points))
    normal[:] = 0.0
    rhs[:] = 0.0
    for f in range(frames):
        if not frame_on[f]:
            continue
        _frame_entries(x, w, unit, observed, point_on, f, 0, points, 0.0, 0.0, entries)
        for c in range(2):
            sums = _row_sums(entries[c], entries[2 + c], s[0], s[1], s[2], points)
            n, r = normal[2 * f + c], rhs[2 * f + c]
            n[0, 0], n[0, 1], n[0, 2], n[0, 3] = sums[0], sums[1], sums[2], sums[3]
            n[1, 0], n[1, 1], n[1, 2], n[1, 3] = sums[1], sums[4], sums[5], sums[6]
            n[2, 0], n[2, 1], n[2, 2], n[2, 3] = sums[2], sums[5], sums[7], sums[8]
            n[3, 0], n[3, 1], n[3, 2], n[3, 3] = sums[3], sums[6], sums[8], sums[9]
            r[0], r[1], r[2], r[3] = sums[10], sums[11], sums[12], sums[13]


def frame_normals_reference(x, w, observed, frame_on, point_on, shape):
    """(normal (2F, 4, 4), rhs (2F, 4)) of :func:`frame_normals`; ``w`` None: unit weights."""
    weight = _entry_weights(w, observed, frame_on, point_on)
    h = np.hstack([shape, np.ones((len(shape), 1))])
    values = np.where(weight > 0, x, 0.0)
    normal = np.einsum("fpc,pi,pj->fcij", weight, h, h).reshape(-1, 4, 4)
    rhs = np.einsum("fpc,fpc,pi->fci", weight, values, h).reshape(-1, 4)
    return normal, rhs


@numba.njit(**_JIT, inline="always")
def _frame_entries(x, w, unit, observed, point_on, f, p0, n, ta, tb, out):  # pragma: no cover - compiled
    """out[0], out[1] = the weights of x and y of points p0 … p0+n in frame f, 0 where the entry
    takes no part; out[2], out[3] = x − ta and y − tb there, 0 where the weight is 0."""
    seen = observed[f, p0 : p0 + n]
    on_point = point_on[p0 : p0 + n]
    values = x[f, p0 : p0 + n]  # indexed from 0 below: plain stride-2 loads that LLVM vectorizes
    wa, wb, xa, xb = out[0], out[1], out[2], out[3]
    if unit:
        for q in range(n):
            on = seen[q] & on_point[q]
            wa[q] = 1.0 if on else 0.0
            wb[q] = 1.0 if on else 0.0
    else:
        given = w[f, p0 : p0 + n]
        for q in range(n):
            on = seen[q] & on_point[q]
            ga = given[q, 0]
            gb = given[q, 1]
            wa[q] = ga if on else 0.0
            wb[q] = gb if on else 0.0
    for q in range(n):
        va = values[q, 0] - ta
        vb = values[q, 1] - tb
        xa[q] = va if wa[q] != 0.0 else 0.0
        xb[q] = vb if wb[q] != 0.0 else 0.0


@numba.njit(**_JIT, inline="always")
def _block_cost(wa, wb, xa, xb, s0, s1, s2, a0, a1, a2, b0, b1, b2, n):  # pragma: no cover - compiled
    """Σ_q wa (xa − a·S_q)² + wb (xb − b·S_q)²."""
    cost = 0.0
    for q in range(n):
        ra = xa[q] - (a0 * s0[q] + a1 * s1[q] + a2 * s2[q])
        rb = xb[q] - (b0 * s0[q] + b1 * s1[q] + b2 * s2[q])
        cost += wa[q] * ra * ra + wb[q] * rb * rb
    return cost


@numba.njit(**_JIT, inline="always")
def _add_weighted(out, wa, wb, ka, kb, n):  # pragma: no cover - compiled
    for q in range(n):
        out[q] += wa[q] * ka + wb[q] * kb


@numba.njit(**_JIT, inline="always")
def _add_weighted_values(out, wa, wb, xa, xb, ka, kb, n):  # pragma: no cover - compiled
    for q in range(n):
        out[q] += wa[q] * xa[q] * ka + wb[q] * xb[q] * kb


@numba.njit(**_JIT, inline="always")
def _row_sums(weight, value, sx, sy, sz, n):  # pragma: no cover - compiled
    """The ten entries of Σ w h hᵀ (upper triangle, row by row) and the four of Σ w v h, h = (S, 1)."""
    a00 = a01 = a02 = a03 = a11 = a12 = a13 = a22 = a23 = a33 = 0.0
    r0 = r1 = r2 = r3 = 0.0
    for p in range(n):
        wv = weight[p]
        s0, s1, s2 = sx[p], sy[p], sz[p]
        w0, w1, w2 = wv * s0, wv * s1, wv * s2
        a00 += w0 * s0
        a01 += w0 * s1
        a02 += w0 * s2
        a03 += w0
        a11 += w1 * s1
        a12 += w1 * s2
        a13 += w1
        a22 += w2 * s2
        a23 += w2
        a33 += wv
        u = wv * value[p]
        r0 += u * s0
        r1 += u * s1
        r2 += u * s2
        r3 += u
    return a00, a01, a02, a03, a11, a12, a13, a22, a23, a33, r0, r1, r2, r3


def _entry_weights(w, observed, frame_on, point_on):
    """(F, P, 2) weights of the entries that take part, 0 elsewhere."""
    on = observed & frame_on[:, None] & point_on[None, :]
    base = np.ones(observed.shape + (2,)) if w is None else w
    return np.where(on[:, :, None], base, 0.0)
