"""The NEES of the difference of two estimates whose errors are correlated: what a split-half test should show.

Two estimates x̂₁, x̂₂ of one quantity from disjoint halves of its observations have errors
with covariances V₁, V₂ and cross-covariance C₁₂.  Their difference d = x̂₁ − x̂₂ is
N(0, V₁ + V₂ − C₁₂ − C₁₂ᵀ), and the split-half statistic dᵀ S⁻¹ d (S the covariance a method
assumes, usually Σ₁ + Σ₂) is distributed as Σ_k λ_k z_k², z ~ N(0, I), λ the eigenvalues of
S^{-1/2} Cov(d) S^{-1/2}.  It is χ²_p only when S = Cov(d); when the halves share part of
their error (C₁₂ positive), it is smaller even with the honest S = V₁ + V₂.

:func:`split_covariances` gives V₁, V₂ and C₁₂ of two least-squares estimates under AR(1)
errors (:class:`~kalmansfm.estimation.noise_model.SerialCorrelation`);
:func:`predict_nees` the distribution of the statistic for any assumed S.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._validation import as_float_array
from ..errors import InvalidInputError
from .noise_model import SerialCorrelation, serial_covariance

__all__ = ["PredictedNees", "SplitCovariances", "nees_weights", "predict_nees", "split_covariances"]


@dataclass(frozen=True)
class SplitCovariances:
    """Covariances of two estimates of the same n quantities from two halves of their observations.

    Attributes
    ----------
    first, second : (n, p, p) covariances V₁, V₂ of each half's estimate.
    cross : (n, p, p) cross-covariance C₁₂ = Cov(x̂₁, x̂₂).
    """

    first: np.ndarray
    second: np.ndarray
    cross: np.ndarray

    @property
    def difference(self) -> np.ndarray:
        """(n, p, p) Cov(x̂₁ − x̂₂) = V₁ + V₂ − C₁₂ − C₁₂ᵀ."""
        return self.first + self.second - self.cross - np.swapaxes(self.cross, 1, 2)

    @property
    def independent_sum(self) -> np.ndarray:
        """(n, p, p) V₁ + V₂: Cov(x̂₁ − x̂₂) if the halves' errors were independent."""
        return self.first + self.second


def split_covariances(first_design: object, second_design: object, positions: object,
                      correlation: SerialCorrelation) -> SplitCovariances:
    """V₁, V₂ and C₁₂ of the least-squares estimates from two halves of each group's observations.

    Parameters
    ----------
    first_design, second_design : (n, m, C, p) whitened Jacobians of each half's fit; NaN
        (or zero rows) at the positions a half does not use.
    positions : (m,) sequence position of each slot (e.g. the view index).
    correlation : the AR(1) errors along the sequence, in the whitened unit.

    Returns
    -------
    SplitCovariances

    Raises
    ------
    InvalidInputError
        The two designs differ in shape.

    Examples
    --------
    One coordinate seen at positions 0 and 1, one half each: independent errors share
    nothing; with ρ = 0.5 the halves share half their variance and Var(d) = 1 + 1 − 2 × 0.5.

    >>> first = np.array([1.0, np.nan]).reshape(1, 2, 1, 1)
    >>> second = np.array([np.nan, 1.0]).reshape(1, 2, 1, 1)
    >>> half = SerialCorrelation(np.array([0.5]), np.zeros(1), np.ones(1), np.zeros(1), 1)
    >>> c = split_covariances(first, second, np.arange(2), half)
    >>> float(c.cross[0, 0, 0]), float(c.difference[0, 0, 0]), float(c.independent_sum[0, 0, 0])
    (0.5, 1.0, 2.0)
    """
    a = as_float_array("first_design", first_design)
    b = as_float_array("second_design", second_design)
    if a.shape != b.shape or a.ndim != 4:
        raise InvalidInputError(f"first_design and second_design must both be (n, m, C, p); got {a.shape} and {b.shape}")
    return SplitCovariances(serial_covariance(a, positions, correlation), serial_covariance(b, positions, correlation),
                            serial_covariance(a, positions, correlation, other=b))


