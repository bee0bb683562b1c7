"""Frames made ready for the differential matcher, the tracks' anchor templates, and their alignment.

:func:`align_templates` aligns templates to a frame near given positions by robust,
centre-weighted Gauss–Newton steps (translation, gain and offset), one compiled pass per
template (:mod:`._align_kernel`); :func:`~kalmansfm.tracking.differential.measure_differential`
aligns each track's anchor and its previous patch with it.  The NumPy reference of the
kernel, which the tests compare it with, is ``tests/reference/alignment.py``.

Coordinates: x = column, y = row, pixel centres at integer coordinates.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from .matching import PreparedFrame, prepare_frame, sample_patches

__all__ = ["Alignment", "AnchorTemplates", "DifferentialFrame", "align_templates", "prepare_differential_frame"]

# Floor of the residual variance σ² (grey levels²): two 8-bit patches, each rounded with
# variance 1/12, never agree better than this, and R = σ² H⁻¹ must stay positive definite.
_QUANTIZATION_VARIANCE = 2.0 / 12.0
# Gaussian weight (px) on the alignment's pixels around the point: the window's rim, where
# background behind a corner moves differently, counts less (cmu_house 0.911 → 0.929 within
# 3 px, the scene 0.38 → 0.32 px RMS; docs/tracking.md).
_CENTRE_SIGMA_PX = 3.0


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


@functools.lru_cache(maxsize=8)
def _centre_weights(n_pixels: int) -> np.ndarray:
    """Flattened Gaussian of σ = ``_CENTRE_SIGMA_PX`` over a square patch of ``n_pixels`` pixels."""
    side = int(round(np.sqrt(n_pixels)))
    g = np.exp(-0.5 * ((np.arange(side) - side // 2) / _CENTRE_SIGMA_PX) ** 2).astype(np.float32)
    return np.outer(g, g).ravel()


class AnchorTemplates:
    """The tracks' anchor templates, one row per track (kept by the tracker between frames).

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
    (:mod:`._align_kernel`); its NumPy reference is ``tests/reference/alignment.py``.

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
    return _align_compiled(frame, bank, start, int(iterations), float(max_shift_px))


def _align_compiled(frame: DifferentialFrame, bank: AnchorTemplates, start: np.ndarray, iterations: int, max_shift_px: float) -> Alignment:
    """The numba kernel (:mod:`._align_kernel`), track by track; same results as its NumPy reference up to rounding."""
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
