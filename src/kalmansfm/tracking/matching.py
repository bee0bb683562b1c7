"""Gated template search: SSD or NCC of square templates inside Kalman gate ellipses.

Everything here works on all tracks at once.  One frame is prepared once
(:func:`prepare_frame`: a float32 copy padded by repeating its border, plus the
box-filtered sums of its squares); the templates are then compared with every
candidate position in the smallest square box that holds each gate ellipse

    (p - p⁻)ᵀ (Σ⁻_pos)⁻¹ (p - p⁻) ≤ c²,

by one batched FFT cross-correlation per box size, and candidates outside the
ellipse or too close to the image border for a full window are excluded.  The
best candidate is refined to sub-pixel precision by a least-squares quadratic fit
of its 3×3 score neighbourhood (and, in the tracker, by :func:`refine_translation`).

Coordinates: x = column, y = row, pixel centres at integer coordinates.  Arrays
are indexed (row, column) only where windows are gathered (:func:`_gather_windows`
and the top-left corners computed just before it).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
import scipy.fft
from numpy.lib.stride_tricks import sliding_window_view

from ..errors import InvalidInputError
from .settings import SCORES

__all__ = [
    "MatchResult",
    "PreparedFrame",
    "match_templates",
    "prepare_frame",
    "refine_translation",
    "TemplateSpectra",
    "sample_patches",
    "subpixel_peak",
    "well_posed_2x2",
]

#: A 2×2 symmetric matrix is well posed (safely invertible) when det > WELL_POSED_RATIO · trace².
WELL_POSED_RATIO = 1e-9


def well_posed_2x2(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The determinant of [[a, b], [b, c]] and whether it is well posed: det > 1e-9 · max(trace, 1e-12)².

    The one conditioning test of the matchers' 2×2 normal matrices (Σ ∇T ∇Tᵀ): the ratio of
    the eigenvalues must exceed about 1e-9.  Elementwise on arrays; the numba kernel of
    :mod:`._align_kernel` writes the same test inline (the tests check they agree).

    Examples
    --------
    >>> det, ok = well_posed_2x2(np.array([4.0, 1.0]), np.array([0.0, 1.0]), np.array([9.0, 1.0]))
    >>> det.tolist(), ok.tolist()
    ([36.0, 0.0], [True, False])
    """
    det = a * c - b * b
    return det, det > WELL_POSED_RATIO * np.maximum(a + c, 1e-12) ** 2


