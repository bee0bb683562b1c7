"""NumPy reference of the differential matcher's template alignment (the compiled kernel's twin in algorithm).

:func:`align_numpy` aligns all templates at once, one array pass per operation;
:mod:`kalmansfm.tracking._align_kernel` does the same per template in one compiled pass,
summing in double precision where this sums single-precision products, so the two agree
to rounding.  The tests compare them.  It lives with the tests because nothing in the
package runs it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kalmansfm.tracking.alignment import (_QUANTIZATION_VARIANCE, Alignment, AnchorTemplates, DifferentialFrame,
                                         _centre_weights)
from kalmansfm.tracking.matching import well_posed_2x2


@dataclass(frozen=True)
class _TemplateTerms:
    """What Gauss–Newton needs of each template, computed once (float32, pixels flattened):
    its zero-mean inner pixels, their gradients, the inverse of H = Σ ∇T ∇Tᵀ and H's
    smallest eigenvalue per pixel."""

    inner: np.ndarray
    gradients: np.ndarray
    norm: np.ndarray
    inverse: np.ndarray
    well_posed: np.ndarray
    min_eigenvalue: np.ndarray
    centre_energy: np.ndarray


def template_terms(templates: np.ndarray) -> _TemplateTerms:
    t = np.asarray(templates, dtype=np.float32)
    n, w = t.shape[0], t.shape[-1]
    m = (w - 2) ** 2
    # Central differences on the inner (w - 2)² pixels, where both neighbours exist.
    gradients = np.stack([t[:, 1:-1, 2:] - t[:, 1:-1, :-2], t[:, 2:, 1:-1] - t[:, :-2, 1:-1]], axis=1).reshape(n, 2, m)
    gradients *= np.float32(0.5)
    inner = t[:, 1:-1, 1:-1].reshape(n, m)
    inner = inner - inner.mean(axis=1, keepdims=True)
    H = (gradients @ np.swapaxes(gradients, 1, 2)).astype(np.float64)
    hxx, hxy, hyy = H[:, 0, 0], H[:, 0, 1], H[:, 1, 1]
    det, well_posed = well_posed_2x2(hxx, hxy, hyy)
    safe_det = np.where(well_posed, det, 1.0)
    # H⁻¹ = [[hyy, -hxy], [-hxy, hxx]] / det
    inverse = np.stack([hyy, -hxy, -hxy, hxx], axis=1).reshape(n, 2, 2) / safe_det[:, None, None]
    # Smallest eigenvalue of H, per pixel.
    min_eigenvalue = (0.5 * (hxx + hyy) - np.sqrt(0.25 * (hxx - hyy) ** 2 + hxy * hxy)) / m
    norm = np.sqrt(np.einsum("ni,ni->n", inner, inner).astype(np.float64))
    centre_energy = np.einsum("ni,ni->n", inner * _centre_weights(m), inner).astype(np.float64)
    return _TemplateTerms(inner, gradients, norm, inverse, well_posed, min_eigenvalue, centre_energy)


@dataclass(frozen=True)
class _Fit:
    ncc: np.ndarray
    sigma_sq: np.ndarray
    step: np.ndarray
    covariance: np.ndarray


def compare(terms: _TemplateTerms, patches: np.ndarray) -> _Fit:
    """Templates against patches of the same (w - 2)² size: NCC, residual variance, Gauss–Newton step, covariance.

    The residual is r = T̃ - g Ĩ with the gain g = ‖T̃‖ / ‖Ĩ‖ (T̃, Ĩ minus their means).
    Pixels that do not move with the point (background behind a corner, the edge of an
    occluder) are down-weighted by Tukey's biweight (1 - (r / c)²)², c = 4.685 s, with
    s = 1.2533 mean|r| (σ of a Gaussian residual; at least the rounding noise), times a Gaussian of σ = 3 px around
    the centre; with these weights w the step is (Σ w ∇T ∇Tᵀ)⁻¹ Σ w ∇T r,
    σ² = Σ w r² / (Σ w - 4) (translation, gain and offset fitted), at least the rounding
    noise of two 8-bit patches, and the covariance σ² (Σ w ∇T ∇Tᵀ)⁻¹ (NaN where singular).
    The NCC weighs the pixels by the same Gaussian (not by the residuals).
    """
    n = patches.shape[0]
    patch = patches.reshape(n, -1)
    patch = patch - patch.mean(axis=1, keepdims=True)
    p_norm = np.sqrt(np.einsum("ni,ni->n", patch, patch).astype(np.float64))
    gain = np.where(p_norm > 1e-9, terms.norm / np.maximum(p_norm, 1e-9), 1.0)
    residual = terms.inner - gain.astype(np.float32)[:, None] * patch
    scale = np.maximum(np.float32(1.2533) * np.abs(residual).mean(axis=1), np.float32(np.sqrt(_QUANTIZATION_VARIANCE)))
    u = residual / (np.float32(4.685) * scale[:, None])
    u *= u
    weights = np.where(u < 1, (1 - u) ** 2, np.float32(0.0))
    centre = _centre_weights(patch.shape[1])
    weights *= centre
    # NCC with the same weight on the centre (the point's own appearance, less its surroundings).
    p_c = patch * centre
    ncc = np.einsum("ni,ni->n", terms.inner, p_c).astype(np.float64) / np.sqrt(
        np.maximum(terms.centre_energy * np.einsum("ni,ni->n", p_c, patch), 1e-12)
    )
    weighted = weights * residual
    sigma_sq = np.einsum("ni,ni->n", weighted, residual).astype(np.float64) / np.maximum(weights.sum(axis=1).astype(np.float64) - 4.0, 1.0)
    sigma_sq = np.maximum(sigma_sq, _QUANTIZATION_VARIANCE)
    H = ((terms.gradients * weights[:, None, :]) @ np.swapaxes(terms.gradients, 1, 2)).astype(np.float64)
    hxx, hxy, hyy = H[:, 0, 0], H[:, 0, 1], H[:, 1, 1]
    det, conditioned = well_posed_2x2(hxx, hxy, hyy)
    well_posed = terms.well_posed & conditioned
    inverse = np.stack([hyy, -hxy, -hxy, hxx], axis=1).reshape(n, 2, 2) / np.where(well_posed, det, 1.0)[:, None, None]
    b = (terms.gradients @ weighted[:, :, None])[:, :, 0].astype(np.float64)
    step = np.where(well_posed[:, None], np.einsum("nij,nj->ni", inverse, b), 0.0)
    covariance = sigma_sq[:, None, None] * inverse
    covariance[~well_posed] = np.nan
    return _Fit(ncc, sigma_sq, step, covariance)


def align_numpy(frame: DifferentialFrame, bank: AnchorTemplates, start: np.ndarray, iterations: int, max_shift_px: float) -> Alignment:
    """The NumPy reference of the alignment: all templates at once, one array pass per operation."""
    w = bank.templates.shape[-1]
    terms = template_terms(bank.templates)
    patches = frame.patches(start, w)
    current = start.copy()
    for _ in range(iterations):
        current = current + compare(terms, patches[:, 1:-1, 1:-1]).step
        patches = frame.patches(current, w)
    converged = np.linalg.norm(current - start, axis=1) <= max_shift_px
    if not converged.all():
        current[~converged] = start[~converged]
        patches = patches.copy()
        patches[~converged] = frame.patches(start[~converged], w)
    fit = compare(terms, patches[:, 1:-1, 1:-1])
    return Alignment(current, fit.ncc, fit.covariance, terms.min_eigenvalue, fit.sigma_sq, converged, patches)
