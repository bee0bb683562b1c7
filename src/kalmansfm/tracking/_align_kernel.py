"""Compiled (numba) kernel of the differential matcher's template alignment: one pass per track.

The same algorithm as the NumPy reference in ``tests/reference/alignment.py``
(``align_numpy``: ``template_terms``, ``compare`` and the bilinear
``sample_patches``), written per track: the NumPy version streams every
(tracks × pixels) array through memory a few dozen times per Gauss–Newton step, this
one keeps a template's 81 inner pixels, their gradients and the patch in the cache
while it samples, fits, steps and fits again.  Sums are accumulated in double
precision (the reference sums single-precision products), so the two agree to
rounding; the tests compare them.

Per track (T the w×w template, its inner (w - 2)² pixels with central-difference
gradients ∇T; I the frame, sampled bilinearly from the padded frame):

* T̃ = inner T minus its mean, H₀ = Σ ∇T ∇Tᵀ (well posed, smallest eigenvalue);
* ``iterations`` times: patch at p, robust weights, step d = (Σ w ∇T ∇Tᵀ)⁻¹ Σ w ∇T r, p += d;
* if p moved more than ``max_shift`` from the start it keeps the start;
* the final fit at p: centre-weighted NCC, σ² and σ² (Σ w ∇T ∇Tᵀ)⁻¹.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .._compilation import watch_compilation

watch_compilation()  # one line on stderr when the kernel is compiled (not when it is loaded from the cache)

# The constants are those of alignment.py (passed in, one definition there).
# The helpers are compiled apart and inlined by LLVM: inlining them in numba's IR (inline="always")
# cost about 0.5 s more compilation, for the same results to the last bit and the same speed.


@njit(cache=True, fastmath={"reassoc", "contract", "arcp"})
def _sample(padded, pad, size, x, y, out):
    """Bilinear size×size patch of ``padded`` centred at (x, y), as ``sample_patches`` (border repeated)."""
    height, width = padded.shape
    wx = math.floor(x)
    wy = math.floor(y)
    fx = np.float32(x - wx)
    fy = np.float32(y - wy)
    top = int(wy) - size // 2 + pad
    left = int(wx) - size // 2 + pad
    top = min(max(top, 0), height - size - 1)
    left = min(max(left, 0), width - size - 1)
    for r in range(size):
        for c in range(size):
            a = np.float32(padded[top + r, left + c])
            b = np.float32(padded[top + r, left + c + 1])
            d = np.float32(padded[top + r + 1, left + c])
            e = np.float32(padded[top + r + 1, left + c + 1])
            upper = a + fx * (b - a)
            lower = d + fx * (e - d)
            out[r, c] = upper + fy * (lower - upper)


@njit(cache=True, fastmath={"reassoc", "contract", "arcp"})
def _fit(inner, gx, gy, centre, norm, centre_energy, well_posed_template, patch, scale_floor, quantization, flat, residual, result):
    """Compare one template (its terms) with the inner pixels of ``patch``; see ``compare`` in the reference.

    result ← [step x, step y, ncc, σ², cov xx, cov xy, cov yy, well posed]."""
    w = patch.shape[0]
    m = (w - 2) * (w - 2)
    k = 0
    total = 0.0
    for r in range(1, w - 1):
        for c in range(1, w - 1):
            flat[k] = patch[r, c]
            total += flat[k]
            k += 1
    mean = np.float32(total / m)
    p_sq = 0.0
    for k in range(m):
        v = flat[k] - mean
        flat[k] = v
        p_sq += v * v
    p_norm = math.sqrt(p_sq)
    gain = np.float32(norm / max(p_norm, 1e-9) if p_norm > 1e-9 else 1.0)
    # Residual r = T̃ - g Ĩ and its robust scale 1.2533 mean|r| (σ of a Gaussian residual).
    abs_sum = 0.0
    for k in range(m):
        v = inner[k] - gain * flat[k]
        residual[k] = v
        abs_sum += abs(v)
    scale = max(1.2533 * abs_sum / m, scale_floor)
    inverse_cutoff = np.float32(1.0 / (4.685 * scale))
    # Tukey's biweight times the centre's Gaussian; NCC weighs by the Gaussian alone.
    zero = np.float32(0.0)
    cross = zero
    p_energy = zero
    sum_w = zero
    sum_wr2 = zero
    hxx = zero
    hxy = zero
    hyy = zero
    bx = zero
    by = zero
    for k in range(m):
        pv = flat[k]
        g = centre[k]
        cross += inner[k] * pv * g
        p_energy += pv * pv * g
        u = residual[k] * inverse_cutoff
        one_minus = max(np.float32(1.0) - u * u, np.float32(0.0))
        weight = one_minus * one_minus * g
        wr = weight * residual[k]
        sum_w += weight
        sum_wr2 += wr * residual[k]
        hxx += weight * gx[k] * gx[k]
        hxy += weight * gx[k] * gy[k]
        hyy += weight * gy[k] * gy[k]
        bx += gx[k] * wr
        by += gy[k] * wr
    # (Single-precision sums of 81 terms, as the reference's; the 2×2 algebra in double.)
    hxx, hxy, hyy, bx, by = float(hxx), float(hxy), float(hyy), float(bx), float(by)
    ncc = float(cross) / math.sqrt(max(centre_energy * float(p_energy), 1e-12))
    sigma_sq = max(float(sum_wr2) / max(float(sum_w) - 4.0, 1.0), quantization)
    # matching.well_posed_2x2, inline (compiled); the tests check the two agree
    det = hxx * hyy - hxy * hxy
    trace = hxx + hyy
    ok = well_posed_template and det > 1e-9 * max(trace, 1e-12) ** 2
    result[2] = ncc
    result[3] = sigma_sq
    if ok:
        # H⁻¹ = [[hyy, -hxy], [-hxy, hxx]] / det
        result[0] = (hyy * bx - hxy * by) / det
        result[1] = (hxx * by - hxy * bx) / det
        result[4] = sigma_sq * hyy / det
        result[5] = -sigma_sq * hxy / det
        result[6] = sigma_sq * hxx / det
        result[7] = 1.0
    else:
        result[0] = 0.0
        result[1] = 0.0
        result[4] = np.nan
        result[5] = np.nan
        result[6] = np.nan
        result[7] = 0.0


@njit(cache=True, fastmath={"reassoc", "contract", "arcp"})
def align_batch(padded, pad, templates, starts, centre, iterations, max_shift, scale_floor, quantization,
                positions, ncc, covariances, min_eigenvalue, residual_variance, converged, patches):
    """Align each template to the padded frame from its start; fills the output arrays (see the module docs)."""
    n, w = templates.shape[0], templates.shape[1]
    m = (w - 2) * (w - 2)
    inner = np.empty(m, np.float32)
    gx = np.empty(m, np.float32)
    gy = np.empty(m, np.float32)
    patch = np.empty((w, w), np.float32)
    residual = np.empty(m, np.float32)
    flat = np.empty(m, np.float32)
    result = np.empty(8)
    for i in range(n):
        # The template's terms: zero-mean inner pixels, central differences, H₀ = Σ ∇T ∇Tᵀ.
        t = templates[i]
        mean = 0.0
        for r in range(1, w - 1):
            for c in range(1, w - 1):
                mean += t[r, c]
        mean /= m
        norm_sq = 0.0
        centre_energy = 0.0
        h0xx = 0.0
        h0xy = 0.0
        h0yy = 0.0
        k = 0
        for r in range(1, w - 1):
            for c in range(1, w - 1):
                v = np.float32(t[r, c] - mean)
                inner[k] = v
                gx[k] = np.float32(0.5) * (t[r, c + 1] - t[r, c - 1])
                gy[k] = np.float32(0.5) * (t[r + 1, c] - t[r - 1, c])
                norm_sq += v * v
                centre_energy += v * v * centre[k]
                h0xx += gx[k] * gx[k]
                h0xy += gx[k] * gy[k]
                h0yy += gy[k] * gy[k]
                k += 1
        det0 = h0xx * h0yy - h0xy * h0xy
        well_posed = det0 > 1e-9 * max(h0xx + h0yy, 1e-12) ** 2  # matching.well_posed_2x2, inline
        min_eigenvalue[i] = (0.5 * (h0xx + h0yy) - math.sqrt(0.25 * (h0xx - h0yy) ** 2 + h0xy * h0xy)) / m
        norm = math.sqrt(norm_sq)
        x0 = starts[i, 0]
        y0 = starts[i, 1]
        if not (math.isfinite(x0) and math.isfinite(y0)):
            positions[i, 0] = x0
            positions[i, 1] = y0
            ncc[i] = np.nan
            residual_variance[i] = np.nan
            converged[i] = False
            for a in range(2):
                for b in range(2):
                    covariances[i, a, b] = np.nan
            for r in range(w):
                for c in range(w):
                    patches[i, r, c] = np.nan
            continue
        # Gauss–Newton steps from the start; an alignment that runs away keeps the start.
        x, y = x0, y0
        _sample(padded, pad, w, x, y, patch)
        for _ in range(iterations):
            _fit(inner, gx, gy, centre, norm, centre_energy, well_posed, patch, scale_floor, quantization, flat, residual, result)
            x += result[0]
            y += result[1]
            _sample(padded, pad, w, x, y, patch)
        ok = math.hypot(x - x0, y - y0) <= max_shift
        if not ok:
            x, y = x0, y0
            _sample(padded, pad, w, x, y, patch)
        _fit(inner, gx, gy, centre, norm, centre_energy, well_posed, patch, scale_floor, quantization, flat, residual, result)
        positions[i, 0] = x
        positions[i, 1] = y
        converged[i] = ok
        ncc[i] = result[2]
        residual_variance[i] = result[3]
        covariances[i, 0, 0] = result[4]
        covariances[i, 0, 1] = result[5]
        covariances[i, 1, 0] = result[5]
        covariances[i, 1, 1] = result[6]
        for r in range(w):  # element by element: a whole-array assignment costs seconds of compilation
            for c in range(w):
                patches[i, r, c] = patch[r, c]