@dataclass(frozen=True)
class PreparedFrame:
    """One grey frame made ready for many template searches.

    Attributes
    ----------
    image : (H, W) float32 frame.
    padded : the frame with ``pad`` pixels on every side repeating the border (float32).
    window_sum_sq : box sums of I² of ``padded`` over ``window``×``window`` windows
        centred on each pixel (float32).
    window : template side length (odd).
    pad : padding width in pixels.
    window_sum : (property, computed on first use) the same for the sums of I.
    ncc_scale : (property, computed on first use) 1 / √(Σ I² - (Σ I)² / n) per window.
    """

    image: np.ndarray
    padded: np.ndarray
    window_sum_sq: np.ndarray
    window: int
    pad: int

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) of the frame."""
        return self.image.shape  # type: ignore[return-value]

    @cached_property
    def window_sum(self) -> np.ndarray:
        """Padded box sums of I over the windows (float32)."""
        size = (self.window, self.window)
        return cv2.boxFilter(self.padded, cv2.CV_32F, size, normalize=False, borderType=cv2.BORDER_REPLICATE)

    @cached_property
    def ncc_scale(self) -> np.ndarray:
        """Padded map of 1 / √(Σ I² - (Σ I)² / n) per window, 0 where the window is flat.

        Computed on first use only (SSD searches never need it), in float64 because
        the difference cancels badly in single precision.
        """
        n_pixels = float(self.window * self.window)
        size = (self.window, self.window)
        s1 = cv2.boxFilter(self.padded, cv2.CV_64F, size, normalize=False, borderType=cv2.BORDER_REPLICATE)
        s2 = cv2.sqrBoxFilter(self.padded, cv2.CV_64F, size, normalize=False, borderType=cv2.BORDER_REPLICATE)
        energy = s2 - s1 * s1 / n_pixels
        # A flat window (std below 0.5 grey level) has no defined NCC: it scores 0.
        textured = energy > 0.25 * n_pixels
        out = np.zeros(self.padded.shape, np.float32)
        out[textured] = 1.0 / np.sqrt(energy[textured])
        return out


# Extra padding so that search patches can be gathered at the FFT size (a few pixels
# more than the patch) without leaving the padded frame.
_FFT_SLACK = 8


def prepare_frame(image: np.ndarray, window: int, max_search_radius: int) -> PreparedFrame:
    """Pad a grey frame and precompute its window sums of I² (one call per frame).

    Examples
    --------
    >>> f = prepare_frame(np.ones((20, 30)), window=5, max_search_radius=4)
    >>> f.padded.shape, float(f.window_sum[f.pad + 10, f.pad + 10])
    ((52, 62), 25.0)
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    pad = int(max_search_radius) + window // 2 + 2 + _FFT_SLACK
    padded = cv2.copyMakeBorder(image, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    # Unnormalised box filter: sum over the window centred on each pixel (OpenCV
    # accumulates float input in double), on the padded frame so that every window
    # the search can touch is consistent with the pixels it correlates.
    window_sum_sq = cv2.sqrBoxFilter(padded, cv2.CV_32F, (window, window), normalize=False, borderType=cv2.BORDER_REPLICATE)
    return PreparedFrame(image, padded, window_sum_sq, window, pad)


def sample_patches(image: np.ndarray | PreparedFrame, centers: np.ndarray, size: int, dtype: type = np.float64) -> np.ndarray:
    """Bilinearly sampled ``size``×``size`` patches centred at sub-pixel ``centers``.

    All pixels of one patch share the same fractional offset, so each patch is one
    (size + 1)² integer window (one fancy-index gather for all patches) blended with
    four weights — exact bilinear interpolation in double precision.

    Parameters
    ----------
    image : (H, W) grey image, or a :class:`PreparedFrame` (whose padding is reused).
    centers : (N, 2) float (x, y) centres.
    size : odd side length.
    dtype : float64 (default) or float32 (half the memory traffic, for the differential tracker).

    Returns
    -------
    (N, size, size) patches of ``dtype``; pixels outside the image repeat the border;
    NaN for non-finite centres.

    Examples
    --------
    >>> img = np.arange(25.0).reshape(5, 5)
    >>> sample_patches(img, np.array([[2.5, 2.0]]), 3)[0]
    array([[ 6.5,  7.5,  8.5],
           [11.5, 12.5, 13.5],
           [16.5, 17.5, 18.5]])
    """
    if isinstance(image, PreparedFrame):
        padded, pad = image.padded, image.pad
    else:
        pad = size // 2 + 2
        padded = cv2.copyMakeBorder(np.asarray(image, dtype=np.float32), pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 2)
    n = centers.shape[0]
    if n == 0:
        return np.zeros((0, size, size), dtype)
    finite = np.isfinite(centers).all(axis=1)
    safe = np.where(finite[:, None], centers, 0.0)
    whole = np.floor(safe)
    fraction = safe - whole
    # Top-left (row, column) of each window in the padded array; clipping an index into
    # the border-replicated padding repeats the border as well.
    top_left = (whole[:, ::-1] - size // 2 + pad).astype(np.intp)
    top_left = np.clip(top_left, 0, np.array(padded.shape) - size - 1)
    windows = _gather_windows(padded, top_left, size + 1).astype(dtype)
    fx, fy = fraction[:, 0, None, None].astype(dtype), fraction[:, 1, None, None].astype(dtype)
    # I(x + fx, y + fy) = (1 - fy)[(1 - fx) I₀₀ + fx I₀₁] + fy[(1 - fx) I₁₀ + fx I₁₁]:
    # blend along x once for all size + 1 rows, then the neighbouring rows along y.
    across = windows[:, :, :-1] + fx * (windows[:, :, 1:] - windows[:, :, :-1])
    upper = across[:, :-1]
    patches = upper + fy * (across[:, 1:] - upper)
    patches[~finite] = np.nan
    return patches


def _gather_windows(array: np.ndarray, top_left_rc: np.ndarray, size: int) -> np.ndarray:
    """(N, size, size) copies of ``array[r:r+size, c:c+size]`` for each (r, c) row of ``top_left_rc``."""
    windows = sliding_window_view(array, (size, size))
    return windows[top_left_rc[:, 0], top_left_rc[:, 1]]


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


def _template_spectra(templates: np.ndarray, fft_size: int, score: str) -> tuple[np.ndarray, np.ndarray]:
    """Conjugate spectra (fft_size², single precision) of the templates times the cost's
    factor (-2 for SSD, -1 for NCC) — zero-mean for NCC — and the templates' zero-mean energies.

    The template occupies only w of the fft_size rows, so the 2D transform is done
    as a real transform of those w rows followed by a complex one along the columns.
    """
    templates = np.asarray(templates, dtype=np.float64)
    # The factor folds the cost's -2 (SSD) or -1 (NCC) into the correlation.
    factor = -2.0 if score == "ssd" else -1.0
    centred = templates - templates.mean(axis=(1, 2), keepdims=True)
    zero_mean_energy = np.einsum("nij,nij->n", centred, centred)
    n, w = templates.shape[:2]
    # Zero-padded explicitly: much faster than letting scipy.fft pad (its ``n=`` argument) for small stacks.
    used = np.zeros((n, w, fft_size), np.float32)
    used[:, :, :w] = factor * (centred if score == "ncc" else templates)
    rows = np.zeros((n, fft_size, fft_size // 2 + 1), np.complex64)
    rows[:, :w] = scipy.fft.rfft(used, axis=2)
    spectra = scipy.fft.fft(rows, axis=1, overwrite_x=True)
    np.conjugate(spectra, out=spectra)
    return spectra, zero_mean_energy


class TemplateSpectra:
    """A stack of templates with their conjugate spectra kept per FFT size and score.

    For templates that rarely change (the tracker's anchors): each spectrum is
    computed on the first search that needs it and reused until its template is
    replaced.  Pass it to :func:`match_templates` in place of the template array.

    Parameters
    ----------
    templates : (N, w, w) templates.

    Examples
    --------
    >>> bank = TemplateSpectra(np.ones((3, 5, 5)))
    >>> bank.take(np.array([0, 2])).replace(np.array([1]), np.zeros((1, 5, 5))).templates.sum(axis=(1, 2))
    array([25.,  0.])
    """

    def __init__(self, templates: np.ndarray, _entries: dict | None = None) -> None:
        self.templates = np.asarray(templates, dtype=np.float64)
        self._entries: dict[tuple[int, str], tuple[np.ndarray, np.ndarray]] = {} if _entries is None else _entries

    def __len__(self) -> int:
        return len(self.templates)

    def spectra(self, rows: np.ndarray, fft_size: int, score: str) -> tuple[np.ndarray, np.ndarray]:
        """Conjugate spectra and zero-mean energies of the templates at ``rows`` (see :func:`_template_spectra`)."""
        key = (fft_size, score)
        if key not in self._entries:
            self._entries[key] = _template_spectra(self.templates, fft_size, score)
        spectra, energy = self._entries[key]
        return spectra[rows], energy[rows]

    def take(self, index: np.ndarray) -> TemplateSpectra:
        """The templates (and their cached spectra) at ``index`` (indices or a boolean mask)."""
        return TemplateSpectra(self.templates[index], {k: (s[index], e[index]) for k, (s, e) in self._entries.items()})

    def append(self, templates: np.ndarray) -> TemplateSpectra:
        """These templates followed by ``templates``; only the new ones are transformed."""
        templates = np.asarray(templates, dtype=np.float64).reshape(-1, *self.templates.shape[1:])
        entries = {}
        for (fft_size, score), (s, e) in self._entries.items():
            s_new, e_new = _template_spectra(templates, fft_size, score)
            entries[(fft_size, score)] = (np.concatenate([s, s_new]), np.concatenate([e, e_new]))
        return TemplateSpectra(np.concatenate([self.templates, templates]), entries)

    def replace(self, rows: np.ndarray, templates: np.ndarray) -> TemplateSpectra:
        """A copy with the templates at ``rows`` replaced; only those are transformed again."""
        new_templates = self.templates.copy()
        new_templates[rows] = templates
        entries = {}
        for (fft_size, score), (s, e) in self._entries.items():
            s, e = s.copy(), e.copy()
            s[rows], e[rows] = _template_spectra(new_templates[rows], fft_size, score)
            entries[(fft_size, score)] = (s, e)
        return TemplateSpectra(new_templates, entries)


def match_templates(
    frame: PreparedFrame,
    templates: np.ndarray | TemplateSpectra,
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
    templates : (N, w, w) templates, w = ``frame.window``; or a :class:`TemplateSpectra`
        of them, whose spectra are then reused across calls.
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
    # The gate ellipse reaches e = c·σ from p⁻ along x (σ = √Σxx) and along y; the
    # integer candidates in [p⁻ - e, p⁻ + e] are at most floor(2e) + 1 per axis, in a
    # box starting at ceil(p⁻ - e).  One e per track (the larger axis) makes the box square.
    reach = np.clip(np.nan_to_num(gate_radius * std.max(axis=1), nan=float(limit)), 1.0, float(limit))
    side = (np.floor(2.0 * reach) + 1.0).astype(int)
    origin = np.ceil(predicted - reach[:, None])
    inverse = np.linalg.inv(np.where(inside[:, None, None], cov, np.eye(2)))
    bank = templates if isinstance(templates, TemplateSpectra) else None
    if bank is not None:
        templates = bank.templates
    for group_side, rows in _size_classes(side, inside):
        # A box enlarged to the group's side grows on both sides (it stays in the padding).
        group_origin = origin[rows] - ((group_side - side[rows]) // 2)[:, None]
        _search_group(
            frame, templates[rows], predicted[rows], group_origin, inverse[rows], gate_radius, score, group_side,
            rows, positions, scores, dissimilarity, searched, bank,
        )
    return MatchResult(positions, scores, dissimilarity, searched)


def _size_classes(side: np.ndarray, inside: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Group the searchable tracks by box side; small groups join the next larger side.

    A larger box than needed is harmless (the gate mask still applies) and one more
    batched call per frame costs more than a few tracks searched in a larger box.
    """
    sides = side[inside]
    rows_inside = np.flatnonzero(inside)
    minimum = max(8, len(sides) // 20)
    classes: list[tuple[int, np.ndarray]] = []
    carried = np.zeros(0, np.intp)
    unique = np.unique(sides)
    for k, value in enumerate(unique):
        rows = np.concatenate([carried, rows_inside[sides == value]])
        if len(rows) < minimum and k + 1 < len(unique):
            carried = rows
            continue
        classes.append((int(value), rows))
        carried = np.zeros(0, np.intp)
    return classes


def _search_group(
    frame: PreparedFrame,
    templates: np.ndarray,
    predicted: np.ndarray,
    origin: np.ndarray,
    inverse: np.ndarray,
    gate_radius: float,
    score: str,
    side: int,
    rows: np.ndarray,
    positions: np.ndarray,
    scores: np.ndarray,
    dissimilarity: np.ndarray,
    searched: np.ndarray,
    bank: TemplateSpectra | None = None,
) -> None:
    """Search one group of tracks whose candidate boxes are ``side``×``side`` from ``origin`` (x, y); fill the outputs at ``rows``.

    Every step is one array operation over the whole group: one fancy-index gather of
    the search patches, one batched FFT cross-correlation, one gather of the window
    sums, the gate and border mask as broadcasts of row and column terms, one argmin.
    """
    n = len(rows)
    w = frame.window
    half_w = w // 2
    height, width = frame.shape
    span = side + w - 1  # pixels per axis of the search patch
    origin_int = origin.astype(np.intp)
    # Top-left candidate of each box in padded (row, column) coordinates.
    cand_top_left = np.stack([origin_int[:, 1], origin_int[:, 0]], axis=1) + frame.pad
    # Cross-correlation C(u) = Σ_i A(u + i) T(i) via FFT: C = F⁻¹[F(A) · conj F(T)], in
    # single precision.  The patches are gathered at the FFT size straight away: the
    # pixels beyond the span only meet the template's zero padding for the kept
    # u < side, so there is no wrap-around.  Only the side×side valid outputs are
    # transformed back (columns first, then the kept rows).
    fft_size = scipy.fft.next_fast_len(span, real=True)
    if fft_size - span > _FFT_SLACK:
        fft_size = span
    patches = _gather_windows(frame.padded, cand_top_left - half_w, fft_size)
    if bank is None:
        spectra, zero_mean_energy = _template_spectra(templates, fft_size, score)
    else:
        spectra, zero_mean_energy = bank.spectra(rows, fft_size, score)
    spectrum = scipy.fft.rfft2(patches)
    spectrum *= spectra
    partial = scipy.fft.ifft(spectrum, axis=1, overwrite_x=True)[:, :side]
    scaled_correlation = scipy.fft.irfft(partial, n=fft_size, axis=2)[:, :, :side]

    if score == "ssd":
        # SSD(u) = Σ I² - 2 Σ I T + Σ T²; the constant Σ T² is added to the best only
        # (it moves neither the argmin nor the quadratic fit's stationary point).
        cost = _gather_windows(frame.window_sum_sq, cand_top_left, side) + scaled_correlation
    else:
        # NCC(u) = Σ I (T - T̄) / (‖T - T̄‖ √(Σ I² - (Σ I)² / n)); the cost is -NCC·‖T - T̄‖
        # (the positive per-track factor does not move the argmin or the fit either).
        cost = _gather_windows(frame.ncc_scale, cand_top_left, side) * scaled_correlation
    flat_cost = cost.reshape(n, -1)

    # Gate: dᵀ Σ⁻¹ d = a dx² + 2 b dx dy + c dy² ≤ c², with the dx² and dy² terms per
    # column and per row; a candidate whose window leaves the frame gets +inf there.
    grid = np.arange(side, dtype=np.float64)
    cand_x = origin[:, 0, None] + grid  # (n, side)
    cand_y = origin[:, 1, None] + grid
    dx = cand_x - predicted[:, 0, None]
    dy = cand_y - predicted[:, 1, None]
    column_term = inverse[:, 0, 0, None] * dx * dx
    row_term = inverse[:, 1, 1, None] * dy * dy
    column_term[(cand_x < half_w) | (cand_x > width - 1 - half_w)] = np.inf
    row_term[(cand_y < half_w) | (cand_y > height - 1 - half_w)] = np.inf
    cross_coefficient = 2.0 * inverse[:, 0, 1]
    radius_sq = gate_radius * gate_radius

    # Usually the best candidate of the whole box already lies in the gate (and the
    # image); then it is the best in the gate as well, and the full mask is not needed.
    best = np.argmin(flat_cost, axis=1)
    k = np.arange(n)
    by, bx = np.divmod(best, side)
    best_mahalanobis_sq = column_term[k, bx] + row_term[k, by] + cross_coefficient * dx[k, bx] * dy[k, by]
    outside = np.flatnonzero(~(best_mahalanobis_sq <= radius_sq))
    ok = np.ones(n, dtype=bool)
    if len(outside):
        o = outside
        mahalanobis_sq = (cross_coefficient[o, None] * dy[o]).astype(np.float32)[:, :, None] * dx[o].astype(np.float32)[:, None, :]
        mahalanobis_sq += column_term[o].astype(np.float32)[:, None, :]
        mahalanobis_sq += row_term[o].astype(np.float32)[:, :, None]
        masked = np.where(mahalanobis_sq <= np.float32(radius_sq), cost[o], np.float32(np.inf)).reshape(len(o), -1)
        best[o] = np.argmin(masked, axis=1)
        ok[o] = np.isfinite(masked[np.arange(len(o)), best[o]])
    by, bx = np.divmod(best, side)
    # 3×3 neighbourhood of the best candidate (edges: repeat the centre so that axis is not refined).
    ny = np.clip(by[:, None] + np.array([-1, 0, 1]), 0, side - 1)
    nx = np.clip(bx[:, None] + np.array([-1, 0, 1]), 0, side - 1)
    neighbourhood = cost[k[:, None, None], ny[:, :, None], nx[:, None, :]].astype(np.float64)
    refine = subpixel_peak(neighbourhood)
    refine[(bx == 0) | (bx == side - 1), 0] = 0.0
    refine[(by == 0) | (by == side - 1), 1] = 0.0
    best_cost = neighbourhood[:, 1, 1]

    pos = np.stack([origin[:, 0] + bx, origin[:, 1] + by], axis=1) + refine
    positions[rows[ok]] = pos[ok]
    if score == "ssd":
        # The score itself directly, in double precision: Σ (I - T)² at the best candidate
        # (the FFT cost's cancellation of large terms leaves errors of ~1e-7 Σ I²).
        best_windows = _gather_windows(frame.padded, cand_top_left - half_w + np.stack([by, bx], axis=1), w)
        difference = best_windows - templates
        ssd = np.einsum("nij,nij->n", difference, difference)
        scores[rows[ok]] = ssd[ok]
        dissimilarity[rows[ok]] = ssd[ok] / np.maximum(zero_mean_energy[ok], 1e-12)
    else:
        ncc = -best_cost / np.sqrt(np.maximum(zero_mean_energy, 1e-12))
        scores[rows[ok]] = ncc[ok]
        dissimilarity[rows[ok]] = 1.0 - ncc[ok]
    searched[rows[ok]] = True


def refine_translation(
    image: np.ndarray | PreparedFrame,
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
    image : (H, W) grey frame, or its :class:`PreparedFrame` (faster: no padding per call).
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
    if not isinstance(image, PreparedFrame):
        image = prepare_frame(image, w, 1)  # pad once for all iterations
    templates = np.asarray(templates, dtype=np.float64)
    # Central differences on the inner (w-2)² pixels, where both neighbours exist.
    gx = 0.5 * (templates[:, 1:-1, 2:] - templates[:, 1:-1, :-2])
    gy = 0.5 * (templates[:, 2:, 1:-1] - templates[:, :-2, 1:-1])
    t_in = templates[:, 1:-1, 1:-1]
    t_in = t_in - t_in.mean(axis=(1, 2), keepdims=True)
    hessian = np.stack(
        [np.einsum("nij,nij->n", gx, gx), np.einsum("nij,nij->n", gx, gy), np.einsum("nij,nij->n", gx, gy), np.einsum("nij,nij->n", gy, gy)],
        axis=1,
    ).reshape(n, 2, 2)
    _, well_posed = well_posed_2x2(hessian[:, 0, 0], hessian[:, 0, 1], hessian[:, 1, 1])
    inv_h = np.linalg.inv(np.where(well_posed[:, None, None], hessian, np.eye(2)))
    t_norm = np.sqrt(np.einsum("nij,nij->n", t_in, t_in))
    current = positions.copy()
    for _ in range(iterations):
        patch = sample_patches(image, current, w - 2)
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
