"""Fusion of repeated measurements of a quantity that moves in a known way.

This is Tasks 1-6 of Thomas & Oliensis, *Fusing Structure by Kalman Filtering*
(``004_cd423c68da9c9743.txt``).  The quantity (a distance, or a landmark's 3D
position in the sensor frame) evolves as

    x_k = C_{k-1} x_{k-1} - b_{k-1}                       (report eq. 23)

with known rotation C (identity for a static target) and known translation b
(zero for a static target, the step v of the walking observer of Task 3), and
is measured directly, p_k = x_k + noise with covariance R_k.

Two independent implementations give the same answer:

* :func:`fuse_recursive` runs the :class:`~kalmansfm.KalmanFilter` (H = I, Q = 0)
  and needs only the previous estimate;
* :func:`fuse_closed_form` evaluates the normalised *moved* weighted mean of all
  measurements so far (report eqs. 12-13, 16, 17-18, 19-22, 24-28).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InvalidInputError
from .._validation import as_float_array, check_covariance, check_finite
from .kalman import KalmanFilter

__all__ = ["FusionResult", "fuse_recursive", "fuse_closed_form"]


@dataclass(frozen=True)
class FusionResult:
    """Fused estimate after each measurement.

    Attributes
    ----------
    estimates : (K, d), or (K, L, d) for L landmarks, or (K,) for scalar input —
        the estimate after measurement k, in the sensor frame of step k.
    covariances : (K, d, d), (K, L, d, d) or (K,) (variances for scalar input).
    """

    estimates: np.ndarray
    covariances: np.ndarray

    @property
    def standard_deviations(self) -> np.ndarray:
        """Square roots of the covariance diagonals, shaped like ``estimates``."""
        if self.covariances.ndim == self.estimates.ndim:  # scalar case: variances
            return np.sqrt(self.covariances)
        return np.sqrt(np.diagonal(self.covariances, axis1=-2, axis2=-1))


@dataclass(frozen=True)
class _Normalized:
    p: np.ndarray  # (K, L, d)
    R: np.ndarray  # (K, L, d, d)
    C: np.ndarray  # (K-1, d, d)
    b: np.ndarray  # (K-1, d)
    layout: str  # "scalar", "single" or "many"


def _normalize(measurements: object, covariances: object, rotations: object, translations: object) -> _Normalized:
    p = as_float_array("measurements", measurements)
    R = as_float_array("covariances", covariances)
    if p.ndim == 1:
        layout = "scalar"
        if R.shape != p.shape:
            raise InvalidInputError(
                f"covariances must have shape {p.shape} (one variance per scalar measurement); got {R.shape}"
            )
        p, R = p[:, None, None], R[:, None, None, None]
    elif p.ndim == 2:
        layout = "single"
        K, d = p.shape
        if R.shape != (K, d, d):
            raise InvalidInputError(f"covariances must have shape ({K}, {d}, {d}); got {R.shape}")
        p, R = p[:, None, :], R[:, None, :, :]
    elif p.ndim == 3:
        layout = "many"
        K, L, d = p.shape
        if R.shape != (K, L, d, d):
            raise InvalidInputError(f"covariances must have shape ({K}, {L}, {d}, {d}); got {R.shape}")
    else:
        raise InvalidInputError(f"measurements must have shape (K,), (K, d) or (K, L, d); got {p.shape}")
    K, L, d = p.shape
    if K < 1:
        raise InvalidInputError("measurements must hold at least one measurement")
    if np.isinf(p).any():
        raise InvalidInputError("measurements must not contain infinity (NaN marks a missing measurement)")
    if np.isnan(p[0]).any():
        raise InvalidInputError("measurements[0] must be finite: the first measurement initialises the estimate")
    rows_present = ~np.isnan(p).any(axis=-1)
    # A missing measurement's covariance is never used; give it a harmless value.
    R = np.where(rows_present[..., None, None], R, np.eye(d))
    # Checked in the caller's layout so that the index in an error message is the caller's index.
    check_covariance("covariances", R if layout == "many" else R[:, 0])
    if rotations is None:
        C = np.broadcast_to(np.eye(d), (K - 1, d, d))
    else:
        C = as_float_array("rotations", rotations)
        if C.shape == (d, d):
            C = np.broadcast_to(C, (K - 1, d, d))
        if C.shape != (K - 1, d, d):
            raise InvalidInputError(f"rotations must have shape ({K - 1}, {d}, {d}) or ({d}, {d}); got {C.shape}")
        check_finite("rotations", C)
    if translations is None:
        b = np.zeros((K - 1, d))
    else:
        b = as_float_array("translations", translations)
        if layout == "scalar" and b.ndim <= 1:
            b = np.broadcast_to(b.reshape(-1, 1), (K - 1, 1)) if b.size in (1, K - 1) else b
        if b.shape == (d,):
            b = np.broadcast_to(b, (K - 1, d))
        if b.shape != (K - 1, d):
            expected = f"({K - 1},) or a scalar" if layout == "scalar" else f"({K - 1}, {d}) or ({d},)"
            raise InvalidInputError(f"translations must have shape {expected}; got {b.shape}")
        check_finite("translations", b)
    return _Normalized(p, R, C, b, layout)


def _shape_result(norm: _Normalized, x: np.ndarray, P: np.ndarray) -> FusionResult:
    if norm.layout == "scalar":
        return FusionResult(x[:, 0, 0], P[:, 0, 0, 0])
    if norm.layout == "single":
        return FusionResult(x[:, 0], P[:, 0])
    return FusionResult(x, P)


def fuse_recursive(
    measurements: object,
    covariances: object,
    rotations: object | None = None,
    translations: object | None = None,
) -> FusionResult:
    """Fuse measurements one at a time with the Kalman filter.

    Parameters
    ----------
    measurements : (K,) scalars, (K, d) vectors, or (K, L, d) for L landmarks
        measured together; a NaN row is a missing measurement (the estimate is
        only moved).  The first measurement must be present.
    covariances : (K,) variances for scalars, else (K, d, d) or (K, L, d, d).
    rotations : C_k, (K-1, d, d) or one (d, d) for every step; identity if None.
    translations : b_k, (K-1, d), one (d,) for every step (a scalar for 1D), or
        None for zero.  The motion is x_k = C_{k-1} x_{k-1} - b_{k-1}.

    Returns
    -------
    FusionResult
        The estimate and covariance after each measurement.

    Examples
    --------
    Task 1: equal variances give the running mean.

    >>> r = fuse_recursive([100.0, 102.0, 101.0], [1.0, 1.0, 1.0])
    >>> r.estimates, r.standard_deviations.round(4)
    (array([100., 101., 101.]), array([1.    , 0.7071, 0.5774]))

    Task 3: an observer walking 1 m closer each step.

    >>> fuse_recursive([10.0, 9.0], [1.0, 1.0], translations=1.0).estimates
    array([10., 9.])
    """
    norm = _normalize(measurements, covariances, rotations, translations)
    K, L, d = norm.p.shape
    kf = KalmanFilter(norm.p[0], norm.R[0], np.eye(d), np.eye(d), np.zeros((d, d)), norm.R[0])
    xs = np.empty((K, L, d))
    Ps = np.empty((K, L, d, d))
    xs[0], Ps[0] = norm.p[0], norm.R[0]
    for k in range(1, K):
        kf.predict(F=norm.C[k - 1], u=-norm.b[k - 1])
        kf.update(norm.p[k], R=norm.R[k])
        xs[k], Ps[k] = kf.x, kf.P
    return _shape_result(norm, xs, Ps)


def fuse_closed_form(
    measurements: object,
    covariances: object,
    rotations: object | None = None,
    translations: object | None = None,
) -> FusionResult:
    """The normalised moved weighted mean of all measurements so far (no recursion).

    After measurement k every earlier measurement p_i is moved into frame k by the
    known motion, m_i = Φ_{k,i} p_i - Σ_{j=i}^{k-1} Φ_{k,j+1} b_j with
    Φ_{k,i} = C_{k-1} ⋯ C_i, its covariance becomes R'_i = Φ_{k,i} R_i Φ_{k,i}ᵀ
    (eqs. 20, 25), and

        S_k = (Σ_i R'_i⁻¹)⁻¹,   x̂_k = S_k Σ_i R'_i⁻¹ m_i      (eqs. 17-18, 19-21, 24-26).

    For scalars with C = 1, b = v this is eq. 16, Σ (z_i - (k-i) v)/r_i / Σ 1/r_i.
    (Printed eq. 26 adds the moved translations; moving a measurement forward
    subtracts them, which is what x_k = C x_{k-1} - b implies and what the
    report's tables show.)  Arguments as for :func:`fuse_recursive`.

    Examples
    --------
    >>> fuse_closed_form([39.602, 39.53], [1.6247**2, 1.7141**2]).estimates.round(3)
    array([39.602, 39.568])
    """
    norm = _normalize(measurements, covariances, rotations, translations)
    K, L, d = norm.p.shape
    present = ~np.isnan(norm.p).any(axis=-1)  # (K, L)
    xs = np.empty((K, L, d))
    Ps = np.empty((K, L, d, d))
    for k in range(K):
        info = np.zeros((L, d, d))
        info_mean = np.zeros((L, d))
        for i in range(k + 1):
            # Φ_{k,i} and the translations moved into frame k.
            Phi = np.eye(d)
            moved_b = np.zeros(d)
            for j in range(i, k):
                Phi = norm.C[j] @ Phi
                moved_b = norm.C[j] @ moved_b + norm.b[j]
            rows = present[i]
            moved_p = norm.p[i, rows] @ Phi.T - moved_b
            moved_R = Phi @ norm.R[i, rows] @ Phi.T
            W = np.linalg.inv(moved_R)
            info[rows] += W
            info_mean[rows] += np.einsum("lij,lj->li", W, moved_p)
        Ps[k] = np.linalg.inv(info)
        xs[k] = np.einsum("lij,lj->li", Ps[k], info_mean)
    return _shape_result(norm, xs, Ps)
