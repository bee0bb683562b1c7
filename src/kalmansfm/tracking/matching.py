"""Gated template search: SSD or NCC of square templates inside Kalman gate ellipses.

Everything here works on all tracks at once.  One frame is prepared once
(:func:`prepare_frame`: a float copy, padded, plus box-filtered sums of the
intensities and of their squares); the templates are then compared with every
candidate position in a square box around each predicted position, by one
batched FFT cross-correlation, and candidates outside the gate ellipse

    (p - p⁻)ᵀ (Σ⁻_pos)⁻¹ (p - p⁻) ≤ c²

or too close to the image border for a full window are excluded.  The best
candidate is refined to sub-pixel precision by a least-squares quadratic fit of
its 3×3 score neighbourhood.

Coordinates: x = column, y = row, pixel centres at integer coordinates.  The
conversion to (row, column) indexing happens in :func:`_gather_windows` only.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft
from numpy.lib.stride_tricks import sliding_window_view
from scipy.stats import chi2

from ..errors import InvalidInputError

__all__ = [
    "MatchResult",
    "PreparedFrame",
    "gate_mask",
    "gate_radius_for_probability",
    "match_templates",
    "prepare_frame",
    "refine_translation",
    "sample_patches",
    "subpixel_peak",
]

SCORES = ("ssd", "ncc")


def gate_radius_for_probability(probability: float) -> float:
    """Gate radius c such that a 2D Gaussian point falls in the gate with ``probability``.

    c² is the ``probability`` quantile of the chi-square distribution with 2
    degrees of freedom, because (p - p⁻)ᵀ Σ⁻¹ (p - p⁻) of a 2D Gaussian is χ²₂.

    Examples
    --------
    >>> round(gate_radius_for_probability(0.95), 4)   # c² = 5.9915
    2.4477
    """
    if not 0.0 < probability < 1.0:
        raise InvalidInputError(f"gate probability must be in (0, 1); got {probability}")
    return float(np.sqrt(chi2.ppf(probability, df=2)))


@dataclass(frozen=True)
class PreparedFrame:
    """One grey frame made ready for many template searches.

    Attributes
    ----------
    image : (H, W) float64 frame.
    padded : the frame with ``pad`` zero pixels on every side.
    window_sum, window_sum_sq : padded box sums of I and I² over ``window``×``window``
        windows centred on each pixel.
    window : template side length (odd).
    pad : padding width in pixels.
    """

    image: np.ndarray
    padded: np.ndarray
    window_sum: np.ndarray
    window_sum_sq: np.ndarray
    window: int
    pad: int

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the frame."""
        return self.image.shape  # type: ignore[return-value]


def prepare_frame(image: np.ndarray, window: int, max_search_radius: int) -> PreparedFrame:
    """Pad a grey frame and precompute its window sums (one call per frame).

    Examples
    --------
    >>> f = prepare_frame(np.ones((20, 30)), window=5, max_search_radius=4)
    >>> f.padded.shape, float(f.window_sum[f.pad + 10, f.pad + 10])
    ((36, 46), 25.0)
    """
    image = np.asarray(image, dtype=np.float64)
    pad = int(max_search_radius) + window // 2 + 2
    padded = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_CONSTANT, value=0.0)
    # Unnormalised box filter: sum over the window centred on each pixel.
    window_sum = cv2.boxFilter(padded, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)
    window_sum_sq = cv2.boxFilter(
        padded * padded, -1, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT
    )
    return PreparedFrame(image, padded, window_sum, window_sum_sq, window, pad)


