"""The noise model fitted by EM: known heavy-tailed and mixed data give back their parameters within the stated errors."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from kalmansfm.errors import InvalidInputError, NotEnoughDataError
from kalmansfm.estimation import fit_noise_model, fit_serial_correlation, serial_covariance
from kalmansfm.estimation.noise_model import SerialCorrelation


def student_t_residuals(rng, n, sigma, nu):
    """2-D Student-t residuals: N(0, σ² I) / √w, w ~ Gamma(ν/2, 2/ν)."""
    return rng.normal(scale=sigma, size=(n, 2)) / np.sqrt(rng.gamma(nu / 2, 2 / nu, size=n))[:, None]


def uniform_disc(rng, n, radius):
    r = radius * np.sqrt(rng.random(n))
    a = rng.uniform(0, 2 * np.pi, n)
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


@pytest.mark.parametrize("seed", [0, 1])
def test_student_t_scale_and_tail_come_back_within_their_standard_errors(seed):
    rng = np.random.default_rng(seed)
    r = student_t_residuals(rng, 20_000, 0.4, 3.0)
    fit = fit_noise_model((r**2).sum(axis=1), model="student-t")
    assert fit.converged
    assert abs(fit.sigma - 0.4) < 3 * fit.sigma_se
    assert abs(fit.tail - 3.0) < 3 * fit.tail_se
    assert 0 < fit.sigma_se < 0.01 and 0 < fit.tail_se < 0.3
    # the weights are the t's posterior means: small for large residuals, about 1 on average
    assert 0.9 < fit.precision.mean() < 1.1
    big = (r**2).sum(axis=1) > 25 * 0.4**2
    assert fit.precision[big].max() < 0.5


@pytest.mark.parametrize("seed", [0, 1])
def test_gaussian_with_uniform_outliers_gives_sigma_and_share_within_their_standard_errors(seed):
    rng = np.random.default_rng(seed)
    n = 20_000
    r = rng.normal(scale=0.5, size=(n, 2))
    bad = rng.random(n) < 0.03
    r[bad] = uniform_disc(rng, bad.sum(), 40.0)
    fit = fit_noise_model((r**2).sum(axis=1), model="mixture", outlier_range=40.0)
    assert abs(fit.sigma - 0.5) < 3 * fit.sigma_se
    assert abs(fit.outlier_share - 0.03) < 3 * fit.outlier_share_se
    # the outliers beyond a few σ are found; the posterior decides the rest
    far = bad & ((r**2).sum(axis=1) > 36 * 0.5**2)
    assert fit.outliers[far].mean() > 0.99
    assert fit.outliers[~bad].mean() < 0.002
    assert fit.tail == np.inf and fit.covariance_factor == 1.0


def test_pooled_group_scales_recover_their_spread_and_shrink_small_groups():
    rng = np.random.default_rng(3)
    groups, alpha = 2000, 2.0
    lam = rng.gamma(alpha, 1 / alpha, size=groups)
    sizes = rng.integers(3, 12, size=groups)
    g = np.repeat(np.arange(groups), sizes)
    r = rng.normal(size=(g.size, 2)) * (0.3 / np.sqrt(lam[g]))[:, None]
    fit = fit_noise_model((r**2).sum(axis=1), model="gaussian", groups=(g,), group_names=("track",))
    spread = fit.groups[0]
    assert spread.name == "track" and abs(spread.spread - alpha) < 3 * spread.spread_se
    # each group's scale is pulled from its own RMS toward 1: never beyond it
    own = np.sqrt(np.bincount(g, (r**2).sum(axis=1)) / (2 * sizes)) / fit.sigma
    assert np.all((spread.scales - 1) * (own - spread.scales) >= -1e-12)
    # and the variance with the scale's uncertainty is the larger, most so for small groups
    assert np.all(spread.std_factors >= spread.scales)
    ratio = spread.std_factors / spread.scales
    assert ratio[sizes == 3].mean() > ratio[sizes == 11].mean()


def test_a_fit_on_a_sample_applies_to_all_with_its_parameters_kept():
    rng = np.random.default_rng(4)
    r = student_t_residuals(rng, 5000, 1.0, 4.0)
    s = (r**2).sum(axis=1)
    fit = fit_noise_model(s[:2500], model="student-t")
    applied = fit_noise_model(s, model="student-t", fixed=fit)
    assert (applied.sigma, applied.tail, applied.sigma_se) == (fit.sigma, fit.tail, fit.sigma_se)
    np.testing.assert_allclose(applied.precision[:2500], fit.precision)


def test_gaussian_sigma_counts_the_degrees_of_freedom():
    s = np.array([1.0, 0.25, 4.0, 2.25])
    k = np.array([2.0, 1.5, 1.0, 0.5])
    fit = fit_noise_model(s, model="gaussian", degrees_of_freedom=k)
    assert fit.sigma == pytest.approx(np.sqrt(s.sum() / k.sum()))
    assert fit.parameters()[0][0] == "sigma_se"


@settings(max_examples=20, deadline=None)
@given(st.floats(0.1, 10.0), st.integers(0, 1000))
def test_the_fit_is_equivariant_to_the_unit_of_the_residuals(c, seed):
    rng = np.random.default_rng(seed)
    r = student_t_residuals(rng, 400, 1.0, 5.0)
    s = (r**2).sum(axis=1)
    a = fit_noise_model(s, model="student-t")
    b = fit_noise_model(c**2 * s, model="student-t")
    assert b.sigma == pytest.approx(c * a.sigma, rel=1e-3)
    assert b.tail == pytest.approx(a.tail, rel=1e-2)


@pytest.mark.parametrize("bad", [
    dict(squared_residuals=[1.0, -1.0]),
    dict(squared_residuals=[1.0, np.nan]),
    dict(squared_residuals=[1.0, 2.0], degrees_of_freedom=[2.0, 3.0]),
    dict(squared_residuals=[1.0, 2.0], groups=(np.array([0.5, 1.0]),)),
    dict(squared_residuals=[1.0, 2.0], model="cauchy"),
])
def test_bad_input_is_refused(bad):
    with pytest.raises(InvalidInputError):
        fit_noise_model(**bad)


def test_all_zero_residuals_cannot_give_a_noise():
    with pytest.raises(NotEnoughDataError):
        fit_noise_model(np.zeros(10))


def _line_fits(rng, n, m, rho):
    e = np.zeros((n, m))
    e[:, 0] = rng.normal(size=n)
    for t in range(1, m):
        e[:, t] = rho * e[:, t - 1] + np.sqrt(1 - rho**2) * rng.normal(size=n)
    design = np.stack([np.ones(m), np.arange(m) / m], axis=1)
    hat = design @ np.linalg.pinv(design)
    J = np.broadcast_to(design[None, :, None], (n, m, 1, 2))
    return (e - e @ hat.T)[..., None], J


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_serial_correlation_of_ar1_errors_comes_back_within_its_standard_error(rho):
    r, J = _line_fits(np.random.default_rng(5), 600, 12, rho)
    fit = fit_serial_correlation(r, J, np.arange(12))
    assert abs(fit.correlation[0] - rho) < max(3 * fit.correlation_se[0], 0.02)
    assert abs(fit.scale[0] - 1) < max(3 * fit.scale_se[0], 0.05)


def test_serial_covariance_of_the_mean_is_the_textbook_one():
    J = np.ones((1, 4, 1, 1))
    rho = 0.5
    c = SerialCorrelation(np.array([rho]), np.zeros(1), np.ones(1), np.zeros(1), 1)
    lags = np.abs(np.subtract.outer(np.arange(4), np.arange(4)))
    expected = (rho**lags).sum() / 16
    assert serial_covariance(J, np.arange(4), c)[0, 0, 0] == pytest.approx(expected)
