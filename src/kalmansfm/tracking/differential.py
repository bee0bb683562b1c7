"""Differential measurement: Lucas–Kanade started from the Kalman prediction, checked, with its own noise.

One call of :func:`measure_differential` measures every track in the current
frame at once (``docs/tracking.md`` has the measurements behind each choice):

1. **Flow from the prediction.**  OpenCV's pyramidal Lucas–Kanade
   (``calcOpticalFlowPyrLK`` with ``OPTFLOW_USE_INITIAL_FLOW``) follows each
   track from its previous position, starting at the predicted position p⁻.
   The pyramid depth is per track: the gate reaches c·√λmax(Σ⁻) from p⁻ (less
   where the track's plausible radius is smaller), and L levels capture about
   ``capture_px``·2^L pixels (measured), so a confident track runs on fewer
   levels.  Tracks are grouped by depth, one OpenCV call per group.
2. **Anchor.**  Each track carries an *anchor*: a template cut at its first
   appearance (or at a later keyframe chosen by the caller).  It is aligned to
   the frame from the flow's match by robust, centre-weighted Gauss–Newton steps
   with gain and offset (:func:`align_templates`, a compiled kernel).
3. **Forward–backward check** where the anchor does not settle the match: the
   flow from the current frame back to the previous one, started at the match
   minus the predicted motion, must land within ``forward_backward_px`` of where
   the track was.  A first appearance that matches very well (NCC ≥
   ``anchor_ncc``) where the flow ended is the point itself: no flow back.
4. **Chain.**  Elsewhere the previous frame's patch is aligned from the flow's
   match by the same robust steps.  The anchor's position is the measurement
   where it matches very well or explains the patch nearly as well as the
   previous frame does (``trust_ratio``), so the track does not drift; the
   chain's otherwise.
5. **Appearance.**  The anchor's centre-weighted NCC at the measurement must be
   at least ``min_ncc`` — or ``rescue_ncc`` where the chain is clean (a mild
   appearance change that the previous frame's patch follows).
6. **Gate and plausibility.**  (z - p⁻)ᵀ (Σ⁻)⁻¹ (z - p⁻) ≤ c², ‖z - p⁻‖ at most the
   track's plausible radius, and the point in the image.
7. **Noise from the refinement.**  R = σ² (Σ w ∇T ∇Tᵀ)⁻¹ of the refinement that
   measured, plus what it inherits (the anchor's covariance when it was cut at a
   keyframe; the previous measurement's for a chained match, whose error is the
   previous one's plus the flow's), plus a floor of (0.12 px)² per axis.

Coasting tracks (no measured position in the previous frame) are not followed by
flow, which would follow whatever hid them: their anchor is searched by SSD in the
gate (:func:`~kalmansfm.tracking.matching.match_templates`), then aligned and taken
only at NCC ≥ ``reacquire_ncc``.

Coordinates: x = column, y = row, pixel centres at integer coordinates.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from ..errors import InvalidInputError
from .matching import PreparedFrame, match_templates, prepare_frame, sample_patches, well_posed_2x2

__all__ = [
    "ACCEPTED",
    "REJECTION_NAMES",
    "Alignment",
    "AnchorTemplates",
    "DifferentialFrame",
    "DifferentialMeasurement",
    "align_templates",
    "measure_differential",
    "pyramid_levels",
]

#: rejection code: the measurement was accepted
ACCEPTED = 0
#: the window around the prediction or the match does not fit in the image
OUTSIDE = 1
#: the flow did not converge (OpenCV status 0), or the coasting track's anchor was not found in its gate
NOT_FOUND = 2
#: the match lies outside the gate ellipse
GATE = 3
#: the flow back to the previous frame misses the previous position
FORWARD_BACKWARD = 4
#: the anchor does not match the patch at the measured position (NCC below ``min_ncc``)
APPEARANCE = 5
#: the anchor's structure tensor is too weak to locate it (flat or edge-only patch)
TEXTURELESS = 6
#: the match lies farther from the prediction than the track's own recent innovations allow
IMPLAUSIBLE = 7

REJECTION_NAMES = {
    ACCEPTED: "accepted",
    OUTSIDE: "outside",
    NOT_FOUND: "not found",
    GATE: "gate",
    FORWARD_BACKWARD: "forward-backward",
    APPEARANCE: "appearance",
    TEXTURELESS: "textureless",
    IMPLAUSIBLE: "implausible",
}

#: a pyramid of L levels above the image captures displacements of about this times 2^L px (window 7–21)
CAPTURE_PX = 4.0
_LK_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
# Floor of the residual variance σ² (grey levels²): two 8-bit patches, each rounded with
# variance 1/12, never agree better than this, and R = σ² H⁻¹ must stay positive definite.
_QUANTIZATION_VARIANCE = 2.0 / 12.0
# Gaussian weight (px) on the alignment's pixels around the point: the window's rim, where
# background behind a corner moves differently, counts less (cmu_house 0.911 → 0.929 within
# 3 px, the scene 0.38 → 0.32 px RMS; docs/tracking.md).
_CENTRE_SIGMA_PX = 3.0
# What σ² H⁻¹ does not see (bilinear interpolation, an appearance that changes slowly): a
# floor of (0.12 px)² on each axis of R, calibrated on the built-in scene's seeds 0-9 (NEES
# 2.35, 1σ rate 0.68) and checked on held-out seeds (tests, docs/tracking.md).
_MODEL_NOISE_PX = 0.12


@dataclass(frozen=True)
class DifferentialFrame:
    """One frame made ready for differential measurement.

    Attributes
    ----------
    grey : (H, W) uint8, what OpenCV's Lucas–Kanade reads.
    window : side of the anchor templates (odd).
    search_radius : largest half-size of an anchor search box (coasting tracks).
    fine : (H, W) float32 frame with more than 8 bits (scaled to 0…255), or None for an
        8-bit frame; the anchors are cut from and aligned to it.
    image : (property) the frame the anchors see, float32: ``fine``, or ``grey`` converted.
    prepared : (property, on first use) the frame prepared for the gated anchor search.
    padded_frame : (property, on first use) the frame with a border repeated around it,
        from which patches are sampled.
    """

    grey: np.ndarray
    window: int
    search_radius: int
    fine: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width)."""
        return self.grey.shape  # type: ignore[return-value]

    @cached_property
    def image(self) -> np.ndarray:
        """The frame as float32 (exact for 8 bits)."""
        return self.fine if self.fine is not None else self.grey.astype(np.float32)

    @cached_property
    def prepared(self) -> PreparedFrame:
        """Padded frame with its window sums; its padding also serves the alignment."""
        return prepare_frame(self.image, self.window, self.search_radius)

    @cached_property
    def padded_frame(self) -> PreparedFrame:
        """The frame with a border repeated around it, for sampling patches (the 8-bit frame as is)."""
        if "prepared" in self.__dict__:
            return self.prepared
        # The box sums of a PreparedFrame are not used by sampling (left empty).
        pad = self.window // 2 + 4
        source = self.fine if self.fine is not None else self.grey
        padded = cv2.copyMakeBorder(source, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
        return PreparedFrame(source, padded, np.zeros((0, 0), np.float32), self.window, pad)

    def patches(self, centers: np.ndarray, size: int | None = None) -> np.ndarray:
        """Bilinear ``size``×``size`` patches (default: the anchor window) at sub-pixel centres (x, y)."""
        return sample_patches(self.padded_frame, centers, self.window if size is None else size, np.float32)


def prepare_differential_frame(frame: np.ndarray, window: int, search_radius: int = 40, grey_scale: float = 1.0) -> DifferentialFrame:
    """Make a grey frame ready for :func:`measure_differential` (once per frame).

    Parameters
    ----------
    frame : (H, W) grey image; uint8 is used as is, other types are multiplied by
        ``grey_scale`` (the anchors see that) and rounded and clipped to 0…255 for the flow.
    window : side of the anchor templates (odd).
    search_radius : largest half-size of an anchor search box.
    grey_scale : factor that brings the frame's grey levels to 0…255 (the same for every
        frame of a sequence, e.g. 255 / 65535 for 16-bit frames): the thresholds on residuals
        and gradients are in 8-bit grey levels.

    Examples
    --------
    >>> f = prepare_differential_frame(np.full((20, 30), 7.4), window=5)
    >>> f.grey.dtype.name, int(f.grey[0, 0]), f.shape, f.patches(np.array([[10.0, 10.0]]), 3).shape
    ('uint8', 7, (20, 30), (1, 3, 3))
    """
    frame = np.asarray(frame)
    if frame.dtype == np.uint8:
        return DifferentialFrame(np.ascontiguousarray(frame), int(window), int(search_radius))
    fine = np.ascontiguousarray(frame, dtype=np.float32)
    if grey_scale != 1.0:
        fine = fine * np.float32(grey_scale)
    grey = np.clip(np.rint(fine), 0, 255).astype(np.uint8)
    return DifferentialFrame(grey, int(window), int(search_radius), fine)


def pyramid_levels(reach_px: np.ndarray, max_level: int, capture_px: float = CAPTURE_PX) -> np.ndarray:
    """Fewest pyramid levels L with ``capture_px``·2^L ≥ reach, clipped to 0…``max_level``.

    Examples
    --------
    >>> pyramid_levels(np.array([1.0, 4.0, 4.1, 10.0, 17.0, 100.0, np.nan]), max_level=3).tolist()
    [0, 0, 1, 2, 3, 3, 3]
    """
    reach = np.asarray(reach_px, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        levels = np.ceil(np.log2(np.maximum(reach, 1e-12) / capture_px))
    levels = np.where(np.isfinite(levels), levels, max_level)
    return np.clip(levels, 0, max_level).astype(np.int64)


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


@functools.lru_cache(maxsize=8)
def _centre_weights(n_pixels: int) -> np.ndarray:
    """Flattened Gaussian of σ = ``_CENTRE_SIGMA_PX`` over a square patch of ``n_pixels`` pixels."""
    side = int(round(np.sqrt(n_pixels)))
    g = np.exp(-0.5 * ((np.arange(side) - side // 2) / _CENTRE_SIGMA_PX) ** 2).astype(np.float32)
    return np.outer(g, g).ravel()


def _template_terms(templates: np.ndarray) -> _TemplateTerms:
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


def _compare(terms: _TemplateTerms, patches: np.ndarray) -> _Fit:
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


class AnchorTemplates:
    """The tracks' anchor templates, one row per track (kept by the tracker between frames).

    The alignment computes a template's terms (gradients, structure tensor) as it goes;
    :attr:`terms` computes them for the NumPy reference on first use.

    Parameters
    ----------
    templates : (N, w, w) templates.

    Examples
    --------
    >>> bank = AnchorTemplates(np.ones((3, 5, 5)))
    >>> bank = bank.take(np.array([0, 2])).replace(np.array([1]), np.zeros((1, 5, 5))).append(np.ones((1, 5, 5)))
    >>> len(bank), bank.templates.sum(axis=(1, 2)).tolist()
    (3, [25.0, 0.0, 25.0])
    """

    def __init__(self, templates: np.ndarray) -> None:
        self.templates = np.ascontiguousarray(templates, dtype=np.float32)

    def __len__(self) -> int:
        return len(self.templates)

    @cached_property
    def terms(self) -> _TemplateTerms:
        """What Gauss–Newton needs of each template (the NumPy reference's form)."""
        return _template_terms(self.templates)

    def take(self, index: np.ndarray) -> AnchorTemplates:
        """The anchors at ``index`` (indices or a boolean mask)."""
        return AnchorTemplates(self.templates[index])

    def append(self, templates: np.ndarray) -> AnchorTemplates:
        """These anchors followed by ``templates``."""
        new = np.asarray(templates, dtype=np.float32).reshape(-1, *self.templates.shape[1:])
        return AnchorTemplates(np.concatenate([self.templates, new]))

    def replace(self, rows: np.ndarray, templates: np.ndarray) -> AnchorTemplates:
        """These anchors with the ones at ``rows`` replaced by ``templates`` (a keyframe)."""
        merged = self.templates.copy()
        merged[np.asarray(rows, dtype=np.intp)] = templates
        return AnchorTemplates(merged)


@dataclass(frozen=True)
class Alignment:
    """Templates aligned to a frame by Gauss–Newton (:func:`align_templates`).

    Attributes
    ----------
    positions : (N, 2) aligned positions (x, y); the start where the alignment ended
        more than ``max_shift_px`` away.
    ncc : (N,) normalised cross-correlation of template and patch at ``positions``.
    covariances : (N, 2, 2) σ² (Σ ∇T ∇Tᵀ)⁻¹, the alignment's own position covariance
        (px²), σ² the residual variance after gain and offset; NaN where ill-posed.
    min_eigenvalue : (N,) smallest eigenvalue of Σ ∇T ∇Tᵀ per pixel (grey levels² / px²).
    residual_variance : (N,) σ², the residual's variance per pixel after gain and offset.
    converged : (N,) True where the alignment ended within ``max_shift_px`` of the start.
    patches : (N, w, w) the frame's patches at ``positions``.
    """

    positions: np.ndarray
    ncc: np.ndarray
    covariances: np.ndarray
    min_eigenvalue: np.ndarray
    residual_variance: np.ndarray
    converged: np.ndarray
    patches: np.ndarray


def align_templates(
    frame: DifferentialFrame,
    templates: np.ndarray | AnchorTemplates,
    start: np.ndarray,
    iterations: int = 2,
    max_shift_px: float = 1.5,
) -> Alignment:
    """Align templates to the frame near ``start`` (Lucas–Kanade for a translation, with gain and offset).

    Minimises Σ w (T̃(u) - g Ĩ(p + u))² over p, where T̃, Ĩ are the template and the
    patch minus their means and the gain g = ‖T̃‖ / ‖Ĩ‖ (so the fit ignores
    brightness and contrast, as NCC does), and w the robust, centre-weighted weights of
    ``_compare``.  Linearising the template gives the step

        d = H⁻¹ Σ w ∇T (T̃ - g Ĩ),   H = Σ w ∇T ∇Tᵀ,

    with the template's gradients (central differences on its inner pixels).  At the
    end, the position's covariance is σ² H⁻¹ with σ² = Σ w r² / (Σ w - 4)
    (translation, gain and offset fitted).  Runs the compiled kernel
    (:mod:`._align_kernel`); ``_align_numpy`` is its NumPy reference.

    Parameters
    ----------
    frame : the prepared frame.
    templates : (N, w, w) templates (w odd, at least 5), or an :class:`AnchorTemplates`.
    start : (N, 2) start positions (x, y).
    iterations : Gauss–Newton steps.
    max_shift_px : an alignment that ends farther than this from ``start`` keeps the start.

    Examples
    --------
    >>> rng = np.random.default_rng(3)
    >>> img = cv2.GaussianBlur(rng.uniform(0, 255, (40, 40)), (0, 0), 2.0)
    >>> f = prepare_differential_frame(img, 11)
    >>> a = align_templates(f, f.patches(np.array([[20.3, 19.6]])), np.array([[20.0, 20.0]]), iterations=4)
    >>> np.round(a.positions, 2), bool(a.ncc[0] > 0.999), bool(a.covariances[0, 0, 0] < 1e-3)
    (array([[20.3, 19.6]]), True, True)
    """
    bank = templates if isinstance(templates, AnchorTemplates) else AnchorTemplates(templates)
    start = np.ascontiguousarray(start, dtype=np.float64).reshape(-1, 2)
    return _ALIGN(frame, bank, start, int(iterations), float(max_shift_px))


def _align_compiled(frame: DifferentialFrame, bank: AnchorTemplates, start: np.ndarray, iterations: int, max_shift_px: float) -> Alignment:
    """The numba kernel (:mod:`._align_kernel`), track by track; same results as ``_align_numpy`` up to rounding."""
    from ._align_kernel import align_batch

    n, w = len(bank), bank.templates.shape[-1]
    padded = frame.padded_frame
    out = Alignment(np.empty((n, 2)), np.empty(n), np.empty((n, 2, 2)), np.empty(n), np.empty(n), np.empty(n, bool), np.empty((n, w, w), np.float32))
    align_batch(
        padded.padded, padded.pad, bank.templates, start, _centre_weights((w - 2) ** 2), iterations, max_shift_px,
        np.sqrt(_QUANTIZATION_VARIANCE), _QUANTIZATION_VARIANCE,
        out.positions, out.ncc, out.covariances, out.min_eigenvalue, out.residual_variance, out.converged, out.patches,
    )
    return out


def _align_numpy(frame: DifferentialFrame, bank: AnchorTemplates, start: np.ndarray, iterations: int, max_shift_px: float) -> Alignment:
    """The NumPy reference of the alignment: all templates at once, one array pass per operation."""
    w = bank.templates.shape[-1]
    terms = bank.terms
    patches = frame.patches(start, w)
    current = start.copy()
    for _ in range(iterations):
        current = current + _compare(terms, patches[:, 1:-1, 1:-1]).step
        patches = frame.patches(current, w)
    converged = np.linalg.norm(current - start, axis=1) <= max_shift_px
    if not converged.all():
        current[~converged] = start[~converged]
        patches = patches.copy()
        patches[~converged] = frame.patches(start[~converged], w)
    fit = _compare(terms, patches[:, 1:-1, 1:-1])
    return Alignment(current, fit.ncc, fit.covariance, terms.min_eigenvalue, fit.sigma_sq, converged, patches)


#: The alignment runs the compiled kernel; the NumPy reference is kept for the tests to compare.
_ALIGN = _align_compiled


@dataclass(frozen=True)
class DifferentialMeasurement:
    """What :func:`measure_differential` found for each of k tracks.

    Attributes
    ----------
    positions : (k, 2) measured positions (x, y); NaN where rejected.
    accepted : (k,) True where the measurement passed every check.
    noise_covariances : (k, 2, 2) measurement noise R (px²) for the Kalman update: the
        refinement's σ² H⁻¹, what it inherits, and a floor of (0.12 px)² per axis; NaN where rejected.
    rejection : (k,) int8 reason code, 0 where accepted (see :data:`REJECTION_NAMES`).
    anchored : (k,) True where the position is the anchor's alignment (drift-free).
    anchor_ncc : (k,) NCC of the anchor at the measured position (NaN if not computed).
    forward_backward_px : (k,) distance between the previous position and the flow
        back from the match (NaN for coasting tracks, failed flows, and tracks whose
        anchor matched very well, where it is not run).
    levels : (k,) pyramid levels used for the flow (-1 for coasting tracks, searched instead).
    patches : (k, w, w) the frame's patches at the measured positions (the next frame's
        ``previous_patches``); NaN where rejected.
    carried_covariances : (k, 2, 2) the part of ``noise_covariances`` that a later chained
        measurement (the next frame's ``previous_covariances``) or an anchor cut here
        (``anchor_covariances``) inherits: R without its model floor of (0.12 px)² per axis.
    keyframe_ok : (k,) True where a new anchor may be cut at the measurement: it is
        anchored, or chained cleanly (the previous frame's patch matches at NCC ≥
        ``clean_ncc`` and the flow back lands within ``clean_forward_backward_px``).
    """

    positions: np.ndarray
    accepted: np.ndarray
    noise_covariances: np.ndarray
    rejection: np.ndarray
    anchored: np.ndarray
    anchor_ncc: np.ndarray
    forward_backward_px: np.ndarray
    levels: np.ndarray
    patches: np.ndarray
    carried_covariances: np.ndarray
    keyframe_ok: np.ndarray


def _flow(
    source: np.ndarray, target: np.ndarray, points: np.ndarray, start: np.ndarray, window: int, levels: int
) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV pyramidal LK from ``points`` in ``source`` to ``target``, started at ``start``; (positions, converged)."""
    found, status, _ = cv2.calcOpticalFlowPyrLK(
        source,
        target,
        np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 1, 2),
        np.ascontiguousarray(start, dtype=np.float32).reshape(-1, 1, 2),
        winSize=(window, window),
        maxLevel=int(levels),
        criteria=_LK_CRITERIA,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    return found.reshape(-1, 2).astype(np.float64), status.reshape(-1) == 1


def _forward_backward(
    previous: DifferentialFrame, current: DifferentialFrame, p_prev: np.ndarray, z: np.ndarray, predicted: np.ndarray,
    window: int, max_level: int, capture_px: float, tolerance_px: float,
) -> np.ndarray:
    """Distance between the previous positions and the flow back from the matches (NaN where it fails).

    The flow back starts where the predicted motion says the match came from,
    z - (p⁻ - p), i.e. the innovation z - p⁻ away from p: if the match is right it has
    to travel that far (± the tolerance), which sets its pyramid depth.
    """
    error = np.full(len(z), np.nan)
    start = z - (predicted - p_prev)
    levels = pyramid_levels(np.linalg.norm(z - predicted, axis=1) + tolerance_px, max_level, capture_px)
    for level in np.unique(levels):
        rows = np.flatnonzero(levels == level)
        back, ok = _flow(current.grey, previous.grey, z[rows], start[rows], window, level)
        error[rows] = np.where(ok, np.linalg.norm(back - p_prev[rows], axis=1), np.nan)
    return error


def _inside(positions: np.ndarray, shape: tuple[int, int], margin: float) -> np.ndarray:
    """True where (x, y) lies at least ``margin`` px inside the pixel centres' range (negative: outside allowed)."""
    height, width = shape
    x, y = positions[:, 0], positions[:, 1]
    with np.errstate(invalid="ignore"):
        return (x >= margin) & (x <= width - 1 - margin) & (y >= margin) & (y <= height - 1 - margin)


def measure_differential(
    previous: DifferentialFrame,
    current: DifferentialFrame,
    previous_positions: np.ndarray,
    previous_patches: np.ndarray,
    predicted_positions: np.ndarray,
    predicted_covariances: np.ndarray,
    anchors: AnchorTemplates,
    *,
    coasting: np.ndarray | None = None,
    previous_covariances: np.ndarray | None = None,
    anchor_covariances: np.ndarray | None = None,
    max_innovation_px: np.ndarray | None = None,
    gate_radius: float = 2.4477,
    window: int = 11,
    max_level: int = 3,
    forward_backward_px: float = 1.0,
    min_ncc: float = 0.8,
    anchor_ncc: float = 0.97,
    trust_ratio: float = 3.0,
    reacquire_ncc: float = 0.9,
    anchor_agreement_px: float = 1.5,
    rescue_ncc: float = 0.7,
    clean_ncc: float = 0.9,
    clean_forward_backward_px: float = 0.25,
    min_eigenvalue: float = 0.1,
    capture_px: float = CAPTURE_PX,
    iterations: int = 2,
    fallback_noise: np.ndarray | None = None,
) -> DifferentialMeasurement:
    """Measure k tracks in ``current`` from their Kalman predictions (module docs).

    Parameters
    ----------
    previous, current : consecutive prepared frames (:func:`prepare_differential_frame`).
    previous_positions : (k, 2) positions (x, y) in ``previous`` (where the chain continues from).
    previous_patches : (k, w, w) patches of ``previous`` at those positions (the last
        call's ``patches``); the chain's appearance and noise are judged against them.
    predicted_positions : (k, 2) predicted positions p⁻ in ``current``.
    predicted_covariances : (k, 2, 2) predicted position covariances Σ⁻.
    anchors : the k anchor templates (w×w, w = ``current.window``).
    coasting : (k,) True for tracks not measured in ``previous``: their anchor is
        searched in the gate instead of followed by flow.
    previous_covariances : (k, 2, 2) noise of the previous measurement (default 0); a
        chained (not anchored) match adds its own to it, as its error is the previous
        one's plus the flow's.
    anchor_covariances : (k, 2, 2) uncertainty of where each anchor was cut (default 0:
        the anchor defines the point).
    max_innovation_px : (k,) largest plausible distance ‖z - p⁻‖ per track (from its
        recent innovations), or None; farther matches are refused, the flow's pyramid
        reaches no farther, and a coasting track's anchor is searched only within it.
    gate_radius : c of the gate (z - p⁻)ᵀ (Σ⁻)⁻¹ (z - p⁻) ≤ c².
    window : side of the flow's window (odd).
    max_level : deepest pyramid level the flow may use.
    forward_backward_px : largest distance between the flow back and the previous position.
    min_ncc : the anchor must match the patch at the measured position at least this well
        (appearance check: an occluder, a jump to another point, a vanishing marker).
    anchor_ncc : at or above this NCC the anchor's alignment is the measurement.
    trust_ratio : the anchor's alignment is also the measurement when its residual
        variance is at most this times the chain's (it explains the patch nearly as well
        as the previous frame does).
    reacquire_ncc : a coasting track is found again only where its anchor matches this well.
    anchor_agreement_px : the anchor's alignment must end this close to the flow's match.
    rescue_ncc : a chained match whose anchor matches at least this well (below
        ``min_ncc``) is still accepted when the chain is clean (a mild appearance change).
    clean_ncc, clean_forward_backward_px : a chained match is *clean* where the previous
        frame's patch matches it at this NCC or better and the flow back lands this close.
    min_eigenvalue : smallest structure-tensor eigenvalue per pixel (grey levels²/px²)
        of the template that locates the point.
    capture_px : displacement a single-level flow captures (sets the pyramid depth).
    iterations : Gauss–Newton steps of the anchor's and the chain's alignments.
    fallback_noise : (2, 2) noise R for a match whose own cannot be estimated (its
        template's structure tensor is singular, next to the image border); None
        refuses such matches (TEXTURELESS).

    Returns
    -------
    DifferentialMeasurement

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> world = cv2.GaussianBlur(rng.uniform(0, 255, (120, 160)), (0, 0), 2.0)
    >>> a = prepare_differential_frame(world[20:100, 20:140], 11)
    >>> b = prepare_differential_frame(world[20:100, 22:142], 11)   # the scene moves 2 px left
    >>> p = np.array([[60.0, 40.0]])
    >>> m = measure_differential(a, b, p, a.patches(p), p - [1.5, 0.0], np.eye(2)[None] * 4.0, AnchorTemplates(a.patches(p)))
    >>> np.round(m.positions, 2), m.accepted, m.anchored, m.rejection
    (array([[58., 40.]]), array([ True]), array([ True]), array([0], dtype=int8))
    """
    if previous.shape != current.shape:
        raise InvalidInputError(f"previous and current frames differ in size: {previous.shape} vs {current.shape}")
    p_prev = np.asarray(previous_positions, dtype=np.float64).reshape(-1, 2)
    predicted = np.asarray(predicted_positions, dtype=np.float64).reshape(-1, 2)
    sigma = np.asarray(predicted_covariances, dtype=np.float64).reshape(-1, 2, 2)
    k = len(p_prev)
    w = current.window
    if predicted.shape[0] != k or sigma.shape[0] != k or anchors.templates.shape != (k, w, w) or previous_patches.shape != (k, w, w):
        raise InvalidInputError(
            f"measure_differential needs one row per track and {w}×{w} patches; got {k} previous positions, "
            f"{predicted.shape[0]} predictions, {sigma.shape[0]} covariances, anchors {anchors.templates.shape}, patches {previous_patches.shape}"
        )
    coasting = np.zeros(k, bool) if coasting is None else np.asarray(coasting, bool)
    zero = np.zeros((k, 2, 2))
    previous_cov = zero if previous_covariances is None else np.asarray(previous_covariances, dtype=np.float64)
    anchor_cov = zero if anchor_covariances is None else np.asarray(anchor_covariances, dtype=np.float64)
    limit = None if max_innovation_px is None else np.asarray(max_innovation_px, dtype=np.float64).reshape(k)

    rejection = np.full(k, ACCEPTED, np.int8)
    z = np.full((k, 2), np.nan)
    fb_error = np.full(k, np.nan)
    levels_used = np.full(k, -1, np.int64)
    searchable = _inside(predicted, current.shape, -0.5) & np.isfinite(sigma).all(axis=(1, 2))
    rejection[~searchable] = OUTSIDE
    # The gate ellipse reaches c·√λmax(Σ⁻) from the prediction; matches beyond the plausible
    # radius are refused anyway, so the search reaches no farther than that either.
    a, b, d = sigma[:, 0, 0], sigma[:, 0, 1], sigma[:, 1, 1]
    lambda_max = 0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b)
    reach = gate_radius * np.sqrt(np.maximum(lambda_max, 0.0))
    if limit is not None:
        reach = np.minimum(reach, limit)

    # 1. Flow from the prediction, one OpenCV call per pyramid depth.
    followed = searchable & ~coasting & _inside(p_prev, current.shape, -0.5)
    levels = pyramid_levels(reach, max_level, capture_px)
    for level in np.unique(levels[followed]):
        rows = np.flatnonzero(followed & (levels == level))
        z[rows], ok = _flow(previous.grey, current.grey, p_prev[rows], predicted[rows], window, level)
        levels_used[rows] = level
        rejection[rows[~ok]] = NOT_FOUND

    # Coasting tracks: search the anchor in the gate, shrunk to the plausible radius.  SSD
    # needs only the frame's window sums of I²; the alignment below checks the NCC.
    searched = np.flatnonzero(searchable & coasting)
    if len(searched):
        search_sigma = sigma[searched] * np.minimum(1.0, (reach[searched] / np.maximum(gate_radius * np.sqrt(lambda_max[searched]), 1e-12)) ** 2)[:, None, None]
        match = match_templates(current.prepared, anchors.templates[searched], predicted[searched], search_sigma, gate_radius, "ssd", current.search_radius)
        z[searched] = match.positions
        rejection[searched[~match.searched]] = NOT_FOUND

    # 3-5. Chain and anchor: appearance, which of the two measures, and the noise.
    anchored = np.zeros(k, bool)
    keyframe_ok = np.zeros(k, bool)
    ncc = np.full(k, np.nan)
    noise = np.full((k, 2, 2), np.nan)
    patches_out = np.full((k, w, w), np.nan, np.float32)
    standing = np.flatnonzero(rejection == ACCEPTED)
    if len(standing):
        flowed = followed[standing]
        bank = anchors if len(standing) == k else anchors.take(standing)
        alignment = align_templates(current, bank, z[standing], iterations, anchor_agreement_px)
        ncc[standing] = alignment.ncc
        # Near the border the anchor's window reaches into the replicated edge: there the chain measures.
        away_from_border = _inside(alignment.positions, current.shape, w // 2 + 1)
        very_good = alignment.converged & (alignment.ncc >= anchor_ncc) & away_from_border
        # 2. Forward–backward check where the anchor does not settle the match on its own (a
        # first appearance that matches very well where the flow ended is the point itself).
        checked = standing[flowed & ~very_good]
        fb_error[checked] = _forward_backward(previous, current, p_prev[checked], z[checked], predicted[checked], window, max_level, capture_px, forward_backward_px)
        rejection[checked[~(fb_error[checked] <= forward_backward_px)]] = FORWARD_BACKWARD
        live = rejection[standing] == ACCEPTED
        # The chain, where the anchor alone does not settle it: the previous frame's patch
        # against the flow's match (the flow reports neither its residual nor its appearance).
        # It is aligned from the match by the same robust, centre-weighted step as the anchor:
        # OpenCV's flow weighs every pixel of its window alike, so background moving behind a
        # corner drags it (the scene over 20 seeds: median RMS 0.328 → 0.255 px).
        chain_positions, chain_patches = z[standing].copy(), alignment.patches.copy()
        chain_variance = np.full(len(standing), np.nan)
        chain_cov = np.full((len(standing), 2, 2), np.nan)
        chain_eigenvalue = np.full(len(standing), np.nan)
        chain_ncc = np.full(len(standing), np.nan)
        judged = flowed & ~very_good & live
        if judged.any():
            chain = align_templates(current, previous_patches[standing[judged]], z[standing[judged]], iterations, anchor_agreement_px)
            chain_positions[judged], chain_patches[judged] = chain.positions, chain.patches
            chain_variance[judged], chain_cov[judged] = chain.residual_variance, chain.covariances
            chain_eigenvalue[judged], chain_ncc[judged] = chain.min_eigenvalue, chain.ncc
        # The anchor measures where it matches very well, or explains the patch nearly as well
        # as the previous frame does; a coasting track (no chain) only at reacquire_ncc.
        as_good = alignment.residual_variance <= trust_ratio * chain_variance
        trusted = alignment.converged & (alignment.ncc >= min_ncc) & np.where(
            flowed, (very_good | as_good) & away_from_border, alignment.ncc >= reacquire_ncc
        )
        anchored[standing] = trusted
        z[standing] = np.where(trusted[:, None], alignment.positions, chain_positions)
        patches_out[standing] = np.where(trusted[:, None, None], alignment.patches, chain_patches)
        # Appearance: the anchor must match (an occluder, a jump to another point), but for a
        # mild change (a car that comes closer, a cyclist's legs) that the chain follows
        # cleanly: the previous frame's patch matches well and the flow back is tight.
        clean_chain = flowed & (chain_ncc >= clean_ncc) & (fb_error[standing] <= clean_forward_backward_px)
        mild = (alignment.ncc >= rescue_ncc) & clean_chain & ~trusted
        rejection[standing[live & ~(alignment.ncc >= min_ncc) & ~mild]] = APPEARANCE
        # A keyframe may be cut only where the measurement is itself clean: anchored, or chained cleanly.
        keyframe_ok[standing] = trusted | clean_chain
        rejection[standing[live & ~flowed & ~trusted]] = NOT_FOUND
        eigenvalue = np.where(trusted | ~flowed, alignment.min_eigenvalue, chain_eigenvalue)
        # (Near the border the padded window's gradients say nothing; OpenCV's own eigenvalue test applies there.)
        rejection[standing[live & ~(eigenvalue >= min_eigenvalue) & away_from_border]] = TEXTURELESS
        # Noise: the refinement's own covariance, plus where the anchor was cut (anchored)
        # or the previous measurement's (chained: its error carries over).
        noise[standing] = np.where(
            (trusted | ~flowed)[:, None, None], alignment.covariances + anchor_cov[standing], chain_cov + previous_cov[standing]
        )

    unknown_noise = (rejection == ACCEPTED) & ~np.isfinite(noise).all(axis=(1, 2))
    if fallback_noise is None:
        rejection[unknown_noise] = TEXTURELESS
    else:
        noise[unknown_noise] = fallback_noise

    # Gate and plausibility; the match must lie in the image.
    standing_mask = rejection == ACCEPTED
    offset = z - predicted
    with np.errstate(invalid="ignore", divide="ignore"):
        # dᵀ Σ⁻¹ d for 2×2 Σ = [[a, b], [b, d]]: (d dx² - 2 b dx dy + a dy²) / (a d - b²)
        dx, dy = offset[:, 0], offset[:, 1]
        mahalanobis_sq = (d * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * d - b * b)
    rejection[standing_mask & ~(mahalanobis_sq <= gate_radius**2)] = GATE
    if limit is not None:
        rejection[(rejection == ACCEPTED) & ~(np.linalg.norm(offset, axis=1) <= limit)] = IMPLAUSIBLE
    # The point itself must lie in the image (a point whose window leaves the image is still
    # measured while the appearance check passes on the part that remains).
    rejection[(rejection == ACCEPTED) & ~_inside(z, current.shape, 0.0)] = OUTSIDE

    accepted = rejection == ACCEPTED
    z[~accepted] = np.nan
    noise[~accepted] = np.nan
    patches_out[~accepted] = np.nan
    anchored &= accepted
    keyframe_ok &= accepted
    return DifferentialMeasurement(
        z, accepted, noise + np.eye(2) * _MODEL_NOISE_PX**2, rejection, anchored, ncc, fb_error, levels_used, patches_out, noise, keyframe_ok
    )