def sample_patches(image: np.ndarray, centers: np.ndarray, size: int) -> np.ndarray:
    """Bilinearly sampled ``size``×``size`` patches centred at sub-pixel ``centers``.

    Parameters
    ----------
    image : (H, W) grey image.
    centers : (N, 2) float (x, y) centres.
    size : odd side length.

    Returns
    -------
    (N, size, size) float64 patches; pixels outside the image repeat the border.

    Examples
    --------
    >>> img = np.arange(25.0).reshape(5, 5)
    >>> sample_patches(img, np.array([[2.5, 2.0]]), 3)[0]
    array([[ 6.5,  7.5,  8.5],
           [11.5, 12.5, 13.5],
           [16.5, 17.5, 18.5]])
    """
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    n = centers.shape[0]
    if n == 0:
        return np.zeros((0, size, size))
    half = size // 2
    offsets = np.arange(-half, half + 1, dtype=np.float64)
    # One remap call for all patches stacked vertically: map rows are (patch, dy), columns dx.
    map_x = (centers[:, 0, None, None] + offsets[None, None, :]) * np.ones((1, size, 1))
    map_y = (centers[:, 1, None, None] + offsets[None, :, None]) * np.ones((1, 1, size))
    out = cv2.remap(
        np.asarray(image, dtype=np.float32),
        map_x.reshape(n * size, size).astype(np.float32),
        map_y.reshape(n * size, size).astype(np.float32),
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(n, size, size).astype(np.float64)


def _gather_windows(array: np.ndarray, top_left_rc: np.ndarray, size: int) -> np.ndarray:
    """(N, size, size) copies of ``array[r:r+size, c:c+size]`` for each (r, c) row of ``top_left_rc``."""
    windows = sliding_window_view(array, (size, size))
    return windows[top_left_rc[:, 0], top_left_rc[:, 1]]


def gate_mask(offsets: np.ndarray, inverse_covariances: np.ndarray, radius: float) -> np.ndarray:
    """True where the offset d = p - p⁻ lies in the gate dᵀ Σ⁻¹ d ≤ c².

    Parameters
    ----------
    offsets : (N, ..., 2) offsets (dx, dy) from each track's predicted position.
    inverse_covariances : (N, 2, 2) inverses of the predicted position covariances.
    radius : c.

    Examples
    --------
    >>> inv = np.linalg.inv(np.array([[[4.0, 0.0], [0.0, 1.0]]]))   # σx = 2, σy = 1
    >>> gate_mask(np.array([[[3.9, 0.0], [0.0, 2.1], [4.1, 0.0]]]), inv, 2.0)
    array([[ True, False, False]])
    """
    d = np.asarray(offsets, dtype=np.float64)
    n = d.shape[0]
    flat = d.reshape(n, -1, 2)
    mahalanobis_sq = np.einsum("npi,nij,npj->np", flat, inverse_covariances, flat)
    return (mahalanobis_sq <= radius * radius).reshape(d.shape[:-1])


# Least-squares fit of f = a + b x + c y + d x² + e x y + g y² on the 3×3 grid.
_GRID_X, _GRID_Y = np.meshgrid([-1.0, 0.0, 1.0], [-1.0, 0.0, 1.0])
_QUADRATIC_DESIGN = np.stack(
    [np.ones(9), _GRID_X.ravel(), _GRID_Y.ravel(), _GRID_X.ravel() ** 2, (_GRID_X * _GRID_Y).ravel(), _GRID_Y.ravel() ** 2],
    axis=1,
)
_QUADRATIC_FIT = np.linalg.pinv(_QUADRATIC_DESIGN)  # (6, 9)


def subpixel_peak(neighbourhoods: np.ndarray) -> np.ndarray:
    """Sub-pixel offsets (dx, dy) of the minimum of 3×3 cost neighbourhoods.

    A 2D quadratic is fitted by least squares to each 3×3 block and its
    stationary point taken.  Where the fit is not a proper minimum (Hessian not
    positive definite) or lands more than one pixel away, separate 1D parabolas
    through the centre row and column are used; offsets are clipped to ±0.5 px.

    Parameters
    ----------
    neighbourhoods : (N, 3, 3) costs (lower is better), centre = best integer candidate.

    Returns
    -------
    (N, 2) offsets (dx, dy) to add to the integer position.

    Examples
    --------
    >>> y, x = np.mgrid[-1:2, -1:2]
    >>> cost = (x - 0.3) ** 2 + 2 * (y + 0.2) ** 2
    >>> np.round(subpixel_peak(cost[None].astype(float)), 6)
    array([[ 0.3, -0.2]])
    """
    v = np.asarray(neighbourhoods, dtype=np.float64).reshape(-1, 9)
    a, b, c, d, e, g = (v @ _QUADRATIC_FIT.T).T
    # Stationary point of the quadratic: [2d e; e 2g] [dx dy]ᵀ = -[b c]ᵀ.
    det = 4.0 * d * g - e * e
    ok = (d > 0) & (det > 0)
    safe_det = np.where(ok, det, 1.0)
    dx = np.where(ok, (-2.0 * g * b + e * c) / safe_det, np.nan)
    dy = np.where(ok, (-2.0 * d * c + e * b) / safe_det, np.nan)
    far = ~(np.abs(dx) <= 1.0) | ~(np.abs(dy) <= 1.0)
    # 1D parabola through three samples: offset = (f₋ - f₊) / (2 (f₋ - 2 f₀ + f₊)).
    grid = v.reshape(-1, 3, 3)
    row, col = grid[:, 1, :], grid[:, :, 1]
    curv_x = row[:, 0] - 2 * row[:, 1] + row[:, 2]
    curv_y = col[:, 0] - 2 * col[:, 1] + col[:, 2]
    px = np.where(curv_x > 0, (row[:, 0] - row[:, 2]) / (2 * np.where(curv_x > 0, curv_x, 1.0)), 0.0)
    py = np.where(curv_y > 0, (col[:, 0] - col[:, 2]) / (2 * np.where(curv_y > 0, curv_y, 1.0)), 0.0)
    dx = np.where(far, px, dx)
    dy = np.where(far, py, dy)
    return np.clip(np.stack([dx, dy], axis=1), -0.5, 0.5)


@dataclass(frozen=True)
class MatchResult:
    """Result of one gated search for N templates.

    Attributes
    ----------
    positions : (N, 2) refined best match (x, y); NaN where nothing could be searched.
    scores : (N,) score of the best integer candidate: SSD (lower is better) or NCC
        (higher is better); NaN where nothing could be searched.
    dissimilarity : (N,) score made comparable across templates: SSD divided by
        the template's own zero-mean energy Σ(T - T̄)², or 1 - NCC; 0 is perfect.
    searched : (N,) True where at least one candidate lay in the gate and the image.
    """

    positions: np.ndarray
    scores: np.ndarray
    dissimilarity: np.ndarray
    searched: np.ndarray


def _template_spectra(templates: np.ndarray, fft_size: int, score: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Conjugate spectra of the templates (zero-mean for NCC), their energy terms."""
    n_pixels = templates.shape[-1] * templates.shape[-2]
    mean = templates.mean(axis=(1, 2), keepdims=True)
    centred = templates - mean
    zero_mean_energy = np.einsum("nij,nij->n", centred, centred)
    used = centred if score == "ncc" else templates
    spectra = np.conj(scipy.fft.rfft2(used.astype(np.float32), s=(fft_size, fft_size)))
    raw_energy = np.einsum("nij,nij->n", templates, templates)
    del n_pixels
    return spectra, raw_energy, zero_mean_energy


def match_templates(
    frame: PreparedFrame,
    templates: np.ndarray,
    predicted: np.ndarray,
    position_covariances: np.ndarray,
    gate_radius: float,
    score: str = "ssd",
    max_search_radius: int | None = None,
) -> MatchResult:
    """Find each template inside its gate ellipse around the predicted position.

    Parameters
    ----------
    frame : the prepared frame (:func:`prepare_frame`), same ``window`` as the templates.
    templates : (N, w, w) templates, w = ``frame.window``.
    predicted : (N, 2) predicted positions p⁻ (x, y).
    position_covariances : (N, 2, 2) predicted position covariances Σ⁻_pos.
    gate_radius : c; candidates with (p - p⁻)ᵀ (Σ⁻_pos)⁻¹ (p - p⁻) > c² are ignored.
    score : ``"ssd"`` (sum of squared differences) or ``"ncc"`` (normalised cross-correlation).
    max_search_radius : cap on the half-size of the search box in pixels
        (default: the frame's padding allows).

    Returns
    -------
    MatchResult

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> img = cv2.GaussianBlur(rng.uniform(0, 255, (60, 80)), (0, 0), 1.5)
    >>> tmpl = sample_patches(img, np.array([[40.0, 30.0]]), 11)
    >>> f = prepare_frame(img, 11, 10)
    >>> m = match_templates(f, tmpl, np.array([[37.0, 32.0]]), np.eye(2)[None] * 9.0, 2.45)
    >>> np.round(m.positions, 3)
    array([[40., 30.]])
    """
    if score not in SCORES:
        raise InvalidInputError(f"score must be one of {SCORES}; got {score!r}")
    predicted = np.asarray(predicted, dtype=np.float64).reshape(-1, 2)
    n = predicted.shape[0]
    w = frame.window
    half_w = w // 2
    height, width = frame.shape
    positions = np.full((n, 2), np.nan)
    scores = np.full(n, np.nan)
    dissimilarity = np.full(n, np.nan)
    searched = np.zeros(n, dtype=bool)
    limit = frame.pad - half_w - 2 if max_search_radius is None else min(max_search_radius, frame.pad - half_w - 2)

    centre = np.round(predicted)
    # Tracks whose prediction is not finite or lies off the image cannot be searched.
    inside = np.isfinite(predicted).all(axis=1)
    inside[inside] = (
        (centre[inside, 0] >= 0) & (centre[inside, 0] <= width - 1) & (centre[inside, 1] >= 0) & (centre[inside, 1] <= height - 1)
    )
    if not inside.any():
        return MatchResult(positions, scores, dissimilarity, searched)
    cov = np.asarray(position_covariances, dtype=np.float64)
    std = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))
    # Half-size of the box that holds the ellipse, rounded up to an even number to
    # make few distinct sizes; each size is one batched computation.
    needed = np.ceil(gate_radius * std.max(axis=1) / 2.0) * 2.0
    needed = np.clip(np.nan_to_num(needed, nan=limit), 1, limit).astype(int)
    inverse = np.linalg.inv(np.where(inside[:, None, None], cov, np.eye(2)))
    for radius in np.unique(needed[inside]):
        rows = np.flatnonzero(inside & (needed == radius))
        _search_group(
            frame, templates[rows], predicted[rows], centre[rows], inverse[rows], gate_radius, score, int(radius),
            rows, positions, scores, dissimilarity, searched,
        )
    return MatchResult(positions, scores, dissimilarity, searched)


def _search_group(
    frame: PreparedFrame,
    templates: np.ndarray,
    predicted: np.ndarray,
    centre: np.ndarray,
    inverse: np.ndarray,
    gate_radius: float,
    score: str,
    radius: int,
    rows: np.ndarray,
    positions: np.ndarray,
    scores: np.ndarray,
    dissimilarity: np.ndarray,
    searched: np.ndarray,
) -> None:
    """Search one group of tracks that share the box half-size ``radius``; fill the outputs at ``rows``."""
    w = frame.window
    half_w = w // 2
    height, width = frame.shape
    side = 2 * radius + 1  # candidates per axis
    span = side + w - 1  # pixels per axis of the search patch
    n_pixels = float(w * w)
    centre_int = centre.astype(np.intp)
    # Top-left pixel of each search patch in padded (row, column) coordinates.
    top_left = np.stack([centre_int[:, 1], centre_int[:, 0]], axis=1) - radius - half_w + frame.pad
    patches = _gather_windows(frame.padded, top_left, span)
    # Box sums at the candidate centres.
    cand_top_left = top_left + half_w
    sum_i = _gather_windows(frame.window_sum, cand_top_left, side)
    sum_i2 = _gather_windows(frame.window_sum_sq, cand_top_left, side)

    fft_size = scipy.fft.next_fast_len(span, real=True)
    spectra, raw_energy, zero_mean_energy = _template_spectra(templates, fft_size, score)
    # Cross-correlation C(u) = Σ_i A(u + i) T(i) via FFT: C = F⁻¹[F(A) · conj F(T)],
    # in single precision (twice as fast; the error is far below the score thresholds).
    spectrum = scipy.fft.rfft2(patches.astype(np.float32), s=(fft_size, fft_size))
    spectrum *= spectra
    correlation = scipy.fft.irfft2(spectrum, s=(fft_size, fft_size))[:, :side, :side].astype(np.float64)
    if score == "ssd":
        # SSD(u) = Σ I² - 2 Σ I T + Σ T²
        cost = sum_i2 - 2.0 * correlation + raw_energy[:, None, None]
        cost = np.maximum(cost, 0.0)
    else:
        # NCC(u) = Σ I (T - T̄) / (‖T - T̄‖ √(Σ I² - (Σ I)² / n)); the cost is -NCC.
        image_energy = sum_i2 - sum_i * sum_i / n_pixels
        template_norm = np.sqrt(np.maximum(zero_mean_energy, 1e-12))
        # A flat window (std below 0.5 grey level) has no defined NCC: score it 0.
        textured = image_energy > 0.25 * n_pixels
        cost = np.where(
            textured, -correlation / (template_norm[:, None, None] * np.sqrt(np.where(textured, image_energy, 1.0))), 0.0
        )

    grid = np.arange(-radius, radius + 1, dtype=np.float64)
    cand_x = centre[:, 0, None, None] + grid[None, None, :]  # (n, 1, side)
    cand_y = centre[:, 1, None, None] + grid[None, :, None]  # (n, side, 1)
    dx = cand_x - predicted[:, 0, None, None]
    dy = cand_y - predicted[:, 1, None, None]
    # Gate: dᵀ Σ⁻¹ d = a dx² + 2 b dx dy + c dy² ≤ c², written out to stay a broadcast.
    a, b, c = inverse[:, 0, 0, None, None], inverse[:, 0, 1, None, None], inverse[:, 1, 1, None, None]
    allowed = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy <= gate_radius * gate_radius
    # Clip the ellipse to the image: the whole window must lie inside the frame.
    allowed &= (cand_x >= half_w) & (cand_x <= width - 1 - half_w) & (cand_y >= half_w) & (cand_y <= height - 1 - half_w)
    any_allowed = allowed.reshape(len(rows), -1).any(axis=1)
    masked = np.where(allowed, cost, np.inf).reshape(len(rows), -1)
    best = np.argmin(masked, axis=1)
    by, bx = np.divmod(best, side)
    # 3×3 neighbourhood of the best candidate (edges: repeat the centre so that axis is not refined).
    ny = np.clip(by[:, None] + np.array([-1, 0, 1]), 0, side - 1)
    nx = np.clip(bx[:, None] + np.array([-1, 0, 1]), 0, side - 1)
    k = np.arange(len(rows))[:, None, None]
    neighbourhood = cost[k, ny[:, :, None], nx[:, None, :]]
    at_edge_x = (bx == 0) | (bx == side - 1)
    at_edge_y = (by == 0) | (by == side - 1)
    refine = subpixel_peak(neighbourhood)
    refine[at_edge_x, 0] = 0.0
    refine[at_edge_y, 1] = 0.0
    best_cost = cost[np.arange(len(rows)), by, bx]

    ok = any_allowed
    pos = np.stack([centre[:, 0] + bx - radius, centre[:, 1] + by - radius], axis=1) + refine
    positions[rows[ok]] = pos[ok]
    if score == "ssd":
        scores[rows[ok]] = best_cost[ok]
        dissimilarity[rows[ok]] = best_cost[ok] / np.maximum(zero_mean_energy[ok], 1e-12)
    else:
        scores[rows[ok]] = -best_cost[ok]
        dissimilarity[rows[ok]] = 1.0 + best_cost[ok]
    searched[rows[ok]] = True


def refine_translation(
    image: np.ndarray,
    templates: np.ndarray,
    positions: np.ndarray,
    iterations: int = 3,
    max_step_px: float = 1.0,
) -> np.ndarray:
    """Sub-pixel Gauss–Newton refinement of template positions (Lucas–Kanade for a translation).

    Each template T is aligned with the image I around its position p by
    minimising Σ (T(u) - g·(I(p + u) - Ī) - T̄)² over the translation, with the
    gain g and the means Ī, T̄ taken per patch (so the step is insensitive to
    brightness and contrast changes, as NCC is).  Linearising the template,
    T(u - d) ≈ T(u) - ∇T(u)·d, gives the step

        d = (Σ ∇T ∇Tᵀ)⁻¹ Σ ∇T (T - g·(I - Ī) - T̄)

    which needs the template gradients only once.  All N patches are sampled
    bilinearly in one call per iteration.  Steps larger than ``max_step_px`` in
    total are undone (the refinement keeps the start position).

    Parameters
    ----------
    image : (H, W) grey frame.
    templates : (N, w, w) templates (w odd).
    positions : (N, 2) start positions (x, y), e.g. the best integer match.

    Returns
    -------
    (N, 2) refined positions.

    Examples
    --------
    >>> rng = np.random.default_rng(3)
    >>> img = cv2.GaussianBlur(rng.uniform(0, 255, (40, 40)), (0, 0), 2.0)
    >>> tmpl = sample_patches(img, np.array([[20.3, 19.6]]), 11)
    >>> np.round(refine_translation(img, tmpl, np.array([[20.0, 20.0]]), iterations=5), 2)
    array([[20.3, 19.6]])
    """
    positions = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    n, w = templates.shape[0], templates.shape[-1]
    if n == 0:
        return positions.copy()
    gy, gx = np.gradient(np.asarray(templates, dtype=np.float64), axis=(1, 2))
    # Drop the outer ring where np.gradient is one-sided.
    inner = (slice(None), slice(1, w - 1), slice(1, w - 1))
    gx, gy, t_in = gx[inner], gy[inner], templates[inner]
    t_in = t_in - t_in.mean(axis=(1, 2), keepdims=True)
    hessian = np.stack(
        [np.einsum("nij,nij->n", gx, gx), np.einsum("nij,nij->n", gx, gy), np.einsum("nij,nij->n", gx, gy), np.einsum("nij,nij->n", gy, gy)],
        axis=1,
    ).reshape(n, 2, 2)
    det = hessian[:, 0, 0] * hessian[:, 1, 1] - hessian[:, 0, 1] ** 2
    well_posed = det > 1e-9 * np.maximum(hessian[:, 0, 0] + hessian[:, 1, 1], 1e-12) ** 2
    inv_h = np.linalg.inv(np.where(well_posed[:, None, None], hessian, np.eye(2)))
    t_norm = np.sqrt(np.einsum("nij,nij->n", t_in, t_in))
    current = positions.copy()
    for _ in range(iterations):
        patch = sample_patches(image, current, w)[inner]
        patch = patch - patch.mean(axis=(1, 2), keepdims=True)
        p_norm = np.sqrt(np.einsum("nij,nij->n", patch, patch))
        gain = np.where(p_norm > 1e-9, t_norm / np.maximum(p_norm, 1e-9), 1.0)
        residual = t_in - gain[:, None, None] * patch
        b = np.stack([np.einsum("nij,nij->n", gx, residual), np.einsum("nij,nij->n", gy, residual)], axis=1)
        step = np.einsum("nij,nj->ni", inv_h, b)
        current = current + np.where(well_posed[:, None], step, 0.0)
    moved = np.linalg.norm(current - positions, axis=1)
    bad = ~(moved <= max_step_px)
    current[bad] = positions[bad]
    return current
