"""Best similarity (Umeyama) and affine alignment of one 3D point set onto another.

Used to compare a reconstruction, which is defined only up to a similarity (and
the orthographic mirror), with ground-truth 3D points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InvalidInputError, NotEnoughDataError

__all__ = ["Alignment", "align_similarity", "align_affine"]


@dataclass(frozen=True)
class Alignment:
    """``aligned = scale * source @ rotation.T + translation`` (affine: ``source @ rotation.T + translation``).

    Attributes
    ----------
    aligned : (N, d) the transformed source points (NaN rows stay NaN).
    scale : float (1.0 for an affine alignment, whose ``rotation`` then holds the full linear map).
    rotation : (d, d) rotation (det +1; det −1 if a reflection was allowed and fitted better).
    translation : (d,)
    rms : RMS distance between aligned source and target over the rows finite in both.
    """

    aligned: np.ndarray
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    rms: float


def _pair(source: object, target: object, minimum: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.ndim != 2 or src.shape != dst.shape:
        raise InvalidInputError(f"source and target must be (N, d) arrays of one shape; got {src.shape} and {dst.shape}")
    both = np.all(np.isfinite(src), axis=1) & np.all(np.isfinite(dst), axis=1)
    if both.sum() < minimum:
        raise NotEnoughDataError(f"alignment needs >= {minimum} points finite in both sets; got {int(both.sum())}")
    return src, dst, both


def align_similarity(source: np.ndarray, target: np.ndarray, *, allow_reflection: bool = False) -> Alignment:
    """Least-squares similarity (scale, rotation, translation) taking ``source`` onto ``target``.

    Umeyama's closed form: with centred point sets X, Y and Σ = Yᵀ X / N = U D Vᵀ, the
    rotation is U E Vᵀ (E = diag(1, …, 1, ±1) keeps det = +1 unless reflections are
    allowed), the scale is tr(D E) / (mean squared norm of X), and the translation maps
    the source centroid onto the target centroid. Rows with NaN in either set are ignored.

    Parameters
    ----------
    source, target : (N, d) corresponding points.
    allow_reflection : also consider improper rotations — needed to compare an
        orthographic reconstruction, whose depth sign is ambiguous, with ground truth.

    Examples
    --------
    >>> pts = np.random.default_rng(0).normal(size=(10, 3))
    >>> moved = 2.0 * pts @ np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]).T + 5.0
    >>> fit = align_similarity(pts, moved)
    >>> round(fit.scale, 12), fit.rms < 1e-12
    (2.0, True)
    """
    src, dst, both = _pair(source, target, 3)
    x, y = src[both], dst[both]
    mean_x, mean_y = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mean_x, y - mean_y
    u, d, vt = np.linalg.svd(yc.T @ xc / len(x))
    signs = np.ones(len(d))
    if not allow_reflection and np.linalg.det(u) * np.linalg.det(vt) < 0:
        signs[-1] = -1.0
    rotation = (u * signs) @ vt
    variance = np.mean(np.sum(xc**2, axis=1))
    scale = float(np.sum(d * signs) / variance) if variance > 0 else 1.0
    translation = mean_y - scale * rotation @ mean_x
    aligned = scale * src @ rotation.T + translation
    rms = float(np.sqrt(np.mean(np.sum((aligned[both] - y) ** 2, axis=1))))
    return Alignment(aligned, scale, rotation, translation, rms)


def align_affine(source: np.ndarray, target: np.ndarray) -> Alignment:
    """Least-squares affine map (any d × d matrix plus translation) taking ``source`` onto ``target``.

    Examples
    --------
    >>> pts = np.random.default_rng(0).normal(size=(10, 3))
    >>> fit = align_affine(pts, pts @ np.diag([1.0, 2.0, 3.0]) + 1.0)
    >>> fit.rms < 1e-12
    True
    """
    src, dst, both = _pair(source, target, np.asarray(source).shape[-1] + 1)
    homogeneous = np.hstack([src[both], np.ones((both.sum(), 1))])
    solution, *_ = np.linalg.lstsq(homogeneous, dst[both], rcond=None)
    linear, translation = solution[:-1].T, solution[-1]
    aligned = src @ linear.T + translation
    rms = float(np.sqrt(np.mean(np.sum((aligned[both] - dst[both]) ** 2, axis=1))))
    return Alignment(aligned, 1.0, linear, translation, rms)