def nees_weights(assumed: object, actual: object) -> np.ndarray:
    """The weights λ with dᵀ S⁻¹ d = Σ_k λ_k z_k², z ~ N(0, I), when d ~ N(0, actual) and S = ``assumed``.

    λ are the eigenvalues of S^{-1/2} Cov(d) S^{-1/2} (with S = L Lᵀ: of L⁻¹ Cov(d) L⁻ᵀ),
    ascending; all 1 when the assumed covariance is the actual one.

    Parameters
    ----------
    assumed : (n, p, p) symmetric positive definite S.
    actual : (n, p, p) symmetric positive semi-definite Cov(d).

    Returns
    -------
    (n, p) float64

    Raises
    ------
    InvalidInputError
        Shapes that differ or are not (n, p, p); an assumed covariance that is not positive definite.

    Examples
    --------
    >>> nees_weights(np.diag([1.0, 4.0])[None], np.diag([2.0, 1.0])[None]).tolist()
    [[0.25, 2.0]]
    """
    S = as_float_array("assumed", assumed)
    C = as_float_array("actual", actual)
    if S.shape != C.shape or S.ndim != 3 or S.shape[1] != S.shape[2]:
        raise InvalidInputError(f"assumed and actual must both be (n, p, p); got {S.shape} and {C.shape}")
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise InvalidInputError("assumed covariances must be positive definite; one is not") from None
    # M = L⁻¹ Cov(d) L⁻ᵀ has the eigenvalues of S⁻¹ Cov(d) and is symmetric
    half = np.linalg.solve(L, C)
    M = np.linalg.solve(L, np.swapaxes(half, 1, 2))
    return np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, 1, 2)))


@dataclass(frozen=True)
class PredictedNees:
    """Monte-Carlo draws of the NEES dᵀ S⁻¹ d of n points, d ~ N(0, Cov(d)) each.

    Attributes
    ----------
    samples : (n, draws) the statistic of each point in each draw.
    """

    samples: np.ndarray

    @property
    def median(self) -> float:
        """Median of the pooled distribution (all points together), as a split-half table reports it."""
        return float(np.median(self.samples))

    @property
    def median_spread(self) -> float:
        """Standard deviation of the median over the n points of one draw: how far a measured median may stray."""
        return float(np.std(np.median(self.samples, axis=0)))

    def share_within(self, bound: float) -> float:
        """Expected share of the points whose statistic is at most ``bound``."""
        return float(np.mean(self.samples <= bound))


def predict_nees(assumed: object, actual: object, *, draws: int = 200, seed: int = 0) -> PredictedNees:
    """The distribution of dᵀ S⁻¹ d over n points, d ~ N(0, ``actual``), S = ``assumed``, by Monte Carlo.

    Parameters
    ----------
    assumed, actual : (n, p, p) as for :func:`nees_weights`.
    draws : draws per point.
    seed : of the random generator.

    Returns
    -------
    PredictedNees

    Raises
    ------
    InvalidInputError
        As :func:`nees_weights`; ``draws`` < 2.

    Examples
    --------
    Honest covariances give χ²₃ (median 2.37); a difference with half the assumed variance
    gives half of it:

    >>> eye = np.broadcast_to(np.eye(3), (500, 3, 3))
    >>> round(predict_nees(eye, eye).median, 1), round(predict_nees(eye, 0.5 * eye).median, 1)
    (2.4, 1.2)
    """
    if int(draws) < 2:
        raise InvalidInputError(f"draws must be at least 2; got {draws}")
    weights = nees_weights(assumed, actual)
    z = np.random.default_rng(seed).standard_normal((weights.shape[0], int(draws), weights.shape[1]))
    return PredictedNees(np.einsum("nk,ndk->nd", np.clip(weights, 0.0, None), z**2))
