"""A noise model fitted to residuals: Gaussian, Student-t, and either with uniform outliers, with pooled group scales.

Real image residuals are not one Gaussian: their core is narrower and their tail heavier,
and some tracks (a corner on an edge, a T-junction) are noisier than others.  This module
fits, by expectation–maximisation, a model of the squared residual lengths s_i of N
observations (pure estimation: nothing here knows about images):

    s_i = |r_i|²,   r_i | w_i, λ ~ N(0, σ² / (w_i Λ_i) I_{k_i})          (an inlier)
    w_i ~ Gamma(ν/2, ν/2)                 (Student-t: heavy tails; w_i = 1 for a Gaussian)
    Λ_i = Π_g λ_{g, j_g(i)},  λ_{g, j} ~ Gamma(α_g, α_g)   (pooled scales of groups: tracks, views)
    r_i ~ uniform over a disc of radius R with probability ε        (an outlier, optional)

* k_i is the residual's degrees of freedom: 2 for a 2-D residual, 2 − h_i after a fit in
  which the observation had leverage h_i (Σ h_i = the parameters fitted), so that the
  residuals of a least-squares fit give σ with the degrees of freedom counted.
* σ is the scale of a typical observation of a typical group; ν the tail (small: heavy;
  ∞: Gaussian); ε the outliers' share and R their range (the largest residual, the maximum-
  likelihood range of a uniform).
* Group scales are *pooled*: each group's precision multiplier λ has the prior Gamma(α, α)
  (mean 1), α estimated from all groups by maximising their marginal likelihood (empirical
  Bayes).  A group of 3 observations gets the posterior mean (α + K/2) / (α + S/2), pulled
  toward 1 — it does not get its own wild σ.  α → ∞ means no group differs.

Each observation then carries a *precision* π_i = E[w_i] Λ_i relative to 1/σ² — the weight
of iteratively reweighted least squares, or the observation's own standard deviation
σ / √π_i — and, with outliers in the model, the posterior probability of being one.

Standard errors come from the observed information of the marginal likelihood (the latent
w and z integrated out analytically) with the group scales held at their posterior means;
α's from the groups' own marginal likelihood.  Observations are taken as independent
given the scales.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, special, stats

from .._validation import as_float_array, check_choice
from ..errors import InvalidInputError, NotEnoughDataError

__all__ = ["NOISE_MODELS", "GroupScales", "NoiseFit", "SerialCorrelation", "fit_noise_model", "fit_serial_correlation",
           "serial_covariance"]

#: The noise models :func:`fit_noise_model` fits: the core, and whether uniform outliers join it.
NOISE_MODELS = ("gaussian", "student-t", "mixture", "student-t+uniform")
_TAILED = ("student-t", "student-t+uniform")
_OUTLIERS = ("mixture", "student-t+uniform")

# Bounds of the fitted tail ν and group spread α (a bound reached means: no evidence either way).
_NU_BOUNDS = (0.5, 1_000.0)
_ALPHA_BOUNDS = (0.3, 10_000.0)
_SHARE_BOUNDS = (1e-6, 0.5)
# A group's posterior shape α + K/2 must exceed 1 for E[1/λ] to exist; below 1 + this it is capped.
_MIN_SHAPE_EXCESS = 0.05


@dataclass(frozen=True)
class GroupScales:
    """The pooled scales of one grouping of the observations (e.g. by track).

    Attributes
    ----------
    name : what the groups are (``"track"``, ``"view"``).
    spread : α, the shape of the prior Gamma(α, α) of the groups' precision multipliers:
        the groups' σ differ by about 1/√(2α) relative (∞: all alike).
    spread_se : standard error of α (NaN when α sits on a bound).
    scales : (G,) each group's σ multiplier 1/√E[λ] (1 for a group without observations).
    observations : (G,) observations in each group.
    std_factors : (G,) √E[1/λ], the group's σ multiplier with its scale's uncertainty integrated out
        (larger than ``scales`` the fewer observations a group has).
    """

    name: str
    spread: float
    spread_se: float
    scales: np.ndarray = field(repr=False)
    observations: np.ndarray = field(repr=False)
    std_factors: np.ndarray = field(repr=False)


@dataclass(frozen=True)
class NoiseFit:
    """A noise model fitted to N residuals.

    Attributes
    ----------
    model : one of :data:`NOISE_MODELS`.
    sigma, sigma_se : the scale σ (the residuals' unit) and its standard error.
    tail, tail_se : the Student-t degrees of freedom ν and its standard error (∞ and 0 for a
        Gaussian core).
    outlier_share, outlier_share_se : ε, the share of uniform outliers, and its standard
        error (0 without outliers in the model).
    outlier_range : R, the radius of the outliers' disc (NaN without outliers).
    groups : the pooled group scales, one :class:`GroupScales` per grouping.
    precision : (N,) π_i = E[w_i] Λ_i, the observation's weight relative to 1/σ².
    group_precision : (N,) Λ_i alone (the groups' part of π_i).
    group_variance : (N,) Π_g E[1/λ_g]: the groups' variance multiplier with the uncertainty of
        each group's scale integrated out (≥ 1/Λ_i; the honest one for a covariance).
    outlier_probability : (N,) posterior probability that the observation is an outlier
        (zeros without outliers in the model).
    degrees_of_freedom : Σ k_i.
    log_likelihood : of the residuals, the group scales at their posterior means.
    iterations, converged : of the EM.

    Examples
    --------
    >>> fit = fit_noise_model(np.array([1.0, 0.5, 2.0, 1.5]) ** 2, model="gaussian")
    >>> round(fit.sigma, 4), fit.tail, fit.parameters()[0]
    (0.9682, inf, ('sigma_se', 0.2421))
    """

    model: str
    sigma: float
    sigma_se: float
    tail: float
    tail_se: float
    outlier_share: float
    outlier_share_se: float
    outlier_range: float
    groups: tuple[GroupScales, ...]
    precision: np.ndarray = field(repr=False)
    group_precision: np.ndarray = field(repr=False)
    group_variance: np.ndarray = field(repr=False)
    outlier_probability: np.ndarray = field(repr=False)
    degrees_of_freedom: float
    log_likelihood: float
    iterations: int
    converged: bool

    @property
    def observation_std(self) -> np.ndarray:
        """(N,) each observation's standard deviation σ / √π_i (∞ where π_i = 0)."""
        with np.errstate(divide="ignore"):
            return self.sigma / np.sqrt(self.precision)

    @property
    def covariance_factor(self) -> float:
        """(ν + 4) / (ν + 2): the variance of a weighted estimate relative to σ² (Σ π Jᵀ J)⁻¹ (1 for a Gaussian core).

        The Fisher information of a location from a 2-D Student-t observation is
        (ν + 2) / (ν + 4) of the Gaussian one at the same σ; the weights π average to 1.
        """
        return 1.0 if not np.isfinite(self.tail) else float((self.tail + 4.0) / (self.tail + 2.0))

    @property
    def outliers(self) -> np.ndarray:
        """(N,) bool — observations more likely outliers than not (none without outliers in the model)."""
        return self.outlier_probability > 0.5

    def inlier_quantile(self, probability: float, dof: float = 2.0) -> float:
        """The q with P(Λ s / σ² ≤ q) = ``probability`` for an inlier of ``dof`` degrees of freedom.

        A χ²(dof) quantile for a Gaussian core; dof × the F(dof, ν) quantile for a Student-t
        core.  An observation whose Λ s / σ² exceeds it is rejected by a test of that size.

        Examples
        --------
        >>> fit = fit_noise_model(np.ones(10), model="gaussian")
        >>> round(fit.inlier_quantile(0.999), 3)
        13.816
        """
        if not 0.0 < probability < 1.0:
            return float("inf")
        if not np.isfinite(self.tail):
            return float(stats.chi2.ppf(probability, dof))
        return float(dof * stats.f.ppf(probability, dof, self.tail))

    def parameters(self) -> tuple[tuple[str, float], ...]:
        """The fitted parameters besides σ, as (name, value) pairs (for a run summary)."""
        out: list[tuple[str, float]] = [("sigma_se", round(float(self.sigma_se), 4))]
        if self.model in _TAILED:
            out += [("tail_dof", _round(self.tail)), ("tail_dof_se", _round(self.tail_se))]
        if self.model in _OUTLIERS:
            out += [("outlier_share", _round(self.outlier_share)), ("outlier_share_se", _round(self.outlier_share_se)),
                    ("outlier_range", _round(self.outlier_range))]
        for g in self.groups:
            out += [(f"{g.name}_spread", _round(g.spread)), (f"{g.name}_spread_se", _round(g.spread_se))]
        return tuple(out)


def _round(x: float) -> float:
    return float(f"{float(x):.4g}")


def fit_noise_model(
    squared_residuals: object,
    *,
    model: str = "student-t",
    degrees_of_freedom: object | None = None,
    groups: tuple[object, ...] = (),
    group_names: tuple[str, ...] | None = None,
    outlier_range: float | None = None,
    max_iterations: int = 200,
    tolerance: float = 1e-5,
    fixed: NoiseFit | None = None,
) -> NoiseFit:
    """Fit a noise model to squared residual lengths by expectation–maximisation.

    Parameters
    ----------
    squared_residuals : (N,) float >= 0
        s_i = |r_i|² (e.g. pixels²).
    model : one of :data:`NOISE_MODELS`
        ``"gaussian"``; ``"student-t"`` (heavy tails); ``"mixture"`` (a Gaussian core and
        uniform outliers); ``"student-t+uniform"`` (both).
    degrees_of_freedom : (N,) float in (0, 2], optional
        k_i of each residual (default 2): 2 − leverage after a least-squares fit.
    groups : tuple of (N,) int arrays
        Labels 0 … G−1 of each grouping (e.g. the track of each observation, its view); each
        grouping gets pooled scales.
    group_names : names of the groupings (default ``group0``, ``group1``, …).
    outlier_range : float, optional
        R, the radius of the outliers' disc (default: the largest residual).
    max_iterations, tolerance : EM stops when no parameter moves by more than ``tolerance``
        relative (at most ``max_iterations`` rounds).
    fixed : NoiseFit, optional
        A fit whose σ, ν, ε, R and group spreads α are kept (e.g. fitted on a sample): only
        the observations' and groups' posterior quantities are computed for these residuals;
        the standard errors are the fit's.

    Returns
    -------
    NoiseFit

    Raises
    ------
    InvalidInputError
        Negative or non-finite residuals, degrees of freedom outside (0, 2], group labels of
        the wrong shape, an unknown model.
    NotEnoughDataError
        No residual degrees of freedom, or every residual zero.

    Examples
    --------
    Residuals of a Student-t with σ = 0.5 px and ν = 3, five per cent of them uniform
    mismatches within 50 px:

    >>> rng = np.random.default_rng(1)
    >>> n = 20_000
    >>> r = rng.normal(scale=0.5, size=(n, 2)) / np.sqrt(rng.gamma(1.5, 1 / 1.5, size=n))[:, None]
    >>> bad = rng.random(n) < 0.05
    >>> radius = 50 * np.sqrt(rng.random(bad.sum()))
    >>> r[bad] = radius[:, None] * np.stack([np.cos(a := rng.uniform(0, 2 * np.pi, bad.sum())), np.sin(a)], 1)
    >>> fit = fit_noise_model((r**2).sum(axis=1), model="student-t+uniform", outlier_range=50.0)
    >>> bool(abs(fit.sigma - 0.5) < 3 * fit.sigma_se), bool(abs(fit.tail - 3) < 3 * fit.tail_se)
    (True, True)
    >>> bool(abs(fit.outlier_share - 0.05) < 3 * fit.outlier_share_se)
    True
    """
    check_choice("model", model, NOISE_MODELS)
    s = as_float_array("squared_residuals", squared_residuals).ravel()
    if not (np.isfinite(s).all() and (s >= 0).all()):
        raise InvalidInputError("squared_residuals must be finite and >= 0")
    n = s.size
    k = np.full(n, 2.0) if degrees_of_freedom is None else as_float_array("degrees_of_freedom",
                                                                         degrees_of_freedom).ravel()
    if k.shape != (n,) or not (np.isfinite(k).all() and (k > 0).all() and (k <= 2).all()):
        raise InvalidInputError(f"degrees_of_freedom must be ({n},) values in (0, 2]; got shape {k.shape}")
    labels = []
    for gi, g in enumerate(groups):
        a = np.asarray(g)
        if a.shape != (n,) or not np.issubdtype(a.dtype, np.integer) or (n and a.min() < 0):
            raise InvalidInputError(f"groups[{gi}] must be ({n},) integer labels >= 0; got {a.shape} {a.dtype}")
        labels.append(a.astype(np.int64))
    names = tuple(group_names) if group_names is not None else tuple(f"group{i}" for i in range(len(labels)))
    if len(names) != len(labels):
        raise InvalidInputError(f"group_names must name the {len(labels)} groupings; got {len(names)}")
    if n == 0 or k.sum() <= 0:
        raise NotEnoughDataError("fitting a noise model needs residuals with degrees of freedom; got none")
    if not (s > 0).any():
        raise NotEnoughDataError("every residual is zero: the noise cannot be estimated")
    tailed, with_outliers = model in _TAILED, model in _OUTLIERS
    s_max = float(outlier_range) ** 2 if outlier_range is not None else float(s.max())
    if with_outliers and not s_max > 0:
        raise InvalidInputError(f"outlier_range must be > 0; got {outlier_range!r}")

    # start: a robust σ (the median of s / k against a χ²(2)'s median), a moderate tail, few outliers
    sigma2 = float(np.median(s / k) / np.log(2.0)) if np.median(s) > 0 else float(np.mean(s / k))
    nu = 30.0 if tailed else np.inf
    eps = 0.02 if with_outliers else 0.0
    alphas = [1.0] * len(labels)
    if fixed is not None:
        if fixed.model != model or len(fixed.groups) != len(labels):
            raise InvalidInputError(f"fixed must be a {model!r} fit with {len(labels)} groupings")
        sigma2, nu, eps, alphas = fixed.sigma**2, fixed.tail, fixed.outlier_share, [g.spread for g in fixed.groups]
        if with_outliers:
            s_max = fixed.outlier_range**2
    lam = [np.ones(int(g.max()) + 1 if n else 0) for g in labels]
    log_lam = [np.zeros_like(x) for x in lam]
    converged, it = False, 0
    for it in range(1, max_iterations + 1):
        Lam = start_lam = _product(lam, labels, n)
        u = Lam * s / sigma2
        gamma = _inlier_responsibility(u, s, k, Lam, sigma2, nu, eps, s_max) if with_outliers else np.ones(n)
        w = (nu + k) / (nu + u) if np.isfinite(nu) else np.ones(n)
        # σ² = Σ γ E[w] Λ s / Σ γ k
        new_sigma2 = sigma2 if fixed else float(np.sum(gamma * w * Lam * s) / np.sum(gamma * k))
        # group scales, one grouping at a time (the others held)
        new_alphas = []
        for gi, g in enumerate(labels):
            others = Lam / lam[gi][g]
            K = np.bincount(g, gamma * k, minlength=lam[gi].size)
            S = np.bincount(g, gamma * w * others * s, minlength=lam[gi].size) / new_sigma2
            a = alphas[gi] if fixed else _fit_alpha(K, S)
            lam[gi] = (a + K / 2) / (a + S / 2)
            log_lam[gi] = special.digamma(a + K / 2) - np.log(a + S / 2)
            Lam = others * lam[gi][g]
            new_alphas.append(a)
        new_nu = _fit_nu(s, k, Lam, new_sigma2, gamma) if tailed and not fixed else nu
        new_eps = float(np.clip(1.0 - gamma.mean(), *_SHARE_BOUNDS)) if with_outliers and not fixed else eps
        moves = [abs(new_sigma2 / sigma2 - 1)]
        if tailed:
            moves.append(abs(np.log(new_nu / nu)))
        if with_outliers:
            moves.append(abs(new_eps - eps) / max(eps, 1e-3))
        moves += [abs(np.log(a / b)) for a, b in zip(new_alphas, alphas)]
        if fixed is not None and labels:
            moves.append(float(np.max(np.abs(np.log(Lam / start_lam)))))
        sigma2, nu, eps, alphas = new_sigma2, new_nu, new_eps, new_alphas
        if max(moves) < tolerance:
            converged = True
            break

    Lam = _product(lam, labels, n)
    u = Lam * s / sigma2
    gamma = _inlier_responsibility(u, s, k, Lam, sigma2, nu, eps, s_max) if with_outliers else np.ones(n)
    w = (nu + k) / (nu + u) if np.isfinite(nu) else np.ones(n)
    se = (fixed.sigma_se, fixed.tail_se, fixed.outlier_share_se) if fixed is not None else \
        _standard_errors(s, k, Lam, sigma2, nu, eps, s_max, tailed, with_outliers)
    group_records = []
    group_variance = np.ones(n)
    for gi, g in enumerate(labels):
        others = Lam / lam[gi][g]
        K = np.bincount(g, gamma * k, minlength=lam[gi].size)
        S = np.bincount(g, gamma * w * others * s, minlength=lam[gi].size) / sigma2
        a = alphas[gi]
        # E[1/λ] under the posterior Gamma(α + K/2, α + S/2): the group's variance with its scale's uncertainty
        shape = a + K / 2
        variance = np.where(shape > 1 + _MIN_SHAPE_EXCESS, (a + S / 2) / np.maximum(shape - 1, _MIN_SHAPE_EXCESS),
                            (a + S / 2) / _MIN_SHAPE_EXCESS)
        group_variance = group_variance * variance[g]
        spread_se = fixed.groups[gi].spread_se if fixed is not None else _alpha_se(a, K, S)
        group_records.append(GroupScales(names[gi], float(a), spread_se, 1.0 / np.sqrt(lam[gi]),
                                         np.bincount(g, minlength=lam[gi].size), np.sqrt(variance)))
    loglik = float(np.sum(_log_mixture(s, k, Lam, sigma2, nu, eps, s_max)))
    return NoiseFit(model=model, sigma=float(np.sqrt(sigma2)), sigma_se=se[0], tail=float(nu), tail_se=se[1],
                    outlier_share=float(eps), outlier_share_se=se[2],
                    outlier_range=float(np.sqrt(s_max)) if with_outliers else float("nan"),
                    groups=tuple(group_records), precision=np.where(gamma > 0.5, w * Lam, 0.0) if with_outliers
                    else w * Lam, group_precision=Lam, group_variance=group_variance,
                    outlier_probability=1.0 - gamma,
                    degrees_of_freedom=float(k.sum()), log_likelihood=loglik, iterations=it, converged=converged)


def _product(lam: list[np.ndarray], labels: list[np.ndarray], n: int) -> np.ndarray:
    out = np.ones(n)
    for x, g in zip(lam, labels):
        out = out * x[g]
    return out


def _log_inlier(s: np.ndarray, k: np.ndarray, Lam: np.ndarray, sigma2: float, nu: float) -> np.ndarray:
    """log density of s for an inlier: σ²/Λ · χ²(k) (Gaussian) or σ²/Λ · k F(k, ν) (Student-t)."""
    c = Lam / sigma2
    u = c * s
    with np.errstate(divide="ignore", invalid="ignore"):
        # the u^{k/2-1} factor (1 for k = 2, also at u = 0; +∞ at u = 0 for k < 2, as the density is)
        power = np.where(k == 2, 0.0, (k / 2 - 1) * np.log(u))
        if not np.isfinite(nu):
            # χ²(k): u^{k/2-1} e^{-u/2} / (2^{k/2} Γ(k/2))
            out = power - u / 2 - (k / 2) * np.log(2.0) - special.gammaln(k / 2)
        else:
            # u = χ²(k) / (χ²(ν)/ν): Γ((ν+k)/2) / (Γ(k/2) Γ(ν/2)) ν^{ν/2} u^{k/2-1} (ν + u)^{-(ν+k)/2}
            out = (special.gammaln((nu + k) / 2) - special.gammaln(k / 2) - special.gammaln(nu / 2)
                   + (nu / 2) * np.log(nu) + power - ((nu + k) / 2) * np.log(nu + u))
        return out + np.log(c)


def _log_mixture(s, k, Lam, sigma2, nu, eps, s_max) -> np.ndarray:
    inlier = _log_inlier(s, k, Lam, sigma2, nu)
    if eps <= 0:
        return inlier
    # an outlier is uniform over a disc of area π s_max: the density of s = |r|² is 1 / s_max on [0, s_max]
    outlier = np.where(s <= s_max, -np.log(s_max), -np.inf)
    return np.logaddexp(np.log1p(-eps) + inlier, np.log(eps) + outlier)


def _inlier_responsibility(u, s, k, Lam, sigma2, nu, eps, s_max) -> np.ndarray:
    inlier = np.log1p(-eps) + _log_inlier(s, k, Lam, sigma2, nu)
    outlier = np.log(eps) + np.where(s <= s_max, -np.log(s_max), -np.inf)
    return np.exp(inlier - np.logaddexp(inlier, outlier))


def _fit_nu(s, k, Lam, sigma2, gamma) -> float:
    """ν maximising the inliers' marginal (Student-t) likelihood, σ and the scales held."""
    def negative(log_nu: float) -> float:
        return -float(np.sum(gamma * _log_inlier(s, k, Lam, sigma2, float(np.exp(log_nu)))))
    res = optimize.minimize_scalar(negative, bounds=np.log(_NU_BOUNDS), method="bounded",
                                   options={"xatol": 1e-4})
    return float(np.exp(res.x))


def _group_marginal(alpha: float, K: np.ndarray, S: np.ndarray) -> float:
    """Σ_j log ∫ Gamma(λ; α, α) Π_i N(r_i; 0, σ²/λ) dλ, up to terms free of α."""
    return float(np.sum(alpha * np.log(alpha) - special.gammaln(alpha) + special.gammaln(alpha + K / 2)
                        - (alpha + K / 2) * np.log(alpha + S / 2)))


def _fit_alpha(K: np.ndarray, S: np.ndarray) -> float:
    live = K > 0
    if not live.any():
        return _ALPHA_BOUNDS[1]
    Kl, Sl = K[live], S[live]
    res = optimize.minimize_scalar(lambda la: -_group_marginal(float(np.exp(la)), Kl, Sl),
                                   bounds=np.log(_ALPHA_BOUNDS), method="bounded", options={"xatol": 1e-4})
    return float(np.exp(res.x))


def _second_derivative(f, x: float, h: float) -> float:
    return (f(x + h) - 2 * f(x) + f(x - h)) / h**2


def _alpha_se(alpha: float, K: np.ndarray, S: np.ndarray) -> float:
    live = K > 0
    la = np.log(alpha)
    if not live.any() or not (np.log(_ALPHA_BOUNDS[0]) + 1e-2 < la < np.log(_ALPHA_BOUNDS[1]) - 1e-2):
        return float("nan")
    d2 = _second_derivative(lambda x: _group_marginal(float(np.exp(x)), K[live], S[live]), la, 1e-3)
    return float(alpha / np.sqrt(-d2)) if d2 < 0 else float("nan")


def _standard_errors(s, k, Lam, sigma2, nu, eps, s_max, tailed, with_outliers) -> tuple[float, float, float]:
    """Standard errors of σ, ν and ε from the observed information (numerical Hessian, scales held)."""
    theta = [0.5 * np.log(sigma2)]
    if tailed:
        theta.append(np.log(nu))
    if with_outliers:
        theta.append(np.log(eps / (1 - eps)))
    theta = np.array(theta)

    def loglik(t: np.ndarray) -> float:
        i = 1
        nu_t = nu
        if tailed:
            nu_t = float(np.exp(t[i]))
            i += 1
        eps_t = float(1 / (1 + np.exp(-t[i]))) if with_outliers else 0.0
        return float(np.sum(_log_mixture(s, k, Lam, float(np.exp(2 * t[0])), nu_t, eps_t, s_max)))

    m = theta.size
    h = 1e-3
    H = np.empty((m, m))
    f0 = loglik(theta)
    for a in range(m):
        for b in range(a, m):
            ea, eb = np.eye(m)[a] * h, np.eye(m)[b] * h
            if a == b:
                H[a, a] = (loglik(theta + ea) - 2 * f0 + loglik(theta - ea)) / h**2
            else:
                H[a, b] = H[b, a] = (loglik(theta + ea + eb) - loglik(theta + ea - eb) - loglik(theta - ea + eb)
                                     + loglik(theta - ea - eb)) / (4 * h**2)
    try:
        cov = np.linalg.inv(-H)
        var = np.diag(cov)
    except np.linalg.LinAlgError:
        var = np.full(m, np.nan)
    var = np.where(var > 0, var, np.nan)
    sigma_se = float(np.sqrt(sigma2) * np.sqrt(var[0]))
    i = 1
    nu_se = 0.0
    if tailed:
        at_bound = not (_NU_BOUNDS[0] * 1.01 < nu < _NU_BOUNDS[1] / 1.01)
        nu_se = float("nan") if at_bound else float(nu * np.sqrt(var[i]))
        i += 1
    eps_se = float(eps * (1 - eps) * np.sqrt(var[i])) if with_outliers else 0.0
    return sigma_se, nu_se, eps_se


# --- errors correlated along a sequence --------------------------------------------------------------

# Bounds of the fitted lag-one correlation.
_RHO_BOUNDS = (-0.5, 0.995)
# Blocks of groups for the jackknife standard errors.
_JACKKNIFE_BLOCKS = 20


@dataclass(frozen=True)
class SerialCorrelation:
    """Errors that follow an AR(1) process along each group's sequence, one per coordinate.

    Within a group (a track), the error of coordinate c at sequence position a (a view) and
    at position b have the covariance τ_c² ρ_c^|a − b| (in the unit of the whitened
    residuals); different coordinates and different groups are independent.  ρ = 0, τ = 1
    is independent noise.

    Attributes
    ----------
    correlation, correlation_se : (C,) ρ_c and its standard error (jackknife over groups).
    scale, scale_se : (C,) τ_c and its standard error.
    groups : the groups the moments came from.

    Examples
    --------
    >>> SerialCorrelation(np.array([0.0, 0.5]), np.zeros(2), np.ones(2), np.zeros(2), 10).covariance(
    ...     np.array([0, 1, 3]))[:, 1, :, 1].round(3).tolist()
    [[1.0, 0.5, 0.125], [0.5, 1.0, 0.25], [0.125, 0.25, 1.0]]
    """

    correlation: np.ndarray
    correlation_se: np.ndarray
    scale: np.ndarray
    scale_se: np.ndarray
    groups: int

    @classmethod
    def independent(cls, coordinates: int = 2) -> SerialCorrelation:
        """No correlation, unit scale."""
        return cls(np.zeros(coordinates), np.zeros(coordinates), np.ones(coordinates), np.zeros(coordinates), 0)

    def covariance(self, positions: np.ndarray) -> np.ndarray:
        """(m, C, m, C) covariance of the errors at sequence ``positions`` (m,) — τ² ρ^|lag| per coordinate."""
        lag = np.abs(np.subtract.outer(positions, positions)).astype(np.float64)
        C = self.correlation.size
        out = np.zeros((positions.size, C, positions.size, C))
        for c in range(C):
            out[:, c, :, c] = self.scale[c] ** 2 * np.power(self.correlation[c], lag)
        return out

    def parameters(self) -> tuple[tuple[str, float], ...]:
        """ρ and τ per coordinate, with standard errors, as (name, value) pairs."""
        out: list[tuple[str, float]] = []
        for c, axis in enumerate("xyz"[: self.correlation.size]):
            out += [(f"serial_correlation_{axis}", _round(self.correlation[c])),
                    (f"serial_correlation_{axis}_se", _round(self.correlation_se[c])),
                    (f"serial_scale_{axis}", _round(self.scale[c])), (f"serial_scale_{axis}_se", _round(self.scale_se[c]))]
        return tuple(out)


def _lag_tables(residuals: np.ndarray, design: np.ndarray, lags: np.ndarray, used: np.ndarray):
    """Moment tables of one block of groups.

    With M = I − J (JᵀJ)⁻¹ Jᵀ the residual maker of each group's fit, r = M e and
    E[r rᵀ] = M Ω Mᵀ.  Returns the observed Σ r_c² and Σ r_c r'_c over consecutive
    observations (e0, e1: (C,)) and the tables T0, T1 (C target, C source, lags) such that
    the expected values are Σ_source τ² Σ_d T[·, ·, d] ρ^d.
    """
    b, m, C, p = design.shape
    J = np.where(used[..., None, None], design, 0.0).reshape(b, m * C, p)
    r = np.where(used[..., None], residuals, 0.0)
    N_inv = np.linalg.pinv(np.matmul(np.swapaxes(J, 1, 2), J), hermitian=True)
    M = -np.matmul(np.matmul(J, N_inv), np.swapaxes(J, 1, 2))
    eye = np.repeat(used, C, axis=1).astype(np.float64)
    M[:, np.arange(m * C), np.arange(m * C)] += eye
    M = M.reshape(b, m, C, m, C)
    # consecutive observations of each group: (b, m, m) with S[i, j] = 1 for i < j next to each other
    nxt = np.full((b, m), -1)
    for i in range(m):  # the next used position after i (m is small: the number of views)
        later = np.where(used[:, i + 1:], np.arange(i + 1, m)[None], m).min(axis=1) if i + 1 < m else np.full(b, m)
        nxt[:, i] = np.where(used[:, i] & (later < m), later, -1)
    S = np.zeros((b, m, m))
    bi, ii = np.nonzero(nxt >= 0)
    S[bi, ii, nxt[bi, ii]] = 1.0
    n_lags = int(lags.max()) + 1
    T0 = np.zeros((C, C, n_lags))
    T1 = np.zeros((C, C, n_lags))
    flat_lags = lags.ravel()
    for ct in range(C):
        for cs in range(C):
            Mc = np.ascontiguousarray(M[:, :, ct, :, cs])  # (b, rows i, sources k)
            # einsum, not BLAS: these thin products gain nothing from BLAS threads, which stall on a busy machine
            G0 = np.einsum("bik,bil->kl", Mc, Mc)
            G1 = np.einsum("bik,bil->kl", Mc, np.matmul(S, Mc))
            T0[ct, cs] = np.bincount(flat_lags, G0.ravel(), minlength=n_lags)
            T1[ct, cs] = np.bincount(flat_lags, 0.5 * (G1 + G1.T).ravel(), minlength=n_lags)
    e0 = np.einsum("bmc,bmc->c", r, r)
    e1 = np.einsum("bic,bij,bjc->c", r, S, r)
    return e0, e1, T0, T1


def _solve_moments(e0, e1, T0, T1) -> tuple[np.ndarray, np.ndarray]:
    C, _, n_lags = T0.shape
    d = np.arange(n_lags)

    def powers(rho: np.ndarray) -> np.ndarray:
        return np.power(rho[:, None], d[None])  # (C, lags)

    def scales2(rho: np.ndarray) -> np.ndarray:
        A0 = np.einsum("tsd,sd->ts", T0, powers(rho))
        return np.linalg.lstsq(A0, e0, rcond=None)[0]

    def mismatch(rho: np.ndarray) -> np.ndarray:
        A1 = np.einsum("tsd,sd->ts", T1, powers(rho))
        return (A1 @ scales2(rho) - e1) / np.maximum(e0, np.finfo(float).tiny)

    res = optimize.least_squares(mismatch, np.full(C, 0.2), bounds=(np.full(C, _RHO_BOUNDS[0]),
                                                                    np.full(C, _RHO_BOUNDS[1])))
    rho = res.x
    tau2 = np.clip(scales2(rho), np.finfo(float).tiny, None)
    return rho, np.sqrt(tau2)


def _like_lengths(groups: np.ndarray, lengths: np.ndarray, most: int) -> list[np.ndarray]:
    """Runs of ``groups`` (sorted by ascending ``lengths``) of at most ``most``, lengths within a factor 1.25 of the
    run's first: the moment tables of a run cost the cube of its longest length."""
    runs, start = [], 0
    while start < groups.size:
        stop = min(start + most, int(np.searchsorted(lengths, 1.25 * lengths[start], side="right")))
        stop = max(stop, start + 1)
        runs.append(groups[start:stop])
        start = stop
    return runs


def fit_serial_correlation(residuals: object, design: object, positions: object, *,
                           block: int = 4096) -> SerialCorrelation:
    """Fit AR(1) errors along sequences to the residuals of many small least-squares fits, by moments.

    Each of n groups (a track) was fitted by least squares, y = J x + e, over its
    observations: up to m sequence positions (views) × C coordinates, whitened (unit
    variance under independent errors).  Its residuals r = M e (M the residual maker) have
    E[r rᵀ] = M Ω Mᵀ, Ω the AR(1) covariance of :class:`SerialCorrelation`; ρ_c and τ_c solve
    the moment equations of Σ r_c² and of Σ r_c r'_c over consecutive observations.  Because
    M is accounted for, a fit that absorbed part of a slowly varying error (which a
    correlated process has, and an estimate from the raw residuals would miss) is allowed for.

    Parameters
    ----------
    residuals : (n, m, C) whitened residuals, NaN where a group has no observation.
    design : (n, m, C, p) whitened Jacobians of each group's fit (p parameters).
    positions : (m,) sequence position of each of the m slots (lags are their differences).
    block : groups processed together.

    Returns
    -------
    SerialCorrelation

    Raises
    ------
    InvalidInputError
        Shapes that do not agree.
    NotEnoughDataError
        No group with two consecutive observations and residual degrees of freedom.

    Examples
    --------
    Straight lines y = a + b t fitted to 400 series of 10 points whose noise is AR(1) with ρ = 0.7:

    >>> rng = np.random.default_rng(0)
    >>> n, m, rho = 400, 10, 0.7
    >>> e = np.zeros((n, m))
    >>> e[:, 0] = rng.normal(size=n)
    >>> for t in range(1, m):
    ...     e[:, t] = rho * e[:, t - 1] + np.sqrt(1 - rho**2) * rng.normal(size=n)
    >>> J = np.broadcast_to(np.stack([np.ones(m), np.arange(m) / m], 1)[None, :, None], (n, m, 1, 2))
    >>> H = J[0, :, 0] @ np.linalg.pinv(J[0, :, 0])
    >>> r = (e - e @ H.T)[..., None]
    >>> fit = fit_serial_correlation(r, J, np.arange(m))
    >>> bool(abs(fit.correlation[0] - 0.7) < 3 * fit.correlation_se[0]), bool(abs(fit.scale[0] - 1) < 0.2)
    (True, True)
    """
    r = as_float_array("residuals", residuals)
    J = as_float_array("design", design)
    pos = as_float_array("positions", positions)
    if r.ndim != 3 or J.shape[:3] != r.shape or J.ndim != 4 or pos.shape != (r.shape[1],):
        raise InvalidInputError(f"residuals (n, m, C), design (n, m, C, p) and positions (m,) must agree; got "
                                f"{r.shape}, {J.shape} and {pos.shape}")
    used = np.isfinite(r).all(axis=2) & np.isfinite(J).all(axis=(2, 3))
    counts = used.sum(axis=1)
    live = np.flatnonzero(counts * r.shape[2] > J.shape[3])
    if live.size < 2:
        raise NotEnoughDataError("fitting serial correlation needs groups with more observations than parameters; "
                                 f"got {live.size}")
    lags = np.abs(np.subtract.outer(pos, pos)).round().astype(np.int64)
    if (lags < 0).any():
        raise InvalidInputError("positions must be finite")
    blocks = np.array_split(live, min(_JACKKNIFE_BLOCKS, live.size))
    # a group's slots after its last observation are empty: groups of like length share trimmed tables
    last = r.shape[1] - 1 - np.argmax(used[:, ::-1], axis=1)
    n_lags = int(lags.max()) + 1
    parts = []
    for idx in blocks:
        idx = idx[np.argsort(last[idx], kind="stable")]
        acc = None
        for sub in _like_lengths(idx, last[idx] + 1, block):
            w = int(last[sub].max()) + 1
            e0, e1, T0, T1 = _lag_tables(r[sub, :w], J[sub, :w], lags[:w, :w], used[sub, :w])
            pad = ((0, 0), (0, 0), (0, n_lags - T0.shape[2]))
            t = (e0, e1, np.pad(T0, pad), np.pad(T1, pad))
            acc = t if acc is None else tuple(a + b for a, b in zip(acc, t))
        parts.append(acc)
    total = tuple(sum(p[i] for p in parts) for i in range(4))
    rho, tau = _solve_moments(*total)
    # jackknife over blocks of groups
    B = len(parts)
    if B >= 3:
        est = np.array([np.concatenate(_solve_moments(*(total[i] - p[i] for i in range(4)))) for p in parts])
        se = np.sqrt((B - 1) / B * np.sum((est - est.mean(axis=0)) ** 2, axis=0))
    else:
        se = np.full(2 * rho.size, np.nan)
    C = rho.size
    return SerialCorrelation(rho, se[:C], tau, se[C:], int(live.size))


def serial_covariance(design: object, positions: object, correlation: SerialCorrelation,
                      other: object | None = None) -> np.ndarray:
    """Covariance of least-squares estimates when the errors are serially correlated (the sandwich A Ω Bᵀ).

    For each group the estimate x̂ = x + A e, A = (JᵀJ)⁻¹ Jᵀ (whitened design J): its
    covariance is A Ω Aᵀ, Ω from ``correlation`` at ``positions``.  With ``other`` (another
    design of the same groups, e.g. from a disjoint set of observations), the
    cross-covariance A Ω Bᵀ of the two estimates.

    Parameters
    ----------
    design : (n, m, C, p) whitened Jacobians, NaN (or zero rows) where a group has no observation.
    positions : (m,) sequence positions.
    correlation : the serial correlation of the errors.
    other : (n, m, C, p), optional.

    Returns
    -------
    (n, p, p)

    Examples
    --------
    The mean of two observations of one coordinate, independent or correlated by 0.5:

    >>> J = np.ones((1, 2, 1, 1))
    >>> independent = SerialCorrelation.independent(1)
    >>> float(serial_covariance(J, np.arange(2), independent)[0, 0, 0])
    0.5
    >>> half = SerialCorrelation(np.array([0.5]), np.zeros(1), np.ones(1), np.zeros(1), 1)
    >>> float(serial_covariance(J, np.arange(2), half)[0, 0, 0])
    0.75
    """
    def estimator(D: np.ndarray) -> np.ndarray:
        D = np.where(np.isfinite(D), D, 0.0)
        n, m, C, p = D.shape
        flat = D.reshape(n, m * C, p)
        N = np.einsum("bki,bkj->bij", flat, flat)
        return np.einsum("bij,bkj->bik", np.linalg.pinv(N, hermitian=True), flat)  # (n, p, m C)

    J = as_float_array("design", design)
    pos = as_float_array("positions", positions)
    n, m, C, p = J.shape
    omega = correlation.covariance(pos).reshape(m * C, m * C)
    A = estimator(J)
    B = A if other is None else estimator(as_float_array("other", other))
    return np.einsum("bik,kl,bjl->bij", A, omega, B)
